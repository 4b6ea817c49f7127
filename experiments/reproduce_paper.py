"""Reproduce the paper's PPO vs SA-PPO comparison (Figures 11-15, the 98/143 vs 92/154 table).

Trains ``--algo ppo`` and ``--algo sa-ppo`` for K seeds on one preset and step budget (in
process, through ``sagrasp_jax.train.run``), evaluates every final policy on
``--eval-episodes`` fixed-seed episodes (``sagrasp_jax.evaluate.evaluate_run``: deterministic
policy, reward weights at p = 1, held-out seeds), and writes into ``--out-dir``:

* ``fig11_distance_reward.png`` … ``fig14_steps_per_episode.png``: training-episode curves vs env
  steps (mean over seeds and a 95 % t-band across seeds, thin lines per seed), PPO vs SA-PPO;
  ``fig13`` also shows the fixed-seed evaluation success of every SA cycle;
* ``fig15_summary.png``: final success vs steps per successful grasp, ours and the paper's;
* ``sa_schedule.png``: SA-PPO's learning rate and temperature traces (and PPO's constant lr);
* ``results.json`` / ``results.md``: the results table next to the paper's numbers.

Runs go to ``--runs-dir/<algo>-s<seed>``.  Re-running the same command skips finished and
evaluated runs, evaluates finished ones, resumes unfinished ones from their checkpoint and
restarts ones killed before their first checkpoint; a run folder whose config differs from the
requested one is refused.

    python experiments/reproduce_paper.py --preset cpu-quick --total-steps 2000000 --seeds 3 \\
        --out-dir experiments/results/reproduce_cpu --runs-dir runs/reproduce_cpu
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import argparse
import json
import math
import os
import platform
import shutil
import sys
import time
import warnings
from typing import Any, Sequence

import numpy as np

from sagrasp_jax import evaluate, fileio, run_dir, train
from sagrasp_jax.checkpoint import CheckpointError
from sagrasp_jax.config import ConfigError, config_from_dict, config_to_dict

ALGOS = ("ppo", "sa-ppo")
LABELS = {"ppo": "PPO", "sa-ppo": "SA-PPO"}
COLOURS = {"ppo": "tab:blue", "sa-ppo": "tab:orange"}  # the paper's colours
PAPER = {  # docs/task.md §4 / paper §5.3: SB3 + PyBullet, 20M steps
    "ppo": {"success_pct": 92.0, "steps_per_success": 154.0},
    "sa-ppo": {"success_pct": 98.0, "steps_per_success": 143.0},
    "env_steps": 20_000_000,
}
# (file, row key, y label, title) of the training-episode curves, after the paper's figures.
CURVES = (
    ("fig11_distance_reward.png", "r_distance", "distance reward per episode", "Fig. 11 - distance reward"),
    ("fig12_mean_reward.png", "return", "reward per episode", "Fig. 12 - mean reward"),
    ("fig13_success_rate.png", "success", "success rate", "Fig. 13 - success rate"),
    ("fig14_steps_per_episode.png", "episode_steps", "steps per episode", "Fig. 14 - steps per episode"),
)
RESULTS_JSON = "results.json"
RESULTS_MD = "results.md"
EVAL_FILE = "evaluation.json"  # this experiment's own evaluation of each run (--eval-episodes, default seed)
# t_{0.975, df} for df = 1..30 (95 % two-sided); larger df use 1.96.
_T975 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145,
         2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048,
         2.045, 2.042)


class ReproduceError(RuntimeError):
    """A run folder or argument that the experiment cannot use."""


def t975(df: int) -> float:
    """Two-sided 95 % Student-t quantile."""
    return _T975[df - 1] if 1 <= df <= len(_T975) else 1.959964


def mean_ci(values: Sequence[float]) -> dict[str, Any]:
    """Mean and 95 % t-interval across seeds (``None`` bounds with fewer than 2 values)."""
    vals = np.asarray([v for v in values if v is not None and math.isfinite(v)], float)
    if vals.size == 0:
        return {"mean": None, "ci95": [None, None], "n": 0}
    m = float(vals.mean())
    if vals.size < 2:
        return {"mean": m, "ci95": [None, None], "n": 1}
    half = t975(vals.size - 1) * float(vals.std(ddof=1)) / math.sqrt(vals.size)
    return {"mean": m, "ci95": [m - half, m + half], "n": int(vals.size)}


def write_json(path: str, data: Any) -> str:
    """Atomic JSON write (no NaN)."""
    return fileio.atomic_write_json(path, data, sort_keys=True)


def run_name(algo: str, seed: int) -> str:
    return f"{algo}-s{seed}"


# ---------------------------------------------------------------------- training + evaluation

def run_state(out: str) -> str:
    """'new' | 'partial' (checkpoint, not finished) | 'trained' | 'evaluated' | 'stale' (no checkpoint)."""
    if not os.path.isdir(out) or not os.listdir(out):
        return "new"
    if os.path.isfile(os.path.join(out, EVAL_FILE)) and os.path.isfile(os.path.join(out, run_dir.POLICY_FILE)):
        return "evaluated"
    if os.path.isfile(os.path.join(out, run_dir.POLICY_FILE)):
        return "trained"
    if os.path.isfile(os.path.join(out, run_dir.CHECKPOINT_FILE)):
        return "partial"
    return "stale"


def check_same_config(out: str, cfg: Any) -> None:
    """Refuse to reuse a run folder trained with another config."""
    path = os.path.join(out, run_dir.CONFIG_FILE)
    try:
        with open(path, encoding="utf-8") as f:
            saved = json.load(f)
    except (FileNotFoundError, json.JSONDecodeError) as exc:
        raise ReproduceError(f"{path}: unreadable run config ({exc}); delete {out} to retrain it") from None
    want = json.loads(json.dumps(config_to_dict(cfg)))
    try:  # a config saved before a key was added or renamed means what config_from_dict makes of it
        saved = json.loads(json.dumps(config_to_dict(config_from_dict(saved))))
    except (ConfigError, TypeError, ValueError):
        pass  # compared as written (and refused below)
    if saved != want:
        diffs = _dict_diff(saved, want)
        raise ReproduceError(f"{out} was trained with another config ({'; '.join(diffs[:5])}); "
                             f"use another --runs-dir or delete the folder")


def _dict_diff(a: Any, b: Any, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out: list[str] = []
        for k in sorted(set(a) | set(b)):
            out += _dict_diff(a.get(k), b.get(k), f"{prefix}{k}.")
        return out
    return [] if a == b else [f"{prefix[:-1]}: {a!r} != {b!r}"]


def eval_is_current(out: str, episodes: int) -> bool:
    """The run's evaluation.json exists, has ``episodes`` episodes and evaluates the final checkpoint."""
    try:
        with open(os.path.join(out, EVAL_FILE), encoding="utf-8") as f:
            res = json.load(f)
        with open(os.path.join(out, run_dir.CONFIG_FILE), encoding="utf-8") as f:
            total = json.load(f)["train"]["total_steps"]
    except (FileNotFoundError, json.JSONDecodeError, KeyError):
        return False
    return res.get("episodes") == episodes and (res.get("checkpoint_env_steps") or 0) >= total


def ensure_trained(out: str, cfg: Any, tag: str, progress: bool) -> float | None:
    """Bring the run folder ``out`` to a finished training of ``cfg`` (``train.run``, in process).

    The one rule every experiment script follows: a folder trained with another config is refused
    (its config is checked before anything is deleted); a finished one is skipped; one with a
    checkpoint is resumed; one killed before its first checkpoint is started again.  Returns this
    call's training wall time (None: it was finished already)."""
    state = run_state(out)
    config_written = os.path.isfile(os.path.join(out, run_dir.CONFIG_FILE))
    if state != "new" and (state != "stale" or config_written):  # killed before its config: nothing to compare
        check_same_config(out, cfg)
    if state in ("trained", "evaluated"):
        return None
    if state == "stale":
        print(f"{tag}: {out} has no checkpoint (killed before the first one): starting it again", flush=True)
        shutil.rmtree(out)
    resume = state == "partial"
    print(f"{tag}: {'resuming' if resume else 'training'} {cfg.train.total_steps:,} env steps -> {out}", flush=True)
    t = time.perf_counter()
    train.run(cfg, out, resume=resume, progress=progress)
    wall = time.perf_counter() - t
    print(f"{tag}: trained in {wall:.0f} s", flush=True)
    return wall


def train_and_evaluate(algo: str, seed: int, args: argparse.Namespace, index: int, count: int) -> dict[str, Any]:
    """Bring one run to 'evaluated' (train / resume / skip) and return its evaluation."""
    out = os.path.join(args.runs_dir, run_name(algo, seed))
    cfg = train.build_config(args.preset, algo, seed, args.total_steps, args.overrides)
    tag = f"[{index}/{count}] {LABELS[algo]} seed {seed}"
    ensure_trained(out, cfg, tag, not args.no_progress)
    if eval_is_current(out, args.eval_episodes):
        print(f"{tag}: done already, skipped", flush=True)
    else:
        print(f"{tag}: evaluating {args.eval_episodes} episodes", flush=True)
        res = evaluate.evaluate_run(out, args.eval_episodes)
        evaluate.write_results(os.path.join(out, EVAL_FILE), res)
        ov = res["overall"]
        steps = ov.get("mean_steps_per_success")
        print(f"{tag}: success {100 * ov['success_rate']:.1f} %, steps/success "
              f"{'-' if steps is None else f'{steps:.1f}'}, collision {100 * ov['collision_rate']:.1f} %", flush=True)
    with open(os.path.join(out, EVAL_FILE), encoding="utf-8") as f:
        return json.load(f)


# ---------------------------------------------------------------------- aggregation

def load_curves(runs_dir: str, algo: str, seeds: Sequence[int]) -> list[list[dict[str, Any]]]:
    """metrics.jsonl rows of each seed's run."""
    return [run_dir.read_metrics(os.path.join(runs_dir, run_name(algo, s), run_dir.METRICS_FILE)) for s in seeds]


def curve_matrix(runs: list[list[dict[str, Any]]], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(env_steps, values[seed, step]) on the env-step grid shared by all seeds; NaN where missing."""
    grids = [{int(r["env_steps"]): r.get(key) for r in rows if r.get(key) is not None} for rows in runs]
    common = sorted(set().union(*[set(g) for g in grids])) if grids else []
    x = np.asarray(common, float)
    y = np.full((len(grids), len(common)), np.nan)
    for i, g in enumerate(grids):
        for j, step in enumerate(common):
            if step in g:
                y[i, j] = float(g[step])
    return x, y


def band(y: np.ndarray, kind: str = "t95") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean across seeds and a band at every point: ``t95`` (95 % Student-t interval of the mean) or
    ``minmax`` (range of the seeds); the band collapses to the mean where only one seed has a value."""
    n = np.sum(np.isfinite(y), axis=0)
    if y.size == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns
        mean = np.nanmean(y, axis=0)
        if kind == "minmax":
            return mean, np.nanmin(y, axis=0), np.nanmax(y, axis=0)
        sd = np.nanstd(y, axis=0, ddof=1) if y.shape[0] > 1 else np.zeros_like(mean)
        t = np.asarray([t975(int(k) - 1) if k > 1 else 0.0 for k in n])
        half = np.where(n > 1, t * sd / np.sqrt(np.maximum(n, 1)), 0.0)
    return mean, mean - half, mean + half


def band_kind(requested: str, n_seeds: int) -> str:
    """``auto``: the t-interval from 3 seeds on; with 2 (t = 12.7) it says nothing, so the seeds' range."""
    if requested != "auto":
        return requested
    return "t95" if n_seeds >= 3 else "minmax"


BAND_LABELS = {"t95": "95 % t-band across seeds", "minmax": "band: range of the seeds"}


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


def summarise_algo(evals: list[dict[str, Any]], seeds: Sequence[int]) -> dict[str, Any]:
    """Pooled-episode (Wilson) and across-seed (t) statistics of one algorithm's evaluations."""
    ov = [e["overall"] for e in evals]
    n = sum(o["episodes"] for o in ov)
    succ = sum(round(o["success_rate"] * o["episodes"]) for o in ov)
    coll = sum(round(o["collision_rate"] * o["episodes"]) for o in ov)
    tout = sum(round(o["timeout_rate"] * o["episodes"]) for o in ov)
    steps_sum = sum((o["mean_steps_per_success"] or 0.0) * round(o["success_rate"] * o["episodes"]) for o in ov)
    def group(name: str) -> dict[str, Any]:
        """Pooled success / collision of one obstacle group (Wilson 95 %)."""
        gs = [e.get(name, {"episodes": 0}) for e in evals]
        n_g = sum(g["episodes"] for g in gs)
        s_g = sum(round(g.get("success_rate", 0.0) * g["episodes"]) for g in gs)
        c_g = sum(round(g.get("collision_rate", 0.0) * g["episodes"]) for g in gs)
        return {"episodes": n_g, "success_pct": 100.0 * s_g / n_g if n_g else None,
                "success_ci95_wilson_pct": [100.0 * v for v in evaluate.wilson_interval(s_g, n_g)] if n_g else None,
                "collision_pct": 100.0 * c_g / n_g if n_g else None}

    def pct(x: dict[str, Any]) -> dict[str, Any]:
        """Fractions to percent; the t-interval is clipped to [0, 100]."""
        scale = (lambda v: None if v is None else min(100.0, max(0.0, 100.0 * v)))
        return {"mean": scale(x["mean"]), "ci95": [scale(v) for v in x["ci95"]], "n": x["n"]}

    return {
        "seeds": list(seeds),
        "episodes_per_seed": [o["episodes"] for o in ov],
        "pooled": {
            "episodes": n,
            "success_pct": 100.0 * succ / n,
            "success_ci95_wilson_pct": [100.0 * v for v in evaluate.wilson_interval(succ, n)],
            "collision_pct": 100.0 * coll / n,
            "collision_ci95_wilson_pct": [100.0 * v for v in evaluate.wilson_interval(coll, n)],
            "timeout_pct": 100.0 * tout / n,
            "successes": succ,
            "steps_per_success": steps_sum / succ if succ else None,
            "obstacle_present": group("obstacle_present"),
            "obstacle_absent": group("obstacle_absent"),
        },
        "across_seeds": {
            "success_pct": pct(mean_ci([o["success_rate"] for o in ov])),
            "steps_per_success": mean_ci([o["mean_steps_per_success"] for o in ov]),
            "collision_pct": pct(mean_ci([o["collision_rate"] for o in ov])),
        },
        "per_seed": [{"seed": s, "success_pct": 100.0 * o["success_rate"],
                      "steps_per_success": o["mean_steps_per_success"], "collision_pct": 100.0 * o["collision_rate"],
                      "timeout_pct": 100.0 * o["timeout_rate"]} for s, o in zip(seeds, ov)],
    }


def git_state() -> str:
    """``<commit>`` of the checkout, ``+dirty`` when tracked files are modified (or 'unknown')."""
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def env_hashes(runs_dir: str, algo: str, seeds: Sequence[int]) -> list[str]:
    """``config.config_hash`` of the env config each run was trained with (from its raw config.json)."""
    import hashlib

    out = []
    for s in seeds:
        with open(os.path.join(runs_dir, run_name(algo, s), run_dir.CONFIG_FILE), encoding="utf-8") as f:
            env = json.load(f)["env"]
        out.append(hashlib.sha256(json.dumps(env, sort_keys=True).encode()).hexdigest()[:12])
    return out


def training_summary(runs: list[list[dict[str, Any]]]) -> dict[str, Any]:
    """Per seed: training speed, compile time, SA counts, last lr (from the last metrics row)."""
    out = []
    for rows in runs:
        last = rows[-1]
        sa_rows = [r for r in rows if "sa_decision" in r]
        decays = [r["env_steps"] for r in rows if r.get("sa_decayed")]
        out.append({
            "env_steps": last["env_steps"],
            "train_s": last.get("time_s"),
            "steps_per_s_incl_eval": last["env_steps"] / last["time_s"] if last.get("time_s") else None,
            "compile_s": last.get("compile_s"),
            "sa_accepts": last.get("sa_accepts"), "sa_accept_worse": last.get("sa_accept_worse"),
            "sa_rejects": last.get("sa_rejects"), "sa_decays": last.get("sa_decays"),
            "cycles": len(sa_rows), "final_lr": last.get("lr"),
            "first_decay_env_steps": decays[0] if decays else None,
            "last_eval_success": sa_rows[-1].get("eval_success") if sa_rows else None,
            "first_temperature": sa_rows[0].get("temperature") if sa_rows else None,
            "final_temperature": sa_rows[-1].get("temperature") if sa_rows else None,
        })
    return {"per_seed": out}


CURVE_FRACTIONS = (0.1, 0.25, 0.4, 0.6, 0.8, 1.0)


def curve_points(runs: list[list[dict[str, Any]]], total: int, window: int) -> list[dict[str, Any]]:
    """Seed means of the plotted (smoothed) curves at fixed fractions of the budget, for the docs."""
    keys = [c[1] for c in CURVES] + ["eval_success", "lr", "temperature"]
    mats = {k: curve_matrix(runs, k) for k in keys}
    out = []
    for frac in CURVE_FRACTIONS:
        point: dict[str, Any] = {"fraction": frac}
        for k, (x, y) in mats.items():
            if x.size == 0:
                point[k] = None
                continue
            y = smooth(y, window) if k in [c[1] for c in CURVES] else y
            j = int(np.argmin(np.abs(x - frac * total)))
            col = y[:, j]
            point[k] = float(np.nanmean(col)) if np.isfinite(col).any() else None
            point.setdefault("env_steps", int(x[j]))
        out.append(point)
    return out


def _fmt_ci(mean: Any, ci: Sequence[Any], digits: int = 1) -> str:
    if mean is None:
        return "-"
    if ci[0] is None:
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} [{ci[0]:.{digits}f}, {ci[1]:.{digits}f}]"


def markdown_table(results: dict[str, Any]) -> str:
    """The results table (ours next to the paper's) as Markdown."""
    meta = results["meta"]
    lines = [
        f"Preset `{meta['preset']}`, {meta['total_steps']:,} env steps per run, seeds {meta['seeds']}, "
        f"{meta['eval_episodes']} evaluation episodes per seed (deterministic policy, reward weights at p = 1). "
        "Success and collision: pooled over all seeds' episodes with the 95 % Wilson interval; "
        "steps per successful grasp: pooled mean over all successful episodes with the 95 % t-interval "
        "of the per-seed means (across seeds). Across-seed intervals of every metric are in the next table.",
        "",
        "| algorithm | success % [95 % CI, pooled] | steps / successful grasp [95 % CI, across seeds] "
        "| collision % [95 % CI, pooled] | timeout % | paper success % | paper steps |",
        "|---|---|---|---|---|---|---|",
    ]
    for algo in ALGOS:
        r = results["algos"][algo]
        p, a = r["pooled"], r["across_seeds"]
        lines.append(
            f"| {LABELS[algo]} | {_fmt_ci(p['success_pct'], p['success_ci95_wilson_pct'])} "
            f"| {_fmt_ci(p['steps_per_success'], a['steps_per_success']['ci95'])} "
            f"| {_fmt_ci(p['collision_pct'], p['collision_ci95_wilson_pct'])} | {p['timeout_pct']:.1f} "
            f"| {PAPER[algo]['success_pct']:.0f} | {PAPER[algo]['steps_per_success']:.0f} |")
    lines += ["", "| algorithm | episodes with obstacles: success % [95 % CI] | collision % "
                  "| episodes without: success % [95 % CI] | collision % |", "|---|---|---|---|---|"]
    for algo in ALGOS:
        p = results["algos"][algo]["pooled"]
        cells = []
        for name in ("obstacle_present", "obstacle_absent"):
            g = p[name]
            if not g["episodes"]:
                cells += ["- (0 episodes)", "-"]
                continue
            ci = g["success_ci95_wilson_pct"]
            cells += [f"{_fmt_ci(g['success_pct'], ci)} (n = {g['episodes']})", f"{g['collision_pct']:.1f}"]
        lines.append(f"| {LABELS[algo]} | " + " | ".join(cells) + " |")
    lines += ["", "| algorithm | seed | success % | steps / success | collision % | timeout % |",
              "|---|---|---|---|---|---|"]
    for algo in ALGOS:
        r = results["algos"][algo]
        for s in r["per_seed"]:
            steps = "-" if s["steps_per_success"] is None else f"{s['steps_per_success']:.1f}"
            lines.append(f"| {LABELS[algo]} | {s['seed']} | {s['success_pct']:.1f} | {steps} | "
                         f"{s['collision_pct']:.1f} | {s['timeout_pct']:.1f} |")
        a = r["across_seeds"]
        lines.append(f"| {LABELS[algo]} | mean [95 % t-CI across seeds] | {_fmt_ci(a['success_pct']['mean'], a['success_pct']['ci95'])} "
                     f"| {_fmt_ci(a['steps_per_success']['mean'], a['steps_per_success']['ci95'])} "
                     f"| {_fmt_ci(a['collision_pct']['mean'], a['collision_pct']['ci95'])} | |")
    d = results["difference_sa_minus_ppo"]
    d_steps = "-" if d["steps_per_success"] is None else f"{d['steps_per_success']:+.1f}"
    lines += ["", f"SA-PPO − PPO, pooled: success {d['success_pct']:+.1f} points, steps per successful grasp "
                  f"{d_steps}; paper: +6 points, −11 steps."]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------- plots

def plot_all(out_dir: str, curves: dict[str, list[list[dict[str, Any]]]], results: dict[str, Any],
             smooth_window: int) -> list[str]:
    """Write Figures 11-15 and the SA schedule trace; returns the file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    n_seeds = len(results["meta"]["seeds"])
    kind = results["meta"]["band"]
    band_note = f"mean of {n_seeds} seeds, {BAND_LABELS[kind]}"
    for fname, key, ylabel, title in CURVES:
        panels = 2 if key == "success" else 1
        fig, axes = plt.subplots(1, panels, figsize=(6.4 * panels, 4.2), squeeze=False)
        ax = axes[0, 0]
        for algo in ALGOS:
            x, y = curve_matrix(curves[algo], key)
            if key == "success":
                y = 100.0 * y
            y = smooth(y, smooth_window)
            for row in y:
                ax.plot(x, row, color=COLOURS[algo], alpha=0.25, lw=0.7)
            mean, lo, hi = band(y, kind)
            ax.plot(x, mean, color=COLOURS[algo], lw=1.8, label=LABELS[algo])
            ax.fill_between(x, lo, hi, color=COLOURS[algo], alpha=0.2, lw=0)
        ax.set_xlabel("env steps")
        ax.set_ylabel(ylabel + (" (%)" if key == "success" else ""))
        ax.set_title(f"{title} (training episodes)", fontsize=10)
        ax.grid(alpha=0.3)
        if key == "success":
            ax.set_ylim(-2, 102)
        ax.legend(title=band_note, title_fontsize=7, fontsize=8)
        if key == "success":
            ax = axes[0, 1]
            for algo in ALGOS:
                x, y = curve_matrix(curves[algo], "eval_success")
                y = 100.0 * y
                for row in y:
                    ok = np.isfinite(row)
                    ax.plot(x[ok], row[ok], color=COLOURS[algo], alpha=0.25, lw=0.7)
                mean, lo, hi = band(y, kind)
                ok = np.isfinite(mean)
                ax.plot(x[ok], mean[ok], color=COLOURS[algo], lw=1.8, label=LABELS[algo])
                ax.fill_between(x[ok], lo[ok], hi[ok], color=COLOURS[algo], alpha=0.2, lw=0)
            ax.set_xlabel("env steps")
            ax.set_ylabel("success (%)")
            ax.set_ylim(-2, 102)
            ax.set_title("fixed-seed evaluation each SA cycle (deterministic, p = 1)", fontsize=10)
            ax.grid(alpha=0.3)
            ax.legend(title=band_note, title_fontsize=7, fontsize=8)
        fig.tight_layout()
        fig.savefig(os.path.join(out_dir, fname), dpi=110)
        plt.close(fig)
        written.append(fname)

    # Figure 15: final success vs steps per successful grasp, ours (per seed + pooled) and the paper's.
    fig, ax = plt.subplots(figsize=(6.4, 4.6))
    for algo in ALGOS:
        r = results["algos"][algo]
        for s in r["per_seed"]:
            if s["steps_per_success"] is not None:
                ax.scatter(s["steps_per_success"], s["success_pct"], color=COLOURS[algo], alpha=0.4, s=18)
        p = r["pooled"]
        if p["steps_per_success"] is not None:
            lo, hi = p["success_ci95_wilson_pct"]
            sci = r["across_seeds"]["steps_per_success"]["ci95"]
            xerr = None if sci[0] is None else [[p["steps_per_success"] - sci[0]], [sci[1] - p["steps_per_success"]]]
            ax.errorbar(p["steps_per_success"], p["success_pct"], yerr=[[p["success_pct"] - lo], [hi - p["success_pct"]]],
                        xerr=xerr, fmt="o", color=COLOURS[algo], ms=8, capsize=3, label=f"{LABELS[algo]} (ours)")
        ax.scatter(PAPER[algo]["steps_per_success"], PAPER[algo]["success_pct"], marker="*", s=160,
                   color=COLOURS[algo], edgecolor="k", label=f"{LABELS[algo]} (paper, 20M steps)")
    ax.set_xlabel("mean steps per successful grasp\n(error bars: success 95 % Wilson, pooled; "
                  "steps 95 % t across seeds; dots: single seeds)", fontsize=8)
    ax.set_ylabel("success rate (%)")
    ax.set_title(f"Fig. 15 - success vs steps ({results['meta']['total_steps']:,} steps, "
                 f"{results['meta']['eval_episodes']} eval episodes / seed)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "fig15_summary.png"), dpi=110)
    plt.close(fig)
    written.append("fig15_summary.png")

    # SA schedule: lr (log) and temperature per cycle, every seed; reject / decay markers.
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(7.5, 5.6), sharex=True)
    for i, rows in enumerate(curves["sa-ppo"]):
        cyc = [r for r in rows if "sa_decision" in r]
        x = [r["env_steps"] for r in cyc]
        ax1.plot(x, [r["lr"] for r in cyc], color=COLOURS["sa-ppo"], alpha=0.9 - 0.2 * i, lw=1.2,
                 label="SA-PPO" if i == 0 else None)
        rej = [r for r in cyc if r["sa_decision"] == "reject"]
        ax1.scatter([r["env_steps"] for r in rej], [r["lr"] for r in rej], marker="x", color="k", s=12,
                    label="reject" if i == 0 else None, zorder=3)
        worse = [r for r in cyc if r["sa_decision"] == "accept-worse"]
        ax1.scatter([r["env_steps"] for r in worse], [r["lr"] for r in worse], marker="^", color="tab:red", s=12,
                    label="accept-worse" if i == 0 else None, zorder=3)
        ax2.plot(x, [r["temperature"] for r in cyc], color=COLOURS["sa-ppo"], alpha=0.9 - 0.2 * i, lw=1.2)
    for i, rows in enumerate(curves["ppo"]):
        ax1.plot([r["env_steps"] for r in rows], [r["lr"] for r in rows], color=COLOURS["ppo"], lw=1.0, ls="--",
                 label="PPO (constant)" if i == 0 else None)
    ax1.set_yscale("log")
    ax1.set_ylabel("learning rate")
    ax1.set_title("SA-PPO schedule: lr and temperature per cycle (one line per seed)", fontsize=10)
    ax1.grid(alpha=0.3, which="both")
    ax1.legend(fontsize=7)
    ax2.set_ylabel("temperature T (return units)")
    ax2.set_xlabel("env steps")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "sa_schedule.png"), dpi=110)
    plt.close(fig)
    written.append("sa_schedule.png")
    return written


# ---------------------------------------------------------------------- main

def build_results(args: argparse.Namespace, evals: dict[str, list[dict[str, Any]]],
                  curves: dict[str, list[list[dict[str, Any]]]], wall_s: float) -> dict[str, Any]:
    algos = {a: {**summarise_algo(evals[a], args.seeds), "training": training_summary(curves[a]),
                 "env_config_hash": env_hashes(args.runs_dir, a, args.seeds),
                 "curve_points": curve_points(curves[a], args.total_steps, args.smooth)} for a in ALGOS}
    sa, pp = algos["sa-ppo"]["pooled"], algos["ppo"]["pooled"]
    run_s = [(r["train_s"] or 0.0) + (r["compile_s"] or 0.0) for a in ALGOS for r in algos[a]["training"]["per_seed"]]
    diff_steps = (None if sa["steps_per_success"] is None or pp["steps_per_success"] is None
                  else sa["steps_per_success"] - pp["steps_per_success"])
    return {
        "meta": {
            "preset": args.preset, "total_steps": args.total_steps, "seeds": list(args.seeds),
            "eval_episodes": args.eval_episodes, "overrides": list(args.overrides),
            "band": band_kind(args.band, len(args.seeds)), "smooth_window": args.smooth,
            "eval_seed": evals["ppo"][0].get("seed"), "runs_dir": os.path.abspath(args.runs_dir),
            "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} CPU cores",
            "python": sys.version.split()[0], "wall_s_this_invocation": wall_s, "git_at_aggregation": git_state(),
            "train_plus_compile_s_all_runs": sum(run_s),
            "command": "python experiments/reproduce_paper.py " + " ".join(args.argv),
            "ci_note": ("pooled: Wilson 95 % interval over all seeds' evaluation episodes; across_seeds: "
                        "mean of the per-seed values with the 95 % Student-t interval (n = seeds)"),
            "curves_note": ("figure curves are training-episode means over the last train.metrics_window "
                            "finished episodes (reward weights at the current progress p), per iteration; "
                            "eval_success is the fixed-seed deterministic evaluation at p = 1 of every SA cycle"),
        },
        "paper": PAPER,
        "algos": algos,
        "difference_sa_minus_ppo": {"success_pct": sa["success_pct"] - pp["success_pct"], "steps_per_success": diff_steps},
    }


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="cpu-quick", help="trainer preset (cpu-quick, gpu, paper)")
    p.add_argument("--total-steps", type=int, default=None, help="env steps per run (default: the preset's)")
    p.add_argument("--seeds", type=int, default=5, help="number of seeds per algorithm (seeds 0..K-1)")
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--eval-episodes", type=int, default=1000)
    p.add_argument("--out-dir", required=True, help="where plots and tables go")
    p.add_argument("--runs-dir", default=None, help="where run folders go (default OUT_DIR/runs)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="trainer config override for every run, repeatable")
    p.add_argument("--band", choices=("auto", "t95", "minmax"), default="auto",
                   help="curve band: 95 %% t-interval across seeds, the seeds' range, or auto (t95 from 3 seeds)")
    p.add_argument("--smooth", type=int, default=5, help="moving-average window (iterations) of the curves")
    p.add_argument("--no-progress", action="store_true", help="no live training progress bar")
    p.add_argument("--plots-only", action="store_true", help="only aggregate finished, evaluated runs")
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    if args.seeds < 1:
        p.error("--seeds must be >= 1")
    if args.eval_episodes < 1:
        p.error("--eval-episodes must be >= 1")
    args.seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    args.runs_dir = args.runs_dir or os.path.join(args.out_dir, "runs")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    t0 = time.perf_counter()
    try:
        probe = train.build_config(args.preset, "ppo", 0, args.total_steps, args.overrides)
        args.total_steps = probe.train.total_steps
        os.makedirs(args.out_dir, exist_ok=True)
        os.makedirs(args.runs_dir, exist_ok=True)
        jobs = [(a, s) for s in args.seeds for a in ALGOS]
        evals: dict[str, list[dict[str, Any]]] = {a: [] for a in ALGOS}
        for i, (algo, seed) in enumerate(jobs, 1):
            if args.plots_only:
                out = os.path.join(args.runs_dir, run_name(algo, seed))
                if run_state(out) != "evaluated":
                    raise ReproduceError(f"--plots-only: {out} is not finished and evaluated")
                with open(os.path.join(out, EVAL_FILE), encoding="utf-8") as f:
                    evals[algo].append(json.load(f))
            else:
                evals[algo].append(train_and_evaluate(algo, seed, args, i, len(jobs)))
        curves = {a: load_curves(args.runs_dir, a, args.seeds) for a in ALGOS}
        results = build_results(args, evals, curves, time.perf_counter() - t0)
        results["files"] = plot_all(args.out_dir, curves, results, args.smooth)
        md = markdown_table(results)
        write_json(os.path.join(args.out_dir, RESULTS_JSON), results)
        fileio.atomic_write_text(os.path.join(args.out_dir, RESULTS_MD), md)
    except (ConfigError, CheckpointError, ReproduceError, FileExistsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(md)
    print(f"written to {args.out_dir} ({RESULTS_JSON}, {RESULTS_MD}, {', '.join(results['files'])})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
