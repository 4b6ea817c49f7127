"""Reward, success test and terminal-outcome precedence (docs/task.md §2), for every backend.

R = F_d·R_distance + F_s·R_success + F_o·R_obstacle with progress-dependent weights.
Written once, with the array module passed in (``xp`` = numpy or jax.numpy) and no
Python control flow on array values, so the MJX env, the PyBullet reference env and
the evaluation tools score an episode identically.  This module must not import jax.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

from sagrasp_jax.task.config import NEAR_MISS_MODES, RC_MODES, RewardConfig, TaskConfig


class RewardTerms(NamedTuple):
    """The three reward terms and their weights, logged per episode."""

    r_distance: Any
    r_success: Any
    r_obstacle: Any
    f_d: Any
    f_s: Any
    f_o: Any


class Outcome(NamedTuple):
    """Mutually exclusive terminal flags after precedence collision > success > timeout."""

    collision: Any
    success: Any
    timeout: Any


def reward_weights(p: Any, cfg: RewardConfig) -> tuple[Any, Any, Any]:
    """(F_d, F_s, F_o) at training progress ``p`` ∈ [0, 1]: distance shaping fades and the
    terminal verdict gains weight as training goes on (defaults: 2 − p, 0.5 + p, 0.5)."""
    f_d = cfg.f_d0 + cfg.f_d1 * p
    f_s = cfg.f_s0 + cfg.f_s1 * p
    f_o = cfg.f_o + 0 * p  # same shape/type as the other two
    return f_d, f_s, f_o


def grasp_centre(xp: Any, task: Any, target: Any) -> Any:
    """Where the gripper centre closes on the cube (``target``: (..., 3)): over its centre, in the middle of
    the success band's heights; also the end of the straight approach that ``sampling`` tests obstacles
    on.  The deployment loop and the physical check centre there on the *detected* cube before closing,
    so a detection error up to half the band's height and its horizontal tolerance still grasps
    (the detection-ceiling study, docs/results.md §7)."""
    middle = 0.5 * (task.success_dz_min + task.success_dz_max)
    target = xp.asarray(target)
    if not xp.issubdtype(target.dtype, xp.floating):  # whole-number coordinates: not truncated to the offset's dtype
        target = target.astype(float)
    return target + xp.asarray([0.0, 0.0, middle], dtype=target.dtype)  # keeps float32 under jax


def success_flag(xp: Any, cfg: TaskConfig, gripper_centre: Any, target_pos: Any, tilt: Any) -> Any:
    """Kinematic grasp success (without the no-collision part, see ``resolve_outcome``).

    Horizontal offset ≤ success_xy, gripper centre success_dz_min..success_dz_max above
    the target centre (the open pads then embrace the cube and clear the table), and
    tilt ≤ success_tilt_deg.
    """
    offset = xp.asarray(gripper_centre) - xp.asarray(target_pos)
    horizontal = xp.sqrt(offset[..., 0] ** 2 + offset[..., 1] ** 2)
    dz = offset[..., 2]
    return (
        (horizontal <= cfg.success_xy)
        & (dz >= cfg.success_dz_min)
        & (dz <= cfg.success_dz_max)
        & (xp.asarray(tilt) <= math.radians(cfg.success_tilt_deg))
    )


def approach_potential(xp: Any, cfg: RewardConfig, distance: Any, tilt: Any) -> Any:
    """What R_distance's approach shaping measures progress on: the gripper centre → target distance plus
    ``tilt_weight`` metres per radian of tilt θgz beyond ``tilt_free_deg`` (with ``tilt_near`` > 0, faded in
    linearly from that distance to the target, so only the last part of the approach is asked to be upright).

    The success test needs the tilt ≤ success_tilt_deg, but the distance alone pays nothing for righting the
    gripper: a policy that reaches the cube tilted has collected all the shaping, meets only timeouts from there
    and hovers in place (the hovering trap, docs/design.md).  The tilt part is a potential too, so an episode's
    shaping total still depends only on its first and last pose; with ``tilt_weight = 0`` this is the distance.
    """
    distance = xp.asarray(distance)
    excess = xp.maximum(xp.asarray(tilt) - math.radians(cfg.tilt_free_deg), 0.0)
    near = xp.clip(1.0 - distance / cfg.tilt_near, 0.0, 1.0) if cfg.tilt_near > 0 else 1.0
    return distance + cfg.tilt_weight * near * excess


def near_miss_closeness(xp: Any, cfg: RewardConfig, obstacle_dist: Any) -> Any:
    """c = clip(1 − Δpo/near_miss_distance, 0, 1): 0 outside the near-miss band, 1 at contact."""
    return xp.clip(1.0 - xp.asarray(obstacle_dist) / cfg.near_miss_distance, 0.0, 1.0)


def _as_bool(xp: Any, flag: Any) -> Any:
    return xp.asarray(flag) != 0


def resolve_outcome(xp: Any, collision: Any, success_raw: Any, timeout: Any) -> Outcome:
    """Apply the task's precedence (docs/task.md §2.7) collision > success > timeout to raw per-step flags.

    A step can satisfy several raw conditions at once (e.g. the success pose reached
    while touching the table, or success on the 200th step); exactly one verdict must
    be paid, and the returned flags are mutually exclusive booleans.
    """
    col = _as_bool(xp, collision)
    suc = _as_bool(xp, success_raw) & ~col
    tmo = _as_bool(xp, timeout) & ~col & ~suc
    return Outcome(collision=col, success=suc, timeout=tmo)


def step_reward(
    xp: Any,
    cfg: RewardConfig,
    *,
    progress: Any,
    d_prev: Any,
    d_now: Any,
    collision: Any,
    success: Any,
    timeout: Any,
    obstacle_dist: Any,
    obstacle_present: Any,
    clean_so_far: Any,
    prev_obstacle_dist: Any = None,
) -> tuple[Any, RewardTerms]:
    """Reward of one step; returns (total, RewardTerms).

    ``collision``, ``success`` and ``timeout`` are the raw flags; precedence
    collision > success > timeout is applied here (``resolve_outcome``), so a colliding
    step that also meets the success pose pays the collision verdict only.

    ``d_prev``/``d_now`` are approach potentials (``approach_potential``: the distance to the target, and the
    tilt when ``tilt_weight`` > 0).

    * R_distance = ratio·(d_prev − d_now) + grab-zone term.  ``rc_mode="entry"``: RC·(g_t −
      g_{t−1}), g = [d ≤ d_grab] — potential-based, paid once on entry and taken back on
      leaving, so hovering earns nothing.  ``"per_step"``: RC·g_t on every step (the
      paper's literal form; PPO learns to hover inside d_grab — kept for the ablation).
    * R_success = success_reward on success, failure_reward on collision or timeout.
    * R_obstacle = collision_penalty on collision; otherwise, while an obstacle is present, a
      near-miss term of the closeness c = clip(1 − Δpo/near_miss_distance, 0, 1), and
      clean_success_bonus on success when an obstacle was present and never came nearer than
      near_miss_distance (``clean_so_far`` must already include this step).  Near-miss term,
      ``near_miss_mode="change"`` (default): −near_miss_scale·(c_t − c_{t−1}) on every step
      without a collision (``prev_obstacle_dist`` gives c_{t−1}) — a potential: an episode's
      total is −near_miss_scale·(c_end − c_0), so lingering near an obstacle never costs more
      than a crash.  ``"per_step"`` (the paper's literal form, ablation): −near_miss_scale·c_t
      on every non-terminal step, which accumulates and makes crashing early pay.
    """
    if cfg.rc_mode not in RC_MODES:
        raise ValueError(f"rc_mode must be one of {RC_MODES}, got {cfg.rc_mode!r}")
    if cfg.near_miss_mode not in NEAR_MISS_MODES:
        raise ValueError(f"near_miss_mode must be one of {NEAR_MISS_MODES}, got {cfg.near_miss_mode!r}")
    if cfg.near_miss_mode == "change" and prev_obstacle_dist is None:
        raise ValueError("near_miss_mode='change' needs prev_obstacle_dist (Δpo of the previous step)")
    d_prev = xp.asarray(d_prev)
    d_now = xp.asarray(d_now)
    dtype = xp.result_type(d_prev, d_now)
    outcome = resolve_outcome(xp, collision, success, timeout)
    present = _as_bool(xp, obstacle_present)
    clean = _as_bool(xp, clean_so_far)
    terminal = outcome.collision | outcome.success | outcome.timeout

    g_now = (d_now <= cfg.d_grab).astype(dtype)
    g_prev = (d_prev <= cfg.d_grab).astype(dtype)
    grab = g_now - g_prev if cfg.rc_mode == "entry" else g_now
    r_distance = cfg.ratio * (d_prev - d_now) + cfg.rc * grab

    r_success = xp.where(
        outcome.success,
        cfg.success_reward,
        xp.where(outcome.collision | outcome.timeout, cfg.failure_reward, 0.0),
    ).astype(dtype)

    closeness = near_miss_closeness(xp, cfg, obstacle_dist)
    if cfg.near_miss_mode == "change":
        change = closeness - near_miss_closeness(xp, cfg, prev_obstacle_dist)
        near_miss = xp.where(present & ~outcome.collision, -cfg.near_miss_scale * change, 0.0)
    else:
        near_miss = xp.where(present & ~terminal, -cfg.near_miss_scale * closeness, 0.0)
    clean_bonus = xp.where(outcome.success & present & clean, cfg.clean_success_bonus, 0.0)
    r_obstacle = xp.where(outcome.collision, cfg.collision_penalty, near_miss + clean_bonus).astype(dtype)

    f_d, f_s, f_o = reward_weights(xp.asarray(progress, dtype=dtype), cfg)
    total = f_d * r_distance + f_s * r_success + f_o * r_obstacle
    shape = total.shape
    terms = RewardTerms(
        r_distance=xp.broadcast_to(r_distance, shape),
        r_success=xp.broadcast_to(r_success, shape),
        r_obstacle=xp.broadcast_to(r_obstacle, shape),
        f_d=xp.broadcast_to(f_d, shape),
        f_s=xp.broadcast_to(f_s, shape),
        f_o=xp.broadcast_to(f_o, shape),
    )
    return total, terms
