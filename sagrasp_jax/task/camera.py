"""The depth cameras the cell can carry: one description each (intrinsics, depth noise, depth range, driver).

Every reader of "the camera" reads it here: the scene (``scene.SCENE.camera``: this model at the hand-eye
calibration's pose), the MJCF generated from the scene (its ``depth_camera``), the PyBullet reference env's
render, the twin camera (``deploy.twin_camera``: what the model would report), the hand-eye plan (which
poses the camera sees), the capture file (the intrinsics a capture was taken with) and the camera drivers
(``deploy.cameras``: which SDK opens a model).  NumPy only.

The models are a registry, as the obstacle kinds (``task.shapes``) and the robots (``task.robots``) are:
``register(model)`` adds one (refused, naming the problem, for a taken name, an unknown noise model or
driver (``DRIVERS``), intrinsics that are not positive and finite, a depth range not 0 < near < far),
``registered(*models)`` adds some for a block and restores the registry after, ``names()`` lists them and
``camera_model(name)`` looks one up.  Every reader lists the registry when it is used (the ``--camera-model``
choices of ``deploy.rehearse``, ``deploy --camera twin`` and ``capture``: ``CHOICES``; the capture file's
check of the model it names), so a model registered later is accepted everywhere a model is named.

* ``mecheye_pro_m`` (the default, the paper's camera): a Mech-Eye PRO M's factory intrinsics as Mech-Mind's
  SDK sample ``get_camera_intrinsics`` printed them for one unit (published in a public sample repository):
  1920 × 1200 px, fx 2425.48, fy 2425.33, cx 959.74, cy 632.70, no distortion (the camera delivers rectified
  data).  The paper's Pro M Enhanced is the same optics with a brighter projector: a 43.2° × 27.8° field of
  view, 1.11 × 0.69 m of table at the cell's 1.41 m, 0.58 mm per pixel.  Noise ``industrial``.
* ``realsense_d435``: an Intel RealSense D435's colour camera at 1280 × 720, the grid its depth is aligned to
  (``rs.align``), with the datasheet's nominal 69° × 42° field of view; a unit's own intrinsics (and
  distortion) come from librealsense at capture time.  Noise ``consumer``.

A real capture carries the intrinsics its SDK reported (``deploy.cameras.Capture``); these models are what the
twin renders and what the plan assumes.  ``Intrinsics.scaled(f)`` keeps a model's field of view at f times
its resolution (the studies render the Mech-Eye at 1/4: 480 × 300, 2.3 mm per pixel on the table).

Depth noise (``NOISE_MODELS``, ``apply_depth_noise``), applied along each pixel's ray:

``none``
    the exact render.
``industrial``
    structured light of the Mech-Eye class: σ_z = 0.2 mm at 1.5 m growing with z² (a triangulating
    sensor's law; 0.18 mm at the cell's 1.41 m, the order of the vendor's quoted single-point Z
    repeatability, not checked against a datasheet here), 0.5 % of pixels lost at random, and 50 % of
    the pixels at a depth edge (a neighbour > 10 mm nearer or farther: projector shadows and mixed
    returns) lost.
``consumer``
    active stereo of the RealSense D4xx class: σ_z = 2.5 mm at 1 m growing with z² (stereo RMS error
    z²·σ_disparity/(f·B) with a 50 mm baseline, ≈ 0.08 px subpixel error at 848 px width: 4.9 mm at
    1.41 m), 2 % random dropouts, 60 % dropouts at depth edges, and 20 % of the remaining edge pixels
    "flying" (placed between the near and the far surface, the stereo matcher's edge artefact).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics (OpenCV convention: pixel centres at integer coordinates), no distortion."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        values = (self.fx, self.fy, self.cx, self.cy)
        if not (int(self.width) == self.width >= 8 and int(self.height) == self.height >= 8):
            raise ValueError(f"image size {self.width} × {self.height} must be whole numbers of pixels, at least 8")
        if not all(math.isfinite(float(v)) for v in values) or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"intrinsics fx {self.fx}, fy {self.fy}, cx {self.cx}, cy {self.cy} must be finite, "
                             "the focal lengths positive")
        if not (-0.5 <= self.cx <= self.width - 0.5 and -0.5 <= self.cy <= self.height - 0.5):
            raise ValueError(f"principal point ({self.cx}, {self.cy}) lies outside the {self.width} × {self.height} image")

    def scaled(self, factor: float) -> "Intrinsics":
        """The same field of view at ``factor`` times the resolution (pixel edges, not centres, scale)."""
        if not (math.isfinite(factor) and 0 < factor <= 4):
            raise ValueError(f"resolution factor must be in (0, 4], got {factor}")
        w, h = max(8, round(self.width * factor)), max(8, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return Intrinsics(w, h, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5)

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fov_deg(self) -> tuple[float, float]:
        """Horizontal and vertical field of view (degrees, edge to edge)."""
        return (math.degrees(2 * math.atan((self.width / 2) / self.fx)),
                math.degrees(2 * math.atan((self.height / 2) / self.fy)))

    @property
    def half_fov_tan(self) -> tuple[float, float]:
        """tan of the half field of view, horizontal and vertical (the frustum's slopes)."""
        return (self.width / 2) / self.fx, (self.height / 2) / self.fy

    def rays(self) -> np.ndarray:
        """(H, W, 3) direction of every pixel centre's ray with z = 1 (camera frame)."""
        u = (np.arange(self.width) - self.cx) / self.fx
        v = (np.arange(self.height) - self.cy) / self.fy
        rays = np.ones((self.height, self.width, 3))
        rays[..., 0] = u[None, :]
        rays[..., 1] = v[:, None]
        return rays

    def project(self, cam_points: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) -> pixel coordinates (..., 2) (u, v)."""
        p = np.asarray(cam_points, dtype=float)
        return np.stack([self.fx * p[..., 0] / p[..., 2] + self.cx, self.fy * p[..., 1] / p[..., 2] + self.cy], axis=-1)

    def as_list(self) -> list[float]:
        """[width, height, fx, fy, cx, cy]: the capture file's form."""
        return [float(self.width), float(self.height), self.fx, self.fy, self.cx, self.cy]

    @classmethod
    def from_list(cls, values: object) -> "Intrinsics":
        v = np.asarray(values, dtype=float).reshape(-1)
        if v.shape != (6,) or not np.isfinite(v).all():
            raise ValueError(f"intrinsics must be 6 finite numbers [width, height, fx, fy, cx, cy], got {v.tolist()}")
        return cls(int(v[0]), int(v[1]), float(v[2]), float(v[3]), float(v[4]), float(v[5]))


@dataclass(frozen=True)
class DepthNoise:
    """A depth camera's errors: σ_z = sigma_mm·(z / ref_m)² along the ray, and lost pixels."""

    name: str
    sigma_mm: float  # axial standard deviation at ref_m
    ref_m: float
    dropout: float  # fraction of valid pixels lost at random
    edge_dropout: float  # fraction of depth-edge pixels lost
    edge_jump_mm: float = 10.0  # a neighbour this much nearer or farther makes a pixel an edge pixel
    flying: float = 0.0  # fraction of the kept edge pixels put between the near and the far surface


NOISE_MODELS: dict[str, DepthNoise] = {
    "none": DepthNoise("none", 0.0, 1.0, 0.0, 0.0),
    "industrial": DepthNoise("industrial", 0.2, 1.5, 0.005, 0.5),
    "consumer": DepthNoise("consumer", 2.5, 1.0, 0.02, 0.6, flying=0.2),
}


def _entry(registry: dict[str, Any], name: Any, what: str) -> Any:
    """``name``'s entry of ``registry`` (an entry itself is returned as it is); ``ValueError`` naming the known ones."""
    if not isinstance(name, str):
        return name
    if name not in registry:
        raise ValueError(f"unknown {what} {name!r}; known: {', '.join(registry)}")
    return registry[name]


def noise_model(name: str | DepthNoise) -> DepthNoise:
    return _entry(NOISE_MODELS, name, "depth-noise model")


@dataclass(frozen=True)
class CameraModel:
    """One depth camera the cell can carry (module docstring)."""

    name: str  # the registry key (``register``, ``names()``), written into capture files
    product: str  # what the vendor calls it
    intrinsics: Intrinsics  # nominal: what the twin renders; a real capture carries its unit's own
    noise: str  # the depth-noise model of its class (``NOISE_MODELS``)
    driver: str  # the ``deploy.cameras`` driver that opens it (one of ``DRIVERS``)
    depth_range_m: tuple[float, float]  # where it reports anything (also the twin's clip planes)

    @property
    def fovy_deg(self) -> float:
        return self.intrinsics.fov_deg[1]


DRIVERS: tuple[str, ...] = ("mecheye", "realsense")  # the drivers deploy.cameras has (open_camera): the one list

# The registry (``register``; read it through ``names()`` and ``camera_model``).  ``CAMERA_MODELS`` is the registry
# itself, not a copy: it follows ``register`` and ``registered``.
CAMERA_MODELS: dict[str, CameraModel] = {
    "mecheye_pro_m": CameraModel("mecheye_pro_m", "Mech-Eye PRO M (Enhanced)",
                                 Intrinsics(1920, 1200, 2425.48, 2425.33, 959.74, 632.70), "industrial", "mecheye",
                                 (0.3, 3.0)),
    "realsense_d435": CameraModel("realsense_d435", "Intel RealSense D435 (colour-aligned depth)",
                                  Intrinsics(1280, 720, 924.0, 924.0, 639.5, 359.5), "consumer", "realsense",
                                  (0.3, 3.0)),
}
DEFAULT_CAMERA = "mecheye_pro_m"


def camera_model(name: str | CameraModel) -> CameraModel:
    """The registered model ``name`` (a ``CameraModel`` is returned as it is); ``ValueError`` naming the known ones."""
    return _entry(CAMERA_MODELS, name, "camera model")


def names() -> tuple[str, ...]:
    """The registered camera models, the default first."""
    return tuple(CAMERA_MODELS)


class RegisteredNames:
    """The registered model names as the registry holds them when asked (``in``, iteration): an argparse
    ``choices`` that a model registered after the parser was built is one of."""

    def __contains__(self, name: object) -> bool:
        return name in CAMERA_MODELS

    def __iter__(self) -> Iterator[str]:
        return iter(names())

    def __len__(self) -> int:
        return len(CAMERA_MODELS)

    def __repr__(self) -> str:
        return f"RegisteredNames{names()}"


CHOICES = RegisteredNames()  # the --camera-model choices


def _problems(model: CameraModel) -> list[str]:
    """What keeps ``model`` out of the registry (empty when nothing does)."""
    problems = []
    if not (isinstance(model.name, str) and model.name.isidentifier()):
        problems.append(f"name {model.name!r} must be an identifier (it is a --camera-model choice and a capture "
                        "file's camera)")
    elif model.name in CAMERA_MODELS:
        problems.append(f"name {model.name!r} is taken")
    if model.noise not in NOISE_MODELS:
        problems.append(f"noise model {model.noise!r} is not one of {', '.join(NOISE_MODELS)}")
    if model.driver not in DRIVERS:
        problems.append(f"driver {model.driver!r} is not one of {', '.join(DRIVERS)} (deploy.cameras)")
    k = model.intrinsics
    if not isinstance(k, Intrinsics):
        problems.append(f"intrinsics must be a task.camera.Intrinsics, got {type(k).__name__}")
    else:
        try:  # checked again: an entry's fields can be changed after its own check (object.__setattr__)
            values = [float(v) for v in k.as_list()]
            if not all(math.isfinite(v) for v in values) or min(values[:4]) <= 0:
                raise ValueError(f"intrinsics {values} (width, height, fx, fy, cx, cy) must be finite, the size and "
                                 "the focal lengths positive")
            Intrinsics(k.width, k.height, k.fx, k.fy, k.cx, k.cy)
        except (TypeError, ValueError) as exc:
            problems.append(str(exc))
    try:
        near, far = (float(v) for v in model.depth_range_m)
        ok = math.isfinite(near) and math.isfinite(far) and 0 < near < far
    except (TypeError, ValueError):
        ok = False
    if not ok:
        problems.append(f"depth range {model.depth_range_m!r} must be two finite distances, m, with 0 < near < far")
    return problems


def register(model: CameraModel) -> CameraModel:
    """Add a camera model defined outside this module (a plugin's, a test's); ``ValueError`` naming every problem.
    Everything that names camera models then knows it: the ``--camera-model`` option of the rehearsal, of
    ``deploy --camera twin`` and of ``capture``, the twin camera (``deploy.twin_camera.TwinCamera(model=...)``)
    and capture files."""
    if not isinstance(model, CameraModel):
        raise ValueError(f"a camera model must be a task.camera.CameraModel, got {type(model).__name__}")
    problems = _problems(model)
    if problems:
        raise ValueError(f"camera model {model.name!r} cannot be registered: " + "; ".join(problems))
    CAMERA_MODELS[model.name] = model
    return model


@contextlib.contextmanager
def registered(*models: CameraModel) -> Iterator[tuple[CameraModel, ...]]:
    """The registry with ``models`` added for the block (``register``), restored after, whatever happens."""
    before = dict(CAMERA_MODELS)
    try:
        for model in models:
            register(model)
        yield models
    finally:
        CAMERA_MODELS.clear()
        CAMERA_MODELS.update(before)


def _edge_pixels(depth: np.ndarray, jump: float) -> tuple[np.ndarray, np.ndarray]:
    """(edge mask, depth of the farthest-apart 4-neighbour) of a depth map (NaN = no return)."""
    h, w = depth.shape
    padded = np.pad(depth, 1, constant_values=np.nan)
    edge = np.zeros((h, w), bool)
    other = depth.copy()
    best = np.zeros((h, w))
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        nb = padded[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
        diff = np.abs(nb - depth)
        with np.errstate(invalid="ignore"):
            bigger = diff > np.maximum(best, jump)
        bigger &= np.isfinite(diff)
        other = np.where(bigger, nb, other)
        best = np.where(bigger, diff, best)
        edge |= bigger
    return edge, other


def apply_depth_noise(cloud_mm: np.ndarray, noise: str | DepthNoise, rng: np.random.Generator) -> np.ndarray:
    """``cloud_mm`` (H, W, 3, camera frame, mm, NaN = no return) as the noisy camera would report it."""
    model = noise_model(noise)
    cloud = np.array(cloud_mm, dtype=np.float64, copy=True)
    if model.name == "none" or not np.isfinite(cloud).any():
        return cloud.astype(np.float32)
    z = cloud[..., 2]
    valid = np.isfinite(z)
    edge, other = _edge_pixels(z, model.edge_jump_mm)
    lost = valid & (rng.random(z.shape) < model.dropout)
    lost |= edge & valid & (rng.random(z.shape) < model.edge_dropout)
    z_new = z.copy()
    if model.flying > 0:
        fly = edge & valid & ~lost & (rng.random(z.shape) < model.flying)
        t = rng.random(z.shape)
        z_new = np.where(fly, z + t * (other - z), z_new)
    sigma = model.sigma_mm * (z_new / (1000.0 * model.ref_m)) ** 2
    z_new = z_new + sigma * rng.standard_normal(z.shape)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = z_new / z
    cloud = cloud * scale[..., None]
    cloud[lost | ~valid] = np.nan
    return cloud.astype(np.float32)
