"""SA-PPO / PPO training: ``python -m sagrasp_jax.train --preset cpu-quick --out runs/NAME``.

This module is the command line; the library is :mod:`sagrasp_jax.training` (``launch.run``: validate, lock
and check the run folders, train; ``trainer.Trainer`` and its parts).  ``--algo sa-ppo`` / ``--algo ppo``
are ``--lr-schedule sa`` / ``--lr-schedule constant``; ``--lr-schedule`` also takes kl-adaptive, cosine and
linear.  ``--seeds 0-4`` trains a seed group in one compiled program, one run folder per seed.
Everything that changes the numbers lives in jax arrays or in the checkpoint's host state,
so a killed run resumed from its last checkpoint continues exactly as if uninterrupted.

Run folder (``sagrasp_jax.training.run_dir`` owns its layout): ``config.json``, ``metrics.jsonl`` (one row
per iteration), ``tb/`` (TensorBoard), ``checkpoint.ckpt`` (every ``train.checkpoint_every_cycles``
cycles and at the end) and ``policy.npz`` (the final policy in the ``sagrasp_jax.task.policy_file``
format).  The folder is locked while a training writes it; ``--resume`` continues from the
checkpoint, or restarts a run killed before its first checkpoint from the beginning.
"""


from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS and the compile-cache dir before jax is imported)

import argparse
import contextlib
import os
import sys
from typing import Any

from sagrasp_jax.base import cli
from sagrasp_jax.base import extras

if __name__ == "__main__":  # a missing extra ends in one line naming it (exit 2), not an import traceback
    extras.require_cli("train", prog="python -m sagrasp_jax.train")

from sagrasp_jax.base import fileio  # noqa: E402
from sagrasp_jax.task.config import LR_SCHEDULES, PRESETS, SEED_RANGE, Config, ConfigError, check_range  # noqa: E402
from sagrasp_jax.training import distributed, run_dir  # noqa: E402
from sagrasp_jax.training.checkpoint import CheckpointError  # noqa: E402
from sagrasp_jax.training.run_dir import CHECKPOINT_FILE, CONFIG_FILE, RunDirError  # noqa: E402
# the library names this module has always offered (``train.run``, ``train.Trainer``, ...)
from sagrasp_jax.training.cycles import Schedule, make_schedule  # noqa: E402,F401
from sagrasp_jax.training.launch import (  # noqa: E402,F401
    ALGO_SCHEDULES, ALGOS, MAX_SEEDS, build_config, check_seeds, cpu_devices_for, group_seeds_in, parse_seeds, run,
    use_cpu_devices,
)
from sagrasp_jax.training.run_log import TIME_FIELDS  # noqa: E402,F401
from sagrasp_jax.training.seed_group import HostState, RunnerState, seed_config, seed_dir  # noqa: E402,F401
from sagrasp_jax.training.trainer import EnvFactory, Trainer, default_envs, enable_compilation_cache  # noqa: E402,F401


class _ListKeys(argparse.Action):
    """``--list-keys``: print every config key (meaning, value, valid values) and exit, like --help."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        from sagrasp_jax.task.config_parse import describe_keys

        preset = namespace.preset or "cpu-quick"
        if preset not in PRESETS:
            parser.error(f"unknown preset {preset!r}; valid presets: {', '.join(PRESETS)}")
        try:
            print(describe_keys(preset), flush=True)
        except BrokenPipeError:  # `--list-keys | head`: the reader left; that is not an error
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())  # Python's exit-time flush must not fail again
        parser.exit()


def _parser() -> argparse.ArgumentParser:
    p = cli.Parser(prog="python -m sagrasp_jax.train", description=__doc__.split("\n\n")[0],
                                epilog="--list-keys shows every KEY for --set with its meaning, value and valid values.")
    p.add_argument("--preset", default=None, help=f"one of {', '.join(PRESETS)} (default cpu-quick)")
    p.add_argument("--algo", default=None,
                   help=f"one of {', '.join(ALGOS)} (default sa-ppo): shorthand for --lr-schedule sa / constant")
    p.add_argument("--lr-schedule", default=None, metavar="NAME",
                   help=f"learning-rate schedule (lr.schedule), one of {', '.join(LR_SCHEDULES)} (default sa)")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--seeds", default=None, metavar="LIST",
                   help="train a seed group in one program, e.g. 0-4 or 0,2,5: one run folder OUT/seed<S> per seed, "
                        f"each as a single run's (--resume on OUT continues them all); at most {MAX_SEEDS} seeds")
    p.add_argument("--out", required=True, help="run folder (refused if it exists and is not empty, unless --resume)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="config override, repeatable (e.g. ppo.num_envs=512)")
    p.add_argument("--config", default=None, metavar="FILE",
                   help="config keys from a JSON (or YAML, with PyYAML) file, over --preset's values; --algo, --seed, "
                        "--total-steps and --set apply over it")
    p.add_argument("--total-steps", type=int, default=None)
    p.add_argument("--init-from", default=None, metavar="RUN",
                   help="start from RUN's final policy, value network and normaliser (fresh optimizer and SA state), "
                        "e.g. a kinematic run fine-tuned with --set env.control.mode=dynamic; sets train.init_from")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/checkpoint.ckpt (a run killed before its first checkpoint restarts)")
    p.add_argument("--stop-after-cycles", type=int, default=None,
                   help="checkpoint and stop after this many SA cycles (simulates a preemption)")
    p.add_argument("--no-progress", action="store_true", help="no live progress bar")
    p.add_argument("--list-keys", nargs=0, action=_ListKeys,
                   help="list every config key with its meaning, its value in --preset (given before it) and its valid values; exit")
    dist = p.add_argument_group("multi-process training (jax.distributed, one process per host; see sagrasp_jax.training.distributed)")
    dist.add_argument("--coordinator", default=None, metavar="HOST:PORT", help="address of process 0")
    dist.add_argument("--num-processes", type=int, default=1)
    dist.add_argument("--process-id", type=int, default=0)
    dist.add_argument("--connect-timeout", type=float, default=distributed.CONNECT_TIMEOUT, metavar="SECONDS",
                      help="how long the processes wait for each other at start before stopping with a message naming "
                           f"the missing one (default {distributed.CONNECT_TIMEOUT:g})")
    return p


def check_args(args: argparse.Namespace) -> None:
    """Range checks of the numeric options (their config keys are checked again by ``validate``)."""
    if args.seed is not None:
        check_range("--seed", args.seed, *SEED_RANGE)
    if args.total_steps is not None:
        check_range("--total-steps", args.total_steps, 1, 10**12)
    if args.stop_after_cycles is not None:
        check_range("--stop-after-cycles", args.stop_after_cycles, 1, 10**6)


def resolve_seeds(args: argparse.Namespace) -> list[int] | None:
    """The seed group of ``--seeds`` (or, on ``--resume`` of a seed-group folder, its seeds); None: one run."""
    if args.seeds is None:
        return group_seeds_in(args.out) if args.resume else None
    if args.seed is not None:
        raise ConfigError("--seed and --seeds: give one of them (--seeds 3 trains seed 3 as a group of one)")
    if args.coordinator:
        raise ConfigError("--seeds trains in one process; it does not combine with --coordinator")
    return parse_seeds(args.seeds)


def resolve_config(args: argparse.Namespace, seeds: list[int] | None = None) -> Config:
    """The run's config; on --resume without config options it is the run folder's config.json (a
    seed group's: its first seed's)."""
    overrides = list(args.overrides)
    if args.init_from is not None:
        overrides.append(f"train.init_from={os.path.abspath(args.init_from)}")
    explicit = any(v is not None for v in (args.preset, args.algo, args.lr_schedule, args.seed, args.total_steps,
                                           args.config)) or overrides
    if args.resume and not explicit:
        folder = args.out if seeds is None else seed_dir(args.out, seeds[0])
        if not os.path.isfile(os.path.join(folder, CONFIG_FILE)) and not os.path.isfile(os.path.join(folder, CHECKPOINT_FILE)):
            raise RunDirError(f"{folder}: cannot resume, no {CONFIG_FILE} and no {CHECKPOINT_FILE} there (the run "
                              "wrote neither); start it again without --resume, or pass its config options")
        return run_dir.load_config(folder)
    return build_config(args.preset or "cpu-quick", args.algo, args.seed, args.total_steps, overrides,
                        args.lr_schedule, args.config)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        check_args(args)
        seeds = resolve_seeds(args)
        cfg = resolve_config(args, seeds)
        distributed.check_options(args.coordinator, args.num_processes, args.process_id, cfg.ppo.num_envs,
                                  args.connect_timeout)
        use_cpu_devices(cfg, args.num_processes if args.coordinator else 1)
        if args.coordinator:
            distributed.initialize(args.coordinator, args.num_processes, args.process_id, args.connect_timeout)
        with _sigterm_as_interrupt():
            run(cfg, args.out, resume=args.resume, progress=not args.no_progress,
                stop_after_cycles=args.stop_after_cycles, seeds=seeds)
    except (ConfigError, CheckpointError, RunDirError, distributed.DistributedError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except fileio.NotWritable as exc:  # a full disk (or a folder gone read-only) during the run
        print(f"error: {exc}; {args.out} continues from its last checkpoint with --resume once it can be written",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        terminated = isinstance(exc, Terminated)
        print(f"\n{'terminated (SIGTERM)' if terminated else 'interrupted'}: {args.out} continues from its last "
              "checkpoint with --resume", file=sys.stderr)
        return 143 if terminated else 130
    return 0


# after a dropped Terminated or Ctrl-C, the delay before the signal is raised again: the hook has long returned by then
# (and where the signal lands in a gc callback again, it is dropped and raised again once more)
REDELIVER_S = 0.05


class Terminated(KeyboardInterrupt):
    """SIGTERM during a training (``train.main``): stops it like Ctrl-C, at any point."""


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Any:
    """SIGTERM raises ``Terminated`` (a KeyboardInterrupt) for the block: the run stops as on Ctrl-C,
    with its message and exit status 143, and resumes from its last checkpoint.

    Where the handler ran inside code whose exceptions Python drops (a gc callback such as jax's
    ``_xla_gc_callback``, a ``__del__``) the ``Terminated`` reaches ``sys.unraisablehook`` instead, and the
    run went on to its end; so did a Ctrl-C's ``KeyboardInterrupt`` there.  The hook has the signal (SIGTERM
    or SIGINT) raised again from a short timer thread (``_thread.interrupt_main``; asked from the hook itself,
    the handler would run inside the hook and be dropped again), so the run stops at the main thread's next
    Python line outside such code."""
    import _thread
    import signal
    import threading

    def handler(signum: int, frame: Any) -> None:
        raise Terminated()

    def unraisable(info: Any) -> None:
        if isinstance(info.exc_value, KeyboardInterrupt):  # Terminated is one
            signum = signal.SIGTERM if isinstance(info.exc_value, Terminated) else signal.SIGINT
            again = threading.Timer(REDELIVER_S, _thread.interrupt_main, (signum,))
            again.daemon = True
            again.start()
        else:
            previous_hook(info)

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread: leave SIGTERM alone
        yield
        return
    previous_hook, sys.unraisablehook = sys.unraisablehook, unraisable
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        sys.unraisablehook = previous_hook


if __name__ == "__main__":
    sys.exit(main())
