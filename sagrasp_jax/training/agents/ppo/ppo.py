"""The PPO training step: one iteration (rollout, normaliser, GAE, minibatch epochs) and the jitted cycle.

brax 0.14.2's ``ppo.train`` does not run on jax >= 0.10, so the loop lives here, split by
concern as brax's ``training/agents/ppo`` is: ``networks`` (networks, optimizer, action maths),
``losses`` (GAE, the PPO loss), ``rollout`` (acting), ``sharding`` (devices), ``policy_eval``
(evaluation), ``metrics_window`` (the training-episode window) and this module, the update.
``make_cycle`` jits a ``lax.while_loop`` of several iterations (a cycle's worth) so the host
syncs once per cycle.  The host's lr schedule owns the learning rate (``sagrasp_jax.training.lr_schedule``):
every call is given the lr of each of its iterations as an argument (the optimizer state holds none), and under
``kl-adaptive``, which adapts it after every minibatch, returns the lr each iteration ended at for the host to
keep.  With ``group`` it trains several seeds at once: the whole cycle
is vmapped over a leading seed axis (docs/design.md, "Seed groups").
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import math
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from brax.envs.base import State
from brax.training.acme import running_statistics
from jax.sharding import Mesh, PartitionSpec

from sagrasp_jax.training import lr_schedule
from sagrasp_jax.task.config import PPOConfig
from sagrasp_jax.training.agents.ppo.losses import Batch, loss_and_grad, make_batch
from sagrasp_jax.training.metrics_window import kind_success_keys, update_window
from sagrasp_jax.training.agents.ppo.actor_critic import (
    Normaliser, Params, PPONetworks, TrainingState, apply_learning_rate, critic_extra_of, mean_policy_entropy,
)
from sagrasp_jax.training.agents.ppo.rollout import RESET_STATS, Env, rollout, set_progress
from sagrasp_jax.training.sharding import BATCH_AXIS, pmean, seed_batch_spec, sharded


# per-iteration scalars that ``make_cycle`` returns (plus finite, episodes_finished, RESET_STATS, window)
CYCLE_METRICS = ("loss", "policy_loss", "value_loss", "entropy_bonus", "approx_kl", "clip_fraction", "grad_norm",
                 "entropy", "reward_mean")


def sgd_epochs(params: Params, opt_state: optax.OptState, normaliser: Normaliser, batch: Batch, key: jax.Array,
               networks: PPONetworks, optimizer: optax.GradientTransformation,
               cfg: PPOConfig, axis_name: str | None = None,
               kl_rule: lr_schedule.Rule | None = None,
               epochs: jax.Array | None = None, *,
               lr: jax.Array) -> tuple[Params, optax.OptState, jax.Array, dict[str, jax.Array]]:
    """``num_epochs`` passes over the batch in ``num_minibatches`` shuffled minibatches, each step scaled by
    ``lr`` (``apply_learning_rate``); returns the lr the passes ended at (``lr`` itself but under ``kl_rule``).

    ``epochs`` (a traced count ≤ ``num_epochs``; ``epochs_at``) runs only the first that many of
    the same passes, in a loop whose length is set at run time, so one compiled program serves
    every count; the metrics are then the passes' means (shape []), not [epochs, minibatches].

    With ``axis_name`` each device shuffles its own share (a minibatch is the union of the
    devices' minibatches) and the gradients are averaged over devices.  With ``kl_rule`` (the
    ``kl-adaptive`` schedule) each minibatch first adapts the lr to its KL, as brax does, then
    takes its step with it.  The KL is ``step_kl``, the k3 estimate mean(e^s − 1 − s), s = log π_θ(a) −
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
    lr = jnp.asarray(lr, jnp.float32)
    Carry = tuple[Params, optax.OptState, jax.Array, jax.Array]  # (params, opt state, lr, first minibatch)

    def minibatch_step(carry: Carry, xs: tuple[Batch, jax.Array]):
        params, opt_state, lr, first = carry
        minibatch, k = xs
        (_, metrics), grads = loss_and_grad(params, normaliser, minibatch, k, networks, cfg, axis_name)
        if kl_rule is not None:
            adapted = lr_schedule.kl_adaptive_lr(jnp, kl_rule, lr, metrics["step_kl"])
            lr = jnp.where(first, lr, adapted)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        metrics["grad_norm"] = optax.tree.norm(grads)
        params = optax.apply_updates(params, apply_learning_rate(updates, lr))
        return (params, opt_state, lr, jnp.zeros((), bool)), metrics

    def epoch(carry: Carry, k: jax.Array):
        k_perm, k_mb = jax.random.split(k)
        if axis_name is not None:
            k_perm = jax.random.fold_in(k_perm, jax.lax.axis_index(axis_name))
        perm = jax.random.permutation(k_perm, n)
        shuffled = jax.tree_util.tree_map(lambda x: x[perm].reshape((cfg.num_minibatches, mb) + x.shape[1:]), batch)
        return jax.lax.scan(minibatch_step, carry, (shuffled, jax.random.split(k_mb, cfg.num_minibatches)))

    keys = jax.random.split(key, cfg.num_epochs)
    start: Carry = (params, opt_state, lr, jnp.ones((), bool))
    if epochs is None:
        (params, opt_state, lr, _), metrics = jax.lax.scan(epoch, start, keys)
        return params, opt_state, lr, metrics

    def counted_epoch(e: jax.Array, carry: tuple[Carry, dict[str, jax.Array]]):
        state, sums = carry
        state, metrics = epoch(state, keys[e])
        return state, jax.tree_util.tree_map(lambda total, x: total + jnp.sum(x, axis=0), sums, metrics)

    shapes = jax.eval_shape(epoch, start, keys[0])[1]
    zeros = jax.tree_util.tree_map(lambda x: jnp.zeros(x.shape[1:], x.dtype), shapes)
    (params, opt_state, lr, _), sums = jax.lax.fori_loop(0, epochs, counted_epoch, (start, zeros))
    steps = (epochs * cfg.num_minibatches).astype(jnp.float32)
    return params, opt_state, lr, jax.tree_util.tree_map(lambda total: total / steps, sums)


def epochs_at(cfg: PPOConfig, progress: jax.Array) -> jax.Array | None:
    """SGD passes at training ``progress``: ``late_epochs`` from ``late_from`` on, else ``num_epochs``;
    None when ``late_epochs`` is off or not below ``num_epochs`` (``sgd_epochs`` then runs its fixed scan,
    as before the key: a run that sets fewer passes than a preset's late count keeps its own throughout)."""
    if not cfg.late_epochs or cfg.late_epochs >= cfg.num_epochs:
        return None
    return jnp.where(progress >= cfg.late_from, cfg.late_epochs, cfg.num_epochs).astype(jnp.int32)


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


def iteration(train_state: TrainingState, env_state: State, key: jax.Array, progress: jax.Array, lr: jax.Array, *,
              env: Env, networks: PPONetworks, optimizer: optax.GradientTransformation,
              cfg: PPOConfig, axis_name: str | None = None, hand_scaled: np.ndarray | None = None,
              critic_extra: int = 0, kl_rule: lr_schedule.Rule | None = None) -> tuple[TrainingState, State, dict[str, Any]]:
    """One PPO iteration at learning rate ``lr``; if the loss or new params are non-finite the old train state
    (and ``lr``) is kept.

    ``metrics["finite"]`` tells the host to count the rollback (the envs keep running); ``metrics["learning_rate"]``
    is the lr the iteration ended at (``lr`` itself but under ``kl_rule``, see ``sgd_epochs``).  With
    ``axis_name`` (inside ``shard_map``) ``env_state`` is this device's share of the env batch;
    normaliser statistics, advantage statistics, gradients and metrics are global.
    """
    k_roll, k_sgd = jax.random.split(key)
    env_state = set_progress(env_state, progress)
    params = train_state.params
    env_state, data, episodes = rollout(env, networks, params, train_state.normaliser, env_state, k_roll,
                                        cfg.unroll_length, axis_name, critic_extra)
    entropy = pmean(mean_policy_entropy(networks, params, train_state.normaliser, data.obs), axis_name)
    normaliser = update_normaliser(train_state.normaliser, data.obs, cfg, hand_scaled, axis_name)
    batch = make_batch(networks, params, normaliser, data, env_state.obs, cfg, critic_extra_of(env_state, critic_extra))
    new_params, opt_state, new_lr, sgd_metrics = sgd_epochs(params, train_state.opt_state, normaliser, batch, k_sgd,
                                                            networks, optimizer, cfg, axis_name, kl_rule,
                                                            epochs_at(cfg, progress), lr=lr)
    new_state = TrainingState(params=new_params, opt_state=opt_state, normaliser=normaliser)
    finite = _all_finite(sgd_metrics["loss"]) & _all_finite(new_state)
    if axis_name is not None:  # every device must take the same branch
        finite = jax.lax.pmin(finite.astype(jnp.int32), axis_name) > 0
    kept = jax.tree_util.tree_map(lambda new, old: jnp.where(finite, new, old), new_state, train_state)
    metrics: dict[str, Any] = {k: jnp.mean(v) for k, v in sgd_metrics.items()}
    metrics.update(entropy=entropy, finite=finite, reward_mean=pmean(jnp.mean(data.reward), axis_name),
                   episodes=episodes, learning_rate=jnp.where(finite, new_lr, jnp.asarray(lr, jnp.float32)))
    return kept, env_state, metrics


def make_cycle(env: Env, networks: PPONetworks, optimizer: optax.GradientTransformation, cfg: PPOConfig,
               mesh: Mesh, length: int, hand_scaled: np.ndarray | None = None, critic_extra: int = 0,
               lr_rule: lr_schedule.Rule | None = None, seed_axis: bool = False
               ) -> Callable[..., tuple[TrainingState, State, dict[str, Any], dict[str, Any]]]:
    """Jitted run of up to ``length`` PPO iterations in one call (a ``lax.while_loop``), one host sync.

    ``cycle(train_state, env_state, window, train_key, first, count, progress, lr)`` runs iterations
    ``first … first + count - 1`` (``count ≤ length``; iteration i uses ``fold_in(train_key, i)``,
    ``progress[i - first]`` and the lr the host gave it), stopping after a non-finite one (its
    state is not kept, see ``iteration``).  The host's lr schedule owns the lr; ``lr_rule``
    (``lr_schedule.Rule``; default: ``fixed``) says what the call does with its ``lr`` rows
    (``lr_schedule.iteration_lrs``): ``fixed`` (constant, sa) and ``per_iteration`` (cosine,
    linear) run iteration j at ``lr[j]``; ``kl`` (kl-adaptive) starts at ``lr[0]`` and adapts it
    after every minibatch, each iteration going on from the lr the last one ended at.
    Each iteration appends its finished episodes to ``window`` (``init_window``).  Returns the
    new states and per-iteration metrics of shape [length]: ``executed`` marks the iterations
    that ran; ``window`` holds the window means; ``learning_rate`` the lr each iteration ended at,
    what the host's schedule keeps (``lr_schedule.observe``), and under ``kl``, ``step_kl`` the
    mean KL its minibatches measured (see ``sgd_epochs``).

    With ``seed_axis`` every argument and result leads with a seed axis (a seed group, env states
    [S, B, ...] split over the mesh on B): the cycle is vmapped over it, each seed with its own
    ``first``, ``count``, ``progress`` and ``lr`` rows.  A seed whose iteration is non-finite stops
    there, the others run on (a batched ``while_loop`` keeps a stopped seed's carry unchanged).
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
                              "steps_to_success": f32(), "window_episodes": i32(),
                              **{k: f32() for k in kind_success_keys(window["values"])}}}

        def run(carry: tuple[TrainingState, State, dict[str, Any]], j: jax.Array, lr_j: jax.Array):
            ts, es, win = carry
            key = jax.random.fold_in(train_key, first + j)
            ts, es, metrics = iteration(ts, es, key, progress[j], lr_j, env=env, networks=networks, optimizer=optimizer,
                                        cfg=cfg, axis_name=BATCH_AXIS, hand_scaled=hand_scaled,
                                        critic_extra=critic_extra, kl_rule=kl_rule)
            episodes = metrics["episodes"]
            out = {k: metrics[k].astype(jnp.float32) for k in CYCLE_METRICS}
            out["learning_rate"] = metrics["learning_rate"]
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
            j, _, _, _, stopped, _, _ = carry
            return (j < count) & ~stopped

        def body(carry: tuple[Any, ...]) -> tuple[Any, ...]:
            j, ts, es, win, _, outs, last_lr = carry
            (ts, es, win), out = run((ts, es, win), j, last_lr if mode == "kl" else lr[j])
            outs = jax.tree_util.tree_map(lambda buf, x: buf.at[j].set(x), outs, out)
            return j + 1, ts, es, win, ~out["finite"], outs, out["learning_rate"]

        outs = jax.tree_util.tree_map(lambda x: jnp.zeros((length,) + x.shape, x.dtype), skipped)
        init = (jnp.zeros((), jnp.int32), train_state, env_state, window, jnp.zeros((), bool), outs,
                jnp.asarray(lr[0], jnp.float32))
        ran, ts, es, win, _, outs, _ = jax.lax.while_loop(cond, body, init)
        outs["executed"] = jnp.arange(length) < ran
        return ts, es, win, outs

    run = jax.vmap(local) if seed_axis else local
    env_spec = seed_batch_spec() if seed_axis else shard
    return jax.jit(sharded(run, mesh, (rep, env_spec, rep, rep, rep, rep, rep, rep), (rep, env_spec, rep, rep)))


def num_iterations(total_steps: int, cfg: PPOConfig) -> int:
    return max(1, math.ceil(total_steps / (cfg.num_envs * cfg.unroll_length)))
