"""PPO's losses: GAE, the clipped surrogate with value and entropy terms, and their gradients.

As brax's ``losses.py``: pure functions of a flattened batch.  With ``axis_name`` the batch
is this device's share of a global batch; the advantage statistics and the gradients are
global (``sharding.pmean``).
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

from typing import NamedTuple

import jax
import jax.numpy as jnp

from sagrasp_jax.task.config import PPOConfig
from sagrasp_jax.training.agents.ppo.actor_critic import (
    Normaliser, Params, PPONetworks, critic_input, tanh_gaussian_entropy,
)
from sagrasp_jax.training.agents.ppo.rollout import Transition
from sagrasp_jax.training.sharding import pmean


class Batch(NamedTuple):
    """Flattened training data for the minibatch epochs."""

    obs: jax.Array
    critic_extra: jax.Array
    raw_action: jax.Array
    log_prob: jax.Array
    advantage: jax.Array
    target: jax.Array  # GAE return, the value target
    # kl-adaptive only: log-probs of the actions under the iteration's pre-SGD policy and updated
    # normaliser, the reference of the KL the lr rule reads (``sgd_epochs``); None otherwise
    kl_log_prob: jax.Array | None = None


def compute_gae(rewards: jax.Array, values: jax.Array, dones: jax.Array, bootstrap_value: jax.Array,
                gamma: float, lam: float) -> tuple[jax.Array, jax.Array]:
    """Standard GAE over [T, B]: A_t = δ_t + γλ(1-d_t)A_{t+1}; returns (advantages, A + V).

    ``dones[t]`` ends the episode *at* step t (every end is terminal in this task, timeouts
    included), so nothing is bootstrapped across it.
    """
    next_values = jnp.concatenate([values[1:], bootstrap_value[None]], axis=0)
    not_done = 1.0 - dones
    deltas = rewards + gamma * not_done * next_values - values

    def backward(acc: jax.Array, xs: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
        delta, nd = xs
        acc = delta + gamma * lam * nd * acc
        return acc, acc

    _, advantages = jax.lax.scan(backward, jnp.zeros_like(bootstrap_value), (deltas, not_done), reverse=True)
    return advantages, advantages + values


def ppo_loss(params: Params, normaliser: Normaliser, batch: Batch, key: jax.Array, networks: PPONetworks,
             cfg: PPOConfig, axis_name: str | None = None) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Clipped surrogate + value MSE (SB3 weighting) − entropy bonus (brax tanh-corrected estimate).

    With ``axis_name`` the batch is this device's share of a global batch: the advantage
    normalisation uses the global mean and std; the returned loss is the local mean (the
    caller averages gradients over devices)."""
    dist = networks.parametric_action_distribution
    logits = networks.policy_network.apply(normaliser, params.policy, batch.obs)
    log_prob = dist.log_prob(logits, batch.raw_action)
    log_ratio = log_prob - batch.log_prob
    ratio = jnp.exp(log_ratio)
    adv = batch.advantage
    if cfg.normalize_advantages:
        mean = pmean(jnp.mean(adv), axis_name)
        std = jnp.sqrt(pmean(jnp.mean(jnp.square(adv - mean)), axis_name))
        adv = (adv - mean) / (std + 1e-8)
    clipped = jnp.clip(ratio, 1.0 - cfg.clip_eps, 1.0 + cfg.clip_eps)
    policy_loss = -jnp.mean(jnp.minimum(ratio * adv, clipped * adv))
    value = networks.value_network.apply(normaliser, params.value, critic_input(batch.obs, batch.critic_extra))
    value_loss = jnp.mean(jnp.square(batch.target - value))
    entropy = jnp.mean(tanh_gaussian_entropy(networks, logits, key, axis_name))
    total = policy_loss + cfg.value_coef * value_loss - cfg.entropy_coef * entropy
    metrics = {
        "loss": total,
        "policy_loss": policy_loss,
        "value_loss": value_loss,
        "entropy_bonus": entropy,
        "approx_kl": jnp.mean((ratio - 1.0) - log_ratio),
        "clip_fraction": jnp.mean((jnp.abs(ratio - 1.0) > cfg.clip_eps).astype(jnp.float32)),
    }
    if batch.kl_log_prob is not None:  # KL(π_start ‖ π_θ) of this iteration's SGD so far (k3 estimator)
        step = jax.lax.stop_gradient(log_prob - batch.kl_log_prob)
        metrics["step_kl"] = jnp.mean(jnp.expm1(step) - step)
    return total, metrics


def loss_and_grad(params: Params, normaliser: Normaliser, batch: Batch, key: jax.Array,
                  networks: PPONetworks, cfg: PPOConfig,
                  axis_name: str | None = None) -> tuple[tuple[jax.Array, dict[str, jax.Array]], Params]:
    """Loss and gradients of the (global) batch: local values averaged over ``axis_name``."""
    (loss, metrics), grads = jax.value_and_grad(ppo_loss, has_aux=True)(params, normaliser, batch, key, networks,
                                                                       cfg, axis_name)
    return (pmean(loss, axis_name), pmean(metrics, axis_name)), pmean(grads, axis_name)


def make_batch(networks: PPONetworks, params: Params, normaliser: Normaliser, data: Transition,
               final_obs: jax.Array, cfg: PPOConfig, final_extra: jax.Array | None = None) -> Batch:
    """GAE with the pre-update value net, then flatten [T, B] → [T·B]."""
    if final_extra is None:
        final_extra = jnp.zeros(final_obs.shape[:-1] + (0,), final_obs.dtype)
    values = networks.value_network.apply(normaliser, params.value, critic_input(data.obs, data.critic_extra))
    bootstrap = networks.value_network.apply(normaliser, params.value, critic_input(final_obs, final_extra))
    advantages, targets = compute_gae(data.reward, values, data.done, bootstrap, cfg.gamma, cfg.gae_lambda)
    flat = lambda x: x.reshape((x.shape[0] * x.shape[1],) + x.shape[2:])  # (explicit: width-0 arrays too)
    return Batch(obs=flat(data.obs), critic_extra=flat(data.critic_extra), raw_action=flat(data.raw_action),
                 log_prob=flat(data.log_prob),
                 advantage=flat(advantages), target=flat(targets))

