"""Brax-style PPO as small pure functions over typed NamedTuples.

brax 0.14.2's ``ppo.train`` does not run on jax >= 0.10, so the loop lives here; brax supplies
only the networks, the tanh-Gaussian distribution and the running observation statistics.
Everything in one PPO iteration (rollout, normaliser update, GAE, minibatch epochs) is one
jitted function; the host sets the learning rate and the training progress between calls.

Data parallelism: the env batch is sharded over a 1-D ``Mesh`` of local devices, params and
optimizer state are replicated.  Losses are means over the *global* minibatch, so under jit the
partitioner inserts the cross-device gradient reduction; on one device nothing changes.
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
from flax import linen
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from sagrasp_jax.config import NetworkConfig, PPOConfig

Normaliser = running_statistics.RunningStatisticsState
PPONetworks = ppo_networks.PPONetworks
BATCH_AXIS = "batch"

_ACTIVATIONS: dict[str, Callable[[jax.Array], jax.Array]] = {
    "tanh": linen.tanh, "relu": linen.relu, "silu": linen.swish, "elu": linen.elu,
}


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
    """brax PPO networks whose preprocessor normalises with the running stats and clips (SPEC §2).

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


def set_learning_rate(opt_state: optax.OptState, lr: float) -> optax.OptState:
    """Return ``opt_state`` with a new Adam lr (the optimizer built by ``make_optimizer``)."""
    inject = opt_state[1]
    old = inject.hyperparams["learning_rate"]
    hyper = dict(inject.hyperparams, learning_rate=jnp.asarray(lr, dtype=old.dtype))
    if isinstance(old, jax.Array):  # keep it where the rest of the state lives (replicated)
        hyper["learning_rate"] = jax.device_put(hyper["learning_rate"], old.sharding)
    return (opt_state[0], inject._replace(hyperparams=hyper), *opt_state[2:])


# --------------------------------------------------------------------------- sharding

def make_mesh(devices: list[jax.Device] | None = None) -> Mesh:
    return Mesh(np.array(devices if devices is not None else jax.local_devices()), (BATCH_AXIS,))


def batch_sharding(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec(BATCH_AXIS))


def replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec())


def shard_batch(tree: Any, mesh: Mesh) -> Any:
    """Place a pytree whose leaves all lead with the env-batch axis, split over the mesh."""
    return jax.device_put(tree, batch_sharding(mesh))


def replicate(tree: Any, mesh: Mesh) -> Any:
    return jax.device_put(tree, replicated(mesh))


# --------------------------------------------------------------------------- policy maths

def sample_action(networks: PPONetworks, params: Params, normaliser: Normaliser, obs: jax.Array,
                  key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(action in [-1, 1], pre-tanh sample, its log-prob under the tanh-Gaussian)."""
    dist = networks.parametric_action_distribution
    logits = networks.policy_network.apply(normaliser, params.policy, obs)
    raw = dist.sample_no_postprocessing(logits, key)
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
             cfg: PPOConfig) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Clipped surrogate + value MSE (SB3 weighting) − entropy bonus (brax tanh-corrected estimate)."""
    dist = networks.parametric_action_distribution
    logits = networks.policy_network.apply(normaliser, params.policy, batch.obs)
    log_prob = dist.log_prob(logits, batch.raw_action)
    log_ratio = log_prob - batch.log_prob
    ratio = jnp.exp(log_ratio)
    adv = batch.advantage
    if cfg.normalize_advantages:
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    clipped = jnp.clip(ratio, 1.0 - cfg.clip_eps, 1.0 + cfg.clip_eps)
    policy_loss = -jnp.mean(jnp.minimum(ratio * adv, clipped * adv))
    value = networks.value_network.apply(normaliser, params.value, critic_input(batch.obs, batch.critic_extra))
    value_loss = jnp.mean(jnp.square(batch.target - value))
    entropy = jnp.mean(dist.entropy(logits, key))
    total = policy_loss + cfg.value_coef * value_loss - cfg.entropy_coef * entropy
    return total, {
        "loss": total,
        "policy_loss": policy_loss,
        "value_loss": value_loss,
        "entropy_bonus": entropy,
        "approx_kl": jnp.mean((ratio - 1.0) - log_ratio),
        "clip_fraction": jnp.mean((jnp.abs(ratio - 1.0) > cfg.clip_eps).astype(jnp.float32)),
    }


def loss_and_grad(params: Params, normaliser: Normaliser, batch: Batch, key: jax.Array,
                  networks: PPONetworks, cfg: PPOConfig) -> tuple[tuple[jax.Array, dict[str, jax.Array]], Params]:
    return jax.value_and_grad(ppo_loss, has_aux=True)(params, normaliser, batch, key, networks, cfg)


# --------------------------------------------------------------------------- rollout and update

def set_progress(env_state: State, progress: jax.Array) -> State:
    """Write training progress p into every env (the reward weights F_d, F_s read it)."""
    info = dict(env_state.info)
    info["progress"] = jnp.full_like(info["progress"], progress)
    return env_state.replace(info=info)


def rollout(env: Env, networks: PPONetworks, params: Params, normaliser: Normaliser, env_state: State,
            key: jax.Array, unroll_length: int, critic_extra: int = 0) -> tuple[State, Transition, dict[str, jax.Array]]:
    """Run the vmapped, auto-resetting env for ``unroll_length`` steps.

    Returns the final env state, [T, B] transitions, and [T, B] episode metrics (env's
    ``info["episode"]`` plus ``done``) to be read only where ``done == 1``.  A wrapper that
    declares ``batched = True`` is stepped through its ``batch_step`` (whole batch at once,
    so it can amortise reset sampling); otherwise ``step`` is vmapped.
    """
    step_fn = env.batch_step if getattr(env, "batched", False) else jax.vmap(env.step)

    def one_step(state: State, k: jax.Array) -> tuple[State, tuple[Transition, dict[str, jax.Array]]]:
        action, raw, log_prob = sample_action(networks, params, normaliser, state.obs, k)
        nxt = step_fn(state, action)
        trans = Transition(obs=state.obs, critic_extra=critic_extra_of(state, critic_extra), raw_action=raw,
                           log_prob=log_prob, reward=nxt.reward, done=nxt.done)
        episode = dict(nxt.info["episode"], done=nxt.done)
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
               cfg: PPOConfig) -> tuple[Params, optax.OptState, dict[str, jax.Array]]:
    """``num_epochs`` passes over the batch in ``num_minibatches`` shuffled minibatches."""
    n = batch.obs.shape[0]
    mb = n // cfg.num_minibatches

    def minibatch_step(carry: tuple[Params, optax.OptState], xs: tuple[Batch, jax.Array]):
        params, opt_state = carry
        minibatch, k = xs
        (_, metrics), grads = loss_and_grad(params, normaliser, minibatch, k, networks, cfg)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        metrics["grad_norm"] = optax.tree.norm(grads)
        return (optax.apply_updates(params, updates), opt_state), metrics

    def epoch(carry: tuple[Params, optax.OptState], k: jax.Array):
        k_perm, k_mb = jax.random.split(k)
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
                      hand_scaled: np.ndarray | None = None) -> Normaliser:
    """Running mean/std update (std floored at ``obs_std_floor``); ``hand_scaled`` entries stay at
    mean 0, std 1 — observation entries already scaled by hand (and 0 when absent), which a
    normaliser fitted on mostly obstacle-free data would turn into outliers (SPEC §2, Layouts)."""
    normaliser = running_statistics.update(normaliser, obs, std_min_value=cfg.obs_std_floor)
    if hand_scaled is None or not np.any(hand_scaled):
        return normaliser
    mask = jnp.asarray(hand_scaled)
    return normaliser.replace(mean=jnp.where(mask, 0.0, normaliser.mean).astype(normaliser.mean.dtype),
                              std=jnp.where(mask, 1.0, normaliser.std).astype(normaliser.std.dtype))


def iteration(train_state: TrainingState, env_state: State, key: jax.Array, progress: jax.Array, *,
              env: Env, networks: PPONetworks, optimizer: optax.GradientTransformation,
              cfg: PPOConfig, hand_scaled: np.ndarray | None = None,
              critic_extra: int = 0) -> tuple[TrainingState, State, dict[str, Any]]:
    """One PPO iteration; if the loss or new params are non-finite the old train state is kept.

    ``metrics["finite"]`` tells the host to count the rollback (the envs keep running).
    """
    k_roll, k_sgd = jax.random.split(key)
    env_state = set_progress(env_state, progress)
    params = train_state.params
    env_state, data, episodes = rollout(env, networks, params, train_state.normaliser, env_state, k_roll,
                                        cfg.unroll_length, critic_extra)
    entropy = mean_policy_entropy(networks, params, train_state.normaliser, data.obs)
    normaliser = update_normaliser(train_state.normaliser, data.obs, cfg, hand_scaled)
    batch = make_batch(networks, params, normaliser, data, env_state.obs, cfg, critic_extra_of(env_state, critic_extra))
    new_params, opt_state, sgd_metrics = sgd_epochs(params, train_state.opt_state, normaliser, batch, k_sgd,
                                                    networks, optimizer, cfg)
    new_state = TrainingState(params=new_params, opt_state=opt_state, normaliser=normaliser)
    finite = _all_finite(sgd_metrics["loss"]) & _all_finite(new_state)
    kept = jax.tree_util.tree_map(lambda new, old: jnp.where(finite, new, old), new_state, train_state)
    metrics: dict[str, Any] = {k: jnp.mean(v) for k, v in sgd_metrics.items()}
    metrics.update(entropy=entropy, finite=finite, reward_mean=jnp.mean(data.reward), episodes=episodes)
    return kept, env_state, metrics


def make_iteration(env: Env, networks: PPONetworks, optimizer: optax.GradientTransformation, cfg: PPOConfig,
                   mesh: Mesh, hand_scaled: np.ndarray | None = None,
                   critic_extra: int = 0) -> Callable[..., tuple[TrainingState, State, dict[str, Any]]]:
    """Jit ``iteration`` with env-batch sharding on the env state and replicated params."""
    repl, shard = replicated(mesh), batch_sharding(mesh)

    def fn(train_state: TrainingState, env_state: State, key: jax.Array, progress: jax.Array):
        ts, es, metrics = iteration(train_state, env_state, key, progress, env=env, networks=networks,
                                    optimizer=optimizer, cfg=cfg, hand_scaled=hand_scaled, critic_extra=critic_extra)
        ts = jax.lax.with_sharding_constraint(ts, repl)
        es = jax.lax.with_sharding_constraint(es, shard)
        return ts, es, metrics

    return jax.jit(fn)


def make_reset(env: Env, mesh: Mesh) -> Callable[[jax.Array], State]:
    """Jitted batched reset whose output is split over the mesh (keys: [B] PRNG keys)."""
    shard = batch_sharding(mesh)
    return jax.jit(lambda keys: jax.lax.with_sharding_constraint(jax.vmap(env.reset)(keys), shard))


# --------------------------------------------------------------------------- evaluation

def evaluate_policy(networks: PPONetworks, params: Params, normaliser: Normaliser, env: Env, keys: jax.Array,
                    max_steps: int) -> EvalResult:
    """Deterministic policy on one episode per key, reward weights frozen at p = 1, no auto-reset.

    Counting stops at each env's first ``done``; the loop ends when all are done (or at
    ``max_steps``), so a converged policy evaluates in a fraction of the step budget.
    """
    n = keys.shape[0]
    state = set_progress(jax.vmap(env.reset)(keys), 1.0)
    step_fn = jax.vmap(env.step)
    record = jax.tree_util.tree_map(jnp.zeros_like, state.info["episode"])
    zeros = jnp.zeros((n,), jnp.float32)

    def cond(carry):
        t, _, alive, _, _, _ = carry
        return (t < max_steps) & jnp.any(alive)

    def body(carry):
        t, st, alive, rec, ret, steps = carry
        action = deterministic_action(networks, params, normaliser, st.obs)
        nxt = step_fn(st, action)
        ret = ret + jnp.where(alive, nxt.reward, 0.0)
        steps = steps + alive.astype(jnp.float32)
        ended = alive & (nxt.done > 0)
        rec = jax.tree_util.tree_map(lambda r, e: jnp.where(ended, e, r), rec, nxt.info["episode"])
        return t + 1, nxt, alive & ~ended, rec, ret, steps

    init = (jnp.array(0), state, jnp.ones((n,), bool), record, zeros, zeros)
    _, _, alive, rec, ret, steps = jax.lax.while_loop(cond, body, init)
    finished = ~alive
    success = rec["success"] * finished
    collision = rec["collision"] * finished
    timeout = jnp.where(finished, rec["timeout"], 1.0)
    n_success = jnp.sum(success)
    steps_to_success = jnp.where(n_success > 0, jnp.sum(steps * success) / jnp.maximum(n_success, 1.0), jnp.nan)
    episodes = dict(rec, success=success, collision=collision, timeout=timeout)
    episodes.update({"return": ret, "steps": steps, "finished": finished.astype(jnp.float32)})
    return EvalResult(mean_return=jnp.mean(ret), success_rate=jnp.mean(success),
                      steps_to_success=steps_to_success, collision_rate=jnp.mean(collision),
                      timeout_rate=jnp.mean(timeout), episodes=episodes)


def make_evaluator(networks: PPONetworks, env: Env, max_steps: int) -> Callable[[Params, Normaliser, jax.Array], EvalResult]:
    def fn(params: Params, normaliser: Normaliser, keys: jax.Array) -> EvalResult:
        return evaluate_policy(networks, params, normaliser, env, keys, max_steps)

    return jax.jit(fn)


def eval_keys(seed: int, episodes: int) -> jax.Array:
    """The fixed evaluation set: one reset key per episode, from one seed."""
    return jax.random.split(jax.random.PRNGKey(seed), episodes)


def num_iterations(total_steps: int, cfg: PPOConfig) -> int:
    return max(1, math.ceil(total_steps / (cfg.num_envs * cfg.unroll_length)))
