"""Fault injection (issue 16): kills, damaged files, concurrent writers, bad numbers, read-only
outputs and tampered policies.  Each case checks the exit code, the message and that nothing
changed.  Runs in about a minute on 2 cores: the toy env (tests/toy_env.py) stands in for the
grasp env wherever the env does not matter, and every refusal happens before an env is built.

The numbered tests map to the defects of issue 16:
1 ``deploy --json`` with NaN/inf input; 2 concurrent writers; 3 evaluate on a damaged config;
4 resume on a damaged metrics log; 5 values that validated but crashed later; 6 a run killed
before its first checkpoint; 7 read-only outputs; 8 safety limits from the robot, not the
policy; 9 stale checkpoint temp files and evaluations replaced without warning.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import contextlib
import hashlib
import json
import math
import os
import random
import re
import shutil
import subprocess
import sys
import time
import typing
from typing import Any, Callable

import numpy as np
import pytest

from conftest import toy_config, toy_factory

from sagrasp_jax.task import config as config_mod
from sagrasp_jax.task import config_history
from sagrasp_jax.task import config_parse
from sagrasp_jax import evaluate, export, train
from sagrasp_jax.training import evaluation
from sagrasp_jax.base import fileio
from sagrasp_jax.training import launch, run_dir
from sagrasp_jax.training import trainer as trainer_mod
from sagrasp_jax.task import policy_file as runtime
from sagrasp_jax.task.config import HOME_Q, get_config
from sagrasp_jax.deploy import __main__ as deploy_cli
from sagrasp_jax.deploy.calibration import CameraCalibration, ObstacleRejected
from sagrasp_jax.deploy.loop import Obstacle, run_episode
from sagrasp_jax.deploy.safety import PolicyMismatch

_GL = os.environ.get("MUJOCO_GL")
from sagrasp_jax import render  # noqa: E402  (render picks MUJOCO_GL on import: keep the session's)
from sagrasp_jax import parity as parity_command  # noqa: E402
from paths import REPO  # noqa: E402

if _GL is None:
    os.environ.pop("MUJOCO_GL", None)

DRIVER = os.path.join(REPO, "tests", "fault_driver.py")
TARGET = np.array([0.10, -0.45, 0.025])  # a cube centre in the trained region (world, m)
BAD_FLOATS = ("nan", "inf", "-inf", "1e30")
BAD_INTS = ("nan", "inf", "-inf", str(10**30))


# ---------------------------------------------------------------------- helpers

def snapshot(folder: str) -> dict[str, tuple[int, str]]:
    """Every file below ``folder``: (mtime_ns, sha256), to assert that nothing changed; a symlink or a
    FIFO, device or socket as (mtime_ns, what it is), never opened."""
    import stat

    out = {}
    for root, dirs, files in os.walk(folder):
        for name in files + [d for d in dirs if os.path.islink(os.path.join(root, d))]:
            path = os.path.join(root, name)
            st = os.lstat(path)
            if stat.S_ISLNK(st.st_mode):
                out[os.path.relpath(path, folder)] = (st.st_mtime_ns, f"link to {os.readlink(path)}")
            elif not stat.S_ISREG(st.st_mode):
                out[os.path.relpath(path, folder)] = (st.st_mtime_ns, fileio.file_kind(st.st_mode))
            else:
                with open(path, "rb") as f:
                    out[os.path.relpath(path, folder)] = (st.st_mtime_ns, hashlib.sha256(f.read()).hexdigest())
    return out


def call(main: Callable[[list[str]], int], argv: list[str], capsys: pytest.CaptureFixture) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of an in-process CLI ``main``; argparse's own refusals included."""
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    out = capsys.readouterr()
    return code, out.out, out.err


def damage(path: str, how: str) -> None:
    with open(path, "rb") as f:
        data = f.read()
    if how == "truncated":
        data = data[: len(data) // 2]
    elif how == "garbled":
        mid = len(data) // 2
        data = data[:mid] + b"\x00\xff\xfe garbage \x80\x81" * 4 + data[mid + 60:]
    else:
        data = b""
    with open(path, "wb") as f:
        f.write(data)


def rows(run: str) -> list[dict[str, Any]]:
    return [{k: v for k, v in r.items() if k not in train.TIME_FIELDS}
            for r in run_dir.read_metrics(run_dir.path(run, run_dir.METRICS_FILE))]


def policy_arrays(run: str) -> dict[str, np.ndarray]:
    with np.load(run_dir.path(run, run_dir.POLICY_FILE)) as data:
        return {k: data[k] for k in data.files}


@pytest.fixture
def run_copy(toy_run: str, tmp_path) -> str:
    """A private copy of the finished toy run folder."""
    return shutil.copytree(toy_run, str(tmp_path / "run"))


def write_policy(path: str, cfg: config_mod.Config | None = None) -> str:
    """A small valid grasp policy file (constant action), no training needed."""
    weights = [(np.zeros((17, 8), np.float32), np.zeros(8, np.float32)),
               (np.zeros((8, 12), np.float32), np.zeros(12, np.float32))]
    return runtime.save_policy_npz(path, weights=weights, activation="tanh", obs_mean=np.zeros(17), obs_std=np.ones(17),
                                   config=cfg or get_config("paper"))


@pytest.fixture(scope="module")
def policy_file(tmp_path_factory) -> str:
    return write_policy(str(tmp_path_factory.mktemp("policy") / "policy.npz"))


def cam_mm(world_top: Any) -> list[str]:
    return [f"{v:.6f}" for v in CameraCalibration.default().base_to_cam(np.asarray(world_top), units="mm")]


TARGET_CAM = cam_mm(TARGET + [0, 0, 0.025])  # the detected top face


@pytest.fixture
def no_twin(monkeypatch):
    """Fail the test if the deploy CLI builds a robot backend (it must refuse before that)."""
    import sagrasp_jax.deploy.twin as twin

    def refuse(*a, **k):
        raise AssertionError("a twin was built: the input was not refused before moving")

    monkeypatch.setattr(twin, "PyBulletTwin", refuse)


def readonly_location(tmp_path) -> str:
    """A folder that this process cannot write into: a chmod-ed folder, or (as root, whom chmod
    does not stop) a folder on sysfs; skips where neither holds."""
    if os.geteuid() != 0:
        folder = tmp_path / "readonly"
        folder.mkdir()
        folder.chmod(0o555)
        return str(folder)
    for folder in ("/sys/kernel", "/sys", "/proc/sys"):
        try:
            fileio.check_writable(folder)
        except OSError:
            return folder
    pytest.skip("no read-only location available to this (root) process")


class Twinless:
    """A RobotInterface that records what reaches it (the library path of the deploy loop)."""

    def __init__(self) -> None:
        self.sent: list[np.ndarray] = []

    def read_joints(self) -> np.ndarray:
        return np.array(HOME_Q)

    def command_joint_targets(self, q: np.ndarray) -> None:
        self.sent.append(np.array(q))

    def open_gripper(self) -> None:
        pass

    def close_gripper(self) -> None:
        pass


# ---------------------------------------------------------------------- 1: deploy --json with NaN / inf

@pytest.mark.parametrize("argv,message", [
    (["--target-cam", "nan", "-77", "1374"], "--target-cam: camera point [nan, -77.0, 1374.0] must be 3 finite"),
    (["--target-cam", "-147", "inf", "1374"], "--target-cam: camera point [-147.0, inf, 1374.0] must be 3 finite"),
    (["--target-yaw", "nan"], "--target-yaw nan must be a finite angle"),
    (["--target-yaw=-inf"], "--target-yaw -inf must be a finite angle"),
])
def test_1_deploy_json_refuses_nan_and_inf_with_exit_2(policy_file, argv, message, capsys, no_twin):
    argv = ["--policy", policy_file, *(["--target-cam", *TARGET_CAM] if argv[0] != "--target-cam" else []), *argv, "--json"]
    code, out, err = call(deploy_cli.main, argv, capsys)
    assert code == 2 and message in err and "Traceback" not in err
    report = json.loads(out, parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))
    assert report["outcome"] == "input_refused" and message in report["message"]


# ---------------------------------------------------------------------- 2: concurrent writers

def test_2_a_second_writer_is_refused_and_changes_nothing(run_copy, tmp_path, capsys):
    before = snapshot(run_copy)
    with run_dir.FolderLock(run_copy):  # another process writing the run folder
        code, _, err = call(train.main, ["--out", run_copy, "--resume", "--no-progress"], capsys)
        assert code == 2 and "is in use by another process" in err
        code, _, err = call(evaluate.main, ["--run", run_copy, "--episodes", "8"], capsys)
        assert code == 2 and "is in use by another process" in err
        code, _, err = call(export.main, ["--run", run_copy, "--out", run_copy, "--no-onnx"], capsys)
        assert code == 2 and "is in use by another process" in err
    assert snapshot(run_copy) == before
    fresh = str(tmp_path / "fresh")
    with run_dir.FolderLock(fresh, create=True):  # a training that has just created its folder
        code, _, err = call(train.main, ["--out", fresh, "--no-progress"], capsys)
        assert code == 2 and "is in use by another process" in err
    assert not os.path.exists(fresh)  # the lock holder made it and removed it, still empty


# ---------------------------------------------------------------------- 3 / 4 / 9: every run-folder file damaged

READERS = {
    run_dir.CONFIG_FILE: ("resume", "evaluate", "export"),
    run_dir.METRICS_FILE: ("resume",),
    run_dir.CHECKPOINT_FILE: ("resume", "evaluate", "export"),
    run_dir.POLICY_FILE: ("deploy", "render"),
}
CASES = [(name, command, how) for name, commands in READERS.items() for command in commands
         for how in ("truncated", "garbled", "emptied")]


def _run_command(command: str, run: str, tmp_path, capsys) -> tuple[int, str]:  # noqa: C901
    if command == "resume":
        code, _, err = call(train.main, ["--out", run, "--resume", "--no-progress"], capsys)
    elif command == "evaluate":
        code, _, err = call(evaluate.main, ["--run", run, "--episodes", "8"], capsys)
    elif command == "export":
        code, _, err = call(export.main, ["--run", run, "--out", str(tmp_path / "export"), "--no-onnx"], capsys)
        assert not os.path.exists(tmp_path / "export")
    elif command == "deploy":
        code, _, err = call(deploy_cli.main, ["--policy", run_dir.path(run, run_dir.POLICY_FILE),
                                              "--target-cam", *TARGET_CAM], capsys)
    else:
        code, _, err = call(render.main, ["--policy", run_dir.path(run, run_dir.POLICY_FILE),
                                          "--out", str(tmp_path / "video.mp4")], capsys)
        assert not os.path.exists(tmp_path / "video.mp4")
    return code, err


@pytest.mark.parametrize("name,command,how", CASES, ids=[f"{c}-{n}-{h}" for n, c, h in CASES])
def test_3_4_each_damaged_run_file_is_refused_by_each_reader(run_copy, tmp_path, capsys, name, command, how, no_twin):
    path = run_dir.path(run_copy, name)
    damage(path, how)
    before = snapshot(run_copy)
    code, err = _run_command(command, run_copy, tmp_path, capsys)
    assert code == 2, err
    assert path in err, err  # the message names the damaged file
    assert "Traceback" not in err
    assert snapshot(run_copy) == before


@pytest.mark.parametrize("how", ["truncated", "garbled", "emptied"])
def test_9_a_damaged_earlier_evaluation_is_not_replaced_without_force(run_copy, how, capsys, monkeypatch):
    monkeypatch.setattr(evaluation, "evaluate_run", lambda *a, **k: pytest.fail("evaluated before refusing"))
    cfg = run_dir.load_config(run_copy)
    path = run_dir.path(run_copy, run_dir.evaluation_file(8, cfg.eval.seed + 1))
    run_dir.write_json(path, {"episodes": 8, "overall": {"success_rate": 0.5}})
    damage(path, how)
    before = snapshot(run_copy)
    code, _, err = call(evaluate.main, ["--run", run_copy, "--episodes", "8"], capsys)
    assert code == 2 and path in err and "--force" in err
    assert snapshot(run_copy) == before


def test_4_resume_names_the_line_of_a_damaged_metrics_log(run_copy, capsys):
    path = run_dir.path(run_copy, run_dir.METRICS_FILE)
    with open(path, "rb") as f:
        lines = f.read().split(b"\n")
    lines[3] = b'{"iteration": 3, "loss": \x00\x01\xfe}'
    with open(path, "wb") as f:
        f.write(b"\n".join(lines))
    before = snapshot(run_copy)
    code, _, err = call(train.main, ["--out", run_copy, "--resume", "--no-progress"], capsys)
    assert code == 2 and f"{path}: damaged metrics log at line 4" in err
    assert snapshot(run_copy) == before


# ---------------------------------------------------------------------- 5: NaN / inf / huge / crash-later values

def _numeric_keys() -> list[str]:
    def numeric(annotation: Any) -> bool:
        if typing.get_origin(annotation) is tuple:
            return all(a in (int, float) for a in typing.get_args(annotation) if a is not Ellipsis)
        return annotation in (int, float)

    keys = []
    for key in config_mod.valid_keys():
        *path, leaf = key.split(".")
        obj: Any = config_mod.Config()
        for name in path:
            obj = getattr(obj, name)
        if numeric(typing.get_type_hints(type(obj))[leaf]):
            keys.append(key)
    return keys


NUMERIC_KEYS = _numeric_keys()


def test_5_every_numeric_key_has_a_range():
    """A new numeric config key must declare its range (NaN/inf/huge are refused by it)."""
    assert [key for key in NUMERIC_KEYS if config_mod.key_specs()[key].range is None] == []


@pytest.mark.parametrize("key", NUMERIC_KEYS)
def test_5_nan_inf_and_huge_set_values_are_refused(key, tmp_path, capsys):
    current = config_mod.get_key(config_mod.Config(), key)
    out = tmp_path / "run"
    for bad in BAD_FLOATS:
        if isinstance(current, tuple):
            value = "[" + ", ".join([bad] * len(current) if current else [bad]) + "]"
        else:
            value = bad
        code, _, err = call(train.main, ["--out", str(out), "--no-progress", "--set", f"{key}={value}"], capsys)
        assert code == 2 and key in err, (key, value, err)
        assert not out.exists()


@pytest.mark.parametrize("argv,message", [
    (["--set", "train.checkpoint_every_cycles=0"], "train.checkpoint_every_cycles: 0"),
    (["--set", "train.log_every=0"], "train.log_every: 0"),
    (["--seed", "-1"], "--seed=-1 is outside the allowed range"),
    (["--seed", str(2**32)], "--seed=4294967296 is outside the allowed range"),
    (["--total-steps", "0"], "--total-steps=0"),
    (["--stop-after-cycles", "0"], "--stop-after-cycles=0"),
])
def test_5_values_that_used_to_crash_later_are_refused_up_front(argv, message, tmp_path, capsys):
    out = tmp_path / "run"
    code, _, err = call(train.main, ["--out", str(out), "--no-progress", *argv], capsys)
    assert code == 2 and message in err and not out.exists()


@pytest.mark.parametrize("max_steps", ["0", "-5"])
def test_5_evaluate_max_steps_below_one_is_refused(run_copy, max_steps, capsys):
    before = snapshot(run_copy)
    code, _, err = call(evaluate.main, ["--run", run_copy, "--episodes", "8", "--max-steps", max_steps], capsys)
    assert code == 2 and f"--max-steps={max_steps} is outside the allowed range [1, 100000]" in err
    assert snapshot(run_copy) == before


def _cli_cases(policy: str, run: str, tmp: str) -> list[tuple[str, Callable[[list[str]], int], list[str], str, tuple[str, ...]]]:
    """(name, main, base argv, flag, bad values) for every numeric option of every command."""
    out = os.path.join(tmp, "out")
    deploy_base = ["--policy", policy, "--target-cam", *TARGET_CAM, "--json"]
    cases = [("train", train.main, ["--out", out, "--no-progress"], flag, BAD_INTS)
             for flag in ("--seed", "--total-steps", "--stop-after-cycles")]
    cases += [("evaluate", evaluate.main, ["--run", run, "--out", os.path.join(out, "e.json")], flag, BAD_INTS)
              for flag in ("--episodes", "--seed", "--max-steps")]
    cases += [("export", export.main, ["--run", run, "--out", out], "--opset", BAD_INTS)]
    cases += [("deploy", deploy_cli.main, deploy_base, flag, BAD_FLOATS)
              for flag in ("--target-yaw", "--base-z-offset", "--base-yaw")]
    cases += [("deploy", deploy_cli.main, deploy_base, "--max-steps", BAD_INTS)]
    cases += [("render", render.main, ["--policy", policy, "--out", os.path.join(out, "v.mp4")], flag, BAD_INTS)
              for flag in ("--episodes", "--seed", "--width", "--height", "--fps", "--max-steps")]
    cases += [("parity", parity_command.main, ["--out", os.path.join(out, "p.json"), "--quiet"], flag, BAD_INTS)
              for flag in ("--episodes", "--seed", "--max-steps", "--batch")]
    return cases


def test_5_nan_inf_and_huge_numeric_options_of_every_command_are_refused(policy_file, run_copy, tmp_path, capsys,
                                                                          no_twin):
    before = snapshot(run_copy)
    for name, main, base, flag, values in _cli_cases(policy_file, run_copy, str(tmp_path)):
        for value in values:
            code, out, err = call(main, [*base, f"{flag}={value}"], capsys)
            assert code == 2 and flag in err and "Traceback" not in err, (name, flag, value, err)
            if name == "deploy":
                assert json.loads(out)["outcome"] == "input_refused"
            assert not os.path.exists(tmp_path / "out"), (name, flag, value)
    # the detections: every number of --target-cam and of an --obstacle ("-inf" cannot be passed to an
    # option taking several values: argparse reads it as an option name)
    obstacle = [*cam_mm([0.25, -0.30, 0.16]), "30"]
    several = [v for v in BAD_FLOATS if not v.startswith("-")]
    for i in range(3):
        for value in several:
            cam = list(TARGET_CAM)
            cam[i] = value
            code, out, err = call(deploy_cli.main, ["--policy", policy_file, "--target-cam", *cam, "--json"], capsys)
            assert code == 2 and "--target-cam" in err and json.loads(out)["outcome"] == "input_refused"
    for i in range(4):
        for value in several:
            ob = list(obstacle)
            ob[i] = value
            code, out, err = call(deploy_cli.main, ["--policy", policy_file, "--target-cam", *TARGET_CAM,
                                                    "--obstacle", "sphere", *ob, "--json"], capsys)
            assert code == 2 and "--obstacle #1" in err and json.loads(out)["outcome"] == "input_refused", err
    for value in several:  # a box's yaw
        code, out, err = call(deploy_cli.main, ["--policy", policy_file, "--target-cam", *TARGET_CAM, "--obstacle",
                                                "box", *cam_mm([0.25, -0.30, 0.08]), "40", "40", "80", value], capsys)
        assert code == 2 and "--obstacle #1: box yaw" in err
    assert snapshot(run_copy) == before


# ---------------------------------------------------------------------- 6: killed before the first checkpoint

def test_6_a_run_killed_before_its_first_checkpoint_restarts_with_resume(toy_run, tmp_path, capsys):
    out = str(tmp_path / "run")
    os.makedirs(os.path.join(out, run_dir.TB_DIR))
    run_dir.write_config(out, toy_config())
    shutil.copy(run_dir.path(toy_run, run_dir.METRICS_FILE), run_dir.path(out, run_dir.METRICS_FILE))  # rows, no ckpt
    before = snapshot(out)
    code, _, err = call(train.main, ["--out", out, "--no-progress"], capsys)
    assert code == 2 and "stopped before its first checkpoint; pass --resume to restart it" in err
    assert snapshot(out) == before
    train.run(toy_config(), out, resume=True, env_factory=toy_factory(), progress=False)
    assert "restarting it from the beginning" in capsys.readouterr().err
    assert rows(out) == rows(toy_run)
    assert {k: v.tolist() for k, v in policy_arrays(out).items()} == {k: v.tolist() for k, v in policy_arrays(toy_run).items()}


# ---------------------------------------------------------------------- 7: read-only outputs

def test_7_read_only_outputs_are_refused_before_any_work(policy_file, run_copy, tmp_path, capsys, monkeypatch):
    readonly = readonly_location(tmp_path)
    monkeypatch.setattr(launch, "Trainer", lambda *a, **k: pytest.fail("the env was built before refusing"))
    monkeypatch.setattr(evaluation, "evaluate_run", lambda *a, **k: pytest.fail("evaluated before refusing"))
    before = snapshot(run_copy)
    target = os.path.join(readonly, "sagrasp-fault-test")
    code, _, err = call(train.main, ["--out", target, "--no-progress"], capsys)
    assert code == 2 and "cannot create run folder" in err and not os.path.exists(target)
    code, _, err = call(evaluate.main, ["--run", run_copy, "--episodes", "8", "--out", target + ".json"], capsys)
    assert code == 2 and "cannot write into output folder" in err
    code, _, err = call(export.main, ["--run", run_copy, "--out", target, "--no-onnx"], capsys)
    assert code == 2 and "cannot create output folder" in err
    code, _, err = call(render.main, ["--policy", policy_file, "--out", target + ".mp4"], capsys)
    assert code == 2 and "cannot write into output folder" in err
    code, _, err = call(parity_command.main, ["--out", target + ".json", "--quiet"], capsys)
    assert code == 2 and "cannot write into output folder" in err
    assert snapshot(run_copy) == before


# ---------------------------------------------------------------------- 8: safety from the robot; tampered policies

def _tampered(path: str, edit: Callable[[dict[str, Any]], None], rehash: bool) -> str:
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    cfg = json.loads(str(arrays["config_json"]))
    edit(cfg)
    arrays["config_json"] = np.asarray(json.dumps(cfg, sort_keys=True))
    if rehash:
        arrays["config_hash"] = np.asarray(config_history.config_hash(config_parse.config_from_dict(cfg)))
        arrays["action_scale"] = np.asarray(cfg["env"]["control"]["q_max"], np.float64)
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    return path


@pytest.mark.parametrize("edit,rehash,message", [
    (lambda c: c["env"]["control"].update(q_max=0.5), True,
     "control constants this robot does not use: env.control.q_max (rad per step): policy 0.5, deployment 0.05"),
    (lambda c: c["env"]["control"].update(control_dt=0.5), True, "env.control.control_dt (s): policy 0.5"),
    (lambda c: c["env"]["control"].update(q_limit=3.14), True, "env.control.q_limit (rad): policy 3.14, URDF"),
    (lambda c: c["env"]["control"].update(q_max=0.5), False, "file edited?"),
])
def test_8_a_tampered_policy_file_is_refused_before_moving(policy_file, tmp_path, edit, rehash, message, capsys, no_twin):
    path = _tampered(shutil.copy(policy_file, str(tmp_path / "policy.npz")), edit, rehash)
    before = snapshot(str(tmp_path))
    code, out, err = call(deploy_cli.main, ["--policy", path, "--target-cam", *TARGET_CAM, "--json"], capsys)
    assert code == 2 and message in err and json.loads(out)["outcome"] == "input_refused"
    assert snapshot(str(tmp_path)) == before
    if rehash:  # the library path refuses it too, and nothing reaches the robot
        robot = Twinless()
        with pytest.raises(PolicyMismatch, match="control constants"):
            run_episode(robot, runtime.load_policy(path), TARGET)
        assert robot.sent == []


def test_8_obstacle_inside_the_training_clearance_is_refused_before_moving(policy_file, capsys, no_twin):
    cfg = get_config("cpu-quick").env
    # a cylinder 0.06 m from the cube centre, surface 0.03 m away: under target_clearance = 0.10 m
    top = cam_mm(TARGET + [0.06, 0.0, 0.1])
    code, out, err = call(deploy_cli.main, ["--policy", policy_file, "--target-cam", *TARGET_CAM, "--obstacle",
                                            "cylinder", *top, "30", "200", "--json"], capsys)
    assert code == 2 and "obstacle too close to the cube: obstacle 1 (cylinder) is 0.0300 m from it" in err
    assert f"target_clearance = {cfg.sampling.target_clearance:g} m" in err
    robot = Twinless()
    near = Obstacle("box", tuple(TARGET + [0.0, 0.08, 0.0]), (0.04, 0.04, 0.05))
    with pytest.raises(ObstacleRejected, match=r"obstacle 1 \(box\) is 0.0400 m"):
        run_episode(robot, runtime.load_policy(policy_file), TARGET, obstacles=[near])
    assert robot.sent == []
    far = Obstacle("sphere", tuple(TARGET + [0.16, 0.0, 0.125]), (0.05, 0.0, 0.0))  # surface 0.11 m: allowed
    report = run_episode(robot, runtime.load_policy(policy_file), TARGET, obstacles=[far], max_steps=2, grasp=False)
    assert report.steps == 2 and len(robot.sent) == 2


# ---------------------------------------------------------------------- 9: evaluation outputs

def test_9_evaluate_names_its_output_and_refuses_to_replace_another_evaluation(run_copy, capsys, monkeypatch):
    monkeypatch.setattr(evaluation, "default_eval_env", lambda cfg: toy_factory()(cfg)[1])
    cfg = run_dir.load_config(run_copy)
    seed = cfg.eval.seed + 1
    assert call(evaluate.main, ["--run", run_copy, "--episodes", "16"], capsys)[0] == 0
    first = run_dir.path(run_copy, f"evaluation-16ep-seed{seed}.json")
    assert json.load(open(first))["episodes"] == 16
    assert call(evaluate.main, ["--run", run_copy, "--episodes", "32", "--seed", "7"], capsys)[0] == 0
    assert json.load(open(run_dir.path(run_copy, "evaluation-32ep-seed7.json")))["episodes"] == 32
    assert json.load(open(first))["episodes"] == 16  # untouched
    assert call(evaluate.main, ["--run", run_copy, "--episodes", "16"], capsys)[0] == 0  # the same evaluation again
    # the file now claims an older checkpoint: a different evaluation, kept unless --force
    old = json.load(open(first))
    old["checkpoint_iteration"] = 3
    run_dir.write_json(first, old)
    before = snapshot(run_copy)
    code, _, err = call(evaluate.main, ["--run", run_copy, "--episodes", "16"], capsys)
    assert code == 2 and f"{first} holds a different result (checkpoint_iteration 3 -> " in err and "--force" in err
    assert snapshot(run_copy) == before
    assert call(evaluate.main, ["--run", run_copy, "--episodes", "16", "--force"], capsys)[0] == 0
    assert json.load(open(first))["checkpoint_iteration"] != 3


# ---------------------------------------------------------------------- 2 / 6 / 9: real kills

class Driver:
    """tests/fault_driver.py in a subprocess (the toy training through train.run)."""

    def __init__(self, out: str, *extra: str, env: dict[str, str] | None = None) -> None:
        # Cache even the trainer's many sub-second compiles: each driver starts in ≈ 6 s, not 10.  PYTHONPATH:
        # this checkout's package, whatever an editable install elsewhere points at.
        env = dict(os.environ, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
                   PYTHONPATH=os.pathsep.join([REPO, *filter(None, [os.environ.get("PYTHONPATH")])]), **(env or {}))
        self.proc = subprocess.Popen([sys.executable, DRIVER, out, *extra], stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, cwd=REPO, env=env)

    def wait_for(self, marker: str, timeout: float = 240.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if not line:
                return False  # exited
            if line.strip() == marker:
                return True
        raise AssertionError(f"driver did not print {marker} in {timeout} s")

    def kill(self) -> int:
        with contextlib.suppress(ProcessLookupError):
            self.proc.kill()
        return self.finish()

    def finish(self) -> int:
        rest, _ = self.proc.communicate(timeout=240)
        assert self.proc.returncode in (0, -9), rest[-3000:]
        return self.proc.returncode


def test_2_6_9_kills_at_random_points_then_resume_equals_the_uninterrupted_run(toy_run, tmp_path, capsys):
    out = str(tmp_path / "run")
    rng = random.Random(16)
    # A kill in the middle of the first checkpoint write: before the first checkpoint, with a temp file left.
    assert Driver(out, "--die-in-checkpoint-write", "1").finish() == -9
    temps = fileio.temp_files(out)
    assert len(temps) == 1 and os.path.basename(temps[0]).startswith(".checkpoint.ckpt.")
    assert not os.path.exists(run_dir.path(out, run_dir.CHECKPOINT_FILE))
    before = snapshot(out)
    code, _, err = call(train.main, ["--out", out, "--no-progress"], capsys)  # a fresh start is refused, and says why
    assert code == 2 and "stopped before its first checkpoint" in err and snapshot(out) == before
    for round_ in range(2):
        driver = Driver(out, "--slow", "0.1")  # resume (or restart): the temp file goes first
        if driver.wait_for("COMPILED"):
            assert fileio.temp_files(out) == []
            if round_ == 0:  # a second writer meanwhile is refused, naming the one at work
                before = snapshot(out)
                code, _, err = call(train.main, ["--out", out, "--resume", "--no-progress"], capsys)
                assert code == 2 and f"is in use by another process (pid {driver.proc.pid}" in err
                assert snapshot(out) == before
            time.sleep(rng.uniform(0.0, 1.5))
        driver.kill()
    # And a kill during a later checkpoint write, if the run has one left to write.
    if Driver(out, "--die-in-checkpoint-write", "1").finish() == -9:
        assert [os.path.basename(t).startswith(".checkpoint.ckpt.") for t in fileio.temp_files(out)] == [True]
    train.run(toy_config(), out, resume=True, env_factory=toy_factory(), progress=False)
    assert fileio.temp_files(out) == []
    assert rows(out) == rows(toy_run)
    assert {k: v.tolist() for k, v in policy_arrays(out).items()} == {k: v.tolist() for k, v in policy_arrays(toy_run).items()}
    ckpt, ref = run_dir.load_checkpoint(out), run_dir.load_checkpoint(toy_run)
    assert ckpt.host == ref.host
    for name in ref.trees:
        assert ckpt.trees[name].keys() == ref.trees[name].keys()
        for leaf in ckpt.trees[name]:
            np.testing.assert_array_equal(ckpt.trees[name][leaf], ref.trees[name][leaf], err_msg=f"{name}{leaf}")



# ====================================================================== issue 27
# 1 dynamic-mode resume; 2 deploy's cell from the deployment, not the policy file; 3 multi-process
# options; 4 full disks; 5 an evaluation's identity includes what was trained; 6 NaN / Infinity in the
# metrics log; 7 oversized policy files; 8 a checkpoint that is a folder; 9 SIGTERM; 10 evaluations
# lock their result file, not its folder; 11 an empty hidden-layer list.

TWO_CPU_DEVICES = {"JAX_PLATFORMS": "cpu",
                   "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}


def _checkpoints_equal(a: str, b: str) -> None:
    ckpt, ref = run_dir.load_checkpoint(a), run_dir.load_checkpoint(b)
    assert ckpt.host == ref.host
    for name in ref.trees:
        assert ckpt.trees[name].keys() == ref.trees[name].keys()
        for leaf in ckpt.trees[name]:
            np.testing.assert_array_equal(ckpt.trees[name][leaf], ref.trees[name][leaf], err_msg=f"{name}{leaf}")


def test_27_1_dynamic_mode_kill_and_resume_equals_the_uninterrupted_run(tmp_path):
    # Two devices: the env batch is split, and zero-size MJX fields ([B, 0]) must come back from the
    # checkpoint placed as the jitted reset places them, or the second call after a resume fails.  One
    # process trains the uninterrupted run and leaves a copy of its folder as a kill right after the first
    # checkpoint would leave it (a dynamic-mode trainer takes ≈ 15 s to build: two, not three)
    ref, out = str(tmp_path / "ref"), str(tmp_path / "run")
    assert Driver(ref, "--dynamic", "--snapshot-after-checkpoint", "1", out, env=TWO_CPU_DEVICES).finish() == 0
    assert run_dir.checkpoint_counters(run_dir.load_checkpoint(out))["iteration"] == 1  # after cycle 1 of 3
    assert Driver(out, "--dynamic", env=TWO_CPU_DEVICES).finish() == 0  # two more cycles: two calls
    assert len(rows(out)) == 3 and rows(out) == rows(ref)
    assert {k: v.tolist() for k, v in policy_arrays(out).items()} == {k: v.tolist() for k, v in policy_arrays(ref).items()}
    _checkpoints_equal(out, ref)


@pytest.mark.parametrize("edit,target,message", [
    (lambda c: c["env"]["sampling"].update(target_x=[-0.8, 0.8], target_radius=[0.25, 1.0]), ["-645", "-66", "1417"],
     "trained for a cell this deployment does not have: env.sampling.target_x (m): policy [-0.8, 0.8], deployment "
     "[-0.35, 0.35]; env.sampling.target_radius (m): policy [0.25, 1.0], deployment [0.25, 0.65]"),
    (lambda c: c["env"]["sampling"].update(target_size=[0.002, 0.002, 0.002]), TARGET_CAM,
     "env.sampling.target_size (m, full extents): policy [0.002, 0.002, 0.002], deployment [0.02, 0.02, 0.05]"),
    (lambda c: c["env"]["sampling"].update(target_clearance=0.01), TARGET_CAM,
     "env.sampling.target_clearance (m): policy 0.01, deployment 0.1"),
])
def test_27_2_a_policy_recording_another_cell_is_refused_before_moving(policy_file, tmp_path, edit, target, message,
                                                                        capsys, no_twin):
    path = _tampered(shutil.copy(policy_file, str(tmp_path / "policy.npz")), edit, rehash=True)  # hash recomputed
    code, out, err = call(deploy_cli.main, ["--policy", path, "--target-cam", *target, "--json"], capsys)
    assert code == 2 and message in err and "Traceback" not in err, err
    assert json.loads(out)["outcome"] == "input_refused"
    robot = Twinless()
    with pytest.raises(PolicyMismatch, match="trained for a cell this deployment does not have"):
        run_episode(robot, runtime.load_policy(path), TARGET)
    assert robot.sent == []


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def test_27_3_multi_process_options_are_checked_and_the_start_is_time_boxed(tmp_path, capsys, monkeypatch):
    import threading

    from sagrasp_jax.training import distributed

    monkeypatch.setattr(launch, "Trainer", lambda *a, **k: pytest.fail("the env was built before refusing"))
    out = str(tmp_path / "run")
    port = _free_port()
    for argv, message in [
        (["--coordinator", f"localhost:{port}", "--num-processes", "0"], "--num-processes=0 must lie in 1"),
        (["--coordinator", f"localhost:{port}", "--num-processes", "3"],
         "ppo.num_envs=256 must be divisible by --num-processes=3"),
        (["--coordinator", "x", "--num-processes", "2"], "--coordinator 'x' must be HOST:PORT"),
        (["--coordinator", "host0:99999", "--num-processes", "2"], "--coordinator 'host0:99999' must be HOST:PORT"),
        (["--coordinator", f"localhost:{port}", "--num-processes", "2", "--process-id", "2"],
         "--process-id=2 must lie in 0 … 1"),
        (["--num-processes", "2"], "--num-processes and --process-id need --coordinator"),
        (["--coordinator", f"localhost:{port}", "--num-processes", "2", "--connect-timeout", "nan"],
         "--connect-timeout=nan must be"),
    ]:
        code, _, err = call(train.main, ["--out", out, "--no-progress", *argv], capsys)
        assert code == 2 and message in err and "Traceback" not in err, (argv, err)
    # nobody at the coordinator / a peer that never comes: a message naming the missing process, in time
    for process_id, message in [(1, f"process 1 cannot reach the coordinator localhost:{port} (process 0) within 1 s"),
                                (0, f"process 1 never connected to the coordinator localhost:{port} within 1 s")]:
        t = time.monotonic()
        code, _, err = call(train.main, ["--out", out, "--no-progress", "--coordinator", f"localhost:{port}",
                                         "--num-processes", "2", "--process-id", str(process_id),
                                         "--connect-timeout", "1"], capsys)
        assert code == 2 and message in err and "--connect-timeout" in err and "Traceback" not in err, err
        assert time.monotonic() - t < 30
    assert not os.path.exists(out)
    # and processes that do come meet (the rendezvous before jax.distributed)
    host = threading.Thread(target=distributed.rendezvous, args=(f"localhost:{port}", 3, 0, 20.0))
    host.start()
    peers = [threading.Thread(target=distributed.rendezvous, args=(f"localhost:{port}", 3, i, 20.0)) for i in (1, 2)]
    for p in peers:
        p.start()
    for p in [host, *peers]:
        p.join(30)
        assert not p.is_alive()


@contextlib.contextmanager
def _full_file_system(tmp_path) -> typing.Iterator[str | None]:
    """A 256 KiB tmpfs filled to its last byte, or None where this process may not mount one."""
    import errno

    folder = tmp_path / "full"
    folder.mkdir()
    try:
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(folder)],
                                 capture_output=True).returncode == 0
    except OSError:
        mounted = False
    if not mounted:
        yield None
        return
    try:
        fd = os.open(folder / "filler", os.O_WRONLY | os.O_CREAT)
        try:
            while True:
                os.write(fd, b"\0" * 4096)
        except OSError as exc:
            assert exc.errno == errno.ENOSPC
        finally:
            os.close(fd)
        yield str(folder)
    finally:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)


def _enospc(*args: Any) -> typing.NoReturn:
    import errno

    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_27_4_a_full_disk_is_refused_before_any_work(run_copy, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(launch, "Trainer", lambda *a, **k: pytest.fail("the env was built before refusing"))
    monkeypatch.setattr(evaluation, "evaluate_run", lambda *a, **k: pytest.fail("evaluated before refusing"))
    before_run = snapshot(run_copy)
    with _full_file_system(tmp_path) as full:
        if full is None:  # no tmpfs to be had: the probe's write meets ENOSPC, as on a full disk
            full = str(tmp_path / "full")
            monkeypatch.setattr(fileio, "_write_probe", _enospc)
        before = snapshot(full)
        for main, argv in [(train.main, ["--out", os.path.join(full, "run"), "--no-progress"]),
                           (evaluate.main, ["--run", run_copy, "--episodes", "8", "--out", os.path.join(full, "e.json")]),
                           (export.main, ["--run", run_copy, "--out", os.path.join(full, "export"), "--no-onnx"])]:
            code, _, err = call(main, argv, capsys)
            assert code == 2 and f"cannot write into {'run' if main is train.main else 'output'} folder" in err, err
            assert "No space left on device" in err and "Traceback" not in err
        assert snapshot(full) == before
    assert snapshot(run_copy) == before_run


def _atomic_write_failing(monkeypatch, name: str, nth: int = 1) -> None:
    """fileio.atomic_write of the ``nth`` write of a file called ``name`` meets a full disk half-way."""
    original = fileio.atomic_write
    seen = [0]

    def atomic_write(path: str, write: Callable[[str], None]) -> str:
        if os.path.basename(path) == name:
            seen[0] += 1
            if seen[0] == nth:
                def half_then_full(tmp: str) -> None:
                    write(tmp)
                    with open(tmp, "r+b") as f:
                        f.truncate(os.path.getsize(tmp) // 2)
                    _enospc()

                return original(path, half_then_full)
        return original(path, write)

    monkeypatch.setattr(fileio, "atomic_write", atomic_write)


def test_27_4_b_out_of_space_during_training_exits_2_and_the_run_resumes(toy_run, tmp_path, capsys, monkeypatch):
    out = str(tmp_path / "run")
    os.makedirs(out)
    run_dir.write_config(out, toy_config())
    monkeypatch.setattr(trainer_mod, "default_envs", toy_factory())
    _atomic_write_failing(monkeypatch, run_dir.CHECKPOINT_FILE, nth=2)
    code, _, err = call(train.main, ["--out", out, "--resume", "--no-progress"], capsys)
    ckpt = run_dir.path(out, run_dir.CHECKPOINT_FILE)
    assert code == 2 and f"cannot write {ckpt}: No space left on device" in err and "Traceback" not in err, err
    assert f"{out} continues from its last checkpoint with --resume" in err
    assert fileio.temp_files(out) == []  # no partial file
    assert run_dir.checkpoint_counters(run_dir.load_checkpoint(out))["iteration"] == 4  # the first one, whole
    monkeypatch.undo()
    train.run(toy_config(), out, resume=True, env_factory=toy_factory(), progress=False)
    assert rows(out) == rows(toy_run)
    _checkpoints_equal(out, toy_run)


def test_27_4_c_evaluate_that_cannot_write_its_result_shows_it_and_exits_2(run_copy, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(evaluation, "default_eval_env", lambda cfg: toy_factory()(cfg)[1])
    out = str(tmp_path / "results" / "e.json")
    _atomic_write_failing(monkeypatch, "e.json")
    code, stdout, err = call(evaluate.main, ["--run", run_copy, "--episodes", "8", "--out", out], capsys)
    assert code == 2 and f"cannot write {out}: No space left on device" in err and "not saved" in err, err
    assert "Traceback" not in err and "8 episodes of the evaluation mix" in stdout  # the work is not lost
    assert not os.path.exists(os.path.dirname(out))  # made for the result, removed again: nothing left


def _retrained(run: str, seed: int) -> None:
    """The run as if trained again with ``--seed``: another config, other weights, the same counters."""
    from flax import serialization

    from sagrasp_jax.training import checkpoint

    cfg = config_parse.apply_overrides(run_dir.load_config(run), [f"train.seed={seed}"])
    ckpt = run_dir.load_checkpoint(run)
    trees = {name: dict(flat) for name, flat in ckpt.trees.items()}
    key = next(k for k in trees["train_state"] if "kernel" in k)
    trees["train_state"][key] = trees["train_state"][key] + np.float32(0.01)
    payload = serialization.msgpack_serialize(trees)
    header = dict(ckpt.header, config=config_mod.config_to_dict(cfg), payload_bytes=len(payload),
                  payload_sha256=hashlib.sha256(payload).hexdigest())
    head = json.dumps(header, sort_keys=True).encode()
    fileio.atomic_write_bytes(ckpt.path, checkpoint.MAGIC + checkpoint._LEN.pack(len(head)) + head + payload)
    run_dir.write_config(run, cfg)


def test_27_5_a_retrained_run_is_another_evaluation(run_copy, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(evaluation, "default_eval_env", lambda cfg: toy_factory()(cfg)[1])
    out = str(tmp_path / "results" / "e.json")
    argv = ["--run", run_copy, "--episodes", "16", "--out", out]
    assert call(evaluate.main, argv, capsys)[0] == 0
    first = json.load(open(out))
    assert first["config_sha256"] and first["checkpoint_sha256"]
    _retrained(run_copy, seed=1)
    before = snapshot(str(tmp_path / "results"))
    code, _, err = call(evaluate.main, argv, capsys)
    assert code == 2 and f"{out} holds a different result (" in err and "--force" in err, err
    assert f"config_sha256 {first['config_sha256']!r} -> " in err and f"checkpoint_sha256 {first['checkpoint_sha256']!r}" in err
    assert snapshot(str(tmp_path / "results")) == before
    assert call(evaluate.main, [*argv, "--force"], capsys)[0] == 0
    assert json.load(open(out))["checkpoint_sha256"] != first["checkpoint_sha256"]


def test_27_6_resume_reads_nan_and_infinity_in_the_metrics_log(toy_run, run_copy, capsys, monkeypatch):
    out = run_copy  # a resume keeps the rows before its checkpoint: here all of them, rewritten
    path = run_dir.path(out, run_dir.METRICS_FILE)
    lines = open(path).read().splitlines()
    expected = rows(toy_run)
    for i, (key, value) in enumerate([("loss", math.nan), ("grad_norm", math.inf), ("value_loss", -math.inf)]):
        row = json.loads(lines[i + 1])
        row[key] = value
        lines[i + 1] = json.dumps(row)  # NaN, Infinity, -Infinity: what Python's json writes by default
        expected[i + 1][key] = None
    assert "NaN" in lines[1] and "Infinity" in lines[2]
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
    monkeypatch.setattr(trainer_mod, "default_envs", toy_factory())
    code, _, err = call(train.main, ["--out", out, "--resume", "--no-progress"], capsys)
    assert code == 0 and "Traceback" not in err, err
    assert rows(out) == expected  # kept, as null: what this trainer's logger writes for a non-finite value


def _policy_with_member(src: str, path: str, key: str, shape: tuple[int, ...], data_bytes: int) -> str:
    """``src``'s arrays with member ``key`` replaced by a float64 .npy header of ``shape`` and
    ``data_bytes`` zero bytes after it (deflated: a zip bomb when large)."""
    import io
    import zipfile

    with np.load(src) as data:
        arrays = {k: data[k] for k in data.files}
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for k, v in arrays.items():
            if k != key:
                buf = io.BytesIO()
                np.save(buf, v)
                zf.writestr(f"{k}.npy", buf.getvalue())
                continue
            with zf.open(f"{k}.npy", "w", force_zip64=True) as f:
                head = io.BytesIO()
                np.lib.format.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": shape})
                f.write(head.getvalue())
                chunk = b"\0" * (1 << 20)
                for start in range(0, data_bytes, len(chunk)):
                    f.write(chunk[: data_bytes - start])
    return path


@pytest.mark.parametrize("shape,data_bytes,message", [
    ((37 * 2**30 // 8,), 17 * 8, "obs_mean.npy's header claims float64[4966055936] (39728447488 bytes) but the member "
                                 "holds 136 bytes; not read"),
    ((2**40 // 8,), 17 * 8, "(1099511627776 bytes) but the member holds 136 bytes; not read"),
    ((300 * 2**20 // 8,), 300 * 2**20, "bytes unpacked, over the 268435456 bytes a policy file may hold (zip bomb?)"),
], ids=["37GiB-header", "1TiB-header", "zip-bomb"])
def test_27_7_an_oversized_policy_file_is_refused_before_it_is_read(policy_file, tmp_path, shape, data_bytes, message,
                                                                     capsys, no_twin):
    path = _policy_with_member(policy_file, str(tmp_path / "policy.npz"), "obs_mean", shape, data_bytes)
    with pytest.raises(runtime.PolicyFormatError, match="not read"):
        runtime.load_policy(path)
    code, out, err = call(deploy_cli.main, ["--policy", path, "--target-cam", *TARGET_CAM, "--json"], capsys)
    assert code == 2 and message in err and "Traceback" not in err, err
    code, _, err = call(render.main, ["--policy", path, "--out", str(tmp_path / "v.mp4")], capsys)
    assert code == 2 and message in err and not os.path.exists(tmp_path / "v.mp4")


def test_27_8_a_checkpoint_that_is_a_folder_is_refused(run_copy, tmp_path, capsys):
    ckpt = run_dir.path(run_copy, run_dir.CHECKPOINT_FILE)
    os.unlink(ckpt)
    os.makedirs(ckpt)
    before = snapshot(run_copy)
    for command in ("evaluate", "export", "resume"):
        code, err = _run_command(command, run_copy, tmp_path, capsys)
        assert code == 2 and f"{ckpt} is a folder, not a checkpoint file" in err and "Traceback" not in err, (command, err)
    assert snapshot(run_copy) == before


def test_27_9_sigterm_stops_training_with_a_message_and_the_run_resumes(toy_run, tmp_path):
    import signal

    out = str(tmp_path / "run")
    os.makedirs(out)
    run_dir.write_config(out, toy_config())
    driver = Driver(out, "--cli", "--slow", "0.1", env={"JAX_NUM_CPU_DEVICES": "1"})
    assert driver.wait_for("COMPILED")
    time.sleep(0.3)
    driver.proc.send_signal(signal.SIGTERM)
    rest, _ = driver.proc.communicate(timeout=120)
    assert driver.proc.returncode == 143, rest[-3000:]
    assert f"terminated (SIGTERM): {out} continues from its last checkpoint with --resume" in rest
    assert "Traceback" not in rest and fileio.temp_files(out) == []
    train.run(toy_config(), out, resume=True, env_factory=toy_factory(), progress=False)
    assert rows(out) == rows(toy_run)


def test_27_10_evaluations_of_different_runs_write_into_one_results_folder_at_once(run_copy, toy_run, tmp_path, capsys,
                                                                                    monkeypatch):
    monkeypatch.setattr(evaluation, "default_eval_env", lambda cfg: toy_factory()(cfg)[1])
    results = str(tmp_path / "results")
    a, b = os.path.join(results, "a.json"), os.path.join(results, "b.json")
    inner: dict[str, tuple[int, str, str]] = {}
    evaluate_run = evaluation.evaluate_run

    def evaluating(run: str, *args: Any, **kwargs: Any) -> dict[str, Any]:  # meanwhile, two more evaluations
        if not inner:
            inner["same file"] = call(evaluate.main, ["--run", toy_run, "--episodes", "8", "--out", a], capsys)
            inner["other file"] = call(evaluate.main, ["--run", toy_run, "--episodes", "8", "--out", b], capsys)
        return evaluate_run(run, *args, **kwargs)

    monkeypatch.setattr(evaluation, "evaluate_run", evaluating)
    code, _, err = call(evaluate.main, ["--run", run_copy, "--episodes", "8", "--out", a], capsys)
    assert code == 0, err
    code, _, err = inner["same file"]
    assert code == 2 and f"{a} is being written by another process (pid {os.getpid()}" in err, err
    assert inner["other file"][0] == 0, inner["other file"][2]
    assert json.load(open(a))["run"] == os.path.abspath(run_copy) and json.load(open(b))["run"] == os.path.abspath(toy_run)
    assert sorted(os.listdir(results)) == ["a.json", "b.json"]  # no lock file left
    with run_dir.FolderLock(results):  # a training or an export writing there still keeps evaluations out
        code, _, err = call(evaluate.main, ["--run", toy_run, "--episodes", "8", "--out", b], capsys)
        assert code == 2 and "is in use by another process" in err


def test_27_11_an_empty_hidden_layer_list_is_refused(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(launch, "Trainer", lambda *a, **k: pytest.fail("a linear network was about to be trained"))
    out = str(tmp_path / "run")
    for key in ("ppo.network.policy_hidden", "ppo.network.value_hidden"):
        code, _, err = call(train.main, ["--out", out, "--no-progress", "--set", f"{key}="], capsys)
        assert code == 2 and f"{key} is empty: give at least one hidden layer width" in err and "Traceback" not in err
    assert not os.path.exists(out)


# ====================================================================== issue 40
# The input surfaces added in issue 27's round and files that are not files: 1-4 --config files (digits,
# nesting, YAML types, devices and alias bombs), 5 --seeds, 6 output paths that are devices or FIFOs,
# 7 sysid on a log it cannot fit, 8 an evaluation output that is a FIFO, 9 run-folder inputs that are FIFOs;
# and a symlinked tb/, a coordinator that is never reached, a policy file without its clearance key.

LEGACY_RUN = os.path.join(REPO, "tests", "data", "legacy_v0_1")


@contextlib.contextmanager
def _fifo(path: str) -> typing.Iterator[str]:
    """A FIFO at ``path``.  Should the code under test open it after all, a watchdog opens the other end
    after 10 s so that the open returns: the test then fails on its time or message instead of hanging."""
    import threading

    os.mkfifo(path)
    stop = threading.Event()

    def release() -> None:
        if stop.wait(10.0):
            return
        while not stop.is_set():
            for flags in (os.O_WRONLY | os.O_NONBLOCK, os.O_RDONLY | os.O_NONBLOCK):
                with contextlib.suppress(OSError):
                    os.close(os.open(path, flags))
            stop.wait(0.1)

    watchdog = threading.Thread(target=release, daemon=True)
    watchdog.start()
    try:
        yield path
    finally:
        stop.set()
        watchdog.join()


def _billion_laughs() -> str:
    text = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n'
    for prev, cur in zip("abcdefgh", "bcdefghi"):
        text += f"{cur}: &{cur} [{','.join([f'*{prev}'] * 9)}]\n"
    return text


# (file name, content, what the message says); the content of a device or FIFO case is the special file it is
CONFIG_FILE_CASES = [
    ("digits.json", '{"ppo": {"num_envs": 1' + "0" * 5000 + "}}", "not valid JSON (an integer of 5001 digits (at most 64))"),
    ("deep.json", "[" * 100_000 + "]" * 100_000, "not valid JSON (nested deeper than 32 levels)"),
    ("deep-objects.json", '{"a":' * 40_000 + "1" + "}" * 40_000, "nested deeper than 32 levels"),
    ("set.yaml", "ppo: !!set {a, b}\n", "tag tag:yaml.org,2002:set is not allowed in a config file"),
    ("date.yaml", "env: {task: {max_steps: 2001-12-14}}\n", "bad value '2001-12-14' for env.task.max_steps (int)"),
    ("laughs.yaml", _billion_laughs(), "an alias (*a) is not allowed in a config file"),
    ("deep.yaml", "a: " + "[" * 100_000 + "]" * 100_000 + "\n", "nested deeper than 32 levels"),
    ("big.json", '{"train.seed": 1, "x": "' + "a" * (config_parse.MAX_CONFIG_BYTES + 1) + '"}',
     f"bytes, over the {config_parse.MAX_CONFIG_BYTES} bytes a config file may hold; not read"),
    ("null.json", "/dev/null", "is a character device, not a regular file"),
    ("fifo.json", "FIFO", "is a FIFO (named pipe), not a regular file"),
]


@pytest.mark.parametrize("name,content,message", CONFIG_FILE_CASES, ids=[c[0] for c in CONFIG_FILE_CASES])
def test_40_1_2_3_4_config_files_beyond_their_bounds_are_refused(name, content, message, run_copy, tmp_path, capsys,
                                                                    monkeypatch):
    if name.endswith(".yaml"):
        pytest.importorskip("yaml")
    monkeypatch.setattr(launch, "Trainer", lambda *a, **k: pytest.fail("the env was built before refusing"))
    path = str(tmp_path / name)
    with contextlib.ExitStack() as stack:
        if content == "FIFO":
            stack.enter_context(_fifo(path))
        elif content.startswith("/dev/"):
            os.symlink(content, path)
        else:
            with open(path, "w") as f:
                f.write(content)
        before = snapshot(run_copy)
        out, result = str(tmp_path / "fresh"), str(tmp_path / "e.json")
        for main, argv in [(train.main, ["--out", out, "--no-progress", "--config", path]),
                           (evaluate.main, ["--run", run_copy, "--episodes", "8", "--out", result, "--config", path])]:
            t = time.monotonic()
            code, _, err = call(main, argv, capsys)
            assert code == 2 and message in err and "Traceback" not in err, err
            assert time.monotonic() - t < 5.0, name
        assert not os.path.exists(out) and not os.path.exists(result) and snapshot(run_copy) == before


def _bounded_python(code: str, memory: int = 1 << 30) -> subprocess.CompletedProcess:
    """``code`` in a jax-free Python process capped at ``memory`` bytes of address space and 60 s: a
    regression that reads without bound fails here instead of filling this machine's memory."""
    cap = f"import resource\nresource.setrlimit(resource.RLIMIT_AS, ({memory}, {memory}))\n"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([REPO, *filter(None, [os.environ.get("PYTHONPATH")])]))
    return subprocess.run([sys.executable, "-c", cap + code], capture_output=True, text=True, timeout=60, cwd=REPO,
                          env=env)


def test_40_4_dev_zero_and_a_billion_laughs_are_refused_in_bounded_memory(tmp_path):
    pytest.importorskip("yaml")
    zero, laughs = str(tmp_path / "z.json"), str(tmp_path / "laughs.yaml")
    os.symlink("/dev/zero", zero)
    with open(laughs, "w") as f:
        f.write(_billion_laughs())
    probe = ("import time\nfrom sagrasp_jax.task import config, config_parse\n"
             "for path in {paths!r}:\n"
             "    t = time.monotonic()\n"
             "    try:\n        config_parse.file_overrides(path)\n    except config.ConfigError as exc:\n"
             "        print(f'{{time.monotonic() - t:.3f}} {{exc}}'.splitlines()[0])\n")
    res = _bounded_python(probe.format(paths=[zero, laughs]))
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr[-2000:]
    (t_zero, zero_msg), (t_laughs, laughs_msg) = [line.split(" ", 1) for line in res.stdout.splitlines()]
    assert zero_msg == f"--config {zero} is a character device, not a regular file"
    assert "an alias (*a) is not allowed in a config file" in laughs_msg
    assert float(t_zero) < 1.0 and float(t_laughs) < 1.0


@pytest.mark.parametrize("seeds,message", [
    ("0-100000", f"--seeds '0-100000': more than {train.MAX_SEEDS} seeds"),
    ("0-999", f"--seeds '0-999': more than {train.MAX_SEEDS} seeds"),
    (",".join(["7"] * 200_000), f"more than {train.MAX_SEEDS} seeds"),
    ("0-4294967296", "--seeds=4294967296 is outside the allowed range [0, 4294967295]"),
    ("1-" + "9" * 5000, "is not a seed or a range A-B of seeds"),
    ("0-4,3", "--seeds: seed 3 given twice"),
])
def test_40_5_seed_lists_are_bounded_and_refused_before_any_folder(seeds, message, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(launch, "Trainer", lambda *a, **k: pytest.fail("the env was built before refusing"))
    out = str(tmp_path / "group")
    t = time.monotonic()
    code, _, err = call(train.main, ["--out", out, "--no-progress", "--seeds", seeds], capsys)
    assert code == 2 and message in err and "Traceback" not in err, err
    assert time.monotonic() - t < 2.0 and not os.path.exists(out)
    assert train.parse_seeds(f"0-{train.MAX_SEEDS - 1}") == list(range(train.MAX_SEEDS))  # the bound itself trains
    with pytest.raises(config_mod.ConfigError, match="seed 5 given twice"):  # the duplicate check is linear
        train.check_seeds(list(range(train.MAX_SEEDS - 1)) + [5])


def _servo_log(latency: float = 1.0, steps: int = 300, offset: float = 0.0, seed: int = 0) -> Any:
    """A log of the lagged servo model itself (random-walk commands), any latency, no noise."""
    from sagrasp_jax.task import control
    from sagrasp_jax.task.robot import load_robot
    from sagrasp_jax.deploy import sysid
    from sagrasp_jax.task.config import ControlConfig

    cfg = ControlConfig()
    rng = np.random.default_rng(seed)
    command = np.cumsum(rng.uniform(-0.04, 0.04, (steps, 6)), axis=0)
    queue = np.zeros((control.latency_queue_size(latency) or 1, 6))
    x = x_prev = np.zeros(6)
    readings = np.empty((steps, 6))
    gain = np.asarray(cfg.lag_gain)
    for t in range(steps):
        readings[t] = x + offset
        queue = np.concatenate([command[t][None], queue[:-1]])
        c, p, f = control.delayed_commands(np, queue, latency) if latency else (command[t], command[t], 0.0)
        w = control.held_command_weight(np, f, gain)
        x, x_prev = control.servo_model_step(np, load_robot(), cfg, x, x_prev, (1 - w) * c + w * p, gain), x
    return sysid.RobotLog(np.arange(steps) * cfg.control_dt, command, readings)


def _write_log(path: str, log: Any) -> str:
    from sagrasp_jax.deploy import sysid

    with open(path, "w") as f:
        f.write(",".join(sysid.COLUMNS) + "\n")
        for t, c, y in zip(log.time, log.command, log.measured):
            f.write(",".join(repr(float(v)) for v in [t, *c, *y]) + "\n")
    return path


def test_40_6_8_outputs_that_are_devices_or_fifos_are_refused(run_copy, tmp_path, capsys, monkeypatch):
    from sagrasp_jax.deploy import sysid

    monkeypatch.setattr(evaluation, "evaluate_run", lambda *a, **k: pytest.fail("evaluated before refusing"))
    log = _write_log(str(tmp_path / "log.csv"), _servo_log())
    results = tmp_path / "results"
    results.mkdir()
    with _fifo(str(results / "f.json")) as fifo, _fifo(str(results / "v.mp4")) as video:
        before, before_run = snapshot(str(tmp_path)), snapshot(run_copy)
        for main, argv, message in [
            (sysid.main, ["--log", log, "--out", "/dev/full"], "cannot write /dev/full: it is a character device"),
            (sysid.main, ["--log", log, "--out", fifo], f"cannot write {fifo}: it is a FIFO (named pipe)"),
            (evaluate.main, ["--run", run_copy, "--episodes", "8", "--out", fifo], f"cannot write {fifo}: it is a FIFO"),
            (evaluate.main, ["--run", run_copy, "--episodes", "8", "--out", "/dev/full"], "it is a character device"),
            (render.main, ["--policy", run_dir.path(run_copy, run_dir.POLICY_FILE), "--out", video], "it is a FIFO"),
        ]:
            t = time.monotonic()
            code, out, err = call(main, argv, capsys)
            assert code == 2 and message in err and "Traceback" not in err and "written" not in out, (argv, err)
            assert time.monotonic() - t < 5.0
        assert sorted(os.listdir(results)) == ["f.json", "v.mp4"]  # no .f.json.evallock.tmp left behind
        assert snapshot(str(tmp_path)) == before and snapshot(run_copy) == before_run
        assert fileio.file_kind(os.stat("/dev/full").st_mode) == "a character device"  # not replaced by a file
    export_dir = tmp_path / "export"
    export_dir.mkdir()
    with _fifo(str(export_dir / "policy.npz")) as fifo:
        code, _, err = call(export.main, ["--run", run_copy, "--out", str(export_dir), "--no-onnx"], capsys)
        assert code == 2 and f"cannot write {fifo}: it is a FIFO" in err and os.listdir(export_dir) == ["policy.npz"]


def _sysid_refuses(log: Any, message: str, tmp_path, capsys) -> str:
    from sagrasp_jax.deploy import sysid

    out = str(tmp_path / "sysid.json")
    code, stdout, err = call(sysid.main, ["--log", _write_log(str(tmp_path / "log.csv"), log), "--out", out], capsys)
    assert code == 2 and message in err and "Traceback" not in err, err
    assert "--set" not in stdout and not os.path.exists(out)
    return err


def test_40_7_sysid_refuses_a_log_it_cannot_fit_and_says_what_it_could_not_identify(tmp_path, capsys):
    from sagrasp_jax.deploy import sysid

    good = _servo_log(latency=1.0)
    fit = sysid.identify(good)
    items = sysid.overrides(fit)  # a log the model fits: every item passes training's own check
    assert config_parse.apply_overrides(get_config("cpu-quick"), items).env.randomize.latency == pytest.approx(2.0, abs=0.1)
    rng = np.random.default_rng(1)
    noise = sysid.RobotLog(good.time, rng.uniform(-1, 1, good.command.shape), rng.uniform(-1, 1, good.measured.shape))
    err = _sysid_refuses(noise, "log: cannot identify the arm from this log: the servo model explains only", tmp_path,
                         capsys)
    assert "of q6's step-to-step motion (≥ 90% in a servo log)" in err
    _sysid_refuses(_servo_log(latency=5.0), "the command latency is at least 4 control steps, beyond the 3 steps "
                   "training can randomise (env.randomize.latency): not identified", tmp_path, capsys)
    err = _sysid_refuses(_servo_log(latency=3.5), "control steps, beyond the 3 steps training can randomise", tmp_path,
                         capsys)
    assert "at least" not in err
    still = sysid.RobotLog(good.time, good.command, np.full_like(good.measured, 0.1))  # commanded, never moves
    _sysid_refuses(still, "q1, q2, q3, q4, q5, q6 never move (readings or commands span under 0.001 rad)", tmp_path,
                   capsys)
    off = _servo_log(offset=0.15)  # a good fit, but an offset training cannot randomise over
    _sysid_refuses(off, "training would refuse, so it is not identified: --set env.randomize.joint_offset=0.225 "
                   "(invalid value for env.randomize.joint_offset: 0.225 (must be in [0, 0.2]))", tmp_path, capsys)


@pytest.mark.parametrize("name,commands,message", [
    (run_dir.CHECKPOINT_FILE, ("evaluate", "export", "resume"), "is a FIFO (named pipe), not a checkpoint file"),
    (run_dir.CONFIG_FILE, ("evaluate", "export", "resume"), "is a FIFO (named pipe), not a regular file"),
    (run_dir.METRICS_FILE, ("resume",), "is a FIFO (named pipe), not a metrics log"),
    (run_dir.POLICY_FILE, ("deploy", "render"), "is a FIFO (named pipe), not a policy file"),
])
def test_40_9_run_files_that_are_fifos_are_refused_before_they_are_opened(name, commands, message, run_copy, tmp_path,
                                                                          capsys, no_twin):
    path = run_dir.path(run_copy, name)
    os.unlink(path)
    with _fifo(path):
        before = snapshot(run_copy)
        for command in commands:
            t = time.monotonic()
            code, err = _run_command(command, run_copy, tmp_path, capsys)
            assert code == 2 and f"{path} {message}" in err and "Traceback" not in err, (command, err)
            assert time.monotonic() - t < 5.0, command
        assert snapshot(run_copy) == before


def test_40_a_symlink_in_the_run_folder_is_never_written_through(run_copy, tmp_path, capsys):
    outside = str(tmp_path / "outside")
    shutil.move(run_dir.path(run_copy, run_dir.TB_DIR), outside)
    os.symlink(outside, run_dir.path(run_copy, run_dir.TB_DIR))
    metrics_outside = str(tmp_path / "metrics.jsonl")
    before_run, before_outside = snapshot(run_copy), snapshot(outside)
    for name in (run_dir.TB_DIR, run_dir.METRICS_FILE):
        if name == run_dir.METRICS_FILE:  # the same for a file that training appends to
            os.unlink(run_dir.path(run_copy, run_dir.TB_DIR))
            shutil.move(outside, run_dir.path(run_copy, run_dir.TB_DIR))
            shutil.move(run_dir.path(run_copy, name), metrics_outside)
            os.symlink(metrics_outside, run_dir.path(run_copy, name))
            before_run, before_outside = snapshot(run_copy), {"m": snapshot(str(tmp_path))["metrics.jsonl"]}
        code, _, err = call(train.main, ["--out", run_copy, "--resume", "--no-progress"], capsys)
        entry = run_dir.path(run_copy, name)
        assert code == 2 and f"{entry} is a symbolic link (to " in err and "writes only inside its run folder" in err, err
        assert "Traceback" not in err and snapshot(run_copy) == before_run
        assert (snapshot(outside) if name == run_dir.TB_DIR else {"m": snapshot(str(tmp_path))["metrics.jsonl"]}) \
            == before_outside


def test_40_a_coordinator_that_is_never_reached_is_named_as_such(tmp_path, capsys, monkeypatch):
    """Something at the coordinator's address accepts the connection (a proxy or firewall in front of an
    unroutable address) but is not process 0: 'cannot reach', not 'did not see every process'."""
    import socket
    import threading

    monkeypatch.setattr(launch, "Trainer", lambda *a, **k: pytest.fail("the env was built before refusing"))
    out = str(tmp_path / "run")
    for answer, said in [(None, ""), (b"HTTP/1.1 400 Bad Request\r\n\r\n", " (it answered b'HTTP/1.1 400 Bad Request')")]:
        server = socket.create_server(("localhost", 0))
        port = server.getsockname()[1]
        stop = threading.Event()

        def serve() -> None:
            conns = []
            server.settimeout(0.1)
            while not stop.is_set():
                with contextlib.suppress(OSError):
                    conn, _ = server.accept()
                    conns.append(conn)
                    if answer:
                        conn.sendall(answer)
                        conn.close()
            for conn in conns:
                conn.close()

        thread = threading.Thread(target=serve)
        thread.start()
        try:
            code, _, err = call(train.main, ["--out", out, "--no-progress", "--coordinator", f"localhost:{port}",
                                             "--num-processes", "2", "--process-id", "1", "--connect-timeout", "1"],
                                capsys)
        finally:
            stop.set()
            thread.join()
            server.close()
        address = f"localhost:{port}"
        assert code == 2 and "Traceback" not in err and "did not see every process" not in err, err
        assert (f"process 1 cannot reach the coordinator {address} (process 0) within 1 s (--connect-timeout): "
                f"something at {address} accepted the connection but never answered as process 0{said}: the "
                "coordinator was not reached") in err, err
    assert not os.path.exists(out)


def test_40_a_policy_file_without_its_clearance_key_is_refused(policy_file, tmp_path, capsys, no_twin):
    path = shutil.copy(policy_file, str(tmp_path / "policy.npz"))
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    cfg = json.loads(str(arrays["config_json"]))
    del cfg["env"]["sampling"]["target_clearance"]
    arrays["config_json"] = np.asarray(json.dumps(cfg, sort_keys=True))
    arrays["config_hash"] = np.asarray(config_history.env_dict_hash(cfg["env"]))  # a consistent edit: the hash matches
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    message = f"{path}: config_json does not record env.sampling.target_clearance"
    with pytest.raises(runtime.PolicyFormatError, match="does not record env.sampling.target_clearance"):
        runtime.load_policy(path)
    code, out, err = call(deploy_cli.main, ["--policy", path, "--target-cam", *TARGET_CAM, "--json"], capsys)
    assert code == 2 and message in err and json.loads(out)["outcome"] == "input_refused" and "Traceback" not in err
    legacy = runtime.load_policy(os.path.join(LEGACY_RUN, "policy_cpu_quick_3M.npz"))  # version 0.1 records it
    assert legacy.env_config().sampling.target_clearance == get_config("paper").env.sampling.target_clearance


# ====================================================================== issue 54
# The robot side's reliability: 1 calibration files beyond their bounds (deep JSON, a 401-digit integer, a
# .npy header claiming 74.5 GiB, a 200 MB text file, a FIFO, a folder) and the other inputs' readers; 2 a policy
# whose inputs are not its own config's; 3 outputs that name a file that is no result of their kind; 4 Ctrl-C;
# 5 perception's refusals, calibrate --out "".

def _npy_header_only(path: str, shape: tuple[int, ...]) -> str:
    """A .npy file whose header claims ``shape`` float64s and which holds none of them."""
    import io

    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": shape})
    with open(path, "wb") as f:
        f.write(head.getvalue())
    return path


CALIBRATION_CASES = [
    ("deep.json", "[" * 100_000 + "]" * 100_000, "cannot read a 4×4 matrix (ValueError: nested deeper than 32 levels)"),
    ("digits.json", "[[1" + "0" * 400 + ",0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]",
     "cannot read a 4×4 matrix (ValueError: an integer of 401 digits (at most 64))"),
    ("huge.npy", "NPY", "its .npy header claims float64[100000, 100000] (80000000000 bytes) but the file holds 0 bytes"),
    ("big.txt", "SPARSE", "209715200 bytes, over the 1048576 bytes a calibration file may hold; not read"),
    ("fifo.json", "FIFO", "fifo.json is a FIFO (named pipe), not a calibration file"),
    ("folder.json", "FOLDER", "folder.json is a folder, not a calibration file"),
]


@pytest.mark.parametrize("name,content,message", CALIBRATION_CASES, ids=[c[0] for c in CALIBRATION_CASES])
def test_54_1_calibration_files_beyond_their_bounds_are_refused(name, content, message, policy_file, tmp_path, capsys,
                                                                 no_twin):
    path = str(tmp_path / name)
    with contextlib.ExitStack() as stack:
        if content == "FIFO":
            stack.enter_context(_fifo(path))
        elif content == "FOLDER":
            os.mkdir(path)
        elif content == "NPY":
            _npy_header_only(path, (100_000, 100_000))
        elif content == "SPARSE":
            with open(path, "wb") as f:
                f.truncate(200 * 2**20)  # 200 MB that take no disk
        else:
            with open(path, "w") as f:
                f.write(content)
        t = time.monotonic()
        code, out, err = call(deploy_cli.main, ["--policy", policy_file, "--target-cam", *TARGET_CAM,
                                                "--calibration", path, "--json"], capsys)
        assert code == 2 and message in err and "not found" not in err and "Traceback" not in err, err
        assert json.loads(out)["outcome"] == "input_refused" and time.monotonic() - t < 5.0


def test_54_1_the_other_inputs_of_the_robot_side_are_bounded_regular_files(tmp_path, capsys, no_twin):
    """A policy file over its size cap is refused before it is read; a metrics log (plot) that is a FIFO is named,
    never opened; the pairs file (calibrate) and the robot log (sysid) already were (issue 40)."""
    from sagrasp_jax.base import run_files

    big = str(tmp_path / "big.npz")
    with open(big, "wb") as f:
        f.truncate(runtime.MAX_POLICY_FILE_BYTES + 1)
    with pytest.raises(runtime.PolicyFormatError, match="bytes a policy file may hold; not read"):
        runtime.load_policy(big)
    run = tmp_path / "run"
    run.mkdir()
    (run / run_files.CONFIG_FILE).write_text("{}")
    with _fifo(str(run / run_files.METRICS_FILE)):
        t = time.monotonic()
        with pytest.raises(run_files.RunFolderError, match="is a FIFO \\(named pipe\\), not a regular file"):
            run_files.read_metrics(str(run))
        assert time.monotonic() - t < 5.0


def _cut_policy(path: str, names: list[str]) -> str:
    """The packaged policy cut to the first ``len(names)`` inputs, renamed ``names``; its config unchanged."""
    n = len(names)
    with np.load(runtime.pretrained_path("pretrained")) as data:
        arrays = {k: data[k] for k in data.files}
    arrays.update(layer_0_w=arrays["layer_0_w"][:n], obs_mean=arrays["obs_mean"][:n], obs_std=arrays["obs_std"][:n],
                  obs_size=np.asarray(n, np.int64), obs_layout=np.asarray(names))
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    return path


def test_54_2_a_policy_whose_inputs_are_not_its_configs_is_refused_before_anything_connects(tmp_path, capsys,
                                                                                            no_twin):
    pytest.importorskip("pybullet")
    layout = list(runtime.load_policy("pretrained").obs_layout)
    cut = _cut_policy(str(tmp_path / "cut.npz"), [f"in_{i}" for i in range(17)])
    renamed = _cut_policy(str(tmp_path / "renamed.npz"), layout[:3] + ["q_four"] + layout[4:])
    message = {cut: "its 17 inputs (in_0, in_1, in_2, in_3, ...) do not match its own config, whose 'relative_lag' "
                    "observation layout has 35",
               renamed: "its inputs do not match its own config's 'relative_lag' observation layout: input 3 is "
                        "'q_four' where the layout has 'q4'"}
    for path, said in message.items():
        with pytest.raises(runtime.PolicyFormatError, match=re.escape(f"{path}: {said}")):
            runtime.load_policy(path)
        code, out, err = call(deploy_cli.main, ["--policy", path, "--target-cam", *TARGET_CAM, "--json"], capsys)
        assert code == 2 and said in err and json.loads(out)["outcome"] == "input_refused", err
        code, out, err = call(evaluate.main, ["--backend", "twin", "--policy", path, "--episodes", "1"], capsys)
        assert code == 2 and said in err and "cube held" not in out, err
    # inputs named as export names another env's (the tests' toy env): the file loads, nothing runs it on the task
    other = _cut_policy(str(tmp_path / "other.npz"), [f"obs_{i}" for i in range(17)])
    assert runtime.load_policy(other).obs_size == 17
    said = "not a grasp policy, refused before anything connects"
    code, _, err = call(deploy_cli.main, ["--policy", other, "--target-cam", *TARGET_CAM], capsys)
    assert code == 2 and said in err, err
    code, _, err = call(evaluate.main, ["--backend", "twin", "--policy", other, "--episodes", "1"], capsys)
    assert code == 2 and said in err, err
    with pytest.raises(runtime.PolicyFormatError, match=said):
        run_episode(Twinless(), runtime.load_policy(other), TARGET)


def test_54_3_outputs_that_name_a_file_of_another_kind_are_refused_even_with_force(run_copy, tmp_path, capsys,
                                                                                   monkeypatch):
    """evaluate --backend twin, deploy.rehearse, deploy --camera twin and the MJX evaluate: an --out that names
    the run's config, its policy or another kind of result is refused before any work, with --force too; the
    run folder is unchanged.  (A twin result of another evaluation needs --force: tests/commands/test_evaluate.py.)"""
    pytest.importorskip("pybullet")
    from sagrasp_jax.deploy import rehearse

    monkeypatch.setattr(rehearse, "rehearse", lambda *a, **k: pytest.fail("ran before refusing"))
    monkeypatch.setattr(evaluation, "evaluate_run", lambda *a, **k: pytest.fail("evaluated before refusing"))
    run = str(tmp_path / "twin-run")
    os.makedirs(run)
    shutil.copy(runtime.pretrained_path("pretrained"), os.path.join(run, "policy.npz"))
    run_dir.write_json(os.path.join(run, "config.json"), {"train": {"seed": 0}})
    mjx_result = os.path.join(run, "mjx.json")
    run_dir.write_json(mjx_result, {"episodes": 8, "overall": {"success_rate": 0.5}})
    config, policy = os.path.join(run, "config.json"), os.path.join(run, "policy.npz")
    expected = {config: f"{config} exists and is not a twin evaluation result (it lacks the 'backend', 'episodes', "
                        "'summary' entries one has); --force replaces only a result",
                policy: f"{policy} exists and holds binary data, not a twin evaluation result; --force replaces only",
                mjx_result: f"{mjx_result} exists and is not a twin evaluation result (it lacks the 'backend', "
                            "'summary' entries one has)"}
    before = snapshot(run)
    for out, message in expected.items():
        for force in ([], ["--force"]):
            for main, argv in [(evaluate.main, ["--backend", "twin", "--run", run, "--episodes", "1"]),
                               (rehearse.main, ["--policy", policy, "--episodes", "1"]),
                               (deploy_cli.main, ["--camera", "twin", "--policy", policy, "--scenes", "1"])]:
                code, _, err = call(main, [*argv, "--out", out, *force], capsys)
                assert code == 2 and message in err and "Traceback" not in err, (main, err)
    assert snapshot(run) == before
    before = snapshot(run_copy)
    for out in (run_dir.path(run_copy, run_dir.CONFIG_FILE), run_dir.path(run_copy, run_dir.POLICY_FILE)):
        code, _, err = call(evaluate.main, ["--run", run_copy, "--episodes", "8", "--out", out, "--force"], capsys)
        assert code == 2 and f"{out} exists and " in err and "--force replaces only a result" in err, err
    assert snapshot(run_copy) == before


# ---------------------------------------------------------------------- 54.4: Ctrl-C

def _interrupt(code: str, argv: list[str], marker: str, delay: float, env: dict[str, str] | None = None,
               timeout: float = 240.0) -> tuple[int, str, str, float]:
    """Run ``python -c code argv...`` (this checkout on its path), send it SIGINT ``delay`` s after it printed
    a line holding ``marker``: (exit status, stdout, stderr, seconds from the signal to its exit)."""
    import signal

    env = dict(os.environ, PYTHONPATH=os.pathsep.join([REPO, *filter(None, [os.environ.get("PYTHONPATH")])]),
               **(env or {}))
    proc = subprocess.Popen([sys.executable, "-c", code, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=REPO, env=env)
    seen = []
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            seen.append(line)
            if marker in line:
                break
        assert seen and marker in seen[-1], f"no {marker} line: {''.join(seen)[-2000:]}{proc.stderr.read()[-3000:]}"
        time.sleep(delay)
        proc.send_signal(signal.SIGINT)
        t = time.monotonic()
        out, err = proc.communicate(timeout=timeout)
        return proc.returncode, "".join(seen) + out, err, time.monotonic() - t
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def _one_interrupted_line(err: str) -> str:
    """The one line a command stopped by Ctrl-C prints (PyBullet's own chatter may end without a newline before
    it), with no traceback around it."""
    lines = [line[line.index("interrupted (Ctrl-C): "):] for line in err.splitlines() if "interrupted (Ctrl-C)" in line]
    assert len(lines) == 1 and "Traceback" not in err and "KeyboardInterrupt" not in err, err[-3000:]
    return lines[0]


SLOW_TWIN = """
import sys, time
from sagrasp_jax.deploy import twin, __main__ as deploy
real = twin.PyBulletTwin.command_joint_targets
def slow(self, q):
    print("MOVING", flush=True)
    time.sleep(0.2)
    return real(self, q)
twin.PyBulletTwin.command_joint_targets = slow
sys.exit(deploy.main(sys.argv[1:]))
"""


def test_54_4_ctrl_c_stops_a_twin_deploy_with_one_line_and_exit_130(policy_file, tmp_path):
    pytest.importorskip("pybullet")
    code, out, err, took = _interrupt(SLOW_TWIN, ["--policy", policy_file, "--target-cam", *TARGET_CAM,
                                                  "--max-steps", "1000", "--json"], "MOVING", 0.3)
    line = _one_interrupted_line(err)
    assert code == 130 and took < 5.0, (code, took, err[-2000:])
    assert "the episode on the twin was stopped before its next command and the twin closed" in line
    assert "nothing was written" in line and '"outcome"' not in out


def test_54_4_ctrl_c_on_the_aubo_stops_before_the_next_command_and_closes_the_session(policy_file, capsys,
                                                                                       monkeypatch):
    import signal
    import socket
    import threading

    from test_hardware_adapters import FakeController

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals reach only the main thread")

    def unhandled(signum: int, frame: Any) -> typing.NoReturn:  # not a KeyboardInterrupt: it would end the session
        raise AssertionError("the Ctrl-C reached the test: the deploy command did not handle it")


    from sagrasp_jax.deploy import aubo

    class Interrupting(FakeController):
        def __getattr__(self, name: str) -> Any:
            if name == "servoJoint":
                def servo(*args: Any) -> int:
                    self.calls.append(("servoJoint", *args))
                    if len(self.named("servoJoint")) == 3:
                        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C while the third command is under way
                    return 0
                return servo
            return super().__getattr__(name)

    fake = Interrupting()

    class FakeSdk:
        RpcClient = fake
        AuboErrorCodes = type("Codes", (), {"__members__": {}})

    monkeypatch.setattr(aubo, "import_sdk", lambda: FakeSdk)
    previous = signal.signal(signal.SIGINT, unhandled)
    try:
        with socket.create_server(("127.0.0.1", 0)) as listener:  # the TCP probe's controller
            port = listener.getsockname()[1]
            code, out, err = call(deploy_cli.main, ["--policy", policy_file, "--target-cam", *TARGET_CAM, "--backend",
                                                    "aubo", "--host", "127.0.0.1", "--port", str(port), "--gripper-io",
                                                    "settle=0", "--max-steps", "50"], capsys)
        handler = signal.getsignal(signal.SIGINT)
    finally:
        signal.signal(signal.SIGINT, previous)
    line = _one_interrupted_line(err)
    assert code == 130 and "before its next command to the arm" in line and "controller session closed" in line
    assert len(fake.named("servoJoint")) == 3  # nothing sent after the Ctrl-C
    assert [c[0] for c in fake.calls[-4:]] == ["setServoModeSelect", "logout", "disconnect", "setLogHandler"]
    assert fake.calls[-4] == ("setServoModeSelect", 0)  # servo mode left
    assert handler is unhandled  # the CLI put the handler back


SLOW_SCENES = """
import os, sys, time
from sagrasp_jax.deploy import rehearse
def slow(*a, **k):
    print(f"SCENE {os.getpid()}", flush=True)
    time.sleep(60)  # a scene that would run on for a minute
rehearse.run_scene = slow
sys.exit(rehearse.main(sys.argv[1:]))
"""


def test_54_4_ctrl_c_to_a_twin_evaluation_terminates_its_workers_at_once(tmp_path):
    """``evaluate --backend twin --workers 2`` left its workers running 34 s after a SIGINT to it.  Its scenes run
    in ``deploy.rehearse.run_cli`` (as ``deploy --camera twin``'s do), driven here through deploy.rehearse's own
    command, which spares the subprocess evaluate's jax import."""
    pytest.importorskip("pybullet")
    run = str(tmp_path / "run")
    os.makedirs(run)
    out_file = os.path.join(run, "twin.json")
    code, out, err, took = _interrupt(SLOW_SCENES, ["--policy", "pretrained", "--episodes", "4", "--workers", "2",
                                                    "--condition", "kinematic", "--out", out_file], "SCENE", 0.5)
    line = _one_interrupted_line(err)
    assert code == 130 and took < 10.0, (code, took, err[-2000:])
    assert "the twin rehearsal was stopped after 0 of 4 scenes (its 2 worker processes terminated)" in line
    assert line.endswith("no result was written") and os.listdir(run) == []
    # two workers print to one pipe: their lines may interleave ("SCENE 1SCENE 2\n\n"), so read every pid in it
    workers = {int(pid) for pid in re.findall(r"SCENE (\d+)", out)}
    assert workers
    for pid in workers:  # gone, not running their scenes on
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


MJX_EVALUATE = """
import sys
from sagrasp_jax import evaluate
from sagrasp_jax.training import fixed_seed_eval
make = fixed_seed_eval.make_evaluator
def marked(*a, **k):
    print("COMPILING", flush=True)  # what follows: tracing, then XLA's compile of the evaluator (seconds)
    return make(*a, **k)
fixed_seed_eval.make_evaluator = marked
sys.exit(evaluate.main(sys.argv[1:]))
"""


def test_54_4_ctrl_c_during_the_mjx_evaluations_compile_exits_130_not_sigsegv(tmp_path):
    """The compile of the real env's evaluator takes ≈ 20 s here with the compilation cache off; a Ctrl-C 2 s in
    used to raise inside jax (a gc callback swallowed it, or the exit died of SIGSEGV with XLA's threads
    running).  It now ends the process at once: exit 130, one line, no lock file, no result."""
    run = shutil.copytree(LEGACY_RUN, str(tmp_path / "run"))
    results = str(tmp_path / "results")
    os.makedirs(results)
    out_file = os.path.join(results, "e.json")
    code, out, err, took = _interrupt(MJX_EVALUATE, ["--run", run, "--episodes", "8", "--out", out_file], "COMPILING",
                                      2.0, env={"JAX_ENABLE_COMPILATION_CACHE": "false"})
    line = _one_interrupted_line(err)
    assert code == 130 and took < 5.0, (code, took, err[-2000:])
    assert line == f"interrupted (Ctrl-C): the evaluation of {run} was stopped; nothing was written"
    assert os.listdir(results) == []  # neither the result nor the lock file


# ---------------------------------------------------------------------- 54.5

def test_54_5_perception_refuses_bad_library_input_with_a_perception_error():
    from test_perception import CAL, SCENE, cast

    from sagrasp_jax.deploy import perception

    cloud, rgb = cast(SCENE)
    cases = [
        (lambda: perception.detect_scene(cloud, np.full(rgb.shape, "a"), CAL), "RGB image must be uint8 or floats"),
        (lambda: perception.detect_scene(cloud, [[1, 2], [3]], CAL), "RGB image is not an \\(H, W, 3\\) array"),
        (lambda: perception.point_at_pixel(cloud, float("nan"), 3.0), "pixel \\(nan, 3.0\\) must be two finite"),
        (lambda: perception.point_at_pixel(cloud, 3.0, 3.0, window=-1), "window -1 must be a whole number"),
        (lambda: perception.detect_scene(cloud, rgb, CAL, target_size=["a", "b", "c"]), "target_size .* 3 full extents"),
        (lambda: perception.detect_scene(cloud, rgb, CAL, target_size=[0.05]), "target_size .* 3 full extents"),
        (lambda: perception.detect_scene(cloud, rgb, CAL, detections=[perception.Detection("target", (math.nan, 0, 1, 1))]),
         "its box must be 4 finite pixel coordinates"),
    ]
    for fn, message in cases:
        with pytest.raises(perception.PerceptionError, match=message):
            fn()


def test_54_5_an_empty_output_path_is_named_as_such(tmp_path, capsys):
    from sagrasp_jax import calibrate

    pairs = tmp_path / "pairs.csv"
    pairs.write_text("1,2,3,4,5,6\n")
    code, _, err = call(calibrate.main, ["--pairs", str(pairs), "--out", ""], capsys)
    assert code == 2 and "the calibration output is an empty path '': name the file to write" in err, err
    assert os.listdir(tmp_path) == ["pairs.csv"]
