"""Training wrapper: auto-reset from *freshly sampled* episode starts (SPEC §2).

brax's ``AutoResetWrapper`` restores each slot's first reset state, so a slot would
replay one scene forever.  Here every env carries a *pending* start — a complete,
never-used reset state — that replaces it the step it finishes; consumed pendings are
then re-sampled.

Two ways to step:

* ``step(state, action)``: one env, ``jax.vmap``-able.  It samples a new pending on
  every step where the env finished; under ``vmap`` that select still computes a reset
  for every env every step (≈ the cost of a sampling pass per env-step).
* ``batch_step(states, actions)``: the whole batch (leading axis = envs), for training.
  At most ``refill`` consumed pendings are re-sampled per step (default: 1/16 of the
  batch, rotating so none starves), and none when no env finished — the expensive
  obstacle-feasibility sampling then costs ~1/16 of a reset per env-step.  An env that
  finishes again before its pending was refilled would replay it; that is counted in
  ``metrics["stale_resets"]`` (0 in practice: episodes are longer than the refill lag).
"""

from __future__ import annotations

import math
from typing import Any

import sagrasp_jax  # noqa: F401
import jax
import jax.numpy as jnp
from brax.envs.base import State

PENDING_KEYS = ("pending", "pending_fresh", "reset_key")


def _select(mask: jax.Array, a: Any, b: Any) -> Any:
    """Per-env where over two pytrees whose leaves have the env axis first."""

    def pick(x: jax.Array, y: jax.Array) -> jax.Array:
        m = jnp.reshape(mask, mask.shape + (1,) * (x.ndim - mask.ndim))
        return jnp.where(m, x, y)

    return jax.tree_util.tree_map(pick, a, b)


def _core(state: State) -> State:
    info = {k: v for k, v in state.info.items() if k not in PENDING_KEYS}
    return state.replace(info=info)


class AutoReset:
    """Wrap a GraspEnv for training (see module doc)."""

    batched = True  # the trainer may call batch_step instead of vmapping step

    def __init__(self, env: Any, refill_fraction: float = 1 / 16):
        self.env = env
        self.observation_size = env.observation_size
        self.action_size = env.action_size
        self.refill_fraction = refill_fraction

    def reset(self, rng: jax.Array) -> State:
        k_state, k_pending, k_next = jax.random.split(rng, 3)
        state = self.env.reset(k_state)
        info = dict(state.info)
        info["pending"] = self.env.reset(k_pending)
        info["pending_fresh"] = jnp.ones((), bool)
        info["reset_key"] = k_next
        metrics = dict(state.metrics, stale_resets=jnp.zeros(()))
        return state.replace(info=info, metrics=metrics)

    def _swap(self, nxt: State, pending: State, done: jax.Array) -> State:
        """Where done: the pending start replaces the env; reward, done and the finished
        episode's metrics stay those of the finishing step."""
        swapped = _select(done, pending, nxt)
        info = dict(swapped.info)
        info["episode"] = nxt.info["episode"]
        info["progress"] = nxt.info["progress"]
        return swapped.replace(reward=nxt.reward, done=nxt.done, info=info)

    def step(self, state: State, action: jax.Array) -> State:
        """One env (vmap-able): fresh pending sampled wherever the env finished."""
        pending = state.info["pending"]
        nxt = self.env.step(_core(state), action)
        done = nxt.done > 0.5
        out = self._swap(nxt, pending, done)
        k_new, k_next = jax.random.split(state.info["reset_key"])
        fresh_pending = self.env.reset(k_new)
        info = dict(out.info)
        info["pending"] = _select(done, fresh_pending, pending)
        info["pending_fresh"] = jnp.ones((), bool)
        info["reset_key"] = jnp.where(done, k_next, state.info["reset_key"])
        metrics = dict(out.metrics, stale_resets=jnp.zeros(()))
        return out.replace(info=info, metrics=metrics)

    def batch_step(self, state: State, action: jax.Array) -> State:
        """The whole batch; refills at most ``refill`` consumed pendings per step."""
        n = state.done.shape[0]
        refill = max(1, math.ceil(n * self.refill_fraction))
        pending, fresh, keys = state.info["pending"], state.info["pending_fresh"], state.info["reset_key"]
        nxt = jax.vmap(self.env.step)(_core(state), action)
        done = nxt.done > 0.5
        stale = done & ~fresh
        out = self._swap(nxt, pending, done)
        consumed = ~fresh | done
        # rotate the scan start so that a backlog is served round-robin
        offset = jnp.sum(state.info["steps"]) % n
        order = (jnp.arange(n) + offset) % n
        picked = jnp.nonzero(consumed[order], size=refill, fill_value=n)[0]
        idx = jnp.where(picked < n, order[jnp.minimum(picked, n - 1)], n)

        def do_refill(args: tuple[Any, jax.Array, jax.Array]) -> tuple[Any, jax.Array, jax.Array]:
            pend, fr, ks = args
            safe = jnp.minimum(idx, n - 1)
            split = jax.vmap(jax.random.split)(ks[safe])  # (refill, 2, key)
            new_states = jax.vmap(self.env.reset)(split[:, 0])
            pend = jax.tree_util.tree_map(lambda p, s: p.at[idx].set(s, mode="drop"), pend, new_states)
            fr = fr.at[idx].set(True, mode="drop")
            ks = ks.at[idx].set(split[:, 1], mode="drop")
            return pend, fr, ks

        fresh = fresh & ~done
        pending, fresh, keys = jax.lax.cond(jnp.any(consumed), do_refill, lambda a: a, (pending, fresh, keys))
        info = dict(out.info)
        info.update(pending=pending, pending_fresh=fresh, reset_key=keys)
        metrics = dict(out.metrics, stale_resets=stale.astype(out.reward.dtype))
        return out.replace(info=info, metrics=metrics)
