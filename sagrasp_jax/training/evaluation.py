"""The offline evaluation of a trained run: fixed-seed episodes, their rates and what identifies them.

``evaluate_run`` plays a run's latest checkpoint with the deterministic policy (tanh of the Gaussian mean)
and reward weights frozen at p = 1, one episode per key from a held-out evaluation seed (by default
``eval.seed + 1``, so the SA selection set is not reused), in the run's env, another scene set
(``scene_config``) or with ``env.*`` changes (``env_overrides``), and summarises success with its 95 %
Wilson interval, steps per success, collisions (and what was hit), timeouts, overall and per episode kind.
``trained_identity`` is what a result file records of what was trained (config hash, checkpoint digest),
so a command can tell whether an existing file holds the same evaluation.  ``replay_final_poses`` replays
the same episodes recording each final arm pose, for what happens after them (the physical grasp check).

It lives with the trainer because it is the trainer's policy, restored (``restore``), run through the
training's own jitted evaluator (``fixed_seed_eval``) in the JAX env: the command
(``python -m sagrasp_jax.evaluate``: options, result file, lock, table), the studies in ``experiments/``
and the tests call it alike.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import dataclasses
import math
import os
import time
from typing import Any, Callable, NamedTuple

import jax
import numpy as np

from sagrasp_jax.training.agents.ppo import actor_critic
from sagrasp_jax.training import fixed_seed_eval as policy_eval
from sagrasp_jax.training.agents.ppo import rollout
from sagrasp_jax.training import run_dir
from sagrasp_jax.training import restore
from sagrasp_jax.task.config import SEED_RANGE, Config, ConfigError, blocking_sampling, check_range

EvalEnvFactory = Callable[[Config], rollout.Env]
SCENE_SETS = ("mix", "blocking")
MAX_EPISODES = 100_000  # one batch: every episode's start state is in memory at once
MAX_STEPS = 100_000
# On CPU the episodes run this many at a time, each slot taking the next episode when its own ends
# (fixed_seed_eval.evaluate_policy; accelerators run every episode at once): 1,000 `robot` episodes of the
# README policy in 0.78 s instead of 4.58 s all at once on 2 cores (32 slots: 0.83 s, 128: 1.01 s); the same
# episodes, their floats within 3.8e-6 (docs/results-archive.md §17).
CPU_SLOTS = 64


def default_eval_env(cfg: Config) -> rollout.Env:
    from sagrasp_jax.envs.grasp_env import GraspEnv

    return GraspEnv(cfg.env)


def scene_config(cfg: Config, scenes: str) -> Config:
    """The evaluation's config: ``mix`` = the run's own env (the evaluation mix, obstacle_prob 0.2);
    ``blocking`` = every episode has an obstacle on the straight approach path (sampling.py's
    blocking placement, docs/task.md §1 feasibility rules kept)."""
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


def env_overrides(cfg: Config, overrides: list[str] | None) -> Config:
    """``cfg`` with ``--set`` changes of the evaluated env (``env.*`` keys only; the policy's
    observation layout must stay the same)."""
    from sagrasp_jax.task import observation
    from sagrasp_jax.task.config_parse import apply_overrides

    overrides = list(overrides or [])
    bad = [o for o in overrides if not o.strip().startswith("env.")]
    if bad:
        raise ConfigError(f"--set changes the evaluated env only (env.* keys), not {', '.join(bad)}")
    out = apply_overrides(cfg, overrides)
    if observation.layout_of(out.env) != observation.layout_of(cfg.env):
        raise ConfigError(f"--set {' '.join(overrides)} changes the observation layout the policy was trained with")
    return out


def check_options(episodes: int, seed: int | None, max_steps: int | None) -> None:
    """The evaluation's ranges, named as the command's options; checked before any work (the command
    checks them before it locks its result file, ``evaluate_run`` again for library callers)."""
    check_range("--episodes", episodes, 1, MAX_EPISODES)
    if seed is not None:
        check_range("--seed", seed, *SEED_RANGE)
    if max_steps is not None:
        check_range("--max-steps", max_steps, 1, MAX_STEPS)


def resolve_options(cfg: Config, seed: int | None, max_steps: int | None) -> tuple[int, int]:
    """The evaluation seed (default ``eval.seed + 1``, held out) and step cap (default the config's)."""
    seed = (cfg.eval.seed + 1) % (SEED_RANGE[1] + 1) if seed is None else seed
    return seed, cfg.env.task.max_steps if max_steps is None else max_steps


def evaluate_run(run: str, episodes: int = 1000, seed: int | None = None, max_steps: int | None = None,
                 env_factory: EvalEnvFactory | None = None, scenes: str = "mix",
                 overrides: list[str] | None = None) -> dict[str, Any]:
    """Play ``episodes`` fixed-seed episodes with the run's policy and summarise them (in the run's env,
    or with ``overrides`` of it)."""
    check_options(episodes, seed, max_steps)
    cfg = run_dir.load_config(run)
    ckpt = run_dir.load_checkpoint(run, cfg)  # verified before the env is built
    counters = run_dir.checkpoint_counters(ckpt)
    trained = trained_identity(cfg, ckpt)
    env = (env_factory or default_eval_env)(scene_config(env_overrides(cfg, overrides), scenes))
    params, normaliser = restore.restore_policy(cfg, ckpt, env.observation_size, env.action_size)
    networks = actor_critic.make_networks(cfg.ppo.network, env.observation_size, env.action_size, cfg.ppo.obs_clip)
    seed, steps = resolve_options(cfg, seed, max_steps)
    t = time.perf_counter()
    keys = policy_eval.eval_keys(seed, episodes)
    evaluator = policy_eval.make_evaluator(networks, env, steps, slots=policy_eval.slots_for_backend(CPU_SLOTS))
    result = jax.device_get(evaluator(params, normaliser, keys))
    wall = time.perf_counter() - t
    eps = {k: np.asarray(v) for k, v in result.episodes.items()}
    present = eps["obstacle_present"] > 0 if "obstacle_present" in eps else np.zeros(episodes, bool)
    blocking = present & (eps["blocking"] > 0) if "blocking" in eps else np.zeros(episodes, bool)
    everyone = np.ones(episodes, bool)
    return {
        "run": os.path.abspath(run),
        "episodes": episodes,
        "scenes": scenes,
        **({"env_overrides": list(overrides)} if overrides else {}),
        "seed": seed,
        "max_steps": steps,
        "progress_weights": 1.0,
        "policy": "deterministic",
        "checkpoint_iteration": counters.get("iteration"),
        "checkpoint_env_steps": counters.get("env_steps"),
        **trained,
        "wall_s": wall,
        "overall": summarise(eps, everyone),
        "obstacle_present": summarise(eps, present),
        "blocking": summarise(eps, blocking),
        "obstacle_absent": summarise(eps, ~present),
        "fallback_episodes": int(np.sum(eps["fallback"] > 0)) if "fallback" in eps else 0,
    }


def config_identity(cfg: Config) -> str:
    """A hash of a run's whole config (seed included; ``config_history.config_hash`` covers the env only), in its
    first-written layout (``config_history.identity_dict``), so a key's rename keeps older runs' evaluation files valid."""
    import hashlib
    import json

    from sagrasp_jax.task.config_history import identity_dict

    return hashlib.sha256(json.dumps(identity_dict(cfg), sort_keys=True).encode()).hexdigest()[:16]


def trained_identity(cfg: Config, ckpt: Any) -> dict[str, Any]:
    """What was trained, in an evaluation's identity: ``config_identity`` and the checkpoint's payload digest
    (a retrained run at the same iteration is another evaluation)."""
    return {"config_sha256": config_identity(cfg), "checkpoint_sha256": ckpt.header.get("payload_sha256")}


def write_results(path: str, results: dict[str, Any]) -> str:
    return run_dir.write_json(path, results)




class FinalPoses(NamedTuple):
    """``evaluate_run``'s episodes replayed with each episode's final arm joints (``replay_final_poses``)."""

    episodes: dict[str, np.ndarray]  # per-episode records, as ``evaluate_run`` summarises them
    q_final: np.ndarray  # (episodes, dof) the arm's measured joints when each episode ended
    specs: Any  # the episodes' true scenes, a ResetSpec of (episodes, ...) arrays
    target_error: np.ndarray  # (episodes, 3) the detection error each episode's policy saw (0 without one)
    env_cfg: Any  # the evaluated env's EnvConfig

    def spec(self, i: int) -> Any:
        """Episode ``i``'s true scene as a ResetSpec of NumPy arrays."""
        return type(self.specs)(*(np.asarray(leaf)[i] for leaf in self.specs))


def replay_final_poses(run: str, episodes: int, seed: int, max_steps: int,
                       overrides: list[str] | None = None, scenes: str = "mix") -> FinalPoses:
    """Replay ``evaluate_run``'s episodes (same keys, same jitted evaluator, the env wrapped to copy the final
    joints into the episode record) for what happens after them: the physical grasp check, the detection
    ceiling study."""
    from sagrasp_jax.envs.grasp_env import GraspEnv

    env_cfg = scene_config(env_overrides(run_dir.load_config(run), overrides), scenes).env
    env = _FinalPoseRecorder(GraspEnv(env_cfg))
    cfg, params, normaliser, _ = restore.load_policy_state(run, env.observation_size, env.action_size)
    networks = actor_critic.make_networks(cfg.ppo.network, env.observation_size, env.action_size, cfg.ppo.obs_clip)
    keys = policy_eval.eval_keys(seed, episodes)
    evaluator = policy_eval.make_evaluator(networks, env, max_steps, slots=policy_eval.slots_for_backend(CPU_SLOTS))
    result = jax.device_get(evaluator(params, normaliser, keys))
    first = jax.device_get(jax.jit(jax.vmap(env.reset))(keys).info)
    target_error = np.asarray(first["randomize"]["target_error"]) if "randomize" in first else np.zeros((episodes, 3))
    eps = {k: np.asarray(v) for k, v in result.episodes.items()}
    q_final = np.stack([eps[f"final_q{i + 1}"] for i in range(env.dof)], axis=-1)
    return FinalPoses(eps, q_final, first["reset"], target_error, env_cfg)


class _FinalPoseRecorder:
    """Env wrapper that copies the measured arm joints (``GraspEnv.measured_joints``) into ``info["episode"]``
    as scalar entries ``final_q1..N`` (N = the env's robot's joints; scalars, so ``fixed_seed_eval.evaluate_policy``
    keeps them per episode)."""

    def __init__(self, env: Any) -> None:
        self.env = env
        self.dof = env.robot.dof  # the env's arm (env.robot)
        self.observation_size = env.observation_size
        self.action_size = env.action_size

    def _record(self, state: Any) -> Any:
        q = self.env.measured_joints(state)
        episode = dict(state.info["episode"], **{f"final_q{i + 1}": q[i] for i in range(self.dof)})
        return state.replace(info=dict(state.info, episode=episode))

    def reset(self, rng: Any) -> Any:
        return self._record(self.env.reset(rng))

    def step(self, state: Any, action: Any) -> Any:
        return self._record(self.env.step(state, action))
