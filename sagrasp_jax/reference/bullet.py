"""PyBullet helpers the reference env and the deploy twin share: primitives in MuJoCo's size convention,
quaternions, a client's disconnect.  Needs only pybullet (the ``twin`` extra); no gymnasium, no mujoco.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sagrasp_jax.base import extras

extras.require("twin", what="the PyBullet helpers")
import pybullet as pb  # noqa: E402

from sagrasp_jax.task.robot import BOX, CAPSULE, CYLINDER, SPHERE  # noqa: E402


def rotation_to_quaternion(rot: np.ndarray) -> tuple[float, float, float, float]:
    """3×3 rotation → PyBullet quaternion (x, y, z, w); Shepperd's method, stable for any angle."""
    m = np.asarray(rot, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        w, x, y, z = 0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        w, x, y, z = (m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        w, x, y, z = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        w, x, y, z = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s
    return (x, y, z, w)


def quaternions_to_rotations(quats: np.ndarray) -> np.ndarray:
    """(..., 4) PyBullet quaternions (x, y, z, w) → (..., 3, 3) rotations, vectorised."""
    q = np.asarray(quats, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ]
    return np.stack(rows, -2)


def shape_kwargs(kind: int, size: Any, visual: bool) -> dict[str, Any]:
    """createCollisionShape / createVisualShape arguments for a primitive in MuJoCo's size convention."""
    size = [float(v) for v in size]
    if kind == SPHERE:
        return {"shapeType": pb.GEOM_SPHERE, "radius": size[0]}
    if kind == BOX:
        return {"shapeType": pb.GEOM_BOX, "halfExtents": size}
    if kind in (CYLINDER, CAPSULE):
        length_key = "length" if visual else "height"  # PyBullet names the same thing differently
        shape = pb.GEOM_CYLINDER if kind == CYLINDER else pb.GEOM_CAPSULE
        return {"shapeType": shape, "radius": size[0], length_key: 2 * size[1]}
    raise ValueError(f"unknown primitive kind {kind}")


def disconnect(client: int) -> int:
    """Disconnect a PyBullet client if it is connected (idempotent); returns -1, the "closed" id."""
    if client >= 0:
        try:
            pb.disconnect(physicsClientId=client)
        except pb.error:
            pass
    return -1
