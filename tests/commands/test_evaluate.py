"""Evaluation CLI: Wilson interval, summaries split by obstacle, atomic JSON, clear errors."""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import json
import os

import numpy as np
import pytest

from conftest import toy_factory

from sagrasp_jax import evaluate
from sagrasp_jax.training import evaluation


def test_wilson_interval_known_values():
    lo, hi = evaluation.wilson_interval(0, 10)
    assert lo == 0.0 and hi == pytest.approx(0.2775, abs=1e-4)
    lo, hi = evaluation.wilson_interval(5, 10)
    assert (lo, hi) == (pytest.approx(0.2366, abs=1e-4), pytest.approx(0.7634, abs=1e-4))
    lo, hi = evaluation.wilson_interval(980, 1000)
    assert lo == pytest.approx(0.9694, abs=1e-4) and hi == pytest.approx(0.9870, abs=1e-4)


def test_summary_counts_what_was_hit():
    eps = {"success": np.array([1, 0, 0, 1.0]), "collision": np.array([0, 1, 0, 0.0]),
           "timeout": np.array([0, 0, 1, 0.0]), "steps": np.array([10, 5, 200, 20.0]),
           "return": np.array([1, -1, -1, 1.0]), "finished": np.ones(4),
           "hit_gantry": np.array([0, 1, 0, 0.0]), "hit_obstacle": np.zeros(4)}
    s = evaluation.summarise(eps, np.ones(4, bool))
    assert s["success_rate"] == 0.5 and s["mean_steps_per_success"] == 15.0
    assert s["collision_by"] == {"gantry": 0.25, "obstacle": 0.0} and s["timeout_rate"] == 0.25
    assert evaluation.summarise(eps, np.zeros(4, bool)) == {"episodes": 0}


def test_evaluate_run_writes_json_and_table(toy_run, tmp_path):
    res = evaluation.evaluate_run(toy_run, episodes=200, env_factory=lambda cfg: toy_factory()(cfg)[1])
    again = evaluation.evaluate_run(toy_run, episodes=200, env_factory=lambda cfg: toy_factory()(cfg)[1])
    assert res["overall"] == again["overall"]  # deterministic
    o = res["overall"]
    assert o["episodes"] == 200 == res["obstacle_present"]["episodes"] + res["obstacle_absent"]["episodes"]
    assert o["success_ci95"][0] <= o["success_rate"] <= o["success_ci95"][1]
    assert o["success_rate"] + o["collision_rate"] + o["timeout_rate"] == pytest.approx(1.0)
    path = evaluation.write_results(str(tmp_path / "e.json"), res)
    assert json.load(open(path))["seed"] == res["seed"] and os.listdir(tmp_path) == ["e.json"]
    table = evaluate.format_table(res)
    assert "95 % CI (Wilson)" in table and "hit obstacle" in table and "no obstacle" in table


def test_cli_errors_on_a_folder_that_is_not_a_run(tmp_path, capsys):
    assert evaluate.main(["--run", str(tmp_path), "--episodes", "10"]) == 2
    assert "config.json" in capsys.readouterr().err
    assert os.listdir(tmp_path) == []


def test_a_twin_evaluation_of_a_run_writes_its_result_into_the_run_folder(tmp_path, capsys):
    """Issue 54: as the MJX evaluation does, named by the same scheme with the backend and condition, atomically,
    and replacing only the same result (another one with --force)."""
    import hashlib
    import shutil

    pytest.importorskip("pybullet")
    from sagrasp_jax.task.policy_file import pretrained_path

    run = tmp_path / "run"
    run.mkdir()
    shutil.copy(pretrained_path("pretrained"), run / "policy.npz")
    (run / "config.json").write_text("{}")
    argv = ["--backend", "twin", "--run", str(run), "--episodes", "1", "--condition", "kinematic"]
    assert evaluate.main(argv) == 0
    path = run / "evaluation-1ep-seed0-twin-kinematic.json"
    assert f"written {path}" in capsys.readouterr().out
    assert sorted(os.listdir(run)) == ["config.json", path.name, "policy.npz"]  # no temp or lock file left
    result = json.loads(path.read_text())
    assert (result["backend"], result["episodes"], result["condition"], result["seed"]) == ("twin", 1, "kinematic", 0)
    assert result["policy"] == str(run / "policy.npz")
    assert result["policy_sha256"] == hashlib.sha256((run / "policy.npz").read_bytes()).hexdigest()
    path.write_text(json.dumps(dict(result, seed=5)))  # another twin result under that name
    assert evaluate.main(argv) == 2
    assert f"{path} holds a different result (seed 5 -> 0); pass --force" in capsys.readouterr().err
    assert json.loads(path.read_text())["seed"] == 5
    assert evaluate.main([*argv, "--force"]) == 0
    assert json.loads(path.read_text())["seed"] == 0


def test_a_mistyped_option_is_named_with_the_nearest_one(capsys):
    with pytest.raises(SystemExit) as stop:
        evaluate.main(["--run", "r", "--episdes", "8"])
    assert stop.value.code == 2
    assert capsys.readouterr().err.splitlines() == [
        "python -m sagrasp_jax.evaluate: error: unknown option --episdes (did you mean --episodes?)"]
