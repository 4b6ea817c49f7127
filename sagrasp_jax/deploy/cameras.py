"""Real depth cameras as perception sources: the paper's Mech-Eye and Intel RealSense, through the vendors' SDKs.

A ``CameraSource`` has ``capture() -> Capture(rgb, cloud_mm)`` and ``close()``: ``rgb`` (H, W, 3) uint8 and
``cloud_mm`` (H, W, 3) float32, the organized point cloud in the camera frame (x right, y down, z along the
optical axis, OpenCV's and both vendors' convention), millimetres, NaN where there is no return, the same
pixel grid as the image — what ``deploy.twin_camera`` renders and ``deploy.perception`` reads.

* ``MechEyeCamera(ip)`` (``pip install "sagrasp_jax[mecheye]"``, Mech-Mind's ``mecheyeapi``, wheels for CPython
  3.7–3.11 only): one ``Camera.capture_2d_and_3d`` per capture, read through
  ``Frame2DAnd3D.get_textured_point_cloud`` (the 2D image mapped onto the depth map's grid): its ``vertices()``
  are in mm (the SDK's default unit, set explicitly with ``set_point_cloud_unit``) with NaN where invalid, its
  ``colors()`` BGR.  The capture carries the depth camera's intrinsics (``get_camera_intrinsics``, when
  ``get_camera_resolutions`` gives the depth map the cloud's size: ``mecheye_intrinsics``), the model
  (``get_camera_info``: ``mecheye_pro_m`` for a PRO M or Pro M Enhanced; "" for any other, named in ``source``),
  ``source`` "mecheye IP SERIAL" and the time it was asked for.
* ``RealSenseCamera(serial=None)`` (``pip install "sagrasp_jax[realsense]"``, Intel's ``pyrealsense2``; on
  Linux it also needs the system's libusb-1.0, Debian's ``libusb-1.0-0``): depth and colour streams, the depth
  aligned to the colour camera (``rs.align``), the cloud from ``rs.pointcloud`` (librealsense's own
  deprojection, with the camera's intrinsics and distortion) in metres, 0 where there is no depth: converted to
  mm and NaN.  ``RealSenseCamera("path/to/recording.db3")`` (or an older librealsense's ROS1 ``.bag``) plays a
  recording back through the same ``rs.pipeline``, ``rs.align`` and ``rs.pointcloud`` instead of a device
  (``rs.config.enable_device_from_file``, not in real time, not repeated): ``deploy.realsense_record`` writes
  such a recording of the twin's renders.  The capture's intrinsics are the colour stream's pinhole part
  (width, height, fx, fy, ppx, ppy); its distortion coefficients are not kept, since the cloud from
  ``rs.pointcloud`` has already been deprojected with them.

The conversions from the SDKs' arrays (``mecheye_capture``, ``realsense_capture``) are pure NumPy, tested on
the SDKs' real frame objects built without a device (a Mech-Eye ``TexturedPointCloud`` filled by hand, a
RealSense software device's depth frame through ``rs.pointcloud``); ``RealSenseCamera`` has run on
recordings of the twin's renders (``tests/deploy/test_realsense_librealsense.py``).  Neither camera class has run
against a real camera here.  Every capture has a timeout; a camera that is absent or does not answer raises
``CameraError`` naming it (deploy exits 2: nothing moved).

Mech-Eye API 2.6.0 without a camera, as measured here (Linux x86-64, CPython 3.11).  It has no virtual or
file-backed area-scan camera (``Camera.save_virtual_device_file`` writes an .mraw for Mech-Eye Viewer from a
connected camera; only the laser profilers' ``VirtualProfiler`` loads one) and no reader for the frames it saves
(PLY, PCD, CSV): nothing replays through it (``deploy --camera replay:FILE`` replays the project's capture files).
Its containers (``TexturedPointCloud``, ``CameraIntrinsics``, ``CameraResolutions``, ``CameraInfo``) are built
and filled without a device; ``Camera.discover_cameras`` keeps to its timeout (0.2 s, 2.0 s: an empty list).
``Camera.connect`` does not keep to its timeout, and holds the GIL (no Python thread can cut it short): it runs
the system's ``ping`` to the camera, sends a ZeroMQ request to TCP port 5577 (``CameraInfo.port`` is not used),
waits about 1 s and, after a failure, runs ``ping`` again.  Whatever the timeout (0.1 to 10 s) it returned after
1.0 s against loopback with nothing listening, with a listener that accepts and says nothing, and with a ZeroMQ
peer that never replies; after 1.8 to 4.1 s for an absent host on this machine's subnet (ping's ARP wait); after
13 s with a ``ping`` that took 6 s.  Its code for an unanswered request is -2 (DEVICE_OFFLINE, "the device is
unreachable") when ``ping`` fails or is not installed, -9 (TIMEOUT_ERROR) when the host answers ping; a host
name or a file path is -7 (INVALID_INPUT_ERROR) at once.  So ``MechEyeCamera`` first opens a plain TCP
connection to port 5577 within its timeout and asks the SDK only when something accepts it.  The SDK writes its
own lines to stderr (and, on a machine's first run, its logger's to stdout) and logs to /var/log/mmind (else
/tmp): ``MechEyeCamera`` holds what the SDK writes during its calls (to stderr after a success; after a failure
the error carries the SDK's message).  A ``Camera`` that tried a silent peer and lives on until the
interpreter's exit hangs that exit, so a failed one is dropped at once.

What of this path ran here (``tests/deploy/test_mecheye_sdk.py``): the SDK's ``connect`` against those loopback peers,
through ``open_camera`` and the ``capture`` and ``deploy`` commands (refused with exit 2 within the timeout), and
the SDK's containers through ``mecheye_capture``, ``mecheye_intrinsics`` and ``mecheye_model``.  What never ran:
a Mech-Eye camera — a successful ``connect``, ``set_point_cloud_unit``, ``get_camera_info``,
``get_camera_intrinsics`` and ``get_camera_resolutions`` on a connection, ``capture_2d_and_3d`` and its
timeout, a real frame's ``get_textured_point_cloud`` (that its grid is the depth map's, with the depth camera's
intrinsics, is read from Mech-Mind's docstrings and samples, not seen), ``disconnect`` of a live connection, and
what a camera's server makes of the bare TCP connection opened before the SDK's.
"""

from __future__ import annotations

import datetime
import importlib
import ipaddress
import os
import re
import shutil
import socket
import sys
import time
from typing import Any, NamedTuple, Protocol, runtime_checkable

import numpy as np

from sagrasp_jax.base import extras
from sagrasp_jax.base.native_output import held_native_output
from sagrasp_jax.task import camera as camera_models
from sagrasp_jax.task.camera import Intrinsics

CAMERAS = camera_models.DRIVERS  # the drivers open_camera has: task.camera keeps the list its models name


class CameraError(RuntimeError):
    """The camera is absent, refused, timed out or returned no data; nothing has moved."""


class Capture(NamedTuple):
    """One capture in the project's form (module docstring), with what is known of where it came from."""

    rgb: np.ndarray  # (H, W, 3) uint8
    cloud_mm: np.ndarray  # (H, W, 3) float32, camera frame, mm, NaN where no return
    intrinsics: Intrinsics | None = None  # the pixel grid's, as the SDK (or the twin) reported them
    camera: str = ""  # the task.camera model name ("mecheye_pro_m", "realsense_d435"), "" when not known
    source: str = ""  # what took it: "mecheye 192.168.1.10", "realsense 0123456789", "twin seed 0 scene 3", a file
    time_utc: str = ""  # ISO 8601, when it was taken
    truth: dict[str, Any] | None = None  # a twin capture's true scene (capture_file.scene_truth); None for a camera
    robot_q: tuple[float, ...] | None = None  # the arm's joints (rad) when it was taken: perception leaves the arm
    # out of the scene there; None: the arm was out of view (parked, or a capture taken before it came in)


@runtime_checkable
class CameraSource(Protocol):
    """What the perception needs from a camera: a capture in the project's form, and a clean close."""

    def capture(self) -> Capture: ...

    def close(self) -> None: ...


# ---- pure conversions (NumPy only; tested without the SDKs' devices) ----


def _no_return_to_nan(cloud: np.ndarray) -> np.ndarray:
    """NaN for every point without a return: NaN/inf anywhere, or z ≤ 0 (nothing lies at or behind the lens;
    RealSense marks a missing depth with 0)."""
    cloud = np.array(cloud, dtype=np.float32)
    bad = ~np.isfinite(cloud).all(axis=-1) | ~(cloud[..., 2] > 0)
    cloud[bad] = np.nan
    return cloud


def checked_capture(rgb: Any, cloud_mm: Any, source: str) -> Capture:
    """A ``Capture`` after checking shapes and types, or ``CameraError`` naming ``source``."""
    rgb, cloud = np.asarray(rgb), np.asarray(cloud_mm)
    if cloud.ndim != 3 or cloud.shape[2] != 3 or cloud.shape[0] < 1 or cloud.shape[1] < 1:
        raise CameraError(f"{source}: point cloud of shape {cloud.shape}; expected (H, W, 3) (an empty frame?)")
    if rgb.shape != cloud.shape:
        raise CameraError(f"{source}: image of shape {rgb.shape} does not match the cloud's {cloud.shape}")
    if rgb.dtype != np.uint8:
        raise CameraError(f"{source}: image of type {rgb.dtype}; expected uint8")
    return Capture(np.ascontiguousarray(rgb), np.ascontiguousarray(cloud, dtype=np.float32))


def mecheye_capture(vertices: Any, colors_bgr: Any, unit_to_mm: float = 1.0) -> Capture:
    """Mech-Eye ``TexturedPointCloud.vertices()`` (H, W, 3) and ``.colors()`` (H, W, 3, BGR) -> ``Capture``.

    ``unit_to_mm`` is 1 for the SDK's millimetres (the unit ``MechEyeCamera`` sets), 1000 for metres.
    """
    vertices = np.asarray(vertices)
    cloud = _no_return_to_nan(vertices * np.float32(unit_to_mm)) if vertices.ndim == 3 else vertices
    colors = np.asarray(colors_bgr)
    rgb = colors[..., ::-1] if colors.ndim == 3 else colors
    return checked_capture(rgb, cloud, "Mech-Eye")


# CameraInfo.model ("Mech-Eye PRO M", "Mech-Eye Pro M Enhanced"), lower case, letters and digits, less "mecheye"
MECHEYE_MODELS = {"prom": "mecheye_pro_m", "promenhanced": "mecheye_pro_m"}


def mecheye_model(model: str) -> str:
    """The ``task.camera`` model of a Mech-Eye ``CameraInfo.model``: ``mecheye_pro_m`` for a PRO M or Pro M Enhanced
    (the same optics), "" for any other model (one ``task.camera`` does not describe)."""
    key = re.sub(r"[^a-z0-9]", "", str(model).lower()).removeprefix("mecheye")
    return MECHEYE_MODELS.get(key, "")


def mecheye_intrinsics(intrinsics: Any, resolutions: Any, height: int, width: int) -> Intrinsics | None:
    """The pinhole intrinsics of a textured point cloud's ``height`` × ``width`` grid from Mech-Eye API's
    ``CameraIntrinsics`` and ``CameraResolutions``: the depth camera's (``get_textured_point_cloud`` is the depth
    map's grid in the depth camera's frame, the 2D image mapped onto it; Mech-Mind's samples deproject the depth map
    with these), when the depth map is that size; None otherwise, or when the values are not a camera's (zeros: not
    read from a device).  The distortion coefficients are not kept: the cloud is 3D already."""
    depth = resolutions.depth
    if (int(depth.width), int(depth.height)) != (int(width), int(height)):
        return None
    m = intrinsics.depth.camera_matrix
    try:
        return Intrinsics(int(width), int(height), float(m.fx), float(m.fy), float(m.cx), float(m.cy))
    except ValueError:
        return None


def realsense_capture(color: Any, vertices_m: Any, height: int, width: int, color_format: str = "rgb8") -> Capture:
    """RealSense colour frame data (H, W, 3) and ``points.get_vertices()`` (H·W or H·W×3 float32, metres, 0 where no
    depth, the depth aligned to the colour camera) -> ``Capture`` in mm with NaN."""
    v = np.asarray(vertices_m)
    if v.dtype.names:  # get_vertices() with dims=1: a structured (f0, f1, f2) array
        v = np.stack([v[name] for name in v.dtype.names[:3]], axis=-1)
    if v.size != height * width * 3:
        raise CameraError(f"RealSense: {v.size // 3} points for a {width} × {height} frame (depth not aligned to colour?)")
    cloud = _no_return_to_nan(v.reshape(height, width, 3).astype(np.float32) * np.float32(1000.0))
    if color_format not in ("rgb8", "bgr8"):
        raise CameraError(f"RealSense: colour format {color_format!r}; expected rgb8 or bgr8")
    rgb = np.asarray(color)
    if color_format == "bgr8" and rgb.ndim == 3:
        rgb = rgb[..., ::-1]
    return checked_capture(rgb, cloud, "RealSense")


# ---- the SDKs ----


def import_vendor(extra: str, module: str, what: str) -> Any:
    """``module`` of ``extra``: ``MissingExtra`` (exit 2 with the install hint) when absent, ``CameraError``
    when installed but broken (pyrealsense2 without the system's libusb-1.0, say)."""
    extras.require(extra, what=what)
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        hint = (" (install the system's libusb-1.0: on Debian and Ubuntu apt-get install libusb-1.0-0)"
                if "libusb" in str(exc) else "")
        raise CameraError(f"{what}: {module} is installed but does not import on this machine: {exc}{hint}") from None


MECHEYE_PORT = 5577  # the TCP port Mech-Eye API 2.6 connects to (ZeroMQ; seen with strace: CameraInfo.port is not used)


def _held_output(call: Any, *args: Any) -> tuple[Any, str]:
    """``call(*args)`` with file descriptors 1 and 2 going to a temporary file: its result and what it wrote.

    Mech-Eye API writes its own lines to the terminal (its logger's first-run notes to stdout, "Network request timed
    out ..." and the shell's "ping: not found" to stderr), which would break ``--json``'s stdout and the one-line
    error; it also keeps its own log (/var/log/mmind/eye_api_logs, else under /tmp)."""
    with held_native_output() as held:
        result = call(*args)
    return result, held[0] if held else ""


class MechEyeCamera:
    """A Mech-Eye industrial 3D camera at ``ip`` (the paper's Pro M Enhanced): ``capture``, ``close``.

    ``timeout_s`` bounds the connection: a plain TCP connection to the camera's port first (Mech-Eye API's own
    ``connect`` does not keep to its timeout, module docstring), then the SDK's ``connect``.  ``capture_timeout_s``
    is handed to ``capture_2d_and_3d``."""

    def __init__(self, ip: str, timeout_s: float = 5.0, capture_timeout_s: float = 10.0) -> None:
        self._camera = None
        if not isinstance(ip, str) or not ip.strip():
            raise CameraError(f"Mech-Eye camera address {ip!r} must be an IP address")
        self.ip = ip.strip()
        try:
            ipaddress.IPv4Address(self.ip)
        except ValueError:
            hint = (": Mech-Eye API opens no file (an .mraw is Mech-Eye Viewer's virtual device); replay a capture file "
                    "with --camera replay:FILE" if self.ip.lower().endswith(".mraw") or os.sep in self.ip else "")
            raise CameraError(f"Mech-Eye camera address {self.ip!r} must be an IPv4 address such as 192.168.1.10 "
                              f"(Mech-Eye API takes no host names){hint}") from None
        self.timeout_s = float(timeout_s)
        self.capture_timeout_ms = int(round(capture_timeout_s * 1000))
        self._sdk = import_vendor("mecheye", "mecheye.area_scan_3d_camera", "the Mech-Eye camera")
        self._shared = importlib.import_module("mecheye.shared")
        self._port_answers()
        camera = self._sdk.Camera()
        t0 = time.monotonic()
        status, written = _held_output(camera.connect, self.ip, int(round(self.timeout_s * 1000)))
        if not status.is_ok():
            camera = None  # gone now: a Camera that tried a silent peer and lives on to the interpreter's exit hangs it
            raise CameraError(self._connect_failure(status, time.monotonic() - t0))
        if written.strip():
            print(written.rstrip(), file=sys.stderr)
        self._camera = camera
        self._check(self._camera.set_point_cloud_unit(self._shared.CoordinateUnit_Millimeter), "set_point_cloud_unit(mm)")
        info = self._sdk.CameraInfo()
        self._check(self._camera.get_camera_info(info), "get_camera_info")
        self.serial, self.model_name = str(info.serial_number), str(info.model)
        self.model = mecheye_model(self.model_name)
        self.source = f"mecheye {self.ip} {self.serial}".strip()
        if not self.model:
            self.source += f" ({self.model_name or 'model not reported'}: not a task.camera model)"
        self._intrinsics, self._resolutions = self._sdk.CameraIntrinsics(), self._sdk.CameraResolutions()
        if not (self._camera.get_camera_intrinsics(self._intrinsics).is_ok()
                and self._camera.get_camera_resolutions(self._resolutions).is_ok()):
            self._intrinsics = self._resolutions = None  # the captures then carry no intrinsics

    def _port_answers(self) -> None:
        """``CameraError`` unless something accepts a TCP connection on the camera's port within the timeout."""
        try:
            with socket.create_connection((self.ip, MECHEYE_PORT), timeout=self.timeout_s):
                return
        except TimeoutError:
            reason = f"no answer within {self.timeout_s:g} s"
        except OSError as exc:
            reason = (exc.strerror or str(exc)).lower()
        raise CameraError(f"Mech-Eye camera at {self.ip}: connect failed: nothing accepts a connection on its TCP port "
                          f"{MECHEYE_PORT} ({reason}; timeout {self.timeout_s:g} s): is the camera on, at this address, "
                          "on this PC's network?")

    def _status_text(self, status: Any) -> str:
        code = status.error_code
        names = {getattr(self._shared.ErrorStatus, n): n.removeprefix("MMIND_STATUS_")
                 for n in dir(self._shared.ErrorStatus) if n.startswith("MMIND_")}
        return f"{status.error_description} (SDK code {code} {names.get(code, '')})".replace(" )", ")")

    def _connect_failure(self, status: Any, elapsed: float) -> str:
        hint = ""
        if status.error_code == self._shared.ErrorStatus.MMIND_STATUS_DEVICE_OFFLINE and shutil.which("ping") is None:
            hint = ("; Mech-Eye API judges a camera reachable by running the system's ping, which is not installed "
                    "here (Debian and Ubuntu: apt-get install iputils-ping)")
        return (f"Mech-Eye camera at {self.ip}: connect failed after {elapsed:.1f} s (timeout {self.timeout_s:g} s): "
                f"{self._status_text(status)}{hint}")

    def _check(self, status: Any, what: str) -> None:
        if not status.is_ok():
            self.close()
            raise CameraError(f"Mech-Eye camera at {self.ip}: {what} failed: {self._status_text(status)}")

    def capture(self) -> Capture:
        if self._camera is None:
            raise CameraError(f"Mech-Eye camera at {self.ip}: closed")
        frame = self._sdk.Frame2DAnd3D()
        taken = now_utc()
        status, written = _held_output(self._camera.capture_2d_and_3d, frame, self.capture_timeout_ms)
        self._check(status, f"capture_2d_and_3d (timeout {self.capture_timeout_ms / 1000:g} s)")
        if written.strip():
            print(written.rstrip(), file=sys.stderr)
        cloud = frame.get_textured_point_cloud()
        if cloud.is_empty():
            raise CameraError(f"Mech-Eye camera at {self.ip}: the capture holds no point cloud")
        capture = mecheye_capture(cloud.vertices(), cloud.colors())
        height, width = capture.cloud_mm.shape[:2]
        intrinsics = (mecheye_intrinsics(self._intrinsics, self._resolutions, height, width)
                      if self._intrinsics is not None else None)
        return capture._replace(intrinsics=intrinsics, camera=self.model, source=self.source, time_utc=taken)

    def close(self) -> None:
        camera, self._camera = getattr(self, "_camera", None), None
        if camera is not None:
            _held_output(camera.disconnect)


RECORDING_SUFFIXES = (".db3", ".bag")  # librealsense 2.59 records rosbag2 (.db3) only; its playback also reads ROS1 .bag


def is_recording(address: str) -> bool:
    """Whether a RealSense ``--camera-address`` names a recording rather than a serial number: it ends in .db3 or
    .bag, holds a path separator, or is an existing file (a serial number is digits)."""
    return (address.lower().endswith(RECORDING_SUFFIXES) or os.sep in address
            or (os.altsep is not None and os.altsep in address) or os.path.isfile(address))


def realsense_model(device_name: str) -> str:
    """The ``task.camera`` model of a RealSense device (or recording) by its name: a model named in it (a twin
    recording's), else ``realsense_d435`` unless the name is of another RealSense product ("" then: not known)."""
    for name in camera_models.names():
        if name in device_name:
            return name
    other = re.search(r"\b(D4\d\d|D5\d\d|L5\d\d|SR3\d\d|T26\d)", device_name)
    return "" if other and "D435" not in device_name else "realsense_d435"


def _frame_time_utc(rs: Any, frame: Any) -> str:
    """When ``frame`` was taken, ISO 8601: its own timestamp when that is host time (ms since the epoch), else now."""
    now = datetime.datetime.now(datetime.timezone.utc)
    try:
        host = frame.get_frame_timestamp_domain() in (rs.timestamp_domain.system_time, rs.timestamp_domain.global_time)
        taken = datetime.datetime.fromtimestamp(frame.get_timestamp() / 1000.0, datetime.timezone.utc)
    except (RuntimeError, ValueError, OverflowError, OSError):
        host = False
    when = taken if host and datetime.datetime(2000, 1, 1, tzinfo=datetime.timezone.utc) <= taken <= now + \
        datetime.timedelta(days=1) else now
    return when.isoformat(timespec="milliseconds")


class RealSenseCamera:
    """An Intel RealSense depth camera (``serial``, or the only/first one connected), or a recording of one
    (``serial`` a .db3/.bag file: ``is_recording``): ``capture``, ``close``.

    Either way the frames come through ``rs.pipeline``, the depth is aligned to the colour camera (``rs.align``) and
    the cloud is librealsense's (``rs.pointcloud``).  A recording is played once, paused until the pipeline listens
    and then not in real time (its frame sets come back in order; ``deploy.realsense_record`` measured it): each
    ``capture`` takes the next one that holds depth and colour; past the last, ``CameraError``."""

    def __init__(self, serial: str | None = None, width: int = 1280, height: int = 720, fps: int = 30,
                 timeout_s: float = 5.0) -> None:
        rs = self._rs = import_vendor("realsense", "pyrealsense2", "the RealSense camera")
        self.timeout_ms = int(round(timeout_s * 1000))
        self._pipeline = self._playback = None
        self.file = serial if serial is not None and is_recording(serial) else None
        if self.file is not None:
            config = self._open_recording(rs, self.file)
        else:
            ctx = rs.context()
            found = [d.get_info(rs.camera_info.serial_number) for d in ctx.query_devices()]
            if not found:  # pipeline.start would wait 15 s to say the same
                raise CameraError("RealSense: no camera connected (USB 3 cable, udev rules?)")
            if serial is not None and serial not in found:
                raise CameraError(f"RealSense: no camera with serial {serial}; connected: {', '.join(found)}")
            self.serial = serial or found[0]
            self.name = next(d.get_info(rs.camera_info.name) for d in ctx.query_devices()
                             if d.get_info(rs.camera_info.serial_number) == self.serial)
            self.source = f"realsense {self.serial}"
            config = rs.config()
            config.enable_device(self.serial)
            config.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
            config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
            self._pipeline = rs.pipeline(ctx)
        self.model = realsense_model(self.name)
        try:
            self._pipeline.start(config)
        except RuntimeError as exc:
            self._pipeline = None
            what = f"the recording {self.file}" if self.file else f"{width} × {height} @ {fps} fps depth + colour"
            raise CameraError(f"RealSense {self.serial}: cannot start {what}: {exc}") from None
        if self._playback is not None:
            self._playback.resume()
        self._align = rs.align(rs.stream.color)
        self._pointcloud = rs.pointcloud()

    def _open_recording(self, rs: Any, path: str) -> Any:
        """The pipeline's config for a recording: checked to be one, to hold depth and colour, and set to play every
        frame (not in real time) before the pipeline starts."""
        self.serial = path
        self.source = f"realsense {os.path.abspath(path)}"
        if not os.path.isfile(path):
            raise CameraError(f"RealSense recording {path}: no such file")
        probe = rs.config()  # opening the file on its own: what it is and which streams it holds
        probe.enable_device_from_file(path, repeat_playback=False)
        try:
            held = {s.stream_type() for s in probe.resolve(rs.pipeline_wrapper(rs.pipeline())).get_streams()}
        except RuntimeError as exc:
            reason = str(exc).split("Reason: ", 1)[-1]
            raise CameraError(f"RealSense recording {path}: not a librealsense recording (a .db3 of its recorder or "
                              f"an older ROS1 .bag) that this pyrealsense2 can read: {reason}") from None
        if not {rs.stream.depth, rs.stream.color} <= held:
            names = ", ".join(sorted(str(s).split(".")[-1] for s in held)) or "no stream"
            raise CameraError(f"RealSense recording {path}: needs a depth and a colour stream; it holds {names}")
        config = rs.config()
        config.enable_device_from_file(path, repeat_playback=False)
        config.enable_stream(rs.stream.depth)
        config.enable_stream(rs.stream.color)
        self._pipeline = rs.pipeline()
        try:  # resolved first (pipeline.start then uses this device), so that it plays not in real time from its start
            profile = config.resolve(rs.pipeline_wrapper(self._pipeline))
        except RuntimeError as exc:
            raise CameraError(f"RealSense recording {path}: cannot play its depth and colour: {exc}") from None
        device = profile.get_device()
        self._playback = device.as_playback()
        self._playback.set_real_time(False)  # every frame, as fast as they are read
        self._playback.pause()  # until the pipeline listens (resumed after start): else its first frames may be lost
        self.name = device.get_info(rs.camera_info.name) if device.supports(rs.camera_info.name) else ""
        return config

    def _next_frames(self) -> Any:
        """The next frame set with depth and colour within the timeout (a recording: until its end)."""
        rs = self._rs
        deadline = time.monotonic() + self.timeout_ms / 1000
        ended = 0
        while True:
            ok, frames = self._pipeline.try_wait_for_frames(100)
            if ok and frames.get_depth_frame() and frames.get_color_frame():
                return frames
            if self._playback is not None and self._playback.current_status() == rs.playback_status.stopped:
                ended += 1  # the reader may stop before the last frames are out: look twice more
                if ended > 2:
                    raise CameraError(f"RealSense recording {self.file}: no more frames with depth and colour")
            if time.monotonic() > deadline:
                raise CameraError(f"RealSense {self.serial}: no frames with depth and colour within "
                                  f"{self.timeout_ms / 1000:g} s")

    def capture(self) -> Capture:
        rs = self._rs
        if self._pipeline is None:
            raise CameraError(f"RealSense {self.serial}: closed")
        frames = self._align.process(self._next_frames())
        depth, color = frames.get_depth_frame(), frames.get_color_frame()
        if not depth or not color:
            raise CameraError(f"RealSense {self.serial}: a frame set without depth or colour")
        points = self._pointcloud.calculate(depth)
        fmt = str(color.get_profile().format()).split(".")[-1]
        capture = realsense_capture(np.asanyarray(color.get_data()), np.asanyarray(points.get_vertices(2)),
                                    depth.get_height(), depth.get_width(), color_format=fmt)
        k = color.get_profile().as_video_stream_profile().get_intrinsics()
        try:  # the pinhole part; the distortion is already in the cloud (rs.pointcloud deprojects with it)
            intrinsics = Intrinsics(int(k.width), int(k.height), float(k.fx), float(k.fy), float(k.ppx), float(k.ppy))
        except ValueError as exc:
            raise CameraError(f"RealSense {self.serial}: the colour stream's intrinsics: {exc}") from None
        if (intrinsics.width, intrinsics.height) != (capture.rgb.shape[1], capture.rgb.shape[0]):
            raise CameraError(f"RealSense {self.serial}: colour intrinsics of {k.width} × {k.height} for a "
                              f"{capture.rgb.shape[1]} × {capture.rgb.shape[0]} image")
        return capture._replace(intrinsics=intrinsics, camera=self.model, source=self.source,
                                time_utc=_frame_time_utc(rs, color))

    def close(self) -> None:
        pipeline, self._pipeline = getattr(self, "_pipeline", None), None
        self._playback = None
        if pipeline is not None:
            try:
                pipeline.stop()
            except RuntimeError:  # never started (a refused recording)
                pass


def now_utc() -> str:
    """Now, as a capture's ``time_utc`` (ISO 8601, milliseconds)."""
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="milliseconds")


def capture_once(kind: str, address: str | None = None, robot_q: Any = None) -> Capture:
    """One capture of the ``kind`` camera at ``address`` (opened, captured, closed), with the arm's joints
    ``robot_q`` when they are known; ``source`` and ``time_utc`` filled where the driver left them empty.  The
    ``camera`` model stays the driver's word ("" when it cannot name a known one): never guessed."""
    camera = open_camera(kind, address)
    try:
        capture = camera.capture()
    finally:
        camera.close()
    return capture._replace(robot_q=None if robot_q is None else tuple(float(v) for v in robot_q),
                            source=capture.source or f"{kind} {address or ''}".strip(),
                            time_utc=capture.time_utc or now_utc())


def open_camera(kind: str, address: str | None = None) -> CameraSource:
    """``mecheye`` (``address`` = its IP, required) or ``realsense`` (``address`` = serial or a recording, optional)."""
    if kind == "mecheye":
        if not address:
            raise CameraError("the Mech-Eye camera needs its IP address")
        return MechEyeCamera(address)
    if kind == "realsense":
        return RealSenseCamera(address or None)
    raise CameraError(f"camera {kind!r} is not one of {', '.join(CAMERAS)}")
