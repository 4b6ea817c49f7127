"""Reproduce the paper's PPO vs SA-PPO comparison (Figures 11-15, the 98/143 vs 92/154 table).

A study over ``experiments.study`` with two variants, the paper's algorithms: ``ppo`` (the constant
learning rate) and ``sa-ppo`` (the SA schedule, docs/task.md §3), K seeds each on one preset and
step budget.  Every final policy is evaluated on ``--eval-episodes`` fixed-seed episodes
(``evaluate.evaluate_run``: deterministic policy, reward weights at p = 1, held-out seeds), and
``--out-dir`` gets (``experiments.paper_figures``):

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
import os
import sys
import time
from typing import Any, Sequence

from experiments import paper_figures, stats, study
from sagrasp_jax import fileio

# The study's variants: the paper's two algorithms as learning-rate schedules (what `train --algo` means).
VARIANTS: dict[str, tuple[str, ...]] = {"ppo": ("lr.schedule=constant",), "sa-ppo": ("lr.schedule=sa",)}
RESULTS_JSON = "results.json"
RESULTS_MD = "results.md"
RECORD_FILE = "evaluation.json"  # this experiment's record of each run (its --eval-episodes evaluation)
PAIRED = (("success_pct", True), ("steps_per_success", False), ("collision_pct", False))  # ppo vs sa-ppo, seed by seed


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
        results, curves = paper_figures.build_results(spec, {a: a for a in VARIANTS}, evals, args.band, args.smooth,
                                                      args.eval_episodes)
        results["paired_ppo_minus_sa_ppo"] = stats.compare_with_reference(
            {v: [per_seed(r) for r in recs] for v, recs in records.items()}, "sa-ppo", PAIRED)["ppo"]
        results["meta"]["wall_s_this_invocation"] = time.perf_counter() - t0
        results["meta"]["command"] = study.command("reproduce_paper", argv)
        os.makedirs(args.out_dir, exist_ok=True)
        results["files"] = paper_figures.plot_all(args.out_dir, curves, results, args.smooth)
        md = paper_figures.markdown_table(results)
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
