"""Evaluation of a policy during training: deterministic episodes on a fixed set of reset keys.

The SA metric and every cycle's ``eval_*`` fields come from here; the same function serves
``training.evaluation``'s offline evaluations (``python -m sagrasp_jax.evaluate``).  Episodes stop
at their first ``done`` and run in a few slots at a time on CPU (see ``evaluate_policy``).
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.sharding import Mesh, PartitionSpec

from sagrasp_jax.training.agents.ppo.actor_critic import Normaliser, Params, PPONetworks, deterministic_action
from sagrasp_jax.training.agents.ppo.rollout import Env, set_progress
from sagrasp_jax.training.sharding import BATCH_AXIS, pmean, psum, sharded


class EvalResult(NamedTuple):
    mean_return: jax.Array
    success_rate: jax.Array
    steps_to_success: jax.Array  # mean over successful episodes; NaN if none
    collision_rate: jax.Array
    timeout_rate: jax.Array  # includes episodes unfinished after max_steps
    episodes: dict[str, jax.Array]  # per episode: env metrics + "return", "steps", "finished"


def evaluate_policy(networks: PPONetworks, params: Params, normaliser: Normaliser, env: Env, keys: jax.Array,
                    max_steps: int, slots: int | None = None, axis_name: str | None = None) -> EvalResult:
    """Deterministic policy on one episode per key, reward weights frozen at p = 1, no auto-reset.

    Counting stops at each episode's first ``done`` (or after ``max_steps`` steps: unfinished,
    counted as a timeout).  ``slots`` episodes run at a time (default: all); when one ends, its
    slot takes the next episode, so with few slots finished episodes are not stepped for
    nothing while a few long ones run on — a converged policy evaluates in a fraction of the
    step budget.  The loop ends when every episode has ended.  Per-episode results come back in
    key order.  With ``axis_name`` (inside ``shard_map``) ``keys`` are this device's share and
    the rates are global.
    """
    n = keys.shape[0]
    s = n if slots is None else max(1, min(slots, n))
    starts = set_progress(jax.vmap(env.reset)(keys), 1.0)
    step_fn = jax.vmap(env.step)
    take = lambda idx: jax.tree_util.tree_map(lambda x: x[idx], starts)
    record = jax.tree_util.tree_map(jnp.zeros_like, starts.info["episode"])
    zeros, zeros_s = jnp.zeros((n,), jnp.float32), jnp.zeros((s,), jnp.float32)

    def cond(carry):
        return jnp.any(carry[1] < n)

    def body(carry):
        st, ep, ret_s, steps_s, next_ep, rec, ret, steps, finished = carry
        active = ep < n
        action = deterministic_action(networks, params, normaliser, st.obs)
        nxt = step_fn(st, action)
        ret_s = ret_s + jnp.where(active, nxt.reward, 0.0)
        steps_s = steps_s + active.astype(jnp.float32)
        done = active & (nxt.done > 0)
        end = done | (active & (steps_s >= max_steps))
        at_done, at_end = jnp.where(done, ep, n), jnp.where(end, ep, n)
        rec = jax.tree_util.tree_map(lambda r, e: r.at[at_done].set(e, mode="drop"), rec, nxt.info["episode"])
        ret = ret.at[at_end].set(ret_s, mode="drop")
        steps = steps.at[at_end].set(steps_s, mode="drop")
        finished = finished.at[at_done].set(True, mode="drop")
        # an ended slot takes the next episode (or idles when none is left)
        new_ep = next_ep + jnp.cumsum(end.astype(jnp.int32)) - 1
        load = end & (new_ep < n)
        ep = jnp.where(end, jnp.where(load, new_ep, n), ep)
        st = _select_rows(load, take(jnp.minimum(new_ep, n - 1)), nxt)
        ret_s, steps_s = jnp.where(end, 0.0, ret_s), jnp.where(end, 0.0, steps_s)
        return st, ep, ret_s, steps_s, next_ep + jnp.sum(end.astype(jnp.int32)), rec, ret, steps, finished

    init = (take(jnp.arange(s)), jnp.arange(s), zeros_s, zeros_s, jnp.asarray(s, jnp.int32), record, zeros, zeros,
            jnp.zeros((n,), bool))
    *_, rec, ret, steps, finished = jax.lax.while_loop(cond, body, init)
    success = rec["success"] * finished
    collision = rec["collision"] * finished
    timeout = jnp.where(finished, rec["timeout"], 1.0)
    n_success = psum(jnp.sum(success), axis_name)
    steps_to_success = jnp.where(n_success > 0, psum(jnp.sum(steps * success), axis_name) / jnp.maximum(n_success, 1.0),
                                 jnp.nan)
    episodes = dict(rec, success=success, collision=collision, timeout=timeout)
    episodes.update({"return": ret, "steps": steps, "finished": finished.astype(jnp.float32)})
    mean = lambda x: pmean(jnp.mean(x), axis_name)
    return EvalResult(mean_return=mean(ret), success_rate=mean(success), steps_to_success=steps_to_success,
                      collision_rate=mean(collision), timeout_rate=mean(timeout), episodes=episodes)


def _select_rows(mask: jax.Array, a: Any, b: Any) -> Any:
    """Per-row where over two pytrees whose leaves lead with the row axis."""
    return jax.tree_util.tree_map(lambda x, y: jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y), a, b)


def make_evaluator(networks: PPONetworks, env: Env, max_steps: int, mesh: Mesh | None = None,
                   slots: int | None = None) -> Callable[[Params, Normaliser, jax.Array], EvalResult]:
    """Jitted ``evaluate_policy``.  With ``mesh``, keys split over it: each device runs its share
    (``slots`` is then per device) and only the rates are combined; per-episode arrays stay split."""
    if mesh is None:
        return jax.jit(lambda params, normaliser, keys: evaluate_policy(networks, params, normaliser, env, keys,
                                                                         max_steps, slots))
    rep, shard = PartitionSpec(), PartitionSpec(BATCH_AXIS)

    def local(params: Params, normaliser: Normaliser, keys: jax.Array) -> EvalResult:
        return evaluate_policy(networks, params, normaliser, env, keys, max_steps, slots, BATCH_AXIS)

    specs = EvalResult(mean_return=rep, success_rate=rep, steps_to_success=rep, collision_rate=rep,
                       timeout_rate=rep, episodes=shard)
    return jax.jit(sharded(local, mesh, (rep, rep, shard), specs))


def slots_for_backend(cpu_slots: int) -> int | None:
    """``cpu_slots`` on CPU, where episodes run a few at a time (``evaluate_policy``'s slots); None (every
    episode at once) on accelerators."""
    return cpu_slots if jax.default_backend() == "cpu" else None


def eval_keys(seed: int, episodes: int) -> jax.Array:
    """The fixed evaluation set: one reset key per episode, from one seed."""
    return jax.random.split(jax.random.PRNGKey(seed), episodes)
