"""geometry.py and reference/exact_geometry.py: closed-form cases per primitive pair, independent brute-force references,
cylinder error bounds, plane distances, dispatch helpers and NumPy / JAX agreement.

References are written here from scratch (support functions, projections, point SDFs) so
that they share no code with the module under test:

* any unit direction n gives a lower bound on the signed distance of two convex sets,
  n·(c_B - c_A) - h_A(n) - h_B(n), and the maximum over all n *is* the signed distance
  (distance when separated, minus the penetration depth when overlapping);
* alternating projections produce pairs of real points, so their distance is an upper
  bound when separated (and the direction joining them a matching lower bound).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401  (sets XLA flags before jax is imported)
import exact_geometry as geo  # the oracle; re-exports geometry's functions
from sagrasp_jax.task.config import HOME_Q
from sagrasp_jax.task.robot import BOX, CAPSULE, CYLINDER, SPHERE, forward_kinematics, load_robot, primitive_poses
from sagrasp_jax.task.scene import SCENE

I3 = np.eye(3)
KINDS = (SPHERE, CAPSULE, BOX, CYLINDER)
ALL_PAIRS = [(a, b) for a in KINDS for b in KINDS if a <= b]


# ------------------------------------------------------------------ helpers


def axis_angle(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return I3 + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def random_sizes(rng: np.random.Generator, kind: int, n: int) -> np.ndarray:
    if kind == SPHERE:
        return np.c_[rng.uniform(0.02, 0.1, n), np.zeros((n, 2))]
    if kind in (CAPSULE, CYLINDER):
        return np.c_[rng.uniform(0.02, 0.09, n), rng.uniform(0.01, 0.2, n), np.zeros(n)]
    return rng.uniform(0.01, 0.15, (n, 3))


def random_prims(rng: np.random.Generator, kind: int, n: int, spread: float = 0.2):
    return rng.uniform(-spread, spread, (n, 3)), random_rotations(rng, n), random_sizes(rng, kind, n)


def ref_width(kind: int, rot: np.ndarray, size: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Support half-width of centred primitives along unit n (..., M, 3); rot (..., 3, 3)."""
    loc = np.einsum("...mi,...ij->...mj", n, rot)
    az = np.abs(loc[..., 2])
    r, h = size[..., 0:1], size[..., 1:2]
    if kind == SPHERE:
        return np.broadcast_to(r, az.shape)
    if kind == CAPSULE:
        return r + h * az
    if kind == BOX:
        return np.einsum("...mj,...j->...m", np.abs(loc), size)
    return r * np.linalg.norm(loc[..., :2], axis=-1) + h * az


def fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    th = np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], -1)


def support_signed_distance(ka, pa, ra, sa, kb, pb, rb, sb, extra=None, seed: int = 0, iters: int = 150) -> np.ndarray:
    """max over unit n of the separation along n, per case (C,): a lower bound that converges
    to the signed distance.  Candidates: dense directions, the primitives' axes and their
    cross products (the exact optimum for flat contacts) and optional ``extra`` (C, E, 3);
    then a shrinking pattern search whose trial directions are also snapped onto the planes
    normal to each axis, where the support functions have their ridges."""
    c = len(pa)
    delta = pb - pa
    axes = np.concatenate([np.swapaxes(ra, 1, 2), np.swapaxes(rb, 1, 2)], axis=1)  # (C, 6, 3)
    cross = np.cross(axes[:, :, None], axes[:, None, :]).reshape(c, -1, 3)
    norm = np.linalg.norm(cross, axis=-1, keepdims=True)
    cross = np.where(norm > 1e-9, cross / np.maximum(norm, 1e-300), axes[:, :1])
    dirs = [np.broadcast_to(fibonacci_sphere(2000), (c, 2000, 3)), axes, cross]
    if extra is not None:
        dirs.append(extra)
    dirs = np.concatenate(dirs, axis=1)
    dirs = np.concatenate([dirs, -dirs], axis=1)

    def gap(n: np.ndarray) -> np.ndarray:
        return np.einsum("cmi,ci->cm", n, delta) - ref_width(ka, ra, sa, n) - ref_width(kb, rb, sb, n)

    def unit(v: np.ndarray) -> np.ndarray:
        return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)

    g = gap(dirs)
    top = np.argsort(g, axis=1)[:, -4:]
    cur = np.take_along_axis(dirs, top[..., None], axis=1)  # (C, 4, 3)
    fc = gap(cur)
    step = np.full(fc.shape, 0.05)
    rng = np.random.default_rng(seed)
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    for _ in range(iters):
        t1 = unit(np.cross(cur, rng.normal(size=3)))
        t2 = np.cross(cur, t1)
        ang = angles + rng.uniform(0, 2 * np.pi)
        tangent = np.cos(ang)[:, None] * t1[:, :, None] + np.sin(ang)[:, None] * t2[:, :, None]
        trial = unit(cur[:, :, None] + step[..., None, None] * tangent)
        trial = np.concatenate([trial, cur[:, :, None]], axis=2)  # (C, 4, T, 3)
        snapped = []
        for i in range(6):
            flat = trial - np.einsum("cktj,cj->ckt", trial, axes[:, i])[..., None] * axes[:, i, None, None]
            ok = np.linalg.norm(flat, axis=-1, keepdims=True) > 1e-6  # a zero vector is no direction
            snapped.append(np.where(ok, unit(flat), trial))
        trial = np.concatenate([trial] + snapped, axis=2)
        ft = gap(trial.reshape(c, -1, 3)).reshape(trial.shape[:3])
        j = np.argmax(ft, axis=-1)
        best = np.take_along_axis(ft, j[..., None], -1)[..., 0]
        better = best > fc
        cur = np.where(better[..., None], np.take_along_axis(trial, j[..., None, None], 2)[:, :, 0], cur)
        fc = np.where(better, best, fc)
        step = np.where(better, step, step * 0.7)
    return np.maximum(fc.max(axis=1), g.max(axis=1))


def core_directions(ka, a, kb, b) -> np.ndarray:
    """Unit vectors (C, 1, 3) between the closest points of the primitives' cores (a sphere's
    centre, a capsule's axis segment, boxes and cylinders themselves): the exact depth
    direction of overlapping spheres and capsules whose cores are apart."""
    def core(kind, prim):
        pos, rot, size = prim
        return pos, rot, size * np.array([0.0, 1.0, 1.0]) if kind in (SPHERE, CAPSULE) else size

    pa, ra, sa = core(ka, a)
    pb, rb, sb = core(kb, b)
    x = pa.copy()
    for _ in range(400):
        y = ref_project(kb, pb, rb, sb, x)
        x = ref_project(ka, pa, ra, sa, y)
    v = ref_project(kb, pb, rb, sb, x) - x
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return np.where(n > 1e-12, v / np.maximum(n, 1e-300), np.array([1.0, 0, 0]))[:, None]


def ref_project(kind: int, pos, rot, size, p) -> np.ndarray:
    """Closest point of each primitive to p (all (C, ...))."""
    loc = np.einsum("cji,cj->ci", rot, p - pos)
    if kind == SPHERE:
        n = np.linalg.norm(loc, axis=1, keepdims=True)
        q = np.where(n > size[:, :1], loc * size[:, :1] / np.maximum(n, 1e-300), loc)
    elif kind == BOX:
        q = np.clip(loc, -size, size)
    elif kind == CYLINDER:
        rho = np.linalg.norm(loc[:, :2], axis=1, keepdims=True)
        xy = np.where(rho > size[:, :1], loc[:, :2] * size[:, :1] / np.maximum(rho, 1e-300), loc[:, :2])
        q = np.c_[xy, np.clip(loc[:, 2], -size[:, 1], size[:, 1])]
    else:
        axis = np.c_[np.zeros((len(p), 2)), np.clip(loc[:, 2], -size[:, 1], size[:, 1])]
        v = loc - axis
        n = np.linalg.norm(v, axis=1, keepdims=True)
        q = np.where(n > size[:, :1], axis + v * size[:, :1] / np.maximum(n, 1e-300), loc)
    return pos + np.einsum("cij,cj->ci", rot, q)


def alternating_projection(ka, pa, ra, sa, kb, pb, rb, sb, iters: int = 1000) -> tuple[np.ndarray, np.ndarray]:
    """Alternating projections between two separated convex sets: the distance of the final
    pair of real points (an upper bound on the separation) and, as a certificate, the
    separation along the unit vector joining them (a lower bound)."""
    x = pa.copy()
    for _ in range(iters):
        y = ref_project(kb, pb, rb, sb, x)
        x = ref_project(ka, pa, ra, sa, y)
    y = ref_project(kb, pb, rb, sb, x)
    dist = np.linalg.norm(y - x, axis=1)
    n = ((y - x) / np.maximum(dist, 1e-300)[:, None])[:, None]
    gap = np.einsum("cmi,ci->cm", n, pb - pa) - ref_width(ka, ra, sa, n) - ref_width(kb, rb, sb, n)
    return dist, gap[:, 0]


def ref_point_box(p, pos, rot, half) -> np.ndarray:
    loc = np.einsum("...ji,...j->...i", rot, p - pos)
    q = np.abs(loc) - half
    return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(axis=-1), 0)


def ref_point_cylinder(p, pos, rot, size) -> np.ndarray:
    loc = np.einsum("...ji,...j->...i", rot, p - pos)
    q = np.stack([np.linalg.norm(loc[..., :2], axis=-1) - size[..., 0], np.abs(loc[..., 2]) - size[..., 1]], -1)
    return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(axis=-1), 0)


def capsule_ends(pos, rot, size):
    axis = rot[..., :, 2] * size[..., 1:2]
    return pos - axis, pos + axis


def pd(ka, a, kb, b, **kw) -> float:
    return float(geo.pair_distance(np, ka, *a, kb, *b, **kw))


def prim(pos, rot=I3, size=(0.1, 0.1, 0.1)):
    return (np.asarray(pos, float), np.asarray(rot, float), np.asarray(size, float))


# ---------------------------------------------------------- point distances


POINT_CASES = [
    # (kind, point, pos, rot, size, expected)
    (BOX, (0.3, 0, 0), (0, 0, 0), I3, (0.1, 0.2, 0.3), 0.2),
    (BOX, (0.2, 0.3, 0), (0, 0, 0), I3, (0.1, 0.2, 0.3), math.hypot(0.1, 0.1)),
    (BOX, (0.2, 0.3, 0.4), (0, 0, 0), I3, (0.1, 0.2, 0.3), 0.1 * math.sqrt(3)),
    (BOX, (0.05, 0, 0), (0, 0, 0), I3, (0.1, 0.2, 0.3), -0.05),
    (BOX, (0.0, 0.15, 0.1), (0, 0, 0), I3, (0.1, 0.2, 0.3), -0.05),
    (BOX, (1.3, 0, 0), (1, 0, 0), axis_angle((0, 0, 1), math.pi / 2), (0.1, 0.2, 0.3), 0.1),  # sees the y half-extent
    (CYLINDER, (0.3, 0, 0), (0, 0, 0), I3, (0.1, 0.2, 0), 0.2),
    (CYLINDER, (0, 0.05, 0.5), (0, 0, 0), I3, (0.1, 0.2, 0), 0.3),
    (CYLINDER, (0.2, 0, 0.3), (0, 0, 0), I3, (0.1, 0.2, 0), math.hypot(0.1, 0.1)),
    (CYLINDER, (0, 0, 0.15), (0, 0, 0), I3, (0.1, 0.2, 0), -0.05),
    (CYLINDER, (0.08, 0, 0), (0, 0, 0), I3, (0.1, 0.2, 0), -0.02),
    (CYLINDER, (0.5, 0, 0), (0, 0, 0), axis_angle((0, 1, 0), math.pi / 2), (0.1, 0.2, 0), 0.3),  # axis along x
    (CAPSULE, (0.2, 0, 0.05), (0, 0, 0), I3, (0.05, 0.1, 0), 0.15),
    (CAPSULE, (0, 0, 0.3), (0, 0, 0), I3, (0.05, 0.1, 0), 0.15),
    (CAPSULE, (0.01, 0, 0.05), (0, 0, 0), I3, (0.05, 0.1, 0), -0.04),
    (CAPSULE, (0.3, 0, 0), (0, 0, 0), axis_angle((0, 1, 0), math.pi / 2), (0.05, 0.1, 0), 0.15),
    (SPHERE, (0.3, 0.4, 0), (0, 0, 0), I3, (0.1, 0, 0), 0.4),
    (SPHERE, (0.02, 0, 0), (0, 0, 0), I3, (0.1, 0, 0), -0.08),
]


@pytest.mark.parametrize("case", range(len(POINT_CASES)))
def test_point_distance_closed_form(case: int) -> None:
    kind, point, pos, rot, size, expected = POINT_CASES[case]
    got = geo.point_distance(np, kind, np.array(point, float), np.array(pos, float), rot, np.array(size, float))
    assert abs(float(got) - expected) < 1e-12


def test_point_distances_match_reference_on_random_points() -> None:
    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.4, 0.4, (500, 3))
    pos, rot, size = random_prims(rng, BOX, 500)
    got = geo.point_box_distance(np, pts, pos, rot, size)
    np.testing.assert_allclose(got, ref_point_box(pts, pos, rot, size), atol=1e-14)
    pos, rot, size = random_prims(rng, CYLINDER, 500)
    np.testing.assert_allclose(
        geo.point_cylinder_distance(np, pts, pos, rot, size), ref_point_cylinder(pts, pos, rot, size), atol=1e-14
    )


# ------------------------------------------------------------ closed forms


def _vertex_up_rotation() -> np.ndarray:
    """Rotation taking the cube diagonal (1, 1, 1)/√3 onto +x: a vertex then points at +x."""
    a = np.ones(3) / math.sqrt(3)
    b = np.array([1.0, 0, 0])
    v = np.cross(a, b)
    return axis_angle(v, math.acos(float(a @ b)))


VERTEX_UP = _vertex_up_rotation()

def sph(pos, r: float):
    return SPHERE, prim(pos, I3, (r, 0, 0))


def cap(pos, r: float, half: float, rot=I3):
    return CAPSULE, prim(pos, rot, (r, half, 0))


def box(pos, half, rot=I3):
    return BOX, prim(pos, rot, half)


def cyl(pos, r: float, half: float, rot=I3):
    return CYLINDER, prim(pos, rot, (r, half, 0))


ALONG_X = axis_angle((0, 1, 0), math.pi / 2)  # local z -> world x
ALONG_Y = axis_angle((1, 0, 0), -math.pi / 2)  # local z -> world y
DIAGONAL = axis_angle((1, 1, 0), math.pi / 2)  # local z -> world (1, -1, 0)/√2
BOX_A = box((0, 0, 0), (0.1, 0.2, 0.3))
CYL_A = cyl((0, 0, 0), 0.1, 0.2)
TILT_45 = axis_angle((0, 1, 0), math.pi / 4)
S2, R2 = math.sqrt(2), math.sqrt(0.5)

PAIR_CASES = [
    # (name, (kind_a, prim_a), (kind_b, prim_b), expected)
    ("sphere-sphere gap", sph((0, 0, 0), 0.1), sph((0.3, 0, 0.4), 0.05), 0.35),
    ("sphere-sphere overlap", sph((0, 0, 0), 0.1), sph((0.12, 0, 0), 0.05), -0.03),
    ("sphere-capsule side", sph((0.2, 0, 0.05), 0.05), cap((0, 0, 0), 0.03, 0.1), 0.12),
    ("sphere-capsule end", sph((0, 0, 0.3), 0.05), cap((0, 0, 0), 0.03, 0.1), 0.12),
    ("sphere-capsule overlap", sph((0.06, 0, 0), 0.05), cap((0, 0, 0), 0.03, 0.1), -0.02),
    ("sphere-box corner", sph((0.2, 0.3, 0.4), 0.05), BOX_A, 0.1 * math.sqrt(3) - 0.05),
    ("sphere-box centre inside", sph((0.07, 0, 0), 0.05), BOX_A, -0.08),
    ("sphere-cylinder rim", sph((0.2, 0, 0.3), 0.05), CYL_A, math.hypot(0.1, 0.1) - 0.05),
    ("sphere-cylinder inside", sph((0.08, 0, 0), 0.01), CYL_A, -0.03),
    # capsule-capsule: skew axes 0.3 apart, parallel side by side, collinear, parallel with
    # offset ends, closest at two endpoints, crossing overlap
    ("capsule-capsule skew", cap((0, 0, 0), 0.02, 0.1), cap((0, 0.3, 0), 0.03, 0.1, ALONG_X), 0.25),
    ("capsule-capsule parallel", cap((0, 0, 0), 0.02, 0.1), cap((0.2, 0, 0.05), 0.03, 0.1), 0.15),
    ("capsule-capsule collinear", cap((0, 0, 0), 0.02, 0.1), cap((0, 0, 0.5), 0.03, 0.1), 0.25),
    ("capsule-capsule offset ends", cap((0, 0, 0), 0.02, 0.1), cap((0.1, 0, 0.5), 0.03, 0.1), math.hypot(0.1, 0.3) - 0.05),
    ("capsule-capsule endpoints", cap((0, 0, 0), 0.02, 0.1), cap((0.5, 0.2, 0.3), 0.03, 0.1, ALONG_X), 0.24**0.5 - 0.05),
    ("capsule-capsule overlap", cap((0, 0, 0), 0.05, 0.1), cap((0, 0.05, 0), 0.05, 0.1, ALONG_X), -0.05),
    # capsule-box: parallel to a face, pointing at a face, across a vertical edge (axis along
    # (1, -1, 0) at 0.1 from the edge), fully inside, poking through a face
    ("capsule-box side", cap((0.25, 0, 0.1), 0.05, 0.1), BOX_A, 0.1),
    ("capsule-box end", cap((0, 0.1, 0.5), 0.05, 0.1), BOX_A, 0.05),
    ("capsule-box edge", cap((0.1 + 0.1 * R2, 0.2 + 0.1 * R2, 0.05), 0.02, 0.15, DIAGONAL), BOX_A, 0.08),
    ("capsule-box inside", cap((0, 0, 0), 0.02, 0.1), BOX_A, -0.12),
    ("capsule-box through face", cap((0.1, 0, 0), 0.02, 0.1, ALONG_X), BOX_A, -0.12),
    # capsule-cylinder: beside the side, above the cap, towards the rim, inside
    ("capsule-cylinder side", cap((0.3, 0, 0), 0.02, 0.1), CYL_A, 0.18),
    ("capsule-cylinder cap", cap((0.05, 0, 0.4), 0.02, 0.1, ALONG_Y), CYL_A, 0.18),
    ("capsule-cylinder rim", cap((0.2, 0, 0.4), 0.02, 0.1, ALONG_Y), CYL_A, math.hypot(0.1, 0.2) - 0.02),
    ("capsule-cylinder inside", cap((0, 0, 0), 0.02, 0.1), CYL_A, -0.12),
    # box-box: face-face, crossing edges, vertex on a face, overlap depths
    ("box-box face-face", box((0, 0, 0), (0.1, 0.1, 0.1)), box((0.35, 0.05, 0), (0.1, 0.2, 0.3)), 0.15),
    (
        "box-box edge-edge",
        box((0, 0, 0), (0.1, 0.1, 0.1), axis_angle((0, 0, 1), math.pi / 4)),
        box((0.4, 0, 0), (0.1, 0.1, 0.1), axis_angle((0, 1, 0), math.pi / 4)),
        0.4 - 0.2 * S2,
    ),
    ("box-box vertex-face", box((0, 0, 0), (0.1, 0.1, 0.1), VERTEX_UP), box((0.5, 0.1, -0.05), (0.2, 0.3, 0.3)), 0.3 - 0.1 * 3**0.5),
    ("box-box overlap", box((0, 0, 0), (0.1, 0.1, 0.1)), box((0.15, 0.02, 0), (0.1, 0.2, 0.3)), -0.05),
    (
        "box-box overlap rotated",
        box((0, 0, 0), (0.1, 0.1, 0.1), axis_angle((0, 0, 1), math.pi / 4)),
        box((0.2, 0, 0), (0.1, 0.5, 0.5)),
        0.2 - 0.1 * S2 - 0.1,
    ),
    ("box-box contained", box((0, 0, 0), (0.3, 0.3, 0.3)), box((0.1, 0, 0), (0.05, 0.05, 0.05)), -0.25),
]


@pytest.mark.parametrize("case", [c[0] for c in PAIR_CASES])
def test_pair_closed_form(case: str) -> None:
    _, (ka, a), (kb, b), expected = next(c for c in PAIR_CASES if c[0] == case)
    got = pd(ka, a, kb, b)
    tol = 1e-9 if (ka, kb) != (CAPSULE, CYLINDER) else 1e-8  # golden section on a 0.2 m axis
    assert abs(got - expected) < tol, (got, expected)
    assert abs(pd(kb, b, ka, a) - got) < 1e-12  # the argument order does not matter


def test_cylinder_pairs_closed_form_within_bound() -> None:
    """Face-on configurations with known answers: the prism error is bounded and present."""
    cases = [
        # box beside the side, box above the cap, box on the rim's diagonal, overlap through the side
        (BOX, prim((0.3, 0, 0), size=(0.1, 0.1, 0.1)), prim((0, 0, 0), size=(0.1, 0.2, 0)), 0.1),
        (BOX, prim((0, 0.02, 0.35), size=(0.1, 0.1, 0.1)), prim((0, 0, 0), size=(0.05, 0.2, 0)), 0.05),
        (BOX, prim((0.2, 0, 0.3), TILT_45, (0.05, 0.1, 0.05)), prim((0, 0, 0), size=(0.05, 0.2, 0)), 0.25 * R2 - 0.05),
        (BOX, prim((0.17, 0, 0), size=(0.1, 0.3, 0.3)), prim((0, 0, 0), size=(0.1, 0.1, 0)), -0.03),
        (CYLINDER, prim((0.3, 0, 0), size=(0.05, 0.1, 0)), prim((0, 0, 0), size=(0.085, 0.2, 0)), 0.3 - 0.135),
        (CYLINDER, prim((0.02, 0, 0.4), size=(0.05, 0.1, 0)), prim((0, 0, 0), size=(0.085, 0.2, 0)), 0.1),
        (CYLINDER, prim((0.12, 0, 0), size=(0.05, 0.1, 0)), prim((0, 0, 0), size=(0.085, 0.2, 0)), -0.015),
    ]
    errors = []
    for kind, a, cyl, expected in cases:
        got = pd(kind, a, CYLINDER, cyl)
        bound = geo.cylinder_error_bound(cyl[2][0]) if kind == BOX else geo.cylinder_error_bound(a[2][0], cyl[2][0])
        assert abs(got - expected) <= bound + 1e-9, (kind, got, expected, bound)
        errors.append(abs(got - expected))
    assert max(errors) > 1e-6  # the prism is an approximation: the test would notice it becoming exact


# ------------------------------------------------ random cases vs references


EXACT_PAIRS = [p for p in ALL_PAIRS if CYLINDER not in p or p in ((SPHERE, CYLINDER), (CAPSULE, CYLINDER))]


@pytest.mark.parametrize("pair", EXACT_PAIRS, ids=lambda p: f"{p[0]}-{p[1]}")
def test_exact_pairs_separated_are_sandwiched_by_references(pair: tuple[int, int]) -> None:
    """Separated pairs: the alternating-projection certificate (lower bound) <= ours <= the
    distance of its final point pair (upper bound), the two bounds 1e-9 apart."""
    ka, kb = pair
    rng = np.random.default_rng(10 + 4 * ka + kb)
    a = random_prims(rng, ka, 40, 0.25)
    b = random_prims(rng, kb, 40, 0.25)
    ours = geo.pair_distance(np, ka, *a, kb, *b)
    sep = ours > 1e-3
    a = tuple(x[sep] for x in a)
    b = tuple(x[sep] for x in b)
    ours = ours[sep]
    assert len(ours) >= 12
    upper, lower = alternating_projection(ka, *a, kb, *b)
    assert np.all(upper - lower < 1e-9)  # the references pin the true distance down
    assert np.all(ours >= lower - 1e-9), (ours - lower).min()
    assert np.all(ours <= upper + 1e-9), (ours - upper).max()


@pytest.mark.parametrize("pair", [(SPHERE, BOX), (CAPSULE, CAPSULE), (BOX, BOX), (SPHERE, CYLINDER)], ids=str)
def test_exact_pairs_overlapping_match_penetration_depth(pair: tuple[int, int]) -> None:
    """Overlapping pairs with an exact depth: ours equals max over directions of the separation."""
    ka, kb = pair
    rng = np.random.default_rng(20 + 4 * ka + kb)
    a = random_prims(rng, ka, 60, 0.08)
    b = random_prims(rng, kb, 60, 0.08)
    ours = geo.pair_distance(np, ka, *a, kb, *b)
    keep = ours < -1e-3
    if pair == (CAPSULE, CAPSULE):  # exact only while the axis segments do not cross
        keep &= ours + a[2][:, 0] + b[2][:, 0] > 1e-2
    a = tuple(x[keep] for x in a)
    b = tuple(x[keep] for x in b)
    assert keep.sum() >= 8
    ref = support_signed_distance(ka, *a, kb, *b, extra=core_directions(ka, a, kb, b))
    np.testing.assert_allclose(ours[keep], ref, atol=1e-9, rtol=0)


def test_capsule_box_and_cylinder_match_dense_axis_sampling_inside_and_out() -> None:
    """min over the capsule axis of the other's SDF (what the two functions define, overlap included)."""
    rng = np.random.default_rng(5)
    caps = random_prims(rng, CAPSULE, 40, 0.12)
    p0, p1 = capsule_ends(*caps)
    t = np.linspace(0, 1, 20001)
    pts = p0[:, None] + t[None, :, None] * (p1 - p0)[:, None]
    length = np.linalg.norm(p1 - p0, axis=1)
    for kind, ref in ((BOX, ref_point_box), (CYLINDER, ref_point_cylinder)):
        other = random_prims(rng, kind, 40, 0.12)
        dense = ref(pts, other[0][:, None], other[1][:, None], other[2][:, None]).min(axis=1) - caps[2][:, 0]
        ours = geo.pair_distance(np, CAPSULE, *caps, kind, *other)
        assert (ours < 0).sum() >= 8 and (ours > 0).sum() >= 8  # both regimes are exercised
        assert np.all(ours <= dense + 1e-9)
        assert np.all(ours >= dense - length / 20000 - 1e-9)


def test_segment_box_distance_degenerate_and_axis_parallel_segments() -> None:
    rng = np.random.default_rng(6)
    pos, rot, size = random_prims(rng, BOX, 200, 0.1)
    p = rng.uniform(-0.3, 0.3, (200, 3))
    # a zero-length segment is the point
    got = geo.segment_box_distance(np, p, p, pos, rot, size)
    np.testing.assert_allclose(got, ref_point_box(p, pos, rot, size), atol=1e-14)
    # segments along a box axis (zero direction components in the box frame) vs dense sampling
    q = p + rot[:, :, 0] * rng.uniform(-0.3, 0.3, (200, 1))
    t = np.linspace(0, 1, 4001)
    samples = p[:, None] + t[None, :, None] * (q - p)[:, None]
    dense = ref_point_box(samples, pos[:, None], rot[:, None], size[:, None]).min(1)
    ours = geo.segment_box_distance(np, p, q, pos, rot, size)
    assert np.all(ours <= dense + 1e-12)
    assert np.all(ours >= dense - np.linalg.norm(q - p, axis=1) / 4000 - 1e-12)
    assert np.abs(geo.segment_segment_distance(np, p, p, q, q) - np.linalg.norm(p - q, axis=1)).max() < 1e-14


def test_nearly_parallel_capsules() -> None:
    """The ill-conditioned line-line critical point must not leak into the result."""
    base = prim((0, 0, 0), size=(0.02, 0.2, 0))
    for angle in (0.0, 1e-9, 1e-6, 1e-3):
        for shift in (0.0, 0.1, 0.35):
            b = prim((0.1, 0.0, shift), axis_angle((0, 1, 0), angle), (0.03, 0.2, 0))
            b0, b1 = capsule_ends(*b)
            t = np.linspace(0, 1, 20001)
            seg = b0 + t[:, None] * (b1 - b0)
            z = np.clip(seg[:, 2], -0.2, 0.2)
            dense = np.sqrt(seg[:, 0] ** 2 + seg[:, 1] ** 2 + (seg[:, 2] - z) ** 2).min() - 0.05
            got = pd(CAPSULE, base, CAPSULE, b)
            assert got <= dense + 1e-12 and got >= dense - 0.4 / 20000, (angle, shift, got, dense)


def test_degenerate_configurations() -> None:
    """Coincident shapes, zero-length capsules and collinear axes give finite, right values."""
    box = prim((0.1, -0.2, 0.3), axis_angle((1, 2, 3), 0.7), (0.05, 0.08, 0.12))
    assert pd(BOX, box, BOX, box) == pytest.approx(-0.1, abs=1e-12)  # coincident: depth = smallest extent
    sphere = prim(box[0], I3, (0.02, 0, 0))
    assert pd(SPHERE, sphere, BOX, box) == pytest.approx(-0.07, abs=1e-12)  # centre at the box centre
    cyl = prim((0.0, 0.1, 0.2), axis_angle((0, 1, 1), 0.4), (0.04, 0.1, 0))
    assert abs(pd(CYLINDER, cyl, CYLINDER, cyl) + 0.08) <= geo.cylinder_error_bound(0.04, 0.04)
    # a zero-length capsule is a sphere, against every kind
    rng = np.random.default_rng(12)
    for kind in KINDS:
        other = tuple(x[0] for x in random_prims(rng, kind, 1, 0.1))
        for centre in rng.uniform(-0.2, 0.2, (5, 3)):
            dot = prim(centre, axis_angle((1, 0, 0), 0.3), (0.03, 0.0, 0))
            ball = prim(centre, I3, (0.03, 0, 0))
            assert pd(CAPSULE, dot, kind, other) == pytest.approx(pd(SPHERE, ball, kind, other), abs=1e-8)
    # collinear overlapping capsule axes: the axis distance is 0
    collinear = pd(*cap((0, 0, 0), 0.02, 0.1), *cap((0, 0, 0.05), 0.03, 0.1))
    assert collinear == pytest.approx(-0.05, abs=1e-15)
    # every pair at coincident poses is finite and overlapping (the JAX tests below include
    # these poses in their batches)
    p = prim((0.0, 0.0, 0.0), I3, (0.05, 0.05, 0.05))
    for ka, kb in ALL_PAIRS:
        ref = pd(ka, p, kb, p)
        assert np.isfinite(ref) and ref < -0.04


# ------------------------------------------------------- cylinder approximations


def cylinder_surface(pos, rot, size, n_ring: int = 720, n_height: int = 120, n_radial: int = 30) -> np.ndarray:
    """Dense points on a cylinder's surface (rims, side and caps), (M, 3)."""
    th = np.linspace(0, 2 * np.pi, n_ring, endpoint=False)
    ring = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], -1)
    z = np.linspace(-size[1], size[1], n_height)
    side = (size[0] * ring[None] + z[:, None, None] * np.array([0, 0, 1.0])).reshape(-1, 3)
    rad = np.linspace(0, size[0], n_radial)
    disc = (rad[:, None, None] * ring[None]).reshape(-1, 3)
    caps = np.concatenate([disc + [0, 0, size[1]], disc - [0, 0, size[1]]])
    return pos + np.concatenate([side, caps]) @ rot.T


@pytest.mark.parametrize("kind", [BOX, CYLINDER], ids=["box-cylinder", "cylinder-cylinder"])
def test_cylinder_pairs_within_stated_bound(kind: int) -> None:
    rng = np.random.default_rng(30 + kind)
    n = 24
    a = random_prims(rng, kind, n, 0.15)
    cyl = random_prims(rng, CYLINDER, n, 0.15)
    ours = geo.pair_distance(np, kind, *a, CYLINDER, *cyl)
    ref = support_signed_distance(kind, *a, CYLINDER, *cyl)
    if kind == BOX:
        bound = np.array([geo.cylinder_error_bound(r) for r in cyl[2][:, 0]])
    else:
        bound = np.array([geo.cylinder_error_bound(ra, rb) for ra, rb in zip(a[2][:, 0], cyl[2][:, 0])])
    assert (ref < 0).sum() >= 4 and (ref > 0).sum() >= 4
    assert np.all(np.abs(ours - ref) <= bound + 1e-7), np.max(np.abs(ours - ref) - bound)
    # separated cases: dense surface samples of the cylinder give an independent upper bound
    for i in np.nonzero(ref > 0)[0][:6]:
        pts = cylinder_surface(cyl[0][i], cyl[1][i], cyl[2][i])
        if kind == BOX:
            sampled = ref_point_box(pts, a[0][i], a[1][i], a[2][i]).min()
        else:
            sampled = ref_point_cylinder(pts, a[0][i], a[1][i], a[2][i]).min()
        assert ref[i] <= sampled + 1e-9
        assert ours[i] <= sampled + bound[i]
    # the default prism keeps every pair of this project under 2 mm
    assert geo.cylinder_error_bound(0.085) < 1e-3
    assert geo.cylinder_error_bound(0.085, 0.085) < 1.2e-3


# ----------------------------------------------------------------- plane


def test_plane_distance_per_kind() -> None:
    rng = np.random.default_rng(8)
    for kind in KINDS:
        pos, rot, size = random_prims(rng, kind, 50, 0.3)
        ours = geo.plane_distance(np, kind, pos, rot, size)
        if kind == SPHERE:
            expected = pos[:, 2] - size[:, 0]
        elif kind == CAPSULE:
            expected = pos[:, 2] - size[:, 1] * np.abs(rot[:, 2, 2]) - size[:, 0]
        elif kind == BOX:
            corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
            expected = (pos[:, None] + np.einsum("cij,ckj->cki", rot, corners[None] * size[:, None])).min(axis=1)[:, 2]
        else:
            expected = np.array([cylinder_surface(p, r, s, 3600, 2, 2)[:, 2].min() for p, r, s in zip(pos, rot, size)])
        atol = 1e-12 if kind != CYLINDER else 1e-6  # rim sampled every 0.1°
        np.testing.assert_allclose(ours, expected, atol=atol)
        # the kind may also be data
        np.testing.assert_allclose(geo.plane_distance(np, np.full(50, kind), pos, rot, size), ours, atol=1e-15)
    assert float(geo.plane_distance(np, BOX, np.array([0, 0, 0.025]), I3, np.array([0.01, 0.01, 0.025]))) == 0.0
    above = geo.plane_distance(np, SPHERE, np.array([0, 0, 0.2]), I3, np.array([0.05, 0, 0]), plane_z=0.1)
    assert float(above) == pytest.approx(0.05)


# ------------------------------------------------------------------- dispatch


def test_distance_to_obstacle_selects_by_kind_and_empty_slot_is_inf() -> None:
    rng = np.random.default_rng(9)
    obs_kind = np.array([SPHERE, CYLINDER, BOX, -1])
    obs_pos = rng.uniform(-0.2, 0.2, (4, 3))
    obs_rot = random_rotations(rng, 4)
    obs_size = np.array([[0.05, 0, 0], [0.04, 0.1, 0], [0.03, 0.04, 0.05], [0.05, 0.05, 0.05]])
    for rk in KINDS:
        rpos, rrot, rsize = random_prims(rng, rk, 1)
        got = geo.distance_to_obstacle(np, rk, rpos, rrot, rsize, obs_kind, obs_pos, obs_rot, obs_size)
        for j in range(3):
            ref = pd(rk, (rpos[0], rrot[0], rsize[0]), obs_kind[j], (obs_pos[j], obs_rot[j], obs_size[j]))
            assert got[j] == pytest.approx(ref, abs=1e-15)
        assert got[3] == np.inf


def robot_and_scene(q: np.ndarray):
    robot = load_robot()
    kin = forward_kinematics(np, robot, q)
    pos, rot = primitive_poses(np, robot, kin)
    return robot.prim_kind, pos, rot, robot.prim_size, SCENE.static_arrays()


def test_distance_matrix_matches_pairwise_for_the_robot_and_scene() -> None:
    q = np.array(HOME_Q)
    kinds, pos, rot, size, (skinds, spos, srot, ssize) = robot_and_scene(q)
    mat = geo.distance_matrix(np, kinds, pos, rot, size, skinds, spos, srot, ssize)
    assert mat.shape == (len(kinds), len(skinds))
    for i in range(len(kinds)):
        for j in range(len(skinds)):
            ref = pd(kinds[i], (pos[i], rot[i], size[i]), skinds[j], (spos[j], srot[j], ssize[j]))
            assert mat[i, j] == pytest.approx(ref, abs=1e-15)
    assert np.all(mat > 0.1)  # the home pose is well clear of the gantry and camera
    # self distances: the robot against itself, symmetric with the diagonal <= 0
    self_mat = geo.distance_matrix(np, kinds, pos, rot, size, kinds, pos, rot, size)
    np.testing.assert_allclose(self_mat, self_mat.T, atol=1e-9)
    assert np.all(np.diag(self_mat) < 0)


def test_obstacle_matrix_and_batching() -> None:
    rng = np.random.default_rng(11)
    qs = np.array(HOME_Q) + rng.uniform(-0.3, 0.3, (3, 6))
    robot = load_robot()
    pos, rot = primitive_poses(np, robot, forward_kinematics(np, robot, qs))  # (3, G, ...)
    obs_kind = np.array([[SPHERE, -1], [CYLINDER, BOX], [BOX, SPHERE]])
    obs_pos = np.array([0.0, -0.45, 0.1]) + rng.uniform(-0.1, 0.1, (3, 2, 3))
    obs_rot = random_rotations(rng, 6).reshape(3, 2, 3, 3)
    obs_size = np.tile(np.array([0.04, 0.1, 0.05]), (3, 2, 1))
    obstacles = (obs_kind, obs_pos, obs_rot, obs_size)
    mat = geo.obstacle_distance_matrix(np, robot.prim_kind, pos, rot, robot.prim_size, *obstacles)
    assert mat.shape == (3, len(robot.primitives), 2)
    for e in range(3):
        for g in range(len(robot.primitives)):
            for n in range(2):
                if obs_kind[e, n] < 0:
                    assert mat[e, g, n] == np.inf
                    continue
                mine = (pos[e, g], rot[e, g], robot.prim_size[g])
                ref = pd(robot.prim_kind[g], mine, obs_kind[e, n], (obs_pos[e, n], obs_rot[e, n], obs_size[e, n]))
                assert mat[e, g, n] == pytest.approx(ref, abs=1e-15)


# ------------------------------------------------------------- NumPy vs JAX


def _batch_inputs(n: int, seed: int):
    """Random primitives per kind; case 0 of every kind sits at one coincident pose and case 1
    has a zero-length capsule, so the JAX runs also cover the degenerate configurations."""
    rng = np.random.default_rng(seed)
    prims = {k: random_prims(rng, k, n, 0.15) for k in KINDS}
    for pos, rot, size in prims.values():
        pos[0], rot[0], size[0] = 0.0, I3, 0.05
    prims[CAPSULE][2][1, 1] = 0.0
    return prims


def _all_pairs(xp, prims):
    return [geo.pair_distance(xp, ka, *prims[ka], kb, *prims[kb]) for ka, kb in ALL_PAIRS]


def test_jax_jit_x64_matches_numpy(x64) -> None:
    jax = x64
    import jax.numpy as jnp

    prims = _batch_inputs(32, 40)
    ref = _all_pairs(np, prims)
    got = jax.jit(lambda p: _all_pairs(jnp, p))({k: tuple(jnp.asarray(x) for x in v) for k, v in prims.items()})
    for (ka, kb), r, g in zip(ALL_PAIRS, ref, got):
        assert g.dtype == jnp.float64 and np.all(np.isfinite(np.asarray(g)))
        np.testing.assert_allclose(np.asarray(g), r, atol=1e-12, rtol=0, err_msg=f"{ka}-{kb}")


def test_jax_vmap_float32_matches_numpy_and_robot_matrix_jits() -> None:
    import jax
    import jax.numpy as jnp

    prims = _batch_inputs(64, 41)
    ref = _all_pairs(np, prims)
    args = {k: tuple(jnp.asarray(x, jnp.float32) for x in v) for k, v in prims.items()}
    got = jax.jit(jax.vmap(lambda p: _all_pairs(jnp, p)))(args)
    for (ka, kb), r, g in zip(ALL_PAIRS, ref, got):
        assert g.dtype == jnp.float32 and g.shape == (64,) and np.all(np.isfinite(np.asarray(g)))
        np.testing.assert_allclose(np.asarray(g), r, atol=2e-6, rtol=0, err_msg=f"{ka}-{kb}")

    # the robot-vs-scene matrix, jitted and vmapped over a batch of joint vectors
    robot = load_robot()
    skinds, spos, srot, ssize = SCENE.static_arrays()
    qs = np.array(HOME_Q) + np.random.default_rng(2).uniform(-0.5, 0.5, (8, 6))

    def matrix(xp, q):
        pos, rot = primitive_poses(xp, robot, forward_kinematics(xp, robot, q))
        return geo.distance_matrix(xp, robot.prim_kind, pos, rot, robot.prim_size, skinds, spos, srot, ssize)

    got = jax.jit(jax.vmap(lambda q: matrix(jnp, q)))(jnp.asarray(qs, jnp.float32))
    np.testing.assert_allclose(np.asarray(got), matrix(np, qs), atol=2e-6)
