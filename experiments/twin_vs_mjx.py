"""The robot's grasp against the simulator's: MJX success and physical hold beside the twin's held cube.

For each ``--run NAME=FOLDER`` and each named condition (``config.EVAL_CONDITIONS``) on each scene set
(the evaluation mix, blocking-only scenes): the MJX evaluation (``evaluate.evaluate_run``: kinematic
success; with ``--physical``, every success closed and lifted in CPU MuJoCo, ``evaluate.evaluate_physical``)
and the deployment at scale on the PyBullet twin (``deploy.rehearse``: the run's ``policy.npz`` through the
deploy loop, judged by the cube held after the lift).  Prints a Markdown table and writes JSON (the twin's
per-episode records included).

    python -m experiments.twin_vs_mjx --run s0=runs/quick_s0 --cases kinematic:mix robot:mix kinematic:blocking \\
        robot:blocking robot-wide:mix --twin-episodes 500 --mjx-episodes 1000 --physical --workers 2 \\
        --out experiments/results/twin_vs_mjx_s0.json
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Any

import sagrasp_jax  # noqa: F401  (XLA flags)

from sagrasp_jax import evaluate
from sagrasp_jax.task.config import EVAL_CONDITIONS
from sagrasp_jax.deploy import rehearse
from sagrasp_jax.base.fileio import atomic_write_json

DEFAULT_CASES = ("kinematic:mix", "robot:mix", "kinematic:blocking", "robot:blocking", "robot-wide:mix")


def mjx_case(folder: str, condition: str, scenes: str, episodes: int, physical: bool) -> dict[str, Any]:
    """MJX success (and physical hold) of one run in one condition on one scene set."""
    overrides = list(EVAL_CONDITIONS[condition])
    res = evaluate.evaluate_run(folder, episodes, overrides=overrides, scenes=scenes)
    key = "blocking" if scenes == "blocking" else "overall"
    out = {"success": res[key].get("success_rate"), "obstacle_success": res["obstacle_present"].get("success_rate"),
           "episodes": episodes, "steps_per_success": res[key].get("mean_steps_per_success")}
    if physical:
        seed, steps = evaluate.resolve_options(evaluate.run_dir.load_config(folder), None, None)
        ph = evaluate.evaluate_physical(folder, episodes, seed, steps, overrides=overrides, scenes=scenes)
        out["physical"] = ph["physical_success_rate"]
        out["physical_given_kinematic"] = ph["physical_given_kinematic"]
    return out


def twin_case(folder: str, condition: str, scenes: str, episodes: int, seed: int, workers: int) -> dict[str, Any]:
    res = rehearse.rehearse(os.path.join(folder, "policy.npz"), episodes, condition, scenes, seed, workers,
                            progress=False)
    print(rehearse.format_table(res), file=sys.stderr, flush=True)
    return res


def table(results: dict[str, Any]) -> str:
    head = ("| run | condition | scenes | MJX success | MJX physical hold | twin held (95 % CI) | twin obstacle scenes "
            "| twin reached | twin failures | twin − MJX physical |")
    lines = [head, "|---" * (head.count("|") - 1) + "|"]
    for run, cases in results.items():
        for name, case in cases.items():
            mjx, twin = case["mjx"], case["twin"]["summary"]
            t = twin["all"]
            ob = twin["obstacle"]
            pct = lambda v: "-" if v is None else f"{100 * v:.1f} %"  # noqa: E731
            fails = ", ".join(f"{k} {v}" for k, v in t["failures"].items()) or "none"
            ref = mjx.get("physical", mjx["success"])
            gap = "-" if ref is None or t["held_rate"] is None else f"{100 * (t['held_rate'] - ref):+.1f}"
            cond, scenes = name.split(":")
            lines.append(f"| {run} | {cond} | {scenes} | {pct(mjx['success'])} | {pct(mjx.get('physical'))} | "
                         f"{pct(t['held_rate'])} ({100 * t['held_ci95'][0]:.1f}-{100 * t['held_ci95'][1]:.1f}, "
                         f"n={t['episodes']}) | {pct(ob['held_rate'])} (n={ob['episodes']}) | {pct(t['reached_rate'])} "
                         f"| {fails} | {gap} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.twin_vs_mjx", description=__doc__.split("\n\n")[0])
    p.add_argument("--run", action="append", required=True, metavar="NAME=FOLDER")
    p.add_argument("--cases", nargs="+", default=list(DEFAULT_CASES), metavar="CONDITION:SCENES")
    p.add_argument("--twin-episodes", type=int, default=500)
    p.add_argument("--mjx-episodes", type=int, default=1000)
    p.add_argument("--twin-seed", type=int, default=0)
    p.add_argument("--physical", action="store_true", help="also the MJX physical grasp check")
    p.add_argument("--no-mjx", action="store_true", help="the twin alone")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    for case in args.cases:
        cond, _, scenes = case.partition(":")
        if cond not in EVAL_CONDITIONS or scenes not in rehearse.SCENE_SETS:
            p.error(f"--cases {case}: CONDITION:SCENES with a condition of {', '.join(EVAL_CONDITIONS)} and scenes "
                    f"{' or '.join(rehearse.SCENE_SETS)}")
    results: dict[str, Any] = {}
    for item in args.run:
        name, _, folder = item.partition("=")
        results[name] = {}
        for case in args.cases:
            cond, _, scenes = case.partition(":")
            t0 = time.perf_counter()
            mjx = {"success": None} if args.no_mjx else mjx_case(folder, cond, scenes, args.mjx_episodes, args.physical)
            twin = twin_case(folder, cond, scenes, args.twin_episodes, args.twin_seed, args.workers)
            results[name][case] = {"mjx": mjx, "twin": twin, "wall_s": time.perf_counter() - t0}
            print(f"{name} {case}: MJX {mjx}, twin held {twin['summary']['all']['held_rate']}", file=sys.stderr, flush=True)
            atomic_write_json(args.out, {"args": vars(args), "results": results}, indent=1)
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
