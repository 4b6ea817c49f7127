"""The twin's renders as a RealSense recording, so that librealsense itself reads them: no camera needed.

What this is for: the path a real RealSense capture takes — ``rs.pipeline``, ``rs.align`` to the colour camera,
``rs.pointcloud``, ``deploy.cameras.RealSenseCamera`` — run on the twin's renders (``deploy.twin_camera``).
``write_bag`` builds an ``rs.software_device`` (a depth sensor, z16, and a colour sensor, rgb8, on the render's
pixel grid), wraps it in ``rs.recorder`` and feeds it the frames; ``RealSenseCamera(path)`` plays the file back.
``through_librealsense`` does both for one capture (``deploy.rehearse --camera-driver realsense``).

What it is not: a real camera.  No RealSense device has run here.  The frames are the twin's (its optics, its
noise model, ``task.camera``); librealsense only stores, aligns and deprojects them, so the round trip measures
librealsense's share of the pipeline and the adapter's handling of it, not a D435's stereo depth.

Details, each measured with pyrealsense2 2.59.1:

* **The file.** librealsense 2.59's recorder writes rosbag2 (SQLite) files and refuses any name not ending in
  ``.db3``; its playback also reads the older ROS1 ``.bag``.  The images are stored losslessly (depth and colour
  came back bit for bit).
* **Depth.** z16 in ``depth_units`` metres per count (0.001, a D435's default, or 0.0001): the cloud's z rounded
  to the nearest count, 0 (no return) where the cloud is NaN.  A depth beyond the z16 range is refused.  The
  cloud played back lies within half a count of the render's along each ray: on D435 twin renders (consumer
  noise, 320 × 180 and 1280 × 720) at most 0.62 mm (p99 0.56 mm) from it with 1 mm counts, 0.062 mm (p99
  0.056 mm) with 0.1 mm counts; no pixel lost or added.
* **The grid.** The twin's depth already lies on the colour grid (extrinsics identity).  rs.align maps each depth
  pixel's top-left corner onto the colour image and rounds it down (measured: the colour's principal point
  0.001 px right of the depth's makes the mapping exact, 0.01 px left of it moves every pixel).  With the depth
  stream's intrinsics exactly the colour's, float rounding puts some corners just short of their pixel, and the
  aligned depth of a twin render loses whole rows and columns (4.4 % of the points at 320 × 180, 4.3 % at
  1280 × 720, 5.1 % of a Mech-Eye render at 1920 × 1200) and moves others by a pixel (p99 error 7.5-9 mm, at
  depth edges up to 138 mm).  The depth stream therefore declares its principal point ``ALIGN_NUDGE_PX``
  (0.02 px) up and left of the colour's and its focal lengths ``ALIGN_FOV_SHRINK`` (2 ppm) longer, a field of
  view just inside the colour's (else rs.align spreads every depth pixel over two): every depth pixel then lands
  on the colour pixel under it, and the aligned depth is the written one bit for bit.  The cloud is deprojected
  with the colour stream's intrinsics, which are the render's (as float32: exactly for the D435 model's); so are
  the capture's.
* **Timing.** Frames carry host-clock timestamps a frame period (1/30 s) apart from the first frame's
  ``time_utc`` (else now): the pipeline pairs depth and colour by time (frames a second apart came back paired
  with the previous frame's colour).  ``RealSenseCamera`` keeps the playback paused until the pipeline listens and
  then plays it not in real time: 500 of 500 one-frame recordings and 8 of 8 four-frame ones came back whole
  and in order (without the pause, 3 of 200 one-frame playbacks delivered nothing).
"""

from __future__ import annotations

import datetime
import os
import tempfile
import threading
from typing import Any, NamedTuple, Sequence

import numpy as np

from sagrasp_jax.deploy.cameras import Capture, CameraError, import_vendor

DEPTH_UNITS = (0.001, 0.0001)  # m per z16 count: a D400's default (1 mm) and a tenth of it
ALIGN_NUDGE_PX = 0.02  # the depth stream's principal point, up and left of the colour's (module docstring)
ALIGN_FOV_SHRINK = 2e-6  # the depth stream's focal lengths, this fraction longer than the colour's
FPS = 30
DEVICE_NAME = "sagrasp_jax twin render"  # + " of <task.camera model>": RealSenseCamera reads the model from it


class Recorded(NamedTuple):
    """What ``write_bag`` wrote."""

    path: str
    frames: int
    depth_units: float
    width: int
    height: int


def depth_z16(cloud_mm: np.ndarray, depth_units: float) -> np.ndarray:
    """(H, W) uint16 counts of ``depth_units`` m: the cloud's z rounded, 0 where it is NaN or not in front of the
    lens; ``ValueError`` for a depth beyond the z16 range."""
    z = np.asarray(cloud_mm, dtype=np.float64)[..., 2]
    valid = np.isfinite(np.asarray(cloud_mm, dtype=np.float64)).all(axis=-1) & (z > 0)
    counts = np.where(valid, np.rint(np.where(valid, z, 0.0) / (1000.0 * depth_units)), 0.0)
    if counts.max(initial=0.0) > 65535:
        raise ValueError(f"a depth of {np.nanmax(np.where(valid, z, np.nan)):.0f} mm does not fit z16 at {depth_units} m "
                         f"per count (at most {65535 * depth_units:.3f} m); use depth units 0.001")
    return counts.astype(np.uint16)


def _intrinsics(rs: Any, k: Any, nudge: float = 0.0, shrink: float = 0.0) -> Any:
    out = rs.intrinsics()
    out.width, out.height = int(k.width), int(k.height)
    out.fx, out.fy = float(k.fx) * (1 + shrink), float(k.fy) * (1 + shrink)
    out.ppx, out.ppy = float(k.cx) - nudge, float(k.cy) - nudge
    out.model, out.coeffs = rs.distortion.none, [0.0] * 5
    return out


def _host_ms(time_utc: str) -> float | None:
    try:
        return datetime.datetime.fromisoformat(time_utc).timestamp() * 1000.0 if time_utc else None
    except ValueError:
        return None


def write_bag(path: str, frames: Sequence[Any], depth_units: float = 0.001, camera: str = "",
              serial: str = "twin") -> Recorded:
    """Record ``frames`` (each with ``rgb`` (H, W, 3) uint8, ``cloud_mm`` (H, W, 3) mm with NaN and ``intrinsics``, a
    ``task.camera.Intrinsics``: a ``twin_camera.Frame`` or a ``cameras.Capture``; all on one grid) as a librealsense
    recording at ``path`` (``.db3``): a software device's depth (z16) and colour (rgb8) streams through
    ``rs.recorder``.  ``camera`` (a ``task.camera`` model name; default a ``Capture``'s own) goes into the device
    name.  ``ValueError`` for frames it cannot record; ``CameraError`` when pyrealsense2 does not import."""
    rs = import_vendor("realsense", "pyrealsense2", "the RealSense recording")
    if depth_units not in DEPTH_UNITS:
        raise ValueError(f"depth units {depth_units} m: one of {', '.join(str(u) for u in DEPTH_UNITS)}")
    if not str(path).endswith(".db3"):
        raise ValueError(f"{path}: librealsense's recorder writes rosbag2 files, whose names must end in .db3")
    if not frames:
        raise ValueError("no frames to record")
    k = frames[0].intrinsics
    if k is None:
        raise ValueError("the frames need their intrinsics (the twin's Frame or Capture carries them)")
    images = []
    for i, f in enumerate(frames):
        rgb, cloud = np.asarray(f.rgb), np.asarray(f.cloud_mm)
        if f.intrinsics != k:
            raise ValueError(f"frame {i}: intrinsics {f.intrinsics} differ from the first frame's {k}")
        if rgb.shape != (k.height, k.width, 3) or rgb.dtype != np.uint8 or cloud.shape != rgb.shape:
            raise ValueError(f"frame {i}: rgb {rgb.shape} {rgb.dtype} and cloud {cloud.shape} for a {k.width} × "
                             f"{k.height} grid (expected (H, W, 3) uint8 and (H, W, 3))")
        images.append((np.ascontiguousarray(depth_z16(cloud, depth_units)), np.ascontiguousarray(rgb),
                       _host_ms(getattr(f, "time_utc", ""))))
    camera = camera or getattr(frames[0], "camera", "") or ""
    if os.path.exists(path):
        os.remove(path)  # the recorder appends to nothing: an old file would be refused by its SQLite storage
    _record(rs, path, images, k, depth_units, f"{DEVICE_NAME} of {camera}" if camera else DEVICE_NAME, serial)
    return Recorded(str(path), len(images), depth_units, k.width, k.height)


def _record(rs: Any, path: str, images: list[tuple[np.ndarray, np.ndarray, float | None]], k: Any,
            depth_units: float, name: str, serial: str) -> None:
    """The software device, recorded; the recorder closes the file when its last reference goes, at this return."""
    device = rs.software_device()
    device.register_info(rs.camera_info.name, name)
    device.register_info(rs.camera_info.serial_number, serial)
    depth_sensor, colour_sensor = device.add_sensor("Stereo Module"), device.add_sensor("RGB Camera")
    stream = rs.video_stream()
    stream.type, stream.index, stream.uid, stream.width, stream.height = rs.stream.depth, 0, 0, k.width, k.height
    stream.fps, stream.bpp, stream.fmt = FPS, 2, rs.format.z16
    stream.intrinsics = _intrinsics(rs, k, ALIGN_NUDGE_PX, ALIGN_FOV_SHRINK)
    depth_profile = depth_sensor.add_video_stream(stream).as_video_stream_profile()
    depth_sensor.add_read_only_option(rs.option.depth_units, depth_units)
    stream = rs.video_stream()
    stream.type, stream.index, stream.uid, stream.width, stream.height = rs.stream.color, 0, 1, k.width, k.height
    stream.fps, stream.bpp, stream.fmt, stream.intrinsics = FPS, 3, rs.format.rgb8, _intrinsics(rs, k)
    colour_profile = colour_sensor.add_video_stream(stream).as_video_stream_profile()
    identity = rs.extrinsics()
    identity.rotation, identity.translation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0]
    depth_profile.register_extrinsics_to(colour_profile, identity)

    recorder = rs.recorder(path, device)
    sensors = recorder.query_sensors()  # the recorder's wrappers of the two sensors: what streams through them is written
    delivered, lock, done = [0], threading.Lock(), threading.Event()

    def arrived(_frame: Any) -> None:  # a frame is written before it reaches the user's callback
        with lock:
            delivered[0] += 1
            if delivered[0] == 2 * len(images):
                done.set()

    for sensor in sensors:
        sensor.open(sensor.get_stream_profiles()[0])
        sensor.start(arrived)
    try:
        start_ms = images[0][2] if images[0][2] is not None else \
            datetime.datetime.now(datetime.timezone.utc).timestamp() * 1000.0
        for i, (depth, rgb, _) in enumerate(images):
            stamp = start_ms + i * 1000.0 / FPS  # a frame period apart: the pipeline pairs depth and colour by time
            for sensor, profile, pixels, bpp in ((depth_sensor, depth_profile, depth, 2),
                                                 (colour_sensor, colour_profile, rgb, 3)):
                frame = rs.software_video_frame()
                frame.pixels, frame.bpp, frame.stride, frame.timestamp = pixels, bpp, k.width * bpp, stamp
                frame.domain, frame.frame_number, frame.profile = rs.timestamp_domain.system_time, i + 1, profile
                if bpp == 2:
                    frame.depth_units = depth_units
                sensor.on_video_frame(frame)
        if not done.wait(10.0):
            raise CameraError(f"{path}: librealsense's recorder took {delivered[0]} of {2 * len(images)} frames")
    finally:
        for sensor in sensors:
            sensor.stop()
            sensor.close()


def through_librealsense(capture: Capture, depth_units: float = 0.001, folder: str | None = None) -> Capture:
    """``capture`` (a twin capture) written as a one-frame recording and read back through
    ``cameras.RealSenseCamera``: what librealsense makes of it (the cloud from rs.align and rs.pointcloud, the
    intrinsics from the colour stream), with the twin's ``truth`` and ``time_utc`` kept and ``source`` saying so.
    The recording goes in a temporary folder (or ``folder``) and is removed."""
    from sagrasp_jax.deploy.cameras import RealSenseCamera

    with tempfile.TemporaryDirectory(prefix="realsense-", dir=folder) as tmp:
        path = os.path.join(tmp, "capture.db3")
        write_bag(path, [capture], depth_units=depth_units)
        camera = RealSenseCamera(path)
        try:
            seen = camera.capture()
        finally:
            camera.close()
    source = f"{capture.source} through librealsense" if capture.source else "through librealsense"
    return seen._replace(camera=capture.camera or seen.camera, source=source, time_utc=capture.time_utc or seen.time_utc,
                         truth=capture.truth)


def cloud_error_mm(reference: np.ndarray, cloud: np.ndarray) -> dict[str, float]:
    """How far ``cloud`` lies from ``reference`` (both (H, W, 3) mm with NaN): max and p99 of the point distance over
    the pixels valid in both, and the pixels valid in only one of them."""
    a, b = np.asarray(reference, dtype=np.float64), np.asarray(cloud, dtype=np.float64)
    va, vb = np.isfinite(a).all(axis=-1), np.isfinite(b).all(axis=-1)
    both = va & vb
    d = np.linalg.norm(a[both] - b[both], axis=-1) if both.any() else np.zeros(1)
    return {"max_mm": float(d.max()), "p99_mm": float(np.percentile(d, 99)), "points": int(both.sum()),
            "lost": int((va & ~vb).sum()), "added": int((vb & ~va).sum())}
