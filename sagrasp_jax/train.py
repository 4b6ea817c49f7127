"""SA-PPO / PPO trainer: ``python -m sagrasp_jax.train --preset cpu-quick --out runs/NAME``.

The loop is a handful of named steps on a :class:`Trainer`: ``run_calls`` (one jitted call of a
cycle's PPO iterations: rollouts + updates), ``end_cycles`` (fixed-seed deterministic evaluation
at p = 1, then the lr schedule's end of cycle, ``lr_schedule.end_cycle``: SA's decision on the
evaluation metric), ``save_checkpoint``.  Its state is a device-side ``RunnerState`` and a
host-side ``HostState`` per seed; ``train`` hands every metrics row to callbacks (metrics.jsonl,
TensorBoard, the progress bar).  ``--algo sa-ppo`` / ``--algo ppo`` are ``--lr-schedule sa`` /
``--lr-schedule constant``; ``--lr-schedule`` also takes kl-adaptive, cosine and linear.
``--seeds 0-4`` trains a seed group in one compiled program, one run folder per seed.
Everything that changes the numbers lives in jax arrays or in the checkpoint's host state,
so a killed run resumed from its last checkpoint continues exactly as if uninterrupted.

Run folder (``sagrasp_jax.run_dir`` owns its layout): ``config.json``, ``metrics.jsonl`` (one row
per iteration), ``tb/`` (TensorBoard), ``checkpoint.ckpt`` (every ``train.checkpoint_every_cycles``
cycles and at the end) and ``policy.npz`` (the final policy in the ``sagrasp_jax.runtime``
format).  The folder is locked while a training writes it; ``--resume`` continues from the
checkpoint, or restarts a run killed before its first checkpoint from the beginning.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS and the compile-cache dir before jax is imported)

import argparse
import bisect
import concurrent.futures
import contextlib
import math
import os
import sys
import time
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple, Protocol, TextIO

from sagrasp_jax import extras

if __name__ == "__main__":  # a missing extra ends in one line naming it (exit 2), not an import traceback
    extras.require_cli("train", prog="python -m sagrasp_jax.train")

import jax  # noqa: E402
import jax.numpy as jnp
import numpy as np

from sagrasp_jax import (
    actor_critic, checkpoint, distributed, fileio, lr_schedule, metrics_window, observation, policy_eval, ppo, rollout,
    run_dir, sa_schedule, sharding,
)
from sagrasp_jax.checkpoint import CheckpointError
from sagrasp_jax.config import (
    LR_SCHEDULES, PRESETS, SEED_RANGE, Config, ConfigError, apply_overrides, check_range, file_overrides, get_config,
    training_env_config, validate,
)
from sagrasp_jax.run_dir import CHECKPOINT_FILE, CONFIG_FILE, POLICY_FILE, RunDirError, export_policy

ALGOS = ("sa-ppo", "ppo")
ALGO_SCHEDULES = {"sa-ppo": "sa", "ppo": "constant"}  # --algo is shorthand for these lr schedules
# Row fields that depend on wall-clock time, not on the training maths.
TIME_FIELDS = ("time_s", "steps_per_s", "compile_s", "compile_iteration_s", "compile_eval_s", "eval_s", "eta_s")

EnvFactory = Callable[[Config], tuple[rollout.Env, rollout.Env]]  # config -> (auto-reset train env, eval env)
# On CPU the SA evaluation runs this many episodes at a time per device, each slot taking the next
# episode when its own ends (policy_eval.evaluate_policy): ≈ 2x faster than all 128 at once, the same
# numbers.  Accelerators evaluate all episodes at once.
CPU_EVAL_SLOTS = 32
MAX_SEEDS = 64  # seeds in one group (--seeds): one program holds every seed's envs and networks at once


def enable_compilation_cache() -> None:
    """Point jax's persistent cache at the dir sagrasp_jax/__init__ chose (in case jax came first)."""
    cache = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if cache:
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs",
                          float(os.environ.get("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1")))


def default_envs(cfg: Config) -> tuple[rollout.Env, rollout.Env]:
    from sagrasp_jax.env import GraspEnv
    from sagrasp_jax.wrappers import AutoReset

    # training episodes follow the training mix (train.obstacle_prob / blocking_prob), evaluation the task's (docs/task.md §2.8)
    return (AutoReset(GraspEnv(training_env_config(cfg), privileged=cfg.ppo.privileged_critic),
                      replay=cfg.train.curriculum_replay, max_replays=cfg.train.curriculum_max_replays), GraspEnv(cfg.env))


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


@dataclass(frozen=True)
class Schedule:
    steps_per_iteration: int
    num_iterations: int
    cycle_ends: tuple[int, ...]  # completed iterations at the end of each SA cycle; the last is num_iterations

    @property
    def num_cycles(self) -> int:
        return len(self.cycle_ends)

    @property
    def iterations_per_cycle(self) -> int:
        """The longest cycle: the iterations one jitted call runs at most."""
        return max(end - start for start, end in zip((0,) + self.cycle_ends[:-1], self.cycle_ends))

    @property
    def cycle_steps(self) -> int:
        return self.steps_per_iteration * self.iterations_per_cycle

    def cycle_end(self, iteration: int) -> int:
        """Where the cycle containing iteration ``iteration`` (0-based) ends."""
        return self.cycle_ends[bisect.bisect_right(self.cycle_ends, iteration)]


def make_schedule(cfg: Config) -> Schedule:
    """Cycles of whole iterations.  By default exactly ``eval.num_cycles`` of them (fewer only when
    there are fewer iterations): cycle k ends after round((k + 1)·N / num_cycles) of the N
    iterations, so cycles differ by at most one iteration.  With ``eval.cycle_steps`` a cycle is
    round(cycle_steps / steps per iteration) iterations, the last one possibly shorter."""
    per_iter = cfg.ppo.num_envs * cfg.ppo.unroll_length
    n = ppo.num_iterations(cfg.train.total_steps, cfg.ppo)
    if cfg.eval.cycle_steps:
        every = max(1, round(cfg.eval.cycle_steps / per_iter))
        ends = tuple(range(every, n, every)) + (n,)
    else:
        c = min(cfg.eval.num_cycles, n)
        ends = tuple(((k + 1) * n * 2 + c) // (2 * c) for k in range(c))  # round half up, in integers
    return Schedule(per_iter, n, ends)


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
COUNTERS = ("iteration", "env_steps", "cycle_start", "entropy_sum", "entropy_n", "nonfinite")


@dataclass
class HostState:
    """One seed's host-side state: the counters, the lr schedule's state and SA's random stream.

    Everything here is in the checkpoint header (``to_checkpoint``), so a resumed run continues exactly."""

    lr_state: lr_schedule.ScheduleState
    sa_rng: np.random.Generator
    iteration: int = 0  # completed PPO iterations
    env_steps: int = 0
    cycle_start: int = 0  # iteration at which the current cycle began
    entropy_sum: float = 0.0  # over the current cycle's iterations
    entropy_n: int = 0
    nonfinite: int = 0  # iterations rolled back for NaN/inf

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

    def start_cycle(self) -> None:
        self.cycle_start = self.iteration
        self.entropy_sum, self.entropy_n = 0.0, 0


class Callback(Protocol):
    """What ``Trainer.train`` hands each metrics row to (``seed``: the row's seed in a group, else None)."""

    def on_start(self, message: str) -> None: ...

    def on_row(self, row: dict[str, Any], seed: int | None) -> None: ...

    def close(self) -> None: ...


@dataclass
class LoggedRows:
    """Passes a log only the rows it keeps: each cycle's and event's, every ``log_every``-th and the last."""

    log: Any  # run_dir.MetricsLog or run_dir.TensorBoardLog
    log_every: int
    num_iterations: int

    def on_start(self, message: str) -> None:
        pass

    def on_row(self, row: dict[str, Any], seed: int | None) -> None:
        if ("cycle" in row or "event" in row or row["iteration"] % self.log_every == 0
                or row["iteration"] + 1 == self.num_iterations):
            self.log.write(row)

    def close(self) -> None:
        self.log.close()


class ProgressBar:
    """The live tqdm bar over all seeds' env steps: speed, last success, lr, last SA metric; rollback notes."""

    def __init__(self, total: int, initial: int, steps_per_row: int, stream: TextIO) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=total, initial=initial, unit="step", unit_scale=True, dynamic_ncols=True,
                        mininterval=1.0, file=stream)
        self.steps_per_row = steps_per_row
        self.last_metric: float | None = None

    def on_start(self, message: str) -> None:
        self.bar.write(message)

    def on_row(self, row: dict[str, Any], seed: int | None) -> None:
        self.last_metric = row.get("sa_metric", self.last_metric)
        self.bar.update(self.steps_per_row)
        self.bar.set_postfix(sps=f"{row['steps_per_s']:,.0f}", success=_fmt(row.get("success")), lr=f"{row['lr']:.2e}",
                             M=_fmt(self.last_metric), refresh=False)
        if "event" in row:
            who = "" if seed is None else f"seed {seed}, "
            self.bar.write(f"{who}iteration {row['iteration']}: non-finite loss/params -> rolled back to the snapshot, "
                           f"lr {row['lr']:.3g}")

    def close(self) -> None:
        self.bar.close()


class Trainer:
    """One training run bound to a run folder, or a seed group (``seeds``) bound to ``out_dir/seed<S>`` folders.

    Device state is a ``RunnerState`` (stacked over seeds in a group, whose training call is vmapped
    over them, ``ppo.make_cycle(seed_axis=True)``); each seed's host state is a ``HostState``.  The
    single-run accessors (``host``, ``train_state``, ``lr``, ``run_iterations``, ``anneal`` …) are
    the group's seed 0 when there is no group."""

    def __init__(self, cfg: Config, out_dir: str, *, env_factory: EnvFactory | None = None, resume: bool | list[bool] = False,
                 progress: bool = True, stream: TextIO | None = None, devices: list[Any] | None = None,
                 seeds: list[int] | None = None) -> None:
        enable_compilation_cache()
        self.cfg = cfg
        self.out_dir = out_dir
        self.group = seeds is not None
        self.seeds = list(seeds) if seeds is not None else [cfg.train.seed]
        self.cfgs = [seed_config(cfg, s) for s in self.seeds] if self.group else [cfg]
        self.dirs = [seed_dir(out_dir, s) for s in self.seeds] if self.group else [out_dir]
        self.progress = progress
        self.stream = stream if stream is not None else sys.stderr
        self.mesh = sharding.make_mesh(devices)  # default: every device (of every process)
        self.primary = jax.process_index() == 0  # under jax.distributed only process 0 writes files
        if cfg.ppo.num_envs % self.mesh.size:
            raise ConfigError(f"ppo.num_envs={cfg.ppo.num_envs} must be divisible by the {self.mesh.size} devices")
        self.train_env, self.eval_env = (env_factory or default_envs)(cfg)
        self.obs_size, self.action_size = self.train_env.observation_size, self.train_env.action_size
        self.schedule = make_schedule(cfg)
        self.critic_extra = observation.critic_extra_size(cfg)  # privileged critic inputs (0: none)
        provided = getattr(getattr(self.train_env, "env", self.train_env), "privileged_size", 0)
        if self.critic_extra and provided != self.critic_extra:
            raise ConfigError(f"ppo.privileged_critic needs an env that reports {self.critic_extra} privileged inputs "
                              f"(GraspEnv(privileged=True)); the training env reports {provided}")
        self.networks = actor_critic.make_networks(cfg.ppo.network, self.obs_size, self.action_size, cfg.ppo.obs_clip,
                                                   self.critic_extra)
        self.rule = lr_schedule.rule_of(cfg)
        self.optimizer = actor_critic.make_optimizer(cfg.ppo, cfg.ppo.learning_rate)
        self.hand_scaled = getattr(self.eval_env, "hand_scaled_mask", None)  # normaliser leaves these entries alone
        self._cycle = ppo.make_cycle(self.train_env, self.networks, self.optimizer, cfg.ppo, self.mesh,
                                     self.schedule.iterations_per_cycle, self.hand_scaled, self.critic_extra,
                                     self.rule, seed_axis=self.group)
        keys = policy_eval.eval_keys(cfg.eval.seed, cfg.eval.episodes)
        split = cfg.eval.episodes % self.mesh.size == 0
        self.eval_keys = sharding.shard_batch(keys, self.mesh) if split else sharding.replicate(keys, self.mesh)
        slots = CPU_EVAL_SLOTS if jax.default_backend() == "cpu" else None
        evaluate = policy_eval.make_evaluator(self.networks, self.eval_env, cfg.env.task.max_steps,
                                              self.mesh if split else None, slots)
        # a group evaluates seed by seed with this single-seed program (see ``evaluate``)
        self._evaluate = jax.jit(lambda params, normaliser, keys: evaluate(params, normaliser, keys)._replace(episodes={}))
        episode = jax.eval_shape(self.train_env.reset, jax.random.PRNGKey(0)).info["episode"]
        self.window_keys = tuple(episode)
        self._compiled_cycle: Any = None
        self._compiled_eval: Any = None
        self.compile_s: dict[str, float] = {}
        resumed = resume if isinstance(resume, list) else [resume] * len(self.seeds)
        self._reset = rollout.make_reset(self.train_env, self.mesh)
        self.runner = self._fresh_runner(resumed)
        self.hosts = [HostState.fresh(self.rule, c.train.seed) for c in self.cfgs]
        if any(resumed):
            self._load([os.path.join(d, CHECKPOINT_FILE) if r else None for d, r in zip(self.dirs, resumed)])

    # ------------------------------------------------------------------ state

    def _fresh_one(self, cfg: Config, resuming: bool) -> RunnerState:
        """One seed's initial device state, exactly as a single run of ``cfg`` starts."""
        k_params, k_env, k_train = jax.random.split(jax.random.PRNGKey(cfg.train.seed), 3)
        ts = actor_critic.init_training_state(k_params, self.networks, self.optimizer, self.obs_size)
        if cfg.train.init_from and not resuming:  # --init-from: another run's policy and normaliser
            ts = run_dir.init_policy_state(ts, cfg, self.obs_size, self.action_size)
        train_state = sharding.replicate(ts, self.mesh)
        env_state = self._reset(sharding.shard_batch(jax.random.split(k_env, cfg.ppo.num_envs), self.mesh))
        window = sharding.replicate(metrics_window.init_window(self.window_keys, cfg.train.metrics_window), self.mesh)
        return RunnerState(train_state, train_state, env_state, sharding.replicate(k_train, self.mesh), window)

    def _fresh_runner(self, resuming: list[bool]) -> RunnerState:
        if not self.group:
            return self._fresh_one(self.cfg, resuming[0])
        seeds = [sharding.to_host(self._fresh_one(c, r)) for c, r in zip(self.cfgs, resuming)]
        return self._place_group(jax.tree_util.tree_map(lambda *xs: np.stack(xs), *seeds))

    def _place_group(self, stacked: RunnerState) -> RunnerState:
        """A group's stacked host state onto the devices: env states split over the mesh on their env axis."""
        rep = lambda tree: sharding.replicate(tree, self.mesh)  # noqa: E731
        env_state = jax.device_put(sharding.placeable(stacked.env_state), sharding.seed_batch_sharding(self.mesh))
        return RunnerState(rep(stacked.train_state), rep(stacked.snapshot), env_state, rep(stacked.train_key),
                           rep(stacked.window))

    def _seed_trees(self, host_runner: RunnerState, i: int) -> dict[str, Any]:
        """Seed ``i``'s slice of a host copy of the runner state, by checkpoint tree name."""
        tree = jax.tree_util.tree_map(lambda x: x[i], host_runner) if self.group else host_runner
        return {CHECKPOINT_TREES[name]: value for name, value in tree._asdict().items()}

    def save_checkpoint(self, which: list[int] | None = None) -> list[str]:
        """Atomically write, per seed (default: all), everything an exact resume needs (under
        jax.distributed every process gathers, process 0 writes)."""
        host_runner = sharding.to_host(self.runner)
        paths = []
        for i in range(len(self.seeds)) if which is None else which:
            path = os.path.join(self.dirs[i], CHECKPOINT_FILE)
            if self.primary:
                checkpoint.save(path, trees=self._seed_trees(host_runner, i), host=self.hosts[i].to_checkpoint(),
                                config=self.cfgs[i])
            paths.append(path)
        return paths

    def _load(self, paths: list[str | None]) -> None:
        """Each seed's state from its checkpoint (None: that seed starts fresh)."""
        host_runner = sharding.to_host(self.runner)
        seeds: list[RunnerState] = []
        for i, path in enumerate(paths):
            fresh = self._seed_trees(host_runner, i)
            if path is None:
                seeds.append(RunnerState(**{f: fresh[t] for f, t in CHECKPOINT_TREES.items()}))
                continue
            ckpt = checkpoint.load(path)
            checkpoint.check_config(ckpt, self.cfgs[i])
            try:
                self.hosts[i] = HostState.from_checkpoint(ckpt.host, self.rule)
            except (KeyError, TypeError, ValueError) as exc:
                raise CheckpointError(f"{path}: incompatible checkpoint host state ({exc})") from None
            trees = {name: checkpoint.restore_tree(tmpl, ckpt.trees.get(name, {}), name, path)
                     for name, tmpl in fresh.items()}
            seeds.append(RunnerState(**{f: trees[t] for f, t in CHECKPOINT_TREES.items()}))
        if self.group:
            self.runner = self._place_group(jax.tree_util.tree_map(lambda *xs: np.stack(xs), *seeds))
            return
        (one,) = seeds
        rep = lambda tree: sharding.replicate(tree, self.mesh)  # noqa: E731
        self.runner = RunnerState(rep(one.train_state), rep(one.snapshot), _placed_like(one.env_state, self.runner.env_state),
                                  rep(one.train_key), rep(one.window))

    # single-run views (seed 0 of a group)
    @property
    def host(self) -> HostState:
        return self.hosts[0]

    @property
    def train_state(self) -> actor_critic.TrainingState:
        return self.runner.train_state

    @property
    def snapshot(self) -> actor_critic.TrainingState:
        return self.runner.snapshot

    @property
    def env_state(self) -> Any:
        return self.runner.env_state

    @property
    def lr_state(self) -> lr_schedule.ScheduleState:
        return self.hosts[0].lr_state

    @property
    def lr(self) -> float:
        """The learning rate the next iteration starts from."""
        return self.hosts[0].lr_state.lr

    @property
    def sa_state(self) -> sa_schedule.SAState | None:
        """The SA state machine's state (``lr.schedule = sa``; None under the other schedules)."""
        return self.hosts[0].lr_state.sa

    def _choose(self, mask: list[bool], new: Any, old: Any) -> Any:
        """Per seed, ``new`` where ``mask`` else ``old`` (bit-exact; a single run keeps the object itself)."""
        if not self.group:
            return new if mask[0] else old
        if all(mask):
            return new
        if not any(mask):
            return old
        return _select_seeds(np.asarray(mask), new, old)

    def _apply_lr(self) -> None:
        """Make the optimizer state's lr each seed's schedule's (after a decay or a restore)."""
        opt = self.runner.train_state.opt_state
        want = np.array([h.lr_state.lr for h in self.hosts], np.float32)
        if not np.array_equal(np.asarray(actor_critic.learning_rate_of(opt)).reshape(-1), want):
            lr = want if self.group else float(self.hosts[0].lr_state.lr)
            ts = self.runner.train_state._replace(opt_state=actor_critic.set_learning_rate(opt, lr))
            self.runner = self.runner._replace(train_state=ts)

    # ------------------------------------------------------------------ compiled steps

    def _cycle_args(self, counts: list[int]) -> tuple[Any, ...]:
        """Arguments of the jitted call running, per seed, iterations ``host.iteration …`` (+ ``count``)."""
        length = self.schedule.iterations_per_cycle
        rows = []
        for host, count in zip(self.hosts, counts):
            progress = np.array([self._progress(host.iteration + j) for j in range(length)], np.float32)
            rows.append((np.int32(host.iteration), np.int32(count), progress,
                         lr_schedule.iteration_lrs(self.rule, host.lr_state, progress)))
        scalars = tuple(np.stack(x) for x in zip(*rows)) if self.group else rows[0]
        r = self.runner
        return (r.train_state, r.env_state, r.window, r.train_key, *sharding.replicate(scalars, self.mesh))

    def _progress(self, iteration: int) -> float:
        """Training progress p at the start of iteration ``iteration`` (the reward weights and the
        cosine / linear lr read it)."""
        return min(1.0, iteration * self.schedule.steps_per_iteration / self.cfg.train.total_steps)

    def compile(self) -> dict[str, float]:
        """Compile the training call and the evaluation ahead of time.

        XLA compiles the training call on a worker thread (it releases the GIL) while this thread
        traces and compiles the evaluation, so on 2 cores the two overlap: ``compile_s["total"]``
        is the wall time the user waits, ``iteration`` and ``eval`` each program's own (overlapping)
        time from the start."""
        if self._compiled_cycle is None:
            t = time.perf_counter()
            lowered = self._cycle.lower(*self._cycle_args([1] * len(self.seeds)))
            with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="compile-training-call") as pool:
                cycle = pool.submit(lambda: (lowered.compile(), time.perf_counter() - t))
                ts = self._seed_train_state(0)
                compiled_eval = self._evaluate.lower(ts.params, ts.normaliser, self.eval_keys).compile()
                eval_s = time.perf_counter() - t
                self._compiled_cycle, cycle_s = cycle.result()  # re-raises the worker's error here
            self._compiled_eval = compiled_eval
            self.compile_s = {"iteration": cycle_s, "eval": eval_s, "total": time.perf_counter() - t}
        return self.compile_s

    def run_iteration(self) -> dict[str, Any]:
        """One PPO iteration (rollout + update) of a single run; a non-finite result restores the snapshot."""
        return self.run_iterations(1)[-1]

    def run_iterations(self, count: int) -> list[dict[str, Any]]:
        """Up to ``count`` (≤ ``schedule.iterations_per_cycle``) PPO iterations of a single run in one
        jitted call and one host sync, one row each.  A non-finite iteration ends the call and restores
        the snapshot."""
        return self.run_calls([count])[0]

    def run_calls(self, counts: list[int]) -> list[list[dict[str, Any]]]:
        """One jitted call: seed i runs up to ``counts[i]`` iterations (0: none); one row per iteration ran.

        A seed whose iteration is non-finite stops there, is restored to its snapshot alone and ends
        its cycle with ``lr_schedule.nonfinite``; the other seeds run on."""
        for count in counts:
            if not 0 <= count <= self.schedule.iterations_per_cycle:
                raise ValueError(f"run_calls: count {count} outside 0 … {self.schedule.iterations_per_cycle}")
        self.compile()
        t = time.perf_counter()
        ts, env_state, window, metrics = self._compiled_cycle(*self._cycle_args(counts))
        metrics = sharding.to_host(metrics)
        dt = time.perf_counter() - t
        self.runner = self.runner._replace(train_state=ts, env_state=env_state, window=window)
        rows, restore = [], []
        for i in range(len(self.hosts)):
            seed_metrics = jax.tree_util.tree_map(lambda x: x[i], metrics) if self.group else metrics
            seed_rows, finite = self._rows_of_call(i, seed_metrics, dt)
            rows.append(seed_rows)
            restore.append(bool(seed_rows) and not finite)
        if any(restore):
            train_state = self._choose(restore, self.runner.snapshot, self.runner.train_state)
            self.runner = self.runner._replace(train_state=train_state)
            self._apply_lr()
        return rows

    def _rows_of_call(self, i: int, metrics: dict[str, Any], dt: float) -> tuple[list[dict[str, Any]], bool]:
        """Seed ``i``'s rows of a call and whether its last iteration was finite; advances its host state
        (a non-finite end: the lr schedule's forced decision, a new cycle; the caller restores the snapshot)."""
        spi, total = self.schedule.steps_per_iteration, self.cfg.train.total_steps
        host = self.hosts[i]
        first = host.iteration
        means, finite = metrics.pop("window"), metrics.pop("finite")
        ran = int(metrics.pop("executed").sum())
        device_lr = metrics.pop("learning_rate")
        rows: list[dict[str, Any]] = []
        for j in range(ran):
            progress = host.env_steps / total
            host.iteration += 1
            host.env_steps += spi
            row: dict[str, Any] = {"iteration": first + j, "env_steps": host.env_steps, "progress": progress,
                                   "steps_per_s": spi * ran / dt,
                                   "episodes_finished": int(metrics["episodes_finished"][j])}
            row.update({k: float(v[j]) for k, v in metrics.items() if k != "episodes_finished"})
            row.update(self._window_row(means, j))
            if self.rule.mode == "kl":  # the lr after this iteration: what the next one starts from
                row["lr"] = float(device_lr[j])
            elif self.rule.mode == "per_iteration":
                row["lr"] = float(lr_schedule.progress_lr(np, self.rule, np.float32(self._progress(first + j + 1))))
            if finite[j]:
                host.entropy_sum += float(metrics["entropy"][j])
                host.entropy_n += 1
            rows.append(row)
        if not ran:
            return rows, True
        if finite[ran - 1]:
            host.lr_state = lr_schedule.observe(self.rule, host.lr_state, device_lr=float(device_lr[ran - 1]),
                                                progress=self._progress(host.iteration))
            return rows, True
        host.nonfinite += 1
        snapshot_lr = np.asarray(actor_critic.learning_rate_of(self.runner.snapshot.opt_state)).reshape(-1)
        host.lr_state, decision = lr_schedule.nonfinite(
            self.rule, self.cfg.sa, host.lr_state, snapshot_lr=float(snapshot_lr[i]),
            progress=self._progress(host.iteration))
        host.start_cycle()
        rows[-1].update(event="nonfinite", sa_decision=decision.kind, sa_decayed=decision.decayed)
        return rows, False

    @staticmethod
    def _window_row(means: dict[str, np.ndarray], j: int) -> dict[str, Any]:
        """Training-episode metrics over the last ``train.metrics_window`` finished episodes."""
        count = int(means["window_episodes"][j])
        if count == 0:
            return {}
        out: dict[str, Any] = {k: float(v[j]) for k, v in means.items()
                               if k not in ("episode_steps", "steps_to_success", "window_episodes")}
        out["episode_steps"] = float(means["episode_steps"][j])
        sts = float(means["steps_to_success"][j])
        out["steps_to_success"] = sts if math.isfinite(sts) else None
        out["window_episodes"] = count
        return out

    def evaluate(self, i: int = 0) -> policy_eval.EvalResult:
        """Seed ``i``'s fixed-seed deterministic evaluation at p = 1 (the SA metric's source).

        A group evaluates seed by seed with the single run's program: a vmapped evaluation (its
        episode slots reloading under a batched ``while_loop``) measured 9x one seed's time for 5
        seeds, and seed by seed the evaluation of a policy is the single run's, bit for bit."""
        self.compile()
        ts = self._seed_train_state(i)
        return sharding.to_host(self._compiled_eval(ts.params, ts.normaliser, self.eval_keys))

    def _seed_train_state(self, i: int) -> actor_critic.TrainingState:
        """Seed ``i``'s train state on the devices (a group's slice; a single run's own)."""
        if not self.group:
            return self.runner.train_state
        return _seed_slice(self.runner.train_state, np.int32(i))

    def anneal(self, metric: float, entropy: float) -> lr_schedule.CycleOutcome:
        """A single run's end of cycle by its lr schedule (see ``anneal_seeds``)."""
        return self.anneal_seeds([(metric, entropy)])[0]

    def anneal_seeds(self, ending: list[tuple[float, float] | None]) -> list[lr_schedule.CycleOutcome | None]:
        """The lr schedule's end of cycle for each seed given its (metric, entropy) (None: not ending):
        accept → snapshot, reject → restore the snapshot (unless ``sa.rollback`` is off: then keep going
        from the current parameters); set the lr."""
        decisions: list[lr_schedule.CycleOutcome | None] = []
        for host, end in zip(self.hosts, ending):
            if end is None:
                decisions.append(None)
                continue
            host.lr_state, decision = lr_schedule.end_cycle(self.rule, self.cfg.sa, host.lr_state, end[0], end[1],
                                                            host.sa_rng, n_actions=self.action_size)
            decisions.append(decision)
        restore = [d is not None and d.restore for d in decisions]
        accept = [d is not None and not d.restore and d.kind != "reject" for d in decisions]
        train_state = self._choose(restore, self.runner.snapshot, self.runner.train_state)
        self.runner = self.runner._replace(train_state=train_state,
                                           snapshot=self._choose(accept, train_state, self.runner.snapshot))
        self._apply_lr()
        return decisions

    def cycle_due(self, i: int = 0) -> bool:
        """Seed ``i``'s current cycle's last iteration has run (a cycle ends at its fixed ``schedule.cycle_ends``)."""
        return self.hosts[i].iteration in self.schedule.cycle_ends

    def end_cycle(self) -> dict[str, Any]:
        """A single run's evaluation, annealing and next cycle; returns the row fields."""
        return self.end_cycles([True])[0]

    def end_cycles(self, ending: list[bool]) -> list[dict[str, Any] | None]:
        """Evaluate, anneal and start the next cycle of the seeds in ``ending``; returns each one's row fields."""
        per_seed: list[policy_eval.EvalResult | None] = []
        eval_s: list[float] = []
        for i, end in enumerate(ending):
            t = time.perf_counter()
            per_seed.append(self.evaluate(i) if end else None)
            eval_s.append(time.perf_counter() - t)
        metric = [None if e is None else float(e.mean_return if self.cfg.sa.metric == "return" else e.success_rate)
                  for e in per_seed]
        entropy = [h.entropy_sum / max(h.entropy_n, 1) for h in self.hosts]
        decisions = self.anneal_seeds([(m, h) if e else None for m, h, e in zip(metric, entropy, ending)])
        out: list[dict[str, Any] | None] = []
        for i, (host, decision) in enumerate(zip(self.hosts, decisions)):
            if decision is None:
                out.append(None)
                continue
            host.start_cycle()
            out.append(_cycle_row(host.lr_state, decision, per_seed[i], eval_s[i], metric[i], entropy[i]))
        return out

    # ------------------------------------------------------------------ run

    def _callbacks(self) -> tuple[list[list[Callback]], list[Callback]]:
        """Each seed's logs (metrics.jsonl, TensorBoard; process 0 only) and the callbacks all seeds share."""
        logs: list[list[Callback]] = []
        every, n = self.cfg.train.log_every, self.schedule.num_iterations
        try:
            for host, folder in zip(self.hosts, self.dirs):
                logs.append([])
                if self.primary:
                    logs[-1].append(LoggedRows(run_dir.MetricsLog(folder, resume_iteration=host.iteration), every, n))
                    logs[-1].append(LoggedRows(run_dir.TensorBoardLog(folder, resume_step=host.env_steps), every, n))
        except BaseException:
            for callback in (c for seed in logs for c in seed):
                callback.close()
            raise
        shared: list[Callback] = []
        if self.progress and self.primary:
            spi = self.schedule.steps_per_iteration
            shared.append(ProgressBar(len(self.seeds) * self.schedule.num_iterations * spi,
                                      sum(h.env_steps for h in self.hosts), spi, self.stream))
        return logs, shared

    def train(self, stop_after_cycles: int | None = None) -> dict[str, Any]:
        """Train every seed to ``train.total_steps`` (or stop, checkpointed, after ``stop_after_cycles`` cycles).

        One jitted call per cycle (``run_calls``) runs each seed's iterations up to its cycle's end; its
        rows go to the callbacks afterwards, the cycle's row carrying the evaluation and the SA decision.
        Returns the last row (a group's: seed 0's)."""
        if self.primary:
            for folder in self.dirs:
                os.makedirs(folder, exist_ok=True)
        sched = self.schedule
        logs, shared = self._callbacks()
        last_rows: list[dict[str, Any]] = [{} for _ in self.seeds]
        stopped = [False] * len(self.seeds)
        start_steps = [h.env_steps for h in self.hosts]
        try:
            compile_s = self.compile()["total"]
            t_start = time.perf_counter()  # after compiling: time_s, rates and ETA are training only
            for callback in shared:
                callback.on_start(f"compiled in {compile_s:.1f} s (iteration {self.compile_s['iteration']:.1f} s, "
                                  f"eval {self.compile_s['eval']:.1f} s); {sched.num_iterations} iterations in "
                                  f"{sched.num_cycles} cycles of <= {sched.iterations_per_cycle}, "
                                  f"{self.mesh.size} device(s)"
                                  + (f", {len(self.seeds)} seeds in one program" if self.group else ""))
            while True:
                active = [not s and h.iteration < sched.num_iterations for s, h in zip(stopped, self.hosts)]
                if not any(active):
                    break
                lrs = [h.lr_state.lr for h in self.hosts]  # during this call (fixed-lr schedules)
                temperatures = [None if h.lr_state.sa is None else h.lr_state.sa.temperature for h in self.hosts]
                t_call = time.perf_counter()
                rows = self.run_calls([sched.cycle_end(h.iteration) - h.iteration if a else 0
                                       for h, a in zip(self.hosts, active)])
                t_run = time.perf_counter()
                ending = [bool(r) and "event" not in r[-1] and self.cycle_due(i) for i, r in enumerate(rows)]
                if any(ending):
                    for r, fields in zip(rows, self.end_cycles(ending)):
                        if fields is not None:
                            r[-1].update(fields)
                t_end = time.perf_counter()
                due = []
                for i, (host, seed_rows) in enumerate(zip(self.hosts, rows)):
                    if not seed_rows:
                        continue
                    times = (t_start, t_call, t_run, t_end, compile_s, start_steps[i])
                    self._finish_rows(host, seed_rows, lrs[i], temperatures[i], times)
                    for row in seed_rows:
                        for callback in logs[i] + shared:
                            callback.on_row(row, self.seeds[i] if self.group else None)
                    last_rows[i] = seed_rows[-1]
                    cycles = host.lr_state.cycle
                    finished = host.iteration >= sched.num_iterations
                    stopped[i] = ending[i] and stop_after_cycles is not None and cycles >= stop_after_cycles
                    if finished or stopped[i] or (ending[i] and cycles % self.cfg.train.checkpoint_every_cycles == 0):
                        due.append(i)
                if due:
                    self.save_checkpoint(due)
            if self.primary:
                for i, host in enumerate(self.hosts):
                    if host.iteration >= sched.num_iterations:
                        ts = jax.tree_util.tree_map(lambda x: x[i], self.runner.train_state) if self.group \
                            else self.runner.train_state
                        export_policy(os.path.join(self.dirs[i], POLICY_FILE), self.cfgs[i], ts.params, ts.normaliser,
                                      self.obs_size)
        finally:
            for callback in [c for seed in logs for c in seed] + shared:
                callback.close()
        if self.primary:
            for i, row in enumerate(last_rows):
                if row:
                    who = f"seed {self.seeds[i]}: " if self.group else ""
                    print(who + self.summary(row, self.hosts[i].env_steps - start_steps[i], i), file=self.stream)
        return last_rows[0]

    def _finish_rows(self, host: HostState, rows: list[dict[str, Any]], lr: float, temperature: float | None,
                     times: tuple[float, ...]) -> None:
        """The lr, temperature and wall-clock fields of one seed's rows of a call."""
        t_start, t_call, t_run, t_end, compile_s, start_steps = times
        sched = self.schedule
        for j, row in enumerate(rows):
            last = j == len(rows) - 1
            row["lr"] = host.lr_state.lr if last else row.get("lr", lr)  # the lr after the row's iteration
            if host.lr_state.sa is not None:
                row.setdefault("temperature", host.lr_state.sa.temperature if last else temperature)
            elapsed = (t_end if last else t_call + (j + 1) / len(rows) * (t_run - t_call)) - t_start
            done = row["iteration"] + 1
            rate = (done * sched.steps_per_iteration - start_steps) / max(elapsed, 1e-9)
            row.update(time_s=elapsed, compile_s=compile_s, compile_iteration_s=self.compile_s["iteration"],
                       compile_eval_s=self.compile_s["eval"],
                       eta_s=(sched.num_iterations - done) * sched.steps_per_iteration / max(rate, 1e-9))

    def summary(self, row: dict[str, Any], steps: int, i: int = 0) -> str:
        """One line for the end of a run: speed, compile time, SA counts, last evaluation."""
        host = self.hosts[i]
        sa, lr = host.lr_state.sa, host.lr_state.lr
        schedule = (f"SA accept {sa.n_accept}, accept-worse {sa.n_accept_worse}, reject {sa.n_reject}, "
                    f"decays {sa.decays}, lr {sa.lr:.3g}" if sa is not None else
                    f"{self.rule.name} lr schedule, lr {lr:.3g}" + (" (PPO)" if self.rule.name == "constant" else ""))
        return (f"{steps:,} env steps this session, {row['time_s']:.1f} s training ({steps / max(row['time_s'], 1e-9):,.0f} "
                f"steps/s incl. evaluation) + {row['compile_s']:.1f} s compile; {schedule}; "
                f"non-finite {host.nonfinite}; last eval success {_fmt(row.get('eval_success'))}, "
                f"return {_fmt(row.get('eval_return'))}")


def _cycle_row(state: lr_schedule.ScheduleState, decision: lr_schedule.CycleOutcome, ev: policy_eval.EvalResult,
               eval_s: float, metric: float, entropy: float) -> dict[str, Any]:
    """The row fields of a cycle's end: its evaluation and the lr schedule's decision."""
    row = {
        "cycle": state.cycle, "eval_s": eval_s, "eval_return": float(ev.mean_return),
        "eval_success": float(ev.success_rate), "eval_steps_to_success": float(ev.steps_to_success),
        "eval_collision": float(ev.collision_rate), "eval_timeout": float(ev.timeout_rate),
        "sa_metric": metric, "cycle_entropy": entropy, "sa_decision": decision.kind,
        "sa_decayed": decision.decayed, "rollbacks": state.rollbacks,
    }
    sa = state.sa
    if sa is None:  # every cycle kept but those rolled back for a non-finite step
        row.update(sa_accepts=state.cycle - state.rollbacks, sa_rejects=state.rollbacks)
    else:
        row.update(sa_delta_e=decision.delta_e, sa_accept_prob=decision.accept_prob,
                   temperature=decision.temperature, sa_accepts=sa.n_accept, sa_accept_worse=sa.n_accept_worse,
                   sa_rejects=sa.n_reject, sa_decays=sa.decays)
    return row


@jax.jit
def _seed_slice(tree: Any, i: jax.Array) -> Any:
    """Seed ``i``'s slice of a group's stacked device tree."""
    return jax.tree_util.tree_map(lambda x: x[i], tree)


@jax.jit
def _select_seeds(mask: jax.Array, new: Any, old: Any) -> Any:
    """Per seed (leading axis), ``new`` where ``mask`` else ``old``."""
    return jax.tree_util.tree_map(lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b),
                                  new, old)


def seed_config(cfg: Config, seed: int) -> Config:
    """A group member's config: the group's with its own ``train.seed`` (what its run folder records)."""
    return apply_overrides(cfg, [f"train.seed={seed}"])


def seed_dir(out: str, seed: int) -> str:
    """A group member's run folder."""
    return os.path.join(out, f"seed{seed}")


def _placed_like(tree: Any, fresh: Any) -> Any:
    """``tree`` (host arrays from a checkpoint) on the devices exactly as ``fresh`` (the same state
    made by this run's jitted reset) is: the compiled cycle wants its inputs' shardings.  Not simply
    split over the batch axis: XLA leaves zero-size leaves (dynamic mode's empty MJX fields, [B, 0])
    replicated, and a resumed run that split them fails its second call (issue 27)."""
    shardings = jax.tree_util.tree_map(lambda x: x.sharding, fresh)
    return jax.device_put(sharding.placeable(tree), shardings)


def _fmt(value: Any) -> str:
    return "-" if value is None else f"{value:.3g}"


# ---------------------------------------------------------------------- CLI

class _ListKeys(argparse.Action):
    """``--list-keys``: print every config key (meaning, value, valid values) and exit, like --help."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        from sagrasp_jax.config import describe_keys

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
    p = argparse.ArgumentParser(prog="python -m sagrasp_jax.train", description=__doc__.split("\n\n")[0],
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
    dist = p.add_argument_group("multi-process training (jax.distributed, one process per host; see sagrasp_jax.distributed)")
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
        run_dir.check_init_from(cfg)
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


class Terminated(KeyboardInterrupt):
    """SIGTERM during a training (``train.main``): stops it like Ctrl-C, at any point."""


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Any:
    """SIGTERM raises ``Terminated`` (a KeyboardInterrupt) for the block: the run stops as on Ctrl-C,
    with its message and exit status 143, and resumes from its last checkpoint."""
    import signal

    def handler(signum: int, frame: Any) -> None:
        raise Terminated()

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread: leave SIGTERM alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
