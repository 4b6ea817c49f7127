"""Transfer errors a deployment rehearsal simulates: latency, servo lag and gains, joint offsets and noise.

Plain data, no PyBullet and no jax: the deploy CLI validates these before a twin exists.  ``draw`` takes one
episode's errors from an ``env.randomize`` section with the distributions the MJX env draws them from
(``grasp_env.GraspEnv._draw_randomization``), so a named evaluation condition means the same errors on the twin.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sagrasp_jax.task.config import RandomizeConfig
from sagrasp_jax.task import robots

MAX_TWIN_LATENCY = 10.0  # control steps
SERVO_GAIN_RANGE = (0.1, 2.0)  # factor on the fitted servo model's gain
MAX_JOINT_OFFSET = 0.2  # rad: env.randomize.joint_offset's range
MAX_JOINT_NOISE = 0.2  # rad


def _per_joint(value: Any, what: str, dof: int) -> tuple[float, ...]:
    v = np.broadcast_to(np.asarray(value, dtype=float), (dof,)) if np.ndim(value) == 0 else np.asarray(value, float)
    if v.shape != (dof,) or not np.isfinite(v).all():
        raise ValueError(f"twin {what} must be one number or {dof} finite numbers (one per joint), got {value!r}")
    return tuple(float(x) for x in v)


@dataclass(frozen=True)
class TransferErrors:
    """How a simulated arm (the twin) departs from an exact one during the approach (all off by default).

    The MJX env's transfer knobs, one episode's values: the servos track commands in their own frame, the
    joint readings are off by ``joint_offset`` and noisy, commands arrive ``latency`` control steps late.
    """

    latency: float = 0.0  # control steps between a command and its execution (whole steps queue, the fraction blends)
    servo_lag: bool = False  # joints follow commands through the fitted servo model instead of reaching them at once
    servo_gain: Any = 1.0  # the servo model's per-step gain is scaled by this (one factor, or one per joint): a gain error
    joint_offset: Any = 0.0  # rad added to every joint reading (one value or one per joint): a calibration error
    joint_noise: float = 0.0  # rad, std of the Gaussian noise on every joint reading
    dof: int = robots.DEFAULT_DOF  # joints of the arm these errors are for (the twin's robot.dof; checked there)
    servo_gains: tuple[float, ...] = field(init=False, repr=False)
    offsets: tuple[float, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not (0.0 <= float(self.latency) <= MAX_TWIN_LATENCY):
            raise ValueError(f"twin latency {self.latency} must be in [0, {MAX_TWIN_LATENCY}] control steps")
        gains = _per_joint(self.servo_gain, "servo gain factor", self.dof)
        lo, hi = SERVO_GAIN_RANGE
        if not all(lo <= g <= hi for g in gains):
            raise ValueError(f"twin servo gain factor {self.servo_gain} must be in [{lo}, {hi}] (each joint)")
        offsets = _per_joint(self.joint_offset, "joint offset", self.dof)
        if not all(abs(o) <= MAX_JOINT_OFFSET for o in offsets):
            raise ValueError(f"twin joint offset {self.joint_offset} rad must be within ±{MAX_JOINT_OFFSET} (each joint)")
        if not (np.isfinite(self.joint_noise) and 0.0 <= float(self.joint_noise) <= MAX_JOINT_NOISE):
            raise ValueError(f"twin joint noise {self.joint_noise} rad must be in [0, {MAX_JOINT_NOISE}]")
        object.__setattr__(self, "servo_gains", gains)
        object.__setattr__(self, "offsets", offsets)

    @property
    def any(self) -> bool:
        return bool(self.latency or self.servo_lag or any(self.offsets) or self.joint_noise)


def draw(randomize: RandomizeConfig, servo_lag: bool, rng: np.random.Generator,
         dof: int = robots.DEFAULT_DOF) -> tuple[TransferErrors, np.ndarray]:
    """One episode's transfer errors and detection error (m, (3,)) from ``randomize``, as the MJX env draws them:
    gain factors 1 ± U(servo_gain) per joint, latency U(0, latency), offsets U(±joint_offset) per joint, a noise
    std U(0, joint_noise), a detection error U(±target_error) per axis.  ``servo_lag`` is the control mode's
    (the MJX servos lag in every mode but ``kinematic``); ``dof`` is the arm's joint count (``robot.dof``)."""
    r = randomize
    u = lambda shape, half: half * rng.uniform(-1.0, 1.0, shape)  # noqa: E731
    errors = TransferErrors(
        latency=float(r.latency * rng.uniform()),
        servo_lag=servo_lag,
        servo_gain=tuple(1.0 + u(dof, r.servo_gain)),
        joint_offset=tuple(u(dof, r.joint_offset)),
        joint_noise=float(r.joint_noise * rng.uniform()),
        dof=dof,
    )
    return errors, u(3, r.target_error)
