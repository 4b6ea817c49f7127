"""A scripted (non-learned) IK controller, used to prove the task is solvable through ``env.step``."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from sagrasp_jax import robot
from sagrasp_jax.config import EnvConfig

APPROACH_HEIGHT = 0.08  # m above the target centre before descending
GRASP_HEIGHT = 0.0125  # m above the target centre: middle of the success band


def scripted_action(cfg: EnvConfig, q: jax.Array, target: jax.Array) -> jax.Array:
    """Damped-least-squares step toward a waypoint above the target, then down to it,
    keeping the gripper pointing down; returned as an action in [-1, 1]^6."""
    model = robot.load_robot()

    def residual(qv: jax.Array, goal: jax.Array) -> jax.Array:
        kin = robot.forward_kinematics(jnp, model, qv)
        return jnp.concatenate([kin.gripper_centre - goal, 0.3 * kin.approach_axis[:2]])

    kin = robot.forward_kinematics(jnp, model, q)
    horizontal = jnp.linalg.norm(kin.gripper_centre[:2] - target[:2])
    # descend as the horizontal error closes: a smooth schedule, no switching chatter
    height = GRASP_HEIGHT + APPROACH_HEIGHT * jnp.clip(horizontal / 0.02, 0.0, 1.0)
    goal = target + jnp.array([0.0, 0.0, 1.0]) * height
    r = residual(q, goal)
    jac = jax.jacfwd(residual)(q, goal)
    dq = jac.T @ jnp.linalg.solve(jac @ jac.T + 1e-4 * jnp.eye(5), -r)
    return jnp.clip(dq / cfg.control.q_max, -1.0, 1.0)
