"""Safety layer: dangerous joint commands are refused with a clear message, never clipped."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sagrasp_jax.task.config import HOME_GRIPPER_CENTRE, HOME_Q, EnvConfig
from sagrasp_jax.deploy.safety import (
    DeploySettings,
    PolicyMismatch,
    SafetyLayer,
    SafetyViolation,
    WorkspaceBox,
    check_policy_constants,
)
from sagrasp_jax.task.robot import forward_kinematics, load_robot, solve_home_pose

HOME = np.array(HOME_Q)


def _ik(point) -> np.ndarray:
    """Gripper centre at ``point``, pointing down: IK continued from home in small moves so it
    stays on the home pose's elbow-up branch, as a real approach would."""
    q = HOME
    start = np.array(HOME_GRIPPER_CENTRE)
    for s in np.linspace(0.1, 1.0, 10):
        q = solve_home_pose(q, start + s * (np.asarray(point) - start))
    q = (q + np.pi) % (2 * np.pi) - np.pi  # same pose; q1 passes ±π behind the robot
    np.testing.assert_allclose(forward_kinematics(np, load_robot(), q).gripper_centre, point, atol=1e-6)
    return q


@pytest.fixture(scope="module")
def layer() -> SafetyLayer:
    return SafetyLayer()


def test_valid_command_passes_unchanged(layer):
    step = np.array([0.05, -0.05, 0.03, -0.02, 0.049, -0.05])
    q = layer.check(HOME + step, HOME)
    np.testing.assert_array_equal(q, HOME + step)
    layer.check_pose(HOME, "home pose")


@pytest.mark.parametrize(
    "point",
    [(0.35, -0.60, 0.035), (-0.35, -0.60, 0.035), (0.35, -0.25, 0.035), (-0.35, -0.25, 0.035), (0.0, -0.62, 0.03)],
)
def test_trained_region_is_inside_the_workspace(layer, point):
    """Grasp poses over the corners of the sampled target region must pass every rule."""
    layer.check_pose(_ik(point))


def test_joint_limit_refused(layer):
    q_prev = HOME.copy()
    q_prev[0] = 3.03
    q = q_prev.copy()
    q[0] = 3.07
    with pytest.raises(SafetyViolation, match=r"joint 1 \(shoulder_joint\) = 3\.0700 rad is outside its limit \[-3\.0543, 3\.0543\]"):
        layer.check(q, q_prev)
    q = HOME.copy()
    q[5] = 3.0543  # exactly at the limit (what the control step's clip produces) is allowed
    layer.check_pose(q)


def test_too_fast_refused(layer):
    q = HOME.copy()
    q[1] += 0.06
    with pytest.raises(SafetyViolation, match=r"joint 2 \(upperArm_joint\) moves 0\.0600 rad in one step, over the limit 0\.0500"):
        layer.check(q, HOME)
    q = HOME.copy()
    q[4] -= 0.0501
    with pytest.raises(SafetyViolation, match=r"joint 5 \(wrist2_joint\)"):
        layer.check(q, HOME)


def test_step_limit_is_velocity_times_dt_when_smaller_than_max_step():
    layer = SafetyLayer(DeploySettings(max_step=0.2))
    # 2.5964 rad/s × 0.05 s = 0.12982 (J1-J3); 3.1105 × 0.05 = 0.155525 (J4-J6).
    np.testing.assert_allclose(layer.step_limit, [0.12982] * 3 + [0.155525] * 3)
    assert np.all(SafetyLayer().step_limit == 0.05)
    q = HOME.copy()
    q[0] += 0.13
    with pytest.raises(SafetyViolation, match=r"over the limit 0\.1298 rad = min\(velocity 2\.5964 rad/s × 0\.05 s, max step 0\.2"):
        layer.check(q, HOME)


def test_limits_never_come_from_a_policy_config():
    """Issue 16 #8: a policy's env config (here one claiming q_max = 0.5) can neither be passed as the
    layer's limits nor get past the deployment's constants."""
    base = EnvConfig()
    loose = dataclasses.replace(base, control=dataclasses.replace(base.control, q_max=0.5, control_dt=0.2))
    with pytest.raises(TypeError, match="never from a policy"):
        SafetyLayer(loose)
    with pytest.raises(PolicyMismatch, match=r"env.control.q_max \(rad per step\): policy 0.5, deployment 0.05.*"
                                             r"env.control.control_dt \(s\): policy 0.2, deployment 0.05"):
        check_policy_constants(loose)
    wide = dataclasses.replace(base, control=dataclasses.replace(base.control, q_limit=3.14))
    with pytest.raises(PolicyMismatch, match=r"q_limit \(rad\): policy 3.14, URDF joint limit 3.0543"):
        check_policy_constants(wide)
    check_policy_constants(base)  # the training defaults are this robot's


def test_out_of_workspace_refused(layer):
    with pytest.raises(SafetyViolation, match=r"gripper centre x = 0\.5500 m is outside the workspace box \[-0\.500, 0\.500\]"):
        layer.check_pose(_ik((0.55, -0.20, 0.35)))
    with pytest.raises(SafetyViolation, match=r"gripper centre y = 0\.3200 m .* \[-0\.850, 0\.300\]"):
        layer.check_pose(_ik((0.45, 0.32, 0.40)))
    # Zero pose: arm straight up, gripper centre at z = 1.0085 m (flange checkpoint of docs/task.md §1).
    with pytest.raises(SafetyViolation, match=r"gripper centre z = 1\.0085 m .* \[0\.000, 1\.000\]"):
        layer.check_pose(np.zeros(6))
    roomy = SafetyLayer(workspace=WorkspaceBox(upper=(0.5, 0.3, 1.2)))
    roomy.check_pose(np.zeros(6))
    with pytest.raises(ValueError, match="must be below"):
        WorkspaceBox(lower=(0.0, 0.0, 0.0), upper=(1.0, 1.0, 0.0))


def test_table_refused(layer):
    """Gripper centre 1 cm above the table: inside the box, but the fingertips are in the table."""
    with pytest.raises(SafetyViolation, match=r"(left|right)_finger/0 reaches z = -0\.00\d+ m, not above the table"):
        layer.check_pose(_ik((0.0, -0.45, 0.010)))
    layer.check_pose(_ik((0.0, -0.45, 0.030)))  # the lowest success height clears it


def test_nan_and_shape_refused(layer):
    q = HOME.copy()
    q[2] = np.nan
    with pytest.raises(SafetyViolation, match=r"NaN/inf for joint 3 \(foreArm_joint\)"):
        layer.check(q, HOME)
    with pytest.raises(SafetyViolation, match="6 joint values"):
        layer.check(HOME[:5], HOME)


def test_collision_hook(layer):
    seen = []

    def hook(q: np.ndarray) -> str | None:
        seen.append(q)
        return "wrist1 hits the upper arm" if q[3] > 0.26 else None

    guarded = SafetyLayer(collision_check=hook)
    guarded.check(HOME, HOME)
    q = HOME.copy()
    q[3] += 0.03
    with pytest.raises(SafetyViolation, match="wrist1 hits the upper arm"):
        guarded.check(q, HOME)
    assert len(seen) == 2
