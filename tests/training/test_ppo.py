"""PPO pieces: GAE by hand, lr injection, non-finite rollback, evaluation, entropy, 2 devices (the
iterations run through the training call, ``ppo.make_cycle``)."""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import toy_config
from toy_env import AutoReset, PointReach

from sagrasp_jax.training.agents.ppo import actor_critic
from sagrasp_jax.training.agents.ppo import losses
from sagrasp_jax.training import metrics_window
from sagrasp_jax.training import fixed_seed_eval as policy_eval
from sagrasp_jax.training.agents.ppo import ppo
from sagrasp_jax.training.agents.ppo import rollout
from sagrasp_jax.training import sa_schedule
from sagrasp_jax.training import sharding
from paths import TESTS  # noqa: E402


def _setup(env=None, cfg=None, mesh=None):
    cfg = cfg or toy_config().ppo
    env = env or AutoReset(PointReach())
    mesh = mesh or sharding.make_mesh()
    nets = actor_critic.make_networks(cfg.network, env.observation_size, env.action_size, cfg.obs_clip)
    opt = actor_critic.make_optimizer(cfg)
    ts = sharding.replicate(actor_critic.init_training_state(jax.random.PRNGKey(0), nets, opt, env.observation_size), mesh)
    es = rollout.make_reset(env, mesh)(sharding.shard_batch(jax.random.split(jax.random.PRNGKey(1), cfg.num_envs), mesh))
    return cfg, env, mesh, nets, opt, ts, es


def _iteration(env, nets, opt, cfg, mesh, ts, es, key, progress, lr=3e-4):
    """One PPO iteration at ``lr`` through the training call (``ppo.make_cycle``, one iteration long); its
    per-iteration metrics as scalars."""
    cycle = ppo.make_cycle(env, nets, opt, cfg, mesh, 1)
    window = metrics_window.init_window(("return", "success", "steps"), 64)
    args = (window, key, np.int32(0), np.int32(1), np.array([progress], np.float32), np.array([lr], np.float32))
    ts2, es2, _, metrics = cycle(ts, es, *sharding.replicate(args, mesh))
    return ts2, es2, jax.tree_util.tree_map(lambda x: x[0], sharding.to_host(metrics))


def test_gae_matches_hand_computed_case():
    rewards = jnp.array([[1.0], [0.0], [2.0]])
    values = jnp.array([[0.5], [0.4], [0.3]])
    dones = jnp.array([[0.0], [1.0], [0.0]])
    adv, ret = losses.compute_gae(rewards, values, dones, jnp.array([0.2]), gamma=0.9, lam=0.8)
    # δ2 = 2 + 0.9·0.2 − 0.3 = 1.88; δ1 = 0 − 0.4 (episode ends at t=1); δ0 = 1 + 0.9·0.4 − 0.5 = 0.86
    # A1 = δ1 (no bootstrap across the end); A0 = 0.86 + 0.9·0.8·(−0.4) = 0.572
    np.testing.assert_allclose(adv[:, 0], [0.572, -0.4, 1.88], rtol=1e-6)
    np.testing.assert_allclose(ret[:, 0], [1.072, 0.0, 2.18], rtol=1e-6, atol=1e-7)


def test_learning_rate_is_the_calls_argument_and_not_optimizer_state():
    cfg, env, mesh, nets, opt, ts, es = _setup()
    # the host owns the lr: the optimizer state holds none
    paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(ts.opt_state)[0]]
    assert not any("learning_rate" in p for p in paths) and any(".mu" in p for p in paths), paths
    # A zero lr leaves the params unchanged through a whole iteration; the call's lr moves them.
    frozen, _, metrics = _iteration(env, nets, opt, cfg, mesh, ts, es, jax.random.PRNGKey(2), 0.0, lr=0.0)
    assert bool(metrics["finite"]) and float(metrics["learning_rate"]) == 0.0
    for a, b in zip(jax.tree_util.tree_leaves(frozen.params), jax.tree_util.tree_leaves(ts.params)):
        np.testing.assert_array_equal(a, b)
    moved, _, metrics = _iteration(env, nets, opt, cfg, mesh, ts, es, jax.random.PRNGKey(2), 0.0, lr=1.25e-4)
    assert float(metrics["learning_rate"]) == np.float32(1.25e-4)
    assert any(not np.array_equal(a, b) for a, b in zip(jax.tree_util.tree_leaves(moved.params),
                                                         jax.tree_util.tree_leaves(ts.params)))


def test_iteration_writes_progress_and_counts_finished_episodes():
    cfg, env, mesh, nets, opt, ts, es = _setup()
    ts2, es2, m = _iteration(env, nets, opt, cfg, mesh, ts, es, jax.random.PRNGKey(2), 0.25)
    np.testing.assert_array_equal(np.asarray(es2.info["progress"]), 0.25)
    assert m["executed"] and m["episodes_finished"] > 0 and m["window"]["window_episodes"] == min(m["episodes_finished"], 64)
    assert 1.0 <= m["window"]["episode_steps"] <= 30.0  # episodes end within the toy's 30 steps
    assert bool(m["finite"]) and np.isfinite(float(m["loss"]))
    assert int(ts2.opt_state[1].count) == cfg.num_epochs * cfg.num_minibatches


def test_late_epochs_run_fewer_of_the_same_passes_from_late_from_on():
    """``ppo.late_epochs``: before ``late_from`` an iteration takes the fixed scan's passes (same update count,
    parameters equal to float rounding); from it on, only ``late_epochs`` of them, in the same program."""
    import dataclasses
    base, env, mesh, nets, opt, ts, es = _setup()
    assert base.num_epochs >= 2
    late = dataclasses.replace(base, late_epochs=1, late_from=0.5)
    key = jax.random.PRNGKey(2)
    fixed, _, m_fixed = _iteration(env, nets, opt, base, mesh, ts, es, key, 0.25)
    early, _, m_early = _iteration(env, nets, opt, late, mesh, ts, es, key, 0.25)
    after, _, m_after = _iteration(env, nets, opt, late, mesh, ts, es, key, 0.75)
    per_epoch = base.num_minibatches
    assert int(early.opt_state[1].count) == int(fixed.opt_state[1].count) == base.num_epochs * per_epoch
    assert int(after.opt_state[1].count) == per_epoch
    for a, b in zip(jax.tree_util.tree_leaves(early.params), jax.tree_util.tree_leaves(fixed.params)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(m_early["loss"], m_fixed["loss"], rtol=1e-5, atol=1e-6)  # the passes' mean
    moved = lambda new: sum(float(jnp.sum(jnp.abs(x - y))) for x, y in
                            zip(jax.tree_util.tree_leaves(new.params), jax.tree_util.tree_leaves(ts.params)))
    assert 0 < moved(after) < moved(early)  # one pass moves the policy, less far than all of them
    assert bool(m_after["finite"]) and np.isfinite(float(m_after["loss"]))


def test_nonfinite_iteration_keeps_the_old_state_bit_for_bit():
    cfg, env, mesh, nets, opt, ts, es = _setup(env=AutoReset(PointReach(nan_progress=(0.5, 1.0))))
    kept, es2, m = _iteration(env, nets, opt, cfg, mesh, ts, es, jax.random.PRNGKey(3), 0.6)
    assert not bool(m["finite"])
    for a, b in zip(jax.tree_util.tree_leaves(kept), jax.tree_util.tree_leaves(ts)):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(np.asarray(es2.obs), np.asarray(es.obs))  # the envs kept running


def test_evaluation_is_deterministic_and_stops_at_first_done():
    cfg, env, mesh, nets, opt, ts, es = _setup()
    ev = policy_eval.make_evaluator(nets, PointReach(max_steps=30), 30)
    keys = policy_eval.eval_keys(7, 64)
    a = jax.device_get(ev(ts.params, ts.normaliser, keys))
    b = jax.device_get(ev(ts.params, ts.normaliser, keys))
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(x, y)
    eps = a.episodes
    assert np.all(eps["finished"] == 1) and np.all((eps["steps"] >= 1) & (eps["steps"] <= 30))
    outcome = eps["success"] + eps["collision"] + eps["timeout"]
    np.testing.assert_array_equal(outcome, 1.0)  # exactly one way each episode ended
    assert float(a.success_rate) == pytest.approx(eps["success"].mean())
    # A step cap below the episode length leaves episodes unfinished, counted as timeouts.
    short = jax.device_get(policy_eval.make_evaluator(nets, PointReach(max_steps=30), 1)(ts.params, ts.normaliser, keys))
    assert np.all(short.episodes["steps"] == 1)
    assert float(short.timeout_rate) == pytest.approx(1.0 - short.episodes["success"].mean()
                                                      - short.episodes["collision"].mean())


@pytest.mark.parametrize("cap", [30, 5])
def test_evaluation_in_slots_matches_all_episodes_at_once(cap):
    """A few slots, each taking the next episode when its own ends: the same per-episode results
    (in key order) as running all episodes side by side, with or without the step cap."""
    cfg, env, mesh, nets, opt, ts, es = _setup()
    keys = policy_eval.eval_keys(3, 40)
    full = jax.device_get(policy_eval.make_evaluator(nets, PointReach(max_steps=30), cap)(ts.params, ts.normaliser, keys))
    slots = jax.device_get(policy_eval.make_evaluator(nets, PointReach(max_steps=30), cap, slots=6)(ts.params, ts.normaliser,
                                                                                             keys))
    assert full.episodes.keys() == slots.episodes.keys()
    for k in full.episodes:
        np.testing.assert_allclose(slots.episodes[k], full.episodes[k], rtol=1e-5, atol=1e-5, err_msg=k)
    for a, b in zip(full[:5], slots[:5]):
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-5)
    assert len(set(np.asarray(full.episodes["steps"]).tolist())) >= 2  # slots free up at different times


def test_closed_form_entropy_matches_the_schedule_helper():
    cfg, env, mesh, nets, opt, ts, es = _setup()
    obs = np.asarray(es.obs)
    h = float(actor_critic.mean_policy_entropy(nets, ts.params, ts.normaliser, obs))
    logits = nets.policy_network.apply(ts.normaliser, ts.params.policy, obs)
    std = nets.parametric_action_distribution.create_dist(logits).scale
    assert h == pytest.approx(sa_schedule.gaussian_entropy(std=np.asarray(std)), rel=1e-5)


_TWO_DEVICE_SCRIPT = textwrap.dedent("""
    import sys
    sys.path.insert(0, {tests!r})
    import sagrasp_jax, jax, numpy as np
    from conftest import FIRST_GRADIENT_SETS, first_gradients, toy_config
    from toy_env import AutoReset, PointReach
    from sagrasp_jax.training import sharding
    assert len(jax.devices()) == 2, jax.devices()
    cfg = toy_config(extra=FIRST_GRADIENT_SETS)
    env = AutoReset(PointReach())
    one = first_gradients(env, cfg, sharding.make_mesh(jax.devices()[:1]))
    two = first_gradients(env, cfg, sharding.make_mesh(jax.devices()))
    diff = max(float(np.max(np.abs(a - b))) for a, b in zip(one[1:], two[1:]))
    print("dtype", one[1].dtype, "loss diff", abs(float(one[0]) - float(two[0])), "max grad diff", diff)
    assert abs(float(one[0]) - float(two[0])) < {tol} and diff < {tol}
""")


@pytest.mark.parametrize("x64,tol", [(True, 1e-5), (False, 1e-4)])
def test_two_host_devices_give_the_same_first_gradients(x64: bool, tol: float):
    """Sharded = unsharded maths, through the training call (``ppo.make_cycle``).  In float64 the gradients agree to 1e-5 (docs/task.md §3's check, free of
    float32 noise); in float32 the two differently fused programs still agree to 1e-4."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
               JAX_PLATFORMS="cpu", JAX_ENABLE_X64="1" if x64 else "0")
    script = _TWO_DEVICE_SCRIPT.format(tests=TESTS, tol=tol)
    res = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "max grad diff" in res.stdout


def test_jitted_initial_state_is_the_eager_one_bit_for_bit():
    """The trainer builds its initial params, normaliser and optimiser state in one jitted program
    (``actor_critic.jitted_init_training_state``) instead of eagerly: the README preset's networks must come out the same to
    the bit once placed on a device as the trainer places them (the eager normaliser's ``std_eps`` is a
    Python float, the jitted one a weakly typed array: the same after ``device_put``), or every run's
    numbers would move."""
    from sagrasp_jax.task import observation
    from sagrasp_jax.task.config import get_config
    from sagrasp_jax.task import robots

    cfg = get_config("cpu-quick")
    obs_size = len(observation.layout_of(cfg.env))
    nets = actor_critic.make_networks(cfg.ppo.network, obs_size, robots.get(cfg.env.robot).dof, cfg.ppo.obs_clip,
                                      observation.critic_extra_size(cfg))
    opt = actor_critic.make_optimizer(cfg.ppo)
    key = jax.random.split(jax.random.PRNGKey(cfg.train.seed), 3)[0]
    eager = actor_critic.init_training_state(key, nets, opt, obs_size)
    jitted = actor_critic.jitted_init_training_state(nets, opt, obs_size)(key)
    a, b = jax.tree_util.tree_leaves(jax.device_put(eager)), jax.tree_util.tree_leaves(jax.device_put(jitted))
    assert jax.tree_util.tree_structure(eager) == jax.tree_util.tree_structure(jitted) and len(a) > 10
    for x, y in zip(a, b):
        assert (x.dtype, x.shape, x.weak_type) == (y.dtype, y.shape, y.weak_type)
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
