"""Episode-start sampling (docs/task.md §1): target pose, dynamic obstacles, start-pose noise.

The maths is backend-agnostic and takes its randomness as a flat vector of uniform
numbers in [0, 1) (``uniforms_needed(cfg)`` long).  The MJX env draws it with
``jax.random.uniform``, the PyBullet reference env with NumPy; the same vector gives
the same reset in both.  Everything is fixed-size (no rejection loops): every
candidate of every attempt is evaluated and the first feasible one is selected, so it
jits, vmaps and costs the same for every env.

Obstacle kinds are ``cfg.obstacle_kinds`` (entries of ``shapes.SHAPES``: each says how its size,
height and yaw are drawn and holds its SDF, footprint and bounding radius); a slot's candidates are
split evenly among them.  Feasibility of an obstacle (docs/task.md §1): (a) horizontal clearance from its surface to the
target centre ≥ ``target_clearance``; (b) every robot primitive at the (noisy) start
pose ≥ ``robot_clearance`` from the obstacle — measured between the obstacle's exact shape
and the robot's sphere cover (``collision.py``) less the cover's capsule dip, so never optimistic; (c) the two
obstacles' bounding spheres do not overlap (conservative).  When a slot has no feasible
candidate the whole scene (target too) is re-drawn, up to ``scene_redraws`` times; the
rare fallback is an obstacle-free scene, counted in ``fallback``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from sagrasp_jax.task.config import SamplingConfig, TaskConfig
import numpy as np

from sagrasp_jax.task import collision
from sagrasp_jax.task import reward
from sagrasp_jax.task import shapes
from sagrasp_jax.task import robots
from sagrasp_jax.task.robot import Kinematics, RobotModel, forward_kinematics
from sagrasp_jax.task.shapes import ObstacleShape

_PER_CANDIDATE = 8  # kind order offset, 3 sizes, disc radius, disc angle, height, yaw (shapes.draw)
_PER_TARGET = 3  # x, y, yaw


class ResetSpec(NamedTuple):
    """An explicit episode start: what the MJX and PyBullet envs both accept."""

    q0: Any  # (dof,) start joint vector
    target_pos: Any  # (3,) cube centre
    target_yaw: Any  # () rad
    obstacle_active: Any  # (max_obstacles,) bool
    obstacle_kind: Any  # (max_obstacles,) int: a shapes.SHAPES id (env.sampling.obstacle_kinds)
    obstacle_pos: Any  # (max_obstacles, 3) centre
    obstacle_yaw: Any  # (max_obstacles,) rad about world z (0 for shapes round about z)
    obstacle_size: Any  # (max_obstacles, 3) MuJoCo size convention of the shape's primitive
    redraws: Any  # () whole-scene re-draws used
    fallback: Any  # () 1 if obstacles were wanted but none was feasible


def uniforms_needed(cfg: SamplingConfig, dof: int = robots.DEFAULT_DOF) -> int:
    """How many uniforms ``sample_reset`` turns into a scene for an arm of ``dof`` joints (the package passes
    its env's robot's; the default robot's by default)."""
    attempts = cfg.scene_redraws + 1
    per_attempt = cfg.target_candidates * _PER_TARGET + cfg.max_obstacles * cfg.obstacle_candidates * _PER_CANDIDATE
    return 2 + dof + attempts * per_attempt + 1  # presence, count, start noise, attempts, blocking placement


PATH_SAMPLES = 24  # points along the approach segment for the blocking test of obstacle candidates
BLOCKING_T = (0.1, 0.9)  # where along the approach segment a blocking obstacle is placed
BLOCKING_OFFSET = 0.03  # m, lateral (horizontal) and, for spheres, vertical jitter about the segment


def path_clearance(xp: Any, robot: RobotModel, task: TaskConfig, reset: "ResetSpec", samples: int = 32,
                   levels: int = 3, kinds: tuple[int, ...] | None = None) -> Any:
    """Distance (slots,) from the straight segment (gripper centre at the start pose → grasp point)
    to each obstacle's surface; +inf for empty slots.  The obstacle's SDF along the segment is convex,
    so a grid of ``samples`` points finds the cell holding the minimum and each further level grids
    the two cells around the best point: at 3 levels of 32 the result overshoots the true minimum by
    < 0.05 mm on a 0.5 m segment (tested against a 20,001-point scan)."""
    dtype = xp.asarray(reset.target_pos).dtype
    q0 = xp.asarray(reset.q0, dtype=dtype)
    start = forward_kinematics(xp, robot, q0).gripper_centre
    end = reward.grasp_centre(xp, task, xp.asarray(reset.target_pos, dtype=dtype))
    kind, pos = xp.asarray(reset.obstacle_kind), xp.asarray(reset.obstacle_pos, dtype=dtype)
    yaw, size = xp.asarray(reset.obstacle_yaw, dtype=dtype), xp.asarray(reset.obstacle_size, dtype=dtype)

    def f(t: Any) -> Any:  # (slots, n) SDF at start + t·(end − start)
        points = start + t[..., None] * (end - start)
        return shapes.sdf(xp, kind[:, None], pos[:, None], yaw[:, None], size[:, None], points, kinds)

    grid = xp.linspace(-1.0, 1.0, samples, dtype=dtype)
    t = xp.broadcast_to(xp.linspace(0.0, 1.0, samples, dtype=dtype), kind.shape + (samples,))
    half_width = 1.0 / (samples - 1)
    best = xp.full(kind.shape, xp.inf, dtype=dtype)
    for _ in range(levels):
        values = f(t)
        best = xp.minimum(best, xp.min(values, axis=-1))
        onehot = xp.arange(samples)[None, :] == xp.argmin(values, axis=-1)[:, None]
        centre = xp.sum(xp.where(onehot, t, 0.0), axis=-1)  # (slots,) best point of this level
        t = xp.clip(centre[:, None] + half_width * grid, 0.0, 1.0)
        half_width = 2.0 * half_width / (samples - 1)
    return xp.where(xp.asarray(reset.obstacle_active), best, xp.inf)


def is_blocking(xp: Any, robot: RobotModel, cfg: SamplingConfig, task: TaskConfig, reset: "ResetSpec") -> Any:
    """An obstacle scene whose straight approach path passes within ``cfg.blocking_margin`` of an obstacle."""
    return xp.any(path_clearance(xp, robot, task, reset, kinds=shapes.kind_ids(cfg.obstacle_kinds)) < cfg.blocking_margin)


def _lerp(lo_hi: tuple[float, float], u: Any) -> Any:
    return lo_hi[0] + (lo_hi[1] - lo_hi[0]) * u


def _first_true(xp: Any, mask: Any) -> tuple[Any, Any]:
    """Index of the first True along the last axis, and whether there is one."""
    any_true = xp.any(mask, axis=-1)
    return xp.argmax(mask, axis=-1), any_true


def _select(xp: Any, values: Any, index: Any, axis: int) -> Any:
    """values indexed by ``index`` along ``axis`` (index has the shape of values without that axis
    and trailing dims).  A one-hot product: under vmap on CPU it is several times faster than a gather."""
    n = values.shape[axis]
    onehot = xp.arange(n) == xp.expand_dims(index, -1)  # (..., n)
    onehot = xp.moveaxis(onehot, -1, axis if axis >= 0 else values.ndim + axis)
    extra = values.ndim - onehot.ndim
    onehot = onehot.reshape(onehot.shape + (1,) * extra)
    if values.dtype == bool:
        return xp.any(onehot & values, axis=axis)
    return xp.sum(xp.where(onehot, values, 0), axis=axis)


class _KindGroups(NamedTuple):
    """The candidates of a slot grouped by kind: ``per_kind`` consecutive candidates of each shape of
    ``env.sampling.obstacle_kinds``, in that order.  Every per-kind computation runs on its group's
    static slice, so a candidate's shape maths is its own kind's only."""

    shapes: tuple[ObstacleShape, ...]
    per_kind: int

    @property
    def count(self) -> int:
        return self.per_kind * len(self.shapes)

    def items(self) -> list[tuple[ObstacleShape, slice]]:
        return [(shape, slice(g * self.per_kind, (g + 1) * self.per_kind)) for g, shape in enumerate(self.shapes)]

    def map(self, xp: Any, fn: Any, axis: int) -> Any:
        """``fn(shape, slice)`` for every group, concatenated along the candidate ``axis``."""
        return xp.concatenate([fn(shape, sl) for shape, sl in self.items()], axis=axis)


def _kind_groups(cfg: SamplingConfig) -> _KindGroups:
    kinds = shapes.shapes_of(cfg.obstacle_kinds)
    return _KindGroups(kinds, cfg.obstacle_candidates // len(kinds))  # a remainder goes unused


def _by_kind(xp: Any, kind: Any, branches: list[tuple[tuple[int, ...], Any]], default: Any, trailing: int = 0) -> Any:
    """Nested ``where`` over candidate kinds: the value of the first branch whose ids hold ``kind``,
    else ``default``.  The cheap per-kind quantities (size, height, yaw, footprint, bounding radius)
    are computed for every candidate and selected this way; the SDFs, the costly part, per group."""
    out = default
    for ids, value in reversed(branches):
        mask = kind == ids[0]
        for k in ids[1:]:
            mask = mask | (kind == k)
        out = xp.where(mask[..., None] if trailing else mask, value, out)
    return out


def _per_kind(xp: Any, kind: Any, entries: tuple[ObstacleShape, ...], value: Any, trailing: int = 0) -> Any:
    """``value(entry)`` of each candidate's own kind; the last entry's is the default."""
    return _by_kind(xp, kind, [((s.id,), value(s)) for s in entries[:-1]], value(entries[-1]), trailing)


class _Candidates(NamedTuple):
    """Obstacle candidates of every attempt and slot, (attempts, slots, n_o[, 3])."""

    kind: Any
    size: Any
    yaw: Any
    pos: Any  # disc placement (docs/task.md §1); the blocking placement may move slot 0's
    rest_z: Any  # centre height of the kinds resting on the table (None if every kind floats)
    order: Any  # visiting position of each candidate (first feasible in this order wins)


def _draw_targets(xp: Any, cfg: SamplingConfig, u_target: Any) -> tuple[Any, Any, Any]:
    """First candidate of each attempt inside the reachable annulus: xy (attempts, 2), yaw, found."""
    tx, ty = _lerp(cfg.target_x, u_target[..., 0]), _lerp(cfg.target_y, u_target[..., 1])
    tyaw = _lerp(cfg.target_yaw, u_target[..., 2])
    radius = xp.sqrt(tx**2 + ty**2)
    ok_t = (radius >= cfg.target_radius[0]) & (radius <= cfg.target_radius[1])
    it, has_t = _first_true(xp, ok_t)  # (attempts,)
    target_xy = xp.stack([_select(xp, tx, it, 1), _select(xp, ty, it, 1)], axis=-1)  # (attempts, 2)
    return target_xy, _select(xp, tyaw, it, 1), has_t


def _floating_z(xp: Any, kind: Any, entries: tuple[ObstacleShape, ...], rest_z: Any, height: Any) -> Any:
    """Centre heights: ``height(entry)`` for floating kinds, ``rest_z`` for those resting on the table."""
    floating = tuple(s for s in entries if s.float_z is not None)
    if rest_z is None:
        return _per_kind(xp, kind, floating, height)
    return _by_kind(xp, kind, [((s.id,), height(s)) for s in floating], rest_z)


def _draw_obstacles(xp: Any, cfg: SamplingConfig, groups: _KindGroups, u_obs: Any, target_xy: Any) -> _Candidates:
    """Candidates for every attempt and slot: ``per_kind`` of each kind (static, so the robot
    clearance needs one shape's SDF per candidate), visited in the interleaved order kind (off),
    kind (off+1), ... with a uniform random offset per slot, so the first candidate's kind is uniform.
    Each kind draws its size from the candidate's uniforms 1-3 (``ObstacleShape.sample_size``), its
    centre height from uniform 6 if it floats, else it rests on the table, and its yaw from uniform 7
    if it has one; the horizontal position is uniform in the disc around the midpoint between the
    home gripper centre and the target (uniforms 4, 5)."""
    entries, n_o = groups.shapes, groups.count
    n_kinds = len(entries)
    kind_pattern = np.repeat(np.asarray([s.id for s in entries]), groups.per_kind)  # (n_o,)
    kind = xp.broadcast_to(xp.asarray(kind_pattern), u_obs.shape[:-1])
    offset = xp.minimum((u_obs[..., 0, 0] * n_kinds).astype(xp.int32), n_kinds - 1)  # (attempts, slots)
    group, within = np.arange(n_o) // groups.per_kind, np.arange(n_o) % groups.per_kind
    order = n_kinds * within + (group - offset[..., None]) % n_kinds
    s1, s2, s3 = u_obs[..., 1], u_obs[..., 2], u_obs[..., 3]
    sizes = {s.id: s.sample_size(xp, cfg, s1, s2, s3) for s in entries}
    size = _per_kind(xp, kind, entries, lambda s: sizes[s.id], trailing=1)
    mid = 0.5 * (xp.asarray(cfg.home_xy) + target_xy)  # (attempts, 2)
    rho = cfg.obstacle_disc_radius * xp.sqrt(u_obs[..., 4])
    phi = 2 * xp.pi * u_obs[..., 5]
    ox = mid[:, None, None, 0] + rho * xp.cos(phi)
    oy = mid[:, None, None, 1] + rho * xp.sin(phi)
    resting = tuple(s for s in entries if s.float_z is None)
    rest_z = _per_kind(xp, kind, resting, lambda s: s.half_height(size)) if resting else None
    oz = _floating_z(xp, kind, entries, rest_z, lambda s: _lerp(getattr(cfg, s.float_z), u_obs[..., 6]))
    yawed = tuple(s.id for s in entries if s.yawed)
    drawn_yaw = 2 * xp.pi * u_obs[..., 7] - xp.pi
    if len(yawed) == n_kinds:
        oyaw = drawn_yaw
    else:
        oyaw = _by_kind(xp, kind, [(yawed, drawn_yaw)], 0.0) if yawed else xp.zeros_like(drawn_yaw)
    return _Candidates(kind, size, oyaw, xp.stack([ox, oy, oz], axis=-1), rest_z, order)


def _obstacle_to_robot(xp: Any, robot: RobotModel, kin: Kinematics, kind: int, pos: Any, yaw: Any, size: Any) -> Any:
    """Distance (...,) from obstacle candidates of one static kind (exact shapes) to the robot's
    conservative sphere cover (collision.py): docs/task.md §2.8's "every robot collision geometry"."""
    cover = collision.sphere_cover(robot)
    spheres = collision.cover_centres(xp, robot, kin)  # (S, 3)
    sdf = shapes.sdf(xp, kind, pos[..., None, :], yaw[..., None], size[..., None, :], spheres)
    return xp.min(sdf - xp.asarray(cover.radius, dtype=spheres.dtype), axis=-1)


def _blocking_placement(xp: Any, cfg: SamplingConfig, task: TaskConfig, groups: _KindGroups, kin: Kinematics,
                        u_obs: Any, cand: _Candidates, target_xy: Any, block: Any) -> tuple[Any, Any]:
    """"Blocking" scenes (probability blocking_prob among obstacle scenes): slot 0's candidates sit on
    the straight segment from the start gripper centre to the grasp point (same shapes and sizes, a
    horizontal offset of ≤ BLOCKING_OFFSET, floating shapes at the segment's height) and must pass
    within blocking_margin of it; slot 1 keeps the disc placement.  Returns the candidate positions
    (attempts, slots, n_o, 3) and the mask of candidates that satisfy the blocking requirement."""
    attempts, slots, n_o = cand.kind.shape
    start = kin.gripper_centre  # (3,)
    dtype = start.dtype
    t_grasp = xp.concatenate([target_xy, xp.full((attempts, 1), cfg.target_size[2] / 2, dtype=dtype)], axis=-1)
    end = reward.grasp_centre(xp, task, t_grasp)  # (attempts, 3)
    t = _lerp(BLOCKING_T, u_obs[:, 0, :, 4])  # (attempts, n_o)
    along = start + t[..., None] * (end - start)[:, None, :]  # (attempts, n_o, 3)
    heading = (end - start)[:, :2]
    perp = xp.stack([-heading[:, 1], heading[:, 0]], axis=-1) / xp.sqrt(xp.sum(heading**2, axis=-1, keepdims=True))
    lateral = BLOCKING_OFFSET * (2 * u_obs[:, 0, :, 5] - 1)

    # floating kinds at the segment's height, jittered; the others rest on the table
    bz = _floating_z(xp, cand.kind[:, 0], groups.shapes, None if cand.rest_z is None else cand.rest_z[:, 0],
                     lambda s: xp.clip(along[..., 2] + BLOCKING_OFFSET * (2 * u_obs[:, 0, :, 6] - 1), *getattr(cfg, s.float_z)))
    path_pos = xp.stack([along[..., 0] + lateral * perp[:, None, 0], along[..., 1] + lateral * perp[:, None, 1], bz], -1)
    pos = xp.concatenate([xp.where(block, path_pos, cand.pos[:, 0])[:, None], cand.pos[:, 1:]], axis=1)
    frac = xp.linspace(0.0, 1.0, PATH_SAMPLES, dtype=dtype)
    path = start + frac[:, None] * (end - start)[:, None, :]  # (attempts, PATH_SAMPLES, 3)
    near_path = groups.map(
        xp,
        lambda shape, sl: xp.min(shapes.sdf(xp, shape.id, pos[:, 0, sl, None, :], cand.yaw[:, 0, sl, None],
                                            cand.size[:, 0, sl, None, :], path[:, None]), axis=-1),
        axis=-1,
    ) < cfg.blocking_margin  # (attempts, n_o): an upper bound of the true clearance is below the margin
    blocking_ok = xp.concatenate([(near_path | ~block)[:, None], xp.ones((attempts, slots - 1, n_o), bool)], axis=1)
    return pos, blocking_ok


def _feasible(xp: Any, robot: RobotModel, cfg: SamplingConfig, groups: _KindGroups, kin: Kinematics,
              cand: _Candidates, pos: Any, target_xy: Any) -> Any:
    """docs/task.md §1 (a) and (b) per candidate (attempts, slots, n_o): footprint clear of the target,
    exact shape clear of the robot's cover at the start pose."""
    d = target_xy[:, None, None, :] - pos[..., :2]
    footprints: dict[Any, list[int]] = {}  # kinds sharing a footprint function share its value
    for shape in groups.shapes:
        footprints.setdefault(shape.footprint, []).append(shape.id)
    (first, *others) = [(tuple(ids), fn(xp, d, cand.yaw, cand.size)) for fn, ids in footprints.items()]
    clear_target = _by_kind(xp, cand.kind, others, first[1]) >= cfg.target_clearance
    robot_gap = groups.map(xp, lambda shape, sl: _obstacle_to_robot(
        xp, robot, kin, shape.id, pos[..., sl, :], cand.yaw[..., sl], cand.size[..., sl, :]), axis=-1)
    # the cover over-reaches boxes and cylinders but dips ≤ CAPSULE_DIP between a capsule's spheres
    return clear_target & (robot_gap >= cfg.robot_clearance + collision.CAPSULE_DIP)


def _choose(xp: Any, cfg: SamplingConfig, u_present: Any, u_count: Any, has_t: Any, ok: Any, order: Any, pos: Any,
            bound: Any) -> tuple[Any, Any, Any, Any, Any]:
    """The first feasible candidate of each slot in visiting order (slot 1 must also keep clear of
    slot 0's, bounding spheres apart, docs/task.md §1 (c)), then the first attempt whose scene is feasible.
    Returns (attempt index, chosen candidate per slot (slots,), whether any attempt worked, the
    fallback flag, the wanted obstacle count)."""
    n_o = ok.shape[-1]

    def first_in_order(mask: Any, slot: int) -> tuple[Any, Any]:
        rank = xp.where(mask, order[:, slot], n_o + 1)
        return xp.argmin(rank, axis=-1), xp.any(mask, axis=-1)

    i0, has0 = first_in_order(ok[:, 0], 0)
    pos0, r0 = _select(xp, pos[:, 0], i0, 1), _select(xp, bound[:, 0], i0, 1)
    apart = xp.sqrt(xp.sum((pos[:, 1] - pos0[:, None, :]) ** 2, axis=-1)) > bound[:, 1] + r0[:, None]
    i1, has1 = first_in_order(ok[:, 1] & apart, 1)

    want = u_present < cfg.obstacle_prob
    count = xp.where(u_count < 0.5, 1, 2)
    feasible = has_t & has0 & ((count < 2) | has1)
    attempt_ok = xp.where(want, feasible, has_t)
    ia, any_ok = _first_true(xp, attempt_ok)
    ia = xp.where(any_ok, ia, 0)
    fallback = want & ~(any_ok & _select(xp, feasible, ia, 0))
    chosen = xp.stack([_select(xp, i0, ia, 0), _select(xp, i1, ia, 0)])  # (slots,)
    active = xp.stack([want & ~fallback, want & ~fallback & (count >= 2)])
    return ia, chosen, any_ok, fallback, active


def sample_reset(xp: Any, robot: RobotModel, cfg: SamplingConfig, task: TaskConfig, u: Any) -> ResetSpec:
    """Turn ``uniforms_needed(cfg)`` uniforms into a feasible episode start."""
    attempts = cfg.scene_redraws + 1
    n_t, slots = cfg.target_candidates, cfg.max_obstacles
    groups = _kind_groups(cfg)
    u_present, u_count = u[0], u[1]
    dof = len(task.home_q)  # one start joint per arm joint (validate: as many as env.robot has)
    q0 = xp.asarray(task.home_q) + _lerp((-task.start_noise, task.start_noise), u[2:2 + dof])
    body = u[2 + dof:-1].reshape(attempts, -1)
    u_target = body[:, : n_t * _PER_TARGET].reshape(attempts, n_t, _PER_TARGET)
    u_obs = body[:, n_t * _PER_TARGET :].reshape(attempts, slots, cfg.obstacle_candidates, _PER_CANDIDATE)
    u_obs = u_obs[..., : groups.count, :]

    target_xy, target_yaw, has_t = _draw_targets(xp, cfg, u_target)
    cand = _draw_obstacles(xp, cfg, groups, u_obs, target_xy)
    kin = forward_kinematics(xp, robot, q0)
    if cfg.blocking_prob > 0:
        pos, blocking_ok = _blocking_placement(xp, cfg, task, groups, kin, u_obs, cand, target_xy, u[-1] < cfg.blocking_prob)
    else:
        pos, blocking_ok = cand.pos, True
    ok = _feasible(xp, robot, cfg, groups, kin, cand, pos, target_xy) & blocking_ok
    bound = _per_kind(xp, cand.kind, groups.shapes, lambda s: s.bounding_radius(xp, cand.size))
    ia, chosen, any_ok, fallback, active = _choose(xp, cfg, u_present, u_count, has_t, ok, cand.order, pos, bound)

    def pick(values: Any) -> Any:  # (attempts, slots, n_o, ...) -> (slots, ...)
        per_slot = _select(xp, values, ia, 0)
        return xp.stack([_select(xp, per_slot[s], chosen[s], 0) for s in range(slots)])

    return ResetSpec(
        q0=q0,
        target_pos=xp.concatenate([_select(xp, target_xy, ia, 0), xp.asarray([cfg.target_size[2] / 2])]),
        target_yaw=_select(xp, target_yaw, ia, 0),
        obstacle_active=active,
        obstacle_kind=pick(cand.kind),
        obstacle_pos=pick(pos),
        obstacle_yaw=pick(cand.yaw),
        obstacle_size=pick(cand.size),
        redraws=xp.where(any_ok, ia, cfg.scene_redraws),
        fallback=fallback,
    )
