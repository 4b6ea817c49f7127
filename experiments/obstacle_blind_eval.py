"""Does a trained policy use its obstacle inputs?  Evaluate it on obstacle-only episodes twice:
seeing (the real observation) and blind (obstacle entries replaced by the no-obstacle encoding
(0, 0, −1), Δpo = 1).  Deterministic NumPy policy, reward weights at p = 1, no observation noise.

    python experiments/obstacle_blind_eval.py --policy runs/quick/policy.npz --episodes 200 \
        --out experiments/results/obstacle_blind_eval.json
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np

import sagrasp_jax  # noqa: F401
import jax
import jax.numpy as jnp

from sagrasp_jax import runtime
from sagrasp_jax.env import GraspEnv
from sagrasp_jax.fileio import atomic_write_json

OBSTACLE_ENTRIES = slice(12, 16)  # obstacle xyz and Δpo in observation.OBS_LAYOUT


def evaluate(policy: runtime.NumpyPolicy, episodes: int, seed: int, blind: bool) -> dict:
    cfg = policy.env_config()
    cfg = dataclasses.replace(
        cfg,
        sampling=dataclasses.replace(cfg.sampling, obstacle_prob=1.0),
        task=dataclasses.replace(cfg.task, obs_noise_std=0.0),
    )
    env = GraspEnv(cfg)
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(seed), episodes))
    state = state.replace(info=dict(state.info, progress=jnp.ones(episodes)))
    step = jax.jit(jax.vmap(env.step))
    alive = np.ones(episodes, bool)
    record: dict[str, np.ndarray] = {}
    blind_values = np.array(list(cfg.task.no_obstacle_pos) + [cfg.task.obstacle_dist_clip])
    for _ in range(cfg.task.max_steps):
        obs = np.asarray(state.obs, dtype=float).copy()
        if blind:
            obs[:, OBSTACLE_ENTRIES] = blind_values
        state = step(state, jnp.asarray(policy(obs), jnp.float32))
        done = np.asarray(state.done) > 0
        ended = alive & done
        for key, value in state.info["episode"].items():
            record[key] = np.where(ended, np.asarray(value), record.get(key, np.zeros(episodes)))
        alive &= ~done
        if not alive.any():
            break
    success = record["success"]
    return {
        "episodes": episodes,
        "success_rate": float(success.mean()),
        "collision_rate": float(record["collision"].mean()),
        "collision_by": {k[4:]: float(v.mean()) for k, v in record.items() if k.startswith("hit_")},
        "mean_steps_per_success": float(record["steps"][success > 0].mean()) if success.any() else None,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", required=True, help="policy.npz of a trained run")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--out", default=None, help="JSON output (optional)")
    args = parser.parse_args(argv)
    try:
        policy = runtime.load_policy(args.policy)
    except (OSError, runtime.PolicyFormatError) as exc:
        parser.error(str(exc))
    result = {"policy": args.policy, "seed": args.seed}
    for name, blind in (("seeing", False), ("blind", True)):
        result[name] = evaluate(policy, args.episodes, args.seed, blind)
        r = result[name]
        print(f"{name:7s} success {r['success_rate']:.3f}  collision {r['collision_rate']:.3f}  "
              + "  ".join(f"{k} {v:.3f}" for k, v in r["collision_by"].items()))
    if args.out:
        atomic_write_json(args.out, result)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
