"""SA-PPO / PPO trainer: ``python -m sagrasp_jax.train --preset cpu-quick --out runs/NAME``.

The loop is a handful of named steps on a :class:`Trainer`: ``run_iteration`` (one jitted PPO
iteration: rollout + update), ``evaluate`` (fixed-seed deterministic episodes at p = 1),
``anneal`` (the lr schedule's end of cycle, ``lr_schedule.end_cycle``: SA's decision on the
evaluation metric), ``save_checkpoint``.  ``--algo sa-ppo`` / ``--algo ppo`` are
``--lr-schedule sa`` / ``--lr-schedule constant``; ``--lr-schedule`` also takes kl-adaptive,
cosine and linear.
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
import dataclasses
import math
import os
import sys
import time
from dataclasses import dataclass
from typing import Any, Callable, TextIO

from sagrasp_jax import extras

if __name__ == "__main__":  # a missing extra ends in one line naming it (exit 2), not an import traceback
    extras.require_cli("train", prog="python -m sagrasp_jax.train")

import jax  # noqa: E402
import numpy as np

from sagrasp_jax import checkpoint, distributed, fileio, lr_schedule, observation, ppo, run_dir, sa_schedule
from sagrasp_jax.checkpoint import CheckpointError
from sagrasp_jax.config import (
    LR_SCHEDULES, PRESETS, SEED_RANGE, Config, ConfigError, apply_overrides, check_range, file_overrides, get_config,
    training_env_config, validate,
)
from sagrasp_jax.run_dir import CHECKPOINT_FILE, CONFIG_FILE, POLICY_FILE, RunDirError, RunLogger, export_policy

ALGOS = ("sa-ppo", "ppo")
ALGO_SCHEDULES = {"sa-ppo": "sa", "ppo": "constant"}  # --algo is shorthand for these lr schedules
# Row fields that depend on wall-clock time, not on the training maths.
TIME_FIELDS = ("time_s", "steps_per_s", "compile_s", "compile_iteration_s", "compile_eval_s", "eval_s", "eta_s")

EnvFactory = Callable[[Config], tuple[ppo.Env, ppo.Env]]  # config -> (auto-reset train env, eval env)
# On CPU the SA evaluation runs this many episodes at a time per device, each slot taking the next
# episode when its own ends (ppo.evaluate_policy): ≈ 2x faster than all 128 at once, the same
# numbers.  Accelerators evaluate all episodes at once.
CPU_EVAL_SLOTS = 32


def enable_compilation_cache() -> None:
    """Point jax's persistent cache at the dir sagrasp_jax/__init__ chose (in case jax came first)."""
    cache = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if cache:
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs",
                          float(os.environ.get("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1")))


def default_envs(cfg: Config) -> tuple[ppo.Env, ppo.Env]:
    from sagrasp_jax.env import GraspEnv
    from sagrasp_jax.wrappers import AutoReset

    # training episodes follow the training mix (train.obstacle_prob / blocking_prob), evaluation the task's (docs/task.md §2.8)
    return AutoReset(GraspEnv(training_env_config(cfg), privileged=cfg.ppo.privileged_critic)), GraspEnv(cfg.env)


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


@dataclass
class HostState:
    """Host-side counters; JSON-safe, stored in the checkpoint header."""

    iteration: int = 0  # completed PPO iterations
    env_steps: int = 0
    cycle_start: int = 0  # iteration at which the current cycle began
    entropy_sum: float = 0.0  # over the current cycle's iterations
    entropy_n: int = 0
    nonfinite: int = 0  # iterations rolled back for NaN/inf


class Trainer:
    """One training run bound to a run folder."""

    def __init__(self, cfg: Config, out_dir: str, *, env_factory: EnvFactory | None = None, resume: bool = False,
                 progress: bool = True, stream: TextIO | None = None, devices: list[Any] | None = None) -> None:
        enable_compilation_cache()
        self.cfg = cfg
        self.out_dir = out_dir
        self.progress = progress
        self.stream = stream if stream is not None else sys.stderr
        self.mesh = ppo.make_mesh(devices)  # default: every device (of every process)
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
        self.networks = ppo.make_networks(cfg.ppo.network, self.obs_size, self.action_size, cfg.ppo.obs_clip,
                                          self.critic_extra)
        self.rule = lr_schedule.rule_of(cfg)
        self.optimizer = ppo.make_optimizer(cfg.ppo, cfg.ppo.learning_rate)
        self.hand_scaled = getattr(self.eval_env, "hand_scaled_mask", None)  # normaliser leaves these entries alone
        self._cycle = ppo.make_cycle(self.train_env, self.networks, self.optimizer, cfg.ppo, self.mesh,
                                     self.schedule.iterations_per_cycle, self.hand_scaled, self.critic_extra,
                                     self.rule)
        keys = ppo.eval_keys(cfg.eval.seed, cfg.eval.episodes)
        split = cfg.eval.episodes % self.mesh.size == 0
        self.eval_keys = ppo.shard_batch(keys, self.mesh) if split else ppo.replicate(keys, self.mesh)
        slots = CPU_EVAL_SLOTS if jax.default_backend() == "cpu" else None
        evaluate = ppo.make_evaluator(self.networks, self.eval_env, cfg.env.task.max_steps,
                                      self.mesh if split else None, slots)
        self._evaluate = jax.jit(lambda params, normaliser, keys: evaluate(params, normaliser, keys)._replace(episodes={}))
        episode = jax.eval_shape(self.train_env.reset, jax.random.PRNGKey(0)).info["episode"]
        self.window_keys = tuple(episode)
        self._compiled_cycle: Any = None
        self._compiled_eval: Any = None
        self.compile_s: dict[str, float] = {}
        self._resuming = resume
        self._fresh_state()
        if resume:
            self._load(os.path.join(out_dir, CHECKPOINT_FILE))

    # ------------------------------------------------------------------ state

    def _fresh_state(self) -> None:
        cfg = self.cfg
        k_params, k_env, k_train = jax.random.split(jax.random.PRNGKey(cfg.train.seed), 3)
        ts = ppo.init_training_state(k_params, self.networks, self.optimizer, self.obs_size)
        if cfg.train.init_from and not self._resuming:  # --init-from: another run's policy and normaliser
            ts = run_dir.init_policy_state(ts, cfg, self.obs_size, self.action_size)
        self.train_state: ppo.TrainingState = ppo.replicate(ts, self.mesh)
        self.snapshot: ppo.TrainingState = self.train_state
        reset = ppo.make_reset(self.train_env, self.mesh)
        self.env_state = reset(ppo.shard_batch(jax.random.split(k_env, cfg.ppo.num_envs), self.mesh))
        self.train_key = ppo.replicate(k_train, self.mesh)
        self.lr_state = lr_schedule.init(self.rule)
        self.sa_rng = np.random.default_rng([cfg.train.seed, 0x5A])
        self.host = HostState()
        self.window = ppo.replicate(ppo.init_window(self.window_keys, cfg.train.metrics_window), self.mesh)

    def _trees(self) -> dict[str, Any]:
        return {"train_state": self.train_state, "snapshot": self.snapshot, "env_state": self.env_state,
                "train_key": self.train_key, "episode_window": self.window}

    def save_checkpoint(self) -> str:
        """Atomically write everything an exact resume needs (under jax.distributed every process
        gathers, process 0 writes)."""
        path = os.path.join(self.out_dir, CHECKPOINT_FILE)
        host = {"counters": dataclasses.asdict(self.host), "lr_state": self.lr_state.to_dict(),
                "sa_rng": self.sa_rng.bit_generator.state}
        trees = ppo.to_host(self._trees())
        if self.primary:
            checkpoint.save(path, trees=trees, host=host, config=self.cfg)
        return path

    def _load(self, path: str) -> None:
        ckpt = checkpoint.load(path)
        checkpoint.check_config(ckpt, self.cfg)
        try:
            host = ckpt.host
            counters = HostState(**host["counters"])
            if "lr_state" in host:
                lr_state = lr_schedule.ScheduleState.from_dict(host["lr_state"])
            else:  # written before lr schedules: SA's state machine served plain PPO too
                lr_state = lr_schedule.from_legacy(host["sa_state"], self.rule.name)
            if (lr_state.sa is None) != (self.rule.name != "sa"):
                raise ValueError(f"its lr-schedule state does not fit lr.schedule={self.rule.name}")
            rng = np.random.default_rng()
            rng.bit_generator.state = host["sa_rng"]
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"{path}: incompatible checkpoint host state ({exc})") from None
        trees = {name: checkpoint.restore_tree(tmpl, ckpt.trees.get(name, {}), name, path)
                 for name, tmpl in ppo.to_host(self._trees()).items()}
        self.train_state = ppo.replicate(trees["train_state"], self.mesh)
        self.snapshot = ppo.replicate(trees["snapshot"], self.mesh)
        self.env_state = _placed_like(trees["env_state"], self.env_state)
        self.train_key = ppo.replicate(trees["train_key"], self.mesh)
        self.window = ppo.replicate(trees["episode_window"], self.mesh)
        self.host, self.lr_state, self.sa_rng = counters, lr_state, rng

    @property
    def lr(self) -> float:
        """The learning rate the next iteration starts from."""
        return self.lr_state.lr

    @property
    def sa_state(self) -> sa_schedule.SAState | None:
        """The SA state machine's state (``lr.schedule = sa``; None under the other schedules)."""
        return self.lr_state.sa

    def _apply_lr(self) -> None:
        """Make the optimizer state's lr the schedule's (after a decay or a restore)."""
        opt = self.train_state.opt_state
        if ppo.get_learning_rate(opt) != np.float32(self.lr):
            self.train_state = self.train_state._replace(opt_state=ppo.set_learning_rate(opt, self.lr))

    # ------------------------------------------------------------------ compiled steps

    def _cycle_args(self, count: int) -> tuple[Any, ...]:
        """Arguments of the jitted call running iterations ``host.iteration …`` (+ ``count``)."""
        first = self.host.iteration
        progress = np.array([self._progress(first + j) for j in range(self.schedule.iterations_per_cycle)], np.float32)
        lrs = lr_schedule.iteration_lrs(self.rule, self.lr_state, progress)
        scalars = ppo.replicate((np.int32(first), np.int32(count), progress, lrs), self.mesh)
        return (self.train_state, self.env_state, self.window, self.train_key, *scalars)

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
            lowered = self._cycle.lower(*self._cycle_args(1))
            with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="compile-training-call") as pool:
                cycle = pool.submit(lambda: (lowered.compile(), time.perf_counter() - t))
                compiled_eval = self._evaluate.lower(self.train_state.params, self.train_state.normaliser,
                                                     self.eval_keys).compile()
                eval_s = time.perf_counter() - t
                self._compiled_cycle, cycle_s = cycle.result()  # re-raises the worker's error here
            self._compiled_eval = compiled_eval
            self.compile_s = {"iteration": cycle_s, "eval": eval_s, "total": time.perf_counter() - t}
        return self.compile_s

    def run_iteration(self) -> dict[str, Any]:
        """One PPO iteration (rollout + update); a non-finite result restores the snapshot."""
        return self.run_iterations(1)[-1]

    def run_iterations(self, count: int) -> list[dict[str, Any]]:
        """Up to ``count`` (≤ ``schedule.iterations_per_cycle``) PPO iterations in one jitted call and
        one host sync, one row each.  A non-finite iteration ends the call and restores the snapshot."""
        if not 1 <= count <= self.schedule.iterations_per_cycle:
            raise ValueError(f"run_iterations: count {count} outside 1 … {self.schedule.iterations_per_cycle}")
        self.compile()
        spi, total = self.schedule.steps_per_iteration, self.cfg.train.total_steps
        first = self.host.iteration
        t = time.perf_counter()
        ts, env_state, window, metrics = self._compiled_cycle(*self._cycle_args(count))
        metrics = ppo.to_host(metrics)
        dt = time.perf_counter() - t
        self.env_state, self.window = env_state, window
        means, finite = metrics.pop("window"), metrics.pop("finite")
        ran = int(metrics.pop("executed").sum())
        device_lr = metrics.pop("learning_rate")
        rows: list[dict[str, Any]] = []
        for j in range(ran):
            progress = self.host.env_steps / total
            self.host.iteration += 1
            self.host.env_steps += spi
            row: dict[str, Any] = {"iteration": first + j, "env_steps": self.host.env_steps, "progress": progress,
                                   "steps_per_s": spi * ran / dt,
                                   "episodes_finished": int(metrics["episodes_finished"][j])}
            row.update({k: float(v[j]) for k, v in metrics.items() if k != "episodes_finished"})
            row.update(self._window_row(means, j))
            if self.rule.mode == "kl":  # the lr after this iteration: what the next one starts from
                row["lr"] = float(device_lr[j])
            elif self.rule.mode == "per_iteration":
                row["lr"] = float(lr_schedule.progress_lr(np, self.rule, np.float32(self._progress(first + j + 1))))
            if finite[j]:
                self.host.entropy_sum += float(metrics["entropy"][j])
                self.host.entropy_n += 1
            rows.append(row)
        if finite[ran - 1]:
            self.train_state = ts
            self.lr_state = lr_schedule.observe(self.rule, self.lr_state, device_lr=float(device_lr[ran - 1]),
                                                progress=self._progress(self.host.iteration))
        else:
            self.host.nonfinite += 1
            self.lr_state, decision = lr_schedule.nonfinite(
                self.rule, self.cfg.sa, self.lr_state, snapshot_lr=ppo.get_learning_rate(self.snapshot.opt_state),
                progress=self._progress(self.host.iteration))
            self.train_state = self.snapshot
            self._apply_lr()
            self._start_cycle()
            rows[-1].update(event="nonfinite", sa_decision=decision.kind, sa_decayed=decision.decayed)
        return rows

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

    def evaluate(self) -> ppo.EvalResult:
        """The fixed-seed deterministic evaluation at p = 1 (the SA metric's source)."""
        self.compile()
        ts = self.train_state
        return ppo.to_host(self._compiled_eval(ts.params, ts.normaliser, self.eval_keys))

    def anneal(self, metric: float, entropy: float) -> lr_schedule.CycleOutcome:
        """The lr schedule's end of cycle: accept → snapshot, reject → restore the snapshot (unless
        ``sa.rollback`` is off: then keep going from the current parameters); set the lr."""
        self.lr_state, decision = lr_schedule.end_cycle(self.rule, self.cfg.sa, self.lr_state, metric, entropy,
                                                        self.sa_rng, n_actions=self.action_size)
        if decision.restore:
            self.train_state = self.snapshot
        elif decision.kind != "reject":
            self.snapshot = self.train_state
        self._apply_lr()
        return decision

    def _start_cycle(self) -> None:
        self.host.cycle_start = self.host.iteration
        self.host.entropy_sum, self.host.entropy_n = 0.0, 0

    def cycle_due(self) -> bool:
        """The current cycle's last iteration has run (a cycle ends at its fixed ``schedule.cycle_ends``)."""
        return self.host.iteration in self.schedule.cycle_ends

    def end_cycle(self) -> dict[str, Any]:
        """Evaluate, anneal, start the next cycle; returns the row fields."""
        t = time.perf_counter()
        ev = self.evaluate()
        eval_s = time.perf_counter() - t
        metric = float(ev.mean_return if self.cfg.sa.metric == "return" else ev.success_rate)
        entropy = self.host.entropy_sum / max(self.host.entropy_n, 1)
        decision = self.anneal(metric, entropy)
        self._start_cycle()
        state = self.lr_state
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

    # ------------------------------------------------------------------ run

    def train(self, stop_after_cycles: int | None = None) -> dict[str, Any]:
        """Train to ``train.total_steps`` (or stop, checkpointed, after ``stop_after_cycles`` cycles).

        One jitted call per SA cycle (``run_iterations``) runs the cycle's iterations; its rows are
        written afterwards, the cycle's row carrying the evaluation and the SA decision."""
        if self.primary:
            os.makedirs(self.out_dir, exist_ok=True)
        logger = (RunLogger(self.out_dir, resume_iteration=self.host.iteration, resume_step=self.host.env_steps)
                  if self.primary else None)
        sched = self.schedule
        bar = _progress_bar(self.progress and self.primary, sched, self.host.env_steps, self.stream)
        last_row: dict[str, Any] = {}
        last_metric: float | None = None
        compile_s = self.compile()["total"]
        t_start = time.perf_counter()  # after compiling: time_s, rates and ETA are training only
        start_steps = self.host.env_steps
        if bar is not None:
            bar.write(f"compiled in {compile_s:.1f} s (iteration {self.compile_s['iteration']:.1f} s, "
                      f"eval {self.compile_s['eval']:.1f} s); {sched.num_iterations} iterations in "
                      f"{sched.num_cycles} cycles of <= {sched.iterations_per_cycle}, {self.mesh.size} device(s)")
        try:
            while self.host.iteration < sched.num_iterations:
                lr = self.lr  # during this call (fixed-lr schedules)
                temperature = None if self.sa_state is None else self.sa_state.temperature
                t_call = time.perf_counter()
                end = sched.cycle_end(self.host.iteration)
                rows = self.run_iterations(end - self.host.iteration)
                t_run = time.perf_counter()
                cycle_ended = "event" not in rows[-1] and self.cycle_due()
                if cycle_ended:
                    rows[-1].update(self.end_cycle())
                t_end = time.perf_counter()
                for j, row in enumerate(rows):
                    last = j == len(rows) - 1
                    row["lr"] = self.lr if last else row.get("lr", lr)  # the lr after the row's iteration
                    if self.sa_state is not None:
                        row.setdefault("temperature", self.sa_state.temperature if last else temperature)
                    elapsed = (t_end if last else t_call + (j + 1) / len(rows) * (t_run - t_call)) - t_start
                    done = row["iteration"] + 1
                    rate = (done * sched.steps_per_iteration - start_steps) / max(elapsed, 1e-9)
                    row.update(time_s=elapsed, compile_s=compile_s, compile_iteration_s=self.compile_s["iteration"],
                               compile_eval_s=self.compile_s["eval"],
                               eta_s=(sched.num_iterations - done) * sched.steps_per_iteration / max(rate, 1e-9))
                    if logger is not None and ((cycle_ended and last) or "event" in row
                                               or row["iteration"] % self.cfg.train.log_every == 0
                                               or done == sched.num_iterations):
                        logger.write(row)
                    last_metric = row.get("sa_metric", last_metric)
                    if bar is not None:
                        bar.update(sched.steps_per_iteration)
                        bar.set_postfix(sps=f"{rate:,.0f}", success=_fmt(row.get("success")), lr=f"{row['lr']:.2e}",
                                        M=_fmt(last_metric), refresh=False)
                        if "event" in row:
                            bar.write(f"iteration {row['iteration']}: non-finite loss/params -> rolled back to the "
                                      f"snapshot, lr {self.lr:.3g}")
                last_row = rows[-1]
                cycles = self.lr_state.cycle
                finished = self.host.iteration >= sched.num_iterations
                stop = cycle_ended and stop_after_cycles is not None and cycles >= stop_after_cycles
                if finished or stop or (cycle_ended and cycles % self.cfg.train.checkpoint_every_cycles == 0):
                    self.save_checkpoint()
                if stop and not finished:
                    return last_row
            if self.host.iteration >= sched.num_iterations and self.primary:
                export_policy(os.path.join(self.out_dir, POLICY_FILE), self.cfg, self.train_state.params,
                              self.train_state.normaliser, self.obs_size)
        finally:
            if logger is not None:
                logger.close()
            if bar is not None:
                bar.close()
        if last_row and self.primary:
            print(self.summary(last_row, self.host.env_steps - start_steps), file=self.stream)
        return last_row

    def summary(self, row: dict[str, Any], steps: int) -> str:
        """One line for the end of a run: speed, compile time, SA counts, last evaluation."""
        sa = self.sa_state
        schedule = (f"SA accept {sa.n_accept}, accept-worse {sa.n_accept_worse}, reject {sa.n_reject}, "
                    f"decays {sa.decays}, lr {sa.lr:.3g}" if sa is not None else
                    f"{self.rule.name} lr schedule, lr {self.lr:.3g}" + (" (PPO)" if self.rule.name == "constant" else ""))
        return (f"{steps:,} env steps this session, {row['time_s']:.1f} s training ({steps / max(row['time_s'], 1e-9):,.0f} "
                f"steps/s incl. evaluation) + {row['compile_s']:.1f} s compile; {schedule}; "
                f"non-finite {self.host.nonfinite}; last eval success {_fmt(row.get('eval_success'))}, "
                f"return {_fmt(row.get('eval_return'))}")


def _placed_like(tree: Any, fresh: Any) -> Any:
    """``tree`` (host arrays from a checkpoint) on the devices exactly as ``fresh`` (the same state
    made by this run's jitted reset) is: the compiled cycle wants its inputs' shardings.  Not simply
    split over the batch axis: XLA leaves zero-size leaves (dynamic mode's empty MJX fields, [B, 0])
    replicated, and a resumed run that split them fails its second call (issue 27)."""
    shardings = jax.tree_util.tree_map(lambda x: x.sharding, fresh)
    return jax.device_put(ppo._placeable(tree), shardings)


def _fmt(value: Any) -> str:
    return "-" if value is None else f"{value:.3g}"


def _progress_bar(enabled: bool, sched: Schedule, initial: int, stream: TextIO) -> Any:
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=sched.num_iterations * sched.steps_per_iteration, initial=initial, unit="step",
                unit_scale=True, dynamic_ncols=True, mininterval=1.0, file=stream)


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


def resolve_config(args: argparse.Namespace) -> Config:
    """The run's config; on --resume without config options it is the run folder's config.json."""
    overrides = list(args.overrides)
    if args.init_from is not None:
        overrides.append(f"train.init_from={os.path.abspath(args.init_from)}")
    explicit = any(v is not None for v in (args.preset, args.algo, args.lr_schedule, args.seed, args.total_steps,
                                           args.config)) or overrides
    if args.resume and not explicit:
        if not os.path.isfile(os.path.join(args.out, CONFIG_FILE)) and not os.path.isfile(os.path.join(args.out, CHECKPOINT_FILE)):
            raise RunDirError(f"{args.out}: cannot resume, no {CONFIG_FILE} and no {CHECKPOINT_FILE} there (the run "
                              "wrote neither); start it again without --resume, or pass its config options")
        return run_dir.load_config(args.out)
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
        progress: bool = True, stop_after_cycles: int | None = None, stream: TextIO | None = None) -> Trainer:
    """Library entry point: validate, lock and check the folder, train; returns the finished trainer.

    Everything that can refuse the run (config, folder, checkpoint, metrics log, a second writer,
    a read-only location) is checked before the env is built, and nothing is written before
    all of it passed.  See ``run_dir`` for the fresh / resume / restart rules."""
    validate(cfg)
    if cfg.train.init_from and not resume:  # refuse an unusable --init-from before the run folder is touched
        run_dir.check_init_from(cfg)
    primary = jax.process_index() == 0  # under jax.distributed process 0 owns the run folder
    lock = run_dir.FolderLock(out, create=True, what="run folder") if primary else contextlib.nullcontext()
    with lock:
        try:
            mode = run_dir.prepare_training(out, cfg, resume) if primary else ("resume" if resume else "fresh")
        except (CheckpointError, RunDirError):
            distributed.all_ok(False)  # under jax.distributed the other processes stop too
            raise
        if not distributed.all_ok(True):
            raise CheckpointError(f"{out}: another process refused this run folder (see its error)")
        if mode == "restart":
            print(f"{out}: no checkpoint yet (the run stopped before its first one): restarting it from the "
                  "beginning", file=stream if stream is not None else sys.stderr)
        trainer = Trainer(cfg, out, env_factory=env_factory, resume=mode == "resume", progress=progress,
                          stream=stream)  # writes nothing
        if mode != "resume" and trainer.primary:
            run_dir.write_config(out, cfg)
        trainer.train(stop_after_cycles=stop_after_cycles)
    return trainer


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        check_args(args)
        cfg = resolve_config(args)
        distributed.check_options(args.coordinator, args.num_processes, args.process_id, cfg.ppo.num_envs,
                                  args.connect_timeout)
        use_cpu_devices(cfg, args.num_processes if args.coordinator else 1)
        if args.coordinator:
            distributed.initialize(args.coordinator, args.num_processes, args.process_id, args.connect_timeout)
        with _sigterm_as_interrupt():
            run(cfg, args.out, resume=args.resume, progress=not args.no_progress,
                stop_after_cycles=args.stop_after_cycles)
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
