"""Does SA-PPO beat PPO?  Every learning-rate schedule, and SA with each of its parts switched off,
K seeds each, the same env-step budget on one preset.

Variants (``--variants``, default the five schedules; ``--ablation`` adds the four SA ablations):

* ``constant`` (the paper's PPO, ``--algo ppo``), ``sa`` (docs/task.md §3, ``--algo sa-ppo``), ``kl-adaptive``
  (brax / rsl_rl), ``cosine``, ``linear``: ``lr.schedule``;
* ``sa-no-metropolis``, ``sa-no-rollback``, ``sa-no-plateau-decay``, ``sa-no-entropy-temperature``:
  ``lr.schedule=sa`` with ``sa.metropolis`` / ``sa.rollback`` / ``sa.plateau_decay`` /
  ``sa.entropy_temperature`` off (docs/design.md, "SA ablation switches").

Every run trains ``--total-steps`` env steps of ``--preset`` (in process, ``train.run``; seeds
0 … K−1), then ``evaluate.evaluate_run`` plays ``--eval-episodes`` fixed held-out episodes of the
evaluation mix (success overall, without obstacle, with obstacle, blocking; steps per success)
and ``--blocking-episodes`` of blocking-only scenes.  From ``metrics.jsonl``: env steps and
training wall clock until the per-cycle evaluation (``eval.episodes`` fixed episodes) first
reaches 90 % and 98 % success, the final lr and the SA counts.  Reported per variant: means
with 95 % t-intervals across seeds, pooled success with Wilson intervals, and for every variant
a paired comparison with ``sa`` (the same seeds): mean difference, its 95 % t-interval, the
paired t-test's two-sided p and the seeds won.  Prints Markdown tables, writes JSON to
``--out`` and, with matplotlib, learning curves (per-cycle evaluation success, mean and band
across seeds) and lr traces next to it, and — when ``constant`` and ``sa`` both ran — the paper's
Figures 11-15 and the SA trace for the two (``reproduce_paper.plot_all``) in ``<out>_figures/``.
Re-running skips evaluated runs, evaluates finished
ones, resumes unfinished ones from their checkpoint and restarts ones killed before their
first checkpoint; a run folder trained with another config is refused.

    python experiments/compare_schedules.py --preset cpu-quick --seeds 5 --ablation \\
        --runs-dir runs/compare_schedules_cpu --out experiments/results/compare_schedules_cpu.json
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import argparse
import importlib.util
import math
import os
import platform
import sys
import time
from typing import Any, Sequence

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_vs_paper_stack import first_reach  # noqa: E402
from obstacle_ablation import _cell, _rate, finished_record  # noqa: E402
from reproduce_paper import (  # noqa: E402
    ALGOS, BAND_LABELS, ReproduceError, band, band_kind, curve_matrix, ensure_trained, git_state, mean_ci, plot_all,
    summarise_algo, t975, write_json,
)

from sagrasp_jax import evaluate, run_dir, train  # noqa: E402
from sagrasp_jax.checkpoint import CheckpointError  # noqa: E402
from sagrasp_jax.config import LR_SCHEDULES, ConfigError, get_config  # noqa: E402
from sagrasp_jax.run_dir import RunDirError  # noqa: E402

SCHEDULE_VARIANTS: dict[str, list[str]] = {name: [f"lr.schedule={name}"] for name in LR_SCHEDULES}
ABLATION_VARIANTS: dict[str, list[str]] = {
    f"sa-no-{switch.replace('_', '-')}": ["lr.schedule=sa", f"sa.{switch}=false"]
    for switch in ("metropolis", "rollback", "plateau_decay", "entropy_temperature")
}
ALL_VARIANTS = SCHEDULE_VARIANTS | ABLATION_VARIANTS
REFERENCE = "sa"  # every other variant is compared with this one, seed by seed
LEVELS = (0.9, 0.98)  # per-cycle evaluation success levels whose first crossing is reported
RESULT_FILE = "schedule_eval.json"
# metrics compared with the reference, seed by seed: (key, label, larger is better)
PAIRED = (("success_overall", "overall success %", True), ("success_obstacle", "obstacle success %", True),
          ("success_blocking_scenes", "blocking-scenes success %", True),
          ("steps_per_success", "steps / success", False), ("env_steps_to_90", "env steps to 90 %", False))


# ---------------------------------------------------------------------- statistics

def _betacf(a: float, b: float, x: float) -> float:
    """Continued fraction of the regularised incomplete beta function (modified Lentz)."""
    tiny, qab, qap, qam = 1e-300, a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 300):
        m2 = 2 * m
        for aa in (m * (b - m) * x / ((qam + m2) * (a + m2)), -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))):
            d = 1.0 + aa * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + aa / c
            c = c if abs(c) > tiny else tiny
            h *= d * c
        if abs(d * c - 1.0) < 1e-15:
            break
    return h


def betainc(a: float, b: float, x: float) -> float:
    """Regularised incomplete beta I_x(a, b)."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    front = math.exp(math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x))
    if x < (a + 1.0) / (a + b + 2.0):
        return front * _betacf(a, b, x) / a
    return 1.0 - front * _betacf(b, a, 1.0 - x) / b


def t_test_p(t: float, df: int) -> float:
    """Two-sided p of Student's t with ``df`` degrees of freedom."""
    if not math.isfinite(t):
        return 0.0
    return betainc(0.5 * df, 0.5, df / (df + t * t))


def paired(a: Sequence[float | None], b: Sequence[float | None], larger_is_better: bool = True) -> dict[str, Any]:
    """Paired comparison of ``a`` − ``b`` over the seeds where both have a value: mean difference,
    95 % t-interval, paired t-test two-sided p, and how many seeds ``a`` wins / ties / loses."""
    pairs = [(x, y) for x, y in zip(a, b) if x is not None and y is not None and math.isfinite(x) and math.isfinite(y)]
    diffs = [x - y for x, y in pairs]
    out: dict[str, Any] = {"n": len(diffs), "mean_diff": None, "ci95": [None, None], "t": None, "p": None,
                           "wins": 0, "ties": 0, "losses": 0}
    if not diffs:
        return out
    sign = 1.0 if larger_is_better else -1.0
    out["wins"] = sum(sign * d > 0 for d in diffs)
    out["ties"] = sum(d == 0 for d in diffs)
    out["losses"] = sum(sign * d < 0 for d in diffs)
    n = len(diffs)
    mean = sum(diffs) / n
    out["mean_diff"] = mean
    if n < 2:
        return out
    sd = math.sqrt(sum((d - mean) ** 2 for d in diffs) / (n - 1))
    half = t975(n - 1) * sd / math.sqrt(n)
    out["ci95"] = [mean - half, mean + half]
    if sd == 0.0:
        out["p"] = 1.0 if mean == 0.0 else 0.0  # every seed the same difference: t is infinite (not JSON), p 0
    else:
        out["t"] = mean / (sd / math.sqrt(n))
        out["p"] = t_test_p(out["t"], n - 1)
    return out


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
    reach = first_reach(points, list(LEVELS))
    last = rows[-1]
    counts = {k: last.get(k) for k in ("sa_accepts", "sa_accept_worse", "sa_rejects", "sa_decays", "rollbacks")}
    lrs = [r["lr"] for r in rows if r.get("lr") is not None]
    return {"reach": reach, "final_lr": last.get("lr"), "min_lr": min(lrs) if lrs else None,
            "max_lr": max(lrs) if lrs else None, "train_time_s": times[-1] if times else None,
            "env_steps": last.get("env_steps"), "cycles": len(cycles), "nonfinite": sum("event" in r for r in rows),
            "final_eval_success": points[-1][2] if points else None, **counts}


def run_one(variant: str, seed: int, args: argparse.Namespace, tag: str) -> dict[str, Any]:
    """Train (or resume / skip) one run and evaluate it; returns its result record."""
    out = os.path.join(args.runs_dir, f"{variant}-s{seed}")
    cfg = train.build_config(args.preset, None, seed, args.total_steps, ALL_VARIANTS[variant] + args.overrides)
    wanted = {"eval_episodes": args.eval_episodes, "blocking_episodes": args.blocking_episodes}
    done = finished_record(out, cfg, RESULT_FILE, wanted, tag)
    if done is not None:
        return done
    wall = ensure_trained(out, cfg, tag, not args.no_progress)
    print(f"{tag}: evaluating {args.eval_episodes} episodes of the mix"
          + (f" and {args.blocking_episodes} blocking scenes" if args.blocking_episodes else ""), flush=True)
    mix = evaluate.evaluate_run(out, args.eval_episodes)
    blocking = evaluate.evaluate_run(out, args.blocking_episodes, scenes="blocking") if args.blocking_episodes else None
    rows = run_dir.read_metrics(os.path.join(out, run_dir.METRICS_FILE))
    record = {"variant": variant, "overrides": ALL_VARIANTS[variant], "seed": seed, **wanted, "mix": mix,
              "blocking_scenes": blocking, "train_wall_s": wall, "compile_s": rows[-1].get("compile_s"),
              **curve_facts(rows)}
    write_json(os.path.join(out, RESULT_FILE), record)
    ov = mix["overall"]
    steps = ov.get("mean_steps_per_success")
    print(f"{tag}: success {100 * ov['success_rate']:.1f} % (no obstacle "
          f"{_fmt(_rate(mix['obstacle_absent']))} %, obstacle {_fmt(_rate(mix['obstacle_present']))} %"
          + ("" if blocking is None else f", blocking scenes {_fmt(_rate(blocking['blocking']))} %")
          + f"), steps/success {_fmt(steps)}, final lr {_fmt(record['final_lr'], '.3g')}", flush=True)
    return record


def _fmt(v: Any, spec: str = ".1f") -> str:
    return "-" if v is None else format(v, spec)


# ---------------------------------------------------------------------- summaries

def _reach(record: dict[str, Any], level: float, key: str) -> float | None:
    hit = record["reach"].get(f"{level:g}")
    return hit[key] if isinstance(hit, dict) else None


def per_seed_metrics(r: dict[str, Any]) -> dict[str, Any]:
    mix, blocking = r["mix"], r.get("blocking_scenes")
    return {
        "success_overall": _rate(mix["overall"]),
        "success_no_obstacle": _rate(mix["obstacle_absent"]),
        "success_obstacle": _rate(mix["obstacle_present"]),
        "success_blocking_in_mix": _rate(mix["blocking"]),
        "success_blocking_scenes": None if blocking is None else _rate(blocking["blocking"]),
        "steps_per_success": mix["overall"].get("mean_steps_per_success"),
        "collision_overall": _rate(mix["overall"], "collision_rate"),
        "env_steps_to_90": _reach(r, 0.9, "env_steps"), "env_steps_to_98": _reach(r, 0.98, "env_steps"),
        "wall_s_to_90": _reach(r, 0.9, "time_s"), "wall_s_to_98": _reach(r, 0.98, "time_s"),
        "final_lr": r.get("final_lr"), "final_eval_success": None if r.get("final_eval_success") is None
        else 100.0 * r["final_eval_success"], "train_time_s": r.get("train_time_s"),
        "sa_rejects": r.get("sa_rejects"), "sa_accept_worse": r.get("sa_accept_worse"), "sa_decays": r.get("sa_decays"),
        "rollbacks": r.get("rollbacks"),
    }


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Means and 95 % t-intervals across seeds (time to a level: over the seeds that reached it)."""
    per_seed = [{"seed": r["seed"], **per_seed_metrics(r)} for r in records]
    keys = [k for k in per_seed[0] if k != "seed"] if per_seed else []
    out: dict[str, Any] = {k: mean_ci([p[k] for p in per_seed if p[k] is not None]) for k in keys}
    for level in LEVELS:
        out[f"reached_{round(100 * level)}"] = sum(_reach(r, level, "env_steps") is not None for r in records)
    out["seeds"] = [r["seed"] for r in records]
    out["pooled_mix"] = summarise_algo([r["mix"] for r in records], out["seeds"])["pooled"] if records else None
    out["per_seed"] = per_seed
    return out


def compare_with_reference(summary: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Every variant minus ``sa``, seed by seed (seeds both have)."""
    if REFERENCE not in summary:
        return {}
    ref = {p["seed"]: p for p in summary[REFERENCE]["per_seed"]}
    out: dict[str, Any] = {}
    for name, s in summary.items():
        if name == REFERENCE:
            continue
        mine = {p["seed"]: p for p in s["per_seed"]}
        seeds = sorted(set(ref) & set(mine))
        out[name] = {key: paired([mine[k][key] for k in seeds], [ref[k][key] for k in seeds], better)
                     for key, _, better in PAIRED}
        out[name]["seeds"] = seeds
    return out


def _steps(stat: dict[str, Any]) -> str:
    if stat["mean"] is None:
        return "-"
    lo, hi = stat["ci95"]
    m = f"{stat['mean'] / 1e6:.2f}M"
    return m if lo is None else f"{m} [{lo / 1e6:.2f}, {hi / 1e6:.2f}]"


def _lr(stat: dict[str, Any]) -> str:
    return "-" if stat["mean"] is None else f"{stat['mean']:.2g}"


def markdown(summary: dict[str, dict[str, Any]], versus: dict[str, Any], n_seeds: int) -> str:
    cols = [("success_overall", "overall %", _cell), ("success_no_obstacle", "no obstacle %", _cell),
            ("success_obstacle", "obstacle %", _cell), ("success_blocking_in_mix", "blocking (in mix) %", _cell),
            ("success_blocking_scenes", "blocking scenes %", _cell), ("steps_per_success", "steps / success", _cell),
            ("env_steps_to_90", "env steps to 90 %", _steps), ("env_steps_to_98", "env steps to 98 %", _steps),
            ("final_lr", "final lr", _lr)]
    lines = [f"Mean [95 % t-interval across seeds]; time to a level over the seeds that reached it (n shown), "
             f"{n_seeds} seed(s) per variant.", "",
             "| variant | " + " | ".join(c[1] for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for name, s in summary.items():
        cells = []
        for key, _, fmt in cols:
            cell = fmt(s[key])
            if key.startswith("env_steps_to_"):
                cell += f" (n = {s['reached_' + key[-2:]]})"
            cells.append(cell)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if versus:
        lines += ["", f"Paired with `{REFERENCE}` seed by seed: variant − {REFERENCE}, mean [95 % t-interval], "
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


def _save(fig: Any, path: str) -> str:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def figures(args: argparse.Namespace, variants: list[str], seeds: list[int], stem: str) -> list[str]:
    """Per-cycle evaluation success (mean and band across seeds) and lr traces of every variant."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no figures", file=sys.stderr)
        return []
    runs = {v: [run_dir.read_metrics(os.path.join(args.runs_dir, f"{v}-s{s}", run_dir.METRICS_FILE)) for s in seeds]
            for v in variants}
    kind = band_kind("auto", len(seeds))
    written = []
    fig, ax = plt.subplots(figsize=(8, 4.8))
    for v in variants:
        x, y = curve_matrix(runs[v], "eval_success")
        if x.size == 0:
            continue
        mean, lo, hi = band(100.0 * y, kind)
        line, = ax.plot(x, mean, lw=1.4, label=v, ls=_line_style(v))
        ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.15)
    ax.set_xlabel("env steps")
    ax.set_ylabel("per-cycle evaluation success (%)")
    ax.set_title(f"{args.preset}, {len(seeds)} seed(s): mean and {BAND_LABELS[kind]}", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    written.append(_save(fig, f"{stem}_curves.png"))
    fig, ax = plt.subplots(figsize=(8, 4.2))
    for v in variants:
        x, y = curve_matrix(runs[v], "lr")
        if x.size:
            ax.plot(x, band(y, "minmax")[0], lw=1.2, label=v, ls=_line_style(v))
    ax.set_yscale("log")
    ax.set_xlabel("env steps")
    ax.set_ylabel("learning rate (mean over seeds)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, ncol=2)
    written.append(_save(fig, f"{stem}_lr.png"))
    return written


PAPER_PAIR = {"ppo": "constant", "sa-ppo": "sa"}  # the paper's two algorithms as schedules here


def paper_figures(args: argparse.Namespace, records: dict[str, list[dict[str, Any]]], seeds: list[int],
                  stem: str) -> list[str]:
    """The paper's Figures 11-15 and the SA trace (``reproduce_paper.plot_all``) for ``constant``
    (the paper's PPO) against ``sa``, from these runs, into ``<stem>_figures/``."""
    if not set(PAPER_PAIR.values()) <= set(records) or importlib.util.find_spec("matplotlib") is None:
        return []
    evals = {a: [r["mix"] for r in sorted(records[v], key=lambda r: r["seed"])] for a, v in PAPER_PAIR.items()}
    curves = {a: [run_dir.read_metrics(os.path.join(args.runs_dir, f"{v}-s{s}", run_dir.METRICS_FILE)) for s in seeds]
              for a, v in PAPER_PAIR.items()}
    results = {"meta": {"seeds": seeds, "band": band_kind("auto", len(seeds)), "total_steps": args.total_steps,
                        "eval_episodes": args.eval_episodes},
               "algos": {a: summarise_algo(evals[a], seeds) for a in ALGOS}}
    out_dir = f"{stem}_figures"
    os.makedirs(out_dir, exist_ok=True)
    return [os.path.join(out_dir, name) for name in plot_all(out_dir, curves, results, smooth_window=5)]


# ---------------------------------------------------------------------- main

def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python experiments/compare_schedules.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="cpu-quick")
    p.add_argument("--total-steps", type=int, default=None, help="env steps per run (default: the preset's)")
    p.add_argument("--seeds", type=int, default=5, help="seeds 0..K-1")
    p.add_argument("--variants", default=None,
                   help=f"comma list of {', '.join(ALL_VARIANTS)} (default: the five schedules, and with --ablation "
                        "the SA ablations)")
    p.add_argument("--ablation", action="store_true", help="also SA with each of its four parts switched off")
    p.add_argument("--eval-episodes", type=int, default=1000, help="held-out episodes of the evaluation mix per run")
    p.add_argument("--blocking-episodes", type=int, default=1000, help="blocking-only episodes per run (0: none)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="extra config override for every run")
    p.add_argument("--runs-dir", default=None, help="default runs/compare_schedules_<preset>")
    p.add_argument("--out", default=None, help="default experiments/results/compare_schedules_<preset>.json")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    if args.total_steps is None:
        args.total_steps = get_config(args.preset).train.total_steps
    if args.seeds < 1 or args.total_steps < 1 or args.eval_episodes < 1 or args.blocking_episodes < 0:
        p.error("--seeds, --total-steps and --eval-episodes must be >= 1, --blocking-episodes >= 0")
    args.runs_dir = args.runs_dir or os.path.join("runs", f"compare_schedules_{args.preset}")
    args.out = args.out or os.path.join("experiments", "results", f"compare_schedules_{args.preset}.json")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    variants = list(SCHEDULE_VARIANTS) + (list(ABLATION_VARIANTS) if args.ablation else [])
    if args.variants:
        variants = [v.strip() for v in args.variants.split(",") if v.strip()]
        unknown = [v for v in variants if v not in ALL_VARIANTS]
        if unknown:
            print(f"error: unknown variant(s) {', '.join(unknown)}; valid: {', '.join(ALL_VARIANTS)}", file=sys.stderr)
            return 2
    seeds = list(range(args.seeds))
    jobs = [(v, s) for s in seeds for v in variants]  # seed-major: every variant has a seed early
    records: dict[str, list[dict[str, Any]]] = {v: [] for v in variants}
    t0 = time.perf_counter()
    try:
        for i, (v, s) in enumerate(jobs, 1):
            records[v].append(run_one(v, s, args, f"[{i}/{len(jobs)}] {v} seed {s}"))
    except (ConfigError, CheckpointError, RunDirError, ReproduceError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    summary = {v: summarise(sorted(recs, key=lambda r: r["seed"])) for v, recs in records.items()}
    versus = compare_with_reference(summary)
    stem = os.path.splitext(args.out)[0]
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    written = [] if args.no_figures else (figures(args, variants, seeds, stem)
                                          + paper_figures(args, records, seeds, stem))
    result = {
        "preset": args.preset, "total_steps": args.total_steps, "seeds": seeds, "eval_episodes": args.eval_episodes,
        "blocking_episodes": args.blocking_episodes, "extra_overrides": args.overrides,
        "variants": {v: ALL_VARIANTS[v] for v in variants}, "reference": REFERENCE, "levels": list(LEVELS),
        "summary": summary, "paired_vs_reference": versus, "figures": [os.path.relpath(p) for p in written],
        "runs": records, "wall_s_this_call": time.perf_counter() - t0,
        "command": "python experiments/compare_schedules.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "git": git_state(), "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores",
    }
    write_json(args.out, result)
    print(markdown(summary, versus, len(seeds)))
    print(f"written to {args.out}" + "".join(f", {p}" for p in written))
    return 0


if __name__ == "__main__":
    sys.exit(main())
