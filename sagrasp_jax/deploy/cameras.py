"""Real depth cameras as perception sources: the paper's Mech-Eye and Intel RealSense, through the vendors' SDKs.

A ``CameraSource`` has ``capture() -> Capture(rgb, cloud_mm)`` and ``close()``: ``rgb`` (H, W, 3) uint8 and
``cloud_mm`` (H, W, 3) float32, the organized point cloud in the camera frame (x right, y down, z along the
optical axis, OpenCV's and both vendors' convention), millimetres, NaN where there is no return, the same
pixel grid as the image — what ``deploy.twin_camera`` renders and ``deploy.perception`` reads.

* ``MechEyeCamera(ip)`` (``pip install "sagrasp_jax[mecheye]"``, Mech-Mind's ``mecheyeapi``): one
  ``Camera.capture_2d_and_3d`` per capture, read through ``Frame2DAnd3D.get_textured_point_cloud`` (the 2D
  image mapped onto the depth grid): its ``vertices()`` are in mm (the SDK's default unit, set explicitly
  with ``set_point_cloud_unit``) with NaN where invalid, its ``colors()`` BGR.
* ``RealSenseCamera(serial=None)`` (``pip install "sagrasp_jax[realsense]"``, Intel's ``pyrealsense2``; on
  Linux it also needs the system's libusb-1.0): depth and colour streams, the depth aligned to the colour
  camera (``rs.align``), the cloud from ``rs.pointcloud`` (librealsense's own deprojection, with the
  camera's intrinsics and distortion) in metres, 0 where there is no depth: converted to mm and NaN.

The conversions from the SDKs' arrays (``mecheye_capture``, ``realsense_capture``) are pure NumPy, tested on
the SDKs' real frame objects built without a device (a Mech-Eye ``TexturedPointCloud`` filled by hand, a
RealSense software device's depth frame through ``rs.pointcloud``).  Neither camera class has run against
a real camera here.  Every capture has a timeout; a camera that is absent or does not answer raises
``CameraError`` naming it (deploy exits 2: nothing moved).
"""

from __future__ import annotations

import importlib
from typing import Any, NamedTuple, Protocol, runtime_checkable

import numpy as np

from sagrasp_jax.base import extras
from sagrasp_jax.task.camera import Intrinsics

CAMERAS = ("mecheye", "realsense")


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
        hint = " (install the system's libusb-1.0, e.g. apt install libusb-1.0-0)" if "libusb" in str(exc) else ""
        raise CameraError(f"{what}: {module} is installed but does not import on this machine: {exc}{hint}") from None


class MechEyeCamera:
    """A Mech-Eye industrial 3D camera at ``ip`` (the paper's Pro M Enhanced): ``capture``, ``close``."""

    def __init__(self, ip: str, timeout_s: float = 5.0, capture_timeout_s: float = 10.0) -> None:
        if not isinstance(ip, str) or not ip.strip():
            raise CameraError(f"Mech-Eye camera address {ip!r} must be an IP address")
        self.ip = ip.strip()
        self.capture_timeout_ms = int(round(capture_timeout_s * 1000))
        self._sdk = import_vendor("mecheye", "mecheye.area_scan_3d_camera", "the Mech-Eye camera")
        self._shared = importlib.import_module("mecheye.shared")
        self._camera = self._sdk.Camera()
        self._check(self._camera.connect(self.ip, int(round(timeout_s * 1000))), f"connect (timeout {timeout_s:g} s)",
                    connected=False)
        self._check(self._camera.set_point_cloud_unit(self._shared.CoordinateUnit_Millimeter), "set_point_cloud_unit(mm)")

    def _check(self, status: Any, what: str, connected: bool = True) -> None:
        if not status.is_ok():
            if connected:
                self.close()
            raise CameraError(f"Mech-Eye camera at {self.ip}: {what} failed: {status.error_description} "
                              f"(code {status.error_code})")

    def capture(self) -> Capture:
        frame = self._sdk.Frame2DAnd3D()
        self._check(self._camera.capture_2d_and_3d(frame, self.capture_timeout_ms),
                    f"capture_2d_and_3d (timeout {self.capture_timeout_ms / 1000:g} s)")
        cloud = frame.get_textured_point_cloud()
        if cloud.is_empty():
            raise CameraError(f"Mech-Eye camera at {self.ip}: the capture holds no point cloud")
        return mecheye_capture(cloud.vertices(), cloud.colors())

    def close(self) -> None:
        camera, self._camera = getattr(self, "_camera", None), None
        if camera is not None:
            camera.disconnect()


class RealSenseCamera:
    """An Intel RealSense depth camera (``serial``, or the only/first one connected): ``capture``, ``close``."""

    def __init__(self, serial: str | None = None, width: int = 1280, height: int = 720, fps: int = 30,
                 timeout_s: float = 5.0) -> None:
        rs = self._rs = import_vendor("realsense", "pyrealsense2", "the RealSense camera")
        self.timeout_ms = int(round(timeout_s * 1000))
        ctx = rs.context()
        found = [d.get_info(rs.camera_info.serial_number) for d in ctx.query_devices()]
        if not found:  # pipeline.start would wait 15 s to say the same
            raise CameraError("RealSense: no camera connected (USB 3 cable, udev rules?)")
        if serial is not None and serial not in found:
            raise CameraError(f"RealSense: no camera with serial {serial}; connected: {', '.join(found)}")
        self.serial = serial or found[0]
        config = rs.config()
        config.enable_device(self.serial)
        config.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
        config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
        self._pipeline = rs.pipeline(ctx)
        try:
            self._pipeline.start(config)
        except RuntimeError as exc:
            self._pipeline = None
            raise CameraError(f"RealSense {self.serial}: cannot start {width} × {height} @ {fps} fps depth + colour: "
                              f"{exc}") from None
        self._align = rs.align(rs.stream.color)
        self._pointcloud = rs.pointcloud()

    def capture(self) -> Capture:
        if self._pipeline is None:
            raise CameraError(f"RealSense {self.serial}: closed")
        try:
            frames = self._align.process(self._pipeline.wait_for_frames(self.timeout_ms))
        except RuntimeError as exc:
            raise CameraError(f"RealSense {self.serial}: no frames within {self.timeout_ms / 1000:g} s: {exc}") from None
        depth, color = frames.get_depth_frame(), frames.get_color_frame()
        if not depth or not color:
            raise CameraError(f"RealSense {self.serial}: a frame set without depth or colour")
        points = self._pointcloud.calculate(depth)
        return realsense_capture(np.asanyarray(color.get_data()), np.asanyarray(points.get_vertices(2)),
                                 depth.get_height(), depth.get_width())

    def close(self) -> None:
        pipeline, self._pipeline = getattr(self, "_pipeline", None), None
        if pipeline is not None:
            pipeline.stop()


def open_camera(kind: str, address: str | None = None) -> CameraSource:
    """``mecheye`` (``address`` = its IP, required) or ``realsense`` (``address`` = serial, optional)."""
    if kind == "mecheye":
        if not address:
            raise CameraError("the Mech-Eye camera needs its IP address")
        return MechEyeCamera(address)
    if kind == "realsense":
        return RealSenseCamera(address or None)
    raise CameraError(f"camera {kind!r} is not one of {', '.join(CAMERAS)}")
