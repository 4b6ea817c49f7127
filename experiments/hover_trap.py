"""The hovering trap: which approach shaping lets the README preset escape it, and where a hovering policy stops.

``train --preset cpu-quick --algo sa-ppo --total-steps 3000000 --seed 1`` with the paper's approach
shaping (the distance alone) ends with 0 % success and 94 % timeouts (docs/design.md, "The hovering
trap").  Variants of the approach potential (``reward.approach_potential``), a table over
``experiments.study``:

* ``distance-only``: the paper's d (the tilt keys at the values that mean their absence);
* ``tilt-everywhere-5deg``: d + 0.05 m/rad · tilt beyond 5°, along the whole approach;
* ``tilt-everywhere``: d + 0.05 m/rad · tilt beyond 10° (the success test's tilt), along the whole approach;
* ``tilt-near`` (the presets): the same, faded in over the last 10 cm.

Every run is evaluated on 1,000 fixed episodes in the ``robot`` and ``kinematic`` conditions
(``config.EVAL_CONDITIONS``), and the kinematic episodes that timed out are replayed to their final
poses: how many stood inside the success test's horizontal tolerance and height band, and how tilted
they were.  Prints a table and writes JSON.  Run from the repository root:

    python -m experiments.hover_trap --seeds 1-1 --runs-dir runs/hover_trap \\
        --out experiments/results/hover_trap_3M.json
"""

from __future__ import annotations

import argparse
import sys
from typing import Any, Sequence

import numpy as np

from experiments import study
from sagrasp_jax import config, evaluate, robot, run_dir

_ABSENT = tuple(f"{k}={v}" for k, v in config.ADDED_KEYS.items() if k.startswith("env.reward.tilt"))
VARIANTS: dict[str, tuple[str, ...]] = {
    "distance-only": _ABSENT,
    "tilt-everywhere-5deg": ("env.reward.tilt_free_deg=5", "env.reward.tilt_near=0"),
    "tilt-everywhere": ("env.reward.tilt_near=0",),
    "tilt-near": (),
}
CONDITIONS = ("robot", "kinematic")
RESULT_FILE = "hover_trap_eval.json"


def final_poses(folder: str, episodes: int) -> dict[str, Any]:
    """The kinematic condition's timeouts replayed to their final poses: where a hovering policy stops."""
    max_steps = run_dir.load_config(folder).env.task.max_steps
    fp = evaluate.replay_final_poses(folder, episodes, 0, max_steps, list(config.EVAL_CONDITIONS["kinematic"]))
    task = fp.env_cfg.task
    timeout = fp.episodes["timeout"] > 0.5
    if not timeout.any():
        return {"timeouts": 0}
    kin = robot.forward_kinematics(np, robot.load_robot(), fp.q_final[timeout])
    offset = kin.gripper_centre - np.asarray(fp.specs.target_pos)[timeout]
    horizontal, dz = np.hypot(offset[:, 0], offset[:, 1]), offset[:, 2]
    tilt = np.degrees(robot.tilt(np, kin.approach_axis))
    return {
        "timeouts": int(timeout.sum()),
        "in_horizontal_tolerance": float(np.mean(horizontal <= task.success_xy)),
        "in_height_band": float(np.mean((dz >= task.success_dz_min) & (dz <= task.success_dz_max))),
        "tilt_within_success": float(np.mean(tilt <= task.success_tilt_deg)),
        "tilt_deg_median": float(np.median(tilt)),
        "horizontal_mm_median": float(1e3 * np.median(horizontal)),
    }


def measure(episodes: int) -> study.Measure:
    def run(folder: str, variant: str, seed: int) -> dict[str, Any]:
        out = {name: study.Evaluation(episodes, condition=name)(folder) for name in CONDITIONS}
        out["kinematic_timeouts"] = final_poses(folder, episodes)
        print(f"{variant} seed {seed}: " + ", ".join(
            f"{name} {100 * out[name]['overall']['success_rate']:.1f} %" for name in CONDITIONS), flush=True)
        return out
    return run


def row(record: dict[str, Any]) -> dict[str, Any]:
    poses = record["kinematic_timeouts"]
    return {
        **{f"success_{name}": study.rate(record[name]["overall"]) for name in CONDITIONS},
        **{f"timeout_{name}": study.rate(record[name]["overall"], "timeout_rate") for name in CONDITIONS},
        "steps_per_success_robot": record["robot"]["overall"]["mean_steps_per_success"],
        "timeouts_tilt_deg_median": poses.get("tilt_deg_median"),
        "timeouts_in_horizontal_tolerance": poses.get("in_horizontal_tolerance"),
    }


def markdown(records: dict[str, list[dict[str, Any]]]) -> str:
    lines = ["| variant | seed | robot % | kinematic % | timeouts robot % | steps / success | timeouts: median tilt ° |"
             " in xy tolerance |", "|---" * 8 + "|"]
    for variant, recs in records.items():
        for r in recs:
            x = row(r)
            cells = [x["success_robot"], x["success_kinematic"], x["timeout_robot"], x["steps_per_success_robot"],
                     x["timeouts_tilt_deg_median"], x["timeouts_in_horizontal_tolerance"]]
            lines.append(f"| {variant} | {r['seed']} | " + " | ".join("-" if c is None else f"{c:.2f}" for c in cells) + " |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.hover_trap", description=__doc__.split("\n\n")[0])
    study.add_arguments(p, seeds=1, runs_dir="runs/hover_trap")
    p.add_argument("--eval-episodes", type=int, default=1000)
    p.add_argument("--out", default="experiments/results/hover_trap_3M.json")
    p.set_defaults(seeds="1-1", total_steps=3_000_000)  # seed 1: the seed that hovered
    args = p.parse_args(argv)
    if args.eval_episodes < 1:
        p.error("--eval-episodes must be >= 1")
    try:
        spec = study.study_from_args(args)
        table = study.pick_variants(VARIANTS, args.variants, list(VARIANTS))
        records = study.run_study(spec, table, measure(args.eval_episodes), {"eval_episodes": args.eval_episodes},
                                  RESULT_FILE, args.conditions, args.eval_episodes)
    except study.ERRORS as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    result = {"preset": spec.preset, "total_steps": spec.total_steps, "seeds": list(spec.seeds),
              "variants": {k: list(v) for k, v in table.items()}, "eval_episodes": args.eval_episodes,
              "rows": {v: [{"seed": r["seed"], **row(r)} for r in recs] for v, recs in records.items()},
              "runs": records, "command": study.command("hover_trap", argv), "git": study.git_state(),
              "machine": study.machine()}
    return study.report(args.out, result, markdown(records))


if __name__ == "__main__":
    sys.exit(main())
