"""Files written by version 0.1 (before observation layouts, the near-miss potential and the fine
obstacle geometry) keep loading with the behaviour they were trained with.

``tests/data/legacy_v0_1`` holds, as 0.1 wrote them: ``policy_cpu_quick_3M.npz`` (the README's
cpu-quick run, seed 0, 3M steps: 99.4 % of obstacle-free episodes), its 1,000-episode
``evaluation_cpu_quick_3M.json``, and the ``config.json`` + ``checkpoint.ckpt`` of a tiny run
folder (8 envs, 128 steps).
"""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401
from sagrasp_jax.task import config
from sagrasp_jax.task import config_parse
from sagrasp_jax.task import observation
from sagrasp_jax.task.policy_file import load_policy
from paths import DATA as TEST_DATA  # noqa: E402

DATA = os.path.join(TEST_DATA, "legacy_v0_1")
POLICY = os.path.join(DATA, "policy_cpu_quick_3M.npz")


def test_legacy_config_gets_its_old_semantics():
    with open(os.path.join(DATA, "config.json"), encoding="utf-8") as f:
        raw = json.load(f)
    assert "obs_layout" not in raw["env"]["task"]  # written before the key existed
    cfg = config_parse.config_from_dict(raw)
    assert cfg.env.task.obs_layout == "paper"
    assert cfg.env.reward.near_miss_mode == "per_step"
    assert cfg.env.task.obstacle_geometry == "cover"
    assert config_parse.config_from_dict(config.config_to_dict(cfg)) == cfg  # a full dict round-trips unchanged


def test_legacy_policy_loads_with_the_paper_layout():
    policy = load_policy(POLICY)
    assert policy.obs_size == 17 and policy.obs_layout == observation.PAPER_LAYOUT
    env = policy.env_config()
    assert (env.task.obs_layout, env.reward.near_miss_mode, env.task.obstacle_geometry) == ("paper", "per_step", "cover")
    assert policy(np.zeros((3, 17)) + policy.obs_mean).shape == (3, 6)


def test_legacy_run_folder_evaluates_and_exports(tmp_path):
    from sagrasp_jax.training.evaluation import evaluate_run
    from sagrasp_jax.export import export_run

    run = tmp_path / "legacy_run"
    run.mkdir()
    for name in ("config.json", "checkpoint.ckpt"):
        shutil.copy(os.path.join(DATA, name), run / name)
    result = evaluate_run(str(run), episodes=8)
    assert result["overall"]["episodes"] == 8
    manifest = export_run(str(run), str(tmp_path / "export"), onnx=False)
    assert len(manifest["obs_layout"]) == 17
    assert load_policy(str(tmp_path / "export" / "policy.npz")).env_config().task.obs_layout == "paper"


def test_legacy_policy_grasps_on_the_twin():
    pytest.importorskip("pybullet")
    from sagrasp_jax.deploy import run_episode, scene_spec
    from sagrasp_jax.deploy.twin import PyBulletTwin

    policy = load_policy(POLICY)
    cfg = policy.env_config()
    target = np.array([0.10, -0.45, 0.025])
    q0 = np.array(config.HOME_Q)
    with PyBulletTwin(scene_spec(q0, target, 0.0, [], cfg), cfg, q0=q0) as twin:
        report = run_episode(twin, policy, target, 0.0)
    assert report.outcome == "success", report
    assert report.steps < 60
    assert report.grasp is not None and report.grasp["lifted"]
