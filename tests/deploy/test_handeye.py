"""Hand-eye calibration from point pairs (deploy.handeye) and its CLI (python -m sagrasp_jax.calibrate)."""

from __future__ import annotations

import itertools
import json
import os
import re
import subprocess
import sys
import tracemalloc

import numpy as np
import pytest

from sagrasp_jax import calibrate
from sagrasp_jax.deploy import handeye
from sagrasp_jax.deploy.calibration import CameraCalibration
from sagrasp_jax.deploy.handeye import (
    HandEyeError,
    check_pairs,
    fit_hand_eye,
    kabsch,
    norm_p95,
    outlier_sigmas,
    plan_poses,
    predict_errors,
    rotation_angle_deg,
    workspace_points_mm,
)
from sagrasp_jax.deploy.safety import SafetyLayer
from sagrasp_jax.task.robot import forward_kinematics, load_robot
from sagrasp_jax.task.scene import SCENE, T_CAM_BASE_MM, orthonormalise
from paths import REPO  # noqa: E402

R_TRUE = orthonormalise(T_CAM_BASE_MM[:3, :3])
T_TRUE = T_CAM_BASE_MM[:3, 3]
# ten TCP positions (mm, base frame): the corners of the workspace the cube and the obstacles occupy, and two inside
DESIGN = np.r_[np.array(list(itertools.product((-350, 350), (-650, -200), (30, 400))), float),
               [[0.0, -425.0, 215.0], [0.0, -425.0, 60.0]]]
# where the mapped points matter: the target region's grid at the cube's height
WORKSPACE = np.stack(np.meshgrid(np.linspace(-350, 350, 8), np.linspace(-600, -250, 6), [25.0]), -1).reshape(-1, 3)


def camera_points(base_mm: np.ndarray, noise_mm: float = 0.0, seed: int = 0) -> np.ndarray:
    """What the camera sees of TCP points (the true T_cam_base inverted), with isotropic noise σ per axis."""
    rng = np.random.default_rng(seed)
    return (base_mm - T_TRUE) @ R_TRUE + rng.normal(0.0, noise_mm, base_mm.shape)


def mapped_error_mm(rot: np.ndarray, t: np.ndarray) -> float:
    """Mean 3-D distance over the workspace between the fitted and the true mapping of camera points."""
    cam = (WORKSPACE - T_TRUE) @ R_TRUE
    return float(np.linalg.norm(cam @ rot.T + t - WORKSPACE, axis=1).mean())


def test_exact_pairs_give_the_transform_back():
    fit = fit_hand_eye(camera_points(DESIGN), DESIGN)
    np.testing.assert_allclose(fit.rotation, R_TRUE, atol=1e-12)
    np.testing.assert_allclose(fit.translation_mm, T_TRUE, atol=1e-9)
    assert fit.rms_mm < 1e-9 and fit.residuals_mm.shape == (10,)
    assert np.isclose(np.linalg.det(fit.rotation), 1.0)


def test_kabsch_never_returns_a_reflection():
    """Points on a plane admit a mirror image with the same residual; the fit keeps det R = +1."""
    flat = DESIGN.copy()
    flat[:, 2] = 100.0
    rot, _ = kabsch(camera_points(flat), flat)
    assert np.isclose(np.linalg.det(rot), 1.0)
    np.testing.assert_allclose(rot, R_TRUE, atol=1e-9)


def test_recovers_a_known_calibration_from_ten_pairs_with_1mm_noise():
    """docs/task.md §5.1: 10 pairs spread over the workspace, 1 mm of noise.  With 1 mm RMS (3-D) per camera
    point, 95 % of 200 draws are within 0.1° and the median maps workspace points within 0.5 mm; with 1 mm
    per axis (√3 more), the median is still within 0.1°.  The camera origin itself, 1.4 m from the pairs,
    moves by the rotation error × 1.4 m: the mapped workspace point is what the grasp sees."""
    angle, mapped = [], []
    for seed in range(200):
        fit = fit_hand_eye(camera_points(DESIGN, 1.0 / np.sqrt(3), seed), DESIGN)
        angle.append(rotation_angle_deg(fit.rotation, R_TRUE))
        mapped.append(mapped_error_mm(fit.rotation, fit.translation_mm))
    assert np.percentile(angle, 95) <= 0.1, np.percentile(angle, 95)
    assert np.median(mapped) <= 0.5, np.median(mapped)
    per_axis = [rotation_angle_deg(fit_hand_eye(camera_points(DESIGN, 1.0, s), DESIGN).rotation, R_TRUE) for s in range(200)]
    assert np.median(per_axis) <= 0.1, np.median(per_axis)
    # the residuals report the noise: RMS ≈ σ·√3·√((N − 6)/N) for 10 pairs
    fit = fit_hand_eye(camera_points(DESIGN, 1.0, 0), DESIGN)
    assert 0.8 < fit.rms_mm < 2.0


@pytest.mark.parametrize("edit, message", [
    (lambda c, b: (c[:3], b[:3]), "3 point pair"),
    (lambda c, b: (np.where(np.arange(10)[:, None] == 4, np.nan, c), b), "#5 hold NaN"),
    (lambda c, b: (c / 1000.0, b), "1000 × those between the camera points.*camera points like metres"),
    (lambda c, b: (c, b / 1000.0), "camera points look like mm and the TCP points like metres"),
    (lambda c, b: (np.r_[c[:9], c[9:] / 1000.0], b), "pair\\(s\\) #10 disagree in scale"),
])
def test_degenerate_and_mixed_sets_refused(edit, message):
    cam, base = edit(camera_points(DESIGN), DESIGN.copy())
    with pytest.raises(HandEyeError, match=message):
        fit_hand_eye(cam, base)


def test_points_along_a_line_or_bunched_refused():
    line = np.array([[-300.0 + 100 * i, -400.0, 100.0] for i in range(6)])
    with pytest.raises(HandEyeError, match="along a line: the turn about that line is not determined"):
        fit_hand_eye(camera_points(line), line)
    nearly = line + np.random.default_rng(0).normal(0, 2.0, line.shape)  # 2 mm off the line: still a line
    with pytest.raises(HandEyeError, match="along a line"):
        fit_hand_eye(camera_points(nearly), nearly)
    bunch = np.full((6, 3), 100.0) + np.random.default_rng(0).normal(0, 1.0, (6, 3))
    with pytest.raises(HandEyeError, match="bunched together"):
        fit_hand_eye(camera_points(bunch), bunch)


def test_a_mismatched_pair_is_refused_by_the_residual():
    cam, base = camera_points(DESIGN), DESIGN.copy()
    cam[[3, 7]] = cam[[7, 3]]  # two rows swapped: each pair now names another point
    with pytest.raises(HandEyeError, match=r"RMS residual .* > 5 mm \(worst: #(4|8) "):
        fit_hand_eye(cam, base)
    fit = fit_hand_eye(camera_points(DESIGN, 1.0), base, max_rms_mm=5.0)  # honest noise passes
    assert fit.rms_mm < 5.0


# ---------------------------------------------------------------------- the CLI


def write_pairs(path, cam, base, header=True, comment=True):
    lines = (["# pairs measured by hand", ""] if comment else []) + (
        ["tcp_x,tcp_y,tcp_z,cam_x,cam_y,cam_z"] if header else [])
    for c, b in zip(cam, base):
        values = (*b, *c) if header else (*c, *b)
        lines.append(",".join(f"{v:.6f}" for v in values))
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def test_cli_writes_the_file_deploy_reads(tmp_path, capsys):
    pairs = write_pairs(tmp_path / "pairs.csv", camera_points(DESIGN, 0.3), DESIGN)  # header in another order
    out = tmp_path / "cal" / "calibration.json"
    assert calibrate.main(["--pairs", pairs, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "RMS" in text and "  10 " in text and f"written {out}" in text
    record = json.loads(out.read_text())
    assert record["units"] == "mm" and record["pairs"] == 10 and len(record["residuals_mm"]) == 10
    cal = CameraCalibration.from_file(str(out))  # what `deploy --calibration` does with it
    np.testing.assert_allclose(cal.camera_position, T_TRUE / 1000, atol=2e-3)
    assert rotation_angle_deg(cal.rotation, R_TRUE) < 0.1
    # headerless, metres for both sets
    plain = write_pairs(tmp_path / "plain.csv", camera_points(DESIGN) / 1000, DESIGN / 1000, header=False, comment=False)
    assert calibrate.main(["--pairs", plain, "--out", str(tmp_path / "m.json"), "--cam-units", "m", "--tcp-units", "m",
                           "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(np.array(printed["T_cam_base"])[:3, 3], T_TRUE, atol=0.01)  # the file holds µm


@pytest.mark.parametrize("content, message", [
    ("1,2,3,4,5,6\n1,2,3,4,5,6\n", "2 point pair"),
    ("a,b,c,d,e,f\n", "header"),
    ("1,2,3,4,5\n", "5 values"),
    ("1,2,x,4,5,6\n", "must be a number"),
    ("", "no point pairs"),
])
def test_cli_refuses_bad_files_with_exit_2_and_writes_nothing(tmp_path, capsys, content, message):
    pairs = tmp_path / "pairs.csv"
    pairs.write_text(content)
    out = tmp_path / "calibration.json"
    out.write_text("previous calibration\n")
    assert calibrate.main(["--pairs", str(pairs), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and "nothing written" in err
    assert out.read_text() == "previous calibration\n"  # the old file is untouched


def test_cli_mixed_units_and_missing_file_exit_2(tmp_path):
    mixed = write_pairs(tmp_path / "mixed.csv", camera_points(DESIGN) / 1000, DESIGN)  # camera in m, TCP in mm
    res = subprocess.run([sys.executable, "-m", "sagrasp_jax.calibrate", "--pairs", mixed, "--out",
                          str(tmp_path / "c.json")], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert res.returncode == 2 and "camera points like metres" in res.stderr, res.stderr
    assert not (tmp_path / "c.json").exists()
    res = subprocess.run([sys.executable, "-m", "sagrasp_jax.calibrate", "--pairs", str(tmp_path / "none.csv"), "--out",
                          str(tmp_path / "c.json")], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert res.returncode == 2 and "none.csv" in res.stderr


# ---------------------------------------------------------------------- how good a fit is, and where to take the pairs


@pytest.fixture(scope="module")
def plan():
    return plan_poses()  # the default: 10 poses, predicted with 1 mm of noise per axis


def draws(base, sigma, n, seed=0):
    """Monte-Carlo: rotation angle (deg, (n,)) and 3-D error of mapped workspace points (mm, (n, 5)) of Kabsch fits
    to camera points with ``sigma`` of noise per axis."""
    rng = np.random.default_rng(seed)
    work = workspace_points_mm()
    seen = (work - T_TRUE) @ R_TRUE
    angle, mapped = [], []
    for _ in range(n):
        rot, t = kabsch((base - T_TRUE) @ R_TRUE + rng.normal(0.0, sigma, base.shape), base)
        angle.append(rotation_angle_deg(rot, R_TRUE))
        mapped.append(np.linalg.norm(seen @ rot.T + t - work, axis=1))
    return np.array(angle), np.array(mapped)


rng_sets = np.random.default_rng(7)
WEAK_SETS = {  # what an independent check found accepted without a word (0.44–0.59° off)
    "4 pairs": np.c_[rng_sets.uniform(-350, 350, 4), rng_sets.uniform(-650, -200, 4), rng_sets.uniform(30, 400, 4)],
    "near-line": np.c_[np.linspace(-350, 350, 10), -425 + rng_sets.normal(0, 25, 10), 200 + rng_sets.normal(0, 25, 10)],
    "100 mm cube": np.array([0.0, -425.0, 200.0]) + rng_sets.uniform(-50, 50, (10, 3)),
    "10 at random": np.c_[rng_sets.uniform(-350, 350, 10), rng_sets.uniform(-650, -200, 10), rng_sets.uniform(30, 400, 10)],
}


def test_norm_p95_and_outlier_threshold_are_the_distributions_quantiles():
    assert abs(float(norm_p95(np.eye(3))) - 2.7955) < 0.01  # √χ²₃(0.95)
    cov = np.diag([4.0, 1.0, 0.01])
    sample = np.linalg.norm(np.random.default_rng(1).normal(size=(400_000, 3)) * np.sqrt(np.diag(cov)), axis=1)
    assert abs(float(norm_p95(cov)) / np.percentile(sample, 95) - 1) < 0.01
    assert abs(outlier_sigmas(10) - 4.033) < 0.01 and abs(outlier_sigmas(10_000) - 5.54) < 0.01


@pytest.mark.parametrize("name", ["plan", "100 mm cube", "10 at random"])
def test_predicted_p95_errors_match_monte_carlo(plan, name):
    """The first-order prediction against 400 noisy fits (1 mm per axis): rotation and every workspace point
    within 12 % (the p95 of 400 draws scatters by ≈ 6 %)."""
    base = np.array([p.tcp_mm for p in plan.poses]) if name == "plan" else WEAK_SETS[name]
    rot, at = predict_errors(base, 1.0)
    angle, mapped = draws(base, 1.0, 400)
    assert abs(np.percentile(angle, 95) / rot - 1) < 0.12, (np.percentile(angle, 95), rot)
    np.testing.assert_allclose(np.percentile(mapped, 95, axis=0), at, rtol=0.12)


def test_plan_poses_are_reachable_safe_visible_and_well_spread(plan):
    model = load_robot()
    safety = SafetyLayer(robot=model)
    tcp = np.array([p.tcp_mm for p in plan.poses])
    assert len(plan.poses) == 10 and len({tuple(t) for t in tcp}) == 10
    for pose in plan.poses:
        kin = forward_kinematics(np, model, pose.q)
        np.testing.assert_allclose(kin.gripper_centre * 1000, pose.tcp_mm, atol=0.1)
        np.testing.assert_allclose(kin.approach_axis, pose.approach, atol=1e-3)
        assert abs(pose.finger_axis[2]) < 1e-6 and 30 <= pose.tilt_deg <= 75
        safety.check_pose(pose.q)  # joint limits, workspace box, table
        cam = (pose.tcp_mm / 1000 - np.array(SCENE.camera.pos)) @ SCENE.camera.rot  # in the paper camera's view
        assert abs(cam[0] / cam[2]) < 960 / 2425.48 and abs(cam[1] / cam[2]) < 600 / 2425.33
    assert 40 <= tcp[:, 2].min() and tcp[:, 2].max() <= 400 and np.ptp(tcp[:, 2]) > 300
    assert np.ptp(tcp[:, 0]) >= 700 and np.ptp(tcp[:, 1]) >= 450  # wider than the target region (700 × 350 mm)
    # what it promises with 1 mm of noise per axis, against the hand-placed corners of DESIGN (0.160°, 1.27 mm)
    assert plan.rotation_p95_deg < 0.15 and plan.workspace_p95_mm < 1.2 and plan.centre_p95_mm < 0.95
    rot, at = predict_errors(DESIGN, 1.0)
    assert rot > 0.155 and at.max() > 1.25


def test_plan_with_1mm_noise_per_axis_passes_and_its_errors_are_as_predicted(plan):
    """--plan's 10 poses, 1 mm of noise per axis on every camera point, 60 calibrations: all accepted under the
    default limits; p95 0.14° and 1.2 mm (predicted 0.145°, 1.17 mm; the 0.5 mm some ask for is below the
    Cramér–Rao bound of ten pairs: σ/√10 per axis at the centroid alone is 0.88 mm at p95 in 3-D)."""
    base = np.array([p.tcp_mm for p in plan.poses])
    angle, mapped = [], []
    for seed in range(60):
        fit = fit_hand_eye(camera_points(base, 1.0, seed), base)  # default limits: refuses nothing here
        angle.append(rotation_angle_deg(fit.rotation, R_TRUE))
        mapped.append(mapped_error_mm(fit.rotation, fit.translation_mm))
        assert fit.quality.rotation_p95_deg <= 0.25 and fit.quality.workspace_p95_mm <= 2.0
    assert np.percentile(angle, 95) < 0.17 and np.percentile(mapped, 95) < 1.0
    floor = fit_hand_eye(camera_points(base, 0.1, 0), base).quality  # little noise: the assumed 1 mm holds
    assert floor.noise_mm == 1.0 and abs(floor.rotation_p95_deg - plan.rotation_p95_deg) < 1e-9


@pytest.mark.parametrize("name", list(WEAK_SETS))
def test_weak_sets_are_refused_naming_their_predicted_error(name):
    base = WEAK_SETS[name]
    with pytest.raises(HandEyeError, match=r"predicted p95 error rotation (\d+\.\d+)° > 0\.25°") as info:
        fit_hand_eye(camera_points(base, 1.0, 3), base)
    named = float(re.search(r"rotation (\d+\.\d+)°", str(info.value)).group(1))
    at_floor, _ = predict_errors(base, 1.0)  # the noise the draws have; the message's σ is max(1 mm, measured)
    assert named >= round(at_floor, 3) > 0.25
    angle, _ = draws(base, 1.0, 300, seed=11)
    assert abs(np.percentile(angle, 95) / at_floor - 1) < 0.15  # and it is what happens


def test_quality_warnings_outliers_noise_and_near_limit(plan):
    base = np.array([p.tcp_mm for p in plan.poses])
    cam = camera_points(base, 0.5, 4)
    cam[6] += [0.0, 0.0, 6.0]  # one misread pair: 6 mm off, far beyond 4 σ of 1 mm
    fit = fit_hand_eye(cam, base)
    assert fit.quality.outliers == (7,) and any("#7" in w for w in fit.quality.warnings)
    noisy = fit_hand_eye(camera_points(base, 2.0, 4), base, max_rot_deg=1.0, max_mm=5.0)  # 2 mm per axis
    assert 1.6 < noisy.quality.noise_mm < 2.5 and noisy.quality.noise_mm == noisy.quality.measured_noise_mm
    assert any("more than the 1 mm assumed" in w for w in noisy.quality.warnings)
    assert noisy.quality.rotation_p95_deg > plan.rotation_p95_deg * 1.6  # the prediction scales with the measured noise
    near = fit_hand_eye(camera_points(base, 0.3, 4), base, noise_mm=1.5)  # 0.216° of 0.25°: warned, accepted
    assert any("over 80% of its limit 0.25°" in w for w in near.quality.warnings)
    quiet = fit_hand_eye(camera_points(base, 1.0, 4), base)
    assert quiet.quality.warnings == () and quiet.quality.outliers == ()


def test_unit_check_on_many_pairs_names_the_rows_in_linear_memory():
    rng = np.random.default_rng(2)
    base = np.c_[rng.uniform(-350, 350, 10_000), rng.uniform(-650, -200, 10_000), rng.uniform(30, 400, 10_000)]
    cam = camera_points(base, 1.0, 2)
    tracemalloc.start()
    fit = fit_hand_eye(cam, base)  # the cap: N × N × 3 distances would be 2.4 GB
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 20e6, peak  # ≈ 9 MB
    assert fit.quality.rotation_p95_deg < 0.02 and fit.quality.outliers == ()
    mixed = cam[:500].copy()
    mixed[[6, 299]] /= 1000.0
    with pytest.raises(HandEyeError, match=r"pair\(s\) #7, #300 disagree in scale"):
        fit_hand_eye(mixed, base[:500])
    with pytest.raises(HandEyeError, match="camera points like metres"):
        fit_hand_eye(cam[:500] / 1000.0, base[:500])
    with pytest.raises(HandEyeError, match="10001 point pairs: at most 10000"):
        check_pairs(np.zeros((10_001, 3)), np.zeros((10_001, 3)))


def test_cli_refuses_150k_pairs_at_the_cap(tmp_path, capsys):
    pairs = tmp_path / "many.csv"
    pairs.write_text("cam_x,cam_y,cam_z,tcp_x,tcp_y,tcp_z\n" + "1.5,2.5,1300.5,10.5,-400.5,50.5\n" * 150_000)  # 5.5 MB
    out = tmp_path / "calibration.json"
    tracemalloc.start()
    assert calibrate.main(["--pairs", str(pairs), "--out", str(out)]) == 2
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    err = capsys.readouterr().err
    assert "more than 10000 point pairs" in err and "nothing written" in err and not out.exists()
    assert peak < 60e6, peak  # the file (5.5 MB) and at most 10,000 rows


def test_cli_weak_set_exit_2_and_quality_block(tmp_path, capsys, plan):
    weak = write_pairs(tmp_path / "weak.csv", camera_points(WEAK_SETS["100 mm cube"], 1.0), WEAK_SETS["100 mm cube"])
    out = tmp_path / "calibration.json"
    assert calibrate.main(["--pairs", weak, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert re.search(r"rotation \d\.\d+° > 0\.25° \(--max-rot-deg\); mapped workspace points \d+\.\d+ mm", err), err
    assert not out.exists()
    base = np.array([p.tcp_mm for p in plan.poses])
    good = write_pairs(tmp_path / "good.csv", camera_points(base, 1.0, 1), base)
    assert calibrate.main(["--pairs", good, "--out", str(out)]) == 0
    assert "predicted p95 error: rotation 0.14" in capsys.readouterr().out
    quality = json.loads(out.read_text())["quality"]
    assert quality["pairs"] == 10 and quality["noise_floor_mm"] == 1.0 and quality["limits"] == {"max_rot_deg": 0.25,
                                                                                                  "max_mm": 2.0}
    assert 0.14 < quality["predicted_p95_rotation_deg"] < 0.2 and 1.1 < quality["predicted_p95_workspace_mm"] < 1.6
    assert quality["spread_mm"][2] > 100 and quality["outliers"] == [] and quality["warnings"] == []
    # a tighter limit refuses the same pairs, naming the limit
    assert calibrate.main(["--pairs", good, "--out", str(tmp_path / "t.json"), "--max-rot-deg", "0.1"]) == 2
    assert "> 0.1° (--max-rot-deg)" in capsys.readouterr().err
    for bad in (["--noise-mm", "0"], ["--max-mm", "nan"], ["--max-rot-deg", "-1"]):
        assert calibrate.main(["--pairs", good, "--out", str(tmp_path / "b.json"), *bad]) == 2
        assert "must be a positive number" in capsys.readouterr().err


def test_cli_plan_writes_pairs_rows_to_fill_in(tmp_path, capsys, plan):
    out = tmp_path / "plan.csv"
    assert calibrate.main(["--plan", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "10 TCP poses" in text and re.search(r"rotation 0\.14\d°", text) and f"written {out}" in text
    rows = [line for line in out.read_text().splitlines() if line and not line.startswith("#")]
    assert rows[0] == "tcp_x,tcp_y,tcp_z,cam_x,cam_y,cam_z" and len(rows) == 11
    tcp = np.array([[float(v) for v in row.split(",")[:3]] for row in rows[1:]])
    np.testing.assert_allclose(tcp, [p.tcp_mm for p in plan.poses])
    assert calibrate.main(["--pairs", str(out), "--out", str(tmp_path / "c.json")]) == 2  # not filled in yet
    assert "cam_x, cam_y, cam_z empty" in capsys.readouterr().err
    cam = camera_points(tcp, 1.0, 9)  # what the camera saw at each pose
    filled = "\n".join(line if line.startswith("#") or not line.endswith(",,,") else
                       line[:-3] + "," + ",".join(f"{v:.3f}" for v in cam[int(k)])
                       for k, line in zip(np.cumsum([not ln.startswith("#") and ln.endswith(",,,") for ln in
                                                     out.read_text().splitlines()]) - 1, out.read_text().splitlines()))
    out.write_text(filled + "\n")
    assert calibrate.main(["--pairs", str(out), "--out", str(tmp_path / "c.json")]) == 0
    cal = CameraCalibration.from_file(str(tmp_path / "c.json"))
    assert rotation_angle_deg(cal.rotation, R_TRUE) < 0.25
    capsys.readouterr()
    assert calibrate.main(["--plan", "--json", "--plan-count", "4"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert len(record["poses"]) == 4 and len(record["poses"][0]["q_rad"]) == 6 and record["warnings"] == []
    assert calibrate.main(["--plan", "--plan-count", "3"]) == 2
    assert "plan between 4 and 100 poses" in capsys.readouterr().err
    assert calibrate.main(["--plan", "--pairs", str(out)]) == 2
    assert "--plan takes no --pairs" in capsys.readouterr().err
