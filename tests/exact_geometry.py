"""Exact signed distances between every pair of collision primitives: the test oracle.

Production code needs only the few queries in ``sagrasp_jax.task.geometry`` (point SDFs, capsule vs
box, the table plane); the per-step rules approximate the robot by spheres against exact
obstacle shapes (``collision``, ``shapes``).  This module holds the rest, the exact
primitive-pair distances that ``tests/`` (``test_geometry``, ``test_collision``, ``test_env``,
``test_observation``, ``test_scene_mix``) measure those approximations against, and that
experiments may use.  It lives in ``tests/`` beside its users (``import exact_geometry``: the
tests folder is on ``sys.path`` under pytest) and outside the package, which never needs it.  It
re-exports ``geometry``'s public functions, so one import gives the full set; it must not import jax.

Conventions as in ``geometry``: ``xp`` first, MuJoCo size convention, positive = gap.
Exactness:

* sphere vs anything, capsule vs capsule, box vs box: exact signed distance
  (penetration depth = minimum translation distance; for capsule-capsule while the
  two axis segments do not cross, for box-box always, via the 15-axis SAT).
* capsule vs box, capsule vs cylinder: exact outside; when overlapping the value is
  ``min over the capsule axis of sdf_other - r`` (correct sign, continuous through
  contact, but not the minimum translation distance).
* cylinder vs box, cylinder vs cylinder: the cylinder is replaced by a prism with a
  regular ``sides``-gon cross-section; worst-case error in ``cylinder_error_bound``
  (< 1.2 mm for every primitive pair of this project at the default 24 sides).

Performance, for choosing what a test may afford: CPU time per pair, float32,
``jax.jit(jax.vmap(...))`` over 1024 pairs, one core of the 2-core dev Xeon: sphere-* 0.05 µs,
capsule-capsule 0.11, capsule-box 0.13, capsule-cylinder 0.23, box-box 1.0, box-cylinder 4.5,
cylinder-cylinder 23.  The robot's 10 primitives against 2 obstacle slots of traced kind (every
kind evaluated, see ``distance_to_obstacle``): 190 µs per env.  NumPy pays per operation
(~2-7 ms per box/cylinder pair call): fine for one env, not for batches.  That cost is why the
per-step rules use sphere sets instead (``collision``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from sagrasp_jax.task.geometry import (  # noqa: F401  (re-exported: the full set in one module)
    _BIG,
    _add,
    _capsule_segment,
    _const,
    _cross,
    _cylinder_sdf,
    _dot,
    _len,
    _m,
    _mtv,
    _mul,
    _mv,
    _point_segment,
    _prep,
    _rel,
    _safe_div,
    _segment_box_outside,
    _sub,
    _tm,
    _tv,
    _v,
    capsule_box_distance,
    plane_distance,
    point_box_distance,
    point_capsule_distance,
    point_cylinder_distance,
    point_distance,
    point_sphere_distance,
    segment_box_distance,
    support_radius,
)
from sagrasp_jax.task.geometry import __all__ as geometry_all
from sagrasp_jax.task.robot import BOX, CAPSULE, CYLINDER, SPHERE

Array = Any
Vec = tuple[Any, Any, Any]
Mat = tuple[Vec, Vec, Vec]

__all__ = geometry_all + [  # geometry's public functions, re-exported, and the oracle's own
    "SPHERE",
    "CAPSULE",
    "BOX",
    "CYLINDER",
    "GOLDEN_ITERS",
    "CYLINDER_SIDES",
    "CYLINDER_GOLDEN_ITERS",
    "segment_segment_distance",
    "segment_cylinder_distance",
    "sphere_sphere_distance",
    "sphere_capsule_distance",
    "sphere_box_distance",
    "sphere_cylinder_distance",
    "capsule_capsule_distance",
    "capsule_cylinder_distance",
    "box_box_distance",
    "box_cylinder_distance",
    "cylinder_cylinder_distance",
    "cylinder_error_bound",
    "pair_distance",
    "distance_to_obstacle",
    "distance_matrix",
    "obstacle_distance_matrix",
]

# Golden-section steps for the exact 1-D convex minimisation of capsule vs cylinder:
# the bracket shrinks to 0.618^40 ≈ 4e-9 of the segment (< 1e-8 m for robot links).
GOLDEN_ITERS = 40
# Sides of the prism that stands in for a cylinder in cylinder-box / cylinder-cylinder.
CYLINDER_SIDES = 24
# Golden-section steps inside the cylinder approximations: within 0.618^24 ≈ 1e-5 of an
# edge length (15 µm for the 1.54 m gantry posts), small beside the prism error.
CYLINDER_GOLDEN_ITERS = 24

_INVPHI = (math.sqrt(5.0) - 1.0) / 2.0

# Box edges: edge e runs along local axis _EDGE_AXIS[e], from the vertex _EDGE_SIGNS[e]
# (sign -1 on that axis) to the opposite end.
_EDGE_AXIS = np.repeat(np.arange(3), 4)
_EDGE_SIGNS = np.array(
    [[-1.0, sy, sz] for sy in (-1, 1) for sz in (-1, 1)]
    + [[sx, -1.0, sz] for sx in (-1, 1) for sz in (-1, 1)]
    + [[sx, sy, -1.0] for sx in (-1, 1) for sy in (-1, 1)]
)
_EDGE_STEP = 2.0 * np.eye(3)[_EDGE_AXIS]  # edge vector / half-extents


# ------------------------------------------------------------- 1-D minimisation


def _min_last(xp: Any, x: Array, unfused: bool = False) -> Array:
    """Minimum over the trailing axis.

    ``unfused=True`` is for the output of a golden-section search: XLA:CPU (legacy emitters,
    which the package selects for MJX) fuses a large elementwise producer into a reduction
    and then runs it unvectorised (3-7x slower); folding slices with ``minimum`` instead
    compiles the producer once per slice (seconds).  A sort cannot fuse, so the producer
    stays one vectorised loop, compiles once, and sorting a few dozen values costs little.
    """
    if unfused:
        return xp.sort(x, axis=-1)[..., 0]
    return xp.min(x, axis=-1)


def _golden_min(xp: Any, f: Callable[[Array], Array], like: Array, iters: int) -> Array:
    """min over t in [0, 1] of a convex f, elementwise over ``like``'s shape.

    Golden-section search (one evaluation per step) plus both endpoints.  Every value is
    f at a real t, so the result is an upper bound on the minimum that exceeds it by at
    most the variation of f over a bracket of 0.618^iters.
    """
    a = xp.zeros_like(like)
    b = xp.ones_like(like)
    c = b - _INVPHI * (b - a)
    d = a + _INVPHI * (b - a)
    fc, fd = f(c), f(d)
    best = xp.minimum(xp.minimum(f(a), f(b)), xp.minimum(fc, fd))
    for _ in range(iters):
        left = fc <= fd
        a = xp.where(left, a, c)
        b = xp.where(left, d, b)
        x = xp.where(left, b - _INVPHI * (b - a), a + _INVPHI * (b - a))
        fx = f(x)
        c, d, fc, fd = (
            xp.where(left, x, d),
            xp.where(left, c, x),
            xp.where(left, fx, fd),
            xp.where(left, fc, fx),
        )
        best = xp.minimum(best, fx)
    return best

def _segments_vs_cylinder(
    xp: Any,
    start: Vec,
    dirs: Vec,
    radius: Array,
    half_height: Array,
    iters: int,
) -> Array:
    """min over each segment (trailing axis) of the exact cylinder SDF (cylinder-local coordinates)."""

    def f(t: Array) -> Array:
        return _cylinder_sdf(xp, _add(start, _mul(dirs, t)), radius, half_height)

    return _golden_min(xp, f, start[0] + dirs[0] + radius, iters)


def _box_edges(xp: Any, half: Vec, rot: Mat, pos: Vec) -> tuple[Vec, Vec]:
    """Start points and edge vectors (trailing axis of 12) of a box with half-extents ``half``,
    rotation ``rot`` and centre ``pos`` given in some frame, in that frame."""
    like = half[0]
    start_local = tuple(half[j][..., None] * _const(xp, _EDGE_SIGNS[:, j], like) for j in range(3))
    step_local = tuple(half[j][..., None] * _const(xp, _EDGE_STEP[:, j], like) for j in range(3))
    rot_t = _tm(rot)
    return _add(_tv(pos), _mv(rot_t, start_local)), _mv(rot_t, step_local)  # type: ignore[arg-type]


def _sat(xp: Any, axes: Vec, offset: Vec, widths: Sequence[Callable[[Vec], Array]]) -> Array:
    """max over candidate axes (trailing axis) of |offset·L| - Σ support half-widths along unit L.

    For two convex polytopes and their face normals plus edge-direction cross products this
    is the exact signed distance when they overlap (minus the penetration depth) and
    positive iff they are separated.  Near-degenerate cross products (parallel edges) are
    skipped: their direction would be rounding noise.
    """
    n = _len(xp, *axes)
    valid = n > float(np.sqrt(np.finfo(n.dtype).eps))
    unit = _mul(axes, 1.0 / xp.where(valid, n, 1.0))
    gap = xp.abs(_dot(unit, _tv(offset)))
    for width in widths:
        gap = gap - width(unit)
    return xp.max(xp.where(valid, gap, -_BIG), axis=-1)


def _linear_axes(xp: Any, table: tuple[np.ndarray, np.ndarray], rot: Mat) -> Vec:
    """Candidate axes (trailing axis A) that depend linearly on ``rot``: D + Σ C·rot entries.

    The static tables skip zero coefficients at trace time, so each axis costs only the
    products it really has.
    """
    coef, const = table  # (3, 3, 3, A), (3, A)
    like = rot[0][0]
    out = []
    for k in range(3):
        acc = xp.zeros_like(like)[..., None] + _const(xp, const[k], like)
        for i in range(3):
            for j in range(3):
                if np.any(coef[k, i, j] != 0):
                    acc = acc + rot[i][j][..., None] * _const(xp, coef[k, i, j], like)
        out.append(acc)
    return tuple(out)  # type: ignore[return-value]


def _tabulate(build: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(C, D) with build(M) = D + Σ_ij C[:, i, j] M_ij for a ``build`` linear in M (plus constant)."""
    const = build(np.zeros((3, 3)))  # (A, 3)
    coef = np.zeros((3, 3, 3, const.shape[0]))
    for i in range(3):
        for j in range(3):
            basis = np.zeros((3, 3))
            basis[i, j] = 1.0
            coef[:, i, j, :] = (build(basis) - const).T
    coef[np.abs(coef) < 1e-15] = 0.0
    return coef, const.T.copy()


# --------------------------------------------------------------- prism (cylinder)


@functools.lru_cache(maxsize=8)
def _prism(sides: int) -> dict[str, Any]:
    """Static data of the regular ``sides``-gon prism standing in for a cylinder."""
    if sides < 8 or sides % 4:
        raise ValueError(f"cylinder prism needs a multiple of 4 sides, at least 8; got {sides}")
    theta = 2.0 * np.pi * np.arange(sides) / sides
    mid = theta[: sides // 2] + np.pi / sides
    zeros = np.zeros_like(mid)
    normals = np.stack([np.cos(mid), np.sin(mid), zeros], axis=-1)  # (K/2, 3) side faces
    rim_dirs = np.stack([-np.sin(mid), np.cos(mid), zeros], axis=-1)  # (K/2, 3) cap edges
    zhat = np.array([[0.0, 0.0, 1.0]])
    edge_dirs = np.concatenate([zhat, rim_dirs])  # (K/2 + 1, 3) all edge directions
    eye = np.eye(3)

    def box_cyl_axes(m: np.ndarray) -> np.ndarray:  # box frame; m = cylinder rotation in it
        crosses = np.cross(eye[:, None, :], (edge_dirs @ m.T)[None, :, :]).reshape(-1, 3)
        return np.concatenate([eye, (normals @ m.T), m[None, :, 2], crosses])

    def cyl_cyl_axes(m: np.ndarray) -> np.ndarray:  # frame of A; m = B's rotation in it
        crosses = np.cross(edge_dirs[:, None, :], (edge_dirs @ m.T)[None, :, :]).reshape(-1, 3)
        return np.concatenate([zhat, normals, m[None, :, 2], normals @ m.T, crosses])

    k = np.arange(sides)
    nxt = (k + 1) % sides
    ring = np.stack([np.cos(theta), np.sin(theta)], axis=-1)
    # 2K rim chords (top, bottom) and K side edges: start / end in (x/R, y/R, z/hh) units.
    start = np.concatenate(
        [np.c_[ring, np.ones(sides)], np.c_[ring, -np.ones(sides)], np.c_[ring, -np.ones(sides)]]
    )
    end = np.concatenate(
        [np.c_[ring[nxt], np.ones(sides)], np.c_[ring[nxt], -np.ones(sides)], np.c_[ring, np.ones(sides)]]
    )
    return {
        # vertex directions in the first quadrant: with |x|, |y| folded in (the polygon is
        # symmetric under x -> -x and y -> -y) they give the support in K/4 + 1 products.
        "quarter_verts": ring[: sides // 4 + 1],
        # vertex radius / cylinder radius: the polygon then deviates by the same amount
        # outward (at the vertices) and inward (at the edge midpoints).
        "scale": 2.0 / (1.0 + math.cos(math.pi / sides)),
        "edge_start": start,
        "edge_step": end - start,
        "box_cyl_axes": _tabulate(box_cyl_axes),
        "cyl_cyl_axes": _tabulate(cyl_cyl_axes),
    }


@functools.lru_cache(maxsize=1)
def _box_box_axes() -> tuple[np.ndarray, np.ndarray]:
    eye = np.eye(3)

    def build(m: np.ndarray) -> np.ndarray:  # frame of A; m = B's rotation in it
        return np.concatenate([eye, m.T, np.cross(eye[:, None, :], m.T[None, :, :]).reshape(-1, 3)])

    return _tabulate(build)


def cylinder_error_bound(
    radius_a: float, radius_b: float | None = None, sides: int = CYLINDER_SIDES, iters: int = CYLINDER_GOLDEN_ITERS
) -> float:
    """Worst-case error (m) of ``box_cylinder_distance`` (one radius) or
    ``cylinder_cylinder_distance`` (two radii) with a ``sides``-gon prism.

    Each prism lies within ε = r·tan²(π/2K) (Hausdorff) of its cylinder.  Signed distance
    is 1-Lipschitz in each set's support function, so the prisms' signed distance is within
    Σε of the cylinders'; the separated branch measures prism edges against the exact other
    cylinder, which adds at most max ε.  Hence 2ε for cylinder-box and
    ε_a + ε_b + max(ε_a, ε_b) for cylinder-cylinder (K = 24: 0.0086·r resp. ≤ 0.0129·r_max,
    i.e. 0.73 mm for the 0.085 m robot base against a box and 0.94 mm against a 0.05 m
    cylinder).  Included: the golden-section tolerance on the rim chords of
    cylinder-cylinder (0.618^(iters-8) of a chord, ~1e-4·r).  Not included: the tolerance on
    the long edges, 0.618^iters of their length (15 µm for the 1.54 m gantry posts).
    """
    k = math.tan(math.pi / (2 * sides)) ** 2
    if radius_b is None:
        return 2.0 * k * radius_a
    r_max = max(radius_a, radius_b)
    chord = 2.0 * r_max * 2.0 / (1.0 + math.cos(math.pi / sides)) * math.sin(math.pi / sides)
    return k * (radius_a + radius_b + r_max) + _INVPHI ** max(iters - 8, 4) * chord


def _frames(xp: Any, pos_a: Array, rot_a: Array, pos_b: Array, rot_b: Array,
            axes_table: tuple[np.ndarray, np.ndarray]) -> tuple[Mat, Vec, Mat, Vec, Vec, Mat]:
    """For a SAT between A and B: B's pose in A's frame, A's pose in B's frame, the candidate axes
    (in A's frame, from a ``_tabulate`` table) and B's rotation in A's frame transposed."""
    ma, mb = _m(rot_a), _m(rot_b)
    m_ab, t_ab = _rel(ma, _v(pos_a), mb, _v(pos_b))
    m_ba, t_ba = _rel(mb, _v(pos_b), ma, _v(pos_a))
    return m_ab, t_ab, m_ba, t_ba, _linear_axes(xp, axes_table, m_ab), _tm(m_ab)


def _prism_width(xp: Any, local: Vec, radius: Array, half_height: Array, prism: dict[str, Any]) -> Array:
    """Support half-width of the prism along unit vectors ``local`` given in its own frame
    (trailing axis); ``radius`` and ``half_height`` carry the batch shape."""
    ax, ay = xp.abs(local[0]), xp.abs(local[1])
    proj = xp.maximum(ax, ay)  # the vertices at 0 and 90 degrees
    for c, s in prism["quarter_verts"][1:-1]:
        proj = xp.maximum(proj, ax * float(c) + ay * float(s))
    return (radius * prism["scale"])[..., None] * proj + half_height[..., None] * xp.abs(local[2])


def _prism_edges(
    xp: Any, radius: Array, half_height: Array, rot: Mat, pos: Vec, prism: dict[str, Any]
) -> tuple[Vec, Vec]:
    """Start points and edge vectors (trailing axis 3K: rim chords, then side edges) of the
    prism of a cylinder with rotation ``rot`` and centre ``pos`` in some frame, in that frame."""
    r_vert = (radius * prism["scale"])[..., None]
    hh = half_height[..., None]
    scales = (r_vert, r_vert, hh)
    start_local = tuple(scales[j] * _const(xp, prism["edge_start"][:, j], radius) for j in range(3))
    step_local = tuple(scales[j] * _const(xp, prism["edge_step"][:, j], radius) for j in range(3))
    rot_t = _tm(rot)
    return _add(_tv(pos), _mv(rot_t, start_local)), _mv(rot_t, step_local)  # type: ignore[arg-type]

# --------------------------------------------------------------- segment queries


def _segment_segment(xp: Any, p0: Vec, d1: Vec, q0: Vec, d2: Vec) -> Array:
    r = _sub(p0, q0)
    a, e, b = _dot(d1, d1), _dot(d2, d2), _dot(d1, d2)
    c, f = _dot(d1, r), _dot(d2, r)
    n = _cross(d1, d2)
    denom = _dot(n, n)  # a·e - b², without the cancellation
    s = xp.clip(_safe_div(xp, b * f - c * e, denom), 0.0, 1.0)
    t = xp.clip(_safe_div(xp, a * f - b * c, denom), 0.0, 1.0)
    interior = _len(xp, *_sub(_add(r, _mul(d1, s)), _mul(d2, t)))
    p1, q1 = _add(p0, d1), _add(q0, d2)
    ends = xp.minimum(
        xp.minimum(_point_segment(xp, p0, q0, d2), _point_segment(xp, p1, q0, d2)),
        xp.minimum(_point_segment(xp, q0, p0, d1), _point_segment(xp, q1, p0, d1)),
    )
    return xp.minimum(interior, ends)


def segment_segment_distance(xp: Any, p0: Array, p1: Array, q0: Array, q1: Array) -> Array:
    """Exact distance (...,) between segments [p0, p1] and [q0, q1] (parallel and degenerate too).

    The minimum is either interior to both segments (the unique critical point of the
    line-line problem) or has an endpoint on one side.  The four endpoint-segment distances
    and the distance at the clipped critical point are all distances between real points,
    so their minimum is exact without a special case for (near-)parallel segments, where
    the critical point is ill-conditioned.
    """
    p0, p1, q0, q1 = (_v(a) for a in _prep(xp, p0, p1, q0, q1))
    return _segment_segment(xp, p0, _sub(p1, p0), q0, _sub(q1, q0))

def segment_cylinder_distance(
    xp: Any, p0: Array, p1: Array, pos: Array, rot: Array, size: Array, iters: int = GOLDEN_ITERS
) -> Array:
    """min (...,) over the segment of the cylinder's signed distance: golden-section search on a
    convex function (the SDF of a convex set is convex), within 0.618^iters of the segment."""
    p0, p1, pos, rot, size = _prep(xp, p0, p1, pos, rot, size)
    m = _m(rot)
    l0 = _tv(_mtv(m, _sub(_v(p0), _v(pos))))
    d = _tv(_mtv(m, _sub(_v(p1), _v(p0))))
    return _segments_vs_cylinder(xp, l0, d, size[..., 0:1], size[..., 1:2], iters)[..., 0]


# ------------------------------------------------------------------ pair distances
# Uniform signature (xp, pos_a, rot_a, size_a, pos_b, rot_b, size_b) -> (...,); all
# broadcast over leading dimensions, so they also vmap.  Names follow the kind order
# SPHERE < CAPSULE < BOX < CYLINDER.


def sphere_sphere_distance(xp: Any, pos_a: Array, rot_a: Array, size_a: Array,
                           pos_b: Array, rot_b: Array, size_b: Array) -> Array:
    """Exact: centre distance minus both radii."""
    pos_a, size_a, pos_b, size_b = _prep(xp, pos_a, size_a, pos_b, size_b)
    return _len(xp, *_sub(_v(pos_a), _v(pos_b))) - size_a[..., 0] - size_b[..., 0]


def _sphere_vs(point_fn: Callable[..., Array], doc: str) -> Callable[..., Array]:
    """Sphere A vs primitive B: B's point SDF at A's centre minus A's radius."""

    def distance(xp: Any, pos_a: Array, rot_a: Array, size_a: Array,
             pos_b: Array, rot_b: Array, size_b: Array) -> Array:
        pos_a, size_a = _prep(xp, pos_a, size_a)
        return point_fn(xp, pos_a, pos_b, rot_b, size_b) - size_a[..., 0]

    distance.__doc__ = doc
    return distance


sphere_capsule_distance = _sphere_vs(point_capsule_distance, "Exact: centre to capsule axis, minus both radii.")
sphere_box_distance = _sphere_vs(point_box_distance,
                                 "Exact (also with the centre inside the box): box SDF at the centre minus the radius.")
sphere_cylinder_distance = _sphere_vs(point_cylinder_distance, "Exact: cylinder SDF at the centre minus the radius.")


def capsule_capsule_distance(xp: Any, pos_a: Array, rot_a: Array, size_a: Array,
                             pos_b: Array, rot_b: Array, size_b: Array) -> Array:
    """Exact: segment-segment distance minus both radii (penetration exact while the axes do not cross)."""
    pos_a, rot_a, size_a, pos_b, rot_b, size_b = _prep(xp, pos_a, rot_a, size_a, pos_b, rot_b, size_b)
    a0, da = _capsule_segment(pos_a, rot_a, size_a)
    b0, db = _capsule_segment(pos_b, rot_b, size_b)
    return _segment_segment(xp, a0, da, b0, db) - size_a[..., 0] - size_b[..., 0]

def capsule_cylinder_distance(xp: Any, pos_a: Array, rot_a: Array, size_a: Array,
                              pos_b: Array, rot_b: Array, size_b: Array, iters: int = GOLDEN_ITERS) -> Array:
    """Capsule A vs cylinder B: golden-section min over the capsule axis of the exact cylinder
    SDF, minus the radius (exact outside to ~1e-9 m, correct sign inside)."""
    pos_a, rot_a, size_a, pos_b, rot_b, size_b = _prep(xp, pos_a, rot_a, size_a, pos_b, rot_b, size_b)
    a0, da = _capsule_segment(pos_a, rot_a, size_a)
    mb = _m(rot_b)
    l0 = _tv(_mtv(mb, _sub(a0, _v(pos_b))))
    d = _tv(_mtv(mb, da))
    inner = _segments_vs_cylinder(xp, l0, d, size_b[..., 0:1], size_b[..., 1:2], iters)[..., 0]
    return inner - size_a[..., 0]


def box_box_distance(xp: Any, pos_a: Array, rot_a: Array, size_a: Array,
                     pos_b: Array, rot_b: Array, size_b: Array) -> Array:
    """Exact signed distance between two boxes.

    The 15-axis SAT decides overlap and, when overlapping, its smallest overlap is the
    penetration depth.  When separated, the closest points of two disjoint convex
    polytopes can always be taken with one of them on an edge, so the distance is the
    minimum of the 24 closed-form edge-box distances.
    """
    pos_a, rot_a, size_a, pos_b, rot_b, size_b = _prep(xp, pos_a, rot_a, size_a, pos_b, rot_b, size_b)
    ha, hb = _v(size_a), _v(size_b)
    m_ab, t_ab, m_ba, t_ba, axes, m_ab_t = _frames(xp, pos_a, rot_a, pos_b, rot_b, _box_box_axes())
    gap = _sat(xp, axes, t_ab, [
        lambda u: _dot(_tv(ha), (xp.abs(u[0]), xp.abs(u[1]), xp.abs(u[2]))),
        lambda u: _dot(_tv(hb), tuple(xp.abs(c) for c in _mtv(m_ab_t, u))),  # type: ignore[arg-type]
    ])
    s_a, d_a = _box_edges(xp, ha, m_ba, t_ba)
    s_b, d_b = _box_edges(xp, hb, m_ab, t_ab)
    sep = xp.minimum(
        _min_last(xp, _segment_box_outside(xp, s_a, d_a, _tv(hb))),
        _min_last(xp, _segment_box_outside(xp, s_b, d_b, _tv(ha))),
    )
    return xp.where(gap > 0, sep, gap)


def box_cylinder_distance(xp: Any, pos_a: Array, rot_a: Array, size_a: Array,
                          pos_b: Array, rot_b: Array, size_b: Array,
                          sides: int = CYLINDER_SIDES, iters: int = CYLINDER_GOLDEN_ITERS) -> Array:
    """Box A vs cylinder B, within ``cylinder_error_bound(r_B, sides=sides)`` of the exact value.

    The cylinder becomes a ``sides``-gon prism.  A SAT over the prism-box axes (box faces,
    prism faces, box-edge x prism-edge crosses) decides overlap and gives the depth.  When
    separated, the distance is the minimum of the 3K prism edges against the box (closed
    form) and the 12 box edges against the exact cylinder (golden section).
    """
    prism = _prism(sides)
    pos_a, rot_a, size_a, pos_b, rot_b, size_b = _prep(xp, pos_a, rot_a, size_a, pos_b, rot_b, size_b)
    ha = _v(size_a)
    radius, half_height = size_b[..., 0], size_b[..., 1]
    m_ab, t_ab, m_ba, t_ba, axes, m_ab_t = _frames(xp, pos_a, rot_a, pos_b, rot_b, prism["box_cyl_axes"])
    gap = _sat(xp, axes, t_ab, [
        lambda u: _dot(_tv(ha), (xp.abs(u[0]), xp.abs(u[1]), xp.abs(u[2]))),
        lambda u: _prism_width(xp, _mtv(m_ab_t, u), radius, half_height, prism),
    ])
    p_start, p_step = _prism_edges(xp, radius, half_height, m_ab, t_ab, prism)
    prism_to_box = _min_last(xp, _segment_box_outside(xp, p_start, p_step, _tv(ha)))
    b_start, b_step = _box_edges(xp, ha, m_ba, t_ba)
    box_to_cyl = _segments_vs_cylinder(xp, b_start, b_step, radius[..., None], half_height[..., None], iters)
    return xp.where(gap > 0, xp.minimum(prism_to_box, _min_last(xp, box_to_cyl, unfused=True)), gap)


def cylinder_cylinder_distance(xp: Any, pos_a: Array, rot_a: Array, size_a: Array,
                               pos_b: Array, rot_b: Array, size_b: Array,
                               sides: int = CYLINDER_SIDES, iters: int = CYLINDER_GOLDEN_ITERS) -> Array:
    """Two cylinders, within ``cylinder_error_bound(r_A, r_B, sides)`` of the exact value.

    Both become ``sides``-gon prisms; a SAT over (K/2+1)² + K + 2 axes decides overlap and
    gives the depth; when separated, the distance is the minimum of each prism's 3K edges
    against the other, exact, cylinder (golden section).  The most expensive pair: keep
    cylinder-cylinder pairs to the few that can actually meet.
    """
    prism = _prism(sides)
    pos_a, rot_a, size_a, pos_b, rot_b, size_b = _prep(xp, pos_a, rot_a, size_a, pos_b, rot_b, size_b)
    ra, ha, rb, hb = size_a[..., 0], size_a[..., 1], size_b[..., 0], size_b[..., 1]
    m_ab, t_ab, m_ba, t_ba, axes, m_ab_t = _frames(xp, pos_a, rot_a, pos_b, rot_b, prism["cyl_cyl_axes"])
    gap = _sat(xp, axes, t_ab, [
        lambda u: _prism_width(xp, u, ra, ha, prism),
        lambda u: _prism_width(xp, _mtv(m_ab_t, u), rb, hb, prism),
    ])
    n_chords = 2 * sides

    def edges_vs_cylinder(start: Vec, step: Vec, radius: Array, half_height: Array) -> Array:
        # Rim chords are short (0.26 r at 24 sides): 8 fewer golden steps suffice for them.
        r_e, h_e = radius[..., None], half_height[..., None]
        head = (tuple(c[..., :n_chords] for c in start), tuple(c[..., :n_chords] for c in step))
        tail = (tuple(c[..., n_chords:] for c in start), tuple(c[..., n_chords:] for c in step))
        chords = _segments_vs_cylinder(xp, *head, r_e, h_e, max(iters - 8, 4))  # type: ignore[arg-type]
        sides_ = _segments_vs_cylinder(xp, *tail, r_e, h_e, iters)  # type: ignore[arg-type]
        return xp.minimum(_min_last(xp, chords, unfused=True), _min_last(xp, sides_, unfused=True))

    a_start, a_step = _prism_edges(xp, ra, ha, m_ba, t_ba, prism)  # A's prism edges in B's frame
    b_start, b_step = _prism_edges(xp, rb, hb, m_ab, t_ab, prism)  # B's prism edges in A's frame
    sep = xp.minimum(edges_vs_cylinder(a_start, a_step, rb, hb), edges_vs_cylinder(b_start, b_step, ra, ha))
    return xp.where(gap > 0, sep, gap)


def _swap(fn: Callable[..., Array]) -> Callable[..., Array]:
    def swapped(xp: Any, pa: Array, ra: Array, sa: Array, pb: Array, rb: Array, sb: Array, **kw: Any) -> Array:
        return fn(xp, pb, rb, sb, pa, ra, sa, **kw)

    return swapped


_PAIR_FUNCTIONS: dict[tuple[int, int], Callable[..., Array]] = {
    (SPHERE, SPHERE): sphere_sphere_distance,
    (SPHERE, CAPSULE): sphere_capsule_distance,
    (SPHERE, BOX): sphere_box_distance,
    (SPHERE, CYLINDER): sphere_cylinder_distance,
    (CAPSULE, CAPSULE): capsule_capsule_distance,
    (CAPSULE, BOX): capsule_box_distance,
    (CAPSULE, CYLINDER): capsule_cylinder_distance,
    (BOX, BOX): box_box_distance,
    (BOX, CYLINDER): box_cylinder_distance,
    (CYLINDER, CYLINDER): cylinder_cylinder_distance,
}
for (_ka, _kb), _fn in list(_PAIR_FUNCTIONS.items()):
    _PAIR_FUNCTIONS.setdefault((_kb, _ka), _swap(_fn))
_PRISM_PAIRS = {(BOX, CYLINDER), (CYLINDER, BOX), (CYLINDER, CYLINDER)}


def pair_distance(
    xp: Any,
    kind_a: int,
    pos_a: Array,
    rot_a: Array,
    size_a: Array,
    kind_b: int,
    pos_b: Array,
    rot_b: Array,
    size_b: Array,
    sides: int = CYLINDER_SIDES,
) -> Array:
    """Signed distance (...,) between primitives of static kinds ``kind_a`` and ``kind_b``."""
    key = (int(kind_a), int(kind_b))
    if key not in _PAIR_FUNCTIONS:
        raise ValueError(f"unknown primitive kinds {key}")
    kw = {"sides": sides} if key in _PRISM_PAIRS else {}
    return _PAIR_FUNCTIONS[key](xp, pos_a, rot_a, size_a, pos_b, rot_b, size_b, **kw)

# --------------------------------------------------------------------- dispatch


def distance_to_obstacle(xp: Any, robot_kind: int, robot_pos: Array, robot_rot: Array, robot_size: Array,
                         obs_kind: Array, obs_pos: Array, obs_rot: Array, obs_size: Array,
                         obstacle_kinds: Sequence[int] = (SPHERE, CYLINDER, BOX), sides: int = CYLINDER_SIDES) -> Array:
    """Signed distance (...,) from a robot primitive of static kind to an obstacle whose kind is
    data (``obs_kind``, an integer array broadcasting with the poses).

    Every pair function for ``obstacle_kinds`` is evaluated and the right one selected with
    ``where`` (a traced kind costs the sum of those pair costs).  A kind outside
    ``obstacle_kinds`` (e.g. -1 for an empty obstacle slot) gives +inf.
    """
    obs_kind = xp.asarray(obs_kind)
    out: Array = xp.inf
    for k in obstacle_kinds:
        d = pair_distance(xp, robot_kind, robot_pos, robot_rot, robot_size, k, obs_pos, obs_rot, obs_size, sides=sides)
        out = xp.where(obs_kind == k, d, out)
    return out


def _groups(kinds: Sequence[int] | np.ndarray) -> tuple[list[tuple[int, np.ndarray]], np.ndarray]:
    """Indices per static kind, and the permutation that undoes the grouping."""
    flat = np.asarray(kinds, dtype=int).reshape(-1)
    groups = [(int(k), np.nonzero(flat == k)[0]) for k in sorted(set(flat.tolist()))]
    order = np.concatenate([idx for _, idx in groups]) if groups else np.zeros(0, dtype=int)
    return groups, np.argsort(order)


def _rows_of(ia: np.ndarray, pos: Array, rot: Array, size: Array) -> tuple[Array, Array, Array]:
    """Primitives ``ia`` of a set, with an axis for the other set's primitives after theirs."""
    return pos[..., ia, None, :], rot[..., ia, None, :, :], size[..., ia, None, :]


def distance_matrix(
    xp: Any,
    kinds_a: Sequence[int] | np.ndarray,
    pos_a: Array,
    rot_a: Array,
    size_a: Array,
    kinds_b: Sequence[int] | np.ndarray,
    pos_b: Array,
    rot_b: Array,
    size_b: Array,
    sides: int = CYLINDER_SIDES,
) -> Array:
    """(..., G, N) signed distances between G primitives of static ``kinds_a`` (e.g.
    ``load_robot().prim_kind`` with poses from ``primitive_poses``: (..., G, 3), (..., G, 3, 3),
    sizes (G, 3) or (..., G, 3)) and N primitives of static ``kinds_b`` (e.g. the scene's
    ``static_arrays()``).

    One broadcast call per kind pair present (at most 16 blocks, however large G and N), and
    the blocks are put back in input order.
    """
    groups_a, inv_a = _groups(kinds_a)
    groups_b, inv_b = _groups(kinds_b)
    pos_a, rot_a, size_a, pos_b, rot_b, size_b = _prep(xp, pos_a, rot_a, size_a, pos_b, rot_b, size_b)
    batch = np.broadcast_shapes(
        pos_a.shape[:-2], rot_a.shape[:-3], size_a.shape[:-2], pos_b.shape[:-2], rot_b.shape[:-3], size_b.shape[:-2]
    )
    rows = []
    for ka, ia in groups_a:
        cols = []
        for kb, ib in groups_b:
            b_cols = (pos_b[..., None, ib, :], rot_b[..., None, ib, :, :], size_b[..., None, ib, :])
            block = pair_distance(xp, ka, *_rows_of(ia, pos_a, rot_a, size_a), kb, *b_cols, sides=sides)
            cols.append(xp.broadcast_to(block, batch + (len(ia), len(ib))))
        rows.append(xp.concatenate(cols, axis=-1))
    full = xp.concatenate(rows, axis=-2)
    return full[..., inv_a, :][..., inv_b]


def obstacle_distance_matrix(xp: Any, kinds_a: Sequence[int] | np.ndarray, pos_a: Array, rot_a: Array, size_a: Array,
                             obs_kind: Array, obs_pos: Array, obs_rot: Array, obs_size: Array,
                             obstacle_kinds: Sequence[int] = (SPHERE, CYLINDER, BOX),
                             sides: int = CYLINDER_SIDES) -> Array:
    """(..., G, N) signed distances between G robot primitives of static kinds and N obstacle
    slots whose kinds are data (``obs_kind`` (..., N); kinds outside ``obstacle_kinds``, e.g.
    -1 for an empty slot, give +inf).  One broadcast call per (robot kind, obstacle kind)."""
    groups_a, inv_a = _groups(kinds_a)
    pos_a, rot_a, size_a, obs_pos, obs_rot, obs_size = _prep(xp, pos_a, rot_a, size_a, obs_pos, obs_rot, obs_size)
    obs_kind = xp.asarray(obs_kind)
    batch = np.broadcast_shapes(pos_a.shape[:-2], rot_a.shape[:-3], size_a.shape[:-2], obs_kind.shape[:-1],
                                obs_pos.shape[:-2], obs_rot.shape[:-3], obs_size.shape[:-2])
    n = obs_pos.shape[-2]
    obstacles = (obs_kind[..., None, :], obs_pos[..., None, :, :], obs_rot[..., None, :, :, :],
                 obs_size[..., None, :, :])
    rows = []
    for ka, ia in groups_a:
        block = distance_to_obstacle(xp, ka, *_rows_of(ia, pos_a, rot_a, size_a), *obstacles,
                                     obstacle_kinds=obstacle_kinds, sides=sides)
        rows.append(xp.broadcast_to(block, batch + (len(ia), n)))
    return xp.concatenate(rows, axis=-2)[..., inv_a, :]
