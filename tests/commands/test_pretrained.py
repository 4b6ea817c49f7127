"""The pretrained policy shipped in the package: found by name, the file its provenance names, usable by deploy."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from sagrasp_jax.task.policy_file import PRETRAINED, PolicyFormatError, load_policy, pretrained_path, pretrained_provenance
from tiny_run import REPO


def test_pretrained_policy_by_name_is_the_file_its_provenance_names() -> None:
    for name in PRETRAINED:
        policy = load_policy(name)
        prov = pretrained_provenance(name)
        with open(pretrained_path(name), "rb") as fh:
            assert hashlib.sha256(fh.read()).hexdigest() == prov["policy_sha256"]
        assert policy.path == pretrained_path(name)
        assert policy.env_config().task.obs_layout == "relative_lag"
        assert "--seed 0" in prov["training_command"] and prov["config_identity"] == "b3d87b3b19f173a7"
        measured = prov["measured"]
        assert measured["mjx_robot_success"] >= 0.99 and measured["twin_robot_held"] >= 0.98, measured
    action = load_policy("pretrained")(np.zeros(load_policy("pretrained").obs_size))
    assert action.shape == (6,) and np.all(np.abs(action) <= 1)


def test_a_name_is_the_packaged_policy_whatever_the_folder_holds(tmp_path, monkeypatch) -> None:
    """Issue 54: a file or folder named ``pretrained`` in the working folder no longer shadows the packaged
    policy; it is read only when given as a path (``./pretrained``).  An unknown name says what exists."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(PolicyFormatError, match="pretrained policy's name: cpu-quick-s0, pretrained"):
        load_policy("no-such-policy")
    (tmp_path / "pretrained").write_bytes(b"not a zip")
    assert load_policy("pretrained").path == pretrained_path("pretrained")
    with pytest.raises(PolicyFormatError, match="not a readable .npz"):
        load_policy("./pretrained")
    os.unlink(tmp_path / "pretrained")
    os.mkdir(tmp_path / "pretrained")  # a run folder of that name, say
    assert load_policy("pretrained").path == pretrained_path("pretrained")
    with pytest.raises(PolicyFormatError, match=r"^\./pretrained is a folder without a policy.npz"):
        load_policy("./pretrained")
    shutil.copy(pretrained_path("pretrained"), tmp_path / "pretrained" / "policy.npz")  # a folder means its policy
    assert load_policy("./pretrained").path == os.path.join(".", "pretrained", "policy.npz")


def test_deploy_runs_the_pretrained_policy_by_name() -> None:
    from sagrasp_jax.deploy.calibration import CameraCalibration

    pytest.importorskip("pybullet")
    top = CameraCalibration.default().base_to_cam(np.array([0.10, -0.45, 0.05]), units="mm")
    res = subprocess.run([sys.executable, "-m", "sagrasp_jax.deploy", "--policy", "pretrained", "--target-cam",
                          *[f"{v:.4f}" for v in top], "--json"], capture_output=True, text=True, timeout=300,
                         cwd=REPO)
    report = json.loads(res.stdout)
    assert res.returncode == 0 and report["held"] is True, res.stderr[-2000:]
    assert report["outcome"] == "success" and report["steps"] < 60
