"""Watch a policy: ``python -m sagrasp_jax.render --run runs/NAME --out rollout.mp4`` (or ``--policy policy.npz``).

Writes the video and a still (``--png``, default beside the video: ``rollout.png``).  ``--run``
takes a finished run folder (its ``policy.npz``); ``--policy`` an exported policy file (or a
pretrained policy's name).

The episodes show the task's scene kinds in turn (``EPISODE_KINDS``): an obstacle beside the
approach, an obstacle on it ("blocking", docs/task.md §1.5), no obstacle, then again.  Episode ``i``
of ``--seed s`` is the first scene of that kind the shared sampler draws from the uniforms of
``default_rng([s, i, attempt])`` (attempt 0, 1, ...), so the same command renders the same scenes.
Each is run by the deployment loop (``deploy.loop.run_episode``: NumPy policy, shared control step,
safety layer) on MuJoCo through ``grasp_check.MujocoRobot``: the approach is kinematic like training,
then the gripper closes and lifts with physics, as in the physical grasp check.

Frames come from MuJoCo's offscreen renderer at the control rate (20 fps).  The default camera,
``tracking``, looks at the cube, the gripper and the obstacles from the front of the cell, across the
approach, and follows them (smoothed) as the gripper closes in; it leaves out the gantry and its
camera, which stand above the table.  ``overview`` and ``depth_camera`` are the scene's fixed cameras.
Obstacles are drawn amber, the cube red.  A banner on every frame says the episode, its scene kind and
the step, and on the episode's last frames the outcome (``OUTCOMES``: grasped, dropped, collision,
timeout, safety stop) on its colour, in a small built-in bitmap font.  The mp4 is written with
imageio-ffmpeg (extra ``render``), plus a PNG still of the first successful episode's end (lifted).

Headless machines render through EGL: ``MUJOCO_GL=egl`` is the default here (set it before
MuJoCo is imported).  It needs the system packages ``libegl1 libegl-mesa0 libopengl0
libgl1-mesa-dri`` (Debian/Ubuntu).  Without a working backend the command stops with a message
naming it, exit status 2.  Nothing here imports jax.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before anything imports mujoco: it picks the GL backend on import

import dataclasses
import math
import sys
from typing import Any, Sequence

import numpy as np

from sagrasp_jax.base import cli
from sagrasp_jax.base import extras
from sagrasp_jax.base import fileio
from sagrasp_jax.base import run_files
from sagrasp_jax.task.config import SEED_RANGE, ConfigError, blocking_sampling, check_range
from sagrasp_jax.deploy.safety import PolicyMismatch
from sagrasp_jax.task.policy_file import PolicyFormatError, load_policy

CAMERAS = ("tracking", "overview", "depth_camera")
GL_PACKAGES = "libegl1 libegl-mesa0 libopengl0 libgl1-mesa-dri"
HOLD_FRAMES = 10  # frames repeated at the start and end of each episode (0.5 s at 20 fps)

# Scene kinds, shown in this order (then again): what the policy has to cope with.
EPISODE_KINDS = ("obstacle", "blocking", "no obstacle")
KIND_LABELS = {"obstacle": "obstacle", "blocking": "blocking obstacle", "no obstacle": "no obstacle"}
SCENE_TRIES = 64  # draws per episode to find a scene of its kind; then the last draw, labelled as what it is

OBSTACLE_RGBA = (0.95, 0.62, 0.12, 1.0)  # amber: apart from the white arm and the red cube
# Outcome word and its banner colour (RGB) per way an episode ends.
OUTCOMES = {
    "grasped": (40, 170, 60),
    "dropped": (225, 140, 20),
    "collision": (210, 40, 40),
    "timeout": (120, 120, 130),
    "safety stop": (210, 40, 40),
}

# The tracking camera: direction, margins, smoothing.
TRACK_AZIMUTHS = tuple(range(0, 360, 30))  # deg, the directions tried (90: looking along +y, at the robot)
TRACK_ELEVATIONS = (-40.0, -60.0)  # deg, looking down on the table
TRACK_FOVY = 30.0  # deg, the vertical field of view (narrow: the near links of the arm do not loom)
TRACK_MIN_VIEW = 0.45  # m, the least height of the view at the look-at point (closer, the cube would fill it)
TRACK_MAX_DISTANCE = 4.0  # m
TRACK_ARM_PENALTY = 4.0  # score lost per keyframe for a frame the arm would fill (views past the arm's links)
TRACK_FRONT_BONUS = 0.5  # score for looking at the robot from the front of the cell
TRACK_WINDOW = 6  # frames either side averaged (0.3 s at 20 fps): the camera glides
CUBE_MARGIN = 0.04  # m around the cube centre kept in view
GRIPPER_MARGIN = 0.07  # m around the gripper centre and these bodies' origins (the gripper and the wrist above it)
# The gripper's bodies the tracking camera frames besides the grasp point: the flange (the child link of the robot's
# flange joint) and the link before the wrist's (the AUBO-i5's: flange, wrist2_Link); ``gripper_bodies``.

# A 5×7 bitmap font, rows top to bottom ("#" ink), drawn at an integer scale.
FONT = {
    "A": ".###.|#...#|#...#|#####|#...#|#...#|#...#",
    "B": "####.|#...#|#...#|####.|#...#|#...#|####.",
    "C": ".###.|#...#|#....|#....|#....|#...#|.###.",
    "D": "####.|#...#|#...#|#...#|#...#|#...#|####.",
    "E": "#####|#....|#....|####.|#....|#....|#####",
    "F": "#####|#....|#....|####.|#....|#....|#....",
    "G": ".###.|#...#|#....|#.###|#...#|#...#|.####",
    "H": "#...#|#...#|#...#|#####|#...#|#...#|#...#",
    "I": ".###.|..#..|..#..|..#..|..#..|..#..|.###.",
    "J": "..###|...#.|...#.|...#.|...#.|#..#.|.##..",
    "K": "#...#|#..#.|#.#..|##...|#.#..|#..#.|#...#",
    "L": "#....|#....|#....|#....|#....|#....|#####",
    "M": "#...#|##.##|#.#.#|#.#.#|#...#|#...#|#...#",
    "N": "#...#|#...#|##..#|#.#.#|#..##|#...#|#...#",
    "O": ".###.|#...#|#...#|#...#|#...#|#...#|.###.",
    "P": "####.|#...#|#...#|####.|#....|#....|#....",
    "Q": ".###.|#...#|#...#|#...#|#.#.#|#..#.|.##.#",
    "R": "####.|#...#|#...#|####.|#.#..|#..#.|#...#",
    "S": ".####|#....|#....|.###.|....#|....#|####.",
    "T": "#####|..#..|..#..|..#..|..#..|..#..|..#..",
    "U": "#...#|#...#|#...#|#...#|#...#|#...#|.###.",
    "V": "#...#|#...#|#...#|#...#|#...#|.#.#.|..#..",
    "W": "#...#|#...#|#...#|#.#.#|#.#.#|#.#.#|.#.#.",
    "X": "#...#|#...#|.#.#.|..#..|.#.#.|#...#|#...#",
    "Y": "#...#|#...#|.#.#.|..#..|..#..|..#..|..#..",
    "Z": "#####|....#|...#.|..#..|.#...|#....|#####",
    "0": ".###.|#...#|#..##|#.#.#|##..#|#...#|.###.",
    "1": "..#..|.##..|..#..|..#..|..#..|..#..|.###.",
    "2": ".###.|#...#|....#|...#.|..#..|.#...|#####",
    "3": "#####|...#.|..#..|...#.|....#|#...#|.###.",
    "4": "...#.|..##.|.#.#.|#..#.|#####|...#.|...#.",
    "5": "#####|#....|####.|....#|....#|#...#|.###.",
    "6": "..##.|.#...|#....|####.|#...#|#...#|.###.",
    "7": "#####|....#|...#.|..#..|.#...|.#...|.#...",
    "8": ".###.|#...#|#...#|.###.|#...#|#...#|.###.",
    "9": ".###.|#...#|#...#|.####|....#|...#.|.##..",
    " ": ".....|.....|.....|.....|.....|.....|.....",
    ".": ".....|.....|.....|.....|.....|.##..|.##..",
    ",": ".....|.....|.....|.....|.##..|..#..|.#...",
    ":": ".....|.##..|.##..|.....|.##..|.##..|.....",
    "/": ".....|....#|...#.|..#..|.#...|#....|.....",
    "-": ".....|.....|.....|#####|.....|.....|.....",
    "(": "...#.|..#..|.#...|.#...|.#...|..#..|...#.",
    ")": ".#...|..#..|...#.|...#.|...#.|..#..|.#...",
    "%": "##...|##..#|...#.|..#..|.#...|#..##|...##",
    "+": ".....|..#..|..#..|#####|..#..|..#..|.....",
    "=": ".....|.....|#####|.....|#####|.....|.....",
    "?": ".###.|#...#|....#|...#.|..#..|.....|..#..",
    "!": "..#..|..#..|..#..|..#..|..#..|.....|..#..",
    "'": "..#..|..#..|.#...|.....|.....|.....|.....",
    "_": ".....|.....|.....|.....|.....|.....|#####",
    "|": "..#..|..#..|..#..|..#..|..#..|..#..|..#..",
    "<": "...#.|..#..|.#...|#....|.#...|..#..|...#.",
    ">": ".#...|..#..|...#.|....#|...#.|..#..|.#...",
    "#": ".#.#.|.#.#.|#####|.#.#.|#####|.#.#.|.#.#.",
}
GLYPH_W, GLYPH_H = 5, 7


class RenderError(RuntimeError):
    """Rendering is impossible here (no GL backend, no video writer) or the input is bad."""


def _gl_error(exc: BaseException) -> RenderError:
    backend = os.environ.get("MUJOCO_GL", "")
    return RenderError(
        f"offscreen rendering failed with the OpenGL backend MUJOCO_GL={backend!r} ({type(exc).__name__}: {exc}). "
        f"On a headless Linux machine use MUJOCO_GL=egl (the default of this command) with the system packages "
        f"{GL_PACKAGES} (e.g. apt-get install -y {GL_PACKAGES}); osmesa needs libosmesa6."
    )


def _mujoco() -> Any:
    """Import MuJoCo, turning a broken GL backend (it is chosen at import time) into a RenderError."""
    if "mujoco" in extras.missing("render"):
        raise extras.MissingExtra(("render",), ["mujoco"], "rendering a video")
    try:
        import mujoco
    except Exception as exc:  # a missing GL library surfaces as AttributeError/OSError/ImportError from PyOpenGL
        raise _gl_error(exc) from None
    return mujoco


def _imageio() -> Any:
    extras.require("render", what="writing mp4")
    import imageio.v2 as imageio
    import imageio_ffmpeg  # noqa: F401  (the mp4 writer; fail here, not after rendering)

    return imageio


# -- text ------------------------------------------------------------------------------------
_GLYPHS = {c: np.array([[ch == "#" for ch in row] for row in rows.split("|")]) for c, rows in FONT.items()}


def text_scale(height: int) -> int:
    """The font's scale for a frame ``height`` pixels tall (1 up to 360 px, 2 at 480, 3 at 720)."""
    return max(1, round(height / 240))


def text_width(text: str, scale: int) -> int:
    return len(text) * (GLYPH_W + 1) * scale - scale if text else 0


def draw_text(img: np.ndarray, text: str, x: int, y: int, scale: int, rgb: Sequence[int]) -> None:
    """Draw ``text`` (upper-cased; an unknown character as "?") with its top left corner at (x, y), in place,
    clipped to the image."""
    h, w = img.shape[:2]
    for i, ch in enumerate(text.upper()):
        glyph = _GLYPHS.get(ch, _GLYPHS["?"])
        mask = np.kron(glyph, np.ones((scale, scale), bool))
        x0 = x + i * (GLYPH_W + 1) * scale
        ys, xs = slice(max(y, 0), min(y + mask.shape[0], h)), slice(max(x0, 0), min(x0 + mask.shape[1], w))
        if ys.start >= ys.stop or xs.start >= xs.stop:
            continue
        sub = mask[ys.start - y : ys.stop - y, xs.start - x0 : xs.stop - x0]
        img[ys, xs][sub] = rgb


def banner_height(height: int) -> int:
    scale = text_scale(height)
    return (GLYPH_H + 4) * scale


def annotate(frame: np.ndarray, left: str, right: str, outcome: str | None = None) -> np.ndarray:
    """A copy of ``frame`` with the banner across its top: ``left`` (episode, scene kind) in white, ``right``
    (step or phase) right-aligned, and the outcome word on its colour (``OUTCOMES``) at the right end."""
    out = frame.copy()
    h, w = out.shape[:2]
    scale = text_scale(h)
    bh = min(banner_height(h), h)
    out[:bh] = (out[:bh].astype(np.uint16) * 2 // 7).astype(np.uint8)  # darkened, the scene still faintly seen
    pad, y = 2 * scale, 2 * scale
    x_right = w - pad
    if outcome is not None:
        word = outcome.upper()
        chip = text_width(word, scale) + 2 * pad
        out[:bh, max(x_right - chip + pad, 0) : w] = OUTCOMES[outcome]
        draw_text(out, word, x_right - chip + 2 * pad, y, scale, (255, 255, 255))
        x_right -= chip + pad
    if right:
        x_right -= text_width(right, scale)
        draw_text(out, right, x_right, y, scale, (230, 230, 230))
    room = (x_right - 2 * pad) // ((GLYPH_W + 1) * scale)  # whole characters that fit before the right part
    draw_text(out, left[: max(room, 0)], pad, y, scale, (255, 255, 255))
    return out


# -- scenes ----------------------------------------------------------------------------------
def scene_kind(spec: Any, model: Any, env_cfg: Any) -> str:
    """"no obstacle", "obstacle" or "blocking" (the straight approach passes within the blocking margin)."""
    from sagrasp_jax.task import sampling

    if not np.any(spec.obstacle_active):
        return "no obstacle"
    return "blocking" if bool(sampling.is_blocking(np, model, env_cfg.sampling, env_cfg.task, spec)) else "obstacle"


def kind_sampling(env_cfg: Any, kind: str) -> Any:
    """The policy's sampling set to draw scenes of ``kind`` (every scene with an obstacle, placed on the path or not)."""
    if kind == "no obstacle":
        return dataclasses.replace(env_cfg.sampling, obstacle_prob=0.0, blocking_prob=0.0)
    return blocking_sampling(env_cfg.sampling, 1.0, 1.0 if kind == "blocking" else 0.0)


def episode_scene(env_cfg: Any, model: Any, seed: int, index: int) -> tuple[Any, str]:
    """Episode ``index``'s scene for ``seed``: of kind ``EPISODE_KINDS[index % 3]`` when the sampler gives one
    within ``SCENE_TRIES`` draws; returns (ResetSpec with NumPy leaves, its kind)."""
    from sagrasp_jax.task import sampling

    wanted = EPISODE_KINDS[index % len(EPISODE_KINDS)]
    s = kind_sampling(env_cfg, wanted)
    for attempt in range(SCENE_TRIES):
        u = np.random.default_rng([seed, index, attempt]).random(sampling.uniforms_needed(s, model.dof))
        spec = sampling.ResetSpec(*(np.asarray(v) for v in sampling.sample_reset(np, model, s, env_cfg.task, u)))
        kind = scene_kind(spec, model, env_cfg)
        if kind == wanted:
            break
    return spec, kind


def outcome_of(report: Any) -> str:
    """The banner's word for how a deployment episode ended (a key of ``OUTCOMES``)."""
    if report.outcome == "success":
        return "grasped" if report.held else "dropped"
    return {"collision": "collision", "timeout": "timeout"}.get(report.outcome, "safety stop")


# -- cameras ---------------------------------------------------------------------------------
def _direction(azimuth: float, elevation: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A MuJoCo free camera's forward, right and up vectors (azimuth 90°: looking along +y)."""
    az, el = math.radians(azimuth), math.radians(elevation)
    fwd = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return fwd, right, np.cross(right, fwd)


class TrackingCamera:
    """A free MuJoCo camera on what the episode is about: the cube, the gripper and the obstacles.

    It is planned after the episode has run, from its recorded states (``plan``).  The direction (azimuth,
    elevation) is fixed for the episode: of ``TRACK_AZIMUTHS`` × ``TRACK_ELEVATIONS``, the one from which the
    cube and each obstacle are least hidden (by the arm, by each other) at the episode's key moments (start,
    grasp pose, end), counted in segmentation renders (``choose_direction``).  Every frame the look-at point
    and the distance are fitted to the bounding spheres of the cube, the gripper (centre, flange, wrist) and each
    obstacle's geom (``fit``), then smoothed over ``TRACK_WINDOW`` frames either side.
    """

    def __init__(self, mujoco: Any, scene: Any, width: int, height: int) -> None:
        from sagrasp_jax.task import scene_mjcf
        from sagrasp_jax.task import shapes

        self.mujoco = mujoco
        self.model = scene.model
        spec = scene.reset_spec
        self.model.vis.global_.fovy = TRACK_FOVY
        usable = max(1.0 - 2.0 * banner_height(height) / height, 0.3)  # the banner covers the top: fit below it
        self.tan_v = math.tan(math.radians(TRACK_FOVY) / 2) * usable
        self.tan_h = math.tan(math.radians(TRACK_FOVY) / 2) * width / height
        self.obstacles = [self.model.geom(scene_mjcf.obstacle_geom_name(slot, shapes.BY_ID[int(spec.obstacle_kind[slot])])).id
                          for slot in np.nonzero(np.asarray(spec.obstacle_active))[0]]
        self.cube = self.model.geom("target_geom").id
        self.gripper = [self.model.body(name).id for name in gripper_bodies(scene.robot)]
        self.arm_geoms = _arm_geoms(self.model, scene.robot)
        self.centre = self.model.site("gripper_center").id
        self.data = mujoco.MjData(self.model)
        self.azimuth, self.elevation = 90.0, TRACK_ELEVATIONS[0]
        self.aspect = width / height

    def _pose(self, qpos: np.ndarray) -> None:
        self.data.qpos[:] = qpos
        self.mujoco.mj_kinematics(self.model, self.data)

    def _spheres(self) -> tuple[np.ndarray, np.ndarray]:
        d, m = self.data, self.model
        centres = [d.geom_xpos[self.cube], d.site_xpos[self.centre], *(d.xpos[b] for b in self.gripper)]
        radii = [CUBE_MARGIN] + [GRIPPER_MARGIN] * (1 + len(self.gripper))
        centres += [d.geom_xpos[g] for g in self.obstacles]
        radii += [float(m.geom_rbound[g]) for g in self.obstacles]
        return np.array(centres), np.array(radii)

    def fit(self, azimuth: float, elevation: float) -> tuple[np.ndarray, float]:
        """The look-at point and distance that frame the current pose's spheres from this direction."""
        fwd, right, up = _direction(azimuth, elevation)
        centres, radii = self._spheres()
        c0 = centres.mean(axis=0)
        rel = centres - c0
        x, y, z = rel @ right, rel @ up, rel @ fwd
        xc = (np.max(x + radii) + np.min(x - radii)) / 2
        yc = (np.max(y + radii) + np.min(y - radii)) / 2
        need = np.maximum((np.abs(x - xc) + radii) / self.tan_h, (np.abs(y - yc) + radii) / self.tan_v) - z
        closest = TRACK_MIN_VIEW / 2 / math.tan(math.radians(TRACK_FOVY) / 2)
        return c0 + xc * right + yc * up, float(np.clip(np.max(need), closest, TRACK_MAX_DISTANCE))

    def camera(self, lookat: np.ndarray, distance: float, azimuth: float, elevation: float) -> Any:
        cam = self.mujoco.MjvCamera()
        cam.type = self.mujoco.mjtCamera.mjCAMERA_FREE
        cam.lookat[:] = lookat
        cam.distance, cam.azimuth, cam.elevation = distance, azimuth, elevation
        return cam

    def visibility(self, renderer: Any, option: Any, azimuth: float, elevation: float) -> tuple[np.ndarray, float]:
        """Pixels of the cube and of each obstacle seen from this direction in the current pose, and the share of
        the frame the arm (shoulder to wrist) covers (segmentation)."""
        lookat, distance = self.fit(azimuth, elevation)
        renderer.update_scene(self.data, camera=self.camera(lookat, distance, azimuth, elevation), scene_option=option)
        seg = renderer.render()
        geoms = np.where(seg[..., 1] == int(self.mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)
        seen = np.array([np.count_nonzero(geoms == g) for g in [self.cube, *self.obstacles]], dtype=float)
        return seen, float(np.isin(geoms, self.arm_geoms).mean())

    def choose_direction(self, keyframes: Sequence[np.ndarray], option: Any) -> tuple[float, float]:
        """The direction that shows the cube and the obstacles best at these poses: each object's visible pixels
        as a fraction of its best view's, summed (the cube counts twice), a slight preference for the front."""
        candidates = [(float(a), float(e)) for a in TRACK_AZIMUTHS for e in TRACK_ELEVATIONS]
        h = 96
        renderer = self.mujoco.Renderer(self.model, h, int(round(h * self.aspect / 16)) * 16 or 16)
        try:
            renderer.enable_segmentation_rendering()
            seen = np.zeros((len(candidates), len(keyframes), 1 + len(self.obstacles)))
            arm = np.zeros((len(candidates), len(keyframes)))
            for k, qpos in enumerate(keyframes):
                self._pose(qpos)
                for c, (az, el) in enumerate(candidates):
                    seen[c, k], arm[c, k] = self.visibility(renderer, option, az, el)
        finally:
            renderer.close()
        share = seen / np.maximum(seen.max(axis=0, keepdims=True), 1.0)
        weights = np.ones(seen.shape[-1])
        weights[0] = 2.0
        front = np.array([_direction(az, el)[0][1] for az, el in candidates])  # looking towards +y, the robot
        score = (share * weights).sum(axis=(1, 2)) - TRACK_ARM_PENALTY * arm.sum(axis=1) + TRACK_FRONT_BONUS * front
        return candidates[int(np.argmax(score))]

    def plan(self, states: Sequence[np.ndarray], keyframes: Sequence[int], option: Any) -> list[Any]:
        """One camera per recorded state: the chosen direction, the smoothed fitted look-at and distance."""
        self.azimuth, self.elevation = self.choose_direction([states[k] for k in keyframes], option)
        fits = []
        for qpos in states:
            self._pose(qpos)
            fits.append(self.fit(self.azimuth, self.elevation))
        lookat = _smooth(np.array([f[0] for f in fits]), TRACK_WINDOW)
        distance = _smooth(np.array([[f[1]] for f in fits]), TRACK_WINDOW)[:, 0]
        return [self.camera(a, d, self.azimuth, self.elevation) for a, d in zip(lookat, distance)]


def gripper_bodies(arm: Any) -> tuple[str, str]:
    """The MJCF bodies of ``arm`` (a ``RobotModel``) the tracking camera keeps in view with the grasp point: its
    flange (the URDF child link of ``spec.flange_joint``) and the link before its wrist's."""
    import xml.etree.ElementTree as ET

    joint = ET.parse(arm.urdf_path).getroot().find(f"joint[@name='{arm.spec.flange_joint}']")
    return joint.find("child").get("link"), arm.link_names[-2]


def _arm_geoms(model: Any, arm: Any) -> np.ndarray:
    """The arm's geoms from its base to the wrist (the gripper, from the last wrist link on, is left out); ``arm``
    is the ``RobotModel`` whose link names the MJCF's bodies carry."""
    parents = model.body_parentid
    base, wrist = model.body(arm.link_names[0]).id, model.body(arm.link_names[-1]).id

    def under(body: int, root: int) -> bool:
        while body > 0 and body != root:
            body = int(parents[body])
        return body == root

    return np.array([g for g in range(model.ngeom) if under(int(model.geom_bodyid[g]), base)
                     and not under(int(model.geom_bodyid[g]), wrist)], dtype=np.int64)


def _smooth(values: np.ndarray, window: int) -> np.ndarray:
    """A centred moving average over ``window`` frames either side (edges repeated)."""
    if window < 1 or len(values) < 2:
        return values
    padded = np.concatenate([np.repeat(values[:1], window, 0), values, np.repeat(values[-1:], window, 0)])
    kernel = np.ones(2 * window + 1) / (2 * window + 1)
    return np.stack([np.convolve(padded[:, j], kernel, mode="valid") for j in range(values.shape[1])], axis=1)


def prepare_model(mujoco: Any, model: Any, camera: str) -> None:
    """Colour the episode's obstacle geoms amber; for the tracking camera hide the gantry and its camera (the
    scene's fixed parts over the table), whose pillars and shadows would cross the close view."""
    from sagrasp_jax.task import scene_mjcf
    from sagrasp_jax.task import shapes
    from sagrasp_jax.task.scene import SCENE

    for slot in range(SCENE.obstacles.count):
        for shape in shapes.SHAPES:
            gid = model.geom(scene_mjcf.obstacle_geom_name(slot, shape)).id
            model.geom_rgba[gid, :3] = OBSTACLE_RGBA[:3]  # the inactive ones keep alpha 0
    if camera == "tracking":
        for part in SCENE.static_parts:
            gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, part.name)
            if gid >= 0:
                model.geom_rgba[gid, 3] = 0.0  # transparent geoms are not drawn, nor cast shadows


class StateRecorder:
    """Collects an episode's states (``qpos``) and what each shows, one per video frame."""

    def __init__(self) -> None:
        self.states: list[np.ndarray] = []
        self.phases: list[str] = []  # "start", "approach", "closing", "lifting"

    def capture(self, scene: Any, phase: str = "approach") -> None:
        self.states.append(scene.data.qpos.copy())
        self.phases.append(phase)


def _filmed_robot(scene: Any, control_dt: float, recorder: StateRecorder) -> Any:
    """``MujocoRobot`` whose frames know the phase they show (approach, closing, lifting)."""
    from sagrasp_jax.reference.grasp_check import MujocoRobot

    class FilmedRobot(MujocoRobot):
        phase = "approach"

        def close_gripper(self) -> None:
            self.phase = "closing"
            super().close_gripper()
            self.phase = "lifting"

    robot = FilmedRobot(scene, control_dt)
    robot.on_frame = lambda s: recorder.capture(s, robot.phase)
    return robot


class FrameRenderer:
    """An offscreen renderer bound to one episode's model; renders recorded states from a camera."""

    def __init__(self, mujoco: Any, model: Any, camera: str, width: int, height: int) -> None:
        if camera not in CAMERAS:
            raise RenderError(f"camera {camera!r} is unknown; choose one of {', '.join(CAMERAS)}")
        if camera != "tracking" and mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera) < 0:
            raise RenderError(f"camera {camera!r} is not in the model; choose one of {', '.join(CAMERAS)}")
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, height)
        self.mujoco, self.model = mujoco, model
        try:
            self.renderer = mujoco.Renderer(model, height, width)
        except Exception as exc:  # mujoco.FatalError or EGL errors: no usable context
            raise _gl_error(exc) from None
        self.data = mujoco.MjData(model)
        self.option = mujoco.MjvOption()
        self.option.sitegroup[:] = 0  # no site markers (the gripper centre's green dot)

    def render(self, qpos: np.ndarray, camera: Any) -> np.ndarray:
        self.data.qpos[:] = qpos
        self.mujoco.mj_forward(self.model, self.data)
        self.renderer.update_scene(self.data, camera=camera, scene_option=self.option)
        return self.renderer.render().copy()

    def close(self) -> None:
        self.renderer.close()


def label_frames(frames: Sequence[np.ndarray], phases: Sequence[str], index: int, episodes: int, kind: str,
                 steps: int, steps_limit: int, outcome: str) -> list[np.ndarray]:
    """The episode's frames with their banners: episode and scene kind, the step (or phase), the outcome at the end."""
    left = f"episode {index + 1}/{episodes}: {KIND_LABELS[kind]}"
    out, step = [], 0
    for frame, phase in zip(frames, phases):
        if phase == "approach":
            step += 1
            right = f"step {step}/{steps_limit}" if step <= steps else "aligning"
        elif phase == "end":
            right = f"step {steps}"
        else:
            right = phase
        out.append(annotate(frame, left, right, outcome if phase == "end" else None))
    return out


def render_episode(mujoco: Any, scene: Any, states: Sequence[np.ndarray], phases: Sequence[str], camera: str,
                   width: int, height: int) -> list[np.ndarray]:
    """Frames of an episode's recorded states: the first and last held ``HOLD_FRAMES`` (``phases`` gains
    "start" and "end" for them), the camera planned over the whole episode."""
    prepare_model(mujoco, scene.model, camera)
    film = FrameRenderer(mujoco, scene.model, camera, width, height)
    try:
        if camera == "tracking":
            approach = [i for i, p in enumerate(phases) if p == "approach"]
            keyframes = [0, approach[-1] if approach else 0, len(states) - 1]
            cameras = TrackingCamera(mujoco, scene, width, height).plan(states, keyframes, film.option)
        else:
            cameras = [camera] * len(states)
        frames = [film.render(q, c) for q, c in zip(states, cameras)]
    finally:
        film.close()
    return [frames[0]] * (HOLD_FRAMES - 1) + frames + [frames[-1]] * HOLD_FRAMES


def render_episodes(policy_path: str, episodes: int = 3, camera: str = "tracking", seed: int = 0, width: int = 640,
                    height: int = 480, max_steps: int | None = None) -> tuple[list[np.ndarray], list[dict[str, Any]], int]:
    """Run and render ``episodes`` scenes (kinds in ``EPISODE_KINDS`` order); returns (frames, per-episode reports
    with ``kind``, ``label`` (the banner's outcome), ``frames`` (how many) and ``scene`` (the reset spec as lists),
    index of the still)."""
    mujoco = _mujoco()
    from sagrasp_jax.deploy.loop import obstacles_from_spec, run_episode
    from sagrasp_jax.reference.grasp_check import GraspScene
    from sagrasp_jax.task.robot import load_robot

    if episodes < 1:
        raise RenderError(f"--episodes must be >= 1, got {episodes}")
    if camera not in CAMERAS:
        raise RenderError(f"--camera must be one of {', '.join(CAMERAS)}, got {camera!r}")
    policy = load_policy(policy_path)
    cfg = policy.env_config()
    model = load_robot(cfg.robot)  # the policy's arm
    steps_limit = cfg.task.max_steps if max_steps is None else int(max_steps)
    frames: list[np.ndarray] = []
    reports: list[dict[str, Any]] = []
    still = -1
    for i in range(episodes):
        spec, kind = episode_scene(cfg, model, seed, i)
        scene = GraspScene(spec, spec.q0, arm=model)
        recorder = StateRecorder()
        recorder.capture(scene, "start")
        robot = _filmed_robot(scene, cfg.control.control_dt, recorder)
        report = run_episode(robot, policy, spec.target_pos, float(spec.target_yaw), obstacles_from_spec(spec),
                             max_steps=max_steps)
        shot = render_episode(mujoco, scene, recorder.states, recorder.phases, camera, width, height)
        phases = ["start"] * HOLD_FRAMES + recorder.phases[1:] + ["end"] * HOLD_FRAMES
        outcome = outcome_of(report)
        labelled = label_frames(shot, phases, i, episodes, kind, report.steps, steps_limit, outcome)
        if still < 0 or (report.success and not any(r["success"] for r in reports)):
            still = len(frames) + len(labelled) - 1  # the first success's last frame, else episode 1's
        frames += labelled
        reports.append(report.to_dict() | {"kind": kind, "label": outcome, "frames": len(labelled),
                                           "scene": {k: np.asarray(v).tolist() for k, v in spec._asdict().items()}})
    return frames, reports, still


def write_video(path: str, frames: Sequence[np.ndarray], fps: int) -> None:
    imageio = _imageio()

    def write(tmp: str) -> None:
        with imageio.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=7,
                                pixelformat="yuv420p", macro_block_size=16) as writer:
            for frame in frames:
                writer.append_data(frame)

    fileio.atomic_write(path, write)


def write_png(path: str, frame: np.ndarray) -> None:
    imageio = _imageio()
    fileio.atomic_write(path, lambda tmp: imageio.imwrite(tmp, frame, format="PNG"))


def main(argv: Sequence[str] | None = None) -> int:
    p = cli.Parser(prog="python -m sagrasp_jax.render", description=__doc__.split("\n\n")[0])
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--run", help="a finished run folder (python -m sagrasp_jax.train --out): its policy.npz")
    source.add_argument("--policy", help="exported policy.npz (or a pretrained policy's name)")
    p.add_argument("--out", required=True, help="video file (.mp4)")
    p.add_argument("--episodes", type=int, default=3,
                   help=f"episodes; their scene kinds in turn: {', '.join(KIND_LABELS[k] for k in EPISODE_KINDS)}")
    p.add_argument("--camera", default="tracking",
                   help=f"one of {', '.join(CAMERAS)} (tracking: close on the cube, gripper and obstacles; "
                        "the others: the scene's fixed cameras)")
    p.add_argument("--png", default=None, help="the still: the end of the first successful episode (else of the first); "
                                                "default beside the video, same name .png")
    p.add_argument("--no-png", action="store_true", help="write the video only")
    p.add_argument("--seed", type=int, default=0, help="scene sampling seed")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--fps", type=int, default=20, help="video frame rate (20 = real time at the control rate)")
    p.add_argument("--max-steps", type=int, default=None, help="step cap per episode (default: the policy's)")
    args = p.parse_args(argv)
    try:
        if not args.out.lower().endswith(".mp4"):
            raise RenderError(f"--out {args.out!r} must end in .mp4")
        if args.camera not in CAMERAS:
            raise RenderError(f"--camera must be one of {', '.join(CAMERAS)}, got {args.camera!r}")
        if args.run is not None:
            args.policy = run_files.policy_of_run(args.run)
        if args.no_png:
            args.png = None
        elif args.png is None:
            args.png = args.out[:-4] + ".png"
        if args.width % 16 or args.height % 16 or args.width < 16 or args.height < 16:
            raise RenderError(f"--width/--height must be positive multiples of 16 (H.264 blocks), got {args.width}×{args.height}")
        check_range("--width", args.width, 16, 4096)
        check_range("--height", args.height, 16, 4096)
        check_range("--episodes", args.episodes, 1, 1000)
        check_range("--seed", args.seed, *SEED_RANGE)
        check_range("--fps", args.fps, 1, 240)
        if args.max_steps is not None:
            check_range("--max-steps", args.max_steps, 1, 100_000)
        fileio.check_writable(args.out, "output folder", is_folder=False)
        if args.png:
            fileio.check_writable(args.png, "output folder", is_folder=False)
        load_policy(args.policy)  # the user input first, then the GL backend and the writer
        _mujoco()
        _imageio()
        frames, reports, still = render_episodes(args.policy, args.episodes, args.camera, args.seed, args.width,
                                                 args.height, args.max_steps)
        write_video(args.out, frames, args.fps)
        if args.png:
            write_png(args.png, frames[still])
    except (RenderError, PolicyFormatError, PolicyMismatch, ConfigError, OSError, extras.MissingExtra,
            run_files.RunFolderError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for i, r in enumerate(reports):
        grasp = r["grasp"] or {}
        held = f", cube rose {grasp['object_rise'] * 1000:.0f} mm" if "object_rise" in grasp else ""
        print(f"episode {i + 1}: {KIND_LABELS[r['kind']]}, {r['label']} ({r['outcome']} after {r['steps']} steps), "
              f"final offset {r['final_distance'] * 1000:.1f} mm{held}")
    print(f"wrote {args.out} ({len(frames)} frames, {args.fps} fps, camera {args.camera}, MUJOCO_GL={os.environ['MUJOCO_GL']})"
          + (f" and {args.png}" if args.png else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
