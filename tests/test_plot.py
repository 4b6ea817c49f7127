"""``python -m sagrasp_jax.plot``: a run's learning curves to PNG from metrics.jsonl, and the
training-window keys it reads (success per episode kind, ``metrics_window.KIND_SUCCESS``).

The run folders here are written by the test (a config.json and metrics rows shaped like a
training's), so the plot is checked in a second, without a training."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from sagrasp_jax import plot
from sagrasp_jax.base import run_files

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
matplotlib = pytest.importorskip("matplotlib", reason='the plots extra is not installed (pip install "sagrasp_jax[plots]")')


def _rows(n: int = 12, sa: bool = True) -> list[dict]:
    """Metrics rows as a training logs them: per iteration, a window row once episodes finished, a
    cycle row (evaluation, SA decision) every 4th iteration."""
    rows = []
    for i in range(n):
        row = {"iteration": i, "env_steps": 4096 * (i + 1), "lr": 6e-4 * (0.96 if i >= 8 else 1.0), "loss": 0.1}
        if i >= 2:
            row.update(success=i / n, success_no_obstacle=min(1.0, 1.5 * i / n), success_obstacle=i / (2 * n),
                       success_blocking=None if i < 5 else 0.1, obstacle_present=0.7, blocking=0.3,
                       **{"return": float(i)})
        if i % 4 == 3:
            row.update(cycle=i // 4, eval_success=i / n, eval_return=float(i) / 2)
            if sa:
                row.update(sa_metric=float(i) / 2, sa_decision=("accept", "reject", "accept-worse")[i // 4 % 3],
                           sa_decayed=i == 7)
        rows.append(row)
    return rows


def _run(folder, rows: list[dict], tail: str = "") -> str:
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, run_files.CONFIG_FILE), "w") as f:
        json.dump({"env": {}}, f)
    with open(os.path.join(folder, run_files.METRICS_FILE), "w") as f:
        f.write("".join(json.dumps(r) + "\n" for r in rows) + tail)
    return str(folder)


def _plot(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "sagrasp_jax.plot", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=120)


def test_file_names_are_run_dirs():
    from sagrasp_jax.training import run_dir

    assert (run_files.CONFIG_FILE, run_files.METRICS_FILE, run_files.POLICY_FILE) == \
        (run_dir.CONFIG_FILE, run_dir.METRICS_FILE, run_dir.POLICY_FILE)


def test_curves_and_decisions_from_rows():
    rows = _rows()
    x, y = plot.curve(rows, "success_blocking")
    assert x.tolist() == [4096 * k for k in range(3, 13)]
    assert np.isnan(y[:3]).all() and y[3:].tolist() == [0.1] * 7  # null: no blocking episode in the window yet
    decisions = plot.sa_decisions(rows)
    assert decisions["accept"][0].tolist() == [4096 * 4] and decisions["reject"][0].tolist() == [4096 * 8]
    assert decisions["accept-worse"][1].tolist() == [5.5]
    assert plot.smooth(np.array([1.0, np.nan, 3.0, 5.0]), 3).tolist() == [1.0, 2.0, 4.0, 4.0]


def test_plot_writes_a_png_of_the_run(tmp_path):
    run = _run(tmp_path / "run", _rows(), tail='{"iteration": 12, "env_st')  # a last line cut by a kill
    out = tmp_path / "figs" / "curves.png"
    res = _plot("--run", run, "--out", str(out))
    assert res.returncode == 0, res.stderr
    assert "wrote" in res.stdout and "49,152 env steps" in res.stdout
    from matplotlib import image as mpimg

    image = mpimg.imread(str(out))
    assert image.shape[:2] == (880, 1320) and image[..., :3].std() > 0.05  # 12 × 8 in at 110 dpi, not blank
    assert os.listdir(out.parent) == ["curves.png"]  # written atomically: no temp file left


def test_plot_overlays_runs_and_seed_groups_and_schedules_without_sa(tmp_path):
    group = tmp_path / "group"
    for s in (0, 1):
        _run(group / f"seed{s}", _rows(8 + s))
    plain = _run(tmp_path / "ppo", _rows(6, sa=False))
    runs = plot.load_runs([str(group), plain])
    assert [r.label for r in runs] == [str(group / "seed0"), str(group / "seed1"), plain]
    assert [len(r.rows) for r in runs] == [8, 9, 6]
    assert plot.plot_runs(runs, str(tmp_path / "all.png"), smooth_window=3) == str(tmp_path / "all.png")
    assert os.path.getsize(tmp_path / "all.png") > 10_000


@pytest.mark.parametrize("case, message", [
    ("out.jpg", "must end in .png"),
    ("missing", "run folder {tmp}/missing not found"),
    ("notarun", "is not a run folder (no config.json"),
    ("empty", "the metrics log has no rows yet"),
    ("damaged", "damaged metrics log at line 2"),
    ("smooth", "--smooth must be in [1, 100000]"),
])
def test_bad_input_is_refused_with_exit_2_and_nothing_written(tmp_path, case, message):
    (tmp_path / "notarun").mkdir()
    _run(tmp_path / "empty", [])
    _run(tmp_path / "damaged", _rows(3)[:1], tail="not json\n" + json.dumps(_rows(3)[2]) + "\n")
    good = _run(tmp_path / "good", _rows(3))
    run = {"out.jpg": good, "smooth": good}.get(case, str(tmp_path / case))
    out = str(tmp_path / ("out.jpg" if case == "out.jpg" else "out.png"))
    res = _plot("--run", run, "--out", out, *(["--smooth", "0"] if case == "smooth" else []))
    assert res.returncode == 2 and message.format(tmp=tmp_path) in res.stderr, res.stderr
    assert "Traceback" not in res.stderr and not os.path.exists(out)


def test_window_reports_success_per_episode_kind():
    """The training window's success among episodes without obstacle, with one, and blocking; null (NaN)
    while it holds none of a kind."""
    import jax.numpy as jnp

    from sagrasp_jax.training import metrics_window

    keys = ("success", "obstacle_present", "blocking", "steps")
    window = metrics_window.init_window(keys, 8)
    # (T=1, B=6) finished episodes: obstacle-free 2 (1 success), obstacle 4 (3 successes), 2 of them blocking (1)
    eps = {"done": jnp.ones((1, 6)), "success": jnp.array([[1, 0, 1, 1, 1, 0.0]]),
           "obstacle_present": jnp.array([[0, 0, 1, 1, 1, 1.0]]), "blocking": jnp.array([[0, 0, 0, 1, 0, 1.0]]),
           "steps": jnp.full((1, 6), 10.0)}
    window, means = metrics_window.update_window(window, eps)
    assert float(means["success_no_obstacle"]) == 0.5 and float(means["success_obstacle"]) == 0.75
    assert float(means["success_blocking"]) == 0.5 and float(means["success"]) == pytest.approx(4 / 6)
    _, means = metrics_window.update_window(metrics_window.init_window(keys, 8),
                                            dict(eps, obstacle_present=jnp.zeros((1, 6)), blocking=jnp.zeros((1, 6))))
    assert np.isnan(float(means["success_obstacle"])) and np.isnan(float(means["success_blocking"]))
    assert metrics_window.kind_success_keys(("return", "success", "steps")) == []  # windows without the flags
