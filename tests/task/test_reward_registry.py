"""The reward-term registry (``reward.terms``): a term added by one ``RewardTerm`` entry, from outside the
package, is paid in the reward and reported by the episode tracker, both envs, the parity harness and a real
training's metrics.jsonl; the registry is as it was after the block; malformed entries are refused."""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401  (XLA flags before jax)
from sagrasp_jax.task import config
from sagrasp_jax.task import episode
from sagrasp_jax.task import reward
from sagrasp_jax.task.config import RewardConfig

from tiny_run import TINY_ARGS

DEFAULT_KEYS = ("r_distance", "r_success", "r_obstacle")
TOY_SCALE = -0.05  # per metre of approach potential left after the step


def remaining_distance_cost(xp, cfg: RewardConfig, step: reward.StepInputs):
    """A toy per-step term: −0.05 per metre still to go.  Never zero: the gripper never sits exactly on the
    cube's centre (the success pose is 5–20 mm above it)."""
    return TOY_SCALE * step.d_now


def unit_weight(p, cfg: RewardConfig):
    return 1.0 + 0 * p


TOY = reward.RewardTerm("r_toy", "f_toy", remaining_distance_cost, unit_weight)  # the one registry entry


def _step(**kw):
    args = dict(progress=0.3, d_prev=0.30, d_now=0.28, collision=False, success=False, timeout=False,
                obstacle_dist=1.0, prev_obstacle_dist=1.0, obstacle_present=False, clean_so_far=True)
    return reward.step_reward(np, RewardConfig(), **(args | kw))


def test_a_registered_term_is_paid_and_reported_inside_the_block_only():
    total0, terms0 = _step()
    with reward.registered(TOY) as registry:
        assert registry[-1] is TOY and reward.term_keys() == DEFAULT_KEYS + ("r_toy",)
        assert episode.episode_keys()[:5] == ("return",) + DEFAULT_KEYS + ("r_toy",)
        total, terms = _step()
    assert total == pytest.approx(total0 + 1.0 * TOY_SCALE * 0.28, abs=1e-15)  # F_toy = 1 · (−0.05 · 0.28 m)
    assert terms.values["r_toy"] == pytest.approx(-0.014) and terms.weights["f_toy"] == 1.0
    assert {k: terms.values[k] for k in DEFAULT_KEYS} == terms0.values  # the other terms untouched
    assert reward.terms() == reward.DEFAULT_TERMS and "r_toy" not in episode.episode_keys()
    assert "r_toy" not in _step()[1].values


def test_the_registry_is_restored_after_an_error_in_the_block():
    with pytest.raises(RuntimeError, match="inside"):
        with reward.registered(TOY):
            raise RuntimeError("inside")
    assert reward.terms() == reward.DEFAULT_TERMS


@pytest.mark.parametrize("term, error", [
    (dataclasses.replace(TOY, key="toy"), "key must be 'r_' \\+ an identifier, got 'toy'"),
    (dataclasses.replace(TOY, key="r_dist ance"), "key must be 'r_' \\+ an identifier"),
    (dataclasses.replace(TOY, key="r_distance"), "key 'r_distance' is already registered"),
    (dataclasses.replace(TOY, weight_key="f_d"), "weight_key 'f_d' is already registered"),
    (dataclasses.replace(TOY, weight_key="toy"), "weight_key must be 'f_' \\+ an identifier"),
    (dataclasses.replace(TOY, value=None), "value and weight must be callables"),
    ("r_toy", "must be a reward.RewardTerm, got str"),
])
def test_malformed_or_taken_terms_are_refused(term, error):
    with pytest.raises((ValueError, TypeError), match=error):
        with reward.registered(term):
            pass
    assert reward.terms() == reward.DEFAULT_TERMS


def test_a_term_in_another_dtype_is_refused_by_name():
    loose = dataclasses.replace(TOY, value=lambda xp, cfg, step: -0.01)  # a Python float, not the step's float64
    with reward.registered(loose), pytest.raises(TypeError, match="reward term 'r_toy' returned float"):
        _step()


def _small_env_config(max_steps: int = 6, preset: str = "cpu-quick") -> config.EnvConfig:
    env = config.get_config(preset).env
    return dataclasses.replace(env, task=dataclasses.replace(env.task, max_steps=max_steps))


def test_mjx_env_metrics_and_episode_tracker_report_the_registered_term():
    import jax
    import jax.numpy as jnp

    from sagrasp_jax.envs.grasp_env import GraspEnv

    with reward.registered(TOY):
        env = GraspEnv(_small_env_config())
        state = jax.jit(env.reset)(jax.random.PRNGKey(3))
        assert state.metrics["r_toy"] == 0 and state.info["tracker"].term_sums["r_toy"] == 0
        paid = []
        for _ in range(6):
            state = env.step(state, jnp.full(6, 0.3))
            metrics = state.metrics
            assert float(metrics["r_toy"]) == pytest.approx(TOY_SCALE * float(state.info["tracker"].d_prev), rel=1e-6)
            assert float(metrics["r_toy"]) < -1e-4  # the potential is a distance of centimetres at least
            paid.append(float(metrics["r_toy"]))
            assert float(state.info["tracker"].term_sums["r_toy"]) == pytest.approx(sum(paid), rel=1e-5)
            if float(state.done):
                break
        assert float(state.done) == 1.0  # collision, success or the 6-step timeout
        assert set(state.info["episode"]) == set(episode.episode_keys())
        assert float(state.info["episode"]["r_toy"]) == pytest.approx(sum(paid), rel=1e-5)
        values = [float(metrics[k]) for k in DEFAULT_KEYS + ("r_toy",)]
        p = 0.0  # reset's progress
        weights = [2.0 - p, 0.5 + p, 0.5, 1.0]
        assert float(state.reward) == pytest.approx(sum(w * v for w, v in zip(weights, values)), abs=1e-6)


def test_pybullet_env_info_and_parity_columns_read_the_registry():
    pytest.importorskip("pybullet")
    from sagrasp_jax.reference import EPISODE_INFO, parity
    from sagrasp_jax.reference.pybullet_env import PyBulletGraspEnv

    assert parity.reward_keys() == ("reward",) + DEFAULT_KEYS
    with reward.registered(TOY):
        assert parity.reward_keys() == ("reward",) + DEFAULT_KEYS + ("r_toy",)
        env = PyBulletGraspEnv(_small_env_config(max_steps=3, preset="paper"), mode="kinematic")
        try:
            env.reset(seed=0)
            paid, done, info = [], False, {}
            while not done:
                _, _, term, trunc, info = env.step(np.zeros(6))
                assert info["r_toy"] == pytest.approx(TOY_SCALE * float(env._tracker.d_prev), rel=1e-9)
                paid.append(info["r_toy"])
                done = term or trunc
        finally:
            env.close()
    assert all(v < -1e-4 for v in paid)
    assert info[EPISODE_INFO]["r_toy"] == pytest.approx(sum(paid), rel=1e-9)


def test_tiny_training_logs_the_registered_term(tmp_path):
    """One registry entry, and a real (tiny) training's metrics.jsonl has the term's column (the window mean
    of the finished episodes' sums, negative like every step's value) and TensorBoard its scalar.  Episodes
    last at most 8 steps so the one 16-step iteration finishes some."""
    from sagrasp_jax import train
    from sagrasp_jax.training import run_dir

    args = [("env.task.max_steps=8" if a == "env.task.max_steps=50" else a) for a in TINY_ARGS]
    assert "env.task.max_steps=8" in args
    out = str(tmp_path / "run")
    with reward.registered(TOY):
        assert train.main(["--out", out, *args]) == 0
    rows = run_dir.read_metrics(os.path.join(out, run_dir.METRICS_FILE))
    logged = [r for r in rows if "r_toy" in r]
    assert logged, f"no r_toy column in {sorted(rows[-1])}"
    for row in logged:
        assert all(k in row for k in DEFAULT_KEYS)
        assert row["window_episodes"] > 0 and row["r_toy"] < -1e-4, json.dumps(row)
    assert reward.terms() == reward.DEFAULT_TERMS
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    folder = os.path.join(out, run_dir.TB_DIR)
    tags = {value.tag for name in os.listdir(folder) for event in EventFileLoader(os.path.join(folder, name)).Load()
            for value in event.summary.value}
    assert {"train/r_toy", "train/r_distance"} <= tags
