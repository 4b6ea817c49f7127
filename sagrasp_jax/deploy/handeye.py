"""Hand-eye calibration from point pairs: T_cam_base by a least-squares rigid fit (docs/task.md §5.1, §5.7),
how good that fit is, and where to take the pairs.

The paper's Eq. 13–14 map a camera point to the robot base with one 4×4 matrix.  To measure it, touch
(or hold a marker at) N points with the robot's TCP and record, for each, the point as the camera sees
it and the TCP position the controller reports: pairs (p_cam, p_base).  The rigid transform minimising
Σ‖R·p_cam + t − p_base‖² is Kabsch's (Umeyama's without scale): centre both sets, take the SVD of their
cross-covariance, keep det R = +1.  Under isotropic Gaussian noise it is the maximum-likelihood fit.

Refused (``HandEyeError``, exit status 2 in ``python -m sagrasp_jax.calibrate``), before anything is
written: fewer than ``MIN_PAIRS`` pairs (three fix a transform exactly and leave no residual to check
it by) or more than ``MAX_PAIRS``; NaN/inf; points spread along a line (the turn about that line is not
determined) or bunched together; the two sets in different units (a rigid motion keeps distances, so
the distances of the camera points and of the TCP points to the same reference pairs must agree: a
ratio near 1000 means metres against millimetres, and a single pair off by that factor is named); a fit
whose RMS residual exceeds ``max_rms_mm`` (a mismatched pair, a moved camera); and a fit whose predicted
error exceeds the accuracy asked (``max_rot_deg``, ``max_mm``).

How good is it (``FitQuality``)?  To first order the fit's rotation error w (a rotation vector) and its
translation error at the pairs' centroid are independent Gaussians: cov(w) = σ²·H⁻¹ with
H = Σᵢ [dᵢ]ₓᵀ[dᵢ]ₓ = Σᵢ (‖dᵢ‖² I − dᵢdᵢᵀ), dᵢ the TCP points about their centroid b̄, and cov = σ²/N · I at
b̄; a camera point mapped to x in the base is then off by w × (x − b̄) + (that centroid error), covariance
[x − b̄]ₓ σ²H⁻¹ [x − b̄]ₓᵀ + σ²/N · I.  σ is the per-axis noise of a pair (camera and TCP together): the
larger of an assumed floor (``noise_mm``, default 1 mm) and what the residuals measure,
√(Σ‖rᵢ‖² / (3N − 6)).  The report gives the 95th percentiles of the rotation angle ‖w‖ and of the 3-D
error of mapped points over ``workspace_points_mm`` (the target region's corners and centre at the cube
top's height, docs/task.md §1.4: where the camera's points are used); tests/deploy/test_handeye.py checks both
against Monte-Carlo draws.  The prediction covers noise, not a bias common to every pair (a marker that
is not where the controller's TCP is).

Two limits follow from it.  No set of pairs beats σ/√N per axis at the centroid (the Cramér–Rao bound),
so ten pairs with 1 mm of noise per axis cannot map a point better than ≈ 0.9 mm at p95 (3-D) wherever
they are taken; and the camera sees only a 43° × 28° cone, so the rotation's lever is at most a few
hundred mm.  The best ten poses the camera sees and the arm reaches (``plan_poses``) predict 0.145° and
1.17 mm at p95 with 1 mm per axis (0.90 mm at the workspace's centre); 0.1° takes 22 such poses, 0.5 mm
over the whole target region 60 (30 at its centre), or less noise: both scale with σ.  Hence the
defaults ``DEFAULT_MAX_ROT_DEG`` 0.25° and ``DEFAULT_MAX_MM`` 2 mm (refused above; a warning above
``WARN_FRACTION`` of them): the planned poses pass at 1 mm per axis even when the residuals read the noise
1.7 × too high, and every weak set is refused or warned: four pairs, a near-line, ten pairs in a 100 mm
cube, ten pairs drawn at random in the workspace (0.22–0.29° predicted, 1st–50th percentile).

Where to take the pairs (``plan_poses``, ``calibrate --plan``): the positions, within what the camera
sees (the paper's pose, with a margin) and the arm reaches above the table, that minimise the predicted
error (an exchange search on a 50 mm grid between 40 and 400 mm above the table: the volume the cube and
the obstacles occupy), each with a gripper orientation that the URDF's arm reaches by inverse kinematics
from ``env.task.home_q`` without touching the table, the cell or itself, and that leaves the line of
sight from the TCP to the camera clear of the arm and gripper.
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple

import numpy as np

from sagrasp_jax.deploy.safety import SafetyLayer, SafetyViolation
from sagrasp_jax.task import collision, geometry
from sagrasp_jax.task.config import EnvConfig, SamplingConfig
from sagrasp_jax.task.robot import RobotModel, forward_kinematics, load_robot, primitive_poses
from sagrasp_jax.task.sampling import ResetSpec
from sagrasp_jax.task.scene import SCENE

MIN_PAIRS = 4
MAX_PAIRS = 10_000  # a hand-eye set is tens of pairs; this leaves room for automatic collection, in bounded memory
MIN_SPREAD_MM = 20.0  # second singular value of the centred points / √N: less is a line or a bunch
MAX_DISTANCE_RATIO_ERROR = 0.1  # distances in the two sets must agree to 10 %
UNIT_REFERENCES = 64  # pairs the unit check measures every pair's distances to (all of them below that)
DEFAULT_MAX_RMS_MM = 5.0
DEFAULT_NOISE_MM = 1.0  # assumed per-axis noise of a pair: the floor of the prediction's σ
DEFAULT_MAX_ROT_DEG = 0.25  # refuse a predicted p95 rotation error above this
DEFAULT_MAX_MM = 2.0  # refuse a predicted p95 error of mapped workspace points above this
WARN_FRACTION = 0.8  # warn when a predicted error exceeds this fraction of its limit
OUTLIER_FALSE_ALARM = 0.01  # chance that an honest set of pairs has a pair named an outlier (see outlier_sigmas)
NOISE_WARN_RATIO = 1.5  # residuals showing this × the assumed noise are reported
UNIT_SCALE = {"mm": 1.0, "m": 1000.0}
SPHERE_POINTS = 100  # directions of the quadrature in norm_p95 (to ≈ 1e-4)
_CHI3_MEDIAN = 1.5382  # median of ‖e‖ for e ~ N(0, I₃)


class HandEyeError(ValueError):
    """Point pairs that cannot give a trustworthy T_cam_base; nothing is written."""


class FitQuality(NamedTuple):
    """What a set of pairs can promise: the predicted p95 errors and what they rest on (see the module doc)."""

    pairs: int
    spread_mm: tuple[float, float, float]  # RMS distance of the TCP points from their centroid along its principal axes
    residual_rms_mm: float  # RMS of the 3-D residuals
    measured_noise_mm: float  # per axis, √(Σ‖r‖² / (3N − 6))
    noise_floor_mm: float  # per axis, assumed
    noise_mm: float  # per axis, the larger of the two: what the prediction uses
    rotation_p95_deg: float
    workspace_p95_mm: float  # the worst of the workspace points
    centre_p95_mm: float  # at the workspace's centre (the cube's nominal position)
    worst_point_mm: tuple[float, float, float]
    outliers: tuple[int, ...]  # pair numbers (from 1) whose residual exceeds outlier_sigmas(N) σ
    warnings: tuple[str, ...]
    max_rot_deg: float  # the limits it is checked against (check_quality)
    max_mm: float

    def record(self) -> dict[str, Any]:
        """The ``quality`` block of calibration.json."""
        return {
            "pairs": self.pairs,
            "spread_mm": [round(v, 3) for v in self.spread_mm],
            "residual_rms_mm": round(self.residual_rms_mm, 4),
            "measured_noise_mm": round(self.measured_noise_mm, 4),
            "noise_floor_mm": self.noise_floor_mm,
            "noise_mm": round(self.noise_mm, 4),
            "predicted_p95_rotation_deg": round(self.rotation_p95_deg, 4),
            "predicted_p95_workspace_mm": round(self.workspace_p95_mm, 3),
            "predicted_p95_centre_mm": round(self.centre_p95_mm, 3),
            "worst_point_mm": [round(v, 1) for v in self.worst_point_mm],
            "outliers": list(self.outliers),
            "warnings": list(self.warnings),
            "limits": {"max_rot_deg": self.max_rot_deg, "max_mm": self.max_mm},
        }


class HandEyeFit(NamedTuple):
    matrix_mm: np.ndarray  # (4, 4) camera -> base, translation in mm (the file deploy --calibration reads)
    rotation: np.ndarray  # (3, 3)
    translation_mm: np.ndarray  # (3,)
    residuals_mm: np.ndarray  # (N,) ‖R·p_cam + t − p_base‖ per pair
    rms_mm: float
    max_mm: float
    quality: FitQuality


def kabsch(cam: np.ndarray, base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation R (det +1) and translation t minimising Σ‖R·cam_i + t − base_i‖² (no scale)."""
    pc, pb = cam.mean(axis=0), base.mean(axis=0)
    u, _, vt = np.linalg.svd((cam - pc).T @ (base - pb))
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rot, pb - rot @ pc


def _check_units(cam: np.ndarray, base: np.ndarray) -> None:
    """Distances agree between the sets (a rigid motion keeps them), else name the unit mix-up.

    Every pair's distances to up to ``UNIT_REFERENCES`` reference pairs (all pairs when there are no more),
    one reference at a time: memory grows linearly with the pairs."""
    n = len(cam)
    refs = np.unique(np.linspace(0, n - 1, min(n, UNIT_REFERENCES)).round().astype(int))
    ratio = np.full((n, len(refs)), np.nan, dtype=np.float32)  # a 10 % check: single precision is plenty
    for k, j in enumerate(refs):
        d_cam = np.linalg.norm(cam - cam[j], axis=1)
        d_base = np.linalg.norm(base - base[j], axis=1)
        usable = (d_cam > 1e-9) & (d_base > 1e-9)
        ratio[usable, k] = d_base[usable] / d_cam[usable]
    finite = ratio[np.isfinite(ratio)]
    if not finite.size:
        return  # all points coincide: the spread check names that
    overall = float(np.median(finite))
    del finite
    if not abs(overall - 1.0) <= MAX_DISTANCE_RATIO_ERROR:
        hint = ""
        if 300 < overall < 3000:
            hint = ": the TCP points look like mm and the camera points like metres (or --cam-units is wrong)"
        elif 1 / 3000 < overall < 1 / 300:
            hint = ": the camera points look like mm and the TCP points like metres (or --tcp-units is wrong)"
        raise HandEyeError(f"distances between the TCP points are {overall:.4g} × those between the camera points; "
                           f"a rigid transform keeps them equal{hint}")
    ratio.sort(axis=1)  # in place, NaN last: each row's median from its finite head
    count = np.sum(np.isfinite(ratio), axis=1)
    rows = np.arange(n)
    lower, upper = np.maximum(count - 1, 0) // 2, np.maximum(count, 1) // 2
    middle = (ratio[rows, lower].astype(float) + ratio[rows, np.minimum(upper, len(refs) - 1)]) / 2
    per_pair = np.where(count > 0, middle, 1.0)
    bad = np.nonzero(~(np.abs(per_pair - 1.0) <= 0.5))[0]
    if len(bad) and len(bad) < n:
        shown = bad[:10]
        more = f" and {len(bad) - len(shown)} more" if len(bad) > len(shown) else ""
        raise HandEyeError("pair(s) " + ", ".join(f"#{i + 1}" for i in shown) + more + " disagree in scale with the "
                           f"others (distance ratios {', '.join(f'{per_pair[i]:.3g}' for i in shown)}): mixed units in "
                           "those rows?")


def spread_mm(points: np.ndarray) -> np.ndarray:
    """RMS distance (3,) of the points from their centroid along its principal axes, largest first."""
    return np.linalg.svd(points - points.mean(axis=0), compute_uv=False) / math.sqrt(len(points))


def check_pairs(cam_mm: Any, base_mm: Any) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float arrays in mm, or ``HandEyeError`` naming the problem."""
    cam, base = np.asarray(cam_mm, dtype=float), np.asarray(base_mm, dtype=float)
    if cam.ndim != 2 or cam.shape[1:] != (3,) or cam.shape != base.shape:
        raise HandEyeError(f"point pairs must be two (N, 3) arrays of equal N, got {cam.shape} and {base.shape}")
    n = len(cam)
    if n < MIN_PAIRS:
        raise HandEyeError(f"{n} point pair(s): at least {MIN_PAIRS} are needed (3 fix a rigid transform exactly and "
                           "leave no residual to check it by); 10 or more, spread over the workspace, are better")
    if n > MAX_PAIRS:
        raise HandEyeError(f"{n} point pairs: at most {MAX_PAIRS} are taken (a hand-eye set needs tens: "
                           "python -m sagrasp_jax.calibrate --plan)")
    bad = np.nonzero(~(np.isfinite(cam).all(axis=1) & np.isfinite(base).all(axis=1)))[0]
    if len(bad):
        more = f" and {len(bad) - 10} more" if len(bad) > 10 else ""
        raise HandEyeError(f"pair(s) {', '.join(f'#{i + 1}' for i in bad[:10])}{more} hold NaN/inf")
    _check_units(cam, base)
    for name, pts in (("TCP", base), ("camera", cam)):
        s = spread_mm(pts)
        if s[1] < MIN_SPREAD_MM:
            why = ("bunched together: the rotation is not determined" if s[0] < MIN_SPREAD_MM
                   else "along a line: the turn about that line is not determined")
            raise HandEyeError(
                f"the {name} points lie {why} (spread {s[0]:.1f} × {s[1]:.1f} × {s[2]:.1f} mm RMS about their "
                f"centre; each of the two largest must reach {MIN_SPREAD_MM:g} mm); spread the TCP over the "
                "workspace, not along one axis (python -m sagrasp_jax.calibrate --plan)")
    return cam, base


# ------------------------------------------------------------------ the predicted error


def workspace_points_mm(sampling: SamplingConfig | None = None) -> np.ndarray:
    """Where mapped camera points matter (5, 3), mm: the corners of the target region (docs/task.md §1.4,
    ``env.sampling.target_x`` / ``target_y``) and, last, its centre, at the height of the cube's top face
    (the point the camera measures)."""
    s = sampling or SamplingConfig()
    z = 1000.0 * (SCENE.table.top_z + s.target_size[2])
    xs, ys = [1000.0 * v for v in s.target_x], [1000.0 * v for v in s.target_y]
    return np.array([[x, y, z] for x in xs for y in ys] + [[sum(xs) / 2, sum(ys) / 2, z]])


@functools.lru_cache(maxsize=1)
def _sphere_squares() -> np.ndarray:
    """Squared coordinates (SPHERE_POINTS, 3) of a Fibonacci lattice on the unit sphere: nearly equal-area cells."""
    i = np.arange(SPHERE_POINTS) + 0.5
    z = 1.0 - 2.0 * i / SPHERE_POINTS
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z * z)
    u = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
    return u**2


def _erf(x: np.ndarray) -> np.ndarray:
    """erf for x ≥ 0 (Abramowitz & Stegun 7.1.26, error < 1.5e-7): NumPy has none."""
    t = 1.0 / (1.0 + 0.3275911 * x)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    return 1.0 - poly * np.exp(-x * x)


def norm_p95(cov: Any) -> np.ndarray:
    """The 95th percentile of ‖e‖ for e ~ N(0, cov), cov (..., 3, 3) → (...).  With cov's eigenvalues λ,
    e = ρ·(√λ ∘ u) for ρ ~ χ₃ and u uniform on the sphere, independent, so P(‖e‖² ≤ s) is the mean over u of
    the χ²₃ CDF at s / Σ λₖuₖ²: a closed form (erf) averaged over a 100-direction lattice, solved for 0.95 on
    four nested grids (to ≈ 1e-4: 2.7955 for cov = I, √χ²₃(0.95))."""
    cov = np.asarray(cov, dtype=float)
    lam = np.linalg.eigvalsh(cov.reshape(-1, 3, 3)).clip(0.0, None)  # (K, 3), ascending
    g = _sphere_squares() @ lam.T  # (M, K)
    top = np.maximum(lam[:, 2], 1e-300)
    lo = np.log(7.8147 * np.maximum(lam[:, 0], 1e-12 * top))  # χ²₃(0.95) × the smallest and the largest λ
    hi = np.log(7.8147 * top)
    rows = np.arange(len(lam))
    for _ in range(4):  # the bracket (log-width ≤ 28) cut in 15 four times: to < 6e-4, 0.03 % of the norm
        grid = lo[:, None] + (hi - lo)[:, None] * np.linspace(0.0, 1.0, 16)  # (K, 16)
        x = np.exp(grid)[None] / np.maximum(g, 1e-300)[:, :, None]  # (M, K, 16)
        cdf = np.mean(_erf(np.sqrt(x / 2)) - np.sqrt(2 * x / math.pi) * np.exp(-x / 2), axis=0)
        j = np.clip(np.sum(cdf < 0.95, axis=1), 1, 15)
        lo, hi = grid[rows, j - 1], grid[rows, j]
    return np.sqrt(np.exp((lo + hi) / 2)).reshape(cov.shape[:-2])


def _skew(v: np.ndarray) -> np.ndarray:
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def rotation_information(base_mm: np.ndarray) -> np.ndarray:
    """H = Σ (‖dᵢ‖² I − dᵢdᵢᵀ) (mm²) of the points about their centroid: cov(rotation error) = σ² H⁻¹."""
    d = base_mm - base_mm.mean(axis=0)
    scatter = d.T @ d
    return np.trace(scatter) * np.eye(3) - scatter


def predict_errors(base_mm: Any, noise_mm: float, points_mm: Any = None) -> tuple[float, np.ndarray]:
    """(p95 of the rotation error in degrees, p95 of the 3-D error in mm at each of ``points_mm``) of a rigid
    fit to pairs at the TCP points ``base_mm`` with ``noise_mm`` of Gaussian noise per axis (first order; see
    the module doc).  ``points_mm`` defaults to ``workspace_points_mm()``.  inf for points along a line."""
    base = np.asarray(base_mm, dtype=float)
    points = workspace_points_mm() if points_mm is None else np.asarray(points_mm, dtype=float).reshape(-1, 3)
    h = rotation_information(base)
    if not np.linalg.eigvalsh(h)[0] > 1e-9 * max(np.trace(h), 1e-300):
        return math.inf, np.full(len(points), math.inf)
    cov_w = noise_mm**2 * np.linalg.inv(h)
    arm = _skew(points - base.mean(axis=0))
    cov_x = arm @ cov_w @ arm.transpose(0, 2, 1) + noise_mm**2 / len(base) * np.eye(3)
    p95 = norm_p95(np.concatenate([cov_w[None], cov_x]))
    return math.degrees(float(p95[0])), p95[1:]


def outlier_sigmas(pairs: int) -> float:
    """The residual, in σ per axis, beyond which a pair is named an outlier: the 3-D norm of N(0, σ²I) exceeds it
    with probability ``OUTLIER_FALSE_ALARM`` / max(N, 10) per pair (4.03 σ for 10 pairs, 5.54 σ for 10,000)."""
    p = OUTLIER_FALSE_ALARM / max(pairs, 10)
    lo, hi = 0.0, 20.0
    for _ in range(60):  # P(‖e‖ > r) = erfc(r/√2) + √(2/π)·r·exp(−r²/2), decreasing in r
        r = (lo + hi) / 2
        if math.erfc(r / math.sqrt(2)) + math.sqrt(2 / math.pi) * r * math.exp(-r * r / 2) > p:
            lo = r
        else:
            hi = r
    return hi


def assess(base_mm: np.ndarray, residuals_mm: np.ndarray, noise_floor_mm: float = DEFAULT_NOISE_MM,
           max_rot_deg: float = DEFAULT_MAX_ROT_DEG, max_mm: float = DEFAULT_MAX_MM) -> FitQuality:
    """The quality of a fit to pairs at the TCP points ``base_mm`` that left ``residuals_mm`` (3-D, per pair),
    with warnings for outliers, more noise than assumed, few pairs and a prediction near its limits."""
    n = len(base_mm)
    measured = math.sqrt(float(np.sum(residuals_mm**2)) / max(3 * n - 6, 1))
    noise = max(noise_floor_mm, measured)
    rot, at = predict_errors(base_mm, noise)
    points = workspace_points_mm()
    worst = int(np.argmax(at))
    robust = float(np.median(residuals_mm)) / _CHI3_MEDIAN  # per axis, unmoved by a few bad pairs
    sigmas = outlier_sigmas(n)
    limit = sigmas * max(noise_floor_mm, robust)
    outliers = tuple(int(i) + 1 for i in np.nonzero(residuals_mm > limit)[0])
    warnings = []
    if outliers:
        warnings.append(f"pair(s) {', '.join(f'#{i}' for i in outliers[:10])}{' ...' if len(outliers) > 10 else ''} "
                        f"left a residual over {sigmas:.1f} σ ({limit:.2f} mm: "
                        + ", ".join(f"{residuals_mm[i - 1]:.2f} mm" for i in outliers[:10])
                        + "): a misread pair? re-measure or drop it")
    if measured > NOISE_WARN_RATIO * noise_floor_mm:
        warnings.append(f"the residuals show {measured:.2f} mm of noise per axis, more than the {noise_floor_mm:g} mm "
                        "assumed (--noise-mm): the prediction uses the measured noise; check that the marker sits at "
                        "the TCP the controller reports")
    if n < 10:
        warnings.append(f"only {n} pairs: the measured noise rests on {3 * n - 6} numbers; 10 or more are better")
    near = [f"{what} {value:.3g}{unit} is over {WARN_FRACTION:.0%} of its limit {bound:g}{unit}"
            for what, value, bound, unit in (("rotation", rot, max_rot_deg, "°"),
                                             ("mapped points", float(at[worst]), max_mm, " mm"))
            if WARN_FRACTION * bound < value <= bound]
    if near:
        warnings.append("predicted p95 error: " + "; ".join(near)
                        + ": weak pairs (python -m sagrasp_jax.calibrate --plan)")
    return FitQuality(
        pairs=n,
        spread_mm=tuple(float(v) for v in spread_mm(base_mm)),  # type: ignore[arg-type]
        residual_rms_mm=float(np.sqrt(np.mean(residuals_mm**2))),
        measured_noise_mm=measured,
        noise_floor_mm=float(noise_floor_mm),
        noise_mm=noise,
        rotation_p95_deg=rot,
        workspace_p95_mm=float(at[worst]),
        centre_p95_mm=float(at[-1]),
        worst_point_mm=tuple(float(v) for v in points[worst]),  # type: ignore[arg-type]
        outliers=outliers,
        warnings=tuple(warnings),
        max_rot_deg=float(max_rot_deg),
        max_mm=float(max_mm),
    )


def check_quality(quality: FitQuality) -> None:
    """``HandEyeError`` naming the predicted error and the limit when the pairs cannot promise the accuracy asked."""
    over, max_rot_deg, max_mm = [], quality.max_rot_deg, quality.max_mm
    if not quality.rotation_p95_deg <= max_rot_deg:
        over.append(f"rotation {quality.rotation_p95_deg:.3f}° > {max_rot_deg:g}° (--max-rot-deg)")
    if not quality.workspace_p95_mm <= max_mm:
        point = ", ".join(f"{v:.0f}" for v in quality.worst_point_mm)
        over.append(f"mapped workspace points {quality.workspace_p95_mm:.2f} mm (at {point}) > {max_mm:g} mm (--max-mm)")
    if over:
        s = quality.spread_mm
        raise HandEyeError(
            "the pairs cannot promise the accuracy asked: predicted p95 error " + "; ".join(over)
            + f", from {quality.pairs} pairs spread {s[0]:.0f} × {s[1]:.0f} × {s[2]:.0f} mm RMS with "
            f"{quality.noise_mm:.2f} mm of noise per axis (measured {quality.measured_noise_mm:.2f}, assumed "
            f"{quality.noise_floor_mm:g}); take more pairs, spread over the workspace "
            "(python -m sagrasp_jax.calibrate --plan)")


def fit_hand_eye(cam_mm: Any, base_mm: Any, max_rms_mm: float = DEFAULT_MAX_RMS_MM, *,
                 noise_mm: float = DEFAULT_NOISE_MM, max_rot_deg: float = DEFAULT_MAX_ROT_DEG,
                 max_mm: float = DEFAULT_MAX_MM) -> HandEyeFit:
    """T_cam_base (mm) from point pairs, with its residuals and predicted quality; ``HandEyeError`` for a
    degenerate set, a fit whose RMS residual exceeds ``max_rms_mm``, or one whose predicted p95 errors
    (with at least ``noise_mm`` of noise per axis) exceed ``max_rot_deg`` / ``max_mm``."""
    cam, base = check_pairs(cam_mm, base_mm)
    rot, t = kabsch(cam, base)
    residuals = np.linalg.norm(cam @ rot.T + t - base, axis=1)
    rms = float(np.sqrt(np.mean(residuals**2)))
    if not rms <= max_rms_mm:
        worst = np.argsort(residuals)[::-1][:3]
        raise HandEyeError(f"the pairs disagree: RMS residual {rms:.2f} mm > {max_rms_mm:g} mm (worst: "
                           + ", ".join(f"#{i + 1} {residuals[i]:.1f} mm" for i in worst)
                           + "): a mismatched pair, or the camera moved between readings")
    quality = assess(base, residuals, noise_mm, max_rot_deg, max_mm)
    check_quality(quality)
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rot, t
    return HandEyeFit(matrix, rot, t, residuals, rms, float(residuals.max()), quality)


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """The angle of the rotation taking ``b`` to ``a`` (degrees)."""
    cos = (np.trace(np.asarray(a).T @ np.asarray(b)) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, cos))))


# ------------------------------------------------------------------ where to take the pairs

PLAN_HEIGHTS_MM = (40.0, 400.0)  # TCP heights: 4 cm above the table up to the obstacles' tops (≤ 0.36 m)
PLAN_GRID_MM = 50.0
PLAN_REACH_MM = (250.0, 750.0)  # horizontal distance from the base axis a candidate may have (the IK decides)
PLAN_BOX_MARGIN_MM = 50.0  # inside the safety layer's workspace box (deploy.safety.WorkspaceBox)
# The camera's view for the plan: the scene camera's half field of view (tan; task.camera, the Mech-Eye PRO M's
# 43.2° × 27.8°) from the paper's pose, keeping the planned points within 85 % of it for a camera a few cm elsewhere.
CAMERA_HALF_FOV_TAN = SCENE.camera.model.intrinsics.half_fov_tan
PLAN_FOV_MARGIN = 0.85
MARKER_CLEARANCE_MM = 5.0  # the line of sight from the TCP to the camera passes the arm by this much
PLAN_TILTS_DEG = (45.0, 60.0, 30.0, 75.0)  # approach axis from straight down, tried in this order
PLAN_DIRECTIONS = ("outward", "clockwise", "counterclockwise", "toward the camera", "inward")
ROTATION_WEIGHT_MM = 500.0  # the search weighs the rotation error as the error of a point this far away
MAX_PLAN_COUNT = 100


class PlannedPose(NamedTuple):
    tcp_mm: np.ndarray  # (3,) gripper centre (the TCP), base frame
    approach: np.ndarray  # (3,) unit gripper approach axis (flange +z), base frame
    finger_axis: np.ndarray  # (3,) unit direction the fingers open along (flange +x), horizontal
    rpy: np.ndarray  # (3,) the flange's roll, pitch, yaw (rad; R = Rz(yaw)·Ry(pitch)·Rx(roll), the URDF's convention)
    q: np.ndarray  # (dof,) joints (rad) that reach it from env.task.home_q's branch
    tilt_deg: float
    direction: str  # where the approach axis leans: out of / into the base axis, (counter)clockwise, toward the camera

    def record(self) -> dict[str, Any]:
        return {"tcp_mm": [round(float(v), 1) for v in self.tcp_mm],
                "approach": [round(float(v), 4) for v in self.approach],
                "finger_axis": [round(float(v), 4) for v in self.finger_axis],
                "rpy_rad": [round(float(v), 4) for v in self.rpy],
                "q_rad": [round(float(v), 4) for v in self.q],
                "tilt_deg": self.tilt_deg, "leaning": self.direction}


class HandEyePlan(NamedTuple):
    poses: tuple[PlannedPose, ...]  # in the order to visit, from home
    noise_mm: float
    rotation_p95_deg: float  # predicted for pairs at these poses with noise_mm per axis
    workspace_p95_mm: float
    centre_p95_mm: float


def _visible(points_mm: np.ndarray, margin: float = PLAN_FOV_MARGIN) -> np.ndarray:
    cam = (points_mm - 1000.0 * np.asarray(SCENE.camera.pos)) @ SCENE.camera.rot
    z = cam[:, 2]
    return ((z > 0) & (np.abs(cam[:, 0]) <= margin * CAMERA_HALF_FOV_TAN[0] * z)
            & (np.abs(cam[:, 1]) <= margin * CAMERA_HALF_FOV_TAN[1] * z))


def plan_candidates() -> np.ndarray:
    """TCP positions (C, 3) mm on the plan's grid that the camera sees, inside the safety layer's box and reach."""
    box = SafetyLayer().workspace
    lo = [1000.0 * v + PLAN_BOX_MARGIN_MM for v in box.lower[:2]]
    hi = [1000.0 * v - PLAN_BOX_MARGIN_MM for v in box.upper[:2]]
    axes = [np.arange(math.ceil(a / PLAN_GRID_MM), math.floor(b / PLAN_GRID_MM) + 1) * PLAN_GRID_MM
            for a, b in zip(lo, hi)]
    zs = np.arange(PLAN_HEIGHTS_MM[0], PLAN_HEIGHTS_MM[1] + 1e-9, PLAN_GRID_MM)
    grid = np.stack(np.meshgrid(*axes, zs, indexing="ij"), -1).reshape(-1, 3)
    r = np.hypot(grid[:, 0], grid[:, 1])
    return grid[_visible(grid) & (r >= PLAN_REACH_MM[0]) & (r <= PLAN_REACH_MM[1])]


def _design_cost(s1: np.ndarray, s2: np.ndarray, n: int, points: np.ndarray) -> np.ndarray:
    """The search's cost (C,) of designs given by their sums Σb (C, 3) and Σbbᵀ (C, 3, 3): the summed variances
    (σ = 1) of the rotation (times ROTATION_WEIGHT_MM²) and of the worst mapped workspace point."""
    mean = s1 / n
    scatter = s2 - n * mean[:, :, None] * mean[:, None, :]
    trace = np.trace(scatter, axis1=1, axis2=2)
    h = trace[:, None, None] * np.eye(3) - scatter
    ok = np.linalg.det(h) > 1e-9 * np.maximum(trace, 1e-300) ** 3
    hinv = np.linalg.inv(np.where(ok[:, None, None], h, np.eye(3)))
    tr = np.trace(hinv, axis1=1, axis2=2)
    d = points[None] - mean[:, None]
    at = np.sum(d**2, -1) * tr[:, None] - np.einsum("cki,cij,ckj->ck", d, hinv, d)
    return np.where(ok, ROTATION_WEIGHT_MM**2 * tr + at.max(-1) + 3.0 / n, np.inf)


def _exchange(cands: np.ndarray, chosen: list[int], allowed: np.ndarray, points: np.ndarray) -> list[int]:
    """Fedorov-style exchange: swap one chosen candidate for the best other while the cost falls."""
    n, outer = len(chosen), cands[:, :, None] * cands[:, None, :]
    s1, s2 = cands[chosen].sum(0), outer[chosen].sum(0)
    best = float(_design_cost(s1[None], s2[None], n, points)[0])
    for _ in range(100):
        improved = False
        for i in range(n):
            j = chosen[i]
            t1, t2 = s1 - cands[j] + cands, s2 - outer[j] + outer
            cost = _design_cost(t1, t2, n, points)
            cost[~allowed] = np.inf
            cost[chosen] = np.inf
            k = int(np.argmin(cost))
            if cost[k] < best * (1.0 - 1e-9):
                chosen[i], s1, s2, best, improved = k, t1[k], t2[k], float(cost[k]), True
        if not improved:
            break
    return chosen


def _spread_start(cands: np.ndarray, n: int, allowed: np.ndarray) -> list[int]:
    """n allowed candidates spread by farthest-point selection, from the one farthest from their mean."""
    idx = np.nonzero(allowed)[0]
    pts = cands[idx]
    first = int(np.argmax(np.linalg.norm(pts - pts.mean(0), axis=1)))
    chosen, dist = [first], np.linalg.norm(pts - pts[first], axis=1)
    while len(chosen) < min(n, len(idx)):
        k = int(np.argmax(dist))
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(pts - pts[k], axis=1))
    return [int(idx[k]) for k in chosen]


def _approach_axes(tcp_mm: np.ndarray, tilt_deg: float, direction: str) -> np.ndarray:
    """Unit approach axes (P, 3) tilted ``tilt_deg`` from straight down, leaning along ``direction``."""
    radial = tcp_mm[:, :2] / np.linalg.norm(tcp_mm[:, :2], axis=1, keepdims=True)
    lean = {"outward": radial, "inward": -radial,
            "clockwise": np.stack([radial[:, 1], -radial[:, 0]], -1),
            "counterclockwise": np.stack([-radial[:, 1], radial[:, 0]], -1)}.get(direction)
    if lean is None:  # toward the camera's foot
        lean = 1000.0 * np.asarray(SCENE.camera.pos[:2]) - tcp_mm[:, :2]
        lean = lean / np.maximum(np.linalg.norm(lean, axis=1, keepdims=True), 1e-9)
    t = math.radians(tilt_deg)
    return np.concatenate([math.sin(t) * lean, np.full((len(tcp_mm), 1), -math.cos(t))], axis=1)


def _solve_ik(model: RobotModel, tcp_m: np.ndarray, axes: np.ndarray, home: np.ndarray,
              stages: int = 8, iterations: int = 12, final: int = 48,
              damping: float = 1e-2) -> tuple[np.ndarray, np.ndarray]:
    """Joints (P, dof) putting the gripper centre at ``tcp_m`` with its approach axis along ``axes``, by damped
    least squares on a central-difference Jacobian, all P at once, walked from ``home`` in ``stages`` steps (so
    each stays on home's branch); and the remaining error (P,) (m and unit-axis difference, combined)."""
    kin = forward_kinematics(np, model, home)
    start_p, start_a = kin.gripper_centre, kin.approach_axis
    q = np.tile(np.asarray(home, dtype=float), (len(tcp_m), 1))
    dof = model.dof
    probe = np.concatenate([np.zeros((1, dof)), 1e-6 * np.eye(dof), -1e-6 * np.eye(dof)])

    def error(qv: np.ndarray, goal: np.ndarray, axis: np.ndarray) -> np.ndarray:
        k = forward_kinematics(np, model, qv)
        return np.concatenate([k.gripper_centre - goal, k.approach_axis - axis], axis=-1)

    for stage in range(1, stages + 1):
        f = stage / stages
        goal = start_p + f * (tcp_m - start_p)
        axis = start_a + f * (axes - start_a)
        axis = axis / np.linalg.norm(axis, axis=1, keepdims=True)
        for _ in range(iterations + (final if stage == stages else 0)):
            e = error(q[:, None, :] + probe, goal[:, None], axis[:, None])  # (P, 1 + 2 dof, 6 errors)
            jac = (e[:, 1:1 + dof] - e[:, 1 + dof:]).transpose(0, 2, 1) / 2e-6  # (P, 6 errors, dof joints)
            step = np.einsum("pji,pj->pi", jac, np.linalg.solve(
                jac @ jac.transpose(0, 2, 1) + damping**2 * np.eye(jac.shape[1]), -e[:, 0, :, None])[..., 0])
            q = q + step * np.minimum(1.0, 0.3 / np.maximum(np.abs(step).max(-1, keepdims=True), 1e-12))
    q = (q + np.pi) % (2 * np.pi) - np.pi
    return q, np.linalg.norm(error(q, tcp_m, axes), axis=-1)


def _level_fingers(model: RobotModel, q: np.ndarray) -> np.ndarray:
    """Turn the last joint (it moves neither the TCP nor the approach axis) so the fingers open horizontally."""
    q = q.copy()
    rot = forward_kinematics(np, model, q).link_rot[:, -1]
    turn = np.arctan2(-rot[:, 2, 0], rot[:, 2, 1])
    both = (np.stack([q[:, -1] + turn, q[:, -1] + turn + np.pi], -1) + np.pi) % (2 * np.pi) - np.pi
    q[:, -1] = both[np.arange(len(q)), np.argmin(np.abs(both), axis=-1)]
    return q


def _empty_cell_spec(cfg: EnvConfig, dof: int) -> ResetSpec:
    n = cfg.sampling.max_obstacles
    parked = np.tile([0.0, 0.0, -5.0], (n, 1))
    return ResetSpec(np.zeros(dof), np.array([0.0, 0.0, -5.0]), np.asarray(0.0), np.zeros(n, bool), np.zeros(n, np.int32),
                     parked, np.zeros(n), np.full((n, 3), 0.01), np.asarray(0), np.asarray(False))


def _pose_problem(model: RobotModel, q: np.ndarray, tcp_m: np.ndarray, safety: SafetyLayer, cfg: EnvConfig,
                  spec: ResetSpec) -> str | None:
    """Why the arm must not take pose ``q`` for a calibration reading, or None: the safety layer's rules
    (joint limits, workspace box, table), a collision with the cell or itself, or the TCP hidden from the camera."""
    try:
        safety.check_pose(q, "calibration pose")
    except SafetyViolation as exc:
        return str(exc)
    kin = forward_kinematics(np, model, q)
    hits = collision.check(np, model, kin, spec, cfg).hits
    hit = [name for name in ("self", "gantry", "camera", "table") if bool(hits[name])]
    if hit:
        return "collides with " + ", ".join(hit)
    pos, rot = primitive_poses(np, model, kin)
    camera = np.asarray(SCENE.camera.pos)
    ray = (camera - tcp_m) / np.linalg.norm(camera - tcp_m)
    samples = tcp_m + np.linspace(0.02, 1.0, 100)[:, None] * ray
    for g in range(len(model.primitives)):
        d = geometry.point_distance(np, int(model.prim_kind[g]), samples, pos[g], rot[g], model.prim_size[g])
        if float(d.min()) < MARKER_CLEARANCE_MM / 1000.0:
            return f"the camera's view of the TCP is blocked by {model.primitives[g].name}"
    return None


def _rpy(rot: np.ndarray) -> np.ndarray:
    return np.array([math.atan2(rot[2, 1], rot[2, 2]), math.asin(max(-1.0, min(1.0, -rot[2, 0]))),
                     math.atan2(rot[1, 0], rot[0, 0])])


def _reach(model: RobotModel, tcp_mm: np.ndarray, home: np.ndarray) -> list[PlannedPose | None]:
    """For each TCP position, the first orientation (PLAN_TILTS_DEG × PLAN_DIRECTIONS) the arm can take there
    safely with the TCP in the camera's view, or None."""
    cfg, safety = EnvConfig(robot=model.name), SafetyLayer(robot=model)
    spec = _empty_cell_spec(cfg, model.dof)
    found: list[PlannedPose | None] = [None] * len(tcp_mm)
    for tilt in PLAN_TILTS_DEG:
        todo = [i for i, f in enumerate(found) if f is None]
        if not todo:
            break
        pts = np.repeat(tcp_mm[todo], len(PLAN_DIRECTIONS), axis=0)
        axes = np.concatenate([_approach_axes(tcp_mm[[i]], tilt, d) for i in todo for d in PLAN_DIRECTIONS])
        q, err = _solve_ik(model, pts / 1000.0, axes, home)
        q = _level_fingers(model, q)
        for row, (i, d) in enumerate((i, d) for i in todo for d in PLAN_DIRECTIONS):
            if found[i] is not None or not err[row] < 1e-4:
                continue
            if _pose_problem(model, q[row], pts[row] / 1000.0, safety, cfg, spec) is None:
                rot = forward_kinematics(np, model, q[row]).link_rot[-1]
                found[i] = PlannedPose(tcp_mm[i].copy(), rot[:, 2].copy(), rot[:, 0].copy(), _rpy(rot), q[row], tilt, d)
    return found


def _visit_order(poses: list[PlannedPose], home: np.ndarray) -> list[PlannedPose]:
    """Nearest next pose in joint space (largest joint move), from home."""
    left, order, q = list(poses), [], np.asarray(home, dtype=float)
    while left:
        k = int(np.argmin([np.abs(p.q - q).max() for p in left]))
        order.append(left.pop(k))
        q = order[-1].q
    return order


def plan_poses(count: int = 10, noise_mm: float = DEFAULT_NOISE_MM, model: RobotModel | None = None) -> HandEyePlan:
    """``count`` TCP poses for the pairs, chosen to minimise the fit's predicted error (see the module doc),
    each one the arm reaches safely with the TCP in the camera's view; and the p95 errors predicted for pairs
    taken there with ``noise_mm`` of noise per axis.  ``HandEyeError`` if ``count`` is out of range or that
    many poses cannot be found."""
    if not MIN_PAIRS <= count <= MAX_PLAN_COUNT:
        raise HandEyeError(f"--plan-count {count}: plan between {MIN_PAIRS} and {MAX_PLAN_COUNT} poses")
    model = model or load_robot()
    home = np.asarray(model.spec.home_q, dtype=float)  # the robot's start pose (EnvConfig's for the default robot)
    cands = plan_candidates()
    points = workspace_points_mm()
    allowed = np.ones(len(cands), bool)
    reached: dict[int, PlannedPose | None] = {}
    chosen = _spread_start(cands, count, allowed)
    for _ in range(50):
        chosen = _exchange(cands, chosen, allowed, points)
        new = [c for c in chosen if c not in reached]
        reached.update(zip(new, _reach(model, cands[new], home)))
        bad = [c for c in chosen if reached[c] is None]
        if not bad:
            break
        allowed[bad] = False
        if allowed.sum() < count:
            break
        free = [int(k) for k in np.nonzero(allowed)[0] if k not in chosen]
        for i, c in enumerate(chosen):  # a refused pose makes way for its nearest allowed neighbour
            if c in bad:
                k = min(free, key=lambda f: float(np.linalg.norm(cands[f] - cands[c])))
                free.remove(k)
                chosen[i] = k
    poses = [reached.get(c) for c in chosen]
    if any(p is None for p in poses):
        raise HandEyeError(f"could not find {count} calibration poses the arm reaches safely in the camera's view")
    positions = np.array([p.tcp_mm for p in poses])  # type: ignore[union-attr]
    rot, at = predict_errors(positions, noise_mm, points)
    order = tuple(_visit_order(poses, home))  # type: ignore[arg-type]
    return HandEyePlan(order, float(noise_mm), rot, float(at.max()), float(at[-1]))
