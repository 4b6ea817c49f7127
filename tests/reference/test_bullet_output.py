"""PyBullet's native chatter stays off the terminal: the twin commands print no ``b3Warning`` / "No inertial data"
lines nor the import banner, ``--json`` stays JSON on stdout, and a real PyBullet message still reaches stderr."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from tiny_run import REPO

pytest.importorskip("pybullet", reason="the twin extra (pybullet) is not installed")

from sagrasp_jax.reference import bullet  # noqa: E402

NOISE = ("b3Warning", "No inertial data", "pybullet build time")
HEADER = "b3Warning[examples/Importers/ImportURDFDemo/BulletUrdfImporter.cpp,126]:\n"
INERTIAL = "No inertial data for link, using mass=1, localinertiadiagonal = 1,1,1, identity local inertial frame"
# What pybullet 3.2 printed loading the project's URDF and then a missing file, byte for byte.
RAW = (f"pybullet build time: Jan 29 2025 23:17:20\n{HEADER}{INERTIAL}{HEADER}flange{HEADER}{INERTIAL}{HEADER}gripper_center"
       "b3Warning[examples/Importers/ImportURDFDemo/BulletUrdfImporter.cpp,152]:\nURDF file '/x.urdf' not found\n")


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=300, cwd=REPO)


def test_filter_drops_only_the_known_harmless_messages() -> None:
    kept = "b3Warning[examples/Importers/ImportURDFDemo/BulletUrdfImporter.cpp,152]:\nURDF file '/x.urdf' not found\n"
    assert bullet.filter_native_output(RAW, ("flange", "gripper_center")) == kept
    assert bullet.filter_native_output(RAW) == kept  # without the URDF's links: any name-like message after the warning
    # a link the URDF does not list as frame-only is not dropped, nor is what follows a link name on its line
    assert bullet.filter_native_output(f"{HEADER}{INERTIAL}{HEADER}elbow", ("flange",)) == f"{HEADER}elbow"
    assert bullet.filter_native_output(f"{HEADER}{INERTIAL}{HEADER}flangeerror: out of memory\n", ("flange",)) == \
        "error: out of memory\n"
    assert bullet.filter_native_output("a line\nb3Error[x.cpp,1]:\nbroken\n") == "a line\nb3Error[x.cpp,1]:\nbroken\n"


def test_deploy_json_on_the_twin_is_quiet_and_valid() -> None:
    res = _run("-m", "sagrasp_jax.deploy", "--policy", "pretrained", "--target-cam", "-147", "-77", "1374", "--units",
               "mm", "--json")
    assert res.returncode == 0, res.stderr[-3000:]
    report = json.loads(res.stdout)  # stdout is the report alone
    assert report["outcome"] == "success"
    for noise in NOISE:
        assert noise not in res.stdout and noise not in res.stderr, (noise, res.stderr[-2000:])


def test_rehearse_and_the_reference_env_are_quiet() -> None:
    res = _run("-m", "sagrasp_jax.deploy.rehearse", "--policy", "pretrained", "--episodes", "2", "--workers", "1")
    assert res.returncode == 0, res.stderr[-3000:]
    assert "cube held" in res.stdout
    code = ("import gymnasium as gym, sagrasp_jax.reference; env = gym.make('SAGrasp-PyBullet-v0'); env.reset(seed=0); "
            "env.close(); print('ok')")
    env = _run("-c", code)
    assert env.returncode == 0 and env.stdout == "ok\n", env.stderr[-3000:]
    for out in (res.stdout, res.stderr, env.stderr):
        for noise in NOISE:
            assert noise not in out, (noise, out[-2000:])


def test_a_real_message_still_reaches_stderr() -> None:
    """A URDF that is not there: PyBullet's own warning saying so passes (on stderr), the error is raised; what
    Python or C code prints on stdout inside the filtered block goes to stderr too, stdout keeps what follows."""
    code = (
        "import os\n"
        "from sagrasp_jax.reference import bullet\n"  # imports pybullet, its banner filtered
        "import pybullet as pb\n"
        "from sagrasp_jax.task.robot import URDF_PATH\n"
        "client = bullet.connect(pb.DIRECT)\n"
        "bullet.load_urdf(client, URDF_PATH, useFixedBase=True)\n"
        "try:\n"
        "    bullet.load_urdf(client, '/nonexistent/arm.urdf')\n"
        "except pb.error as exc:\n"
        "    print('raised:', exc)\n"
        "with bullet.native_output_filtered():\n"
        "    os.write(1, b'native line\\n')\n"
        "    print('python line')\n"
        "print('report')\n"
    )
    res = _run("-c", code)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout == "raised: Cannot load URDF file.\nreport\n"
    assert "URDF file '/nonexistent/arm.urdf' not found" in res.stderr
    assert "native line\n" in res.stderr and "python line\n" in res.stderr
    assert "No inertial data" not in res.stderr and "pybullet build time" not in res.stderr
