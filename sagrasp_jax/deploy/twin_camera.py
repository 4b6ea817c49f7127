"""A depth camera in the PyBullet twin: the RGB image and organized point cloud the Mech-Eye gives.

The paper's cell has a Mech-Eye Pro M Enhanced on the gantry (docs/task.md §1.3, §5.1).  This module
renders what such a camera reports from a ``deploy.twin.PyBulletTwin``'s scene, so the perception
(``deploy.perception``) and the YOLO option (``deploy.yolo``) can be measured and rehearsed without the
camera:

* **Pose.** The camera sits where the hand-eye calibration says (``scene.SCENE.camera``, the paper's
  T_cam_base, docs/task.md §5.1), or at the pose of any ``CameraCalibration`` (render from the true pose,
  perceive with a wrong calibration, to rehearse a calibration error).  Camera frame as the Mech-Eye's
  (OpenCV's): x to the image's right, y down, z along the optical axis.
* **The camera** (``task.camera``: intrinsics, noise model, depth range): by default the scene's
  (``scene.SCENE.camera.model``, the paper's Mech-Eye PRO M: 1920 × 1200 px, 43.2° × 27.8°), any model of
  ``task.camera.CAMERA_MODELS`` by name (``realsense_d435``), at ``resolution`` times its pixels
  (``Intrinsics.scaled``: the studies use 1/4 of the Mech-Eye's, 480 × 300, 2.3 mm per pixel on the table),
  no distortion (both cameras deliver rectified data); the clip planes are the model's depth range.
* **Output** (``Frame``): ``rgb`` (H, W, 3) uint8; ``cloud_mm`` (H, W, 3) float32 camera-frame points in
  millimetres with NaN where there is no return (the Mech-Eye's organized point cloud); ``segmentation``
  (H, W) PyBullet body ids (−1 none) for labels and ground truth.  The depth comes from the renderer's
  z-buffer, linearised, each pixel's ray through its centre (OpenCV's convention: pixel (u, v) centre at
  u = column index).
* **Depth noise** (``task.camera.NOISE_MODELS``: ``none``, ``industrial``, ``consumer``), applied along
  each pixel's ray (``apply_depth_noise``); it changes the depth only, the image keeps the camera's optics.
* **Colours** follow the paper (red target, white obstacles: ``scene.SCENE``); ``Colours`` sets others,
  ``random_colours`` draws domain-randomised ones (target hue jittered about red, obstacles any light
  grey to white, table any muted colour) and ``random_lighting`` the light, for the YOLO dataset.

Render time at 480 × 300 is a few tens of ms on one core (``experiments/perception_accuracy.py``
reports it).  ER_TINY_RENDERER (CPU, no display) is used always.  The twin's bodies are only read
and recoloured; the arm can be hidden for a capture (``hide_robot``: the arm parked out of view, as a
real capture would be taken before the arm moves over the table) and is put back exactly.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from sagrasp_jax.base import extras
from sagrasp_jax.deploy.calibration import CameraCalibration
from sagrasp_jax.task.camera import (  # noqa: F401  (the camera's description, read here and re-exported)
    CAMERA_MODELS, NOISE_MODELS, CameraModel, DepthNoise, Intrinsics, apply_depth_noise, camera_model, noise_model,
)
from sagrasp_jax.task.scene import SCENE

extras.require("twin", what="the twin camera")
from sagrasp_jax.reference import bullet  # noqa: E402,F401  (imports pybullet with its banner kept off the terminal)
import pybullet as pb  # noqa: E402

MECH_EYE_PRO_M = camera_model("mecheye_pro_m").intrinsics
PARK_Z = -50.0  # m: where a hidden arm waits during a capture


@dataclass(frozen=True)
class Colours:
    """RGBA of the twin's target, obstacles and table top for a capture (the paper's by default)."""

    target: tuple[float, float, float, float] = SCENE.target_rgba
    obstacle: tuple[float, float, float, float] = SCENE.obstacles.rgba
    table: tuple[float, float, float, float] = SCENE.table.rgba
    obstacles: tuple[tuple[float, float, float, float], ...] | None = None  # per obstacle, overrides ``obstacle``


@dataclass(frozen=True)
class Lighting:
    """getCameraImage's light for ER_TINY_RENDERER."""

    direction: tuple[float, float, float] = (0.3, -0.4, 1.0)
    colour: tuple[float, float, float] = (1.0, 1.0, 1.0)
    ambient: float = 0.6
    diffuse: float = 0.35
    specular: float = 0.05
    shadow: bool = False


def _hsv_to_rgb(h: float, s: float, v: float) -> tuple[float, float, float]:
    i = int(h * 6) % 6
    f = h * 6 - math.floor(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i]


def random_colours(rng: np.random.Generator, n_obstacles: int = 2) -> Colours:
    """Domain-randomised colours: target red-ish (hue ±0.03, saturation 0.6-1, value 0.5-1), each
    obstacle light grey to white with a faint tint, table any muted colour."""
    target = (*_hsv_to_rgb(float(rng.uniform(-0.03, 0.03)) % 1.0, float(rng.uniform(0.6, 1.0)),
                           float(rng.uniform(0.5, 1.0))), 1.0)
    obstacles = tuple((*_hsv_to_rgb(float(rng.random()), float(rng.uniform(0.0, 0.12)), float(rng.uniform(0.7, 1.0))), 1.0)
                      for _ in range(n_obstacles))
    table = (*_hsv_to_rgb(float(rng.random()), float(rng.uniform(0.0, 0.45)), float(rng.uniform(0.25, 0.75))), 1.0)
    return Colours(target=target, obstacle=obstacles[0] if obstacles else SCENE.obstacles.rgba, table=table,
                   obstacles=obstacles)


def random_lighting(rng: np.random.Generator) -> Lighting:
    """A light from anywhere in the upper hemisphere, of random warmth and strength, sometimes with shadows."""
    theta, phi = float(rng.uniform(0, 2 * math.pi)), float(rng.uniform(0.1, 1.2))
    warm = float(rng.uniform(-0.15, 0.15))
    return Lighting(
        direction=(math.sin(phi) * math.cos(theta), math.sin(phi) * math.sin(theta), math.cos(phi)),
        colour=(1.0, 1.0 - abs(warm) / 2, 1.0 - warm), ambient=float(rng.uniform(0.35, 0.8)),
        diffuse=float(rng.uniform(0.2, 0.6)), specular=float(rng.uniform(0.0, 0.3)), shadow=bool(rng.random() < 0.3))


class Frame(NamedTuple):
    """One capture: what the Mech-Eye reports (``rgb``, ``cloud_mm``) and the render's ground truth."""

    rgb: np.ndarray  # (H, W, 3) uint8
    cloud_mm: np.ndarray  # (H, W, 3) float32, camera frame, mm, NaN where no return
    segmentation: np.ndarray  # (H, W) int: PyBullet body id seen by each pixel, −1 none
    intrinsics: Intrinsics
    render_s: float  # wall time of the render and the cloud


def _view_matrix(cam_to_world: np.ndarray) -> list[float]:
    """OpenGL view matrix (column-major, as PyBullet wants it) of an OpenCV-convention camera pose."""
    world_to_cv = np.linalg.inv(cam_to_world)
    view = np.diag([1.0, -1.0, -1.0, 1.0]) @ world_to_cv  # OpenCV camera -> OpenGL camera (y up, looking along −z)
    return [float(v) for v in view.T.reshape(-1)]


def _projection_matrix(k: Intrinsics, near: float, far: float) -> list[float]:
    """OpenGL projection (column-major) whose pixel (u, v) centre is OpenCV's (u, v) of intrinsics ``k``.

    ER_TINY_RENDERER samples image row r, column c at window coordinates (c, H − 1 − r), the pixel's
    corner rather than its centre (measured: with the textbook +0.5 the deprojected top face of a cube
    sits 0.5 px off, 1.2 mm at 480 × 300), hence cx as is and cy + 1 after the row flip."""
    w, h = k.width, k.height
    cx, cy = k.cx, k.cy + 1.0
    proj = np.array([
        [2 * k.fx / w, 0.0, 1 - 2 * cx / w, 0.0],
        [0.0, 2 * k.fy / h, 2 * cy / h - 1, 0.0],
        [0.0, 0.0, -(far + near) / (far - near), -2 * far * near / (far - near)],
        [0.0, 0.0, -1.0, 0.0],
    ])
    return [float(v) for v in proj.T.reshape(-1)]


class TwinCamera:
    """Captures ``Frame``s of a ``PyBulletTwin`` from a calibrated camera pose.

    ``model``: a ``task.camera`` model or its name (default the scene's, ``SCENE.camera.model``); its
    intrinsics scaled by ``resolution`` (1 = its full resolution; the field of view is kept), or ``intrinsics``
    as given.  ``pose``: the camera's true pose as a ``CameraCalibration`` (camera -> world); default the
    cell's (``scene.SCENE.camera``, the paper's T_cam_base)."""

    def __init__(self, resolution: float = 1.0, intrinsics: Intrinsics | None = None,
                 pose: CameraCalibration | None = None, model: str | CameraModel | None = None) -> None:
        self.model = camera_model(model) if model is not None else SCENE.camera.model
        base = intrinsics or self.model.intrinsics
        self.intrinsics = base.scaled(resolution) if resolution != 1.0 else base
        if pose is None:
            cam = np.eye(4)
            cam[:3, :3] = SCENE.camera.rot
            cam[:3, 3] = SCENE.camera.pos
        else:
            cam = pose.matrix
        self.cam_to_world = cam
        self._near, self._far = self.model.depth_range_m
        self._view = _view_matrix(cam)
        self._proj = _projection_matrix(self.intrinsics, self._near, self._far)
        self._rays = self.intrinsics.rays()

    def _recolour(self, twin: Any, colours: Colours) -> None:
        client = twin._client
        pb.changeVisualShape(twin.target_body, -1, rgbaColor=list(colours.target), physicsClientId=client)
        for i, body in enumerate(twin.obstacle_bodies):
            rgba = colours.obstacles[i % len(colours.obstacles)] if colours.obstacles else colours.obstacle
            pb.changeVisualShape(body, -1, rgbaColor=list(rgba), physicsClientId=client)
        pb.changeVisualShape(twin.table_body, -1, rgbaColor=list(colours.table), physicsClientId=client)

    def capture(self, twin: Any, noise: str | DepthNoise = "none", rng: np.random.Generator | None = None,
                colours: Colours | None = None, lighting: Lighting | None = None, hide_robot: bool = False) -> Frame:
        """Render the twin's scene as the camera sees it now; ``noise`` by name or ``DepthNoise``.

        ``colours`` recolours the twin's target, obstacles and table (they keep it afterwards);
        ``hide_robot`` parks the arm out of view for this capture only."""
        t0 = time.perf_counter()
        client = twin._client
        k = self.intrinsics
        if colours is not None:
            self._recolour(twin, colours)
        light = lighting or Lighting()
        parked = None
        if hide_robot:
            parked = pb.getBasePositionAndOrientation(twin.robot_body, physicsClientId=client)
            pb.resetBasePositionAndOrientation(twin.robot_body, [0.0, 0.0, PARK_Z], parked[1], physicsClientId=client)
        try:
            _, _, rgba, depth_buffer, seg = pb.getCameraImage(
                k.width, k.height, viewMatrix=self._view, projectionMatrix=self._proj, renderer=pb.ER_TINY_RENDERER,
                lightDirection=list(light.direction), lightColor=list(light.colour), lightAmbientCoeff=light.ambient,
                lightDiffuseCoeff=light.diffuse, lightSpecularCoeff=light.specular, shadow=int(light.shadow),
                physicsClientId=client)
        finally:
            if parked is not None:
                pb.resetBasePositionAndOrientation(twin.robot_body, *parked, physicsClientId=client)
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(k.height, k.width, 4)[..., :3].copy()
        d = np.asarray(depth_buffer, dtype=np.float64).reshape(k.height, k.width)
        z = self._far * self._near / (self._far - (self._far - self._near) * d)  # linear depth along the optical axis, m
        z[d >= 1.0 - 1e-7] = np.nan  # nothing rendered: no return
        cloud = (self._rays * (1000.0 * z)[..., None]).astype(np.float32)
        seg = np.asarray(seg, dtype=np.int64).reshape(k.height, k.width)
        body = np.where(seg >= 0, seg & ((1 << 24) - 1), -1)
        if noise is not None and noise_model(noise).name != "none":
            cloud = apply_depth_noise(cloud, noise, rng if rng is not None else np.random.default_rng())
        return Frame(rgb, cloud, body, k, time.perf_counter() - t0)

    def project(self, p_world: Any) -> np.ndarray:
        """World points (..., 3), m -> pixel coordinates (..., 2) (u, v), OpenCV convention."""
        p = np.asarray(p_world, dtype=float)
        rot, t = self.cam_to_world[:3, :3], self.cam_to_world[:3, 3]
        cam = (p - t) @ rot
        k = self.intrinsics
        return np.stack([k.fx * cam[..., 0] / cam[..., 2] + k.cx, k.fy * cam[..., 1] / cam[..., 2] + k.cy], axis=-1)

