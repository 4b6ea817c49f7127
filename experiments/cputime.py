"""Run a command and write its wall-clock time, process CPU time (user + system, children included)
and the 1-minute load average before and after as JSON: a training budget that other jobs on a
shared machine disturb far less than the wall clock.

    python -m experiments.cputime runs/NAME.cpu.json python -m sagrasp_jax.train ...
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    out, cmd = argv[0], argv[1:]
    t0, load0 = time.time(), os.getloadavg()[0]
    rc = subprocess.call(cmd)
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    with open(out, "w", encoding="utf-8") as f:
        json.dump({"cmd": cmd, "rc": rc, "wall_s": time.time() - t0, "cpu_user_s": usage.ru_utime,
                   "cpu_sys_s": usage.ru_stime, "load_start": load0, "load_end": os.getloadavg()[0]}, f, indent=1)
    return rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
