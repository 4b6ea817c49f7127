"""NumPy policy runtime and the policy.npz format (deployment runs without JAX)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from sagrasp_jax.task.config import Config, get_config
from sagrasp_jax.task.config_history import config_hash
from sagrasp_jax.task.policy_file import (
    FORMAT_VERSION,
    OBS_LAYOUT,
    NumpyPolicy,
    PolicyFormatError,
    load_policy,
    save_policy_npz,
)
from paths import REPO  # noqa: E402

OBS, ACT = 17, 6


def _random_policy(rng: np.random.Generator, hidden: tuple[int, ...] = (32, 24)) -> dict:
    sizes = (OBS, *hidden, 2 * ACT)
    weights = [
        (rng.normal(0, 1 / np.sqrt(i), (i, o)).astype(np.float32), rng.normal(0, 0.1, o).astype(np.float32))
        for i, o in zip(sizes[:-1], sizes[1:])
    ]
    mean = rng.normal(0, 0.5, OBS)
    std = rng.uniform(0.05, 1.0, OBS)
    std[11] = 0.0  # target z is constant in training: the writer must floor it
    return {"weights": weights, "obs_mean": mean, "obs_std": std}


def _reference_forward(parts: dict, activation: str, obs: np.ndarray, floor: float, clip: float) -> np.ndarray:
    """Hand-written forward pass, one observation at a time, scalar activations."""
    act = {
        "tanh": np.tanh,
        "relu": lambda v: v if v > 0 else 0.0,
        "silu": lambda v: v / (1 + np.exp(-v)),
        "elu": lambda v: v if v > 0 else np.exp(v) - 1,
    }[activation]
    out = []
    for o in np.atleast_2d(obs):
        x = [
            min(max((o[k] - parts["obs_mean"][k]) / max(parts["obs_std"][k], floor), -clip), clip)
            for k in range(OBS)
        ]
        n = len(parts["weights"])
        for li, (w, b) in enumerate(parts["weights"]):
            y = [sum(x[i] * float(w[i, j]) for i in range(len(x))) + float(b[j]) for j in range(w.shape[1])]
            x = [act(v) for v in y] if li < n - 1 else y
        out.append([np.tanh(v) for v in x[:ACT]])
    return np.array(out)


@pytest.fixture
def policy_file(tmp_path):
    rng = np.random.default_rng(0)
    parts = _random_policy(rng)
    cfg = get_config("paper")  # a 17-number policy: the paper layout
    path = save_policy_npz(tmp_path / "policy.npz", activation="tanh", config=cfg, **parts)
    return path, parts, cfg


def _rewrite(src: str, dst: str, **changes) -> str:
    with np.load(src) as data:
        arrays = {k: data[k] for k in data.files}
    for key, value in changes.items():
        if value is None:
            arrays.pop(key)
        else:
            arrays[key] = np.asarray(value)
    np.savez(dst, **arrays)
    return dst


@pytest.mark.parametrize("activation", ["tanh", "relu", "silu", "elu"])
def test_matches_reference_forward(tmp_path, activation):
    rng = np.random.default_rng(1)
    parts = _random_policy(rng)
    cfg = Config()
    path = save_policy_npz(tmp_path / "p.npz", activation=activation, config=cfg, **parts)
    policy = load_policy(path)
    obs = rng.normal(0, 1, (5, OBS))
    obs[0, 3] = 100.0  # normalised value beyond ±5: clipped
    obs[1, 11] = 0.027  # 2 mm off a constant training target z: floored std keeps it moderate
    expected = _reference_forward(parts, activation, obs, cfg.ppo.obs_std_floor, cfg.ppo.obs_clip)
    batch = policy(obs)
    assert batch.shape == (5, ACT)
    np.testing.assert_allclose(batch, expected, atol=1e-6)
    np.testing.assert_allclose(policy(obs[2]), expected[2], atol=1e-6)
    assert np.all(np.abs(batch) <= 1.0)
    norm = policy.normalise(obs)
    assert norm[0, 3] == cfg.ppo.obs_clip
    assert np.all(np.abs(norm) <= cfg.ppo.obs_clip)


def test_metadata_and_env_config(policy_file):
    path, parts, cfg = policy_file
    policy = load_policy(path)
    assert isinstance(policy, NumpyPolicy)
    assert policy.obs_size == OBS and policy.action_size == ACT
    assert policy.obs_layout == OBS_LAYOUT
    assert policy.action_scale == cfg.env.control.q_max == 0.05
    assert policy.obs_std_floor == 0.01 and policy.obs_clip == 5.0
    assert policy.obs_std[11] == 0.01  # floored by the writer
    np.testing.assert_allclose(policy.obs_std[:11], parts["obs_std"][:11])
    assert policy.config_hash == config_hash(cfg)
    assert policy.env_config() == cfg.env
    assert policy.config().ppo.network.policy_hidden == cfg.ppo.network.policy_hidden
    assert policy.package_version
    with np.load(path) as data:
        assert int(data["format_version"]) == FORMAT_VERSION
        assert sorted(k for k in data.files if k.startswith("layer_")) == [
            "layer_0_b", "layer_0_w", "layer_1_b", "layer_1_w", "layer_2_b", "layer_2_w",
        ]  # fmt: skip
        assert data["layer_2_w"].shape == (24, 2 * ACT)
        assert json.loads(str(data["config_json"]))["env"]["control"]["control_dt"] == 0.05


def test_bad_observation_refused(policy_file):
    policy = load_policy(policy_file[0])
    obs = np.zeros(OBS)
    obs[15] = np.nan
    with pytest.raises(ValueError, match="d_po"):
        policy(obs)
    with pytest.raises(ValueError, match=r"shape \(17,\)"):
        policy(np.zeros(12))


def test_import_does_not_import_jax(policy_file):
    code = (
        "import sys, numpy as np\n"
        "import sagrasp_jax.task.policy_file as rt, sagrasp_jax.deploy.calibration, sagrasp_jax.deploy.safety\n"
        f"p = rt.load_policy({str(policy_file[0])!r})\n"
        "a = p(np.zeros(17)); sagrasp_jax.deploy.safety.check_policy_constants(p.env_config()); s = sagrasp_jax.deploy.safety.SafetyLayer()\n"
        "bad = sorted(m for m in sys.modules if m == 'jax' or m.startswith(('jax.', 'jaxlib', 'brax', 'flax')))\n"
        "assert not bad, bad\n"
        "print('ok', a.shape)\n"
    )
    env = dict(os.environ, PYTHONPATH=REPO)
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "ok (6,)" in result.stdout


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"obs_std": None}, "missing keys obs_std"),
        ({"layer_1_b": None}, "missing key layer_1_b"),
        ({"format_version": 2}, "format_version 2 is not supported"),
        ({"obs_mean": np.zeros(12)}, r"obs_mean must be float \(17,\)"),
        ({"layer_1_w": np.zeros((31, 24), np.float32)}, r"layer_1_w has shape \(31, 24\), expected \(32, out\)"),
        ({"layer_2_w": np.zeros((24, 6), np.float32), "layer_2_b": np.zeros(6, np.float32)}, "expected 2·action_size = 12"),
        ({"activation": "gelu"}, "activation 'gelu'"),
        ({"obs_std": np.full(17, 0.001)}, "below obs_std_floor"),
        ({"action_scale": 0.1}, "action_scale 0.1 differs"),
        ({"config_hash": "000000000000"}, "does not match its config_json"),
        ({"config_json": "{not json"}, "config_json does not load"),
        ({"obs_clip": np.nan}, "obs_clip is nan"),
    ],
)
def test_invalid_files_refused(policy_file, tmp_path, changes, message):
    bad = _rewrite(policy_file[0], str(tmp_path / "bad.npz"), **changes)
    with pytest.raises(PolicyFormatError, match=message) as info:
        load_policy(bad)
    assert bad in str(info.value)


def test_nan_weight_refused(policy_file, tmp_path):
    with np.load(policy_file[0]) as data:
        w = data["layer_1_w"].copy()
    w[3, 4] = np.nan
    bad = _rewrite(policy_file[0], str(tmp_path / "nan.npz"), layer_1_w=w)
    with pytest.raises(PolicyFormatError, match="layer_1_w has 1 NaN/inf entries"):
        load_policy(bad)


def test_corrupt_and_missing_files(policy_file, tmp_path):
    data = open(policy_file[0], "rb").read()
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(PolicyFormatError, match="truncated.npz: not a readable .npz archive"):
        load_policy(truncated)
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"definitely not a zip file")
    with pytest.raises(PolicyFormatError, match="garbage.npz: not a readable"):
        load_policy(garbage)
    with pytest.raises(PolicyFormatError, match="nowhere.npz: policy file not found"):
        load_policy(tmp_path / "nowhere.npz")


def test_writer_refuses_bad_policy_and_leaves_nothing(tmp_path):
    parts = _random_policy(np.random.default_rng(2))
    parts["weights"][0][0][0, 0] = np.nan
    with pytest.raises(PolicyFormatError, match="layer_0_w has 1 NaN"):
        save_policy_npz(tmp_path / "policy.npz", activation="tanh", config=Config(), **parts)
    assert os.listdir(tmp_path) == []


def test_atomic_write(tmp_path, monkeypatch):
    rng = np.random.default_rng(3)
    target = tmp_path / "policy.npz"
    save_policy_npz(target, activation="relu", config=Config(), **_random_policy(rng))
    assert os.listdir(tmp_path) == ["policy.npz"]
    before = target.read_bytes()

    def broken_savez(f, **arrays):
        f.write(b"PK partial")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", broken_savez)
    with pytest.raises(OSError, match="disk full"):
        save_policy_npz(target, activation="tanh", config=Config(), **_random_policy(rng))
    assert os.listdir(tmp_path) == ["policy.npz"]  # no temp file left behind
    assert target.read_bytes() == before  # the old policy is intact
    monkeypatch.undo()

    save_policy_npz(target, activation="elu", config=Config(), **_random_policy(rng))
    assert os.listdir(tmp_path) == ["policy.npz"]
    assert load_policy(target).activation == "elu"
