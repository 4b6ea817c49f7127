"""The SA-PPO learning-rate plateau schedule (docs/task.md §3) as a state machine."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from sagrasp_jax.training import sa_schedule as sa
from sagrasp_jax.task.config import SAConfig

LR0 = 3e-4  # ppo.learning_rate, where SA starts
CFG = SAConfig(tol=0.05)  # the rules on hand-made numbers: lr0 3e-4, decay 0.98, lr_min 1e-6, tol 0.05, min_delta 0.02, patience 5, rollbacks 3, T0 0.1
H = 1.0  # a fixed entropy keeps T = T0
REJECT = 0.999999  # a uniform draw that rejects any exp(-ΔE/T) < 1 - 1e-6


def _started(cfg: SAConfig = CFG, metric: float = 1.0) -> sa.SAState:
    state, dec = sa.update(cfg, sa.init(LR0), metric, H, 0.5)
    assert dec.kind == "accept"
    return state


def test_first_update_accepts_and_sets_references() -> None:
    state, dec = sa.update(CFG, sa.init(LR0), -3.25, 2.0, np.random.default_rng(0))
    assert dec.kind == "accept" and not dec.decayed
    assert math.isnan(dec.delta_e)
    assert dec.temperature == pytest.approx(CFG.t0)
    assert state.m_acc == -3.25 and state.best_m == -3.25 and state.h0 == 2.0
    assert state.snapshot_id == 1 and state.n_accept == 1 and state.cycle == 1
    assert state.lr == LR0


def test_patience_stalled_cycles_decay_exactly_once() -> None:
    state = _started()
    lrs, decays = [], []
    for _ in range(CFG.patience):
        state, dec = sa.update(CFG, state, 1.0, H, 0.5)  # flat: accepted, but no gain
        assert dec.kind == "accept"
        lrs.append(state.lr)
        decays.append(dec.decayed)
    assert decays == [False] * (CFG.patience - 1) + [True]
    assert lrs[:-1] == [3e-4] * (CFG.patience - 1)
    assert lrs[-1] == pytest.approx(3e-4 * 0.98, rel=1e-12)
    assert state.decays == 1 and state.stall == 0
    # The counter restarted: the next decay needs another full `patience` cycles.
    for i in range(CFG.patience):
        state, dec = sa.update(CFG, state, 1.0, H, 0.5)
        assert dec.decayed == (i == CFG.patience - 1)
    assert state.lr == pytest.approx(3e-4 * 0.98**2, rel=1e-12)


def test_small_gain_below_min_delta_still_stalls() -> None:
    state = _started()
    state, _ = sa.update(CFG, state, 1.0 + 0.5 * CFG.min_delta, H, 0.5)
    assert state.stall == 1 and state.best_m == 1.0
    state, _ = sa.update(CFG, state, 1.0 + 1.5 * CFG.min_delta, H, 0.5)
    assert state.stall == 0 and state.best_m == pytest.approx(1.0 + 1.5 * CFG.min_delta)


def test_within_tol_drop_is_accepted_and_moves_m_acc() -> None:
    state = _started()
    state, dec = sa.update(CFG, state, 1.0 - 0.04, H, REJECT)
    assert dec.kind == "accept" and dec.accept_prob == 1.0
    assert dec.delta_e == pytest.approx(0.04)
    assert state.m_acc == pytest.approx(0.96) and state.best_m == 1.0 and state.stall == 1


def test_max_rollbacks_rejections_decay_once() -> None:
    state = _started()
    kinds, decayed = [], []
    for _ in range(CFG.max_rollbacks):
        state, dec = sa.update(CFG, state, 0.0, H, REJECT)  # ΔE = 1, p = e^-10
        kinds.append(dec.kind)
        decayed.append(dec.decayed)
        assert dec.accept_prob == pytest.approx(math.exp(-10.0))
    assert kinds == ["reject"] * CFG.max_rollbacks
    assert decayed == [False] * (CFG.max_rollbacks - 1) + [True]
    assert state.lr == pytest.approx(3e-4 * 0.98, rel=1e-12)
    assert state.rejections == 0 and state.n_reject == 3 and state.decays == 1
    assert state.stall == 3  # the stall counter grew in the reject branch and was not reset
    assert state.m_acc == 1.0 and state.snapshot_id == 1  # rejects never move the snapshot


def test_both_triggers_in_one_cycle_decay_once() -> None:
    cfg = dataclasses.replace(CFG, patience=3, max_rollbacks=3)
    state = _started(cfg)
    for i in range(3):
        state, dec = sa.update(cfg, state, 0.0, H, REJECT)
        assert dec.decayed == (i == 2)
    assert state.lr == pytest.approx(3e-4 * 0.98, rel=1e-12)
    assert state.decays == 1 and state.stall == 0 and state.rejections == 0


def test_never_more_than_one_decay_per_cycle_random_walk() -> None:
    cfg = dataclasses.replace(CFG, patience=2, max_rollbacks=1)  # triggers fire often
    rng = np.random.default_rng(7)
    state = _started(cfg)
    n_decays = 0
    for _ in range(2000):
        old = state.lr
        state, dec = sa.update(cfg, state, float(rng.normal(1.0, 0.3)), float(rng.normal(H, 0.2)), rng)
        ratio = state.lr / old
        assert ratio == 1.0 or ratio == pytest.approx(0.98, rel=1e-12) or state.lr == cfg.lr_min
        assert dec.decayed == (state.decays == n_decays + 1)
        n_decays = state.decays
    assert n_decays > 100 and state.lr >= cfg.lr_min
    assert state.n_accept + state.n_accept_worse + state.n_reject == state.cycle == 2001


def test_lr_floor() -> None:
    state = _started()
    for _ in range(1000):
        state, dec = sa.force_reject_and_decay(CFG, state)
        assert dec.kind == "reject" and dec.decayed and state.lr >= 1e-6
    assert state.lr == 1e-6 and dec.new_lr == 1e-6
    assert state.decays == 1000 and state.n_reject == 1000
    # 3e-4·0.98^n hits 1e-6 after ceil(ln 300 / ln(1/0.98)) = 283 decays.
    state = _started()
    for _ in range(282):
        state, _ = sa.force_reject_and_decay(CFG, state)
    assert state.lr > 1e-6
    state, _ = sa.force_reject_and_decay(CFG, state)
    assert state.lr == 1e-6


def test_steadily_improving_metric_never_decays() -> None:
    state = _started(metric=0.0)
    for k in range(1, 301):
        state, dec = sa.update(CFG, state, 0.03 * k, H, REJECT)
        assert dec.kind == "accept" and not dec.decayed
    assert state.lr == LR0 and state.decays == 0 and state.stall == 0
    assert state.best_m == pytest.approx(9.0) and state.snapshot_id == 301


def test_metropolis_acceptance_frequency() -> None:
    state = _started(metric=1.0)
    delta_e = 0.1
    p = math.exp(-delta_e / CFG.t0)  # e^-1 ≈ 0.368, since H = H0 gives T = T0
    rng = np.random.default_rng(1234)
    n = 10_000
    accepted = 0
    for _ in range(n):
        _, dec = sa.update(CFG, state, 1.0 - delta_e, H, rng)
        assert dec.kind in ("accept-worse", "reject")
        assert dec.accept_prob == pytest.approx(p, rel=1e-12)
        accepted += dec.kind == "accept-worse"
    sigma = math.sqrt(n * p * (1 - p))
    assert abs(accepted - n * p) < 3 * sigma


def test_accept_worse_moves_snapshot() -> None:
    state = _started(metric=1.0)
    state, dec = sa.update(CFG, state, 0.9, H, 0.0)  # u = 0 always accepts
    assert dec.kind == "accept-worse"
    assert state.m_acc == 0.9 and state.snapshot_id == 2 and state.stall == 1
    assert state.n_accept_worse == 1 and state.rejections == 0


def test_temperature_falls_with_entropy() -> None:
    h0 = sa.gaussian_entropy(np.zeros((32, 6)))
    assert h0 == pytest.approx(6 * 0.5 * math.log(2 * math.pi * math.e))
    state = sa.init(LR0)
    assert sa.temperature(CFG, state, h0) == CFG.t0  # H0 unset: T = T0
    state, dec = sa.update(CFG, state, 1.0, h0, 0.5)
    assert state.h0 == h0 and dec.temperature == pytest.approx(CFG.t0)
    temps = [sa.temperature(CFG, state, sa.gaussian_entropy(np.full((32, 6), ls))) for ls in (0.0, -0.5, -1.0, -2.0)]
    assert all(a > b for a, b in zip(temps, temps[1:]))
    assert temps[1] == pytest.approx(CFG.t0 * math.exp(-0.5), rel=1e-12)  # ΔH/n = -0.5 per dim
    assert temps[3] == pytest.approx(CFG.t0 * math.exp(-2.0), rel=1e-12)
    # A colder policy makes the same drop less likely to be accepted.
    _, hot = sa.update(CFG, state, 0.9, h0, REJECT)
    _, cold = sa.update(CFG, state, 0.9, h0 - 6.0, REJECT)
    assert hot.accept_prob == pytest.approx(math.exp(-1.0))
    assert cold.accept_prob == pytest.approx(math.exp(-0.1 / (CFG.t0 * math.exp(-1.0))))
    assert cold.accept_prob < hot.accept_prob


def test_gaussian_entropy_std_and_log_std_agree() -> None:
    log_std = np.array([[-0.3, 0.2], [0.1, -1.0]])
    a = sa.gaussian_entropy(log_std)
    b = sa.gaussian_entropy(std=np.exp(log_std))
    assert a == pytest.approx(b, rel=1e-12)
    assert a == pytest.approx(2 * 0.5 * math.log(2 * math.pi * math.e) + (-0.3 + 0.2 + 0.1 - 1.0) / 2)
    with pytest.raises(ValueError):
        sa.gaussian_entropy()


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_metric_rejects_and_decays(bad: float) -> None:
    state = _started(metric=1.0)
    state, dec = sa.update(CFG, state, bad, H, 0.0)
    assert dec.kind == "reject" and dec.decayed and dec.accept_prob == 0.0
    assert state.lr == pytest.approx(3e-4 * 0.98, rel=1e-12)
    assert state.m_acc == 1.0 and state.snapshot_id == 1 and state.n_reject == 1


def test_non_finite_metric_before_first_evaluation() -> None:
    state, dec = sa.update(CFG, sa.init(LR0), math.nan, H, 0.5)
    assert dec.kind == "reject" and dec.decayed and state.m_acc is None and state.snapshot_id == 0
    state, dec = sa.update(CFG, state, 0.5, H, 0.5)
    assert dec.kind == "accept" and state.m_acc == 0.5


def test_round_trip_through_json() -> None:
    rng = np.random.default_rng(3)
    state = sa.init(LR0)
    blank = sa.SAState.from_dict(json.loads(json.dumps(state.to_dict(), allow_nan=False)))
    assert blank == state
    for m in (1.0, 0.2, 0.95, math.nan, 1.3, 0.1):
        state, _ = sa.update(CFG, state, m, H - 0.1, rng)
    text = json.dumps(state.to_dict(), allow_nan=False)
    back = sa.SAState.from_dict(json.loads(text))
    assert back == state
    assert back.to_dict() == state.to_dict()
    with pytest.raises(ValueError):
        sa.SAState.from_dict({**state.to_dict(), "extra": 1})


def test_same_rng_same_trajectory() -> None:
    def run(seed: int) -> list[tuple[str, bool, float]]:
        rng = np.random.default_rng(seed)
        state, out = sa.init(LR0), []
        for k in range(200):
            state, dec = sa.update(CFG, state, 1.0 - 0.01 * k + 0.1 * math.sin(k), H, rng)
            out.append((dec.kind, dec.decayed, state.lr))
        return out

    assert run(5) == run(5)


# ---------------------------------------------------------------------- ablation switches

def test_without_metropolis_a_worse_cycle_is_always_rejected() -> None:
    cfg = dataclasses.replace(CFG, metropolis=False)
    state = _started(cfg, metric=1.0)
    state, dec = sa.update(cfg, state, 1.0 - 0.06, H, 0.0)  # u = 0 would accept anything with metropolis on
    assert dec.kind == "reject" and dec.accept_prob == 0.0 and state.n_accept_worse == 0
    # within tol is still an outright accept
    state, dec = sa.update(cfg, state, 1.0 - 0.04, H, 0.0)
    assert dec.kind == "accept"
    rng, ref, metrics = np.random.default_rng(11), np.random.default_rng(11), np.random.default_rng(12)
    state = _started(cfg)
    for _ in range(500):
        state, dec = sa.update(cfg, state, float(metrics.normal(1.0, 0.3)), H, rng)
        ref.random()
        assert dec.kind != "accept-worse"
    assert state.n_accept_worse == 0 and state.n_reject > 50
    assert rng.bit_generator.state == ref.bit_generator.state  # one draw per call, used or not


def test_without_plateau_decay_rule_3_never_decays() -> None:
    cfg = dataclasses.replace(CFG, plateau_decay=False)
    state = _started(cfg)
    for _ in range(3 * CFG.patience):  # stalls
        state, dec = sa.update(cfg, state, 1.0, H, 0.5)
        assert not dec.decayed
    for _ in range(3 * CFG.max_rollbacks):  # rejections in a row
        state, dec = sa.update(cfg, state, 0.0, H, REJECT)
        assert dec.kind == "reject" and not dec.decayed
    assert state.lr == LR0 and state.decays == 0 and state.n_reject == 3 * CFG.max_rollbacks
    # the counters still count and reset as with the decay on
    on = _started()
    off = _started(cfg)
    for m, u in ((1.0, 0.5), (0.0, REJECT), (1.0, 0.5), (0.0, REJECT), (0.0, REJECT), (0.0, REJECT), (1.0, 0.5)):
        on, _ = sa.update(CFG, on, m, H, u)
        off, _ = sa.update(cfg, off, m, H, u)
        assert (off.stall, off.rejections, off.m_acc, off.n_reject) == (on.stall, on.rejections, on.m_acc, on.n_reject)
    # the non-finite escape hatch still decays
    state, dec = sa.force_reject_and_decay(cfg, state)
    assert dec.decayed and state.lr == pytest.approx(LR0 * 0.98)


def test_without_entropy_temperature_t_stays_t0() -> None:
    cfg = dataclasses.replace(CFG, entropy_temperature=False)
    state, _ = sa.update(cfg, sa.init(LR0), 1.0, 5.0, 0.5)
    for h in (5.0, 2.0, -3.0, 10.0):
        assert sa.temperature(cfg, state, h) == cfg.t0
        _, dec = sa.update(cfg, state, 0.9, h, REJECT)
        assert dec.temperature == cfg.t0 and dec.accept_prob == pytest.approx(math.exp(-0.1 / cfg.t0))
    # with it on, a colder policy lowers T (and kappa = 0 does the same as switching it off)
    assert sa.temperature(CFG, state, 2.0) < CFG.t0
    assert sa.temperature(dataclasses.replace(CFG, kappa=0.0), state, 2.0) == CFG.t0
