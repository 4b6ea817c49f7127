"""The PyBullet reference env, the physical grasp check and the parity harness serve the config's ``env.robot``
(issue 56, item 1): with the 7-joint Franka Panda they step, grasp and compare with 7-joint actions."""

from __future__ import annotations

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401  (XLA flags before jax)

pytest.importorskip("pybullet")
pytest.importorskip("gymnasium")

from sagrasp_jax.reference import EPISODE_INFO  # noqa: E402
from sagrasp_jax.reference import parity  # noqa: E402
from sagrasp_jax.reference.grasp_check import (  # noqa: E402
    GraspScene, PhysicalCheckError, physical_grasp_check, scene_xml,
)
from sagrasp_jax.reference.pybullet_env import PyBulletGraspEnv, load_servo_model  # noqa: E402
from sagrasp_jax.task import config, robot, sampling, scripted  # noqa: E402
from sagrasp_jax.task.config_parse import apply_overrides  # noqa: E402

PANDA = robot.load_robot("panda")


def panda_config(*overrides: str) -> config.EnvConfig:
    """The paper preset's env on the Panda, observation noise off."""
    return apply_overrides(config.get_config("paper"), ["robot=panda", "env.task.obs_noise_std=0", *overrides]).env


def test_reference_env_steps_a_panda_with_seven_joint_actions():
    cfg = panda_config()
    env = PyBulletGraspEnv(cfg)
    try:
        assert env.action_space.shape == (7,) and env.robot.name == "panda"
        obs, _ = env.reset(seed=0)
        assert obs.shape == env.observation_space.shape == (len(parity.observation.layout_of(cfg)),)
        q0 = obs[:7].copy()
        np.testing.assert_allclose(q0, env._spec.q0, atol=1e-9)
        action = np.array([0.5, -0.5, 0.25, 0.0, 0.0, 0.0, 1.0])
        obs, _, _, _, info = env.step(action)
        np.testing.assert_allclose(info["q_target"] - q0, action * cfg.control.q_max, atol=1e-9)
        np.testing.assert_allclose(obs[:7], info["q_target"], atol=1e-9)  # kinematic: the joints are the target
        with pytest.raises(ValueError):
            env.step(np.zeros(6))
        # PyBullet's own link frames of the Panda agree with the project's forward kinematics
        for q in np.random.default_rng(0).uniform(PANDA.q_lower, PANDA.q_upper, (5, 7)):
            env.force_state(q, q)
            got, want = env.kinematics(), robot.forward_kinematics(np, PANDA, q)
            for name in got._fields:
                np.testing.assert_allclose(getattr(got, name), getattr(want, name), atol=1e-6, err_msg=name)
    finally:
        env.close()


def scripted_grasp(cfg: config.EnvConfig, seed: int) -> tuple[sampling.ResetSpec, np.ndarray, dict]:
    """The scripted controller's episode ``seed`` in the reference env: its reset, final joints, episode record."""
    env = PyBulletGraspEnv(cfg)
    try:
        obs, _ = env.reset(seed=seed)
        term = trunc = False
        while not (term or trunc):
            obs, _, term, trunc, info = env.step(parity.scripted_actions(cfg, obs)[0])
        return env._spec, np.asarray(info["q_target"]), info[EPISODE_INFO]
    finally:
        env.close()


def test_scripted_controller_grasps_with_the_panda_in_the_reference_env():
    _, q, episode = scripted_grasp(panda_config("env.sampling.obstacle_prob=0"), 1)
    assert q.shape == (7,) and episode["success"] == 1.0 and episode["steps"] < 100


def test_dynamic_mode_reads_the_panda_servos_and_refuses_the_aubo_gains():
    servo = load_servo_model(PANDA)
    assert servo.kp.shape == (7,) and np.allclose(servo.kp, PANDA.spec.servo.kp)
    env = PyBulletGraspEnv(panda_config(), mode="dynamic")
    try:
        env.reset(seed=0)
        obs, *_ = env.step(np.zeros(7))
        assert np.isfinite(obs).all()
    finally:
        env.close()
    with pytest.raises(ValueError, match="fitted gains for 'aubo_i5' only; robot 'panda' needs position_gains"):
        PyBulletGraspEnv(panda_config(), mode="dynamic", servo="position_control")


def test_physical_grasp_check_uses_the_robots_scene_and_pads():
    cfg = panda_config("env.sampling.obstacle_prob=0")
    spec = parity.draw_resets(cfg, 1, np.random.default_rng(0))[0]
    assert np.shape(spec.q0) == (7,)
    scene = GraspScene(spec, spec.q0, arm=PANDA)
    assert scene.model.nu == 9 and scene_xml(PANDA).endswith("scene_panda.xml")  # 7 arm servos and 2 fingers
    np.testing.assert_allclose(scene.arm_q, spec.q0)
    fk = robot.forward_kinematics(np, PANDA, spec.q0)
    np.testing.assert_allclose(scene.gripper_centre, fk.gripper_centre, atol=1e-6)
    with pytest.raises(PhysicalCheckError, match=r"7 finite numbers \(panda\)"):
        GraspScene(spec, np.zeros(6), arm=PANDA)
    # the scripted controller's grasp pose in the reference env: closing and lifting there holds the cube
    spec, q, episode = scripted_grasp(cfg, 1)
    assert episode["success"] == 1.0
    result = physical_grasp_check(q, spec, arm=PANDA)
    assert result["success"], result["reason"]
    assert result["pad_contacts"] == {"left": True, "right": True}


def test_parity_harness_slices_the_panda_layout():
    cfg = panda_config()
    assert parity.joints_entries(cfg) == slice(0, 7)
    assert parity.gripper_entries(cfg) == slice(7, 10) and parity.target_entries(cfg) == slice(10, 13)
    source = parity.make_source("random", cfg, 2, 3, np.random.default_rng(0))
    assert source.fn(None, 0, np.array([0, 1])).shape == (2, 7)
    specs = parity.draw_resets(cfg, 2, np.random.default_rng(0))
    assert all(np.shape(s.q0) == (7,) and isinstance(s, sampling.ResetSpec) for s in specs)
