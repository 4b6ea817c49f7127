"""Plot a run's learning curves: ``python -m sagrasp_jax.plot --run runs/NAME --out curves.png``.

Four panels from the run's ``metrics.jsonl`` against env steps (the ``plots`` extra: matplotlib):

* **success (%)** of the training episodes per kind — without obstacle, with one, blocking — over
  the last ``train.metrics_window`` finished episodes (runs logged before these keys: all episodes
  together), and the per-cycle deterministic evaluation (``eval.episodes`` fixed scenes, p = 1);
* **return** per training episode (same window) and of the per-cycle evaluation;
* **learning rate** (log scale);
* **SA decisions**: the per-cycle metric SA judged, marked accept / accept-worse / reject, with the
  lr decays as vertical lines (other lr schedules: the panel says none were made).

``--run`` may be repeated (runs overlaid, one colour each); a seed group (``train --seeds``) plots
each of its seeds.  ``--smooth N`` averages the training curves over N logged rows.  The PNG is
written atomically.  jax-free: the file is read with ``run_files``.  ``smooth`` and ``pyplot`` serve
the studies' figures too (``experiments/reproduce_paper.py``, ``experiments/compare_schedules.py``).
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any, NamedTuple, Sequence

import numpy as np

from sagrasp_jax.base import extras
from sagrasp_jax.base import fileio
from sagrasp_jax.base import run_files

# success keys of a metrics row: (key, label, line style); training-window means, then the evaluation's
KIND_CURVES = (("success_no_obstacle", "no obstacle", "-"), ("success_obstacle", "obstacle", "--"),
               ("success_blocking", "blocking", ":"))
DECISIONS = {"accept": ("o", "tab:green"), "accept-worse": ("^", "tab:orange"), "reject": ("x", "tab:red")}


class PlotError(ValueError):
    """Bad input for the plot (options, run folders); the message names it."""


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


def curve(rows: Sequence[dict[str, Any]], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(env steps, values) of the rows that carry ``key``; a null value (no such episode yet) is NaN."""
    pts = [(r["env_steps"], r[key]) for r in rows if key in r and not isinstance(r[key], (str, bool))]
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


def load_runs(folders: Sequence[str]) -> list[Run]:
    """Every ``--run``: a run folder, or each seed of a seed group."""
    runs = []
    for folder in folders:
        seeds = [] if os.path.isfile(os.path.join(folder, run_files.CONFIG_FILE)) else run_files.seed_folders(folder)
        for run in seeds or [folder]:
            try:
                rows = run_files.read_metrics(run)
            except run_files.RunFolderError as exc:
                raise PlotError(str(exc)) from None
            if not rows:
                raise PlotError(f"{run}: the metrics log has no rows yet (the training logs one per iteration)")
            runs.append(Run(os.path.normpath(run), rows))
    return runs


def plot_runs(runs: Sequence[Run], out: str, smooth_window: int = 1) -> str:
    """The four panels of the module doc for ``runs``, written to ``out``."""
    plt = pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(12, 8), sharex=True)
    (ax_s, ax_r), (ax_lr, ax_sa) = axes
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    many = len(runs) > 1
    any_sa = False
    for i, run in enumerate(runs):
        c = colours[i % len(colours)]
        tag = f"{run.label}: " if many else ""
        kinds = [k for k in KIND_CURVES if np.isfinite(curve(run.rows, k[0])[1]).any()]
        for key, label, style in kinds or [("success", "all episodes", "-")]:
            x, y = curve(run.rows, key)
            ax_s.plot(x, 100.0 * smooth(y, smooth_window), color=c, ls=style, lw=1.2, label=f"{tag}training, {label}")
        x, y = curve(run.rows, "eval_success")
        if x.size:
            ax_s.plot(x, 100.0 * y, color=c, marker=".", ms=3, lw=0.8, alpha=0.7, label=f"{tag}evaluation")
        x, y = curve(run.rows, "return")
        ax_r.plot(x, smooth(y, smooth_window), color=c, lw=1.2, label=f"{tag}training episodes")
        x, y = curve(run.rows, "eval_return")
        if x.size:
            ax_r.plot(x, y, color=c, marker=".", ms=3, lw=0.8, alpha=0.7, label=f"{tag}evaluation")
        x, y = curve(run.rows, "lr")
        ax_lr.plot(x, y, color=c, lw=1.2, label=run.label if many else None)
        decisions = sa_decisions(run.rows)
        if any(v[0].size for v in decisions.values()):
            any_sa = True
            x, y = curve([r for r in run.rows if "sa_decision" in r], "sa_metric")
            ax_sa.plot(x, y, color=c, lw=0.8, alpha=0.6)
            for kind, (dx, dy) in decisions.items():
                marker, mc = DECISIONS[kind]
                ax_sa.scatter(dx, dy, marker=marker, color=mc, s=16, zorder=3,
                              label=f"{tag}{kind} ({dx.size})" if dx.size or not many else None)
            for step in [r["env_steps"] for r in run.rows if r.get("sa_decayed")]:
                ax_sa.axvline(step, color=c, ls="--", lw=0.6, alpha=0.5)
    ax_s.set_ylabel("success (%)")
    ax_s.set_ylim(-2, 102)
    ax_s.set_title("success: training episodes per kind (window), per-cycle evaluation", fontsize=10)
    ax_r.set_ylabel("return per episode")
    ax_r.set_title("return", fontsize=10)
    ax_lr.set_ylabel("learning rate")
    ax_lr.set_yscale("log")
    ax_lr.set_title("learning rate", fontsize=10)
    ax_sa.set_ylabel("SA metric per cycle")
    ax_sa.set_title("SA decisions (dashed: lr decays)", fontsize=10)
    if not any_sa:
        ax_sa.text(0.5, 0.5, "no SA decisions in this run\n(lr.schedule is not sa)", ha="center", va="center",
                   transform=ax_sa.transAxes)
    for ax in axes.flat:
        ax.grid(alpha=0.3, which="both")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    for ax in axes[1]:
        ax.set_xlabel("env steps")
    fig.suptitle(", ".join(r.label for r in runs), fontsize=10)
    return save(fig, out)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m sagrasp_jax.plot", description=__doc__.split("\n\n")[0])
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
