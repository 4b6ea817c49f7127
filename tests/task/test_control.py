"""control_step: scaling, slow-down, wrist fine-tuning, caps and NumPy/JAX agreement."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401  (sets XLA flags before jax is imported)
from sagrasp_jax.task.config import HOME_Q, ControlConfig
from sagrasp_jax.task.control import alignment_correction, control_step, gripper_state
from sagrasp_jax.task.robot import forward_kinematics, load_robot

CFG = ControlConfig()
ROBOT = load_robot()
HOME = np.array(HOME_Q)
ACTION = np.array([0.5, -1.0, 2.0, -3.0, 0.25, 0.0])  # includes out-of-range entries
CLIPPED = np.array([0.5, -1.0, 1.0, -1.0, 0.25, 0.0])


def tilted(dq5: float) -> np.ndarray:
    """Home pose with wrist 2 (q5) turned: a pure tilt of dq5 rad in one vertical plane."""
    q = HOME.copy()
    q[4] += dq5
    return q


def target_below(q: np.ndarray, dist: float) -> np.ndarray:
    centre, _ = gripper_state(np, ROBOT, q)
    return centre - np.array([0.0, 0.0, dist])


def test_home_pose_is_the_documented_start() -> None:
    centre, theta = gripper_state(np, ROBOT, HOME)
    np.testing.assert_allclose(centre, [0.0, -0.30, 0.35], atol=1e-6)
    assert theta < math.radians(1.0)


def test_far_from_target_is_pure_scaling() -> None:
    res = control_step(np, ROBOT, CFG, HOME, HOME, np.array([0.3, -0.5, 0.05]), ACTION)
    np.testing.assert_allclose(res.dq, 0.05 * CLIPPED, atol=1e-15)
    np.testing.assert_allclose(res.q_target, HOME + 0.05 * CLIPPED, atol=1e-15)
    assert not res.slowed and not res.finetuned
    np.testing.assert_array_equal(res.correction, [0.0, 0.0])


def test_target_accumulates_not_rebased_on_measured_q() -> None:
    q_target = HOME + 0.01
    res = control_step(np, ROBOT, CFG, q_target, HOME, np.array([0.3, -0.5, 0.05]), np.ones(6))
    np.testing.assert_allclose(res.q_target, HOME + 0.01 + 0.05, atol=1e-15)


@pytest.mark.parametrize("dist, factor", [(0.07, 0.3), (0.079, 0.3), (0.081, 1.0), (0.09, 1.0)])
def test_slowdown_inside_d_slow(dist: float, factor: float) -> None:
    res = control_step(np, ROBOT, CFG, HOME, HOME, target_below(HOME, dist), ACTION)
    assert bool(res.slowed) == (factor < 1.0)
    assert not res.finetuned  # home pose is vertical
    np.testing.assert_allclose(res.dq, factor * 0.05 * CLIPPED, atol=1e-15)


def test_slowdown_switch() -> None:
    cfg = dataclasses.replace(CFG, slowdown_enabled=False)
    res = control_step(np, ROBOT, cfg, HOME, HOME, target_below(HOME, 0.05), ACTION)
    assert not res.slowed
    np.testing.assert_allclose(res.dq, 0.05 * CLIPPED, atol=1e-15)


@pytest.mark.parametrize(
    "dq5, dist, active",
    [
        (0.30, 0.09, True),  # 17.2° tilt, inside d_fine
        (0.30, 0.11, False),  # outside d_fine
        (0.10, 0.09, False),  # 5.7° tilt: below the 10° gate
        (0.17, 0.09, False),  # 9.74°
        (0.18, 0.09, True),  # 10.31°
    ],
)
def test_finetune_gate(dq5: float, dist: float, active: bool) -> None:
    q = tilted(dq5)
    res = control_step(np, ROBOT, CFG, q, q, target_below(q, dist), np.zeros(6))
    assert bool(res.finetuned) == active
    assert not res.slowed
    if active:
        # Turning q5 back undoes the tilt; the full step (≈ dq5) is clipped to c = 0.015.
        np.testing.assert_allclose(res.correction, [0.0, -0.015], atol=1e-12)
        np.testing.assert_allclose(res.dq, [0, 0, 0, 0, -0.015, 0], atol=1e-12)
    else:
        np.testing.assert_array_equal(res.correction, [0.0, 0.0])
        np.testing.assert_array_equal(res.dq, np.zeros(6))


def test_unclipped_correction_matches_damped_least_squares() -> None:
    """Check the closed-form 2x2 solve against numpy.linalg on the formula of docs/task.md §2.1."""
    q = tilted(0.3)
    q[3] += 0.2  # make wrist 1 contribute as well
    kin = forward_kinematics(np, ROBOT, q)
    a = kin.joint_axes[3:5].T  # 3x2
    omega = np.cross(kin.approach_axis, [0.0, 0.0, -1.0])
    expected = np.linalg.solve(a.T @ a + 0.05**2 * np.eye(2), a.T @ omega)
    cfg = dataclasses.replace(CFG, fine_clip=10.0)
    got = alignment_correction(np, cfg, kin.joint_axes[3:5], kin.approach_axis)
    np.testing.assert_allclose(got, expected, atol=1e-14)
    assert np.max(np.abs(expected)) > 0.1  # the unclipped step is large: the clip matters
    clipped = alignment_correction(np, CFG, kin.joint_axes[3:5], kin.approach_axis)
    np.testing.assert_allclose(clipped, np.clip(expected, -0.015, 0.015), atol=1e-14)


def test_finetune_keeps_per_joint_cap_hard() -> None:
    q = tilted(0.3)
    action = np.array([0.0, 0.0, 0.0, 1.0, -1.0, 0.0])
    res = control_step(np, ROBOT, CFG, q, q, target_below(q, 0.09), action)
    assert res.finetuned
    # q4: 0.05 + ~0 stays 0.05; q5: -0.05 - 0.015 is capped to -0.05.
    np.testing.assert_allclose(res.dq[3:5], [0.05, -0.05], atol=1e-12)
    res = control_step(np, ROBOT, CFG, q, q, target_below(q, 0.09), -action)
    np.testing.assert_allclose(res.dq[3:5], [-0.05, 0.05 - 0.015], atol=1e-12)
    assert np.all(np.abs(res.dq) <= CFG.q_max + 1e-15)


def test_finetune_after_slowdown_and_reduces_tilt() -> None:
    q = tilted(0.3)
    _, tilt_before = gripper_state(np, ROBOT, q)
    res = control_step(np, ROBOT, CFG, q, q, target_below(q, 0.06), np.zeros(6))
    assert res.slowed and res.finetuned
    _, tilt_after = gripper_state(np, ROBOT, res.q_target)
    assert tilt_after < tilt_before
    np.testing.assert_allclose(tilt_before - tilt_after, 0.015, atol=1e-9)
    # With a policy action the slowed Δq gets the correction on top: 0.3·0.05 − 0.015.
    res = control_step(np, ROBOT, CFG, q, q, target_below(q, 0.06), np.array([0, 0, 0, 0, 1.0, 0]))
    np.testing.assert_allclose(res.dq[4], 0.3 * 0.05 - 0.015, atol=1e-12)


def test_finetune_switch() -> None:
    cfg = dataclasses.replace(CFG, finetune_enabled=False)
    q = tilted(0.3)
    res = control_step(np, ROBOT, cfg, q, q, target_below(q, 0.09), np.zeros(6))
    assert not res.finetuned
    np.testing.assert_array_equal(res.dq, np.zeros(6))
    np.testing.assert_array_equal(res.correction, [0.0, 0.0])


def test_joint_limit_clip() -> None:
    q_target = HOME.copy()
    q_target[0] = 3.04
    q_target[2] = -3.03
    res = control_step(np, ROBOT, CFG, q_target, HOME, np.array([0.3, -0.5, 0.05]), np.array([1, 0, -1, 0, 0, 0.0]))
    assert res.q_target[0] == pytest.approx(3.0543)
    assert res.q_target[2] == pytest.approx(-3.0543)
    np.testing.assert_allclose(res.dq[[0, 2]], [0.05, -0.05])  # dq is the request, before the limit clip


def test_numpy_batch_matches_single_calls() -> None:
    qs = np.stack([HOME, tilted(0.3), tilted(0.1)])
    targets = np.stack([target_below(HOME, 0.5), target_below(qs[1], 0.09), target_below(qs[2], 0.05)])
    actions = np.stack([ACTION, np.zeros(6), -ACTION])
    batch = control_step(np, ROBOT, CFG, qs, qs, targets, actions)
    for i in range(3):
        single = control_step(np, ROBOT, CFG, qs[i], qs[i], targets[i], actions[i])
        for b, s in zip(batch, single):
            np.testing.assert_allclose(b[i], s, atol=1e-15)


CASES = [
    (HOME, 0.5, ACTION),
    (HOME, 0.05, ACTION),
    (tilted(0.3), 0.09, np.zeros(6)),
    (tilted(0.3), 0.06, np.array([0.2, -0.4, 0.9, 1.0, -1.0, 0.3])),
    (tilted(0.1), 0.09, -ACTION),
]


@pytest.mark.parametrize("case", range(len(CASES)))
def test_numpy_and_jax_jit_agree_x64(x64, case: int) -> None:
    jax = x64
    import jax.numpy as jnp

    q, dist, action = CASES[case]
    target = target_below(q, dist)
    q_target = q + 0.003
    ref = control_step(np, ROBOT, CFG, q_target, q, target, action)
    fn = jax.jit(lambda qt, qn, t, a: control_step(jnp, ROBOT, CFG, qt, qn, t, a))
    got = fn(jnp.asarray(q_target), jnp.asarray(q), jnp.asarray(target), jnp.asarray(action))
    assert got.q_target.dtype == jnp.float64
    for r, g in zip(ref, got):
        np.testing.assert_allclose(np.asarray(g), r, atol=1e-12, rtol=0)


def test_jax_vmap_float32_matches_numpy() -> None:
    import jax
    import jax.numpy as jnp

    qs = np.stack([c[0] for c in CASES])
    targets = np.stack([target_below(c[0], c[1]) for c in CASES])
    actions = np.stack([c[2] for c in CASES])
    ref = control_step(np, ROBOT, CFG, qs, qs, targets, actions)
    fn = jax.jit(jax.vmap(lambda qt, qn, t, a: control_step(jnp, ROBOT, CFG, qt, qn, t, a)))
    got = fn(*(jnp.asarray(x, dtype=jnp.float32) for x in (qs, qs, targets, actions)))
    for r, g in zip(ref, got):
        np.testing.assert_allclose(np.asarray(g, dtype=float), r, atol=1e-5, rtol=0)


def test_shared_maths_does_not_import_jax() -> None:
    """The deployment runtime runs control/reward without jax installed."""
    import subprocess
    import sys

    code = "import sys, sagrasp_jax.task.control, sagrasp_jax.task.reward; assert 'jax' not in sys.modules, 'jax imported'"
    subprocess.run([sys.executable, "-c", code], check=True)
