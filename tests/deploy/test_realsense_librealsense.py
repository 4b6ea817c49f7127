"""librealsense itself on the twin's renders: ``deploy.realsense_record`` writes them as a recording (an
``rs.software_device`` through ``rs.recorder``) and ``deploy.cameras.RealSenseCamera`` plays it back through
``rs.pipeline``, ``rs.align`` and ``rs.pointcloud``, as it would run a camera.

What is real here: pyrealsense2's own classes on data (no camera: none has run here).  What is the twin's: the
frames (its optics and noise model).  The tests skip without pyrealsense2, or with it but without the system's
libusb-1.0 (``pip install "sagrasp_jax[realsense]"``; Debian: ``apt-get install libusb-1.0-0``).
"""

from __future__ import annotations

import datetime
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from sagrasp_jax.deploy import cameras
from sagrasp_jax.deploy.__main__ import main as deploy_main
from sagrasp_jax.task.camera import CAMERA_MODELS, Intrinsics

ENV = {**os.environ, "PYTHONWARNINGS": "ignore"}
D435_HALF = CAMERA_MODELS["realsense_d435"].intrinsics.scaled(0.5)  # 640 × 360, a D435 colour mode


@pytest.fixture(scope="module")
def rs():
    try:
        import pyrealsense2
    except ImportError as exc:  # absent, or installed without the system's libusb-1.0
        pytest.skip(f"pyrealsense2 does not import ({exc}): pip install \"sagrasp_jax[realsense]\" and the system's "
                    "libusb-1.0 (Debian: apt-get install libusb-1.0-0)")
    return pyrealsense2


def _frame(k: Intrinsics, seed: int = 0) -> cameras.Capture:
    """A synthetic capture on ``k``'s grid: a table at 1.41 m with a 50 mm step and some pixels without a return."""
    rng = np.random.default_rng(seed)
    z = np.full((k.height, k.width), 1410.0) + rng.uniform(-3, 3, (k.height, k.width))
    z[k.height // 3: k.height // 2, k.width // 3: k.width // 2] -= 50.0
    cloud = (k.rays() * z[..., None]).astype(np.float32)
    cloud[rng.random(z.shape) < 0.02] = np.nan
    rgb = rng.integers(0, 256, (k.height, k.width, 3), dtype=np.uint8)
    return cameras.Capture(rgb, cloud, k, "realsense_d435", "synthetic", "2026-01-02T03:04:05.678+00:00")


def _bound_mm(cloud: np.ndarray, depth_units: float) -> np.ndarray:
    """Per pixel, the most the z16 rounding moves a point: half a count along its ray (+ float32's share)."""
    ray = np.linalg.norm(cloud / cloud[..., 2:3], axis=-1)
    return 0.5 * 1000.0 * depth_units * ray + 1e-3


# ---- pure helpers (no librealsense) ----


def test_a_recording_address_is_told_from_a_serial(tmp_path) -> None:
    assert cameras.is_recording("scene.db3") and cameras.is_recording("old/scene.BAG")
    assert cameras.is_recording(os.path.join("dir", "scene"))
    assert not cameras.is_recording("0123456789")
    (tmp_path / "notes.txt").write_text("x")
    assert cameras.is_recording(str(tmp_path / "notes.txt"))  # an existing file: refused later as not a recording
    assert cameras.realsense_model("Intel RealSense D435") == "realsense_d435"
    assert cameras.realsense_model("Intel RealSense D435I") == "realsense_d435"
    assert cameras.realsense_model("") == "realsense_d435"
    assert cameras.realsense_model("Intel RealSense D415") == ""  # another RealSense: not a model described here
    assert cameras.realsense_model("sagrasp_jax twin render of mecheye_pro_m") == "mecheye_pro_m"


# ---- (a) a frame through a recording and back ----


@pytest.mark.parametrize("depth_units", [0.001, 0.0001])
def test_a_recording_plays_back_the_same_cloud_to_the_depth_quantisation(rs, tmp_path, depth_units: float) -> None:
    from sagrasp_jax.deploy import realsense_record

    frames = [_frame(D435_HALF, 0), _frame(D435_HALF, 1)]
    path = str(tmp_path / "two.db3")
    written = realsense_record.write_bag(path, frames, depth_units=depth_units)
    assert written == realsense_record.Recorded(path, 2, depth_units, 640, 360)
    camera = cameras.RealSenseCamera(path)
    try:
        for i, frame in enumerate(frames):  # every frame set, in order (played not in real time)
            cap = camera.capture()
            valid = np.isfinite(frame.cloud_mm).all(axis=-1)
            assert np.array_equal(np.isfinite(cap.cloud_mm).all(axis=-1), valid)  # no pixel lost or added by rs.align
            err = np.linalg.norm(cap.cloud_mm[valid].astype(np.float64) - frame.cloud_mm[valid], axis=-1)
            assert np.all(err <= _bound_mm(frame.cloud_mm[valid], depth_units))
            assert err.max() > 0.2 * 1000 * depth_units  # rounded, as z16 is: not the float cloud passed through
            assert np.array_equal(cap.rgb, frame.rgb)
            assert cap.intrinsics == D435_HALF  # the colour stream's, as written (exact in float32 here)
            assert cap.camera == "realsense_d435" and cap.source == f"realsense {path}"
            taken = datetime.datetime.fromisoformat(cap.time_utc) - datetime.datetime.fromisoformat(frames[0].time_utc)
            assert abs(taken.total_seconds() - i / 30) <= 0.001 and cap.truth is None  # the first's time, 1/30 s apart
        with pytest.raises(cameras.CameraError, match="no more frames with depth and colour"):
            camera.capture()
    finally:
        camera.close()


def test_without_the_align_nudge_rs_align_loses_pixels_on_one_grid(rs, tmp_path, monkeypatch) -> None:
    """Why the recording's depth stream declares its principal point 0.02 px off (realsense_record's docstring):
    with the colour's intrinsics exactly, librealsense's align drops whole rows and columns of the same grid."""
    from sagrasp_jax.deploy import realsense_record

    monkeypatch.setattr(realsense_record, "ALIGN_NUDGE_PX", 0.0)
    monkeypatch.setattr(realsense_record, "ALIGN_FOV_SHRINK", 0.0)
    frame = _frame(D435_HALF)
    cap = realsense_record.through_librealsense(frame, folder=str(tmp_path))
    lost = realsense_record.cloud_error_mm(frame.cloud_mm, cap.cloud_mm)["lost"]
    assert lost > 0.01 * np.isfinite(frame.cloud_mm).all(axis=-1).sum()


def test_a_twin_render_through_librealsense(rs, tmp_path) -> None:
    pytest.importorskip("pybullet")
    from sagrasp_jax.deploy import rehearse, realsense_record
    from sagrasp_jax.deploy.twin import PyBulletTwin
    from sagrasp_jax.task.config import EnvConfig

    env = EnvConfig()
    spec, rng = rehearse.draw_scene(env, 0, 2)
    with PyBulletTwin(spec, env, q0=spec.q0, seed=2) as twin:
        capture = rehearse.twin_capture(twin, spec, rehearse.CameraSettings("consumer", 0.5, "realsense_d435"), rng)
    seen = realsense_record.through_librealsense(capture, folder=str(tmp_path))
    err = realsense_record.cloud_error_mm(capture.cloud_mm, seen.cloud_mm)
    assert err["lost"] == err["added"] == 0 and err["max_mm"] <= 0.5 * 1.25 + 1e-3  # 1 mm counts, rays within 39°
    assert seen.intrinsics == capture.intrinsics == D435_HALF and np.array_equal(seen.rgb, capture.rgb)
    assert seen.truth == capture.truth and seen.source == "twin through librealsense"
    assert os.listdir(tmp_path) == []  # the recording is removed


# ---- (b) deploy --camera realsense on a recording, end to end ----


def _run(*args: str, cwd: str | os.PathLike[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, env=ENV, capture_output=True, text=True, timeout=300)


def test_deploy_camera_realsense_on_a_recording_holds_the_cube(rs, tmp_path) -> None:
    """A D435 twin capture (scene 2 of seed 0: an obstacle scene) that ``--camera replay:`` holds on the twin, written
    as a recording: ``deploy --camera realsense --camera-address scene.db3`` holds it too, from librealsense's cloud
    (the twin then stands where perception put the cube: a recording holds no true scene)."""
    pytest.importorskip("pybullet")
    from sagrasp_jax.deploy import capture_file, realsense_record

    npz = tmp_path / "scene.npz"
    r = _run("sagrasp_jax.capture", "--camera", "twin", "--camera-model", "realsense_d435", "--camera-resolution",
             "0.5", "--scene", "2", "--out", str(npz), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    capture = capture_file.load_capture(str(npz))
    assert capture.truth["kind"] == "obstacle"
    r = _run("sagrasp_jax.deploy", "--camera", f"replay:{npz}", "--policy", "pretrained", "--json", "--record",
             str(tmp_path / "replay"), cwd=tmp_path)
    assert r.returncode == 0 and json.loads(r.stdout)["held"] is True, r.stderr
    bag = str(tmp_path / "scene.db3")
    realsense_record.write_bag(bag, [capture])
    record = tmp_path / "record"
    r = _run("sagrasp_jax.deploy", "--camera", "realsense", "--camera-address", bag, "--policy", "pretrained",
             "--backend", "twin", "--json", "--record", str(record), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    report = json.loads(r.stdout)
    assert report["outcome"] == "success" and report["held"] is True
    given = report["input"]["capture"]
    assert given["camera"] == "realsense_d435" and given["source"] == f"realsense {bag}"
    assert given["pixels"] == [640, 360] and given["intrinsics"] == D435_HALF.as_list()
    seen = report["input"]["perception"]
    assert np.linalg.norm(np.subtract(seen["target_world"], capture.truth["target_pos"])) < 0.005
    assert len(seen["obstacles_world"]) == len(capture.truth["obstacles"])
    assert sorted(os.listdir(record)) == ["capture.npz", "report.json"]
    saved = capture_file.load_capture(str(record / "capture.npz"))
    assert saved.intrinsics == D435_HALF and saved.truth is None


# ---- (c) refusals ----


def _refused(capsys, address: str) -> str:
    record = os.path.join(os.path.dirname(address), "record-" + os.path.basename(address))
    code = deploy_main(["--camera", "realsense", "--camera-address", address, "--policy", "pretrained", "--backend",
                        "twin", "--record", record])
    err = capsys.readouterr().err
    assert code == 2, err
    return err


def test_deploy_refuses_a_missing_or_foreign_recording(rs, tmp_path, capsys) -> None:
    missing = str(tmp_path / "missing.db3")
    assert f"refused before moving: RealSense recording {missing}: no such file" in _refused(capsys, missing)
    for name, content in (("notes.txt", "not a recording"), ("text.db3", "not a database"), ("text.bag", "hello")):
        path = tmp_path / name
        path.write_text(content)
        err = _refused(capsys, str(path))
        assert f"RealSense recording {path}: not a librealsense recording" in err, err


def test_a_recording_without_colour_is_refused_naming_what_it_holds(rs, tmp_path) -> None:
    k = Intrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)
    path = str(tmp_path / "depth_only.db3")

    def record() -> None:
        device = rs.software_device()
        sensor = device.add_sensor("Stereo Module")
        stream = rs.video_stream()
        stream.type, stream.index, stream.uid, stream.width, stream.height = rs.stream.depth, 0, 0, k.width, k.height
        stream.fps, stream.bpp, stream.fmt = 30, 2, rs.format.z16
        intr = rs.intrinsics()
        intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy = k.width, k.height, k.fx, k.fy, k.cx, k.cy
        stream.intrinsics = intr
        profile = sensor.add_video_stream(stream).as_video_stream_profile()
        recorder = rs.recorder(path, device)
        wrapped = recorder.query_sensors()[0]
        wrapped.open(profile)
        wrapped.start(lambda f: None)
        frame = rs.software_video_frame()
        frame.pixels, frame.bpp, frame.stride, frame.timestamp = np.full((k.height, k.width), 1400, np.uint16), 2, \
            2 * k.width, 0.0
        frame.domain, frame.frame_number, frame.profile = rs.timestamp_domain.system_time, 1, profile
        sensor.on_video_frame(frame)
        wrapped.stop()
        wrapped.close()

    record()
    with pytest.raises(cameras.CameraError, match="depth_only.db3: needs a depth and a colour stream; it holds depth"):
        cameras.RealSenseCamera(path)


def test_write_bag_refuses_what_it_cannot_record(rs, tmp_path) -> None:
    from sagrasp_jax.deploy import realsense_record

    frame = _frame(Intrinsics(32, 24, 30.0, 30.0, 15.5, 11.5))
    with pytest.raises(ValueError, match="must end in .db3"):
        realsense_record.write_bag(str(tmp_path / "scene.bag"), [frame])
    with pytest.raises(ValueError, match="depth units 0.01 m"):
        realsense_record.write_bag(str(tmp_path / "scene.db3"), [frame], depth_units=0.01)
    far = frame._replace(cloud_mm=frame.cloud_mm * np.float32(5.0))  # 7 m: beyond z16 at 0.1 mm
    with pytest.raises(ValueError, match="does not fit z16 at 0.0001 m"):
        realsense_record.write_bag(str(tmp_path / "scene.db3"), [far], depth_units=0.0001)
    with pytest.raises(ValueError, match="intrinsics"):
        realsense_record.write_bag(str(tmp_path / "scene.db3"), [frame, _frame(D435_HALF)])


# ---- the rehearsal's driver ----


def test_rehearse_camera_driver_realsense_routes_the_capture_through_librealsense(rs) -> None:
    pytest.importorskip("pybullet")
    from sagrasp_jax.deploy import rehearse
    from sagrasp_jax.task.policy_file import load_policy

    env = rehearse.condition_env(load_policy("pretrained").env_config(), "kinematic")
    camera = rehearse.CameraSettings("consumer", 0.5, "realsense_d435", "realsense")
    record = rehearse.run_scene("pretrained", env, env, 0, 2, camera)
    assert record["held"] and record["librealsense"]["lost"] == 0 and record["librealsense"]["max_mm"] < 0.7
    assert camera.describe()["driver"] == "realsense"
    assert "driver" not in camera._replace(driver="twin").describe()  # a twin-driver result names its camera as before
