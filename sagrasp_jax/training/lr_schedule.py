"""Learning-rate schedules of the trainer: one interface, five rules (``lr.schedule``).

* ``constant``: ``ppo.learning_rate`` throughout (the paper's PPO); the lr never moves.
* ``sa``: docs/task.md §3's simulated-annealing plateau schedule (``sa_schedule``), on the host once
  per cycle; a reject restores the snapshot.
* ``kl-adaptive``: brax ≥ 0.14 / rsl_rl, on the device after every minibatch's KL: lr ÷
  ``kl_factor`` above 2·``desired_kl``, × ``kl_factor`` below ``desired_kl`` / 2, kept in
  [``kl_lr_min``, ``kl_lr_max``].
* ``cosine``: lr0 → ``lr.final`` by a half cosine in progress p, set before every iteration.
* ``linear``: lr0 → ``lr.final`` linearly in p, set before every iteration.

p = env steps done / ``train.total_steps`` (the progress the reward weights read).  Every
schedule starts at ``ppo.learning_rate``.

One owner: the host's :class:`ScheduleState` is the learning rate.  Each jitted call is told the lr of
its iterations (``iteration_lrs``, an argument of the call); the optimizer state holds none.  Only
``kl-adaptive`` moves the lr inside a call (after every minibatch): it starts from the host's lr and the
call returns the lr it ended at, which the host stores (``observe``).

Pure functions over a typed :class:`ScheduleState` (a NamedTuple, like brax's training
states), host-side, with the two per-step rules for any array module (``progress_lr(xp, …)``,
``kl_adaptive_lr(xp, …)``: numpy on the host and in the tests, jax.numpy for ``kl_adaptive_lr``
inside the jitted cycle, ``ppo.sgd_epochs``).  ``cosine`` and ``linear`` are optax's
``cosine_decay_schedule`` and ``linear_schedule`` over progress (one "step" = the whole budget):
the same maths as the formulas they replaced (lr_f + (lr0 − lr_f)·(1 + cos πp)/2, lr0 + (lr_f − lr0)·p),
equal within float32 rounding (a few ulp; ``tests/training/test_lr_schedule.py``), not bit for bit.  The trainer calls

* :func:`iteration_lrs` before a jitted call: the lr of each of its iterations, passed to the call
  (``kl-adaptive``: the lr its first iteration starts from);
* :func:`observe` after a call whose iterations were all finite: the lr the next iteration
  starts from (``kl-adaptive``: the one the call returned as its last iteration's);
* :func:`end_cycle` at the end of each cycle with the evaluation metric and the entropy:
  ``sa`` decides (accept / accept-worse / reject, maybe decay), the others always keep;
* :func:`nonfinite` when an iteration went non-finite: restore the snapshot (``sa`` also
  decays; ``kl-adaptive`` takes the snapshot's lr, ``ScheduleState.snapshot_lr``).

The whole state, SA's included, goes into the checkpoint (``to_dict`` / ``from_dict``), and the
``cosine`` / ``linear`` lr is a function of the checkpointed step counter, so a resumed run
continues exactly, whatever the schedule.  (Checkpoints written before the host owned the lr also
hold it in the optimizer state; ``checkpoint.restore_tree`` drops that copy.)
"""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple

import numpy as np
import optax

from sagrasp_jax.training import sa_schedule
from sagrasp_jax.task.config import LR_SCHEDULES, Config, SAConfig
from sagrasp_jax.task import robots
from sagrasp_jax.training.sa_schedule import DecisionKind, SAState

SCHEDULES = LR_SCHEDULES
# What a jitted call does with the lrs the host gives it (``ppo.make_cycle``'s ``lr_rule.mode``): "fixed" = the
# host's one lr for every iteration; "per_iteration" = each iteration's from ``iteration_lrs``; "kl" = starts
# at the host's lr, adapted on the device after every minibatch and returned to the host.
LR_MODES = {"constant": "fixed", "sa": "fixed", "kl-adaptive": "kl", "cosine": "per_iteration",
            "linear": "per_iteration"}


class Rule(NamedTuple):
    """A schedule's fixed parameters (from ``ppo.learning_rate`` and the ``lr`` section)."""

    name: str
    lr0: float
    final: float = 1e-6
    desired_kl: float = 0.01
    kl_factor: float = 1.5
    kl_lr_min: float = 1e-5
    kl_lr_max: float = 1e-2

    @property
    def mode(self) -> str:
        return LR_MODES[self.name]


def rule_of(cfg: Config) -> Rule:
    lr = cfg.lr
    if lr.schedule not in SCHEDULES:
        raise ValueError(f"unknown lr schedule {lr.schedule!r}; valid: {', '.join(SCHEDULES)}")
    return Rule(name=lr.schedule, lr0=float(cfg.ppo.learning_rate), final=float(lr.final),
                desired_kl=float(lr.desired_kl), kl_factor=float(lr.kl_factor), kl_lr_min=float(lr.kl_lr_min),
                kl_lr_max=float(lr.kl_lr_max))


class ScheduleState(NamedTuple):
    """What the schedule carries between cycles (the checkpoint holds it)."""

    lr: float  # the learning rate the next PPO iteration starts from: the one owner of the lr
    cycle: int = 0  # cycles ended (end_cycle or nonfinite)
    rollbacks: int = 0  # times the trainer restored the snapshot (sa rejects with rollback on, non-finite steps)
    sa: SAState | None = None  # the SA state machine (schedule "sa" only)
    snapshot_lr: float | None = None  # the lr when the snapshot was taken, a kl-adaptive restore's (None: ``lr``)

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON dict."""
        return {"lr": self.lr, "cycle": self.cycle, "rollbacks": self.rollbacks,
                "sa": None if self.sa is None else self.sa.to_dict(), "snapshot_lr": self.snapshot_lr}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ScheduleState:
        """Inverse of :meth:`to_dict`; refuses unknown or missing keys.  A dict written before ``snapshot_lr``
        (the lr lived in the optimizer state too) has none: its checkpoints were written when the snapshot had
        just been taken or restored (a cycle's end, a non-finite step), so the snapshot's lr was ``lr``."""
        required = set(cls._fields) - {"snapshot_lr"}
        if not isinstance(data, dict) or not required <= set(data) or not set(data) <= set(cls._fields):
            keys = sorted(data) if isinstance(data, dict) else type(data).__name__
            raise ValueError(f"ScheduleState.from_dict: expected keys {sorted(cls._fields)}, got {keys}")
        sa = None if data["sa"] is None else SAState.from_dict(data["sa"])
        return cls(lr=float(data["lr"]), cycle=int(data["cycle"]), rollbacks=int(data["rollbacks"]), sa=sa,
                   snapshot_lr=float(data.get("snapshot_lr", data["lr"])))

    @property
    def restore_lr(self) -> float:
        """The lr the snapshot was taken at."""
        return self.lr if self.snapshot_lr is None else self.snapshot_lr


class CycleOutcome(NamedTuple):
    """What the trainer does with one cycle's updates under any lr schedule: keep or restore, the next lr."""

    kind: DecisionKind  # accept | accept-worse | reject
    decayed: bool  # the lr was decayed by this decision (sa only)
    new_lr: float
    restore: bool  # the trainer restores the snapshot (a reject with rollback on, or a non-finite step)
    temperature: float = math.nan  # sa: the temperature used; NaN otherwise
    delta_e: float = math.nan  # sa: M_acc − M
    accept_prob: float = 1.0  # sa: probability with which this outcome could be accepted

    @property
    def kept(self) -> bool:
        """The cycle's updates stay: the snapshot moves to them (an accept, or an accept-worse)."""
        return not self.restore and self.kind != "reject"


# ------------------------------------------------------------------ the per-step rules (any array module)

def optax_schedule(rule: Rule) -> Callable[[Any], Any] | None:
    """optax's schedule of ``rule`` over progress p ∈ [0, 1] (``None`` for schedules that are not a function of p):
    cosine lr_f + (lr0 − lr_f)·(1 + cos πp)/2, linear lr0 + (lr_f − lr0)·p (a warm-up when lr_f > lr0)."""
    if rule.name == "cosine":
        return optax.cosine_decay_schedule(rule.lr0, decay_steps=1, alpha=rule.final / rule.lr0)
    if rule.name == "linear":
        return optax.linear_schedule(rule.lr0, rule.final, transition_steps=1)
    return None


def progress_lr(xp: Any, rule: Rule, progress: Any) -> Any:
    """The lr (float32, an ``xp`` array) at training progress p ∈ [0, 1] (clipped): ``optax_schedule``'s for
    cosine and linear; any other schedule starts at lr0 and this returns lr0."""
    p = xp.clip(xp.asarray(progress, dtype=xp.float32), 0.0, 1.0)
    schedule = optax_schedule(rule)
    if schedule is not None:
        return xp.asarray(schedule(p), dtype=xp.float32)
    return xp.full_like(p, rule.lr0)


def kl_adaptive_lr(xp: Any, rule: Rule, lr: Any, kl: Any) -> Any:
    """brax's ``adaptive_kl_learning_rate`` (rsl_rl's rule): lr ÷ kl_factor (not below kl_lr_min) when
    KL > 2·desired_kl, lr × kl_factor (not above kl_lr_max) when 0 < KL < desired_kl / 2, else lr."""
    lr = xp.where(kl > 2.0 * rule.desired_kl, xp.maximum(rule.kl_lr_min, lr / rule.kl_factor), lr)
    return xp.where((kl < rule.desired_kl / 2.0) & (kl > 0.0), xp.minimum(rule.kl_lr_max, lr * rule.kl_factor), lr)


# ------------------------------------------------------------------ the host-side interface

def init(rule: Rule) -> ScheduleState:
    """Fresh state at ``rule.lr0`` (``sa``: with a fresh SA state machine)."""
    sa = sa_schedule.init(rule.lr0) if rule.name == "sa" else None
    return ScheduleState(lr=rule.lr0, sa=sa, snapshot_lr=rule.lr0)


def iteration_lrs(rule: Rule, state: ScheduleState, progress: np.ndarray) -> np.ndarray:
    """float32 lr of each iteration of the next jitted call (its argument), given their progress values: the
    rule's for ``per_iteration`` schedules, the state's lr otherwise (``kl``: where the call starts adapting)."""
    if rule.mode == "per_iteration":
        return np.asarray(progress_lr(np, rule, np.asarray(progress, np.float32)), np.float32)
    return np.full(np.shape(progress), state.lr, np.float32)


def _next_lr(rule: Rule, state: ScheduleState, kl_lr: float, progress: float) -> float:
    if rule.mode == "per_iteration":
        return float(progress_lr(np, rule, np.float32(progress)))
    if rule.mode == "kl":
        return float(kl_lr)
    return state.lr


def observe(rule: Rule, state: ScheduleState, *, ended_lr: float, progress: float) -> ScheduleState:
    """After a jitted call that ended finite: ``ended_lr`` is the lr the call returned for its last
    iteration (what ``kl-adaptive`` adapted it to; the host's own lr otherwise), ``progress`` that of the
    next iteration."""
    return state._replace(lr=_next_lr(rule, state, ended_lr, progress))


def end_cycle(rule: Rule, sa_cfg: SAConfig, state: ScheduleState, metric: float, entropy: float,
              rng: np.random.Generator | float, n_actions: int = robots.DEFAULT_DOF) -> tuple[ScheduleState, CycleOutcome]:
    """The end-of-cycle decision.  ``sa``: docs/task.md §3 (``sa_schedule.update``: one uniform draw of
    ``rng``); with ``sa.rollback`` off a reject does not restore.  Every other schedule keeps the
    cycle's updates (and draws nothing)."""
    if rule.name != "sa":  # kept: the snapshot moves to the current state, and its lr with it
        kept = state._replace(cycle=state.cycle + 1, snapshot_lr=state.lr)
        return kept, CycleOutcome("accept", False, state.lr, False)
    sa, d = sa_schedule.update(sa_cfg, state.sa, metric, entropy, rng, n_actions=n_actions)
    restore = d.kind == "reject" and sa_cfg.rollback
    outcome = CycleOutcome(d.kind, d.decayed, d.new_lr, restore, d.temperature, d.delta_e, d.accept_prob)
    new = state._replace(lr=sa.lr, cycle=state.cycle + 1, rollbacks=state.rollbacks + int(restore), sa=sa,
                         snapshot_lr=sa.lr if outcome.kept else state.snapshot_lr)
    return new, outcome


def nonfinite(rule: Rule, sa_cfg: SAConfig, state: ScheduleState, *,
              progress: float) -> tuple[ScheduleState, CycleOutcome]:
    """A non-finite loss or parameter: the trainer restores the snapshot and starts a fresh cycle.
    ``sa`` also decays the lr (``sa_schedule.force_reject_and_decay``); ``kl-adaptive`` goes on from
    the snapshot's lr (``state.restore_lr``), ``cosine`` / ``linear`` from the rule's lr at ``progress``,
    ``constant`` as is."""
    if rule.name == "sa":
        sa, d = sa_schedule.force_reject_and_decay(sa_cfg, state.sa)
        new = state._replace(lr=sa.lr, cycle=state.cycle + 1, rollbacks=state.rollbacks + 1, sa=sa)
        return new, CycleOutcome(d.kind, d.decayed, d.new_lr, True, d.temperature, d.delta_e, d.accept_prob)
    lr = _next_lr(rule, state, state.restore_lr, progress)
    new = state._replace(lr=lr, cycle=state.cycle + 1, rollbacks=state.rollbacks + 1)
    return new, CycleOutcome("reject", False, lr, True, accept_prob=0.0)


def from_legacy(sa_state: dict[str, Any], name: str) -> ScheduleState:
    """The state of a checkpoint written before lr schedules (its host state held ``sa_state`` only,
    also for plain PPO, whose lr never moved)."""
    sa = SAState.from_dict(sa_state)
    if name == "sa":
        return ScheduleState(lr=sa.lr, cycle=sa.cycle, rollbacks=sa.n_reject, sa=sa, snapshot_lr=sa.lr)
    return ScheduleState(lr=sa.lr, cycle=sa.cycle, rollbacks=sa.n_reject, snapshot_lr=sa.lr)
