"""Installs as a user gets them, outside this checkout.

* The wheel (``pip wheel --no-deps``) carries the URDF and the MJCF and names numpy as its only
  required dependency.
* ``[train,twin]`` installed non-editable into a fresh venv (the heavy packages come from this
  interpreter's site-packages through a path file, so jax is not downloaded again; the package
  itself is the wheel's copy): a tiny training, its export and a deploy on the twin, all run from
  a folder outside the repository.
* The core alone in a fresh venv without any other site-packages (pip installs numpy): jax,
  jaxlib, mujoco, brax, gymnasium and pybullet are absent, the deployment loop runs a scripted
  ``RobotInterface``, commands that need an extra exit 2 naming it; then ``[twin]`` adds pybullet
  and deploy runs on the twin.

Needs pip to reach a package index (numpy, pybullet, tensorboard, setuptools for the build).
"""

from __future__ import annotations

import glob
import json
import os
import shutil
import site
import subprocess
import sys
import zipfile

import pytest

from tiny_run import REPO, TINY_ARGS

LEGACY_POLICY = os.path.join(REPO, "tests", "data", "legacy_v0_1", "policy_cpu_quick_3M.npz")
DEPLOY_ARGS = ["--target-cam", "-147", "-77", "1374", "--units", "mm", "--json"]
HEAVY = ("jax", "jaxlib", "mujoco", "brax", "flax", "optax", "gymnasium", "pybullet")


def run(cmd: list[str], cwd: str, timeout: float = 600, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env=env if env is not None else clean_env())


def clean_env() -> dict[str, str]:
    """No PYTHONPATH: the venvs must find the installed copy, not this checkout."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}


def pip(python: str, *args: str) -> None:
    res = run([sys.executable, "-m", "pip", "--python", python, "install", "-q", "--disable-pip-version-check", *args],
              cwd=REPO, timeout=900)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]


def new_venv(path: str) -> str:
    res = run([sys.executable, "-m", "venv", "--without-pip", path], cwd=REPO)
    assert res.returncode == 0, res.stderr
    return os.path.join(path, "bin", "python")


def site_packages(python: str) -> str:
    res = run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd="/")
    return res.stdout.strip()


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> str:
    """The wheel built from a copy of the package sources (no stale build/ of the checkout)."""
    base = tmp_path_factory.mktemp("wheel")
    src = base / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(os.path.join(REPO, name), src / name)
    shutil.copytree(os.path.join(REPO, "sagrasp_jax"), src / "sagrasp_jax",
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    res = run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(base / "dist"), str(src)], cwd=str(base),
              timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    (path,) = glob.glob(str(base / "dist" / "sagrasp_jax-*.whl"))
    return path


def test_the_wheel_ships_the_robot_and_needs_only_numpy(wheel):
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        (meta,) = [n for n in names if n.endswith(".dist-info/METADATA")]
        metadata = z.read(meta).decode()
    assert {"sagrasp_jax/urdf/aubo_i5_eg2.urdf", "sagrasp_jax/mjcf/scene.xml", "sagrasp_jax/mjcf/aubo_i5_eg2.xml",
            "sagrasp_jax/pretrained/cpu_quick_s0.npz", "sagrasp_jax/pretrained/cpu_quick_s0.json"} <= names
    required = [line for line in metadata.splitlines() if line.startswith("Requires-Dist:") and "extra ==" not in line]
    assert len(required) == 1 and required[0].startswith("Requires-Dist: numpy"), required
    extras = {line.split(":", 1)[1].strip() for line in metadata.splitlines() if line.startswith("Provides-Extra:")}
    assert {"train", "twin", "reference", "export", "render", "warp", "baseline", "plots", "test"} <= extras


def test_extras_in_pyproject():
    """The test extra holds everything the train extra does; the twin is pybullet alone; the core is numpy."""
    import tomllib

    with open(os.path.join(REPO, "pyproject.toml"), "rb") as f:
        project = tomllib.load(f)["project"]
    extras = project["optional-dependencies"]
    assert project["dependencies"] == ["numpy>=2.0,<2.5"]
    assert set(extras["train"]) <= set(extras["test"]) and set(extras["reference"]) <= set(extras["test"])
    assert [r.split(">")[0] for r in extras["twin"]] == ["pybullet"]
    assert any(r.startswith("tensorboard>") for r in extras["train"])


def _outside(tmp_path_factory: pytest.TempPathFactory, name: str) -> str:
    work = str(tmp_path_factory.mktemp(name))
    assert not os.path.realpath(work).startswith(os.path.realpath(REPO) + os.sep)
    return work


def test_wheel_with_train_and_twin_trains_exports_and_deploys_outside_the_repo(wheel, tmp_path_factory):
    work = _outside(tmp_path_factory, "train_venv")
    python = new_venv(os.path.join(work, "venv"))
    # this interpreter's packages (jax, mujoco, ...) without its own sagrasp_jax (an editable install)
    shared = os.path.join(work, "shared-site")
    os.makedirs(shared)
    for parent in site.getsitepackages():
        for entry in os.listdir(parent):
            if entry.startswith(("sagrasp_jax", "__editable__", "_sagrasp")) or entry.endswith(".pth") or \
                    os.path.exists(os.path.join(shared, entry)):
                continue
            os.symlink(os.path.join(parent, entry), os.path.join(shared, entry))
    with open(os.path.join(site_packages(python), "shared-site.pth"), "w") as f:
        f.write(shared + "\n")
    pip(python, f"{wheel}[train,twin]")

    res = run([python, "-c", "import sagrasp_jax, tensorboard; print(sagrasp_jax.__file__)"], cwd=work)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().startswith(os.path.join(work, "venv")), res.stdout  # the wheel's copy
    res = run([python, "-m", "sagrasp_jax.train", "--out", "run", *TINY_ARGS], cwd=work)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    # the console script, ONNX included: [train] brings export's packages
    res = run([os.path.join(work, "venv", "bin", "sagrasp-export"), "--run", "run", "--out", "policy"], cwd=work)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert os.path.isfile(os.path.join(work, "policy", "policy.onnx")), os.listdir(os.path.join(work, "policy"))
    res = run([python, "-m", "sagrasp_jax.deploy", "--policy", "policy/policy.npz", *DEPLOY_ARGS], cwd=work)
    assert res.returncode in (0, 1), res.stdout[-3000:] + res.stderr[-3000:]  # success, or a tiny policy's timeout
    assert json.loads(res.stdout)["outcome"] in ("success", "timeout", "collision")


SCRIPTED_DEPLOY = r'''
import sys
import numpy as np
from sagrasp_jax.deploy import run_episode
from sagrasp_jax.task.policy_file import load_policy

class ScriptedRobot:
    """A RobotInterface that tracks every joint target exactly (the AUBO's precise tracking)."""
    def __init__(self, q0):
        self.q, self.commands, self.gripper = np.array(q0, float), 0, []
    def read_joints(self):
        return self.q.copy()
    def command_joint_targets(self, q):
        self.q, self.commands = np.array(q, float), self.commands + 1
    def open_gripper(self):
        self.gripper.append("open")
    def close_gripper(self):
        self.gripper.append("close")

policy = load_policy(sys.argv[1])
robot = ScriptedRobot(policy.env_config().task.home_q)
report = run_episode(robot, policy, np.array([0.10, -0.45, 0.025]), 0.0)
heavy = [m for m in ("jax", "jaxlib", "mujoco", "brax", "flax", "optax", "gymnasium", "pybullet") if m in sys.modules]
print(report.outcome, report.steps, robot.commands, ",".join(robot.gripper), "heavy:" + ",".join(heavy))
'''


def test_core_install_is_numpy_only_and_deploys(wheel, tmp_path_factory):
    work = _outside(tmp_path_factory, "core_venv")
    python = new_venv(os.path.join(work, "venv"))
    pip(python, wheel)  # numpy comes with it, nothing else
    probe = f"import importlib.util as u; print([m for m in {HEAVY!r} if u.find_spec(m)])"
    res = run([python, "-c", probe], cwd=work)
    assert res.returncode == 0 and res.stdout.strip() == "[]", res.stdout + res.stderr

    shutil.copy(LEGACY_POLICY, os.path.join(work, "policy.npz"))
    with open(os.path.join(work, "scripted.py"), "w") as f:
        f.write(SCRIPTED_DEPLOY)
    res = run([python, "scripted.py", "policy.npz"], cwd=work)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    outcome, steps, commands, gripper, heavy = res.stdout.split()
    assert outcome == "success" and int(steps) < 60 and int(commands) > int(steps), res.stdout
    assert gripper == "close" and heavy == "heavy:", res.stdout  # after the success: close, then lift

    res = run([python, "-m", "sagrasp_jax"], cwd=work)  # the command list, in a core install too
    assert res.returncode == 0 and "sagrasp_jax[" in res.stdout and "  plot " in res.stdout, res.stdout + res.stderr
    res = run([python, "-c", "from sagrasp_jax import envs; envs.load('grasp-kinematic')"], cwd=work)
    assert res.returncode == 1 and "ModuleNotFoundError" not in res.stderr, res.stderr
    assert res.stderr.strip().splitlines()[-1].endswith('which are not installed: pip install "sagrasp_jax[train]"')

    # what needs an extra says which, in wheel syntax, with exit 2 (deploy: before anything moves)
    res = run([python, "-m", "sagrasp_jax.deploy", "--policy", "policy.npz", *DEPLOY_ARGS], cwd=work)
    assert res.returncode == 2 and 'pip install \\"sagrasp_jax[twin]\\"' in res.stdout, res.stdout + res.stderr
    assert json.loads(res.stdout)["outcome"] == "input_refused"
    for module in ("train", "evaluate"):
        res = run([python, "-m", f"sagrasp_jax.{module}", "--help"], cwd=work)
        assert res.returncode == 2 and 'pip install "sagrasp_jax[train]"' in res.stderr, res.stderr
        assert "Traceback" not in res.stderr
    res = run([python, "-m", "sagrasp_jax.export", "--run", "r", "--out", "o"], cwd=work)
    assert res.returncode == 2 and 'pip install "sagrasp_jax[train]"' in res.stderr and "Traceback" not in res.stderr

    pip(python, f"{wheel}[twin]")  # pybullet only
    res = run([python, "-c", probe], cwd=work)
    assert res.stdout.strip() == "['pybullet']", res.stdout + res.stderr
    res = run([python, "-m", "sagrasp_jax.deploy", "--policy", "policy.npz", *DEPLOY_ARGS], cwd=work)
    assert res.returncode in (0, 1), res.stdout[-3000:] + res.stderr[-3000:]  # 0.1's policy: the pose, held or not
    assert json.loads(res.stdout)["outcome"] == "success"
    # the pretrained policy shipped in the wheel, by name: a core + [twin] install deploys without training
    res = run([python, "-m", "sagrasp_jax.deploy", "--policy", "pretrained", *DEPLOY_ARGS], cwd=work)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    report = json.loads(res.stdout)
    assert report["outcome"] == "success" and report["held"] is True, report
