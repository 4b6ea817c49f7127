"""Hand-eye calibration from point pairs: T_cam_base by a least-squares rigid fit (docs/task.md §5.1).

The paper's Eq. 13–14 map a camera point to the robot base with one 4×4 matrix.  To measure it, touch
(or hold a marker at) N points with the robot's TCP and record, for each, the point as the camera sees
it and the TCP position the controller reports: pairs (p_cam, p_base).  The rigid transform minimising
Σ‖R·p_cam + t − p_base‖² is Kabsch's (Umeyama's without scale): centre both sets, take the SVD of their
cross-covariance, keep det R = +1.  Under isotropic Gaussian noise it is the maximum-likelihood fit.

Refused (``HandEyeError``, exit status 2 in ``python -m sagrasp_jax.calibrate``), before anything is
written: fewer than ``MIN_PAIRS`` pairs (three fix a transform exactly and leave no residual to check
it by); NaN/inf; points spread along a line (the turn about that line is not determined) or bunched
together; the two sets in different units (a rigid motion keeps distances, so the pairwise distances
of the camera points and of the TCP points must agree: a ratio near 1000 means metres against
millimetres, and a single pair off by that factor is named); a fit whose RMS residual exceeds
``max_rms_mm`` (a mismatched pair, a moved camera).

How good is it?  The rotation's error is about σ / (spread·√N): ten pairs with 1 mm of noise per axis,
spread over the workspace's corners (0.7 × 0.45 × 0.37 m), give a median 0.09° (0.05° at 1 mm RMS in
3-D); mapped table points land within 0.4 mm RMS.  The camera origin itself lies 1.4 m from the pairs, so
its own position error is that rotation error times 1.4 m (≈ 1.6 mm): what the grasp needs is the
mapped point, which is why the design spreads the pairs over the volume the cube and obstacles occupy.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

MIN_PAIRS = 4
MIN_SPREAD_MM = 20.0  # second singular value of the centred points / √N: less is a line or a bunch
MAX_DISTANCE_RATIO_ERROR = 0.1  # pairwise distances of the two sets must agree to 10 %
DEFAULT_MAX_RMS_MM = 5.0
UNIT_SCALE = {"mm": 1.0, "m": 1000.0}


class HandEyeError(ValueError):
    """Point pairs that cannot give a trustworthy T_cam_base; nothing is written."""


class HandEyeFit(NamedTuple):
    matrix_mm: np.ndarray  # (4, 4) camera -> base, translation in mm (the file deploy --calibration reads)
    rotation: np.ndarray  # (3, 3)
    translation_mm: np.ndarray  # (3,)
    residuals_mm: np.ndarray  # (N,) ‖R·p_cam + t − p_base‖ per pair
    rms_mm: float
    max_mm: float


def kabsch(cam: np.ndarray, base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation R (det +1) and translation t minimising Σ‖R·cam_i + t − base_i‖² (no scale)."""
    pc, pb = cam.mean(axis=0), base.mean(axis=0)
    u, _, vt = np.linalg.svd((cam - pc).T @ (base - pb))
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rot, pb - rot @ pc


def _check_units(cam: np.ndarray, base: np.ndarray) -> None:
    """Pairwise distances agree between the sets (a rigid motion keeps them), else name the unit mix-up."""
    n = len(cam)
    d_cam = np.linalg.norm(cam[:, None] - cam[None], axis=-1)
    d_base = np.linalg.norm(base[:, None] - base[None], axis=-1)
    usable = ~np.eye(n, dtype=bool) & (d_cam > 1e-9) & (d_base > 1e-9)
    if not usable.any():
        return  # all points coincide: the spread check names that
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(usable, d_base / d_cam, np.nan)
    overall = float(np.nanmedian(ratio))
    if not abs(overall - 1.0) <= MAX_DISTANCE_RATIO_ERROR:
        hint = ""
        if 300 < overall < 3000:
            hint = ": the TCP points look like mm and the camera points like metres (or --cam-units is wrong)"
        elif 1 / 3000 < overall < 1 / 300:
            hint = ": the camera points look like mm and the TCP points like metres (or --tcp-units is wrong)"
        raise HandEyeError(f"distances between the TCP points are {overall:.4g} × those between the camera points; "
                           f"a rigid transform keeps them equal{hint}")
    with np.errstate(invalid="ignore"):
        per_pair = np.array([np.nanmedian(r) if np.isfinite(r).any() else 1.0 for r in ratio])
    bad = [i for i in range(n) if not abs(per_pair[i] - 1.0) <= 0.5]
    if bad and len(bad) < n:
        raise HandEyeError("pair(s) " + ", ".join(f"#{i + 1}" for i in bad) + " disagree in scale with the others "
                           f"(distance ratios {', '.join(f'{per_pair[i]:.3g}' for i in bad)}): mixed units in those rows?")


def check_pairs(cam_mm: Any, base_mm: Any) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float arrays in mm, or ``HandEyeError`` naming the problem."""
    cam, base = np.asarray(cam_mm, dtype=float), np.asarray(base_mm, dtype=float)
    if cam.ndim != 2 or cam.shape[1:] != (3,) or cam.shape != base.shape:
        raise HandEyeError(f"point pairs must be two (N, 3) arrays of equal N, got {cam.shape} and {base.shape}")
    n = len(cam)
    if n < MIN_PAIRS:
        raise HandEyeError(f"{n} point pair(s): at least {MIN_PAIRS} are needed (3 fix a rigid transform exactly and "
                           "leave no residual to check it by); 10 or more, spread over the workspace, are better")
    bad = [i + 1 for i in range(n) if not (np.isfinite(cam[i]).all() and np.isfinite(base[i]).all())]
    if bad:
        raise HandEyeError(f"pair(s) {', '.join(f'#{i}' for i in bad)} hold NaN/inf")
    _check_units(cam, base)
    for name, pts in (("TCP", base), ("camera", cam)):
        s = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False) / math.sqrt(n)
        if s[1] < MIN_SPREAD_MM:
            why = ("bunched together: the rotation is not determined" if s[0] < MIN_SPREAD_MM
                   else "along a line: the turn about that line is not determined")
            raise HandEyeError(
                f"the {name} points lie {why} (spread {s[0]:.1f} × {s[1]:.1f} × {s[2]:.1f} mm RMS about their "
                f"centre; each of the two largest must reach {MIN_SPREAD_MM:g} mm); spread the TCP over the "
                "workspace, not along one axis")
    return cam, base


def fit_hand_eye(cam_mm: Any, base_mm: Any, max_rms_mm: float = DEFAULT_MAX_RMS_MM) -> HandEyeFit:
    """T_cam_base (mm) from point pairs, with its residuals; ``HandEyeError`` for a degenerate set or a
    fit whose RMS residual exceeds ``max_rms_mm``."""
    cam, base = check_pairs(cam_mm, base_mm)
    rot, t = kabsch(cam, base)
    residuals = np.linalg.norm(cam @ rot.T + t - base, axis=1)
    rms = float(np.sqrt(np.mean(residuals**2)))
    if not rms <= max_rms_mm:
        worst = np.argsort(residuals)[::-1][:3]
        raise HandEyeError(f"the pairs disagree: RMS residual {rms:.2f} mm > {max_rms_mm:g} mm (worst: "
                           + ", ".join(f"#{i + 1} {residuals[i]:.1f} mm" for i in worst)
                           + "): a mismatched pair, or the camera moved between readings")
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rot, t
    return HandEyeFit(matrix, rot, t, residuals, rms, float(residuals.max()))


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """The angle of the rotation taking ``b`` to ``a`` (degrees)."""
    cos = (np.trace(np.asarray(a).T @ np.asarray(b)) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, cos))))
