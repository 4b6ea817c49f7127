"""brax's conventions kept: ``brax.envs.training.wrap`` + ``acting.generate_unroll`` run the grasp
env through several dones with fresh restarts, stable dtypes and a fixed metric key set; so does
MuJoCo Playground's ``wrap_for_brax_training`` (PyPI ``playground``, the ``playground`` extra; that
case is skipped where it is not installed)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401  (XLA flags before jax)
import jax
import jax.numpy as jnp
from brax import envs as brax_envs
from brax.envs.wrappers import training
from brax.training import acting

from sagrasp_jax import envs
from sagrasp_jax.task.config import get_config
from sagrasp_jax.task.episode import episode_keys

MAX_STEPS = 5  # the task's own timeout: zero actions time out every 5 steps
N_ENVS = 3


def small_config():
    cfg = get_config("cpu-quick")
    task = dataclasses.replace(cfg.env.task, max_steps=MAX_STEPS, obs_layout="paper")
    return dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, task=task))


def zero_policy(obs, key):
    state = obs["state"] if isinstance(obs, dict) else obs
    return jnp.zeros(state.shape[:-1] + (6,)), {}


def test_registry_and_brax_interface():
    env = envs.load("grasp-kinematic", small_config())
    assert isinstance(env, brax_envs.Env) and env.cfg.control.mode == "kinematic"
    assert env.action_size == 6 and env.observation_size == 17 and env.backend == "mjx"
    assert envs.load("grasp-dynamic", small_config().env).cfg.control.mode == "dynamic"
    assert brax_envs.get_environment("sagrasp_grasp_kinematic", config=small_config()).observation_size == 17
    with pytest.raises(ValueError, match="valid envs: grasp-kinematic, grasp-dynamic"):
        envs.load("grasp")


def _playground_wrap(env, episode_length, action_repeat):
    wrapper = pytest.importorskip("mujoco_playground._src.wrapper",
                                  reason='MuJoCo Playground is not installed (pip install "sagrasp_jax[playground]")')
    return wrapper.wrap_for_brax_training(env, episode_length=episode_length, action_repeat=action_repeat)


@pytest.mark.parametrize("wrap", [training.wrap, _playground_wrap], ids=["brax", "playground"])
def test_training_wrap_restarts_fresh_episodes_with_stable_dtypes_and_keys(wrap):
    env = envs.load("grasp-kinematic", small_config())
    wrapped = wrap(env, episode_length=1000, action_repeat=1)
    state = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(0), N_ENVS))
    assert state.data is state.pipeline_state  # Playground's name for the physics
    keys0, dtypes0 = set(state.metrics), jax.tree.map(lambda x: x.dtype, state)
    unroll = jax.jit(lambda s, k: acting.generate_unroll(wrapped, s, zero_policy, k, 3 * MAX_STEPS + 2,
                                                         extra_fields=("steps", "truncation", "episode")))
    final, data = unroll(state, jax.random.PRNGKey(1))
    # the scan would refuse a changed dtype or key set; check them all the same
    assert set(final.metrics) == keys0 and jax.tree.map(lambda x: x.dtype, final) == dtypes0
    assert final.info["steps"].dtype == jnp.float32 and final.pipeline_state["episode"]["steps"].dtype == jnp.int32

    done = np.asarray(data.discount) == 0  # (T, N): a timeout is the task's terminal verdict
    t_done = np.nonzero(done[:, 0])[0]
    assert list(t_done) == [MAX_STEPS - 1, 2 * MAX_STEPS - 1, 3 * MAX_STEPS - 1] and (done == done[:, :1]).all()
    extras = data.extras["state_extras"]
    episode = jax.tree.map(np.asarray, extras["episode"])
    assert set(episode) == set(episode_keys())
    # every finished episode is MAX_STEPS long and timed out: the counters restarted with the episode
    assert (episode["steps"][done] == MAX_STEPS).all() and (episode["timeout"][done] == 1).all()
    assert (np.asarray(extras["steps"])[t_done] == MAX_STEPS).all()  # brax's EpisodeWrapper counter restarts too
    assert (np.asarray(extras["truncation"]) == 0).all()  # episode_length 1000 never cuts a 5-step episode

    # fresh scenes: the target (observed) stays within an episode and changes at every restart
    i = env.inner.obs_layout.index("target_x")
    target = np.asarray(data.observation)[..., i:i + 3]  # (T, N, 3): the observation each action was taken on
    starts = [0] + [t + 1 for t in t_done]
    scenes = np.stack([target[s] for s in starts])  # (episodes, N, 3)
    for s, e in zip(starts, starts[1:] + [len(target)]):
        assert np.allclose(target[s:e], target[s])
    for a in range(len(starts)):
        for b in range(a):
            assert (np.abs(scenes[a] - scenes[b]).max(axis=-1) > 1e-4).all(), "a restart replayed a scene"


def test_eval_wrapper_and_privileged_dict_observation():
    env = envs.load("grasp-kinematic", small_config(), privileged=True)
    n, extra = env.inner.observation_size, env.inner.privileged_size
    assert extra > 0 and env.observation_size == {"state": (n,), "privileged_state": (n + extra,)}
    wrapped = training.EvalWrapper(training.wrap(env, episode_length=4, action_repeat=1))  # what brax's evaluator runs
    state = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(2), N_ENVS))
    assert state.obs["state"].shape == (N_ENVS, n) and state.obs["privileged_state"].shape == (N_ENVS, n + extra)
    final, data = jax.jit(lambda s, k: acting.generate_unroll(wrapped, s, zero_policy, k, 6,
                                                              extra_fields=("truncation",)))(state, jax.random.PRNGKey(3))
    assert set(final.metrics) == set(state.metrics) and "reward" in final.metrics
    assert np.asarray(data.extras["state_extras"]["truncation"])[3].all()  # the wrapper's 4-step cut is a truncation
    np.testing.assert_array_equal(np.asarray(final.obs["privileged_state"])[:, :n], np.asarray(final.obs["state"]))


@pytest.mark.slow
def test_brax_ppo_train_improves_the_return_with_the_jax_shim():
    """brax's own PPO on the adapter (after ``jax_compat_for_brax_ppo``): 40k steps lift the
    deterministic evaluation return well above the untrained policy's (≈ 30 s with a warm compile cache)."""
    from brax.training.agents.ppo import train as brax_ppo

    envs.jax_compat_for_brax_ppo()
    returns = []
    brax_ppo.train(environment=envs.load("grasp-kinematic"), num_timesteps=40_000, episode_length=200, num_envs=64,
                   unroll_length=16, batch_size=64, num_minibatches=4, num_updates_per_batch=2, learning_rate=3e-4,
                   entropy_cost=1e-3, num_evals=2, num_eval_envs=32, normalize_observations=True, seed=0,
                   progress_fn=lambda step, metrics: returns.append(float(metrics["eval/episode_reward"])))
    assert len(returns) == 2 and all(np.isfinite(returns))
    assert returns[1] > returns[0] + 2.0, returns
