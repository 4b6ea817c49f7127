"""The work cell as plain data: one description that builds both the MJCF and the PyBullet scene.

World frame = AUBO-i5 base frame (docs/task.md §1).  Static parts (table, gantry, camera
with its bracket) are fixed primitives; the target and the dynamic obstacle slots
only declare their geometry limits here, their poses are sampled per episode
(``sampling.py``).  No other module writes a coordinate of the cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sagrasp_jax.task.camera import DEFAULT_CAMERA, CameraModel, camera_model
from sagrasp_jax.task.robot import BOX

# Hand-eye calibration camera -> robot base, millimetres (paper Eq. 13, docs/task.md §5).
T_CAM_BASE_MM = np.array(
    [
        [-0.9961, 0.0219, 0.0854, -162.08],
        [0.0241, 0.9994, 0.0246, -403.37],
        [-0.0848, 0.0265, -0.9960, 1408.24],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


def orthonormalise(rot: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (SVD); the printed calibration is orthonormal only to ~1e-4."""
    u, _, vt = np.linalg.svd(np.asarray(rot, dtype=float))
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    return r


CAMERA_ROT = orthonormalise(T_CAM_BASE_MM[:3, :3])
CAMERA_POS = T_CAM_BASE_MM[:3, 3] / 1000.0


@dataclass(frozen=True)
class StaticPart:
    """A fixed primitive of the cell (MuJoCo size convention, see robot.py)."""

    name: str
    kind: int
    pos: tuple[float, float, float]
    rot: np.ndarray
    size: tuple[float, float, float]
    rgba: tuple[float, float, float, float]
    role: str  # "gantry" | "camera": what a collision with it is reported as


@dataclass(frozen=True)
class Table:
    """The table top is the plane z = top_z; the box is only drawn below it."""

    top_z: float = 0.0
    half_extents: tuple[float, float, float] = (0.9, 0.9, 0.02)
    centre_xy: tuple[float, float] = (0.0, -0.25)
    rgba: tuple[float, float, float, float] = (0.55, 0.45, 0.35, 1.0)


@dataclass(frozen=True)
class CameraSpec:
    """The cell's depth camera: a model of ``task.camera`` (intrinsics, noise, driver) at the calibrated pose."""

    pos: tuple[float, float, float]
    rot: np.ndarray  # columns = camera axes in the world; optical axis = +z column (≈ world −z)
    model: CameraModel = camera_model(DEFAULT_CAMERA)

    @property
    def fovy_deg(self) -> float:
        """Vertical field of view (the MJCF camera's ``fovy``)."""
        return self.model.fovy_deg

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.model.intrinsics.width, self.model.intrinsics.height

    @property
    def optical_axis(self) -> np.ndarray:
        return self.rot[:, 2]

    @property
    def mujoco_rot(self) -> np.ndarray:
        """MuJoCo cameras look along their own −z: R·diag(1, −1, −1)."""
        return self.rot @ np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class ObstacleSlots:
    """Dynamic obstacles: up to ``count`` slots, each holding one shape of ``shapes.SHAPES`` (docs/task.md §1)."""

    count: int = 2
    rgba: tuple[float, float, float, float] = (0.95, 0.95, 0.95, 1.0)


@dataclass(frozen=True)
class Scene:
    table: Table
    static_parts: tuple[StaticPart, ...]
    camera: CameraSpec
    target_size: tuple[float, float, float]  # full extents (x, y, z)
    target_rgba: tuple[float, float, float, float]
    obstacles: ObstacleSlots

    def part(self, name: str) -> StaticPart:
        for p in self.static_parts:
            if p.name == name:
                return p
        raise KeyError(name)

    def static_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """kinds (N,), positions (N,3), rotations (N,3,3), sizes (N,3) of the static parts."""
        return (
            np.array([p.kind for p in self.static_parts], dtype=np.int32),
            np.array([p.pos for p in self.static_parts], dtype=float),
            np.stack([p.rot for p in self.static_parts]),
            np.array([p.size for p in self.static_parts], dtype=float),
        )


def _build_scene() -> Scene:
    eye = np.eye(3)
    post_half = (0.02, 0.02, 0.77)  # 0.04 × 0.04 × 1.54 m
    post_x, post_y = 0.60, -0.40
    beam_z = 2 * post_half[2] - 0.02  # beam sits on the post tops
    grey = (0.35, 0.35, 0.38, 1.0)
    camera_half = (0.13, 0.03, 0.035)  # 0.26 × 0.06 × 0.07 m, long side along the camera x axis
    cam_top = float(CAMERA_POS[2]) + camera_half[2]
    beam_bottom = beam_z - 0.02
    bracket_half = (0.02, 0.02, float((beam_bottom - cam_top) / 2))
    parts = (
        StaticPart("gantry_post_left", BOX, (-post_x, post_y, post_half[2]), eye, post_half, grey, "gantry"),
        StaticPart("gantry_post_right", BOX, (post_x, post_y, post_half[2]), eye, post_half, grey, "gantry"),
        StaticPart("gantry_beam", BOX, (0.0, post_y, beam_z), eye, (post_x + 0.02, 0.02, 0.02), grey, "gantry"),
        StaticPart(
            "camera_bracket",
            BOX,
            (float(CAMERA_POS[0]), float(CAMERA_POS[1]), float((beam_bottom + cam_top) / 2)),
            eye,
            bracket_half,
            grey,
            "camera",
        ),
        StaticPart("camera_body", BOX, tuple(float(v) for v in CAMERA_POS), CAMERA_ROT, camera_half, (0.1, 0.1, 0.1, 1.0), "camera"),
    )
    return Scene(
        table=Table(),
        static_parts=parts,
        camera=CameraSpec(pos=tuple(float(v) for v in CAMERA_POS), rot=CAMERA_ROT),
        target_size=(0.02, 0.02, 0.05),
        target_rgba=(0.85, 0.1, 0.1, 1.0),
        obstacles=ObstacleSlots(),
    )


SCENE = _build_scene()
