"""The AUBO adapter (``deploy.aubo.AuboRobot``) with the vendor's own client inside, ``pyaubo_sdk.RpcClient``
0.24.x, end to end against an emulated controller (``tests/aubo_emulator.py``: the wire protocol that client
speaks, found against loopback listeners; a child process, since the SDK holds the GIL while it waits).

What is real here: the SDK's client, its framing, its login, its JSON-RPC calls and its reactions to a refused
login, a silent controller and a dropped connection; the adapter; the deploy command line.  What is emulated:
the controller (its answers are the ones the SDK accepts, its joints follow ``servoJoint`` kinematically)
and so the gripper wiring behind the tool outputs.  No real controller has answered any of this.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from typing import Any

import numpy as np
import pytest

pytest.importorskip("pyaubo_sdk", reason="pyaubo-sdk (the [aubo] extra; CPython <= 3.12 wheels, Linux x86_64 and "
                    "Windows) is not installed: the vendor's client cannot be run against the emulator")

from aubo_emulator import FACTORY_LOGIN_TOKEN, AuboEmulator  # noqa: E402

from sagrasp_jax.deploy.aubo import AuboConnectionError, AuboError, AuboRobot, AuboSettings, GripperIO  # noqa: E402
from sagrasp_jax.deploy.calibration import CameraCalibration  # noqa: E402
from sagrasp_jax.deploy.safety import SafetyLayer  # noqa: E402
from sagrasp_jax.task.config import HOME_Q  # noqa: E402
from paths import REPO  # noqa: E402

HOME = np.array(HOME_Q)
COMMANDS = ("setServoModeSelect", "servoJoint", "setToolIoInput", "setToolDigitalOutput")
# tests/deploy/test_hardware_adapters.py's target: the cube's top at (0.10, -0.45, 0.05) m in the world, in the camera
TARGET_CAM = [f"{v:.6f}" for v in CameraCalibration.default().base_to_cam(np.array([0.10, -0.45, 0.05]), units="mm")]
FAST_GRIPPER = "close=0:1,open=0:0,settle=0.1"  # the default wiring, a shorter settle time


def _session(emu: AuboEmulator, closed: bool = True) -> list[dict[str, Any]]:
    """The requests and events of the SDK's connection (not the adapter's TCP probe, which sends nothing); with
    ``closed``, once the emulator has seen the client close it (it logs the close when it reads it: on a loaded
    machine that comes a moment after the client's process has gone), at most 5 s."""
    deadline = time.monotonic() + 5.0
    while True:
        calls = emu.calls()
        conn = next(c["conn"] for c in calls if c.get("name") == "getInterfaceVersionCode")
        session = [c for c in calls if c["conn"] == conn]
        if not closed or session[-1].get("event") == "eof" or time.monotonic() > deadline:
            return session
        time.sleep(0.05)


def _names(calls: list[dict[str, Any]]) -> list[str]:
    return [c.get("name") or c["event"] for c in calls]


def _deploy(emu: AuboEmulator, *args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """``python -m sagrasp_jax.deploy --backend aubo`` pointed at the emulator."""
    return subprocess.run([sys.executable, "-m", "sagrasp_jax.deploy", "--backend", "aubo", "--host", emu.host,
                           "--port", str(emu.port), *args], capture_output=True, text=True, timeout=120, cwd=REPO,
                          env={**os.environ, **(env or {})})


def _episode_line(*extra: str) -> list[str]:
    return ["--policy", "pretrained", "--target-cam", *TARGET_CAM, "--gripper-io", FAST_GRIPPER, "--json", *extra]


# ---- the adapter in this process, the emulator in its own ----


def test_vendor_client_connects_logs_in_and_reads_the_joints() -> None:
    with AuboEmulator(joints=HOME) as emu:
        with AuboRobot(emu.host, emu.port) as robot:
            q = robot.read_joints()
            assert robot.robot_name == "rob1" and robot.status() == ("Running", "Normal")
        np.testing.assert_allclose(q, HOME, atol=1e-12)  # the controller's list of floats, through the SDK
        calls = _session(emu)
        state = emu.state()
    # the SDK's own sequence: version check, text login (which fetches the robot and axis names), then the calls
    assert _names(calls) == ["accept", "getInterfaceVersionCode", "login", "getRobotNames", "getAxisNames",
                             "getJointPositions", "getRobotModeType", "getSafetyModeType", "eof"]
    login = calls[2]
    assert login["params"] == {"user": "aubo", "token": FACTORY_LOGIN_TOKEN, "sdk_version": "0.24.0"}
    assert login["answer"] == "SUCCEED"
    assert calls[5]["method"] == "rob1.RobotState.getJointPositions"
    assert state["open_connections"] == [] and state["connections"] == 2  # the TCP probe and the session


def test_dry_run_reads_the_emulated_arm_and_commands_nothing() -> None:
    offset = np.array([0.0, 0.01, 0.0, 0.0, 0.0, -0.02])
    with AuboEmulator(joints=HOME + offset) as emu:
        with AuboRobot(emu.host, emu.port) as robot:
            report = robot.dry_run(HOME)
        calls = emu.calls()
        state = emu.state()
    assert report.home.at_home and report.home.max_error == pytest.approx(0.02, abs=1e-12)
    np.testing.assert_allclose(report.home.error, offset, atol=1e-12)
    assert (report.robot_name, report.robot_mode, report.safety_mode) == ("rob1", "Running", "Normal")
    assert [c for c in calls if c.get("name") in COMMANDS] == []
    assert state["servo_mode"] == 0 and not any(state["tool_output"].values())
    assert all(state["tool_is_input"].values())  # not even the pins' direction was touched


def test_servo_targets_reach_the_emulated_arm_and_close_leaves_servo_mode() -> None:
    with AuboEmulator(joints=HOME) as emu:
        robot = AuboRobot(emu.host, emu.port, AuboSettings(gripper=GripperIO(settle_s=0.0)))
        step = np.array([0.02, -0.02, 0.02, 0.0, 0.01, 0.01])
        targets = [HOME + k * step for k in range(1, 6)]
        t0 = time.perf_counter()
        for q in targets:
            robot.command_joint_targets(q)
        elapsed = time.perf_counter() - t0
        measured = robot.read_joints()
        robot.close_gripper()
        during = emu.state()
        robot.close()
        time.sleep(0.06)  # the last target's period (t = 0.05 s) is over: the emulated joints are there
        sent = emu.calls("servoJoint")
        after = emu.state()
        modes = [c["params"]["mode"] for c in emu.calls("setServoModeSelect")]
    assert 0.2 <= elapsed < 0.6, elapsed  # five control periods of 0.05 s
    assert len(sent) == 5 and all(c["answer"] == {"result": 0} for c in sent)
    for call, q in zip(sent, targets):
        np.testing.assert_allclose(call["params"]["q"], q, atol=1e-12)
        params = {k: v for k, v in call["params"].items() if k != "q"}
        assert params == pytest.approx({"a": 20.0, "v": 1.0, "t": 0.05, "lookahead_time": 0.05, "gain": 150.0})
    np.testing.assert_allclose(measured, targets[-1], atol=0.011)  # at most one period short of the last target
    np.testing.assert_allclose(after["joints"], targets[-1], atol=1e-9)
    assert during["servo_mode"] == 1 and during["tool_output"]["0"] is True and during["tool_is_input"]["0"] is False
    assert modes == [1, 0] and after["servo_mode"] == 0 and after["open_connections"] == []


def test_an_arm_in_protective_stop_is_refused_before_any_command() -> None:
    with AuboEmulator(joints=HOME, safety_mode="ProtectiveStop") as emu:
        with AuboRobot(emu.host, emu.port) as robot:
            with pytest.raises(AuboError, match="safety mode ProtectiveStop"):
                robot.command_joint_targets(HOME)
        assert emu.calls(*COMMANDS) == []


def test_a_reset_connection_fails_the_call_at_once_and_close_still_returns() -> None:
    with AuboEmulator(joints=HOME, drop_at_servo=3, drop_mode="reset") as emu:
        robot = AuboRobot(emu.host, emu.port)
        robot.command_joint_targets(HOME)
        robot.command_joint_targets(HOME)
        t0 = time.perf_counter()
        with pytest.raises(AuboError, match=rf"{emu.host}:{emu.port}: servoJoint failed: .*Connection reset by peer"):
            robot.command_joint_targets(HOME)
        assert time.perf_counter() - t0 < 0.5  # an RST is seen at once; a FIN waits out the request timeout
        with pytest.raises(AuboError, match="RPC client has not connected"):
            robot.read_joints()
        robot.close()  # leaving servo mode fails (no connection): logged, not raised
        assert _names(_session(emu, closed=False))[-1] == "dropped" and len(emu.calls("servoJoint")) == 3


def test_a_refused_login_is_named_as_such() -> None:
    with AuboEmulator(joints=HOME, refuse_login=True) as emu:
        with pytest.raises(AuboConnectionError, match=rf"{emu.host}:{emu.port}: login as 'aubo' refused"):
            AuboRobot(emu.host, emu.port, AuboSettings(request_timeout_s=0.3))
        assert _names(_session(emu)) == ["accept", "getInterfaceVersionCode", "login", "eof"]


# ---- the deploy command line, in a subprocess, against the emulator ----


def test_deploy_episode_through_the_vendor_client() -> None:
    """A whole episode: the pretrained policy from the home pose, the slide, the close, the lift."""
    safety = SafetyLayer()
    with AuboEmulator(joints=HOME) as emu:
        res = _deploy(emu, *_episode_line())
        calls = _session(emu)
        state = emu.state()
    assert "Traceback" not in res.stderr, res.stderr
    # the AUBO cannot tell whether the cube is held: held null, exit 1 (deploy's docstring)
    assert res.returncode == 1, res.stderr
    report = json.loads(res.stdout)
    assert report["outcome"] == "success" and report["held"] is None
    grasp = report["grasp"]
    assert grasp["closed"] and grasp["lifted"] and grasp["held"] is None
    assert 0.04 < grasp["gripper_rise"] < 0.06  # the 5 cm lift, measured by the emulated joints
    servo = [c for c in calls if c.get("name") == "servoJoint"]
    targets = np.array([c["params"]["q"] for c in servo])
    assert len(servo) > report["steps"]  # the policy's steps, then the slide, the hold and the lift
    assert all(c["answer"] == {"result": 0} for c in servo)
    # every target the controller received is within the safety layer's per-step limit of the one before it
    # (the first of the start pose), and within the joint limits
    steps = np.abs(np.diff(np.vstack([HOME, targets]), axis=0))
    assert np.all(steps <= safety.step_limit + 1e-9), steps.max(axis=0)
    assert np.all(targets >= safety.robot.q_lower) and np.all(targets <= safety.robot.q_upper)
    assert {c["params"]["t"] for c in servo} == {safety.control_dt}
    gaps = np.diff([c["t"] for c in servo])
    assert 0.04 < float(np.median(gaps)) < 0.08, gaps  # one target per control period
    # the gripper: opened at the start, closed after the slide, before the lift
    names = _names(calls)
    outputs = [(i, c["params"]) for i, c in enumerate(calls) if c.get("name") == "setToolDigitalOutput"]
    assert [p for _, p in outputs] == [{"index": 0, "value": False}, {"index": 0, "value": True}]
    assert names.index("setToolIoInput") < outputs[0][0] < names.index("servoJoint") < outputs[1][0]
    assert names[outputs[1][0] + 1:].count("servoJoint") >= 2  # the lift came after the close
    assert state["tool_output"]["0"] is True
    # the session: servo mode on before the first target and off at the end, the socket closed by the client
    modes = [c["params"]["mode"] for c in calls if c.get("name") == "setServoModeSelect"]
    assert modes == [1, 0] and state["servo_mode"] == 0
    assert names[-1] == "eof" and state["open_connections"] == []
    assert "[aubo sdk] RPC Client logout" in res.stderr  # logout sends nothing: the SDK's own log says it ran
    np.testing.assert_allclose(state["target"], targets[-1], atol=1e-12)
    assert np.all(np.abs(np.subtract(state["joints"], targets[-1])) <= safety.step_limit + 1e-9)
    # the joints the loop read at the grasp pose: the last policy target, or on the way there from the one before
    lag = np.abs(np.subtract(report["final_q"], targets[report["steps"] - 1]))
    assert np.all(lag <= np.abs(targets[report["steps"] - 1] - targets[report["steps"] - 2]) + 1e-9), lag


def test_dry_run_command_reports_the_emulated_joints() -> None:
    with AuboEmulator(joints=HOME + np.array([0.0, 0.0, 0.1, 0.0, 0.0, 0.0])) as emu:
        res = _deploy(emu, "--dry-run", "--json")
        calls = emu.calls()
    assert res.returncode == 1, res.stderr  # read-only check: not at home
    report = json.loads(res.stdout)
    assert report["outcome"] == "dry_run" and report["commanded"] is False and not report["home"]["at_home"]
    assert report["home"]["max_error"] == pytest.approx(0.1, abs=1e-12)
    assert [c for c in calls if c.get("name") in COMMANDS] == []


def test_deploy_refuses_an_arm_away_from_home_before_moving() -> None:
    with AuboEmulator(joints=HOME + np.array([0.0, 0.0, 0.1, 0.0, 0.0, 0.0])) as emu:
        res = _deploy(emu, *_episode_line())
        calls = _session(emu)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    report = json.loads(res.stdout)
    assert report["outcome"] == "input_refused" and "5.73° from the home pose" in report["message"]
    assert [c for c in calls if c.get("name") in COMMANDS] == [] and _names(calls)[-1] == "eof"


def test_deploy_wrong_password_exits_2_naming_host_and_port() -> None:
    with AuboEmulator(joints=HOME) as emu:
        res = _deploy(emu, *_episode_line(), env={"AUBO_PASSWORD": "wrong"})
        calls = _session(emu)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    report = json.loads(res.stdout)
    assert report["outcome"] == "input_refused"
    assert report["message"].startswith(f"AUBO controller at 127.0.0.1:{emu.port}: login as 'aubo' refused")
    login = calls[2]
    assert login["name"] == "login" and login["answer"] == "FAILED"
    assert login["params"]["token"] != FACTORY_LOGIN_TOKEN  # the controller saw another password
    assert _names(calls) == ["accept", "getInterfaceVersionCode", "login", "eof"]


def test_deploy_silent_controller_exits_2_within_the_request_timeout() -> None:
    request_timeout = AuboSettings().request_timeout_s
    with AuboEmulator(joints=HOME, silent=True) as emu:
        t0 = time.perf_counter()
        res = _deploy(emu, *_episode_line())
        wall = time.perf_counter() - t0
        calls = _session(emu)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    report = json.loads(res.stdout)
    assert report["outcome"] == "input_refused" and f"127.0.0.1:{emu.port}" in report["message"]
    assert "code -7" in report["message"]
    assert _names(calls) == ["accept", "getInterfaceVersionCode", "eof"]
    waited = calls[-1]["t"] - calls[1]["t"]  # the SDK's version check, unanswered, until the client hung up
    assert request_timeout - 0.05 <= waited < request_timeout + 1.0, waited
    assert wall < 15.0, wall


def test_deploy_connection_dropped_mid_episode_stops_with_exit_3() -> None:
    """The controller closes the connection when the 10th target arrives: the call in flight waits out the
    request timeout, the episode stops ("refused", exit 3: deploy's status for a robot stopped mid-episode)."""
    with AuboEmulator(joints=HOME, drop_at_servo=10) as emu:
        res = _deploy(emu, *_episode_line())
        calls = _session(emu, closed=False)
        state = emu.state()
    assert res.returncode == 3 and "Traceback" not in res.stderr, res.stderr
    report = json.loads(res.stdout)
    assert report["outcome"] == "refused"
    assert report["message"] == (f"AUBO controller at 127.0.0.1:{emu.port}: servoJoint failed: AuboException: RPC "
                                 "request timeout.")
    assert _names(calls)[-1] == "dropped" and state["servo_count"] == 10 and state["open_connections"] == []
    # the close could not leave servo mode over a closed connection: said, not raised
    assert "setServoModeSelect(0) during close failed: RPC client has not connected" in res.stderr


def test_a_real_cell_line_camera_and_arm_through_the_vendors_code(tmp_path) -> None:
    """The one command of a real cell, every vendor's code that runs without hardware on the way:
    ``deploy --camera realsense`` (a librealsense recording of a twin render) ``--backend aubo`` (pyaubo-sdk
    against the emulator). The arm's joints are read from the controller before the capture and saved with it."""
    pytest.importorskip("pybullet")
    realsense_record = pytest.importorskip("sagrasp_jax.deploy.realsense_record")
    try:
        import pyrealsense2  # noqa: F401
    except ImportError as exc:
        pytest.skip(f"pyrealsense2 does not import: {exc}")
    from sagrasp_jax.deploy import capture_file, rehearse
    from sagrasp_jax.deploy.twin import PyBulletTwin
    from sagrasp_jax.task.config import EnvConfig

    env_cfg = EnvConfig()
    spec, rng = rehearse.draw_scene(rehearse.scene_env(env_cfg, "mix"), 0, 3)
    with PyBulletTwin(spec, env_cfg, q0=spec.q0, seed=3) as twin:
        capture = rehearse.twin_capture(twin, spec, rehearse.CameraSettings("industrial", 0.25), rng)
    recording = str(tmp_path / "scene.db3")
    realsense_record.write_bag(recording, [capture])
    with AuboEmulator(joints=HOME) as emu:
        res = _deploy(emu, "--policy", "pretrained", "--camera", "realsense", "--camera-address", recording,
                      "--gripper-io", FAST_GRIPPER, "--json", "--record", str(tmp_path / "rec"))
        sessions = [c["conn"] for c in emu.calls() if c.get("name") == "getInterfaceVersionCode"]
        names = [c.get("name") for c in emu.calls()]
    assert "Traceback" not in res.stderr, res.stderr
    assert res.returncode == 1, res.stderr  # the AUBO cannot tell held: exit 1 after a whole episode
    report = json.loads(res.stdout)
    assert report["outcome"] == "success" and report["grasp"]["closed"] and report["grasp"]["lifted"]
    seen = report["input"]["perception"]["target_world"]
    assert np.linalg.norm(np.subtract(seen, spec.target_pos)) < 0.005  # through librealsense, within 5 mm
    saved = capture_file.load_capture(str(tmp_path / "rec" / "capture.npz"))
    np.testing.assert_allclose(saved.robot_q, HOME, atol=1e-9)  # the joints the controller reported
    assert saved.source.startswith("realsense ") and saved.camera == capture.camera  # the recording's device name
    assert len(sessions) == 2 and "servoJoint" in names  # the joints read before the capture, then the episode
