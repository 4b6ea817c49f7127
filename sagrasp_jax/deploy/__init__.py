"""Deployment on the real AUBO-i5 or its PyBullet twin, without JAX (docs/task.md §5).

``calibration`` maps camera detections to the robot base frame and refuses targets outside
the trained region; ``safety`` refuses dangerous joint commands; ``loop`` runs the exported
policy in closed loop through a ``RobotInterface``; ``twin`` is the PyBullet backend
(imported on first use, so the rest works where PyBullet is not installed).
"""

from __future__ import annotations

from typing import Any

from sagrasp_jax.deploy.calibration import CalibrationError, CameraCalibration, TargetRejected
from sagrasp_jax.deploy.loop import (
    DeployError,
    DeployReport,
    Obstacle,
    RobotInterface,
    build_observation,
    run_episode,
    scene_spec,
    send_checked,
)
from sagrasp_jax.deploy.safety import SafetyLayer, SafetyViolation, WorkspaceBox

__all__ = [
    "CalibrationError",
    "CameraCalibration",
    "DeployError",
    "DeployReport",
    "Obstacle",
    "PyBulletTwin",
    "RobotInterface",
    "SafetyLayer",
    "SafetyViolation",
    "TargetRejected",
    "WorkspaceBox",
    "build_observation",
    "run_episode",
    "scene_spec",
    "send_checked",
]


def __getattr__(name: str) -> Any:
    if name == "PyBulletTwin":
        from sagrasp_jax.deploy.twin import PyBulletTwin

        return PyBulletTwin
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
