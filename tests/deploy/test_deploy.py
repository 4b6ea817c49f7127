"""Deployment loop on the PyBullet twin: training observation, safety before every command, CLI refusals."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("pybullet")

from sagrasp_jax.task import sampling  # noqa: E402
from sagrasp_jax.task.config import HOME_Q, RandomizeConfig, get_config  # noqa: E402
from sagrasp_jax.deploy import (  # noqa: E402
    CameraCalibration,
    Obstacle,
    SafetyLayer,
    SafetyViolation,
    TargetRejected,
    WorkspaceBox,
    build_observation,
    run_episode,
    scene_spec,
    send_checked,
)
from sagrasp_jax.deploy.__main__ import camera_yaw_to_world  # noqa: E402
from sagrasp_jax.deploy.loop import collision_hook  # noqa: E402
from sagrasp_jax.deploy.twin import PyBulletTwin  # noqa: E402
from sagrasp_jax.task.robot import forward_kinematics, load_robot, solve_home_pose  # noqa: E402
from sagrasp_jax.task.policy_file import load_policy, save_policy_npz  # noqa: E402
from tiny_run import REPO, tiny_run  # noqa: E402

HOME = np.array(HOME_Q)
TARGET = np.array([0.10, -0.45, 0.025])
MODEL = load_robot()


@pytest.fixture(scope="session")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> str:
    return tiny_run(str(tmp_path_factory.getbasetemp()))


@pytest.fixture(scope="module")
def policy(run_dir: str):
    return load_policy(os.path.join(run_dir, "policy.npz"))


def constant_policy(tmp_path, action) -> object:
    """A policy whose deterministic action is ``action`` whatever it sees (zero weights, biased output)."""
    loc = np.arctanh(np.asarray(action, dtype=np.float64))
    weights = [(np.zeros((17, 8), np.float32), np.zeros(8, np.float32)),
               (np.zeros((8, 12), np.float32), np.concatenate([loc, np.zeros(6)]).astype(np.float32))]
    path = save_policy_npz(tmp_path / "const.npz", weights=weights, activation="tanh", obs_mean=np.zeros(17),
                           obs_std=np.ones(17), config=get_config("paper"))
    return load_policy(path)


class Spy:
    """Records what reaches the robot."""

    def __init__(self, robot: PyBulletTwin) -> None:
        self.robot, self.sent = robot, []

    def read_joints(self):
        return self.robot.read_joints()

    def command_joint_targets(self, q):
        self.sent.append(np.array(q))
        self.robot.command_joint_targets(q)

    def open_gripper(self):
        self.robot.open_gripper()

    def close_gripper(self):
        self.robot.close_gripper()

    def object_position(self):
        return self.robot.object_position()


def _twin(target=TARGET, obstacles=(), q0=HOME, yaw=0.0) -> PyBulletTwin:
    cfg = get_config("cpu-quick").env
    return PyBulletTwin(scene_spec(q0, target, yaw, obstacles, cfg), cfg, q0=q0)


def test_observation_is_the_training_envs() -> None:
    """Same numbers as GraspEnv (noise and transfer errors off) for sampled scenes, obstacles included."""
    import jax

    from sagrasp_jax.envs.grasp_env import GraspEnv

    cfg = get_config("cpu-quick").env
    cfg = dataclasses.replace(cfg, task=dataclasses.replace(cfg.task, obs_noise_std=0.0),
                              sampling=dataclasses.replace(cfg.sampling, obstacle_prob=1.0),
                              randomize=RandomizeConfig())  # the training's transfer errors off: the same scene seen
    env = GraspEnv(cfg)
    rng = np.random.default_rng(0)
    reset_to = jax.jit(env.reset_to)
    specs = [sampling.sample_reset(np, MODEL, cfg.sampling, cfg.task, rng.random(sampling.uniforms_needed(cfg.sampling)))
             for _ in range(12)]
    specs = [s for s in specs if s.obstacle_active.any()][:4]  # skip the rare no-feasible-obstacle fallback
    assert len(specs) == 4
    for spec in specs:
        ours = build_observation(MODEL, cfg, spec.q0, spec).obs
        theirs = np.asarray(reset_to(spec, jax.random.PRNGKey(0)).obs)
        np.testing.assert_allclose(ours, theirs, atol=2e-5)
        assert ours[15] < 1.0  # Δpo of a real obstacle, not the "none" value


def test_safety_refuses_over_limit_and_too_fast_commands_twin_stays(policy) -> None:
    layer = SafetyLayer()
    with _twin() as twin:
        before = twin.read_joints()
        over = before.copy()
        over[0] = 3.10
        with pytest.raises(SafetyViolation, match=r"joint 1 \(shoulder_joint\) .* outside its limit"):
            send_checked(twin, layer, over, over - [0.04, 0, 0, 0, 0, 0])
        fast = before + [0, 0.2, 0, 0, 0, 0]
        with pytest.raises(SafetyViolation, match=r"joint 2 .* moves 0\.2000 rad in one step"):
            send_checked(twin, layer, fast, before)
        np.testing.assert_array_equal(twin.read_joints(), before)
        ok = before + [0.02, -0.01, 0, 0, 0, 0]
        send_checked(twin, layer, ok, before)  # a valid command does reach the twin
        np.testing.assert_allclose(twin.read_joints(), ok, atol=1e-12)


def test_target_outside_workspace_refused_before_moving(policy) -> None:
    with _twin() as twin:
        before = twin.read_joints()
        with pytest.raises(TargetRejected, match="x = 0.6000 m is outside"):
            run_episode(twin, policy, [0.60, -0.45, 0.025])
        with pytest.raises(TargetRejected, match="NaN"):
            run_episode(twin, policy, [np.nan, -0.45, 0.025])
        np.testing.assert_array_equal(twin.read_joints(), before)


def test_tiny_policy_episode_on_twin_reports_and_obeys_safety(policy) -> None:
    obstacle = Obstacle("cylinder", (0.25, -0.30, 0.08), (0.03, 0.08, 0.0))
    with _twin(obstacles=[obstacle]) as twin:
        spy = Spy(twin)
        report = run_episode(spy, policy, TARGET, obstacles=[obstacle], max_steps=30)
        final = twin.read_joints()
    assert report.outcome in ("success", "timeout", "collision", "refused")
    assert report.success == (report.outcome == "success")
    assert 1 <= report.steps <= 30 and len(spy.sent) == report.steps
    assert report.obstacles == 1 and 0.0 < report.min_obstacle_clearance < 1.0
    assert report.final_distance > 0 and len(report.final_q) == 6 and report.target == TARGET.tolist()
    d = report.to_dict()
    for key in ("outcome", "steps", "success", "min_obstacle_clearance", "final_distance", "final_tilt_deg", "message"):
        assert key in d
    json.dumps(d, allow_nan=False)
    # every command the twin received passes the layer the loop uses, one after the other
    cfg = policy.env_config()
    spec = scene_spec(HOME, TARGET, 0.0, [obstacle], cfg)
    layer = SafetyLayer(robot=MODEL, collision_check=collision_hook(MODEL, cfg, spec))
    previous = HOME
    for q in spy.sent:
        layer.check(q, previous)
        previous = q
    np.testing.assert_allclose(final, spy.sent[-1], atol=1e-12)


def test_loop_stops_at_the_first_refused_command(tmp_path) -> None:
    """A policy that drives the gripper down under a tightened workspace floor is stopped by the
    layer; the refused command never reaches the twin."""
    down = constant_policy(tmp_path, [0, 0.9, 0, 0, 0, 0])  # q2 up: the arm tips forward and down
    start_z = float(forward_kinematics(np, MODEL, HOME).gripper_centre[2])
    layer = SafetyLayer(robot=MODEL, workspace=WorkspaceBox(lower=(-0.5, -0.85, start_z - 0.05)))
    with _twin() as twin:
        spy = Spy(twin)
        report = run_episode(spy, down, TARGET, safety=layer)
        final = twin.read_joints()
    assert report.outcome == "refused" and not report.success
    assert "workspace box" in report.message and f"step {report.steps + 1}" in report.message
    assert len(spy.sent) == report.steps >= 1
    np.testing.assert_array_equal(final, spy.sent[-1])
    assert forward_kinematics(np, MODEL, final).gripper_centre[2] >= start_z - 0.05


def test_grasp_pose_closes_and_lifts_the_cube_on_twin(policy) -> None:
    """Starting at a success pose the loop stops at once, closes the gripper and lifts 5 cm; the cube comes along."""
    q = HOME
    start = forward_kinematics(np, MODEL, HOME).gripper_centre
    goal = TARGET + [0, 0, 0.0125]
    for s in np.linspace(0.1, 1.0, 10):
        q = solve_home_pose(q, start + s * (goal - start))
    with _twin(q0=q, yaw=0.4) as twin:
        report = run_episode(twin, policy, TARGET, 0.4)
    assert report.outcome == "success" and report.steps == 0
    grasp = report.grasp
    assert grasp["closed"] and grasp["lifted"], grasp
    assert abs(grasp["gripper_rise"] - 0.05) < 0.005
    assert grasp["object_held"] and grasp["object_rise"] > 0.04, grasp


def _deploy(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sagrasp_jax.deploy", *args], capture_output=True, text=True,
                          timeout=300, cwd=REPO)


def _cam_mm(world_top) -> list[str]:
    return [f"{v:.6f}" for v in CameraCalibration.default().base_to_cam(np.asarray(world_top), units="mm")]


def test_cli_json_report_on_twin(run_dir: str) -> None:
    top = _cam_mm(TARGET + [0, 0, 0.025])
    ob = _cam_mm([0.25, -0.30, 0.16])
    cap = _cam_mm([-0.20, -0.45, 0.06])  # a capsule lying on the table (the policy's config has the paper's kinds only)
    res = _deploy("--policy", os.path.join(run_dir, "policy.npz"), "--target-cam", *top, "--target-yaw", "30",
                  "--obstacle", "cylinder", *ob, "30", "160", "--obstacle", "capsule", *cap, "30", "200", "45",
                  "--max-steps", "20", "--json")
    assert res.returncode in (0, 1, 3), res.stderr[-2000:]
    report = json.loads(res.stdout)  # stdout is the JSON alone (PyBullet's banners go to stderr)
    assert report["outcome"] in ("success", "timeout", "collision", "refused")
    np.testing.assert_allclose(report["target"], TARGET, atol=1e-8)
    np.testing.assert_allclose(report["input"]["obstacles_world"][0]["centre"], [0.25, -0.30, 0.08], atol=1e-8)
    np.testing.assert_allclose(report["input"]["obstacles_world"][0]["size"], [0.03, 0.08, 0.0], atol=1e-12)
    capsule = report["input"]["obstacles_world"][1]
    assert capsule["kind"] == "capsule" and report["obstacles"] == 2
    np.testing.assert_allclose(capsule["centre"], [-0.20, -0.45, 0.03], atol=1e-8)  # top − radius
    np.testing.assert_allclose(capsule["size"], [0.03, 0.07, 0.0], atol=1e-12)  # (r, half axis = 0.2 / 2 − r)
    assert capsule["yaw"] == pytest.approx(camera_yaw_to_world(CameraCalibration.default(), math.radians(45), math.pi))
    assert abs(report["target_yaw"]) <= math.pi / 4 + 1e-9
    assert report["steps"] <= 20 and report["min_obstacle_clearance"] is not None


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--target-cam", "-147", "-77", "1374", "--units", "m"], "wrong units? (given --units m; try --units mm)"),
        (["--target-cam", "-0.147", "-0.077", "1.374"], "wrong units? (given --units mm; try --units m)"),
        (["--target-cam", "500", "-77", "1374"], "x = -0.5445 m is outside"),
        (["--target-cam", "nan", "-77", "1374"], "must be 3 finite numbers"),
        (["--target-cam", "-147", "-77", "1374", "--obstacle", "cone", "0", "0", "1300", "30"], "one of sphere, cylinder, box, capsule"),
        (["--target-cam", "-147", "-77", "1374", "--obstacle", "box", "0", "0", "1300", "30"], "box takes X Y Z LX LY LZ"),
        (["--target-cam", "-147", "-77", "1374", "--obstacle", "sphere", "0", "0", "1300", "900"], "outside [0.005, 0.5] m"),
        (["--target-cam", "-147", "-77", "1374", "--obstacle", "capsule", "0", "0", "1300", "30", "50"],
         "must exceed twice its radius"),
    ],
)
def test_cli_refuses_bad_input_before_moving(run_dir: str, args: list[str], message: str) -> None:
    res = _deploy("--policy", os.path.join(run_dir, "policy.npz"), *args)
    assert res.returncode == 2, res.stdout + res.stderr
    assert "refused before moving" in res.stderr and message in res.stderr
    assert "Traceback" not in res.stderr
    assert "pybullet build time" not in res.stdout + res.stderr  # refused before a twin was even built


def test_deploy_modules_do_not_import_jax() -> None:
    code = ("import sys; import sagrasp_jax.deploy.loop, sagrasp_jax.deploy.twin, sagrasp_jax.deploy.__main__, "
            "sagrasp_jax.reference.grasp_check; sys.exit(any(m == 'jax' or m.startswith('jax.') for m in sys.modules))")
    assert subprocess.run([sys.executable, "-c", code], cwd=REPO, timeout=120).returncode == 0


# ---- issue 54, "the first five minutes": what a newcomer meets first


def _cam_top(world_top) -> list[str]:
    return [f"{v:.6f}" for v in CameraCalibration.default().base_to_cam(np.asarray(world_top), units="mm")]


def test_help_says_what_policy_target_cam_and_obstacle_take(capsys) -> None:
    from sagrasp_jax.deploy.__main__ import main as deploy_main

    with pytest.raises(SystemExit) as stop:
        deploy_main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert stop.value.code == 0
    for said in ("a policy.npz file (export's output), a folder holding one (a finished run folder, or export's --out "
                 "folder), or the name of a policy shipped in the package: pretrained",
                 "a file or folder of that name in the working folder is given as a path, ./pretrained",
                 "the centre of its top face, in the camera frame, in --units (default mm)",
                 "X Y Z the top of the obstacle (the highest point the depth camera sees on it) in the camera frame",
                 "sphere X Y Z R | cylinder X Y Z R H | box X Y Z LX LY LZ [YAW_DEG] | capsule X Y Z R L [YAW_DEG]; R "
                 "radius, H height, LX LY LZ full side lengths", "L length tip to tip",
                 "--dry-run check everything and stop before the first motion: print what would be done",
                 "default the paper's printed calibration, built in"):
        assert said in text, said


def test_a_mistyped_option_is_named_with_the_nearest_one(capsys) -> None:
    from sagrasp_jax.deploy.__main__ import main as deploy_main

    argv = ["--polcy", "pretrained", "--target-cam", "-147", "-77", "1374"]
    with pytest.raises(SystemExit) as stop:
        deploy_main(argv)
    err = capsys.readouterr().err
    assert stop.value.code == 2
    assert err.splitlines() == ["python -m sagrasp_jax.deploy: error: unknown option --polcy (did you mean --policy?)"]
    with pytest.raises(SystemExit):
        deploy_main([*argv, "--json"])
    out, err = capsys.readouterr()
    assert json.loads(out)["message"] == "unknown option --polcy (did you mean --policy?)"
    with pytest.raises(SystemExit) as stop:  # --camera twin's and --dry-run's parsers too
        deploy_main(["--camera", "twin", "--policy", "pretrained", "--scenez", "2"])
    assert stop.value.code == 2 and "unknown option --scenez (did you mean --scenes?)" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        deploy_main(["--backend", "aubo", "--host", "h", "--dry-run", "--prot", "1"])
    assert "unknown option --prot (did you mean --port?)" in capsys.readouterr().err


def test_dry_run_added_to_a_deploy_line_stops_before_the_first_motion(capsys, monkeypatch) -> None:
    """The README's advice, "run --dry-run first", on a whole deploy line: everything is checked, what would be
    done is printed, no twin is built.  The calibration is named without citing a file the wheel lacks."""
    from sagrasp_jax.deploy import twin
    from sagrasp_jax.deploy.__main__ import main as deploy_main

    monkeypatch.setattr(twin, "PyBulletTwin", lambda *a, **k: pytest.fail("a dry run built the twin"))
    line = ["--policy", "pretrained", "--target-cam", *_cam_top(TARGET + [0, 0, 0.025]),
            "--obstacle", "sphere", "-40", "-160", "1300", "30", "--dry-run"]
    assert deploy_main([*line, "--json"]) == 0
    out = capsys.readouterr().out
    report = json.loads(out)
    assert report["outcome"] == "dry_run" and report["commanded"] is False
    plan = report["plan"]
    np.testing.assert_allclose(plan["target_world"], TARGET, atol=1e-5)
    assert plan["backend"] == "twin" and plan["policy"] == "pretrained" and len(plan["obstacles_world"]) == 1
    assert plan["calibration"] == "the paper's printed calibration (built in)" and "docs/" not in out
    assert CameraCalibration.default().source == "the paper's printed calibration (built in)"
    assert deploy_main(line) == 0
    text = capsys.readouterr().out
    assert text.startswith("dry run: would deploy pretrained on the PyBullet twin; nothing was commanded")
    assert "obstacle       sphere" in text and "at most        200 policy steps" in text
    assert deploy_main([*line, "--target-cam", "500", "-77", "1374"]) == 2  # checked as a real run is
    assert "x = -0.5445 m is outside" in capsys.readouterr().err


def test_dry_run_of_an_aubo_deploy_line_connects_and_commands_nothing(capsys, monkeypatch) -> None:
    """The same on the AUBO (through the FakeController test double of tests/deploy/test_hardware_adapters.py): the
    plan, then the controller's read-only report; nothing commanded, the session closed."""
    import socket

    from test_hardware_adapters import COMMANDS, FakeController

    from sagrasp_jax.deploy import aubo
    from sagrasp_jax.deploy.__main__ import main as deploy_main

    fake = FakeController()

    class FakeSdk:
        RpcClient = fake
        AuboErrorCodes = type("Codes", (), {"__members__": {}})

    monkeypatch.setattr(aubo, "import_sdk", lambda: FakeSdk)
    with socket.create_server(("127.0.0.1", 0)) as listener:
        code = deploy_main(["--policy", "pretrained", "--target-cam", *_cam_top(TARGET + [0, 0, 0.025]), "--backend",
                            "aubo", "--host", "127.0.0.1", "--port", str(listener.getsockname()[1]), "--dry-run"])
    out = capsys.readouterr().out
    assert code == 0 and "would deploy pretrained on the AUBO-i5 at 127.0.0.1" in out and "AT HOME" in out, out
    assert fake.named(*COMMANDS) == [] and [c[0] for c in fake.calls[-3:]] == ["logout", "disconnect", "setLogHandler"]
