"""The actor-critic: policy and value networks, their optimizer and the policy's action maths.

brax supplies the networks, the tanh-Gaussian distribution and the running observation
statistics; this module builds them for the task (normalised, clipped observations; an
optional privileged critic), builds an optimizer whose state holds no learning rate (the lr is an argument of every
step, owned by the host's lr schedule: ``lr_schedule``), and samples actions with device-count-independent noise.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax
from brax.envs.base import State
from brax.training import networks as brax_networks
from brax.training.acme import running_statistics
from brax.training.agents.ppo import networks as ppo_networks
from brax.training.distribution import TanhBijector
from flax import linen

from sagrasp_jax.task.config import ACTIVATIONS, NetworkConfig, PPOConfig
from sagrasp_jax.training.sharding import batch_normal

Normaliser = running_statistics.RunningStatisticsState
PPONetworks = ppo_networks.PPONetworks

_ACTIVATIONS: dict[str, Callable[[jax.Array], jax.Array]] = {name: getattr(linen, name) for name in ACTIVATIONS}


class Params(NamedTuple):
    policy: Any
    value: Any


class TrainingState(NamedTuple):
    """What SGD changes and what an SA rejection restores."""

    params: Params
    opt_state: optax.OptState
    normaliser: Normaliser



def make_networks(net: NetworkConfig, obs_size: int, action_size: int, obs_clip: float,
                  critic_extra: int = 0) -> PPONetworks:
    """brax PPO networks whose preprocessor normalises with the running stats and clips (docs/task.md §2).

    With ``critic_extra`` > 0 the value network also reads that many privileged inputs appended
    to the observation (already scaled by the env, not normalised): an asymmetric actor-critic
    whose policy — all that is exported — never needs them."""
    if net.activation not in _ACTIVATIONS:
        raise ValueError(f"activation {net.activation!r} not one of {', '.join(_ACTIVATIONS)}")
    preprocess = functools.partial(_normalise, obs_clip=obs_clip)
    nets = ppo_networks.make_ppo_networks(
        obs_size,
        action_size,
        preprocess_observations_fn=preprocess,
        policy_hidden_layer_sizes=tuple(net.policy_hidden),
        value_hidden_layer_sizes=tuple(net.value_hidden),
        activation=_ACTIVATIONS[net.activation],
    )
    if not critic_extra:
        return nets
    value = brax_networks.make_value_network(
        obs_size + critic_extra,
        preprocess_observations_fn=functools.partial(_normalise_head, obs_clip=obs_clip, obs_size=obs_size),
        hidden_layer_sizes=tuple(net.value_hidden),
        activation=_ACTIVATIONS[net.activation],
        kernel_init=jax.nn.initializers.lecun_uniform(),
    )
    return nets.replace(value_network=value)


def _normalise(obs: jax.Array, normaliser: Normaliser, obs_clip: float) -> jax.Array:
    return running_statistics.normalize(obs, normaliser, max_abs_value=obs_clip)


def _normalise_head(x: jax.Array, normaliser: Normaliser, obs_clip: float, obs_size: int) -> jax.Array:
    """Normalise the observation part of a critic input; the privileged tail passes unchanged."""
    return jnp.concatenate([_normalise(x[..., :obs_size], normaliser, obs_clip), x[..., obs_size:]], axis=-1)


def critic_input(obs: jax.Array, critic_extra: jax.Array) -> jax.Array:
    """What the value network reads: the observation and the privileged inputs (possibly none)."""
    return jnp.concatenate([obs, critic_extra.astype(obs.dtype)], axis=-1)


def critic_extra_of(state: State, width: int) -> jax.Array:
    """The env's privileged critic inputs (``info["privileged"]``), or a width-0 array."""
    if width:
        return state.info["privileged"]
    return jnp.zeros(state.obs.shape[:-1] + (0,), state.obs.dtype)


def make_optimizer(cfg: PPOConfig) -> optax.GradientTransformation:
    """Adam's direction behind grad-norm clipping, without its lr: ``apply_learning_rate`` scales the updates by
    the lr the jitted call was given, so the optimizer state holds no lr for anyone to read or write.  Adam's
    constants stay float32 state entries (``inject_hyperparams``), as in the optimizer before
    (``inject_hyperparams(optax.adam)``): read at run time, not folded into the program as constants, so a run
    computes what it computed then, bit for bit."""
    return optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm),
                       optax.inject_hyperparams(_adam_direction)(b1=0.9, b2=0.999, eps=1e-8, eps_root=0.0))


def _adam_direction(b1: float, b2: float, eps: float, eps_root: float) -> optax.GradientTransformation:
    """``optax.adam`` without its last step (× −lr): a chain, so its state sits where ``optax.adam``'s did."""
    return optax.chain(optax.scale_by_adam(b1=b1, b2=b2, eps=eps, eps_root=eps_root))


def apply_learning_rate(updates: Any, lr: jax.Array) -> Any:
    """``updates`` × −lr: optax.adam's last step (``scale_by_learning_rate``'s ``scale(-1 * lr)``), bit for bit."""
    step = -1 * lr
    return jax.tree_util.tree_map(lambda g: step * g, updates)


def init_policy(key: jax.Array, networks: PPONetworks, obs_size: int) -> tuple[Params, Normaliser]:
    """Fresh policy and value parameters and an empty observation normaliser (no optimizer)."""
    k_policy, k_value = jax.random.split(key)
    params = Params(policy=networks.policy_network.init(k_policy), value=networks.value_network.init(k_value))
    return params, running_statistics.init_state(jnp.zeros((obs_size,), jnp.float32))


def init_training_state(key: jax.Array, networks: PPONetworks, optimizer: optax.GradientTransformation,
                        obs_size: int) -> TrainingState:
    params, normaliser = init_policy(key, networks, obs_size)
    return TrainingState(params=params, opt_state=optimizer.init(params), normaliser=normaliser)


# XLA options of a program that runs once per run: LLVM at -O0 compiles the initial state's program in 0.8 s of CPU
# instead of 4.5 on the 2-core VM (issue 55) and its run time does not matter.  Only where the outputs stay the
# same to the bit: the initial state does (tests/test_ppo.py compares it with the eager one); the first batched
# reset does not (obstacle sizes and observations moved by an ulp at -O1), so it keeps XLA's default.
RUN_ONCE_COMPILE = {"xla_backend_optimization_level": 0}


def jitted_init_training_state(networks: PPONetworks, optimizer: optax.GradientTransformation, obs_size: int,
                               compiler_options: dict[str, Any] | None = None) -> Callable[[jax.Array], TrainingState]:
    """``init_training_state`` as one jitted program of the key: eagerly it compiles ~40 small ops one by one
    (≈ 1 s cold).  Once placed on a device its state is the eager one bit for bit (the normaliser's
    ``std_eps``, a Python float eagerly, comes out a weakly typed array); compiled with ``RUN_ONCE_COMPILE``
    and ``compiler_options`` (the trainer's other XLA options)."""
    return jax.jit(lambda key: init_training_state(key, networks, optimizer, obs_size),
                   compiler_options={**(compiler_options or {}), **RUN_ONCE_COMPILE})


def sample_action(networks: PPONetworks, params: Params, normaliser: Normaliser, obs: jax.Array,
                  key: jax.Array, axis_name: str | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(action in [-1, 1], pre-tanh sample, its log-prob under the tanh-Gaussian)."""
    dist = networks.parametric_action_distribution
    logits = networks.policy_network.apply(normaliser, params.policy, obs)
    gauss = dist.create_dist(logits)
    raw = batch_normal(key, gauss.loc.shape, axis_name) * gauss.scale + gauss.loc  # brax's sample_no_postprocessing
    return dist.postprocess(raw), raw, dist.log_prob(logits, raw)


def deterministic_action(networks: PPONetworks, params: Params, normaliser: Normaliser,
                         obs: jax.Array) -> jax.Array:
    logits = networks.policy_network.apply(normaliser, params.policy, obs)
    return networks.parametric_action_distribution.mode(logits)


def gaussian_entropy_from_logits(networks: PPONetworks, logits: jax.Array) -> jax.Array:
    """Closed-form entropy of the pre-tanh Gaussian, summed over action dims (SA temperature)."""
    scale = networks.parametric_action_distribution.create_dist(logits).scale
    return jnp.sum(0.5 * jnp.log(2.0 * jnp.pi * jnp.e) + jnp.log(scale), axis=-1)


def mean_policy_entropy(networks: PPONetworks, params: Params, normaliser: Normaliser,
                        obs: jax.Array) -> jax.Array:
    logits = networks.policy_network.apply(normaliser, params.policy, obs)
    return jnp.mean(gaussian_entropy_from_logits(networks, logits))


def tanh_gaussian_entropy(networks: PPONetworks, logits: jax.Array, key: jax.Array,
                          axis_name: str | None = None) -> jax.Array:
    """brax's one-sample estimate of the tanh-Gaussian entropy (``dist.entropy``), per row."""
    gauss = networks.parametric_action_distribution.create_dist(logits)
    sample = batch_normal(key, gauss.loc.shape, axis_name) * gauss.scale + gauss.loc
    return jnp.sum(gauss.entropy() + TanhBijector().forward_log_det_jacobian(sample), axis=-1)

