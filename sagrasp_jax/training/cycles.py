"""The training's schedule: cycles of PPO iterations, and what each call's and each cycle's results decide.

A run is ``Schedule.num_cycles`` cycles of whole iterations.  A jitted call runs a seed's iterations up to its
cycle's end (``call_args``); its metrics advance the seed's counters and its lr schedule (``advance``: the
per-iteration lr, a non-finite iteration's forced decision); at a cycle's end the fixed-seed evaluation's
metric goes to the lr schedule (SA's accept / reject / decay, ``anneal``), which restores or keeps each seed's
snapshot.  Everything that changes the numbers is here or in the jitted call, and all of it is in the
checkpoint (``seed_group.HostState``), so a resumed run continues exactly.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sagrasp_jax.task.config import Config
from sagrasp_jax.training import lr_schedule, sharding
from sagrasp_jax.training.agents.ppo import ppo
from sagrasp_jax.training.fixed_seed_eval import EvalResult
from sagrasp_jax.training.seed_group import SeedGroup


@dataclass(frozen=True)
class Schedule:
    steps_per_iteration: int
    num_iterations: int
    cycle_ends: tuple[int, ...]  # completed iterations at the end of each SA cycle; the last is num_iterations

    @property
    def num_cycles(self) -> int:
        return len(self.cycle_ends)

    @property
    def iterations_per_cycle(self) -> int:
        """The longest cycle: the iterations one jitted call runs at most."""
        return max(end - start for start, end in zip((0,) + self.cycle_ends[:-1], self.cycle_ends))

    @property
    def cycle_steps(self) -> int:
        return self.steps_per_iteration * self.iterations_per_cycle

    def cycle_end(self, iteration: int) -> int:
        """Where the cycle containing iteration ``iteration`` (0-based) ends."""
        return self.cycle_ends[bisect.bisect_right(self.cycle_ends, iteration)]


def make_schedule(cfg: Config) -> Schedule:
    """Cycles of whole iterations.  By default exactly ``eval.num_cycles`` of them (fewer only when
    there are fewer iterations): cycle k ends after round((k + 1)·N / num_cycles) of the N
    iterations, so cycles differ by at most one iteration.  With ``eval.cycle_steps`` a cycle is
    round(cycle_steps / steps per iteration) iterations, the last one possibly shorter."""
    per_iter = cfg.ppo.num_envs * cfg.ppo.unroll_length
    n = ppo.num_iterations(cfg.train.total_steps, cfg.ppo)
    if cfg.eval.cycle_steps:
        every = max(1, round(cfg.eval.cycle_steps / per_iter))
        ends = tuple(range(every, n, every)) + (n,)
    else:
        c = min(cfg.eval.num_cycles, n)
        ends = tuple(((k + 1) * n * 2 + c) // (2 * c) for k in range(c))  # round half up, in integers
    return Schedule(per_iter, n, ends)


def progress(schedule: Schedule, cfg: Config, iteration: int) -> float:
    """Training progress p at the start of iteration ``iteration`` (the reward weights and the
    cosine / linear lr read it)."""
    return min(1.0, iteration * schedule.steps_per_iteration / cfg.train.total_steps)


def call_args(group: SeedGroup, schedule: Schedule, rule: lr_schedule.Rule, cfg: Config,
              counts: list[int]) -> tuple[Any, ...]:
    """Arguments of the jitted call running, per seed, iterations ``host.iteration …`` (+ ``count``)."""
    length = schedule.iterations_per_cycle
    rows = []
    for host, count in zip(group.hosts, counts):
        p = np.array([progress(schedule, cfg, host.iteration + j) for j in range(length)], np.float32)
        rows.append((np.int32(host.iteration), np.int32(count), p, lr_schedule.iteration_lrs(rule, host.lr_state, p)))
    scalars = tuple(np.stack(x) for x in zip(*rows)) if group.group else rows[0]
    r = group.runner
    return (r.train_state, r.env_state, r.window, r.train_key, *sharding.replicate(scalars, group.mesh))


def advance(group: SeedGroup, i: int, metrics: dict[str, Any], dt: float, schedule: Schedule,
            rule: lr_schedule.Rule, cfg: Config) -> tuple[list[dict[str, Any]], bool]:
    """Seed ``i``'s rows of a call and whether its last iteration was finite; advances its host state
    (a non-finite end: the lr schedule's forced decision, a new cycle; the caller restores the snapshot)."""
    spi, total = schedule.steps_per_iteration, cfg.train.total_steps
    host = group.hosts[i]
    first = host.iteration
    means, finite = metrics.pop("window"), metrics.pop("finite")
    ran = int(metrics.pop("executed").sum())
    ended_lr = metrics.pop("learning_rate")  # the lr each iteration ended at (kl-adaptive: as adapted)
    rows: list[dict[str, Any]] = []
    for j in range(ran):
        p = host.env_steps / total
        host.iteration += 1
        host.env_steps += spi
        row: dict[str, Any] = {"iteration": first + j, "env_steps": host.env_steps, "progress": p,
                               "steps_per_s": spi * ran / dt,
                               "episodes_finished": int(metrics["episodes_finished"][j])}
        row.update({k: float(v[j]) for k, v in metrics.items() if k != "episodes_finished"})
        row.update(window_row(means, j))
        if rule.mode == "kl":  # the lr after this iteration: what the next one starts from
            row["lr"] = float(ended_lr[j])
        elif rule.mode == "per_iteration":
            row["lr"] = float(lr_schedule.progress_lr(np, rule, np.float32(progress(schedule, cfg, first + j + 1))))
        if finite[j]:
            host.entropy_sum += float(metrics["entropy"][j])
            host.entropy_n += 1
        rows.append(row)
    if not ran:
        return rows, True
    if finite[ran - 1]:
        host.lr_state = lr_schedule.observe(rule, host.lr_state, ended_lr=float(ended_lr[ran - 1]),
                                            progress=progress(schedule, cfg, host.iteration))
        return rows, True
    host.nonfinite += 1
    host.lr_state, decision = lr_schedule.nonfinite(rule, cfg.sa, host.lr_state,
                                                    progress=progress(schedule, cfg, host.iteration))
    host.start_cycle()
    rows[-1].update(event="nonfinite", sa_decision=decision.kind, sa_decayed=decision.decayed)
    return rows, False


def window_row(means: dict[str, np.ndarray], j: int) -> dict[str, Any]:
    """Training-episode metrics over the last ``train.metrics_window`` finished episodes."""
    count = int(means["window_episodes"][j])
    if count == 0:
        return {}
    out: dict[str, Any] = {k: float(v[j]) for k, v in means.items()
                           if k not in ("episode_steps", "steps_to_success", "window_episodes")}
    out["episode_steps"] = float(means["episode_steps"][j])
    sts = float(means["steps_to_success"][j])
    out["steps_to_success"] = sts if math.isfinite(sts) else None
    out["window_episodes"] = count
    return out


def anneal(group: SeedGroup, rule: lr_schedule.Rule, cfg: Config, n_actions: int,
           ending: list[tuple[float, float] | None]) -> list[lr_schedule.CycleOutcome | None]:
    """The lr schedule's end of cycle for each seed given its (metric, entropy) (None: not ending):
    accept → snapshot, reject → restore the snapshot (unless ``sa.rollback`` is off: then keep going
    from the current parameters).  The lr each seed goes on with is its schedule's, the next call's argument."""
    decisions: list[lr_schedule.CycleOutcome | None] = []
    for host, end in zip(group.hosts, ending):
        if end is None:
            decisions.append(None)
            continue
        host.lr_state, decision = lr_schedule.end_cycle(rule, cfg.sa, host.lr_state, end[0], end[1], host.sa_rng,
                                                        n_actions=n_actions)
        decisions.append(decision)
    group.restore_and_accept(restore=[d is not None and d.restore for d in decisions],
                             accept=[d is not None and d.kept for d in decisions])
    return decisions


def stop_rule(host: Any, cfg: Config, success: float, kept: bool) -> dict[str, Any]:
    """The stopping rule (``train.stop_success`` over ``train.stop_cycles``) at a cycle's end: records the
    cycle's evaluation success in the seed's window and stops the seed (``host.stopped_at``) when the window is
    full, its pooled success is at least ``stop_success`` and the lr schedule kept the policy just evaluated (so
    the run's policy is the one the last evaluation judged).  Returns the row fields (none when the rule is off)."""
    train = cfg.train
    if not train.stop_success:
        return {}
    host.recent_evals = (list(host.recent_evals) + [float(success)])[-train.stop_cycles:]
    pooled = float(np.mean(host.recent_evals))
    held = kept and len(host.recent_evals) == train.stop_cycles and pooled >= train.stop_success
    if held:
        host.stopped_at = host.env_steps
    return {"stop_window_success": pooled, "stop_window_cycles": len(host.recent_evals), "stopped_by_rule": held}


def cycle_metric(cfg: Config, ev: EvalResult | None) -> float | None:
    """The number SA judges a cycle by (``sa.metric``): the evaluation's success rate or mean return."""
    return None if ev is None else float(ev.mean_return if cfg.sa.metric == "return" else ev.success_rate)


def cycle_row(state: lr_schedule.ScheduleState, decision: lr_schedule.CycleOutcome, ev: EvalResult,
              eval_s: float, metric: float, entropy: float) -> dict[str, Any]:
    """The row fields of a cycle's end: its evaluation and the lr schedule's decision."""
    row = {
        "cycle": state.cycle, "eval_s": eval_s, "eval_return": float(ev.mean_return),
        "eval_success": float(ev.success_rate), "eval_steps_to_success": float(ev.steps_to_success),
        "eval_collision": float(ev.collision_rate), "eval_timeout": float(ev.timeout_rate),
        "sa_metric": metric, "cycle_entropy": entropy, "sa_decision": decision.kind,
        "sa_decayed": decision.decayed, "rollbacks": state.rollbacks,
    }
    sa = state.sa
    if sa is None:  # every cycle kept but those rolled back for a non-finite step
        row.update(sa_accepts=state.cycle - state.rollbacks, sa_rejects=state.rollbacks)
    else:
        row.update(sa_delta_e=decision.delta_e, sa_accept_prob=decision.accept_prob,
                   temperature=decision.temperature, sa_accepts=sa.n_accept, sa_accept_worse=sa.n_accept_worse,
                   sa_rejects=sa.n_reject, sa_decays=sa.decays)
    return row
