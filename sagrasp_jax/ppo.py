"""Brax-style PPO as small pure functions over typed NamedTuples.

brax 0.14.2's ``ppo.train`` does not run on jax >= 0.10, so the loop lives here; brax supplies
only the networks, the tanh-Gaussian distribution and the running observation statistics.
A PPO iteration (rollout, normaliser update, GAE, minibatch epochs) is a pure function;
``make_cycle`` jits a ``lax.while_loop`` of several of them (a cycle's worth) so the host syncs
once per cycle; the host sets the training progress and the learning rate (per iteration, or
between calls), or the ``kl-adaptive`` schedule adapts it after every minibatch
(``sagrasp_jax.lr_schedule``).

Data parallelism: the env batch is split over a 1-D ``Mesh`` of devices — the local ones, or
every process's under ``jax.distributed`` — and params and optimizer state are replicated.
Each device runs its share inside ``shard_map``: it steps and auto-resets its own envs, and
the normaliser statistics, advantage statistics, gradients and metrics are averaged over the
mesh (``axis_name``), so the maths is that of one global batch.  Sampling noise is drawn for
the global batch and sliced, so the first iteration's gradients do not depend on the device
count; on one device nothing changes.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import functools
import math
from typing import Any, Callable, NamedTuple, Protocol

import jax
import jax.numpy as jnp
import numpy as np
import optax
from brax.envs.base import State
from brax.training.acme import running_statistics
from brax.training import networks as brax_networks
from brax.training.agents.ppo import networks as ppo_networks
from brax.training.distribution import TanhBijector
from flax import linen
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from sagrasp_jax import lr_schedule
from sagrasp_jax.config import ACTIVATIONS, NetworkConfig, PPOConfig

Normaliser = running_statistics.RunningStatisticsState
PPONetworks = ppo_networks.PPONetworks
BATCH_AXIS = "batch"

_ACTIVATIONS: dict[str, Callable[[jax.Array], jax.Array]] = {name: getattr(linen, name) for name in ACTIVATIONS}


class Env(Protocol):
    """The env API of docs/architecture.md (single env; the trainer vmaps it)."""

    observation_size: int
    action_size: int

    def reset(self, rng: jax.Array) -> State: ...

    def step(self, state: State, action: jax.Array) -> State: ...


class Params(NamedTuple):
    policy: Any
    value: Any


class TrainingState(NamedTuple):
    """What SGD changes and what an SA rejection restores."""

    params: Params
    opt_state: optax.OptState
    normaliser: Normaliser


class Transition(NamedTuple):
    """One env step of the rollout; leading dims [T, B] after the scan."""

    obs: jax.Array
    critic_extra: jax.Array  # privileged critic inputs (env info "privileged"); width 0 without a privileged critic
    raw_action: jax.Array  # pre-tanh sample: the log-prob is taken of this
    log_prob: jax.Array
    reward: jax.Array
    done: jax.Array


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


class EvalResult(NamedTuple):
    mean_return: jax.Array
    success_rate: jax.Array
    steps_to_success: jax.Array  # mean over successful episodes; NaN if none
    collision_rate: jax.Array
    timeout_rate: jax.Array  # includes episodes unfinished after max_steps
    episodes: dict[str, jax.Array]  # per episode: env metrics + "return", "steps", "finished"


# --------------------------------------------------------------------------- construction

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


def make_optimizer(cfg: PPOConfig, learning_rate: float) -> optax.GradientTransformation:
    """Adam behind grad-norm clipping; the lr is a state entry so the host can change it."""
    return optax.chain(
        optax.clip_by_global_norm(cfg.max_grad_norm),
        optax.inject_hyperparams(optax.adam)(learning_rate=learning_rate),
    )


def init_training_state(key: jax.Array, networks: PPONetworks, optimizer: optax.GradientTransformation,
                        obs_size: int) -> TrainingState:
    k_policy, k_value = jax.random.split(key)
    params = Params(policy=networks.policy_network.init(k_policy), value=networks.value_network.init(k_value))
    normaliser = running_statistics.init_state(jnp.zeros((obs_size,), jnp.float32))
    return TrainingState(params=params, opt_state=optimizer.init(params), normaliser=normaliser)


def get_learning_rate(opt_state: optax.OptState) -> float:
    return float(opt_state[1].hyperparams["learning_rate"])


def with_learning_rate(opt_state: optax.OptState, lr: jax.Array) -> optax.OptState:
    """``set_learning_rate`` inside a traced function (``lr`` a traced scalar)."""
    inject = opt_state[1]
    old = inject.hyperparams["learning_rate"]
    hyper = dict(inject.hyperparams, learning_rate=jnp.asarray(lr, dtype=old.dtype))
    return (opt_state[0], inject._replace(hyperparams=hyper), *opt_state[2:])


def learning_rate_of(opt_state: optax.OptState) -> jax.Array:
    """The Adam lr in ``opt_state`` as an array (traceable)."""
    return opt_state[1].hyperparams["learning_rate"]


def set_learning_rate(opt_state: optax.OptState, lr: float) -> optax.OptState:
    """Return ``opt_state`` with a new Adam lr (the optimizer built by ``make_optimizer``)."""
    inject = opt_state[1]
    old = inject.hyperparams["learning_rate"]
    hyper = dict(inject.hyperparams, learning_rate=jnp.asarray(lr, dtype=old.dtype))
    if isinstance(old, jax.Array):  # keep it where the rest of the state lives (replicated)
        hyper["learning_rate"] = jax.device_put(np.asarray(lr, dtype=old.dtype), old.sharding)
    return (opt_state[0], inject._replace(hyperparams=hyper), *opt_state[2:])


# --------------------------------------------------------------------------- sharding

def make_mesh(devices: list[jax.Device] | None = None) -> Mesh:
    """1-D mesh over ``devices`` (default: every device of every process; the local ones without
    ``jax.distributed``)."""
    return Mesh(np.array(devices if devices is not None else jax.devices()), (BATCH_AXIS,))


def batch_sharding(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec(BATCH_AXIS))


def replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec())


def _placeable(tree: Any) -> Any:
    """Under several processes ``device_put`` onto a global sharding wants host arrays (the same on
    every process); each process keeps its own slices."""
    if jax.process_count() == 1:
        return tree
    return jax.tree_util.tree_map(lambda x: np.asarray(x) if isinstance(x, jax.Array) and x.is_fully_addressable
                                  else x, tree)


def shard_batch(tree: Any, mesh: Mesh) -> Any:
    """Place a pytree whose leaves all lead with the env-batch axis, split over the mesh."""
    return jax.device_put(_placeable(tree), batch_sharding(mesh))


def replicate(tree: Any, mesh: Mesh) -> Any:
    return jax.device_put(_placeable(tree), replicated(mesh))


def to_host(tree: Any) -> Any:
    """NumPy copy of a pytree of arrays.  Leaves split over several processes are gathered from all
    of them, so under ``jax.distributed`` every process must call this at the same point."""

    def get(x: Any) -> Any:
        if not isinstance(x, jax.Array) or jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            return x
        if x.is_fully_addressable:
            return np.asarray(x)
        if x.is_fully_replicated:
            return np.asarray(x.addressable_data(0))
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))

    return jax.tree_util.tree_map(get, tree)


def _pmean(x: Any, axis_name: str | None) -> Any:
    return x if axis_name is None else jax.lax.pmean(x, axis_name)


def _psum(x: Any, axis_name: str | None) -> Any:
    return x if axis_name is None else jax.lax.psum(x, axis_name)


# --------------------------------------------------------------------------- policy maths

def _normal(key: jax.Array, shape: tuple[int, ...], axis_name: str | None = None) -> jax.Array:
    """Standard normals for this device's rows of a batch split over ``axis_name``: its slice of one
    draw for the whole batch, so a sample does not depend on how many devices share the batch."""
    if axis_name is None:
        return jax.random.normal(key, shape)
    n = jax.lax.axis_size(axis_name)
    full = jax.random.normal(key, (n * shape[0],) + tuple(shape[1:]))
    return jax.lax.dynamic_slice_in_dim(full, jax.lax.axis_index(axis_name) * shape[0], shape[0])


def sample_action(networks: PPONetworks, params: Params, normaliser: Normaliser, obs: jax.Array,
                  key: jax.Array, axis_name: str | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(action in [-1, 1], pre-tanh sample, its log-prob under the tanh-Gaussian)."""
    dist = networks.parametric_action_distribution
    logits = networks.policy_network.apply(normaliser, params.policy, obs)
    gauss = dist.create_dist(logits)
    raw = _normal(key, gauss.loc.shape, axis_name) * gauss.scale + gauss.loc  # brax's sample_no_postprocessing
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
    sample = _normal(key, gauss.loc.shape, axis_name) * gauss.scale + gauss.loc
    return jnp.sum(gauss.entropy() + TanhBijector().forward_log_det_jacobian(sample), axis=-1)


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
        mean = _pmean(jnp.mean(adv), axis_name)
        std = jnp.sqrt(_pmean(jnp.mean(jnp.square(adv - mean)), axis_name))
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
    return (_pmean(loss, axis_name), _pmean(metrics, axis_name)), _pmean(grads, axis_name)


# --------------------------------------------------------------------------- rollout and update

def set_progress(env_state: State, progress: jax.Array) -> State:
    """Write training progress p into every env (the reward weights F_d, F_s read it)."""
    info = dict(env_state.info)
    info["progress"] = jnp.full_like(info["progress"], progress)
    return env_state.replace(info=info)


RESET_STATS = ("reset_overflow", "reset_replays")  # per-step auto-reset counters, when the env reports them
# per-iteration scalars that ``make_cycle`` returns (plus finite, episodes_finished, RESET_STATS, window)
CYCLE_METRICS = ("loss", "policy_loss", "value_loss", "entropy_bonus", "approx_kl", "clip_fraction", "grad_norm",
                 "entropy", "reward_mean")


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


def sgd_epochs(params: Params, opt_state: optax.OptState, normaliser: Normaliser, batch: Batch, key: jax.Array,
               networks: PPONetworks, optimizer: optax.GradientTransformation,
               cfg: PPOConfig, axis_name: str | None = None,
               kl_rule: lr_schedule.Rule | None = None) -> tuple[Params, optax.OptState, dict[str, jax.Array]]:
    """``num_epochs`` passes over the batch in ``num_minibatches`` shuffled minibatches.

    With ``axis_name`` each device shuffles its own share (a minibatch is the union of the
    devices' minibatches) and the gradients are averaged over devices.  With ``kl_rule`` (the
    ``kl-adaptive`` schedule) each minibatch first adapts the lr to its KL, as brax does, then
    takes its step.  The KL is ``step_kl``, the k3 estimate mean(e^s − 1 − s), s = log π_θ(a) −
    log π_start(a), of KL(π_start ‖ π_θ) on the minibatch (averaged over devices), π_start being
    the policy before this iteration's SGD under the already updated normaliser: what the
    epochs moved, as in brax (which updates its normaliser after the epochs for that reason);
    the PPO ratio's ``approx_kl`` would also count the normaliser's move.  The iteration's first
    minibatch, where π_θ = π_start and the KL is 0 by definition, leaves the lr alone."""
    n = batch.obs.shape[0]
    mb = n // cfg.num_minibatches
    if kl_rule is not None:
        dist = networks.parametric_action_distribution
        logits = networks.policy_network.apply(normaliser, params.policy, batch.obs)
        batch = batch._replace(kl_log_prob=jax.lax.stop_gradient(dist.log_prob(logits, batch.raw_action)))
        start_count = opt_state[1].count  # optax.inject_hyperparams counts the updates

    def minibatch_step(carry: tuple[Params, optax.OptState], xs: tuple[Batch, jax.Array]):
        params, opt_state = carry
        minibatch, k = xs
        (_, metrics), grads = loss_and_grad(params, normaliser, minibatch, k, networks, cfg, axis_name)
        if kl_rule is not None:
            lr = learning_rate_of(opt_state)
            adapted = lr_schedule.kl_adaptive_lr(jnp, kl_rule, lr, metrics["step_kl"])
            opt_state = with_learning_rate(opt_state, jnp.where(opt_state[1].count == start_count, lr, adapted))
        updates, opt_state = optimizer.update(grads, opt_state, params)
        metrics["grad_norm"] = optax.tree.norm(grads)
        return (optax.apply_updates(params, updates), opt_state), metrics

    def epoch(carry: tuple[Params, optax.OptState], k: jax.Array):
        k_perm, k_mb = jax.random.split(k)
        if axis_name is not None:
            k_perm = jax.random.fold_in(k_perm, jax.lax.axis_index(axis_name))
        perm = jax.random.permutation(k_perm, n)
        shuffled = jax.tree_util.tree_map(lambda x: x[perm].reshape((cfg.num_minibatches, mb) + x.shape[1:]), batch)
        return jax.lax.scan(minibatch_step, carry, (shuffled, jax.random.split(k_mb, cfg.num_minibatches)))

    (params, opt_state), metrics = jax.lax.scan(epoch, (params, opt_state), jax.random.split(key, cfg.num_epochs))
    return params, opt_state, metrics


def _all_finite(tree: Any) -> jax.Array:
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)
              if jnp.issubdtype(x.dtype, jnp.inexact)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.array(True)


def update_normaliser(normaliser: Normaliser, obs: jax.Array, cfg: PPOConfig,
                      hand_scaled: np.ndarray | None = None, axis_name: str | None = None) -> Normaliser:
    """Running mean/std update (std floored at ``obs_std_floor``); ``hand_scaled`` entries stay at
    mean 0, std 1 — observation entries already scaled by hand (and 0 when absent), which a
    normaliser fitted on mostly obstacle-free data would turn into outliers (docs/task.md §2, Layouts)."""
    normaliser = running_statistics.update(normaliser, obs, std_min_value=cfg.obs_std_floor, pmap_axis_name=axis_name)
    if hand_scaled is None or not np.any(hand_scaled):
        return normaliser
    mask = jnp.asarray(hand_scaled)
    return normaliser.replace(mean=jnp.where(mask, 0.0, normaliser.mean).astype(normaliser.mean.dtype),
                              std=jnp.where(mask, 1.0, normaliser.std).astype(normaliser.std.dtype))


def iteration(train_state: TrainingState, env_state: State, key: jax.Array, progress: jax.Array, *,
              env: Env, networks: PPONetworks, optimizer: optax.GradientTransformation,
              cfg: PPOConfig, axis_name: str | None = None, hand_scaled: np.ndarray | None = None,
              critic_extra: int = 0, kl_rule: lr_schedule.Rule | None = None) -> tuple[TrainingState, State, dict[str, Any]]:
    """One PPO iteration; if the loss or new params are non-finite the old train state is kept.

    ``metrics["finite"]`` tells the host to count the rollback (the envs keep running).  With
    ``axis_name`` (inside ``shard_map``) ``env_state`` is this device's share of the env batch;
    normaliser statistics, advantage statistics, gradients and metrics are global.
    """
    k_roll, k_sgd = jax.random.split(key)
    env_state = set_progress(env_state, progress)
    params = train_state.params
    env_state, data, episodes = rollout(env, networks, params, train_state.normaliser, env_state, k_roll,
                                        cfg.unroll_length, axis_name, critic_extra)
    entropy = _pmean(mean_policy_entropy(networks, params, train_state.normaliser, data.obs), axis_name)
    normaliser = update_normaliser(train_state.normaliser, data.obs, cfg, hand_scaled, axis_name)
    batch = make_batch(networks, params, normaliser, data, env_state.obs, cfg, critic_extra_of(env_state, critic_extra))
    new_params, opt_state, sgd_metrics = sgd_epochs(params, train_state.opt_state, normaliser, batch, k_sgd,
                                                    networks, optimizer, cfg, axis_name, kl_rule)
    new_state = TrainingState(params=new_params, opt_state=opt_state, normaliser=normaliser)
    finite = _all_finite(sgd_metrics["loss"]) & _all_finite(new_state)
    if axis_name is not None:  # every device must take the same branch
        finite = jax.lax.pmin(finite.astype(jnp.int32), axis_name) > 0
    kept = jax.tree_util.tree_map(lambda new, old: jnp.where(finite, new, old), new_state, train_state)
    metrics: dict[str, Any] = {k: jnp.mean(v) for k, v in sgd_metrics.items()}
    metrics.update(entropy=entropy, finite=finite, reward_mean=_pmean(jnp.mean(data.reward), axis_name),
                   episodes=episodes)
    return kept, env_state, metrics


def _sharded(fn: Callable[..., Any], mesh: Mesh, in_specs: Any, out_specs: Any) -> Callable[..., Any]:
    return jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False)


def make_iteration(env: Env, networks: PPONetworks, optimizer: optax.GradientTransformation, cfg: PPOConfig,
                   mesh: Mesh, hand_scaled: np.ndarray | None = None,
                   critic_extra: int = 0) -> Callable[..., tuple[TrainingState, State, dict[str, Any]]]:
    """Jitted ``iteration``: each device runs its share of the env batch (``shard_map``), params
    replicated; ``metrics["episodes"]`` stays split over the devices."""
    rep, shard = PartitionSpec(), PartitionSpec(BATCH_AXIS)

    def local(train_state: TrainingState, env_state: State, key: jax.Array, progress: jax.Array):
        ts, es, metrics = iteration(train_state, env_state, key, progress, env=env, networks=networks,
                                    optimizer=optimizer, cfg=cfg, axis_name=BATCH_AXIS, hand_scaled=hand_scaled,
                                    critic_extra=critic_extra)
        episodes = metrics.pop("episodes")
        return ts, es, metrics, episodes

    fn = _sharded(local, mesh, (rep, shard, rep, rep), (rep, shard, rep, PartitionSpec(None, BATCH_AXIS)))

    def wrapped(train_state: TrainingState, env_state: State, key: jax.Array, progress: jax.Array):
        ts, es, metrics, episodes = fn(train_state, env_state, key, progress)
        return ts, es, dict(metrics, episodes=episodes)

    return jax.jit(wrapped)


def make_first_gradients(env: Env, networks: PPONetworks, cfg: PPOConfig,
                         mesh: Mesh) -> Callable[..., tuple[jax.Array, Params]]:
    """Jitted (loss, gradients) of the first iteration's whole batch, by the training code path
    (rollout, normaliser update, GAE; devices average): the multi-device / multi-process check."""
    rep, shard = PartitionSpec(), PartitionSpec(BATCH_AXIS)

    def local(train_state: TrainingState, env_state: State, key: jax.Array):
        k_roll, k_loss = jax.random.split(key)
        es, data, _ = rollout(env, networks, train_state.params, train_state.normaliser, env_state, k_roll,
                              cfg.unroll_length, BATCH_AXIS)
        norm = running_statistics.update(train_state.normaliser, data.obs, std_min_value=cfg.obs_std_floor,
                                         pmap_axis_name=BATCH_AXIS)
        batch = make_batch(networks, train_state.params, norm, data, es.obs, cfg)
        # env-major rows, so that each device's rows are one slice of the global batch (its envs): the
        # entropy estimate's noise (``_normal``) then does not depend on the device count either
        t, b = data.reward.shape
        batch = jax.tree_util.tree_map(lambda x: x.reshape((t, b) + x.shape[1:]).swapaxes(0, 1).reshape(x.shape),
                                       batch)
        (loss, _), grads = loss_and_grad(train_state.params, norm, batch, k_loss, networks, cfg, BATCH_AXIS)
        return loss, grads

    return jax.jit(_sharded(local, mesh, (rep, shard, rep), (rep, rep)))


# --------------------------------------------------------------------------- training-episode window

def init_window(keys: tuple[str, ...], size: int) -> dict[str, Any]:
    """Device-side ring buffer of the last ``size`` finished training episodes' metrics."""
    return {"values": {k: jnp.zeros((size,), jnp.float32) for k in keys},
            "count": jnp.zeros((), jnp.int32), "ptr": jnp.zeros((), jnp.int32)}


def update_window(window: dict[str, Any], episodes: dict[str, jax.Array]) -> tuple[dict[str, Any], dict[str, jax.Array]]:
    """Append the episodes that finished in [T, B] ``episodes`` (time-major, then env order) and
    return the window means: every metric but ``steps``, ``episode_steps``, ``steps_to_success``
    (NaN without a success) and ``window_episodes``."""
    size = next(iter(window["values"].values())).shape[0]
    done = episodes["done"].reshape(-1) > 0.5
    rank = jnp.cumsum(done.astype(jnp.int32)) - 1
    n_new = jnp.sum(done.astype(jnp.int32))
    keep = done & (rank >= n_new - size)
    pos = jnp.where(keep, (window["ptr"] + rank) % size, size)
    values = {k: buf.at[pos].set(episodes[k].reshape(-1).astype(buf.dtype), mode="drop")
              for k, buf in window["values"].items()}
    count = jnp.minimum(window["count"] + n_new, size)
    new = {"values": values, "count": count, "ptr": (window["ptr"] + n_new) % size}
    valid = (jnp.arange(size) < count).astype(jnp.float32)
    n = jnp.maximum(count, 1).astype(jnp.float32)
    means = {k: jnp.sum(v * valid) / n for k, v in values.items() if k != "steps"}
    steps = values.get("steps", jnp.zeros((size,), jnp.float32))
    success = values.get("success", jnp.zeros((size,), jnp.float32)) * valid
    n_success = jnp.sum(success)
    means["episode_steps"] = jnp.sum(steps * valid) / n
    means["steps_to_success"] = jnp.where(n_success > 0, jnp.sum(steps * success) / jnp.maximum(n_success, 1.0),
                                          jnp.nan)
    means["window_episodes"] = count
    return new, means


# --------------------------------------------------------------------------- several iterations per call

def make_cycle(env: Env, networks: PPONetworks, optimizer: optax.GradientTransformation, cfg: PPOConfig,
               mesh: Mesh, length: int, hand_scaled: np.ndarray | None = None, critic_extra: int = 0,
               lr_rule: lr_schedule.Rule | None = None
               ) -> Callable[..., tuple[TrainingState, State, dict[str, Any], dict[str, Any]]]:
    """Jitted run of up to ``length`` PPO iterations in one call (a ``lax.while_loop``), one host sync.

    ``cycle(train_state, env_state, window, train_key, first, count, progress, lr)`` runs iterations
    ``first … first + count - 1`` (``count ≤ length``; iteration i uses ``fold_in(train_key, i)``,
    ``progress[i - first]`` and, under a ``per_iteration`` lr schedule, ``lr[i - first]``),
    stopping after a non-finite one (its state is not kept, see ``iteration``).  ``lr_rule``
    (``lr_schedule.Rule``; default: the host's lr) says how the lr moves inside the call:
    ``fixed`` (constant, sa) keeps the optimizer state's, ``per_iteration`` (cosine, linear)
    sets ``lr[j]`` before iteration j, ``kl`` (kl-adaptive) adapts it after every minibatch.
    Each iteration appends its finished episodes to ``window`` (``init_window``).  Returns the
    new states and per-iteration metrics of shape [length]: ``executed`` marks the iterations
    that ran; ``window`` holds the window means; ``learning_rate`` the optimizer's lr after it
    (and under ``kl``, ``step_kl`` the mean KL its minibatches measured, see ``sgd_epochs``).
    """
    rep, shard = PartitionSpec(), PartitionSpec(BATCH_AXIS)
    mode = "fixed" if lr_rule is None else lr_rule.mode
    kl_rule = lr_rule if mode == "kl" else None

    def local(train_state: TrainingState, env_state: State, window: dict[str, Any], train_key: jax.Array,
              first: jax.Array, count: jax.Array, progress: jax.Array, lr: jax.Array):
        f32 = lambda: jnp.zeros((), jnp.float32)
        i32 = lambda: jnp.zeros((), jnp.int32)
        # the per-iteration outputs, spelled out so their buffers need no second trace of ``run``
        skipped = {**{k: f32() for k in (*CYCLE_METRICS, *RESET_STATS)}, "finite": jnp.zeros((), bool),
                   "episodes_finished": i32(), "learning_rate": f32(), **({"step_kl": f32()} if kl_rule else {}),
                   "window": {**{k: f32() for k in window["values"] if k != "steps"}, "episode_steps": f32(),
                              "steps_to_success": f32(), "window_episodes": i32()}}

        def run(carry: tuple[TrainingState, State, dict[str, Any]], j: jax.Array):
            ts, es, win = carry
            key = jax.random.fold_in(train_key, first + j)
            if mode == "per_iteration":
                ts = ts._replace(opt_state=with_learning_rate(ts.opt_state, lr[j]))
            ts, es, metrics = iteration(ts, es, key, progress[j], env=env, networks=networks, optimizer=optimizer,
                                        cfg=cfg, axis_name=BATCH_AXIS, hand_scaled=hand_scaled,
                                        critic_extra=critic_extra, kl_rule=kl_rule)
            episodes = metrics["episodes"]
            out = {k: metrics[k].astype(jnp.float32) for k in CYCLE_METRICS}
            out["learning_rate"] = learning_rate_of(ts.opt_state).astype(jnp.float32)
            if kl_rule is not None:  # the mean KL the kl-adaptive rule read over the iteration's minibatches
                out["step_kl"] = metrics["step_kl"].astype(jnp.float32)
            out.update({name: jax.lax.psum(jnp.sum(episodes.get(name, jnp.zeros(()))), BATCH_AXIS).astype(jnp.float32)
                        for name in RESET_STATS})
            out["finite"] = metrics["finite"]
            out["episodes_finished"] = jax.lax.psum(jnp.sum(episodes["done"] > 0.5, dtype=jnp.int32), BATCH_AXIS)
            kept = {k: episodes[k] for k in (*win["values"], "done")}
            win, out["window"] = update_window(win, jax.lax.all_gather(kept, BATCH_AXIS, axis=1, tiled=True))
            return (ts, es, win), out

        def cond(carry: tuple[Any, ...]) -> jax.Array:
            j, _, _, _, stopped, _ = carry
            return (j < count) & ~stopped

        def body(carry: tuple[Any, ...]) -> tuple[Any, ...]:
            j, ts, es, win, _, outs = carry
            (ts, es, win), out = run((ts, es, win), j)
            outs = jax.tree_util.tree_map(lambda buf, x: buf.at[j].set(x), outs, out)
            return j + 1, ts, es, win, ~out["finite"], outs

        outs = jax.tree_util.tree_map(lambda x: jnp.zeros((length,) + x.shape, x.dtype), skipped)
        init = (jnp.zeros((), jnp.int32), train_state, env_state, window, jnp.zeros((), bool), outs)
        ran, ts, es, win, _, outs = jax.lax.while_loop(cond, body, init)
        outs["executed"] = jnp.arange(length) < ran
        return ts, es, win, outs

    return jax.jit(_sharded(local, mesh, (rep, shard, rep, rep, rep, rep, rep, rep), (rep, shard, rep, rep)))


def make_reset(env: Env, mesh: Mesh) -> Callable[[jax.Array], State]:
    """Jitted batched reset whose output is split over the mesh (keys: [B] PRNG keys)."""
    shard = batch_sharding(mesh)
    return jax.jit(lambda keys: jax.lax.with_sharding_constraint(jax.vmap(env.reset)(keys), shard))


# --------------------------------------------------------------------------- evaluation

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
    n_success = _psum(jnp.sum(success), axis_name)
    steps_to_success = jnp.where(n_success > 0, _psum(jnp.sum(steps * success), axis_name) / jnp.maximum(n_success, 1.0),
                                 jnp.nan)
    episodes = dict(rec, success=success, collision=collision, timeout=timeout)
    episodes.update({"return": ret, "steps": steps, "finished": finished.astype(jnp.float32)})
    mean = lambda x: _pmean(jnp.mean(x), axis_name)
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
    return jax.jit(_sharded(local, mesh, (rep, rep, shard), specs))


def eval_keys(seed: int, episodes: int) -> jax.Array:
    """The fixed evaluation set: one reset key per episode, from one seed."""
    return jax.random.split(jax.random.PRNGKey(seed), episodes)


def num_iterations(total_steps: int, cfg: PPOConfig) -> int:
    return max(1, math.ceil(total_steps / (cfg.num_envs * cfg.unroll_length)))
