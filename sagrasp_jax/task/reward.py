"""Reward, success test and terminal-outcome precedence (docs/task.md §2), for every backend.

R = Σ F_x·R_x over the registered reward terms: F_d·R_distance + F_s·R_success + F_o·R_obstacle by
default, with progress-dependent weights.  Each term is one ``RewardTerm`` entry of the registry
(``terms()``): the name it is reported under, its per-step value, its weight.  The episode tracker,
both envs' per-step reports, the parity harness and the training metrics read the registry, so a new
term is one entry (``register``, or ``registered`` for a with-block) plus its config keys, if any.
Written once, with the array module passed in (``xp`` = numpy or jax.numpy) and no
Python control flow on array values, so the MJX env, the PyBullet reference env and
the evaluation tools score an episode identically.  This module must not import jax.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Any, Callable, Iterator, NamedTuple

from sagrasp_jax.task.config import NEAR_MISS_MODES, RC_MODES, RewardConfig, TaskConfig


class Outcome(NamedTuple):
    """Mutually exclusive terminal flags after precedence collision > success > timeout."""

    collision: Any
    success: Any
    timeout: Any


def grasp_centre(xp: Any, task: Any, target: Any) -> Any:
    """Where the gripper centre closes on the cube (``target``: (..., 3)): over its centre, in the middle of
    the success band's heights; also the end of the straight approach that ``sampling`` tests obstacles
    on.  The deployment loop and the physical check centre there on the *detected* cube before closing,
    so a detection error up to half the band's height and its horizontal tolerance still grasps
    (the detection-ceiling study, docs/results-archive.md §7)."""
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




# --------------------------------------------------------------------------------------------
# the reward terms and their registry
# --------------------------------------------------------------------------------------------
class StepInputs(NamedTuple):
    """What a reward term sees of one step (arrays broadcast over the same leading batch dims)."""

    d_prev: Any  # approach potential (``approach_potential``) before the step, in the step's float dtype
    d_now: Any  # approach potential after the step
    outcome: Outcome  # the step's verdict after precedence (``resolve_outcome``)
    obstacle_dist: Any  # Δpo after the step
    prev_obstacle_dist: Any  # Δpo before the step (None when the caller has none: near_miss_mode="per_step")
    obstacle_present: Any  # bool: the episode has an active obstacle
    clean_so_far: Any  # bool: no obstacle came nearer than near_miss_distance, this step included
    dtype: Any  # the step's float dtype: a term's value must come back in it


@dataclass(frozen=True)
class RewardTerm:
    """One term F_x·R_x of the reward: everything the package needs to compute, sum and report it.

    ``key`` ("r_…") names the term's per-step value wherever it is reported: the envs' per-step metrics
    and info, the finished episode's sum (``episode.episode_keys``), the training rows of metrics.jsonl
    and TensorBoard, the parity harness's compared columns.  ``weight_key`` ("f_…") names its weight in
    ``RewardTerms.weights`` and ``reward_weights``.  ``value(xp, cfg, step)`` is R_x of one step
    (``StepInputs``), written once for numpy and jax.numpy, in ``step.dtype``; ``weight(p, cfg)`` is F_x at
    the training progress ``p`` (an array of that dtype; a constant weight still returns an array of p's
    shape, e.g. ``c + 0 * p``).  A term's config keys belong in ``RewardConfig``.
    """

    key: str
    weight_key: str
    value: Callable[[Any, RewardConfig, StepInputs], Any]
    weight: Callable[[Any, RewardConfig], Any]


def distance_value(xp: Any, cfg: RewardConfig, step: StepInputs) -> Any:
    """R_distance = ratio·(d_prev − d_now) + grab-zone term.  ``rc_mode="entry"``: RC·(g_t − g_{t−1}),
    g = [d ≤ d_grab] — potential-based, paid once on entry and taken back on leaving, so hovering earns
    nothing.  ``"per_step"``: RC·g_t on every step (the paper's literal form; PPO learns to hover inside
    d_grab — kept for the ablation)."""
    if cfg.rc_mode not in RC_MODES:
        raise ValueError(f"rc_mode must be one of {RC_MODES}, got {cfg.rc_mode!r}")
    g_now = (step.d_now <= cfg.d_grab).astype(step.dtype)
    g_prev = (step.d_prev <= cfg.d_grab).astype(step.dtype)
    grab = g_now - g_prev if cfg.rc_mode == "entry" else g_now
    return cfg.ratio * (step.d_prev - step.d_now) + cfg.rc * grab


def success_value(xp: Any, cfg: RewardConfig, step: StepInputs) -> Any:
    """R_success = success_reward on success, failure_reward on collision or timeout, else 0."""
    outcome = step.outcome
    return xp.where(
        outcome.success,
        cfg.success_reward,
        xp.where(outcome.collision | outcome.timeout, cfg.failure_reward, 0.0),
    ).astype(step.dtype)


def obstacle_value(xp: Any, cfg: RewardConfig, step: StepInputs) -> Any:
    """R_obstacle = collision_penalty on collision; otherwise, while an obstacle is present, a near-miss term
    of the closeness c = clip(1 − Δpo/near_miss_distance, 0, 1), and clean_success_bonus on success when an
    obstacle was present and never came nearer than near_miss_distance.  Near-miss term,
    ``near_miss_mode="change"`` (default): −near_miss_scale·(c_t − c_{t−1}) on every step without a
    collision — a potential: an episode's total is −near_miss_scale·(c_end − c_0), so lingering near an
    obstacle never costs more than a crash.  ``"per_step"`` (the paper's literal form, ablation):
    −near_miss_scale·c_t on every non-terminal step, which accumulates and makes crashing early pay."""
    if cfg.near_miss_mode not in NEAR_MISS_MODES:
        raise ValueError(f"near_miss_mode must be one of {NEAR_MISS_MODES}, got {cfg.near_miss_mode!r}")
    if cfg.near_miss_mode == "change" and step.prev_obstacle_dist is None:
        raise ValueError("near_miss_mode='change' needs prev_obstacle_dist (Δpo of the previous step)")
    outcome, present = step.outcome, step.obstacle_present
    closeness = near_miss_closeness(xp, cfg, step.obstacle_dist)
    if cfg.near_miss_mode == "change":
        change = closeness - near_miss_closeness(xp, cfg, step.prev_obstacle_dist)
        near_miss = xp.where(present & ~outcome.collision, -cfg.near_miss_scale * change, 0.0)
    else:
        terminal = outcome.collision | outcome.success | outcome.timeout
        near_miss = xp.where(present & ~terminal, -cfg.near_miss_scale * closeness, 0.0)
    clean_bonus = xp.where(outcome.success & present & step.clean_so_far, cfg.clean_success_bonus, 0.0)
    return xp.where(outcome.collision, cfg.collision_penalty, near_miss + clean_bonus).astype(step.dtype)


def distance_weight(p: Any, cfg: RewardConfig) -> Any:
    """F_d = f_d0 + f_d1·p: the approach shaping fades as training goes on (default 2 − p)."""
    return cfg.f_d0 + cfg.f_d1 * p


def success_weight(p: Any, cfg: RewardConfig) -> Any:
    """F_s = f_s0 + f_s1·p: the terminal verdict gains weight as training goes on (default 0.5 + p)."""
    return cfg.f_s0 + cfg.f_s1 * p


def obstacle_weight(p: Any, cfg: RewardConfig) -> Any:
    """F_o = f_o, constant (default 0.5)."""
    return cfg.f_o + 0 * p  # same shape/type as the other two


DISTANCE = RewardTerm("r_distance", "f_d", distance_value, distance_weight)  # approach shaping and grab zone
SUCCESS = RewardTerm("r_success", "f_s", success_value, success_weight)  # the episode's verdict
OBSTACLE = RewardTerm("r_obstacle", "f_o", obstacle_value, obstacle_weight)  # collision, near miss, clean pass
DEFAULT_TERMS = (DISTANCE, SUCCESS, OBSTACLE)  # summed in this order: the packaged policy's float32 sums

_registry: tuple[RewardTerm, ...] = DEFAULT_TERMS


def terms() -> tuple[RewardTerm, ...]:
    """The registered reward terms, in the order they are summed and reported.  Read when an env is traced
    (jit keeps the terms it traced with), so register a term before building the env that pays it."""
    return _registry


def term_keys() -> tuple[str, ...]:
    """The names the registered terms are reported under (``RewardTerm.key``), in registry order."""
    return tuple(t.key for t in _registry)


def _check_term(term: RewardTerm, current: tuple[RewardTerm, ...]) -> None:
    if not isinstance(term, RewardTerm):
        raise TypeError(f"a reward term must be a reward.RewardTerm, got {type(term).__name__}")
    for field, prefix in (("key", "r_"), ("weight_key", "f_")):
        name = getattr(term, field)
        if not (isinstance(name, str) and name.startswith(prefix) and name[len(prefix):].isidentifier()):
            # the prefixes keep a term's reported names apart from every other episode or step metric
            raise ValueError(f"reward term {field} must be '{prefix}' + an identifier, got {name!r}")
        taken = [getattr(t, field) for t in current]
        if name in taken:
            raise ValueError(f"reward term {field} {name!r} is already registered ({', '.join(taken)})")
    if not (callable(term.value) and callable(term.weight)):
        raise TypeError(f"reward term {term.key!r}: value and weight must be callables")


def register(term: RewardTerm) -> None:
    """Add ``term`` to the registry for good (after the others in the sum); see ``registered`` for a
    with-block.  Refuses a term whose key or weight key is malformed or taken."""
    global _registry
    _check_term(term, _registry)
    _registry = _registry + (term,)


@contextlib.contextmanager
def registered(*extra: RewardTerm) -> Iterator[tuple[RewardTerm, ...]]:
    """``with reward.registered(term, ...):`` the terms are paid and reported inside the block (envs built
    there); the registry is restored as it was on leaving, also on an error."""
    global _registry
    saved = _registry
    try:
        for term in extra:
            register(term)
        yield _registry
    finally:
        _registry = saved


class RewardTerms(NamedTuple):
    """The registered terms' per-step values and weights, broadcast to the reward's shape."""

    values: dict[str, Any]  # RewardTerm.key -> R_x of the step
    weights: dict[str, Any]  # RewardTerm.weight_key -> F_x at the step's progress


def reward_weights(p: Any, cfg: RewardConfig) -> dict[str, Any]:
    """{weight key: F_x} of the registered terms at training progress ``p`` ∈ [0, 1] (defaults: F_d = 2 − p,
    F_s = 0.5 + p, F_o = 0.5: distance shaping fades and the terminal verdict gains weight)."""
    return {t.weight_key: t.weight(p, cfg) for t in _registry}


def _checked_value(term: RewardTerm, value: Any, dtype: Any) -> Any:
    """A term's value, refused unless it is an array of the step's dtype (a float64 constant would
    otherwise promote the whole reward under numpy)."""
    got = getattr(value, "dtype", None)
    if got is None or got != dtype:  # (numpy reads a dtype None as float64)
        raise TypeError(f"reward term {term.key!r} returned {type(value).__name__} of dtype {got}, "
                        f"the step's dtype is {dtype} (StepInputs.dtype)")
    return value


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
    """Reward of one step, Σ F_x·R_x over the registered terms in registry order; returns (total, RewardTerms).

    ``collision``, ``success`` and ``timeout`` are the raw flags; precedence
    collision > success > timeout is applied here (``resolve_outcome``), so a colliding
    step that also meets the success pose pays the collision verdict only.

    ``d_prev``/``d_now`` are approach potentials (``approach_potential``: the distance to the target, and the
    tilt when ``tilt_weight`` > 0).  ``clean_so_far`` must already include this step; ``prev_obstacle_dist``
    (Δpo of the previous step) is needed by near_miss_mode="change".  The terms: ``distance_value``,
    ``success_value``, ``obstacle_value`` and any registered ones.
    """
    d_prev = xp.asarray(d_prev)
    d_now = xp.asarray(d_now)
    dtype = xp.result_type(d_prev, d_now)
    step = StepInputs(
        d_prev=d_prev, d_now=d_now, outcome=resolve_outcome(xp, collision, success, timeout),
        obstacle_dist=obstacle_dist, prev_obstacle_dist=prev_obstacle_dist,
        obstacle_present=_as_bool(xp, obstacle_present), clean_so_far=_as_bool(xp, clean_so_far), dtype=dtype,
    )
    registry = _registry
    values = [_checked_value(term, term.value(xp, cfg, step), dtype) for term in registry]
    p = xp.asarray(progress, dtype=dtype)
    weights = [term.weight(p, cfg) for term in registry]
    total = weights[0] * values[0]
    for weight, value in zip(weights[1:], values[1:]):
        total = total + weight * value  # left to right, as F_d·R_d + F_s·R_s + F_o·R_o always summed
    shape = total.shape
    return total, RewardTerms(
        values={t.key: xp.broadcast_to(v, shape) for t, v in zip(registry, values)},
        weights={t.weight_key: xp.broadcast_to(w, shape) for t, w in zip(registry, weights)},
    )
