"""The collision rules of docs/task.md §2 for one env at one pose, shared by both simulators.

Backend-agnostic (``xp`` = numpy or jax.numpy, single env, never imports jax): the MJX
env vmaps ``check``; the PyBullet reference env, the sampler and the deployment
safety layer call the same code with NumPy.

Cost is what shapes this module: it runs every control step of every training env.
Exact primitive-pair distances (``tests/exact_geometry.py``, the tests' oracle) for the robot's boxes and cylinders
against boxes and cylinders cost 10^4-10^5 flops a pair, about 1 ms per env step on a
CPU core.  So the robot is checked through a **sphere cover**: every URDF primitive
of a moving link is replaced by spheres (``sphere_cover``) —

* capsules by spheres of the capsule radius along the axis, spaced so the surface
  between them dips ≤ ``CAPSULE_DIP`` (an under-approximation by up to 5 mm);
* boxes by a grid of cells of half-size ≤ ``BOX_CELL`` and spheres circumscribing the
  cells (a conservative cover; bulge ≤ ``sphere_cover(...).bulge`` per primitive,
  about 1-1.6 cm at face centres, 0 at corners);
* cylinders likewise by circumscribing spheres along the axis (conservative).

— and every obstacle keeps its exact shape: a sphere-to-shape distance is the
shape's closed-form point SDF minus the radius.  The table and the target, where
grasping needs millimetres, stay exact: the table through the support function of
each URDF primitive, the target cuboid through the separating-axis test (boxes) and
closed-form segment-box distances (capsules).  Results:

* ``obstacle_dist`` / Δpo: cover-sphere distance to each dynamic obstacle (exact
  shapes), i.e. the true robot-obstacle distance minus at most the cover bulge;
* gantry posts: cover-sphere vs post boxes.  The camera, its bracket and the beam are
  above the arm's reach (≤ 1.22 m vs ≥ 1.37 m, proved in ``tests/task/test_collision.py``)
  and are not checked per step;
* self-collision: cover spheres of wrist1, wrist2, wrist3 (flange and gripper) against
  those of base, shoulder and upper arm.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from sagrasp_jax.task import geometry
from sagrasp_jax.task import shapes
from sagrasp_jax.task.config import EnvConfig
from sagrasp_jax.task.robot import BOX, CAPSULE, CYLINDER, SPHERE, Kinematics, RobotModel, primitive_poses
from sagrasp_jax.task.scene import SCENE

HIT_KINDS = ("obstacle", "gantry", "camera", "table", "target", "self")
CAPSULE_DIP = 0.005  # m, max surface dip between consecutive capsule cover spheres
BOX_CELL = 0.025  # m, max half-size of a box cover cell
UNREACHABLE_ROLES_MIN_Z = 1.3  # m: static parts wholly above this are out of the arm's reach (tested)


class SphereCover(NamedTuple):
    link: np.ndarray  # (S,) link index of each sphere
    local: np.ndarray  # (S, 3) centre in the link frame
    radius: np.ndarray  # (S,)
    prim: np.ndarray  # (S,) index of the URDF primitive it covers
    bulge: np.ndarray  # (G,) max distance the cover sticks out of each primitive


class CollisionResult(NamedTuple):
    obstacle_dist: Any  # (slots,) robot -> obstacle distance, clipped; the clip value for empty slots
    nearest_obstacle_dist: Any  # () Δpo, clipped to TaskConfig.obstacle_dist_clip
    nearest_obstacle_pos: Any  # (3,) centre of the nearest active obstacle or TaskConfig.no_obstacle_pos
    hits: dict[str, Any]  # name -> () bool, names in HIT_KINDS
    any_collision: Any  # () bool
    robot_to_obstacle: Any  # (slots, 3) closest robot point -> nearest obstacle surface point (0 for empty slots)
    gripper_to_obstacle: Any  # (slots, 3) gripper centre -> nearest obstacle surface point (0 for empty slots)


def _axis_points(half: float, spacing: float) -> np.ndarray:
    n = max(1, int(math.ceil(2 * half / spacing)) + 1) if half > 0 else 1
    return np.linspace(-half, half, n) if n > 1 else np.zeros(1)


_COVERS: dict[int, tuple[RobotModel, SphereCover]] = {}


def _cover(robot: RobotModel) -> SphereCover:
    cached = _COVERS.get(id(robot))
    if cached is not None and cached[0] is robot:
        return cached[1]
    cover = _build_cover(robot)
    _COVERS[id(robot)] = (robot, cover)
    return cover


def _build_cover(robot: RobotModel) -> SphereCover:
    links, centres, radii, prims, bulges = [], [], [], [], []
    for g, prim in enumerate(robot.primitives):
        r, h = prim.size[0], prim.size[1]
        if prim.kind == SPHERE:
            local, rad, bulge = np.zeros((1, 3)), np.array([r]), 0.0
        elif prim.kind == CAPSULE:
            spacing = 2 * math.sqrt(r**2 - (r - CAPSULE_DIP) ** 2)
            zs = _axis_points(h, spacing)
            local = np.stack([np.zeros_like(zs), np.zeros_like(zs), zs], -1)
            rad, bulge = np.full(len(zs), r), 0.0
        elif prim.kind == CYLINDER:
            n = max(1, int(math.ceil(h / max(r, 1e-9))))
            cell = h / n
            zs = np.linspace(-h + cell, h - cell, n)
            local = np.stack([np.zeros_like(zs), np.zeros_like(zs), zs], -1)
            rho = math.hypot(r, cell)
            rad, bulge = np.full(n, rho), rho - min(r, cell)
        elif prim.kind == BOX:
            half = np.array(prim.size)
            counts = np.maximum(1, np.ceil(half / BOX_CELL - 1e-9)).astype(int)
            cell = half / counts
            axes = [np.linspace(-half[i] + cell[i], half[i] - cell[i], counts[i]) for i in range(3)]
            grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
            rho = float(np.linalg.norm(cell))
            local, rad, bulge = grid, np.full(len(grid), rho), rho - float(cell.min())
        else:  # pragma: no cover - parse_urdf only produces the four kinds
            raise ValueError(prim.kind)
        world_local = (prim.local[:3, :3] @ local.T).T + prim.local[:3, 3]
        links.append(np.full(len(local), prim.link))
        centres.append(world_local)
        radii.append(rad)
        prims.append(np.full(len(local), g))
        bulges.append(bulge)
    link = np.concatenate(links).astype(np.int32)
    order = np.argsort(link, kind="stable")
    return SphereCover(
        link=link[order],
        local=np.concatenate(centres)[order],
        radius=np.concatenate(radii)[order],
        prim=np.concatenate(prims).astype(np.int32)[order],
        bulge=np.array(bulges),
    )


def sphere_cover(robot: RobotModel) -> SphereCover:
    """The robot's conservative sphere cover in link frames (computed once per robot model)."""
    return _cover(robot)


FINE_ERROR = 0.004  # m: the fine sphere set's two-sided error bound (Hausdorff distance to the URDF primitives)
_FINE: dict[int, tuple[RobotModel, SphereCover]] = {}


def fine_cover(robot: RobotModel) -> SphereCover:
    """Spheres within ``FINE_ERROR`` of the robot's moving primitives, both ways (link frames).

    Every sphere lies inside its primitive grown by FINE_ERROR, and every point of the
    primitive's surface lies within FINE_ERROR of a sphere, so a distance from any shape to the
    union differs from the exact distance to the primitives by at most FINE_ERROR (for gaps;
    overlaps shallower than that may be missed).  Capsules: spheres of the capsule radius
    along the axis.  Boxes and cylinders: spheres of radius δ + E centred on the primitive
    shrunk by δ (δ ≤ 2.73·E, so the corners are reached too), on a grid whose spacing is
    refined until a dense sample of the surface verifies the bound (``_fine_primitive``).
    """
    cached = _FINE.get(id(robot))
    if cached is not None and cached[0] is robot:
        return cached[1]
    links, centres, radii, prims = [], [], [], []
    for g, prim in enumerate(robot.primitives):
        if prim.link == 0:  # the base never moves: obstacles keep clear of it at sampling time
            continue
        local, rad = _fine_primitive(prim.kind, np.asarray(prim.size, float), FINE_ERROR)
        links.append(np.full(len(local), prim.link))
        centres.append((prim.local[:3, :3] @ local.T).T + prim.local[:3, 3])
        radii.append(rad)
        prims.append(np.full(len(local), g))
    link = np.concatenate(links).astype(np.int32)
    order = np.argsort(link, kind="stable")
    cover = SphereCover(
        link=link[order],
        local=np.concatenate(centres)[order],
        radius=np.concatenate(radii)[order],
        prim=np.concatenate(prims).astype(np.int32)[order],
        bulge=np.full(len(robot.primitives), FINE_ERROR),
    )
    _FINE[id(robot)] = (robot, cover)
    return cover


def _grid(half: float, spacing: float) -> np.ndarray:
    if half <= 1e-12:
        return np.zeros(1)
    return np.linspace(-half, half, int(math.ceil(2 * half / spacing)) + 1)


def _surface_samples(kind: int, size: np.ndarray, n: int = 24) -> np.ndarray:
    """Points spread over the surface of a box or cylinder (primitive frame), edges and corners included."""
    t = np.linspace(-1.0, 1.0, n)
    a, b = np.meshgrid(t, t, indexing="ij")
    a, b = a.ravel(), b.ravel()
    if kind == BOX:
        faces = []
        for axis in range(3):
            u, v = [i for i in range(3) if i != axis]
            for sign in (-1.0, 1.0):
                pts = np.zeros((a.size, 3))
                pts[:, axis] = sign * size[axis]
                pts[:, u], pts[:, v] = a * size[u], b * size[v]
                faces.append(pts)
        return np.concatenate(faces)
    r, h = size[0], size[1]
    ang = np.linspace(0.0, 2 * np.pi, 4 * n, endpoint=False)
    th, z = np.meshgrid(ang, t * h, indexing="ij")
    side = np.stack([r * np.cos(th.ravel()), r * np.sin(th.ravel()), z.ravel()], -1)
    rho, th2 = np.meshgrid(np.linspace(0.0, r, n), ang, indexing="ij")
    caps = [np.stack([rho.ravel() * np.cos(th2.ravel()), rho.ravel() * np.sin(th2.ravel()), np.full(rho.size, sign * h)], -1)
            for sign in (-1.0, 1.0)]
    return np.concatenate([side, *caps])


def _fine_primitive(kind: int, size: np.ndarray, error: float) -> tuple[np.ndarray, np.ndarray]:
    """(centres (n, 3), radii (n,)) in the primitive frame: a sphere set within ``error`` of it."""
    if kind == SPHERE:
        return np.zeros((1, 3)), np.array([size[0]])
    if kind == CAPSULE:
        r, h = size[0], size[1]
        zs = _axis_points(h, 2 * math.sqrt(2 * r * error + error**2))
        return np.stack([np.zeros_like(zs), np.zeros_like(zs), zs], -1), np.full(len(zs), r)
    delta = min(2.7 * error, float(size[0]), float(size[1]) if kind == CYLINDER else float(size.min()))
    radius = delta + error
    samples = _surface_samples(kind, size)
    spacing = math.sqrt(2.0) * math.sqrt(4 * delta * error + 4 * error**2)
    for _ in range(40):
        if kind == BOX:
            inner = size - delta
            axes = [_grid(float(h), spacing) for h in inner]
            pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
            flat = (inner <= 1e-12).any()
            on_surface = flat | (np.abs(np.abs(pts) - inner) < 1e-12).any(-1)
            pts = pts[on_surface]
        else:
            r_in, h_in = size[0] - delta, size[1] - delta
            zs = _grid(h_in, spacing)
            ring = max(1, int(math.ceil(2 * math.pi * r_in / spacing))) if r_in > 1e-12 else 1
            ang = np.linspace(0.0, 2 * np.pi, ring, endpoint=False)
            side = [(r_in * math.cos(t), r_in * math.sin(t), z) for z in zs for t in ang]
            cap = []
            for rho in _grid(r_in, spacing)[_grid(r_in, spacing) >= -1e-12][:-1] if r_in > 1e-12 else []:
                n_ring = max(1, int(math.ceil(2 * math.pi * rho / spacing))) if rho > 1e-12 else 1
                cap += [(rho * math.cos(t), rho * math.sin(t), z) for z in (-h_in, h_in)
                        for t in np.linspace(0.0, 2 * np.pi, n_ring, endpoint=False)]
            pts = np.unique(np.round(np.array(side + cap), 12), axis=0)
        gap = np.min(np.linalg.norm(samples[:, None, :] - pts[None], axis=-1) - radius, axis=1)
        if gap.max() <= error:
            return pts, np.full(len(pts), radius)
        spacing *= 0.9
    raise RuntimeError(f"no fine sphere set within {error} m for primitive kind {kind} size {size}")  # pragma: no cover


def cover_centres(xp: Any, robot: RobotModel, kin: Kinematics, cover: SphereCover | None = None) -> Any:
    """World centres (S, 3) of a sphere set (default: the conservative cover); sets are sorted by
    link, so each link's spheres are one static slice: a small matmul per link instead of a gather."""
    cover = _cover(robot) if cover is None else cover
    dtype = kin.link_pos.dtype
    parts = []
    for link in np.unique(cover.link):
        sel = np.nonzero(cover.link == link)[0]
        local = xp.asarray(cover.local[sel[0] : sel[-1] + 1], dtype=dtype)
        parts.append(kin.link_pos[..., link, None, :] + local @ xp.swapaxes(kin.link_rot[..., link, :, :], -1, -2))
    return xp.concatenate(parts, axis=-2)


def lowest_z(part: Any) -> float:
    """Height of a static part's lowest point."""
    return float(part.pos[2] - np.abs(np.asarray(part.rot)[2]) @ np.asarray(part.size))


ARM_REACH_Z = 1.25  # m, above every point the arm can reach (tests/envs/test_env.py checks ≤ 1.22 m)


def spans_reach(part: Any) -> bool:
    """An upright box standing on the table and taller than the arm's reach."""
    return bool(np.allclose(part.rot, np.eye(3)) and part.pos[2] - part.size[2] <= 0.0 and part.pos[2] + part.size[2] >= ARM_REACH_Z)


def reachable_parts() -> list[int]:
    """Static parts that reach below UNREACHABLE_ROLES_MIN_Z (the gantry posts)."""
    return [i for i, p in enumerate(SCENE.static_parts) if lowest_z(p) < UNREACHABLE_ROLES_MIN_Z]


_I1 = np.array([1, 2, 0], dtype=np.int32)  # (i+1) % 3; int32 whether or not jax runs in x64
_I2 = np.array([2, 0, 1], dtype=np.int32)  # (i+2) % 3


def boxes_overlap(xp: Any, pos_a: Any, rot_a: Any, half_a: Any, pos_b: Any, rot_b: Any, half_b: Any) -> Any:
    """Exact overlap test of two oriented boxes: the 15-axis separating-axis test in the
    Gottschalk form (all axes from R = AᵀB elementwise, no cross products or normalising),
    ≈ 150 flops.  Touching counts as no overlap."""
    r = xp.swapaxes(rot_a, -1, -2) @ rot_b  # B's axes in A's frame (columns)
    t = xp.swapaxes(rot_a, -1, -2) @ (pos_b - pos_a)
    abs_r = xp.abs(r) + 1e-9  # parallel edges: keep the cross-axis tests conservative
    sep_a = xp.abs(t) > half_a + abs_r @ half_b
    sep_b = xp.abs(t @ r) > half_a @ abs_r + half_b
    # axis A_i x B_j: |t[i2]·R[i1,j] − t[i1]·R[i2,j]| > a[i1]|R[i2,j]| + a[i2]|R[i1,j]| + b[j1]|R[i,j2]| + b[j2]|R[i,j1]|
    lhs = xp.abs(t[_I2, None] * r[_I1, :] - t[_I1, None] * r[_I2, :])
    rhs = (
        half_a[_I1, None] * abs_r[_I2, :]
        + half_a[_I2, None] * abs_r[_I1, :]
        + half_b[None, _I1] * abs_r[:, _I2]
        + half_b[None, _I2] * abs_r[:, _I1]
    )
    separated = xp.any(sep_a) | xp.any(sep_b) | xp.any(lhs > rhs)
    return ~separated


def _target_hits(xp: Any, robot: RobotModel, prim_pos: Any, prim_rot: Any, t_pos: Any, t_rot: Any, t_half: Any) -> Any:
    """Exact overlap of the gripper's primitives (those fixed to wrist3: flange, body, pads)
    with the target cuboid: separating axes for boxes, closed-form segment-box for capsules, spheres
    exact, the flange cylinder through its circumscribing sphere (it sits 10 cm above the
    pads).  The rest of the arm is checked through its cover spheres in ``check``."""
    hits = []
    dtype = prim_pos.dtype
    for g in np.nonzero(robot.prim_link == len(robot.link_names) - 1)[0]:
        kind = int(robot.prim_kind[g])
        size = xp.asarray(robot.prim_size[g], dtype=dtype)
        if kind == BOX:
            hits.append(boxes_overlap(xp, prim_pos[g], prim_rot[g], size, t_pos, t_rot, t_half))
            continue
        if kind == CAPSULE:
            gap = geometry.capsule_box_distance(xp, prim_pos[g], prim_rot[g], size, t_pos, t_rot, t_half)
        else:
            r = float(robot.prim_size[g][0]) if kind == SPHERE else math.hypot(robot.prim_size[g][0], robot.prim_size[g][1])
            gap = geometry.point_box_distance(xp, prim_pos[g], t_pos, t_rot, t_half) - r
        hits.append(gap < 0.0)
    return xp.any(xp.stack(hits))


def _link_slice(cover: SphereCover, first: int, last: int) -> slice:
    """The cover spheres of links first..last (inclusive) as a static slice (cover is sorted by link)."""
    sel = np.nonzero((cover.link >= first) & (cover.link <= last))[0]
    return slice(int(sel[0]), int(sel[-1]) + 1)


def nearest_slot(xp: Any, per_slot: Any) -> Any:
    """One-hot (slots,) of the nearest obstacle slot: the lowest-index slot at the minimum distance.

    The tie-break both simulators share: on equal distances (e.g. two identical obstacles) the lower
    slot wins, in NumPy and JAX alike, whatever either library's argmin or sort does with ties.  (A
    tolerance would not make the choice more stable: it only moves the switch point, and the two
    simulators' distances differ by the same amount on either side of it.)"""
    at_min = per_slot <= xp.min(per_slot)
    return at_min & (xp.cumsum(at_min.astype(xp.int32)) == 1)


def check(xp: Any, robot: RobotModel, kin: Kinematics, reset: Any, cfg: EnvConfig) -> CollisionResult:
    """Collision flags and obstacle distances for one env at one pose (docs/task.md §2)."""
    cover = _cover(robot)
    last = len(robot.link_names) - 1
    centres = cover_centres(xp, robot, kin)  # (S, 3)
    dtype = centres.dtype
    radius = xp.asarray(cover.radius, dtype=dtype)
    clip = cfg.task.obstacle_dist_clip

    # dynamic obstacles: spheres of the moving links (fine set or conservative cover) vs exact shapes
    if cfg.task.obstacle_geometry == "fine":
        o_cover = fine_cover(robot)
        o_centres = cover_centres(xp, robot, kin, o_cover)
        o_radius = xp.asarray(o_cover.radius, dtype=dtype)
    else:
        moving = _link_slice(cover, 1, last)
        o_centres, o_radius = centres[moving], radius[moving]
    active = xp.asarray(reset.obstacle_active)
    kind = xp.asarray(reset.obstacle_kind)
    kinds = shapes.kind_ids(cfg.sampling.obstacle_kinds)  # only the configured shapes are computed
    if isinstance(kind, np.ndarray):  # NumPy callers (PyBullet env, deployment) get a check, not a wrong shape
        unknown = sorted(set(np.asarray(kind)[np.asarray(active, bool)].tolist()) - set(kinds))
        if unknown:
            raise ValueError(f"obstacle kind(s) {unknown} are not in env.sampling.obstacle_kinds "
                             f"{cfg.sampling.obstacle_kinds} (ids {kinds})")
    o_pos = xp.asarray(reset.obstacle_pos, dtype=dtype)
    o_yaw = xp.asarray(reset.obstacle_yaw, dtype=dtype)
    o_size = xp.asarray(reset.obstacle_size, dtype=dtype)
    sdf = shapes.sdf(
        xp, kind[:, None], o_pos[:, None, :], o_yaw[:, None], o_size[:, None, :], o_centres[None, :, :], kinds
    ) - o_radius[None, :]  # (slots, S)
    slot_min = xp.min(sdf, axis=-1)
    per_slot = xp.where(active, slot_min, xp.inf)
    hit_obstacle = xp.any(per_slot < 0.0)
    any_active = xp.any(active)
    onehot = nearest_slot(xp, per_slot)[:, None]
    nearest_pos = xp.where(any_active, xp.sum(xp.where(onehot, o_pos, 0.0), axis=0), xp.asarray(cfg.task.no_obstacle_pos, dtype=dtype))
    nearest_dist = xp.minimum(xp.min(per_slot), clip)
    obstacle_dist = xp.minimum(per_slot, clip)
    # nearest-point vectors: from the slot's closest sphere, and from the gripper centre
    closest = (xp.arange(sdf.shape[-1])[None, :] == xp.argmin(sdf, axis=-1)[:, None])[..., None]  # (slots, S, 1)
    star = xp.sum(xp.where(closest, o_centres[None, :, :], 0.0), axis=1)  # (slots, 3)
    to_surface = shapes.surface_point(xp, kind, o_pos, o_yaw, o_size, star, kinds) - star
    length = xp.sqrt(xp.sum(to_surface**2, axis=-1, keepdims=True))
    outside = shapes.sdf(xp, kind, o_pos, o_yaw, o_size, star, kinds)[:, None] >= 0.0
    toward = xp.where(outside, 1.0, -1.0) * to_surface / xp.maximum(length, 1e-9)
    robot_to_obstacle = xp.where(active[:, None], slot_min[:, None] * toward, 0.0)
    centre = xp.broadcast_to(kin.gripper_centre.astype(dtype), o_pos.shape)
    gripper_vec = shapes.surface_point(xp, kind, o_pos, o_yaw, o_size, centre, kinds) - centre
    gripper_to_obstacle = xp.where(active[:, None], gripper_vec, 0.0)

    # gantry posts (camera, bracket and beam are out of reach)
    reach = _link_slice(cover, robot.spec.reach_link, last)
    hit_gantry = xp.zeros((), bool)
    hit_camera = xp.zeros((), bool)
    for i in reachable_parts():
        part = SCENE.static_parts[i]
        local = centres[reach] - xp.asarray(part.pos, dtype=dtype)
        if not np.allclose(part.rot, np.eye(3)):
            local = local @ xp.asarray(part.rot, dtype=dtype)
        axes = 2 if spans_reach(part) else 3  # a post from the floor past the arm's reach: footprint test
        q = xp.abs(local[:, :axes]) - xp.asarray(part.size[:axes], dtype=dtype)
        d = xp.sqrt(xp.sum(xp.maximum(q, 0.0) ** 2, axis=-1)) + xp.minimum(xp.max(q, axis=-1), 0.0) - radius[reach]
        hit = xp.any(d < 0.0)
        if part.role == "gantry":
            hit_gantry = hit_gantry | hit
        else:
            hit_camera = hit_camera | hit

    # table: exact support function of every reaching primitive
    prim_pos, prim_rot = primitive_poses(xp, robot, kin)
    g_reach = np.nonzero(robot.prim_link >= robot.spec.reach_link)[0]
    lowest = [
        geometry.plane_distance(xp, int(robot.prim_kind[g]), prim_pos[g], prim_rot[g], xp.asarray(robot.prim_size[g], dtype=dtype), SCENE.table.top_z)
        for g in g_reach
    ]
    hit_table = xp.any(xp.stack(lowest) < 0.0)

    # target cuboid: exact
    t_half = xp.asarray([s / 2 for s in cfg.sampling.target_size], dtype=dtype)
    t_pos = xp.asarray(reset.target_pos, dtype=dtype)
    t_rot = shapes.yaw_rotation(xp, xp.asarray(reset.target_yaw, dtype=dtype))
    arm = _link_slice(cover, robot.spec.reach_link, last - 1)
    rel = centres[arm] - t_pos
    local = rel @ t_rot
    q = xp.abs(local) - t_half
    d_arm = xp.sqrt(xp.sum(xp.maximum(q, 0.0) ** 2, axis=-1)) + xp.minimum(xp.max(q, axis=-1), 0.0) - radius[arm]
    hit_target = _target_hits(xp, robot, prim_pos, prim_rot, t_pos, t_rot, t_half) | xp.any(d_arm < 0.0)

    # self-collision: cover spheres of the wrists and gripper vs the exact base, shoulder, upper arm
    mov = _link_slice(cover, robot.self_moving_links[0], robot.self_moving_links[-1])
    self_gaps = []
    for g in np.nonzero(np.isin(robot.prim_link, robot.self_static_links))[0]:
        d = geometry.point_distance(
            xp, int(robot.prim_kind[g]), centres[mov], prim_pos[g], prim_rot[g], xp.asarray(robot.prim_size[g], dtype=dtype)
        )
        self_gaps.append(xp.min(d - radius[mov]))
    hit_self = xp.min(xp.stack(self_gaps)) < 0.0

    hits = {"obstacle": hit_obstacle, "gantry": hit_gantry, "camera": hit_camera, "table": hit_table, "target": hit_target, "self": hit_self}
    any_collision = hit_obstacle | hit_gantry | hit_camera | hit_table | hit_target | hit_self
    return CollisionResult(obstacle_dist, nearest_dist, nearest_pos, hits, any_collision, robot_to_obstacle,
                           gripper_to_obstacle)
