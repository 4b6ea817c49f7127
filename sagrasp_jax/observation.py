"""The 17-number observation of SPEC §2, written once for the MJX env, the PyBullet
reference env and the deployment loop (``xp`` = numpy or jax.numpy; no jax import)."""

from __future__ import annotations

from typing import Any, NamedTuple

from sagrasp_jax import collision
from sagrasp_jax.config import EnvConfig
from sagrasp_jax.robot import Kinematics, RobotModel, forward_kinematics, tilt

# Entries in order; the exporter stores these names with every policy.
OBS_LAYOUT: tuple[str, ...] = (
    "q1", "q2", "q3", "q4", "q5", "q6",
    "gripper_x", "gripper_y", "gripper_z",
    "target_x", "target_y", "target_z",
    "obstacle_x", "obstacle_y", "obstacle_z",
    "d_po", "theta_gz",
)  # fmt: skip
OBS_SIZE = len(OBS_LAYOUT)


class Observed(NamedTuple):
    obs: Any  # (17,)
    kin: Kinematics
    col: collision.CollisionResult
    tilt: Any  # θgz, rad


def assemble(xp: Any, q: Any, gripper_centre: Any, target_pos: Any, col: collision.CollisionResult, theta: Any) -> Any:
    """Concatenate the entries in ``OBS_LAYOUT`` order (``q`` may already carry sensor noise)."""
    return xp.concatenate(
        [
            q,
            gripper_centre,
            xp.asarray(target_pos, dtype=gripper_centre.dtype),
            col.nearest_obstacle_pos,
            xp.reshape(col.nearest_obstacle_dist, (1,)),
            xp.reshape(theta, (1,)),
        ]
    )


def observe(xp: Any, robot: RobotModel, cfg: EnvConfig, q: Any, reset: Any, kin: Kinematics | None = None) -> Observed:
    """Noise-free observation at measured joints ``q`` for the scene ``reset`` (a ResetSpec).

    ``kin`` lets a simulator pass its own link frames (PyBullet); by default our FK of ``q``."""
    kin = forward_kinematics(xp, robot, q) if kin is None else kin
    col = collision.check(xp, robot, kin, reset, cfg)
    theta = tilt(xp, kin.approach_axis)
    return Observed(assemble(xp, q, kin.gripper_centre, reset.target_pos, col, theta), kin, col, theta)
