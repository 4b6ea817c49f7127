"""Simulated-annealing learning-rate plateau schedule of SA-PPO (docs/task.md §3).

A small, pure, host-side state machine (the ``sa`` schedule of ``sagrasp_jax.training.lr_schedule``,
which hands it the trainer's calls): :func:`update` runs once per *cycle* (never per PPO
iteration) with the cycle's evaluation metric M and the mean policy entropy H, and returns a
new :class:`SAState` plus an :class:`AnnealOutcome` that says what to do with the parameters:

* ``"accept"`` / ``"accept-worse"``: take a snapshot (params, optimizer state,
  observation normaliser); ``state.snapshot_id`` names it.
* ``"reject"``: restore params, optimizer state and normaliser from the last
  snapshot (envs keep running).
* ``decision.decayed``: set the optimizer learning rate to ``decision.new_lr``.

Nothing here is jitted or imports jax: it runs once per cycle, and keeping it plain
Python makes it trivially deterministic and checkpointable (a NamedTuple, like brax's
training states; ``to_dict`` / ``from_dict`` are JSON-safe).  Randomness enters only through the explicit ``rng``
argument of :func:`update`, which consumes exactly one uniform draw per call so a
resumed run stays in step with an uninterrupted one.

Snapshot id 0 means "the initial parameters": the trainer should snapshot them before
the first cycle so that a reject before the first accepted evaluation (only possible
through a non-finite metric or loss) has something to restore.

The ablation switches of ``SAConfig`` (``metropolis``, ``plateau_decay``,
``entropy_temperature``) act here; ``rollback`` acts in the trainer (a reject is still a
reject here, the trainer just keeps its parameters).
"""

from __future__ import annotations

import math
from typing import Any, Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from sagrasp_jax.task.config import SAConfig
from sagrasp_jax.task import robots

DecisionKind = Literal["accept", "accept-worse", "reject"]

_HALF_LOG_2PI_E = 0.5 * math.log(2.0 * math.pi * math.e)


class SAState(NamedTuple):
    """Everything the schedule carries between cycles (goes into checkpoints).

    ``best_m`` is the reference for stall detection: it moves only when an accepted
    metric beats it by more than ``min_delta`` (as in early stopping), so a slow creep
    of sub-``min_delta`` gains adds up until it counts instead of being swallowed.
    """

    lr: float
    decays: int = 0  # lr decays so far (scheduled or forced)
    m_acc: float | None = None  # metric of the last accepted snapshot; None before the first
    best_m: float | None = None
    stall: int = 0  # cycles without a gain over best_m of more than min_delta
    rejections: int = 0  # rejections in a row
    h0: float | None = None  # entropy at the first update; temperature reference
    temperature: float | None = None  # temperature used by the last update
    snapshot_id: int = 0  # 0 = initial parameters; +1 per accepted snapshot
    n_accept: int = 0
    n_accept_worse: int = 0
    n_reject: int = 0
    cycle: int = 0  # decisions taken so far (update or force_reject_and_decay)

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON dict (no NaN: unset values are None)."""
        return dict(self._asdict())

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SAState:
        """Inverse of :meth:`to_dict`; refuses unknown or missing keys so a stale checkpoint fails loudly."""
        names = set(cls._fields)
        unknown = set(data) - names
        missing = names - set(data)
        if unknown or missing:
            raise ValueError(
                f"SAState.from_dict: unknown keys {sorted(unknown)}, missing keys {sorted(missing)}"
            )
        ints = {"decays", "stall", "rejections", "snapshot_id", "n_accept", "n_accept_worse", "n_reject", "cycle"}
        kwargs: dict[str, Any] = {}
        for name in names:
            value = data[name]
            if name in ints:
                kwargs[name] = int(value)
            elif value is None:
                kwargs[name] = None
            else:
                kwargs[name] = float(value)
        if kwargs["lr"] is None:
            raise ValueError("SAState.from_dict: lr must not be None")
        return cls(**kwargs)


class AnnealOutcome(NamedTuple):
    """What the SA rule decided for one cycle (accept, accept a worse one, reject; decay), for lr_schedule."""

    kind: DecisionKind
    decayed: bool
    new_lr: float
    temperature: float  # NaN when no entropy was available (forced reject)
    delta_e: float  # M_acc - M; NaN on the first evaluation or a non-finite metric
    accept_prob: float  # probability with which this outcome could be accepted


def init(lr0: float, h0: float | None = None) -> SAState:
    """Fresh schedule at ``lr0`` (``ppo.learning_rate``); ``h0`` may be given if the trainer measures
    the initial entropy itself."""
    return SAState(lr=float(lr0), h0=None if h0 is None else float(h0))


def gaussian_entropy(log_std: ArrayLike | None = None, *, std: ArrayLike | None = None) -> float:
    """Closed-form entropy of a diagonal Gaussian, summed over the last axis, averaged over the rest.

    This is the *pre-tanh* entropy (the tanh squashing has no closed form and would
    make H depend on the mean).  Give exactly one of ``log_std`` and ``std``; the
    trainer evaluates the policy's scale on the cycle's observations and passes the
    batch here, so H = mean over observations of sum_i (½·log(2πe) + log σ_i).
    """
    if (log_std is None) == (std is None):
        raise ValueError("gaussian_entropy: give exactly one of log_std and std")
    if log_std is None:
        log_sigma = np.log(np.asarray(std, dtype=np.float64))
    else:
        log_sigma = np.asarray(log_std, dtype=np.float64)
    log_sigma = np.atleast_1d(log_sigma)
    per_sample = np.sum(_HALF_LOG_2PI_E + log_sigma, axis=-1)
    return float(np.mean(per_sample))


def temperature(cfg: SAConfig, state: SAState, entropy: float, n_actions: int = robots.DEFAULT_DOF) -> float:
    """T = T0·exp(κ·(H − H0)/n_actions): hot while the policy explores, cold as it converges.

    Before H0 is known (first call) H0 = H, so T = T0.  Dividing by n_actions makes κ a
    per-dimension rate, independent of the action size.  With ``entropy_temperature`` off,
    T = T0 always.
    """
    if not cfg.entropy_temperature:
        return float(cfg.t0)
    h = float(entropy)
    h0 = h if state.h0 is None else state.h0
    return float(cfg.t0 * math.exp(cfg.kappa * (h - h0) / n_actions))


def _uniform(rng: np.random.Generator | float) -> float:
    if isinstance(rng, np.random.Generator):
        return float(rng.random())
    u = float(rng)
    if not 0.0 <= u < 1.0:
        raise ValueError(f"uniform draw must be in [0, 1), got {u}")
    return u


def _decayed_lr(cfg: SAConfig, lr: float) -> float:
    return max(lr * cfg.decay, cfg.lr_min)


def force_reject_and_decay(cfg: SAConfig, state: SAState) -> tuple[SAState, AnnealOutcome]:
    """Reject (restore the snapshot) and decay lr unconditionally: the non-finite escape hatch.

    The trainer calls this when a loss, gradient or parameter goes non-finite;
    :func:`update` calls it for a non-finite metric or entropy.  It ends the cycle (the
    trainer starts a fresh one from the restored snapshot) and resets both counters:
    the lr just changed, so patience and the rollback count start over.  It is an escape
    hatch, not rule 3: it decays even with ``plateau_decay`` off.
    """
    lr = _decayed_lr(cfg, state.lr)
    new = state._replace(
        lr=lr,
        decays=state.decays + 1,
        stall=0,
        rejections=0,
        n_reject=state.n_reject + 1,
        cycle=state.cycle + 1,
    )
    last_t = math.nan if state.temperature is None else state.temperature
    return new, AnnealOutcome("reject", True, lr, last_t, math.nan, 0.0)


def update(
    cfg: SAConfig,
    state: SAState,
    metric: float,
    entropy: float,
    rng: np.random.Generator | float,
    n_actions: int = robots.DEFAULT_DOF,
) -> tuple[SAState, AnnealOutcome]:
    """One end-of-cycle decision (docs/task.md §3 rules 1-3).

    ``rng`` is a NumPy Generator (exactly one ``random()`` draw per call, used or not)
    or an already drawn uniform in [0, 1).  The first finite evaluation is always
    accepted.  A non-finite metric or entropy is a reject plus a forced decay.
    ``cfg.metropolis`` off: a worse cycle is never accepted (probability 0; the draw is
    still consumed); ``cfg.plateau_decay`` off: rule 3 never decays the lr (its counters
    still count and reset as usual).
    """
    u = _uniform(rng)
    m = float(metric)
    h = float(entropy)

    if not (math.isfinite(m) and math.isfinite(h)):
        return force_reject_and_decay(cfg, state)

    h0 = h if state.h0 is None else state.h0
    state = state._replace(h0=h0)
    t = temperature(cfg, state, h, n_actions)

    if state.m_acc is None:
        # First evaluation: nothing to compare with, so it defines the reference.
        new = state._replace(
            m_acc=m,
            best_m=m,
            stall=0,
            rejections=0,
            temperature=t,
            snapshot_id=state.snapshot_id + 1,
            n_accept=state.n_accept + 1,
            cycle=state.cycle + 1,
        )
        return new, AnnealOutcome("accept", False, state.lr, t, math.nan, 1.0)

    delta_e = state.m_acc - m
    m_acc, best_m = state.m_acc, state.best_m
    stall, rejections, snapshot_id = state.stall, state.rejections, state.snapshot_id
    n_accept, n_accept_worse, n_reject = state.n_accept, state.n_accept_worse, state.n_reject

    if delta_e <= cfg.tol:
        # Rule 1: within tolerance or better -> accept; only a real gain over best resets patience.
        kind: DecisionKind = "accept"
        accept_prob = 1.0
        m_acc = m
        snapshot_id += 1
        n_accept += 1
        rejections = 0
        if best_m is None or m > best_m + cfg.min_delta:
            best_m = m
            stall = 0
        else:
            stall += 1
    else:
        # Rule 2: Metropolis; the stall counter grows whatever the draw says.
        accept_prob = math.exp(-delta_e / t) if cfg.metropolis and t > 0.0 else 0.0
        stall += 1
        if u < accept_prob:
            kind = "accept-worse"
            m_acc = m
            snapshot_id += 1
            n_accept_worse += 1
            rejections = 0
        else:
            kind = "reject"
            n_reject += 1
            rejections += 1

    # Rule 3: at most one decay per cycle; reset whichever counter(s) triggered it.
    stall_fired = stall >= cfg.patience
    rollback_fired = rejections >= cfg.max_rollbacks
    decayed = cfg.plateau_decay and (stall_fired or rollback_fired)
    lr = _decayed_lr(cfg, state.lr) if decayed else state.lr
    if stall_fired:
        stall = 0
    if rollback_fired:
        rejections = 0

    new = state._replace(
        lr=lr,
        decays=state.decays + int(decayed),
        m_acc=m_acc,
        best_m=best_m,
        stall=stall,
        rejections=rejections,
        temperature=t,
        snapshot_id=snapshot_id,
        n_accept=n_accept,
        n_accept_worse=n_accept_worse,
        n_reject=n_reject,
        cycle=state.cycle + 1,
    )
    return new, AnnealOutcome(kind, decayed, lr, t, delta_e, accept_prob)
