"""Evaluate a trained run: ``python -m sagrasp_jax.evaluate --run runs/NAME --episodes 1000``.

The run's latest checkpoint is played with the deterministic policy (tanh of the Gaussian
mean) and reward weights frozen at p = 1, one episode per seed from a held-out evaluation
seed (by default ``sa.eval_seed + 1``, so the SA selection set is not reused).  Reported:
success rate with its 95 % Wilson interval, mean steps per successful grasp, collision rate
(and what was hit, from the episodes' ``hit_*`` flags), timeout rate, each overall and split by
obstacle present / absent.  The JSON goes atomically into the run folder.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from typing import Any, Callable

import jax
import numpy as np

from sagrasp_jax import checkpoint, observation, ppo
from sagrasp_jax.control import ACTION_SIZE
from sagrasp_jax.checkpoint import CheckpointError
from sagrasp_jax.config import Config, ConfigError, blocking_sampling, config_from_dict

RESULT_FILE = "evaluation.json"
EvalEnvFactory = Callable[[Config], ppo.Env]
SCENE_SETS = ("mix", "blocking")


def default_eval_env(cfg: Config) -> ppo.Env:
    from sagrasp_jax.env import GraspEnv

    return GraspEnv(cfg.env)


def scene_config(cfg: Config, scenes: str) -> Config:
    """The evaluation's config: ``mix`` = the run's own env (SPEC mix, obstacle_prob 0.2);
    ``blocking`` = every episode has an obstacle on the straight approach path (sampling.py's
    blocking placement, SPEC §1 feasibility rules kept)."""
    if scenes not in SCENE_SETS:
        raise ConfigError(f"--scenes must be one of {', '.join(SCENE_SETS)}, got {scenes!r}")
    if scenes == "mix":
        return cfg
    env = dataclasses.replace(cfg.env, sampling=blocking_sampling(cfg.env.sampling, 1.0, 1.0))
    return dataclasses.replace(cfg, env=env)


def wilson_interval(successes: float, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (sane at 0 % and 100 %, unlike Wald)."""
    if n <= 0:
        return (math.nan, math.nan)
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


def load_policy_state(run_dir: str, obs_size: int | None = None, action_size: int = ACTION_SIZE
                      ) -> tuple[Config, ppo.Params, ppo.Normaliser, dict[str, Any]]:
    """Config, params and normaliser of the run's latest checkpoint (and its counters); the
    observation size defaults to that of the run's observation layout."""
    from sagrasp_jax.train import CHECKPOINT_FILE, CONFIG_FILE

    cfg_path = os.path.join(run_dir, CONFIG_FILE)
    try:
        with open(cfg_path, encoding="utf-8") as f:
            cfg = config_from_dict(json.load(f))
    except FileNotFoundError:
        raise CheckpointError(f"{cfg_path}: not a run folder (no config.json)") from None
    except (json.JSONDecodeError, TypeError, ValueError) as exc:
        raise CheckpointError(f"{cfg_path}: unreadable config ({exc})") from None
    ckpt = checkpoint.load(os.path.join(run_dir, CHECKPOINT_FILE))
    checkpoint.check_config(ckpt, cfg)
    obs_size = len(observation.layout_of(cfg.env)) if obs_size is None else obs_size
    networks = ppo.make_networks(cfg.ppo.network, obs_size, action_size, cfg.ppo.obs_clip)
    optimizer = ppo.make_optimizer(cfg.ppo, cfg.sa.lr0)
    template = ppo.init_training_state(jax.random.PRNGKey(0), networks, optimizer, obs_size)
    ts = checkpoint.restore_tree(template, ckpt.trees.get("train_state", {}), "train_state", ckpt.path)
    return cfg, ts.params, ts.normaliser, ckpt.host.get("counters", {})


def summarise(episodes: dict[str, np.ndarray], mask: np.ndarray) -> dict[str, Any]:
    """Rates over the episodes selected by ``mask``."""
    n = int(mask.sum())
    if n == 0:
        return {"episodes": 0}
    sel = {k: np.asarray(v)[mask] for k, v in episodes.items()}
    success = sel["success"] > 0
    lo, hi = wilson_interval(float(success.sum()), n)
    hits = {k[4:]: float(np.mean(v > 0)) for k, v in sorted(sel.items()) if k.startswith("hit_")}
    return {
        "episodes": n,
        "success_rate": float(success.mean()),
        "success_ci95": [lo, hi],
        "mean_steps_per_success": float(sel["steps"][success].mean()) if success.any() else None,
        "collision_rate": float(np.mean(sel["collision"] > 0)),
        "collision_by": hits,
        "timeout_rate": float(np.mean(sel["timeout"] > 0)),
        "unfinished": int(np.sum(sel["finished"] == 0)),
        "mean_return": float(sel["return"].mean()),
    }


def evaluate_run(run_dir: str, episodes: int = 1000, seed: int | None = None, max_steps: int | None = None,
                 env_factory: EvalEnvFactory | None = None, scenes: str = "mix") -> dict[str, Any]:
    """Play ``episodes`` fixed-seed episodes with the run's policy and summarise them."""
    if episodes < 1:
        raise ConfigError(f"--episodes must be >= 1, got {episodes}")
    from sagrasp_jax.train import CONFIG_FILE

    with open(os.path.join(run_dir, CONFIG_FILE), encoding="utf-8") as f:
        env = (env_factory or default_eval_env)(scene_config(config_from_dict(json.load(f)), scenes))
    cfg, params, normaliser, counters = load_policy_state(run_dir, env.observation_size, env.action_size)
    networks = ppo.make_networks(cfg.ppo.network, env.observation_size, env.action_size, cfg.ppo.obs_clip)
    seed = cfg.sa.eval_seed + 1 if seed is None else seed
    steps = max_steps or cfg.env.task.max_steps
    t = time.perf_counter()
    result = jax.device_get(ppo.make_evaluator(networks, env, steps)(params, normaliser, ppo.eval_keys(seed, episodes)))
    wall = time.perf_counter() - t
    eps = {k: np.asarray(v) for k, v in result.episodes.items()}
    present = eps["obstacle_present"] > 0 if "obstacle_present" in eps else np.zeros(episodes, bool)
    blocking = present & (eps["blocking"] > 0) if "blocking" in eps else np.zeros(episodes, bool)
    everyone = np.ones(episodes, bool)
    return {
        "run": os.path.abspath(run_dir),
        "episodes": episodes,
        "scenes": scenes,
        "seed": seed,
        "max_steps": steps,
        "progress_weights": 1.0,
        "policy": "deterministic",
        "checkpoint_iteration": counters.get("iteration"),
        "checkpoint_env_steps": counters.get("env_steps"),
        "wall_s": wall,
        "overall": summarise(eps, everyone),
        "obstacle_present": summarise(eps, present),
        "blocking": summarise(eps, blocking),
        "obstacle_absent": summarise(eps, ~present),
        "fallback_episodes": int(np.sum(eps["fallback"] > 0)) if "fallback" in eps else 0,
    }


def write_results(path: str, results: dict[str, Any]) -> str:
    text = json.dumps(results, indent=2, sort_keys=True, allow_nan=False) + "\n"
    checkpoint.atomic_write_bytes(path, text.encode())
    return path


def format_table(results: dict[str, Any]) -> str:
    """A plain-text table: one column per episode group."""
    groups = [("all", results["overall"]), ("obstacle", results["obstacle_present"])]
    groups += [("blocking", results["blocking"])] if "blocking" in results else []
    groups += [("no obstacle", results["obstacle_absent"])]
    hit_keys = sorted({k for _, g in groups for k in g.get("collision_by", {})})

    def pct(v: Any) -> str:
        return "-" if v is None else f"{100 * v:.1f} %"

    rows: list[tuple[str, list[str]]] = [
        ("episodes", [str(g["episodes"]) for _, g in groups]),
        ("success", [pct(g.get("success_rate")) for _, g in groups]),
        ("  95 % CI (Wilson)", [("-" if "success_ci95" not in g else
                                 f"{100 * g['success_ci95'][0]:.1f}-{100 * g['success_ci95'][1]:.1f} %")
                                for _, g in groups]),
        ("steps / success", [("-" if g.get("mean_steps_per_success") is None else f"{g['mean_steps_per_success']:.1f}")
                             for _, g in groups]),
        ("collision", [pct(g.get("collision_rate")) for _, g in groups]),
    ]
    rows += [(f"  hit {k}", [pct(g.get("collision_by", {}).get(k)) for _, g in groups]) for k in hit_keys]
    rows += [("timeout", [pct(g.get("timeout_rate")) for _, g in groups]),
             ("mean return (p=1)", [("-" if g.get("mean_return") is None else f"{g['mean_return']:.3f}")
                                    for _, g in groups])]
    width = max(len(r[0]) for r in rows) + 2
    scenes = results.get("scenes", "mix")
    kind = "blocking-only scenes" if scenes == "blocking" else "the evaluation mix"
    lines = [f"{results['episodes']} episodes of {kind}, seed {results['seed']}, deterministic policy, reward weights at p = 1",
             "".ljust(width) + "".join(name.rjust(14) for name, _ in groups)]
    lines += [label.ljust(width) + "".join(c.rjust(14) for c in cells) for label, cells in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m sagrasp_jax.evaluate", description=__doc__.split("\n\n")[0])
    p.add_argument("--run", required=True, help="run folder written by sagrasp_jax.train")
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--seed", type=int, default=None, help="evaluation seed (default sa.eval_seed + 1)")
    p.add_argument("--max-steps", type=int, default=None, help="step cap per episode (default env.task.max_steps)")
    p.add_argument("--scenes", default="mix", choices=SCENE_SETS,
                   help="mix: the SPEC's scene mix (20 %% obstacle episodes); blocking: every episode has an obstacle "
                        "on the straight approach path")
    p.add_argument("--out", default=None, help=f"result JSON (default RUN/{RESULT_FILE})")
    p.add_argument("--physical", action="store_true",
                   help="also replay each kinematic success through the MuJoCo physical grasp check (close, lift 5 cm)")
    args = p.parse_args(argv)
    try:
        results = evaluate_run(args.run, args.episodes, args.seed, args.max_steps, scenes=args.scenes)
        if args.physical:
            from sagrasp_jax.physical import evaluate_physical

            results["physical"] = evaluate_physical(args.run, args.episodes, results["seed"], results["max_steps"])
    except (ConfigError, CheckpointError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    path = write_results(args.out or os.path.join(args.run, RESULT_FILE), results)
    print(format_table(results))
    if "physical" in results:
        ph = results["physical"]
        print(f"physical grasp check: {ph['physical_successes']} of {ph['kinematic_successes']} kinematic successes held "
              f"the cube when lifted {ph['lift'] * 100:.0f} cm ({100 * ph['physical_success_rate']:.1f} % of all episodes)")
    print(f"written to {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
