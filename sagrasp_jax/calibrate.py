"""Hand-eye calibration: ``python -m sagrasp_jax.calibrate --pairs pairs.csv --out calibration.json``.

    python -m sagrasp_jax.calibrate --plan [--plan-count N] [--noise-mm MM] [--out plan.csv|plan.json] [--json]
    python -m sagrasp_jax.calibrate --pairs pairs.csv --out calibration.json
        [--cam-units mm|m] [--tcp-units mm|m] [--max-rms MM] [--noise-mm MM] [--max-rot-deg DEG] [--max-mm MM] [--json]

``--plan`` prints where to take the pairs: N TCP poses (default 10) in the robot's base frame (mm), each with
an orientation and the joints that reach it, that the camera sees and the arm reaches safely, chosen to
minimise the fit's predicted error (``deploy.handeye.plan_poses``); ``--out plan.csv`` writes them as the
rows of a pairs file to fill in (the camera's point at each pose; the TCP the controller reports there),
``--out plan.json`` as JSON.

``pairs.csv``: one point pair per row, the camera's point then the robot's TCP point (in the controller's
base frame), ``cam_x,cam_y,cam_z,tcp_x,tcp_y,tcp_z``; a header row with those names is optional (with it the
columns may come in any order); blank rows and rows starting with ``#`` are skipped.  Millimetres unless
``--cam-units`` / ``--tcp-units`` say metres.

The least-squares rigid fit (``deploy.handeye``: Kabsch, no scale) gives T_cam_base; every pair's
residual, the RMS and the fit's predicted p95 errors (rotation, and mapped points over the target region,
from the pairs' spread and their noise per axis: the residuals' or ``--noise-mm``, default 1 mm, whichever
is larger) are printed, and ``--out`` gets, written atomically, the JSON file ``python -m
sagrasp_jax.deploy --calibration`` reads: ``{"T_cam_base": 4×4 (translation in mm), ..., "quality": {...}}``.
Warnings (stderr, and the quality block): outlying pairs, more noise than assumed, fewer than 10 pairs, a
predicted error near its limit.

Exit status 0 written; 2 refused, nothing written: an unreadable file, fewer than 4 pairs or more than
10,000, NaN, points along a line, mixed units, a fit whose RMS residual exceeds ``--max-rms`` (default
5 mm), a predicted p95 error over ``--max-rot-deg`` (default 0.25°) or ``--max-mm`` (default 2 mm), or a
result the deployment would refuse (``deploy.calibration.CameraCalibration.from_matrix``).  NumPy only.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import sys
from typing import Any, Sequence

import numpy as np

from sagrasp_jax.base import cli
from sagrasp_jax.deploy.calibration import CalibrationError, CameraCalibration
from sagrasp_jax.deploy.handeye import (
    DEFAULT_MAX_MM,
    DEFAULT_MAX_RMS_MM,
    DEFAULT_MAX_ROT_DEG,
    DEFAULT_NOISE_MM,
    MAX_PAIRS,
    UNIT_SCALE,
    HandEyeError,
    HandEyeFit,
    HandEyePlan,
    fit_hand_eye,
    plan_poses,
)
from sagrasp_jax.task import robots
from sagrasp_jax.task.robot import RobotModel, load_robot
from sagrasp_jax.base.fileio import NotWritable, atomic_write_json, atomic_write_text, check_writable, read_regular

COLUMNS = ("cam_x", "cam_y", "cam_z", "tcp_x", "tcp_y", "tcp_z")
MAX_PAIRS_BYTES = 10 * 1024 * 1024


def read_pairs(path: str) -> tuple[np.ndarray, np.ndarray]:
    """(camera points, TCP points), (N, 3) each, as written; ``HandEyeError`` naming the bad row, or a file of
    more than ``MAX_PAIRS`` pairs (refused at the first row past the cap: memory stays bounded)."""
    try:
        text = read_regular(path, MAX_PAIRS_BYTES, "pairs file").decode("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise HandEyeError(f"{path}: cannot read the pairs file ({exc})") from None
    order: list[int] | None = None  # the columns' order, once the first row has said whether it is a header
    values: list[list[float]] = []
    for i, row in enumerate(csv.reader(io.StringIO(text))):
        if not row or not "".join(row).strip() or row[0].strip().startswith("#"):
            continue
        line = i + 1
        if order is None:
            order = list(range(6))
            first = [c.strip().lower() for c in row]
            if not any(_numeric([c]) for c in first):  # a header row: no cell is a number
                if sorted(first) != sorted(COLUMNS):
                    raise HandEyeError(f"{path}: header {row} must name the columns {', '.join(COLUMNS)}")
                order = [first.index(c) for c in COLUMNS]
                continue
        if len(row) != 6:
            raise HandEyeError(f"{path}:{line}: {len(row)} values; a pair is 6 numbers ({', '.join(COLUMNS)})")
        try:
            numbers = [float(row[j]) for j in order]
        except ValueError:
            empty = [name for name, j in zip(COLUMNS, order) if not row[j].strip()]
            hint = f" ({', '.join(empty)} empty: a planned pose not yet measured?)" if empty else ""
            raise HandEyeError(f"{path}:{line}: {row}: every value must be a number{hint}") from None
        if len(values) == MAX_PAIRS:
            raise HandEyeError(f"{path}: more than {MAX_PAIRS} point pairs; at most {MAX_PAIRS} are taken (a hand-eye "
                               "set needs tens: python -m sagrasp_jax.calibrate --plan)")
        values.append(numbers)
    if order is None:
        raise HandEyeError(f"{path}: no point pairs in the file")
    data = np.array(values, dtype=float).reshape(-1, 6)
    return data[:, :3], data[:, 3:]


def _numeric(row: Sequence[str]) -> bool:
    try:
        [float(c) for c in row]
    except ValueError:
        return False
    return True


def calibration_record(fit: HandEyeFit, source: str) -> dict[str, Any]:
    """The calibration file's content: the matrix deploy reads and how it was measured."""
    return {
        "T_cam_base": [[float(v) for v in row] for row in fit.matrix_mm],
        "units": "mm",
        "source": source,
        "pairs": int(len(fit.residuals_mm)),
        "rms_residual_mm": fit.rms_mm,
        "max_residual_mm": fit.max_mm,
        "residuals_mm": [float(v) for v in fit.residuals_mm],
        "quality": fit.quality.record(),
    }


def _parser() -> argparse.ArgumentParser:
    p = cli.Parser(prog="python -m sagrasp_jax.calibrate", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 2)[2])
    p.add_argument("--pairs", help="CSV of point pairs: cam_x,cam_y,cam_z,tcp_x,tcp_y,tcp_z (required unless --plan)")
    p.add_argument("--out", help="calibration JSON to write (deploy --calibration reads it; required unless --plan); "
                                 "with --plan, the plan: .json as JSON, else a pairs CSV to fill in")
    p.add_argument("--cam-units", choices=tuple(UNIT_SCALE), default="mm", help="units of the camera points (default mm)")
    p.add_argument("--tcp-units", choices=tuple(UNIT_SCALE), default="mm", help="units of the TCP points (default mm)")
    p.add_argument("--max-rms", type=float, default=DEFAULT_MAX_RMS_MM, metavar="MM",
                   help=f"refuse a fit whose RMS residual exceeds this (default {DEFAULT_MAX_RMS_MM:g} mm)")
    p.add_argument("--noise-mm", type=float, default=DEFAULT_NOISE_MM, metavar="MM",
                   help="noise of a pair per axis (camera and TCP together) assumed at least in the predicted error "
                        f"(default {DEFAULT_NOISE_MM:g} mm; the residuals' own estimate is used when larger)")
    p.add_argument("--max-rot-deg", type=float, default=DEFAULT_MAX_ROT_DEG, metavar="DEG",
                   help=f"refuse pairs whose predicted p95 rotation error exceeds this (default {DEFAULT_MAX_ROT_DEG:g}°)")
    p.add_argument("--max-mm", type=float, default=DEFAULT_MAX_MM, metavar="MM",
                   help="refuse pairs whose predicted p95 error of mapped points over the target region exceeds this "
                        f"(default {DEFAULT_MAX_MM:g} mm)")
    p.add_argument("--plan", action="store_true", help="print the TCP poses to take the pairs at, instead of fitting")
    p.add_argument("--plan-count", type=int, default=10, metavar="N", help="poses in the plan (default 10)")
    p.add_argument("--robot", choices=robots.names(), default=robots.DEFAULT,
                   help=f"--plan: the arm that takes the poses (env.robot; default {robots.DEFAULT})")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    return p


def _check_options(args: argparse.Namespace) -> None:
    for name in ("max_rms", "noise_mm", "max_rot_deg", "max_mm"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0):
            raise HandEyeError(f"--{name.replace('_', '-')} {value} must be a positive number")


def _report(fit: HandEyeFit, out: str) -> str:
    q = fit.quality
    shown = range(len(fit.residuals_mm))
    lines = ["pair  residual (mm)"]
    if len(fit.residuals_mm) > 50:
        shown = sorted(np.argsort(fit.residuals_mm)[::-1][:10])
        lines = ["pair  residual (mm), the 10 largest"]
    for i in shown:
        flag = "  <- outlier" if i + 1 in q.outliers else ""
        lines.append(f"{i + 1:>4}  {fit.residuals_mm[i]:10.3f}{flag}")
    lines.append(f"RMS {fit.rms_mm:.3f} mm, max {fit.max_mm:.3f} mm over {len(fit.residuals_mm)} pairs")
    lines.append(f"spread {q.spread_mm[0]:.0f} × {q.spread_mm[1]:.0f} × {q.spread_mm[2]:.0f} mm RMS; noise "
                 f"{q.noise_mm:.2f} mm per axis (measured {q.measured_noise_mm:.2f}, assumed {q.noise_floor_mm:g})")
    lines.append(f"predicted p95 error: rotation {q.rotation_p95_deg:.3f}° (limit {q.max_rot_deg:g}°), mapped points "
                 f"{q.workspace_p95_mm:.2f} mm over the target region (limit {q.max_mm:g} mm; {q.centre_p95_mm:.2f} mm "
                 "at its centre)")
    lines.append("T_cam_base (mm):")
    lines += ["  [" + ", ".join(f"{v:10.4f}" for v in row) + "]" for row in fit.matrix_mm]
    lines.append(f"written {out}")
    return "\n".join(lines)


def plan_record(plan: HandEyePlan, max_rot_deg: float = DEFAULT_MAX_ROT_DEG,
                max_mm: float = DEFAULT_MAX_MM, model: RobotModel | None = None) -> dict[str, Any]:
    """The plan as JSON: the poses in the order to visit and the error predicted for pairs taken there."""
    tcp_mm = 1000.0 * float((model or load_robot()).gripper_centre_local[2])  # the planning arm's TCP
    over = [f"{what} {value:.3g}{unit} > {limit:g}{unit} ({option})" for what, value, limit, unit, option in (
        ("rotation", plan.rotation_p95_deg, max_rot_deg, "°", "--max-rot-deg"),
        ("mapped points", plan.workspace_p95_mm, max_mm, " mm", "--max-mm")) if value > limit]
    warnings = ["the plan's predicted p95 error exceeds the limits calibrate applies: " + "; ".join(over)
                + ": plan more poses (--plan-count)"] if over else []
    return {
        "frame": "the robot's base frame (the URDF's, docs/task.md §1.1): positions in mm, angles and joints in rad",
        "tcp": f"the gripper centre, {tcp_mm:g} mm along the flange's z axis: hold the marker there, in the camera's view",
        "poses": [{"pose": k, **pose.record()} for k, pose in enumerate(plan.poses, 1)],
        "noise_mm": plan.noise_mm,
        "predicted_p95_rotation_deg": round(plan.rotation_p95_deg, 4),
        "predicted_p95_workspace_mm": round(plan.workspace_p95_mm, 3),
        "predicted_p95_centre_mm": round(plan.centre_p95_mm, 3),
        "limits": {"max_rot_deg": max_rot_deg, "max_mm": max_mm},
        "warnings": warnings,
    }


def _vector(values: Sequence[float], digits: int = 3) -> str:
    return "(" + ", ".join(f"{v:+.{digits}f}" for v in values) + ")"


def plan_csv(record: dict[str, Any]) -> str:
    """The plan as the rows of a pairs file to fill in: the planned TCP, empty camera columns, a comment per pose."""
    lines = [f"# hand-eye calibration plan (python -m sagrasp_jax.calibrate --plan): {len(record['poses'])} TCP poses in "
             "the robot's base frame (mm), in the order to visit",
             f"# TCP: {record['tcp']}",
             "# at each pose write the camera's point of the marker into cam_x,cam_y,cam_z and the TCP the controller "
             "reports into tcp_x,tcp_y,tcp_z;",
             "# then: python -m sagrasp_jax.calibrate --pairs THIS_FILE --out calibration.json",
             "# the poses are checked (reach, joint limits, table, cell, self-collision, the camera's view), "
             "not the paths between them",
             f"# predicted p95 error with {record['noise_mm']:g} mm of noise per axis: rotation "
             f"{record['predicted_p95_rotation_deg']:g}°, mapped points {record['predicted_p95_workspace_mm']:g} mm",
             "tcp_x,tcp_y,tcp_z,cam_x,cam_y,cam_z"]
    for pose in record["poses"]:
        lines.append(f"# pose {pose['pose']}: approach {_vector(pose['approach'])} ({pose['tilt_deg']:g}° from "
                     f"straight down, {pose['leaning']}), flange rpy {_vector(pose['rpy_rad'])} rad, "
                     f"joints {_vector(pose['q_rad'])} rad")
        lines.append(",".join(f"{v:.1f}" for v in pose["tcp_mm"]) + ",,,")
    return "\n".join(lines) + "\n"


def _plan_report(record: dict[str, Any], out: str | None) -> str:
    lines = [f"hand-eye calibration plan: {len(record['poses'])} TCP poses in the robot's base frame (mm), in the order "
             "to visit from home",
             f"TCP: {record['tcp']}",
             "pose    tcp_x    tcp_y    tcp_z  approach (x, y, z)         lean                    joints q (rad)"]
    for pose in record["poses"]:
        lean = f"{pose['tilt_deg']:g}° {pose['leaning']}"
        lines.append(f"{pose['pose']:>4} " + "".join(f"{v:9.1f}" for v in pose["tcp_mm"])
                     + f"  {_vector(pose['approach'], 2):24} {lean:23} " + " ".join(f"{v:+.3f}" for v in pose["q_rad"]))
    limits = record["limits"]
    lines.append(f"predicted p95 error with {record['noise_mm']:g} mm of noise per axis: rotation "
                 f"{record['predicted_p95_rotation_deg']:.3f}° (limit {limits['max_rot_deg']:g}°), mapped points "
                 f"{record['predicted_p95_workspace_mm']:.2f} mm over the target region (limit {limits['max_mm']:g} mm; "
                 f"{record['predicted_p95_centre_mm']:.2f} mm at its centre)")
    lines.append("at each pose record the camera's point of the marker and the TCP the controller reports: one row "
                 "cam_x,cam_y,cam_z,tcp_x,tcp_y,tcp_z of the pairs file; the poses are checked, not the paths between "
                 "them: move from one to the next through home or by a path you have checked")
    if out is not None:
        lines.append(f"written {out}")
    return "\n".join(lines)


def _plan_command(args: argparse.Namespace) -> int:
    try:
        if args.pairs is not None:
            raise HandEyeError("--plan takes no --pairs: it says where to take them")
        _check_options(args)
        if args.out is not None:
            check_writable(args.out, "plan output", is_folder=False)
        model = load_robot(args.robot)
        record = plan_record(plan_poses(args.plan_count, args.noise_mm, model), args.max_rot_deg, args.max_mm, model)
        if args.out is not None:
            if args.out.lower().endswith(".json"):
                atomic_write_json(args.out, record)
            else:
                atomic_write_text(args.out, plan_csv(record))
    except (HandEyeError, NotWritable, OSError) as exc:
        print(f"python -m sagrasp_jax.calibrate: error: {exc}; nothing written", file=sys.stderr)
        return 2
    for warning in record["warnings"]:
        print(f"python -m sagrasp_jax.calibrate: warning: {warning}", file=sys.stderr)
    print(json.dumps(record, indent=2) if args.json else _plan_report(record, args.out))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.plan:
        return _plan_command(args)
    if args.pairs is None or args.out is None:
        parser.error("--pairs and --out are required (or --plan)")
    try:
        _check_options(args)
        check_writable(args.out, "calibration output", is_folder=False)
        cam, tcp = read_pairs(args.pairs)
        fit = fit_hand_eye(cam * UNIT_SCALE[args.cam_units], tcp * UNIT_SCALE[args.tcp_units], args.max_rms,
                           noise_mm=args.noise_mm, max_rot_deg=args.max_rot_deg, max_mm=args.max_mm)
        CameraCalibration.from_matrix(fit.matrix_mm, "mm", source="fitted hand-eye matrix")  # what deploy will check
        record = calibration_record(fit, args.pairs)
        atomic_write_json(args.out, record)
    except (HandEyeError, CalibrationError, NotWritable, OSError) as exc:
        print(f"python -m sagrasp_jax.calibrate: error: {exc}; nothing written", file=sys.stderr)
        return 2
    for warning in fit.quality.warnings:
        print(f"python -m sagrasp_jax.calibrate: warning: {warning}", file=sys.stderr)
    print(json.dumps(record, indent=2) if args.json else _report(fit, args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
