"""Training throughput and time-to-success: our JAX trainer vs the paper's stack, same machine, one run.

Each stack trains for a fixed wall-clock budget (``--seconds`` of training, after its own
start-up and compilation), one after the other so they never share the CPU:

1. **the paper's stack**: Stable-Baselines3 PPO on the PyBullet reference env
   (``SAGrasp-PyBullet-v0``) with the paper's Table 2 settings, taken from
   ``sb3-baseline`` below (its ``PAPER_PPO``, ``HIDDEN``, ``OBS_CLIP``, ``UPDATE_STEPS``,
   env wrappers as there: ``DummyVecEnv`` → ``VecMonitor`` → ``VecNormalize``).  It runs in a
   separate interpreter given by ``--sb3-python`` (SB3 and torch stay out of the main venv);
   without it, or when SB3 cannot be imported there, the stack is reported as skipped;
2. **ours**: ``python -m sagrasp_jax.train --preset cpu-quick`` (SA-PPO), stopped once its
   ``metrics.jsonl`` shows ``--seconds`` of training time.

Both stacks run their own full-length configuration (SB3: the paper's 20M-step budget sets
the reward weights' progress p; ours: the preset's ``train.total_steps``) and are cut by the
clock.  Reported per stack: env steps, training env-steps/s (excluding start-up/compilation,
including updates and — ours — SA evaluations), the same including start-up, and the wall
time / env steps at which the training-episode success rate over the last ``--window``
finished episodes first reaches each ``--success`` level ("not reached in budget" otherwise).
Prints a ratio table and writes JSON atomically.

    python -m experiments.bench_vs_paper_stack --seconds 120 --sb3-python .venv-sb3/bin/python \\
        --out experiments/results/bench_vs_paper_stack_cpu.json

``raw`` compares raw dynamic stepping, no learning, in one run: the paper stack's (a bare PyBullet AUBO-i5
chain under position control, 12 physics steps of 1/240 s per 0.05 s control step, timed before and after
ours) against our dynamic env (MJX servo physics) at batch 256 in a jitted ``lax.scan``, bare and with the
auto-reset that training steps it through, on 1 and on every CPU device:

    python -m experiments.bench_vs_paper_stack raw --out experiments/results/raw_dynamic_cpu.json
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import importlib.metadata
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from typing import Any

import numpy as np

from sagrasp_jax.training.stats import first_reach
from sagrasp_jax.base import fileio

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAPER_STEPS_PER_S = 375.8  # paper, SB3 + PyBullet on an RTX 4070 machine (docs/task.md §4)
PAPER_TOTAL_STEPS = 20_000_000


# ---------------------------------------------------------------------- ours

def bench_ours(seconds: float, preset: str, overrides: list[str], levels: list[float], window: int,
               work: str, max_startup_s: float) -> dict[str, Any]:
    """Train our SA-PPO via the CLI until ``seconds`` of training time, then stop it and read its metrics."""
    from experiments.study import watch_trainer  # here: the SB3 worker imports this module without jax
    from sagrasp_jax.training.run_dir import METRICS_FILE

    out = os.path.join(work, "ours")
    cmd = [sys.executable, "-m", "sagrasp_jax.train", "--preset", preset, "--algo", "sa-ppo", "--seed", "0",
           "--out", out, "--no-progress", "--set", f"train.metrics_window={window}"]
    for item in overrides:
        cmd += ["--set", item]
    log_path = os.path.join(work, "ours.log")

    def stop_reason(rows: list[dict[str, Any]], since_launch: float) -> str | None:
        if rows and rows[-1].get("time_s", 0.0) >= seconds:
            return f"{seconds:.0f} s of training"
        if not rows and since_launch > max_startup_s:
            raise RuntimeError(f"our trainer logged nothing within {max_startup_s:.0f} s; see {log_path}")
        return None

    rows, reason, code, wall = watch_trainer(cmd, ROOT, log_path, os.path.join(out, METRICS_FILE), 0.5, stop_reason)
    stopped = reason is not None
    if not rows or (not stopped and code != 0):
        with open(log_path, encoding="utf-8") as f:
            tail = f.read()[-2000:]
        raise RuntimeError(f"our trainer failed (exit {code}):\n{tail}")
    last = rows[-1]
    train_s, steps = float(last["time_s"]), int(last["env_steps"])
    training_curve = [(float(r["time_s"]), int(r["env_steps"]), float(r["success"])) for r in rows
                      if r.get("success") is not None and r.get("window_episodes", 0) >= window]
    eval_curve = [(float(r["time_s"]), int(r["env_steps"]), float(r["eval_success"])) for r in rows
                  if r.get("eval_success") is not None]
    with open(os.path.join(out, "config.json"), encoding="utf-8") as f:
        cfg = json.load(f)
    return {
        "status": "ok",
        "what": f"sagrasp_jax.train --preset {preset} --algo sa-ppo (MJX/JAX env, kinematic mode), CPU",
        "command": " ".join(cmd[1:]),
        "layout": f"{cfg['ppo']['num_envs']} envs x {cfg['ppo']['unroll_length']} steps per update",
        "network": {"policy": cfg["ppo"]["network"]["policy_hidden"], "value": cfg["ppo"]["network"]["value_hidden"]},
        "total_steps_config": cfg["train"]["total_steps"],
        "stopped_by_budget": stopped,
        "env_steps": steps,
        "train_s": train_s,
        "startup_s": wall - train_s,
        "compile_s": last.get("compile_s"),
        "env_steps_per_s": steps / train_s,
        "env_steps_per_s_incl_startup": steps / wall,
        "episodes": sum(int(r.get("episodes_finished", 0)) for r in rows),  # rows: every iteration (log_every 1)
        "success_window": window,
        "last_training_success": last.get("success"),
        "last_training_success_episodes": last.get("window_episodes"),
        "last_eval_success": eval_curve[-1][2] if eval_curve else None,
        "time_to_success": first_reach(training_curve, levels),
        "time_to_eval_success": first_reach(eval_curve, levels),
    }


# ---------------------------------------------------------------------- the paper's stack: SB3 PPO, Table 2

SB3_BASELINE_DOC = """Stable-Baselines3 PPO on the PyBullet reference env with the paper's Table 2 settings.

Why: the paper trained SB3 PPO on PyBullet at 375.8 env-steps/s; this is the same stack on
our reference env (same task as the MJX env, checked by ``sagrasp_jax.reference.parity``), the anchor
that the MJX/JAX trainer's throughput is compared with.  It reports env-steps/s and the
training episodes' success rate; it is not meant to reproduce the paper's curves.

    python -m experiments.bench_vs_paper_stack sb3-baseline --total-steps 200000 --out sb3_baseline.json

Settings (docs/task.md §3 ``paper`` preset = Table 2 with SB3 defaults where it is silent): 2048 env
steps per update as **16 envs × 128 steps** (default; ``--n-envs 1`` gives 1 env × 2048, the
SB3 default layout), minibatch 256, 10 epochs, clip 0.2, γ 0.99, GAE λ 0.95, entropy coef 0,
value coef 0.5, max grad norm 0.5, policy and value MLPs 64×64 tanh, constant lr 3e-4 (the
paper's PPO baseline; SA-PPO's schedule lives in the JAX trainer).  The envs step in one
process (``DummyVecEnv``: on 2 cores subprocesses only add IPC) and observations are
normalised by ``VecNormalize`` (running mean/std, clipped to ±5, rewards untouched), as
docs/task.md §2 asks.  SB3's policy is a state-independent-std Gaussian whose actions are clipped
to [-1, 1] (our JAX PPO uses a tanh-Gaussian); the reward weights follow training
progress p = steps / total, set on every env at each rollout start.

Stable-Baselines3 (and torch) are in the ``baseline`` extra, not in the test or CI install:
``pip install -e .[baseline]``.
"""

UPDATE_STEPS = 2048  # env steps per PPO update (Table 2)
PAPER_PPO = {
    "batch_size": 256,
    "n_epochs": 10,
    "clip_range": 0.2,
    "gamma": 0.99,
    "gae_lambda": 0.95,
    "ent_coef": 0.0,
    "vf_coef": 0.5,
    "max_grad_norm": 0.5,
    "learning_rate": 3e-4,
}
HIDDEN = [64, 64]
OBS_CLIP = 5.0


def _import_sb3() -> tuple[Any, Any]:
    """Import SB3 and torch lazily, with an actionable message when the extra is missing."""
    try:
        import stable_baselines3
        import torch
    except ImportError as exc:
        raise SystemExit(
            f"error: this baseline needs Stable-Baselines3 and torch ({exc.name} is missing).\n"
            "Install the baseline extra: pip install -e .[baseline]\n"
            "(it pulls torch, gigabytes with CUDA wheels; keep it out of the training/CI environment)"
        ) from None
    return stable_baselines3, torch


def with_mode(env_cfg: Any, mode: str) -> Any:
    """The env config with the control mode set (kinematic = the paper's resetJointState stepping)."""
    return dataclasses.replace(env_cfg, control=dataclasses.replace(env_cfg.control, mode=mode))


def sb3_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m experiments.bench_vs_paper_stack sb3-baseline",
                                     description=SB3_BASELINE_DOC.split("\n\n")[0])
    parser.add_argument("--total-steps", type=int, default=200_000, help="env steps to train (paper: 20M)")
    parser.add_argument("--out", default="sb3_baseline.json", help="JSON result path")
    parser.add_argument("--mode", choices=("kinematic", "dynamic"), default="kinematic")
    parser.add_argument("--n-envs", type=int, default=16, help="16 (16 × 128 steps) or 1 (1 × 2048)")
    parser.add_argument("--seed", type=int, default=0)
    return parser


def with_task_metrics(env: Any) -> Any:
    """Wrap a reference env so its timeouts count as terminal as in the
    paper's setup (its episode metrics are ``info["task_episode"]``: SB3's VecMonitor owns ``info["episode"]``) (the −1 is the task's verdict, docs/task.md §2.7): the env reports them as
    ``truncated`` (Gymnasium's convention), which SB3 would bootstrap."""
    import gymnasium as gym

    class TaskMetrics(gym.Wrapper):
        def step(self, action: Any) -> Any:
            obs, reward, terminated, truncated, info = self.env.step(action)
            terminated, truncated = terminated or truncated, False
            return obs, reward, terminated, truncated, info

    return TaskMetrics(env)


def sb3_baseline_main(argv: list[str] | None = None) -> int:
    """``sb3-baseline``: SB3 PPO on the reference env with Table 2's settings for a number of env steps."""
    args = sb3_parser().parse_args(argv)
    if args.total_steps < 1 or args.n_envs < 1 or UPDATE_STEPS % args.n_envs:
        print(f"error: --total-steps must be ≥ 1 and --n-envs must divide {UPDATE_STEPS}", file=sys.stderr)
        return 2
    sb3, torch = _import_sb3()
    import gymnasium as gym
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.logger import Logger
    from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor, VecNormalize

    from sagrasp_jax.task.config import get_config
    from sagrasp_jax.reference.pybullet_env import PyBulletGraspEnv

    cfg = with_mode(get_config("paper").env, args.mode)
    raw_envs: list[PyBulletGraspEnv] = []

    def make(rank: int) -> Any:
        def thunk() -> gym.Env:
            env = PyBulletGraspEnv(cfg)
            env.reset(seed=args.seed * 1000 + rank)
            raw_envs.append(env)
            return with_task_metrics(env)

        return thunk

    venv = VecNormalize(VecMonitor(DummyVecEnv([make(i) for i in range(args.n_envs)])),
                        norm_obs=True, norm_reward=False, clip_obs=OBS_CLIP, gamma=PAPER_PPO["gamma"])
    episodes: list[dict[str, float]] = []
    total = args.total_steps

    class Progress(BaseCallback):
        """Sets the reward weights' training progress p on every env and collects episode metrics."""

        def _on_rollout_start(self) -> None:
            p = min(1.0, self.num_timesteps / total)
            for env in raw_envs:
                env.progress = p

        def _on_step(self) -> bool:
            for info in self.locals["infos"]:
                if "task_episode" in info:
                    episodes.append(info["task_episode"])
            return True

    model = PPO(
        "MlpPolicy", venv, n_steps=UPDATE_STEPS // args.n_envs, seed=args.seed, device="cpu", verbose=0,
        policy_kwargs={"net_arch": {"pi": HIDDEN, "vf": HIDDEN}, "activation_fn": torch.nn.Tanh},
        **PAPER_PPO,
    )
    model.set_logger(Logger(folder=None, output_formats=[]))  # the default logger litters $TMPDIR with SB3-* folders
    start = time.perf_counter()
    model.learn(total_timesteps=total, callback=Progress())
    wall = time.perf_counter() - start
    steps = int(model.num_timesteps)
    last = episodes[-100:]
    result = {
        "what": "Stable-Baselines3 PPO on SAGrasp-PyBullet-v0 (paper Table 2 settings)",
        "mode": args.mode,
        "total_steps": steps,
        "wall_s": wall,
        "env_steps_per_s": steps / wall,
        "layout": f"{args.n_envs} envs x {UPDATE_STEPS // args.n_envs} steps (DummyVecEnv)",
        "ppo": PAPER_PPO | {"n_steps": UPDATE_STEPS // args.n_envs, "n_envs": args.n_envs, "net": "64x64 tanh",
                            "obs_normalisation": f"VecNormalize clip {OBS_CLIP}"},
        "episodes": len(episodes),
        "success_rate_last_100": float(np.mean([e["success"] for e in last])) if last else None,
        "collision_rate_last_100": float(np.mean([e["collision"] for e in last])) if last else None,
        "mean_return_last_100": float(np.mean([e["return"] for e in last])) if last else None,
        "versions": {"stable_baselines3": sb3.__version__, "torch": torch.__version__,
                     "pybullet": importlib.metadata.version("pybullet"), "python": platform.python_version()},
        "machine": {"cpus": os.cpu_count(), "torch_threads": torch.get_num_threads(), "platform": platform.platform()},
        "seed": args.seed,
    }
    venv.close()
    fileio.atomic_write_json(args.out, result, default=float)
    print(f"{steps} env steps in {wall:.1f} s: {steps / wall:.0f} env-steps/s; "
          f"success (last 100 episodes) {result['success_rate_last_100']}; written to {args.out}")
    return 0


# ---------------------------------------------------------------------- the paper's stack (worker side)

def sb3_worker(seconds: float, n_envs: int, seed: int, levels: list[float], window: int, out: str) -> int:
    """Runs inside the SB3 interpreter: SB3 PPO with the Table 2 settings below for ``seconds``."""
    t_launch = time.perf_counter()
    sb3, torch = _import_sb3()
    import numpy as np
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor, VecNormalize

    from sagrasp_jax.task.config import get_config
    from sagrasp_jax.reference.pybullet_env import PyBulletGraspEnv

    if UPDATE_STEPS % n_envs:
        raise SystemExit(f"error: --sb3-envs must divide {UPDATE_STEPS}")

    cfg = with_mode(get_config("paper").env, "kinematic")
    raw: list[Any] = []

    def make(rank: int) -> Any:
        def thunk() -> Any:
            env = PyBulletGraspEnv(cfg)
            env.reset(seed=seed * 1000 + rank)
            raw.append(env)
            return with_task_metrics(env)
        return thunk

    venv = VecNormalize(VecMonitor(DummyVecEnv([make(i) for i in range(n_envs)])), norm_obs=True,
                        norm_reward=False, clip_obs=OBS_CLIP, gamma=PAPER_PPO["gamma"])
    model = PPO("MlpPolicy", venv, n_steps=UPDATE_STEPS // n_envs, seed=seed, device="cpu", verbose=0,
                policy_kwargs={"net_arch": {"pi": HIDDEN, "vf": HIDDEN}, "activation_fn": torch.nn.Tanh},
                **PAPER_PPO)
    recent: collections.deque[float] = collections.deque(maxlen=window)
    curve: list[tuple[float, int, float]] = []
    updates: list[tuple[float, int]] = []
    state = {"t0": 0.0, "episodes": 0}

    class Budget(BaseCallback):
        """Sets progress p, records episode success and update boundaries, stops after ``seconds``."""

        def _on_training_start(self) -> None:
            state["t0"] = time.perf_counter()

        def _on_rollout_start(self) -> None:
            t = time.perf_counter() - state["t0"]
            updates.append((t, int(self.num_timesteps)))
            for env in raw:
                env.progress = min(1.0, self.num_timesteps / PAPER_TOTAL_STEPS)

        def _on_step(self) -> bool:
            t = time.perf_counter() - state["t0"]
            for info in self.locals["infos"]:
                if "task_episode" in info:
                    recent.append(float(info["task_episode"]["success"]))
                    state["episodes"] += 1
                    if len(recent) == window:
                        curve.append((t, int(self.num_timesteps), float(np.mean(recent))))
            return t < seconds

    startup = time.perf_counter() - t_launch
    model.learn(total_timesteps=PAPER_TOTAL_STEPS, callback=Budget())
    train_s = time.perf_counter() - state["t0"]
    steps = int(model.num_timesteps)
    venv.close()
    # Rate over whole collect+update iterations (the cut falls inside a rollout, whose update never ran).
    t_upd, s_upd = updates[-1] if len(updates) > 1 else (train_s, steps)
    result = {
        "status": "ok",
        "what": "Stable-Baselines3 PPO on SAGrasp-PyBullet-v0 (kinematic), paper Table 2 settings from "
                "experiments/bench_vs_paper_stack.py (sb3-baseline)",
        "layout": f"{n_envs} envs x {UPDATE_STEPS // n_envs} steps per update (DummyVecEnv)",
        "ppo": {**PAPER_PPO, "n_steps": UPDATE_STEPS // n_envs, "n_envs": n_envs,
                "net": "x".join(map(str, HIDDEN)) + " tanh"},
        "env_steps": steps,
        "train_s": train_s,
        "startup_s": startup,
        "updates_completed": max(len(updates) - 1, 0),
        "env_steps_per_s": s_upd / t_upd if t_upd > 0 else steps / train_s,
        "env_steps_per_s_incl_partial_rollout": steps / train_s,
        "env_steps_per_s_incl_startup": steps / (train_s + startup),
        "episodes": state["episodes"],
        "success_window": window,
        "last_training_success": float(np.mean(recent)) if recent else None,
        "last_training_success_episodes": len(recent),
        "time_to_success": first_reach(curve, levels),
        "time_to_eval_success": "no separate evaluation (training episodes only)",
        "versions": {"stable_baselines3": sb3.__version__, "torch": torch.__version__, "python": platform.python_version()},
        "torch_threads": torch.get_num_threads(),
    }
    fileio.atomic_write_json(out, result, sort_keys=True)
    return 0


def bench_sb3(sb3_python: str | None, seconds: float, n_envs: int, levels: list[float], window: int,
              work: str, timeout_s: float) -> dict[str, Any]:
    """Run the SB3 worker in ``sb3_python``; skipped (with the reason) when that is not possible."""
    if not sb3_python:
        return {"status": "skipped", "reason": "no --sb3-python given (SB3/torch are not in this venv)"}
    exe = shutil.which(sb3_python) or sb3_python
    if not os.path.isfile(exe):
        return {"status": "skipped", "reason": f"--sb3-python {sb3_python} does not exist"}
    probe = subprocess.run([exe, "-c", "import stable_baselines3, torch, pybullet, gymnasium"],
                           capture_output=True, text=True)
    if probe.returncode != 0:
        return {"status": "skipped", "reason": f"{sb3_python} cannot import SB3/torch/pybullet/gymnasium: "
                                               f"{probe.stderr.strip().splitlines()[-1] if probe.stderr.strip() else ''}"}
    out = os.path.join(work, "sb3.json")
    cmd = [exe, "-m", "experiments.bench_vs_paper_stack", "--sb3-worker", "--seconds", str(seconds), "--sb3-envs", str(n_envs),
           "--window", str(window), "--worker-out", out, "--success", *map(str, levels)]
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout_s)
    if res.returncode != 0 or not os.path.exists(out):
        return {"status": "error", "reason": f"SB3 worker exit {res.returncode}: {(res.stderr or res.stdout)[-1500:]}"}
    with open(out, encoding="utf-8") as f:
        result = json.load(f)
    result["wall_s"] = time.perf_counter() - t0
    result["python"] = sb3_python
    return result


# ---------------------------------------------------------------------- report

def _fmt_reach(value: Any) -> str:
    if isinstance(value, dict):
        return f"{value['time_s']:.0f} s / {value['env_steps'] / 1e3:.0f}k steps"
    return str(value)


def summary_table(result: dict[str, Any]) -> str:
    """Plain-text comparison: rates, ratios, time to each success level."""
    ours, sb3 = result["ours"], result["sb3"]
    lines = [f"{result['seconds']:.0f} s of training per stack on {result['machine']}", ""]
    hdr = f"{'':44}{'SB3+PyBullet (paper stack)':>30}{'ours (JAX, cpu-quick)':>28}{'ratio ours/SB3':>16}"
    lines.append(hdr)

    def row(label: str, key: str, fmt: str = "{:,.0f}", ratio_ok: bool = True) -> None:
        a = sb3.get(key) if sb3.get("status") == "ok" else None
        b = ours.get(key)
        ratio = (f"{b / a:,.1f}x" if ratio_ok and isinstance(a, (int, float)) and isinstance(b, (int, float)) and a
                 else "-")
        lines.append(f"{label:44}{(fmt.format(a) if a is not None else sb3.get('status', '-')):>30}"
                     f"{(fmt.format(b) if b is not None else '-'):>28}{ratio:>16}")

    row("env steps in budget", "env_steps")
    row("training env-steps/s (excl. start-up)", "env_steps_per_s")
    row("env-steps/s incl. start-up/compile", "env_steps_per_s_incl_startup")
    row("start-up + compile (s)", "startup_s", "{:,.1f}", ratio_ok=False)
    row("episodes finished in budget", "episodes", ratio_ok=False)
    row(f"training success, last <= {result['window']} episodes", "last_training_success", "{:.3f}", ratio_ok=False)
    for level in result["levels"]:
        key = f"{level:g}"
        a = sb3["time_to_success"][key] if sb3.get("status") == "ok" else sb3.get("status")
        b = ours["time_to_success"][key]
        lines.append(f"{'time to ' + format(level, '.0%') + ' training success':44}{_fmt_reach(a):>30}"
                     f"{_fmt_reach(b):>28}")
    lines.append(f"{'paper (SB3+PyBullet, RTX 4070 machine)':44}{PAPER_STEPS_PER_S:>30,.1f}"
                 f"{'':>28}{(ours['env_steps_per_s'] / PAPER_STEPS_PER_S):>15,.1f}x")
    if sb3.get("status") != "ok":
        lines.append(f"SB3 stack {sb3.get('status')}: {sb3.get('reason')}")
    return "\n".join(lines)


def raw_main(argv: list[str] | None = None) -> int:
    """``raw``: our dynamic env's env-steps/s at ``--batch`` against the bare PyBullet chain's dynamic stepping."""
    p = argparse.ArgumentParser(prog="bench_vs_paper_stack raw", description=raw_main.__doc__)
    p.add_argument("--batch", type=int, default=256, help="our env batch (default 256)")
    p.add_argument("--scan-steps", type=int, default=200, help="env steps per timed lax.scan call")
    p.add_argument("--pybullet-steps", type=int, default=3000, help="control steps of the bare chain per timing")
    p.add_argument("--physics-steps", type=int, default=12, help="PyBullet physics steps (1/240 s) per control step")
    p.add_argument("--out", default=None, help="result JSON (default: print only)")
    args = p.parse_args(argv)
    if min(args.batch, args.scan_steps, args.pybullet_steps, args.physics_steps) < 1:
        p.error("--batch, --scan-steps, --pybullet-steps and --physics-steps must be >= 1")
    from experiments import bench_env
    import jax

    def paper_side() -> float:
        row = bench_env.bench_bare_pybullet(args.pybullet_steps, physics_steps=args.physics_steps)
        if row is None:
            raise SystemExit("error: pybullet is not installed (pip install -e \".[twin]\")")
        return row["env_steps_per_s"]

    before = paper_side()
    rows = []
    for auto_reset in (False, True):
        for devices in sorted({1, len(jax.devices())}):
            if args.batch % devices:
                continue
            row = bench_env.bench_jax("dynamic", args.batch, args.scan_steps, auto_reset, devices=devices)
            rows.append(row)
            print(f"  ours dynamic, batch {args.batch}, {'auto-reset' if auto_reset else 'bare step'}, "
                  f"{devices} device(s): {row['env_steps_per_s']:,.0f} env-steps/s", flush=True)
    after = paper_side()
    paper = (before + after) / 2
    trained = max(r["env_steps_per_s"] for r in rows if r["auto_reset"])
    bare = max(r["env_steps_per_s"] for r in rows if not r["auto_reset"])
    result = {
        "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} CPU cores",
        "load_1min_end": round(os.getloadavg()[0], 2),
        "command": "python -m experiments.bench_vs_paper_stack raw " + " ".join(sys.argv[2:] if argv is None else argv),
        "paper_raw_dynamic": {"what": f"bare PyBullet AUBO-i5 chain, position control, {args.physics_steps} x 1/240 s "
                                      "per control step, link pose, one closest-point query",
                              "env_steps_per_s_before": before, "env_steps_per_s_after": after,
                              "env_steps_per_s": paper},
        "ours": rows,
        "ratio_auto_reset": trained / paper, "ratio_bare_step": bare / paper,
    }
    print(f"{'paper stack, raw dynamic stepping (bare chain)':52s} {paper:>10,.0f} env-steps/s "
          f"(before {before:,.0f}, after {after:,.0f})")
    print(f"{'ours, dynamic, as training steps it (auto-reset)':52s} {trained:>10,.0f} env-steps/s   {trained / paper:.1f}x")
    print(f"{'ours, dynamic, bare step':52s} {bare:>10,.0f} env-steps/s   {bare / paper:.1f}x")
    if args.out:
        fileio.atomic_write_json(args.out, result, sort_keys=True)
        print(f"written to {args.out}")
    return 0


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=120.0, help="training wall-clock budget per stack")
    p.add_argument("--sb3-python", default=None, help="interpreter with stable-baselines3 + torch + sagrasp_jax[reference]")
    p.add_argument("--sb3-envs", type=int, default=16, help="SB3 envs (16 x 128 or 1 x 2048 steps per update)")
    p.add_argument("--preset", default="cpu-quick", help="our trainer's preset")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override for our trainer, repeatable")
    p.add_argument("--success", type=float, nargs="+", default=[0.25, 0.5, 0.8],
                   help="training success levels for time-to-success")
    p.add_argument("--window", type=int, default=256, help="finished training episodes per success estimate")
    p.add_argument("--max-startup-s", type=float, default=900.0, help="give up if our trainer logs nothing by then")
    p.add_argument("--out", default=None, help="result JSON (default: print only)")
    p.add_argument("--sb3-worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--worker-out", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.seconds <= 0:
        p.error("--seconds must be > 0")
    if args.window < 1:
        p.error("--window must be >= 1")
    if any(not 0 < s <= 1 for s in args.success):
        p.error("--success levels must lie in (0, 1]")
    if args.sb3_worker and not args.worker_out:
        p.error("--sb3-worker needs --worker-out")
    return args


def main(argv: list[str] | None = None) -> int:
    given = sys.argv[1:] if argv is None else list(argv)
    if given[:1] == ["sb3-baseline"]:
        return sb3_baseline_main(given[1:])
    if given[:1] == ["raw"]:
        return raw_main(given[1:])
    args = parse_args(argv)
    if args.sb3_worker:
        return sb3_worker(args.seconds, args.sb3_envs, 0, args.success, args.window, args.worker_out)
    import sagrasp_jax  # noqa: F401  (fails early with a clear ImportError if the package is missing)

    with tempfile.TemporaryDirectory(prefix="bench_stack.") as work:
        print(f"[1/2] SB3 PPO on the PyBullet reference env, {args.seconds:.0f} s ...", flush=True)
        sb3 = bench_sb3(args.sb3_python, args.seconds, args.sb3_envs, args.success, args.window, work,
                        timeout_s=args.seconds + args.max_startup_s)
        print(f"      {sb3['status']}" + (f": {sb3['env_steps_per_s']:,.0f} env-steps/s" if sb3["status"] == "ok"
                                         else f" ({sb3.get('reason')})"), flush=True)
        print(f"[2/2] ours ({args.preset}), {args.seconds:.0f} s of training after compilation ...", flush=True)
        try:
            ours = bench_ours(args.seconds, args.preset, args.overrides, args.success, args.window, work,
                              args.max_startup_s)
        except RuntimeError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
        print(f"      {ours['env_steps_per_s']:,.0f} env-steps/s", flush=True)
    ratio = (ours["env_steps_per_s"] / sb3["env_steps_per_s"]) if sb3["status"] == "ok" else None
    result = {
        "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} CPU cores, "
                   f"load average at end {os.getloadavg()[0]:.1f}",
        "command": "python -m experiments.bench_vs_paper_stack " + " ".join(sys.argv[1:] if argv is None else argv),
        "seconds": args.seconds, "levels": args.success, "window": args.window,
        "success_note": ("time to success: first moment the training-episode success rate over the last "
                         f"{args.window} finished episodes reaches the level (training time after start-up)"),
        "sb3": sb3, "ours": ours,
        "paper": {"env_steps_per_s": PAPER_STEPS_PER_S, "machine": "RTX 4070 machine (paper)",
                  "total_steps": PAPER_TOTAL_STEPS},
        "ratio_ours_over_sb3_env_steps_per_s": ratio,
        "ratio_ours_over_paper_env_steps_per_s": ours["env_steps_per_s"] / PAPER_STEPS_PER_S,
    }
    table = summary_table(result)
    print(table)
    if args.out:
        fileio.atomic_write_json(args.out, result, sort_keys=True)
        print(f"written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
