"""Does SA-PPO beat PPO?  Every learning-rate schedule, and SA with each of its parts switched off,
K seeds each, the same env-step budget on one preset.

Variants (``--variants``, default the five schedules; ``--ablation`` adds the four SA ablations):

* ``constant`` (the paper's PPO, ``--algo ppo``), ``sa`` (docs/task.md §3, ``--algo sa-ppo``), ``kl-adaptive``
  (brax / rsl_rl), ``cosine``, ``linear``: ``lr.schedule``;
* ``sa-no-metropolis``, ``sa-no-rollback``, ``sa-no-plateau-decay``, ``sa-no-entropy-temperature``:
  ``lr.schedule=sa`` with ``sa.metropolis`` / ``sa.rollback`` / ``sa.plateau_decay`` /
  ``sa.entropy_temperature`` off (docs/design.md, "SA ablation switches").

The variants are a table (``VARIANTS``) over ``experiments.study``.  Every run trains ``--total-steps``
env steps of ``--preset`` (in process, ``train.run``; seeds 0 … K−1) into
``--runs-dir/<variant>/seed<S>/``, then ``evaluation.evaluate_run`` plays ``--eval-episodes`` fixed held-out episodes of the
evaluation mix (success overall, without obstacle, with obstacle, blocking; steps per success)
and ``--blocking-episodes`` of blocking-only scenes.  From ``metrics.jsonl``: env steps and
training wall clock until the per-cycle evaluation (``eval.episodes`` fixed episodes) first
reaches 90 / 95 / 98 / 99 % success (read again from metrics.jsonl at every summary), the final lr and the SA counts.  Reported per variant: means
with 95 % t-intervals across seeds, pooled success with Wilson intervals, and for every variant
a paired comparison with ``sa`` (the same seeds): mean difference, its 95 % t-interval, the
paired t-test's two-sided p and the seeds won.  Prints Markdown tables, writes JSON to
``--out`` and, with matplotlib, learning curves (per-cycle evaluation success, mean and band
across seeds) and lr traces next to it, and — when ``constant`` and ``sa`` both ran — the paper's
Figures 11-15 and the SA trace for the two (``reproduce_paper.plot_all``) in ``<out>_figures/``.
With ``--reference-from FILE`` the reference's rows come from an earlier result file measured the same way
(checked before anything trains) instead of being trained again.  Re-running skips evaluated runs and
evaluates finished ones; with ``--resume`` it continues runs that stopped before they finished; a run
folder trained with another config is refused.  Run from the repository root:

    python -m experiments.compare_schedules --preset cpu-quick --seeds 5 --ablation \\
        --runs-dir runs/compare_schedules_cpu --out experiments/results/compare_schedules_cpu.json
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import statistics
import sys
import time
from typing import Any, Mapping, Sequence

from experiments import reproduce_paper, study
from sagrasp_jax.training import stats
from sagrasp_jax import plot
from sagrasp_jax.training import evaluation
from sagrasp_jax.base import extras
from sagrasp_jax.training import run_dir
from sagrasp_jax.task.config import LR_SCHEDULES

SCHEDULE_VARIANTS: dict[str, tuple[str, ...]] = {name: (f"lr.schedule={name}",) for name in LR_SCHEDULES}
ABLATION_VARIANTS: dict[str, tuple[str, ...]] = {
    f"sa-no-{switch.replace('_', '-')}": ("lr.schedule=sa", f"sa.{switch}=false")
    for switch in ("metropolis", "rollback", "plateau_decay", "entropy_temperature")
}
VARIANTS = SCHEDULE_VARIANTS | ABLATION_VARIANTS
REFERENCE = "sa"  # every other variant is compared with this one, seed by seed
LEVELS = (0.9, 0.95, 0.98, 0.99)  # per-cycle evaluation success levels whose first crossing is reported
RESULT_FILE = "schedule_eval.json"
# metrics compared with the reference, seed by seed: (key, label, larger is better)
PAIRED = (("success_overall", "overall success %", True), ("success_obstacle", "obstacle success %", True),
          ("success_blocking_scenes", "blocking-scenes success %", True),
          ("steps_per_success", "steps / success", False), ("env_steps_to_90", "env steps to 90 %", False),
          ("env_steps_to_98", "env steps to 98 %", False), ("env_steps_to_99", "env steps to 99 %", False))
PAPER_PAIR = {"ppo": "constant", "sa-ppo": "sa"}  # the paper's two algorithms as schedules here


# ---------------------------------------------------------------------- one run

def training_time(rows: list[dict[str, Any]]) -> list[float]:
    """Training wall clock of every row, summed over sessions (``time_s`` restarts when a run resumes)."""
    out, offset, last = [], 0.0, 0.0
    for r in rows:
        t = r.get("time_s")
        if t is None:
            out.append(offset + last)
            continue
        if t < last:  # a new session
            offset += last
        last = t
        out.append(offset + t)
    return out


def curve_facts(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Time to LEVELS, final lr and SA counts from a run's metrics.jsonl rows."""
    times = training_time(rows)
    cycles = [(t, r) for t, r in zip(times, rows) if "sa_decision" in r]
    points = [(t, int(r["env_steps"]), float(r["eval_success"])) for t, r in cycles if r.get("eval_success") is not None]
    reach = stats.first_reach(points, LEVELS)
    last = rows[-1]
    counts = {k: last.get(k) for k in ("sa_accepts", "sa_accept_worse", "sa_rejects", "sa_decays", "rollbacks")}
    lrs = [r["lr"] for r in rows if r.get("lr") is not None]
    return {"reach": reach, "final_lr": last.get("lr"), "min_lr": min(lrs) if lrs else None,
            "max_lr": max(lrs) if lrs else None, "train_time_s": times[-1] if times else None,
            "env_steps": last.get("env_steps"), "cycles": len(cycles), "nonfinite": sum("event" in r for r in rows),
            "final_eval_success": points[-1][2] if points else None, **counts}


def measure(eval_episodes: int, blocking_episodes: int) -> study.Measure:
    """A run's record: the evaluation mix, blocking-only scenes (0: none) and its curve's facts."""
    def run(folder: str, variant: str, seed: int) -> dict[str, Any]:
        mix = study.Evaluation(eval_episodes)(folder)
        blocking = study.Evaluation(blocking_episodes, scenes="blocking")(folder) if blocking_episodes else None
        rows = run_dir.read_metrics(os.path.join(folder, run_dir.METRICS_FILE))
        record = {"mix": mix, "blocking_scenes": blocking, "compile_s": rows[-1].get("compile_s"), **curve_facts(rows)}
        ov = mix["overall"]
        print(f"{variant} seed {seed}: success {100 * ov['success_rate']:.1f} % (no obstacle "
              f"{_fmt(study.rate(mix['obstacle_absent']))} %, obstacle {_fmt(study.rate(mix['obstacle_present']))} %"
              + ("" if blocking is None else f", blocking scenes {_fmt(study.rate(blocking['blocking']))} %")
              + f"), steps/success {_fmt(ov.get('mean_steps_per_success'))}, final lr {_fmt(record['final_lr'], '.3g')}",
              flush=True)
        return record
    return run


def _fmt(v: Any, spec: str = ".1f") -> str:
    return "-" if v is None else format(v, spec)


# ---------------------------------------------------------------------- summaries

def _reach(record: dict[str, Any], level: float, key: str) -> float | None:
    hit = record["reach"].get(f"{level:g}")
    return hit[key] if isinstance(hit, dict) else None


def per_seed_metrics(r: dict[str, Any]) -> dict[str, Any]:
    return {
        **study.kind_rates(r),
        "collision_overall": study.rate(r["mix"]["overall"], "collision_rate"),
        **{f"env_steps_to_{round(100 * lv)}": _reach(r, lv, "env_steps") for lv in LEVELS},
        **{f"wall_s_to_{round(100 * lv)}": _reach(r, lv, "time_s") for lv in LEVELS},
        "final_lr": r.get("final_lr"), "final_eval_success": None if r.get("final_eval_success") is None
        else 100.0 * r["final_eval_success"], "train_time_s": r.get("train_time_s"),
        "sa_rejects": r.get("sa_rejects"), "sa_accept_worse": r.get("sa_accept_worse"), "sa_decays": r.get("sa_decays"),
        "rollbacks": r.get("rollbacks"), **study.condition_rates(r),
    }


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Means and 95 % t-intervals across seeds (time to a level: over the seeds that reached it)."""
    per_seed = [{"seed": r["seed"], **per_seed_metrics(r)} for r in records]
    out: dict[str, Any] = stats.summarise(per_seed)
    for level in LEVELS:
        out[f"reached_{round(100 * level)}"] = sum(_reach(r, level, "env_steps") is not None for r in records)
    out["seeds"] = [r["seed"] for r in records]
    out["pooled_mix"] = (reproduce_paper.summarise_algo([r["mix"] for r in records], out["seeds"])["pooled"]
                         if records else None)
    out["per_seed"] = per_seed
    return out


def _steps(stat: dict[str, Any]) -> str:
    if stat["mean"] is None:
        return "-"
    lo, hi = stat["ci95"]
    m = f"{stat['mean'] / 1e6:.2f}M"
    return m if lo is None else f"{m} [{lo / 1e6:.2f}, {hi / 1e6:.2f}]"


def _lr(stat: dict[str, Any]) -> str:
    return "-" if stat["mean"] is None else f"{stat['mean']:.2g}"


def markdown(summary: dict[str, dict[str, Any]], versus: dict[str, Any], n_seeds: int, reference: str = REFERENCE) -> str:
    cell = stats.cell
    cols = [("success_overall", "overall %", cell), ("success_no_obstacle", "no obstacle %", cell),
            ("success_obstacle", "obstacle %", cell), ("success_blocking_in_mix", "blocking (in mix) %", cell),
            ("success_blocking_scenes", "blocking scenes %", cell), ("steps_per_success", "steps / success", cell),
            ("env_steps_to_90", "env steps to 90 %", _steps), ("env_steps_to_98", "env steps to 98 %", _steps),
            ("env_steps_to_99", "env steps to 99 %", _steps),
            ("final_lr", "final lr", _lr)]
    lines = [f"Mean [95 % t-interval across seeds]; time to a level over the seeds that reached it (n shown), "
             f"{n_seeds} seed(s) per variant.", "",
             "| variant | " + " | ".join(c[1] for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for name, s in summary.items():
        cells = []
        for key, _, fmt in cols:
            text = fmt(s[key])
            if key.startswith("env_steps_to_"):
                text += f" (n = {s['reached_' + key[-2:]]})"
            cells.append(text)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if versus:
        lines += ["", f"Paired with `{reference}` seed by seed: variant − {reference}, mean [95 % t-interval], "
                      "paired t-test p, seeds where the variant is better / worse.", "",
                  "| variant | " + " | ".join(label for _, label, _ in PAIRED) + " |", "|---" * (len(PAIRED) + 1) + "|"]
        for name, cmp in versus.items():
            cells = []
            for key, _, _ in PAIRED:
                c = cmp[key]
                if c["mean_diff"] is None:
                    cells.append("-")
                    continue
                scale = 1e6 if key.startswith("env_steps") else 1.0
                unit = "M" if scale > 1 else ""
                lo, hi = c["ci95"]
                ci = "" if lo is None else f" [{lo / scale:+.2f}, {hi / scale:+.2f}]"
                p = "" if c["p"] is None else f", p {c['p']:.2g}"
                cells.append(f"{c['mean_diff'] / scale:+.2f}{unit}{ci}{p} ({c['wins']}/{c['losses']})")
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ---------------------------------------------------------------------- figures

def _line_style(variant: str) -> str:
    """SA-ablation variants dashed, schedules solid."""
    return "--" if variant.startswith("sa-no-") else "-"


def figures(spec: study.Study, variants: list[str], stem: str) -> list[str]:
    """Per-cycle evaluation success (mean and band across seeds) and lr traces of every variant."""
    try:
        plt = plot.pyplot()
    except extras.MissingExtra as exc:
        print(f"{exc}: no figures", file=sys.stderr)
        return []
    runs = {v: study.load_curves(spec, v) for v in variants}
    kind = stats.band_kind("auto", len(spec.seeds))
    written = []
    fig, ax = plt.subplots(figsize=(8, 4.8))
    for v in variants:
        x, y = stats.curve_matrix(runs[v], "eval_success")
        if x.size == 0:
            continue
        mean, lo, hi = stats.band(100.0 * y, kind)
        line, = ax.plot(x, mean, lw=1.4, label=v, ls=_line_style(v))
        ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.15)
    ax.set_xlabel("env steps")
    ax.set_ylabel("per-cycle evaluation success (%)")
    ax.set_title(f"{spec.preset}, {len(spec.seeds)} seed(s): mean and {stats.BAND_LABELS[kind]}", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    written.append(plot.save(fig, f"{stem}_curves.png"))
    fig, ax = plt.subplots(figsize=(8, 4.2))
    for v in variants:
        x, y = stats.curve_matrix(runs[v], "lr")
        if x.size:
            ax.plot(x, stats.band(y, "minmax")[0], lw=1.2, label=v, ls=_line_style(v))
    ax.set_yscale("log")
    ax.set_xlabel("env steps")
    ax.set_ylabel("learning rate (mean over seeds)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, ncol=2)
    written.append(plot.save(fig, f"{stem}_lr.png"))
    return written


def paper_figures_for(spec: study.Study, records: dict[str, list[dict[str, Any]]], eval_episodes: int,
                      stem: str) -> list[str]:
    """The paper's Figures 11-15 and the SA trace (``reproduce_paper.plot_all``) for ``constant``
    (the paper's PPO) against ``sa``, from these runs, into ``<stem>_figures/``."""
    if not set(PAPER_PAIR.values()) <= set(records) or importlib.util.find_spec("matplotlib") is None:
        return []
    evals = {a: [r["mix"] for r in records[v]] for a, v in PAPER_PAIR.items()}
    results, curves = reproduce_paper.build_results(spec, PAPER_PAIR, evals, "auto", 5, eval_episodes)
    out_dir = f"{stem}_figures"
    os.makedirs(out_dir, exist_ok=True)
    return [os.path.join(out_dir, name) for name in reproduce_paper.plot_all(out_dir, curves, results, smooth_window=5)]


# ---------------------------------------------------------------------- main

def parse_args(argv: Sequence[str] | None, module: str = "compare_schedules", description: str | None = None,
               seeds: int = 5, eval_episodes: int = 1000, blocking_episodes: int = 1000,
               ablation: bool = True) -> argparse.Namespace:
    """This study's options; ``module`` names the variant table using them (its prog, runs folder and JSON)."""
    p = argparse.ArgumentParser(prog=f"python -m experiments.{module}",
                                description=description or __doc__.split("\n\n")[0])
    study.add_arguments(p, seeds=seeds, runs_dir=None)
    if ablation:
        p.add_argument("--ablation", action="store_true", help="also SA with each of its four parts switched off")
    p.add_argument("--eval-episodes", type=int, default=eval_episodes,
                   help=f"held-out episodes of the evaluation mix per run (default {eval_episodes})")
    p.add_argument("--blocking-episodes", type=int, default=blocking_episodes,
                   help=f"blocking-only episodes per run, 0: none (default {blocking_episodes})")
    p.add_argument("--out", default=None, help=f"default experiments/results/{module}_<preset>.json")
    p.add_argument("--reference-from", default=None, metavar="JSON",
                   help="take the reference variant's per-seed results from this earlier result file of the same "
                        "preset, budget, seeds, evaluation and conditions instead of training it again")
    p.add_argument("--reference", default=None, metavar="VARIANT",
                   help="pair every variant with this one seed by seed (default: the table's reference)")
    p.add_argument("--no-figures", action="store_true")
    args = p.parse_args(argv)
    if args.eval_episodes < 1 or args.blocking_episodes < 0:
        p.error("--eval-episodes must be >= 1, --blocking-episodes >= 0")
    args.runs_dir = args.runs_dir or os.path.join("runs", f"{module}_{args.preset}")
    args.out = args.out or os.path.join("experiments", "results", f"{module}_{args.preset}.json")
    return args


def recorded_reference(args: argparse.Namespace, spec: study.Study, table: study.Variants, reference: str,
                       chosen: study.Variants) -> dict[str, Any]:
    """The ``reference`` variant's summary from ``args.reference_from``, an earlier result file of this study
    (runs are deterministic on one machine, so retraining would reproduce it).  Refused unless it was measured
    the same way: the same seeds, each trained with the config the reference has here (``config_identity``:
    preset, budget, overrides and every default at that time), the same evaluation episodes and conditions."""
    path = args.reference_from
    if reference in chosen:
        raise study.StudyError(f"--reference-from: {reference!r} is both trained here and read from {path}")
    try:
        with open(path, encoding="utf-8") as f:
            old = json.load(f)
        recorded, runs = old["summary"][reference], old["runs"][reference]
    except (OSError, ValueError) as exc:
        raise study.StudyError(f"--reference-from {path}: cannot read it ({exc})") from exc
    except (KeyError, TypeError) as exc:
        raise study.StudyError(f"--reference-from {path}: no summary of {reference!r} in it") from exc
    want = {"eval_episodes": args.eval_episodes, "blocking_episodes": args.blocking_episodes}
    differ = [f"{k} {old.get(k)!r} (here {v!r})" for k, v in want.items() if old.get(k) != v]
    conditions = {c for r in runs for c in r.get("conditions", {})}
    if conditions != set(args.conditions or ()):
        differ.append(f"conditions {sorted(conditions)} (here {sorted(args.conditions or ())})")
    if [r.get("seed") for r in runs] != list(spec.seeds):
        differ.append(f"seeds {[r.get('seed') for r in runs]} (here {list(spec.seeds)})")
    else:
        trained = [r.get("mix", {}).get("config_sha256") for r in runs]
        here = [evaluation.config_identity(spec.config(table[reference], s)) for s in spec.seeds]
        if trained != here:
            differ.append(f"its runs were trained with another config (config_sha256 {trained}, here {here}: "
                          "preset, budget, overrides or a default changed)")
    if differ:
        raise study.StudyError(f"--reference-from {path}: measured differently: " + "; ".join(differ))
    return {**recorded, "from": path}


def screen_reach(per_seed: Sequence[dict[str, Any]], horizon: Mapping[int, int]) -> dict[str, Any]:
    """Time to each level within a screen: per seed the env steps (None: not within the seed's ``horizon``,
    the env steps its screen ran), how many seeds reached it, and the median over all seeds with a seed that
    did not reach it counted as beyond every one that did (None when half or more did not)."""
    out: dict[str, Any] = {"per_seed": [], "reached": {}, "median": {}}
    for p in per_seed:
        row = {"seed": p["seed"], "horizon": horizon[p["seed"]]}
        for level in LEVELS:
            key = f"env_steps_to_{round(100 * level)}"
            steps = p.get(key)
            row[key] = steps if steps is not None and steps <= horizon[p["seed"]] else None
        out["per_seed"].append(row)
    for level in LEVELS:
        key = f"env_steps_to_{round(100 * level)}"
        values = [float("inf") if r[key] is None else r[key] for r in out["per_seed"]]
        median = statistics.median(values) if values else float("inf")
        out["reached"][key] = sum(r[key] is not None for r in out["per_seed"])
        out["median"][key] = None if math.isinf(median) else median
    return out


def screen_markdown(screen: Mapping[str, dict[str, Any]], steps: int, versus: Mapping[str, Any] | None = None,
                    reference: str = REFERENCE) -> str:
    heads = [f"env steps to {round(100 * level)} %" for level in LEVELS]
    lines = [f"Screen: the first {steps:,} env steps of each run's full-budget schedule; per seed the env steps until "
             "the per-cycle evaluation first reached a level ('-': not within the screen), then the median over the "
             "seeds and how many reached it.", "", "| variant | seed | " + " | ".join(heads) + " |",
             "|---" * (len(heads) + 2) + "|"]
    fmt = lambda v: "-" if v is None else f"{v / 1e6:.2f}M"  # noqa: E731
    for name, s in screen.items():
        for r in s["per_seed"]:
            lines.append(f"| {name} | {r['seed']} | "
                         + " | ".join(fmt(r[f'env_steps_to_{round(100 * lv)}']) for lv in LEVELS) + " |")
        lines.append(f"| {name} | median | " + " | ".join(
            f"{fmt(s['median'][k])} ({s['reached'][k]}/{len(s['per_seed'])})"
            for k in (f"env_steps_to_{round(100 * lv)}" for lv in LEVELS)) + " |")
    if versus:
        lines += ["", f"Paired with `{reference}` over the seeds where both reached the level: mean difference of "
                      "env steps, paired t-test p, seeds where the variant was sooner / later.", "",
                  "| variant | " + " | ".join(heads) + " |", "|---" * (len(heads) + 1) + "|"]
        for name, cmp in versus.items():
            cells = []
            for lv in LEVELS:
                c = cmp[f"env_steps_to_{round(100 * lv)}"]
                cells.append("-" if c["mean_diff"] is None else f"{c['mean_diff'] / 1e6:+.2f}M"
                             + ("" if c["p"] is None else f", p {c['p']:.2g}") + f" ({c['wins']}/{c['losses']}, n {c['n']})")
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def run_screen(args: argparse.Namespace, spec: study.Study, table: study.Variants, chosen: study.Variants,
               reference: str, recorded: dict[str, Any] | None, argv: Sequence[str] | None, module: str,
               t0: float) -> int:
    """``--screen-steps N``: train every chosen variant's seeds N env steps into their full budget's schedule
    (``study.screen_study``) and compare the time to each level within them; the reference's rows may come
    from a finished study (``--reference-from``), its times cut at the same horizon."""
    folders = study.screen_study(spec, chosen)
    screen: dict[str, dict[str, Any]] = {}
    if recorded is not None:
        horizon = {s: spec.screen_horizon(spec.config(table[reference], s)) for s in spec.seeds}
        screen[reference] = {**screen_reach(recorded["per_seed"], horizon), "from": recorded["from"]}
    for variant, by_seed in folders.items():
        per_seed = []
        for seed, folder in by_seed.items():
            facts = curve_facts(run_dir.read_metrics(os.path.join(folder, run_dir.METRICS_FILE)))
            per_seed.append({"seed": seed, **{f"env_steps_to_{round(100 * lv)}": _reach(facts, lv, "env_steps")
                                              for lv in LEVELS}})
        screen[variant] = screen_reach(per_seed, {s: spec.screen_horizon(spec.config(chosen[variant], s))
                                                  for s in spec.seeds})
    keys = [(f"env_steps_to_{round(100 * lv)}", False) for lv in LEVELS]
    versus = stats.compare_with_reference({v: s["per_seed"] for v, s in screen.items()}, reference, keys)
    result = {
        "preset": spec.preset, "total_steps": spec.total_steps, "screen_steps": spec.screen_steps,
        "paired_vs_reference": versus,
        "seeds": list(spec.seeds), "extra_overrides": args.overrides,
        "variants": {v: list(sets) for v, sets in chosen.items()}, "reference": reference, "levels": list(LEVELS),
        "screen": screen, "wall_s_this_call": time.perf_counter() - t0, "command": study.command(module, argv),
        "git": study.git_state(), "machine": study.machine(),
    }
    return study.report(args.out, result, screen_markdown(screen, spec.screen_steps or 0, versus, reference))


def run_table(args: argparse.Namespace, table: study.Variants, default: Sequence[str], reference: str,
              argv: Sequence[str] | None, module: str = "compare_schedules") -> int:
    """Train, evaluate and summarise the chosen variants of ``table``, each paired with ``reference`` seed by
    seed; the time-to-level facts are read again from every run's metrics.jsonl (a record saved by an
    older version of this script may lack a level)."""
    t0 = time.perf_counter()
    try:
        spec = study.study_from_args(args)
        if reference not in table:
            raise study.StudyError(f"--reference {reference!r} is not a variant here; valid: {', '.join(table)}")
        chosen = study.pick_variants(table, args.variants, default)
        recorded = recorded_reference(args, spec, table, reference, chosen) if args.reference_from else None
        if spec.screen_steps is not None:
            return run_screen(args, spec, table, chosen, reference, recorded, argv, module, t0)
        identity = {"eval_episodes": args.eval_episodes, "blocking_episodes": args.blocking_episodes}
        records = study.run_study(spec, chosen, measure(args.eval_episodes, args.blocking_episodes), identity,
                                  RESULT_FILE, args.conditions, args.eval_episodes)
    except study.ERRORS as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for variant, recs in records.items():
        for r in recs:
            r.update(curve_facts(run_dir.read_metrics(os.path.join(spec.folder(variant, r["seed"]), run_dir.METRICS_FILE))))
    summary = {v: summarise(recs) for v, recs in records.items()}
    if recorded is not None:
        summary = {reference: recorded, **summary}
    versus = stats.compare_with_reference({v: s["per_seed"] for v, s in summary.items()}, reference,
                                          [(key, better) for key, _, better in PAIRED])
    stem = os.path.splitext(args.out)[0]
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    written = [] if args.no_figures else (figures(spec, list(chosen), stem)
                                          + paper_figures_for(spec, records, args.eval_episodes, stem))
    result = {
        "preset": spec.preset, "total_steps": spec.total_steps, "seeds": list(spec.seeds),
        "eval_episodes": args.eval_episodes, "blocking_episodes": args.blocking_episodes,
        "extra_overrides": args.overrides, "variants": {v: list(sets) for v, sets in chosen.items()},
        "reference": reference, "levels": list(LEVELS), "summary": summary, "paired_vs_reference": versus,
        "figures": [os.path.relpath(p) for p in written], "runs": records, "wall_s_this_call": time.perf_counter() - t0,
        "command": study.command(module, argv), "git": study.git_state(), "machine": study.machine(),
    }
    return study.report(args.out, result, markdown(summary, versus, len(spec.seeds), reference), written)


# ---------------------------------------------------------------------- failures: a result file read back

FAILURES_DOC = """What the failed episodes of a study's runs were: per variant, summed over its seeds, the episodes of each kind
(the ``robot`` condition's obstacle and no-obstacle episodes, the run's own blocking-only scenes) that hit the
obstacle, the table, the cube, anything else, or timed out, from a ``compare_schedules`` / ``sooner`` result file."""

_NAMED = ("obstacle", "table", "target")  # collision parts reported by name; the rest are "other"


def failure_counts(group: dict[str, Any]) -> dict[str, int]:
    """Episode counts of one evaluated group (``episodes``, rates of success, timeout and each collision part)."""
    n = int(group["episodes"])
    by = group.get("collision_by", {})
    out = {"episodes": n, "failed": round(n * (1.0 - group["success_rate"])), "timeout": round(n * group["timeout_rate"])}
    for part in _NAMED:
        out[part] = round(n * by.get(part, 0.0))
    out["other"] = max(0, round(n * group["collision_rate"]) - sum(out[p] for p in _NAMED))  # rounding: never < 0
    return out


def failures_table(result: dict[str, Any], condition: str | None) -> dict[str, dict[str, dict[str, int]]]:
    """variant -> episode kind -> summed counts over the variant's recorded runs."""
    out: dict[str, dict[str, dict[str, int]]] = {}
    for variant, runs in result.get("runs", {}).items():
        kinds: dict[str, dict[str, int]] = {}
        for run in runs:
            source = run["conditions"][condition] if condition else run["mix"]
            groups = {"obstacle": source["obstacle_present"], "no obstacle": source["obstacle_absent"]}
            if run.get("blocking_scenes"):
                groups["blocking scenes (own env)"] = run["blocking_scenes"]["blocking"]
            for kind, group in groups.items():
                counts = failure_counts(group)
                kinds[kind] = {k: kinds.get(kind, {}).get(k, 0) + v for k, v in counts.items()}
        out[variant] = kinds
    return out


def failures_main(argv: Sequence[str] | None = None) -> int:
    """``failures RESULT``: what the failed episodes of a study's runs were (see ``FAILURES_DOC``)."""
    p = argparse.ArgumentParser(prog="python -m experiments.compare_schedules failures", description=FAILURES_DOC)
    p.add_argument("result", help="a compare_schedules / sooner result JSON")
    p.add_argument("--condition", default=None, help="the evaluation condition the mix rows come from (e.g. robot)")
    args = p.parse_args(argv)
    try:
        with open(args.result, encoding="utf-8") as f:
            result = json.load(f)
        rows = failures_table(result, args.condition)
    except (OSError, ValueError) as exc:
        print(f"error: {args.result}: cannot read it ({exc})", file=sys.stderr)
        return 2
    except KeyError as exc:
        print(f"error: {args.result}: no {exc} in its run records (is --condition one it evaluated?)", file=sys.stderr)
        return 2
    print("| variant | episodes | failed | obstacle | timeouts | cube | table | other |")
    print("|---|---|---|---|---|---|---|---|")
    for variant, kinds in rows.items():
        for kind, c in kinds.items():
            print(f"| {variant}, {kind} | {c['episodes']} | {c['failed']} | {c['obstacle']} | {c['timeout']} | "
                  f"{c['target']} | {c['table']} | {c['other']} |")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    given = sys.argv[1:] if argv is None else list(argv)
    if given[:1] == ["failures"]:
        return failures_main(given[1:])
    args = parse_args(argv)
    default = list(SCHEDULE_VARIANTS) + (list(ABLATION_VARIANTS) if args.ablation else [])
    return run_table(args, VARIANTS, default, args.reference or REFERENCE, argv)


if __name__ == "__main__":
    sys.exit(main())
