"""Is a trained policy robot-grade?  Evaluate runs in every transfer condition (docs/results.md, §7).

Each ``--run NAME=FOLDER`` is evaluated on ``--episodes`` fixed-seed episodes of the evaluation mix (seed
``eval.seed + 1``, deterministic policy) in the named conditions of ``config.EVAL_CONDITIONS``
(kinematic, dynamic, robot = dynamic with every transfer knob on at the real arm's levels, robot-latency2 =
the same with up to 2 steps of latency), optionally in the dynamic env with one knob on at a time
(``--per-knob``, the rows of the robot-grade issue's table), on blocking-only scenes in the robot condition
(``--blocking``), and through the physical grasp check with and without detection error (``--physical``).
Prints a Markdown table and writes JSON.

    python -m experiments.robot_grade --run s0=runs/robot_s0 --run s1=runs/robot_s1 --run s2=runs/robot_s2 \\
        --blocking --physical --out experiments/results/robot_grade_cpu.json
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

import sagrasp_jax  # noqa: F401  (XLA flags)

from sagrasp_jax import evaluate, run_dir
from sagrasp_jax.config import EVAL_CONDITIONS, ROBOT_KNOBS
from sagrasp_jax.fileio import atomic_write_json

CONDITIONS = ("kinematic", "dynamic", "robot", "robot-latency2")


def per_knob_conditions() -> dict[str, tuple[str, ...]]:
    """The dynamic env with one transfer knob on at a time (the others off)."""
    base = EVAL_CONDITIONS["dynamic"]
    out = {}
    for knob in ROBOT_KNOBS:
        key = knob.split("=")[0]
        out["dynamic+" + key.rsplit(".", 1)[1]] = tuple(o for o in base if not o.startswith(key + "=")) + (knob,)
    return out


def summary(result: dict[str, Any]) -> dict[str, Any]:
    overall, obstacle = result["overall"], result["obstacle_present"]
    by = overall.get("collision_by", {})
    return {"overall": overall.get("success_rate"), "obstacle": obstacle.get("success_rate"),
            "obstacle_n": obstacle.get("episodes", 0), "no_obstacle": result["obstacle_absent"].get("success_rate"),
            "collision": overall["collision_rate"], "hit_table": by.get("table", 0.0), "hit_target": by.get("target", 0.0),
            "hit_obstacle": by.get("obstacle", 0.0), "timeout": overall["timeout_rate"],
            "steps_per_success": overall["mean_steps_per_success"]}


def evaluate_conditions(folder: str, episodes: int, conditions: dict[str, tuple[str, ...]], blocking: bool,
                        physical: bool) -> dict[str, Any]:
    cfg = run_dir.load_config(folder)
    seed, steps = evaluate.resolve_options(cfg, None, None)
    out: dict[str, Any] = {}
    for name, overrides in conditions.items():
        out[name] = summary(evaluate.evaluate_run(folder, episodes, overrides=list(overrides)))
        print(f"{folder} {name}: {out[name]}", file=sys.stderr, flush=True)
    if blocking:
        res = evaluate.evaluate_run(folder, episodes, overrides=list(EVAL_CONDITIONS["robot"]), scenes="blocking")
        out["robot_blocking_scenes"] = summary(res)
        res = evaluate.evaluate_run(folder, episodes, overrides=list(EVAL_CONDITIONS["kinematic"]), scenes="blocking")
        out["kinematic_blocking_scenes"] = summary(res)
    if physical:
        for name in ("kinematic", "kinematic-target-error"):
            ph = evaluate.evaluate_physical(folder, episodes, seed, steps, overrides=list(EVAL_CONDITIONS[name]))
            out["physical_" + name] = {k: ph[k] for k in ("kinematic_successes", "physical_successes", "physical_success_rate")}
            out["physical_" + name]["held_of_successes"] = ph["physical_successes"] / max(1, ph["kinematic_successes"])
            print(f"{folder} physical {name}: {out['physical_' + name]}", file=sys.stderr, flush=True)
    return out


def _pct(v: Any) -> str:
    return "-" if v is None else f"{100 * v:.1f}"


def table(report: dict[str, Any]) -> str:
    lines = ["| run | condition | overall % | obstacle % | no obstacle % | collisions % (table / cube / obstacle) | "
             "timeout % | steps / success |", "|---|---|---|---|---|---|---|---|"]
    for run, entry in report["runs"].items():
        for cond, s in entry["eval"].items():
            if cond.startswith("physical_"):
                continue
            steps = "-" if s["steps_per_success"] is None else f"{s['steps_per_success']:.1f}"
            lines.append(f"| {run} | {cond} | {_pct(s['overall'])} | {_pct(s['obstacle'])} | {_pct(s['no_obstacle'])} | "
                         f"{_pct(s['collision'])} ({_pct(s['hit_table'])} / {_pct(s['hit_target'])} / "
                         f"{_pct(s['hit_obstacle'])}) | {_pct(s['timeout'])} | {steps} |")
        for cond in ("physical_kinematic", "physical_kinematic-target-error"):
            if cond in entry["eval"]:
                ph = entry["eval"][cond]
                lines.append(f"| {run} | {cond} | held {ph['physical_successes']} of {ph['kinematic_successes']} "
                             f"successes ({_pct(ph['held_of_successes'])} %) | | | | | |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", action="append", default=[], metavar="NAME=FOLDER", required=True)
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--conditions", default=",".join(CONDITIONS),
                        help=f"comma-separated names of config.EVAL_CONDITIONS (default {','.join(CONDITIONS)})")
    parser.add_argument("--per-knob", action="store_true", help="also the dynamic env with one knob on at a time")
    parser.add_argument("--blocking", action="store_true", help="also blocking-only scenes (robot and kinematic)")
    parser.add_argument("--physical", action="store_true", help="also the physical grasp check, with and without target error")
    parser.add_argument("--out", default="experiments/results/robot_grade_cpu.json")
    args = parser.parse_args(argv)
    names = [c for c in args.conditions.split(",") if c]
    unknown = [c for c in names if c not in EVAL_CONDITIONS]
    if unknown:
        parser.error(f"unknown condition(s) {', '.join(unknown)}; valid: {', '.join(EVAL_CONDITIONS)}")
    conditions = {c: EVAL_CONDITIONS[c] for c in names}
    if args.per_knob:
        conditions.update(per_knob_conditions())
    report: dict[str, Any] = {"episodes": args.episodes, "conditions": {k: list(v) for k, v in conditions.items()},
                              "runs": {}}
    for item in args.run:
        name, folder = item.split("=", 1)
        report["runs"][name] = {"folder": os.path.abspath(folder),
                                "eval": evaluate_conditions(folder, args.episodes, conditions, args.blocking, args.physical)}
        atomic_write_json(args.out, report)  # after every run: a long study keeps what it has
    print(table(report))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
