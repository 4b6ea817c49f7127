"""A seed group's checkpoints: one ``checkpoint.ckpt`` per seed's run folder, each exactly a single run's.

``save`` writes (process 0 under ``jax.distributed``; every process gathers) each seed's device trees and
host state; ``load`` puts them back so that a resumed run continues as if it had never stopped.  The file
format is :mod:`sagrasp_jax.training.checkpoint`'s.
"""

from __future__ import annotations

import os

from sagrasp_jax.training import checkpoint, lr_schedule, sharding
from sagrasp_jax.training.checkpoint import CheckpointError
from sagrasp_jax.training.run_dir import CHECKPOINT_FILE
from sagrasp_jax.training.seed_group import CHECKPOINT_TREES, HostState, RunnerState, SeedGroup


def paths(group: SeedGroup, resumed: list[bool]) -> list[str | None]:
    """Each seed's checkpoint path where it resumes, None where it starts fresh."""
    return [os.path.join(d, CHECKPOINT_FILE) if r else None for d, r in zip(group.dirs, resumed)]


def save(group: SeedGroup, primary: bool, which: list[int] | None = None) -> list[str]:
    """Atomically write, per seed (default: all), everything an exact resume needs (under
    jax.distributed every process gathers, process 0 writes)."""
    host_runner = sharding.to_host(group.runner)
    written = []
    for i in range(len(group)) if which is None else which:
        path = os.path.join(group.dirs[i], CHECKPOINT_FILE)
        if primary:
            checkpoint.save(path, trees=group.seed_trees(host_runner, i), host=group.hosts[i].to_checkpoint(),
                            config=group.cfgs[i])
        written.append(path)
    return written


def load(group: SeedGroup, ckpt_paths: list[str | None], rule: lr_schedule.Rule) -> None:
    """Each seed's state from its checkpoint (None: that seed keeps its fresh state)."""
    host_runner = sharding.to_host(group.runner)
    seeds: list[RunnerState] = []
    for i, path in enumerate(ckpt_paths):
        fresh = group.seed_trees(host_runner, i)
        if path is None:
            seeds.append(RunnerState(**{f: fresh[t] for f, t in CHECKPOINT_TREES.items()}))
            continue
        ckpt = checkpoint.load(path)
        checkpoint.check_config(ckpt, group.cfgs[i])
        try:
            group.hosts[i] = HostState.from_checkpoint(ckpt.host, rule)
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"{path}: incompatible checkpoint host state ({exc})") from None
        trees = {name: checkpoint.restore_tree(tmpl, ckpt.trees.get(name, {}), name, path)
                 for name, tmpl in fresh.items()}
        seeds.append(RunnerState(**{f: trees[t] for f, t in CHECKPOINT_TREES.items()}))
    group.runner = group.place(seeds)
