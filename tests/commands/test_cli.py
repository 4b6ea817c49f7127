"""Every command refuses a mistyped option in one line that names it and the nearest valid one, exit 2."""

from __future__ import annotations

import json
import subprocess
import sys

from tiny_run import REPO

COMMANDS = ("train", "evaluate", "export", "render", "plot", "calibrate", "sysid", "parity", "deploy", "capture",
            "deploy.rehearse")

# One process runs every command's module as ``python -m`` would (runpy), so the heavy imports happen once.
DRIVER = r"""
import contextlib, io, json, runpy, sys
out = {}
for name in sys.argv[1:]:
    err = io.StringIO()
    sys.argv = [name, "--otu", "x"]
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            runpy.run_module("sagrasp_jax." + name, run_name="__main__")
        code = 0
    except SystemExit as exc:
        code = exc.code
    out[name] = [code, err.getvalue()]
print(json.dumps(out))
"""


def test_a_mistyped_option_is_named_with_the_nearest_one():
    done = subprocess.run([sys.executable, "-c", DRIVER, *COMMANDS], capture_output=True, text=True, timeout=600,
                          cwd=REPO)
    assert done.returncode == 0, done.stderr[-3000:]
    results = json.loads(done.stdout.strip().splitlines()[-1])
    for name in COMMANDS:
        code, err = results[name]
        lines = [line for line in err.splitlines() if line.strip()]
        assert code == 2, (name, code, err)
        nearest = "--port" if name == "deploy" else "--out"  # deploy writes no file: its nearest is --port
        assert len(lines) == 1 and lines[0].endswith(f"unknown option --otu (did you mean {nearest}?)"), (name, err)
