"""The parity harness (docs/task.md §2 parity rules): it passes on the real pair of envs, and it can fail.

The harness runs JAX in float64; switching x64 on inside the shared pytest process would change
every later test's dtypes, so the end-to-end runs go through the CLI in a subprocess.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401  (XLA flags before jax)

pytest.importorskip("pybullet")
pytest.importorskip("gymnasium")

from sagrasp_jax import parity as parity_command  # noqa: E402
from sagrasp_jax.reference import parity  # noqa: E402
from paths import REPO as ROOT  # noqa: E402



def run_cli(*args: str, tmp_path) -> tuple[int, dict, str]:
    out = tmp_path / "parity.json"
    proc = subprocess.run(
        [sys.executable, "-m", "sagrasp_jax.parity", "--quiet", "--out", str(out), *args],
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )
    report = json.loads(out.read_text()) if out.exists() else {}
    return proc.returncode, report, proc.stdout + proc.stderr


def test_quick_kinematic_parity_passes(tmp_path):
    """50 episodes of random and of scripted actions, short episodes: every per-step error far
    below the tolerances, every flag identical, the same success rate in both envs."""
    rc, report, text = run_cli("--quick", "--max-steps", "50", "--seed", "3", tmp_path=tmp_path)
    assert rc == 0, text
    assert report["passed"] and report["mode"] == "kinematic"
    for name in ("random", "scripted"):
        sec = report["sources"][name]
        assert sec["episodes"] == 50 and sec["flag_agreement"] == 1.0
        assert sec["trajectory"]["gripper_centre"]["max"] < 1e-6
        assert sec["trajectory"]["reward"]["max"] < 1e-5
        assert sec["jax"]["success_rate"] == sec["pybullet"]["success_rate"]
    assert report["sources"]["scripted"]["jax"]["success_rate"] > 0.5  # the success branch is exercised
    assert "PASSED" in text


def test_kinematic_parity_passes_with_capsules_switched_on(tmp_path):
    """The fourth obstacle kind (a capsule lying on the table) built by both envs from the registry:
    same distances, observations and verdicts step by step.  Mixed with boxes (the other yawed kind)
    so that most episodes hold a capsule; ``--set env.sampling.obstacle_kinds=sphere,cylinder,box,capsule
    --set env.sampling.obstacle_candidates=12 --quick`` passes too (docs/design.md)."""
    rc, report, text = run_cli("--episodes", "16", "--max-steps", "40", "--seed", "1",
                               "--set", "env.sampling.obstacle_kinds=box,capsule",
                               "--set", "env.sampling.obstacle_candidates=6", "--set", "env.sampling.obstacle_prob=1.0",
                               tmp_path=tmp_path)
    assert rc == 0, text
    assert report["passed"] and report["obstacle_kinds"] == ["box", "capsule"]
    assert report["obstacles_per_kind"].get("capsule", 0) >= 3, report["obstacles_per_kind"]
    for name in ("random", "scripted"):
        assert report["sources"][name]["flag_agreement"] == 1.0
        assert report["sources"][name]["trajectory"]["obs"]["max"] < 1e-5


def test_a_perturbed_reward_constant_makes_the_harness_fail(tmp_path):
    """ratio 10 → 10.5 in the reference env's config only: the distance term no longer matches."""
    rc, report, text = run_cli("--episodes", "4", "--max-steps", "10", "--actions", "random",
                               "--reference-set", "env.reward.ratio=10.5", tmp_path=tmp_path)
    assert rc == 1, text
    assert report["passed"] is False
    failed = {c["quantity"] for c in report["checks"] if not c["ok"]}
    assert {"r_distance", "reward"} <= failed
    assert "gripper_centre" not in failed  # the motion itself still agrees
    assert "FAIL random r_distance" in text


def test_cli_refuses_bad_arguments(capsys):
    assert parity_command.main(["--actions", "random,bogus", "--out", ""]) == 2
    assert "bogus" in capsys.readouterr().err
    assert parity_command.main(["--episodes", "0", "--out", ""]) == 2


def test_parity_configs_change_only_what_they_must():
    base = parity.get_config("paper")
    jax_cfg, ref_cfg = parity.parity_configs(base, "dynamic", 30, ["env.reward.ratio=10.5"])
    assert jax_cfg.task.obs_noise_std == 0.0 == ref_cfg.task.obs_noise_std
    assert jax_cfg.control.mode == "dynamic" == ref_cfg.control.mode
    assert jax_cfg.task.max_steps == 30 == ref_cfg.task.max_steps
    assert jax_cfg.reward.ratio == 10.0 and ref_cfg.reward.ratio == 10.5
    assert jax_cfg.control == ref_cfg.control and jax_cfg.sampling == ref_cfg.sampling


def test_resets_come_from_numpy_uniforms_through_the_shared_sampler():
    cfg = parity.get_config("paper").env
    a = parity.draw_resets(cfg, 5, np.random.default_rng(0))
    b = parity.draw_resets(cfg, 5, np.random.default_rng(0))
    for x, y in zip(a, b):
        for field in x._fields:
            np.testing.assert_array_equal(np.asarray(getattr(x, field)), np.asarray(getattr(y, field)))
    stacked = parity._stack_specs(a)
    assert stacked.q0.shape == (5, 6) and stacked.obstacle_pos.shape == (5, 2, 3)


def test_format_report_lists_failures():
    report = {
        "mode": "kinematic", "episodes_per_source": 1, "seed": 0, "max_steps": 5, "obstacle_episodes": 0,
        "tolerances": {"gripper_centre": 1e-4, "reward": 1e-4, "obs": 1e-4, "flag_agreement": 1.0},
        "sources": {}, "passed": False,
        "checks": [{"source": "random", "quantity": "reward", "value": 0.2, "op": "≤", "tolerance": 1e-4, "ok": False}],
    }
    text = parity.format_report(report)
    assert "FAIL random reward = 0.2" in text and text.endswith("FAILED")
