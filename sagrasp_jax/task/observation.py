"""The policy's observation, every layout, written once for the MJX env, the PyBullet reference
env, parity, export and the deployment loop (``xp`` = numpy or jax.numpy; no jax import).

Layouts (``env.task.obs_layout``; a policy file records its entry names and its config):

* ``paper`` — the 17 numbers the paper lists (docs/task.md §2): q1..q6, gripper centre, target centre,
  nearest obstacle centre, Δpo, θgz; with no obstacle the centre is the sentinel
  ``no_obstacle_pos`` and Δpo the clip value.  Kept for reproduction and parity with the paper.
* ``relative`` — the same 13 robot/target numbers, then per obstacle slot, nearest first: a
  presence flag, the vector from the gripper centre to the obstacle's nearest surface point,
  the vector from the closest robot point to it (both / ``obs_vector_scale``, clipped to
  ± ``obs_vector_clip``), and a closeness max(0, 1 − Δpo / ``obs_closeness_range``); with
  ``obs_obstacle_shape`` also the vector to the obstacle's centre and its bounding box's
  half-extents (``obstacle_shape``).  Every
  obstacle entry is 0 when the slot is empty, so "absent" is the natural value, and these
  entries are hand-scaled: the trainer's running normaliser leaves them alone
  (``hand_scaled_mask``; docs/design.md, "Observation layouts").
* ``relative_lag`` — ``relative`` followed by each joint's pending command ``(q_target − q_reading) /
  q_max`` (clipped to ± ``obs_pending_clip``, hand-scaled): the part of the commanded joint targets the
  arm has not executed yet.  Under command latency or servo lag the policy cannot otherwise tell that
  its last commands are still on their way; 0 when the arm tracks exactly.  Every backend has both
  numbers: the env its command queue and joints, the deployment loop what it sent and what it reads.

Joint readings carry Gaussian sensor noise in training (``noisy_joints``; the only place the
noise model lives).
"""

from __future__ import annotations

import re
from typing import Any, NamedTuple

import numpy as np

from sagrasp_jax.task import collision
from sagrasp_jax.task import shapes
from sagrasp_jax.task.config import OBS_LAYOUTS, Config, EnvConfig, TaskConfig
from sagrasp_jax.task import robots
from sagrasp_jax.task.robot import Kinematics, RobotModel, forward_kinematics, tilt


def _robot_entries(dof: int) -> tuple[str, ...]:
    """One reading per arm joint, then the gripper centre and the target centre."""
    return (*(f"q{j}" for j in range(1, dof + 1)),
            "gripper_x", "gripper_y", "gripper_z",
            "target_x", "target_y", "target_z")  # fmt: skip


def _paper_layout(dof: int) -> tuple[str, ...]:
    return _robot_entries(dof) + ("obstacle_x", "obstacle_y", "obstacle_z", "d_po", "theta_gz")


DEFAULT_DOF = robots.DEFAULT_DOF
PAPER_LAYOUT: tuple[str, ...] = _paper_layout(DEFAULT_DOF)  # the default robot's (the AUBO-i5's)
OBS_LAYOUT = PAPER_LAYOUT  # the first release's names (policy files of version 0.1 hold exactly these)
OBS_SIZE = len(OBS_LAYOUT)
_SLOT_ENTRIES = ("present", "gripper_dx", "gripper_dy", "gripper_dz", "robot_dx", "robot_dy", "robot_dz", "closeness")


_SHAPE_ENTRIES = ("centre_dx", "centre_dy", "centre_dz", "extent_x", "extent_y", "extent_z")  # obs_obstacle_shape
EXTENT_SCALE = 0.1  # m: obs_obstacle_shape's bounding-box half-extents (0.02-0.17 m in the sampled ranges) / this


def _pending_entries(dof: int) -> tuple[str, ...]:
    """relative_lag: (q_target − q_reading) / q_max per joint."""
    return tuple(f"pending{j}" for j in range(1, dof + 1))


def _relative_layout(slots: int, shape: bool, dof: int) -> tuple[str, ...]:
    entries = _SLOT_ENTRIES + _SHAPE_ENTRIES * shape
    return _robot_entries(dof) + ("theta_gz",) + tuple(f"obstacle{k}_{e}" for k in range(slots) for e in entries)


LAYOUT_NAMES = OBS_LAYOUTS  # declared once in config (env.task.obs_layout's choices)


def layout(name: str, slots: int = 2, obstacle_shape: bool = False, dof: int = DEFAULT_DOF) -> tuple[str, ...]:
    """Entry names of a layout, in order (``obstacle_shape``: ``env.task.obs_obstacle_shape``; ``dof``: the
    arm's joint count, the default robot's unless given)."""
    if name == "paper":
        if obstacle_shape:
            raise ValueError("obstacle shape entries need a relative layout; the paper's layout has no obstacle slots")
        return _paper_layout(dof)
    if name == "relative":
        return _relative_layout(slots, obstacle_shape, dof)
    if name == "relative_lag":
        return _relative_layout(slots, obstacle_shape, dof) + _pending_entries(dof)
    raise ValueError(f"unknown observation layout {name!r}; valid layouts: {', '.join(LAYOUT_NAMES)}")



def layout_of(cfg: EnvConfig) -> tuple[str, ...]:
    return layout(cfg.task.obs_layout, cfg.sampling.max_obstacles, cfg.task.obs_obstacle_shape, robots.get(cfg.robot).dof)


def hand_scaled_mask(names: tuple[str, ...]) -> np.ndarray:
    """Entries the running normaliser must leave alone (mean 0, std 1): the relative layouts'
    obstacle entries and pending commands, already scaled by hand and 0 when absent."""
    return np.array([re.fullmatch(r"obstacle\d+_\w+|pending\d+", n) is not None for n in names])


class Observed(NamedTuple):
    obs: Any
    kin: Kinematics
    col: collision.CollisionResult
    tilt: Any  # θgz, rad


def noise_std(task: TaskConfig, progress: Any) -> Any:
    """σ of the joint-reading noise at training progress p (grows with p if obs_noise_growth > 0)."""
    return task.obs_noise_std * (1.0 + task.obs_noise_growth * progress)


def noisy_joints(task: TaskConfig, q: Any, progress: Any, standard_normal: Any) -> Any:
    """Joint readings with sensor noise: ``standard_normal`` is a (dof,) draw of N(0, 1) from the env's RNG."""
    return q + noise_std(task, progress) * standard_normal


def _sorted_slots(xp: Any, key: Any, values: Any) -> Any:
    """``values`` (slots, k) reordered by ascending ``key`` (slots,) with a one-hot permutation."""
    order = xp.argsort(key)
    perm = xp.arange(key.shape[0])[None, :] == order[:, None]  # (slots, slots): row i picks slot order[i]
    return xp.sum(xp.where(perm[:, :, None], values[None, :, :], 0.0), axis=1)


def assemble(xp: Any, cfg: EnvConfig, q: Any, gripper_centre: Any, reset: Any, col: collision.CollisionResult,
             theta: Any, q_command: Any = None) -> Any:
    """The observation of layout ``cfg.task.obs_layout`` (``q`` may already carry sensor noise).

    ``q_command``: the joint targets last commanded, in the frame of the readings ``q`` (needed by
    ``relative_lag``; ignored by the other layouts)."""
    task = cfg.task
    dtype = gripper_centre.dtype
    target = xp.asarray(reset.target_pos, dtype=dtype)
    theta = xp.reshape(xp.asarray(theta, dtype=dtype), (1,))
    if task.obs_layout == "paper":
        if task.obs_obstacle_shape:
            raise ValueError("env.task.obs_obstacle_shape needs a relative observation layout")
        return xp.concatenate(
            [q, gripper_centre, target, col.nearest_obstacle_pos, xp.reshape(col.nearest_obstacle_dist, (1,)), theta]
        )
    if task.obs_layout not in ("relative", "relative_lag"):
        raise ValueError(f"unknown observation layout {task.obs_layout!r}")
    active = xp.asarray(reset.obstacle_active)
    present = active.astype(dtype)
    scale, clip = task.obs_vector_scale, task.obs_vector_clip
    closeness = xp.clip(1.0 - col.obstacle_dist / task.obs_closeness_range, 0.0, 1.0) * present
    columns = [
        present[:, None],
        xp.clip(col.gripper_to_obstacle / scale, -clip, clip),
        xp.clip(col.robot_to_obstacle / scale, -clip, clip),
        closeness[:, None],
    ]
    if task.obs_obstacle_shape:
        columns += [c * present[:, None] for c in obstacle_shape(xp, cfg, reset, gripper_centre)]
    slots = xp.concatenate(columns, axis=-1)  # (slots, 8 or 14), zero rows for empty slots
    key = xp.where(active, col.obstacle_dist, xp.inf)
    parts = [q, gripper_centre, target, theta, xp.reshape(_sorted_slots(xp, key, slots), (-1,))]
    if task.obs_layout == "relative_lag":
        if q_command is None:
            raise ValueError("the relative_lag layout needs the last commanded joint targets (q_command)")
        parts.append(pending(xp, cfg, q, q_command))
    return xp.concatenate(parts)


def obstacle_shape(xp: Any, cfg: EnvConfig, reset: Any, gripper_centre: Any) -> tuple[Any, Any]:
    """``obs_obstacle_shape``'s columns per slot: the gripper centre → obstacle centre vector (/ obs_vector_scale,
    clipped to ± obs_vector_clip) (slots, 3) and the world-aligned bounding box's half-extents / EXTENT_SCALE
    (slots, 3).  With the nearest-surface vector they say which way the obstacle extends and how far, so the
    policy can tell a thin post from a wide box it must go around (empty slots are zeroed by the caller)."""
    dtype = gripper_centre.dtype
    clip = cfg.task.obs_vector_clip
    centre = xp.asarray(reset.obstacle_pos, dtype=dtype) - gripper_centre
    half = shapes.extent(xp, xp.asarray(reset.obstacle_kind), xp.asarray(reset.obstacle_yaw, dtype=dtype),
                         xp.asarray(reset.obstacle_size, dtype=dtype), shapes.kind_ids(cfg.sampling.obstacle_kinds))
    return xp.clip(centre / cfg.task.obs_vector_scale, -clip, clip), half / EXTENT_SCALE


def pending(xp: Any, cfg: EnvConfig, q_reading: Any, q_command: Any) -> Any:
    """``relative_lag``'s pending command: (q_command − q_reading) / q_max, clipped to ± obs_pending_clip."""
    clip = cfg.task.obs_pending_clip
    return xp.clip((xp.asarray(q_command, dtype=q_reading.dtype) - q_reading) / cfg.control.q_max, -clip, clip)


def blind(xp: Any, cfg: EnvConfig, obs: Any) -> Any:
    """``obs`` (..., size) with every obstacle entry replaced by its "no obstacle" value: what the
    policy would see if the obstacles were not there (experiments/obstacle_ablation.py, blind_study)."""
    names = layout_of(cfg)
    if cfg.task.obs_layout == "paper":
        absent = dict(zip(("obstacle_x", "obstacle_y", "obstacle_z"), cfg.task.no_obstacle_pos))
        absent["d_po"] = cfg.task.obstacle_dist_clip
    else:
        absent = {n: 0.0 for n, hand in zip(names, hand_scaled_mask(names)) if hand}
    mask = np.array([n in absent for n in names])
    values = np.array([absent.get(n, 0.0) for n in names])
    return xp.where(xp.asarray(mask), xp.asarray(values, dtype=obs.dtype), obs)


_PRIVILEGED_SIZE_AND_PLACE = ("size_x", "size_y", "size_z", "dx", "dy", "dz", "distance")
PRIVILEGED_SCALE = 0.1  # m: obstacle sizes in the privileged critic inputs are divided by this


def privileged_layout(cfg: EnvConfig) -> tuple[str, ...]:
    """Names of the privileged critic inputs (training only; the policy never sees them)."""
    return ("progress", "time_fraction", "blocking") + tuple(
        f"obstacle{k}_{e}" for k in range(cfg.sampling.max_obstacles)
        for e in ("present", *cfg.sampling.obstacle_kinds, *_PRIVILEGED_SIZE_AND_PLACE))  # a one-hot of the env's kinds


def critic_extra_size(cfg: Config) -> int:
    """How many privileged inputs the value network reads (0 without ``ppo.privileged_critic``)."""
    return len(privileged_layout(cfg.env)) if cfg.ppo.privileged_critic else 0


def privileged(xp: Any, cfg: EnvConfig, reset: Any, col: collision.CollisionResult, gripper_centre: Any, steps: Any,
               progress: Any, blocking: Any) -> Any:
    """What the critic may know beyond the observation: training progress p (the reward weights
    depend on it), the time left before the 200-step timeout, whether the scene blocks the straight
    path, and every obstacle's kind, size, centre (from the gripper) and distance.  All hand-scaled."""
    dtype = gripper_centre.dtype
    present = xp.asarray(reset.obstacle_active).astype(dtype)
    kind = xp.asarray(reset.obstacle_kind)
    onehot = xp.stack([(kind == k).astype(dtype) for k in shapes.kind_ids(cfg.sampling.obstacle_kinds)], axis=-1)
    size = xp.asarray(reset.obstacle_size, dtype=dtype) / PRIVILEGED_SCALE
    clip = cfg.task.obs_vector_clip
    centre = xp.clip((xp.asarray(reset.obstacle_pos, dtype=dtype) - gripper_centre) / cfg.task.obs_vector_scale, -clip, clip)
    dist = xp.clip(col.obstacle_dist / cfg.task.obs_vector_scale, -1.0, clip)
    slots = xp.concatenate([present[:, None], onehot, size, centre, dist[:, None]], axis=-1) * present[:, None]
    head = xp.stack([xp.asarray(progress, dtype=dtype), xp.asarray(steps, dtype=dtype) / cfg.task.max_steps,
                     xp.asarray(blocking, dtype=dtype)])
    return xp.concatenate([head, xp.reshape(slots, (-1,))])


def observe(xp: Any, robot: RobotModel, cfg: EnvConfig, q: Any, reset: Any, kin: Kinematics | None = None,
            q_command: Any = None) -> Observed:
    """Noise-free observation at measured joints ``q`` for the scene ``reset`` (a ResetSpec).

    ``kin`` lets a simulator pass its own link frames (PyBullet); by default our FK of ``q``.
    ``q_command``: the joint targets last sent (``relative_lag``); ``q`` itself (nothing pending) if None."""
    kin = forward_kinematics(xp, robot, q) if kin is None else kin
    col = collision.check(xp, robot, kin, reset, cfg)
    theta = tilt(xp, kin.approach_axis)
    q_command = q if q_command is None else q_command
    return Observed(assemble(xp, cfg, q, kin.gripper_centre, reset, col, theta, q_command), kin, col, theta)
