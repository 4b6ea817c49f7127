"""Stable-Baselines3 PPO on the PyBullet reference env with the paper's Table 2 settings.

Why: the paper trained SB3 PPO on PyBullet at 375.8 env-steps/s; this is the same stack on
our reference env (same task as the MJX env, checked by ``sagrasp_jax.parity``), the anchor
that the MJX/JAX trainer's throughput is compared with.  It reports env-steps/s and the
training episodes' success rate; it is not meant to reproduce the paper's curves.

    python -m experiments.sb3_baseline --total-steps 200000 --out sb3_baseline.json

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

from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata
import os
import platform
import sys
import time
from typing import Any

import numpy as np

from sagrasp_jax import fileio

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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
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


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.total_steps < 1 or args.n_envs < 1 or UPDATE_STEPS % args.n_envs:
        print(f"error: --total-steps must be ≥ 1 and --n-envs must divide {UPDATE_STEPS}", file=sys.stderr)
        return 2
    sb3, torch = _import_sb3()
    import gymnasium as gym
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.logger import Logger
    from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor, VecNormalize

    from sagrasp_jax.config import get_config
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


if __name__ == "__main__":
    sys.exit(main())
