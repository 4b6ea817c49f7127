"""The paper's YOLO step as an option: a 2-D detector whose boxes feed ``deploy.perception``.

The paper's pipeline: YOLO marks the target (and obstacles) in the 2-D image, the point cloud turns the
box's centre pixel into a camera point.  ``YoloDetector`` (``pip install "sagrasp_jax[yolo]"``,
Ultralytics YOLO) returns ``perception.Detection`` boxes labelled with ``CLASSES`` (the names the
dataset generator ``python -m sagrasp_jax.deploy.yolo_dataset`` writes); ``detect_with_yolo`` hands them
to ``perception.detect_scene``, where the target box chooses the cube's region in place of the colour
test and the geometry then measures it (top-face centre and yaw), and ``perception.point_at_pixel``
is the paper's own pixel -> camera point.

No weights ship with the project: train them on the generator's images, e.g. from scratch
``yolo detect train data=DIR/dataset.yaml model=yolov8n.yaml imgsz=480 epochs=100`` (Ultralytics' CLI;
``model=yolov8n.pt`` starts from Ultralytics' pretrained weights, which it downloads), then
``YoloDetector("runs/detect/train/weights/best.pt")``.  Ultralytics wants numpy images in BGR order;
the detector converts the camera's RGB.  Only this module's ``YoloDetector`` imports ultralytics.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from sagrasp_jax.base import extras
from sagrasp_jax.task import shapes
from sagrasp_jax.deploy.calibration import CameraCalibration
from sagrasp_jax.deploy.perception import Detection, PerceptionError, SceneDetection, detect_scene

def classes() -> tuple[str, ...]:
    """The dataset's labels, class id = index: the cube, then every registered obstacle kind (``shapes.NAMES``,
    read now: a kind registered after import is a class too)."""
    return ("target", *shapes.NAMES)


def __getattr__(name: str) -> Any:
    if name == "CLASSES":  # the old constant, kept live: ``classes()``
        return classes()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def detections_from_arrays(xyxy: Any, cls: Any, conf: Any, names: Mapping[int, str] | Sequence[str]) -> list[Detection]:
    """Detector output arrays (N, 4) pixel boxes, (N,) class ids, (N,) scores -> ``Detection``s."""
    boxes = np.asarray(xyxy, dtype=float).reshape(-1, 4)
    ids = np.asarray(cls).reshape(-1).astype(int)
    scores = np.asarray(conf, dtype=float).reshape(-1)
    if not len(boxes) == len(ids) == len(scores):
        raise PerceptionError(f"detector output of unequal lengths: {len(boxes)} boxes, {len(ids)} classes, {len(scores)} scores")
    lookup = dict(names) if isinstance(names, Mapping) else dict(enumerate(names))
    unknown = sorted({int(i) for i in ids if int(i) not in lookup})
    if unknown:
        raise PerceptionError(f"detector class id(s) {unknown} have no name (known: {lookup})")
    return [Detection(str(lookup[int(i)]), tuple(float(v) for v in b), float(s)) for b, i, s in zip(boxes, ids, scores)]


class YoloDetector:
    """An Ultralytics YOLO model as a ``perception`` detector: ``detector(rgb) -> list[Detection]``."""

    def __init__(self, weights: str, conf: float = 0.25, imgsz: int | None = None, device: str = "cpu") -> None:
        extras.require("yolo", what="the YOLO detector")
        from ultralytics import YOLO

        self.model = YOLO(weights)
        self.conf, self.imgsz, self.device = float(conf), imgsz, device

    def __call__(self, rgb: Any) -> list[Detection]:
        image = np.asarray(rgb)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise PerceptionError(f"YOLO needs an (H, W, 3) uint8 RGB image, got {image.shape} {image.dtype}")
        kwargs: dict[str, Any] = {"conf": self.conf, "verbose": False, "device": self.device}
        if self.imgsz is not None:
            kwargs["imgsz"] = self.imgsz
        result = self.model.predict(source=np.ascontiguousarray(image[..., ::-1]), **kwargs)[0]  # Ultralytics: BGR
        boxes = result.boxes
        return detections_from_arrays(boxes.xyxy.cpu().numpy(), boxes.cls.cpu().numpy(), boxes.conf.cpu().numpy(),
                                      result.names)


def detect_with_yolo(detector: Any, cloud_mm: Any, rgb: Any, calibration: CameraCalibration | None = None,
                     **kwargs: Any) -> SceneDetection:
    """``perception.detect_scene`` with the detector's target boxes choosing the cube (one box: one cube;
    none: "no cube found"; two on different regions: "two cube candidates")."""
    return detect_scene(cloud_mm, rgb, calibration, detections=detector(rgb), **kwargs)
