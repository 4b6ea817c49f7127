"""A toy-env training in its own process, for tests/test_faults.py to kill.

    python tests/fault_driver.py OUT [--slow SECONDS] [--die-in-checkpoint-write N]

Runs ``train.run(toy_config(), OUT, resume=True, env_factory=toy_factory())``: the CLI's library
path (lock, folder checks, fresh / resume / restart, checkpoints) on the toy env, so a kill and
resume cost seconds, not a real-env compile.  Prints ``COMPILED`` once the trainer has compiled
(the folder is locked and its config written by then).  ``--slow`` sleeps after every iteration
so that random kill times spread over the training; it changes no number.
``--die-in-checkpoint-write N`` SIGKILLs the process half-way through writing the N-th
checkpoint of this process (after the temp file is half written, before the rename): the state
a kill during a checkpoint write leaves.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from conftest import toy_config, toy_factory  # noqa: E402

from sagrasp_jax import fileio, run_dir, train  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("out")
    p.add_argument("--slow", type=float, default=0.0)
    p.add_argument("--die-in-checkpoint-write", type=int, default=0)
    args = p.parse_args()

    if args.die_in_checkpoint_write:
        original = fileio.atomic_write
        writes = [0]

        def atomic_write(path: str, write):  # type: ignore[no-untyped-def]
            if os.path.basename(path) == run_dir.CHECKPOINT_FILE:
                writes[0] += 1
                if writes[0] == args.die_in_checkpoint_write:
                    def dying(tmp: str) -> None:
                        write(tmp)
                        with open(tmp, "r+b") as f:
                            f.truncate(os.path.getsize(tmp) // 2)
                        os.kill(os.getpid(), signal.SIGKILL)

                    return original(path, dying)
            return original(path, write)

        fileio.atomic_write = atomic_write

    compile_once = train.Trainer.compile

    def compile(self):  # type: ignore[no-untyped-def]
        first = self._compiled_cycle is None
        out = compile_once(self)
        if first:
            print("COMPILED", flush=True)
        return out

    train.Trainer.compile = compile
    if args.slow:
        step = train.Trainer.run_iterations

        def run_iterations(self, count):  # type: ignore[no-untyped-def]
            rows = step(self, count)
            time.sleep(args.slow * len(rows))  # as slow as before, one sleep per iteration
            return rows

        train.Trainer.run_iterations = run_iterations
    train.run(toy_config(), args.out, resume=True, env_factory=toy_factory(), progress=False)
    print("FINISHED", flush=True)


if __name__ == "__main__":
    main()
