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
  reads ``cli_lengths`` / ``from_lengths`` (``--obstacle capsule X Y Z R L [YAW_DEG]``);
* perception (``deploy/perception.py``, NumPy only) reads the entry's ``perception`` part
  (``Perceived``): how to fit the kind to what the camera saw of an object (``Seen``), how to tell it
  from another flat-topped kind by its top's outline, the smallest shape of the kind covering a box of
  points, and its horizontal reach; the YOLO dataset's classes are ``NAMES``.

Adding a shape is one entry here (plus size-range keys in ``config.SamplingConfig`` if it needs new
ones; only new keys need ``config_history.ADDED_KEYS``) and its tests: the scene MJCF gets its slot geoms
when loaded (``scene_mjcf.load_scene_spec``) and ``env.sampling.obstacle_kinds`` accepts its name.
A kind defined outside this module (a plugin, a test's toy kind) is added with ``register`` or, for a
block, ``registered`` (which restores the registry after); modules read ``shapes.SHAPES`` /
``BY_NAME`` / ``NAMES`` at call time, never a copy taken at import.  The kinds an env draws are ``env.sampling.obstacle_kinds`` (names; default the paper's
sphere, cylinder and box).  ``kind`` may be a Python int (only that shape is computed) or an
integer array (each kind of ``kinds`` — default every registered kind — is computed and the
right one selected with ``where``: pass the config's kinds where cost matters).  ``xp`` is
numpy or jax.numpy; this module must not import jax, nor any package module but ``robot`` and
``point_fits`` (NumPy fits for the perception parts).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Any, Callable, Iterator, NamedTuple, Sequence

import numpy as np

from sagrasp_jax.task.point_fits import convex_hull, fit_circle, fit_sphere, min_area_rect, polygon_area, wrap
from sagrasp_jax.task.robot import BOX, CAPSULE, CYLINDER, SPHERE

Vec = tuple[Any, Any, Any]
_TINY = 1e-12
_EYE = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
_LYING = ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0))  # rotation about y by +90°: local z -> frame x


def _norm(xp: Any, *comps: Any) -> Any:
    return xp.sqrt(sum(c * c for c in comps))


def _lerp(lo_hi: tuple[float, float], u: Any) -> Any:
    return lo_hi[0] + (lo_hi[1] - lo_hi[0]) * u


class Seen(NamedTuple):
    """What the depth camera saw of one object above the table (world frame, m; ``deploy/perception.py``'s region):
    what a kind's ``Perceived.fit`` reads."""

    points: np.ndarray  # (N, 3) the object's points
    area: np.ndarray  # (N,) each point's pixel footprint on a plane parallel to the table, m²
    height: np.ndarray  # (N,) each point's height above the table
    top: float  # its top's height above the table (robust to noise)
    base_z: float  # world z of the table under it
    # its top face (perception.TopFace): centroid (3,), area, centre_xy (2,), sides, angle (its minimum-area
    # rectangle), outline_xy (K, 2), rim_xy (the outline on the face's true edge), occluded (a nearer object hides
    # part of it), pitch (a pixel's side there)
    face: Any


class CoverBox(NamedTuple):
    """The points a covering shape must hold (``perception._cover``), as a box: a horizontal rectangle about the
    cover's centre (sides ``a`` along ``angle``, ``b`` across, already grown by the noise margin) from the table
    up to ``top``; ``round_r`` is the farthest point's horizontal distance from that centre (plus the margin)."""

    a: float
    b: float
    angle: float
    top: float
    round_r: float


Fit = tuple[np.ndarray, np.ndarray, float]  # centre (3,) world, size (3,) MuJoCo convention, yaw


@dataclass(frozen=True)
class Perceived:
    """A kind's part in perception (``deploy/perception.py``; NumPy only).  Perception fits every allowed kind
    to an object, keeps the one whose surface (``sdf``) lies nearest its points, between flat-topped kinds
    decides by ``top_misfit``, and where no fit holds the points returns the allowed kind's ``cover`` of least
    volume."""

    # Seen -> (centre, size, yaw) of the kind as it rests in the cell, or None: the points cannot be this kind
    fit: Callable[[Seen], Fit | None]
    # CoverBox -> (size, yaw, volume): the smallest shape of this kind, centred on the box's centre at half its
    # top, that holds the box (a conservative stand-in for an object no fit holds)
    cover: Callable[[CoverBox], tuple[np.ndarray, float, float]]
    # (centre, size, yaw) -> points (K, 3) whose horizontal convex hull holds the shape's footprint and whose
    # highest lies at its top: what a cover adds of a fit it replaces
    hull_points: Callable[[np.ndarray, np.ndarray, float], np.ndarray]
    reach: Callable[[np.ndarray], float]  # size -> horizontal distance from the centre to its farthest point
    # flat-topped kinds: the top face -> how far its outline is from this kind's top (lower: more like it;
    # comparable between the flat-topped kinds for one face).  Depth noise moves points along the rays, so the
    # outline, not the 3-D residual, tells a box from a cylinder.  None: not told apart by its top.
    top_misfit: Callable[[Any], float] | None = None


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
    perception: Perceived  # how the depth camera's perception fits it, tells it apart and covers it
    # deploy --help: what each of cli_lengths means ("": said with another; unset: the bare letters).  The first
    # kind to use a letter says what it means.
    cli_help: tuple[str, ...] = ()

    @property
    def tilt_matrix(self) -> np.ndarray:
        return np.asarray(self.tilt, dtype=float)

    @property
    def cli_usage(self) -> str:
        return " ".join(("X", "Y", "Z", *self.cli_lengths)) + (" [YAW_DEG]" if self.yawed else "")


# ------------------------------------------------------------------ perception helpers the kinds share (NumPy)

BOX_FILL = 0.89  # hull area / minimum-area rectangle of a top's outline: a disc's π/4 = 0.785, a rectangle's 1


def ring_points(centres_xy: Sequence[np.ndarray], r: float, z_lo: float, z_hi: float) -> np.ndarray:
    """Points (K, 3) at ``z_lo`` and ``z_hi`` whose horizontal hull holds the discs of radius ``r`` about
    ``centres_xy``: 16-gons circumscribing each circle (a ``Perceived.hull_points`` for round kinds)."""
    turn = np.arange(16) * math.pi / 8
    ring = np.stack([np.cos(turn), np.sin(turn)], axis=1) / math.cos(math.pi / 16)  # holds the unit circle
    xy = np.concatenate([np.asarray(e) + r * ring for e in centres_xy])
    return np.c_[np.r_[xy, xy], np.r_[[z_lo] * len(xy), [z_hi] * len(xy)]]


def _outline_fill(face: Any) -> float:
    """The top outline's convex hull area over its minimum-area rectangle's (1 for a rectangle, π/4 for a disc)."""
    hull = convex_hull(face.outline_xy)
    _, sides, _ = min_area_rect(face.outline_xy)
    return polygon_area(hull) / max(sides[0] * sides[1], 1e-12) if len(hull) >= 3 else 1.0


def rectangle_top_misfit(face: Any) -> float:
    """A rectangular top's ``top_misfit``.  Whole: how far the outline's fill falls short of ``BOX_FILL`` (the
    hull shrugs off a ragged, partly dropped outline).  Partly hidden: the RMS distance of the visible rim's
    points to the outline's minimum-area rectangle's sides."""
    if not face.occluded:
        return max(BOX_FILL - _outline_fill(face), 0.0)
    xy = face.rim_xy
    rect_centre, sides, angle = min_area_rect(face.outline_xy)
    c, s = math.cos(angle), math.sin(angle)
    d = xy - rect_centre
    u, v = np.abs(d @ np.array([c, s])), np.abs(d @ np.array([-s, c]))
    to_side = np.minimum(np.abs(sides[0] / 2 - u), np.abs(sides[1] / 2 - v))
    return float(np.sqrt(np.mean(to_side**2)))


def disc_top_misfit(face: Any) -> float:
    """A round top's ``top_misfit``.  Whole: how far the outline's fill reaches over ``BOX_FILL``.  Partly
    hidden: the RMS distance of the visible rim's points to their least-squares circle."""
    if not face.occluded:
        return max(_outline_fill(face) - BOX_FILL, 0.0)
    xy = face.rim_xy
    centre, r = fit_circle(xy)
    return float(np.sqrt(np.mean((np.linalg.norm(xy - centre, axis=1) - r) ** 2)))


def _axis(yaw: float) -> tuple[np.ndarray, np.ndarray]:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([c, s]), np.array([-s, c])


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


def _sphere_fit(seen: Seen) -> Fit | None:
    """Least-squares sphere through the points; none reaching into the table is a sphere of the cell."""
    c, r = fit_sphere(seen.points)
    if not (0.005 < r < 0.3) or c[2] - r < seen.base_z - 0.01:
        return None
    return c, np.array([r, 0.0, 0.0]), 0.0


def _sphere_cover(box: CoverBox) -> tuple[np.ndarray, float, float]:
    r = math.sqrt((box.a / 2) ** 2 + (box.b / 2) ** 2 + (box.top / 2) ** 2)  # through the box's corners
    return np.array([r, 0.0, 0.0]), 0.0, 4.0 / 3.0 * math.pi * r**3


SPHERE_PERCEIVED = Perceived(
    fit=_sphere_fit, cover=_sphere_cover, reach=lambda size: float(size[0]),
    hull_points=lambda c, size, yaw: ring_points([c[:2]], float(size[0]), c[2] - size[0], c[2] + size[0]),
)

SPHERE_SHAPE = ObstacleShape(
    id=SPHERE, name="sphere", primitive=SPHERE, tilt=_EYE, yawed=False, float_z="sphere_z", size_keys=("sphere_radius",),
    sample_size=_sphere_size, half_height=lambda size: size[..., 0], sdf=_sphere_sdf, surface=_sphere_surface,
    bounding_radius=lambda xp, size: size[..., 0], footprint=_round_footprint,
    extent=lambda xp, yaw, size: xp.stack([size[..., 0]] * 3, axis=-1),
    cli_lengths=("R",), from_lengths=lambda ls: (ls[0], 0.0, 0.0), perception=SPHERE_PERCEIVED,
    cli_help=("R radius",),
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


def _cylinder_fit(seen: Seen) -> Fit | None:
    """Upright on the table, as tall as the object's top; its radius from the top disc's area and its axis
    through the disc's centroid, or, where a nearer object hides part of the top, from the rim's visible arc."""
    face, half = seen.face, seen.top / 2
    if face.occluded:
        xy, r = fit_circle(face.rim_xy)
        r += face.pitch / 2  # outline pixel centres lie half a pixel inside the rim
    else:
        xy, r = face.centroid[:2], math.sqrt(face.area / math.pi)
    return np.array([xy[0], xy[1], seen.base_z + half]), np.array([r, half, 0.0]), 0.0


def _cylinder_cover(box: CoverBox) -> tuple[np.ndarray, float, float]:
    return np.array([box.round_r, box.top / 2, 0.0]), 0.0, math.pi * box.round_r**2 * box.top


CYLINDER_PERCEIVED = Perceived(
    fit=_cylinder_fit, cover=_cylinder_cover, reach=lambda size: float(size[0]), top_misfit=disc_top_misfit,
    hull_points=lambda c, size, yaw: ring_points([c[:2]], float(size[0]), c[2] - size[1], c[2] + size[1]),
)

CYLINDER_SHAPE = ObstacleShape(
    id=CYLINDER, name="cylinder", primitive=CYLINDER, tilt=_EYE, yawed=False, float_z=None,
    size_keys=("cylinder_radius", "cylinder_height"), sample_size=_cylinder_size, half_height=lambda size: size[..., 1],
    sdf=_cylinder_sdf, surface=_cylinder_surface,
    bounding_radius=lambda xp, size: xp.sqrt(size[..., 0] ** 2 + size[..., 1] ** 2), footprint=_round_footprint,
    extent=lambda xp, yaw, size: xp.stack([size[..., 0], size[..., 0], size[..., 1]], axis=-1),
    cli_lengths=("R", "H"), from_lengths=lambda ls: (ls[0], ls[1] / 2, 0.0), perception=CYLINDER_PERCEIVED,
    cli_help=("R radius", "H height"),
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


def _box_fit(seen: Seen) -> Fit | None:
    """On the table, as tall as the object's top; its footprint the top face's minimum-area rectangle (grown to
    the face's measured area)."""
    face, half = seen.face, seen.top / 2
    centre = np.array([face.centre_xy[0], face.centre_xy[1], seen.base_z + half])
    return centre, np.array([face.sides[0] / 2, face.sides[1] / 2, half]), wrap(face.angle, math.pi)


def _box_cover(box: CoverBox) -> tuple[np.ndarray, float, float]:
    return np.array([box.a / 2, box.b / 2, box.top / 2]), wrap(box.angle, math.pi), box.a * box.b * box.top


def _box_hull_points(c: np.ndarray, size: np.ndarray, yaw: float) -> np.ndarray:
    """Its eight corners."""
    axis, across = _axis(yaw)
    hx, hy, hz = (float(v) for v in size)
    xy = np.array([c[:2] + i * hx * axis + j * hy * across for i in (-1, 1) for j in (-1, 1)])
    return np.c_[np.r_[xy, xy], np.r_[[c[2] - hz] * 4, [c[2] + hz] * 4]]


BOX_PERCEIVED = Perceived(
    fit=_box_fit, cover=_box_cover, hull_points=_box_hull_points, reach=lambda size: math.hypot(size[0], size[1]),
    top_misfit=rectangle_top_misfit,
)

BOX_SHAPE = ObstacleShape(
    id=BOX, name="box", primitive=BOX, tilt=_EYE, yawed=True, float_z=None, size_keys=("box_half",),
    sample_size=_box_size, half_height=lambda size: size[..., 2], sdf=_box_sdf, surface=_box_surface,
    bounding_radius=lambda xp, size: xp.sqrt(xp.sum(size**2, axis=-1)),
    footprint=_box_footprint, extent=_box_extent,
    cli_lengths=("LX", "LY", "LZ"), from_lengths=lambda ls: (ls[0] / 2, ls[1] / 2, ls[2] / 2),
    perception=BOX_PERCEIVED,
    cli_help=("LX LY LZ full side lengths (LX along the camera's x axis turned by YAW_DEG about its optical axis)", "", ""),
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


def _capsule_fit(seen: Seen) -> Fit | None:
    """Lying on the table: its radius half the object's top; its axis the long principal axis of the points
    above the radius (area-weighted), from end to end of them."""
    r = seen.top / 2
    upper = seen.height >= r
    xy = seen.points[upper, :2]
    wts = seen.area[upper]
    mean = (xy * wts[:, None]).sum(axis=0) / wts.sum()
    cov = np.cov((xy - mean).T, aweights=wts)
    evals, evecs = np.linalg.eigh(cov)
    axis = evecs[:, 1]
    along = (xy - mean) @ axis
    across = (xy - mean) @ np.array([-axis[1], axis[0]])
    lo, hi = float(along.min()), float(along.max())
    mid_across = float(np.average(across, weights=wts))
    length = hi - lo + math.sqrt(float(np.median(seen.area)))  # end pixels' centres: half a pitch short each
    half_axis = max(length / 2 - r, 0.0)
    centre_xy = mean + axis * (lo + hi) / 2 + np.array([-axis[1], axis[0]]) * mid_across
    centre = np.array([centre_xy[0], centre_xy[1], seen.base_z + r])
    return centre, np.array([r, half_axis, 0.0]), wrap(math.atan2(axis[1], axis[0]), math.pi)


def _capsule_cover(box: CoverBox) -> tuple[np.ndarray, float, float]:
    """Along the box's long side, through its corners."""
    long_axis = box.angle if box.a >= box.b else box.angle + math.pi / 2
    r = math.hypot(min(box.a, box.b) / 2, box.top / 2)
    length = max(box.a, box.b)
    return np.array([r, length / 2, 0.0]), wrap(long_axis, math.pi), math.pi * r**2 * length + 4.0 / 3.0 * math.pi * r**3


def _capsule_hull_points(c: np.ndarray, size: np.ndarray, yaw: float) -> np.ndarray:
    axis, _ = _axis(yaw)
    r, h = float(size[0]), float(size[1])
    return ring_points([c[:2] + k * h * axis for k in (-1, 1)], r, c[2] - r, c[2] + r)


CAPSULE_PERCEIVED = Perceived(
    fit=_capsule_fit, cover=_capsule_cover, hull_points=_capsule_hull_points, reach=lambda size: float(size[0] + size[1]),
)

CAPSULE_SHAPE = ObstacleShape(
    id=CAPSULE, name="capsule", primitive=CAPSULE, tilt=_LYING, yawed=True, float_z=None,
    size_keys=("capsule_radius", "capsule_length"), sample_size=_capsule_size, half_height=lambda size: size[..., 0],
    sdf=_capsule_sdf, surface=_capsule_surface, bounding_radius=lambda xp, size: size[..., 0] + size[..., 1],
    footprint=_capsule_footprint, extent=_capsule_extent, cli_lengths=("R", "L"), from_lengths=_capsule_from_lengths,
    perception=CAPSULE_PERCEIVED,
    cli_help=("R radius", "L length tip to tip (lying on the table, along the camera's x axis turned by YAW_DEG)"),
)


# ------------------------------------------------------------------------------ registry

SHAPES: tuple[ObstacleShape, ...] = (SPHERE_SHAPE, CYLINDER_SHAPE, BOX_SHAPE, CAPSULE_SHAPE)
BY_ID: dict[int, ObstacleShape] = {s.id: s for s in SHAPES}
BY_NAME: dict[str, ObstacleShape] = {s.name: s for s in SHAPES}
NAMES: tuple[str, ...] = tuple(BY_NAME)
PAPER_KINDS: tuple[str, ...] = ("sphere", "cylinder", "box")  # docs/task.md §1: the default env.sampling.obstacle_kinds
PRIMITIVES = (SPHERE, CAPSULE, BOX, CYLINDER)  # what an entry's primitive may be: MuJoCo and PyBullet draw these
_LISTENERS: list[Callable[[], None]] = []  # called after the registry changes (config's choices of obstacle_kinds)


def on_change(listener: Callable[[], None]) -> None:
    """Call ``listener()`` whenever ``register`` or ``registered`` changes the registry (modules that derive
    something from ``NAMES`` at import, such as config's choices of ``env.sampling.obstacle_kinds``)."""
    _LISTENERS.append(listener)


def _set_registry(entries: Sequence[ObstacleShape]) -> None:
    global SHAPES, NAMES
    SHAPES = tuple(entries)
    BY_ID.clear()
    BY_ID.update((s.id, s) for s in SHAPES)
    BY_NAME.clear()
    BY_NAME.update((s.name, s) for s in SHAPES)
    NAMES = tuple(BY_NAME)
    for listener in _LISTENERS:
        listener()


def register(shape: ObstacleShape) -> ObstacleShape:
    """Add a kind defined outside this module (a plugin's, a test's) to the registry; ValueError naming what
    clashes or is missing.  Everything that reads the registry then knows it: ``env.sampling.obstacle_kinds``
    accepts its name, the sampler, the collision maths, the MJX env, the scene MJCF's slots
    (``scene_mjcf.load_scene_spec``), the PyBullet twin, perception and the YOLO classes."""
    problems = []
    if shape.id in BY_ID:
        problems.append(f"id {shape.id} is taken by {BY_ID[shape.id].name!r}")
    if shape.name in BY_NAME:
        problems.append(f"name {shape.name!r} is taken")
    if not shape.name.isidentifier():
        problems.append(f"name {shape.name!r} must be an identifier (it names MJCF geoms, CLI kinds and config values)")
    if shape.primitive not in PRIMITIVES:
        problems.append(f"primitive {shape.primitive} is not one of robot.SPHERE, CAPSULE, BOX, CYLINDER {PRIMITIVES}")
    if np.asarray(shape.tilt).shape != (3, 3):
        problems.append("tilt must be a 3 × 3 rotation")
    if shape.cli_help and len(shape.cli_help) != len(shape.cli_lengths):
        problems.append("cli_help must say what each of cli_lengths means")
    if not isinstance(shape.perception, Perceived):
        problems.append("perception must be a shapes.Perceived")
    if problems:
        raise ValueError(f"obstacle kind {shape.name!r} cannot be registered: " + "; ".join(problems))
    _set_registry((*SHAPES, shape))
    return shape


@contextlib.contextmanager
def registered(*extra: ObstacleShape) -> Iterator[tuple[ObstacleShape, ...]]:
    """The registry with ``extra`` kinds added for the block (``register``), restored after, whatever happens."""
    before = SHAPES
    try:
        for shape in extra:
            register(shape)
        yield extra
    finally:
        _set_registry(before)


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
