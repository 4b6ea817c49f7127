"""The learning-rate schedules (sagrasp_jax/training/lr_schedule.py) on hand-made inputs."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sagrasp_jax.task import config
from sagrasp_jax.task import config_parse
from sagrasp_jax.training import lr_schedule as L
from sagrasp_jax.task.config import SAConfig

LR0 = 3e-4
SA = SAConfig(tol=0.05)
KL = L.Rule("kl-adaptive", LR0)  # brax / rsl_rl defaults: desired KL 0.01, factor 1.5, lr in [1e-5, 1e-2]


def _rule(name: str, **kw) -> L.Rule:
    return L.Rule(name, LR0, **kw)


def _xps():
    import jax.numpy as jnp

    return [np, jnp]


# ---------------------------------------------------------------------- kl-adaptive

@pytest.mark.parametrize("xp", _xps(), ids=["numpy", "jax"])
def test_kl_adaptive_above_inside_and_below_the_band(xp) -> None:
    lr = xp.float32(3e-4)
    rule = lambda kl: float(L.kl_adaptive_lr(xp, KL, lr, xp.float32(kl)))
    # above the band (KL > 2·0.01): ÷ 1.5
    assert rule(0.05) == pytest.approx(2e-4, rel=1e-6)
    assert rule(0.0201) == pytest.approx(2e-4, rel=1e-6)
    # inside the band [0.005, 0.02], ends included: unchanged
    for kl in (0.005, 0.0051, 0.01, 0.0199, 0.02):
        assert rule(kl) == pytest.approx(3e-4, rel=1e-7), kl
    # below the band (0 < KL < 0.005): × 1.5
    assert rule(0.001) == pytest.approx(4.5e-4, rel=1e-6)
    assert rule(0.0049) == pytest.approx(4.5e-4, rel=1e-6)
    # a KL of exactly 0 (no update measured) leaves the lr alone, as brax does
    assert rule(0.0) == pytest.approx(3e-4, rel=1e-7)


@pytest.mark.parametrize("xp", _xps(), ids=["numpy", "jax"])
def test_kl_adaptive_stays_in_its_bounds(xp) -> None:
    low = float(L.kl_adaptive_lr(xp, KL, xp.float32(1.2e-5), xp.float32(1.0)))
    high = float(L.kl_adaptive_lr(xp, KL, xp.float32(9e-3), xp.float32(1e-4)))
    assert low == pytest.approx(1e-5, rel=1e-6) and high == pytest.approx(1e-2, rel=1e-6)
    lr = xp.float32(LR0)
    for _ in range(100):
        lr = L.kl_adaptive_lr(xp, KL, lr, xp.float32(1e-6))
    assert float(lr) == pytest.approx(1e-2, rel=1e-6)
    for _ in range(100):
        lr = L.kl_adaptive_lr(xp, KL, lr, xp.float32(5.0))
    assert float(lr) == pytest.approx(1e-5, rel=1e-6)
    # other settings: factor 2, desired 0.02
    rule = L.Rule("kl-adaptive", LR0, desired_kl=0.02, kl_factor=2.0)
    assert float(L.kl_adaptive_lr(xp, rule, xp.float32(LR0), xp.float32(0.03))) == pytest.approx(LR0, rel=1e-7)
    assert float(L.kl_adaptive_lr(xp, rule, xp.float32(LR0), xp.float32(0.05))) == pytest.approx(LR0 / 2, rel=1e-6)
    assert float(L.kl_adaptive_lr(xp, rule, xp.float32(LR0), xp.float32(0.009))) == pytest.approx(LR0 * 2, rel=1e-6)


def test_kl_adaptive_is_elementwise() -> None:
    out = L.kl_adaptive_lr(np, KL, np.full(4, 3e-4), np.array([0.05, 0.01, 0.001, 0.0]))
    assert out == pytest.approx([2e-4, 3e-4, 4.5e-4, 3e-4])


# ---------------------------------------------------------------------- cosine and linear

@pytest.mark.parametrize("xp", _xps(), ids=["numpy", "jax"])
def test_cosine_endpoints_and_midpoint(xp) -> None:
    rule = _rule("cosine", final=1e-6)
    lr = lambda p: float(L.progress_lr(xp, rule, p))
    assert lr(0.0) == pytest.approx(LR0, rel=1e-6)
    assert lr(1.0) == pytest.approx(1e-6, rel=1e-4)
    assert lr(0.5) == pytest.approx((LR0 + 1e-6) / 2, rel=1e-6)
    assert lr(0.25) == pytest.approx(1e-6 + (LR0 - 1e-6) * (1 + math.cos(math.pi / 4)) / 2, rel=1e-6)
    assert lr(-0.5) == lr(0.0) and lr(1.5) == lr(1.0)  # progress is clipped to [0, 1]
    ps = np.linspace(0, 1, 101)
    values = np.asarray(L.progress_lr(xp, rule, ps))
    assert np.all(np.diff(values) < 0)
    # flat at both ends (zero slope), steepest in the middle
    slopes = -np.diff(values)
    assert slopes[0] < slopes[50] and slopes[-1] < slopes[50]


@pytest.mark.parametrize("xp", _xps(), ids=["numpy", "jax"])
def test_linear_endpoints(xp) -> None:
    rule = _rule("linear", final=1e-5)
    lr = lambda p: float(L.progress_lr(xp, rule, p))
    assert lr(0.0) == pytest.approx(LR0, rel=1e-6)
    assert lr(1.0) == pytest.approx(1e-5, rel=1e-5)
    assert lr(0.25) == pytest.approx(LR0 + 0.25 * (1e-5 - LR0), rel=1e-6)
    assert lr(2.0) == lr(1.0)
    # a final lr above the start makes it a linear warm-up
    assert float(L.progress_lr(xp, _rule("linear", final=1e-3), 0.5)) == pytest.approx((LR0 + 1e-3) / 2, rel=1e-6)


@pytest.mark.parametrize("name, lr0, final", [("cosine", 3e-4, 1e-6), ("cosine", 6e-4, 3e-5), ("linear", 3e-4, 1e-5),
                                               ("linear", 6e-4, 1e-3)])
def test_optax_schedules_are_the_closed_form_maths(name, lr0, final) -> None:
    """optax's cosine decay and linear schedule over progress equal the closed forms the module had
    (float64 here) within float32 rounding: a few ulp of lr0 over 100,001 progress values."""
    rule = L.Rule(name, lr0, final=final)
    p = np.linspace(0.0, 1.0, 100_001).astype(np.float32)
    got = L.progress_lr(np, rule, p)
    pd = p.astype(np.float64)
    exact = final + (lr0 - final) * 0.5 * (1 + np.cos(np.pi * pd)) if name == "cosine" else lr0 + (final - lr0) * pd
    assert isinstance(got, np.ndarray) and got.dtype == np.float32 and got.shape == p.shape
    assert np.max(np.abs(got - exact)) < 4 * np.spacing(np.float32(max(lr0, final)))


def test_other_schedules_have_no_progress_rule() -> None:
    for name in ("constant", "sa", "kl-adaptive"):
        assert L.progress_lr(np, _rule(name), np.array([0.0, 0.7, 1.0])) == pytest.approx([LR0] * 3)


# ---------------------------------------------------------------------- the host-side interface

def test_iteration_lrs() -> None:
    p = np.array([0.0, 0.5, 1.0], np.float32)
    for name in ("constant", "sa", "kl-adaptive"):
        state = L.init(_rule(name))._replace(lr=1.5e-4)
        out = L.iteration_lrs(_rule(name), state, p)
        assert out.dtype == np.float32 and out.tolist() == [np.float32(1.5e-4)] * 3
    cos = L.iteration_lrs(_rule("cosine"), L.init(_rule("cosine")), p)
    assert cos.dtype == np.float32 and cos[0] == np.float32(LR0) and cos[2] == pytest.approx(1e-6, rel=1e-4)


def test_constant_keeps_every_cycle_and_its_lr() -> None:
    rule = _rule("constant")
    state = L.init(rule)
    assert state == L.ScheduleState(lr=LR0, snapshot_lr=LR0) and state.sa is None
    for m in (1.0, 0.0, -5.0, math.nan, -10.0):
        state, d = L.end_cycle(rule, SA, state, m, 1.0, 0.999999)
        assert d.kind == "accept" and not d.decayed and not d.restore and d.new_lr == LR0
        state = L.observe(rule, state, ended_lr=np.float32(LR0), progress=0.3)
    assert state.lr == LR0 and state.cycle == 5 and state.rollbacks == 0
    state, d = L.nonfinite(rule, SA, state, progress=0.4)
    assert d.kind == "reject" and d.restore and not d.decayed and state.lr == LR0
    assert state.cycle == 6 and state.rollbacks == 1


def test_kl_adaptive_state_keeps_the_calls_lr_and_the_snapshots() -> None:
    """The host owns the lr: it keeps what the call adapted it to, and the lr of the snapshot a restore returns to."""
    rule = KL
    state = L.observe(rule, L.init(rule), ended_lr=float(np.float32(7e-4)), progress=0.2)
    assert state.lr == float(np.float32(7e-4)) and state.snapshot_lr == LR0  # the snapshot: still the start
    state, d = L.end_cycle(rule, SA, state, 1.0, 1.0, 0.5)
    assert d.kind == "accept" and not d.restore and state.lr == state.snapshot_lr == float(np.float32(7e-4))
    state = L.observe(rule, state, ended_lr=9e-4, progress=0.25)
    state, d = L.nonfinite(rule, SA, state, progress=0.3)  # back to the snapshot's lr
    assert d.restore and state.lr == float(np.float32(7e-4)) and state.rollbacks == 1
    # a state written before the host kept the snapshot's lr (checkpoints at a snapshot: the lr was its)
    old = {k: v for k, v in state._replace(lr=6e-4).to_dict().items() if k != "snapshot_lr"}
    assert L.ScheduleState.from_dict(old).restore_lr == 6e-4


@pytest.mark.parametrize("name", ["cosine", "linear"])
def test_progress_schedules_state_tracks_the_next_iteration(name: str) -> None:
    rule = _rule(name)
    state = L.observe(rule, L.init(rule), ended_lr=123.0, progress=0.5)
    assert state.lr == pytest.approx(float(L.progress_lr(np, rule, 0.5)), rel=1e-6)
    state, d = L.nonfinite(rule, SA, state, progress=1.0)
    assert d.restore and state.lr == pytest.approx(1e-6, rel=1e-4)


def test_sa_end_cycle_is_the_sa_state_machine() -> None:
    from sagrasp_jax.training import sa_schedule

    rule = _rule("sa")
    state = L.init(rule)
    assert state.sa == sa_schedule.init(LR0)
    raw = state.sa
    for m, u in ((1.0, 0.5), (0.0, 0.999999), (0.0, 0.999999), (0.0, 0.999999), (0.95, 0.1)):
        state, d = L.end_cycle(rule, SA, state, m, 1.0, u)
        raw, want = sa_schedule.update(SA, raw, m, 1.0, u)
        assert state.sa == raw and state.lr == raw.lr
        assert (d.kind, d.decayed, d.new_lr, d.temperature, d.accept_prob) == (
            want.kind, want.decayed, want.new_lr, want.temperature, want.accept_prob)
        assert d.restore == (d.kind == "reject")
    assert state.rollbacks == 3 and state.cycle == 5 and state.lr == pytest.approx(LR0 * 0.98)


def test_sa_without_rollback_rejects_but_does_not_restore() -> None:
    rule, cfg = _rule("sa"), SAConfig(tol=0.05, rollback=False)
    state, _ = L.end_cycle(rule, cfg, L.init(rule), 1.0, 1.0, 0.5)
    state, d = L.end_cycle(rule, cfg, state, 0.0, 1.0, 0.999999)
    assert d.kind == "reject" and not d.restore
    assert state.rollbacks == 0 and state.sa.n_reject == 1 and state.sa.m_acc == 1.0
    # same state machine as with rollback on: the switch acts only on what the trainer does
    with_rb, _ = L.end_cycle(rule, SA, L.end_cycle(rule, SA, L.init(rule), 1.0, 1.0, 0.5)[0], 0.0, 1.0, 0.999999)
    assert with_rb.sa == state.sa
    # a non-finite step restores whatever the switch says
    state, d = L.nonfinite(rule, cfg, state, progress=0.5)
    assert d.restore and d.decayed and state.rollbacks == 1


@pytest.mark.parametrize("name", config.LR_SCHEDULES)
def test_state_round_trips_through_json(name: str) -> None:
    rule = _rule(name)
    state = L.init(rule)
    for m in (1.0, 0.2, 0.95, 1.3):
        state, _ = L.end_cycle(rule, SA, state, m, 0.9, np.random.default_rng(3))
    state, _ = L.nonfinite(rule, SA, state, progress=0.25)
    back = L.ScheduleState.from_dict(json.loads(json.dumps(state.to_dict(), allow_nan=False)))
    assert back == state and back.to_dict() == state.to_dict()
    with pytest.raises(ValueError):
        L.ScheduleState.from_dict({**state.to_dict(), "extra": 1})
    with pytest.raises(ValueError):
        L.ScheduleState.from_dict({k: v for k, v in state.to_dict().items() if k != "cycle"})


def test_legacy_sa_state_becomes_a_schedule_state() -> None:
    from sagrasp_jax.training import sa_schedule

    sa = sa_schedule.SAState(lr=2e-4, decays=3, n_accept=7, n_reject=2, cycle=9)
    state = L.from_legacy(sa.to_dict(), "sa")
    assert state == L.ScheduleState(lr=2e-4, cycle=9, rollbacks=2, sa=sa, snapshot_lr=2e-4)
    want = L.ScheduleState(lr=2e-4, cycle=9, rollbacks=2, snapshot_lr=2e-4)
    assert L.from_legacy(sa.to_dict(), "constant") == want


# ---------------------------------------------------------------------- config

def test_rule_of_reads_one_initial_lr() -> None:
    cfg = config_parse.apply_overrides(config.get_config("paper"), ["ppo.learning_rate=1e-4", "lr.schedule=sa"])
    rule = L.rule_of(cfg)
    assert rule.lr0 == 1e-4 and L.init(rule).sa.lr == 1e-4  # SA starts where --set ppo.learning_rate says
    cfg = config_parse.apply_overrides(cfg, ["lr.schedule=kl-adaptive", "lr.desired_kl=0.02", "lr.kl_factor=2",
                                       "lr.kl_lr_min=1e-6", "lr.kl_lr_max=1e-3"])
    assert L.rule_of(cfg) == L.Rule("kl-adaptive", 1e-4, 1e-6, 0.02, 2.0, 1e-6, 1e-3)
    assert [L.Rule(n, LR0).mode for n in config.LR_SCHEDULES] == ["fixed", "fixed", "kl", "per_iteration",
                                                                   "per_iteration"]


def test_default_presets_keep_their_schedule_numbers() -> None:
    # the paper's SA from lr 3e-4, decaying ×0.98; cpu-quick starts at 6e-4 and decays ×0.96 (docs/results-archive.md §10)
    start = {"paper": (3e-4, 0.98), "cpu-quick": (6e-4, 0.96), "gpu": (3e-4, 0.98), "cpu-physics": (6e-4, 0.96),
             "gpu-physics": (3e-4, 0.98)}
    assert set(start) == set(config.PRESETS)
    for preset in config.PRESETS:
        cfg = config.get_config(preset)
        assert cfg.lr.schedule == "sa" and cfg.ppo.learning_rate == start[preset][0]
        sa = cfg.sa
        assert (sa.decay, sa.lr_min, sa.tol, sa.min_delta, sa.patience, sa.max_rollbacks, sa.t0, sa.kappa) == (
            start[preset][1], 1e-6, 0.2, 0.02, 5, 3, 0.1, 1.0)
        assert sa.metropolis and sa.rollback and sa.plateau_decay and sa.entropy_temperature


@pytest.mark.parametrize("sets,message", [
    (["lr.schedule=step"], "lr.schedule='step' is not one of constant, sa, kl-adaptive, cosine, linear"),
    (["lr.kl_factor=1"], "lr.kl_factor"),
    (["lr.kl_lr_min=1e-2", "lr.kl_lr_max=1e-3"], "lr.kl_lr_min"),
    (["ppo.learning_rate=1e-7"], "sa.lr_min"),  # SA would start below its floor
    (["sa.lr0=1e-4"], "replaced by ppo.learning_rate"),
    (["sa.enabled=false"], "replaced by lr.schedule"),
])
def test_bad_schedule_settings_are_refused(sets: list[str], message: str) -> None:
    with pytest.raises(config.ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        config_parse.apply_overrides(config.get_config("cpu-quick"), sets)
    # the SA floor only binds the sa schedule
    assert config_parse.apply_overrides(config.get_config("cpu-quick"), ["lr.schedule=constant", "ppo.learning_rate=1e-7"])


def test_configs_saved_before_lr_schedules_mean_the_same_training() -> None:
    saved = config.config_to_dict(config.get_config("cpu-quick"))
    del saved["lr"]
    sa_run = json.loads(json.dumps(saved))
    sa_run["sa"].update(enabled=True, lr0=2e-4)
    sa_run["ppo"]["learning_rate"] = 3e-4  # ignored by SA-PPO before
    cfg = config_parse.config_from_dict(sa_run)
    assert cfg.lr.schedule == "sa" and cfg.ppo.learning_rate == 2e-4
    ppo_run = json.loads(json.dumps(saved))
    ppo_run["sa"].update(enabled=False, lr0=3e-4)
    ppo_run["ppo"]["learning_rate"] = 1e-4
    cfg = config_parse.config_from_dict(ppo_run)
    assert cfg.lr.schedule == "constant" and cfg.ppo.learning_rate == 1e-4
    assert config_parse.config_from_dict(config.config_to_dict(cfg)) == cfg
    with pytest.raises(config.ConfigError, match="sa.enabled"):
        config_parse.config_from_dict({**saved, "sa": {**saved["sa"], "enabled": "yes"}})
