"""A training's state, per seed: what lives on the devices (``RunnerState``) and on the host (``HostState``).

A single run is a group of one.  In a seed group (``train --seeds``) every device leaf leads with the seed
axis and the training call is vmapped over it; env states are split over the mesh on their env axis.  This
module owns that placement and the per-seed selections (restore one seed's snapshot) so that a group's seed
computes bit for bit what the same seed computes alone.  The lr is no device state: each seed's host schedule
owns it (``HostState.lr_state``) and gives it to every call.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any, Iterable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sagrasp_jax.task.config import Config
from sagrasp_jax.task.config_parse import apply_overrides
from sagrasp_jax.training import lr_schedule, sharding
from sagrasp_jax.training.agents.ppo import actor_critic


class RunnerState(NamedTuple):
    """What lives on the devices between training calls; in a seed group every leaf leads with the seed axis.

    The checkpoint stores these trees under ``CHECKPOINT_TREES``' names (one seed's slice per run folder)."""

    train_state: actor_critic.TrainingState
    snapshot: actor_critic.TrainingState  # the last accepted train state: SA's restore point
    env_state: Any
    train_key: Any
    window: dict[str, Any]  # the training-episode window (metrics_window)


# RunnerState field -> its tree name in the checkpoint (the layout runs written before the split use)
CHECKPOINT_TREES = {"train_state": "train_state", "snapshot": "snapshot", "env_state": "env_state",
                    "train_key": "train_key", "window": "episode_window"}
COUNTERS = ("iteration", "env_steps", "cycle_start", "entropy_sum", "entropy_n", "nonfinite", "recent_evals",
            "stopped_at")


@dataclass
class HostState:
    """One seed's host-side state: the counters, the lr schedule's state (the lr's one owner) and SA's random stream.

    Everything here is in the checkpoint header (``to_checkpoint``), so a resumed run continues exactly."""

    lr_state: lr_schedule.ScheduleState
    sa_rng: np.random.Generator
    iteration: int = 0  # completed PPO iterations
    env_steps: int = 0
    cycle_start: int = 0  # iteration at which the current cycle began
    entropy_sum: float = 0.0  # over the current cycle's iterations
    entropy_n: int = 0
    nonfinite: int = 0  # iterations rolled back for NaN/inf
    recent_evals: list[float] = field(default_factory=list)  # the stopping rule's window of evaluation success rates
    stopped_at: int = 0  # env steps at which the stopping rule ended the run (0: it has not)

    @classmethod
    def fresh(cls, rule: lr_schedule.Rule, seed: int) -> HostState:
        return cls(lr_state=lr_schedule.init(rule), sa_rng=np.random.default_rng([seed, 0x5A]))

    def to_checkpoint(self) -> dict[str, Any]:
        return {"counters": {k: getattr(self, k) for k in COUNTERS}, "lr_state": self.lr_state.to_dict(),
                "sa_rng": self.sa_rng.bit_generator.state}

    @classmethod
    def from_checkpoint(cls, host: dict[str, Any], rule: lr_schedule.Rule) -> HostState:
        """The host state of a checkpoint header (also one written before lr schedules: ``sa_state``)."""
        if "lr_state" in host:
            lr_state = lr_schedule.ScheduleState.from_dict(host["lr_state"])
        else:  # written before lr schedules: SA's state machine served plain PPO too
            lr_state = lr_schedule.from_legacy(host["sa_state"], rule.name)
        if (lr_state.sa is None) != (rule.name != "sa"):
            raise ValueError(f"its lr-schedule state does not fit lr.schedule={rule.name}")
        rng = np.random.default_rng()
        rng.bit_generator.state = host["sa_rng"]
        unknown = set(host["counters"]) - set(COUNTERS)
        if unknown:
            raise ValueError(f"unknown counters {', '.join(sorted(unknown))}")
        return cls(lr_state=lr_state, sa_rng=rng, **host["counters"])

    def finished(self, num_iterations: int) -> bool:
        """The seed has trained its whole budget of ``num_iterations``, or its stopping rule ended it."""
        return self.iteration >= num_iterations or bool(self.stopped_at)

    def start_cycle(self) -> None:
        self.cycle_start = self.iteration
        self.entropy_sum, self.entropy_n = 0.0, 0


def seed_config(cfg: Config, seed: int) -> Config:
    """A group member's config: the group's with its own ``train.seed`` (what its run folder records)."""
    return apply_overrides(cfg, [f"train.seed={seed}"])


def seed_dir(out: str, seed: int) -> str:
    """A group member's run folder."""
    return os.path.join(out, f"seed{seed}")


class SeedGroup:
    """The seeds of one training program: their configs, run folders, device state and host states.

    ``group`` False: a single run (no seed axis; its objects are used as they are)."""

    def __init__(self, cfg: Config, out_dir: str, seeds: list[int] | None, mesh: Any, rule: lr_schedule.Rule) -> None:
        self.group = seeds is not None
        self.seeds = list(seeds) if seeds is not None else [cfg.train.seed]
        self.cfgs = [seed_config(cfg, s) for s in self.seeds] if self.group else [cfg]
        self.dirs = [seed_dir(out_dir, s) for s in self.seeds] if self.group else [out_dir]
        self.mesh = mesh
        self.hosts = [HostState.fresh(rule, c.train.seed) for c in self.cfgs]
        self.runner: RunnerState | None = None

    def __len__(self) -> int:
        return len(self.seeds)

    def place(self, seeds: Iterable[RunnerState]) -> RunnerState:
        """Each seed's host (or device) state onto the devices: a group's stacked, env states split over the
        mesh on their env axis; a single run's as its freshly reset state (``self.runner``) is placed.  A group's
        seeds are copied to the host one at a time as ``seeds`` yields them, so a generator of fresh device
        states never holds more than one seed's on the devices."""
        rep = lambda tree: sharding.replicate(tree, self.mesh)  # noqa: E731
        if not self.group:
            (one,) = seeds
            if self.runner is None:  # a fresh single run: placed by its own jitted reset already
                return one
            return RunnerState(rep(one.train_state), rep(one.snapshot), _placed_like(one.env_state, self.runner.env_state),
                               rep(one.train_key), rep(one.window))
        stacked = jax.tree_util.tree_map(lambda *xs: np.stack(xs), *[sharding.to_host(s) for s in seeds])
        env_state = jax.device_put(sharding.placeable(stacked.env_state), sharding.seed_batch_sharding(self.mesh))
        return RunnerState(rep(stacked.train_state), rep(stacked.snapshot), env_state, rep(stacked.train_key),
                           rep(stacked.window))

    def seed_trees(self, host_runner: RunnerState, i: int) -> dict[str, Any]:
        """Seed ``i``'s slice of a host copy of the runner state, by checkpoint tree name."""
        tree = jax.tree_util.tree_map(lambda x: x[i], host_runner) if self.group else host_runner
        return {CHECKPOINT_TREES[name]: value for name, value in tree._asdict().items()}

    def choose(self, mask: list[bool], new: Any, old: Any) -> Any:
        """Per seed, ``new`` where ``mask`` else ``old`` (bit-exact; a single run keeps the object itself)."""
        if not self.group:
            return new if mask[0] else old
        if all(mask):
            return new
        if not any(mask):
            return old
        return _select_seeds(np.asarray(mask), new, old)

    def restore_and_accept(self, restore: list[bool], accept: list[bool]) -> None:
        """Seeds in ``restore`` go back to their snapshot; those in ``accept`` make theirs the new snapshot."""
        train_state = self.choose(restore, self.runner.snapshot, self.runner.train_state)
        self.runner = self.runner._replace(train_state=train_state,
                                           snapshot=self.choose(accept, train_state, self.runner.snapshot))

    def train_state_of(self, i: int) -> actor_critic.TrainingState:
        """Seed ``i``'s train state on the devices (a group's slice; a single run's own)."""
        if not self.group:
            return self.runner.train_state
        return _seed_slice(self.runner.train_state, np.int32(i))

    def metrics_of(self, metrics: dict[str, Any], i: int) -> dict[str, Any]:
        """Seed ``i``'s part of a call's host metrics."""
        return jax.tree_util.tree_map(lambda x: x[i], metrics) if self.group else metrics


@jax.jit
def _seed_slice(tree: Any, i: jax.Array) -> Any:
    """Seed ``i``'s slice of a group's stacked device tree."""
    return jax.tree_util.tree_map(lambda x: x[i], tree)


@jax.jit
def _select_seeds(mask: jax.Array, new: Any, old: Any) -> Any:
    """Per seed (leading axis), ``new`` where ``mask`` else ``old``."""
    return jax.tree_util.tree_map(lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b),
                                  new, old)


def _placed_like(tree: Any, fresh: Any) -> Any:
    """``tree`` (host arrays from a checkpoint) on the devices exactly as ``fresh`` (the same state
    made by this run's jitted reset) is: the compiled cycle wants its inputs' shardings.  Not simply
    split over the batch axis: XLA leaves zero-size leaves (dynamic mode's empty MJX fields, [B, 0])
    replicated, and a resumed run that split them fails its second call (issue 27)."""
    shardings = jax.tree_util.tree_map(lambda x: x.sharding, fresh)
    return jax.device_put(sharding.placeable(tree), shardings)
