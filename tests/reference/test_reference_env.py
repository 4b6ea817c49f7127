"""The PyBullet reference env (docs/task.md §1-§2): Gymnasium contract, same starts as the JAX env,
PyBullet's own kinematics, collisions, both control modes, episode metrics, rendering."""

from __future__ import annotations

import dataclasses
import math
import os

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401  (XLA flags before jax)

pytest.importorskip("pybullet")
gym = pytest.importorskip("gymnasium")

from sagrasp_jax.task import config  # noqa: E402
from sagrasp_jax.task import observation  # noqa: E402
from sagrasp_jax.task import robot  # noqa: E402
from sagrasp_jax.task import sampling  # noqa: E402
from sagrasp_jax.reference import ENV_ID, ENV_IDS, EPISODE_INFO, MAX_EPISODE_STEPS  # noqa: E402
from sagrasp_jax.task.episode import episode_keys
from sagrasp_jax.reference.pybullet_env import PyBulletGraspEnv  # noqa: E402
from paths import REPO  # noqa: E402

ROBOT = robot.load_robot()


def env_config(mode: str = "kinematic", noise: float | None = 0.0, obstacle_prob: float | None = None,
               max_steps: int | None = None) -> config.EnvConfig:
    cfg = config.get_config("paper").env
    task = cfg.task if noise is None else dataclasses.replace(cfg.task, obs_noise_std=noise)
    if max_steps is not None:
        task = dataclasses.replace(task, max_steps=max_steps)
    samp = cfg.sampling if obstacle_prob is None else dataclasses.replace(cfg.sampling, obstacle_prob=obstacle_prob)
    return dataclasses.replace(cfg, control=dataclasses.replace(cfg.control, mode=mode), task=task, sampling=samp)


def explicit_spec(q0, target=(0.1, -0.45, 0.025), obstacle=None) -> sampling.ResetSpec:
    """An explicit reset with at most one obstacle ``(kind, centre, size)``."""
    return sampling.ResetSpec(
        q0=np.asarray(q0, float), target_pos=np.asarray(target, float), target_yaw=np.array(0.3),
        obstacle_active=np.array([obstacle is not None, False]),
        obstacle_kind=np.array([obstacle[0] if obstacle else robot.SPHERE, robot.SPHERE]),
        obstacle_pos=np.array([obstacle[1] if obstacle else (0, 0, -5), (0, 0, -5)], float),
        obstacle_yaw=np.zeros(2),
        obstacle_size=np.array([obstacle[2] if obstacle else (0.05, 0, 0), (0.05, 0, 0)], float),
        redraws=np.array(0), fallback=np.array(False),
    )


@pytest.fixture(scope="module")
def kin_env():
    env = PyBulletGraspEnv(env_config())
    yield env
    env.close()


@pytest.mark.parametrize("layout", observation.LAYOUT_NAMES)
def test_registered_per_layout_and_check_env_passes_with_its_defaults(layout):
    """One id per observation layout; Gymnasium's checker with its defaults (render check
    included) passes on this headless machine: ``human`` is advertised only with a display."""
    from gymnasium.utils.env_checker import check_env

    env = gym.make(ENV_IDS[layout])
    try:
        check_env(env.unwrapped)
        assert env.observation_space.shape == (len(observation.layout(layout)),) and env.action_space.shape == (6,)
        assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)
        assert env.unwrapped.render_mode is None
    finally:
        env.close()
    assert {"paper": 17, "relative": 29}.get(layout, len(observation.layout(layout))) == len(observation.layout(layout))
    if not os.environ.get("DISPLAY"):
        assert "human" not in env.unwrapped.metadata["render_modes"]


@pytest.mark.parametrize("env_id", [*ENV_IDS.values(), ENV_ID])
def test_gymnasium_time_limit_and_episode_statistics_on_every_id(env_id):
    """Every registered id: TimeLimit at the env's own timeout (``max_episode_steps``), and
    RecordEpisodeStatistics, single and vector, at the end of an episode ended by the env itself
    (a 5-step timeout) and by a shorter TimeLimit: Gymnasium's ``info["episode"]`` is theirs, the task's
    metrics stay under ``info["task_episode"]``."""
    from gymnasium.wrappers import RecordEpisodeStatistics, TimeLimit
    from gymnasium.wrappers.vector import RecordEpisodeStatistics as VectorEpisodeStatistics

    assert gym.spec(env_id).max_episode_steps == MAX_EPISODE_STEPS == config.get_config("paper").env.task.max_steps
    env = gym.make(env_id)
    try:
        assert isinstance(env, TimeLimit) and env.spec.max_episode_steps == MAX_EPISODE_STEPS
    finally:
        env.close()
    zero = np.zeros(6, np.float32)
    # ended by the env (its timeout): both dicts on the last step, the same return
    env = RecordEpisodeStatistics(gym.make(env_id, cfg=env_config(max_steps=5), max_episode_steps=5))
    try:
        env.reset(seed=0)
        total, steps, done = 0.0, 0, False
        while not done:
            _, reward, term, trunc, info = env.step(zero)
            total, steps, done = total + reward, steps + 1, term or trunc
        assert steps <= 5 and info["episode"]["l"] == steps and info["episode"]["r"] == pytest.approx(total)
        assert info[EPISODE_INFO]["steps"] == steps and info[EPISODE_INFO]["return"] == pytest.approx(total, abs=1e-5)
    finally:
        env.close()
    # cut by a shorter TimeLimit, then the vector wrapper over two envs
    env = RecordEpisodeStatistics(gym.make(env_id, max_episode_steps=3))
    try:
        env.reset(seed=0)
        for _ in range(3):
            _, _, term, trunc, info = env.step(zero)
        assert trunc and not term and info["episode"]["l"] == 3
    finally:
        env.close()
    envs = VectorEpisodeStatistics(gym.make_vec(env_id, num_envs=2, vectorization_mode="sync", max_episode_steps=3))
    try:
        envs.reset(seed=0)
        for _ in range(3):
            _, _, term, trunc, info = envs.step(np.zeros((2, 6), np.float32))
        assert np.all(term | trunc) and info["_episode"].all() and np.all(info["episode"]["l"] <= 3)
    finally:
        envs.close()


def test_plain_id_is_the_paper_layout():
    env = gym.make(ENV_ID)
    try:
        assert env.observation_space.shape == (17,)
    finally:
        env.close()


def test_seeded_resets_are_reproducible_and_build_the_obstacles():
    env = PyBulletGraspEnv(env_config(noise=None, obstacle_prob=1.0))
    try:
        a, info_a = env.reset(seed=5)
        b, info_b = env.reset(seed=5)
        np.testing.assert_array_equal(a, b)  # noise included: it comes from np_random too
        spec = info_a["reset_spec"]
        assert len(env._obstacle_bodies) == int(spec.obstacle_active.sum()) >= 1
        assert np.abs(a[:6] - spec.q0).max() > 0  # σ = 0.005 rad joint noise is on by default
        c, _ = env.reset(seed=6)
        assert not np.allclose(a[9:12], c[9:12])  # a different seed, a different target
    finally:
        env.close()


def test_pybullet_link_frames_match_project_kinematics(kin_env):
    """The Kinematics built from PyBullet's link states equals the URDF FK (float64, ~1e-8 m)."""
    kin_env.reset(options={"reset_spec": explicit_spec(config.HOME_Q)})
    rng = np.random.default_rng(0)
    for q in rng.uniform(-3.0, 3.0, (20, 6)):
        kin_env.force_state(q, q)
        got, want = kin_env.kinematics(), robot.forward_kinematics(np, ROBOT, q)
        for name in got._fields:
            np.testing.assert_allclose(getattr(got, name), getattr(want, name), atol=1e-6, err_msg=name)


def test_same_reset_spec_gives_the_same_first_observation_as_the_jax_env():
    import jax

    from sagrasp_jax.envs.grasp_env import GraspEnv

    cfg = env_config(obstacle_prob=0.5)
    jax_env = GraspEnv(cfg)
    reset_to = jax.jit(jax_env.reset_to)
    env = PyBulletGraspEnv(cfg)
    rng = np.random.default_rng(1)
    n = sampling.uniforms_needed(cfg.sampling)
    try:
        with_obstacles = 0
        for i in range(12):
            spec = sampling.sample_reset(np, ROBOT, cfg.sampling, cfg.task, rng.random(n))
            with_obstacles += bool(spec.obstacle_active.any())
            obs_pb, _ = env.reset(options={"reset_spec": spec})
            obs_jax = np.asarray(reset_to(spec, jax.random.PRNGKey(i)).obs)
            np.testing.assert_allclose(obs_pb, obs_jax, atol=1e-5)
        assert with_obstacles >= 3
    finally:
        env.close()


def test_obstacle_at_the_gripper_is_a_collision_in_both_envs():
    """An obstacle placed on the gripper centre: both envs end the first step with a collision
    verdict and the hit attributed to the obstacle; PyBullet's own distance query agrees."""
    import jax
    import jax.numpy as jnp

    from sagrasp_jax.envs.grasp_env import GraspEnv

    cfg = env_config()
    home = np.array(config.HOME_Q)
    centre = robot.forward_kinematics(np, ROBOT, home).gripper_centre
    spec = explicit_spec(home, obstacle=(robot.SPHERE, centre, (0.05, 0.0, 0.0)))
    env = PyBulletGraspEnv(cfg)
    try:
        obs, _ = env.reset(options={"reset_spec": spec})
        assert obs[15] < 0  # Δpo: overlapping
        assert env.pybullet_distance()["obstacle_0"] < 0  # PyBullet's own geometry overlaps too
        _, rew, term, trunc, info = env.step(np.zeros(6))
        assert term and not trunc and info["collision"] and info["hits"]["obstacle"]
        assert info[EPISODE_INFO]["hit_obstacle"] == 1.0 and info[EPISODE_INFO]["collision"] == 1.0
    finally:
        env.close()
    jax_env = GraspEnv(cfg)
    state = jax.jit(jax_env.reset_to)(spec, jax.random.PRNGKey(0))
    state = jax.jit(jax_env.step)(state, jnp.zeros(6))
    assert float(state.done) == 1.0
    assert float(state.info["episode"]["collision"]) == 1.0 and float(state.info["episode"]["hit_obstacle"]) == 1.0
    assert float(state.reward) == pytest.approx(float(rew), abs=1e-4)


def test_a_clear_start_is_not_a_collision(kin_env):
    obs, _ = kin_env.reset(options={"reset_spec": explicit_spec(config.HOME_Q)})
    _, _, term, _, info = kin_env.step(np.zeros(6))
    assert not term and not any(info["hits"].values())
    dist = kin_env.pybullet_distance()
    assert dist["table"] > 0.05 and dist["target"] > 0.1  # the upper arm passes 6 cm above the table


def test_timeout_ends_the_episode_with_its_metrics():
    env = PyBulletGraspEnv(env_config(max_steps=5))
    try:
        env.reset(options={"reset_spec": explicit_spec(config.HOME_Q), "progress": 0.5})
        for t in range(5):
            _, _, term, trunc, info = env.step(np.zeros(6))
            assert term is False  # Gymnasium's time-limit convention: a timeout truncates
            assert trunc is (t == 4)
        ep = info[EPISODE_INFO]
        assert set(ep) == set(episode_keys())
        assert ep["timeout"] == 1.0 and ep["steps"] == 5.0 and ep["success"] == 0.0 and info["is_success"] is False
        # zero action, no movement: the return is the weighted −1 timeout verdict alone (F_s = 0.5 + p)
        assert ep["return"] == pytest.approx(-1.0 * (0.5 + 0.5), abs=1e-9)
        with pytest.raises(RuntimeError):
            env.step(np.zeros(6))
    finally:
        env.close()


def test_dynamic_mode_holds_and_tracks_the_target():
    """The MJX servo law on PyBullet's dynamics (gravity on, torque limits from the MJCF): holds the
    start pose against gravity and follows a moving joint target with a lag of a few hundredths of a radian."""
    env = PyBulletGraspEnv(env_config(mode="dynamic"))
    try:
        env.reset(options={"reset_spec": explicit_spec(config.HOME_Q)})
        for _ in range(10):
            env.step(np.zeros(6))
        q, _ = env._measure()
        assert np.abs(q - np.array(config.HOME_Q)).max() < 1e-3
        lags = []
        for _ in range(10):
            obs, _, term, _, info = env.step(np.full(6, 0.5))
            assert not term
            lags.append(np.abs(info["q_target"] - obs[:6]).max())
        assert 1e-4 < max(lags) < 0.05
        assert np.abs(obs[:6] - np.array(config.HOME_Q)).min() > 0.1  # it really moved (10 × 0.025 rad)
    finally:
        env.close()


def test_rgb_array_render_and_human_needs_a_display(monkeypatch):
    env = PyBulletGraspEnv(env_config(), render_mode="rgb_array")
    try:
        env.reset(seed=0)
        img = env.render()
        assert img.shape == (400, 640, 3) and img.dtype == np.uint8 and img.std() > 5  # the Mech-Eye's 16:10 view, 640 wide
    finally:
        env.close()
    monkeypatch.delenv("DISPLAY", raising=False)
    import sys

    if sys.platform.startswith("linux"):
        with pytest.raises(RuntimeError, match="display"):
            PyBulletGraspEnv(env_config(), render_mode="human")


def test_scripted_controller_succeeds_in_the_reference_env():
    """The harness's scripted action source really grasps (so parity exercises the success branch)."""
    from sagrasp_jax.reference.parity import scripted_actions

    cfg = env_config(obstacle_prob=0.0)
    env = PyBulletGraspEnv(cfg)
    try:
        successes, steps = 0, []
        for seed in range(3):
            obs, _ = env.reset(seed=seed)
            term = trunc = False
            while not (term or trunc):
                obs, _, term, trunc, info = env.step(scripted_actions(cfg, obs)[0])
            successes += info[EPISODE_INFO]["success"] == 1.0
            steps.append(info[EPISODE_INFO]["steps"])
        assert successes == 3 and max(steps) < 80
        assert math.isfinite(info[EPISODE_INFO]["return"])
    finally:
        env.close()


def test_sb3_baseline_explains_a_missing_extra(tmp_path):
    """Without Stable-Baselines3 the baseline script stops with the install hint, writing nothing."""
    import importlib.util
    import os
    import subprocess
    import sys

    if importlib.util.find_spec("stable_baselines3") is not None:
        pytest.skip("stable-baselines3 is installed here")
    root = REPO
    out = tmp_path / "sb3.json"
    proc = subprocess.run([sys.executable, "-m", "experiments.bench_vs_paper_stack", "sb3-baseline", "--total-steps", "10",
                           "--out", str(out)], capture_output=True, text=True, timeout=120, cwd=root)
    assert proc.returncode != 0 and "pip install -e .[baseline]" in proc.stderr
    assert not out.exists()
