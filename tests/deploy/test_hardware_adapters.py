"""Hardware adapters as far as they run without the hardware: the AUBO-i5 (``deploy.aubo``, pyaubo-sdk) and the
Mech-Eye / RealSense cameras (``deploy.cameras``).

What is real here: the vendors' SDKs (when installed) against loopback sockets — a refused port, a port that
accepts and never answers — and the SDKs' own frame objects built without a device (a Mech-Eye
``TexturedPointCloud``, a RealSense software device's depth frame through ``rs.pointcloud``).  What is a test
double: ``FakeController``, an object with the SDK client's method names that records the calls; the tests that
use it check the adapter's own logic (the dry run reads and commands nothing, the servo parameters, the refusals,
the close), never the controller's behaviour, which nothing here has seen.
"""

from __future__ import annotations

import json
import socket
import sys
import time
from typing import Any

import numpy as np
import pytest

from sagrasp_jax.base import extras
from sagrasp_jax.task.config import HOME_Q, get_config
from sagrasp_jax.deploy import aubo, cameras
from sagrasp_jax.deploy.__main__ import main as deploy_main
from sagrasp_jax.deploy.aubo import (
    AuboConnectionError, AuboError, AuboRobot, AuboSettings, GripperIO, ToolOutput, check_ready, home_check,
    joints_from_controller, joints_to_controller, servo_limits,
)
from sagrasp_jax.deploy.calibration import CameraCalibration
from sagrasp_jax.deploy.safety import DeploySettings, SafetyLayer, SafetyViolation
from sagrasp_jax.task.policy_file import save_policy_npz

HOME = np.array(HOME_Q)


def closed_port() -> int:
    """A loopback port nothing listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def listener():
    """A loopback socket that accepts connections (the kernel's backlog) and never answers."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    yield srv.getsockname()[1]
    srv.close()


# ---- AUBO: pure conversions ----


def test_joint_conversion_applies_the_offset_and_refuses_bad_readings() -> None:
    offset = (0.1, 0.0, -0.2, 0.0, 0.0, 0.3)
    reading = [1.0, -0.5, -1.8, 0.25, -1.57, 0.0]  # RobotState.getJointPositions() returns a list of 6 floats
    q = joints_from_controller(reading, offset)
    np.testing.assert_allclose(q, [0.9, -0.5, -1.6, 0.25, -1.57, -0.3])
    np.testing.assert_allclose(joints_to_controller(q, offset), reading)
    assert isinstance(joints_to_controller(q, offset), list)
    for bad in ([0.0] * 5, [0.0] * 5 + [float("nan")], [], None):
        with pytest.raises(AuboError, match="expected 6 finite angles"):
            joints_from_controller(bad)


def test_servo_speed_and_acceleration_come_from_the_deploy_settings() -> None:
    speed, acc = servo_limits(SafetyLayer())  # defaults: max_step 0.05 rad per 0.05 s period binds every joint
    assert speed == pytest.approx(1.0) and acc == pytest.approx(20.0)
    speed, acc = servo_limits(SafetyLayer(DeploySettings(max_step=0.02)))
    assert speed == pytest.approx(0.4) and acc == pytest.approx(8.0)
    assert aubo.lookahead(AuboSettings(), 0.05) == pytest.approx(0.05)
    assert aubo.lookahead(AuboSettings(), 0.01) == pytest.approx(0.03)  # the SDK's range [0.03, 0.2]


def test_home_check() -> None:
    near = HOME + np.array([0.0, 0.04, 0.0, -0.049, 0.0, 0.0])
    check = home_check(near, HOME, 0.05)
    assert check.at_home and check.max_error == pytest.approx(0.049)
    far = HOME + np.array([0.0, 0.0, 0.2, 0.0, 0.0, 0.0])
    check = home_check(far, HOME, 0.05)
    assert not check.at_home and check.max_error == pytest.approx(0.2) and check.error[2] == pytest.approx(0.2)


def test_gripper_io_parses_and_refuses() -> None:
    io = GripperIO.parse("close=1:1+2:0,open=1:0+2:1,settle=0.5")
    assert io.close == (ToolOutput(1, True), ToolOutput(2, False)) and io.open == (ToolOutput(1, False), ToolOutput(2, True))
    assert io.settle_s == 0.5 and GripperIO.parse(io.describe()) == io
    assert GripperIO.parse("settle=2") == GripperIO(settle_s=2.0)  # the other keys keep the default
    for bad, message in [("close=1", "INDEX:LEVEL"), ("close=1:2", "INDEX:LEVEL"), ("shut=1:1", "is not open="),
                         ("settle=abc", "not a number"), ("settle=99", r"\[0, 10\]"), ("close=99:1", r"\[0, 16\)")]:
        with pytest.raises(ValueError, match=message):
            GripperIO.parse(bad)


def test_settings_refuse_out_of_range_values() -> None:
    for kwargs, message in [({"port": 0}, "port"), ({"servo_mode": 2}, "servo mode"), ({"servo_gain": 50.0}, "gain"),
                            ({"lookahead_s": 0.5}, "look-ahead"), ({"request_timeout_s": 0.0}, "request_timeout_s"),
                            ({"joint_offset": (0.0,) * 5}, "joint offset")]:
        with pytest.raises(ValueError, match=message):
            AuboSettings(**kwargs)


# ---- AUBO: the real SDK, where it is installed ----


def test_sdk_mode_enums_and_codes() -> None:
    sdk = pytest.importorskip("pyaubo_sdk")
    check_ready(sdk.RobotModeType.Running, sdk.SafetyModeType.Normal)
    check_ready(sdk.RobotModeType.Running, sdk.SafetyModeType.ReducedMode)
    with pytest.raises(AuboError, match="robot mode PowerOff"):
        check_ready(sdk.RobotModeType.PowerOff, sdk.SafetyModeType.Normal)
    with pytest.raises(AuboError, match="safety mode ProtectiveStop"):
        check_ready(sdk.RobotModeType.Running, sdk.SafetyModeType.ProtectiveStop)
    names = {int(v): k for k, v in sdk.AuboErrorCodes.__members__.items()}
    assert aubo.code_name(-8, names) == "-8 (AUBO_CONN_REFUSED)" and aubo.code_name(-13, names) == "-13 (AUBO_REQUEST_IGNORE)"


def test_refused_connection_names_host_and_port() -> None:
    pytest.importorskip("pyaubo_sdk")
    port = closed_port()
    t0 = time.perf_counter()
    with pytest.raises(AuboConnectionError, match=f"127.0.0.1:{port}: connection refused"):
        AuboRobot("127.0.0.1", port)
    assert time.perf_counter() - t0 < 2.0


def test_silent_controller_times_out_within_the_request_timeout(listener: int) -> None:
    """The real SDK against a socket that accepts and never answers: its version check and login time out."""
    pytest.importorskip("pyaubo_sdk")
    t0 = time.perf_counter()
    with pytest.raises(AuboConnectionError, match=f"127.0.0.1:{listener}") as err:
        AuboRobot("127.0.0.1", listener, AuboSettings(request_timeout_s=0.3))
    elapsed = time.perf_counter() - t0
    assert 0.25 < elapsed < 3.0, elapsed
    assert "0.3 s" in str(err.value)


def test_unreachable_port_times_out_in_the_tcp_probe() -> None:
    """A listener with a full backlog drops further SYNs (Linux): the probe's own timeout bounds the wait."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(0)
    port = srv.getsockname()[1]
    filler = socket.create_connection(("127.0.0.1", port), timeout=1.0)  # fills the backlog (never accepted)
    try:
        t0 = time.perf_counter()
        with pytest.raises(AuboConnectionError, match=f"127.0.0.1:{port}: no connection within 0.3 s"):
            aubo.probe_tcp("127.0.0.1", port, 0.3)
        assert time.perf_counter() - t0 < 2.0
    finally:
        filler.close()
        srv.close()


# ---- AUBO: the adapter's logic against a test double of the SDK client ----


class FakeController:
    """TEST DOUBLE of ``pyaubo_sdk.RpcClient`` and the objects it hands out (method names as the SDK's): it
    records every call and answers what a test sets.  It checks this adapter's logic, not the controller."""

    def __init__(self, joints: Any = HOME_Q, robot_mode: str = "Running", safety_mode: str = "Normal") -> None:
        self.calls: list[tuple] = []
        self.joints = list(joints)
        self.robot_mode, self.safety_mode = robot_mode, safety_mode
        self.servo_mode = 0
        self.tool_inputs = {0: True, 1: True}  # tool I/O pins start as inputs

    def __call__(self) -> FakeController:  # the client factory
        return self

    def __getattr__(self, name: str) -> Any:
        answers = {
            "setLogHandler": None, "setRequestTimeout": 0, "connect": 0, "hasConnected": True, "login": 0,
            "hasLogined": True, "getRobotNames": ["rob1"], "logout": 0, "disconnect": 0, "servoJoint": 0,
            "setToolDigitalOutput": 0,
        }
        if name in answers:
            return lambda *args: (self.calls.append((name, *args)), answers[name])[1]
        raise AttributeError(name)

    def getRobotInterface(self, name: str) -> FakeController:
        self.calls.append(("getRobotInterface", name))
        return self

    getRobotState = getMotionControl = getIoControl = lambda self: self

    def getJointPositions(self) -> list[float]:
        self.calls.append(("getJointPositions",))
        return list(self.joints)

    def getRobotModeType(self) -> str:
        self.calls.append(("getRobotModeType",))
        return self.robot_mode

    def getSafetyModeType(self) -> str:
        self.calls.append(("getSafetyModeType",))
        return self.safety_mode

    def setServoModeSelect(self, mode: int) -> int:
        self.calls.append(("setServoModeSelect", mode))
        self.servo_mode = mode
        return 0

    def getServoModeSelect(self) -> int:
        return self.servo_mode

    def isToolIoInput(self, index: int) -> bool:
        return self.tool_inputs.get(index, False)

    def setToolIoInput(self, index: int, is_input: bool) -> int:
        self.calls.append(("setToolIoInput", index, is_input))
        self.tool_inputs[index] = is_input
        return 0

    def named(self, *names: str) -> list[tuple]:
        return [c for c in self.calls if c[0] in names]


COMMANDS = ("servoJoint", "setServoModeSelect", "setToolDigitalOutput", "setToolIoInput")


def test_dry_run_reads_and_commands_nothing(listener: int) -> None:
    fake = FakeController(joints=HOME + 0.01)
    with AuboRobot("127.0.0.1", listener, client_factory=fake) as robot:
        report = robot.dry_run(HOME)
    assert report.home.at_home and report.home.max_error == pytest.approx(0.01)
    assert (report.robot_name, report.robot_mode, report.safety_mode) == ("rob1", "Running", "Normal")
    assert fake.named(*COMMANDS) == []
    assert fake.named("login") == [("login", "aubo", "123456")] and fake.named("setRequestTimeout") == [("setRequestTimeout", 1000)]
    assert [c[0] for c in fake.calls[-3:]] == ["logout", "disconnect", "setLogHandler"]
    text = report.format()
    assert "AT HOME" in text and f"127.0.0.1:{listener}" in text and "untested on hardware" in text


def test_commands_servo_at_the_control_period_and_refuse_unsafe_steps(listener: int) -> None:
    fake = FakeController()
    robot = AuboRobot("127.0.0.1", listener, AuboSettings(gripper=GripperIO(settle_s=0.0)), client_factory=fake)
    q = HOME.copy()
    t0 = time.perf_counter()
    for _ in range(3):
        q = q + np.array([0.02, -0.02, 0.02, 0.0, 0.0, 0.01])
        robot.command_joint_targets(q)
    elapsed = time.perf_counter() - t0
    assert 0.14 <= elapsed < 0.5, elapsed  # three control periods of 0.05 s
    assert fake.named("setServoModeSelect") == [("setServoModeSelect", 1)]
    sent = fake.named("servoJoint")
    assert len(sent) == 3
    _, q_sent, a, v, t, lookahead_s, gain = sent[-1]
    np.testing.assert_allclose(q_sent, q)
    assert (a, v, t, lookahead_s, gain) == pytest.approx((20.0, 1.0, 0.05, 0.05, 150.0))
    with pytest.raises(SafetyViolation, match="moves 0.1000 rad in one step"):
        robot.command_joint_targets(q + np.array([0.1, 0, 0, 0, 0, 0]))
    assert len(fake.named("servoJoint")) == 3  # refused before anything was sent
    robot.close_gripper()
    assert fake.named("setToolIoInput", "setToolDigitalOutput")[-2:] == [("setToolIoInput", 0, False),
                                                                          ("setToolDigitalOutput", 0, True)]
    robot.close()
    assert fake.calls[-4:-1] == [("setServoModeSelect", 0), ("logout",), ("disconnect",)]
    with pytest.raises(AuboError, match="not connected"):
        robot.read_joints()


def test_refuses_to_servo_an_arm_that_is_not_running(listener: int) -> None:
    fake = FakeController(robot_mode="PowerOff")
    with AuboRobot("127.0.0.1", listener, client_factory=fake) as robot:
        with pytest.raises(AuboError, match="robot mode PowerOff"):
            robot.command_joint_targets(HOME)
    assert fake.named(*COMMANDS) == []


def test_a_failed_servo_call_stops_with_the_sdk_code(listener: int) -> None:
    fake = FakeController()
    robot = AuboRobot("127.0.0.1", listener, client_factory=fake)
    robot._code_names = {13: "AUBO_REQUEST_IGNORE"}
    fake.__class__ = type("Refusing", (FakeController,), {"servoJoint": lambda self, *a: -13})
    with pytest.raises(AuboError, match=r"servoJoint returned -13 \(AUBO_REQUEST_IGNORE\)"):
        robot.command_joint_targets(HOME)
    robot.close()


# ---- the deploy CLI with --backend aubo ----


def _policy(tmp_path) -> str:
    weights = [(np.zeros((17, 8), np.float32), np.zeros(8, np.float32)), (np.zeros((8, 12), np.float32), np.zeros(12, np.float32))]
    return str(save_policy_npz(tmp_path / "zero.npz", weights=weights, activation="tanh", obs_mean=np.zeros(17),
                               obs_std=np.ones(17), config=get_config("paper")))


def _target_cam() -> list[str]:
    top = CameraCalibration.default().base_to_cam(np.array([0.10, -0.45, 0.05]), units="mm")
    return [f"{v:.6f}" for v in top]


def test_cli_refused_connection_exits_2_naming_host_and_port(tmp_path, capsys) -> None:
    pytest.importorskip("pyaubo_sdk")
    port = closed_port()
    code = deploy_main(["--policy", _policy(tmp_path), "--target-cam", *_target_cam(), "--backend", "aubo",
                        "--host", "127.0.0.1", "--port", str(port)])
    err = capsys.readouterr().err
    assert code == 2 and f"127.0.0.1:{port}: connection refused" in err and "Traceback" not in err
    code = deploy_main(["--backend", "aubo", "--host", "127.0.0.1", "--port", str(port), "--dry-run", "--json"])
    out, err = capsys.readouterr()
    assert code == 2 and json.loads(out)["outcome"] == "input_refused" and f"127.0.0.1:{port}" in err


def test_cli_refuses_twin_options_with_aubo_and_aubo_options_with_twin(tmp_path, capsys) -> None:
    policy = _policy(tmp_path)
    code = deploy_main(["--policy", policy, "--target-cam", *_target_cam(), "--backend", "aubo", "--host", "127.0.0.1",
                        "--twin-target-error", "1", "0", "0"])
    assert code == 2 and "--twin-target-error" in capsys.readouterr().err
    code = deploy_main(["--policy", policy, "--target-cam", *_target_cam(), "--backend", "aubo"])
    assert code == 2 and "needs --host" in capsys.readouterr().err
    code = deploy_main(["--policy", policy, "--target-cam", *_target_cam(), "--host", "127.0.0.1"])
    assert code == 2 and "is only for --backend aubo" in capsys.readouterr().err
    code = deploy_main(["--policy", policy, "--target-cam", *_target_cam(), "--backend", "aubo", "--host", "127.0.0.1",
                        "--gripper-io", "close=7"])
    assert code == 2 and "INDEX:LEVEL" in capsys.readouterr().err


def test_cli_missing_sdk_exits_2_with_the_install_hint(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.setitem(sys.modules, "pyaubo_sdk", None)  # as if not installed
    code = deploy_main(["--backend", "aubo", "--host", "127.0.0.1", "--dry-run"])
    assert code == 2 and 'pip install "sagrasp_jax[aubo]"' in capsys.readouterr().err
    code = deploy_main(["--policy", _policy(tmp_path), "--target-cam", *_target_cam(), "--backend", "aubo",
                        "--host", "127.0.0.1"])
    assert code == 2 and 'pip install "sagrasp_jax[aubo]"' in capsys.readouterr().err


def test_cli_dry_run_report_through_a_test_double(listener: int, monkeypatch, capsys) -> None:
    """The CLI's dry run wired to ``FakeController`` (a test double, module docstring): the report's form and the
    exit status; the controller's answers are the double's."""
    fake = FakeController(joints=HOME + np.array([0.0, 0.0, 0.1, 0.0, 0.0, 0.0]))

    class FakeSdk:
        RpcClient = fake
        AuboErrorCodes = type("Codes", (), {"__members__": {}})

    monkeypatch.setattr(aubo, "import_sdk", lambda: FakeSdk)
    code = deploy_main(["--backend", "aubo", "--host", "127.0.0.1", "--port", str(listener), "--dry-run", "--json"])
    report = json.loads(capsys.readouterr().out)
    assert code == 1 and report["outcome"] == "dry_run" and report["commanded"] is False
    assert report["home"]["at_home"] is False and report["home"]["max_error"] == pytest.approx(0.1)
    np.testing.assert_allclose(report["home"]["joints"], fake.joints)
    assert fake.named(*COMMANDS) == []
    fake.joints = list(HOME)
    assert deploy_main(["--backend", "aubo", "--host", "127.0.0.1", "--port", str(listener), "--dry-run"]) == 0
    assert "AT HOME" in capsys.readouterr().out


# ---- cameras: conversions of the SDKs' own frame objects ----


def test_mecheye_textured_point_cloud_to_capture() -> None:
    pytest.importorskip("mecheye")
    from mecheye.area_scan_3d_camera import TexturedPointCloud

    cloud = TexturedPointCloud()  # the SDK's own container, filled by hand (no camera)
    cloud.resize(4, 3)  # width, height
    p = cloud.at(1, 2)  # row, column
    p.x, p.y, p.z, p.b, p.g, p.r = 10.5, -20.0, 1400.25, 3, 2, 250
    q = cloud.at(2, 3)
    q.x, q.y, q.z = float("nan"), float("nan"), float("nan")  # the SDK's "no return"
    cap = cameras.mecheye_capture(cloud.vertices(), cloud.colors())
    assert cap.cloud_mm.shape == (3, 4, 3) and cap.cloud_mm.dtype == np.float32 and cap.rgb.dtype == np.uint8
    np.testing.assert_allclose(cap.cloud_mm[1, 2], [10.5, -20.0, 1400.25])
    assert cap.rgb[1, 2].tolist() == [250, 2, 3]  # BGR -> RGB
    assert np.isnan(cap.cloud_mm[2, 3]).all() and np.isnan(cap.cloud_mm[0, 0]).all()  # z = 0: no return
    assert np.isfinite(cap.cloud_mm).all(axis=-1).sum() == 1
    empty = TexturedPointCloud()
    with pytest.raises(cameras.CameraError, match="expected \\(H, W, 3\\)"):
        cameras.mecheye_capture(empty.vertices(), empty.colors())
    metres = cameras.mecheye_capture(np.full((2, 2, 3), 1.5, np.float32), np.zeros((2, 2, 3), np.uint8), unit_to_mm=1000)
    np.testing.assert_allclose(metres.cloud_mm, 1500.0)


def _realsense():
    try:
        import pyrealsense2 as rs
    except ImportError as exc:  # absent, or installed without the system's libusb-1.0
        pytest.skip(f"pyrealsense2 does not import: {exc}")
    return rs


def test_realsense_software_device_pointcloud_to_capture() -> None:
    """A depth frame from librealsense's software device (no camera) through the SDK's own ``rs.pointcloud``."""
    rs = _realsense()
    W, H = 8, 6
    intr = rs.intrinsics()
    intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy = W, H, 600.0, 600.0, 3.5, 2.5
    intr.model, intr.coeffs = rs.distortion.none, [0.0] * 5
    device = rs.software_device()
    sensor = device.add_sensor("Depth")
    stream = rs.video_stream()
    stream.type, stream.index, stream.uid, stream.width, stream.height = rs.stream.depth, 0, 0, W, H
    stream.fps, stream.bpp, stream.fmt, stream.intrinsics = 30, 2, rs.format.z16, intr
    profile = sensor.add_video_stream(stream)
    sensor.add_read_only_option(rs.option.depth_units, 0.001)
    queue = rs.frame_queue(2)
    sensor.open(profile)
    sensor.start(queue)
    try:
        depth = np.full((H, W), 1400, np.uint16)  # mm in z16 with depth units 0.001
        depth[0, 0] = 0  # no depth
        depth[4, 6] = 1250
        frame = rs.software_video_frame()
        frame.pixels, frame.bpp, frame.stride, frame.timestamp = depth, 2, W * 2, 0.0
        frame.domain, frame.frame_number, frame.profile, frame.depth_units = (
            rs.timestamp_domain.hardware_clock, 1, profile.as_video_stream_profile(), 0.001)
        sensor.on_video_frame(frame)
        depth_frame = queue.wait_for_frame(2000).as_depth_frame()
        points = rs.pointcloud().calculate(depth_frame)
        rgb = np.zeros((H, W, 3), np.uint8)
        rgb[4, 6] = (9, 8, 7)
        cap = cameras.realsense_capture(rgb, np.asanyarray(points.get_vertices(2)), H, W)
        structured = cameras.realsense_capture(rgb, np.asanyarray(points.get_vertices()), H, W)
    finally:
        sensor.stop()
        sensor.close()
    expected = 1000 * np.array(rs.rs2_deproject_pixel_to_point(intr, [6.0, 4.0], 1.25))
    np.testing.assert_allclose(cap.cloud_mm[4, 6], expected, atol=1e-3)
    np.testing.assert_allclose(cap.cloud_mm[4, 6], [(6 - 3.5) / 600 * 1250, (4 - 2.5) / 600 * 1250, 1250], atol=1e-3)
    assert np.isnan(cap.cloud_mm[0, 0]).all() and np.isfinite(cap.cloud_mm[1:]).all()
    assert cap.rgb[4, 6].tolist() == [9, 8, 7]
    np.testing.assert_array_equal(structured.cloud_mm, cap.cloud_mm)
    bgr = cameras.realsense_capture(rgb, np.asanyarray(points.get_vertices(2)), H, W, color_format="bgr8")
    assert bgr.rgb[4, 6].tolist() == [7, 8, 9]


def test_realsense_capture_refuses_mismatched_arrays() -> None:
    with pytest.raises(cameras.CameraError, match="points for a 4 × 3 frame"):
        cameras.realsense_capture(np.zeros((3, 4, 3), np.uint8), np.zeros((10, 3), np.float32), 3, 4)
    with pytest.raises(cameras.CameraError, match="does not match"):
        cameras.realsense_capture(np.zeros((4, 3, 3), np.uint8), np.zeros((12, 3), np.float32), 3, 4)
    with pytest.raises(cameras.CameraError, match="uint8"):
        cameras.realsense_capture(np.zeros((3, 4, 3), np.float32), np.zeros((12, 3), np.float32), 3, 4)


# ---- cameras: missing or broken SDKs, absent devices ----


@pytest.mark.parametrize(("extra", "module", "make"), [
    ("mecheye", "mecheye", lambda: cameras.MechEyeCamera("192.0.2.1")),
    ("realsense", "pyrealsense2", lambda: cameras.RealSenseCamera()),
])
def test_missing_camera_sdk_names_the_extra(monkeypatch, extra: str, module: str, make) -> None:
    monkeypatch.setitem(sys.modules, module, None)
    with pytest.raises(extras.MissingExtra, match=f'pip install "sagrasp_jax\\[{extra}\\]"'):
        make()


def test_broken_realsense_install_says_what_is_missing(monkeypatch) -> None:
    monkeypatch.setattr(extras, "require", lambda *a, **k: None)

    def fail(name: str):
        raise ImportError("libusb-1.0.so.0: cannot open shared object file: No such file or directory")

    monkeypatch.setattr(cameras.importlib, "import_module", fail)
    with pytest.raises(cameras.CameraError, match="libusb-1.0"):
        cameras.RealSenseCamera()


def test_realsense_without_a_camera_says_so_at_once() -> None:
    rs = _realsense()
    if len(rs.context().query_devices()):
        pytest.skip("a RealSense camera is connected")
    t0 = time.perf_counter()
    with pytest.raises(cameras.CameraError, match="no camera connected"):
        cameras.RealSenseCamera()
    assert time.perf_counter() - t0 < 2.0  # pipeline.start would have waited 15 s


def test_mecheye_without_a_camera_names_its_address() -> None:
    pytest.importorskip("mecheye")
    with pytest.raises(cameras.CameraError, match="Mech-Eye camera at 127.0.0.1: connect"):
        cameras.MechEyeCamera("127.0.0.1", timeout_s=0.3)
    with pytest.raises(cameras.CameraError, match="one of mecheye, realsense"):
        cameras.open_camera("kinect")


def test_cli_run_through_a_test_double(tmp_path, listener: int, monkeypatch, capsys) -> None:
    """The normal run's wiring with ``FakeController`` (a test double): an arm away from home is refused before
    anything is sent; at home the gripper opens, and every loop step is one ``servoJoint``."""
    fake = FakeController(joints=HOME + np.array([0.2, 0.0, 0.0, 0.0, 0.0, 0.0]))

    class FakeSdk:
        RpcClient = fake
        AuboErrorCodes = type("Codes", (), {"__members__": {}})

    monkeypatch.setattr(aubo, "import_sdk", lambda: FakeSdk)
    args = ["--policy", _policy(tmp_path), "--target-cam", *_target_cam(), "--backend", "aubo", "--host", "127.0.0.1",
            "--port", str(listener), "--gripper-io", "settle=0", "--max-steps", "2", "--no-grasp"]
    assert deploy_main(args) == 2
    assert "11.46° from the home pose" in capsys.readouterr().err and fake.named(*COMMANDS) == []
    fake.joints = list(HOME)
    assert deploy_main(args) == 1  # a zero policy times out after its two steps
    assert "timeout" in capsys.readouterr().out
    assert fake.named("setToolDigitalOutput") == [("setToolDigitalOutput", 0, False)]  # opened before the run
    assert len(fake.named("servoJoint")) == 2 and fake.calls[-4][0] == "setServoModeSelect"
