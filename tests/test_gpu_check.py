"""``experiments/gpu_check.py --quick``: the GPU check runs end to end at CPU-smoke size and writes
a JSON whose fields and numbers are sane, so the check is ready when a GPU is lent."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_gpu_check_quick_writes_sane_json(tmp_path: pytest.TempPathFactory) -> None:
    out = str(tmp_path / "gpu_check.json")
    res = subprocess.run([sys.executable, "-m", "experiments.gpu_check", "--quick", "--out", out,
                          "--work", str(tmp_path / "work")], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    with open(out, encoding="utf-8") as f:
        result = json.load(f)
    assert result["quick"] is True and result["backend"] == "cpu" and result["wall_s"] > 0
    sections = result["sections"]
    assert set(sections) == {"dynamic", "train", "seeds"}

    dyn = sections["dynamic"]
    assert dyn["status"] == "ok", dyn
    assert dyn["jax"]["env_steps_per_s"] > 0 and dyn["jax"]["mode"] == "dynamic" and dyn["jax"]["batch"] == 16
    if result["versions"]["warp"] == "not installed":
        assert dyn["warp"] == dyn["equal"] == "not installed"
    else:  # MuJoCo Warp present: its rate and the equality test, or their errors (Warp's CPU path needs a compiler)
        assert dyn["warp"]["status"] in ("ok", "error") and dyn["equal"]["status"] in ("ok", "error")
        if dyn["equal"]["status"] == "ok":
            assert dyn["equal"]["max_abs_joint_diff"] >= 0.0 and dyn["equal"]["atol"] == 1e-5

    tr = sections["train"]
    assert tr["status"] == "ok", tr
    assert tr["preset"] == "cpu-quick" and tr["env_steps"] == tr["total_steps"] == 1024
    assert tr["compile_s"] > 0 and tr["median_iteration_env_steps_per_s"] > 0 and tr["overall_env_steps_per_s"] > 0
    assert tr["wall_s"] >= tr["train_s"] > 0
    assert tr["eval_episodes"] == 8 and 0.0 <= tr["success_rate"] <= 1.0
    assert tr["peak_device_memory_bytes"] is None or tr["peak_device_memory_bytes"] > 0

    seeds = sections["seeds"]  # the trainer's --seeds: a group of 2 tiny seeds, or an error row where it is missing
    if seeds["status"] == "ok" and seeds["stopped_by"] == "finished":
        assert set(seeds["per_seed"]) == {"0", "1"} and seeds["env_steps_per_s_all_seeds"] > 0
        assert all(s["policy"] and s["env_steps"] == 1024 for s in seeds["per_seed"].values())
    elif seeds["status"] == "ok":  # stopped when the budget was spent (a slow machine): a checkpointed group
        assert seeds["stopped_by"].startswith("budget of")
    else:
        assert seeds["status"] == "error" and ("--seeds" in seeds["error"] or "no time left" in seeds["error"])
    assert "cpu-quick preset, 1,024 steps" in res.stdout and "written to" in res.stdout
