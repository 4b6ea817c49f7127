"""Camera → base transform of docs/task.md §5 and the target checks before the arm moves."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sagrasp_jax.task.config import SamplingConfig
from sagrasp_jax.deploy.calibration import (
    T_CAM_BASE_MM,
    CalibrationError,
    CameraCalibration,
    TargetRejected,
    detected_top_to_cube_centre,
    validate_target,
)

CAMERA_ORIGIN_M = np.array([-0.16208, -0.40337, 1.40824])


def test_default_matches_spec_by_hand():
    # The printed matrix itself (docs/task.md §5), so an edit of the shared copy in scene.py shows up here.
    assert T_CAM_BASE_MM[0].tolist() == [-0.9961, 0.0219, 0.0854, -162.08]
    assert T_CAM_BASE_MM[2].tolist() == [-0.0848, 0.0265, -0.9960, 1408.24]
    cal = CameraCalibration.default()
    np.testing.assert_allclose(cal.cam_to_base([0.0, 0.0, 0.0]), CAMERA_ORIGIN_M, atol=1e-12)
    np.testing.assert_allclose(cal.camera_position, CAMERA_ORIGIN_M, atol=1e-12)
    # 1 m along the optical axis: t + third column of R (printed 0.0854, 0.0246, -0.9960).
    np.testing.assert_allclose(cal.cam_to_base([0.0, 0.0, 1.0]), [-0.07668, -0.37877, 0.41224], atol=2e-4)
    # Same point given in millimetres.
    np.testing.assert_allclose(cal.cam_to_base([0.0, 0.0, 1000.0], units="mm"), cal.cam_to_base([0, 0, 1]), atol=1e-12)
    # The optical axis meets the table near (-0.04, -0.37) (docs/task.md §1).
    axis = cal.matrix[:3, 2]
    hit = CAMERA_ORIGIN_M - CAMERA_ORIGIN_M[2] / axis[2] * axis
    assert abs(hit[0] + 0.04) < 0.005 and abs(hit[1] + 0.37) < 0.005


def test_rotation_reorthonormalised():
    cal = CameraCalibration.default()
    rot = cal.rotation
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(rot) - 1.0) < 1e-12
    assert 5e-5 < cal.orthonormality_error < 1e-4  # the printed matrix is off by ≈ 9e-5
    assert np.abs(rot - T_CAM_BASE_MM[:3, :3]).max() < 2e-4


def test_round_trip_with_base_corrections():
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, (50, 3)) + [0, 0, 1.2]
    for cal in (CameraCalibration.default(), CameraCalibration.default(base_z_offset=-0.03, base_yaw=0.4)):
        np.testing.assert_allclose(cal.base_to_cam(cal.cam_to_base(points)), points, atol=1e-12)
        np.testing.assert_allclose(cal.cam_to_base(cal.base_to_cam(points)), points, atol=1e-12)
        mm = cal.base_to_cam(points, units="mm")
        np.testing.assert_allclose(mm, cal.base_to_cam(points) * 1000, atol=1e-9)
        np.testing.assert_allclose(cal.cam_to_base(mm, units="mm"), points, atol=1e-12)


def test_base_yaw_and_z_offset_apply_after_camera_transform():
    cal = CameraCalibration.default(base_z_offset=0.03, base_yaw=math.pi / 2)
    # Rz(90°)·(x, y, z) = (−y, x, z), then +0.03 in z.
    np.testing.assert_allclose(cal.cam_to_base([0, 0, 0]), [0.40337, -0.16208, 1.43824], atol=1e-12)


def test_corrupted_matrices_refused():
    typo = T_CAM_BASE_MM.copy()
    typo[0, 1] = 0.0319  # one mistyped digit
    with pytest.raises(CalibrationError, match="not orthonormal"):
        CameraCalibration.from_matrix(typo)
    mirrored = T_CAM_BASE_MM.copy()
    mirrored[:3, 0] *= -1
    with pytest.raises(CalibrationError, match=r"det -0\.9999.* ≤ 0 \(a reflection"):
        CameraCalibration.from_matrix(mirrored)
    nan = T_CAM_BASE_MM.copy()
    nan[1, 3] = np.nan
    with pytest.raises(CalibrationError, match="NaN"):
        CameraCalibration.from_matrix(nan)
    row = T_CAM_BASE_MM.copy()
    row[3, 0] = 1.0
    with pytest.raises(CalibrationError, match="last row"):
        CameraCalibration.from_matrix(row)
    with pytest.raises(CalibrationError, match="4×4"):
        CameraCalibration.from_matrix(T_CAM_BASE_MM[:3])
    # The printed matrix's own error (≈ 9e-5) is accepted; 2e-3 is not.
    off = T_CAM_BASE_MM.copy()
    off[:3, :3] *= 1.002
    with pytest.raises(CalibrationError, match=r"max\|RᵀR − I\|"):
        CameraCalibration.from_matrix(off)


def test_units(tmp_path):
    metres = T_CAM_BASE_MM.copy()
    metres[:3, 3] /= 1000
    a = CameraCalibration.from_matrix(metres, units="m")
    np.testing.assert_allclose(a.matrix, CameraCalibration.default().matrix, atol=1e-12)
    with pytest.raises(CalibrationError, match="units='m'"):
        CameraCalibration.from_matrix(T_CAM_BASE_MM, units="m")  # mm read as metres: 1.5 km away
    with pytest.raises(ValueError, match="'mm' or 'm'"):
        CameraCalibration.from_matrix(T_CAM_BASE_MM, units="cm")


def test_files(tmp_path):
    expected = CameraCalibration.default().matrix
    (tmp_path / "list.json").write_text(json.dumps(T_CAM_BASE_MM.tolist()))
    (tmp_path / "obj.json").write_text(json.dumps({"T_cam_base": T_CAM_BASE_MM.tolist(), "note": "paper"}))
    np.save(tmp_path / "cal.npy", T_CAM_BASE_MM)
    np.savetxt(tmp_path / "cal.txt", T_CAM_BASE_MM)
    for name in ("list.json", "obj.json", "cal.npy", "cal.txt"):
        cal = CameraCalibration.from_file(tmp_path / name)
        np.testing.assert_allclose(cal.matrix, expected, atol=1e-12)
        assert cal.source.endswith(name)
    bad = T_CAM_BASE_MM.copy()
    bad[2, 2] = -0.90
    np.savetxt(tmp_path / "bad.txt", bad)
    with pytest.raises(CalibrationError, match="bad.txt: rotation is not orthonormal"):
        CameraCalibration.from_file(tmp_path / "bad.txt")
    (tmp_path / "broken.json").write_text("[[1, 2], [3")
    with pytest.raises(CalibrationError, match="broken.json: cannot read"):
        CameraCalibration.from_file(tmp_path / "broken.json")
    with pytest.raises(CalibrationError, match="missing.npy: calibration file not found"):
        CameraCalibration.from_file(tmp_path / "missing.npy")


def test_detection_pipeline_end_to_end():
    cal = CameraCalibration.default()
    centre = np.array([0.12, -0.45, 0.025])
    top_cam_mm = cal.base_to_cam(centre + [0, 0, 0.025], units="mm")  # what the depth camera reports
    assert 1300 < top_cam_mm[2] < 1400  # ≈ 1.36 m in front of the camera
    found = validate_target(detected_top_to_cube_centre(cal.cam_to_base(top_cam_mm, units="mm")))
    np.testing.assert_allclose(found, centre, atol=1e-12)


def test_detected_top_to_centre():
    np.testing.assert_allclose(detected_top_to_cube_centre([0.1, -0.4, 0.05]), [0.1, -0.4, 0.025])
    np.testing.assert_allclose(detected_top_to_cube_centre([[0, 0, 0.06]] * 2), [[0, 0, 0.035]] * 2)


def test_validate_target():
    cfg = SamplingConfig()
    for ok in ([0.0, -0.40, 0.025], [0.36, -0.40, 0.015], [-0.30, -0.58, 0.035], [0.0, -0.24, 0.02]):
        validate_target(ok, cfg)
    cases = [
        ([0.38, -0.40, 0.025], r"x = 0\.3800 m is outside \[-0\.3700, 0\.3700\] m"),
        ([0.00, -0.20, 0.025], r"y = -0\.2000 m is outside \[-0\.6200, -0\.2300\] m"),
        ([0.37, -0.62, 0.025], r"√\(x²\+y²\) = 0\.7220 m is outside \[0\.2300, 0\.6700\] m"),
        ([0.00, -0.40, 0.050], r"z = 0\.0500 m is outside \[0\.015, 0\.035\] m"),
        ([0.00, -0.40, 0.010], r"z = 0\.0100 m"),
        ([np.nan, -0.40, 0.025], "NaN"),
    ]
    for point, message in cases:
        with pytest.raises(TargetRejected, match=message):
            validate_target(point, cfg)
    with pytest.raises(TargetRejected, match="x = .*; .*z = "):
        validate_target([0.5, -0.40, 0.1], cfg)  # every violation is listed
    validate_target([0.38, -0.40, 0.025], cfg, margin=0.05)
    with pytest.raises(TargetRejected, match=r"\[-0\.3400, 0\.3400\]"):
        validate_target([0.345, -0.40, 0.025], cfg, margin=-0.01)

