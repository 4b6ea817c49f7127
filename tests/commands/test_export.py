"""Export: policy.npz + policy.onnx from a run folder; NumPy, ONNX and JAX give the same actions."""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from sagrasp_jax import export
from sagrasp_jax.task.config import get_config
from sagrasp_jax.task.config_history import config_hash
from sagrasp_jax.task.config_parse import config_from_dict
from sagrasp_jax.task import observation
from sagrasp_jax.task.policy_file import load_policy, save_policy_npz
from tiny_run import REPO, tiny_run

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")


@pytest.fixture(scope="session")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> str:
    return tiny_run(str(tmp_path_factory.getbasetemp()))


@pytest.fixture(scope="module")
def exported(run_dir: str, tmp_path_factory: pytest.TempPathFactory) -> str:
    """The export CLI run once on the tiny run."""
    out = str(tmp_path_factory.mktemp("export") / "policy")
    res = subprocess.run([sys.executable, "-m", "sagrasp_jax.export", "--run", run_dir, "--out", out],
                         capture_output=True, text=True, timeout=300, cwd=REPO)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "max |Δaction|" in res.stdout
    return out


def test_cli_writes_npz_onnx_and_manifest(exported: str, run_dir: str) -> None:
    assert sorted(os.listdir(exported)) == ["export.json", "policy.npz", "policy.onnx"]  # no temp files left
    with open(os.path.join(run_dir, "config.json")) as f:
        cfg = config_from_dict(json.load(f))
    policy = load_policy(os.path.join(exported, "policy.npz"))
    assert policy.obs_layout == observation.layout_of(cfg.env) and len(policy.obs_layout) == 35  # relative_lag layout
    assert policy.config_hash == config_hash(cfg)
    assert policy.package_version == sagrasp_jax.__version__
    assert policy.action_scale == cfg.env.control.q_max
    assert [w.shape[1] for w, _ in policy.weights[:-1]] == list(cfg.ppo.network.policy_hidden)
    with open(os.path.join(exported, "export.json")) as f:
        manifest = json.load(f)
    assert manifest["config_hash"] == policy.config_hash
    assert manifest["finished"] is True and manifest["checkpoint_env_steps"] == 1024
    assert manifest["obs_layout"] == list(policy.obs_layout)
    assert manifest["onnx_check"]["observations"] == 1000
    assert manifest["onnx_check"]["max_abs_action_diff"] < 1e-5
    for name in ("policy.npz", "policy.onnx"):
        assert manifest["files"][name]["bytes"] == os.path.getsize(os.path.join(exported, name))


def test_onnx_graph_is_plain_opset17_with_metadata(exported: str) -> None:
    model = onnx.load(os.path.join(exported, "policy.onnx"))
    onnx.checker.check_model(model, full_check=True)
    assert {o.domain: o.version for o in model.opset_import}[""] >= 17
    assert [i.name for i in model.graph.input] == ["obs"] and [o.name for o in model.graph.output] == ["action"]
    dims = [d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim]
    assert dims[1] == 35
    meta = {p.key: p.value for p in model.metadata_props}
    policy = load_policy(os.path.join(exported, "policy.npz"))
    assert meta["config_hash"] == policy.config_hash
    assert meta["obs_layout"].split(",") == list(policy.obs_layout)
    ops = {n.op_type for n in model.graph.node}
    assert {"Sub", "Div", "Clip", "MatMul", "Add", "Tanh"} == ops


def test_npz_onnx_and_jax_actions_agree(exported: str, run_dir: str) -> None:
    """1,000 observations: the NumPy runtime, onnxruntime and actor_critic.deterministic_action (same params and
    normaliser, from the run's checkpoint) agree within 1e-5."""
    import jax.numpy as jnp

    from sagrasp_jax.training.agents.ppo import actor_critic

    policy = load_policy(os.path.join(exported, "policy.npz"))
    obs = export.check_observations(policy, 1000, seed=7)
    a_npz = policy(obs)
    a_onnx = export.onnx_actions(os.path.join(exported, "policy.onnx"), obs)
    cfg, params, normaliser, _ = export.load_run(run_dir)
    networks = actor_critic.make_networks(cfg.ppo.network, 17, 6, cfg.ppo.obs_clip)
    a_jax = np.asarray(actor_critic.deterministic_action(networks, params, normaliser, jnp.asarray(obs, jnp.float32)))
    assert a_npz.shape == a_onnx.shape == a_jax.shape == (1000, 6)
    assert np.abs(a_npz).max() > 0.05  # a trivial all-zero policy would agree trivially
    diffs = {
        "npz-onnx": float(np.abs(a_npz - a_onnx).max()),
        "npz-jax": float(np.abs(a_npz - a_jax).max()),
        "onnx-jax": float(np.abs(a_onnx - a_jax).max()),
    }
    print("max |Δaction| over 1000 observations:", diffs)
    assert max(diffs.values()) < 1e-5, diffs


@pytest.mark.parametrize("activation", ["tanh", "relu", "silu", "elu"])
def test_onnx_matches_npz_for_every_activation(tmp_path, activation: str) -> None:
    rng = np.random.default_rng(3)
    sizes = (17, 24, 16, 12)
    weights = [(rng.normal(0, 1 / np.sqrt(i), (i, o)).astype(np.float32), rng.normal(0, 0.2, o).astype(np.float32))
               for i, o in zip(sizes[:-1], sizes[1:])]
    path = save_policy_npz(tmp_path / "p.npz", weights=weights, activation=activation, obs_mean=rng.normal(0, 0.5, 17),
                           obs_std=rng.uniform(0.0, 1.0, 17), config=get_config("paper"))
    policy = load_policy(path)
    onnx_path = export.write_onnx(policy, str(tmp_path / "p.onnx"))
    obs = export.check_observations(policy, 500, seed=1)
    assert np.abs(export.onnx_actions(onnx_path, obs) - policy(obs)).max() < 1e-5


def test_cli_refuses_missing_and_corrupt_runs(run_dir: str, tmp_path, capsys) -> None:
    out = tmp_path / "out"

    def cli(run: object) -> str:
        assert export.main(["--run", str(run), "--out", str(out)]) == 2
        return capsys.readouterr().err

    assert "nope: run folder not found" in cli(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    assert "not a run folder (no config.json)" in cli(tmp_path / "empty")
    (tmp_path / "file").write_text("x")
    assert "not a folder" in cli(tmp_path / "file")

    broken = tmp_path / "broken"
    shutil.copytree(run_dir, broken)
    ckpt = broken / "checkpoint.ckpt"
    ckpt.write_bytes(ckpt.read_bytes()[:-100])
    assert "truncated checkpoint" in cli(broken)
    ckpt.unlink()
    assert "no checkpoint found" in cli(broken)
    assert not out.exists() or not os.listdir(out)  # nothing half-written


def test_failed_onnx_build_leaves_previous_export_intact(exported: str, run_dir: str, tmp_path, monkeypatch) -> None:
    out = tmp_path / "policy"
    shutil.copytree(exported, out)
    before = (out / "policy.onnx").read_bytes()

    def broken(*_a, **_k):
        raise export.ExportError("simulated failure while building the graph")

    monkeypatch.setattr(export, "onnx_model", broken)
    with pytest.raises(export.ExportError, match="simulated failure"):
        export.export_run(run_dir, str(out))
    assert (out / "policy.onnx").read_bytes() == before
    assert sorted(os.listdir(out)) == ["export.json", "policy.npz", "policy.onnx"]
