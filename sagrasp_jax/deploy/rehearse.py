"""Deployment at scale on the twin: an exported policy through the deploy loop over N random scenes.

    python -m sagrasp_jax.deploy.rehearse --policy policy.npz --episodes 500 --condition robot \
        [--scenes mix|blocking] [--seed 0] [--workers 2] [--out twin.json]

(also ``python -m sagrasp_jax.evaluate --backend twin --run RUN ...``, which reads the run's ``policy.npz``).

What a user judges on a robot, not what training scores: each scene is drawn with the project's sampler
(the evaluation mix, or blocking-only scenes), the twin is built on the true scene, and the loop
(``deploy.loop.run_episode``) is handed what a camera would report: the cube with this episode's detection
error, the obstacles.  The loop runs the policy, holds the grasp pose, closes, lifts; the verdict is the cube
**held** after the lift with a clean approach (no obstacle or table touched, the cube not knocked).  The
named conditions are the MJX evaluation's (``config.EVAL_CONDITIONS``): their ``env.randomize`` knobs are
drawn per episode as the MJX env draws them (``deploy.transfer.draw``), and every mode but ``kinematic``
runs the twin's arm through the fitted servo model.  Episode ``i`` of seed ``s`` is the same scene and the
same errors whatever the number of workers.  Nothing here imports jax.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import multiprocessing
import os
import sys
import time
from typing import Any, NamedTuple, Sequence

import numpy as np

from sagrasp_jax.base import cli, extras, fileio
from sagrasp_jax.task import robot
from sagrasp_jax.task import sampling
from sagrasp_jax.task.config import EVAL_CONDITIONS, Config, ConfigError, EnvConfig, blocking_sampling
from sagrasp_jax.task.config_parse import apply_overrides
from sagrasp_jax.deploy import transfer
from sagrasp_jax.deploy.calibration import ObstacleRejected, TargetRejected
from sagrasp_jax.deploy.loop import DeployReport, obstacles_from_spec, run_episode
from sagrasp_jax.task.policy_file import (
    POLICY_HELP, PRETRAINED, NumpyPolicy, PolicyFormatError, load_policy, resolve_policy,
)

SCENE_SETS = ("mix", "blocking")
MAX_EPISODES = 100_000
MAX_WORKERS = 64


def condition_env(env_cfg: EnvConfig, condition: str) -> EnvConfig:
    """The policy's env with the named evaluation condition's overrides (the same as ``evaluate --condition``)."""
    if condition not in EVAL_CONDITIONS:
        raise ConfigError(f"unknown condition {condition!r}; valid: {', '.join(EVAL_CONDITIONS)}")
    return apply_overrides(Config(env=env_cfg), list(EVAL_CONDITIONS[condition])).env


def scene_env(env_cfg: EnvConfig, scenes: str) -> EnvConfig:
    """The env the scenes are drawn from: the evaluation mix, or every scene with an obstacle on the approach."""
    if scenes not in SCENE_SETS:
        raise ConfigError(f"unknown scene set {scenes!r}; valid: {', '.join(SCENE_SETS)}")
    if scenes == "mix":
        return env_cfg
    return dataclasses.replace(env_cfg, sampling=blocking_sampling(env_cfg.sampling, 1.0, 1.0))


def _kind(spec: sampling.ResetSpec, model: robot.RobotModel, env_cfg: EnvConfig) -> str:
    if not np.any(spec.obstacle_active):
        return "no obstacle"
    blocking = sampling.is_blocking(np, model, env_cfg.sampling, env_cfg.task, spec)
    return "blocking" if bool(blocking) else "obstacle"


def episode_kind(spec: sampling.ResetSpec, env_cfg: EnvConfig) -> str:
    """"no obstacle", "obstacle" or "blocking": how the evaluation counts this scene."""
    return _kind(spec, robot.load_robot(env_cfg.robot), env_cfg)


def _failure(report: DeployReport | None, refused: str) -> str:
    """One word for why an episode did not end with the cube held."""
    if report is None:
        return refused
    if report.outcome != "success":
        return {"refused": "safety stop"}.get(report.outcome, report.outcome)
    g = report.grasp or {}
    if not g.get("closed"):
        return "hold refused"
    if g.get("approach_faults"):
        return "approach fault"
    if not g.get("lifted"):
        return "lift stopped"
    return "dropped" if not report.held else ""


CAMERA_DRIVERS = ("twin", "realsense")


class CameraSettings(NamedTuple):
    """End to end from the camera: the twin renders the Mech-Eye's view (``deploy.twin_camera``) and
    ``deploy.perception`` gives the loop the cube and the obstacles instead of the sampler's.  ``driver``
    ``realsense``: each render goes through librealsense first (``deploy.realsense_record.through_librealsense``:
    written as a recording, played back through ``cameras.RealSenseCamera``'s rs.pipeline, rs.align and
    rs.pointcloud, z in 1 mm counts, a D435's default) and perception reads what librealsense returns."""

    noise: str = "industrial"  # depth-noise model (task.camera.NOISE_MODELS)
    resolution: float = 0.25  # fraction of the camera model's pixels (the Mech-Eye's 1920 × 1200; the view is kept)
    model: str = "mecheye_pro_m"  # the camera (task.camera: a registered model)
    driver: str = "twin"  # how the render reaches perception: as rendered, or through librealsense

    def describe(self) -> dict[str, Any]:
        """As a result names it: every field, ``driver`` only when not the default (a twin-driver result names its
        camera as it did before drivers existed)."""
        return {k: v for k, v in self._asdict().items() if not (k == "driver" and v == "twin")}


def _same_detection(a: Any, b: Any) -> bool:
    """Two ``SceneDetection``s equal to the last bit (the cube, its yaw, every obstacle)."""
    return (np.array_equal(a.target_centre, b.target_centre) and a.target_yaw == b.target_yaw
            and list(a.obstacles) == list(b.obstacles))


def _perceive(twin: Any, spec: sampling.ResetSpec, camera: CameraSettings, rng: np.random.Generator,
              record: dict[str, Any], env_cfg: EnvConfig, captures_dir: str | None = None
              ) -> tuple[np.ndarray, float, list[Any]] | None:
    """Capture the twin (the arm out of view), perceive with the policy's obstacle kinds, and record perception's
    errors against the true scene; None (and the record says why) when perception refuses the capture."""
    from sagrasp_jax.deploy.calibration import CameraCalibration
    from sagrasp_jax.deploy.perception import PerceptionError, PerceptionSettings, detect_scene

    capture = twin_capture(twin, spec, camera, rng)
    if camera.driver == "realsense":  # the render through librealsense: what a RealSense capture's path makes of it
        from sagrasp_jax.deploy.cameras import CameraError
        from sagrasp_jax.deploy.realsense_record import cloud_error_mm, through_librealsense

        try:
            rendered, capture = capture, through_librealsense(capture)
        except CameraError as exc:  # librealsense returned no capture: the scene fails as a refused capture would
            record["librealsense"] = {"error": str(exc)}
            record["perception"] = {"refused": f"librealsense: {exc}"}
            return None
        record["librealsense"] = cloud_error_mm(rendered.cloud_mm, capture.cloud_mm)
    settings = PerceptionSettings.for_policy(env_cfg)
    try:
        seen = detect_scene(capture.cloud_mm, capture.rgb, CameraCalibration.default(), settings=settings)
    except PerceptionError as exc:
        seen, refusal = None, str(exc)
    if captures_dir:  # the capture saved, read back and perceived again: the replay must see exactly the same
        from sagrasp_jax.deploy import capture_file

        path = capture_file.save_capture(os.path.join(captures_dir, f"scene-{record['index']:06d}.npz"), capture)
        try:
            replay = capture_file.load_capture(path)
            again = detect_scene(replay.cloud_mm, replay.rgb, CameraCalibration.default(), settings=settings)
            same = seen is not None and _same_detection(seen, again)
        except PerceptionError as exc:
            same = seen is None and str(exc) == refusal
        record["capture_file"], record["replay_identical"] = os.path.basename(path), bool(same)
    if seen is None:
        record["perception"] = {"refused": refusal}
        return None
    truth = obstacles_from_spec(spec)
    errors = [min(float(np.linalg.norm(np.subtract(o.centre, t.centre))) for t in truth) for o in seen.obstacles] \
        if truth else []
    found = sum(any(np.linalg.norm(np.subtract(o.centre, t.centre)) <= 0.02 for o in seen.obstacles) for t in truth)
    record["perception"] = {
        "target_error_mm": [float(1000 * v) for v in seen.target_centre - np.asarray(spec.target_pos)],
        "obstacles_true": len(truth), "obstacles_found": int(found),
        "obstacles_invented": int(sum(e > 0.02 for e in errors)),
        "obstacle_centre_error_mm": [1000 * e for e in errors if e <= 0.02],
    }
    return seen.target_centre, float(seen.target_yaw), list(seen.obstacles)


def draw_scene(scene_cfg: EnvConfig, seed: int, index: int) -> tuple[sampling.ResetSpec, np.random.Generator]:
    """Scene ``index`` of ``seed`` (the same for any number of workers) and the generator that drew it, left where
    the rehearsal draws the episode's errors and the camera's noise from it."""
    model = robot.load_robot(scene_cfg.robot)
    rng = np.random.default_rng([seed, index])
    spec = sampling.sample_reset(np, model, scene_cfg.sampling, scene_cfg.task,
                                 rng.uniform(size=sampling.uniforms_needed(scene_cfg.sampling, model.dof)))
    return sampling.ResetSpec(*(np.asarray(v) for v in spec)), rng


def twin_capture(twin: Any, spec: sampling.ResetSpec, camera: CameraSettings, rng: np.random.Generator,
                 kind: str = "", source: str = "twin") -> Any:
    """The twin's scene as the camera of ``camera`` reports it (the arm out of view), as a ``cameras.Capture``
    holding the true scene (``capture_file.scene_truth``), ready to save and replay."""
    from sagrasp_jax.deploy.cameras import Capture, now_utc
    from sagrasp_jax.deploy.capture_file import scene_truth
    from sagrasp_jax.deploy.twin_camera import TwinCamera

    # The capture is taken with the arm out of view, as a cell captures before the arm moves in: from its home
    # pose the AUBO hides some cubes from the gantry camera (perception refuses those, naming why).
    cam = TwinCamera(camera.resolution, model=camera.model)
    frame = cam.capture(twin, camera.noise, rng, hide_robot=True)
    return Capture(frame.rgb, frame.cloud_mm, frame.intrinsics, cam.model.name, source, now_utc(), scene_truth(spec, kind))


def run_scene(policy_path: str, env_cfg: EnvConfig, scene_cfg: EnvConfig, seed: int, index: int,
              camera: CameraSettings | None = None, captures_dir: str | None = None) -> dict[str, Any]:
    """Scene ``index`` of ``seed`` through the deploy loop on a fresh twin; a JSON-safe record.  With
    ``camera`` the loop is handed what perception finds in the twin's rendered capture (the condition's
    detection error is not added: the camera's own error is the detection error)."""
    from sagrasp_jax.deploy.twin import PyBulletTwin

    policy = _policy(policy_path)
    model = robot.load_robot(env_cfg.robot)  # the policy's arm
    spec, rng = draw_scene(scene_cfg, seed, index)
    errors, target_error = transfer.draw(env_cfg.randomize, env_cfg.control.mode != "kinematic", rng, model.dof)
    detected = np.asarray(spec.target_pos, float) + target_error
    record: dict[str, Any] = {"index": index, "kind": _kind(spec, model, scene_cfg),
                              "target": [float(v) for v in spec.target_pos],
                              "detection_error_mm": [float(1000 * v) for v in target_error],
                              "latency": errors.latency}
    report, refused = None, ""
    with PyBulletTwin(spec, env_cfg, q0=spec.q0, errors=errors, seed=index) as twin:
        if camera is not None:
            seen = _perceive(twin, spec, camera, rng, record, env_cfg, captures_dir)
            scene = seen if seen is not None else None
            refused = "perception refused" if seen is None else ""
        else:
            scene = (detected, float(spec.target_yaw), obstacles_from_spec(spec))
        try:
            if scene is not None:
                report = run_episode(twin, policy, scene[0], scene[1], scene[2])
        except (TargetRejected, ObstacleRejected, ValueError) as exc:
            refused, record["message"] = "input refused", str(exc)
    record["failure"] = _failure(report, refused)
    record["held"] = bool(report is not None and report.held)
    if report is not None:
        g = report.grasp or {}
        record.update(outcome=report.outcome, reached=report.success, steps=report.steps, message=report.message,
                      final_tilt_deg=report.final_tilt_deg, grasp_message=g.get("message", ""),
                      approach_faults=g.get("approach_faults") or [], closing_offset_mm=g.get("closing_offset_mm"),
                      min_obstacle_clearance=report.min_obstacle_clearance)
    return record


_POLICIES: dict[str, NumpyPolicy] = {}


def _policy(path: str) -> NumpyPolicy:
    """The policy at ``path``, loaded once per process and refused unless its inputs are the grasp task's."""
    if path not in _POLICIES:
        policy = load_policy(path)
        policy.check_grasp_inputs()
        _POLICIES[path] = policy
    return _POLICIES[path]


def _scene(args: tuple[str, EnvConfig, EnvConfig, int, int, CameraSettings | None, str | None]) -> dict[str, Any]:
    return run_scene(*args)


def wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """95 % Wilson interval of a rate k / n."""
    if n == 0:
        return (0.0, 1.0)
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (max(0.0, centre - half), min(1.0, centre + half))


def summarise(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Held and reached rates, failure counts and steps per success of a group of episodes."""
    n = len(records)
    held = sum(r["held"] for r in records)
    failures: dict[str, int] = {}
    for r in records:
        if r["failure"]:
            failures[r["failure"]] = failures.get(r["failure"], 0) + 1
    steps = [r["steps"] for r in records if r["held"]]
    return {
        "episodes": n,
        "held_rate": held / n if n else None,
        "held_ci95": list(wilson(held, n)),
        "reached_rate": sum(bool(r.get("reached")) for r in records) / n if n else None,
        "failures": dict(sorted(failures.items())),
        "mean_steps_per_success": float(np.mean(steps)) if steps else None,
    }


def policy_name(policy_path: str) -> str:
    """A policy as a result names it: a pretrained policy's name, else the absolute path of its file."""
    return policy_path if policy_path in PRETRAINED else os.path.abspath(resolve_policy(policy_path))


def rehearse(policy_path: str, episodes: int, condition: str, scenes: str = "mix", seed: int = 0,
             workers: int = 1, progress: bool = True, camera: CameraSettings | None = None,
             captures_dir: str | None = None) -> dict[str, Any]:
    """Run ``episodes`` twin scenes; the summary per episode kind and every episode's record.  With ``camera`` and
    ``captures_dir`` every scene's capture is saved there (``scene-<index>.npz``), read back and perceived again:
    each record says whether the replay saw exactly the same (``replay_identical``)."""
    policy = _policy(policy_path)
    env_cfg = condition_env(policy.env_config(), condition)
    scene_cfg = scene_env(env_cfg, scenes)
    workers = max(1, min(workers, episodes))
    t0 = time.perf_counter()
    records: list[dict[str, Any]] = []
    try:
        if workers == 1:
            for i in range(episodes):
                cli.check()  # a safe point for Ctrl-C: between scenes (and before every command, deploy.loop)
                records.append(run_scene(policy_path, env_cfg, scene_cfg, seed, i, camera, captures_dir))
                if progress and (i + 1) % 50 == 0:
                    print(f"  {i + 1}/{episodes} scenes, held {sum(r['held'] for r in records) / len(records):.1%}",
                          file=sys.stderr, flush=True)
        else:
            records = _in_workers(workers, [(policy_path, env_cfg, scene_cfg, seed, i, camera, captures_dir)
                                           for i in range(episodes)])
    except cli.Interrupted as exc:
        exc.done = exc.done or (len(records), episodes)
        raise
    records.sort(key=lambda r: r["index"])
    groups = {"all": records} | {k: [r for r in records if r["kind"] == k] for k in ("obstacle", "blocking", "no obstacle")}
    groups["obstacle"] = [r for r in records if r["kind"] in ("obstacle", "blocking")]  # every obstacle scene
    return {
        "backend": "twin",
        "policy": policy_name(policy_path),
        "policy_sha256": policy.file_sha256,
        "condition": condition,
        "condition_overrides": list(EVAL_CONDITIONS[condition]),
        "scenes": scenes,
        "seed": seed,
        "episodes": episodes,
        "wall_s": time.perf_counter() - t0,
        "workers": workers,
        "camera": camera.describe() if camera is not None else None,
        "summary": {name: summarise(rs) for name, rs in groups.items()},
        "perception": perception_summary(records) if camera is not None else None,
        "records": records,
    }


def _in_workers(workers: int, tasks: list[tuple[Any, ...]]) -> list[dict[str, Any]]:
    """The scenes over ``workers`` processes, each taking the next scene when it is done; Ctrl-C (``cli.check``,
    polled while waiting) or any error terminates the workers at once, whatever scene they are in (they ignore
    Ctrl-C themselves: the parent stops them)."""
    records: list[dict[str, Any]] = []
    pool = multiprocessing.get_context().Pool(workers, initializer=cli.ignore_interrupts)
    try:
        results = pool.imap_unordered(_scene, tasks)
        while len(records) < len(tasks):
            cli.check()
            try:
                records.append(results.next(timeout=0.1))
            except multiprocessing.TimeoutError:
                continue
        pool.close()
    except BaseException as exc:
        if isinstance(exc, cli.Interrupted):
            exc.done = (len(records), len(tasks))
        pool.terminate()
        raise
    finally:
        pool.join()
    return records


def perception_summary(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Perception's errors over the episodes: target centre error percentiles, obstacles found, missed and
    invented, obstacle centre errors, refusals."""
    seen = [r["perception"] for r in records if "perception" in r and "refused" not in r["perception"]]
    horizontal = np.array([math.hypot(*p["target_error_mm"][:2]) for p in seen]) if seen else np.zeros(0)
    centre = [e for p in seen for e in p["obstacle_centre_error_mm"]]
    pct = lambda a, q: float(np.percentile(a, q)) if len(a) else None  # noqa: E731
    true_n = sum(p["obstacles_true"] for p in seen)
    return {
        "captures": len(records), "refused": len(records) - len(seen),
        "target_horizontal_error_mm": {"p50": pct(horizontal, 50), "p95": pct(horizontal, 95),
                                       "max": float(horizontal.max()) if len(horizontal) else None},
        "obstacles_true": true_n, "obstacles_found": sum(p["obstacles_found"] for p in seen),
        "obstacles_invented": sum(p["obstacles_invented"] for p in seen),
        "obstacle_centre_error_mm": {"p50": pct(centre, 50), "p95": pct(centre, 95)},
        "replayed": sum("replay_identical" in r for r in records),
        "replay_identical": sum(bool(r.get("replay_identical")) for r in records),
    }


def format_table(result: dict[str, Any]) -> str:
    groups = [(name, g) for name, g in result["summary"].items() if g["episodes"]]
    kinds = sorted({k for _, g in groups for k in g["failures"]})
    pct = lambda v: "-" if v is None else f"{100 * v:.1f} %"  # noqa: E731
    rows = [("episodes", [str(g["episodes"]) for _, g in groups]),
            ("cube held", [pct(g["held_rate"]) for _, g in groups]),
            ("  95 % CI", [f"{100 * g['held_ci95'][0]:.1f}-{100 * g['held_ci95'][1]:.1f}" for _, g in groups]),
            ("grasp pose reached", [pct(g["reached_rate"]) for _, g in groups]),
            ("steps / success", ["-" if g["mean_steps_per_success"] is None else f"{g['mean_steps_per_success']:.1f}"
                                 for _, g in groups])]
    rows += [(f"  {k}", [str(g["failures"].get(k, 0)) for _, g in groups]) for k in kinds]
    width = max(len(r[0]) for r in rows) + 2
    cam = result.get("camera") or {}
    model = f"{cam['model']}, " if cam.get("model", "mecheye_pro_m") != "mecheye_pro_m" else ""
    driver = ", through librealsense" if cam.get("driver") == "realsense" else ""
    camera = f", from the camera ({model}{cam['noise']} depth noise{driver})" if cam else ""
    head = f"twin, {result['condition']}, {result['scenes']} scenes{camera}, seed {result['seed']}: {result['wall_s']:.0f} s"
    lines = [head, " " * width + "".join(f"{name:>14}" for name, _ in groups)]
    lines += [label.ljust(width) + "".join(f"{v:>14}" for v in values) for label, values in rows]
    if result.get("perception"):
        p = result["perception"]
        t = p["target_horizontal_error_mm"]
        lines.append(f"perception: {p['refused']} of {p['captures']} captures refused; cube centre error (horizontal) "
                     f"p50 {t['p50'] or 0:.1f} / p95 {t['p95'] or 0:.1f} / max {t['max'] or 0:.1f} mm; obstacles "
                     f"{p['obstacles_found']} of {p['obstacles_true']} found, {p['obstacles_invented']} invented")
        if p.get("replayed"):
            lines.append(f"replays: {p['replay_identical']} of {p['replayed']} saved captures perceived again exactly "
                         "as when taken")
    return "\n".join(lines)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--episodes", type=int, default=500, help="scenes to run (default 500)")
    p.add_argument("--condition", choices=sorted(EVAL_CONDITIONS), default="robot",
                   help="named evaluation condition, as the MJX evaluation's (default robot)")
    p.add_argument("--scenes", choices=SCENE_SETS, default="mix", help="mix: the evaluation mix; blocking: every "
                   "scene has an obstacle on the straight approach path")
    p.add_argument("--seed", type=int, default=0, help="scene and error draws (default 0)")
    p.add_argument("--workers", type=int, default=1, help="processes (default 1; one per core)")
    p.add_argument("--out", default=None, help="write the result as JSON here (an existing file only if it holds the "
                   "same twin result, or another one with --force)")
    p.add_argument("--force", action="store_true", help="replace an --out file that holds another twin result")
    p.add_argument("--camera", choices=("none", "twin"), default="none",
                   help="twin: end to end from the twin's rendered camera through deploy.perception (default none: "
                        "the sampler's scene with the condition's detection error)")
    add_camera_arguments(p, "--camera twin: ")
    p.add_argument("--save-captures", default=None, metavar="DIR",
                   help="--camera twin: save every scene's capture in DIR (scene-<index>.npz, replayable with deploy "
                        "--camera replay:FILE), read it back and perceive it again; the result counts the replays "
                        "that saw exactly the same")


def add_camera_arguments(p: argparse.ArgumentParser, prefix: str = "") -> None:
    """The twin camera's options (here and in ``deploy --camera twin --scenes N``); ``prefix`` starts each help."""
    from sagrasp_jax.task.camera import CHOICES, DEFAULT_CAMERA

    p.add_argument("--camera-model", choices=CHOICES, default=DEFAULT_CAMERA,  # the registry when parsed
                   help=f"{prefix}the camera the twin renders (task.camera's registered models; default {DEFAULT_CAMERA})")
    p.add_argument("--depth-noise", default=None, help=f"{prefix}depth-noise model (none, industrial, consumer; default "
                   "the camera model's: industrial for the Mech-Eye, consumer for the RealSense)")
    p.add_argument("--camera-resolution", type=float, default=0.25,
                   help=f"{prefix}fraction of the camera model's pixels (default 0.25: the Mech-Eye's 1920 × 1200 as "
                        "480 × 300, the RealSense's 1280 × 720 as 320 × 180)")
    p.add_argument("--camera-driver", choices=CAMERA_DRIVERS, default="twin",
                   help=f"{prefix}twin (default): perception reads the render; realsense: the render goes through "
                        "librealsense first (a recording played back through rs.pipeline, rs.align and rs.pointcloud, "
                        "as a RealSense capture; needs pyrealsense2 and the system's libusb-1.0)")


def camera_settings(args: argparse.Namespace) -> CameraSettings | None:
    """The ``CameraSettings`` of parsed options (None without ``--camera twin``); the noise defaults to the model's."""
    if getattr(args, "camera", "none") != "twin":
        return None
    from sagrasp_jax.task.camera import camera_model

    model = camera_model(getattr(args, "camera_model", "mecheye_pro_m"))
    return CameraSettings(args.depth_noise or model.noise, args.camera_resolution, model.name,
                          getattr(args, "camera_driver", "twin"))


def check_arguments(args: argparse.Namespace) -> None:
    if not 1 <= args.episodes <= MAX_EPISODES:
        raise ValueError(f"--episodes must be in [1, {MAX_EPISODES}], got {args.episodes}")
    if not 1 <= args.workers <= MAX_WORKERS:
        raise ValueError(f"--workers must be in [1, {MAX_WORKERS}], got {args.workers}")
    if not 0 <= args.seed < 2**31:
        raise ValueError(f"--seed must be in [0, 2^31), got {args.seed}")
    if getattr(args, "camera", "none") == "twin":
        from sagrasp_jax.task.camera import noise_model

        if args.depth_noise is not None:
            noise_model(args.depth_noise)  # ValueError naming the models
        if not 0.05 <= args.camera_resolution <= 1.0:
            raise ValueError(f"--camera-resolution must be in [0.05, 1], got {args.camera_resolution}")
        if getattr(args, "camera_driver", "twin") == "realsense":  # before any scene: pyrealsense2 and libusb present
            from sagrasp_jax.deploy.cameras import CameraError, import_vendor

            try:
                import_vendor("realsense", "pyrealsense2", "--camera-driver realsense")
            except CameraError as exc:
                raise ValueError(str(exc)) from None
    if getattr(args, "save_captures", None):
        if getattr(args, "camera", "none") != "twin":
            raise ValueError("--save-captures needs --camera twin")
        os.makedirs(args.save_captures, exist_ok=True)
        fileio.check_writable(args.save_captures, "--save-captures folder")


RESULT_KIND = {"backend": "twin", "episodes": None, "summary": None}  # what makes a file a twin result
RESULT_IDENTITY = ("backend", "policy", "policy_sha256", "condition", "scenes", "seed", "episodes", "camera")


def result_identity(policy: NumpyPolicy, policy_path: str, args: argparse.Namespace,
                    camera: CameraSettings | None) -> dict[str, Any]:
    """What a twin result is of (the entries of ``rehearse``'s result that fix its numbers): the same identity
    gives the same result, whatever the number of workers."""
    return {"backend": "twin", "policy": policy_name(policy_path), "policy_sha256": policy.file_sha256,
            "condition": args.condition, "scenes": args.scenes, "seed": args.seed, "episodes": args.episodes,
            "camera": camera.describe() if camera is not None else None}


def check_output(path: str, identity: dict[str, Any], force: bool) -> None:
    """Refuse, before any scene runs, an output that would replace anything but the same twin result (or, with
    ``--force``, another twin result), and a folder that cannot be written (``fileio.check_result_output``)."""
    fileio.check_result_output(path, identity, RESULT_KIND, "twin evaluation result", force)
    fileio.check_writable(os.path.dirname(os.path.abspath(path)))


def run_cli(policy_path: str, args: argparse.Namespace, out: str | None = None) -> int:
    """Shared by this module's CLI, ``deploy --camera twin`` and ``evaluate --backend twin``: validate, run, print,
    write (to ``out``, default ``args.out``); the exit status.  Ctrl-C stops the scenes (the workers at once),
    writes nothing and exits 130 with one line saying so."""
    out = args.out if out is None else out
    try:
        camera = camera_settings(args)
    except ValueError as exc:  # an unknown camera model given programmatically (the parsers offer only known ones)
        print(f"error: {exc}", file=sys.stderr)
        return 2
    with cli.at_safe_points():
        try:
            try:
                check_arguments(args)
                extras.require("twin", what="the twin rehearsal (--backend twin)")
                policy = _policy(policy_path)
                if out:
                    check_output(out, result_identity(policy, policy_path, args, camera), getattr(args, "force", False))
            except (ValueError, PolicyFormatError, ConfigError, extras.MissingExtra, OSError) as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 2
            result = rehearse(policy_path, args.episodes, args.condition, args.scenes, args.seed, args.workers,
                              camera=camera, captures_dir=getattr(args, "save_captures", None))
            cli.check()  # the last safe point: a Ctrl-C from here on lets the result be written
        except cli.Interrupted as exc:
            done, total = exc.done or (0, args.episodes)
            workers = f" (its {args.workers} worker processes terminated)" if args.workers > 1 else ""
            print(cli.interrupted_line(f"the twin rehearsal was stopped after {done} of {total} scenes{workers}",
                                       "no result was written" + (f" ({out} left as it was)" if out and
                                                                   os.path.exists(out) else "")),
                  file=sys.stderr)
            return cli.INTERRUPTED
    print(format_table(result))
    if out:
        try:
            fileio.atomic_write_json(out, result, indent=1)
        except OSError as exc:  # e.g. the disk filled up meanwhile: the table above is the result
            print(f"error: {exc}; the result above was not saved", file=sys.stderr)
            return 2
        print(f"written {out}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    p = cli.Parser(prog="python -m sagrasp_jax.deploy.rehearse", description=__doc__.split("\n\n")[0])
    p.add_argument("--policy", required=True, help=POLICY_HELP)
    add_arguments(p)
    args = p.parse_args(argv)
    return run_cli(args.policy, args)


if __name__ == "__main__":
    sys.exit(main())
