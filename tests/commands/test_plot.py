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
from paths import REPO  # noqa: E402

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
    assert image.shape[:2] == (1155, 1540) and image[..., :3].std() > 0.05  # 14 × 10.5 in at 110 dpi, not blank
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


def _texts(ax) -> list[str]:
    return [t.get_text() for t in ax.get_legend().get_texts()]


def test_the_figure_explains_itself():
    """Each series of the success panel has its own colour and a legend entry naming its episode kind; every
    panel has a legend, x axes in env steps, and a caption saying what it shows (the return's weights at p, the
    SA metric and its decisions)."""
    from matplotlib.colors import to_hex

    fig = plot.figure([plot.Run("run", _rows())])
    try:
        ax_s, ax_r, ax_lr, ax_sa = fig.axes
        lines = [line for line in ax_s.get_lines() if not line.get_label().startswith("_")]
        labels = [line.get_label() for line in lines]
        assert len(lines) == 5 and len({to_hex(line.get_color()) for line in lines}) == 5, labels
        legend = _texts(ax_s)
        for kind in ("all training episodes", "no obstacle: 30 % of episodes", "obstacle (any): 70 % of episodes",
                     "blocking obstacle (on the straight approach): 30 % of episodes", "evaluation"):
            assert any(text.startswith(kind) for text in legend), (kind, legend)
        assert all(ax.get_legend() is not None for ax in fig.axes)
        assert all(ax.get_xlabel().startswith("env steps") for ax in fig.axes)
        captions = {ax: " ".join(t.get_text() for t in ax.texts) for ax in fig.axes}
        assert "F_d = 2 − p" in captions[ax_r] and "can fall while success rises" in captions[ax_r]
        assert "p = 1 weights" in captions[ax_r] and "fixed-seed" in captions[ax_s]
        assert "sa.metric=return" in captions[ax_sa] and "reject" in captions[ax_sa]
        assert ax_sa.get_ylabel() == "M: evaluation return (p = 1)"  # the rows' sa_metric is their eval_return
        assert [text.split(" (")[0] for text in _texts(ax_sa)] == ["M per cycle", "accept", "accept-worse", "reject",
                                                                   "lr decay"]
    finally:
        plot.pyplot().close(fig)


def test_overlaid_runs_keep_the_series_colours_and_differ_by_line_style(tmp_path):
    from matplotlib.colors import to_hex

    rows = _rows()
    success = [dict(r, sa_metric=r["eval_success"]) if "sa_metric" in r else r for r in rows]
    assert plot.sa_metric_kind(rows) == "return" and plot.sa_metric_kind(success) == "success"
    fig = plot.figure([plot.Run("a", rows), plot.Run("b", success)])
    try:
        ax_s = fig.axes[0]
        lines = ax_s.get_lines()
        by_run = [lines[:5], lines[5:]]
        assert [to_hex(x.get_color()) for x in by_run[0]] == [to_hex(x.get_color()) for x in by_run[1]]
        assert {x.get_linestyle() for x in by_run[0]} == {"-"} and {x.get_linestyle() for x in by_run[1]} == {"--"}
        legend = _texts(ax_s)
        assert legend[:4] == ["all training episodes", "no obstacle", "obstacle (any)",
                              "blocking obstacle (on the straight approach)"] and legend[-2:] == ["a", "b"]
        assert fig.axes[3].get_ylabel() == "SA metric M"  # the runs judged different metrics
    finally:
        plot.pyplot().close(fig)


@pytest.mark.parametrize("kind", ["fifo", "dev_zero"])
def test_metrics_log_that_is_no_regular_file_is_refused(tmp_path, kind):
    """Read through fileio.read_regular: a FIFO would block the read forever and /dev/zero never ends; both are
    refused before they are opened (exit 2, nothing written)."""
    run = _run(tmp_path / "run", _rows())
    metrics = os.path.join(run, run_files.METRICS_FILE)
    out = tmp_path / "out.png"
    os.unlink(metrics)
    if kind == "fifo":
        os.mkfifo(metrics)
        message = "is a FIFO (named pipe), not a regular file"
    else:
        os.symlink("/dev/zero", metrics)
        message = "is a character device, not a regular file"
    res = _plot("--run", run, "--out", str(out))
    assert res.returncode == 2 and message in res.stderr, res.stderr
    assert "Traceback" not in res.stderr and not out.exists()


def test_metrics_log_over_the_size_bound_is_refused_before_it_is_read(tmp_path, capsys, monkeypatch):
    run = _run(tmp_path / "run", _rows())
    size = os.path.getsize(os.path.join(run, run_files.METRICS_FILE))
    monkeypatch.setattr(plot, "MAX_METRICS_BYTES", size - 1)
    assert plot.main(["--run", run, "--out", str(tmp_path / "out.png")]) == 2
    assert f"{size} bytes, over the {size - 1} bytes a metrics log may hold; not read" in capsys.readouterr().err
    assert not (tmp_path / "out.png").exists()


def _with_row_field(folder, field, value) -> str:
    rows = _rows(6)
    rows[3][field] = value  # line 4 of 6: not a last line a kill cut short
    return _run(folder, rows)


@pytest.mark.parametrize("field, value, message", [
    ("success", {"a": 1}, "line 4: 'success' must be a rate in [0, 1] or null, got a JSON object"),
    ("lr", [0.001], "line 4: 'lr' must be a positive number or null, got a JSON list"),
    ("sa_metric", "high", "line 4: 'sa_metric' must be a finite number or null, got 'high'"),
    ("env_steps", 10**400, "line 4: 'env_steps' must be a whole number of env steps in [0, 1e+15], got an integer of "
                           "401 digits"),
], ids=["success-object", "lr-list", "sa_metric-string", "env_steps-401-digits"])
def test_non_numeric_fields_are_refused_naming_line_and_field(tmp_path, field, value, message):
    run = _with_row_field(tmp_path / "run", field, value)
    out = tmp_path / "out.png"
    res = _plot("--run", run, "--out", str(out))
    assert res.returncode == 2 and message in res.stderr and "metrics.jsonl: line 4" in res.stderr, res.stderr
    assert "Traceback" not in res.stderr and not out.exists()


@pytest.mark.parametrize("field, value, message", [
    ("success_blocking", True, "'success_blocking' must be a rate in [0, 1] or null, got true"),
    ("eval_success", 1.5, "'eval_success' must be a rate in [0, 1] or null, got 1.5"),
    ("return", 10**400, "'return' must be a finite number or null, got an integer of 401 digits"),
    ("lr", 0, "'lr' must be a positive number or null, got 0"),
    ("env_steps", -1, "'env_steps' must be a whole number of env steps in [0, 1e+15], got -1"),
    ("env_steps", 4096.0, "damaged metrics log at line 4 (not a metrics row"),  # parse_metrics' own check
    ("sa_decision", 5, "'sa_decision' must be one of accept, accept-worse, reject or null, got 5"),
    ("sa_decided", 5, None),  # a field the plot does not read is left alone
    ("sa_decayed", "yes", "'sa_decayed' must be true, false or null, got 'yes'"),
], ids=["bool-rate", "rate-over-1", "huge-return", "zero-lr", "negative-steps", "float-steps", "decision-number",
        "unread-field", "decayed-string"])
def test_each_field_the_plot_reads_is_checked(tmp_path, capsys, field, value, message):
    run = _with_row_field(tmp_path / "run", field, value)
    out = tmp_path / "out.png"
    assert plot.main(["--run", run, "--out", str(out)]) == (0 if message is None else 2)
    err = capsys.readouterr().err
    assert message is None or message in err and "line 4" in err, err
    assert os.path.exists(out) == (message is None)


def test_non_finite_values_count_as_null(tmp_path):
    """NaN and Infinity (a trainer before the null rule wrote them) are gaps, as run_dir rewrites them."""
    rows = _rows(6)
    text = "".join(json.dumps(r) + "\n" for r in rows).replace('"success_blocking": null', '"success_blocking": NaN')
    text = text.replace('"return": 4.0', '"return": Infinity')
    run = _run(tmp_path / "run", [], tail=text)
    runs = plot.load_runs([run])
    assert runs[0].rows[4]["return"] is None and runs[0].rows[3]["success_blocking"] is None
    assert plot.main(["--run", run, "--out", str(tmp_path / "out.png")]) == 0
