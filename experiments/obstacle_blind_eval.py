"""Does a trained policy use its obstacle inputs?  Evaluate it on obstacle-only episodes twice:
seeing (the real observation) and blind (every obstacle entry replaced by its "no obstacle" value,
``observation.blind``: the sentinel (0, 0, −1) and Δpo = 1 in the paper layout, zeros in the
relative one), on the task's disc placement of obstacles and on blocking-only scenes.  Deterministic NumPy
policy, reward weights at p = 1, no observation noise.

    python -m experiments.obstacle_blind_eval --policy runs/quick/policy.npz --episodes 200 \
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

from sagrasp_jax import observation, runtime
from sagrasp_jax.config import blocking_sampling
from sagrasp_jax.env import GraspEnv
from sagrasp_jax.fileio import atomic_write_json

SCENES = ("obstacle", "blocking")


def evaluate(policy: runtime.NumpyPolicy, episodes: int, seed: int, blind: bool, scenes: str = "obstacle") -> dict:
    cfg = policy.env_config()
    cfg = dataclasses.replace(
        cfg,
        sampling=blocking_sampling(cfg.sampling, 1.0, 1.0 if scenes == "blocking" else 0.0),
        task=dataclasses.replace(cfg.task, obs_noise_std=0.0),
    )
    env = GraspEnv(cfg)
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(seed), episodes))
    state = state.replace(info=dict(state.info, progress=jnp.ones(episodes)))
    step = jax.jit(jax.vmap(env.step))
    alive = np.ones(episodes, bool)
    record: dict[str, np.ndarray] = {}
    for _ in range(cfg.task.max_steps):
        obs = np.asarray(state.obs, dtype=float)
        if blind:
            obs = observation.blind(np, cfg, obs)
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
        "scenes": scenes,
        "episodes": episodes,
        "obstacle_episodes": int((record["obstacle_present"] > 0).sum()),
        "success_rate": float(success.mean()),
        "collision_rate": float(record["collision"].mean()),
        "collision_by": {k[4:]: float(v.mean()) for k, v in record.items() if k.startswith("hit_")},
        "mean_steps_per_success": float(record["steps"][success > 0].mean()) if success.any() else None,
    }


def blind_study(policy: runtime.NumpyPolicy, episodes: int, seed: int) -> dict:
    """Seeing vs blind on obstacle-only scenes (disc placement, docs/task.md §1.5) and on blocking-only scenes."""
    result: dict = {"seed": seed, "obs_layout": policy.env_config().task.obs_layout}
    for scenes in SCENES:
        seeing = evaluate(policy, episodes, seed, False, scenes)
        blinded = evaluate(policy, episodes, seed, True, scenes)
        result[scenes] = {"seeing": seeing, "blind": blinded,
                          "seeing_minus_blind": seeing["success_rate"] - blinded["success_rate"]}
    return result


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
    result = blind_study(policy, args.episodes, args.seed)
    result["policy"] = args.policy
    for scenes in SCENES:
        for name in ("seeing", "blind"):
            r = result[scenes][name]
            print(f"{scenes:8s} {name:7s} success {r['success_rate']:.3f}  collision {r['collision_rate']:.3f}  "
                  + "  ".join(f"{k} {v:.3f}" for k, v in r["collision_by"].items()))
        print(f"{scenes:8s} seeing − blind: {100 * result[scenes]['seeing_minus_blind']:+.1f} points")
    if args.out:
        atomic_write_json(args.out, result)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
