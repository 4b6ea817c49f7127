"""The arm's joint count is one fact, ``robot.ARM_DOF`` (= len(ARM_JOINTS)), read from the robot description
(issue 56, item 1): no module states it again as a literal 6, so a robot with another joint count (a 7-DoF
Franka Panda) changes ARM_JOINTS and nothing else.  The scan reads the package's source for the shapes a
literal joint count took in the old code and fails naming file:line; the 6s that are not joint counts (a box's
6 faces, the camera intrinsics' 6 numbers, a hand-eye pair's 6 columns) are allowed by name below, and so are
any joint counts left in training/ named in PENDING_IN_TRAINING (none now)."""

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from sagrasp_jax.task import robot, robots
from tests.paths import REPO

PACKAGE = Path(REPO) / "sagrasp_jax"

# The shapes a literal joint count took: shapes, loops, eyes, zeros, CLI arity, DoF constants, repetitions,
# qpos/qvel slices and comparisons with a model's joint count.
JOINT_COUNT_LITERALS = re.compile(
    r"\(6,\)|(?<![\w.])\((?:[\w.]+, )+6\)|range\(6\)|range\(1, 7\)|nargs=6|eye\(6\b|zeros\(6\)|empty\(6\)|size=6\b|normal\(6\)"
    r"|reshape\(6\)|DOF\s*=\s*6\b|\]\s*\*\s*6\b|,\)\s*\*\s*6\b|\[(?:\.\.\., |:, )?:6\]|!= 6\b|\(1, 6\)\)"
    r"|\b(?:n_actions|action_size|dof)\s*(?::\s*int)?\s*=\s*6\b"
)

# (path, text on the line) of the 6s that are not joint counts, each with why.
NOT_JOINT_COUNTS = {
    ("task/camera.py", "if v.shape != (6,)"): "the intrinsics' 6 numbers [width, height, fx, fy, cx, cy]",
    ("deploy/capture_file.py", "``intrinsics``  float64 (6,)"): "the intrinsics' 6 numbers",
    ("task/geometry.py", "for k in range(6):"): "a box pair's 6 face normals",
    ("calibrate.py", "order = list(range(6))"): "a hand-eye pair's 6 columns",
    ("calibrate.py", "if len(row) != 6:"): "a hand-eye pair's 6 columns",
}
# Joint counts still literal in training/, left while issue 56's parallel work there (the learning-rate plumbing)
# lands: each should take the action count from the env (or robots.DEFAULT_DOF where a library call names no robot).
PENDING_IN_TRAINING: dict[tuple[str, str], str] = {}  # none left


def _write_lines(root: Path, lines: dict[str, str]) -> None:
    """One file per entry under ``root``, its line second (the scans' line numbers then read 2)."""
    for rel, line in lines.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(f"x = 1\n{line}\n")


def joint_count_literals(root: Path) -> list[str]:
    """``path:line: text`` of every joint-count literal under ``root`` (a package tree) not allowed by name."""
    found = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if JOINT_COUNT_LITERALS.search(line) and not any(
                    rel == where and text in line for where, text in {**NOT_JOINT_COUNTS, **PENDING_IN_TRAINING}):
                found.append(f"{rel}:{number}: {line.strip()}")
    return found


def test_no_literal_joint_count_in_the_package():
    found = joint_count_literals(PACKAGE)
    assert not found, "a literal joint count; use robot.ARM_DOF (or RobotModel.dof):\n" + "\n".join(found)


def test_the_scan_sees_the_old_shapes(tmp_path):
    """The scan is not vacuous: each shape the old code used is found, a 6 that is no joint count is not."""
    old = {
        "deploy/aubo.py": "    if q.shape != (6,) or not np.isfinite(q).all():",
        "task/scripted.py": "    eye = xp.eye(6, dtype=q.dtype)",
        "deploy/__main__.py": '    p.add_argument("--twin-start-q", nargs=6, type=float)',
        "deploy/transfer.py": "ARM_DOF = 6",
        "deploy/sysid.py": "    for j in range(6):",
        "training/evaluation.py": "    ARM_DOF = 6",
        "training/ppo.py": "def loss(action_size=6):",
        "envs/grasp_env.py": "        return pipeline, pipeline.qpos[:6].astype(dtype), {}",
        "deploy/twin.py": "        v = [0.0] * 6 if velocity is None else velocity",
        "task/robot.py": "        jac = np.zeros((n, 6))",
        "task/observation.py": 'PENDING = tuple(f"pending{j}" for j in range(1, 7))',
        "training/sa_schedule.py": "def t(n_actions: int = 6):",
    }
    _write_lines(tmp_path, old)
    (tmp_path / "task").joinpath("camera.py").write_text("if v.shape != (6,) or bad:\n")  # allowed by name
    (tmp_path / "export.py").write_text("keys = jax.random.split(key, 6)\nz = zlib.compress(raw, 6)\n")  # calls
    found = joint_count_literals(tmp_path)
    assert sorted(f.split(":")[0] for f in found) == sorted(old)
    assert all(f.split(":")[1] == "2" for f in found)


def test_the_joint_count_comes_from_the_robot_description():
    model = robot.load_robot()
    assert robot.ARM_DOF == len(robot.ARM_JOINTS) == 6  # the AUBO-i5
    assert model.dof == robot.ARM_DOF == robots.get("aubo_i5").dof == robots.DEFAULT_DOF
    assert model.joint_origins.shape == (robot.ARM_DOF, 4, 4) and len(model.link_names) == robot.ARM_DOF + 1


def test_kinematics_follow_the_models_joint_count():
    """forward_kinematics loops over the model's joints, not a fixed 6: a model cut to its first 5 joints gives
    5 joint frames (what a robot with another joint count relies on)."""
    model = robot.load_robot()
    q = np.full(robot.ARM_DOF, 0.1)
    full = robot.forward_kinematics(np, model, q)
    assert full.joint_pos.shape == (robot.ARM_DOF, 3)
    cut = dataclasses.replace(model, joint_origins=model.joint_origins[:5])
    assert cut.dof == 5
    short = robot.forward_kinematics(np, cut, q[:5])
    assert short.joint_pos.shape == (5, 3)
    np.testing.assert_allclose(short.joint_pos, full.joint_pos[:5], atol=1e-12)


# What the layers above the env must not read: the default robot's constants and a robot loaded without a name
# (issue 56, item 1: they take the model from the config or the policy, or a RobotModel argument).
DEFAULT_ROBOT_USES = re.compile(r"\b(?:ARM_DOF|ARM_JOINTS|FINGER_JOINTS|HOME_Q|URDF_PATH)\b"
                                r"|assets\.(?:MJCF_SCENE|MJCF_ROBOT|URDF)\b|load_robot\(\)")
# A library helper's fallback for callers that name no robot (every caller in the package passes one).
DEFAULT_FALLBACKS = ("or load_robot()", "or robot_mod.load_robot()", 'differ from robot.load_robot()"')
BELOW_THE_CONFIG = ("task/", "envs/", "base/")  # the registry, the config and the MJX env that reads env.robot
AUBO_ONLY = ("deploy/aubo.py",)  # the AUBO controller's driver: its joints are the AUBO-i5's


def default_robot_uses(root: Path) -> list[str]:
    """``path:line: text`` of every read of the default robot above the env under ``root`` (a package tree)."""
    found = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if rel.startswith(BELOW_THE_CONFIG) or rel in AUBO_ONLY:
            continue
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            stripped = line
            for allowed in DEFAULT_FALLBACKS:
                stripped = stripped.replace(allowed, "")
            if DEFAULT_ROBOT_USES.search(stripped):
                found.append(f"{rel}:{number}: {line.strip()}")
    return found


def test_no_layer_above_the_env_reads_the_default_robot():
    found = default_robot_uses(PACKAGE) + default_robot_uses(Path(REPO) / "experiments")
    assert not found, ("the default robot read above the env; load robot.load_robot(env_cfg.robot) from the config "
                       "or the policy, or take a RobotModel:\n" + "\n".join(found))


def test_the_default_robot_scan_sees_the_old_uses(tmp_path):
    old = {
        "deploy/twin.py": "        self.arm_joints = [joints[n] for n in robot_mod.ARM_JOINTS]",
        "deploy/loop.py": "    model = load_robot()",
        "reference/grasp_check.py": "SCENE_XML = assets.MJCF_SCENE",
        "deploy/__main__.py": "from sagrasp_jax.task.config import HOME_Q",
        "experiments/bench_env.py": "        arm = pb.loadURDF(robot.URDF_PATH, useFixedBase=True)",
    }
    _write_lines(tmp_path, old)
    (tmp_path / "deploy" / "aubo.py").write_text("ARM_DOF = robots.AUBO_I5.dof\n")  # the driver: allowed
    (tmp_path / "deploy" / "safety.py").write_text("        self.robot = robot or load_robot()\n")  # a fallback
    (tmp_path / "task").mkdir()
    (tmp_path / "task" / "config.py").write_text("HOME_Q = robots.AUBO_I5.home_q\n")  # below the config
    assert sorted(f.split(":")[0] for f in default_robot_uses(tmp_path)) == sorted(old)


if __name__ == "__main__":
    pytest.main([__file__, "-q"])
