"""Capture files: one depth-camera capture saved whole, so that a grasp can be run again from it at a desk.

``python -m sagrasp_jax.capture`` writes one; ``python -m sagrasp_jax.deploy --camera replay:FILE`` reads it
(and every real-camera deploy saves the capture it acted on).  The file is an ``np.savez_compressed``
archive of plain arrays, no pickles:

==============  ====================  ==========================================================================
member          type                  what
==============  ====================  ==========================================================================
``format``      str                   ``FORMAT`` ("sagrasp_jax capture 1")
``rgb``         uint8 (H, W, 3)       the colour image on the cloud's pixel grid (RGB order)
``cloud_mm``    float32 (H, W, 3)     the organized cloud, camera frame (x right, y down, z along the optical
                                      axis), millimetres, NaN where there was no return
``intrinsics``  float64 (6,) or (0,)  [width, height, fx, fy, cx, cy] as the SDK (or the twin) reported them;
                                      empty when not known
``meta``        str                   JSON: ``camera`` (a ``task.camera`` model name or ""), ``source`` (what
                                      took it), ``time_utc``, ``truth`` (a twin capture's true scene:
                                      ``q0``, ``target_pos``, ``target_yaw``, ``obstacles``, ``kind``; else null),
                                      ``robot_q`` (the arm's joints in rad when it was taken, so that perception
                                      leaves the arm out; null: the arm was out of view)
==============  ====================  ==========================================================================

Reading is bounded like every input of the project (``fileio.read_regular``, ``policy_file.read_npz``) and
checks every member; anything else is a ``CaptureFormatError`` naming the file and the problem (exit 2).
"""

from __future__ import annotations

import io
import json
import math
import zipfile
from typing import Any

import numpy as np

from sagrasp_jax.base import fileio
from sagrasp_jax.deploy.cameras import Capture, checked_capture, CameraError
from sagrasp_jax.task import shapes
from sagrasp_jax.task import camera as camera_models
from sagrasp_jax.task.camera import Intrinsics
from sagrasp_jax.task.policy_file import read_npz
from sagrasp_jax.task import robots

FORMAT = "sagrasp_jax capture 1"
MAX_CAPTURE_BYTES = 512 << 20  # a 4K organized cloud and image (≈ 125 MB unpacked) with room to spare
MEMBERS = ("format", "rgb", "cloud_mm", "intrinsics", "meta")
META_KEYS = ("camera", "source", "time_utc", "truth", "robot_q")
TRUTH_KEYS = ("q0", "target_pos", "target_yaw", "obstacles", "kind")


class CaptureFormatError(ValueError):
    """A capture file that cannot be read as one; nothing was done with it."""


def scene_truth(spec: Any, kind: str = "") -> dict[str, Any]:
    """A twin scene (a ``sampling.ResetSpec``) as the capture's ``truth``: JSON-safe, enough to build the twin again."""
    active = np.nonzero(np.asarray(spec.obstacle_active))[0]
    return {"q0": [float(v) for v in np.asarray(spec.q0)], "target_pos": [float(v) for v in np.asarray(spec.target_pos)],
            "target_yaw": float(spec.target_yaw), "kind": kind,
            "obstacles": [{"kind": shapes.BY_ID[int(spec.obstacle_kind[i])].name,
                           "centre": [float(v) for v in spec.obstacle_pos[i]],
                           "size": [float(v) for v in spec.obstacle_size[i]], "yaw": float(spec.obstacle_yaw[i])}
                          for i in active]}


def _joint_count(value: Any, path: str, field: str) -> int:
    """The joint count of a capture's joint vector: any registered robot's (the file does not name the robot; the
    deploy command checks it against the policy's)."""
    counts = sorted({robots.get(name).dof for name in robots.names()})
    n = len(value) if isinstance(value, (list, tuple)) else -1
    if n not in counts:
        raise CaptureFormatError(f"{path}: meta.{field} must be one joint angle per joint of a registered robot "
                                 f"({' or '.join(map(str, counts))} numbers), got {value!r}")
    return n


def _finite(value: Any, n: int, path: str, field: str, what: str = "") -> list[float]:
    """``value``, a JSON list of ``n`` finite numbers, or ``CaptureFormatError`` naming ``meta.FIELD``."""
    try:
        v = np.asarray(value, dtype=float).reshape(-1) if isinstance(value, list) else np.zeros(0)
    except (TypeError, ValueError):
        v = np.zeros(0)
    if v.shape != (n,) or not np.isfinite(v).all():
        raise CaptureFormatError(f"{path}: meta.{field} must be {what or f'{n} finite numbers'}, got {value!r}")
    return [float(x) for x in v]


def _check_truth(truth: Any, path: str) -> dict[str, Any] | None:
    if truth is None:
        return None

    def numbers(value: Any, n: int, what: str) -> list[float]:
        return _finite(value, n, path, f"truth.{what}")

    if not isinstance(truth, dict) or sorted(truth) != sorted(TRUTH_KEYS):
        raise CaptureFormatError(f"{path}: meta.truth must hold exactly {', '.join(TRUTH_KEYS)}")
    obstacles = truth["obstacles"]
    if not isinstance(obstacles, list) or len(obstacles) > 16:
        raise CaptureFormatError(f"{path}: meta.truth.obstacles must be a list (at most 16)")
    checked = []
    for i, ob in enumerate(obstacles):
        if not isinstance(ob, dict) or sorted(ob) != ["centre", "kind", "size", "yaw"] or ob["kind"] not in shapes.BY_NAME:
            raise CaptureFormatError(f"{path}: meta.truth.obstacles[{i}] must be {{kind ({', '.join(shapes.NAMES)}), "
                                     "centre, size, yaw}")
        checked.append({"kind": ob["kind"], "centre": numbers(ob["centre"], 3, f"obstacles[{i}].centre"),
                        "size": numbers(ob["size"], 3, f"obstacles[{i}].size"),
                        "yaw": numbers([ob["yaw"]], 1, f"obstacles[{i}].yaw")[0]})
    return {"q0": numbers(truth["q0"], _joint_count(truth["q0"], path, "truth.q0"), "q0"),
            "target_pos": numbers(truth["target_pos"], 3, "target_pos"),
            "target_yaw": numbers([truth["target_yaw"]], 1, "target_yaw")[0], "obstacles": checked,
            "kind": str(truth["kind"])}


def _meta(capture: Capture) -> str:
    return json.dumps({"camera": capture.camera, "source": capture.source, "time_utc": capture.time_utc,
                       "truth": capture.truth,
                       "robot_q": None if capture.robot_q is None else [float(v) for v in capture.robot_q]},
                      allow_nan=False)


def save_capture(path: str, capture: Capture) -> str:
    """Write ``capture`` to ``path`` atomically (nothing half-written on any error; ``fileio.atomic_write``)."""
    checked = checked_capture(capture.rgb, capture.cloud_mm, "capture")
    k = capture.intrinsics
    if k is not None and (k.width, k.height) != (checked.cloud_mm.shape[1], checked.cloud_mm.shape[0]):
        raise ValueError(f"intrinsics of a {k.width} × {k.height} image for a {checked.cloud_mm.shape[1]} × "
                         f"{checked.cloud_mm.shape[0]} cloud")
    arrays = {"format": np.array(FORMAT), "rgb": checked.rgb, "cloud_mm": checked.cloud_mm,
              "intrinsics": np.asarray(k.as_list() if k is not None else [], dtype=np.float64),
              "meta": np.array(_meta(capture))}

    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)

    return fileio.atomic_write(path, write)


def load_capture(path: str) -> Capture:
    """The ``Capture`` a capture file holds, every member checked (``CaptureFormatError`` otherwise)."""
    data = fileio.read_input(path, MAX_CAPTURE_BYTES, "capture file", CaptureFormatError,
                             f"{path}: capture file not found (python -m sagrasp_jax.capture writes one)")
    try:
        arrays = read_npz(path, io.BytesIO(data), max_bytes=MAX_CAPTURE_BYTES, max_members=len(MEMBERS),
                          error=CaptureFormatError, what="a capture file")
    except CaptureFormatError:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError, NotImplementedError,
            RuntimeError) as exc:
        raise CaptureFormatError(f"{path}: not a readable .npz archive ({type(exc).__name__}: {exc})") from None
    if sorted(arrays) != sorted(MEMBERS):
        raise CaptureFormatError(f"{path}: members {sorted(arrays)}; a capture file holds {', '.join(MEMBERS)} "
                                 "(python -m sagrasp_jax.capture writes one)")
    fmt, meta_text = arrays["format"], arrays["meta"]
    if fmt.shape != () or fmt.dtype.kind != "U" or str(fmt) != FORMAT:
        raise CaptureFormatError(f"{path}: format {fmt!r}, not {FORMAT!r}")
    if meta_text.shape != () or meta_text.dtype.kind != "U":
        raise CaptureFormatError(f"{path}: meta must be one JSON string")
    try:
        meta = json.loads(str(meta_text))
    except json.JSONDecodeError as exc:
        raise CaptureFormatError(f"{path}: meta is not JSON ({exc})") from None
    if not isinstance(meta, dict) or sorted(meta) != sorted(META_KEYS):
        raise CaptureFormatError(f"{path}: meta must hold exactly {', '.join(META_KEYS)}")
    if meta["camera"] not in ("", *camera_models.names()):
        raise CaptureFormatError(f"{path}: camera {meta['camera']!r} is not one of {', '.join(camera_models.names())} "
                                 "(task.camera's registered models)")
    if not all(isinstance(meta[k], str) for k in ("source", "time_utc")):
        raise CaptureFormatError(f"{path}: meta.source and meta.time_utc must be strings")
    rgb, cloud = arrays["rgb"], arrays["cloud_mm"]
    if cloud.dtype != np.float32:
        raise CaptureFormatError(f"{path}: cloud_mm of type {cloud.dtype}; a capture file holds float32 millimetres")
    try:
        checked = checked_capture(rgb, cloud, path)
    except CameraError as exc:
        raise CaptureFormatError(str(exc)) from None
    k = arrays["intrinsics"]
    intrinsics = None
    if k.size:
        try:
            intrinsics = Intrinsics.from_list(k)
        except ValueError as exc:
            raise CaptureFormatError(f"{path}: {exc}") from None
        if (intrinsics.width, intrinsics.height) != (cloud.shape[1], cloud.shape[0]):
            raise CaptureFormatError(f"{path}: intrinsics of a {intrinsics.width} × {intrinsics.height} image for a "
                                     f"{cloud.shape[1]} × {cloud.shape[0]} cloud")
    robot_q = meta["robot_q"]
    if robot_q is not None:
        what = "the arm's joint angles in rad (one per joint of a registered robot)"
        q = _finite(robot_q, _joint_count(robot_q, path, "robot_q"), path, "robot_q", what)
        if max(abs(v) for v in q) > 2 * math.pi:
            raise CaptureFormatError(f"{path}: meta.robot_q must be {what}, got {robot_q!r}")
        robot_q = tuple(q)
    return Capture(checked.rgb, checked.cloud_mm, intrinsics, meta["camera"], meta["source"], meta["time_utc"],
                   _check_truth(meta["truth"], path), robot_q)
