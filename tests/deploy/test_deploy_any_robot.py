"""Every layer above the MJX env serves the robot the policy's config names (issue 56, item 1): a 7-joint Franka
Panda policy runs through the deploy loop on the PyBullet twin, the deploy command takes its start pose with 7
joints, and the AUBO driver refuses it naming both robots."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

pytest.importorskip("pybullet")

from sagrasp_jax.deploy import rehearse, transfer  # noqa: E402
from sagrasp_jax.deploy.__main__ import main as deploy_main  # noqa: E402
from sagrasp_jax.deploy.calibration import CameraCalibration  # noqa: E402
from sagrasp_jax.deploy.loop import DeployError, obstacles_from_spec, run_episode  # noqa: E402
from sagrasp_jax.deploy.safety import PolicyMismatch, SafetyLayer, check_policy_constants  # noqa: E402
from sagrasp_jax.deploy.transfer import TransferErrors  # noqa: E402
from sagrasp_jax.deploy.twin import PyBulletTwin  # noqa: E402
from sagrasp_jax.task import observation, robot, robots, scripted  # noqa: E402
from sagrasp_jax.task.config import get_config  # noqa: E402
from sagrasp_jax.task.config_parse import apply_overrides  # noqa: E402
from sagrasp_jax.task.policy_file import NumpyPolicy, PolicyFormatError, load_policy, save_policy_npz  # noqa: E402

PANDA = robot.load_robot("panda")


def _policy_file(tmp_path, robot_name: str, seed: int = 0) -> str:
    """A random-init policy file for ``robot_name`` (cpu-quick's config with env.robot set): its inputs are that
    robot's observation layout, its outputs one per joint."""
    cfg = apply_overrides(get_config("cpu-quick"), [f"robot={robot_name}"])
    layout = observation.layout_of(cfg.env)
    dof = robots.get(robot_name).dof
    rng = np.random.default_rng(seed)
    weights = [(rng.normal(0, 0.1, (len(layout), 16)).astype(np.float32), np.zeros(16, np.float32)),
               (rng.normal(0, 0.1, (16, 2 * dof)).astype(np.float32), np.zeros(2 * dof, np.float32))]
    return str(save_policy_npz(tmp_path / f"{robot_name}.npz", weights=weights, activation="tanh",
                               obs_mean=np.zeros(len(layout)), obs_std=np.ones(len(layout)), config=cfg,
                               obs_layout=layout))


class ScriptedPolicy:
    """The package's scripted controller behind a policy file's interface (its config, its checks): actions that
    reach the cube, so the loop's grasp and lift run too."""

    def __init__(self, policy: NumpyPolicy) -> None:
        self.policy, self.path = policy, policy.path
        self.cfg = policy.env_config()
        layout = observation.layout_of(self.cfg)
        self.joints = slice(layout.index("q1"), layout.index("q1") + robots.get(self.cfg.robot).dof)
        self.target = slice(layout.index("target_x"), layout.index("target_x") + 3)
        self.actions: list[np.ndarray] = []

    def check_grasp_inputs(self) -> None:
        self.policy.check_grasp_inputs()

    def env_config(self):
        return self.cfg

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        action = scripted.scripted_action(np, self.cfg, obs[self.joints], obs[self.target])
        self.actions.append(action)
        return action


@pytest.fixture(scope="module")
def panda_policy(tmp_path_factory) -> str:
    return _policy_file(tmp_path_factory.mktemp("panda"), "panda")


def test_panda_policy_file_has_seven_actions_and_its_layout(panda_policy) -> None:
    policy = load_policy(panda_policy)
    policy.check_grasp_inputs()
    assert policy.env_config().robot == "panda" and policy.action_size == 7 == PANDA.dof
    assert policy.obs_layout[:8] == ("q1", "q2", "q3", "q4", "q5", "q6", "q7", "gripper_x")


def test_twin_runs_a_panda_through_the_deploy_loop_over_several_scenes(panda_policy) -> None:
    """Scripted 7-joint actions through the loop on the twin's Panda: every scene reaches the grasp pose, closes,
    lifts and holds the cube; the twin reads and is commanded 7 joints (the AUBO's 6 would be refused)."""
    policy = ScriptedPolicy(load_policy(panda_policy))
    cfg = policy.cfg
    kinds = []
    for index in range(3):
        spec, _ = rehearse.draw_scene(cfg, 0, index)
        assert np.shape(spec.q0) == (7,)
        kinds.append(rehearse.episode_kind(spec, cfg))
        with PyBulletTwin(spec, cfg, q0=spec.q0) as twin:
            assert twin.robot.name == "panda" and twin.read_joints().shape == (7,)
            report = run_episode(twin, policy, spec.target_pos, float(spec.target_yaw), obstacles_from_spec(spec))
            assert report.outcome == "success" and report.held is True, (index, report.message, report.grasp)
            assert 10 < report.steps < 100
            with pytest.raises(ValueError, match="7 finite values"):
                twin.command_joint_targets(np.zeros(6))
    assert all(a.shape == (7,) for a in policy.actions)
    assert "obstacle" in kinds  # one of the three scenes has an obstacle (seed 0)


def test_rehearsal_scene_of_a_random_panda_policy(panda_policy) -> None:
    """``rehearse.run_scene`` (the rehearsal's worker) serves the policy's robot: a random-init Panda policy drives
    the twin's Panda under the robot condition's transfer errors, drawn for 7 joints, to an outcome."""
    env_cfg = rehearse.condition_env(load_policy(panda_policy).env_config(), "robot")
    record = rehearse.run_scene(panda_policy, env_cfg, env_cfg, 0, 0)
    assert record["outcome"] in ("timeout", "collision", "refused") and record["held"] is False
    assert 1 <= record["steps"] <= env_cfg.task.max_steps
    errors, _ = transfer.draw(env_cfg.randomize, True, np.random.default_rng(0), PANDA.dof)
    assert len(errors.offsets) == len(errors.servo_gains) == 7 and errors.dof == 7


def test_twin_refuses_errors_and_start_pose_of_another_joint_count(panda_policy) -> None:
    cfg = load_policy(panda_policy).env_config()
    spec, _ = rehearse.draw_scene(cfg, 0, 0)
    with pytest.raises(ValueError, match="transfer errors are for 6 joints; panda has 7"):
        PyBulletTwin(spec, cfg, errors=TransferErrors(latency=1.0))
    with pytest.raises(ValueError, match=r"7 finite joint angles \(panda\)"):
        PyBulletTwin(spec, cfg, q0=np.zeros(6))
    with PyBulletTwin(spec, cfg) as twin:  # the default start is the config's home pose
        np.testing.assert_allclose(twin.true_joints(), cfg.task.home_q, atol=1e-9)


def test_safety_layer_and_constants_are_the_policys_robots(panda_policy) -> None:
    policy = load_policy(panda_policy)
    cfg = policy.env_config()
    check_policy_constants(cfg)  # the Panda's own URDF: accepted
    with pytest.raises(PolicyMismatch, match="trained for the robot 'panda'; this robot is 'aubo_i5'"):
        check_policy_constants(cfg, robot=robot.load_robot("aubo_i5"))
    layer = SafetyLayer(robot=PANDA)
    assert layer.joint_names[6] == "joint 7 (panda_joint7)"
    spec, _ = rehearse.draw_scene(cfg, 0, 0)
    with PyBulletTwin(spec, cfg) as twin:
        with pytest.raises(PolicyMismatch, match="trained for the robot 'panda'; the safety layer guards 'aubo_i5'"):
            run_episode(twin, policy, spec.target_pos, safety=SafetyLayer())


def test_loop_refuses_an_arm_that_reports_another_joint_count(panda_policy) -> None:
    class SixJoints:
        def read_joints(self):
            return np.zeros(6)

    with pytest.raises(DeployError, match=r"expected 7 finite values \(panda\)"):
        run_episode(SixJoints(), load_policy(panda_policy), (0.10, -0.45, 0.025))


def test_a_policy_whose_actions_are_not_its_robots_joints_is_refused(tmp_path) -> None:
    cfg = apply_overrides(get_config("cpu-quick"), ["robot=panda"])
    layout = observation.layout_of(cfg.env)
    weights = [(np.zeros((len(layout), 8), np.float32), np.zeros(8, np.float32)),
               (np.zeros((8, 12), np.float32), np.zeros(12, np.float32))]  # 6 actions
    path = save_policy_npz(tmp_path / "six.npz", weights=weights, activation="tanh", obs_mean=np.zeros(len(layout)),
                           obs_std=np.ones(len(layout)), config=cfg, obs_layout=layout)
    with pytest.raises(PolicyFormatError, match="6 actions, but its robot 'panda' has 7 joints"):
        load_policy(path).check_grasp_inputs()


# ---- the deploy command ----


def _target_cam() -> list[str]:
    top = CameraCalibration.default().base_to_cam(np.array([0.10, -0.45, 0.05]), units="mm")
    return [f"{v:.6f}" for v in top]


def test_deploy_refuses_a_panda_policy_on_the_aubo_driver(panda_policy, tmp_path, capsys) -> None:
    """Exit 2 before anything connects or is written, the message naming both robots."""
    record = tmp_path / "record"
    before = sorted(os.listdir(tmp_path))
    code = deploy_main(["--policy", panda_policy, "--target-cam", *_target_cam(), "--backend", "aubo",
                        "--host", "127.0.0.1", "--json"])
    out, err = capsys.readouterr()
    assert code == 2 and json.loads(out)["outcome"] == "input_refused"
    assert "trained for the robot 'panda'" in err and "--backend aubo drives the 'aubo_i5' only" in err
    assert sorted(os.listdir(tmp_path)) == before and not record.exists()
    code = deploy_main(["--backend", "aubo", "--host", "127.0.0.1", "--dry-run", "--policy", panda_policy])
    err = capsys.readouterr().err
    assert code == 2 and "'panda'" in err and "'aubo_i5'" in err


def test_twin_start_q_takes_one_angle_per_joint_of_the_policys_robot(panda_policy, tmp_path, capsys) -> None:
    aubo_policy = _policy_file(tmp_path, "aubo_i5")
    home7 = [f"{v:.9f}" for v in robots.get("panda").home_q]
    code = deploy_main(["--policy", panda_policy, "--target-cam", *_target_cam(), "--twin-start-q", *home7[:6]])
    err = capsys.readouterr().err
    assert code == 2 and "--twin-start-q takes 7 joint angles (one per joint of panda" in err and "got 6" in err
    code = deploy_main(["--policy", aubo_policy, "--target-cam", *_target_cam(), "--twin-start-q", *home7])
    err = capsys.readouterr().err
    assert code == 2 and "--twin-start-q takes 6 joint angles (one per joint of aubo_i5" in err and "got 7" in err
    code = deploy_main(["--policy", panda_policy, "--target-cam", *_target_cam(), "--twin-joint-offset", *["0"] * 6])
    err = capsys.readouterr().err
    assert code == 2 and "--twin-joint-offset takes one value or one per joint (7 for panda), got 6" in err
    # the right arity is accepted: the Panda's home pose given explicitly, checked through to the ideal arm's plan
    code = deploy_main(["--policy", panda_policy, "--target-cam", *_target_cam(), "--twin-start-q", *home7,
                        "--dry-run", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and out["outcome"] == "dry_run", out
    assert all(len(q) == 7 for q in out["input"]["planned"]["first_commands_rad"])


# ---- system identification of another arm ----


def test_sysid_reads_and_fits_a_seven_joint_log(tmp_path, capsys) -> None:
    """``sysid --robot panda``: a log of the Panda's own lagged servo model (no latency, known offsets) gives back
    its gains and offsets, and overrides that training accepts on the Panda (led by robot=panda)."""
    from sagrasp_jax.deploy import sysid
    from sagrasp_jax.task import control

    cfg = sysid.robot_control("panda")
    rng = np.random.default_rng(0)
    steps, offset = 300, np.linspace(-0.003, 0.003, 7)
    t = np.arange(steps)[:, None] * cfg.control_dt  # sweeps of ±0.2 rad about the home pose (inside every limit)
    command = np.asarray(robots.get("panda").home_q) + 0.1 * (np.sin(2.1 * t + rng.uniform(0, 6, 7))
                                                              + np.sin(5.3 * t * rng.uniform(0.5, 1.5, 7)))
    x = x_prev = command[0].copy()
    readings = np.empty((steps, 7))
    for t in range(steps):
        readings[t] = x + offset
        x, x_prev = control.servo_model_step(np, PANDA, cfg, x, x_prev, command[t], np.asarray(cfg.lag_gain)), x
    header = ",".join(sysid.columns(7))
    assert header.endswith("cmd_q7,q1,q2,q3,q4,q5,q6,q7")
    log = tmp_path / "panda.csv"
    log.write_text(header + "\n" + "".join(",".join(repr(float(v)) for v in (t * cfg.control_dt, *c, *y)) + "\n"
                                         for t, (c, y) in enumerate(zip(command, readings))))
    out = tmp_path / "sysid.json"
    assert sysid.main(["--log", str(log), "--out", str(out), "--robot", "panda"]) == 0
    report = json.loads(out.read_text())
    np.testing.assert_allclose(report["lag_gain"], cfg.lag_gain, atol=0.01)
    np.testing.assert_allclose(report["joint_offset"], offset, atol=0.001)
    assert report["overrides"][0] == "robot=panda"
    trained = apply_overrides(get_config("cpu-quick"), report["overrides"])
    assert trained.env.robot == "panda" and len(trained.env.control.lag_gain) == 7
    # the same log read as the default robot's (6 joints) is refused naming the columns
    assert sysid.main(["--log", str(log), "--out", str(tmp_path / "aubo.json")]) == 2
    assert "columns must be" in capsys.readouterr().err and not (tmp_path / "aubo.json").exists()
