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

**Learnability curriculum** (``replay > 0``, ``train.curriculum_replay``; ``batch_step`` only): every env
remembers one scene it failed, with the tries and successes of its replays since, and draws its
next start from it instead of a fresh sample with probability ``replay × 4 p̂(1 − p̂)``, where
p̂ = (successes + ½) / (tries + 1) (``learnability``): most often the scenes the policy solves
sometimes but not always, seldom those it always solves or never does.  A fresh scene it fails
replaces the remembered one unless that one is at least as learnable (a scene failed once scores
p̂ = ¼); a scene is retired after ``max_replays`` replays (``train.curriculum_max_replays``), so that
one solved about half the time, whose score never falls, cannot take an env over.  Across the batch
that is a buffer of ``num_envs`` scenes next to the fresh ones.  A replay is a new start built from the remembered ``ResetSpec`` (its own randomisation draws), never a used
state, so ``reset_replays`` stays 0; ``metrics["curriculum_starts"]`` counts the replays started and
``info["episode"]["replay"]`` marks a finished episode that was one (the training-episode window's
share of replays).
"""

from __future__ import annotations

import math
from typing import Any

import sagrasp_jax  # noqa: F401
import jax
import jax.numpy as jnp
from brax.envs.base import State

PENDING_KEYS = ("pending", "pending_fresh", "reset_key")
# the curriculum's per-env state: the remembered scene, its replays' tries and successes, its generation (a
# replacement bumps it) and the generation the running episode and the pending start were drawn from (-1: fresh)
CURRICULUM_KEYS = ("replay_spec", "replay_tries", "replay_successes", "replay_gen", "scene_gen", "pending_gen")
RESET_METRICS = ("reset_overflow", "reset_replays", "curriculum_starts")
FRESH = -1  # the generation of a freshly sampled start


def learnability(tries: Any, successes: Any) -> Any:
    """p̂(1 − p̂) of a scene solved ``successes`` times in ``tries`` (p̂ = (s + ½) / (n + 1)): 0.1875 after one
    failure, 0.25 at one success in two, → 0 for a scene always or never solved."""
    p = (successes + 0.5) / (tries + 1.0)
    return p * (1.0 - p)


FAILED_ONCE = learnability(1.0, 0.0)  # 0.1875: what a freshly failed scene scores


def _select(mask: jax.Array, a: Any, b: Any) -> Any:
    """Per-env where over two pytrees whose leaves have the env axis first."""

    def pick(x: jax.Array, y: jax.Array) -> jax.Array:
        m = jnp.reshape(mask, mask.shape + (1,) * (x.ndim - mask.ndim))
        return jnp.where(m, x, y)

    return jax.tree_util.tree_map(pick, a, b)


def _core(state: State) -> State:
    """The wrapped env's own state: without the wrapper's info keys."""
    info = {k: v for k, v in state.info.items() if k not in PENDING_KEYS + CURRICULUM_KEYS}
    return state.replace(info=info)


class AutoReset:
    """Wrap a GraspEnv for training (see module doc)."""

    batched = True  # the trainer may call batch_step instead of vmapping step

    def __init__(self, env: Any, refill_fraction: float = 1 / 16, replay: float = 0.0, max_replays: int = 8):
        if not 0.0 <= replay <= 1.0:
            raise ValueError(f"replay={replay!r}: the curriculum's replay scale is a probability in [0, 1]")
        if max_replays < 1:
            raise ValueError(f"max_replays={max_replays!r}: a remembered scene needs at least one replay")
        if replay and not (hasattr(env, "sample_spec") and hasattr(env, "reset_to")):
            raise ValueError(f"the learnability curriculum (replay={replay}) needs an env with sample_spec and reset_to "
                             f"(GraspEnv); {type(env).__name__} has not")
        self.env = env
        self.observation_size = env.observation_size
        self.action_size = env.action_size
        self.refill_fraction = refill_fraction
        self.replay = replay
        self.max_replays = max_replays

    def reset(self, rng: jax.Array) -> State:
        k_state, k_pending, k_next = jax.random.split(rng, 3)
        # both starts through one copy of the scene sampler (a 2-step loop, not two inlined resets): the same
        # states, and the batched reset compiles in ≈ 3.6 s instead of 6.4 s on 2 cores
        starts = jax.lax.map(self.env.reset, jnp.stack([k_state, k_pending]))
        state, pending = (jax.tree_util.tree_map(lambda x, i=i: x[i], starts) for i in (0, 1))
        info = dict(state.info)
        info["pending"] = pending
        info["pending_fresh"] = jnp.ones((), bool)
        info["reset_key"] = k_next
        zero = jnp.zeros((), state.reward.dtype)
        if self.replay:
            fresh = jnp.asarray(FRESH, jnp.int32)
            info.update(replay_spec=state.info["reset"], replay_tries=zero, replay_successes=zero,
                        replay_gen=fresh, scene_gen=fresh, pending_gen=fresh,
                        episode=dict(state.info["episode"], replay=zero))
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
        if self.replay:  # the curriculum acts in batch_step; here its state is carried and every start is fresh
            info.update({k: state.info[k] for k in CURRICULUM_KEYS})
            info["scene_gen"] = jnp.where(done, FRESH, state.info["scene_gen"])
            info["pending_gen"] = jnp.asarray(FRESH, jnp.int32)
            info["episode"] = dict(out.info["episode"], replay=(state.info["scene_gen"] != FRESH).astype(zero.dtype))
        metrics = dict(out.metrics, **{k: zero for k in RESET_METRICS})
        return out.replace(info=info, metrics=metrics)

    def _start(self, key: jax.Array, slot_spec: Any, p_replay: jax.Array, slot_gen: jax.Array) -> tuple[State, jax.Array]:
        """One env's next start under the curriculum: its remembered scene with probability ``p_replay``, else a
        fresh one (drawn either way, from the same key as ``reset``); returns the state and its generation."""
        spec, rng = self.env.sample_spec(key)
        replay = jax.random.uniform(jax.random.fold_in(key, 1)) < p_replay
        spec = jax.tree_util.tree_map(lambda r, f: jnp.where(replay, r, f), slot_spec, spec)
        return self.env.reset_to(spec, rng), jnp.where(replay, slot_gen, FRESH)

    def _refill(self, pending: Any, keys: jax.Array, gens: jax.Array | None, todo: jax.Array, chunk: int,
                curriculum: tuple[Any, jax.Array, jax.Array] | None) -> tuple[Any, jax.Array, jax.Array | None]:
        """Re-sample the pending start of every env in ``todo`` from its own key chain, ``chunk`` envs
        per pass of a ``lax.while_loop`` (no pass when ``todo`` is empty).  ``curriculum`` (each env's
        remembered scene, replay probability and generation) may put a remembered scene in a fresh one's
        place; ``gens`` are the pending starts' generations (None without a curriculum)."""
        n = todo.shape[0]

        def one_pass(carry: tuple[Any, jax.Array, Any, jax.Array]) -> tuple[Any, jax.Array, Any, jax.Array]:
            pend, ks, gs, left = carry
            idx = jnp.nonzero(left, size=chunk, fill_value=n)[0]
            safe = jnp.minimum(idx, n - 1)
            split = jax.vmap(jax.random.split)(ks[safe])  # (chunk, 2, key)
            if curriculum is None:
                new_states = jax.vmap(self.env.reset)(split[:, 0])
            else:
                slot_spec, p_replay, slot_gen = curriculum
                new_states, new_gens = jax.vmap(self._start)(
                    split[:, 0], jax.tree_util.tree_map(lambda x: x[safe], slot_spec), p_replay[safe], slot_gen[safe])
                gs = gs.at[idx].set(new_gens, mode="drop")
            pend = jax.tree_util.tree_map(lambda p, s: p.at[idx].set(s, mode="drop"), pend, new_states)
            return pend, ks.at[idx].set(split[:, 1], mode="drop"), gs, left.at[idx].set(False, mode="drop")

        pending, keys, gens, _ = jax.lax.while_loop(lambda c: jnp.any(c[3]), one_pass, (pending, keys, gens, todo))
        return pending, keys, gens

    def _held(self, gen: jax.Array, tries: jax.Array) -> jax.Array:
        """Whether an env remembers a scene it may still replay (its first try was the failure itself)."""
        return (gen != FRESH) & (tries <= self.max_replays)

    def _remember(self, info: dict[str, Any], done: jax.Array, success: jax.Array) -> dict[str, Any]:
        """The curriculum's memory after this step's finished episodes: a replay of the remembered scene counts
        as a try (and a success); a fresh scene that failed replaces it unless it is at least as learnable and
        not yet retired (replayed ``max_replays`` times)."""
        gen, scene_gen = info["replay_gen"], info["scene_gen"]
        replayed = scene_gen != FRESH
        counted = done & replayed & (scene_gen == gen)  # a replay of an older remembered scene no longer counts
        tries = info["replay_tries"] + counted
        successes = info["replay_successes"] + (counted & success)
        score = jnp.where(self._held(gen, tries), learnability(tries, successes), -1.0)
        replace = done & ~replayed & ~success & (score <= FAILED_ONCE)
        return {"replay_spec": _select(replace, info["reset"], info["replay_spec"]),
                "replay_tries": jnp.where(replace, 1.0, tries).astype(tries.dtype),
                "replay_successes": jnp.where(replace, 0.0, successes).astype(tries.dtype),
                "replay_gen": gen + replace.astype(gen.dtype)}

    def batch_step(self, state: State, action: jax.Array) -> State:
        """The whole batch: swaps in the pending starts of the envs that finished, after re-sampling
        (one sampling pass of ``refill`` envs) the overflow plus up to ``refill`` stale pendings."""
        n = state.done.shape[0]
        refill = max(1, math.ceil(n * self.refill_fraction))
        pending, fresh, keys = state.info["pending"], state.info["pending_fresh"], state.info["reset_key"]
        nxt = jax.vmap(self.env.step)(_core(state), action)
        done = nxt.done > 0.5
        memory, curriculum, gens = {}, None, None
        if self.replay:
            memory = self._remember(state.info, done, nxt.info["episode"]["success"] > 0.5)
            held = self._held(memory["replay_gen"], memory["replay_tries"])
            p_replay = jnp.where(held, 4.0 * self.replay * learnability(memory["replay_tries"],
                                                                         memory["replay_successes"]), 0.0)
            curriculum, gens = (memory["replay_spec"], p_replay, memory["replay_gen"]), state.info["pending_gen"]
        overflow = done & ~fresh  # finished again before its pending was refilled: must be served now
        # up to ``refill`` of the other consumed pendings, scanning from a rotating start so none starves
        stale = ~fresh & ~done
        offset = jnp.sum(state.info["steps"]) % n
        order = (jnp.arange(n) + offset) % n
        picked = jnp.nonzero(stale[order], size=refill, fill_value=n)[0]
        routine = jnp.zeros((n,), bool).at[jnp.where(picked < n, order[jnp.minimum(picked, n - 1)], n)].set(
            True, mode="drop")
        todo = overflow | routine
        pending, keys, gens = self._refill(pending, keys, gens, todo, refill, curriculum)
        replays = done & ~(fresh | todo)  # a used start swapped in again: impossible by construction
        out = self._swap(nxt, pending, done)
        info = dict(out.info)
        info.update(pending=pending, pending_fresh=(fresh | todo) & ~done, reset_key=keys)
        dtype = out.reward.dtype
        starts = jnp.zeros((n,), dtype)
        if self.replay:
            info.update(memory, pending_gen=gens, scene_gen=jnp.where(done, gens, state.info["scene_gen"]))
            info["episode"] = dict(out.info["episode"], replay=(state.info["scene_gen"] != FRESH).astype(dtype))
            starts = (done & (gens != FRESH)).astype(dtype)
        metrics = dict(out.metrics, reset_overflow=overflow.astype(dtype), reset_replays=replays.astype(dtype),
                       curriculum_starts=starts)
        return out.replace(info=info, metrics=metrics)
