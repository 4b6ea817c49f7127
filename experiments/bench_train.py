"""Training speed of the README command, in one run: env, trainer, compile, memory, time to success.

    python -m experiments.bench_train --out experiments/results/bench_train_cpu.json

Sections (``--sections``, default all; each prints as it goes, then one table and one JSON):

* ``env``: env-steps/s of (a) the bare env step (``jax.vmap(GraspEnv.step)``) and (b) env +
  auto-reset (``AutoReset.batch_step``), at the preset's batch, random actions, inside a jitted
  ``lax.scan``; (b) also with 30-step episodes (``--reset-steps``), about a trained policy's
  episode length, so the auto-reset samples as often as it does in training.
* ``profile``: where one PPO iteration of the preset goes — every piece jitted and timed alone
  on the iteration's shapes (FK, control step, collision, reward/observation, auto-reset
  sampling, policy forward and sampling, normaliser + value + GAE, minibatch SGD, the
  training-episode window, host sync) next to the real training call and the SA evaluation.
  The pieces are separate programs, so they do not add up exactly to the fused iteration.
* ``run``: the README command (``python -m sagrasp_jax.train --preset cpu-quick --algo sa-ppo
  --seed S``) in a subprocess with a **fresh** persistent compilation cache (cold compile),
  polled while it runs: (c) the median per-iteration env-steps/s, (d) the overall rate
  including the SA evaluations, peak RSS, and the wall time from launch (compile included)
  at which the fixed-seed evaluation success first reaches 90 / 95 / 98 / 99 %.  A run stops once
  99 % is reached or after ``--budget-s``.  More ``--seeds`` run after the first, warm.
  Then the same command again with the now warm cache, stopped after one cycle: warm compile.
* ``group``: ``--seeds`` (the seeds in one compiled program) against the same seeds trained one
  after another, ``--total-steps`` each, both from an empty compilation cache: wall times, their
  ratio (target <= 0.6), peak RSS and the largest group within 4 GB, the load beside them.
* ``sb3``: when Stable-Baselines3 imports (this interpreter or ``--sb3-python``), SB3 PPO on
  the PyBullet reference env for ``--sb3-seconds`` (``bench_vs_paper_stack.py``'s worker,
  the paper's Table 2 settings from ``bench_vs_paper_stack``'s sb3-baseline) and the ratio of training rates; the
  raw stepping rate of the PyBullet env (no learning) is measured either way.

The machine's load average is recorded beside every measurement: on a shared machine rates
drop in proportion, so compare runs made at the same load.

``epochs`` (was ``bench_epochs``): what fewer SGD passes late in the run save, per training call and
projected onto the README run (``EPOCHS_DOC``):

    python -m experiments.bench_train epochs --out experiments/results/bench_epochs_cpu.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from typing import Any, Callable, Sequence

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SECTIONS = ("env", "profile", "run", "sb3", "group")
LEVELS = (0.90, 0.95, 0.98, 0.99)


def load() -> float:
    return round(os.getloadavg()[0], 2)


# ---------------------------------------------------------------------- timing helpers

def time_jitted(fn: Callable[..., Any], *args: Any, reps: int = 7) -> dict[str, float]:
    """Compile ``fn`` (jitted), then the median wall and CPU seconds of ``reps`` calls."""
    import jax
    import numpy as np

    f = jax.jit(fn)
    t = time.perf_counter()
    jax.block_until_ready(f(*args))
    compile_s = time.perf_counter() - t
    walls, cpus = [], []
    for _ in range(reps):
        c, t = time.process_time(), time.perf_counter()
        jax.block_until_ready(f(*args))
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    return {"wall_s": float(np.median(walls)), "cpu_s": float(np.median(cpus)), "compile_s": compile_s}


# ---------------------------------------------------------------------- (a), (b): the env

def bench_env(cfg: Any, steps: int, reset_steps: int) -> dict[str, Any]:
    import jax
    from jax.sharding import PartitionSpec

    from sagrasp_jax.training import sharding
    from sagrasp_jax.envs.grasp_env import GraspEnv
    from sagrasp_jax.envs.auto_reset import AutoReset

    n = cfg.ppo.num_envs
    out: dict[str, Any] = {"batch": n, "steps_per_call": steps}

    def scan_of(step: Callable[..., Any], m: int) -> Callable[..., Any]:
        def run(state: Any, key: jax.Array) -> Any:
            def body(st: Any, k: jax.Array) -> Any:
                st = step(st, jax.random.uniform(k, (m, 6), minval=-1.0, maxval=1.0))
                return st, st.done
            return jax.lax.scan(body, state, jax.random.split(key, steps))
        return run

    cases = [("env_step", cfg.env, False), ("env_autoreset", cfg.env, True),
             (f"env_autoreset_{reset_steps}_step_episodes",
              dataclasses.replace(cfg.env, task=dataclasses.replace(cfg.env.task, max_steps=reset_steps)), True)]
    devices = jax.devices()
    for name, env_cfg, auto in cases:
        base = GraspEnv(env_cfg)
        env = AutoReset(base) if auto else base
        step = env.batch_step if auto else jax.vmap(base.step)
        state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), n))
        state, dones = jax.jit(scan_of(step, n))(state, jax.random.PRNGKey(1))
        row: dict[str, Any] = {"episodes_per_env_step": float(dones.sum()) / (n * steps)}
        for d in sorted({1, len(devices)}):
            mesh = sharding.make_mesh(devices[:d])
            fn = sharding.sharded(scan_of(step, n // d), mesh, (PartitionSpec(sharding.BATCH_AXIS), PartitionSpec()),
                              (PartitionSpec(sharding.BATCH_AXIS), PartitionSpec(None, sharding.BATCH_AXIS)))
            timing = time_jitted(fn, sharding.shard_batch(state, mesh), sharding.replicate(jax.random.PRNGKey(2), mesh), reps=5)
            row[f"{d}_device"] = {"env_steps_per_s": n * steps / timing["wall_s"],
                                  "cpu_us_per_env_step": 1e6 * timing["cpu_s"] / (n * steps),
                                  "compile_s": timing["compile_s"], "load": load()}
            print(f"  {name:36s} {d} device(s) {row[f'{d}_device']['env_steps_per_s']:>10,.0f} env-steps/s  "
                  f"({row[f'{d}_device']['cpu_us_per_env_step']:.2f} CPU-µs/step, load {load()})", flush=True)
        row["env_steps_per_s"] = row[f"{len(devices)}_device"]["env_steps_per_s"]
        out[name] = row
    return out


# ---------------------------------------------------------------------- profile of one iteration

def bench_profile(cfg: Any) -> dict[str, Any]:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from sagrasp_jax import train
    from sagrasp_jax.training.agents.ppo import actor_critic
    from sagrasp_jax.task import collision
    from sagrasp_jax.task import control
    from sagrasp_jax.training.agents.ppo import losses
    from sagrasp_jax.training import metrics_window
    from sagrasp_jax.task import observation
    from sagrasp_jax.training.agents.ppo import ppo
    from sagrasp_jax.task import robot
    from sagrasp_jax.training.agents.ppo import rollout
    from sagrasp_jax.training import sharding
    from sagrasp_jax.task.config import training_env_config
    from sagrasp_jax.envs.grasp_env import GraspEnv
    from sagrasp_jax.envs.auto_reset import AutoReset

    n, t_len = cfg.ppo.num_envs, cfg.ppo.unroll_length
    env = GraspEnv(training_env_config(cfg), privileged=cfg.ppo.privileged_critic)  # the training env
    hand_scaled = env.hand_scaled_mask
    auto = AutoReset(env)
    rob = env.robot
    key = jax.random.PRNGKey(0)
    states = jax.jit(jax.vmap(auto.reset))(jax.random.split(key, n))
    specs = states.info["reset"]
    qs = jnp.asarray(cfg.env.task.home_q) + 0.3 * jax.random.normal(key, (t_len, n, 6))
    actions = jax.random.uniform(key, (t_len, n, 6), minval=-1.0, maxval=1.0)
    fk = jax.vmap(jax.vmap(lambda q: robot.forward_kinematics(jnp, rob, q)))
    kins = jax.jit(fk)(qs)
    pieces: dict[str, dict[str, float]] = {}

    def timed(name: str, fn: Callable[..., Any], *args: Any) -> None:
        pieces[name] = time_jitted(fn, *args)
        print(f"  {name:44s} {1e3 * pieces[name]['wall_s']:8.2f} ms/iteration (CPU {1e3 * pieces[name]['cpu_s']:.2f})",
              flush=True)

    def over_steps(step_fn: Callable[..., Any]) -> Callable[..., Any]:
        def run(xs: Any, *extra: Any) -> Any:
            def body(acc: Any, x: Any) -> Any:
                out = step_fn(x, *extra)
                return acc + sum(jnp.sum(v.astype(jnp.float32)) for v in jax.tree_util.tree_leaves(out)), None
            return jax.lax.scan(body, jnp.zeros(()), xs)[0]
        return run

    timed("forward kinematics (one pass)", over_steps(lambda q: jax.vmap(lambda x: robot.forward_kinematics(jnp, rob, x))(q)), qs)
    timed("control step (incl. one FK pass)", over_steps(
        lambda x, sp: control.control_step(jnp, rob, cfg.env.control, x[0], x[0], sp.target_pos, x[1]).q_target),
        (qs, actions), specs)
    timed("collision check", over_steps(lambda k, sp: jax.vmap(lambda kk, s: collision.check(jnp, rob, kk, s, cfg.env))(
        k, sp)), kins, specs)

    def env_steps(step: Callable[..., Any]) -> Callable[..., Any]:
        def run(state: Any, acts: jax.Array) -> Any:
            return jax.lax.scan(lambda s, a: (step(s, a), None), state, acts)[0].reward
        return run

    core = jax.jit(jax.vmap(env.reset))(jax.random.split(key, n))
    timed("env step (vmap GraspEnv.step)", env_steps(jax.vmap(env.step)), core, actions)
    short = AutoReset(GraspEnv(dataclasses.replace(cfg.env, task=dataclasses.replace(cfg.env.task, max_steps=30))))
    short_states = jax.jit(jax.vmap(short.reset))(jax.random.split(key, n))
    short_states = jax.jit(lambda s, a: jax.lax.scan(lambda st, x: (short.batch_step(st, x), None), s, a)[0])(
        short_states, actions)  # past the synchronous start: resets spread as in training
    timed("env step + auto-reset (30-step episodes)", env_steps(short.batch_step), short_states, actions)

    extra = observation.critic_extra_size(cfg)  # the privileged critic's inputs, as in training
    nets = actor_critic.make_networks(cfg.ppo.network, env.observation_size, env.action_size, cfg.ppo.obs_clip, extra)
    opt = actor_critic.make_optimizer(cfg.ppo, 3e-4)
    ts = actor_critic.init_training_state(key, nets, opt, env.observation_size)
    obs = jax.random.normal(key, (t_len, n, env.observation_size))
    timed("policy forward + sampling", over_steps(
        lambda x, tr: actor_critic.sample_action(nets, tr.params, tr.normaliser, x[0], x[1])[:2]),
        (obs, jax.random.split(key, t_len)), ts)
    data = rollout.Transition(obs=obs, critic_extra=jax.random.normal(key, (t_len, n, extra)), raw_action=actions, log_prob=actions[..., 0], reward=actions[..., 1],
                          done=(actions[..., 2] > 0.9).astype(jnp.float32))

    def gae(tr: Any, d: Any) -> Any:
        norm = ppo.update_normaliser(tr.normaliser, d.obs, cfg.ppo, hand_scaled)
        entropy = actor_critic.mean_policy_entropy(nets, tr.params, tr.normaliser, d.obs)
        return losses.make_batch(nets, tr.params, norm, d, d.obs[-1], cfg.ppo, d.critic_extra[-1]), entropy

    timed("normaliser + entropy + value net + GAE", gae, ts, data)
    batch = jax.jit(gae)(ts, data)[0]
    timed("minibatch SGD (epochs x minibatches)",
          lambda tr, b, k: ppo.sgd_epochs(tr.params, tr.opt_state, tr.normaliser, b, k, nets, opt, cfg.ppo)[:2],
          ts, batch, key)
    win = metrics_window.init_window(tuple(states.info["episode"]), cfg.train.metrics_window)
    episodes = dict(jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (t_len,) + x.shape), states.info["episode"]),
                    done=data.done)
    timed("training-episode window (device side)", metrics_window.update_window, win, episodes)

    # the real thing: the trainer's jitted call on the preset and the SA evaluation, on 1 device and
    # on all devices, the two trainers' calls interleaved so that both see the same load
    devices = jax.devices()
    trainers = {d: train.Trainer(cfg, tempfile.mkdtemp(prefix="bench_train_profile."), progress=False,
                                 devices=devices[:d]) for d in sorted({1, len(devices)})}
    timing: dict[int, dict[str, list[float]]] = {d: {"wall": [], "cpu": [], "sync": [], "eval": []} for d in trainers}
    for tr in trainers.values():
        tr.compile()
        tr.run_iterations(tr.schedule.iterations_per_cycle)  # warm-up
    for rep in range(8):
        for d, tr in trainers.items():
            k = tr.schedule.iterations_per_cycle
            c, t = time.process_time(), time.perf_counter()
            tr.run_iterations(k)
            timing[d]["wall"].append((time.perf_counter() - t) / k)
            timing[d]["cpu"].append((time.process_time() - c) / k)
            if rep % 2 == 0:
                t = time.perf_counter()
                tr.evaluate()
                timing[d]["eval"].append(time.perf_counter() - t)
    for d, tr in trainers.items():
        k = tr.schedule.iterations_per_cycle
        out = jax.block_until_ready(tr._compiled_cycle(*tr._cycle_args([k])))
        for _ in range(5):
            t = time.perf_counter()
            sharding.to_host(out[3])
            timing[d]["sync"].append((time.perf_counter() - t) / k)
        cycle_iters = tr.schedule.num_iterations / tr.schedule.num_cycles
        pieces[f"training call per iteration, {d} device(s) (the real fused program)"] = {
            "wall_s": float(np.median(timing[d]["wall"])), "cpu_s": float(np.median(timing[d]["cpu"])),
            "compile_s": tr.compile_s["iteration"]}
        pieces[f"host sync of a cycle's metrics, per iteration, {d} device(s)"] = {
            "wall_s": float(np.median(timing[d]["sync"])), "cpu_s": math.nan, "compile_s": 0.0}
        pieces[f"SA evaluation per iteration (untrained: 200-step episodes), {d} device(s)"] = {
            "wall_s": float(np.median(timing[d]["eval"])) / cycle_iters, "cpu_s": math.nan,
            "compile_s": tr.compile_s["eval"]}
        for name in list(pieces)[-3:]:
            print(f"  {name:44s} {1e3 * pieces[name]['wall_s']:8.2f} ms/iteration", flush=True)
    iteration_s = pieces[f"training call per iteration, {len(devices)} device(s) (the real fused program)"]["wall_s"]
    steps = n * t_len
    return {"iteration_env_steps": steps, "iterations_per_cycle_mean": cycle_iters, "reference_piece":
            f"training call per iteration, {len(devices)} device(s) (the real fused program)",
            "devices": len(jax.devices()), "pieces": pieces,
            "iteration_env_steps_per_s": steps / iteration_s, "load": load()}


# ---------------------------------------------------------------------- the README command

def _vm_hwm_kb(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/status", encoding="utf-8") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def train_run(args_extra: list[str], work: str, name: str, cache_dir: str, budget_s: float,
              stop_level: float | None, env_extra: dict[str, str] | None = None, root: str = ROOT) -> dict[str, Any]:
    """Run ``python -m sagrasp_jax.train`` and watch its metrics; stop at ``stop_level`` or the budget."""
    from experiments.study import watch_trainer
    from sagrasp_jax.training.run_dir import METRICS_FILE

    out = os.path.join(work, name)
    cmd = [sys.executable, "-m", "sagrasp_jax.train", "--out", out, "--no-progress", *args_extra]
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=cache_dir, **(env_extra or {}))
    log_path = os.path.join(work, f"{name}.log")
    loads: list[float] = []
    reached: dict[str, Any] = {}
    offset, peak_kb = math.inf, 0

    def sample_memory(pid: int) -> None:
        nonlocal peak_kb
        peak_kb = max(peak_kb, _vm_hwm_kb(pid) or 0)

    def stop_reason(rows: list[dict[str, Any]], now: float) -> str | None:
        nonlocal offset
        if rows:
            offset = min(offset, now - rows[-1]["time_s"])  # launch -> start of training
            loads.append(load())
        for r in rows:
            s = r.get("eval_success")
            for level in LEVELS:
                if s is not None and s >= level and f"{level:g}" not in reached:
                    reached[f"{level:g}"] = {"wall_s": offset + r["time_s"], "env_steps": r["env_steps"],
                                             "train_s": r["time_s"]}
        if stop_level is not None and f"{stop_level:g}" in reached:
            return f"reached {stop_level:.0%}"
        return f"budget of {budget_s:.0f} s" if now > budget_s else None

    rows, stopped, code, wall = watch_trainer(cmd, root, log_path, os.path.join(out, METRICS_FILE), 0.25, stop_reason,
                                              env=env, on_poll=sample_memory)
    if not rows:
        with open(log_path, encoding="utf-8") as f:
            raise RuntimeError(f"{name}: the trainer logged nothing (exit {code}):\n{f.read()[-3000:]}")
    last = rows[-1]
    rates = sorted(r["steps_per_s"] for r in rows)
    evals = [r["eval_s"] for r in rows if "eval_s" in r]
    return {
        "command": "python -m sagrasp_jax.train " + " ".join(args_extra),
        "stopped_by": stopped or "finished",
        "wall_s": wall,
        "startup_s": offset if math.isfinite(offset) else None,  # launch -> first training step (import, build, compile)
        "compile_s": last.get("compile_s"),
        "compile_iteration_s": last.get("compile_iteration_s"),
        "compile_eval_s": last.get("compile_eval_s"),
        "env_steps": last["env_steps"],
        "train_s": last["time_s"],
        "median_iteration_env_steps_per_s": rates[len(rates) // 2],
        "overall_env_steps_per_s": last["env_steps"] / last["time_s"],
        "eval_s_mean": sum(evals) / len(evals) if evals else None,
        "eval_share": sum(evals) / last["time_s"] if evals else None,
        "cycles": sum(1 for r in rows if "sa_decision" in r),
        "last_eval_success": next((r["eval_success"] for r in reversed(rows) if "eval_success" in r), None),
        "reset_overflow": sum(r.get("reset_overflow", 0.0) for r in rows),
        "reset_replays": sum(r.get("reset_replays", 0.0) for r in rows) if "reset_replays" in last else None,
        "time_to_eval_success": {f"{lv:g}": reached.get(f"{lv:g}", "not reached") for lv in LEVELS},
        "peak_rss_mb": peak_kb / 1024,
        "load_during": [min(loads), max(loads)] if loads else None,
    }


def bench_run(preset: str, seeds: list[int], overrides: list[str], budget_s: float, work: str,
              root: str = ROOT) -> dict[str, Any]:
    cache = os.path.join(work, "jax_cache")  # fresh: the first run compiles cold
    sets = [a for o in overrides for a in ("--set", o)]
    runs = {}
    for i, seed in enumerate(seeds):
        label = f"seed {seed}" + (" (cold compile)" if i == 0 else " (warm cache)")
        print(f"  README command, {label}, budget {budget_s:.0f} s ...", flush=True)
        r = train_run(["--preset", preset, "--algo", "sa-ppo", "--seed", str(seed), *sets], work, f"seed{seed}",
                      cache, budget_s, max(LEVELS), root=root)
        runs[f"seed{seed}"] = r
        print(f"    {r['median_iteration_env_steps_per_s']:,.0f} env-steps/s per iteration, "
              f"{r['overall_env_steps_per_s']:,.0f} overall, compile {r['compile_s']:.1f} s, start-up "
              f"{r['startup_s']:.1f} s, time to 90/95/98/99 %: "
              + ", ".join(_fmt_reach(r["time_to_eval_success"][f"{lv:g}"]) for lv in LEVELS)
              + f" (load {r['load_during']})", flush=True)
    print("  warm compile: the same command again, stopped after one cycle ...", flush=True)
    warm = train_run(["--preset", preset, "--algo", "sa-ppo", "--seed", str(seeds[0]), *sets, "--stop-after-cycles", "1"],
                     work, "warm", cache, budget_s, None, root=root)
    print(f"    compile {warm['compile_s']:.1f} s, start-up {warm['startup_s']:.1f} s", flush=True)
    return {"runs": runs, "warm": {k: warm[k] for k in ("compile_s", "compile_iteration_s", "compile_eval_s",
                                                         "startup_s", "peak_rss_mb", "load_during")}}


def timed_train(args: list[str], cache_dir: str, root: str = ROOT) -> dict[str, Any]:
    """Wall time (launch to exit, compile included), peak RSS and load of one ``python -m sagrasp_jax.train``."""
    cmd = [sys.executable, "-m", "sagrasp_jax.train", "--no-progress", *args]
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=cache_dir)
    loads, peak_kb = [load()], 0
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    while proc.poll() is None:
        peak_kb = max(peak_kb, _vm_hwm_kb(proc.pid) or 0)
        time.sleep(0.5)
    wall = time.perf_counter() - t
    log = proc.stdout.read() if proc.stdout else ""
    if proc.returncode:
        raise RuntimeError(f"{' '.join(cmd)} exited {proc.returncode}:\n{log[-3000:]}")
    loads.append(load())
    return {"command": "python -m sagrasp_jax.train " + " ".join(args), "wall_s": wall, "peak_rss_mb": peak_kb / 1024,
            "load_start_end": loads}


def last_eval_success(folder: str) -> float | None:
    from sagrasp_jax.training.run_dir import METRICS_FILE, read_metrics

    return next((r["eval_success"] for r in reversed(read_metrics(os.path.join(folder, METRICS_FILE)))
                 if "eval_success" in r), None)


def bench_group(preset: str, seeds: list[int], total_steps: int, overrides: list[str], work: str,
                root: str = ROOT, rss_limit_mb: float = 4096.0) -> dict[str, Any]:
    """``--seeds`` (one program) against the same seeds one after another, the same steps per seed.

    Each arm starts with an empty persistent compilation cache: the sequential runs compile once
    and then hit the cache, the group compiles its own program once.  The largest group within
    ``rss_limit_mb`` is extrapolated from the peak RSS of one run and of the N-seed group
    (memory grows linearly with the seeds: their stacked state and batch)."""
    sets = [a for o in overrides for a in ("--set", o)]
    base = ["--preset", preset, "--algo", "sa-ppo", "--total-steps", str(total_steps), *sets]
    uptime_start = os.getloadavg()
    sequential = {}
    for seed in seeds:
        print(f"  seed {seed} alone ...", flush=True)
        sequential[f"seed{seed}"] = timed_train(base + ["--seed", str(seed), "--out", os.path.join(work, "alone", f"seed{seed}")],
                                                os.path.join(work, "cache_alone"), root)
        print(f"    {sequential[f'seed{seed}']['wall_s']:.0f} s, load {sequential[f'seed{seed}']['load_start_end']}",
              flush=True)
    print(f"  seeds {seeds} as one group ...", flush=True)
    group = timed_train(base + ["--seeds", ",".join(map(str, seeds)), "--out", os.path.join(work, "group")],
                        os.path.join(work, "cache_group"), root)
    print(f"    {group['wall_s']:.0f} s, load {group['load_start_end']}", flush=True)
    seq_wall = sum(r["wall_s"] for r in sequential.values())
    single_rss = max(r["peak_rss_mb"] for r in sequential.values())
    per_seed = max((group["peak_rss_mb"] - single_rss) / max(len(seeds) - 1, 1), 1e-9)
    success = {f"seed{s}": {"alone": last_eval_success(os.path.join(work, "alone", f"seed{s}")),
                            "group": last_eval_success(os.path.join(work, "group", f"seed{s}"))} for s in seeds}
    return {
        "seeds": seeds, "total_steps_per_seed": total_steps,
        "sequential": sequential, "sequential_wall_s": seq_wall,
        "group": group, "group_wall_s": group["wall_s"], "ratio_group_to_sequential": group["wall_s"] / seq_wall,
        "target_ratio": 0.6,
        "rss_mb": {"single_run": single_rss, "group": group["peak_rss_mb"], "per_extra_seed": per_seed,
                   "limit": rss_limit_mb,
                   "largest_group_within_limit": int((rss_limit_mb - (single_rss - per_seed)) // per_seed)},
        "last_cycle_eval_success": success,
        "uptime_load_1_5_15": {"start": list(uptime_start), "end": list(os.getloadavg())},
        "cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
    }


def _fmt_reach(value: Any) -> str:
    return f"{value['wall_s']:.0f} s" if isinstance(value, dict) else str(value)


# ---------------------------------------------------------------------- SB3 and the raw PyBullet env

def bench_sb3_section(sb3_python: str | None, seconds: float, work: str) -> dict[str, Any]:
    from experiments import bench_env
    from experiments import bench_vs_paper_stack as stack

    out: dict[str, Any] = {}
    raw = bench_env.bench_pybullet("kinematic", 2000)
    out["pybullet_raw"] = raw if raw is not None else {"status": "skipped (reference extra missing)"}
    if raw is not None:
        print(f"  raw PyBullet reference env stepping: {raw['env_steps_per_s']:,.0f} env-steps/s (load {load()})", flush=True)
    bare = bench_env.bench_bare_pybullet()
    out["pybullet_bare_chain"] = bare if bare is not None else {"status": "skipped (pybullet missing)"}
    if bare is not None:
        print(f"  raw bare PyBullet AUBO chain stepping: {bare['env_steps_per_s']:,.0f} env-steps/s (load {load()})",
              flush=True)
    python = sb3_python
    if python is None:
        probe = subprocess.run([sys.executable, "-c", "import stable_baselines3, torch"], capture_output=True)
        python = sys.executable if probe.returncode == 0 else None
    if python is None:
        out["sb3"] = {"status": "skipped", "reason": "stable-baselines3 is not importable here (pip install -e .[baseline]) "
                                                     "and no --sb3-python was given"}
    else:
        print(f"  SB3 PPO on the PyBullet reference env for {seconds:.0f} s ...", flush=True)
        out["sb3"] = stack.bench_sb3(python, seconds, 16, list(LEVELS), 256, work, timeout_s=seconds + 900)
    print(f"  SB3: {out['sb3'].get('status')}"
          + (f", {out['sb3']['env_steps_per_s']:,.0f} env-steps/s" if out["sb3"].get("status") == "ok" else ""), flush=True)
    out["load"] = load()
    return out


# ---------------------------------------------------------------------- epochs: fewer passes late in the run

EPOCHS_DOC = """What fewer SGD passes late in the run save: the README preset's training call per iteration with
eight passes throughout (the preset before it adopted ``ppo.late_epochs=4``) against ``ppo.late_epochs``
(4, 2) applied from the first iteration, and against a fixed four-pass scan (``ppo.num_epochs=4``: the
run-time loop's own cost), the calls interleaved so that each sees the same load.  Then what that makes
of the README run's training time, from these per-iteration costs alone (``ppo.late_from`` of the budget at
eight passes, the rest at the late count; evaluation and compile not included)."""

EPOCHS_VARIANTS: dict[str, tuple[str, ...]] = {
    "8 passes throughout": ("ppo.late_epochs=0",),
    "late_epochs=4 (from the start)": ("ppo.late_epochs=4", "ppo.late_from=0"),
    "late_epochs=2 (from the start)": ("ppo.late_epochs=2", "ppo.late_from=0"),
    "num_epochs=4 (fixed scan)": ("ppo.num_epochs=4", "ppo.late_epochs=0"),
}
EPOCHS_REFERENCE = "8 passes throughout"  # the reference every other row is a fraction of


def _is_late(sets: tuple[str, ...]) -> bool:
    """A variant whose passes drop at ppo.late_from: the README run's projection applies to it."""
    return any(item.startswith("ppo.late_epochs=") and item != "ppo.late_epochs=0" for item in sets)


def epochs_main(argv: Sequence[str] | None = None) -> int:
    """``epochs``: the training call's cost per iteration at eight passes against fewer late ones (``EPOCHS_DOC``)."""
    p = argparse.ArgumentParser(prog="python -m experiments.bench_train epochs", description=EPOCHS_DOC.split("\n\n")[0])
    p.add_argument("--preset", default="cpu-quick")
    p.add_argument("--reps", type=int, default=6, help="timed calls of one cycle per variant (median)")
    p.add_argument("--late-from", type=float, default=0.3, help="ppo.late_from of the projected README run")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for every variant (before the variant's own), repeatable")
    p.add_argument("--out", default=None, help="JSON result file")
    args = p.parse_args(argv)
    if args.reps < 1 or not 0.0 <= args.late_from <= 1.0:
        p.error("--reps must be >= 1 and --late-from in [0, 1]")

    import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)
    import jax
    import numpy as np

    from sagrasp_jax import train
    from sagrasp_jax.task.config import ConfigError
    from sagrasp_jax.training import launch

    try:
        configs = {name: launch.build_config(args.preset, "sa-ppo", 0, None, [*args.overrides, *sets])
                   for name, sets in EPOCHS_VARIANTS.items()}
    except ConfigError as exc:
        p.error(str(exc))
    base = configs[EPOCHS_REFERENCE]
    launch.use_cpu_devices(base)
    # one trainer at a time built, compiled and warmed up: programs with cross-device collectives that are
    # enqueued on the devices in different orders (one trainer's start beside another's) can wait on each other
    trainers: dict[str, Any] = {}
    for name, cfg in configs.items():
        tr = trainers[name] = train.Trainer(cfg, tempfile.mkdtemp(prefix="bench_epochs."), progress=False)
        tr.compile()
        tr.run_iterations(tr.schedule.iterations_per_cycle)  # warm-up
        print(f"  {name}: compiled and warmed up", flush=True)
    k = next(iter(trainers.values())).schedule.iterations_per_cycle
    wall: dict[str, list[float]] = {name: [] for name in trainers}
    for _ in range(args.reps):
        for name, tr in trainers.items():
            t = time.perf_counter()
            tr.run_iterations(k)
            wall[name].append((time.perf_counter() - t) / k)
    steps = base.ppo.num_envs * base.ppo.unroll_length
    iterations = next(iter(trainers.values())).schedule.num_iterations
    ms = {name: 1e3 * float(np.median(w)) for name, w in wall.items()}
    eight = ms[EPOCHS_REFERENCE]
    rows = []
    for name, value in ms.items():
        projected = (iterations * (args.late_from * eight + (1 - args.late_from) * value) / 1e3
                     if _is_late(EPOCHS_VARIANTS[name]) else None)
        rows.append({"variant": name, "overrides": list(EPOCHS_VARIANTS[name]), "ms_per_iteration": value,
                     "env_steps_per_s": steps / (value / 1e3), "vs_eight_passes": value / eight,
                     "projected_readme_training_s": projected})
    load = os.getloadavg()
    print(f"\n{args.preset}: {steps} env steps an iteration, {iterations} iterations in the budget, "
          f"{len(jax.devices())} device(s), load {load[0]:.2f}")
    print("| variant | ms / iteration | env-steps/s | × 8 passes | README training, projected (s) |")
    print("|---|---|---|---|---|")
    for r in rows:
        proj = "–" if r["projected_readme_training_s"] is None else f"{r['projected_readme_training_s']:.0f}"
        print(f"| {r['variant']} | {r['ms_per_iteration']:.1f} | {r['env_steps_per_s']:,.0f} | "
              f"{r['vs_eight_passes']:.3f} | {proj} |")
    print(f"(8 passes throughout, projected the same way: {iterations * eight / 1e3:.0f} s; "
          f"late passes from progress {args.late_from})")
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        result: dict[str, Any] = {"preset": args.preset, "overrides": args.overrides, "reps": args.reps, "late_from": args.late_from,
                                  "iteration_env_steps": steps, "iterations": iterations,
                                  "devices": len(jax.devices()), "load": list(load), "machine": platform.processor()
                                  or platform.machine(), "cpus": os.cpu_count(), "rows": rows,
                                  "preset_projected_training_s": iterations * eight / 1e3,
                                  "command": "python -m experiments.bench_train epochs "
                                             + " ".join(sys.argv[2:] if argv is None else argv)}
        tmp = args.out + ".tmp"
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(result, f, indent=1)
        os.replace(tmp, args.out)
    return 0


# ---------------------------------------------------------------------- report

def table(result: dict[str, Any]) -> str:
    lines = [f"bench_train on {result['machine']['cpus']} CPU(s), {result['machine']['devices']} jax device(s); "
             f"load {result['load_start']} at start, {result['load_end']} at end", ""]
    env = result.get("env")
    if env:
        for key, label in (("env_step", "(a) env step"), ("env_autoreset", "(b) env + auto-reset (random actions)")):
            lines.append(f"{label:58s} {env[key]['env_steps_per_s']:>12,.0f} env-steps/s"
                         + f"   (1 device: {env[key]['1_device']['env_steps_per_s']:,.0f})")
        short = next(k for k in env if k.startswith("env_autoreset_"))
        lines.append(f"{'(b) env + auto-reset, ' + short.split('_')[2] + '-step episodes':58s} "
                     f"{env[short]['env_steps_per_s']:>12,.0f} env-steps/s")
    run = result.get("run")
    if run:
        for name, r in run["runs"].items():
            lines.append(f"{'(c) rollout + PPO update, median per iteration, ' + name:58s} "
                         f"{r['median_iteration_env_steps_per_s']:>12,.0f} env-steps/s")
            lines.append(f"{'(d) overall incl. SA evaluations, ' + name:58s} {r['overall_env_steps_per_s']:>12,.0f} env-steps/s")
            lines.append(f"{'    time to 90 / 95 / 98 / 99 % eval success (wall incl. compile)':58s} "
                         + " / ".join(_fmt_reach(r["time_to_eval_success"][f"{lv:g}"]) for lv in LEVELS)
                         + f"  [{r['stopped_by']}, last eval {r['last_eval_success']}]")
            lines.append(f"{'    peak RSS':58s} {r['peak_rss_mb']:>12,.0f} MB")
            if r.get("reset_replays") is not None:
                lines.append(f"{'    auto-reset replays / overflow starts':58s} {r['reset_replays']:>12,.0f} / "
                             f"{r['reset_overflow']:,.0f}")
        first = next(iter(run["runs"].values()))
        lines.append(f"{'compile, cold (fresh cache): compile_s / launch to training':58s} "
                     f"{first['compile_s']:>10.1f} s / {first['startup_s']:.1f} s")
        lines.append(f"{'compile, warm (cached): compile_s / launch to training':58s} "
                     f"{run['warm']['compile_s']:>10.1f} s / {run['warm']['startup_s']:.1f} s")
    group = result.get("group")
    if group:
        n, steps = len(group["seeds"]), group["total_steps_per_seed"]
        label = f"{n} seeds one after another, {steps:,} steps each (wall)"
        lines.append(f"{label:58s} {group['sequential_wall_s']:>10.0f} s")
        label = f"{n} seeds as one group (--seeds), the same steps (wall)"
        lines.append(f"{label:58s} {group['group_wall_s']:>10.0f} s"
                     f"   = {group['ratio_group_to_sequential']:.2f} x (target <= {group['target_ratio']})")
        rss = group["rss_mb"]
        lines.append(f"{'peak RSS one run / group / per extra seed':58s} {rss['single_run']:>10.0f} / "
                     f"{rss['group']:.0f} / {rss['per_extra_seed']:.0f} MB; largest group in "
                     f"{rss['limit'] / 1024:.0f} GB: {rss['largest_group_within_limit']}")
        lines.append(f"{'load (1/5/15 min) at start / end':58s} {group['uptime_load_1_5_15']['start']} / "
                     f"{group['uptime_load_1_5_15']['end']}")
    prof = result.get("profile")
    if prof:
        it = prof["pieces"][prof["reference_piece"]]["wall_s"]
        lines += ["", f"profile: one iteration = {prof['iteration_env_steps']} env steps, "
                      f"{1e3 * it:.1f} ms in the fused training call ({prof['devices']} device(s))"]
        for name, p in prof["pieces"].items():
            share = f"{100 * p['wall_s'] / it:5.0f} %" if math.isfinite(p["wall_s"]) else ""
            lines.append(f"  {name:62s} {1e3 * p['wall_s']:8.2f} ms {share}")
    sb3 = result.get("sb3")
    if sb3:
        raw = sb3["pybullet_raw"].get("env_steps_per_s")
        bare = sb3["pybullet_bare_chain"].get("env_steps_per_s")
        s = sb3["sb3"]
        ours = next(iter(run["runs"].values()))["overall_env_steps_per_s"] if run else None
        if bare:
            lines.append(f"{'raw bare PyBullet AUBO chain stepping (no learning)':58s} {bare:>12,.0f} env-steps/s"
                         + (f"   ours (d) / bare = {ours / bare:.1f}x" if ours else ""))
        if raw:
            lines.append(f"{'raw PyBullet reference env stepping (no learning)':58s} {raw:>12,.0f} env-steps/s"
                         + (f"   ours (d) / raw = {ours / raw:.1f}x" if ours else ""))
        if s.get("status") == "ok":
            lines.append(f"{'SB3 PPO + PyBullet (paper stack), training':58s} {s['env_steps_per_s']:>12,.0f} env-steps/s"
                         + (f"   ours (d) / SB3 = {ours / s['env_steps_per_s']:.1f}x" if ours else ""))
        else:
            lines.append(f"SB3: {s.get('status')} ({s.get('reason')})")
    return "\n".join(lines)


def _finite(value: Any) -> Any:
    """NaN / inf -> None, recursively (strict JSON)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def main(argv: list[str] | None = None) -> int:
    given = sys.argv[1:] if argv is None else list(argv)
    if given[:1] == ["epochs"]:
        return epochs_main(given[1:])
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                epilog="python -m experiments.bench_train epochs --help: fewer SGD passes late in the run")
    p.add_argument("--sections", default=",".join(SECTIONS), help=f"comma-separated subset of {', '.join(SECTIONS)}")
    p.add_argument("--preset", default="cpu-quick")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for every section, repeatable")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="README-command seeds (the first compiles cold)")
    p.add_argument("--budget-s", type=float, default=600.0, help="wall-clock budget per training run")
    p.add_argument("--env-steps", type=int, default=64, help="env steps per timed env call (x the preset's batch)")
    p.add_argument("--reset-steps", type=int, default=30, help="episode cap for the training-like auto-reset rate")
    p.add_argument("--sb3-python", default=None, help="interpreter with stable-baselines3 (default: this one, if it has it)")
    p.add_argument("--sb3-seconds", type=float, default=120.0)
    p.add_argument("--total-steps", type=int, default=None,
                   help="group section: env steps per seed (default the preset's)")
    p.add_argument("--out", default="experiments/results/bench_train_cpu.json")
    p.add_argument("--trainer-root", default=ROOT, help="source tree whose trainer the run section starts "
                   "(e.g. an older checkout, for before/after; put it first on PYTHONPATH too)")
    args = p.parse_args(argv)
    sections = [s for s in args.sections.split(",") if s]
    unknown = set(sections) - set(SECTIONS)
    if unknown:
        p.error(f"unknown sections {sorted(unknown)}; choose from {', '.join(SECTIONS)}")
    import sagrasp_jax
    import jax

    from sagrasp_jax import train
    from sagrasp_jax.base.fileio import atomic_write_json

    cfg = train.build_config(args.preset, "sa-ppo", 0, None, args.overrides)
    if hasattr(train, "use_cpu_devices"):
        train.use_cpu_devices(cfg)  # the devices the training command uses
    result: dict[str, Any] = {
        "command": "python -m experiments.bench_train " + " ".join(sys.argv[1:] if argv is None else argv),
        "machine": {"node": platform.node(), "processor": platform.processor() or platform.machine(),
                    "cpus": os.cpu_count(), "devices": len(jax.devices()), "backend": jax.default_backend(),
                    "xla_flags": os.environ.get("XLA_FLAGS", "")},
        "versions": {"jax": jax.__version__, "sagrasp_jax": sagrasp_jax.__version__,
                     "sagrasp_jax_path": os.path.dirname(sagrasp_jax.__file__)},
        "preset": args.preset, "overrides": args.overrides, "load_start": load(),
    }
    work = tempfile.mkdtemp(prefix="bench_train.")
    try:
        if "env" in sections:
            print("[env] env-steps/s of the env step and env + auto-reset", flush=True)
            result["env"] = bench_env(cfg, args.env_steps, args.reset_steps)
        if "profile" in sections:
            print("[profile] where an iteration's time goes", flush=True)
            result["profile"] = bench_profile(cfg)
        if "run" in sections:
            print("[run] the README command", flush=True)
            result["run"] = bench_run(args.preset, args.seeds, args.overrides, args.budget_s, work,
                                      os.path.abspath(args.trainer_root))
        if "group" in sections:
            print(f"[group] {len(args.seeds)} seeds in one program against one after another", flush=True)
            result["group"] = bench_group(args.preset, args.seeds, args.total_steps or cfg.train.total_steps,
                                          args.overrides, work, os.path.abspath(args.trainer_root))
        if "sb3" in sections:
            print("[sb3] the paper's stack", flush=True)
            result["sb3"] = bench_sb3_section(args.sb3_python, args.sb3_seconds, work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result["load_end"] = load()
    text = table(result)
    print("\n" + text)
    result["table"] = text.splitlines()
    atomic_write_json(args.out, _finite(result), default=float)
    print(f"\nwritten to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
