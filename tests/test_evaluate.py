"""Evaluation CLI: Wilson interval, summaries split by obstacle, atomic JSON, clear errors."""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import json
import os

import numpy as np
import pytest

from conftest import toy_factory

from sagrasp_jax import evaluate


def test_wilson_interval_known_values():
    lo, hi = evaluate.wilson_interval(0, 10)
    assert lo == 0.0 and hi == pytest.approx(0.2775, abs=1e-4)
    lo, hi = evaluate.wilson_interval(5, 10)
    assert (lo, hi) == (pytest.approx(0.2366, abs=1e-4), pytest.approx(0.7634, abs=1e-4))
    lo, hi = evaluate.wilson_interval(980, 1000)
    assert lo == pytest.approx(0.9694, abs=1e-4) and hi == pytest.approx(0.9870, abs=1e-4)


def test_summary_counts_what_was_hit():
    eps = {"success": np.array([1, 0, 0, 1.0]), "collision": np.array([0, 1, 0, 0.0]),
           "timeout": np.array([0, 0, 1, 0.0]), "steps": np.array([10, 5, 200, 20.0]),
           "return": np.array([1, -1, -1, 1.0]), "finished": np.ones(4),
           "hit_gantry": np.array([0, 1, 0, 0.0]), "hit_obstacle": np.zeros(4)}
    s = evaluate.summarise(eps, np.ones(4, bool))
    assert s["success_rate"] == 0.5 and s["mean_steps_per_success"] == 15.0
    assert s["collision_by"] == {"gantry": 0.25, "obstacle": 0.0} and s["timeout_rate"] == 0.25
    assert evaluate.summarise(eps, np.zeros(4, bool)) == {"episodes": 0}


def test_evaluate_run_writes_json_and_table(toy_run, tmp_path):
    res = evaluate.evaluate_run(toy_run, episodes=200, env_factory=lambda cfg: toy_factory()(cfg)[1])
    again = evaluate.evaluate_run(toy_run, episodes=200, env_factory=lambda cfg: toy_factory()(cfg)[1])
    assert res["overall"] == again["overall"]  # deterministic
    o = res["overall"]
    assert o["episodes"] == 200 == res["obstacle_present"]["episodes"] + res["obstacle_absent"]["episodes"]
    assert o["success_ci95"][0] <= o["success_rate"] <= o["success_ci95"][1]
    assert o["success_rate"] + o["collision_rate"] + o["timeout_rate"] == pytest.approx(1.0)
    path = evaluate.write_results(str(tmp_path / "e.json"), res)
    assert json.load(open(path))["seed"] == res["seed"] and os.listdir(tmp_path) == ["e.json"]
    table = evaluate.format_table(res)
    assert "95 % CI (Wilson)" in table and "hit obstacle" in table and "no obstacle" in table


def test_cli_errors_on_a_folder_that_is_not_a_run(tmp_path, capsys):
    assert evaluate.main(["--run", str(tmp_path), "--episodes", "10"]) == 2
    assert "config.json" in capsys.readouterr().err
    assert os.listdir(tmp_path) == []
