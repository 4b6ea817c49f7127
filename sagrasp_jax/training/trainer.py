"""The SA-PPO / PPO trainer: one run, or a seed group in one compiled program, bound to run folders.

``Trainer`` builds the envs, networks and the two compiled programs (a cycle's PPO iterations, the
fixed-seed evaluation) and runs the loop: ``run_calls`` → ``end_cycles`` (evaluate, anneal) →
checkpoint.  Its parts live beside it: the per-seed state and its placement (``seed_group``), the
checkpoints (``group_checkpoint``), the schedule that turns a call's and a cycle's results into counters,
lr and SA decisions (``cycles``), and the rows' way to the logs and the progress bar (``run_log``).
"""

from __future__ import annotations

import concurrent.futures
import os
import sys
import time
from typing import Any, Callable, TextIO

import jax

from sagrasp_jax.base import xla_flags
from sagrasp_jax.task import observation
from sagrasp_jax.task.config import Config, ConfigError, training_env_config
from sagrasp_jax.training import (
    cycles, group_checkpoint, loop, lr_schedule, metrics_window, restore, run_dir, run_log, sharding,
)
from sagrasp_jax.training.agents.ppo import actor_critic, ppo, rollout
from sagrasp_jax.training import fixed_seed_eval as policy_eval
from sagrasp_jax.training.seed_group import HostState, RunnerState, SeedGroup

EnvFactory = Callable[[Config], tuple[rollout.Env, rollout.Env]]  # config -> (auto-reset train env, eval env)
# On CPU the SA evaluation runs this many episodes at a time per device, each slot taking the next
# episode when its own ends (policy_eval.evaluate_policy): ≈ 2x faster than all 128 at once, the same
# numbers.  Accelerators evaluate all episodes at once.
CPU_EVAL_SLOTS = 32


def enable_compilation_cache() -> None:
    """Point jax's persistent cache at the dir sagrasp_jax/__init__ chose (in case jax came first)."""
    cache = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if cache:
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs",
                          float(os.environ.get("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1")))


def default_envs(cfg: Config) -> tuple[rollout.Env, rollout.Env]:
    from sagrasp_jax.envs.auto_reset import AutoReset
    from sagrasp_jax.envs.grasp_env import GraspEnv

    # training episodes follow the training mix (train.obstacle_prob / blocking_prob), evaluation the task's (docs/task.md §2.8)
    return (AutoReset(GraspEnv(training_env_config(cfg), privileged=cfg.ppo.privileged_critic),
                      replay=cfg.train.curriculum_replay, max_replays=cfg.train.curriculum_max_replays), GraspEnv(cfg.env))


class Trainer:
    """One training run bound to a run folder, or a seed group (``seeds``) bound to ``out_dir/seed<S>`` folders.

    The single-run accessors (``host``, ``train_state``, ``lr``, ``run_iterations``, ``anneal`` …) are
    the group's seed 0 when there is no group."""

    def __init__(self, cfg: Config, out_dir: str, *, env_factory: EnvFactory | None = None, resume: bool | list[bool] = False,
                 progress: bool = True, stream: TextIO | None = None, devices: list[Any] | None = None,
                 seeds: list[int] | None = None) -> None:
        enable_compilation_cache()
        self.cfg, self.out_dir, self.progress = cfg, out_dir, progress
        self.stream = stream if stream is not None else sys.stderr
        self.mesh = sharding.make_mesh(devices)  # default: every device (of every process)
        self.primary = jax.process_index() == 0  # under jax.distributed only process 0 writes files
        if cfg.ppo.num_envs % self.mesh.size:
            raise ConfigError(f"ppo.num_envs={cfg.ppo.num_envs} must be divisible by the {self.mesh.size} devices")
        self.train_env, self.eval_env = (env_factory or default_envs)(cfg)
        # XLA options of every program the trainer compiles (train.cpu_fusion_emitters); seeds of a group share them
        self.compiler_options, note = xla_flags.emitter_options(cfg.train.cpu_fusion_emitters, jax.default_backend(),
                                                                xla_flags.installed_jaxlib_version())
        if note and self.primary:
            print(note, file=self.stream)
        self.obs_size, self.action_size = self.train_env.observation_size, self.train_env.action_size
        self.schedule = cycles.make_schedule(cfg)
        self.critic_extra = observation.critic_extra_size(cfg)  # privileged critic inputs (0: none)
        provided = getattr(getattr(self.train_env, "env", self.train_env), "privileged_size", 0)
        if self.critic_extra and provided != self.critic_extra:
            raise ConfigError(f"ppo.privileged_critic needs an env that reports {self.critic_extra} privileged inputs "
                              f"(GraspEnv(privileged=True)); the training env reports {provided}")
        self.networks = actor_critic.make_networks(cfg.ppo.network, self.obs_size, self.action_size, cfg.ppo.obs_clip,
                                                   self.critic_extra)
        self.rule = lr_schedule.rule_of(cfg)
        self.optimizer = actor_critic.make_optimizer(cfg.ppo)
        self.hand_scaled = getattr(self.eval_env, "hand_scaled_mask", None)  # normaliser leaves these entries alone
        self.seed_group = SeedGroup(cfg, out_dir, seeds, self.mesh, self.rule)
        self._cycle = ppo.make_cycle(self.train_env, self.networks, self.optimizer, cfg.ppo, self.mesh,
                                     self.schedule.iterations_per_cycle, self.hand_scaled, self.critic_extra,
                                     self.rule, seed_axis=self.group)
        keys = policy_eval.eval_keys(cfg.eval.seed, cfg.eval.episodes)
        split = cfg.eval.episodes % self.mesh.size == 0
        self.eval_keys = sharding.shard_batch(keys, self.mesh) if split else sharding.replicate(keys, self.mesh)
        slots = policy_eval.slots_for_backend(CPU_EVAL_SLOTS)
        evaluate = policy_eval.make_evaluator(self.networks, self.eval_env, cfg.env.task.max_steps,
                                              self.mesh if split else None, slots)
        # a group evaluates seed by seed with this single-seed program (see ``evaluate``)
        self._evaluate = jax.jit(lambda params, normaliser, keys: evaluate(params, normaliser, keys)._replace(episodes={}))
        self._compiled_cycle: Any = None
        self._compiled_eval: Any = None
        self.compile_s: dict[str, float] = {}
        resumed = resume if isinstance(resume, list) else [resume] * len(self.seeds)
        self._reset = rollout.make_reset(self.train_env, self.mesh, self.compiler_options)
        self._init_state = actor_critic.jitted_init_training_state(self.networks, self.optimizer, self.obs_size,
                                                                   self.compiler_options)
        self.runner = self.seed_group.place(self._fresh_one(c, r) for c, r in zip(self.cfgs, resumed))
        if any(resumed):
            group_checkpoint.load(self.seed_group, group_checkpoint.paths(self.seed_group, resumed), self.rule)

    def _fresh_one(self, cfg: Config, resuming: bool) -> RunnerState:
        """One seed's initial device state, exactly as a single run of ``cfg`` starts."""
        k_params, k_env, k_train = jax.random.split(jax.random.PRNGKey(cfg.train.seed), 3)
        ts = self._init_state(k_params)
        if cfg.train.init_from and not resuming:  # --init-from: another run's policy and normaliser
            ts = restore.init_policy_state(ts, cfg, self.obs_size, self.action_size)
        train_state = sharding.replicate(ts, self.mesh)
        env_state = self._reset(sharding.shard_batch(jax.random.split(k_env, cfg.ppo.num_envs), self.mesh))
        # the window keeps the training env's episode metrics: their names read off the reset state itself (a trace of
        # the env's reset only for its keys cost ≈ 1.2 s a start)
        self.window_keys = tuple(env_state.info["episode"])
        window = sharding.replicate(metrics_window.init_window(self.window_keys, cfg.train.metrics_window), self.mesh)
        return RunnerState(train_state, train_state, env_state, sharding.replicate(k_train, self.mesh), window)

    # the group's state, and a single run's views of it (seed 0 of a group)
    group = property(lambda self: self.seed_group.group)
    seeds = property(lambda self: self.seed_group.seeds)
    cfgs = property(lambda self: self.seed_group.cfgs)
    dirs = property(lambda self: self.seed_group.dirs)
    hosts = property(lambda self: self.seed_group.hosts)
    runner = property(lambda self: self.seed_group.runner, lambda self, value: setattr(self.seed_group, "runner", value))
    host: HostState = property(lambda self: self.hosts[0])  # type: ignore[assignment]
    train_state = property(lambda self: self.runner.train_state)
    snapshot = property(lambda self: self.runner.snapshot)
    env_state = property(lambda self: self.runner.env_state)
    lr_state = property(lambda self: self.hosts[0].lr_state)
    lr = property(lambda self: self.hosts[0].lr_state.lr)  # what the next iteration starts from
    sa_state = property(lambda self: self.hosts[0].lr_state.sa)  # None under schedules other than sa

    def save_checkpoint(self, which: list[int] | None = None) -> list[str]:
        return group_checkpoint.save(self.seed_group, self.primary, which)

    def _cycle_args(self, counts: list[int]) -> tuple[Any, ...]:
        return cycles.call_args(self.seed_group, self.schedule, self.rule, self.cfg, counts)

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
                options = self.compiler_options or None
                cycle = pool.submit(lambda: (lowered.compile(compiler_options=options), time.perf_counter() - t))
                ts = self.seed_group.train_state_of(0)
                compiled_eval = self._evaluate.lower(ts.params, ts.normaliser, self.eval_keys).compile(compiler_options=options)
                eval_s = time.perf_counter() - t
                self._compiled_cycle, cycle_s = cycle.result()  # re-raises the worker's error here
            self._compiled_eval = compiled_eval
            self.compile_s = {"iteration": cycle_s, "eval": eval_s, "total": time.perf_counter() - t}
        return self.compile_s

    def run_iteration(self) -> dict[str, Any]:
        """One PPO iteration (rollout + update) of a single run; a non-finite result restores the snapshot."""
        return self.run_calls([1])[0][-1]

    def run_iterations(self, count: int) -> list[dict[str, Any]]:
        """Up to ``count`` (≤ ``schedule.iterations_per_cycle``) iterations of a single run in one call, one row each."""
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
        rows, rollback = [], []
        for i in range(len(self.hosts)):
            seed_rows, finite = cycles.advance(self.seed_group, i, self.seed_group.metrics_of(metrics, i), dt,
                                               self.schedule, self.rule, self.cfg)
            rows.append(seed_rows)
            rollback.append(bool(seed_rows) and not finite)
        if any(rollback):
            self.seed_group.restore_and_accept(restore=rollback, accept=[False] * len(rollback))
        return rows

    def evaluate(self, i: int = 0) -> policy_eval.EvalResult:
        """Seed ``i``'s fixed-seed deterministic evaluation at p = 1 (the SA metric's source).

        A group evaluates seed by seed with the single run's program: a vmapped evaluation (its
        episode slots reloading under a batched ``while_loop``) measured 9x one seed's time for 5
        seeds, and seed by seed the evaluation of a policy is the single run's, bit for bit."""
        self.compile()
        ts = self.seed_group.train_state_of(i)
        return sharding.to_host(self._compiled_eval(ts.params, ts.normaliser, self.eval_keys))

    def anneal(self, metric: float, entropy: float) -> lr_schedule.CycleOutcome:
        """A single run's end of cycle by its lr schedule (see ``anneal_seeds``)."""
        return self.anneal_seeds([(metric, entropy)])[0]

    def anneal_seeds(self, ending: list[tuple[float, float] | None]) -> list[lr_schedule.CycleOutcome | None]:
        return cycles.anneal(self.seed_group, self.rule, self.cfg, self.action_size, ending)

    def cycle_due(self, i: int = 0) -> bool:
        """Seed ``i``'s current cycle's last iteration has run (a cycle ends at its fixed ``schedule.cycle_ends``)."""
        return self.hosts[i].iteration in self.schedule.cycle_ends

    def end_cycle(self) -> dict[str, Any]:
        """A single run's evaluation, annealing and next cycle; returns the row fields."""
        return self.end_cycles([True])[0]

    def end_cycles(self, ending: list[bool]) -> list[dict[str, Any] | None]:
        """Evaluate, anneal and start the next cycle of the seeds in ``ending``; returns each one's row fields."""
        evals, eval_s = [], []
        for i, end in enumerate(ending):
            t = time.perf_counter()
            evals.append(self.evaluate(i) if end else None)
            eval_s.append(time.perf_counter() - t)
        metric = [cycles.cycle_metric(self.cfg, e) for e in evals]
        entropy = [h.entropy_sum / max(h.entropy_n, 1) for h in self.hosts]
        decisions = self.anneal_seeds([(m, h) if e else None for m, h, e in zip(metric, entropy, ending)])
        out: list[dict[str, Any] | None] = []
        for i, (host, decision) in enumerate(zip(self.hosts, decisions)):
            if decision is not None:
                host.start_cycle()
            if decision is None:
                out.append(None)
                continue
            row = cycles.cycle_row(host.lr_state, decision, evals[i], eval_s[i], metric[i], entropy[i])
            row.update(cycles.stop_rule(host, self.cfgs[i], float(evals[i].success_rate), decision.kept))
            out.append(row)
        return out

    def train(self, stop_after_cycles: int | None = None) -> dict[str, Any]:
        """Train every seed to ``train.total_steps`` or its stopping rule (``train.stop_success``), or stop,
        checkpointed, after ``stop_after_cycles`` cycles;
        returns the last row (a group's: seed 0's).  The loop is :func:`sagrasp_jax.training.loop.train`."""
        return loop.train(self, stop_after_cycles)

    def export_finished(self) -> None:
        """Each finished seed's final policy into its run folder (``policy.npz``; process 0)."""
        for i, host in enumerate(self.hosts):
            if self.primary and host.finished(self.schedule.num_iterations):
                ts = self.seed_group.train_state_of(i)
                restore.export_policy(os.path.join(self.dirs[i], run_dir.POLICY_FILE), self.cfgs[i], ts.params, ts.normaliser,
                              self.obs_size)

    def summary(self, row: dict[str, Any], steps: int, i: int = 0) -> str:
        """One line for the end of a run: speed, compile time, SA counts, last evaluation."""
        return run_log.summary(self.hosts[i], self.rule, row, steps)
