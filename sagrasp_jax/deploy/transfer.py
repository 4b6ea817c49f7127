"""Transfer errors a deployment rehearsal simulates: command latency and servo lag (``--twin-*`` flags).

Plain data, no PyBullet and no jax: the deploy CLI validates these before a twin exists.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TransferErrors:
    """How a simulated arm (the twin) departs from exact tracking before the gripper closes (all off by default)."""

    latency: float = 0.0  # control steps between a command and its execution (whole steps queue, the fraction blends)
    servo_lag: bool = False  # joints follow commands through the fitted servo model instead of reaching them at once
    servo_gain: float = 1.0  # the servo model's per-step gain is scaled by this (servo_lag only): a gain error

    def __post_init__(self) -> None:
        if not (0.0 <= self.latency <= MAX_TWIN_LATENCY):
            raise ValueError(f"twin latency {self.latency} must be in [0, {MAX_TWIN_LATENCY}] control steps")
        if not (0.1 <= self.servo_gain <= 2.0):
            raise ValueError(f"twin servo gain factor {self.servo_gain} must be in [0.1, 2]")


MAX_TWIN_LATENCY = 10.0  # control steps
