"""Plot a run's learning curves: ``python -m sagrasp_jax.plot --run runs/NAME --out curves.png``.

Four panels from the run's ``metrics.jsonl`` against env steps (the ``plots`` extra: matplotlib), each
with a legend and a caption under it that says what it shows:

* **success (%)** of the training episodes, all together and per kind — without obstacle, with one,
  blocking (an obstacle on the straight approach path, a subset of those with one) — over the last
  ``train.metrics_window`` finished episodes, one colour each, and the per-cycle deterministic evaluation
  (the fixed-seed episodes, ``eval.episodes``);
* **return**: the per-episode sum of the shaped reward R = F_d·R_distance + F_s·R_success + F_o·R_obstacle
  (docs/task.md §2.4).  The training episodes are paid with the weights at the run's progress p (by
  default F_d = 2 − p, F_s = 0.5 + p), so their return falls as p grows even while success rises; the
  evaluation is paid with the p = 1 weights throughout;
* **learning rate** (log scale);
* **SA decisions**: the metric M that simulated annealing judged each cycle by — the evaluation's mean
  return at p = 1 (``sa.metric=return``, the default) or its success rate — marked accept /
  accept-worse / reject, with the lr decays as vertical lines (runs without decisions: the panel says so).

``--run`` may be repeated (runs overlaid: one line style each, the colours stay the series'); a seed
group (``train --seeds``) plots each of its seeds.  ``--smooth N`` averages the training curves over N
logged rows.  The metrics log is read like every input (``fileio.read_regular``: a regular file of at
most ``MAX_METRICS_BYTES``) and each field the plot uses is checked (bad input: exit 2 naming the file,
line and field).  The PNG is written atomically.  jax-free.  ``smooth``, ``pyplot`` and ``save`` serve
the studies' figures too (``experiments/reproduce_paper.py``, ``experiments/compare_schedules.py``).
"""

from __future__ import annotations

import math
import os
import sys
import textwrap
from typing import Any, NamedTuple, Sequence

import numpy as np

from sagrasp_jax.base import cli
from sagrasp_jax.base import extras
from sagrasp_jax.base import fileio
from sagrasp_jax.base import run_files

# A metrics.jsonl is read whole, within this bound (refused beyond it before it is read): a row is ≈ 2 kB,
# so this is ≈ 130,000 logged rows, 13 times a 20M-step run of the paper preset logging every iteration.
MAX_METRICS_BYTES = 256 << 20
MAX_ENV_STEPS = 10**15  # a row's env_steps (train.total_steps is at most 10^12)

# The success panel's series of a metrics row: (key, legend label, colour, line style of a single run).
# Training-window means (null while the window holds no episode of a kind: a gap), then the evaluation's.
SUCCESS_SERIES = (("success", "all training episodes", "black", "-"),
                  ("success_no_obstacle", "no obstacle", "tab:blue", "-"),
                  ("success_obstacle", "obstacle (any)", "tab:orange", "--"),
                  ("success_blocking", "blocking obstacle (on the straight approach)", "tab:red", ":"))
EVAL = ("evaluation (deterministic, fixed-seed episodes)", "tab:green")
# each kind's share of the window's episodes, for its legend label: (row key, share is 1 − the key's value)
KIND_SHARE = {"success_no_obstacle": ("obstacle_present", True), "success_obstacle": ("obstacle_present", False),
              "success_blocking": ("blocking", False)}
TRAIN_RETURN, LR_COLOUR, METRIC_COLOUR = "black", "tab:purple", "0.35"
DECISIONS = {"accept": ("o", "tab:green"), "accept-worse": ("^", "tab:orange"), "reject": ("x", "tab:red")}
# line style (and marker) of each overlaid run, in turn
RUN_STYLES = (("-", None), ("--", None), (":", None), ("-.", None), ("-", "s"), ("--", "^"), (":", "v"), ("-.", "D"))

# The fields a row may carry that the plot reads, and what each must be (null also does; NaN and ±Infinity,
# which trainers before the null rule wrote, count as null as ``run_dir.MetricsLog`` rewrites them).
RATES = ("success", "success_no_obstacle", "success_obstacle", "success_blocking", "eval_success",
         "obstacle_present", "blocking")
NUMBERS = ("return", "eval_return", "sa_metric")
POSITIVE = ("lr",)

CAPTIONS = {
    "success": "Training: share of the last train.metrics_window finished training episodes (stochastic policy) "
               "that grasped, all together and per kind (blocking: an obstacle on the straight approach path, a "
               "subset of 'obstacle'). Evaluation: the deterministic policy on the same fixed-seed episodes at the "
               "end of every cycle.",
    "return": "Per-episode sum of the shaped reward R = F_d·R_distance + F_s·R_success + F_o·R_obstacle. Training "
              "episodes are paid with the weights at the training progress p (by default F_d = 2 − p, F_s = 0.5 + p): "
              "the approach shaping (10 per metre closed) goes from weight 2 to 1 while the ±1 verdict goes from 0.5 "
              "to 1.5, so this return can fall while success rises. The evaluation is paid with the p = 1 weights "
              "throughout: comparable from cycle to cycle.",
    "lr": "The optimizer's learning rate after each logged iteration. Under SA it changes only at a decay (dashed "
          "lines on the right): after sa.patience stalled cycles, sa.max_rollbacks rejections in a row, or a "
          "non-finite step.",
    "sa": "Each cycle ends with the fixed-seed evaluation; its M is {metric}. SA compares M with the last accepted "
          "cycle's: accept (at most sa.tol below it: a new snapshot), accept-worse (further below, kept with "
          "probability exp(−ΔE/T)), reject (parameters, optimizer and normaliser restored to the snapshot).",
}
METRIC_WORDS = {"return": ("M: evaluation return (p = 1)", "its mean return with the p = 1 weights, sa.metric=return"),
                "success": ("M: evaluation success (%)", "its success rate, sa.metric=success"),
                None: ("SA metric M", "the evaluation's mean return at p = 1 or, with sa.metric=success, its "
                       "success rate")}


class PlotError(ValueError):
    """Bad input for the plot (options, run folders, metrics rows); the message names it."""


class Run(NamedTuple):
    label: str
    rows: list[dict[str, Any]]


def require_matplotlib() -> None:
    extras.require("plots", what="plotting learning curves")


def pyplot() -> Any:
    """matplotlib.pyplot on the file-only Agg backend (no display needed); MissingExtra without matplotlib."""
    require_matplotlib()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig: Any, path: str, dpi: int = 110) -> str:
    """Write ``fig`` to ``path`` atomically (format from the extension) and close it."""
    fig.tight_layout()
    fileio.atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=dpi, format=os.path.splitext(path)[1][1:] or "png"))
    pyplot().close(fig)
    return path


def smooth(y: np.ndarray, window: int) -> np.ndarray:
    """Centred moving average along the last axis ignoring NaN (window 1 = unchanged)."""
    if window <= 1 or y.shape[-1] == 0:
        return y
    ok = np.isfinite(y)
    kernel = np.ones(window)
    num = np.apply_along_axis(lambda r: np.convolve(r, kernel, "same"), -1, np.where(ok, y, 0.0))
    den = np.apply_along_axis(lambda r: np.convolve(r, kernel, "same"), -1, ok.astype(float))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / den, np.nan)


# ---------------------------------------------------------------------- reading and checking the rows

def _shown(value: Any) -> str:
    """A JSON value in a few words, however large it is."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int) and value.bit_length() > 64:
        return f"an integer of {len(str(abs(value)))} digits"
    if isinstance(value, (dict, list)):
        return "a JSON object" if isinstance(value, dict) else "a JSON list"
    if isinstance(value, str):
        return repr(value) if len(value) <= 24 else repr(value[:24]) + "…"
    return repr(value)


def _number(value: Any) -> float | None:
    """A row value as a float: None for null and the non-finite floats; ValueError for anything but a number
    (a bool too) and for an integer beyond a float's range."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or isinstance(value, int) and abs(value) > 1e300:
        raise ValueError
    number = float(value)
    return number if math.isfinite(number) else None


# what each kind of field must be: (fields, in words, test)
FIELD_RULES = ((RATES, "a rate in [0, 1]", lambda v: 0.0 <= v <= 1.0),
               (NUMBERS, "a finite number", lambda v: True),
               (POSITIVE, "a positive number", lambda v: v > 0.0))


def check_row(row: dict[str, Any]) -> None:
    """Refuse (ValueError naming the field) a row field the plot reads that it could not draw; NaN and
    ±Infinity become null.  Fields it does not read are left alone."""
    steps = row.get("env_steps")
    if type(steps) is not int or not 0 <= steps <= MAX_ENV_STEPS:
        raise ValueError(f"'env_steps' must be a whole number of env steps in [0, {MAX_ENV_STEPS:.0e}], "
                         f"got {_shown(steps)}")
    for fields, what, ok in FIELD_RULES:
        for field in (f for f in fields if f in row):
            try:
                number = _number(row[field])
                if number is not None and not ok(number):
                    raise ValueError
            except ValueError:
                raise ValueError(f"'{field}' must be {what} or null, got {_shown(row[field])}") from None
            row[field] = number
    decision = row.get("sa_decision")
    if decision is not None and decision not in DECISIONS:
        raise ValueError(f"'sa_decision' must be one of {', '.join(DECISIONS)} or null, got {_shown(decision)}")
    decayed = row.get("sa_decayed")
    if decayed is not None and not isinstance(decayed, bool):
        raise ValueError(f"'sa_decayed' must be true, false or null, got {_shown(decayed)}")


def read_metrics(run: str) -> list[dict[str, Any]]:
    """The checked rows of ``run``'s ``metrics.jsonl``, read as a regular file of at most ``MAX_METRICS_BYTES``
    (a FIFO, device or larger file is refused before it is read).  A last line cut short by a kill is dropped;
    any other damage, and a field the plot could not draw, raises PlotError naming the file and line."""
    try:
        file = os.path.join(run_files.check_run(run), run_files.METRICS_FILE)
    except run_files.RunFolderError as exc:
        raise PlotError(str(exc)) from None
    try:
        data = fileio.read_regular(file, MAX_METRICS_BYTES, "metrics log")
    except (fileio.NotRegularFile, fileio.FileTooLarge) as exc:  # their messages start with the path
        raise PlotError(f"cannot read the metrics log: {exc}") from None
    except OSError as exc:
        raise PlotError(f"{file}: cannot read the metrics log ({exc.strerror or exc})") from None
    rows = run_files.parse_metrics(data, file, PlotError, need_env_steps=True)
    numbers = [i + 1 for i, line in enumerate(data.split(b"\n")) if line.strip()]  # parse_metrics' rows' lines
    for number, row in zip(numbers, rows):
        try:
            check_row(row)
        except ValueError as exc:
            raise PlotError(f"{file}: line {number}: {exc}") from None
    return rows


def load_runs(folders: Sequence[str]) -> list[Run]:
    """Every ``--run``: a run folder, or each seed of a seed group."""
    runs = []
    for folder in folders:
        seeds = [] if os.path.isfile(os.path.join(folder, run_files.CONFIG_FILE)) else run_files.seed_folders(folder)
        for run in seeds or [folder]:
            rows = read_metrics(run)
            if not rows:
                raise PlotError(f"{run}: the metrics log has no rows yet (the training logs one per iteration)")
            runs.append(Run(os.path.normpath(run), rows))
    return runs


# ---------------------------------------------------------------------- the series

def curve(rows: Sequence[dict[str, Any]], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(env steps, values) of the rows that carry ``key``; a null value (no such episode yet) is NaN."""
    pts = [(r["env_steps"], r[key]) for r in rows if key in r]
    x = np.asarray([p[0] for p in pts], float)
    y = np.asarray([np.nan if p[1] is None else p[1] for p in pts], float)
    return x, y


def sa_decisions(rows: Sequence[dict[str, Any]]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per SA decision kind: (env steps, the cycle's SA metric) of the cycles that ended so."""
    out = {}
    for kind in DECISIONS:
        pts = [(r["env_steps"], r.get("sa_metric")) for r in rows if r.get("sa_decision") == kind]
        out[kind] = (np.asarray([p[0] for p in pts], float),
                     np.asarray([np.nan if p[1] is None else p[1] for p in pts], float))
    return out


def sa_metric_kind(rows: Sequence[dict[str, Any]]) -> str | None:
    """Which evaluation number the run's SA metric is — ``"return"`` or ``"success"`` (``sa.metric``), read off
    the cycle rows, which log both beside it — or None when the rows do not tell."""
    cycles = [r for r in rows if r.get("sa_metric") is not None and "sa_decision" in r]
    for kind in ("return", "success"):
        if cycles and all(r.get(f"eval_{kind}") is not None and abs(r["sa_metric"] - r[f"eval_{kind}"]) <= 1e-9
                          for r in cycles):
            return kind
    return None


def _share(rows: Sequence[dict[str, Any]], key: str) -> float | None:
    """The mean share of the window's episodes of the kind of success key ``key`` over the run (None: not logged)."""
    flag, complement = KIND_SHARE.get(key, (None, False))
    values = [r[flag] for r in rows if flag and r.get(flag) is not None]
    if not values:
        return None
    share = float(np.mean(values))
    return 1.0 - share if complement else share


def _caption(ax: Any, text: str) -> None:
    """``text`` wrapped under ``ax``'s x label, in small grey type (tight_layout leaves room for it)."""
    ax.annotate(textwrap.fill(text, 110), xy=(0.0, 0.0), xycoords="axes fraction", xytext=(0, -30),
                textcoords="offset points", ha="left", va="top", fontsize=7.5, color="0.25", linespacing=1.3)


# ---------------------------------------------------------------------- the figure

def figure(runs: Sequence[Run], smooth_window: int = 1) -> Any:
    """The figure of the module doc for ``runs`` (its axes: success, return, learning rate, SA decisions)."""
    plt = pyplot()
    from matplotlib.lines import Line2D
    from matplotlib.ticker import EngFormatter

    fig, axes = plt.subplots(2, 2, figsize=(14, 10.5), sharex=True)
    (ax_s, ax_r), (ax_lr, ax_sa) = axes
    many = len(runs) > 1
    metric_kinds = {sa_metric_kind(run.rows) for run in runs}
    metric = metric_kinds.pop() if len(metric_kinds) == 1 else None
    scale_m = 100.0 if metric == "success" else 1.0
    any_sa = any_decay = False
    drawn: list[tuple[str, str]] = []  # success series drawn: (label, colour)
    for i, run in enumerate(runs):
        style, marker = RUN_STYLES[i % len(RUN_STYLES)]
        look = dict(marker=marker, markevery=0.1, ms=4) if marker else {}
        label = (lambda text: None) if many else (lambda text: text)  # many runs: proxy legend entries below
        for key, name, colour, own_style in SUCCESS_SERIES:
            x, y = curve(run.rows, key)
            if not np.isfinite(y).any():
                continue
            share = _share(run.rows, key)
            if share is not None and not many:
                name = f"{name}: {100 * share:.0f} % of episodes"
            if (name, colour) not in drawn:
                drawn.append((name, colour))
            ax_s.plot(x, 100.0 * smooth(y, smooth_window), color=colour, ls=style if many else own_style,
                      lw=1.6 if key == "success" else 1.1, label=label(name), **look)
        x, y = curve(run.rows, "eval_success")
        if x.size:
            ax_s.plot(x, 100.0 * y, color=EVAL[1], ls=style, marker=marker or ".", ms=3.5, lw=0.9,
                      label=label(EVAL[0]))
            if EVAL not in drawn:
                drawn.append(EVAL)
        x, y = curve(run.rows, "return")
        ax_r.plot(x, smooth(y, smooth_window), color=TRAIN_RETURN, ls=style, lw=1.3,
                  label=label("training episodes (weights at progress p)"), **look)
        x, y = curve(run.rows, "eval_return")
        if x.size:
            ax_r.plot(x, y, color=EVAL[1], ls=style, marker=marker or ".", ms=3.5, lw=0.9,
                      label=label("evaluation (weights at p = 1)"))
        x, y = curve(run.rows, "lr")
        ax_lr.plot(x, y, color=LR_COLOUR, ls=style, lw=1.4, label=label("learning rate"), **look)
        decisions = sa_decisions(run.rows)
        if any(v[0].size for v in decisions.values()):
            any_sa = True
            x, y = curve([r for r in run.rows if "sa_decision" in r], "sa_metric")
            ax_sa.plot(x, scale_m * y, color=METRIC_COLOUR, ls=style, lw=0.8, alpha=0.7,
                       label=label("M per cycle"))
            for kind, (dx, dy) in decisions.items():
                mark, mc = DECISIONS[kind]
                ax_sa.scatter(dx, scale_m * dy, marker=mark, color=mc, s=18, zorder=3,
                              label=f"{kind} ({dx.size})" if not many else None)
            for step in [r["env_steps"] for r in run.rows if r.get("sa_decayed")]:
                any_decay = True
                ax_sa.axvline(step, color="tab:blue", ls=style if many else "--", lw=0.6, alpha=0.45)
    if any_decay and not many:
        ax_sa.plot([], [], color="tab:blue", ls="--", lw=0.8, label="lr decay")

    fmt = EngFormatter(sep="")
    for ax in axes.flat:
        ax.grid(alpha=0.3, which="both")
        ax.xaxis.set_major_formatter(fmt)
        ax.tick_params(labelbottom=True)
        ax.set_xlabel("env steps (all envs together)", fontsize=9)
    ax_s.set_ylabel("success (%)")
    ax_s.set_ylim(-2, 102)
    ax_s.set_title("Grasp success: training episodes by kind, and the per-cycle evaluation", fontsize=10,
                   fontweight="bold")
    ax_r.set_ylabel("return per episode (reward units)")
    ax_r.set_title("Return: shaped reward summed over an episode", fontsize=10, fontweight="bold")
    ax_lr.set_ylabel("learning rate (log scale)")
    ax_lr.set_yscale("log")
    ax_lr.set_title("Learning rate", fontsize=10, fontweight="bold")
    ax_sa.set_ylabel(METRIC_WORDS[metric][0])
    ax_sa.set_title("Simulated annealing: each cycle's metric M and decision", fontsize=10, fontweight="bold")
    if not any_sa:
        ax_sa.text(0.5, 0.5, "no SA decisions in this run\n(lr.schedule is not sa)", ha="center", va="center",
                   transform=ax_sa.transAxes)
    _caption(ax_s, CAPTIONS["success"])
    _caption(ax_r, CAPTIONS["return"])
    _caption(ax_lr, CAPTIONS["lr"])
    _caption(ax_sa, CAPTIONS["sa"].format(metric=METRIC_WORDS[metric][1]))

    if many:  # colours are the series, line styles the runs
        runs_legend = [Line2D([], [], color="0.3", ls=RUN_STYLES[i % len(RUN_STYLES)][0],
                              marker=RUN_STYLES[i % len(RUN_STYLES)][1], label=run.label) for i, run in enumerate(runs)]
        ax_s.legend(handles=[Line2D([], [], color=c, lw=1.6, label=n) for n, c in drawn] + runs_legend, fontsize=7,
                    loc="lower right")
        ax_r.legend(handles=[Line2D([], [], color=TRAIN_RETURN, label="training episodes (weights at progress p)"),
                             Line2D([], [], color=EVAL[1], marker=".", label="evaluation (weights at p = 1)")]
                    + runs_legend, fontsize=7)
        ax_lr.legend(handles=runs_legend, fontsize=7)
        if any_sa:
            ax_sa.legend(handles=[Line2D([], [], ls="", marker=m, color=c, label=k) for k, (m, c) in DECISIONS.items()]
                         + [Line2D([], [], color="tab:blue", ls="--", label="lr decay")] + runs_legend, fontsize=7)
    else:
        ax_s.legend(fontsize=7.5, loc="lower right")
        for ax in (ax_r, ax_lr, ax_sa):
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7.5)
    fig.suptitle(", ".join(r.label for r in runs), fontsize=10)
    return fig


def plot_runs(runs: Sequence[Run], out: str, smooth_window: int = 1) -> str:
    """The four panels of the module doc for ``runs``, written to ``out``."""
    return save(figure(runs, smooth_window), out)


def main(argv: Sequence[str] | None = None) -> int:
    p = cli.Parser(prog="python -m sagrasp_jax.plot", description=__doc__.split("\n\n")[0])
    p.add_argument("--run", action="append", required=True, help="run folder (or seed group); repeat to overlay runs")
    p.add_argument("--out", required=True, help="PNG file")
    p.add_argument("--smooth", type=int, default=1, help="moving average over N logged rows of the training curves")
    args = p.parse_args(argv)
    try:
        if not args.out.lower().endswith(".png"):
            raise PlotError(f"--out {args.out!r} must end in .png")
        if not 1 <= args.smooth <= 100_000:
            raise PlotError(f"--smooth must be in [1, 100000], got {args.smooth}")
        require_matplotlib()
        runs = load_runs(args.run)
        fileio.check_writable(args.out, "output folder", is_folder=False)
        plot_runs(runs, args.out, args.smooth)
    except (PlotError, OSError, extras.MissingExtra) as exc:
        print(f"{p.prog}: error: {exc}", file=sys.stderr)
        return 2
    steps = ", ".join(f"{r.rows[-1]['env_steps']:,}" for r in runs)
    print(f"wrote {args.out} ({len(runs)} run(s) up to {steps} env steps)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
