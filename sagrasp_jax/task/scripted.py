"""A scripted (non-learned) grasping controller: proof that the task is solvable, and a
reference action source for the parity harness.

Damped-least-squares steps toward a point above the target that descends as the horizontal
error closes (no switching chatter), keeping the gripper pointing down.  It ignores
obstacles.  The task has five rows (centre, tilt) and every gripper turns freely about its approach axis,
so an arm of more than six joints (the Panda) has self-motion the rows do not pin: there the step also pulls
the joints toward the home pose inside the Jacobian's null space (``POSTURE_GAIN``); without it the closed
loop is chaotic (a 1e-9 rad difference grew to 0.28 rad in 5 of 200 Panda episodes, none of the AUBO's; with
it, to at most 1.6e-7).  Backend-agnostic (``xp`` = numpy or jax.numpy; Jacobian by central differences)
and batched over leading dimensions of ``q`` and ``target``.
"""

from __future__ import annotations

from typing import Any

from sagrasp_jax.task import robot
from sagrasp_jax.task.config import EnvConfig

APPROACH_HEIGHT = 0.08  # m above the target centre while still off to the side
GRASP_HEIGHT = 0.0125  # m above the target centre: the middle of the success band
DESCENT_RADIUS = 0.02  # m of horizontal error over which the waypoint descends
TILT_WEIGHT = 0.3  # weight of the approach-axis tilt residual against position (m)
DAMPING = 1e-4  # λ² of the damped least squares
_EPS = 1e-6  # central-difference step, rad
POSTURE_GAIN = 0.5  # fraction of the null-space distance to the home pose closed per step (arms of > 6 joints)
FREE_ROWS = 6  # the task's five residual rows and the gripper's free yaw: an arm with more joints is redundant


def scripted_action(xp: Any, cfg: EnvConfig, q: Any, target: Any) -> Any:
    """Action(s) in [-1, 1]^dof for joints ``q`` (..., dof) and target centres (..., 3)."""
    model = robot.load_robot(cfg.robot)
    q = xp.asarray(q)
    target = xp.asarray(target, dtype=q.dtype)
    centre = robot.forward_kinematics(xp, model, q).gripper_centre
    horizontal = xp.sqrt(xp.sum((centre[..., :2] - target[..., :2]) ** 2, axis=-1))
    height = GRASP_HEIGHT + APPROACH_HEIGHT * xp.clip(horizontal / DESCENT_RADIUS, 0.0, 1.0)
    goal = target + xp.asarray([0.0, 0.0, 1.0], dtype=q.dtype) * height[..., None]

    def residual(qs: Any, g: Any) -> Any:
        kin = robot.forward_kinematics(xp, model, qs)
        return xp.concatenate([kin.gripper_centre - g, TILT_WEIGHT * kin.approach_axis[..., :2]], axis=-1)

    dof = q.shape[-1]
    eye = xp.eye(dof, dtype=q.dtype)
    probes = q[..., None, :] + _EPS * xp.concatenate([eye, -eye])  # (..., 2 dof, dof)
    res = residual(probes, goal[..., None, :])
    jac = xp.swapaxes(res[..., :dof, :] - res[..., dof:, :], -1, -2) / (2 * _EPS)  # (..., 5, dof)
    r = residual(q, goal)
    lhs = jac @ xp.swapaxes(jac, -1, -2) + DAMPING * xp.eye(5, dtype=q.dtype)
    jac_t = xp.swapaxes(jac, -1, -2)
    dq = (jac_t @ xp.linalg.solve(lhs, -r[..., None]))[..., 0]
    if dof > FREE_ROWS:  # self-motion toward home, projected onto the null space of the task rows
        to_home = xp.asarray(cfg.task.home_q, dtype=q.dtype) - q
        along_task = (jac_t @ xp.linalg.solve(lhs, (jac @ to_home[..., None])))[..., 0]
        dq = dq + POSTURE_GAIN * (to_home - along_task)
    return xp.clip(dq / cfg.control.q_max, -1.0, 1.0)
