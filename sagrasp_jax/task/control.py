"""One control step (docs/task.md §2 steps 1-4), written once for every backend.

The MJX env, the PyBullet reference env and the deployment runtime all turn a
policy action into a new joint target through ``control_step``; keeping a single
implementation is what makes their trajectories comparable step for step.  Every
function takes the array module first (``xp`` = numpy or jax.numpy), uses no
Python control flow on array values (only on config constants), and broadcasts
over leading batch dimensions of the joint vectors.  This module must not import
jax: the deployment runtime runs without it.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from sagrasp_jax.task.config import ControlConfig
from sagrasp_jax.task.robot import RobotModel, forward_kinematics, tilt

# The action has one joint-target increment per arm joint (docs/task.md §2 step 1): its size is the robot's
# ``RobotModel.dof``.  The two wrist joints that the fine-tuning corrects are the robot's
# ``spec.fine_tune_joints`` (the AUBO-i5's: docs/task.md §2 step 3's "joints 4 and 5").


def joint_limits(robot: RobotModel, cfg: ControlConfig) -> tuple[Any, Any]:
    """Lower and upper joint-target limits (dof,): the URDF's, inside ±``cfg.q_limit``."""
    return np.maximum(robot.q_lower, -cfg.q_limit), np.minimum(robot.q_upper, cfg.q_limit)


class ControlResult(NamedTuple):
    """What one control step did; the flags and correction feed the episode metrics."""

    q_target: Any  # (..., dof) new accumulated joint target, inside the joint limits
    dq: Any  # (..., dof) joint increment applied to the target (before the limit clip)
    slowed: Any  # (...,) bool: proximity deceleration was applied
    finetuned: Any  # (...,) bool: vertical-alignment correction was applied
    correction: Any  # (..., 2) Δq_c added to the fine-tune joints (zeros when inactive)


def gripper_state(xp: Any, robot: RobotModel, q: Any) -> tuple[Any, Any]:
    """Gripper centre (..., 3) and tilt θgz (..., rad) at ``q``: the two quantities the
    control gates and the success test look at."""
    kin = forward_kinematics(xp, robot, q)
    return kin.gripper_centre, tilt(xp, kin.approach_axis)


def alignment_correction(xp: Any, cfg: ControlConfig, joint_axes: Any, approach_axis: Any) -> Any:
    """Clipped damped-least-squares wrist step Δq_c (..., 2) that turns the approach axis toward −z.

    ``joint_axes`` (..., 2, 3) are the world axes of joints 4 and 5 (the rows of Aᵀ).
    ω = z_g × (−e_z) is the angular velocity that rotates z_g onto −z; the 2×2 damped
    normal equations are solved in closed form so that NumPy and JAX batch alike.
    The clip to ±c keeps the wrist (and thus the gripper centre) from jumping: a full
    least-squares step would move the gripper by several centimetres.
    """
    z_g = approach_axis
    down = xp.zeros_like(z_g) - xp.asarray([0.0, 0.0, 1.0], dtype=z_g.dtype)
    omega = xp.cross(z_g, down)
    a4, a5 = joint_axes[..., 0, :], joint_axes[..., 1, :]
    lam2 = cfg.fine_damping**2
    m11 = xp.sum(a4 * a4, axis=-1) + lam2
    m22 = xp.sum(a5 * a5, axis=-1) + lam2
    m12 = xp.sum(a4 * a5, axis=-1)
    b1 = xp.sum(a4 * omega, axis=-1)
    b2 = xp.sum(a5 * omega, axis=-1)
    det = m11 * m22 - m12 * m12  # ≥ λ⁴ > 0 thanks to the damping
    x1 = (m22 * b1 - m12 * b2) / det
    x2 = (m11 * b2 - m12 * b1) / det
    raw = cfg.fine_gain * xp.stack([x1, x2], axis=-1)
    return xp.clip(raw, -cfg.fine_clip, cfg.fine_clip)


def control_step(
    xp: Any,
    robot: RobotModel,
    cfg: ControlConfig,
    q_target: Any,
    q_now: Any,
    target_pos: Any,
    action: Any,
) -> ControlResult:
    """docs/task.md §2 steps 1-4: action → Δq → slow-down → wrist fine-tuning → clipped new target.

    The gates (distance, tilt) are measured at the measured joints ``q_now`` before the
    move, so a policy cannot dodge them by the step it is taking.  ``q_target``
    accumulates and is never re-based on ``q_now`` (the real controller tracks targets).
    Order matters and follows docs/task.md §2.1: the correction is added to the already slowed
    Δq, then joints 4 and 5 are re-capped at ±q_max so the per-step joint limit is hard.
    """
    q_target = xp.asarray(q_target)
    q_now = xp.asarray(q_now)
    action = xp.asarray(action)
    kin = forward_kinematics(xp, robot, q_now)
    dist = xp.linalg.norm(kin.gripper_centre - xp.asarray(target_pos), axis=-1)
    no_flag = xp.zeros(dist.shape, dtype=bool)

    dq = xp.clip(action, -1.0, 1.0) * cfg.q_max

    if cfg.slowdown_enabled:
        slowed = dist < cfg.d_slow
        dq = dq * xp.where(slowed, cfg.slow_factor, 1.0).astype(dq.dtype)[..., None]
    else:
        slowed = no_flag

    lo, hi = robot.spec.fine_tune_joints[0], robot.spec.fine_tune_joints[1] + 1
    if cfg.finetune_enabled:
        theta = tilt(xp, kin.approach_axis)
        finetuned = (dist < cfg.d_fine) & (theta > math.radians(cfg.fine_tilt_deg))
        axes = kin.joint_axes[..., lo:hi, :]
        correction = alignment_correction(xp, cfg, axes, kin.approach_axis)
        correction = xp.where(finetuned[..., None], correction, 0.0)
        wrist = xp.clip(dq[..., lo:hi] + correction, -cfg.q_max, cfg.q_max)
        dq = xp.concatenate([dq[..., :lo], wrist, dq[..., hi:]], axis=-1)
    else:
        finetuned = no_flag
        correction = xp.zeros(dist.shape + (hi - lo,), dtype=dq.dtype)

    q_lo, q_hi = joint_limits(robot, cfg)
    new_target = xp.clip(q_target + dq, xp.asarray(q_lo, dtype=dq.dtype), xp.asarray(q_hi, dtype=dq.dtype))
    return ControlResult(
        q_target=new_target,
        dq=dq,
        slowed=slowed,
        finetuned=finetuned,
        correction=correction,
    )


# -- servo lag and command latency (the "lagged" mode, the dynamic mode's latency, the deployment twin) --------


def latency_queue_size(max_latency: float) -> int:
    """Commands to keep for a command latency of up to ``max_latency`` control steps (0 = no queue): the
    whole steps of delay, the command they select and the one before it."""
    return int(math.floor(max_latency)) + 2 if max_latency > 0 else 0


def delayed_commands(xp: Any, queue: Any, latency: Any) -> tuple[Any, Any, Any]:
    """For a latency of ``n + f`` control steps (0 ≤ f < 1) and ``queue`` (K, dof) of commands, newest first:
    the command ``n`` steps old (tracked for the last 1 − f of the control period), the one before it (held
    for the first f of it) and f.  ``latency`` must stay below K − 1 (``latency_queue_size``)."""
    whole = xp.floor(latency)
    n = whole.astype(xp.int32) if hasattr(whole, "astype") else int(whole)
    return queue[n], queue[n + 1], latency - whole


def held_command_weight(xp: Any, fraction: Any, gain: Any) -> Any:
    """The weight of the older command in the per-step servo model when it is held for the first ``fraction``
    of the control period and the newer one for the rest: for a servo that closes ``gain`` of its error per
    period (exponentially in time), w = 1 − (1 − (1 − gain)^(1 − fraction)) / gain — 0 at fraction 0, 1 at 1,
    and below ``fraction`` in between (a late step still moves the joint most of the way)."""
    gain = xp.clip(gain, 1e-6, 1.0 - 1e-6)
    return 1.0 - (1.0 - (1.0 - gain) ** (1.0 - fraction)) / gain


def servo_model_step(xp: Any, robot: RobotModel, cfg: ControlConfig, q: Any, q_prev: Any, command: Any,
                     gain: Any) -> Any:
    """The lagged mode's servos over one control period: each joint closes ``gain`` (per joint; normally
    ``cfg.lag_gain``) of its distance to ``command`` and carries ``cfg.lag_momentum`` of its last step's
    motion ``q − q_prev`` — a least-squares fit of the dynamic mode's MJX servos
    (python -m experiments.robot_grade servo-fit) — inside the joint limits (``joint_limits``)."""
    momentum = xp.asarray(cfg.lag_momentum, dtype=q.dtype)
    q_next = q + gain * (command - q) + momentum * (q - q_prev)
    q_lo, q_hi = joint_limits(robot, cfg)
    return xp.clip(q_next, xp.asarray(q_lo, dtype=q.dtype), xp.asarray(q_hi, dtype=q.dtype))
