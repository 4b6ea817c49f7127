"""A toy-env training in its own process, for tests/commands/test_faults.py to kill.

    python tests/fault_driver.py OUT [--slow SECONDS] [--die-in-checkpoint-write N] [--die-after-checkpoint N]
                                     [--snapshot-after-checkpoint N DIR] [--dynamic] [--cli]

Runs ``train.run(toy_config(), OUT, resume=True, env_factory=toy_factory())``: the CLI's library
path (lock, folder checks, fresh / resume / restart, checkpoints) on the toy env, so a kill and
resume cost seconds, not a real-env compile.  Prints ``COMPILED`` once the trainer has compiled
(the folder is locked and its config written by then).  ``--slow`` sleeps after every iteration
so that random kill times spread over the training; it changes no number.
``--die-in-checkpoint-write N`` SIGKILLs the process half-way through writing the N-th
checkpoint of this process (after the temp file is half written, before the rename): the state
a kill during a checkpoint write leaves.
``--die-after-checkpoint N`` SIGKILLs it right after its N-th checkpoint is written;
``--snapshot-after-checkpoint N DIR`` instead copies the run folder to DIR at that moment (what a
kill there would leave) and trains on: one process gives both the killed and the uninterrupted run.
``--cli`` trains through ``train.main(["--out", OUT, "--resume"])`` (the run's config.json must be
there; toy envs), so that signals meet the CLI's handlers.
``--dynamic`` trains the real grasp env in dynamic mode instead (``dynamic_config``: a few envs,
three one-iteration cycles, a checkpoint after each), the issue-27 resume case.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from conftest import toy_config, toy_factory  # noqa: E402

from sagrasp_jax import train  # noqa: E402
from sagrasp_jax.base import fileio  # noqa: E402
from sagrasp_jax.training import run_dir  # noqa: E402


def dynamic_config():  # type: ignore[no-untyped-def]
    """A tiny dynamic-mode run of the grasp env: 3 cycles of one iteration, checkpointed after each."""
    sets = ["env.control.mode=dynamic", "ppo.num_envs=4", "ppo.unroll_length=4", "ppo.num_minibatches=2",
            "ppo.num_epochs=1", "ppo.network.policy_hidden=32,32,32,32", "ppo.learning_rate=3e-4", "sa.decay=0.98",
            "eval.num_cycles=3", "eval.episodes=4",
            "env.task.max_steps=8",
            "train.checkpoint_every_cycles=1", "train.metrics_window=8", "train.log_every=1"]
    return train.build_config("cpu-quick", "sa-ppo", 0, 3 * 4 * 4, sets)


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("out")
    p.add_argument("--slow", type=float, default=0.0)
    p.add_argument("--die-in-checkpoint-write", type=int, default=0)
    p.add_argument("--die-after-checkpoint", type=int, default=0)
    p.add_argument("--snapshot-after-checkpoint", nargs=2, default=None, metavar=("N", "DIR"))
    p.add_argument("--dynamic", action="store_true")
    p.add_argument("--cli", action="store_true")
    args = p.parse_args()

    if args.snapshot_after_checkpoint:
        import shutil

        n_snapshot, snapshot_dir = int(args.snapshot_after_checkpoint[0]), args.snapshot_after_checkpoint[1]
        saved = fileio.atomic_write
        seen = [0]

        def atomic_write_then_copy(path: str, write):  # type: ignore[no-untyped-def]
            out = saved(path, write)
            if os.path.basename(path) == run_dir.CHECKPOINT_FILE:
                seen[0] += 1
                if seen[0] == n_snapshot:
                    shutil.copytree(args.out, snapshot_dir)
            return out

        fileio.atomic_write = atomic_write_then_copy

    if args.die_after_checkpoint:
        written = fileio.atomic_write
        done = [0]

        def atomic_write_then_die(path: str, write):  # type: ignore[no-untyped-def]
            out = written(path, write)
            if os.path.basename(path) == run_dir.CHECKPOINT_FILE:
                done[0] += 1
                if done[0] == args.die_after_checkpoint:
                    os.kill(os.getpid(), signal.SIGKILL)
            return out

        fileio.atomic_write = atomic_write_then_die
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
        step = train.Trainer.run_calls

        def run_calls(self, counts):  # type: ignore[no-untyped-def]
            rows = step(self, counts)
            time.sleep(args.slow * sum(len(r) for r in rows))  # as slow as before, one sleep per iteration
            return rows

        train.Trainer.run_calls = run_calls
    if args.cli:
        from sagrasp_jax.training import trainer as trainer_mod

        trainer_mod.default_envs = toy_factory()  # what the CLI builds the envs with
        code = train.main(["--out", args.out, "--resume", "--no-progress"])
        print(f"EXIT {code}", flush=True)
        sys.exit(code)
    if args.dynamic:
        train.run(dynamic_config(), args.out, resume=True, progress=False)
    else:
        train.run(toy_config(), args.out, resume=True, env_factory=toy_factory(), progress=False)
    print("FINISHED", flush=True)


if __name__ == "__main__":
    main()
