"""Camera → robot-base transform and the checks a detected target must pass (docs/task.md §5).

The hand-eye calibration maps a camera point to the robot controller's base frame,
``p_ctrl = R·p_cam + t``.  The simulation's world frame is the URDF base frame; the
real controller's base may differ from it by a shift along z and a turn about z, so
two deployment settings follow the camera transform::

    p_world = Rz(base_yaw)·p_ctrl + (0, 0, base_z_offset)

* ``base_z_offset`` (m, default 0): height of the controller's base-frame origin in the
  URDF base frame.  Measure it by commanding a joint vector q, reading the controller's
  TCP position p_ctrl and comparing with ``robot.forward_kinematics`` at the same q:
  ``base_z_offset = z_urdf − z_ctrl``.
* ``base_yaw`` (rad, default 0): rotation of the controller frame about z relative to the
  URDF frame, from the same comparison: ``atan2`` of the two horizontal directions.

Both default to 0 because the paper's calibration was done in the frame our URDF
reproduces (docs/task.md §1); set them only after measuring a difference.

Everything here is NumPy; lengths are metres unless a ``units`` argument says "mm".
"""

from __future__ import annotations

import io
import math
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sagrasp_jax.base import fileio
from sagrasp_jax.task.config import SamplingConfig
from sagrasp_jax.task.config_parse import parse_json
from sagrasp_jax.task.policy_file import npy_header
from sagrasp_jax.task.shapes import footprint_gap

# The paper's printed hand-eye matrix (mm) lives once, in the cell description; re-exported here.
from sagrasp_jax.task.scene import T_CAM_BASE_MM

__all__ = [
    "T_CAM_BASE_MM",
    "CalibrationError",
    "CameraCalibration",
    "ObstacleRejected",
    "TargetRejected",
    "checked_rotation",
    "detected_top_to_cube_centre",
    "standing_cube_centre",
    "validate_obstacle_clearance",
    "validate_target",
    "yaw_rotation",
]

ORTHONORMAL_TOL = 1e-3  # max |RᵀR − I|: the printed matrix is at ≈ 9e-5; worse means a typo or wrong file
CUBE_HALF_HEIGHT = SamplingConfig().target_size[2] / 2  # 0.025 m: detected top face -> cube centre
TARGET_Z_TOLERANCE = 0.010  # m: a detected cube centre this far above/below a cube standing on the table is still one
TARGET_Z_RANGE = (round(CUBE_HALF_HEIGHT - TARGET_Z_TOLERANCE, 9), round(CUBE_HALF_HEIGHT + TARGET_Z_TOLERANCE, 9))  # (0.015, 0.035) m
MAX_CAMERA_DISTANCE = 5.0  # m; a larger translation almost surely means mm read as m
_UNIT_SCALE = {"mm": 1e-3, "m": 1.0}


class CalibrationError(ValueError):
    """A calibration matrix or file that must not be used to place targets."""


class TargetRejected(ValueError):
    """A detected target the policy was not trained for; nothing may move towards it."""


class ObstacleRejected(ValueError):
    """A detected obstacle in a place the policy was never trained with; nothing may move."""


def _unit_scale(units: str) -> float:
    if units not in _UNIT_SCALE:
        raise ValueError(f"units must be 'mm' or 'm', got {units!r}")
    return _UNIT_SCALE[units]


def yaw_rotation(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def checked_rotation(rot: Any, source: str = "calibration") -> tuple[np.ndarray, float]:
    """Nearest rotation (SVD) to ``rot`` if it is within ORTHONORMAL_TOL of one with det > 0.

    Returns the re-orthonormalised matrix and the measured error max|RᵀR − I|; raises
    CalibrationError for anything worse (a mistyped entry, a reflection, a scaled matrix).
    """
    rot = np.asarray(rot, dtype=float)
    if rot.shape != (3, 3) or not np.isfinite(rot).all():
        raise CalibrationError(f"{source}: rotation must be a finite 3×3 matrix, got {rot.shape}")
    err = float(np.abs(rot.T @ rot - np.eye(3)).max())
    det = float(np.linalg.det(rot))
    if det <= 0:
        raise CalibrationError(f"{source}: rotation has det {det:.6f} ≤ 0 (a reflection, not a rotation)")
    if err > ORTHONORMAL_TOL:
        raise CalibrationError(
            f"{source}: rotation is not orthonormal: max|RᵀR − I| = {err:.3g} > {ORTHONORMAL_TOL:g} (det {det:.6f})"
        )
    u, _, vt = np.linalg.svd(rot)
    return u @ vt, err


MAX_CALIBRATION_BYTES = 1 << 20  # a calibration file: a 4×4 matrix and how it was measured (calibrate: a few kB)
DEFAULT_SOURCE = "the paper's printed calibration (built in)"  # CameraCalibration.default()'s source (docs/task.md §5)


def _npy_matrix(data: bytes, path: str) -> np.ndarray:
    """The array of a ``.npy`` file's bytes, its header checked against the bytes it holds before anything is
    allocated (a header claiming 100000 × 100000 floats is refused, not allocated)."""
    stream = io.BytesIO(data)
    try:
        shape, fortran, dtype, _ = npy_header(stream, len(data), "file")
    except ValueError as exc:
        raise CalibrationError(f"{path}: its .npy {exc}") from None
    arr = np.frombuffer(data, dtype=dtype, offset=stream.tell())
    return arr.reshape(shape[::-1]).T if fortran else arr.reshape(shape)


def _read_matrix(path: str) -> np.ndarray:
    """The matrix a calibration file holds, read in bounded time and memory: through ``fileio.read_regular``
    (a FIFO, device or folder is named and refused before it is opened, a file over ``MAX_CALIBRATION_BYTES``
    before it is read), JSON within the config files' bounds (``config_parse.parse_json``: nesting, digits), a
    ``.npy`` header checked against its bytes; every parse error a ``CalibrationError`` naming the file."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".json", ".npy", ".txt", ".csv", ".dat"):
        raise CalibrationError(f"{path}: unknown calibration file type {ext!r}; use .json, .npy or .txt")
    data = fileio.read_input(path, MAX_CALIBRATION_BYTES, "calibration file", CalibrationError,
                             too_large_note="a calibration is a 4×4 matrix")
    try:
        if ext == ".npy":
            return np.asarray(_npy_matrix(data, path), dtype=float)
        text = data.decode("utf-8")
        if ext == ".json":
            parsed = parse_json(text)
            if isinstance(parsed, dict):
                keys = [k for k in ("T_cam_base", "matrix", "T") if k in parsed]
                if not keys:
                    raise CalibrationError(f"{path}: JSON object needs a 'T_cam_base' 4×4 list")
                parsed = parsed[keys[0]]
            return np.asarray(parsed, dtype=float)
        return np.loadtxt(io.StringIO(text), delimiter="," if ext == ".csv" else None, dtype=float, ndmin=2)
    except CalibrationError:
        raise
    except (ValueError, OverflowError, TypeError, RecursionError, MemoryError, EOFError) as exc:
        raise CalibrationError(f"{path}: cannot read a 4×4 matrix ({type(exc).__name__}: {exc})") from None


@dataclass(frozen=True)
class CameraCalibration:
    """Camera → world (URDF base) transform: ``p_world = Rz(yaw)·(R·p_cam + t) + dz·e_z``."""

    rotation: np.ndarray  # (3, 3) orthonormalised camera -> controller base
    translation: np.ndarray  # (3,) camera origin in the controller base frame, metres
    base_z_offset: float = 0.0  # m, see module docstring
    base_yaw: float = 0.0  # rad, see module docstring
    orthonormality_error: float = 0.0  # max|RᵀR − I| of the matrix as given
    source: str = DEFAULT_SOURCE
    matrix: np.ndarray = field(init=False, repr=False)  # 4×4 camera -> world, metres, corrections included

    def __post_init__(self) -> None:
        world = np.eye(4)
        world[:3, :3] = yaw_rotation(self.base_yaw)
        world[2, 3] = self.base_z_offset
        cam = np.eye(4)
        cam[:3, :3] = self.rotation
        cam[:3, 3] = self.translation
        object.__setattr__(self, "matrix", world @ cam)

    @classmethod
    def from_matrix(
        cls,
        t_cam_base: Any,
        units: str = "mm",
        base_z_offset: float = 0.0,
        base_yaw: float = 0.0,
        source: str = "matrix",
    ) -> "CameraCalibration":
        """Validate a 4×4 hand-eye matrix whose translation is in ``units`` ("mm" or "m")."""
        scale = _unit_scale(units)
        t = np.asarray(t_cam_base, dtype=float)
        if t.shape != (4, 4):
            raise CalibrationError(f"{source}: expected a 4×4 matrix, got shape {t.shape}")
        if not np.isfinite(t).all():
            raise CalibrationError(f"{source}: matrix has NaN/inf entries")
        if not np.allclose(t[3], (0.0, 0.0, 0.0, 1.0), atol=1e-9):
            raise CalibrationError(f"{source}: last row must be (0, 0, 0, 1), got {t[3].tolist()}")
        rot, err = checked_rotation(t[:3, :3], source)
        translation = t[:3, 3] * scale
        dist = float(np.linalg.norm(translation))
        if dist > MAX_CAMERA_DISTANCE:
            raise CalibrationError(
                f"{source}: camera is {dist:.1f} m from the base (> {MAX_CAMERA_DISTANCE} m): "
                f"is the translation in mm but read with units={units!r}?"
            )
        for name, value in (("base_z_offset", base_z_offset), ("base_yaw", base_yaw)):
            if not math.isfinite(value):
                raise CalibrationError(f"{source}: {name} = {value} must be finite")
        return cls(rot, translation, float(base_z_offset), float(base_yaw), err, source)

    @classmethod
    def default(cls, base_z_offset: float = 0.0, base_yaw: float = 0.0) -> "CameraCalibration":
        """The paper's printed calibration (docs/task.md §5); its ``source`` says so without citing a file an
        installed package does not ship."""
        return cls.from_matrix(T_CAM_BASE_MM, "mm", base_z_offset, base_yaw, DEFAULT_SOURCE)

    @classmethod
    def from_file(
        cls, path: str | os.PathLike[str], units: str = "mm", base_z_offset: float = 0.0, base_yaw: float = 0.0
    ) -> "CameraCalibration":
        """Load a 4×4 matrix from .json (list, or {"T_cam_base": [...]}), .npy or .txt/.csv."""
        path = os.fspath(path)
        return cls.from_matrix(_read_matrix(path), units, base_z_offset, base_yaw, path)

    @property
    def camera_position(self) -> np.ndarray:
        """Camera origin in the world frame, metres."""
        return self.matrix[:3, 3].copy()

    def cam_to_base(self, p_cam: Any, units: str = "m") -> np.ndarray:
        """Camera-frame point(s) (..., 3) in ``units`` -> world (URDF base) frame, metres."""
        p = np.asarray(p_cam, dtype=float) * _unit_scale(units)
        if p.shape[-1:] != (3,):
            raise ValueError(f"points must have shape (..., 3), got {p.shape}")
        return p @ self.matrix[:3, :3].T + self.matrix[:3, 3]

    def base_to_cam(self, p_base: Any, units: str = "m") -> np.ndarray:
        """World-frame point(s) (..., 3) in metres -> camera frame, in ``units``."""
        p = np.asarray(p_base, dtype=float)
        if p.shape[-1:] != (3,):
            raise ValueError(f"points must have shape (..., 3), got {p.shape}")
        rot, t = self.matrix[:3, :3], self.matrix[:3, 3]
        return ((p - t) @ rot) / _unit_scale(units)


def detected_top_to_cube_centre(p_top: Any, half_height: float = CUBE_HALF_HEIGHT) -> np.ndarray:
    """The detector sees the cube's top face; the policy was trained on the cube centre."""
    p = np.array(p_top, dtype=float)
    p[..., 2] -= half_height
    return p


def validate_target(
    p_base: Any,
    sampling_cfg: SamplingConfig | None = None,
    margin: float = 0.02,
    z_range: tuple[float, float] = TARGET_Z_RANGE,
) -> np.ndarray:
    """Refuse a cube centre (world frame, m) the policy was not trained for; returns it as (3,).

    Allowed: x and y within the sampled ranges widened by ``margin`` on each side, the
    horizontal distance to the base within the sampled annulus widened by ``margin``
    (the margin absorbs detection and calibration error at the border of the trained
    region; a negative margin shrinks the region instead), and z within ``z_range``.
    Raises TargetRejected listing every violated bound with the value and the range.
    """
    cfg = sampling_cfg or SamplingConfig()
    p = np.asarray(p_base, dtype=float)
    if p.shape != (3,):
        raise TargetRejected(f"target centre must be 3 numbers (x, y, z), got shape {p.shape}")
    if not np.isfinite(p).all():
        raise TargetRejected(f"target centre {p.tolist()} has NaN/inf entries (failed detection?)")
    x, y, z = (float(v) for v in p)
    r = math.hypot(x, y)
    bounds = (
        ("x", x, cfg.target_x[0] - margin, cfg.target_x[1] + margin, f"x ∈ [{cfg.target_x[0]:g}, {cfg.target_x[1]:g}]"),
        ("y", y, cfg.target_y[0] - margin, cfg.target_y[1] + margin, f"y ∈ [{cfg.target_y[0]:g}, {cfg.target_y[1]:g}]"),
        (
            "√(x²+y²)",
            r,
            cfg.target_radius[0] - margin,
            cfg.target_radius[1] + margin,
            f"radius ∈ [{cfg.target_radius[0]:g}, {cfg.target_radius[1]:g}]",
        ),
    )
    problems = [
        f"{name} = {value:.4f} m is outside [{lo:.4f}, {hi:.4f}] m (trained {trained} ± {margin:g} m margin)"
        for name, value, lo, hi, trained in bounds
        if not lo <= value <= hi
    ]
    if not z_range[0] <= z <= z_range[1]:
        problems.append(
            f"z = {z:.4f} m is outside [{z_range[0]:g}, {z_range[1]:g}] m (cube centre on the table; "
            "wrong top-face offset, base_z_offset or calibration?)"
        )
    if problems:
        raise TargetRejected(f"target centre ({x:.4f}, {y:.4f}, {z:.4f}) m refused: " + "; ".join(problems))
    return p


def standing_cube_centre(p_base: Any, sampling_cfg: SamplingConfig | None = None) -> np.ndarray:
    """The cube centre with its height taken from what is known, not from the detection: the cube stands on
    the table (the plane z = 0 of the world frame), so its centre is half its height above it, as in every
    training scene.  A depth camera's error in z (and a calibration's) then cannot put the grasp band above
    or below the real cube; ``validate_target`` has already refused a detection more than
    ``TARGET_Z_TOLERANCE`` off that height (not a cube standing on the table)."""
    cfg = sampling_cfg or SamplingConfig()
    p = np.array(p_base, dtype=float)
    p[..., 2] = cfg.target_size[2] / 2
    return p


def validate_obstacle_clearance(target: Any, kind: Any, pos: Any, yaw: Any, size: Any,
                                sampling_cfg: SamplingConfig | None = None, names: Any = None,
                                tolerance: float = 0.0) -> None:
    """Refuse obstacles whose footprint comes nearer the cube centre than training ever put one
    (``env.sampling.target_clearance``, horizontal, docs/task.md §1 (a); 0.10 m): the policy was never
    trained to reach past an obstacle that close, so the scene is refused before anything moves.
    ``tolerance`` (m) is how much nearer a *detected* cube may seem: training placed obstacles around the
    true cube and showed the policy a detection up to ``env.randomize.target_error`` off on each axis.

    ``kind``, ``pos``, ``yaw``, ``size`` describe the active obstacles (N,), (N, 3), (N,), (N, 3);
    ``names`` label them in the message."""
    cfg = sampling_cfg or SamplingConfig()
    kind = np.asarray(kind).reshape(-1)
    if kind.size == 0:
        return
    gap = footprint_gap(np, kind, np.asarray(pos, float).reshape(-1, 3), np.asarray(yaw, float).reshape(-1),
                               np.asarray(size, float).reshape(-1, 3), np.asarray(target, float)[:2])
    names = list(names) if names is not None else [f"obstacle {i + 1}" for i in range(kind.size)]
    close = [f"{names[i]} is {float(gap[i]):.4f} m from it" for i in range(kind.size)
             if not float(gap[i]) >= cfg.target_clearance - tolerance - 1e-9]
    if close:
        raise ObstacleRejected(
            f"obstacle too close to the cube: {'; '.join(close)} horizontally (surface to cube centre), under the "
            f"training clearance env.sampling.target_clearance = {cfg.target_clearance:g} m"
            + (f" less {tolerance * 1000:.1f} mm of detection error" if tolerance else "") + "; refused before moving")
