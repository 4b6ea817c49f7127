"""Hand-eye calibration: ``python -m sagrasp_jax.calibrate --pairs pairs.csv --out calibration.json``.

    python -m sagrasp_jax.calibrate --pairs pairs.csv --out calibration.json
        [--cam-units mm|m] [--tcp-units mm|m] [--max-rms MM] [--json]

``pairs.csv``: one point pair per row, the camera's point then the robot's TCP point (in the controller's
base frame), ``cam_x,cam_y,cam_z,tcp_x,tcp_y,tcp_z``; a header row with those names is optional (with it the
columns may come in any order); blank rows and rows starting with ``#`` are skipped.  Millimetres unless
``--cam-units`` / ``--tcp-units`` say metres.

The least-squares rigid fit (``deploy.handeye``: Kabsch, no scale) gives T_cam_base; every pair's
residual and the RMS are printed, and ``--out`` gets, written atomically, the JSON file ``python -m
sagrasp_jax.deploy --calibration`` reads: ``{"T_cam_base": 4×4 (translation in mm), ...}``.

Exit status 0 written; 2 refused, nothing written: an unreadable file, fewer than 4 pairs, NaN, points
along a line, mixed units, a fit whose RMS residual exceeds ``--max-rms`` (default 5 mm), or a result the
deployment would refuse (``deploy.calibration.CameraCalibration.from_matrix``).  NumPy only.
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

from sagrasp_jax.deploy.calibration import CalibrationError, CameraCalibration
from sagrasp_jax.deploy.handeye import DEFAULT_MAX_RMS_MM, UNIT_SCALE, HandEyeError, HandEyeFit, fit_hand_eye
from sagrasp_jax.base.fileio import NotWritable, atomic_write_json, check_writable, read_regular

COLUMNS = ("cam_x", "cam_y", "cam_z", "tcp_x", "tcp_y", "tcp_z")
MAX_PAIRS_BYTES = 10 * 1024 * 1024


def read_pairs(path: str) -> tuple[np.ndarray, np.ndarray]:
    """(camera points, TCP points), (N, 3) each, as written; ``HandEyeError`` naming the bad row."""
    try:
        text = read_regular(path, MAX_PAIRS_BYTES, "pairs file").decode("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise HandEyeError(f"{path}: cannot read the pairs file ({exc})") from None
    rows = [(i + 1, row) for i, row in enumerate(csv.reader(io.StringIO(text)))
            if row and "".join(row).strip() and not row[0].strip().startswith("#")]
    if not rows:
        raise HandEyeError(f"{path}: no point pairs in the file")
    order = list(range(6))
    first = [c.strip().lower() for c in rows[0][1]]
    if not any(_numeric([c]) for c in first):  # a header row: no cell is a number
        if sorted(first) != sorted(COLUMNS):
            raise HandEyeError(f"{path}: header {rows[0][1]} must name the columns {', '.join(COLUMNS)}")
        order = [first.index(c) for c in COLUMNS]
        rows = rows[1:]
    values = []
    for line, row in rows:
        if len(row) != 6:
            raise HandEyeError(f"{path}:{line}: {len(row)} values; a pair is 6 numbers ({', '.join(COLUMNS)})")
        try:
            numbers = [float(row[j]) for j in order]
        except ValueError:
            raise HandEyeError(f"{path}:{line}: {row}: every value must be a number") from None
        values.append(numbers)
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
    }


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m sagrasp_jax.calibrate", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 2)[2])
    p.add_argument("--pairs", required=True, help="CSV of point pairs: cam_x,cam_y,cam_z,tcp_x,tcp_y,tcp_z")
    p.add_argument("--out", required=True, help="calibration JSON to write (deploy --calibration reads it)")
    p.add_argument("--cam-units", choices=tuple(UNIT_SCALE), default="mm", help="units of the camera points (default mm)")
    p.add_argument("--tcp-units", choices=tuple(UNIT_SCALE), default="mm", help="units of the TCP points (default mm)")
    p.add_argument("--max-rms", type=float, default=DEFAULT_MAX_RMS_MM, metavar="MM",
                   help=f"refuse a fit whose RMS residual exceeds this (default {DEFAULT_MAX_RMS_MM:g} mm)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    return p


def _report(fit: HandEyeFit, out: str) -> str:
    lines = ["pair  residual (mm)"]
    median = float(np.median(fit.residuals_mm))
    for i, r in enumerate(fit.residuals_mm):
        flag = "  <- large" if r > max(3 * median, 2.0) else ""
        lines.append(f"{i + 1:>4}  {r:10.3f}{flag}")
    lines.append(f"RMS {fit.rms_mm:.3f} mm, max {fit.max_mm:.3f} mm over {len(fit.residuals_mm)} pairs")
    lines.append("T_cam_base (mm):")
    lines += ["  [" + ", ".join(f"{v:10.4f}" for v in row) + "]" for row in fit.matrix_mm]
    lines.append(f"written {out}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if not (math.isfinite(args.max_rms) and args.max_rms > 0):
            raise HandEyeError(f"--max-rms {args.max_rms} must be a positive number of mm")
        check_writable(args.out, "calibration output", is_folder=False)
        cam, tcp = read_pairs(args.pairs)
        fit = fit_hand_eye(cam * UNIT_SCALE[args.cam_units], tcp * UNIT_SCALE[args.tcp_units], args.max_rms)
        CameraCalibration.from_matrix(fit.matrix_mm, "mm", source="fitted hand-eye matrix")  # what deploy will check
        record = calibration_record(fit, args.pairs)
        atomic_write_json(args.out, record)
    except (HandEyeError, CalibrationError, NotWritable, OSError) as exc:
        print(f"python -m sagrasp_jax.calibrate: error: {exc}; nothing written", file=sys.stderr)
        return 2
    print(json.dumps(record, indent=2) if args.json else _report(fit, args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
