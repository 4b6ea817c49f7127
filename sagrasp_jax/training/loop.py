"""The training loop (PureJaxRL's shape, with the host in it): per cycle, one jitted call of every seed's PPO
iterations, the cycle's end (evaluation and the lr schedule's decision), the rows to the logs, checkpoints.

``train`` drives a :class:`sagrasp_jax.training.trainer.Trainer`; it adds nothing that changes the numbers
(that is the trainer's call and ``cycles``), only the order of the steps, the wall-clock fields and the
stopping rules (``train.total_steps``, the evaluation's ``train.stop_success``, ``stop_after_cycles``).
"""

from __future__ import annotations

import os
import time
from typing import Any, Protocol, TextIO

from sagrasp_jax.task.config import Config
from sagrasp_jax.training import run_log
from sagrasp_jax.training.cycles import Schedule
from sagrasp_jax.training.seed_group import HostState, SeedGroup


class LoopTrainer(Protocol):
    """What ``train`` uses of a trainer: everything it reads or calls, typed, so the loop's contract is in one
    place (``trainer.Trainer`` implements it; the trainer imports the loop, so the loop cannot import it)."""

    cfg: Config
    schedule: Schedule  # the cycles: iteration counts, cycle ends
    seed_group: SeedGroup
    primary: bool  # process 0 (the one that writes files)
    progress: bool  # show a progress bar
    stream: TextIO  # where the start line and the end summary go
    compile_s: dict[str, float]  # the compile's parts, after ``compile``
    mesh: Any  # jax.sharding.Mesh: ``mesh.size`` devices

    @property
    def group(self) -> bool: ...  # several seeds in one program
    @property
    def seeds(self) -> list[int]: ...
    @property
    def dirs(self) -> list[str]: ...  # each seed's run folder
    @property
    def hosts(self) -> list[HostState]: ...  # each seed's host-side state (iteration, env steps, lr state)

    def compile(self) -> dict[str, float]: ...
    def run_calls(self, counts: list[int]) -> list[list[dict[str, Any]]]: ...
    def cycle_due(self, i: int = 0) -> bool: ...
    def end_cycles(self, ending: list[bool]) -> list[dict[str, Any] | None]: ...
    def save_checkpoint(self, which: list[int] | None = None) -> list[str]: ...
    def export_finished(self) -> None: ...
    def summary(self, row: dict[str, Any], steps: int, i: int = 0) -> str: ...


def train(tr: LoopTrainer, stop_after_cycles: int | None = None) -> dict[str, Any]:
    """Train every seed of ``tr`` (a ``trainer.Trainer``, which calls this; typed by ``LoopTrainer``: the trainer
    imports the loop) to ``train.total_steps`` (or stop, checkpointed, after ``stop_after_cycles`` cycles).

    One jitted call per cycle (``run_calls``) runs each seed's iterations up to its cycle's end; its
    rows go to the callbacks afterwards, the cycle's row carrying the evaluation and the SA decision.
    Returns the last row (a group's: seed 0's)."""
    if tr.primary:
        for folder in tr.dirs:
            os.makedirs(folder, exist_ok=True)
    sched = tr.schedule
    logs, shared = run_log.make_callbacks(tr.seed_group, sched, tr.cfg.train.log_every, tr.primary, tr.progress,
                                          tr.stream)
    last_rows: list[dict[str, Any]] = [{} for _ in tr.seeds]
    stopped = [False] * len(tr.seeds)
    start_steps = [h.env_steps for h in tr.hosts]
    try:
        compile_s = tr.compile()["total"]
        t_start = time.perf_counter()  # after compiling: time_s, rates and ETA are training only
        for callback in shared:
            callback.on_start(f"compiled in {compile_s:.1f} s (iteration {tr.compile_s['iteration']:.1f} s, "
                              f"eval {tr.compile_s['eval']:.1f} s); {sched.num_iterations} iterations in "
                              f"{sched.num_cycles} cycles of <= {sched.iterations_per_cycle}, {tr.mesh.size} device(s)"
                              + (f", {len(tr.seeds)} seeds in one program" if tr.group else ""))
        while True:
            active = [not s and not h.finished(sched.num_iterations) for s, h in zip(stopped, tr.hosts)]
            if not any(active):
                break
            lrs = [h.lr_state.lr for h in tr.hosts]  # during this call (fixed-lr schedules)
            temperatures = [None if h.lr_state.sa is None else h.lr_state.sa.temperature for h in tr.hosts]
            t_call = time.perf_counter()
            rows = tr.run_calls([sched.cycle_end(h.iteration) - h.iteration if a else 0
                                 for h, a in zip(tr.hosts, active)])
            t_run = time.perf_counter()
            ending = [bool(r) and "event" not in r[-1] and tr.cycle_due(i) for i, r in enumerate(rows)]
            if any(ending):
                for r, fields in zip(rows, tr.end_cycles(ending)):
                    if fields is not None:
                        r[-1].update(fields)
            t_end = time.perf_counter()
            due = []
            for i, (host, seed_rows) in enumerate(zip(tr.hosts, rows)):
                if not seed_rows:
                    continue
                times = (t_start, t_call, t_run, t_end, compile_s, start_steps[i])
                run_log.finish_rows(host, seed_rows, lrs[i], temperatures[i], times, sched, tr.compile_s)
                for row in seed_rows:
                    for callback in logs[i] + shared:
                        callback.on_row(row, tr.seeds[i] if tr.group else None)
                last_rows[i] = seed_rows[-1]
                cycles_done = host.lr_state.cycle
                finished = host.finished(sched.num_iterations)
                stopped[i] = ending[i] and stop_after_cycles is not None and cycles_done >= stop_after_cycles
                if finished or stopped[i] or (ending[i] and cycles_done % tr.cfg.train.checkpoint_every_cycles == 0):
                    due.append(i)
            if due:
                tr.save_checkpoint(due)
        tr.export_finished()
    finally:
        for callback in [c for seed in logs for c in seed] + shared:
            callback.close()
    if tr.primary:
        for i, row in enumerate(last_rows):
            if row:
                who = f"seed {tr.seeds[i]}: " if tr.group else ""
                print(who + tr.summary(row, tr.hosts[i].env_steps - start_steps[i], i), file=tr.stream)
    return last_rows[0]
