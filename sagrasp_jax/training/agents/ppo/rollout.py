"""Acting: the env API the trainer needs, batched resets and the rollout that collects transitions.

The env is vmapped over the batch (or stepped whole through a ``batched`` wrapper's
``batch_step``); actions are sampled with the policy (``actor_critic.sample_action``); the
finished episodes' metrics and the auto-reset counters come back beside the transitions.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

from typing import Any, Callable, NamedTuple, Protocol

import jax
import jax.numpy as jnp
from brax.envs.base import State
from jax.sharding import Mesh

from sagrasp_jax.training.agents.ppo.actor_critic import Normaliser, Params, PPONetworks, critic_extra_of, sample_action
from sagrasp_jax.training.sharding import batch_sharding
from sagrasp_jax.envs.auto_reset import RESET_METRICS


class Env(Protocol):
    """The env API of docs/architecture.md (single env; the trainer vmaps it)."""

    observation_size: int
    action_size: int

    def reset(self, rng: jax.Array) -> State: ...

    def step(self, state: State, action: jax.Array) -> State: ...


class Transition(NamedTuple):
    """One env step of the rollout; leading dims [T, B] after the scan."""

    obs: jax.Array
    critic_extra: jax.Array  # privileged critic inputs (env info "privileged"); width 0 without a privileged critic
    raw_action: jax.Array  # pre-tanh sample: the log-prob is taken of this
    log_prob: jax.Array
    reward: jax.Array
    done: jax.Array


RESET_STATS = RESET_METRICS  # per-step auto-reset counters (wrappers.AutoReset's), when the env reports them


def set_progress(env_state: State, progress: jax.Array) -> State:
    """Write training progress p into every env (the reward weights F_d, F_s read it)."""
    info = dict(env_state.info)
    info["progress"] = jnp.full_like(info["progress"], progress)
    return env_state.replace(info=info)


def rollout(env: Env, networks: PPONetworks, params: Params, normaliser: Normaliser, env_state: State,
            key: jax.Array, unroll_length: int, axis_name: str | None = None,
            critic_extra: int = 0) -> tuple[State, Transition, dict[str, jax.Array]]:
    """Run the vmapped, auto-resetting env for ``unroll_length`` steps.

    Returns the final env state, [T, B] transitions, and [T, B] episode metrics (env's
    ``info["episode"]`` plus ``done``) to be read only where ``done == 1``, plus the
    auto-reset counters of ``RESET_STATS`` where the env reports them.  A wrapper that
    declares ``batched = True`` is stepped through its ``batch_step`` (whole batch at once,
    so it can amortise reset sampling); otherwise ``step`` is vmapped.
    """
    step_fn = env.batch_step if getattr(env, "batched", False) else jax.vmap(env.step)

    def one_step(state: State, k: jax.Array) -> tuple[State, tuple[Transition, dict[str, jax.Array]]]:
        action, raw, log_prob = sample_action(networks, params, normaliser, state.obs, k, axis_name)
        nxt = step_fn(state, action)
        trans = Transition(obs=state.obs, critic_extra=critic_extra_of(state, critic_extra), raw_action=raw,
                           log_prob=log_prob, reward=nxt.reward, done=nxt.done)
        episode = dict(nxt.info["episode"], done=nxt.done)
        episode.update({name: nxt.metrics[name] for name in RESET_STATS if name in nxt.metrics})
        return nxt, (trans, episode)

    env_state, (data, episodes) = jax.lax.scan(one_step, env_state, jax.random.split(key, unroll_length))
    return env_state, data, episodes


def make_reset(env: Env, mesh: Mesh, compiler_options: dict[str, Any] | None = None) -> Callable[[jax.Array], State]:
    """Jitted batched reset whose output is split over the mesh (keys: [B] PRNG keys); ``compiler_options``:
    XLA's, as the trainer's other programs get them."""
    shard = batch_sharding(mesh)
    return jax.jit(lambda keys: jax.lax.with_sharding_constraint(jax.vmap(env.reset)(keys), shard),
                   compiler_options=compiler_options or None)
