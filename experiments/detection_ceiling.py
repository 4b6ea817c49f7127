"""Which detection errors make a clean grasp impossible for any policy?  The ceiling under target error.

A policy only knows the detected cube.  The best it can do is to bring the gripper centre to the middle of
the success band of the *detected* cube (horizontally on its centre, 12.5 mm above it, pointing down) with
its pads clear: what the deployment loop and ``evaluate --physical`` do before closing
(``reward.grasp_centre``; ``--aim middle``).  ``--aim policy`` instead closes where the policy itself stops
relative to the cube it sees, as a loop without the final centring would.  This script takes the grasp poses a trained run really ends in (its kinematic successes
without detection error, replayed exactly as ``evaluate --physical`` does; their orientation and yaw
relative to the cube), draws a detection error uniformly in ±E per axis, moves the gripper straight up or
down (IK, ``robot.lift_pose``) to the band's middle above the *detected* cube and puts the true cube, resting
on the table, off by the horizontal error.  For each level E
it reports the share of poses whose true cube is still (a) inside the success band (≤ 10 mm horizontally,
5–20 mm below the gripper centre), (b) clear of the palm and pads (``collision.check``: no hit of the
target or the table), (c) held when the fingers close and lift (``physical.physical_grasp_check``, run whenever the pads are
clear, in the band or not), and (a)–(c) together: the ceiling for that level.  Also the policy's own final offsets (how close to the middle it
aims).  Prints a table and writes JSON.

    python -m experiments.detection_ceiling --run runs/robot_s0 --poses 100 --out experiments/results/detection_ceiling.json
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import sagrasp_jax  # noqa: F401  (XLA flags)
import numpy as np

from sagrasp_jax import collision, evaluate, physical, robot, run_dir
from sagrasp_jax.config import EVAL_CONDITIONS
from sagrasp_jax.fileio import atomic_write_json
from sagrasp_jax.sampling import ResetSpec

LEVELS_MM = (0.0, 2.0, 4.0, 5.0, 6.0, 8.0, 10.0)


def success_poses(run: str, episodes: int, seed: int, max_steps: int) -> tuple[np.ndarray, list[ResetSpec], Any]:
    """Final joints and true scenes of the run's kinematic successes without detection error (obstacle-free
    episodes), replayed as ``evaluate --physical`` does."""
    replay = evaluate.replay_final_poses(run, episodes, seed, max_steps, list(EVAL_CONDITIONS["kinematic"]))
    eps = replay.episodes
    idx = np.nonzero((eps["success"] > 0) & (eps["obstacle_present"] == 0))[0]
    return replay.q_final[idx], [replay.spec(i) for i in idx], replay.env_cfg


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True)
    parser.add_argument("--poses", type=int, default=100, help="success poses per level (the first N)")
    parser.add_argument("--episodes", type=int, default=300, help="episodes replayed to find them")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--levels", default=",".join(f"{v:g}" for v in LEVELS_MM), help="error levels, mm (comma list)")
    parser.add_argument("--aim", choices=("middle", "policy"), default="middle",
                        help="middle: the ideal aim (the ceiling); policy: where the run's policy stops relative to the "
                             "cube it sees, as a deployment stops when its detected cube's band is reached")
    parser.add_argument("--out", default="experiments/results/detection_ceiling.json")
    args = parser.parse_args(argv)
    cfg = run_dir.load_config(args.run)
    seed, steps = evaluate.resolve_options(cfg, None, None)
    q_final, specs, env_cfg = success_poses(args.run, args.episodes, seed, steps)
    q_final, specs = q_final[: args.poses], specs[: args.poses]
    model = robot.load_robot()
    task = env_cfg.task
    middle = 0.5 * (task.success_dz_min + task.success_dz_max)
    kins = [robot.forward_kinematics(np, model, q) for q in q_final]
    own = np.array([k.gripper_centre - np.asarray(s.target_pos) for k, s in zip(kins, specs)])
    rng = np.random.default_rng(args.seed)
    rows = []
    for level in [float(v) for v in args.levels.split(",")]:
        band = clear = held = ceiling = no_ik = 0
        for q0, kin0, spec, own_offset in zip(q_final, kins, specs, own):
            error = rng.uniform(-1.0, 1.0, 3) * level / 1000.0
            # the cube rests on the table where it was.  "middle": the gripper centre over the detected cube's
            # centre at the band's middle above its detected height; "policy": where the policy itself stops
            # relative to the cube it sees (its final offset without error), i.e. where a deployment stops
            rest_z = float(np.asarray(spec.target_pos)[2])
            aim = np.array([0.0, 0.0, middle]) if args.aim == "middle" else own_offset
            height = aim[2] + error[2] - float(kin0.gripper_centre[2] - rest_z)
            try:
                q = robot.lift_pose(model, q0, height)
            except robot.IKError:  # counted as a failure: no pose reaches the band's middle from here
                no_ik += 1
                continue
            kin = robot.forward_kinematics(np, model, q)
            cube = np.array([kin.gripper_centre[0] - aim[0] + error[0], kin.gripper_centre[1] - aim[1] + error[1], rest_z])
            true = spec._replace(target_pos=cube)
            offset = kin.gripper_centre - cube
            in_band = bool(np.hypot(offset[0], offset[1]) <= task.success_xy
                           and task.success_dz_min <= offset[2] <= task.success_dz_max)
            hits = collision.check(np, model, kin, true, env_cfg).hits
            is_clear = not (bool(hits["target"]) or bool(hits["table"]))
            is_held = bool(physical.physical_grasp_check(q, true)["success"]) if is_clear else False  # band or not
            band += in_band
            clear += is_clear
            held += is_held
            ceiling += in_band and is_clear and is_held
        n = len(specs)
        rows.append({"error_mm": level, "poses": n, "no_ik": no_ik, "in_band": band / n, "pads_clear": clear / n,
                     "held": held / n, "ceiling": ceiling / n})
        print(f"±{level:g} mm: {rows[-1]}", file=sys.stderr, flush=True)
    report = {"run": args.run, "aim": args.aim, "band_middle_mm": 1000 * middle, "levels": rows,
              "policy_final_offset_mm": {"horizontal_mean": float(1000 * np.hypot(own[:, 0], own[:, 1]).mean()),
                                         "horizontal_p95": float(1000 * np.percentile(np.hypot(own[:, 0], own[:, 1]), 95)),
                                         "height_mean": float(1000 * own[:, 2].mean()),
                                         "height_p5_p95": [float(1000 * np.percentile(own[:, 2], 5)),
                                                           float(1000 * np.percentile(own[:, 2], 95))]}}
    print("| detection error (± per axis) | in band | pads clear | held | ceiling |\n|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['error_mm']:g} mm | {100 * r['in_band']:.1f} % | {100 * r['pads_clear']:.1f} % | "
              f"{100 * r['held']:.1f} % | {100 * r['ceiling']:.1f} % |")
    print(f"policy's own final offsets without error: {report['policy_final_offset_mm']}")
    atomic_write_json(args.out, report)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
