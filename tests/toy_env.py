"""A tiny 2-D point-reach task with the grasp env's API, so trainer tests run in seconds.

It follows the contract of docs/architecture.md: ``reset(rng)`` / ``step(state, action)``
return ``brax.envs.base.State``; ``info`` carries ``rng``, ``progress`` (set by the trainer),
``steps`` and an ``episode`` dict of per-episode metrics (the finished episode's values on the
step where ``done == 1``).  The reward weights depend on ``progress`` like the real task, so
tests can see that the trainer writes it.  ``nan_progress`` makes the reward NaN inside a
progress window, to exercise the trainer's non-finite rollback.  ``privileged_size`` > 0 adds that many
privileged critic inputs (``info["privileged"]``: progress, time used, the obstacle, zero-padded), so
trainer tests can run a privileged critic.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import jax
import jax.numpy as jnp
from brax.envs.base import State

EPISODE_KEYS = (
    "return", "r_distance", "r_success", "r_obstacle", "success", "collision", "timeout",
    "steps", "obstacle_present", "redraws", "hit_obstacle", "hit_table",
)


def _flag(b: jax.Array) -> jax.Array:
    """0/1 in the default float dtype (float64 under x64, so scan carries keep one type)."""
    return jnp.where(b, 1.0, 0.0)


class PointReach:
    """Move a point in [-1, 1]^2 onto a random target, around an optional disc obstacle."""

    observation_size = 7
    action_size = 2

    def __init__(self, max_steps: int = 30, step_size: float = 0.15, obstacle_prob: float = 0.2,
                 nan_progress: tuple[float, float] | None = None, privileged_size: int = 0) -> None:
        self.max_steps = max_steps
        self.privileged_size = privileged_size
        self.step_size = step_size
        self.obstacle_prob = obstacle_prob
        self.nan_progress = nan_progress

    def _obs(self, pos: jax.Array, target: jax.Array, obstacle: jax.Array) -> jax.Array:
        return jnp.concatenate([pos, target, obstacle[:2], obstacle[2:3] * 0.0 + 0.1])

    def _privileged(self, info: dict) -> jax.Array:
        extra = jnp.concatenate([info["progress"][None], info["steps"][None] / self.max_steps, info["obstacle"]])
        return jnp.pad(extra, (0, max(0, self.privileged_size - extra.shape[0])))[:self.privileged_size]

    def reset(self, rng: jax.Array) -> State:
        rng, k_pos, k_tgt, k_obs, k_has = jax.random.split(rng, 5)
        pos = jax.random.uniform(k_pos, (2,), minval=-0.2, maxval=0.2)
        target = jax.random.uniform(k_tgt, (2,), minval=-0.8, maxval=0.8)
        has_obstacle = jax.random.uniform(k_has) < self.obstacle_prob
        centre = 0.5 * (pos + target) + jax.random.uniform(k_obs, (2,), minval=-0.3, maxval=0.3)
        obstacle = jnp.where(has_obstacle, jnp.append(centre, 1.0), jnp.array([0.0, 0.0, 0.0]))
        zero = jnp.zeros(())
        episode = {k: zero for k in EPISODE_KEYS}
        episode["obstacle_present"] = _flag(has_obstacle)
        info = {
            "rng": rng, "progress": zero, "steps": zero, "pos": pos, "target": target,
            "obstacle": obstacle, "acc": episode, "episode": dict(episode),
        }
        if self.privileged_size:
            info["privileged"] = self._privileged(info)
        return State(pipeline_state=None, obs=self._obs(pos, target, obstacle), reward=zero,
                     done=zero, metrics={}, info=info)

    def step(self, state: State, action: jax.Array) -> State:
        info = state.info
        p = info["progress"]
        action = jnp.clip(action, -1.0, 1.0)
        pos0, target, obstacle = info["pos"], info["target"], info["obstacle"]
        pos = jnp.clip(pos0 + self.step_size * action, -1.0, 1.0)
        d0 = jnp.linalg.norm(pos0 - target)
        d1 = jnp.linalg.norm(pos - target)
        steps = info["steps"] + 1.0
        hit = (obstacle[2] > 0) & (jnp.linalg.norm(pos - obstacle[:2]) < 0.1)
        success = (d1 < 0.08) & ~hit
        timeout = (steps >= self.max_steps) & ~hit & ~success
        r_distance = 5.0 * (d0 - d1)
        r_success = jnp.where(success, 1.0, jnp.where(hit | timeout, -1.0, 0.0))
        r_obstacle = jnp.where(hit, -1.0, 0.0)
        reward = (2.0 - p) * r_distance + (0.5 + p) * r_success + 0.5 * r_obstacle
        if self.nan_progress is not None:
            lo, hi = self.nan_progress
            reward = jnp.where((p >= lo) & (p < hi), jnp.nan, reward)
        done = _flag(hit | success | timeout)
        ep = dict(info["acc"])
        ep["return"] = ep["return"] + reward
        ep["r_distance"] = ep["r_distance"] + r_distance
        ep["r_success"] = ep["r_success"] + r_success
        ep["r_obstacle"] = ep["r_obstacle"] + r_obstacle
        ep["success"] = _flag(success)
        ep["collision"] = _flag(hit)
        ep["hit_obstacle"] = _flag(hit)
        ep["timeout"] = _flag(timeout)
        ep["steps"] = steps
        new_info = dict(info, pos=pos, steps=steps, acc=ep, episode=dict(ep))
        if self.privileged_size:
            new_info["privileged"] = self._privileged(new_info)
        return state.replace(obs=self._obs(pos, target, obstacle), reward=reward, done=done,
                             info=new_info)


class AutoReset:
    """Restart a finished env from a freshly sampled reset (the real wrapper's semantics)."""

    def __init__(self, env: PointReach) -> None:
        self.env = env
        self.observation_size = env.observation_size
        self.action_size = env.action_size

    def reset(self, rng: jax.Array) -> State:
        return self.env.reset(rng)

    def step(self, state: State, action: jax.Array) -> State:
        nxt = self.env.step(state, action)
        rng, sub = jax.random.split(nxt.info["rng"])
        fresh = self.env.reset(sub)
        done = nxt.done > 0
        pick = lambda a, b: jax.tree_util.tree_map(lambda x, y: jnp.where(done, x, y), a, b)
        info = pick(fresh.info, nxt.info)
        info["rng"] = rng
        info["progress"] = nxt.info["progress"]
        info["episode"] = nxt.info["episode"]  # the finished episode's metrics where done
        return nxt.replace(obs=jnp.where(done, fresh.obs, nxt.obs), info=info)
