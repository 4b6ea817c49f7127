"""From the depth camera's point cloud to the cube and the obstacles, in the robot's base frame (docs/task.md §5.7).

The paper marks the cube's pixel with YOLO and reads its camera-frame point from the point cloud.  This
module does the same job with classical geometry, NumPy only (it runs on the robot PC), and returns what
the deployment loop validates: the cube centre and yaw in the world (URDF base) frame and every obstacle
as a ``deploy.loop.Obstacle`` (kind, centre, MuJoCo size, yaw).  Steps (``detect_scene``):

1. **Check the input.** An organized cloud (H, W, 3) in the camera frame, millimetres, NaN where the
   camera had no return (the Mech-Eye's format); a point at depth 0, (0, 0, 0) (the RealSense's and
   Open3D's "no return"), is no return too, wherever the cloud is read.  Refused with ``PerceptionError``:
   another shape, no valid point, too few valid points, depths that are not a depth camera's in
   millimetres (a cloud in metres read as millimetres lies 1.4 mm from the camera, one in centimetres
   140 mm; the message says which unit it looks like and the factor that gives millimetres).
2. **Table plane.** Points within ``plane_band_m`` of the table top (z = 0 through the calibration) are
   fitted by least squares, the band narrowed to 3 σ of the fit's residuals (robust MAD) and refitted;
   the plane must hold a fair share of the points.  This is also the check of the calibration against
   the scene: through it the table must come out at its known height (``max_table_offset_m`` under the
   workspace centre) and level (``max_plane_tilt_deg``), else ``CalibrationMismatch`` names the measured
   offset and tilt (a table far off is found as the largest level surface in view).
3. **Above the table.** Points more than ``min_height_m`` (or 5 σ of the table's noise) above the plane,
   minus the cell's static parts (gantry posts, camera: ``scene.SCENE``) and, given the arm's joints,
   the arm itself (``robot.primitive_poses``, ``robot_margin_m``).
4. **Regions.** Connected regions on the image grid (``label_regions``: 4-neighbours within
   ``max_gap_m`` in 3-D whose depth steps by at most ``max_slope`` pixel pitches, joined across a
   dropped pixel); regions smaller than ``min_region_m2`` and those whose top is narrower than
   ``min_top_side_m`` (fragments) are left over; a side broken off its top at a depth step rejoins it
   (``_merge_sides``).  Where a nearer object borders a region (``occluder_dirs``) its outline is hidden
   there: fits use the outline's own edges.  The left-over pixels are clustered again by 3-D gaps alone
   (``_leftovers``): a side seen nearly edge-on breaks into strips, and under a floating sphere those
   strips may be all that is seen of an obstacle.
5. **The cube.** With RGB: the region whose pixels are mostly red (r − max(g, b) ≥ ``red_margin``).
   Without RGB (or ``use_colour=False``): the region whose flat top is the cube's top face (height and
   both sides within tolerance).  None → "no cube found"; two → "two cube candidates"; a red region
   whose top is not a 20 × 20 mm face 50 mm above the table → "cube not standing on the table".  Its
   top face (points within ``top_tol_m`` of the top) gives the top-face centre (area-weighted centroid,
   each point weighted by its pixel's footprint on the top's plane) and the yaw (minimum-area rectangle
   of the face's outline, wrapped to [−45°, 45°): a square looks the same turned by 90°); the centre is
   the top-face centre 25 mm lower (``calibration.detected_top_to_cube_centre``).  A top face partly
   hidden behind a nearer object (the arm, an obstacle) or cut by the image border is refused: its
   centroid would be off.
6. **Obstacles.** What is seen of an obstacle is never dropped, and every obstacle returned holds every
   point seen of it (to the noise): the safety layer keeps the arm out of the obstacles, so it needs an
   over-approximation, never a miss.  Every other region is fitted as each allowed kind (``kinds``: the
   policy's ``env.sampling.obstacle_kinds``) as it rests in the cell, by the kind's own fit in its registry
   entry (``shapes.SHAPES``' ``perception.fit``; sphere: least-squares sphere; cylinder: upright, top disc's
   area and centroid; box: top face's minimum-area rectangle with its area matched to the measured one;
   capsule: lying, radius half the height, axis along the outline's long side), and the kind whose exact
   surface (``shapes.sdf``) lies nearest the region's points wins, flat-topped kinds (box, cylinder) told
   apart by the top's outline (each entry's ``perception.top_misfit``).  A fit that does not hold the region's points
   (``_uncovered``: a partly hidden obstacle whose visible part does not fix its shape, an object of a kind
   the policy was not trained with) is replaced by a covering shape of an allowed kind (``_cover``: the
   visible points' footprint, with the fit's own guess of it, from the table up to their highest point).
   Why covering and not refusing a kind the policy does not know: the cover holds everything seen, so the
   arm keeps out of it, and the policy observes a kind it was trained with; a cover nearer the cube than
   training put an obstacle is refused by the loop's scene check (``loop.scene_spec``:
   ``calibration.validate_obstacle_clearance``).
   A left-over cluster the cube or an obstacle holds is dropped (a side's strips), one mostly held joins
   that obstacle, any other is an obstacle.  Pieces of one obstacle are joined and fitted again
   (``_obstacle_parts``): two parts cut apart by a nearer object (nothing but it seen between them), two
   partly hidden parts whose footprints overlap or touch, or two fits of one kind with near centres.  A
   region taller or wider than any obstacle the sampler draws is refused (the arm in view without its
   joints, or something that is not part of the task).

A detector (the YOLO option, ``deploy.yolo``) may replace the colour test: its target boxes choose the
cube region (``detections=``), and ``point_at_pixel`` is the paper's own pixel → camera point.
Nothing here imports more than NumPy and the package's NumPy modules.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any, NamedTuple, Sequence

import numpy as np

from sagrasp_jax.task import geometry
from sagrasp_jax.task import shapes
from sagrasp_jax.task.point_fits import convex_hull, min_area_rect, wrap
from sagrasp_jax.task.config import SamplingConfig
from sagrasp_jax.deploy.calibration import CameraCalibration, detected_top_to_cube_centre
from sagrasp_jax.deploy.loop import Obstacle
from sagrasp_jax.task.robot import RobotModel, forward_kinematics, load_robot, primitive_poses
from sagrasp_jax.task.scene import SCENE

DEPTH_RANGE_MM = (300.0, 3000.0)  # where a depth camera over the table reports anything (deploy's DETECTION_RANGE)
WORKSPACE_CENTRE = (float(np.mean(SamplingConfig().target_x)), float(np.mean(SamplingConfig().target_y)))  # m, where
# the table's height is checked: the middle of the region the cube is drawn in
PLANE_POINTS = 20_000  # table points the plane is fitted to (evenly strided)
OCCLUDER_JUMP_M = 0.01  # a neighbour this much nearer (camera z) and not of the region hides part of it
# a fit holds a region when at most this share of its points lies outside it (_uncovered): of a whole region (its
# fit is the object, a few points off by more than the noise allowance are noise), of one partly hidden or cut by
# the image border (its fit rests on part of it, and a point it misses may be a part it failed to reach)
COVER_SHARE, COVER_SHARE_HIDDEN = 0.02, 0.002
LEFTOVER_HELD = 0.05  # a leftover cluster an obstacle holds all but this share of is part of it (_obstacle_parts)
MIN_RED_PIXELS = 12  # red pixels in a region that is not mostly red: a cube on or against something


def _trained_obstacle_limits(cfg: SamplingConfig = SamplingConfig(), margin: float = 0.05) -> tuple[float, float]:
    """(reach, top) of the largest obstacle the sampler draws of any registered kind, plus ``margin``: horizontal
    distance from its centre to its farthest point (a capsule's tip), and its top above the table (a floating
    sphere's).  A kind's largest size is its size from uniforms of 1 (``sample_size``)."""
    reach = top = 0.0
    for shape in shapes.SHAPES:
        size = shape.sample_size(np, cfg, 1.0, 1.0, 1.0)
        half = float(shape.half_height(size))
        reach = max(reach, shape.perception.reach(size))
        top = max(top, getattr(cfg, shape.float_z)[1] + half if shape.float_z else 2 * half)
    return reach + margin, top + margin


MAX_OBSTACLE_REACH_M, MAX_OBSTACLE_TOP_M = _trained_obstacle_limits()  # 0.25 m, 0.41 m for the shipped kinds


class PerceptionError(ValueError):
    """The cloud cannot give a cube (and obstacles) to act on; nothing may move (exit status 2 in a CLI)."""


@dataclass(frozen=True)
class PerceptionSettings:
    """Thresholds of ``detect_scene`` (metres unless named otherwise); the defaults fit the Mech-Eye at
    the cell's 1.4 m and a consumer depth camera alike (noise-dependent ones scale with the table's σ)."""

    plane_band_m: float = 0.03  # first table guess: |z| below this in the world frame
    min_plane_fraction: float = 0.2  # of the valid points must lie on the table
    max_plane_tilt_deg: float = 2.0  # the table's normal against world z: a calibration tilted more is refused
    max_table_offset_m: float = 0.010  # the table's height under the workspace centre against scene.SCENE.table.top_z
    min_height_m: float = 0.008  # above the table: an object's point (at least 5 σ of the table's noise)
    max_gap_m: float = 0.03  # neighbouring pixels this far apart in 3-D are not one surface
    max_slope: float = 5.0  # ... nor those whose depth steps more than this many pixel pitches (a 79° slope)
    min_region_m2: float = 1.5e-4  # smaller regions (footprint area) are noise: 12 × 12 mm
    min_top_side_m: float = 0.008  # a region whose top face is narrower is a fragment of a side (every trained
    # obstacle's top is ≥ 40 mm across, a sphere's top 3 mm ≥ 26 mm, the cube's 20 mm)
    top_tol_m: float = 0.003  # a top face's points lie this close to its height (at least 3 σ of the noise)
    red_margin: float = 0.2  # a red pixel: r − max(g, b) ≥ this (colours in [0, 1])
    red_fraction: float = 0.5  # a red region: this share of its pixels red
    cube_height_tol_m: float = 0.008  # the cube's top above the table: cube height ± this
    cube_side_tol: float = 0.35  # each side of its top face within ± this fraction of the cube's
    robot_margin_m: float = 0.02  # points this near the arm's primitives are the arm
    static_margin_m: float = 0.01  # ... and this near the cell's static parts
    # a region reaching farther from its centre is no trained obstacle, nor one whose top is higher above the table;
    # None: the largest obstacle of any kind registered when perception runs (``_trained_obstacle_limits``)
    max_obstacle_radius_m: float | None = None
    max_obstacle_top_m: float | None = None
    # the obstacle kinds returned: the policy's env.sampling.obstacle_kinds (``for_policy``; default the paper's
    # sphere, cylinder, box).  A region no fit of these holds becomes the covering shape of one of them (``_cover``)
    kinds: tuple[str, ...] = SamplingConfig().obstacle_kinds
    use_colour: bool = True  # with RGB, the cube is the red region

    @classmethod
    def for_policy(cls, env_cfg: Any, **changes: Any) -> "PerceptionSettings":
        """The settings for a policy: its env config's obstacle kinds (``policy.env_config()``, an ``EnvConfig``
        or its ``sampling``), the defaults or ``changes`` otherwise."""
        sampling = getattr(env_cfg, "sampling", env_cfg)
        return cls(**{"kinds": tuple(sampling.obstacle_kinds), **changes})


class Detection(NamedTuple):
    """A 2-D detector's box (pixels, OpenCV convention): the YOLO option's output."""

    label: str  # "target" or a shapes.SHAPES name
    box: tuple[float, float, float, float]  # u0, v0, u1, v1
    score: float = 1.0

    @property
    def centre(self) -> tuple[float, float]:
        return ((self.box[0] + self.box[2]) / 2, (self.box[1] + self.box[3]) / 2)


class SceneDetection(NamedTuple):
    """What the deployment loop needs, in the world (URDF base) frame, metres and radians."""

    target_centre: np.ndarray  # (3,) cube centre, for deploy.calibration.validate_target / run_episode
    target_top: np.ndarray  # (3,) top-face centre as seen
    target_yaw: float  # about world z, wrapped to [−π/4, π/4)
    obstacles: list[Obstacle]
    diagnostics: dict[str, Any]


@dataclass
class _Cloud:
    """The valid points of one capture and what every step shares."""

    shape: tuple[int, int]
    valid: np.ndarray  # (H, W) bool
    cam: np.ndarray  # (H, W, 3) camera frame, m (NaN where invalid)
    world: np.ndarray  # (H, W, 3) world frame, m
    fx: float
    fy: float
    height: Any = None  # (H, W) above the table plane, m (set once the table is fitted)
    area: Any = None  # (H, W) footprint on a plane parallel to the table, m²
    normal: Any = None  # table normal, world
    sigma: float = 0.0  # table noise (robust σ), m
    camera: Any = None  # (3,) the camera's position, world
    pitch: float = 0.002  # m, the median pixel footprint's side on the table


# ---------------------------------------------------------------------------------------------- input checks


def check_cloud(cloud_mm: Any) -> np.ndarray:
    """The cloud as float64 (H, W, 3) millimetres, or ``PerceptionError`` naming what is wrong with it."""
    try:
        cloud = np.asarray(cloud_mm, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PerceptionError(f"point cloud is not numeric: {exc}") from None
    if cloud.ndim != 3 or cloud.shape[2] != 3 or min(cloud.shape[:2]) < 8:
        raise PerceptionError(
            f"point cloud must be organized, shape (H, W, 3) with H, W ≥ 8 (the camera's pixel grid), got {cloud.shape}")
    finite = np.isfinite(cloud).all(axis=2)
    zero = finite & (cloud[..., 2] == 0.0)  # depth 0, (0, 0, 0): the RealSense / Open3D "no return"
    if zero.any():
        cloud = np.where(zero[..., None], np.nan, cloud)  # a copy: the caller's array stays as it was
        finite &= ~zero
    n = int(finite.sum())
    if n == 0:
        raise PerceptionError(f"point cloud {cloud.shape} has no valid point (all NaN/inf or (0, 0, 0)): no return "
                              "from the camera")
    if n < 0.05 * finite.size:
        raise PerceptionError(f"point cloud has only {n} valid points of {finite.size} (< 5 %): camera blocked or "
                              "over/under-exposed")
    depth = float(np.median(cloud[finite][:, 2]))
    lo, hi = DEPTH_RANGE_MM
    if not lo <= depth <= hi:
        # (unit, millimetres per unit): a cloud in that unit, read as mm, has its depth × 1/(mm per unit)
        guess = next(((name, f) for name, f in (("metres", 1000.0), ("centimetres", 10.0), ("micrometres", 1e-3))
                      if lo <= depth * f <= hi), None)
        hint = (f"; it looks like {guess[0]}: give the cloud in millimetres (multiply it by {guess[1]:g})"
                if guess else "")
        raise PerceptionError(f"point cloud's median depth is {depth:.4g} (as mm), outside a depth camera's "
                              f"[{lo:g}, {hi:g}] mm over the table{hint}")
    return cloud


def _check_rgb(rgb: Any, shape: tuple[int, int]) -> np.ndarray:
    try:
        image = np.asarray(rgb)
    except (TypeError, ValueError) as exc:  # ragged nested lists
        raise PerceptionError(f"RGB image is not an (H, W, 3) array: {exc}") from None
    if image.shape != (*shape, 3):
        raise PerceptionError(f"RGB image must be (H, W, 3) = {(*shape, 3)} like the cloud, got {image.shape}")
    if image.dtype == np.uint8:
        return image.astype(np.float64) / 255.0
    if image.dtype.kind not in "biuf":
        raise PerceptionError(f"RGB image must be uint8 or floats in [0, 1], got dtype {image.dtype}")
    image = image.astype(np.float64)
    if not np.isfinite(image).all() or image.min() < 0 or image.max() > 1.0 + 1e-9:
        raise PerceptionError("RGB image must be uint8 or floats in [0, 1]")
    return image


def _check_target_size(target_size: Any) -> np.ndarray:
    try:
        size = np.asarray(target_size, dtype=float)
    except (TypeError, ValueError) as exc:
        raise PerceptionError(f"target_size {target_size!r} must be the cube's 3 full extents in m: {exc}") from None
    if size.shape != (3,) or not np.isfinite(size).all() or (size <= 0).any():
        raise PerceptionError(f"target_size {target_size!r} must be the cube's 3 full extents in m (finite, > 0)")
    return size


def _check_kinds(kinds: Any) -> None:
    if isinstance(kinds, str) or not kinds or any(k not in shapes.BY_NAME for k in kinds):
        raise PerceptionError(f"obstacle kinds {kinds!r} must be some of {', '.join(shapes.NAMES)} (the policy's "
                              "env.sampling.obstacle_kinds)")


def _check_box(det: Any) -> None:
    box = getattr(det, "box", None)
    try:
        ok = len(box) == 4 and all(math.isfinite(float(x)) for x in box)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise PerceptionError(f"detection {det!r}: its box must be 4 finite pixel coordinates (u0, v0, u1, v1)")


def _intrinsics_from_cloud(cam: np.ndarray, valid: np.ndarray) -> tuple[float, float]:
    """fx, fy (px) recovered from the organized cloud itself: x/z grows by 1/fx per column, y/z by 1/fy per row."""
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = cam[..., :2] / cam[..., 2:3]
    out = []
    for step in (ratio[:, 1:, 0] - ratio[:, :-1, 0], ratio[1:, :, 1] - ratio[:-1, :, 1]):
        step = step[np.isfinite(step)]
        if step.size < 10:
            raise PerceptionError("cannot recover the camera's focal length from the cloud (too few neighbouring valid pixels)")
        slope = float(np.median(step))
        if not slope > 0:
            raise PerceptionError("the cloud's x/y do not grow with the pixel column/row: not an organized camera cloud")
        out.append(1.0 / slope)
    return out[0], out[1]


# ---------------------------------------------------------------------------------------------- table


class CalibrationMismatch(PerceptionError):
    """The table does not come out where the scene puts it through this calibration: the calibration is not this
    camera's (or the camera was moved since it was calibrated)."""


def table_height_mode(world_z: np.ndarray) -> float | None:
    """The height (world z, m) of the largest level surface in view: the mode of the points' heights in 5-mm
    bins within ±0.5 m of the table (the table fills most of the view), refined by the median of the points near
    it, or None when nothing lies there."""
    top = SCENE.table.top_z
    z = world_z[np.abs(world_z - top) < 0.5]
    if len(z) < 50:
        return None
    counts, edges = np.histogram(z, bins=200, range=(top - 0.5, top + 0.5))
    i = int(np.argmax(counts))
    mode = (edges[i] + edges[i + 1]) / 2
    return float(np.median(z[np.abs(z - mode) < 0.005]))  # refined within the bin's neighbours


def _mismatch(found: str, settings: PerceptionSettings) -> CalibrationMismatch:
    return CalibrationMismatch(
        f"through this calibration {found} (allowed: ±{settings.max_table_offset_m * 1000:g} mm, "
        f"{settings.max_plane_tilt_deg:g}° from level): the calibration does not match this camera (another "
        "camera's file, the camera moved since, or the wrong --calibration-units / --base-z-offset); calibrate "
        "again (python -m sagrasp_jax.calibrate)")


def fit_table(world: np.ndarray, valid: np.ndarray, settings: PerceptionSettings) -> tuple[np.ndarray, float, float, int]:
    """Robust plane z = a·x + b·y + c through the table's points: (normal, offset d with n·p = d, σ, inliers).

    This is also the check of the calibration against the scene: the plane must come out at the table's known
    height (within ``max_table_offset_m`` under the workspace centre) and level (``max_plane_tilt_deg``), else
    ``CalibrationMismatch`` names the measured offset and tilt."""
    pts = world[valid]
    near = np.abs(pts[:, 2] - SCENE.table.top_z) < settings.plane_band_m
    if near.sum() < max(50, settings.min_plane_fraction * len(pts)):
        mode = table_height_mode(pts[:, 2])
        if mode is not None and abs(mode - SCENE.table.top_z) >= settings.plane_band_m:
            raise _mismatch(f"the largest level surface in view (the table) comes out {1000 * (mode - SCENE.table.top_z):+.0f} "
                            f"mm from the table's height z = {SCENE.table.top_z:g} m", settings)
        raise PerceptionError(
            f"no table plane within {settings.plane_band_m * 1000:.0f} mm of z = {SCENE.table.top_z:g} m in the world frame "
            f"({int(near.sum())} of {len(pts)} points): wrong calibration or base_z_offset?")
    stride = max(1, len(pts) // PLANE_POINTS)
    pts = pts[::stride]  # a plane needs no more than PLANE_POINTS; the fit is the pipeline's costliest step otherwise
    in_band = np.abs(pts[:, 2] - SCENE.table.top_z) < settings.plane_band_m
    for _ in range(4):  # fit the band, σ from the fit's residuals there (MAD), the band narrowed to 3 σ
        sel = pts[in_band]
        coef, *_ = np.linalg.lstsq(np.c_[sel[:, 0], sel[:, 1], np.ones(len(sel))], sel[:, 2], rcond=None)
        res = pts[:, 2] - (coef[0] * pts[:, 0] + coef[1] * pts[:, 1] + coef[2])
        r_in = res[in_band]
        sigma = max(1.4826 * float(np.median(np.abs(r_in - np.median(r_in)))), 2e-5)
        in_band = np.abs(res) < max(3.0 * sigma, 0.001)
        if in_band.sum() < 3:
            break
    inliers = int(in_band.sum()) * stride
    if inliers < settings.min_plane_fraction * len(pts) * stride:
        raise PerceptionError(f"the table plane holds only about {inliers} of {len(pts) * stride} points (< "
                              f"{settings.min_plane_fraction:.0%}): is the camera looking at the table?")
    normal = np.array([-coef[0], -coef[1], 1.0])
    norm = float(np.linalg.norm(normal))
    normal /= norm
    tilt = math.degrees(math.acos(min(1.0, normal[2])))
    x0, y0 = WORKSPACE_CENTRE
    offset = coef[0] * x0 + coef[1] * y0 + coef[2] - SCENE.table.top_z
    if tilt > settings.max_plane_tilt_deg or abs(offset) > settings.max_table_offset_m:
        raise _mismatch(f"the table comes out {1000 * offset:+.1f} mm from its height under the workspace centre and "
                        f"tilted {tilt:.2f}° from level in the world frame", settings)
    return normal, float(coef[2] / norm), sigma, inliers


# ---------------------------------------------------------------------------------------------- masks and regions


def _near_primitives(points: np.ndarray, kinds: np.ndarray, pos: np.ndarray, rot: np.ndarray, size: np.ndarray,
                     margin: float) -> np.ndarray:
    """(N,) bool: points within ``margin`` of any of the primitives (robot.py's size convention)."""
    hit = np.zeros(len(points), bool)
    for k, p, r, s in zip(kinds, pos, rot, size):
        hit |= geometry.point_distance(np, int(k), points, p, r, s) < margin
    return hit


def _robot_primitives(model: RobotModel, q: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    q = np.asarray(q, dtype=float)
    if q.shape != (model.dof,) or not np.isfinite(q).all():
        raise PerceptionError(f"robot joints must be {model.dof} finite values, got {q!r}")
    pos, rot = primitive_poses(np, model, forward_kinematics(np, model, q))
    return model.prim_kind, pos, rot, model.prim_size


def label_regions(mask: np.ndarray, points: np.ndarray, max_gap: float, valid: np.ndarray | None = None,
                  cam_z: np.ndarray | None = None, pitch: np.ndarray | None = None, max_slope: float = math.inf,
                  noise: float = 0.0, skip_gap: float | None = None) -> np.ndarray:
    """Connected regions of ``mask`` (H, W) on the image grid.  4-neighbours are joined when their points
    (H, W, 3) are within ``max_gap`` and, given their camera depths ``cam_z`` and pixel pitches ``pitch``
    (m per pixel at that depth), when the depth changes by at most ``max_slope`` pitches plus 4·√2 σ of
    ``noise``: a steeper step is an occluding edge (a sphere over a box below) or a side seen edge-on,
    whose strip then falls apart into fragments.  Pixels two apart in a row or column are joined the same
    way when the one between them has no return (``valid`` False: a pixel the camera dropped does not
    split a surface), within ``skip_gap`` (default ``max_gap``).  Labels (H, W), −1 outside, regions
    numbered 0.. in order of their smallest pixel index.  Union-find by hooking roots and pointer jumping,
    all in NumPy array operations."""
    h, w = mask.shape
    index = np.full((h, w), -1, dtype=np.int64)
    n = int(mask.sum())
    index[mask] = np.arange(n)
    dropped = ~valid if valid is not None else np.zeros((h, w), bool)
    a_list, b_list = [], []
    for dy, dx in ((0, 1), (1, 0), (0, 2), (2, 0)):
        da, db = index[: h - dy, : w - dx], index[dy:, dx:]
        ok = (da >= 0) & (db >= 0)
        if dy + dx == 2:
            ok &= dropped[dy // 2 : h - dy // 2, dx // 2 : w - dx // 2]
        gap = max_gap if dy + dx == 1 or skip_gap is None else skip_gap
        near = np.linalg.norm(points[: h - dy, : w - dx][ok] - points[dy:, dx:][ok], axis=-1) < gap
        if cam_z is not None and pitch is not None and math.isfinite(max_slope):
            step = np.abs(cam_z[: h - dy, : w - dx][ok] - cam_z[dy:, dx:][ok])
            near &= step <= max_slope * (dy + dx) * pitch[: h - dy, : w - dx][ok] + 4.0 * math.sqrt(2.0) * noise
        a_list.append(da[ok][near])
        b_list.append(db[ok][near])
    a, b = np.concatenate(a_list), np.concatenate(b_list)
    parent = np.arange(n)
    while True:
        ra, rb = parent[a], parent[b]
        differ = ra != rb
        if not differ.any():
            break
        lo, hi = np.minimum(ra[differ], rb[differ]), np.maximum(ra[differ], rb[differ])
        np.minimum.at(parent, hi, lo)
        while True:
            jumped = parent[parent]
            if np.array_equal(jumped, parent):
                break
            parent = jumped
    _, compact = np.unique(parent, return_inverse=True)
    labels = np.full((h, w), -1, dtype=np.int64)
    labels[mask] = compact
    return labels


# ---------------------------------------------------------------------------------------------- 2-D outline maths
# (convex_hull, min_area_rect, wrap and the other 2-D fits: task/point_fits.py)


def _grown_sides(sides: tuple[float, float], area: float) -> tuple[float, float]:
    """Sides of a rectangle grown by the same δ on both so that its area is ``area``: a hull through pixel
    centres falls about a pixel short of the true outline, the pixels' summed footprint does not."""
    l1, l2 = sides
    disc = (l1 + l2) ** 2 - 4.0 * (l1 * l2 - area)
    delta = (-(l1 + l2) + math.sqrt(max(disc, 0.0))) / 2.0
    return l1 + delta, l2 + delta


# ---------------------------------------------------------------------------------------------- region features


class _Region(NamedTuple):
    label: int
    pixels: np.ndarray  # (N, 2) row, col
    world: np.ndarray  # (N, 3)
    height: np.ndarray  # (N,)
    area: np.ndarray  # (N,) footprint on a plane parallel to the table
    top: float  # robust top height above the table
    top_mask: np.ndarray  # (N,) bool: the points within the tolerance of the top
    touches_border: bool
    occluded: np.ndarray  # (N, 4) bool: an occluder next to the pixel in each of DIRECTIONS (occluder_dirs)


DIRECTIONS = ((0, 1), (0, -1), (1, 0), (-1, 0))  # (dy, dx) of the 4-neighbours, in the order of occluder_dirs


def occluder_dirs(cam_z: np.ndarray, labels: np.ndarray, valid: np.ndarray, jump: float) -> np.ndarray:
    """(H, W, 4) bool: in each of ``DIRECTIONS``, the neighbouring pixel (or, when the camera dropped it,
    the one beyond) sees something of another label (another region, the arm, a masked part) nearer by
    more than ``jump``: an occluder hiding the rest of this pixel's object on that side."""
    h, w = cam_z.shape
    z = np.where(valid, cam_z, np.inf)
    zp = np.pad(z, 2, constant_values=np.inf)
    lp = np.pad(labels, 2, constant_values=-2)
    vp = np.pad(valid, 2, constant_values=True)
    out = np.zeros((h, w, 4), bool)
    for k, (dy, dx) in enumerate(DIRECTIONS):
        for step in (1, 2):
            sl = (slice(2 + step * dy, 2 + step * dy + h), slice(2 + step * dx, 2 + step * dx + w))
            hit = (lp[sl] != labels) & (zp[sl] < z - jump)
            if step == 2:  # only across a dropped pixel
                hit &= ~vp[2 + dy : 2 + dy + h, 2 + dx : 2 + dx + w]
            out[..., k] |= hit
    return out


def _regions(cloud: _Cloud, labels: np.ndarray, min_area: float, top_tol: float) -> list[_Region]:
    """The regions whose footprint area reaches ``min_area`` (smaller ones are noise), in label order."""
    rows, cols = np.nonzero(labels >= 0)
    lab = labels[rows, cols]
    area = np.bincount(lab, weights=np.nan_to_num(cloud.area[rows, cols]), minlength=int(labels.max()) + 1)
    keep = np.isin(lab, np.nonzero(area >= min_area)[0])
    rows, cols, lab = rows[keep], cols[keep], lab[keep]
    order = np.argsort(lab, kind="stable")
    rows, cols, lab = rows[order], cols[order], lab[order]
    starts = np.r_[0, np.nonzero(np.diff(lab))[0] + 1, len(lab)]
    hidden = occluder_dirs(cloud.cam[..., 2], labels, cloud.valid, OCCLUDER_JUMP_M)
    return [_region(cloud, int(lab[a]), rows[a:b], cols[a:b], top_tol, hidden[rows[a:b], cols[a:b]])
            for a, b in zip(starts[:-1], starts[1:]) if b > a]


def _region(cloud: _Cloud, label: int, rows: np.ndarray, cols: np.ndarray, top_tol: float,
            occluded: np.ndarray) -> _Region:
    world = cloud.world[rows, cols]
    height = cloud.height[rows, cols]
    top = _top_height(height, top_tol)
    h, w = cloud.shape
    border = bool(rows.min() == 0 or cols.min() == 0 or rows.max() == h - 1 or cols.max() == w - 1)
    return _Region(label, np.c_[rows, cols], world, height, cloud.area[rows, cols], top,
                   height >= top - top_tol, border, occluded)


def border_edges(pixels: np.ndarray, valid: np.ndarray) -> list[str]:
    """The image edges ("left", "right", "top", "bottom") that a set of pixels (N, 2) (row, col) touches: a
    pixel on the border row or column, or one pixel in from it with the border pixel dropped (the camera's
    image ends there, so what lies beyond is unseen).  Left and right are the image's (columns 0 and W − 1)."""
    h, w = valid.shape
    r, c = pixels[:, 0], pixels[:, 1]
    out = []
    for name, at, inner, line in (("left", c == 0, c == 1, (r, 0)), ("right", c == w - 1, c == w - 2, (r, w - 1)),
                                  ("top", r == 0, r == 1, (0, c)), ("bottom", r == h - 1, r == h - 2, (h - 1, c))):
        if at.any() or (inner & ~valid[line]).any():
            out.append(name)
    return out


def _top_height(height: np.ndarray, tol: float) -> float:
    """A region's top above the table, robust to noise: the median of the points within 4/3·tol below
    its 98th height percentile (noise-free: the top face itself; with noise σ and tol = 3 σ, nearly all
    of the top face's points and few of anything else, so the median is the face's height)."""
    if len(height) < 20:
        return float(height.max())
    high = float(np.percentile(height, 98))
    return float(np.median(height[height >= high - 4.0 / 3.0 * tol]))


def _outside(pixels: np.ndarray) -> np.ndarray:
    """(N, 4) bool: for pixels (N, 2) (row, col), whether the 4-neighbour in each of ``DIRECTIONS`` lies
    outside the set; the set's outline is the pixels with any (the hull needs no others)."""
    lo = pixels.min(axis=0)
    grid = np.zeros(tuple(pixels.max(axis=0) - lo + 3), bool)
    r, c = pixels[:, 0] - lo[0] + 1, pixels[:, 1] - lo[1] + 1
    grid[r, c] = True
    return np.stack([~grid[r + dy, c + dx] for dy, dx in DIRECTIONS], axis=1)


class TopFace(NamedTuple):
    """A region's flat top as seen (world frame, m)."""

    centroid: np.ndarray  # (3,) area-weighted centroid of its points
    area: float  # summed pixel footprints, m²
    centre_xy: np.ndarray  # (2,) the rectangle's (unoccluded: the centroid's)
    sides: tuple[float, float]  # the rectangle's sides, along ``angle`` and across
    angle: float  # rad, of the first side
    outline_xy: np.ndarray  # (K, 2) outline points
    outline_hidden: np.ndarray  # (K,) bool: next to a nearer occluder on an outward side
    outline_rim: np.ndarray  # (K,) bool: next to the face's true edge (its side, the table) on an outward side
    pitch: float  # m, typical pixel footprint side on the face

    @property
    def occluded(self) -> bool:
        return int(self.outline_hidden.sum()) >= 2

    @property
    def rim_xy(self) -> np.ndarray:
        """The outline points on the face's true edge (all of them when too few are)."""
        return self.outline_xy[self.outline_rim] if self.outline_rim.sum() >= 5 else self.outline_xy


def _top_face(region: _Region) -> TopFace:
    """The region's top face: centroid, area, outline and minimum-area rectangle.  Unoccluded, the
    rectangle's sides are grown to the face's measured area (a hull through pixel centres falls a pixel
    short) and its centre is the centroid; with part of the face hidden behind a nearer object the area
    and centroid are short of it, so the rectangle is the visible outline's, grown by a pixel."""
    top = region.top_mask
    pts, wts = region.world[top], region.area[top]
    centroid = (pts * wts[:, None]).sum(axis=0) / wts.sum()
    area = float(wts.sum())
    outside = _outside(region.pixels[top])
    edge = outside.any(axis=1)
    occluder = region.occluded[top][edge]
    outline = pts[edge, :2]
    hidden = (outside[edge] & occluder).any(axis=1)
    rim = (outside[edge] & ~occluder).any(axis=1)
    rect_centre, sides, angle = min_area_rect(outline)
    pitch = math.sqrt(float(np.median(wts)))
    face = TopFace(centroid, area, centroid[:2].copy(), _grown_sides(sides, area), angle, outline, hidden, rim, pitch)
    if face.occluded:
        face = face._replace(centre_xy=rect_centre, sides=(sides[0] + pitch, sides[1] + pitch))
    return face


def _red_count(rgb: np.ndarray, region: _Region, margin: float) -> int:
    """The region's red pixels: r − max(g, b) ≥ ``margin``."""
    colour = rgb[region.pixels[:, 0], region.pixels[:, 1]]
    return int((colour[:, 0] - np.maximum(colour[:, 1], colour[:, 2]) >= margin).sum())


# ---------------------------------------------------------------------------------------------- obstacle fits


class ObstacleFit(NamedTuple):
    kind: str
    centre: np.ndarray  # (3,) world
    size: np.ndarray  # (3,) MuJoCo convention
    yaw: float
    residual: float  # m: RMS distance of the region's points to the fitted surface (trimmed)
    conservative: bool = False  # a covering shape of the visible points (``_cover``), not a fit of the object


def _surface_residual(kind: str, centre: np.ndarray, size: np.ndarray, yaw: float, pts: np.ndarray) -> float:
    """Trimmed RMS (best 90 %) of |signed distance| from the points to the fitted shape's surface."""
    shape = shapes.BY_NAME[kind]
    d = np.abs(shapes.sdf(np, shape.id, centre, np.asarray(yaw), size, pts))
    d = np.sort(d)[: max(1, int(0.9 * len(d)))]
    return float(np.sqrt(np.mean(d**2)))


def fit_obstacle(region: _Region, plane_z: float, kinds: Sequence[str]) -> ObstacleFit:
    """The best-fitting kind for a region and its pose and size: each kind's own fit (its registry entry's
    ``perception.fit``), the one whose surface lies nearest the points (smallest residual) wins; when that is a
    flat-topped kind and another was fitted too, the top's outline decides between them (``top_misfit``)."""
    pts = region.world
    face = _top_face(region)
    seen = shapes.Seen(pts, region.area, region.height, region.top, plane_z, face)  # plane_z: the table under it
    fits: list[ObstacleFit] = []
    for kind in kinds:
        if kind not in shapes.BY_NAME:
            raise PerceptionError(f"unknown obstacle kind {kind!r}; known: {', '.join(shapes.NAMES)}")
        found = shapes.BY_NAME[kind].perception.fit(seen)
        if found is None:
            continue  # the points cannot be this kind (a "sphere" reaching into the table)
        centre, size, yaw = found
        fits.append(ObstacleFit(kind, centre, size, yaw, _surface_residual(kind, centre, size, yaw, pts)))
    if not fits:
        raise PerceptionError("no obstacle kind fits a region")
    best = min(fits, key=lambda f: f.residual)
    flat = [f for f in fits if shapes.BY_NAME[f.kind].perception.top_misfit is not None]
    if len(flat) >= 2 and any(f is best for f in flat):
        best = min(flat, key=lambda f: shapes.BY_NAME[f.kind].perception.top_misfit(face))
    return best


# ---------------------------------------------------------------------------------------------- the pipeline


def _prepare(cloud_mm: Any, calibration: CameraCalibration, settings: PerceptionSettings) -> _Cloud:
    cloud = check_cloud(cloud_mm)
    valid = np.isfinite(cloud).all(axis=2)
    cam = np.where(valid[..., None], cloud / 1000.0, np.nan)
    fx, fy = _intrinsics_from_cloud(cam, valid)
    world = calibration.cam_to_base(np.where(valid[..., None], cam, 0.0))
    world[~valid] = np.nan
    data = _Cloud(valid.shape, valid, cam, world, fx, fy, camera=np.asarray(calibration.camera_position, float))
    normal, offset, sigma, _ = fit_table(world, valid, settings)
    data.normal, data.sigma = normal, sigma
    data.height = world @ normal - offset
    # each pixel's footprint on a plane parallel to the table: z²/(fx·fy·|n·r|), r the ray with z = 1
    n_cam = calibration.matrix[:3, :3].T @ normal
    z = cam[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.abs((cam / z[..., None]) @ n_cam)
        data.area = z**2 / (fx * fy * cos)
    data.pitch = math.sqrt(float(np.median(data.area[valid])))
    return data


def _object_mask(data: _Cloud, settings: PerceptionSettings, robot_q: Any, model: RobotModel | None) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        above = data.valid & (data.height > max(settings.min_height_m, 5.0 * data.sigma))
    idx = np.nonzero(above)
    pts = data.world[idx]
    drop = _near_primitives(pts, *SCENE.static_arrays(), settings.static_margin_m)
    if robot_q is not None:
        drop |= _near_primitives(pts, *_robot_primitives(model or load_robot(), robot_q), settings.robot_margin_m)
    above[idx[0][drop], idx[1][drop]] = False
    return above


def point_at_pixel(cloud_mm: Any, u: float, v: float, window: int = 2) -> np.ndarray:
    """The paper's step: a pixel (YOLO's box centre) -> its camera-frame point (mm), the median of the
    valid points in a (2·window + 1)² neighbourhood; ``PerceptionError`` if none is valid."""
    cloud = check_cloud(cloud_mm)
    h, w = cloud.shape[:2]
    if not all(isinstance(x, (int, float, np.integer, np.floating)) and math.isfinite(x) for x in (u, v)):
        raise PerceptionError(f"pixel ({u!r}, {v!r}) must be two finite numbers (u, v)")
    if not isinstance(window, (int, np.integer)) or window < 0:
        raise PerceptionError(f"window {window!r} must be a whole number of pixels ≥ 0")
    r, c = int(round(v)), int(round(u))
    if not (0 <= r < h and 0 <= c < w):
        raise PerceptionError(f"pixel ({u:.1f}, {v:.1f}) is outside the {w} × {h} image")
    patch = cloud[max(0, r - window) : r + window + 1, max(0, c - window) : c + window + 1].reshape(-1, 3)
    patch = patch[np.isfinite(patch).all(axis=1)]
    if len(patch) == 0:
        raise PerceptionError(f"no valid depth within {window} px of pixel ({u:.1f}, {v:.1f})")
    return np.median(patch, axis=0)


def _cube_candidates(regions: list[_Region], rgb: np.ndarray | None, detections: Sequence[Detection] | None,
                     labels: np.ndarray, target_size: np.ndarray, settings: PerceptionSettings) -> tuple[list[int], str]:
    """Indices (into ``regions``) of the cube candidates and how they were chosen."""
    if detections is not None:
        chosen = []
        for det in detections:
            if det.label != "target":
                continue
            u0, v0, u1, v1 = (int(round(x)) for x in det.box)
            box = labels[max(0, v0) : v1 + 1, max(0, u0) : u1 + 1]
            inside = box[box >= 0]
            if inside.size:
                label = int(np.bincount(inside).argmax())
                chosen += [i for i, reg in enumerate(regions) if reg.label == label and i not in chosen]
        return chosen, "detector"
    if rgb is not None and settings.use_colour:
        red = [_red_count(rgb, reg, settings.red_margin) for reg in regions]
        alone = [i for i, reg in enumerate(regions) if red[i] >= settings.red_fraction * len(reg.world)]
        merged = [i for i, reg in enumerate(regions) if i not in alone and red[i] >= MIN_RED_PIXELS]
        if merged:  # red pixels on (or against) another object: a cube, but not on the table
            reg = regions[merged[0]]
            raise PerceptionError(
                f"cube not standing on the table: {red[merged[0]]} red pixels are part of an object whose top is "
                f"{reg.top * 1000:.0f} mm above the table at world ({reg.world[:, 0].mean():.3f}, "
                f"{reg.world[:, 1].mean():.3f}) m (the cube on or against it?)")
        return alone, "colour"
    out = []
    side, height = float(max(target_size[0], target_size[1])), float(target_size[2])
    for i, reg in enumerate(regions):
        if abs(reg.top - height) > settings.cube_height_tol_m or reg.top_mask.sum() < 3:
            continue
        if all(abs(s - side) <= settings.cube_side_tol * side for s in _top_face(reg).sides):
            out.append(i)
    return out, "size"


def detect_scene(cloud_mm: Any, rgb: Any = None, calibration: CameraCalibration | None = None,
                 target_size: Sequence[float] | None = None, *, robot_q: Any = None,
                 detections: Sequence[Detection] | None = None, settings: PerceptionSettings | None = None,
                 robot_model: RobotModel | None = None) -> SceneDetection:
    """The cube and the obstacles in one capture (module docstring); ``PerceptionError`` when the
    capture cannot give exactly one cube standing on the table.

    ``cloud_mm``: (H, W, 3) camera frame, mm, NaN = no return.  ``rgb``: the registered image (H, W, 3),
    uint8 or floats in [0, 1], or None.  ``calibration``: camera -> world (default the paper's).
    ``target_size``: the cube's full extents, m (default ``env.sampling.target_size``).  ``robot_q``: the
    arm's joints when it may be in view.  ``detections``: a 2-D detector's boxes (YOLO) choosing the cube."""
    t0 = time.perf_counter()
    settings = settings or PerceptionSettings()
    if settings.max_obstacle_radius_m is None or settings.max_obstacle_top_m is None:
        reach, top = _trained_obstacle_limits()  # every registered kind's largest, now
        settings = dataclasses.replace(
            settings, max_obstacle_radius_m=reach if settings.max_obstacle_radius_m is None else settings.max_obstacle_radius_m,
            max_obstacle_top_m=top if settings.max_obstacle_top_m is None else settings.max_obstacle_top_m)
    calibration = calibration or CameraCalibration.default()
    size = _check_target_size(target_size if target_size is not None else SamplingConfig().target_size)
    _check_kinds(settings.kinds)
    for det in detections or ():
        _check_box(det)
    data = _prepare(cloud_mm, calibration, settings)
    image = _check_rgb(rgb, data.shape) if rgb is not None else None
    mask = _object_mask(data, settings, robot_q, robot_model)
    cam_z = np.nan_to_num(data.cam[..., 2])
    labels = label_regions(mask, np.nan_to_num(data.world), settings.max_gap_m, data.valid, cam_z,
                           cam_z / data.fx, settings.max_slope, data.sigma)
    top_tol = max(settings.top_tol_m, 3.0 * data.sigma)
    regions, fragments = [], 0
    for reg in _regions(data, labels, settings.min_region_m2, top_tol):
        if min(_top_face(reg).sides) < settings.min_top_side_m:
            fragments += 1  # a steep side cut off its top by dropped pixels, an edge's flying pixels
            continue
        regions.append(reg)
    regions = _merge_sides(data, regions, top_tol)
    found, how = _cube_candidates(regions, image, detections, labels, size, settings)
    if not found:
        raise PerceptionError(f"no cube found ({how}; {len(regions)} object region(s) above the table): is the cube "
                              "in view and not hidden by the arm?")
    if len(found) > 1:
        where = "; ".join(f"top {1000 * regions[i].top:.0f} mm at world ({regions[i].world[:, 0].mean():.3f}, "
                          f"{regions[i].world[:, 1].mean():.3f}) m" for i in found)
        raise PerceptionError(f"{len(found)} cube candidates ({how}): {where}; exactly one cube must be in the cell")
    cube = regions[found[0]]
    face = _top_face(cube)
    sides = face.sides
    side, height = float(max(size[0], size[1])), float(size[2])
    cut = border_edges(cube.pixels[cube.top_mask], data.valid)
    if cut:
        edges = f"{' and '.join(cut)} edge{'s' if len(cut) > 1 else ''}"
        raise PerceptionError(f"the cube's top face is cut by the image border ({edges}); move the camera or the cube "
                              "(its centre and yaw need the whole face)")
    if face.occluded:
        raise PerceptionError(
            f"the cube's top face is partly hidden ({int(face.outline_hidden.sum())} of its outline pixels border a "
            "nearer object: the arm or an obstacle between it and the camera), so its centre cannot be measured; "
            "capture with the arm out of view")
    problems = []
    if abs(cube.top - height) > settings.cube_height_tol_m:
        problems.append(f"its top is {cube.top * 1000:.1f} mm above the table (standing: {height * 1000:.0f} ± "
                        f"{settings.cube_height_tol_m * 1000:.0f} mm)")
    if not all(abs(s - side) <= settings.cube_side_tol * side for s in sides):
        problems.append(f"its top face is {sides[0] * 1000:.0f} × {sides[1] * 1000:.0f} mm (standing: "
                        f"{size[0] * 1000:.0f} × {size[1] * 1000:.0f} mm)")
    if problems:
        raise PerceptionError("cube not standing on the table: " + "; ".join(problems))
    top_point = np.array([face.centre_xy[0], face.centre_xy[1], face.centroid[2]])
    target = detected_top_to_cube_centre(top_point, height / 2)
    yaw = wrap(face.angle, math.pi / 2)
    obstacles, fits = [], []
    leftovers, strays = _leftovers(data, mask, regions, settings, top_tol, int(labels.max()) + 1)
    cube_fit = ObstacleFit(shapes.BOX_SHAPE.name, np.asarray(target, float), size / 2, yaw, 0.0)
    parts, held = _obstacle_parts(data, [reg for i, reg in enumerate(regions) if i != found[0]], leftovers, strays,
                                  cube_fit, top_tol, settings)
    for reg, fit, pieces in parts:
        reach = float(np.max(np.linalg.norm(reg.world[:, :2] - reg.world[:, :2].mean(axis=0), axis=1)))
        if reg.top > settings.max_obstacle_top_m:
            raise PerceptionError(
                f"an object {reg.top:.2f} m tall (world ({reg.world[:, 0].mean():.2f}, {reg.world[:, 1].mean():.2f}) m) "
                f"is taller than any trained obstacle ({settings.max_obstacle_top_m:.2f} m): the arm in view without "
                "robot_q, or something that does not belong in the cell")
        if reach > settings.max_obstacle_radius_m:
            raise PerceptionError(
                f"an object reaching {reach:.2f} m from its centre (world ({reg.world[:, 0].mean():.2f}, "
                f"{reg.world[:, 1].mean():.2f}) m) is larger than any trained obstacle: the arm in view without "
                "robot_q, or something that does not belong in the cell")
        fits.append({"kind": fit.kind, "residual_mm": 1000 * fit.residual, "points": len(reg.world),
                     "touches_border": reg.touches_border, "occluded_px": int(reg.occluded.any(axis=1).sum()),
                     "conservative": fit.conservative, "pieces": pieces})
        obstacles.append(Obstacle(fit.kind, tuple(float(v) for v in fit.centre), tuple(float(v) for v in fit.size),
                                  float(fit.yaw)))
    diagnostics = {
        "plane_normal": data.normal.tolist(), "plane_sigma_mm": 1000 * data.sigma, "valid_points": int(data.valid.sum()),
        "regions": len(regions), "fragments": fragments, "leftovers": len(leftovers), "leftovers_held": held,
        "cube_by": how, "cube_points": len(cube.world), "cube_top_points": int(cube.top_mask.sum()),
        "cube_top_mm": 1000 * cube.top, "cube_face_mm": [1000 * sides[0], 1000 * sides[1]],
        "cube_touches_border": cube.touches_border, "cube_outline_hidden_px": int(face.outline_hidden.sum()),
        "obstacles": fits, "seconds": time.perf_counter() - t0,
    }
    return SceneDetection(target, top_point, yaw, obstacles, diagnostics)


def _merged(data: _Cloud, a: _Region, b: _Region, top_tol: float) -> _Region:
    pixels = np.r_[a.pixels, b.pixels]
    return _region(data, a.label, pixels[:, 0], pixels[:, 1], top_tol, np.r_[a.occluded, b.occluded])


def _distance_to_outline(xy: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """(N,) distance from points (N, 2) to a closed polygon's edges (K, 2)."""
    a, b = poly, np.roll(poly, -1, axis=0)
    ab = b - a
    t = np.clip(((xy[:, None] - a[None]) * ab[None]).sum(-1) / np.maximum((ab**2).sum(-1), 1e-18)[None], 0.0, 1.0)
    return np.linalg.norm(xy[:, None] - (a[None] + t[..., None] * ab[None]), axis=-1).min(axis=1)


def _merge_sides(data: _Cloud, regions: list[_Region], top_tol: float) -> list[_Region]:
    """Regions that are the side of a higher one join it: a vertical face seen nearly edge-on breaks off its
    top at the depth step (``max_slope``), and its points then lie, seen from above, on that top's outline
    (≥ 90 % of them within two pixel pitches + 3 mm of the top face's hull).  A lower object merely under
    or beside a higher one spreads over its own footprint instead."""
    regions = list(regions)
    merged = True
    while merged:
        merged = False
        for i, low in enumerate(regions):
            for j, high in enumerate(regions):
                if i == j or not high.top > low.top + top_tol:
                    continue
                face = _top_face(high)
                hull = convex_hull(face.outline_xy)
                if len(hull) < 3:
                    continue
                near = _distance_to_outline(low.world[:, :2], hull) <= 2 * face.pitch + 0.003
                if near.mean() >= 0.9:
                    regions[j] = _merged(data, high, low, top_tol)
                    del regions[i]
                    merged = True
                    break
            if merged:
                break
    return regions


def _leftovers(data: _Cloud, mask: np.ndarray, kept: Sequence[_Region], settings: PerceptionSettings,
               top_tol: float, first_label: int) -> tuple[list[_Region], np.ndarray]:
    """The object pixels no kept region holds (regions under ``min_region_m2``, fragments) clustered again by
    3-D gaps alone (``max_gap_m``, twice that across a dropped pixel; no depth-step test): a steep side seen
    nearly edge-on falls apart into strips a few pixels high (a camera drops many of them: depth edges), and
    where a nearer object hides the top those strips are all that is seen of an obstacle.  The clusters
    reaching ``min_region_m2``, or a quarter of it where the image border or a nearer object cuts them (a
    top's thin rim beyond a sphere; labels from ``first_label`` on), and the pixels (M, 2) of the smaller
    ones (strays: what a fit or cover of a region they belong to must hold too)."""
    rest = mask.copy()
    for reg in kept:
        rest[reg.pixels[:, 0], reg.pixels[:, 1]] = False
    if not rest.any():
        return [], np.zeros((0, 2), int)
    labels = label_regions(rest, np.nan_to_num(data.world), settings.max_gap_m, data.valid,
                           skip_gap=2.0 * settings.max_gap_m)
    clusters = [reg._replace(label=reg.label + first_label)
                for reg in _regions(data, np.where(rest, labels, -1), settings.min_region_m2 / 4, top_tol)
                if reg.area.sum() >= settings.min_region_m2 or reg.touches_border or reg.occluded.any()]
    for reg in clusters:
        rest[reg.pixels[:, 0], reg.pixels[:, 1]] = False
    return clusters, np.argwhere(rest)


def _uncovered(data: _Cloud, fits: Sequence[ObstacleFit], pts: np.ndarray) -> np.ndarray:
    """(N,) bool: the points (N, 3) that none of ``fits`` holds.  A point is held when some point of its
    ray within 4 σ of the depth noise (at least 1 mm) lies inside the shape grown by a pixel's footprint
    (the noise moves points along their rays; pixel centres fall up to half a pitch from an outline)."""
    ray = pts - data.camera
    ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-9)
    slack = max(4.0 * data.sigma, 0.001)
    tol = max(data.pitch, 0.001)
    out = np.ones(len(pts), bool)
    for fit in fits:
        shape = shapes.BY_NAME[fit.kind]
        for t in np.linspace(-slack, slack, 7):
            with np.errstate(invalid="ignore"):
                d = shapes.sdf(np, shape.id, fit.centre, np.asarray(fit.yaw), fit.size, pts + t * ray)
            out &= ~(d <= tol)  # NaN (a failed fit) holds nothing
    return out


def _shape_points(fit: ObstacleFit) -> np.ndarray:
    """Points (K, 3) whose horizontal convex hull holds the fitted shape's footprint and whose highest is its top
    (the kind's ``perception.hull_points``: a box's corners, polygons circumscribing a round kind's circles)."""
    return shapes.BY_NAME[fit.kind].perception.hull_points(fit.centre, fit.size, float(fit.yaw))


def _cover(data: _Cloud, region: _Region, plane_z: float, settings: PerceptionSettings, strays: np.ndarray,
           fit: ObstacleFit | None = None) -> ObstacleFit:
    """A conservative obstacle of one of ``settings.kinds`` holding every visible point of ``region``, of the
    strays that belong with it (``_strays_of``) and the shape ``fit`` guessed for it (its best guess of what
    is hidden) where that is no larger than a trained obstacle: the points' minimum-area rectangle grown by
    half a pixel and the noise, from the table up to the highest point (what a nearer object hides of it may
    reach down to the table anywhere under what is seen).  Each kind's shape around that box: the box itself,
    the upright cylinder round it, the sphere or the lying capsule through its corners (these two reach into
    the table, which holds nothing anyway); the smallest allowed one (by volume) is returned."""
    pts = np.r_[region.world, _strays_of(data, strays, region, settings)]
    if fit is not None:
        corners = _shape_points(fit)
        reach = np.max(np.linalg.norm(corners[:, :2] - fit.centre[:2], axis=1))
        if np.isfinite(corners).all() and reach <= settings.max_obstacle_radius_m \
                and np.max(corners[:, 2]) - plane_z <= settings.max_obstacle_top_m:
            pts = np.r_[pts, corners]
    xy = pts[:, :2]
    pitch = math.sqrt(float(np.median(region.area)))
    margin = pitch / 2 + data.sigma
    n, offset = data.normal, float((region.world @ data.normal - region.height).mean())
    top = float(np.max(pts @ n - offset)) + data.sigma
    centre_xy, (a, b), angle = min_area_rect(xy)
    if a == 0.0 and b == 0.0:  # fewer than three distinct points
        centre_xy = xy.mean(axis=0)
        a = b = 2.0 * float(np.max(np.linalg.norm(xy - centre_xy, axis=1)))
    a, b = a + 2 * margin, b + 2 * margin
    half = top / 2
    centre = np.array([centre_xy[0], centre_xy[1], plane_z + half])
    r_round = float(np.max(np.linalg.norm(xy - centre_xy, axis=1))) + margin
    box = shapes.CoverBox(a, b, angle, top, r_round)
    options = {k: shapes.BY_NAME[k].perception.cover(box) for k in settings.kinds}  # kind: (size, yaw, volume)
    kind = min(settings.kinds, key=lambda k: options[k][2])
    size, yaw, _ = options[kind]
    return ObstacleFit(kind, centre, size, yaw, _surface_residual(kind, centre, size, yaw, region.world), True)


def _strays_of(data: _Cloud, strays: np.ndarray, region: _Region, settings: PerceptionSettings) -> np.ndarray:
    """World points (K, 3) of the strays (pixels (M, 2)) that belong with ``region``: no higher than its top
    (a side's strips lie under it; a flying pixel under a floating sphere's rim is not the sphere's) and
    within ``max_gap_m`` of its points in 3-D or next to one of its pixels (8-neighbours: a side seen edge-on
    beyond its top's edge); or, where a nearer object borders it, cut off from it by that object alone (an
    image line from the stray to one of its four nearest such pixels of the region crosses nothing else:
    ``_occluder_between``), no farther from its points than one obstacle reaches (``max_obstacle_radius_m``)
    and as high as it may be (a top's rim seen beyond a sphere that hides the rest of it)."""
    gap = settings.max_gap_m
    if len(strays) == 0:
        return np.zeros((0, 3))
    world = data.world[strays[:, 0], strays[:, 1]]
    pts = region.world
    sample = pts[:: max(1, len(pts) // 2000)]
    near = np.zeros(len(strays), bool)
    flat = np.zeros(len(strays))
    low = data.height[strays[:, 0], strays[:, 1]] <= region.top + max(0.003, 3.0 * data.sigma)
    for a in range(0, len(strays), 500):
        diff = world[a : a + 500][:, None] - sample[None]
        near[a : a + 500] = (diff**2).sum(-1).min(axis=1) <= gap**2
        flat[a : a + 500] = (diff[..., :2] ** 2).sum(-1).min(axis=1)
    lo = region.pixels.min(axis=0) - 1
    grid = np.zeros(tuple(region.pixels.max(axis=0) - lo + 2), bool)
    grid[region.pixels[:, 0] - lo[0], region.pixels[:, 1] - lo[1]] = True
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            r, c = strays[:, 0] + dy - lo[0], strays[:, 1] + dx - lo[1]
            inside = (r >= 0) & (c >= 0) & (r < grid.shape[0]) & (c < grid.shape[1])
            near[inside] |= grid[r[inside], c[inside]]
    near &= low
    edge = region.pixels[region.occluded.any(axis=1)]
    edge = edge[:: max(1, len(edge) // 300)]
    if len(edge) and not near.all():
        far = np.nonzero(~near)[0]
        k = min(4, len(edge))  # lines to its four nearest such pixels: one of them may graze the table
        nearest = np.argpartition(((strays[far][:, None] - edge[None]) ** 2).sum(-1), k - 1, axis=1)[:, :k]
        own = np.zeros(data.shape, bool)
        own[region.pixels[:, 0], region.pixels[:, 1]] = True
        cut_off = _occluder_between(data, own, np.repeat(strays[far], k, axis=0), edge[nearest.reshape(-1)])
        near[far] = cut_off.reshape(-1, k).any(axis=1) & (flat[far] <= settings.max_obstacle_radius_m**2)
    return world[near]


def _fit_part(data: _Cloud, region: _Region, settings: PerceptionSettings, strays: np.ndarray) -> ObstacleFit:
    """The region's obstacle of an allowed kind: the best fit of ``settings.kinds`` (``fit_obstacle``) when it holds
    the visible points (``_uncovered``: all but ``COVER_SHARE`` of them, ``COVER_SHARE_HIDDEN`` of a partly
    hidden one; where a nearer object hides part of it, also the strays that belong with it, ``_strays_of``),
    else the conservative ``_cover``.
    A fit falls short where a nearer object or the image border hides part of the obstacle and what is seen
    does not fix its shape (a side without its top, a rim's short arc), or where the obstacle is of a kind
    the policy was not trained with (a lying capsule fitted as a flat-topped kind)."""
    plane_z = _plane_height(data, region)
    try:
        with np.errstate(invalid="ignore", divide="ignore"):
            fit = fit_obstacle(region, plane_z, settings.kinds)
    except ValueError:  # PerceptionError, LinAlgError: no allowed kind can be fitted to it
        fit = None
    pts = region.world
    if region.occluded.any():
        pts = np.r_[pts, _strays_of(data, strays, region, settings)]
    share = COVER_SHARE_HIDDEN if region.occluded.any() or region.touches_border else COVER_SHARE
    if fit is not None and np.isfinite(fit.centre).all() and np.isfinite(fit.size).all() \
            and _uncovered(data, [fit], pts).mean() <= share:
        return fit
    return _cover(data, region, plane_z, settings, strays, fit)


def _occluder_between(data: _Cloud, own: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """(K,) bool for pixel pairs (K, 2) (row, col): whether the straight image line from ``pa`` to ``pb`` crosses
    only ``own`` pixels (H, W), pixels the camera dropped and pixels nearer than both ends by ``OCCLUDER_JUMP_M``,
    at least one of these: nothing but a nearer object lies between the two."""
    if len(pa) == 0:
        return np.zeros(0, bool)
    cam_z = data.cam[..., 2]
    steps = int(min(np.max(np.abs(pb - pa)), 400))
    if steps < 2:
        return np.zeros(len(pa), bool)
    t = np.linspace(0.0, 1.0, steps + 1)[1:-1]
    line = np.rint(pa[:, None, :] + (pb - pa)[:, None, :] * t[None, :, None]).astype(int)  # (K, S, 2)
    r, c = line[..., 0], line[..., 1]
    skip = own[r, c] | ((r == pa[:, None, 0]) & (c == pa[:, None, 1])) | ((r == pb[:, None, 0]) & (c == pb[:, None, 1]))
    valid = data.valid[r, c]
    z_ref = np.minimum(cam_z[pa[:, 0], pa[:, 1]], cam_z[pb[:, 0], pb[:, 1]])[:, None] - OCCLUDER_JUMP_M
    with np.errstate(invalid="ignore"):
        nearer = valid & (cam_z[r, c] < z_ref) & ~skip
    return (nearer | ~valid | skip).all(axis=1) & nearer.any(axis=1)


def _pieces_of_one(data: _Cloud, a: _Region, b: _Region, tries: int = 12) -> bool:
    """Whether two regions are pieces of one obstacle that a nearer object cuts in two: both border a nearer
    object, and a straight image line between some of the nearest pairs of such pixels crosses nothing but
    the occluder (``_occluder_between``).  Table or another object seen between them keeps them apart."""
    ea, eb = a.pixels[a.occluded.any(axis=1)], b.pixels[b.occluded.any(axis=1)]
    if len(ea) == 0 or len(eb) == 0:
        return False
    ea, eb = ea[:: max(1, len(ea) // 300)], eb[:: max(1, len(eb) // 300)]
    own = np.zeros(data.shape, bool)
    own[a.pixels[:, 0], a.pixels[:, 1]] = True
    own[b.pixels[:, 0], b.pixels[:, 1]] = True
    d2 = ((ea[:, None, :] - eb[None, :, :]) ** 2).sum(-1)
    flat = np.argsort(d2, axis=None)[:tries]
    return bool(_occluder_between(data, own, ea[flat // len(eb)], eb[flat % len(eb)]).any())


def _footprints_touch(data: _Cloud, ra: _Region, fa: ObstacleFit, rb: _Region, fb: ObstacleFit) -> bool:
    """Whether either fit's horizontal footprint reaches (within a pixel and the noise) a point of the other."""
    tol = math.sqrt(float(np.median(np.r_[ra.area, rb.area]))) + data.sigma
    for reg, fit in ((ra, fb), (rb, fa)):
        gap = shapes.footprint_gap(np, shapes.BY_NAME[fit.kind].id, fit.centre, np.asarray(fit.yaw), fit.size,
                                   reg.world[:, :2])
        if np.min(gap) <= tol:
            return True
    return False


def _obstacle_parts(data: _Cloud, regions: list[_Region], leftovers: list[_Region], strays: np.ndarray,
                    cube: ObstacleFit, top_tol: float,
                    settings: PerceptionSettings) -> tuple[list[tuple[_Region, ObstacleFit, int]], int]:
    """Each obstacle with the region it was fitted to and how many pieces that region joins, and the number of
    leftover clusters dropped as parts of something already held.  Strays (``_leftovers``) that the cube or
    a region's own fit holds are theirs; the others are held by the obstacles they belong with (``_strays_of``).

    Every region is fitted (``_fit_part``: a fit of an allowed kind that holds its points, else a covering
    shape).  A leftover cluster (``_leftovers``) is dropped when the cube and the obstacles hold all of its
    points (a side's strips: ``_uncovered``), joins the obstacle holding nearly all of them (its region grows
    and is fitted again), and is otherwise the visible part of an obstacle of its own.  Two parts are then
    one obstacle, joined and fitted again, when (a) a nearer object cuts them apart (``_pieces_of_one``),
    (b) both border a nearer object and their footprints overlap or touch, or (c) they are fitted as the
    same kind with centres within half their smaller size (a cylinder's top crossed by a sphere above it);
    never into something larger than any trained obstacle (the joined region's reach and top)."""
    if len(strays):  # those the cube or a region's own fit holds are theirs (a sphere's rim, a box's side)
        fits = [_fit_part(data, reg, settings, np.zeros((0, 2), int)) for reg in regions]
        world = data.world[strays[:, 0], strays[:, 1]]
        strays = strays[_uncovered(data, [cube, *(f for f in fits if not f.conservative)], world)]
    parts = [(reg, _fit_part(data, reg, settings, strays), 1) for reg in regions]
    dropped = 0
    for reg in leftovers:
        if _uncovered(data, [cube, *(fit for _, fit, _ in parts)], reg.world).mean() <= COVER_SHARE_HIDDEN:
            dropped += 1  # the cube's or an obstacle's side
            continue
        share = [1.0 - _uncovered(data, [fit], reg.world).mean() for _, fit, _ in parts]
        k = int(np.argmax(share)) if share else -1
        if k >= 0 and share[k] >= 1.0 - LEFTOVER_HELD:  # mostly an obstacle's side: it joins that obstacle
            joined = _merged(data, parts[k][0], reg, top_tol)
            parts[k] = (joined, _fit_part(data, joined, settings, strays), parts[k][2])
            dropped += 1
            continue
        parts.append((reg, _fit_part(data, reg, settings, strays), 1))
    merged = True
    while merged:
        merged = False
        for i, j in ((i, j) for i in range(len(parts)) for j in range(i + 1, len(parts))):
            (ra, fa, na), (rb, fb, nb) = parts[i], parts[j]
            scale = 0.5 * min(float(np.max(fa.size[:2])), float(np.max(fb.size[:2])))
            hidden = ra.occluded.any() and rb.occluded.any()
            if not ((fa.kind == fb.kind and np.linalg.norm(fa.centre[:2] - fb.centre[:2]) < scale)
                    or (hidden and (_footprints_touch(data, ra, fa, rb, fb) or _pieces_of_one(data, ra, rb)))):
                continue
            reg = _merged(data, ra, rb, top_tol)
            xy = reg.world[:, :2]
            if reg.top > settings.max_obstacle_top_m \
                    or np.max(np.linalg.norm(xy - xy.mean(axis=0), axis=1)) > settings.max_obstacle_radius_m:
                continue
            parts[i] = (reg, _fit_part(data, reg, settings, strays), na + nb)
            del parts[j]
            merged = True
            break
    return parts, dropped


def _plane_height(data: _Cloud, region: _Region) -> float:
    """World z of the table plane under a region's centroid."""
    n = data.normal
    xy = region.world[:, :2].mean(axis=0)
    d = float((region.world @ n - region.height).mean())  # the plane offset (n·p = d)
    return (d - n[0] * xy[0] - n[1] * xy[1]) / n[2]
