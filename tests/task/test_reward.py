"""Reward terms, weights, precedence and success test on hand-computed cases.

Defaults: ratio 10/m, RC 0.05, d_grab 0.05 m, near-miss closeness c = clip(1 − Δpo/0.05, 0, 1),
paid as −0.5·(c_t − c_{t−1}) ("change", default) or −0.5·c_t ("per_step", the paper's form).
Weights (F_d, F_s, F_o) = (2, 0.5, 0.5) at p = 0 and (1, 1.5, 0.5) at p = 1.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401  (sets XLA flags before jax is imported)
from sagrasp_jax.task.config import HOME_Q, PPOConfig, RewardConfig, TaskConfig
from sagrasp_jax.task.control import gripper_state
from sagrasp_jax.task.reward import resolve_outcome, reward_weights, step_reward, success_flag
from sagrasp_jax.task.robot import load_robot

CFG = RewardConfig()
PER_STEP = dataclasses.replace(CFG, rc_mode="per_step")
NEAR_PER_STEP = dataclasses.replace(CFG, near_miss_mode="per_step")
TASK = TaskConfig()


def reward(cfg: RewardConfig = CFG, xp=np, **kw):
    args = dict(
        progress=0.0,
        d_prev=0.3,
        d_now=0.3,
        collision=False,
        success=False,
        timeout=False,
        obstacle_dist=1.0,
        obstacle_present=False,
        clean_so_far=True,
    )
    args.update(kw)
    args.setdefault("prev_obstacle_dist", args["obstacle_dist"])  # Δpo unchanged unless a case says otherwise
    return step_reward(xp, cfg, **args)


def test_weights() -> None:
    assert reward_weights(0.0, CFG) == {"f_d": 2.0, "f_s": 0.5, "f_o": 0.5}
    assert reward_weights(1.0, CFG) == {"f_d": 1.0, "f_s": 1.5, "f_o": 0.5}
    assert reward_weights(0.25, CFG) == {"f_d": 1.75, "f_s": 0.75, "f_o": 0.5}


# (name, cfg, kwargs, (r_distance, r_success, r_obstacle), total at p=0, total at p=1)
CASES = [
    ("approach 2 cm", CFG, dict(d_prev=0.30, d_now=0.28), (0.2, 0, 0), 0.4, 0.2),
    ("retreat 1 cm", CFG, dict(d_prev=0.28, d_now=0.29), (-0.1, 0, 0), -0.2, -0.1),
    ("enter grab zone", CFG, dict(d_prev=0.055, d_now=0.045), (0.15, 0, 0), 0.3, 0.15),
    ("enter grab zone per_step", PER_STEP, dict(d_prev=0.055, d_now=0.045), (0.15, 0, 0), 0.3, 0.15),
    ("hover inside", CFG, dict(d_prev=0.04, d_now=0.04), (0, 0, 0), 0.0, 0.0),
    ("hover inside per_step", PER_STEP, dict(d_prev=0.04, d_now=0.04), (0.05, 0, 0), 0.1, 0.05),
    ("leave grab zone", CFG, dict(d_prev=0.045, d_now=0.055), (-0.15, 0, 0), -0.3, -0.15),
    ("leave grab zone per_step", PER_STEP, dict(d_prev=0.045, d_now=0.055), (-0.1, 0, 0), -0.2, -0.1),
    (
        "near miss at 3 cm per_step",
        NEAR_PER_STEP,
        dict(d_prev=0.2, d_now=0.2, obstacle_dist=0.03, obstacle_present=True, clean_so_far=False),
        (0, 0, -0.2),
        -0.1,
        -0.1,
    ),
    (
        "near miss at 1 cm while approaching per_step",
        NEAR_PER_STEP,
        dict(d_prev=0.21, d_now=0.2, obstacle_dist=0.01, obstacle_present=True, clean_so_far=False),
        (0.1, 0, -0.4),
        0.0,
        -0.1,
    ),
    (
        "lingering at 3 cm: no change, no penalty",
        CFG,
        dict(d_prev=0.2, d_now=0.2, obstacle_dist=0.03, obstacle_present=True, clean_so_far=False),
        (0, 0, 0),
        0.0,
        0.0,
    ),
    (
        "closing in from 6 cm to 3 cm",
        CFG,
        dict(obstacle_dist=0.03, prev_obstacle_dist=0.06, obstacle_present=True, clean_so_far=False),
        (0, 0, -0.2),
        -0.1,
        -0.1,
    ),
    (
        "backing off from 1 cm to 3 cm repays",
        CFG,
        dict(obstacle_dist=0.03, prev_obstacle_dist=0.01, obstacle_present=True, clean_so_far=False),
        (0, 0, 0.2),
        0.1,
        0.1,
    ),
    (
        "change term without an obstacle: none",
        CFG,
        dict(obstacle_dist=1.0, prev_obstacle_dist=0.01, obstacle_present=False),
        (0, 0, 0),
        0.0,
        0.0,
    ),
    (
        "collision pays the penalty, not the change",
        CFG,
        dict(collision=True, obstacle_dist=-0.01, prev_obstacle_dist=0.04, obstacle_present=True, clean_so_far=False),
        (0, -1, -1),
        -0.5 - 0.5,
        -1.5 - 0.5,
    ),
    ("obstacle at 6 cm", CFG, dict(obstacle_dist=0.06, obstacle_present=True), (0, 0, 0), 0.0, 0.0),
    ("no obstacle, dist placeholder", CFG, dict(obstacle_dist=0.0, obstacle_present=False), (0, 0, 0), 0.0, 0.0),
    (
        "collision",
        CFG,
        dict(d_prev=0.2, d_now=0.19, collision=True, obstacle_dist=0.0, obstacle_present=True, clean_so_far=False),
        (0.1, -1, -1),
        -0.8,
        -1.9,
    ),
    (
        "collision beats success and timeout",
        CFG,
        dict(d_prev=0.02, d_now=0.015, collision=True, success=True, timeout=True),
        (0.05, -1, -1),
        -0.9,
        -1.95,
    ),
    ("success, no obstacle", CFG, dict(d_prev=0.02, d_now=0.015, success=True), (0.05, 1, 0), 0.6, 1.55),
    (
        "success, clean obstacle episode",
        CFG,
        dict(d_prev=0.02, d_now=0.015, success=True, obstacle_dist=0.2, obstacle_present=True),
        (0.05, 1, 1),
        1.1,
        2.05,
    ),
    (
        "success after a near miss: no bonus",
        CFG,
        dict(d_prev=0.02, d_now=0.015, success=True, obstacle_dist=0.2, obstacle_present=True, clean_so_far=False),
        (0.05, 1, 0),
        0.6,
        1.55,
    ),
    (
        "success while near an obstacle per_step: no bonus, no near-miss penalty",
        NEAR_PER_STEP,
        dict(d_prev=0.02, d_now=0.015, success=True, obstacle_dist=0.03, obstacle_present=True, clean_so_far=False),
        (0.05, 1, 0),
        0.6,
        1.55,
    ),
    ("success entering grab zone", CFG, dict(d_prev=0.06, d_now=0.016, success=True), (0.49, 1, 0), 1.48, 1.99),
    ("success beats timeout", CFG, dict(d_prev=0.02, d_now=0.015, success=True, timeout=True), (0.05, 1, 0), 0.6, 1.55),
    ("timeout", CFG, dict(timeout=True), (0, -1, 0), -0.5, -1.5),
    (
        "timeout near an obstacle per_step: terminal, no near-miss penalty",
        NEAR_PER_STEP,
        dict(timeout=True, obstacle_dist=0.03, obstacle_present=True, clean_so_far=False),
        (0, -1, 0),
        -0.5,
        -1.5,
    ),
    ("timeout hovering per_step", PER_STEP, dict(d_prev=0.04, d_now=0.04, timeout=True), (0.05, -1, 0), -0.4, -1.45),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
@pytest.mark.parametrize("progress", [0.0, 1.0])
def test_hand_built_cases(case, progress: float) -> None:
    _, cfg, kw, terms, total0, total1 = case
    total, t = reward(cfg, progress=progress, **kw)
    assert list(t.values) == ["r_distance", "r_success", "r_obstacle"]
    np.testing.assert_allclose(list(t.values.values()), terms, atol=1e-12)
    np.testing.assert_allclose(total, total0 if progress == 0.0 else total1, atol=1e-12)
    assert t.weights == pytest.approx(reward_weights(progress, cfg), abs=1e-15)


def test_resolve_outcome_precedence() -> None:
    raw = np.array(
        [[c, s, t] for c in (0, 1) for s in (0, 1) for t in (0, 1)],
        dtype=bool,
    )
    out = resolve_outcome(np, raw[:, 0], raw[:, 1], raw[:, 2])
    expected = {
        (0, 0, 0): (0, 0, 0),
        (0, 0, 1): (0, 0, 1),
        (0, 1, 0): (0, 1, 0),
        (0, 1, 1): (0, 1, 0),
        (1, 0, 0): (1, 0, 0),
        (1, 0, 1): (1, 0, 0),
        (1, 1, 0): (1, 0, 0),
        (1, 1, 1): (1, 0, 0),
    }
    got = np.stack([out.collision, out.success, out.timeout], axis=1)
    for row, flags in zip(raw, got):
        assert tuple(int(v) for v in flags) == expected[tuple(int(v) for v in row)]
    # Float 0/1 flags (the env's done-style encoding) are accepted too.
    out = resolve_outcome(np, 1.0, 1.0, 0.0)
    assert bool(out.collision) and not bool(out.success) and not bool(out.timeout)


def test_rc_mode_is_validated() -> None:
    with pytest.raises(ValueError, match="rc_mode"):
        reward(dataclasses.replace(CFG, rc_mode="always"))
    with pytest.raises(ValueError, match="near_miss_mode"):
        reward(dataclasses.replace(CFG, near_miss_mode="sometimes"))
    with pytest.raises(ValueError, match="prev_obstacle_dist"):
        step_reward(np, CFG, progress=0.0, d_prev=0.3, d_now=0.3, collision=False, success=False, timeout=False,
                    obstacle_dist=0.03, obstacle_present=True, clean_so_far=False)


def _obstacle_episode(cfg: RewardConfig, path: list[tuple[float, float]], end: dict, progress: float,
                      gamma: float) -> float:
    """Discounted return along (distance to target, Δpo) pairs in an obstacle episode; ``end``
    holds the last step's raw flags."""
    ret = 0.0
    for k in range(len(path) - 1):
        (d0, o0), (d1, o1) = path[k], path[k + 1]
        flags = end if k == len(path) - 2 else {}
        total, _ = reward(cfg, progress=progress, d_prev=d0, d_now=d1, obstacle_dist=o1, prev_obstacle_dist=o0,
                          obstacle_present=True, clean_so_far=False, **flags)
        ret += gamma**k * float(total)
    return ret


@pytest.mark.parametrize("gamma", [1.0, PPOConfig().gamma])
@pytest.mark.parametrize("progress", [0.0, 0.5, 1.0])
def test_lingering_near_an_obstacle_beats_crashing_only_under_change(gamma: float, progress: float) -> None:
    """docs/task.md §2: from the same state 2 cm from an obstacle and 10 cm from the cube, working past it
    for 40 steps and then grasping earns more than crashing into it now under the default
    near_miss_mode="change", and less under the paper's per_step term (the trap stays documented)."""
    start = (0.10, 0.02)
    linger = [start] + [(0.10 - 0.0021 * k, 0.02) for k in range(1, 41)] + [(0.012, 0.06)]
    crash = [start, (0.095, -0.005)]
    for cfg, trapped in ((CFG, False), (NEAR_PER_STEP, True)):
        careful = _obstacle_episode(cfg, linger, dict(success=True), progress, gamma)
        crashed = _obstacle_episode(cfg, crash, dict(collision=True), progress, gamma)
        assert (crashed > careful) == trapped, (cfg.near_miss_mode, careful, crashed)


def test_near_miss_change_telescopes() -> None:
    """Under "change" the near-miss terms of an episode sum to −0.5·(c_end − c_0)."""
    dists = [0.2, 0.04, 0.01, 0.03, 0.02, 0.045]
    total = sum(float(reward(CFG, obstacle_dist=b, prev_obstacle_dist=a, obstacle_present=True, clean_so_far=False)[1].values["r_obstacle"])
                for a, b in zip(dists[:-1], dists[1:]))
    c_end = 1 - 0.045 / 0.05
    assert total == pytest.approx(-0.5 * (c_end - 0.0), abs=1e-12)


def _episode_return(cfg: RewardConfig, distances: list[float], last: dict, progress: float, gamma: float) -> float:
    """Discounted return along ``distances``; ``last`` holds the final step's raw flags."""
    steps = len(distances) - 1
    ret = 0.0
    for k in range(steps):
        flags = last if k == steps - 1 else {}
        total, _ = reward(cfg, progress=progress, d_prev=distances[k], d_now=distances[k + 1], **flags)
        ret += gamma**k * float(total)
    return ret


@pytest.mark.parametrize("gamma", [1.0, PPOConfig().gamma])
@pytest.mark.parametrize("progress", [0.0, 1.0])
def test_hovering_trap_only_under_per_step(gamma: float, progress: float) -> None:
    """docs/task.md §2: from the same state inside d_grab, hovering until timeout earns less than
    completing the grasp under rc_mode="entry", and more under the paper's per_step."""
    start = 0.04  # already inside d_grab, 20 steps into the episode
    remaining = TASK.max_steps - 20
    grasp = [start, 0.015]
    hover = [start] * (remaining + 1)
    for cfg, trapped in ((CFG, False), (PER_STEP, True)):
        done = _episode_return(cfg, grasp, dict(success=True), progress, gamma)
        idle = _episode_return(cfg, hover, dict(timeout=True), progress, gamma)
        assert (idle > done) == trapped, (cfg.rc_mode, done, idle)


def _pose_state(dx: float, dy: float, dz: float, dq5: float = 0.0):
    robot = load_robot()
    q = np.array(HOME_Q)
    q[4] += dq5
    centre, theta = gripper_state(np, robot, q)
    return centre, centre - np.array([dx, dy, dz]), theta


@pytest.mark.parametrize(
    "dx, dy, dz, dq5, ok",
    [
        (0.0, 0.0, 0.010, 0.0, True),
        (0.006, 0.006, 0.010, 0.0, True),  # 8.5 mm horizontal
        (0.008, 0.008, 0.010, 0.0, False),  # 11.3 mm horizontal
        (0.0, 0.0, 0.004, 0.0, False),  # too low: pads would hit the table
        (0.0, 0.0, 0.0051, 0.0, True),
        (0.0, 0.0, 0.0199, 0.0, True),
        (0.0, 0.0, 0.021, 0.0, False),  # too high
        (0.0, 0.0, -0.010, 0.0, False),  # below the target centre
        (0.0, 0.0, 0.010, 0.17, True),  # 9.74° tilt
        (0.0, 0.0, 0.010, 0.18, False),  # 10.31° tilt
    ],
)
def test_success_flag(dx: float, dy: float, dz: float, dq5: float, ok: bool) -> None:
    centre, target, theta = _pose_state(dx, dy, dz, dq5)
    assert bool(success_flag(np, TASK, centre, target, theta)) == ok


def test_success_flag_thresholds_in_degrees() -> None:
    centre = np.array([0.0, -0.3, 0.06])
    target = np.array([0.0, -0.3, 0.05])
    assert bool(success_flag(np, TASK, centre, target, math.radians(9.99)))
    assert not bool(success_flag(np, TASK, centre, target, math.radians(10.01)))


def test_numpy_and_jax_agree_batched() -> None:
    import jax
    import jax.numpy as jnp

    rows = [case for case in CASES if case[1] is CFG]
    keys = ["d_prev", "d_now", "collision", "success", "timeout", "obstacle_dist", "obstacle_present", "clean_so_far",
            "prev_obstacle_dist"]
    defaults = dict(
        d_prev=0.3, d_now=0.3, collision=False, success=False, timeout=False,
        obstacle_dist=1.0, obstacle_present=False, clean_so_far=True,
    )
    rows_kw = [{**defaults, **c[2]} for c in rows]
    for kw in rows_kw:
        kw.setdefault("prev_obstacle_dist", kw["obstacle_dist"])
    batch = {k: np.array([kw[k] for kw in rows_kw]) for k in keys}
    progress = np.linspace(0.0, 1.0, len(rows))
    ref_total, ref_terms = step_reward(np, CFG, progress=progress, **batch)
    fn = jax.jit(jax.vmap(lambda p, kw: step_reward(jnp, CFG, progress=p, **kw)))
    total, terms = fn(jnp.asarray(progress, dtype=jnp.float32), {k: jnp.asarray(v) for k, v in batch.items()})
    np.testing.assert_allclose(np.asarray(total), ref_total, atol=1e-5)
    for part in ("values", "weights"):
        ref, got = getattr(ref_terms, part), getattr(terms, part)
        assert set(got) == set(ref)  # jit hands dicts back in sorted key order
        for key in ref:
            np.testing.assert_allclose(np.asarray(got[key]), ref[key], atol=1e-5)
    succ = jax.jit(lambda c, t, th: success_flag(jnp, TASK, c, t, th))
    centre, target, theta = _pose_state(0.0, 0.0, 0.01)
    assert bool(succ(jnp.asarray(centre), jnp.asarray(target), jnp.asarray(theta)))
