"""One grasp from training to robot (docs/design.md, "One grasp"): the deploy loop closes where the success
pose was reached, takes the cube's height as known, and the twin simulates the approach and judges the held cube."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("pybullet")

import pybullet as pb  # noqa: E402

from sagrasp_jax.task import collision  # noqa: E402
from sagrasp_jax.task import reward  # noqa: E402
from sagrasp_jax.task.config import HOME_Q, get_config  # noqa: E402
from sagrasp_jax.deploy import transfer  # noqa: E402
from sagrasp_jax.deploy.__main__ import main as deploy_main  # noqa: E402
from sagrasp_jax.deploy.calibration import standing_cube_centre  # noqa: E402
from sagrasp_jax.deploy.loop import Obstacle, collision_hook, run_episode, scene_spec  # noqa: E402
from sagrasp_jax.deploy.rehearse import rehearse  # noqa: E402
from sagrasp_jax.deploy.twin import PyBulletTwin  # noqa: E402
from sagrasp_jax.task.robot import (  # noqa: E402
    approach_pose, forward_kinematics, lift_pose, load_robot, solve_home_pose, tilt, translated_pose,
)
from sagrasp_jax.task.policy_file import load_policy  # noqa: E402
from tiny_run import REPO, tiny_run  # noqa: E402

MODEL = load_robot()
HOME = np.array(HOME_Q)
TARGET = np.array([0.10, -0.45, 0.025])
CFG = get_config("cpu-quick").env
# A sphere beside the forearm (found by search over the pose pair below): 17 mm clear of the arm at the tilted
# grasp pose, 16 mm inside it once the wrist is swung upright over the same point (the old final centring).
SWING_OBSTACLE = Obstacle("sphere", (0.1116, -0.2729, 0.2222), (0.0584, 0.0, 0.0))


@pytest.fixture(scope="session")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> str:
    return tiny_run(str(tmp_path_factory.getbasetemp()))


@pytest.fixture(scope="module")
def policy(run_dir: str):
    return load_policy(os.path.join(run_dir, "policy.npz"))


def grasp_poses(height: float = 0.0125) -> tuple[np.ndarray, np.ndarray]:
    """(upright, tilted by 9.2°) joints with the gripper centre ``height`` over TARGET's centre."""
    q, start = HOME, forward_kinematics(np, MODEL, HOME).gripper_centre
    goal = TARGET + [0.0, 0.0, height]
    for s in np.linspace(0.1, 1.0, 10):
        q = solve_home_pose(q, start + s * (goal - start))
    tilted = q.copy()
    tilted[3] += 0.16  # wrist 1: the forearm leans back, the gripper tilts as a policy's arrives
    tilted = translated_pose(MODEL, tilted, goal - forward_kinematics(np, MODEL, tilted).gripper_centre, max_joint_move=1.0)
    return q, tilted


def test_translated_pose_keeps_the_orientation_and_the_lift_keeps_the_tilt() -> None:
    _, tilted = grasp_poses()
    kin = forward_kinematics(np, MODEL, tilted)
    assert math.degrees(float(tilt(np, kin.approach_axis))) == pytest.approx(9.17, abs=0.05)
    lifted = forward_kinematics(np, MODEL, lift_pose(MODEL, tilted, 0.05))
    np.testing.assert_allclose(lifted.gripper_centre - kin.gripper_centre, [0, 0, 0.05], atol=1e-6)
    np.testing.assert_allclose(lifted.link_rot[-1], kin.link_rot[-1], atol=1e-6)


def test_blocking_scene_where_upright_centring_collides_now_grasps(policy) -> None:
    """The policy reached the grasp pose tilted 9°, 17 mm clear of an obstacle; swinging the wrist upright (the
    old centring) would put the forearm 16 mm into it.  The loop now closes there, lifts, and the cube is held."""
    _, tilted = grasp_poses()
    spec = scene_spec(tilted, TARGET, 0.0, [SWING_OBSTACLE], CFG)
    check = collision_hook(MODEL, CFG, spec)
    assert check(tilted) is None
    old_centring = approach_pose(MODEL, tilted, reward.grasp_centre(np, CFG.task, TARGET))
    assert "obstacle" in (check(old_centring) or ""), "the scene no longer shows the old centring's collision"
    clearance = float(collision.check(np, MODEL, forward_kinematics(np, MODEL, tilted), spec, CFG).nearest_obstacle_dist)
    assert 0.010 < clearance < 0.025
    with PyBulletTwin(spec, CFG, q0=tilted) as twin:
        report = run_episode(twin, policy, TARGET, 0.0, [SWING_OBSTACLE])
    assert report.outcome == "success" and report.steps == 0
    g = report.grasp
    assert g["closed"] and g["lifted"] and g["approach_faults"] == [], g
    assert report.held is True and g["object_rise"] > 0.04, g
    assert g["closing_tilt_deg"] == pytest.approx(9.17, abs=0.3)  # closed as it arrived, not swung upright


def test_detection_5_mm_high_still_grasps(policy) -> None:
    """A detection 5 mm too high puts the true grasp pose below the band around the detection (the loop would
    wait for a pose it never reaches); the cube's height is known, so the loop stops at once and holds it."""
    _, tilted = grasp_poses(height=0.007)  # 7 mm over the true centre: inside the band [5, 20] mm
    detected = TARGET + [0.0, 0.0, 0.005]
    kin = forward_kinematics(np, MODEL, tilted)
    assert not bool(reward.success_flag(np, CFG.task, kin.gripper_centre, detected, tilt(np, kin.approach_axis)))
    spec = scene_spec(tilted, TARGET, 0.0, [], CFG)
    with PyBulletTwin(spec, CFG, q0=tilted) as twin:
        report = run_episode(twin, policy, detected, 0.0)
    assert report.success and report.steps == 0
    np.testing.assert_allclose(report.target, TARGET, atol=1e-12)
    np.testing.assert_allclose(report.detected_target, detected, atol=1e-12)
    assert report.held is True, report.grasp
    np.testing.assert_allclose(standing_cube_centre([0.1, -0.4, 0.031]), [0.1, -0.4, 0.025])


def test_twin_reports_a_knocked_cube_and_a_brushed_obstacle() -> None:
    """The approach runs under physics: a gripper swept through the cube moves it (a knocked cube), an arm
    link through an obstacle is a touch; a clean approach reports nothing."""
    upright, _ = grasp_poses(height=0.06)  # 6 cm over the cube: clear
    side = translated_pose(MODEL, upright, (0.0, 0.0, -0.055))  # down to 5 mm over the centre: pads around the cube
    beside = translated_pose(MODEL, upright, (0.045, 0.0, 0.0))
    low = translated_pose(MODEL, beside, (0.0, 0.0, -0.045))  # beside the cube, pads at its height
    spec = scene_spec(upright, TARGET, 0.0, [], CFG)
    with PyBulletTwin(spec, CFG, q0=upright) as twin:
        for s in np.linspace(0, 1, 11)[1:]:
            twin.command_joint_targets(upright + s * (side - upright))
        assert twin.approach_faults() == []  # straight down over the cube: the pads pass either side
    with PyBulletTwin(spec, CFG, q0=low) as twin:
        for s in np.linspace(0, 1, 21)[1:]:  # sweep sideways through the cube at its height
            twin.command_joint_targets(low + s * (side - low) * 1.6)
        faults = twin.approach_faults()
    assert any("cube knocked" in f for f in faults), faults
    ob = Obstacle("sphere", (TARGET[0] + 0.14, TARGET[1], 0.16), (0.03, 0.0, 0.0))  # in the gripper's way sideways
    spec = scene_spec(upright, TARGET, 0.0, [ob], CFG)
    across = translated_pose(MODEL, upright, (0.20, 0.0, 0.0))
    with PyBulletTwin(spec, CFG, q0=upright) as twin:
        for s in np.linspace(0, 1, 21)[1:]:
            twin.command_joint_targets(upright + s * (across - upright))
        faults = twin.approach_faults()
    assert any(f.startswith("touched obstacle 1") for f in faults), faults
    assert not any("cube" in f or "table" in f for f in faults), faults


def test_transfer_draws_match_the_mjx_distributions() -> None:
    r = get_config("cpu-quick").env.randomize
    rng = np.random.default_rng(0)
    draws = [transfer.draw(r, True, rng) for _ in range(2000)]
    gains = np.array([d[0].servo_gains for d in draws])
    offsets = np.array([d[0].offsets for d in draws])
    latency = np.array([d[0].latency for d in draws])
    target = np.array([d[1] for d in draws])
    assert gains.min() >= 1 - r.servo_gain and gains.max() <= 1 + r.servo_gain and gains.std() > 0.5 * r.servo_gain / 2
    assert np.abs(offsets).max() <= r.joint_offset and np.abs(target).max() <= r.target_error
    assert 0 <= latency.min() and latency.max() <= r.latency and abs(latency.mean() - r.latency / 2) < 0.1
    assert len({tuple(g) for g in gains[:10]}) == 10  # per joint and per episode
    with pytest.raises(ValueError, match="one per joint"):
        transfer.TransferErrors(servo_gain=(1.0, 1.0))
    with pytest.raises(ValueError, match="joint offset"):
        transfer.TransferErrors(joint_offset=0.5)


def test_twin_joint_offset_is_in_the_readings_not_the_arm() -> None:
    spec = scene_spec(HOME, TARGET, 0.0, [], CFG)
    errors = transfer.TransferErrors(joint_offset=(0.01, -0.01, 0.0, 0.0, 0.005, 0.0))
    with PyBulletTwin(spec, CFG, q0=HOME, errors=errors) as twin:
        np.testing.assert_allclose(twin.read_joints() - twin.true_joints(), errors.offsets, atol=1e-12)
        twin.command_joint_targets(HOME + 0.01)
        np.testing.assert_allclose(twin.true_joints(), HOME + 0.01, atol=1e-9)  # commands in the servos' frame


def test_rehearsal_is_the_same_scene_whatever_the_workers(policy) -> None:
    one = rehearse(policy.path, 4, "robot", "blocking", seed=3, workers=1, progress=False)
    two = rehearse(policy.path, 4, "robot", "blocking", seed=3, workers=2, progress=False)
    strip = lambda rs: [{k: v for k, v in r.items()} for r in rs]  # noqa: E731
    assert strip(one["records"]) == strip(two["records"])
    assert all(r["kind"] == "blocking" for r in one["records"])
    assert one["summary"]["all"]["episodes"] == 4 and set(one["summary"]) >= {"all", "obstacle", "blocking", "no obstacle"}
    assert len({tuple(r["detection_error_mm"]) for r in one["records"]}) == 4


def _cam_mm(world_top) -> list[str]:
    from sagrasp_jax.deploy.calibration import CameraCalibration

    return [f"{v:.6f}" for v in CameraCalibration.default().base_to_cam(np.asarray(world_top), units="mm")]


def test_deploy_exit_status_is_the_held_cube(run_dir: str, monkeypatch, capsys) -> None:
    """0 only when the cube is held after the lift: the same scene held (exit 0) and with a cube too heavy to
    lift (exit 1, the report says not held)."""
    _, tilted = grasp_poses()
    args = ["--policy", os.path.join(run_dir, "policy.npz"), "--target-cam", *_cam_mm(TARGET + [0, 0, 0.025]), "--json",
            "--twin-start-q", *[f"{v:.9f}" for v in tilted]]
    assert deploy_main(args) == 0
    held = json.loads(capsys.readouterr().out)
    assert held["held"] is True and held["grasp"]["object_rise"] > 0.04

    real_init = PyBulletTwin.__init__

    def heavy_cube(self, *a, **k):  # the cube glued to the table: the gripper closes on it and cannot lift it
        real_init(self, *a, **k)
        pb.changeDynamics(self.target_body, -1, mass=50.0, physicsClientId=self._client)

    monkeypatch.setattr(PyBulletTwin, "__init__", heavy_cube)
    assert deploy_main(args) == 1
    dropped = json.loads(capsys.readouterr().out)
    assert dropped["held"] is False and dropped["grasp"]["closed"] and dropped["outcome"] == "success"


def test_deploy_cli_exit_1_on_a_timeout(run_dir: str) -> None:
    res = subprocess.run([sys.executable, "-m", "sagrasp_jax.deploy", "--policy", os.path.join(run_dir, "policy.npz"),
                          "--target-cam", *_cam_mm(TARGET + [0, 0, 0.025]), "--max-steps", "3", "--json"],
                         capture_output=True, text=True, timeout=300, cwd=REPO)
    assert res.returncode == 1, res.stderr[-2000:]
    report = json.loads(res.stdout)
    assert report["outcome"] == "timeout" and report["held"] is None


def test_slide_refused_near_an_obstacle_closes_where_the_arm_stands(policy) -> None:
    """A grasp pose 8 mm off the cube's centre, 4.4 mm clear of an obstacle that the centred pose would overlap
    by 2.9 mm: the slide stops at the first refused step (never sent) and the gripper closes where it stands."""
    from sagrasp_jax.deploy.loop import centring_pose

    q, start = HOME, forward_kinematics(np, MODEL, HOME).gripper_centre
    goal = TARGET + [0.0, -0.008, 0.0125]
    for s in np.linspace(0.1, 1.0, 10):
        q = solve_home_pose(q, start + s * (goal - start))
    q[3] += 0.12
    q = translated_pose(MODEL, q, goal - forward_kinematics(np, MODEL, q).gripper_centre, max_joint_move=1.0)
    ob = Obstacle("sphere", (0.1575, -0.3187, 0.2307), (0.0436, 0.0, 0.0))
    spec = scene_spec(q, TARGET, 0.0, [ob], CFG)
    check = collision_hook(MODEL, CFG, spec)
    assert check(q) is None and "obstacle" in (check(centring_pose(MODEL, CFG, q, TARGET)) or "")
    with PyBulletTwin(spec, CFG, q0=q) as twin:
        report = run_episode(twin, policy, TARGET, 0.0, [ob])
    g = report.grasp
    assert report.success and g["centring"].startswith("stopped") and "obstacle" in g["centring"], g
    assert g["closed"] and g["approach_faults"] == [], g
    assert report.held is True, g  # 8 mm off along the pads' width: still caught


def test_end_to_end_from_the_twin_camera(capsys) -> None:
    """deploy --camera twin: the twin renders, perception finds the cube and the obstacles, the loop grasps;
    the result carries perception's errors (and --scenes is checked like every input)."""
    assert deploy_main(["--backend", "twin", "--camera", "twin", "--policy", "pretrained", "--scenes", "2",
                        "--condition", "robot"]) == 0
    out = capsys.readouterr().out
    assert "from the camera (industrial depth noise)" in out and "perception: 0 of 2 captures refused" in out
    one = rehearse("pretrained", 2, "kinematic", "mix", seed=0, workers=1, progress=False,
                   camera=__import__("sagrasp_jax.deploy.rehearse", fromlist=["CameraSettings"]).CameraSettings())
    p = one["perception"]
    assert p["refused"] == 0 and p["target_horizontal_error_mm"]["p95"] < 5.0, p
    assert one["summary"]["all"]["held_rate"] == 1.0, one["summary"]
    assert deploy_main(["--camera", "twin", "--policy", "pretrained", "--scenes", "0"]) == 2
    assert "--scenes must be in" in capsys.readouterr().err
