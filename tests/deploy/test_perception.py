"""Perception (deploy.perception) on hand-built clouds, its refusals, and on the twin camera's renders.

The hand-built clouds come from an exact ray caster below (table plane, yawed boxes, upright cylinders,
spheres) at the Mech-Eye's optics scaled to 480 × 300, seen through the paper's calibration: no PyBullet
needed.  The rendered ones come from ``deploy.twin_camera`` (skipped without the twin extra).
"""

from __future__ import annotations

import dataclasses
import math
import zlib

import numpy as np
import pytest

from sagrasp_jax.deploy import perception as P
from sagrasp_jax.task import point_fits
from sagrasp_jax.deploy.calibration import CameraCalibration
from sagrasp_jax.deploy.loop import Obstacle
from sagrasp_jax.task.config import EnvConfig, SamplingConfig

CAL = CameraCalibration.default()
# the Mech-Eye Pro M's intrinsics (deploy.twin_camera.MECH_EYE_PRO_M) scaled to 480 × 300
FX, FY, CX, CY, W, H = 606.37, 606.3325, 239.56, 157.8, 480, 300
RED, WHITE, TABLE = (217, 25, 25), (242, 242, 242), (140, 115, 89)


# ---------------------------------------------------------------------- an exact ray caster


def _box_hits(o: np.ndarray, d: np.ndarray, centre, half, yaw) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> box frame
    ol, dl = rot @ (o - np.asarray(centre)), d @ rot.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-np.asarray(half) - ol) / dl, (np.asarray(half) - ol) / dl
    near = np.nanmax(np.minimum(t1, t2), axis=-1)
    far = np.nanmin(np.maximum(t1, t2), axis=-1)
    return np.where((near <= far) & (near > 0), near, np.inf)


def _cylinder_hits(o, d, centre, radius, half_height) -> np.ndarray:
    oc = o - np.asarray(centre)
    a = d[..., 0] ** 2 + d[..., 1] ** 2
    b = 2 * (oc[0] * d[..., 0] + oc[1] * d[..., 1])
    cc = oc[0] ** 2 + oc[1] ** 2 - radius**2
    disc = b**2 - 4 * a * cc
    t_side = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    z_side = oc[2] + t_side * d[..., 2]
    t_side = np.where(np.abs(z_side) <= half_height, t_side, np.inf)
    t_cap = (half_height - oc[2]) / d[..., 2]
    xy = oc[:2] + t_cap[..., None] * d[..., :2]
    t_cap = np.where((xy**2).sum(-1) <= radius**2, t_cap, np.inf)
    return np.minimum(t_side, t_cap)


def _sphere_hits(o, d, centre, radius) -> np.ndarray:
    oc = o - np.asarray(centre)
    a = (d**2).sum(-1)
    b = 2 * (d @ oc)
    disc = b**2 - 4 * a * (oc @ oc - radius**2)
    return np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)


def _capsule_hits(o, d, centre, radius, half_axis, yaw) -> np.ndarray:
    """A capsule lying with its axis along ``yaw``: its two end spheres and the round body between them."""
    c, s = math.cos(yaw), math.sin(yaw)
    axis = np.array([c, s, 0.0])
    ends = [_sphere_hits(o, d, np.asarray(centre) + k * half_axis * axis, radius) for k in (-1, 1)]
    rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> capsule frame, axis along x
    ol, dl = rot @ (o - np.asarray(centre)), d @ rot.T
    a = dl[..., 1] ** 2 + dl[..., 2] ** 2
    b = 2 * (ol[1] * dl[..., 1] + ol[2] * dl[..., 2])
    disc = b**2 - 4 * a * (ol[1] ** 2 + ol[2] ** 2 - radius**2)
    t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    t = np.where(np.abs(ol[0] + t * dl[..., 0]) <= half_axis, t, np.inf)
    return np.minimum(t, np.minimum(*ends))


def cast(objects, cal=CAL, size=(W, H), fx=FX, fy=FY, cx=CX, cy=CY, labels=False):
    """(cloud_mm, rgb) of the table and ``objects``: ("box", centre, half, yaw, rgb) | ("cylinder", centre,
    radius, half_height, rgb) | ("sphere", centre, radius, rgb) | ("capsule", centre, radius, half_axis, yaw,
    rgb), world frame, m; with ``labels`` also (H, W) the index of the object each pixel sees (−1: the table).
    Rays have camera z = 1, so each hit's parameter is the camera-frame depth."""
    w, h = size
    rays = np.ones((h, w, 3))
    rays[..., 0] = ((np.arange(w) - cx) / fx)[None, :]
    rays[..., 1] = ((np.arange(h) - cy) / fy)[:, None]
    rot, origin = cal.matrix[:3, :3], cal.matrix[:3, 3]
    d = rays @ rot.T
    t = np.where(d[..., 2] < 0, -origin[2] / d[..., 2], np.inf)  # the table, z = 0
    rgb = np.broadcast_to(np.array(TABLE, np.uint8), (h, w, 3)).copy()
    seen = np.full((h, w), -1)
    for i, obj in enumerate(objects):
        kind = obj[0]
        if kind == "box":
            hit = _box_hits(origin, d, obj[1], obj[2], obj[3])
        elif kind == "cylinder":
            hit = _cylinder_hits(origin, d, obj[1], obj[2], obj[3])
        elif kind == "capsule":
            hit = _capsule_hits(origin, d, obj[1], obj[2], obj[3], obj[4])
        else:
            hit = _sphere_hits(origin, d, obj[1], obj[2])
        nearer = hit < t
        t = np.where(nearer, hit, t)
        rgb[nearer] = obj[-1]
        seen[nearer] = i
    cloud = (rays * (1000.0 * t)[..., None]).astype(np.float32)
    cloud[~np.isfinite(t)] = np.nan
    return (cloud, rgb, seen) if labels else (cloud, rgb)


def cube(x=0.05, y=-0.45, yaw=0.3, lying=False, z0=0.0, colour=RED):
    half = (0.01, 0.025, 0.01) if lying else (0.01, 0.01, 0.025)
    return ("box", (x, y, z0 + half[2]), half, yaw, colour)


SCENE = [
    cube(),
    ("box", (0.22, -0.40, 0.035), (0.045, 0.025, 0.035), 0.7, WHITE),
    ("cylinder", (-0.15, -0.36, 0.09), 0.03, 0.09, WHITE),
    ("sphere", (-0.05, -0.58, 0.2), 0.045, WHITE),
]


@pytest.fixture(scope="module")
def scene_cloud():
    return cast(SCENE)


def by_kind(obstacles: list[Obstacle]) -> dict[str, Obstacle]:
    return {o.kind: o for o in obstacles}


# ---------------------------------------------------------------------- hand-built clouds


def test_cube_and_obstacles_of_a_hand_built_scene(scene_cloud):
    cloud, rgb = scene_cloud
    det = P.detect_scene(cloud, rgb, CAL)
    np.testing.assert_allclose(det.target_centre, [0.05, -0.45, 0.025], atol=1e-3)
    np.testing.assert_allclose(det.target_top[2], 0.05, atol=5e-4)
    assert abs(math.degrees(P.wrap(det.target_yaw - 0.3, math.pi / 2))) < 2.0
    assert det.diagnostics["cube_by"] == "colour" and det.diagnostics["plane_sigma_mm"] < 0.05
    found = by_kind(det.obstacles)
    assert sorted(found) == ["box", "cylinder", "sphere"], det.obstacles
    box, cyl, sph = found["box"], found["cylinder"], found["sphere"]
    np.testing.assert_allclose(box.centre, (0.22, -0.40, 0.035), atol=2e-3)
    long_first = abs(P.wrap(box.yaw - 0.7, math.pi)) < math.pi / 4
    half = np.array(box.size) if long_first else np.array(box.size)[[1, 0, 2]]
    np.testing.assert_allclose(half, (0.045, 0.025, 0.035), rtol=0.08)
    assert abs(math.degrees(P.wrap(box.yaw - 0.7, math.pi / 2))) < 3.0
    np.testing.assert_allclose(cyl.centre, (-0.15, -0.36, 0.09), atol=2e-3)
    np.testing.assert_allclose(cyl.size[:2], (0.03, 0.09), rtol=0.06)
    np.testing.assert_allclose(sph.centre, (-0.05, -0.58, 0.2), atol=2e-3)
    assert abs(sph.size[0] - 0.045) < 2e-3 and sph.yaw == 0.0


def test_without_colour_the_cube_is_the_region_of_its_size(scene_cloud):
    cloud, rgb = scene_cloud
    for det in (P.detect_scene(cloud, None, CAL), P.detect_scene(cloud, rgb, CAL, settings=P.PerceptionSettings(use_colour=False))):
        assert det.diagnostics["cube_by"] == "size"
        np.testing.assert_allclose(det.target_centre, [0.05, -0.45, 0.025], atol=1e-3)
        assert len(det.obstacles) == 3


CAPSULE = ("capsule", (0.1, -0.35, 0.03), 0.03, 0.08, 0.5, WHITE)  # lying, r 30 mm, 220 mm tip to tip


def test_a_capsule_lying_on_the_table():
    half, r, yaw = 0.08, 0.03, 0.5
    cloud, rgb = cast([cube(-0.2, -0.5, 0.0), CAPSULE])
    det = P.detect_scene(cloud, rgb, CAL, settings=P.PerceptionSettings(kinds=("capsule", "sphere", "cylinder")))
    (ob,) = det.obstacles
    assert ob.kind == "capsule" and not det.diagnostics["obstacles"][0]["conservative"], det.diagnostics["obstacles"]
    np.testing.assert_allclose(ob.centre[:2], (0.1, -0.35), atol=4e-3)
    assert abs(P.wrap(ob.yaw - yaw, math.pi)) < math.radians(3)
    assert abs(ob.size[0] - r) < 2e-3 and abs(ob.size[1] - half) < 0.012


@pytest.mark.parametrize("objects, message", [
    ([SCENE[1]], r"no cube found \(colour; 1 object region"),
    ([cube(), cube(-0.2, -0.35)], "2 cube candidates .*exactly one cube"),
    ([cube(lying=True)], r"cube not standing on the table: its top is 20\.0 mm above the table"),
    ([("box", (0.05, -0.45, 0.03), (0.04, 0.04, 0.03), 0.0, WHITE), cube(z0=0.06)],
     "cube not standing on the table: .* red pixels are part of an object whose top is 110 mm"),
    ([cube(), ("sphere", (0.038, -0.447, 0.2), 0.012, WHITE)], "the cube's top face is partly hidden"),
    ([cube(0.51, -0.45, 0.0)],  # a third of its top face beyond the image's left edge
     r"the cube's top face is cut by the image border \(left edge\); move the camera or the cube"),
])
def test_scenes_without_exactly_one_standing_cube_are_refused(objects, message):
    cloud, rgb = cast(objects)
    with pytest.raises(P.PerceptionError, match=message):
        P.detect_scene(cloud, rgb, CAL)


def test_bad_clouds_are_refused(scene_cloud):
    cloud, rgb = scene_cloud
    cases = [
        (np.full_like(cloud, np.nan), "no valid point"),
        (np.zeros((0, 0, 3)), r"organized, shape \(H, W, 3\)"),
        (cloud.reshape(-1, 3), r"organized, shape \(H, W, 3\).*got \(144000, 3\)"),
        (cloud[..., :2], r"got \(300, 480, 2\)"),
        (cloud / 1000.0, r"median depth is 1\.4\d* \(as mm\).*looks like metres: give the cloud in millimetres "
                         r"\(multiply it by 1000\)"),
        (cloud / 10.0, r"median depth is 14\d\.\d \(as mm\).*looks like centimetres: give the cloud in millimetres "
                       r"\(multiply it by 10\)"),
        (cloud * 1000.0, "looks like micrometres"),
        (np.where(np.arange(W)[None, :, None] < 10, cloud, np.nan), r"only \d+ valid points .* \(< 5 %\)"),
        ([["a"]], "not numeric|organized"),
    ]
    for bad, message in cases:
        with pytest.raises(P.PerceptionError, match=message):
            P.detect_scene(bad, None, CAL)
    with pytest.raises(P.PerceptionError, match=r"RGB image must be \(H, W, 3\)"):
        P.detect_scene(cloud, rgb[:-1], CAL)
    m = CAL.matrix.copy()
    m[2, 3] += 0.12  # the camera believed 12 cm higher: the table 12 cm above z = 0
    with pytest.raises(P.CalibrationMismatch, match=r"the table\) comes out \+1[12]\d mm from the table's height.*does "
                                                    "not match this camera"):
        P.detect_scene(cloud, rgb, CameraCalibration.from_matrix(m, "m"))
    for dz, dy_deg, refused in ((0.006, 0.0, False), (0.015, 0.0, True), (0.0, 1.0, False), (0.0, 3.0, True)):
        # a camera believed dz higher, turned dy_deg about its x axis: within ±10 mm and 2° accepted, else refused
        # with the offset and tilt measured (the table within the 30-mm band either way)
        turn = math.radians(dy_deg)
        rx = np.array([[1, 0, 0], [0, math.cos(turn), -math.sin(turn)], [0, math.sin(turn), math.cos(turn)]])
        m = CAL.matrix.copy()
        m[:3, :3] = rx @ m[:3, :3]
        centre_before = CAL.cam_to_base([0.0, 0.0, 1.41])
        m[:3, 3] += centre_before - (rx @ (centre_before - CAL.camera_position) + CAL.camera_position) + [0, 0, dz]
        cal = CameraCalibration.from_matrix(m, "m")
        if refused:
            with pytest.raises(P.CalibrationMismatch, match=r"the table comes out [+-]\d+\.\d mm .* tilted \d\.\d\d°"):
                P.detect_scene(cloud, rgb, cal)
        else:
            tilt = math.degrees(math.acos(P.detect_scene(cloud, rgb, cal).diagnostics["plane_normal"][2]))
            assert tilt == pytest.approx(dy_deg, abs=0.05)


def test_a_tilted_calibration_is_refused(scene_cloud):
    cloud, rgb = scene_cloud
    tilt = math.radians(8)
    rx = np.array([[1, 0, 0], [0, math.cos(tilt), -math.sin(tilt)], [0, math.sin(tilt), math.cos(tilt)]])
    m = CAL.matrix.copy()
    m[:3, :3] = rx @ m[:3, :3]
    m[2, 3] += 0.07 - (rx @ (CAL.cam_to_base([0.0, 0.0, 1.4]) - CAL.camera_position))[2]  # keep the view's centre on the table
    with pytest.raises(P.PerceptionError, match="tilted .* from level|no table plane|holds only"):
        P.detect_scene(cloud, rgb, CameraCalibration.from_matrix(m, "m"))


def test_noise_and_dropouts_of_a_depth_camera(scene_cloud):
    """σ 2 mm along the rays, 10 % of the pixels dropped: the cube within 2 mm, the obstacles found."""
    cloud, rgb = scene_cloud
    rng = np.random.default_rng(0)
    noisy = cloud * (1 + rng.normal(0, 2.0, cloud.shape[:2]) / cloud[..., 2])[..., None]
    noisy[rng.random(cloud.shape[:2]) < 0.1] = np.nan
    det = P.detect_scene(noisy, rgb, CAL)
    assert np.linalg.norm(det.target_centre - [0.05, -0.45, 0.025]) < 2e-3
    assert sorted(by_kind(det.obstacles)) == ["box", "cylinder", "sphere"]
    assert 1.5 < det.diagnostics["plane_sigma_mm"] < 2.5


def test_a_sphere_hiding_part_of_a_box_below():
    """The box's visible outline is cut by the sphere: the rectangle comes from the edges that are its own."""
    box = ("box", (0.15, -0.42, 0.04), (0.05, 0.035, 0.04), 0.2, WHITE)
    sphere = ("sphere", (0.16, -0.375, 0.16), 0.035, WHITE)  # over one of the box's corners
    cloud, rgb = cast([cube(-0.15, -0.5), box, sphere])
    det = P.detect_scene(cloud, rgb, CAL)
    found = by_kind(det.obstacles)
    assert sorted(found) == ["box", "sphere"]
    assert next(d for d in det.diagnostics["obstacles"] if d["kind"] == "box")["occluded_px"] > 10
    np.testing.assert_allclose(found["box"].centre, (0.15, -0.42, 0.04), atol=1.5e-3)
    np.testing.assert_allclose(found["box"].size, (0.05, 0.035, 0.04), rtol=0.05)  # the face's area would be short
    np.testing.assert_allclose(found["sphere"].centre, (0.16, -0.375, 0.16), atol=1e-3)


def held_share(obstacles: list[Obstacle], points: np.ndarray, tol: float = 0.003) -> float:
    """The share of ``points`` (N, 3) inside some obstacle grown by ``tol``."""
    inside = np.zeros(len(points), bool)
    for ob in obstacles:
        kind = P.shapes.BY_NAME[ob.kind].id
        inside |= P.shapes.sdf(np, kind, np.asarray(ob.centre), np.asarray(ob.yaw), np.asarray(ob.size), points) <= tol
    return float(inside.mean())


def seen_points(cloud: np.ndarray, labels: np.ndarray, index: int) -> np.ndarray:
    """World points of what the camera sees of object ``index``, more than 10 mm above the table (lower ones
    are the table's to the perception)."""
    pts = CAL.cam_to_base(cloud[labels == index].astype(float), "mm")
    return pts[pts[:, 2] > 0.01]


def test_an_obstacle_whose_top_a_sphere_hides_is_kept():
    """A sphere floating over a cylinder hides its top and 83 % of it: the strips of its side that are seen are
    an obstacle (not fragments, not noise), one that holds every point seen of the cylinder."""
    objects = [cube(-0.2, -0.5), ("cylinder", (0.1, -0.4, 0.075), 0.03, 0.075, WHITE),
               ("sphere", (0.1, -0.4, 0.22), 0.05, WHITE)]
    cloud, rgb, labels = cast(objects, labels=True)
    seen = seen_points(cloud, labels, 1)
    assert len(seen) > 100
    det = P.detect_scene(cloud, rgb, CAL)
    assert len(det.obstacles) == 2 and sorted(o.kind for o in det.obstacles)[-1] == "sphere", det.obstacles
    below = [o for o in det.obstacles if o.kind != "sphere"]
    assert held_share(below, seen) == 1.0
    assert max(o.centre[2] + P.shapes.BY_NAME[o.kind].half_height(np.asarray(o.size)) for o in below) < 0.13
    rng = np.random.default_rng(3)  # and with a depth camera's noise and dropped pixels
    noisy = cloud * (1 + rng.normal(0, 0.5, cloud.shape[:2]) / cloud[..., 2])[..., None]
    noisy[rng.random(cloud.shape[:2]) < 0.05] = np.nan
    assert held_share(P.detect_scene(noisy, rgb, CAL).obstacles, seen, 0.004) == 1.0


def test_pieces_of_a_box_cut_by_a_sphere_are_one_obstacle():
    """A sphere over a box's middle cuts its top in two pieces that alone look like a box and a cylinder; they
    are one box, fitted on both pieces' own edges."""
    box = ("box", (-0.205, -0.24, 0.04), (0.046, 0.0225, 0.04), 0.1, WHITE)
    objects = [cube(-0.35, -0.45), box, ("sphere", (-0.205, -0.2485, 0.235), 0.0355, WHITE)]
    cloud, rgb, labels = cast(objects, labels=True)
    det = P.detect_scene(cloud, rgb, CAL)
    found = by_kind(det.obstacles)
    assert sorted(found) == ["box", "sphere"] and len(det.obstacles) == 2, det.obstacles
    info = next(d for d in det.diagnostics["obstacles"] if d["kind"] == "box")
    assert info["pieces"] >= 2 and not info["conservative"], info
    np.testing.assert_allclose(found["box"].centre, box[1], atol=1.5e-3)
    np.testing.assert_allclose(found["box"].size, box[2], rtol=0.06)
    assert held_share(det.obstacles, seen_points(cloud, labels, 1)) == 1.0


def test_hidden_obstacles_are_held_whole():
    """Random scenes of floating spheres in front of boxes and cylinders (partly or mostly hidden, some cut by
    the image border): every point seen of every obstacle lies in a returned obstacle, none returned holds
    nothing of one."""
    rng = np.random.default_rng(7)
    for _ in range(6):
        objects = [cube(-0.3, -0.3)]
        x, y = rng.uniform(-0.1, 0.45), rng.uniform(-0.7, -0.45)
        if rng.random() < 0.5:
            half = rng.uniform(0.02, 0.06, 3)
            objects.append(("box", (x, y, half[2]), tuple(half), rng.uniform(-math.pi, math.pi), WHITE))
            top, reach = 2 * half[2], math.hypot(half[0], half[1])
        else:
            r, h = rng.uniform(0.02, 0.05), rng.uniform(0.1, 0.3)
            objects.append(("cylinder", (x, y, h / 2), r, h / 2, WHITE))
            top, reach = h, r
        r = rng.uniform(0.03, 0.06)
        a, d = rng.uniform(0, 2 * math.pi), rng.uniform(0, reach)
        centre = (x + d * math.cos(a), y + d * math.sin(a), top + r + rng.uniform(0.01, 0.1))
        objects.append(("sphere", centre, r, WHITE))
        cloud, rgb, labels = cast(objects, labels=True)
        det = P.detect_scene(cloud, rgb, CAL)
        seen = [seen_points(cloud, labels, k) for k in (1, 2)]
        for pts in seen:
            assert len(pts) < 30 or held_share(det.obstacles, pts) == 1.0, (objects, det.obstacles)
        every = np.concatenate(seen)
        assert all(held_share([o], every) > 0 for o in det.obstacles), (objects, det.obstacles)


def test_only_the_policys_obstacle_kinds_are_returned():
    """The kinds are the policy's (env.sampling.obstacle_kinds; default the paper's): a lying capsule seen by a
    paper-mix policy is a covering obstacle of a paper kind, holding all of it; unknown kinds are refused."""
    assert P.PerceptionSettings().kinds == SamplingConfig().obstacle_kinds == ("sphere", "cylinder", "box")
    env = EnvConfig(sampling=dataclasses.replace(SamplingConfig(), obstacle_kinds=("sphere", "capsule")))
    assert P.PerceptionSettings.for_policy(env, use_colour=False).kinds == ("sphere", "capsule")
    cloud, rgb, labels = cast([cube(-0.2, -0.5, 0.0), CAPSULE], labels=True)
    seen = seen_points(cloud, labels, 1)
    for kinds in (None, ("sphere",)):
        settings = P.PerceptionSettings(kinds=kinds) if kinds else None
        det = P.detect_scene(cloud, rgb, CAL, settings=settings)
        (ob,) = det.obstacles
        assert ob.kind in (kinds or ("cylinder", "box")) and det.diagnostics["obstacles"][0]["conservative"]
        assert held_share(det.obstacles, seen) == 1.0
    for kinds in (("cone",), (), "box"):
        with pytest.raises(P.PerceptionError, match="obstacle kinds .* must be some of sphere, cylinder, box, capsule"):
            P.detect_scene(cloud, rgb, CAL, settings=P.PerceptionSettings(kinds=kinds))


def test_zero_points_are_no_return(scene_cloud):
    """(0, 0, 0), the RealSense's and Open3D's "no return", reads as NaN everywhere: the same scene."""
    cloud, rgb = scene_cloud
    drop = np.random.default_rng(4).random(cloud.shape[:2]) < 0.1
    zeros, nans = cloud.copy(), cloud.copy()
    zeros[drop], nans[drop] = 0.0, np.nan
    kept = zeros.copy()
    a, b = P.detect_scene(zeros, rgb, CAL), P.detect_scene(nans, rgb, CAL)
    assert np.array_equal(zeros, kept)  # the caller's array is left as it was
    np.testing.assert_allclose(a.target_centre, b.target_centre)
    assert a.obstacles == b.obstacles and a.diagnostics["valid_points"] == b.diagnostics["valid_points"]
    v, u = np.argwhere(drop[5:-5, 5:-5])[0] + 5
    np.testing.assert_allclose(P.point_at_pixel(zeros, u, v, 1), P.point_at_pixel(nans, u, v, 1))
    with pytest.raises(P.PerceptionError, match="no valid point"):
        P.detect_scene(np.zeros_like(cloud), None, CAL)


def test_point_at_pixel_is_the_papers_step(scene_cloud):
    cloud, _ = scene_cloud
    u, v = 100.0, 50.0
    np.testing.assert_allclose(P.point_at_pixel(cloud, u, v, window=0), cloud[50, 100], rtol=1e-6)
    holed = cloud.copy()
    holed[45:56, 95:106] = np.nan
    with pytest.raises(P.PerceptionError, match="no valid depth within 2 px"):
        P.point_at_pixel(holed, u, v)
    with pytest.raises(P.PerceptionError, match="outside the 480 × 300 image"):
        P.point_at_pixel(cloud, 600, 10)


def test_detector_boxes_choose_the_cube(scene_cloud):
    cloud, rgb = scene_cloud
    grey = np.repeat(rgb.mean(axis=2, keepdims=True), 3, axis=2).astype(np.uint8)  # no colour to go by
    top = CAL.base_to_cam([0.05, -0.45, 0.05])
    u, v = FX * top[0] / top[2] + CX, FY * top[1] / top[2] + CY
    box = (u - 8, v - 8, u + 8, v + 8)
    det = P.detect_scene(cloud, grey, CAL, detections=[P.Detection("target", box, 0.9), P.Detection("box", (0, 0, 5, 5))])
    assert det.diagnostics["cube_by"] == "detector"
    np.testing.assert_allclose(det.target_centre, [0.05, -0.45, 0.025], atol=1e-3)
    with pytest.raises(P.PerceptionError, match="no cube found \\(detector"):
        P.detect_scene(cloud, grey, CAL, detections=[])


# ---------------------------------------------------------------------- building blocks


def test_regions_join_across_a_dropped_pixel_only():
    mask = np.zeros((6, 8), bool)
    mask[1:3, 1:3] = True
    mask[1, 4] = True  # two columns from the square, the pixel between dropped
    mask[3, 3] = True  # diagonal neighbour only: a region of its own
    mask[1, 6] = True  # two from (1, 4), the pixel between valid but not in the mask: its own region
    valid = np.ones((6, 8), bool)
    valid[1, 3] = False
    labels = P.label_regions(mask, np.zeros((6, 8, 3)), 0.03, valid)
    assert labels[1, 4] == labels[1, 1] and labels[3, 3] != labels[1, 1] and labels[1, 6] not in (labels[1, 1], labels[3, 3])
    assert sorted(np.unique(labels)) == [-1, 0, 1, 2]
    far = np.zeros((6, 8, 3))
    far[1:3, 2] = (0, 0, 0.05)  # a 5 cm step splits the square
    assert len(np.unique(P.label_regions(mask, far, 0.03, valid))) == 6  # the far column splits off; (1, 4), 5 cm from it, stands alone


def test_border_edges():
    valid = np.ones((6, 8), bool)
    assert P.border_edges(np.array([[2, 3], [3, 4]]), valid) == []
    assert P.border_edges(np.array([[2, 0], [5, 4]]), valid) == ["left", "bottom"]
    assert P.border_edges(np.array([[1, 3]]), valid) == []
    valid[0, 3] = False  # one in from the top edge, the border pixel dropped: what lies beyond is unseen
    assert P.border_edges(np.array([[1, 3], [2, 6]]), valid) == ["top"]
    assert P.border_edges(np.array([[2, 7]]), valid) == ["right"]


def test_a_cover_holds_the_fitted_shape_too():
    """``_shape_points`` (what a cover adds of the fit it replaces): their horizontal hull holds each kind's
    footprint and their highest is its top."""
    rng = np.random.default_rng(0)
    centre = np.array([0.1, -0.3, 0.2])
    for kind, size in (("box", (0.04, 0.02, 0.03)), ("cylinder", (0.03, 0.08, 0)), ("sphere", (0.05, 0, 0)),
                       ("capsule", (0.03, 0.08, 0))):
        fit = P.ObstacleFit(kind, centre, np.array(size, float), 0.7, 0.0)
        pts = P._shape_points(fit)
        hull = P.convex_hull(pts[:, :2])
        samples = centre + rng.uniform(-0.15, 0.15, (20000, 3))
        inside = samples[P.shapes.sdf(np, P.shapes.BY_NAME[kind].id, centre, np.asarray(0.7), fit.size, samples) <= 0]
        a, b = hull, np.roll(hull, -1, axis=0)
        cross = ((b[:, 0] - a[:, 0])[None] * (inside[:, None, 1] - a[None, :, 1])
                 - (b[:, 1] - a[:, 1])[None] * (inside[:, None, 0] - a[None, :, 0]))
        assert len(inside) > 40 and (cross >= -1e-12).all() and inside[:, 2].max() <= pts[:, 2].max(), kind


def test_minimum_area_rectangle_and_hull():
    rng = np.random.default_rng(1)
    u, v = rng.uniform(-0.03, 0.03, 400), rng.uniform(-0.01, 0.01, 400)
    a = 0.4
    xy = np.c_[u * math.cos(a) - v * math.sin(a), u * math.sin(a) + v * math.cos(a)] + (0.2, -0.3)
    centre, sides, angle = point_fits.min_area_rect(xy)
    np.testing.assert_allclose(centre, (0.2, -0.3), atol=1e-3)
    np.testing.assert_allclose(sorted(sides), (0.02, 0.06), atol=1.5e-3)
    assert abs(point_fits.wrap(angle - a, math.pi / 2)) < 0.02
    hull = point_fits.convex_hull(np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5]], float))
    assert len(hull) == 4 and point_fits.polygon_area(hull) == pytest.approx(1.0)


# ---------------------------------------------------------------------- the twin camera's renders

pytest.importorskip("pybullet")
from sagrasp_jax.task import robot  # noqa: E402
from sagrasp_jax.task import sampling  # noqa: E402
from sagrasp_jax.task.config import blocking_sampling  # noqa: E402
from sagrasp_jax.deploy import twin_camera as tc  # noqa: E402
from sagrasp_jax.deploy.twin import PyBulletTwin  # noqa: E402


def _spec(seed: int, blocking: bool):
    cfg = EnvConfig()
    if blocking:
        cfg = EnvConfig(sampling=blocking_sampling(cfg.sampling, 1.0, 1.0))
    u = np.random.default_rng(seed).random(sampling.uniforms_needed(cfg.sampling))
    return cfg, sampling.sample_reset(np, robot.load_robot(), cfg.sampling, cfg.task, u)


@pytest.fixture(scope="module")
def camera():
    return tc.TwinCamera(0.25)


def test_intrinsics_keep_the_field_of_view():
    full = tc.MECH_EYE_PRO_M
    quarter = full.scaled(0.25)
    assert (quarter.width, quarter.height) == (480, 300) and (full.width, full.height) == (1920, 1200)
    np.testing.assert_allclose(quarter.fov_deg, full.fov_deg, atol=0.05)
    np.testing.assert_allclose(full.fov_deg, (43.2, 27.8), atol=0.1)
    np.testing.assert_allclose((quarter.fx, quarter.cx), (FX, CX), atol=0.01)


def test_rendered_scenes_are_perceived(camera):
    """A blocking scene (two obstacles on the approach path) and one of the paper's mix, the arm parked."""
    for seed, blocking in ((3, True), (11, False)):
        cfg, spec = _spec(seed, blocking)
        with PyBulletTwin(spec, cfg, q0=spec.q0) as twin:
            frame = camera.capture(twin, hide_robot=True)
        assert frame.cloud_mm.shape == (300, 480, 3) and frame.rgb.dtype == np.uint8
        det = P.detect_scene(frame.cloud_mm, frame.rgb, CAL)
        assert np.linalg.norm(det.target_centre - spec.target_pos) < 1.5e-3, (seed, det.target_centre, spec.target_pos)
        truth = [(int(spec.obstacle_kind[i]), spec.obstacle_pos[i]) for i in np.nonzero(spec.obstacle_active)[0]]
        assert len(det.obstacles) == len(truth)
        for kind, pos in truth:
            near = min(det.obstacles, key=lambda o: np.linalg.norm(np.asarray(o.centre) - pos))
            assert np.linalg.norm(np.asarray(near.centre) - pos) < 5e-3
            assert P.shapes.BY_NAME[near.kind].id == kind


def test_the_arm_in_view_is_masked_with_its_joints(camera):
    cfg, spec = _spec(3, True)
    with PyBulletTwin(spec, cfg, q0=spec.q0) as twin:
        frame = camera.capture(twin)  # the arm at its start pose, in view
    det = P.detect_scene(frame.cloud_mm, frame.rgb, CAL, robot_q=spec.q0)
    assert np.linalg.norm(det.target_centre - spec.target_pos) < 1.5e-3
    assert len(det.obstacles) == int(np.sum(spec.obstacle_active))
    with pytest.raises(P.PerceptionError, match="taller than any trained obstacle .*: the arm in view without robot_q"):
        P.detect_scene(frame.cloud_mm, frame.rgb, CAL)


def test_depth_noise_models(camera):
    cfg, spec = _spec(11, False)
    with PyBulletTwin(spec, cfg, q0=spec.q0) as twin:
        frame = camera.capture(twin, hide_robot=True)
    table = frame.segmentation == twin.table_body
    z = frame.cloud_mm[..., 2]
    assert np.array_equal(tc.apply_depth_noise(frame.cloud_mm, "none", np.random.default_rng(0)), frame.cloud_mm, equal_nan=True)
    for name, sigma, lost in (("industrial", 0.18, 0.005), ("consumer", 4.9, 0.02)):
        noisy = tc.apply_depth_noise(frame.cloud_mm, name, np.random.default_rng(0))
        dz = (noisy[..., 2] - z)[table & np.isfinite(noisy[..., 2])]
        assert abs(np.std(dz) / sigma - 1) < 0.1, (name, np.std(dz))
        dropped = np.isnan(noisy[..., 2]) & np.isfinite(z)
        assert lost < dropped.mean() < 3 * lost + 0.01, (name, dropped.mean())
        ray = noisy[table][:200] / np.linalg.norm(noisy[table][:200], axis=1, keepdims=True)
        clean = frame.cloud_mm[table][:200] / np.linalg.norm(frame.cloud_mm[table][:200], axis=1, keepdims=True)
        ok = np.isfinite(ray).all(axis=1)
        np.testing.assert_allclose(ray[ok], clean[ok], atol=1e-6)  # moved along its ray only
    with pytest.raises(ValueError, match="unknown depth-noise model 'lidar'"):
        tc.apply_depth_noise(frame.cloud_mm, "lidar", np.random.default_rng(0))


def test_render_geometry_time_and_colours(camera):
    cfg, spec = _spec(11, False)
    with PyBulletTwin(spec, cfg, q0=spec.q0) as twin:
        frame = camera.capture(twin, hide_robot=True)
        top = spec.target_pos + np.array([0.0, 0.0, 0.025])
        u, v = np.round(camera.project(top)).astype(int)
        np.testing.assert_allclose(CAL.cam_to_base(frame.cloud_mm[v, u], "mm"), top, atol=3e-3)
        assert frame.segmentation[v, u] == twin.target_body
        r, g, b = frame.rgb[v, u].astype(int)
        assert r > 2 * max(g, b)  # the paper's red cube
        times = [camera.capture(twin, hide_robot=True).render_s for _ in range(3)]
        assert min(times) < 0.5  # ~0.05 s at 480 × 300 on one core
        rng = np.random.default_rng(2)
        shot = camera.capture(twin, colours=tc.random_colours(rng, len(twin.obstacle_bodies)), lighting=tc.random_lighting(rng))
        assert not np.array_equal(shot.rgb, frame.rgb)
        np.testing.assert_allclose(shot.cloud_mm[v, u], frame.cloud_mm[v, u])  # colours change nothing of the geometry
        assert twin.read_joints().tolist() == pytest.approx(list(spec.q0))  # the parked arm came back


# ---------------------------------------------------------------------- the YOLO option


def test_yolo_dataset_and_detections(tmp_path):
    from sagrasp_jax.deploy import yolo, yolo_dataset

    out = tmp_path / "ds"
    assert yolo_dataset.main(["--out", str(out), "--images", "3", "--val-fraction", "0.34", "--seed", "1"]) == 0
    assert (out / "dataset.yaml").read_text().count(":") >= 8
    images = sorted((out / "images").rglob("*.png"), key=lambda p: p.name)
    labels = sorted((out / "labels").rglob("*.txt"), key=lambda p: p.name)
    assert [p.stem for p in images] == [p.stem for p in labels] == ["000000", "000001", "000002"]
    assert (out / "images" / "val" / "000000.png").exists()
    for label in labels:
        rows = [line.split() for line in label.read_text().splitlines()]
        assert rows and rows[0][0] == "0"  # the target, always in view
        for row in rows:
            assert int(row[0]) < len(yolo.CLASSES) and all(0.0 <= float(x) <= 1.0 for x in row[1:])
    data = images[0].read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    raw = zlib.decompress(data[data.index(b"IDAT") + 4 : data.index(b"IEND") - 8])
    assert (width, height) == (480, 300) and len(raw) == height * (1 + 3 * width)
    assert yolo_dataset.main(["--out", str(out), "--images", "3"]) == 2  # not empty: refused
    assert yolo_dataset.main(["--out", str(tmp_path / "x"), "--images", "0"]) == 2
    assert not (tmp_path / "x").exists()
    dets = yolo.detections_from_arrays([[1, 2, 30, 40], [5, 5, 9, 9]], [0, 3], [0.9, 0.5], {0: "target", 3: "box"})
    assert dets[0] == P.Detection("target", (1.0, 2.0, 30.0, 40.0), 0.9) and dets[1].label == "box"
    with pytest.raises(P.PerceptionError, match="class id\\(s\\) \\[7\\] have no name"):
        yolo.detections_from_arrays([[0, 0, 1, 1]], [7], [0.5], yolo.CLASSES)


def test_yolo_detector_needs_its_extra():
    from sagrasp_jax.base import extras
    from sagrasp_jax.deploy import yolo

    if not extras.missing("yolo"):
        pytest.skip("ultralytics is installed")
    with pytest.raises(extras.MissingExtra, match=r'pip install "sagrasp_jax\[yolo\]"'):
        yolo.YoloDetector("best.pt")


def test_the_accuracy_study_runs_and_reports(tmp_path, capsys):
    """experiments/perception_accuracy.py on two scenes of each mix: its table and JSON (the study's numbers
    are in docs/design.md, "Perception")."""
    import json

    from experiments import perception_accuracy as study

    out = tmp_path / "pa.json"
    assert study.main(["--scenes", "2", "--blocking", "2", "--noise", "none,industrial", "--out", str(out)]) == 0
    assert "| blocking | industrial | 2 | 0 |" in capsys.readouterr().out
    result = json.loads(out.read_text())
    for mix in ("paper", "blocking"):
        for level in ("none", "industrial"):
            summary = result["summary"][mix][level]
            assert summary["scenes"] == 2 and summary["refused"] == 0
            assert summary["target_err_mm"]["max"] < 2.5
    blocking = result["summary"]["blocking"]["none"]["obstacles"]
    assert blocking["true"] >= 2 and blocking["found_share"] == 1.0 and blocking["invented"] == 0
