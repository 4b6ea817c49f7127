"""The dynamic-obstacle shapes: one registry entry per kind, and the shape maths for every backend.

An obstacle is ``kind`` (an ``ObstacleShape.id``), a centre ``pos`` (..., 3), a ``yaw`` about world
z and a ``size`` (..., 3) in MuJoCo's convention for the entry's primitive (sphere (r, 0, 0);
cylinder (r, half height, 0); box half-extents; capsule (r, half length of the axis, 0)).  Its
frame is the centre turned by ``yaw`` about world z; each entry says where its primitive lies in
that frame (``tilt``: the capsule lies on its side, its MuJoCo z axis along the frame's x).

Everything that differs between kinds is in the entry, and everything else reads the registry:

* sampling (``sampling.sample_reset``): which config keys give its size, how its size is drawn
  from the candidate's uniforms, whether it floats (a height range) or rests on the table
  (centre at ``half_height``), whether a yaw is drawn;
* the per-kind maths: signed distance (``sdf``), nearest surface point (``surface``), a
  bounding radius (two obstacles must not overlap), the horizontal footprint gap to a point
  (``footprint``: the target-clearance test, docs/task.md §1 (a)), written once on x/y/z component
  arrays (XLA fuses those into a few elementwise loops; the same maths on a trailing axis of
  length 3 is several times slower on CPU);
* the builders: the MJCF slots (``tools/urdf_to_mjcf.py``, one geom per kind in every slot),
  the PyBullet reference env, the twin, the physical check and the renderer all draw an
  obstacle as the entry's ``primitive`` at ``world_rotation`` (yaw ∘ tilt); the deployment CLI
  reads ``cli_lengths`` / ``from_lengths`` (``--obstacle capsule X Y Z R L [YAW_DEG]``).

Adding a shape is one entry here (plus its size-range keys in ``config.SamplingConfig``) and its
tests.  The kinds an env draws are ``env.sampling.obstacle_kinds`` (names; default the paper's
sphere, cylinder and box).  ``kind`` may be a Python int (only that shape is computed) or an
integer array (each kind of ``kinds`` — default every registered kind — is computed and the
right one selected with ``where``: pass the config's kinds where cost matters).  ``xp`` is
numpy or jax.numpy; this module must not import jax, nor any package module but ``robot``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from sagrasp_jax.task.robot import BOX, CAPSULE, CYLINDER, SPHERE

Vec = tuple[Any, Any, Any]
_TINY = 1e-12
_EYE = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
_LYING = ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0))  # rotation about y by +90°: local z -> frame x


def _norm(xp: Any, *comps: Any) -> Any:
    return xp.sqrt(sum(c * c for c in comps))


def _lerp(lo_hi: tuple[float, float], u: Any) -> Any:
    return lo_hi[0] + (lo_hi[1] - lo_hi[0]) * u


@dataclass(frozen=True)
class ObstacleShape:
    """One obstacle kind: everything the sampler, the maths and the builders need to know about it."""

    id: int  # the value in ResetSpec.obstacle_kind (the paper's kinds keep their primitive ids)
    name: str  # in env.sampling.obstacle_kinds, the deployment CLI, MJCF geom names, reports
    primitive: int  # robot.SPHERE | CAPSULE | BOX | CYLINDER: the MuJoCo / PyBullet primitive that draws it
    tilt: tuple[tuple[float, float, float], ...]  # the primitive's axes (columns) in the obstacle's yawed frame
    yawed: bool  # a yaw is drawn (uniform in [−π, π)) and accepted; else the shape is round about z
    float_z: str | None  # SamplingConfig key of the centre-height range of a floating kind; None: rests on the table
    size_keys: tuple[str, ...]  # SamplingConfig keys its size is drawn from
    # (xp, sampling config, u1, u2, u3) -> size (..., 3): the size from three of a candidate's uniforms
    sample_size: Callable[[Any, Any, Any, Any, Any], Any]
    half_height: Callable[[Any], Any]  # size (..., 3) -> vertical half-extent: the centre z when resting on the table
    sdf: Callable[[Any, Vec, Any], Any]  # (xp, point in the obstacle frame, size) -> signed distance
    surface: Callable[[Any, Vec, Any], Vec]  # (xp, point in the obstacle frame, size) -> nearest surface point there
    bounding_radius: Callable[[Any, Any], Any]  # (xp, size) -> radius of a sphere about the centre holding it
    # (xp, d (..., 2), yaw, size) -> horizontal distance from the footprint to the point centre + d
    footprint: Callable[[Any, Any, Any, Any], Any]
    # (xp, yaw, size) -> half-extents (..., 3) of its world-axis-aligned bounding box (the yawed shape's x/y/z reach
    # from the centre): what the relative observation layouts show of its size (observation.py)
    extent: Callable[[Any, Any, Any], Any]
    cli_lengths: tuple[str, ...]  # deployment CLI: the lengths after X Y Z (full lengths, not halves)
    from_lengths: Callable[[Sequence[float]], tuple[float, float, float]]  # CLI lengths -> size

    @property
    def tilt_matrix(self) -> np.ndarray:
        return np.asarray(self.tilt, dtype=float)

    @property
    def cli_usage(self) -> str:
        return " ".join(("X", "Y", "Z", *self.cli_lengths)) + (" [YAW_DEG]" if self.yawed else "")


# ------------------------------------------------------------------ sphere


def _sphere_size(xp: Any, cfg: Any, u1: Any, u2: Any, u3: Any) -> Any:
    zero = xp.zeros_like(u1)
    return xp.stack([_lerp(cfg.sphere_radius, u1), zero, zero], axis=-1)


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


def _round_footprint(xp: Any, d: Any, yaw: Any, size: Any) -> Any:
    return xp.sqrt(xp.sum(d**2, axis=-1)) - size[..., 0]


SPHERE_SHAPE = ObstacleShape(
    id=SPHERE, name="sphere", primitive=SPHERE, tilt=_EYE, yawed=False, float_z="sphere_z", size_keys=("sphere_radius",),
    sample_size=_sphere_size, half_height=lambda size: size[..., 0], sdf=_sphere_sdf, surface=_sphere_surface,
    bounding_radius=lambda xp, size: size[..., 0], footprint=_round_footprint,
    extent=lambda xp, yaw, size: xp.stack([size[..., 0]] * 3, axis=-1),
    cli_lengths=("R",), from_lengths=lambda ls: (ls[0], 0.0, 0.0),
)


# ------------------------------------------------------------------ upright cylinder


def _cylinder_size(xp: Any, cfg: Any, u1: Any, u2: Any, u3: Any) -> Any:
    return xp.stack([_lerp(cfg.cylinder_radius, u1), _lerp(cfg.cylinder_height, u2) / 2, xp.zeros_like(u1)], axis=-1)


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


CYLINDER_SHAPE = ObstacleShape(
    id=CYLINDER, name="cylinder", primitive=CYLINDER, tilt=_EYE, yawed=False, float_z=None,
    size_keys=("cylinder_radius", "cylinder_height"), sample_size=_cylinder_size, half_height=lambda size: size[..., 1],
    sdf=_cylinder_sdf, surface=_cylinder_surface,
    bounding_radius=lambda xp, size: xp.sqrt(size[..., 0] ** 2 + size[..., 1] ** 2), footprint=_round_footprint,
    extent=lambda xp, yaw, size: xp.stack([size[..., 0], size[..., 0], size[..., 1]], axis=-1),
    cli_lengths=("R", "H"), from_lengths=lambda ls: (ls[0], ls[1] / 2, 0.0),
)


# ------------------------------------------------------------------ yawed box


def _box_size(xp: Any, cfg: Any, u1: Any, u2: Any, u3: Any) -> Any:
    return xp.stack([_lerp(cfg.box_half, u1), _lerp(cfg.box_half, u2), _lerp(cfg.box_half, u3)], axis=-1)


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


def _yawed(xp: Any, d: Any, yaw: Any) -> Any:
    """Horizontal world offsets (..., 2) in the obstacle's yawed frame."""
    c, s = xp.cos(yaw), xp.sin(yaw)
    return xp.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def _box_extent(xp: Any, yaw: Any, size: Any) -> Any:
    c, s = xp.abs(xp.cos(yaw)), xp.abs(xp.sin(yaw))
    return xp.stack([c * size[..., 0] + s * size[..., 1], s * size[..., 0] + c * size[..., 1], size[..., 2]], axis=-1)


def _box_footprint(xp: Any, d: Any, yaw: Any, size: Any) -> Any:
    q = xp.abs(_yawed(xp, d, yaw)) - size[..., :2]
    return xp.sqrt(xp.sum(xp.maximum(q, 0.0) ** 2, axis=-1)) + xp.minimum(xp.max(q, axis=-1), 0.0)


BOX_SHAPE = ObstacleShape(
    id=BOX, name="box", primitive=BOX, tilt=_EYE, yawed=True, float_z=None, size_keys=("box_half",),
    sample_size=_box_size, half_height=lambda size: size[..., 2], sdf=_box_sdf, surface=_box_surface,
    bounding_radius=lambda xp, size: xp.sqrt(xp.sum(size**2, axis=-1)),
    footprint=_box_footprint, extent=_box_extent,
    cli_lengths=("LX", "LY", "LZ"), from_lengths=lambda ls: (ls[0] / 2, ls[1] / 2, ls[2] / 2),
)


# ------------------------------------------------------------------ capsule lying on the table


def _capsule_size(xp: Any, cfg: Any, u1: Any, u2: Any, u3: Any) -> Any:
    return xp.stack([_lerp(cfg.capsule_radius, u1), _lerp(cfg.capsule_length, u2) / 2, xp.zeros_like(u1)], axis=-1)


def _capsule_sdf(xp: Any, v: Vec, size: Any) -> Any:
    """Axis along the frame's x, from −half length to +half length."""
    return _norm(xp, xp.maximum(xp.abs(v[0]) - size[..., 1], 0.0), v[1], v[2]) - size[..., 0]


def _capsule_surface(xp: Any, v: Vec, size: Any) -> Vec:
    r, h = size[..., 0], size[..., 1]
    ax = xp.clip(v[0], -h, h)  # nearest point of the axis
    dx = v[0] - ax
    n = _norm(xp, dx, v[1], v[2])
    scale = r / xp.maximum(n, _TINY)
    on_axis = n < _TINY  # on the axis: straight up
    return (
        xp.where(on_axis, ax, ax + dx * scale),
        xp.where(on_axis, 0.0, v[1] * scale),
        xp.where(on_axis, r, v[2] * scale),
    )


def _capsule_footprint(xp: Any, d: Any, yaw: Any, size: Any) -> Any:
    local = _yawed(xp, d, yaw)
    return xp.sqrt(xp.maximum(xp.abs(local[..., 0]) - size[..., 1], 0.0) ** 2 + local[..., 1] ** 2) - size[..., 0]


def _capsule_extent(xp: Any, yaw: Any, size: Any) -> Any:
    r, h = size[..., 0], size[..., 1]  # the axis lies along the yawed frame's x
    return xp.stack([xp.abs(xp.cos(yaw)) * h + r, xp.abs(xp.sin(yaw)) * h + r, r], axis=-1)


def _capsule_from_lengths(ls: Sequence[float]) -> tuple[float, float, float]:
    radius, length = ls[0], ls[1]  # length tip to tip
    if not length > 2 * radius:
        raise ValueError(f"a capsule's length tip to tip ({length:.4g} m) must exceed twice its radius ({radius:.4g} m)")
    return (radius, length / 2 - radius, 0.0)


CAPSULE_SHAPE = ObstacleShape(
    id=CAPSULE, name="capsule", primitive=CAPSULE, tilt=_LYING, yawed=True, float_z=None,
    size_keys=("capsule_radius", "capsule_length"), sample_size=_capsule_size, half_height=lambda size: size[..., 0],
    sdf=_capsule_sdf, surface=_capsule_surface, bounding_radius=lambda xp, size: size[..., 0] + size[..., 1],
    footprint=_capsule_footprint, extent=_capsule_extent, cli_lengths=("R", "L"), from_lengths=_capsule_from_lengths,
)


# ------------------------------------------------------------------------------ registry

SHAPES: tuple[ObstacleShape, ...] = (SPHERE_SHAPE, CYLINDER_SHAPE, BOX_SHAPE, CAPSULE_SHAPE)
BY_ID: dict[int, ObstacleShape] = {s.id: s for s in SHAPES}
BY_NAME: dict[str, ObstacleShape] = {s.name: s for s in SHAPES}
NAMES: tuple[str, ...] = tuple(BY_NAME)
PAPER_KINDS: tuple[str, ...] = ("sphere", "cylinder", "box")  # docs/task.md §1: the default env.sampling.obstacle_kinds


def shapes_of(names: Sequence[str]) -> tuple[ObstacleShape, ...]:
    """Registry entries for kind names (``env.sampling.obstacle_kinds``); KeyError naming an unknown one."""
    unknown = [n for n in names if n not in BY_NAME]
    if unknown:
        raise KeyError(f"unknown obstacle kind(s) {', '.join(map(repr, unknown))}; known: {', '.join(NAMES)}")
    return tuple(BY_NAME[n] for n in names)


def kind_ids(names: Sequence[str]) -> tuple[int, ...]:
    return tuple(s.id for s in shapes_of(names))


def _dispatch(xp: Any, kind: Any, kinds: Sequence[int] | None, fn: Callable[[ObstacleShape], Any]) -> Any:
    """``fn(entry)`` for a static kind; for a kind array, every entry of ``kinds`` selected with ``where``
    (a kind outside ``kinds`` gets the first one's value).  ``fn`` may return a tuple of arrays."""
    if isinstance(kind, (int, np.integer)):
        return fn(BY_ID[int(kind)])
    ids = tuple(BY_ID) if kinds is None else tuple(kinds)
    values = {k: fn(BY_ID[k]) for k in ids}

    def select(part: Callable[[Any], Any]) -> Any:
        out = part(values[ids[0]])
        for k in ids[1:]:
            out = xp.where(kind == k, part(values[k]), out)
        return out

    first = values[ids[0]]
    if isinstance(first, tuple):
        return tuple(select(lambda v, i=i: v[i]) for i in range(len(first)))
    return select(lambda v: v)


def _to_local(xp: Any, pos: Any, yaw: Any, points: Any) -> Vec:
    """Points (..., 3) in the obstacle frame (yaw about z), as components."""
    dx, dy, dz = points[..., 0] - pos[..., 0], points[..., 1] - pos[..., 1], points[..., 2] - pos[..., 2]
    c, s = xp.cos(yaw), xp.sin(yaw)
    return c * dx + s * dy, -s * dx + c * dy, dz


def _to_world(xp: Any, pos: Any, yaw: Any, local: Vec) -> Any:
    c, s = xp.cos(yaw), xp.sin(yaw)
    x, y, z = local
    return xp.stack([pos[..., 0] + c * x - s * y, pos[..., 1] + s * x + c * y, pos[..., 2] + z], axis=-1)


# ------------------------------------------------------------------------------ public maths


def sdf(xp: Any, kind: Any, pos: Any, yaw: Any, size: Any, points: Any, kinds: Sequence[int] | None = None) -> Any:
    """Signed distance (...,) from ``points`` (..., 3) to obstacles (negative inside).

    ``kind``/``pos``/``yaw``/``size`` broadcast against the points' batch dims."""
    v = _to_local(xp, pos, yaw, points)
    return _dispatch(xp, kind, kinds, lambda s: s.sdf(xp, v, size))


def surface_point(xp: Any, kind: Any, pos: Any, yaw: Any, size: Any, points: Any,
                  kinds: Sequence[int] | None = None) -> Any:
    """The point (..., 3) of the obstacle's surface nearest to each of ``points`` (inside or out)."""
    v = _to_local(xp, pos, yaw, points)
    return _to_world(xp, pos, yaw, _dispatch(xp, kind, kinds, lambda s: s.surface(xp, v, size)))


def bounding_radius(xp: Any, kind: Any, size: Any, kinds: Sequence[int] | None = None) -> Any:
    """Radius (...,) of a sphere about the centre that holds the obstacle."""
    return _dispatch(xp, kind, kinds, lambda s: s.bounding_radius(xp, size))


def extent(xp: Any, kind: Any, yaw: Any, size: Any, kinds: Sequence[int] | None = None) -> Any:
    """Half-extents (..., 3) of the obstacle's world-axis-aligned bounding box about its centre."""
    per_axis = kind if isinstance(kind, (int, np.integer)) else xp.asarray(kind)[..., None]  # against (..., 3)
    return _dispatch(xp, per_axis, kinds, lambda s: s.extent(xp, yaw, size))


def footprint_gap(xp: Any, kind: Any, pos: Any, yaw: Any, size: Any, point_xy: Any,
                  kinds: Sequence[int] | None = None) -> Any:
    """Horizontal distance (...,) from the obstacle's footprint (its outline seen from above) to a
    point: docs/task.md §1 (a)'s "horizontal clearance from the obstacle's surface to the target centre"."""
    d = point_xy - pos[..., :2]
    return _dispatch(xp, kind, kinds, lambda s: s.footprint(xp, d, yaw, size))


def yaw_rotation(xp: Any, yaw: Any) -> Any:
    """Rotation matrices (..., 3, 3) about world z."""
    c, s = xp.cos(yaw), xp.sin(yaw)
    zero, one = xp.zeros_like(yaw), xp.ones_like(yaw)
    return xp.stack([xp.stack([c, -s, zero], -1), xp.stack([s, c, zero], -1), xp.stack([zero, zero, one], -1)], -2)


def world_rotation(kind: int, yaw: float) -> np.ndarray:
    """The world rotation (3, 3) of an obstacle's primitive (yaw ∘ tilt): how every builder places it."""
    return yaw_rotation(np, np.asarray(float(yaw))) @ BY_ID[int(kind)].tilt_matrix


def primitive_rotations(xp: Any, kind: Any, yaw: Any, kinds: Sequence[int] | None = None) -> Any:
    """``world_rotation`` for arrays of kinds and yaws (..., 3, 3), e.g. for exact-distance oracles."""
    base = yaw_rotation(xp, yaw)
    if isinstance(kind, (int, np.integer)):
        return base @ xp.asarray(BY_ID[int(kind)].tilt_matrix, dtype=base.dtype)
    return _dispatch(xp, xp.asarray(kind)[..., None, None], kinds,
                     lambda s: base @ xp.asarray(s.tilt_matrix, dtype=base.dtype))


def yaw_symmetry(shape: ObstacleShape) -> float:
    """The turn after which the shape looks the same (π for boxes and capsules; 2π for round ones)."""
    return math.pi if shape.yawed else 2 * math.pi
