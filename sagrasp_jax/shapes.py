"""Dynamic-obstacle shapes: signed distance and nearest surface point, per kind, for every backend.

An obstacle is ``kind`` (robot.SPHERE | CYLINDER | BOX), a centre ``pos`` (..., 3), a yaw about
world z and a ``size`` (..., 3) in MuJoCo's convention (sphere (r, 0, 0); cylinder (r, half
height, 0) along world z; box half-extents in its yawed frame).  Cylinders and boxes stand
upright; only boxes use the yaw.

Each kind's maths is written once, on x/y/z component arrays (XLA fuses those into a few
elementwise loops; the same maths on a trailing axis of length 3 is several times slower on
CPU).  ``kind`` may be a Python int (only that shape is computed) or an integer array (every
kind is computed and the right one selected with ``where``).  ``xp`` is numpy or jax.numpy;
this module must not import jax.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from sagrasp_jax.robot import BOX, CYLINDER, SPHERE

Vec = tuple[Any, Any, Any]
KINDS = (SPHERE, CYLINDER, BOX)
_TINY = 1e-12


def _to_local(xp: Any, pos: Any, yaw: Any, points: Any) -> Vec:
    """Points (..., 3) in the obstacle frame (yaw about z), as components."""
    dx, dy, dz = points[..., 0] - pos[..., 0], points[..., 1] - pos[..., 1], points[..., 2] - pos[..., 2]
    c, s = xp.cos(yaw), xp.sin(yaw)
    return c * dx + s * dy, -s * dx + c * dy, dz


def _to_world(xp: Any, pos: Any, yaw: Any, local: Vec) -> Any:
    c, s = xp.cos(yaw), xp.sin(yaw)
    x, y, z = local
    return xp.stack([pos[..., 0] + c * x - s * y, pos[..., 1] + s * x + c * y, pos[..., 2] + z], axis=-1)


def _norm(xp: Any, *comps: Any) -> Any:
    return xp.sqrt(sum(c * c for c in comps))


# ------------------------------------------------------------------ per-kind local kernels


def _sphere_sdf(xp: Any, v: Vec, size: Any) -> Any:
    return _norm(xp, *v) - size[..., 0]


def _sphere_surface(xp: Any, v: Vec, size: Any) -> Vec:
    n = _norm(xp, *v)
    scale = size[..., 0] / xp.maximum(n, _TINY)
    at_centre = n < _TINY
    return (
        xp.where(at_centre, 0.0, v[0] * scale),
        xp.where(at_centre, 0.0, v[1] * scale),
        xp.where(at_centre, size[..., 0], v[2] * scale),
    )


def _cylinder_sdf(xp: Any, v: Vec, size: Any) -> Any:
    qr = _norm(xp, v[0], v[1]) - size[..., 0]
    qz = xp.abs(v[2]) - size[..., 1]
    return _norm(xp, xp.maximum(qr, 0.0), xp.maximum(qz, 0.0)) + xp.minimum(xp.maximum(qr, qz), 0.0)


def _cylinder_surface(xp: Any, v: Vec, size: Any) -> Vec:
    r, h = size[..., 0], size[..., 1]
    rad = _norm(xp, v[0], v[1])
    qr, qz = rad - r, xp.abs(v[2]) - h
    inside = (qr <= 0.0) & (qz <= 0.0)
    radial_face = inside & (qr >= qz)  # inside and nearer the side than a cap: push out radially
    to_side = xp.where(inside, radial_face, qr > 0.0)
    scale = xp.where(to_side, r, xp.minimum(rad, r)) / xp.maximum(rad, _TINY)
    ux = xp.where(rad < _TINY, xp.where(to_side, r, 0.0), v[0] * scale)
    uy = xp.where(rad < _TINY, 0.0, v[1] * scale)
    z = xp.where(inside & ~radial_face, xp.where(v[2] >= 0.0, h, -h), xp.clip(v[2], -h, h))
    return ux, uy, z


def _box_sdf(xp: Any, v: Vec, size: Any) -> Any:
    q = [xp.abs(v[i]) - size[..., i] for i in range(3)]
    outside = _norm(xp, *(xp.maximum(qi, 0.0) for qi in q))
    return outside + xp.minimum(xp.maximum(xp.maximum(q[0], q[1]), q[2]), 0.0)


def _box_surface(xp: Any, v: Vec, size: Any) -> Vec:
    half = [size[..., i] for i in range(3)]
    q = [xp.abs(v[i]) - half[i] for i in range(3)]
    inside = (q[0] <= 0.0) & (q[1] <= 0.0) & (q[2] <= 0.0)
    # inside: the coordinate of the nearest face goes to that face (ties: x before y before z)
    face_x = q[0] >= xp.maximum(q[1], q[2])
    face_y = ~face_x & (q[1] >= q[2])
    face_z = ~face_x & ~face_y
    out = []
    for i, face in enumerate((face_x, face_y, face_z)):
        clamped = xp.clip(v[i], -half[i], half[i])
        pushed = xp.where(v[i] >= 0.0, half[i], -half[i])
        out.append(xp.where(inside & face, pushed, clamped))
    return out[0], out[1], out[2]


_SDF: dict[int, Callable[[Any, Vec, Any], Any]] = {SPHERE: _sphere_sdf, CYLINDER: _cylinder_sdf, BOX: _box_sdf}
_SURFACE: dict[int, Callable[[Any, Vec, Any], Vec]] = {
    SPHERE: _sphere_surface, CYLINDER: _cylinder_surface, BOX: _box_surface,
}


def _select(xp: Any, kind: Any, values: dict[int, Any]) -> Any:
    out = None
    for k in KINDS:
        out = values[k] if out is None else xp.where(kind == k, values[k], out)
    return out


# ------------------------------------------------------------------------------ public


def sdf(xp: Any, kind: Any, pos: Any, yaw: Any, size: Any, points: Any) -> Any:
    """Signed distance (...,) from ``points`` (..., 3) to obstacles (negative inside).

    ``kind``/``pos``/``yaw``/``size`` broadcast against the points' batch dims."""
    v = _to_local(xp, pos, yaw, points)
    if isinstance(kind, (int, np.integer)):
        return _SDF[int(kind)](xp, v, size)
    return _select(xp, kind, {k: _SDF[k](xp, v, size) for k in KINDS})


def surface_point(xp: Any, kind: Any, pos: Any, yaw: Any, size: Any, points: Any) -> Any:
    """The point (..., 3) of the obstacle's surface nearest to each of ``points`` (inside or out)."""
    v = _to_local(xp, pos, yaw, points)
    if isinstance(kind, (int, np.integer)):
        local = _SURFACE[int(kind)](xp, v, size)
    else:
        per_kind = {k: _SURFACE[k](xp, v, size) for k in KINDS}
        local = tuple(_select(xp, kind, {k: per_kind[k][i] for k in KINDS}) for i in range(3))
    return _to_world(xp, pos, yaw, local)
