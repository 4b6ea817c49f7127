"""Watch a policy: ``python -m sagrasp_jax.render --run runs/NAME --out rollout.mp4`` (or ``--policy policy.npz``).

Writes the video and a still (``--png``, default beside the video: ``rollout.png``).  ``--run``
takes a finished run folder (its ``policy.npz``); ``--policy`` an exported policy file.

Each episode is a training scene (target, obstacles, start noise from the shared sampler,
``--seed``), run by the deployment loop (``deploy.loop.run_episode``: NumPy policy, shared
control step, safety layer) on MuJoCo through ``grasp_check.MujocoRobot``: the approach is
kinematic like training, then the gripper closes and lifts with physics, as in the physical
grasp check.  Frames come from MuJoCo's offscreen renderer at the control rate (20 fps) from
the ``overview`` or the calibrated ``depth_camera``; the mp4 is written with imageio-ffmpeg
(extra ``render``), plus an optional PNG still of the first successful episode's end (lifted).

Headless machines render through EGL: ``MUJOCO_GL=egl`` is the default here (set it before
MuJoCo is imported).  It needs the system packages ``libegl1 libegl-mesa0 libopengl0
libgl1-mesa-dri`` (Debian/Ubuntu).  Without a working backend the command stops with a message
naming it, exit status 2.  Nothing here imports jax.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before anything imports mujoco: it picks the GL backend on import

import argparse
import sys
from typing import Any, Sequence

import numpy as np

from sagrasp_jax.base import extras
from sagrasp_jax.base import fileio
from sagrasp_jax.base import run_files
from sagrasp_jax.task.config import SEED_RANGE, ConfigError, check_range
from sagrasp_jax.deploy.safety import PolicyMismatch
from sagrasp_jax.task.policy_file import PolicyFormatError, load_policy

CAMERAS = ("overview", "depth_camera")
GL_PACKAGES = "libegl1 libegl-mesa0 libopengl0 libgl1-mesa-dri"
HOLD_FRAMES = 10  # frames repeated at the start and end of each episode (0.5 s at 20 fps)


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


class FrameRecorder:
    """An offscreen renderer bound to one episode's model; collects RGB frames."""

    def __init__(self, mujoco: Any, model: Any, camera: str, width: int, height: int) -> None:
        if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera) < 0:
            raise RenderError(f"camera {camera!r} is not in the model; choose one of {', '.join(CAMERAS)}")
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, height)
        try:
            self.renderer = mujoco.Renderer(model, height, width)
        except Exception as exc:  # mujoco.FatalError or EGL errors: no usable context
            raise _gl_error(exc) from None
        self.camera = camera
        self.frames: list[np.ndarray] = []

    def capture(self, scene: Any) -> None:
        self.renderer.update_scene(scene.data, camera=self.camera)
        self.frames.append(self.renderer.render().copy())

    def close(self) -> None:
        self.renderer.close()


def render_episodes(policy_path: str, episodes: int = 3, camera: str = "overview", seed: int = 0, width: int = 640,
                    height: int = 480, max_steps: int | None = None) -> tuple[list[np.ndarray], list[dict[str, Any]], int]:
    """Run and render ``episodes`` sampled scenes; returns (frames, per-episode reports, index of the still)."""
    mujoco = _mujoco()
    from sagrasp_jax.task import sampling
    from sagrasp_jax.deploy.loop import obstacles_from_spec, run_episode
    from sagrasp_jax.reference.grasp_check import GraspScene, MujocoRobot
    from sagrasp_jax.task.robot import load_robot

    if episodes < 1:
        raise RenderError(f"--episodes must be >= 1, got {episodes}")
    if camera not in CAMERAS:
        raise RenderError(f"--camera must be one of {', '.join(CAMERAS)}, got {camera!r}")
    policy = load_policy(policy_path)
    cfg = policy.env_config()
    model = load_robot()
    rng = np.random.default_rng(seed)
    frames: list[np.ndarray] = []
    reports: list[dict[str, Any]] = []
    still = -1
    for _ in range(episodes):
        u = rng.random(sampling.uniforms_needed(cfg.sampling))
        spec = sampling.sample_reset(np, model, cfg.sampling, cfg.task, u)
        scene = GraspScene(spec, spec.q0)
        recorder = FrameRecorder(mujoco, scene.model, camera, width, height)
        try:
            recorder.capture(scene)
            recorder.frames *= HOLD_FRAMES
            robot = MujocoRobot(scene, cfg.control.control_dt, on_frame=recorder.capture)
            report = run_episode(robot, policy, spec.target_pos, float(spec.target_yaw), obstacles_from_spec(spec),
                                 max_steps=max_steps)
            recorder.frames += [recorder.frames[-1]] * HOLD_FRAMES
        finally:
            recorder.close()
        if still < 0 or (report.success and not any(r["success"] for r in reports)):
            still = len(frames) + len(recorder.frames) - 1  # the first success's last frame, else episode 1's
        frames += recorder.frames
        reports.append(report.to_dict())
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
    p = argparse.ArgumentParser(prog="python -m sagrasp_jax.render", description=__doc__.split("\n\n")[0])
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--run", help="a finished run folder (python -m sagrasp_jax.train --out): its policy.npz")
    source.add_argument("--policy", help="exported policy.npz")
    p.add_argument("--out", required=True, help="video file (.mp4)")
    p.add_argument("--episodes", type=int, default=3)
    p.add_argument("--camera", default="overview", help=f"one of {', '.join(CAMERAS)}")
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
        print(f"episode {i + 1}: {r['outcome']} after {r['steps']} steps, final offset {r['final_distance'] * 1000:.1f} mm{held}")
    print(f"wrote {args.out} ({len(frames)} frames, {args.fps} fps, camera {args.camera}, MUJOCO_GL={os.environ['MUJOCO_GL']})"
          + (f" and {args.png}" if args.png else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
