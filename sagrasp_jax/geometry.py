"""Signed distances between collision primitives, written once for NumPy and JAX.

SPEC §2 ("Collision") asks for analytic distances and overlaps computed from body
poses, not MJX contacts.  Every public function takes the array module first
(``xp`` = numpy or jax.numpy), has no Python control flow on array values (fixed
iteration counts unroll), and broadcasts over leading batch dimensions, so the same
code runs in the PyBullet reference env and the deployment runtime (NumPy) and
jits / vmaps in the MJX env.  This module must not import jax.

Primitives follow MuJoCo's size convention (see ``robot.py``): a primitive is
``pos (..., 3)``, ``rot (..., 3, 3)`` (world rotation, columns = local axes) and
``size (..., 3)``: sphere ``(r, 0, 0)``, capsule ``(r, half_length, 0)`` along local
z, cylinder ``(r, half_height, 0)`` along local z, box half-extents.

Sign convention: positive = gap between the surfaces, negative = overlap.  Exactness:

* sphere vs anything, capsule vs capsule, box vs box: exact signed distance
  (penetration depth = minimum translation distance; for capsule-capsule while the
  two axis segments do not cross, for box-box always, via the 15-axis SAT).
* capsule vs box, capsule vs cylinder: exact outside; when overlapping the value is
  ``min over the capsule axis of sdf_other - r`` (correct sign, continuous through
  contact, but not the minimum translation distance).
* cylinder vs box, cylinder vs cylinder: the cylinder is replaced by a prism with a
  regular ``sides``-gon cross-section; worst-case error in ``cylinder_error_bound``
  (< 1.2 mm for every primitive pair of this project at the default 24 sides).

Performance: the kernels work on x/y/z component arrays (never on a trailing axis of
length 3), so XLA fuses each pair function into a few elementwise loops; that is ~10x
faster on CPU than the same maths on (..., 3) arrays.  Measured CPU time per pair,
float32, ``jax.jit(jax.vmap(...))`` over 1024 pairs, one core of the 2-core dev Xeon:
sphere-* 0.05 µs, capsule-capsule 0.11, capsule-box 0.13, capsule-cylinder 0.23,
box-box 1.0, box-cylinder 4.5, cylinder-cylinder 23.  The robot's 10 primitives against
the 5 static boxes of the cell: 71 µs per env; against 2 obstacle slots of traced kind
(every kind evaluated, see ``distance_to_obstacle``): 190 µs per env, half of it the four
cylinder-cylinder pairs of the base and the flange, so leave the static base out of
obstacle queries.  NumPy pays per operation (~2-7 ms per box/cylinder pair call): fine
for one env, not for batches.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from sagrasp_jax.robot import BOX, CAPSULE, CYLINDER, SPHERE

Array = Any
Vec = tuple[Any, Any, Any]  # x, y, z component arrays
Mat = tuple[Vec, Vec, Vec]  # rows of a 3x3 matrix, each a Vec of component arrays

__all__ = [
    "SPHERE",
    "CAPSULE",
    "BOX",
    "CYLINDER",
    "GOLDEN_ITERS",
    "CYLINDER_SIDES",
    "CYLINDER_GOLDEN_ITERS",
    "point_sphere_distance",
    "point_capsule_distance",
    "point_box_distance",
    "point_cylinder_distance",
    "point_distance",
    "segment_segment_distance",
    "segment_box_distance",
    "segment_cylinder_distance",
    "sphere_sphere_distance",
    "sphere_capsule_distance",
    "sphere_box_distance",
    "sphere_cylinder_distance",
    "capsule_capsule_distance",
    "capsule_box_distance",
    "capsule_cylinder_distance",
    "box_box_distance",
    "box_cylinder_distance",
    "cylinder_cylinder_distance",
    "cylinder_error_bound",
    "pair_distance",
    "support_radius",
    "plane_distance",
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
_BIG = 1e30  # finite sentinel (fits float32) for masked maxima / minima

# Box edges: edge e runs along local axis _EDGE_AXIS[e], from the vertex _EDGE_SIGNS[e]
# (sign -1 on that axis) to the opposite end.
_EDGE_AXIS = np.repeat(np.arange(3), 4)
_EDGE_SIGNS = np.array(
    [[-1.0, sy, sz] for sy in (-1, 1) for sz in (-1, 1)]
    + [[sx, -1.0, sz] for sx in (-1, 1) for sz in (-1, 1)]
    + [[sx, sy, -1.0] for sx in (-1, 1) for sy in (-1, 1)]
)
_EDGE_STEP = 2.0 * np.eye(3)[_EDGE_AXIS]  # edge vector / half-extents


# ------------------------------------------------------------ component algebra


def _prep(xp: Any, *arrays: Any) -> list[Array]:
    """Convert to one common floating dtype (float32 stays float32)."""
    arrs = [xp.asarray(a) for a in arrays]
    dtype = xp.result_type(*arrs, 1.0)
    return [a.astype(dtype) for a in arrs]


def _v(a: Array) -> Vec:
    return (a[..., 0], a[..., 1], a[..., 2])


def _m(r: Array) -> Mat:
    return tuple(tuple(r[..., i, j] for j in range(3)) for i in range(3))  # type: ignore[return-value]


def _add(a: Vec, b: Vec) -> Vec:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def _sub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _mul(a: Vec, s: Array) -> Vec:
    return (a[0] * s, a[1] * s, a[2] * s)


def _dot(a: Vec, b: Vec) -> Array:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _len(xp: Any, *comps: Array) -> Array:
    """Euclidean norm of the given components, with a finite gradient at zero."""
    sq = comps[0] * comps[0]
    for c in comps[1:]:
        sq = sq + c * c
    return _sqrt(xp, sq)


def _sqrt(xp: Any, sq: Array) -> Array:
    """sqrt of a non-negative array with a finite gradient at zero."""
    pos = sq > 0
    return xp.where(pos, xp.sqrt(xp.where(pos, sq, 1.0)), 0.0)


def _mv(m: Mat, v: Vec) -> Vec:
    """m·v."""
    return tuple(m[i][0] * v[0] + m[i][1] * v[1] + m[i][2] * v[2] for i in range(3))  # type: ignore[return-value]


def _mtv(m: Mat, v: Vec) -> Vec:
    """mᵀ·v."""
    return tuple(m[0][j] * v[0] + m[1][j] * v[1] + m[2][j] * v[2] for j in range(3))  # type: ignore[return-value]


def _mtm(a: Mat, b: Mat) -> Mat:
    """aᵀ·b."""
    return tuple(  # type: ignore[return-value]
        tuple(a[0][i] * b[0][j] + a[1][i] * b[1][j] + a[2][i] * b[2][j] for j in range(3)) for i in range(3)
    )


def _tv(v: Vec) -> Vec:
    """Add a trailing (feature) axis to every component."""
    return (v[0][..., None], v[1][..., None], v[2][..., None])


def _tm(m: Mat) -> Mat:
    return tuple(_tv(row) for row in m)  # type: ignore[return-value]


def _rel(rot_f: Mat, pos_f: Vec, rot_o: Mat, pos_o: Vec) -> tuple[Mat, Vec]:
    """Pose of frame o expressed in frame f: (rot_fᵀ·rot_o, rot_fᵀ·(pos_o - pos_f))."""
    return _mtm(rot_f, rot_o), _mtv(rot_f, _sub(pos_o, pos_f))


def _safe_div(xp: Any, num: Array, den: Array) -> Array:
    """num/den where den != 0, else 0 (callers clip the result into [0, 1])."""
    ok = den != 0
    return xp.where(ok, num / xp.where(ok, den, 1.0), 0.0)


def _const(xp: Any, table: np.ndarray, like: Array) -> Array:
    return xp.asarray(table, dtype=like.dtype)


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


# ------------------------------------------------------------- local-frame kernels


def _box_sdf(xp: Any, x: Vec, half: Vec) -> Array:
    q = [xp.abs(x[i]) - half[i] for i in range(3)]
    outside = _len(xp, *(xp.maximum(qi, 0.0) for qi in q))
    return outside + xp.minimum(xp.maximum(xp.maximum(q[0], q[1]), q[2]), 0.0)


def _cylinder_sdf(xp: Any, x: Vec, radius: Array, half_height: Array) -> Array:
    qr = _len(xp, x[0], x[1]) - radius
    qz = xp.abs(x[2]) - half_height
    return _len(xp, xp.maximum(qr, 0.0), xp.maximum(qz, 0.0)) + xp.minimum(xp.maximum(qr, qz), 0.0)


def _point_segment(xp: Any, p: Vec, a: Vec, d: Vec) -> Array:
    """Distance from p to the segment a + t·d, t in [0, 1]."""
    r = _sub(p, a)
    t = xp.clip(_safe_div(xp, _dot(r, d), _dot(d, d)), 0.0, 1.0)
    return _len(xp, *_sub(r, _mul(d, t)))


def _segment_box_outside(xp: Any, l0: Vec, d: Vec, half: Vec) -> Array:
    """Exact unsigned distance from the segment l0 + t·d, t in [0, 1], to the box |x| <= half.

    The squared outside distance along the segment, Σ_i max(|x_i(t)| - h_i, 0)², is convex
    and C¹ with a piecewise-linear derivative D(t) whose kinks are where a coordinate
    crosses a face plane (6 values) .  D is monotone, so the minimiser lies between the last
    kink with D <= 0 and the first with D > 0, where D is linear: one interpolation gives it
    exactly.  The distances at all kinks are kept as a fallback against rounding.
    """
    zero = xp.zeros_like(l0[0] + d[0] + half[0])
    ts = [zero, zero + 1.0]
    for i in range(3):
        ts.append(xp.clip(_safe_div(xp, half[i] - l0[i], d[i]), 0.0, 1.0))
        ts.append(xp.clip(_safe_div(xp, -half[i] - l0[i], d[i]), 0.0, 1.0))

    def deriv_and_sq(t: Array) -> tuple[Array, Array]:
        deriv, sq = zero, zero
        for i in range(3):
            x = l0[i] + t * d[i]
            excess = xp.maximum(xp.abs(x) - half[i], 0.0)
            deriv = deriv + d[i] * xp.where(x < 0, -excess, excess)
            sq = sq + excess * excess
        return deriv, sq

    t_lo, d_lo, t_hi, d_hi, best = zero, zero - _BIG, zero + 1.0, zero + _BIG, zero + _BIG
    for t in ts:
        deriv, sq = deriv_and_sq(t)
        neg = deriv <= 0
        t_lo = xp.where(neg, xp.maximum(t_lo, t), t_lo)
        d_lo = xp.where(neg, xp.maximum(d_lo, deriv), d_lo)
        t_hi = xp.where(neg, t_hi, xp.minimum(t_hi, t))
        d_hi = xp.where(neg, d_hi, xp.minimum(d_hi, deriv))
        best = xp.minimum(best, sq)
    any_neg = d_lo > -0.5 * _BIG
    any_pos = d_hi < 0.5 * _BIG
    both = any_neg & any_pos
    t_star = t_lo - xp.where(both, d_lo, 0.0) * _safe_div(xp, t_hi - t_lo, xp.where(both, d_hi - d_lo, 0.0))
    t_star = xp.clip(xp.where(any_neg, xp.where(any_pos, t_star, 1.0), 0.0), 0.0, 1.0)
    _, sq_star = deriv_and_sq(t_star)
    return _sqrt(xp, xp.minimum(best, sq_star))


def _segment_box_inside(xp: Any, l0: Vec, d: Vec, half: Vec) -> Array:
    """min over t of max_i(|x_i(t)| - h_i): negative iff the segment enters the box interior.

    It is the minimum of the upper envelope of six lines in t, attained at an endpoint or
    where two of the lines cross (15 pairs), so evaluating those 17 candidates is exact.
    """
    slopes = [d[i] for i in range(3)] + [-d[i] for i in range(3)]
    icepts = [l0[i] - half[i] for i in range(3)] + [-l0[i] - half[i] for i in range(3)]
    zero = xp.zeros_like(l0[0] + d[0] + half[0])
    ts = [zero, zero + 1.0]
    for k in range(6):
        for j in range(k + 1, 6):
            ts.append(xp.clip(_safe_div(xp, icepts[j] - icepts[k], slopes[k] - slopes[j]), 0.0, 1.0))
    best = zero + _BIG
    for t in ts:
        env = slopes[0] * t + icepts[0]
        for k in range(1, 6):
            env = xp.maximum(env, slopes[k] * t + icepts[k])
        best = xp.minimum(best, env)
    return best


def _segment_box_sdf(xp: Any, l0: Vec, d: Vec, half: Vec) -> Array:
    """Exact min over the segment of the box SDF (box-local coordinates)."""
    inside = _segment_box_inside(xp, l0, d, half)
    return xp.where(inside < 0, inside, _segment_box_outside(xp, l0, d, half))


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


# ------------------------------------------------------------------ point SDFs


def point_sphere_distance(xp: Any, point: Array, pos: Array, rot: Array, size: Array) -> Array:
    """Signed distance (...,) from points to a sphere (``rot`` unused, kept for a uniform API)."""
    point, pos, size = _prep(xp, point, pos, size)
    return _len(xp, *_sub(_v(point), _v(pos))) - size[..., 0]


def point_capsule_distance(xp: Any, point: Array, pos: Array, rot: Array, size: Array) -> Array:
    """Signed distance (...,) from points to a capsule: distance to its axis segment minus r."""
    point, pos, rot, size = _prep(xp, point, pos, rot, size)
    axis = _mul((rot[..., 0, 2], rot[..., 1, 2], rot[..., 2, 2]), size[..., 1])
    return _point_segment(xp, _v(point), _sub(_v(pos), axis), _mul(axis, 2.0)) - size[..., 0]


def point_box_distance(xp: Any, point: Array, pos: Array, rot: Array, size: Array) -> Array:
    """Exact signed distance (...,) from points to a box (negative = depth below the nearest face)."""
    point, pos, rot, size = _prep(xp, point, pos, rot, size)
    return _box_sdf(xp, _mtv(_m(rot), _sub(_v(point), _v(pos))), _v(size))


def point_cylinder_distance(xp: Any, point: Array, pos: Array, rot: Array, size: Array) -> Array:
    """Exact signed distance (...,) from points to a finite solid cylinder."""
    point, pos, rot, size = _prep(xp, point, pos, rot, size)
    return _cylinder_sdf(xp, _mtv(_m(rot), _sub(_v(point), _v(pos))), size[..., 0], size[..., 1])


_POINT_FUNCTIONS = {
    SPHERE: point_sphere_distance,
    CAPSULE: point_capsule_distance,
    BOX: point_box_distance,
    CYLINDER: point_cylinder_distance,
}


def point_distance(xp: Any, kind: int, point: Array, pos: Array, rot: Array, size: Array) -> Array:
    """Signed distance (...,) from points to a primitive of a static ``kind``."""
    return _POINT_FUNCTIONS[int(kind)](xp, point, pos, rot, size)


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


def segment_box_distance(xp: Any, p0: Array, p1: Array, pos: Array, rot: Array, size: Array) -> Array:
    """Exact min (...,) over the segment [p0, p1] of the box's signed distance (closed form)."""
    p0, p1, pos, rot, size = _prep(xp, p0, p1, pos, rot, size)
    m = _m(rot)
    l0 = _mtv(m, _sub(_v(p0), _v(pos)))
    d = _mtv(m, _sub(_v(p1), _v(p0)))
    return _segment_box_sdf(xp, l0, d, _v(size))


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


def sphere_sphere_distance(
    xp: Any,
    pos_a: Array,
    rot_a: Array,
    size_a: Array,
    pos_b: Array,
    rot_b: Array,
    size_b: Array,
) -> Array:
    """Exact: centre distance minus both radii."""
    pos_a, size_a, pos_b, size_b = _prep(xp, pos_a, size_a, pos_b, size_b)
    return _len(xp, *_sub(_v(pos_a), _v(pos_b))) - size_a[..., 0] - size_b[..., 0]


def sphere_capsule_distance(
    xp: Any,
    pos_a: Array,
    rot_a: Array,
    size_a: Array,
    pos_b: Array,
    rot_b: Array,
    size_b: Array,
) -> Array:
    """Exact: centre to capsule axis, minus both radii."""
    pos_a, size_a = _prep(xp, pos_a, size_a)
    return point_capsule_distance(xp, pos_a, pos_b, rot_b, size_b) - size_a[..., 0]


def sphere_box_distance(
    xp: Any,
    pos_a: Array,
    rot_a: Array,
    size_a: Array,
    pos_b: Array,
    rot_b: Array,
    size_b: Array,
) -> Array:
    """Exact (also with the centre inside the box): box SDF at the centre minus the radius."""
    pos_a, size_a = _prep(xp, pos_a, size_a)
    return point_box_distance(xp, pos_a, pos_b, rot_b, size_b) - size_a[..., 0]


def sphere_cylinder_distance(
    xp: Any,
    pos_a: Array,
    rot_a: Array,
    size_a: Array,
    pos_b: Array,
    rot_b: Array,
    size_b: Array,
) -> Array:
    """Exact: cylinder SDF at the centre minus the radius."""
    pos_a, size_a = _prep(xp, pos_a, size_a)
    return point_cylinder_distance(xp, pos_a, pos_b, rot_b, size_b) - size_a[..., 0]


def _capsule_segment(pos: Array, rot: Array, size: Array) -> tuple[Vec, Vec]:
    axis = _mul((rot[..., 0, 2], rot[..., 1, 2], rot[..., 2, 2]), size[..., 1])
    return _sub(_v(pos), axis), _mul(axis, 2.0)


def capsule_capsule_distance(
    xp: Any,
    pos_a: Array,
    rot_a: Array,
    size_a: Array,
    pos_b: Array,
    rot_b: Array,
    size_b: Array,
) -> Array:
    """Exact: segment-segment distance minus both radii (penetration exact while the axes do not cross)."""
    pos_a, rot_a, size_a, pos_b, rot_b, size_b = _prep(xp, pos_a, rot_a, size_a, pos_b, rot_b, size_b)
    a0, da = _capsule_segment(pos_a, rot_a, size_a)
    b0, db = _capsule_segment(pos_b, rot_b, size_b)
    return _segment_segment(xp, a0, da, b0, db) - size_a[..., 0] - size_b[..., 0]


def capsule_box_distance(
    xp: Any,
    pos_a: Array,
    rot_a: Array,
    size_a: Array,
    pos_b: Array,
    rot_b: Array,
    size_b: Array,
) -> Array:
    """Capsule A vs box B: exact min over the capsule axis of the box SDF, minus the radius.

    Closed form (piecewise-quadratic outside, piecewise-linear inside) rather than a
    golden-section search: the same value to rounding, several times cheaper and with no
    sequential dependency.
    """
    pos_a, rot_a, size_a, pos_b, rot_b, size_b = _prep(xp, pos_a, rot_a, size_a, pos_b, rot_b, size_b)
    a0, da = _capsule_segment(pos_a, rot_a, size_a)
    mb = _m(rot_b)
    l0 = _mtv(mb, _sub(a0, _v(pos_b)))
    return _segment_box_sdf(xp, l0, _mtv(mb, da), _v(size_b)) - size_a[..., 0]


def capsule_cylinder_distance(
    xp: Any,
    pos_a: Array,
    rot_a: Array,
    size_a: Array,
    pos_b: Array,
    rot_b: Array,
    size_b: Array,
    iters: int = GOLDEN_ITERS,
) -> Array:
    """Capsule A vs cylinder B: golden-section min over the capsule axis of the exact cylinder
    SDF, minus the radius (exact outside to ~1e-9 m, correct sign inside)."""
    pos_a, rot_a, size_a, pos_b, rot_b, size_b = _prep(xp, pos_a, rot_a, size_a, pos_b, rot_b, size_b)
    a0, da = _capsule_segment(pos_a, rot_a, size_a)
    mb = _m(rot_b)
    l0 = _tv(_mtv(mb, _sub(a0, _v(pos_b))))
    d = _tv(_mtv(mb, da))
    inner = _segments_vs_cylinder(xp, l0, d, size_b[..., 0:1], size_b[..., 1:2], iters)[..., 0]
    return inner - size_a[..., 0]


def box_box_distance(
    xp: Any,
    pos_a: Array,
    rot_a: Array,
    size_a: Array,
    pos_b: Array,
    rot_b: Array,
    size_b: Array,
) -> Array:
    """Exact signed distance between two boxes.

    The 15-axis SAT decides overlap and, when overlapping, its smallest overlap is the
    penetration depth.  When separated, the closest points of two disjoint convex
    polytopes can always be taken with one of them on an edge, so the distance is the
    minimum of the 24 closed-form edge-box distances.
    """
    pos_a, rot_a, size_a, pos_b, rot_b, size_b = _prep(xp, pos_a, rot_a, size_a, pos_b, rot_b, size_b)
    ma, mb, ha, hb = _m(rot_a), _m(rot_b), _v(size_a), _v(size_b)
    m_ab, t_ab = _rel(ma, _v(pos_a), mb, _v(pos_b))  # B in A's frame
    m_ba, t_ba = _rel(mb, _v(pos_b), ma, _v(pos_a))  # A in B's frame
    axes = _linear_axes(xp, _box_box_axes(), m_ab)
    m_ab_t = _tm(m_ab)
    gap = _sat(
        xp,
        axes,
        t_ab,
        [
            lambda u: _dot(_tv(ha), (xp.abs(u[0]), xp.abs(u[1]), xp.abs(u[2]))),
            lambda u: _dot(_tv(hb), tuple(xp.abs(c) for c in _mtv(m_ab_t, u))),  # type: ignore[arg-type]
        ],
    )
    s_a, d_a = _box_edges(xp, ha, m_ba, t_ba)
    s_b, d_b = _box_edges(xp, hb, m_ab, t_ab)
    sep = xp.minimum(
        _min_last(xp, _segment_box_outside(xp, s_a, d_a, _tv(hb))),
        _min_last(xp, _segment_box_outside(xp, s_b, d_b, _tv(ha))),
    )
    return xp.where(gap > 0, sep, gap)


def box_cylinder_distance(
    xp: Any,
    pos_a: Array,
    rot_a: Array,
    size_a: Array,
    pos_b: Array,
    rot_b: Array,
    size_b: Array,
    sides: int = CYLINDER_SIDES,
    iters: int = CYLINDER_GOLDEN_ITERS,
) -> Array:
    """Box A vs cylinder B, within ``cylinder_error_bound(r_B, sides=sides)`` of the exact value.

    The cylinder becomes a ``sides``-gon prism.  A SAT over the prism-box axes (box faces,
    prism faces, box-edge x prism-edge crosses) decides overlap and gives the depth.  When
    separated, the distance is the minimum of the 3K prism edges against the box (closed
    form) and the 12 box edges against the exact cylinder (golden section).
    """
    prism = _prism(sides)
    pos_a, rot_a, size_a, pos_b, rot_b, size_b = _prep(xp, pos_a, rot_a, size_a, pos_b, rot_b, size_b)
    ma, mb, ha = _m(rot_a), _m(rot_b), _v(size_a)
    radius, half_height = size_b[..., 0], size_b[..., 1]
    m_ab, t_ab = _rel(ma, _v(pos_a), mb, _v(pos_b))  # cylinder in the box frame
    m_ba, t_ba = _rel(mb, _v(pos_b), ma, _v(pos_a))  # box in the cylinder frame
    axes = _linear_axes(xp, prism["box_cyl_axes"], m_ab)
    m_ab_t = _tm(m_ab)
    gap = _sat(
        xp,
        axes,
        t_ab,
        [
            lambda u: _dot(_tv(ha), (xp.abs(u[0]), xp.abs(u[1]), xp.abs(u[2]))),
            lambda u: _prism_width(xp, _mtv(m_ab_t, u), radius, half_height, prism),
        ],
    )
    p_start, p_step = _prism_edges(xp, radius, half_height, m_ab, t_ab, prism)
    prism_to_box = _min_last(xp, _segment_box_outside(xp, p_start, p_step, _tv(ha)))
    b_start, b_step = _box_edges(xp, ha, m_ba, t_ba)
    box_to_cyl = _segments_vs_cylinder(xp, b_start, b_step, radius[..., None], half_height[..., None], iters)
    return xp.where(gap > 0, xp.minimum(prism_to_box, _min_last(xp, box_to_cyl, unfused=True)), gap)


def cylinder_cylinder_distance(
    xp: Any,
    pos_a: Array,
    rot_a: Array,
    size_a: Array,
    pos_b: Array,
    rot_b: Array,
    size_b: Array,
    sides: int = CYLINDER_SIDES,
    iters: int = CYLINDER_GOLDEN_ITERS,
) -> Array:
    """Two cylinders, within ``cylinder_error_bound(r_A, r_B, sides)`` of the exact value.

    Both become ``sides``-gon prisms; a SAT over (K/2+1)² + K + 2 axes decides overlap and
    gives the depth; when separated, the distance is the minimum of each prism's 3K edges
    against the other, exact, cylinder (golden section).  The most expensive pair: keep
    cylinder-cylinder pairs to the few that can actually meet.
    """
    prism = _prism(sides)
    pos_a, rot_a, size_a, pos_b, rot_b, size_b = _prep(xp, pos_a, rot_a, size_a, pos_b, rot_b, size_b)
    ma, mb = _m(rot_a), _m(rot_b)
    ra, ha, rb, hb = size_a[..., 0], size_a[..., 1], size_b[..., 0], size_b[..., 1]
    m_ab, t_ab = _rel(ma, _v(pos_a), mb, _v(pos_b))  # B in A's frame
    m_ba, t_ba = _rel(mb, _v(pos_b), ma, _v(pos_a))  # A in B's frame
    axes = _linear_axes(xp, prism["cyl_cyl_axes"], m_ab)
    m_ab_t = _tm(m_ab)
    gap = _sat(
        xp,
        axes,
        t_ab,
        [
            lambda u: _prism_width(xp, u, ra, ha, prism),
            lambda u: _prism_width(xp, _mtv(m_ab_t, u), rb, hb, prism),
        ],
    )
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


# ------------------------------------------------------------- support and plane


def support_radius(xp: Any, kind: int | Array, rot: Array, size: Array, direction: Array) -> Array:
    """Half-width (...,) of a primitive along the unit ``direction``: max over its points x of
    direction·(x - pos) (all four kinds are centrally symmetric).

    ``kind`` may be a static int or an integer array (then every formula is computed and
    selected with ``where``; unknown kinds give NaN).
    """
    rot, size, direction = _prep(xp, rot, size, direction)
    loc = _mtv(_m(rot), _v(direction))
    r, h = size[..., 0], size[..., 1]
    az = xp.abs(loc[2])
    values = {
        SPHERE: lambda: r * _len(xp, *loc),
        CAPSULE: lambda: r * _len(xp, *loc) + h * az,
        BOX: lambda: _dot(_v(size), (xp.abs(loc[0]), xp.abs(loc[1]), az)),
        CYLINDER: lambda: r * _len(xp, loc[0], loc[1]) + h * az,
    }
    if isinstance(kind, (int, np.integer)):
        return values[int(kind)]()
    kind = xp.asarray(kind)
    out = xp.zeros_like(r) + xp.nan
    for k, value in values.items():
        out = xp.where(kind == k, value(), out)
    return out


def plane_distance(
    xp: Any,
    kind: int | Array,
    pos: Array,
    rot: Array,
    size: Array,
    plane_z: float = 0.0,
) -> Array:
    """Signed distance (...,) from a primitive to the half-space z <= ``plane_z`` (the table):
    height of its lowest point above the plane, via the support function (exact, every kind;
    ``kind`` static or an integer array)."""
    pos, rot, size = _prep(xp, pos, rot, size)
    up = xp.zeros_like(pos) + xp.asarray([0.0, 0.0, 1.0], dtype=pos.dtype)
    return pos[..., 2] - support_radius(xp, kind, rot, size, up) - plane_z


# --------------------------------------------------------------------- dispatch


def distance_to_obstacle(
    xp: Any,
    robot_kind: int,
    robot_pos: Array,
    robot_rot: Array,
    robot_size: Array,
    obs_kind: Array,
    obs_pos: Array,
    obs_rot: Array,
    obs_size: Array,
    obstacle_kinds: Sequence[int] = (SPHERE, CYLINDER, BOX),
    sides: int = CYLINDER_SIDES,
) -> Array:
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
            block = pair_distance(
                xp,
                ka,
                pos_a[..., ia, None, :],
                rot_a[..., ia, None, :, :],
                size_a[..., ia, None, :],
                kb,
                pos_b[..., None, ib, :],
                rot_b[..., None, ib, :, :],
                size_b[..., None, ib, :],
                sides=sides,
            )
            cols.append(xp.broadcast_to(block, batch + (len(ia), len(ib))))
        rows.append(xp.concatenate(cols, axis=-1))
    full = xp.concatenate(rows, axis=-2)
    return full[..., inv_a, :][..., inv_b]


def obstacle_distance_matrix(
    xp: Any,
    kinds_a: Sequence[int] | np.ndarray,
    pos_a: Array,
    rot_a: Array,
    size_a: Array,
    obs_kind: Array,
    obs_pos: Array,
    obs_rot: Array,
    obs_size: Array,
    obstacle_kinds: Sequence[int] = (SPHERE, CYLINDER, BOX),
    sides: int = CYLINDER_SIDES,
) -> Array:
    """(..., G, N) signed distances between G robot primitives of static kinds and N obstacle
    slots whose kinds are data (``obs_kind`` (..., N); kinds outside ``obstacle_kinds``, e.g.
    -1 for an empty slot, give +inf).  One broadcast call per (robot kind, obstacle kind)."""
    groups_a, inv_a = _groups(kinds_a)
    pos_a, rot_a, size_a, obs_pos, obs_rot, obs_size = _prep(xp, pos_a, rot_a, size_a, obs_pos, obs_rot, obs_size)
    obs_kind = xp.asarray(obs_kind)
    batch = np.broadcast_shapes(
        pos_a.shape[:-2],
        rot_a.shape[:-3],
        size_a.shape[:-2],
        obs_kind.shape[:-1],
        obs_pos.shape[:-2],
        obs_rot.shape[:-3],
        obs_size.shape[:-2],
    )
    n = obs_pos.shape[-2]
    rows = []
    for ka, ia in groups_a:
        block = distance_to_obstacle(
            xp,
            ka,
            pos_a[..., ia, None, :],
            rot_a[..., ia, None, :, :],
            size_a[..., ia, None, :],
            obs_kind[..., None, :],
            obs_pos[..., None, :, :],
            obs_rot[..., None, :, :, :],
            obs_size[..., None, :, :],
            obstacle_kinds=obstacle_kinds,
            sides=sides,
        )
        rows.append(xp.broadcast_to(block, batch + (len(ia), n)))
    return xp.concatenate(rows, axis=-2)[..., inv_a, :]
