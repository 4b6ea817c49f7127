"""Training wrapper: auto-reset from *freshly sampled* episode starts (docs/task.md §2).

brax's ``AutoResetWrapper`` restores each slot's first reset state, so a slot would
replay one scene forever.  Here every env carries a *pending* start — a complete,
never-used reset state — that replaces it the step it finishes; consumed pendings are
then re-sampled.  Every start of env ``i`` comes from its own key chain
(``info["reset_key"]``, split once per sampled start), in the order it is used, so the
sequence of scenes an env plays does not depend on when the refill ran (nor on how the
batch is split over devices).

Two ways to step:

* ``step(state, action)``: one env, ``jax.vmap``-able.  It samples a new pending on
  every step where the env finished; under ``vmap`` that select still computes a reset
  for every env every step (≈ the cost of a sampling pass per env-step).
* ``batch_step(states, actions)``: the whole batch (leading axis = envs), for training.
  Per step it re-samples at most ``refill`` consumed pendings (default: 1/16 of the
  batch, rotating so none starves), and none when none is consumed — the expensive
  obstacle-feasibility sampling then costs ~1/16 of a reset per env-step.  An env that
  finishes again before its pending was refilled (short episodes, few envs) is an
  **overflow**: its pending is re-sampled before the swap, in the same batch-level
  ``lax.while_loop`` (``refill`` envs per pass; one pass in the usual case, none when
  nothing is consumed, more only while an overflow lasts).  So no scene is ever
  replayed; ``metrics["reset_overflow"]`` counts the overflow starts and
  ``metrics["reset_replays"]`` the replayed ones (0 by construction; the trainer logs
  both).
"""

from __future__ import annotations

import math
from typing import Any

import sagrasp_jax  # noqa: F401
import jax
import jax.numpy as jnp
from brax.envs.base import State

PENDING_KEYS = ("pending", "pending_fresh", "reset_key")
RESET_METRICS = ("reset_overflow", "reset_replays")


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
        zero = jnp.zeros((), state.reward.dtype)
        metrics = dict(state.metrics, **{k: zero for k in RESET_METRICS})
        return state.replace(info=info, metrics=metrics)

    def _swap(self, nxt: State, start: State, done: jax.Array) -> State:
        """Where done: ``start`` replaces the env; reward, done and the finished
        episode's metrics stay those of the finishing step."""
        swapped = _select(done, start, nxt)
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
        zero = jnp.zeros((), out.reward.dtype)
        metrics = dict(out.metrics, **{k: zero for k in RESET_METRICS})
        return out.replace(info=info, metrics=metrics)

    def _refill(self, pending: Any, keys: jax.Array, todo: jax.Array, chunk: int) -> tuple[Any, jax.Array]:
        """Re-sample the pending start of every env in ``todo`` from its own key chain, ``chunk`` envs
        per pass of a ``lax.while_loop`` (no pass when ``todo`` is empty)."""
        n = todo.shape[0]

        def one_pass(carry: tuple[Any, jax.Array, jax.Array]) -> tuple[Any, jax.Array, jax.Array]:
            pend, ks, left = carry
            idx = jnp.nonzero(left, size=chunk, fill_value=n)[0]
            split = jax.vmap(jax.random.split)(ks[jnp.minimum(idx, n - 1)])  # (chunk, 2, key)
            new_states = jax.vmap(self.env.reset)(split[:, 0])
            pend = jax.tree_util.tree_map(lambda p, s: p.at[idx].set(s, mode="drop"), pend, new_states)
            return pend, ks.at[idx].set(split[:, 1], mode="drop"), left.at[idx].set(False, mode="drop")

        pending, keys, _ = jax.lax.while_loop(lambda c: jnp.any(c[2]), one_pass, (pending, keys, todo))
        return pending, keys

    def batch_step(self, state: State, action: jax.Array) -> State:
        """The whole batch: swaps in the pending starts of the envs that finished, after re-sampling
        (one sampling pass of ``refill`` envs) the overflow plus up to ``refill`` stale pendings."""
        n = state.done.shape[0]
        refill = max(1, math.ceil(n * self.refill_fraction))
        pending, fresh, keys = state.info["pending"], state.info["pending_fresh"], state.info["reset_key"]
        nxt = jax.vmap(self.env.step)(_core(state), action)
        done = nxt.done > 0.5
        overflow = done & ~fresh  # finished again before its pending was refilled: must be served now
        # up to ``refill`` of the other consumed pendings, scanning from a rotating start so none starves
        stale = ~fresh & ~done
        offset = jnp.sum(state.info["steps"]) % n
        order = (jnp.arange(n) + offset) % n
        picked = jnp.nonzero(stale[order], size=refill, fill_value=n)[0]
        routine = jnp.zeros((n,), bool).at[jnp.where(picked < n, order[jnp.minimum(picked, n - 1)], n)].set(
            True, mode="drop")
        todo = overflow | routine
        pending, keys = self._refill(pending, keys, todo, refill)
        replays = done & ~(fresh | todo)  # a used start swapped in again: impossible by construction
        out = self._swap(nxt, pending, done)
        info = dict(out.info)
        info.update(pending=pending, pending_fresh=(fresh | todo) & ~done, reset_key=keys)
        dtype = out.reward.dtype
        metrics = dict(out.metrics, reset_overflow=overflow.astype(dtype), reset_replays=replays.astype(dtype))
        return out.replace(info=info, metrics=metrics)
