"""Capture files, the capture command and ``deploy --camera replay:FILE``: from a saved capture to a held cube.

The captures are the twin's (``capture --camera twin``: rendered, industrial depth noise, the true scene kept);
what these tests check is the path a real cell's capture takes: the file read back bit for bit, perceived with
the policy's kinds, the calibration checked against the table, the loop run, the capture and report saved.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile

import numpy as np
import pytest

pytest.importorskip("pybullet")

from sagrasp_jax.deploy import capture_file  # noqa: E402
from sagrasp_jax.deploy.cameras import Capture  # noqa: E402
from sagrasp_jax.deploy.loop import IdealArm, plan_episode  # noqa: E402
from sagrasp_jax.task.camera import CAMERA_MODELS, Intrinsics  # noqa: E402
from sagrasp_jax.task.policy_file import load_policy  # noqa: E402
from sagrasp_jax.task.scene import T_CAM_BASE_MM  # noqa: E402

ENV = {**os.environ, "PYTHONWARNINGS": "ignore"}


def _run(*args: str, cwd: str | os.PathLike[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, env=ENV, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def captures(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """Two twin captures written by the command: a paper-mix scene and a blocking scene."""
    folder = tmp_path_factory.mktemp("captures")
    made = {}
    for name, extra in (("mix", ["--scene", "3"]), ("blocking", ["--scene-set", "blocking", "--scene", "5"])):
        out = folder / f"{name}.npz"
        r = _run("sagrasp_jax.capture", "--camera", "twin", *extra, "--out", str(out), cwd=folder)
        assert r.returncode == 0, r.stderr
        assert f"wrote {out}: mecheye_pro_m, 480 × 300 px" in r.stdout
        made[name] = str(out)
    return made


def test_a_capture_file_reads_back_bit_for_bit(captures: dict[str, str], tmp_path) -> None:
    cap = capture_file.load_capture(captures["blocking"])
    k = CAMERA_MODELS["mecheye_pro_m"].intrinsics.scaled(0.25)
    assert cap.intrinsics == k and cap.camera == "mecheye_pro_m" and cap.source == "twin seed 0 scene 5 (blocking)"
    assert cap.cloud_mm.shape == (300, 480, 3) and cap.cloud_mm.dtype == np.float32 and cap.rgb.dtype == np.uint8
    assert 0.9 < np.isfinite(cap.cloud_mm).all(axis=-1).mean() < 1.0  # the industrial noise drops some pixels
    assert cap.truth["kind"] == "blocking" and len(cap.truth["obstacles"]) >= 1 and len(cap.truth["q0"]) == 6
    again = capture_file.load_capture(capture_file.save_capture(str(tmp_path / "again.npz"), cap))
    assert np.array_equal(again.cloud_mm, cap.cloud_mm, equal_nan=True) and np.array_equal(again.rgb, cap.rgb)
    assert again._replace(rgb=None, cloud_mm=None) == cap._replace(rgb=None, cloud_mm=None)


def _rewrite(src: str, dst: str, **changes: np.ndarray) -> str:
    with zipfile.ZipFile(src) as zf:
        arrays = {name[:-4]: np.load(zf.open(name)) for name in zf.namelist()}
    arrays.update(changes)
    for name in [n for n, v in changes.items() if v is None]:
        del arrays[name]
    with open(dst, "wb") as fh:
        np.savez(fh, **arrays)
    return dst


def test_a_bad_capture_file_is_refused_naming_the_problem(captures: dict[str, str], tmp_path) -> None:
    src = captures["mix"]
    meta = json.loads(str(np.load(src)["meta"]))
    bad = {
        "missing.npz": (None, "capture file not found"),
        "text.npz": (lambda p: open(p, "w").write("not a zip"), "not a readable .npz archive"),
        "no_meta.npz": ({"meta": None}, "members .* a capture file holds format, rgb, cloud_mm, intrinsics, meta"),
        "format.npz": ({"format": np.array("sagrasp_jax capture 9")}, "format .* not 'sagrasp_jax capture 1'"),
        "float64.npz": ({"cloud_mm": np.load(src)["cloud_mm"].astype(np.float64)}, "cloud_mm of type float64"),
        "intrinsics.npz": ({"intrinsics": np.array([640.0, 480, 600, 600, 320, 240])},
                           "intrinsics of a 640 × 480 image for a 480 × 300 cloud"),
        "camera.npz": ({"meta": np.array(json.dumps(meta | {"camera": "kinect"}))}, "camera 'kinect' is not one of"),
        "truth.npz": ({"meta": np.array(json.dumps(meta | {"truth": meta["truth"] | {"q0": [0.0] * 5}}))},
                      r"meta.truth.q0 must be one joint angle per joint of a registered robot \(6 or 7 numbers\)"),
        "rgb.npz": ({"rgb": np.load(src)["rgb"][:-1]}, r"image of shape \(299, 480, 3\) does not match"),
    }
    for name, (change, message) in bad.items():
        path = str(tmp_path / name)
        if callable(change):
            change(path)
        elif change is not None:
            _rewrite(src, path, **change)
        with pytest.raises(capture_file.CaptureFormatError, match=message) as info:
            capture_file.load_capture(path)
        assert path in str(info.value)
    pickled = str(tmp_path / "pickled.npz")
    _rewrite(src, pickled, meta=np.array([{"camera": ""}], dtype=object))
    with pytest.raises(capture_file.CaptureFormatError, match="pickles are not read"):
        capture_file.load_capture(pickled)


def test_replay_on_the_twin_holds_the_cube_and_saves_the_report(captures: dict[str, str], tmp_path) -> None:
    for name in ("mix", "blocking"):
        record = tmp_path / f"record-{name}"
        r = _run("sagrasp_jax.deploy", "--camera", f"replay:{captures[name]}", "--policy", "pretrained", "--json",
                 "--record", str(record), cwd=tmp_path)
        assert r.returncode == 0, r.stderr
        report = json.loads(r.stdout)
        assert report["outcome"] == "success" and report["held"] is True
        truth = capture_file.load_capture(captures[name]).truth
        seen = report["input"]["perception"]
        # perception's cube within 3 mm of the true one; as many obstacles as the scene holds
        assert np.linalg.norm(np.subtract(seen["target_world"], truth["target_pos"])) < 0.003
        assert len(seen["obstacles_world"]) == len(truth["obstacles"])
        assert report["input"]["capture_file"] == os.path.abspath(captures[name])
        assert sorted(os.listdir(record)) == ["report.json"]  # a replay saves the report, not the capture again
        assert json.loads((record / "report.json").read_text()) == report


def test_dry_run_shows_the_detection_and_the_first_commands_and_replays_exactly(captures: dict[str, str], tmp_path) -> None:
    reports = []
    for i in range(2):
        r = _run("sagrasp_jax.deploy", "--camera", f"replay:{captures['blocking']}", "--policy", "pretrained",
                 "--dry-run", "--json", "--record", str(tmp_path / f"dry{i}"), cwd=tmp_path)
        assert r.returncode == 0, r.stderr
        reports.append(json.loads(r.stdout))
    plan = reports[0]["plan"]
    assert reports[0]["commanded"] is False
    assert plan["planned"]["ideal_arm_outcome"] == "success" and len(plan["planned"]["first_commands_rad"]) == 5
    first = np.array(plan["planned"]["first_commands_rad"])
    assert np.abs(np.diff(np.r_[[plan["start_q"]], first], axis=0)).max() < 0.1  # small steps from the start pose
    assert plan["perception"]["cube_by"] == "colour" and plan["perception"]["obstacles_world"]
    a, b = (dict(rep["plan"]["perception"]) for rep in reports)
    a.pop("seconds"), b.pop("seconds")
    assert a == b  # the same capture, the same detection to the last digit
    text = _run("sagrasp_jax.deploy", "--camera", f"replay:{captures['blocking']}", "--policy", "pretrained",
                "--dry-run", "--record", str(tmp_path / "dry-text"), cwd=tmp_path)
    assert text.returncode == 0 and "perception     cube by colour" in text.stdout
    assert "planned        on an ideal arm: success after" in text.stdout


def test_a_calibration_that_puts_the_table_elsewhere_is_refused_with_the_offset(captures: dict[str, str], tmp_path) -> None:
    for dz, expected in ((20.0, r"the table comes out -20\.\d mm"), (120.0, r"comes out -12\d mm from the table's height")):
        matrix = T_CAM_BASE_MM.copy()
        matrix[2, 3] -= dz  # the camera believed dz mm lower than it is: the table comes out dz below z = 0
        cal = tmp_path / f"cal{dz:g}.npy"
        np.save(cal, matrix)
        r = _run("sagrasp_jax.deploy", "--camera", f"replay:{captures['mix']}", "--policy", "pretrained", "--json",
                 "--calibration", str(cal), "--record", str(tmp_path / f"rec{dz:g}"), cwd=tmp_path)
        assert r.returncode == 2, r.stderr
        refusal = json.loads(r.stdout)
        assert refusal["outcome"] == "input_refused"
        assert "does not match this camera" in refusal["message"]
        import re

        assert re.search(expected, refusal["message"]), refusal["message"]


@pytest.mark.parametrize("argv, message", [
    (["--target-cam", "0", "0", "1400"], "give the cube either as --target-cam X Y Z .* not both"),
    (["--obstacle", "sphere", "0", "0", "1300", "30"], "--obstacle: with --camera the perception finds"),
    (["--camera-address", "x"], "--camera-address is for a camera; a replay reads its FILE"),
])
def test_camera_option_conflicts_are_refused(captures: dict[str, str], tmp_path, argv, message) -> None:
    r = _run("sagrasp_jax.deploy", "--camera", f"replay:{captures['mix']}", "--policy", "pretrained", *argv,
             "--record", str(tmp_path / "rec"), cwd=tmp_path)
    assert r.returncode == 2
    import re

    assert re.search(message, r.stderr), r.stderr
    assert not (tmp_path / "rec").exists()  # refused before anything was written


def test_deploy_and_capture_refusals(captures: dict[str, str], tmp_path) -> None:
    full = tmp_path / "full"
    full.mkdir()
    (full / "x").write_text("")
    cases = [
        (["sagrasp_jax.deploy", "--camera", "replay:", "--policy", "pretrained"], "needs the capture file's path"),
        (["sagrasp_jax.deploy", "--camera", "kinect", "--policy", "pretrained"], "'kinect': one of mecheye, realsense"),
        (["sagrasp_jax.deploy", "--camera", "mecheye", "--policy", "pretrained"], "needs --camera-address IP"),
        (["sagrasp_jax.deploy", "--camera", f"replay:{captures['mix']}", "--policy", "pretrained", "--record", str(full)],
         "the folder is not empty"),
        (["sagrasp_jax.deploy", "--camera", f"replay:{tmp_path / 'none.npz'}", "--policy", "pretrained", "--record",
          str(tmp_path / "r1")], "capture file not found"),
        (["sagrasp_jax.capture", "--camera", "twin", "--out", captures["mix"]], "exists \\(add --force"),
        (["sagrasp_jax.capture", "--camera", "mecheye", "--out", str(tmp_path / "m.npz")], "needs --camera-address"),
        (["sagrasp_jax.capture", "--camera", "realsense", "--scene", "3", "--out", str(tmp_path / "r.npz")],
         "--scene is only for --camera twin"),
        (["sagrasp_jax.capture", "--camera", "twin", "--camera-address", "1.2.3.4", "--out", str(tmp_path / "t.npz")],
         "--camera-address and --arm-joints are for a real camera"),
    ]
    for argv, message in cases:
        r = _run(*argv, cwd=tmp_path)
        assert r.returncode == 2, (argv, r.stdout, r.stderr)
        import re

        assert re.search(message, r.stderr), (argv, r.stderr)
        assert "Traceback" not in r.stderr
    assert not any(p.name.endswith(".npz") for p in tmp_path.iterdir())


def test_the_ideal_arm_plan_sends_what_the_loop_would(captures: dict[str, str]) -> None:
    """plan_episode: every command an ideal arm gets, in order, the arm where the last one put it."""
    truth = capture_file.load_capture(captures["mix"]).truth
    policy = load_policy("pretrained")
    report, commands = plan_episode(policy, truth["q0"], truth["target_pos"], truth["target_yaw"], [])
    assert report.outcome == "success" and report.steps == len(commands) > 5
    assert np.allclose(report.final_q, commands[-1])
    arm = IdealArm(truth["q0"])
    arm.command_joint_targets(np.zeros(6))
    assert np.array_equal(arm.read_joints(), np.zeros(6)) and len(arm.commands) == 1


def test_capture_save_refuses_mismatched_intrinsics(tmp_path) -> None:
    cap = Capture(np.zeros((10, 12, 3), np.uint8), np.full((10, 12, 3), 1000.0, np.float32), Intrinsics(12, 11, 10, 10, 6, 5))
    with pytest.raises(ValueError, match="intrinsics of a 12 × 11 image for a 12 × 10 cloud"):
        capture_file.save_capture(str(tmp_path / "c.npz"), cap)
    assert not list(tmp_path.iterdir())


def _arm_in_view_capture(folder, robot_q_known: bool) -> str:
    """A twin capture taken with the arm at its start pose, in the camera's view (a real cell's capture before the
    arm moves), with or without its joints recorded."""
    from sagrasp_jax.deploy import rehearse
    from sagrasp_jax.deploy.twin import PyBulletTwin
    from sagrasp_jax.deploy.twin_camera import TwinCamera
    from sagrasp_jax.task.config import EnvConfig

    env_cfg = EnvConfig()
    spec, rng = rehearse.draw_scene(rehearse.scene_env(env_cfg, "mix"), 0, 5)
    with PyBulletTwin(spec, env_cfg, q0=spec.q0, seed=5) as twin:
        frame = TwinCamera(0.25).capture(twin, "industrial", rng, hide_robot=False)
    cap = Capture(frame.rgb, frame.cloud_mm, frame.intrinsics, "mecheye_pro_m", "twin, arm in view", "",
                  capture_file.scene_truth(spec, "no obstacle"),
                  tuple(float(v) for v in spec.q0) if robot_q_known else None)
    return capture_file.save_capture(str(folder / f"arm-{robot_q_known}.npz"), cap)


def test_the_arm_in_view_is_left_out_where_its_joints_say(tmp_path) -> None:
    """The AUBO at home stands in the gantry camera's view: with the joints the capture was taken at, perception
    leaves it out and the cube is held; without them the arm is an object taller than any obstacle, refused."""
    known = _arm_in_view_capture(tmp_path, True)
    assert capture_file.load_capture(known).robot_q is not None
    r = _run("sagrasp_jax.deploy", "--camera", f"replay:{known}", "--policy", "pretrained", "--json", "--record",
             str(tmp_path / "known"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    report = json.loads(r.stdout)
    assert report["held"] is True and report["input"]["capture"]["robot_q"] is not None
    unknown = _arm_in_view_capture(tmp_path, False)
    r = _run("sagrasp_jax.deploy", "--camera", f"replay:{unknown}", "--policy", "pretrained", "--record",
             str(tmp_path / "unknown"), cwd=tmp_path)
    assert r.returncode == 2 and "taller than any trained obstacle" in r.stderr, r.stderr
