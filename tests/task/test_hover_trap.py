"""The hovering trap and its fix, on the poses where a policy that hovered ended its episodes.

``tests/data/hover_poses.json`` holds 24 final poses of no-obstacle timeouts of the policy that hovered
(``train --preset cpu-quick --algo sa-ppo --total-steps 3000000 --seed 1`` before the fix: 0 % success,
94 % timeouts).  Every one stands over its cube inside the success test's position tolerances or near
them, with the gripper tilted 10-41° (the test wants ≤ 10°).  The approach shaping then paid nothing for
righting the gripper, and the env's own wrist correction moves the gripper centre off the cube, so it
costs: hovering was a local optimum.  With the tilt part of the approach potential
(``env.reward.tilt_weight``) righting in place pays, and an upright grasp from there succeeds.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sagrasp_jax.task import config
from sagrasp_jax.task import config_parse
from sagrasp_jax.task import control
from sagrasp_jax.task import reward
from sagrasp_jax.task import robot
from sagrasp_jax.task import sampling
from sagrasp_jax.envs.grasp_env import GraspEnv
from paths import DATA  # noqa: E402

HOVER_POSES = os.path.join(DATA, "hover_poses.json")


@pytest.fixture(scope="module")
def hover() -> dict:
    with open(HOVER_POSES) as f:
        return json.load(f)


@pytest.fixture(scope="module")
def model() -> robot.RobotModel:
    return robot.load_robot()


def _env_config(tilt_weight: float) -> config.EnvConfig:
    """The README preset's env in the kinematic mode without transfer errors, with this tilt weight."""
    cfg = config_parse.apply_overrides(config.get_config("cpu-quick"),
                                       list(config.KNOBS_OFF) + ["env.control.mode=kinematic"])
    return dataclasses.replace(cfg.env, reward=dataclasses.replace(cfg.env.reward, tilt_weight=tilt_weight))


def test_hover_poses_fail_only_the_tilt(hover: dict, model: robot.RobotModel) -> None:
    """The trap's signature: near the grasp point, the gripper tilted beyond the success test's 10°."""
    task = config.get_config("cpu-quick").env.task
    q = np.asarray(hover["q"])
    target = np.asarray(hover["target_pos"])
    centre, tilt = control.gripper_state(np, model, q)
    offset = centre - target
    assert np.all(np.degrees(tilt) > task.success_tilt_deg - 0.05)
    assert np.median(np.hypot(offset[:, 0], offset[:, 1])) <= task.success_xy
    assert np.all(np.abs(offset[:, 2] - 0.5 * (task.success_dz_min + task.success_dz_max)) < 0.035)  # within 3.5 cm of the band's middle
    assert not np.any(reward.success_flag(np, task, centre, target, tilt))


def test_righting_with_the_wrist_costs_shaping_without_the_tilt_potential(hover: dict, model: robot.RobotModel) -> None:
    """Zero actions over the cube: the env's wrist correction rights the gripper but moves its centre away;
    with the distance alone that is paid for by every pose (the policy learned to cancel the correction)."""
    cfg = _env_config(0.0)
    costs = []
    for q, target in zip(hover["q"], hover["target_pos"]):
        q = np.asarray(q)
        target = np.asarray(target)
        centre, tilt_before = control.gripper_state(np, model, q)
        before = reward.approach_potential(np, cfg.reward, np.linalg.norm(centre - target), tilt_before)
        for _ in range(60):
            q = control.control_step(np, model, cfg.control, q, q, target, np.zeros(6)).q_target
        centre, tilt = control.gripper_state(np, model, q)
        # at least half-way righted to the correction's threshold (it stops acting once the centre leaves d_fine)
        threshold = cfg.control.fine_tilt_deg
        assert math.degrees(float(tilt)) <= threshold + 0.5 * (math.degrees(float(tilt_before)) - threshold) + 0.5
        after = reward.approach_potential(np, cfg.reward, np.linalg.norm(centre - target), tilt)
        costs.append(cfg.reward.ratio * (after - before))
    assert min(costs) > 0.0
    assert np.median(costs) > 0.4  # ≈ 4 cm further from the cube, against a success worth F_s ≈ 0.5-1.5


def _upright_grasp_episode(env: GraspEnv, model: robot.RobotModel, q_hover: np.ndarray, target: np.ndarray,
                           yaw: float, steps: int = 40) -> tuple[float, bool, float, float]:
    """Start at the hover pose and steer the joints to the upright grasp pose over the cube (IK): the summed
    R_distance, whether the episode ended in a success, and the final distance to the cube centre and tilt."""
    goal = robot.approach_pose(model, q_hover, reward.grasp_centre(np, env.cfg.task, target), max_joint_move=1.0)
    n = env.cfg.sampling.max_obstacles
    spec = sampling.ResetSpec(
        q0=jnp.asarray(q_hover), target_pos=jnp.asarray(target), target_yaw=jnp.asarray(yaw),
        obstacle_active=jnp.zeros(n, bool), obstacle_kind=jnp.zeros(n, jnp.int32), obstacle_pos=jnp.zeros((n, 3)),
        obstacle_yaw=jnp.zeros(n), obstacle_size=jnp.full((n, 3), 0.02), redraws=jnp.asarray(0), fallback=jnp.asarray(0))
    state = env.reset_to(spec, jax.random.PRNGKey(0))
    step = jax.jit(env.step)
    gain = env.cfg.control.q_max * env.cfg.control.slow_factor
    shaping = 0.0
    for _ in range(steps):
        command = np.asarray(state.info["q_target"])
        state = step(state, jnp.asarray(np.clip((goal - command) / gain, -1.0, 1.0)))
        shaping += float(state.metrics["r_distance"])
        if bool(state.done):
            break
    return (shaping, bool(state.info["episode"]["success"]), float(state.metrics["distance"]),
            float(state.metrics["tilt"]))


def test_the_tilt_potential_pays_for_an_upright_grasp_from_the_hover(hover: dict, model: robot.RobotModel) -> None:
    """Through the env's step: an upright grasp from a hover pose succeeds, and R_distance pays for the
    righting — the tilt part of the potential — besides the distance part, which alone (tilt_weight = 0) is all
    the shaping there was."""
    rcfg = config.get_config("cpu-quick").env.reward
    assert rcfg.tilt_weight > 0.0, "the README preset must carry the hovering trap's fix"
    env = GraspEnv(_env_config(rcfg.tilt_weight))
    for i in (0, 2, 12):  # tilted 37°, 36° and 39°
        q, target, yaw = np.asarray(hover["q"][i]), np.asarray(hover["target_pos"][i]), float(hover["target_yaw"][i])
        shaping, success, d_end, tilt_end = _upright_grasp_episode(env, model, q, target, yaw)
        assert success
        centre, tilt = control.gripper_state(np, model, q)
        d_start = float(np.linalg.norm(centre - target))
        start, end = (float(reward.approach_potential(np, rcfg, d_start, tilt)),
                      float(reward.approach_potential(np, rcfg, d_end, tilt_end)))
        # the grab zone's entry bonus is paid on the potential too (paid once the gripper is also upright)
        distance_part = rcfg.ratio * (d_start - d_end) + rcfg.rc * float(start > rcfg.d_grab >= end)
        tilt_part = shaping - distance_part
        owed = rcfg.ratio * ((start - d_start) - (end - d_end))
        assert tilt_part == pytest.approx(owed, abs=2e-4)
        assert tilt_part > 0.5 * rcfg.ratio * (start - d_start) > 0.05


def test_approach_potential_counts_tilt_only_near_the_cube_and_beyond_the_free_angle() -> None:
    rcfg = config.get_config("cpu-quick").env.reward  # 0.05 m/rad beyond 10°, faded in from 10 cm
    tilted = math.radians(40.0)
    excess = math.radians(40.0 - rcfg.tilt_free_deg)
    assert float(reward.approach_potential(np, rcfg, 0.0, tilted)) == pytest.approx(rcfg.tilt_weight * excess)
    assert float(reward.approach_potential(np, rcfg, 0.5 * rcfg.tilt_near, tilted)) == pytest.approx(
        0.5 * rcfg.tilt_near + 0.5 * rcfg.tilt_weight * excess)
    assert float(reward.approach_potential(np, rcfg, rcfg.tilt_near, tilted)) == pytest.approx(rcfg.tilt_near)
    assert float(reward.approach_potential(np, rcfg, 0.3, tilted)) == pytest.approx(0.3)  # far: the distance alone
    assert float(reward.approach_potential(np, rcfg, 0.02, math.radians(9.0))) == pytest.approx(0.02)  # within 10°
    paper = config.get_config("paper").env.reward
    assert float(reward.approach_potential(np, paper, 0.02, tilted)) == 0.02  # the paper's d
    batch = reward.approach_potential(jnp, rcfg, jnp.asarray([0.0, 0.3]), jnp.asarray([tilted, tilted]))
    np.testing.assert_allclose(np.asarray(batch), [rcfg.tilt_weight * excess, 0.3], rtol=1e-6)
