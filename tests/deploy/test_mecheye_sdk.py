"""The Mech-Eye path against Mech-Mind's real SDK (``mecheyeapi`` 2.6, the ``[mecheye]`` extra) with no camera.

What is real here: the SDK's ``Camera.connect`` against loopback (nothing listening; a listener on the SDK's port
5577 that accepts and says nothing), through ``MechEyeCamera``, ``open_camera`` and the ``capture`` and ``deploy``
commands; the SDK's own containers (``CameraIntrinsics``, ``CameraResolutions``, ``CameraInfo``,
``TexturedPointCloud``, ``ErrorStatus``) built and filled without a device.  What is a test double: the connected
camera in ``test_capture_fills_intrinsics_model_source_and_time`` (an object with ``capture_2d_and_3d``'s name
that hands back a hand-filled cloud), which checks ``MechEyeCamera.capture``'s own wiring only.  No Mech-Eye
camera was reached: what never ran is listed in ``deploy.cameras``'s module docstring.
"""

from __future__ import annotations

import datetime
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np
import pytest

from sagrasp_jax.deploy import cameras
from sagrasp_jax.task.camera import CAMERA_MODELS

try:
    import mecheye.area_scan_3d_camera as sdk
    import mecheye.shared as shared
except ImportError as exc:  # wheels for CPython 3.7-3.11 only
    pytest.skip(f"Mech-Mind's mecheyeapi does not import here ({exc}): pip install \"sagrasp_jax[mecheye]\" "
                "(CPython <= 3.11)", allow_module_level=True)

PORT = cameras.MECHEYE_PORT
MARGIN_S = 1.5  # a loaded 2-core machine's start-up and scheduling on top of a timeout
PRO_M = CAMERA_MODELS["mecheye_pro_m"].intrinsics


def _port_taken() -> bool:
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", PORT)) == 0


@pytest.fixture
def nothing_listening() -> None:
    if _port_taken():
        pytest.skip(f"something listens on 127.0.0.1:{PORT}")


@pytest.fixture
def silent_listener():
    """A listener on 127.0.0.1:5577 (the only port the SDK connects to) that accepts (the kernel's backlog) and never
    says anything: a host where something answers TCP but no camera's server."""
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        srv.bind(("127.0.0.1", PORT))
    except OSError as exc:
        srv.close()
        pytest.skip(f"127.0.0.1:{PORT} is taken ({exc}); the SDK connects to that port only")
    srv.listen(32)
    yield srv
    srv.close()


def _run(*args: str) -> tuple[subprocess.CompletedProcess, float]:
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, timeout=90)
    return done, time.monotonic() - t0


# ---- the SDK's connect, no camera ----


def test_nothing_listening_is_refused_at_once(nothing_listening) -> None:
    t0 = time.monotonic()
    with pytest.raises(cameras.CameraError) as refused:
        cameras.open_camera("mecheye", "127.0.0.1")
    elapsed = time.monotonic() - t0
    message = str(refused.value)
    assert message.startswith("Mech-Eye camera at 127.0.0.1: connect failed")
    assert f"TCP port {PORT} (connection refused; timeout 5 s)" in message and "\n" not in message
    assert elapsed < 1.0 + MARGIN_S  # the SDK alone takes 1.0 s here, more where ping waits


def test_silent_listener_gives_the_sdks_code_within_the_timeout(silent_listener, capfd) -> None:
    t0 = time.monotonic()
    with pytest.raises(cameras.CameraError) as refused:
        cameras.MechEyeCamera("127.0.0.1", timeout_s=2.0)
    elapsed = time.monotonic() - t0
    message = str(refused.value)
    assert message.startswith("Mech-Eye camera at 127.0.0.1: connect failed after ")
    assert "(timeout 2 s)" in message and "Failed to connect to the Mech-Eye Industrial 3D Camera" in message
    # -2 DEVICE_OFFLINE where ping fails or is absent (then the message says so), -9 TIMEOUT_ERROR where it answers
    assert "(SDK code -2 DEVICE_OFFLINE)" in message or "(SDK code -9 TIMEOUT_ERROR)" in message
    assert ("iputils-ping" in message) == ("code -2" in message and shutil.which("ping") is None)
    assert elapsed < 2.0 + MARGIN_S
    out, err = capfd.readouterr()
    assert out == "" and err == ""  # the SDK's own lines (ping, "Network request timed out") were held


def test_sdk_refuses_host_names_and_files_before_connecting() -> None:
    for address, says in [("localhost", "takes no host names"), ("/data/scene.mraw", "replay a capture file"),
                          ("256.1.1.1", "IPv4 address")]:
        t0 = time.monotonic()
        with pytest.raises(cameras.CameraError) as refused:
            cameras.MechEyeCamera(address)
        assert time.monotonic() - t0 < 0.5
        assert str(refused.value).startswith(f"Mech-Eye camera address '{address}' must be an IPv4 address")
        assert says in str(refused.value)
    status = sdk.Camera().connect("localhost", 1000)  # the SDK says the same of a name: no DNS
    assert status.error_code == shared.ErrorStatus.MMIND_STATUS_INVALID_INPUT_ERROR


def test_sdk_output_is_held_off_stdout(capfd) -> None:
    def noisy(a: int) -> int:
        os.write(1, b"Logger: [loadConfig] Key not found\n")
        os.write(2, b"sh: 1: ping: not found\n")
        return a + 1

    result, written = cameras._held_output(noisy, 41)
    assert result == 42 and written == "Logger: [loadConfig] Key not found\nsh: 1: ping: not found\n"
    assert capfd.readouterr() == ("", "")


# ---- the commands ----


def test_capture_command_refuses_with_one_line_and_writes_nothing(tmp_path, silent_listener) -> None:
    out = tmp_path / "x.npz"
    done, elapsed = _run("sagrasp_jax.capture", "--camera", "mecheye", "--camera-address", "127.0.0.1",
                         "--out", str(out))
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: Mech-Eye camera at 127.0.0.1: connect failed after "), lines
    assert "SDK code" in lines[0] and "(timeout 5 s)" in lines[0] and done.stdout == ""
    assert not out.exists() and list(tmp_path.iterdir()) == []
    assert elapsed < 30  # and the interpreter exited: a failed SDK Camera left to its exit hangs it


def test_deploy_refuses_as_json_naming_the_camera(tmp_path, silent_listener) -> None:
    record = tmp_path / "rec"
    done, _ = _run("sagrasp_jax.deploy", "--camera", "mecheye", "--camera-address", "127.0.0.1", "--policy",
                   "pretrained", "--json", "--record", str(record))
    assert done.returncode == 2, done.stderr
    report = json.loads(done.stdout)  # stdout is the JSON alone: none of the SDK's lines
    assert report["outcome"] == "input_refused" and report["input"]["camera"] == "mecheye"
    assert report["message"].startswith("Mech-Eye camera at 127.0.0.1: connect failed after ")
    assert not (record / "capture.npz").exists()


# ---- the SDK's containers, no device ----


def _sdk_intrinsics(depth: tuple[float, float, float, float], texture: tuple[float, float, float, float]):
    k = sdk.CameraIntrinsics()
    for cam, (fx, fy, cx, cy) in ((k.depth, depth), (k.texture, texture)):
        cam.camera_matrix.fx, cam.camera_matrix.fy, cam.camera_matrix.cx, cam.camera_matrix.cy = fx, fy, cx, cy
    return k


def _sdk_resolutions(width: int, height: int):
    r = sdk.CameraResolutions()
    r.depth.width, r.depth.height = width, height
    r.texture.width, r.texture.height = width, height
    return r


def test_intrinsics_from_the_sdks_objects() -> None:
    k = _sdk_intrinsics((PRO_M.fx, PRO_M.fy, PRO_M.cx, PRO_M.cy), (2000.0, 2000.0, 950.0, 600.0))
    got = cameras.mecheye_intrinsics(k, _sdk_resolutions(1920, 1200), 1200, 1920)
    assert got == PRO_M  # the depth camera's, not the texture camera's
    assert cameras.mecheye_intrinsics(k, _sdk_resolutions(1920, 1200), 600, 960) is None  # not the cloud's grid
    assert cameras.mecheye_intrinsics(sdk.CameraIntrinsics(), _sdk_resolutions(1920, 1200), 1200, 1920) is None


def test_model_from_camera_info() -> None:
    info = sdk.CameraInfo()
    for model, name in [("Mech-Eye PRO M", "mecheye_pro_m"), ("Mech-Eye Pro M Enhanced", "mecheye_pro_m"),
                        ("PRO M", "mecheye_pro_m"), ("Mech-Eye NANO", ""), ("Mech-Eye PRO S", ""), ("", "")]:
        info.model = model
        assert cameras.mecheye_model(info.model) == name, model


def test_capture_fills_intrinsics_model_source_and_time() -> None:
    """``MechEyeCamera.capture``'s wiring with a test double for the connected SDK camera."""
    cloud = sdk.TexturedPointCloud()
    cloud.resize(16, 10)
    p = cloud.at(5, 8)
    p.x, p.y, p.z, p.b, p.g, p.r = 1.0, 2.0, 1400.0, 10, 20, 30

    class Frame:
        def get_textured_point_cloud(self):
            return cloud

    calls = []

    class Connected:  # the test double: the SDK camera after a successful connect
        def capture_2d_and_3d(self, frame, timeout_ms):
            calls.append(timeout_ms)
            return shared.ErrorStatus()

        def disconnect(self):
            calls.append("disconnect")

    camera = object.__new__(cameras.MechEyeCamera)
    camera.ip, camera.capture_timeout_ms, camera.model = "192.168.1.10", 10000, "mecheye_pro_m"
    camera.source = "mecheye 192.168.1.10 ABC123"
    camera._camera, camera._shared = Connected(), shared
    camera._sdk = SimpleNamespace(Frame2DAnd3D=Frame)
    camera._intrinsics = _sdk_intrinsics((20.0, 20.0, 7.5, 4.5), (1.0, 1.0, 0.0, 0.0))
    camera._resolutions = _sdk_resolutions(16, 10)
    before = datetime.datetime.now(datetime.timezone.utc)
    cap = camera.capture()
    assert calls == [10000]
    assert cap.cloud_mm.shape == (10, 16, 3) and cap.rgb[5, 8].tolist() == [30, 20, 10]
    np.testing.assert_allclose(cap.cloud_mm[5, 8], [1.0, 2.0, 1400.0])
    assert cap.intrinsics is not None and cap.intrinsics.as_list() == [16, 10, 20.0, 20.0, 7.5, 4.5]
    assert (cap.camera, cap.source) == ("mecheye_pro_m", "mecheye 192.168.1.10 ABC123")
    taken = datetime.datetime.fromisoformat(cap.time_utc)
    assert before - datetime.timedelta(seconds=1) <= taken <= datetime.datetime.now(datetime.timezone.utc)
    camera._resolutions = _sdk_resolutions(32, 20)  # a depth map of another size: no intrinsics rather than wrong ones
    assert camera.capture().intrinsics is None
    Connected.capture_2d_and_3d = lambda self, frame, timeout_ms: shared.ErrorStatus(
        shared.ErrorStatus.MMIND_STATUS_TIMEOUT_ERROR, "Command execution timed out.")
    with pytest.raises(cameras.CameraError, match=r"capture_2d_and_3d \(timeout 10 s\) failed: Command execution timed "
                                                  r"out\. \(SDK code -9 TIMEOUT_ERROR\)"):
        camera.capture()
    assert calls[-1] == "disconnect" and camera._camera is None
    with pytest.raises(cameras.CameraError, match="closed"):
        camera.capture()
