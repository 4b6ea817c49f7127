"""Starting a training from code: the config a command line means (``build_config``), the seed list of
``--seeds`` (``parse_seeds``), the CPU split into devices (``use_cpu_devices``), and ``run``: validate, lock and
check the run folders, train.  ``python -m sagrasp_jax.train`` is this with a command line in front.
"""

from __future__ import annotations

import contextlib
import os
import sys
from typing import TextIO

import jax

from sagrasp_jax.task.config import LR_SCHEDULES, SEED_RANGE, Config, ConfigError, check_range, get_config, validate
from sagrasp_jax.task.config_parse import apply_overrides, file_overrides
from sagrasp_jax.training import distributed, restore, run_dir
from sagrasp_jax.training.checkpoint import CheckpointError
from sagrasp_jax.training.run_dir import CONFIG_FILE, RunDirError
from sagrasp_jax.training.seed_group import seed_config, seed_dir
from sagrasp_jax.training.trainer import EnvFactory, Trainer

ALGOS = ("sa-ppo", "ppo")
ALGO_SCHEDULES = {"sa-ppo": "sa", "ppo": "constant"}  # --algo is shorthand for these lr schedules
MAX_SEEDS = 64  # seeds in one group (--seeds): one program holds every seed's envs and networks at once


def build_config(preset: str = "cpu-quick", algo: str | None = None, seed: int | None = None,
                 total_steps: int | None = None, overrides: list[str] | None = None,
                 lr_schedule: str | None = None, config_file: str | None = None) -> Config:
    """Preset, then ``--config`` FILE, then ``--algo`` or ``--lr-schedule``, ``--seed``,
    ``--total-steps``, then ``--set`` overrides, validated.  ``algo`` is shorthand for a schedule
    (``ALGO_SCHEDULES``); giving both is refused unless they agree; neither means ``sa`` unless the
    file sets ``lr.schedule``.  ``--set lr.schedule=…`` in ``overrides`` wins over all."""
    if algo is not None and algo not in ALGOS:
        raise ConfigError(f"unknown algo {algo!r}; valid algos: {', '.join(ALGOS)}")
    if lr_schedule is not None and lr_schedule not in LR_SCHEDULES:
        raise ConfigError(f"unknown lr schedule {lr_schedule!r}; valid lr schedules: {', '.join(LR_SCHEDULES)}")
    if algo is not None and lr_schedule is not None and ALGO_SCHEDULES[algo] != lr_schedule:
        raise ConfigError(f"--algo {algo} means --lr-schedule {ALGO_SCHEDULES[algo]}, not {lr_schedule}; give one of them")
    cfg = get_config(preset)
    from_file = file_overrides(config_file) if config_file is not None else []
    chosen = lr_schedule or (ALGO_SCHEDULES[algo] if algo else None)
    file_sets_schedule = any(item.split("=", 1)[0].strip() == "lr.schedule" for item in from_file)
    sets = [] if chosen is None and file_sets_schedule else [f"lr.schedule={ALGO_SCHEDULES['sa-ppo']}"]
    sets += from_file + ([f"lr.schedule={chosen}"] if chosen else [])
    if seed is not None:
        sets.append(f"train.seed={seed}")
    if total_steps is not None:
        sets.append(f"train.total_steps={total_steps}")
    return apply_overrides(cfg, sets + list(overrides or []))


def parse_seeds(text: str) -> list[int]:
    """``--seeds``: comma-separated seeds or inclusive ranges, e.g. ``0-4`` or ``0,2,5`` or ``0-2,7``; at most
    ``MAX_SEEDS`` of them, each in ``SEED_RANGE``, none twice.  A range is counted before it is spelled out,
    so ``0-100000`` is refused at once."""
    seeds: list[int] = []
    for item in text.split(","):
        first, sep, last = item.strip().partition("-")
        try:
            lo, hi = int(first), int(last) if sep else int(first)
        except ValueError:  # 5,000 digits too (Python's int() limit)
            raise ConfigError(f"--seeds {text[:80]!r}: {item.strip()[:40]!r} is not a seed or a range A-B of seeds") from None
        if hi < lo:
            raise ConfigError(f"--seeds {text[:80]!r}: the range {item.strip()} is empty (write it low-high)")
        check_range("--seeds", lo, *SEED_RANGE)
        check_range("--seeds", hi, *SEED_RANGE)
        if len(seeds) + hi - lo + 1 > MAX_SEEDS:
            raise ConfigError(f"--seeds {text[:80]!r}: more than {MAX_SEEDS} seeds; a seed group trains at most "
                              f"{MAX_SEEDS} seeds in one program (train larger sets as several groups)")
        seeds.extend(range(lo, hi + 1))
    check_seeds(seeds, "--seeds")
    return seeds


def check_seeds(seeds: list[int], what: str = "seeds") -> None:
    """A seed group's seeds: at least one, at most ``MAX_SEEDS``, each in the seed range, none twice."""
    if not seeds:
        raise ConfigError(f"{what}: no seed given")
    if len(seeds) > MAX_SEEDS:
        raise ConfigError(f"{what}: {len(seeds)} seeds; a seed group trains at most {MAX_SEEDS}")
    for seed in seeds:
        check_range(what, seed, *SEED_RANGE)
    seen: set[int] = set()
    twice: set[int] = set()
    for seed in seeds:  # linear: a set, not seeds.count per seed
        (twice if seed in seen else seen).add(seed)
    if twice:
        raise ConfigError(f"{what}: seed {', '.join(map(str, sorted(twice)))} given twice")


def group_seeds_in(out: str) -> list[int] | None:
    """The seeds of a seed-group folder (its ``seed<S>`` run folders), or None when ``out`` is not one."""
    if not os.path.isdir(out) or os.path.exists(os.path.join(out, CONFIG_FILE)):
        return None
    found = sorted(int(n[4:]) for n in os.listdir(out) if n.startswith("seed") and n[4:].isdigit()
                   and os.path.isdir(os.path.join(out, n)))
    return found or None


def cpu_devices_for(cfg: Config, processes: int = 1) -> int:
    """CPU devices per process for a run: one per usable core (XLA:CPU runs most of one device's
    program on one thread, so a single device leaves the other cores idle), such that the
    ``processes`` × devices divide ``ppo.num_envs``."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    devices = max(1, min(cores, cfg.ppo.num_envs // processes))
    while cfg.ppo.num_envs % (devices * processes):
        devices -= 1
    return devices


def use_cpu_devices(cfg: Config, processes: int = 1) -> None:
    """Split the CPU into ``cpu_devices_for`` devices for this run (the env batch is sharded over
    them) unless the device count was chosen already (``JAX_NUM_CPU_DEVICES``, XLA_FLAGS'
    ``--xla_force_host_platform_device_count``) or jax has started its backends."""
    chosen = "JAX_NUM_CPU_DEVICES" in os.environ or "xla_force_host_platform_device_count" in os.environ.get(
        "XLA_FLAGS", "")
    if not chosen:
        try:
            jax.config.update("jax_num_cpu_devices", cpu_devices_for(cfg, processes))
        except RuntimeError:  # jax already started: keep its devices
            pass


def run(cfg: Config, out: str, *, resume: bool = False, env_factory: EnvFactory | None = None,
        progress: bool = True, stop_after_cycles: int | None = None, stream: TextIO | None = None,
        seeds: list[int] | None = None) -> Trainer:
    """Library entry point: validate, lock and check the folder, train; returns the finished trainer.

    With ``seeds`` it trains a seed group in one program into ``out/seed<S>`` run folders (``out``
    itself holds nothing else).  Everything that can refuse the run (config, folders, checkpoints,
    metrics logs, a second writer, a read-only location) is checked before the env is built, and
    nothing is written before all of it passed.  See ``run_dir`` for the fresh / resume / restart rules."""
    validate(cfg)
    if seeds is not None:
        check_seeds(seeds)
    if cfg.train.init_from and not resume:  # refuse an unusable --init-from before the run folder is touched
        restore.check_init_from(cfg)
    primary = jax.process_index() == 0  # under jax.distributed process 0 owns the run folder
    folders = [out] if seeds is None else [seed_dir(out, s) for s in seeds]
    cfgs = [cfg] if seeds is None else [seed_config(cfg, s) for s in seeds]
    with contextlib.ExitStack() as locks:
        try:
            if primary and seeds is not None:
                locks.enter_context(run_dir.FolderLock(out, create=True, what="seed-group folder"))
                if not resume and os.listdir(out):
                    raise RunDirError(f"{out} exists and is not empty; choose a new --out or pass --resume")
                if os.path.exists(os.path.join(out, CONFIG_FILE)):
                    raise RunDirError(f"{out} holds a single run, not a seed group; resume it without --seeds")
            for folder in folders if primary else ():
                locks.enter_context(run_dir.FolderLock(folder, create=True, what="run folder"))
            modes = ([run_dir.prepare_training(f, c, resume) for f, c in zip(folders, cfgs)] if primary
                     else ["resume" if resume else "fresh"] * len(folders))
        except (CheckpointError, RunDirError):
            distributed.all_ok(False)  # under jax.distributed the other processes stop too
            raise
        if not distributed.all_ok(True):
            raise CheckpointError(f"{out}: another process refused this run folder (see its error)")
        for folder, mode in zip(folders, modes):
            if mode == "restart":
                print(f"{folder}: no checkpoint yet (the run stopped before its first one): restarting it from the "
                      "beginning", file=stream if stream is not None else sys.stderr)
        trainer = Trainer(cfg, out, env_factory=env_factory, resume=[m == "resume" for m in modes], progress=progress,
                          stream=stream, seeds=seeds)  # writes nothing
        if trainer.primary:
            for folder, seed_cfg, mode in zip(folders, cfgs, modes):
                if mode != "resume":
                    run_dir.write_config(folder, seed_cfg)
        trainer.train(stop_after_cycles=stop_after_cycles)
    return trainer
