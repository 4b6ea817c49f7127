"""Training throughput and time-to-success: our JAX trainer vs the paper's stack, same machine, one run.

Each stack trains for a fixed wall-clock budget (``--seconds`` of training, after its own
start-up and compilation), one after the other so they never share the CPU:

1. **the paper's stack**: Stable-Baselines3 PPO on the PyBullet reference env
   (``SAGrasp-PyBullet-v0``) with the paper's Table 2 settings, taken from
   ``experiments.sb3_baseline`` (its ``PAPER_PPO``, ``HIDDEN``, ``OBS_CLIP``, ``UPDATE_STEPS``,
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
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from typing import Any, Callable

from experiments.stats import first_reach
from sagrasp_jax import fileio

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAPER_STEPS_PER_S = 375.8  # paper, SB3 + PyBullet on an RTX 4070 machine (docs/task.md §4)
PAPER_TOTAL_STEPS = 20_000_000


def watch_trainer(cmd: list[str], cwd: str, log_path: str, metrics_path: str, poll_s: float,
                  stop_reason: Callable[[list[dict[str, Any]], float], str | None],
                  env: dict[str, str] | None = None, on_poll: Callable[[int], None] | None = None,
                  ) -> tuple[list[dict[str, Any]], str | None, int | None, float]:
    """Run a trainer command (output to ``log_path``), reading its ``metrics.jsonl`` every ``poll_s``
    seconds; ``stop_reason(rows, seconds since launch)`` returning a reason SIGTERMs it (it
    checkpoints and exits).  ``on_poll(pid)`` samples the process (e.g. its memory).  Returns the
    final metric rows, the stop reason (None: it exited by itself), its exit code and the wall time."""
    from sagrasp_jax.run_dir import read_metrics

    stopped: str | None = None
    t0 = time.perf_counter()
    with open(log_path, "w", encoding="utf-8") as log:
        proc = subprocess.Popen(cmd, cwd=cwd, stdout=log, stderr=subprocess.STDOUT, env=env)
        try:
            while proc.poll() is None:
                time.sleep(poll_s)
                if on_poll is not None:
                    on_poll(proc.pid)
                rows = read_metrics(metrics_path) if os.path.exists(metrics_path) else []
                stopped = stop_reason(rows, time.perf_counter() - t0)
                if stopped:
                    proc.send_signal(signal.SIGTERM)
                    break
            proc.wait(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    rows = read_metrics(metrics_path) if os.path.exists(metrics_path) else []
    return rows, stopped, proc.returncode, time.perf_counter() - t0


# ---------------------------------------------------------------------- ours

def bench_ours(seconds: float, preset: str, overrides: list[str], levels: list[float], window: int,
               work: str, max_startup_s: float) -> dict[str, Any]:
    """Train our SA-PPO via the CLI until ``seconds`` of training time, then stop it and read its metrics."""
    from sagrasp_jax.run_dir import METRICS_FILE

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


# ---------------------------------------------------------------------- the paper's stack (worker side)

def sb3_worker(seconds: float, n_envs: int, seed: int, levels: list[float], window: int, out: str) -> int:
    """Runs inside the SB3 interpreter: SB3 PPO with sb3_baseline's Table 2 settings for ``seconds``."""
    t_launch = time.perf_counter()
    from experiments import sb3_baseline as base  # the settings' single source

    sb3, torch = base._import_sb3()
    import numpy as np
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor, VecNormalize

    from sagrasp_jax.config import get_config
    from sagrasp_jax.reference.pybullet_env import PyBulletGraspEnv

    if base.UPDATE_STEPS % n_envs:
        raise SystemExit(f"error: --sb3-envs must divide {base.UPDATE_STEPS}")

    cfg = base.with_mode(get_config("paper").env, "kinematic")
    raw: list[Any] = []

    def make(rank: int) -> Any:
        def thunk() -> Any:
            env = PyBulletGraspEnv(cfg)
            env.reset(seed=seed * 1000 + rank)
            raw.append(env)
            return base.with_task_metrics(env)
        return thunk

    venv = VecNormalize(VecMonitor(DummyVecEnv([make(i) for i in range(n_envs)])), norm_obs=True,
                        norm_reward=False, clip_obs=base.OBS_CLIP, gamma=base.PAPER_PPO["gamma"])
    model = PPO("MlpPolicy", venv, n_steps=base.UPDATE_STEPS // n_envs, seed=seed, device="cpu", verbose=0,
                policy_kwargs={"net_arch": {"pi": base.HIDDEN, "vf": base.HIDDEN}, "activation_fn": torch.nn.Tanh},
                **base.PAPER_PPO)
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
                "experiments/sb3_baseline.py",
        "layout": f"{n_envs} envs x {base.UPDATE_STEPS // n_envs} steps per update (DummyVecEnv)",
        "ppo": {**base.PAPER_PPO, "n_steps": base.UPDATE_STEPS // n_envs, "n_envs": n_envs,
                "net": "x".join(map(str, base.HIDDEN)) + " tanh"},
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
