"""Reproduce the paper's PPO vs SA-PPO comparison (Figures 11-15, the 98/143 vs 92/154 table).

A study over ``experiments.study`` with two variants, the paper's algorithms: ``ppo`` (the constant
learning rate) and ``sa-ppo`` (the SA schedule, docs/task.md §3), K seeds each on one preset and
step budget.  Every final policy is evaluated on ``--eval-episodes`` fixed-seed episodes
(``evaluation.evaluate_run``: deterministic policy, reward weights at p = 1, held-out seeds), and
``--out-dir`` gets (the report's part below, which ``compare_schedules`` uses too for its ``constant`` / ``sa``
runs):

* ``fig11_distance_reward.png`` … ``fig14_steps_per_episode.png``: training-episode curves vs env
  steps (mean over seeds and a 95 % t-band across seeds, thin lines per seed), PPO vs SA-PPO;
  ``fig13`` also shows the fixed-seed evaluation success of every SA cycle;
* ``fig15_summary.png``: final success vs steps per successful grasp, ours and the paper's;
* ``sa_schedule.png``: SA-PPO's learning rate and temperature traces (and PPO's constant lr);
* ``results.json`` / ``results.md``: the results table next to the paper's numbers.

Runs go to ``--runs-dir/<algo>/seed<S>/`` (default ``OUT_DIR/runs``).  Re-running the same
command skips evaluated runs and evaluates finished ones; a run stopped before it finished is
continued with ``--resume``; a run folder whose config differs from the requested one is refused.
Run from the repository root:

    python -m experiments.reproduce_paper --preset cpu-quick --total-steps 2000000 --seeds 3 \\
        --out-dir experiments/results/reproduce_cpu --runs-dir runs/reproduce_cpu
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import platform
import sys
import time
from typing import Any, Sequence

import numpy as np

from experiments import study
from experiments.study import Study, git_state, load_curves, machine
from sagrasp_jax.training import evaluation
from sagrasp_jax.plot import pyplot, save, smooth  # the package's plotting helpers (python -m sagrasp_jax.plot)
from sagrasp_jax.task import reward
from sagrasp_jax.training import run_dir
from sagrasp_jax.training.stats import BAND_LABELS, band, band_kind, curve_matrix, mean_ci
from sagrasp_jax.training import stats
from sagrasp_jax.base import fileio

# The study's variants: the paper's two algorithms as learning-rate schedules (what `train --algo` means).
VARIANTS: dict[str, tuple[str, ...]] = {"ppo": ("lr.schedule=constant",), "sa-ppo": ("lr.schedule=sa",)}
RESULTS_JSON = "results.json"
RESULTS_MD = "results.md"
RECORD_FILE = "evaluation.json"  # this experiment's record of each run (its --eval-episodes evaluation)
PAIRED = (("success_pct", True), ("steps_per_success", False), ("collision_pct", False))  # ppo vs sa-ppo, seed by seed


# ---------------------------------------------------------------------- the report: figures and table

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
    ("fig11_distance_reward.png", reward.DISTANCE.key, "distance reward per episode", "Fig. 11 - distance reward"),
    ("fig12_mean_reward.png", "return", "reward per episode", "Fig. 12 - mean reward"),
    ("fig13_success_rate.png", "success", "success rate", "Fig. 13 - success rate"),
    ("fig14_steps_per_episode.png", "episode_steps", "steps per episode", "Fig. 14 - steps per episode"),
)


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
                "success_ci95_wilson_pct": [100.0 * v for v in evaluation.wilson_interval(s_g, n_g)] if n_g else None,
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
            "success_ci95_wilson_pct": [100.0 * v for v in evaluation.wilson_interval(succ, n)],
            "collision_pct": 100.0 * coll / n,
            "collision_ci95_wilson_pct": [100.0 * v for v in evaluation.wilson_interval(coll, n)],
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



def env_hashes(folders: Sequence[str]) -> list[str]:
    """``config_history.config_hash`` of the env config each run was trained with (from its raw config.json)."""
    out = []
    for folder in folders:
        with open(os.path.join(folder, run_dir.CONFIG_FILE), encoding="utf-8") as f:
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
    paired = results.get("paired_ppo_minus_sa_ppo", {}).get("success_pct")
    if paired and paired["mean_diff"] is not None:
        p = "-" if paired["p"] is None else f"{paired['p']:.2g}"
        lines.append(f"PPO − SA-PPO seed by seed: success {paired['mean_diff']:+.1f} points (paired t-test p {p}; "
                     f"PPO better on {paired['wins']} of {paired['n']} seeds).")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------- plots

def plot_all(out_dir: str, curves: dict[str, list[list[dict[str, Any]]]], results: dict[str, Any],
             smooth_window: int) -> list[str]:
    """Write Figures 11-15 and the SA schedule trace; returns the file names."""
    plt = pyplot()
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
        save(fig, os.path.join(out_dir, fname))
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
    save(fig, os.path.join(out_dir, "fig15_summary.png"))
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
    save(fig, os.path.join(out_dir, "sa_schedule.png"))
    written.append("sa_schedule.png")
    return written



# ---------------------------------------------------------------------- the whole report

def build_results(study: Study, runs: dict[str, str], evals: dict[str, list[dict[str, Any]]], band_choice: str,
                  smooth_window: int, eval_episodes: int) -> tuple[dict[str, Any], dict[str, list[list[dict[str, Any]]]]]:
    """The results (``results.json``) of the paper's two algorithms, ``runs`` naming the study variant
    that stands for each (``{"ppo": ..., "sa-ppo": ...}``), and each algorithm's training curves."""
    curves = {a: load_curves(study, runs[a]) for a in ALGOS}
    algos = {a: {**summarise_algo(evals[a], study.seeds), "training": training_summary(curves[a]),
                 "env_config_hash": env_hashes([study.folder(runs[a], s) for s in study.seeds]),
                 "curve_points": curve_points(curves[a], study.total_steps, smooth_window)} for a in ALGOS}
    sa, pp = algos["sa-ppo"]["pooled"], algos["ppo"]["pooled"]
    run_s = [(r["train_s"] or 0.0) + (r["compile_s"] or 0.0) for a in ALGOS for r in algos[a]["training"]["per_seed"]]
    diff_steps = (None if sa["steps_per_success"] is None or pp["steps_per_success"] is None
                  else sa["steps_per_success"] - pp["steps_per_success"])
    meta = {
        "preset": study.preset, "total_steps": study.total_steps, "seeds": list(study.seeds),
        "eval_episodes": eval_episodes, "overrides": list(study.overrides),
        "band": band_kind(band_choice, len(study.seeds)), "smooth_window": smooth_window,
        "eval_seed": evals["ppo"][0].get("seed"), "runs_dir": os.path.abspath(study.runs_dir), "variants": runs,
        "machine": f"{platform.node()} {machine()}", "python": sys.version.split()[0],
        "git_at_aggregation": git_state(), "train_plus_compile_s_all_runs": sum(run_s),
        "ci_note": ("pooled: Wilson 95 % interval over all seeds' evaluation episodes; across_seeds: "
                    "mean of the per-seed values with the 95 % Student-t interval (n = seeds)"),
        "curves_note": ("figure curves are training-episode means over the last train.metrics_window "
                        "finished episodes (reward weights at the current progress p), per iteration; "
                        "eval_success is the fixed-seed deterministic evaluation at p = 1 of every SA cycle"),
    }
    return {"meta": meta, "paper": PAPER, "algos": algos,
            "difference_sa_minus_ppo": {"success_pct": sa["success_pct"] - pp["success_pct"],
                                        "steps_per_success": diff_steps}}, curves


# ---------------------------------------------------------------------- the study

def measure(episodes: int) -> study.Measure:
    """A run's record: its evaluation on ``episodes`` episodes of the evaluation mix."""
    def run(folder: str, variant: str, seed: int) -> dict[str, Any]:
        mix = study.Evaluation(episodes)(folder)
        ov = mix["overall"]
        steps = ov.get("mean_steps_per_success")
        print(f"{variant} seed {seed}: success {100 * ov['success_rate']:.1f} %, steps/success "
              f"{'-' if steps is None else f'{steps:.1f}'}, collision {100 * ov['collision_rate']:.1f} %", flush=True)
        return {"mix": mix}
    return run


def per_seed(record: dict[str, Any]) -> dict[str, Any]:
    """The paired metrics of one run."""
    ov = record["mix"]["overall"]
    return {"seed": record["seed"], "success_pct": study.rate(ov), "steps_per_success": ov["mean_steps_per_success"],
            "collision_pct": study.rate(ov, "collision_rate")}


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m experiments.reproduce_paper", description=__doc__.split("\n\n")[0])
    study.add_arguments(p, seeds=5, runs_dir=None, variants=False)  # the paper's two, always
    p.add_argument("--first-seed", type=int, default=0, help="with a count K in --seeds: seeds FIRST .. FIRST+K-1")
    p.add_argument("--eval-episodes", type=int, default=1000)
    p.add_argument("--out-dir", required=True, help="where plots and tables go")
    p.add_argument("--band", choices=("auto", "t95", "minmax"), default="auto",
                   help="curve band: 95 %% t-interval across seeds, the seeds' range, or auto (t95 from 3 seeds)")
    p.add_argument("--smooth", type=int, default=5, help="moving-average window (iterations) of the curves")
    p.add_argument("--plots-only", action="store_true", help="only aggregate finished, evaluated runs")
    args = p.parse_args(argv)
    if args.eval_episodes < 1:
        p.error("--eval-episodes must be >= 1")
    if args.first_seed and not args.seeds.isdigit():
        p.error("--first-seed goes with a count in --seeds (a range or list names its seeds itself)")
    args.runs_dir = args.runs_dir or os.path.join(args.out_dir, "runs")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    t0 = time.perf_counter()
    try:
        spec = study.study_from_args(args)
        if args.first_seed:
            spec = dataclasses.replace(spec, seeds=tuple(s + args.first_seed for s in spec.seeds))
        records = study.run_study(spec, VARIANTS, measure(args.eval_episodes), {"eval_episodes": args.eval_episodes},
                                  RECORD_FILE, args.conditions, args.eval_episodes, train_missing=not args.plots_only)
        evals = {v: [r["mix"] for r in recs] for v, recs in records.items()}
        results, curves = build_results(spec, {a: a for a in VARIANTS}, evals, args.band, args.smooth,
                                                      args.eval_episodes)
        results["paired_ppo_minus_sa_ppo"] = stats.compare_with_reference(
            {v: [per_seed(r) for r in recs] for v, recs in records.items()}, "sa-ppo", PAIRED)["ppo"]
        results["meta"]["wall_s_this_invocation"] = time.perf_counter() - t0
        results["meta"]["command"] = study.command("reproduce_paper", argv)
        os.makedirs(args.out_dir, exist_ok=True)
        results["files"] = plot_all(args.out_dir, curves, results, args.smooth)
        md = markdown_table(results)
        study.write_json(os.path.join(args.out_dir, RESULTS_JSON), results)
        fileio.atomic_write_text(os.path.join(args.out_dir, RESULTS_MD), md)
    except study.ERRORS as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(md)
    print(f"written to {args.out_dir} ({RESULTS_JSON}, {RESULTS_MD}, {', '.join(results['files'])})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
