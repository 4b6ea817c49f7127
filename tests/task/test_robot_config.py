"""``env.robot`` chooses the arm: ``--set robot=NAME`` sets it and the per-joint keys to that robot's values; a
per-joint key with another robot's joint count is refused naming both; the env follows the robot."""

import dataclasses

import numpy as np
import pytest

from sagrasp_jax.task import config, config_history, robot, robots
from sagrasp_jax.task.config_parse import apply_overrides

# The AUBO-i5 under another name with another start pose: a second registered robot of the same joint count.
TWIN_ARM = dataclasses.replace(robots.AUBO_I5, name="aubo_variant", home_q=tuple(v + 0.01 for v in robots.AUBO_I5.home_q),
                               servo=dataclasses.replace(robots.AUBO_I5.servo, lag_gain=(0.5,) * 6))


def test_the_default_robot_is_the_aubo_and_keeps_old_hashes():
    cfg = config.get_config("cpu-quick")
    assert cfg.env.robot == "aubo_i5" and cfg.env.task.home_q == robots.AUBO_I5.home_q
    assert config_history.ADDED_KEYS["env.robot"] == "aubo_i5"  # an old config (no env.robot) meant the AUBO
    assert "robot" not in config_history.identity_dict(cfg)["env"]  # so its identity does not change


def test_setting_the_robot_sets_its_per_joint_keys_unless_given():
    with robots.registered(TWIN_ARM):
        cfg = apply_overrides(config.get_config("cpu-quick"), ["robot=aubo_variant"])
        assert cfg.env.robot == "aubo_variant"
        assert cfg.env.task.home_q == TWIN_ARM.home_q and cfg.env.control.lag_gain == (0.5,) * 6
        mine = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6)
        cfg = apply_overrides(config.get_config("cpu-quick"), ["env.robot=aubo_variant", f"env.task.home_q={','.join(map(str, mine))}"])
        assert cfg.env.task.home_q == mine and cfg.env.control.lag_gain == (0.5,) * 6  # given: kept; the rest: the robot's
    with pytest.raises(config.ConfigError, match="aubo_variant.*not one of aubo_i5"):  # unregistered again after the block
        apply_overrides(config.get_config("cpu-quick"), ["robot=aubo_variant"])


def test_a_per_joint_key_of_the_wrong_length_names_the_robot():
    with pytest.raises(config.ConfigError, match=r"env.task.home_q has 7 values; env.robot=aubo_i5 has 6 joints"):
        apply_overrides(config.get_config("cpu-quick"), ["env.task.home_q=0,0,0,0,0,0,0"])


def test_an_unknown_robot_lists_the_registered_ones():
    with pytest.raises(config.ConfigError, match="env.robot='ur5e' is not one of aubo_i5"):
        apply_overrides(config.get_config("cpu-quick"), ["robot=ur5e"])
    with pytest.raises(robots.UnknownRobot, match="unknown robot 'ur5e'; registered: aubo_i5"):
        robot.load_robot("ur5e")


def test_register_refuses_a_spec_whose_per_joint_values_miss_a_joint():
    with pytest.raises(ValueError, match="home_q and home_seed need 6 values"):
        robots.register(dataclasses.replace(TWIN_ARM, home_q=TWIN_ARM.home_q[:5]))
    with pytest.raises(ValueError, match="servo.kp needs 6 values"):
        robots.register(dataclasses.replace(TWIN_ARM, servo=dataclasses.replace(TWIN_ARM.servo, kp=(1.0,))))
    with pytest.raises(ValueError, match="fine_tune_joints"):
        robots.register(dataclasses.replace(TWIN_ARM, fine_tune_joints=(3, 5)))
    assert "aubo_variant" not in robots.names()


def test_the_env_reads_the_robot_it_is_given():
    import jax

    from sagrasp_jax.envs.grasp_env import GraspEnv

    with robots.registered(TWIN_ARM):
        cfg = apply_overrides(config.get_config("cpu-quick"), ["robot=aubo_variant", "env.task.start_noise=0"])
        env = GraspEnv(cfg.env)
        assert env.robot.name == "aubo_variant" and env.action_size == 6
        state = env.reset(jax.random.PRNGKey(0))
        np.testing.assert_allclose(np.asarray(state.info["q_target"]), np.asarray(robots.AUBO_I5.home_q) + 0.01, atol=1e-6)
