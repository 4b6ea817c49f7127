"""Per-step episode bookkeeping around the shared reward, written once for both simulators.

The MJX env and the PyBullet reference env measure a pose in their own way (our FK / PyBullet's
link frames) and then do exactly the same thing with it: decide the outcome (collision >
success > timeout), pay the reward, update the clean-pass flag, the near-miss potential and the
per-episode accumulators, and report the finished episode's metrics.  ``start`` and ``advance``
are that part, pure functions of a ``Tracker`` (``xp`` = numpy or jax.numpy; no jax import), so
the two simulators cannot drift apart in it.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from sagrasp_jax.task import collision
from sagrasp_jax.task import reward
from sagrasp_jax.task.config import EnvConfig

# Per-episode metrics besides the return and the reward terms' sums (``episode_keys``).
OUTCOME_KEYS = (
    "success",
    "collision",
    "timeout",
    "steps",
    "obstacle_present",
    "redraws",
    "fallback",
    "min_obstacle_dist",
    "blocking",
) + tuple(f"hit_{name}" for name in collision.HIT_KINDS)


def episode_keys() -> tuple[str, ...]:
    """The metrics every simulator reports when an episode ends (info["episode"]; the training rows of
    metrics.jsonl average them): the return, each registered reward term's sum (``reward.term_keys``:
    r_distance, r_success, r_obstacle), then ``OUTCOME_KEYS``.  Read from the registry at each call."""
    return ("return",) + reward.term_keys() + OUTCOME_KEYS


class Tracker(NamedTuple):
    """What an episode carries from step to step besides the robot state."""

    steps: Any  # () int, control steps taken
    d_prev: Any  # () approach potential (reward.approach_potential: distance to the target, tilt) after the previous step
    obstacle_dist_prev: Any  # () Δpo after the previous step (near-miss potential)
    clean: Any  # () bool: an obstacle was never nearer than near_miss_distance
    blocking: Any  # () bool: the straight approach path passes within blocking_margin of an obstacle
    ret: Any  # () accumulated reward
    term_sums: dict[str, Any]  # reward term key (reward.term_keys) -> () its sum over the episode so far
    min_obstacle_dist: Any  # () smallest Δpo so far


class Step(NamedTuple):
    reward: Any  # () total reward of the step
    terms: reward.RewardTerms
    outcome: reward.Outcome
    done: Any  # () bool
    tracker: Tracker
    episode: dict[str, Any]  # the episode's metrics (episode_keys()) as if it ended on this step


def start(xp: Any, cfg: EnvConfig, d0: Any, tilt0: Any, col: collision.CollisionResult, blocking: Any) -> Tracker:
    """The tracker at the start pose (distance ``d0`` to the target, tilt ``tilt0``, collision result ``col``)."""
    d0 = xp.asarray(d0)
    d0 = reward.approach_potential(xp, cfg.reward, d0, xp.asarray(tilt0, dtype=d0.dtype))
    zero = xp.zeros_like(d0)
    return Tracker(
        steps=xp.zeros((), dtype=xp.int32),
        d_prev=d0,
        obstacle_dist_prev=xp.asarray(col.nearest_obstacle_dist, dtype=d0.dtype),
        clean=xp.ones((), dtype=bool),
        blocking=xp.asarray(blocking, dtype=bool),
        ret=zero,
        term_sums={key: zero for key in reward.term_keys()},
        min_obstacle_dist=xp.asarray(col.nearest_obstacle_dist, dtype=d0.dtype),
    )


def advance(xp: Any, cfg: EnvConfig, tracker: Tracker, reset: Any, *, progress: Any, d_now: Any,
            col: collision.CollisionResult, gripper_centre: Any, tilt: Any) -> Step:
    """Outcome, reward and bookkeeping of one control step that ended at the measured pose (``d_now``: the
    gripper centre's distance to the target, ``tilt``: θgz)."""
    dtype = tracker.d_prev.dtype
    potential = xp.asarray(reward.approach_potential(xp, cfg.reward, d_now, tilt), dtype=dtype)
    steps = tracker.steps + 1
    success_raw = reward.success_flag(xp, cfg.task, gripper_centre, reset.target_pos, tilt)
    timeout = steps >= cfg.task.max_steps
    outcome = reward.resolve_outcome(xp, col.any_collision, success_raw, timeout)
    present = xp.any(xp.asarray(reset.obstacle_active))
    dist = xp.asarray(col.nearest_obstacle_dist, dtype=dtype)
    clean = tracker.clean & ~(present & (dist < cfg.reward.near_miss_distance))
    total, terms = reward.step_reward(
        xp, cfg.reward, progress=progress, d_prev=tracker.d_prev, d_now=potential,
        collision=outcome.collision, success=outcome.success, timeout=outcome.timeout,
        obstacle_dist=dist, obstacle_present=present, clean_so_far=clean, prev_obstacle_dist=tracker.obstacle_dist_prev,
    )
    new = Tracker(
        steps=steps,
        d_prev=potential,
        obstacle_dist_prev=dist,
        clean=clean,
        blocking=tracker.blocking,
        ret=tracker.ret + total,
        term_sums={key: tracker.term_sums[key] + value for key, value in terms.values.items()},
        min_obstacle_dist=xp.minimum(tracker.min_obstacle_dist, dist),
    )
    as_float = lambda v: xp.asarray(v).astype(dtype)  # noqa: E731
    episode = {
        "return": new.ret,
        **new.term_sums,
        "success": as_float(outcome.success),
        "collision": as_float(outcome.collision),
        "timeout": as_float(outcome.timeout),
        "steps": as_float(steps),
        "obstacle_present": as_float(present),
        "redraws": as_float(reset.redraws),
        "fallback": as_float(reset.fallback),
        "min_obstacle_dist": new.min_obstacle_dist,
        "blocking": as_float(tracker.blocking),
    } | {f"hit_{name}": as_float(outcome.collision & hit) for name, hit in col.hits.items()}
    done = outcome.collision | outcome.success | outcome.timeout
    return Step(reward=total, terms=terms, outcome=outcome, done=done, tracker=new,
                episode={k: episode[k] for k in episode_keys()})
