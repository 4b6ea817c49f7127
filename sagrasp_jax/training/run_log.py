"""Where a training's rows go: each seed's ``metrics.jsonl`` and TensorBoard, the live progress bar, the
closing summary line.  Rows are built by :mod:`sagrasp_jax.training.cycles`; this module adds their
wall-clock fields and hands them on.  Nothing here changes the training's numbers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, TextIO

from sagrasp_jax.training import lr_schedule, run_dir
from sagrasp_jax.training.cycles import Schedule
from sagrasp_jax.training.seed_group import HostState, SeedGroup

# Row fields that depend on wall-clock time, not on the training maths.
TIME_FIELDS = ("time_s", "steps_per_s", "compile_s", "compile_iteration_s", "compile_eval_s", "eval_s", "eta_s")


class Callback(Protocol):
    """What ``Trainer.train`` hands each metrics row to (``seed``: the row's seed in a group, else None)."""

    def on_start(self, message: str) -> None: ...

    def on_row(self, row: dict[str, Any], seed: int | None) -> None: ...

    def close(self) -> None: ...


@dataclass
class LoggedRows:
    """Passes a log only the rows it keeps: each cycle's and event's, every ``log_every``-th and the last."""

    log: Any  # run_dir.MetricsLog or run_dir.TensorBoardLog
    log_every: int
    num_iterations: int

    def on_start(self, message: str) -> None:
        pass

    def on_row(self, row: dict[str, Any], seed: int | None) -> None:
        if ("cycle" in row or "event" in row or row["iteration"] % self.log_every == 0
                or row["iteration"] + 1 == self.num_iterations):
            self.log.write(row)

    def close(self) -> None:
        self.log.close()


class ProgressBar:
    """The live tqdm bar over all seeds' env steps: speed, last success, lr, last SA metric; rollback notes."""

    def __init__(self, total: int, initial: int, steps_per_row: int, stream: TextIO) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=total, initial=initial, unit="step", unit_scale=True, dynamic_ncols=True,
                        mininterval=1.0, file=stream)
        self.steps_per_row = steps_per_row
        self.last_metric: float | None = None

    def on_start(self, message: str) -> None:
        self.bar.write(message)

    def on_row(self, row: dict[str, Any], seed: int | None) -> None:
        self.last_metric = row.get("sa_metric", self.last_metric)
        self.bar.update(self.steps_per_row)
        self.bar.set_postfix(sps=f"{row['steps_per_s']:,.0f}", success=fmt(row.get("success")), lr=f"{row['lr']:.2e}",
                             M=fmt(self.last_metric), refresh=False)
        if "event" in row:
            who = "" if seed is None else f"seed {seed}, "
            self.bar.write(f"{who}iteration {row['iteration']}: non-finite loss/params -> rolled back to the snapshot, "
                           f"lr {row['lr']:.3g}")

    def close(self) -> None:
        self.bar.close()


def make_callbacks(group: SeedGroup, schedule: Schedule, log_every: int, primary: bool, progress: bool,
                   stream: TextIO) -> tuple[list[list[Callback]], list[Callback]]:
    """Each seed's logs (metrics.jsonl, TensorBoard; process 0 only) and the callbacks all seeds share."""
    logs: list[list[Callback]] = []
    n = schedule.num_iterations
    try:
        for host, folder in zip(group.hosts, group.dirs):
            logs.append([])
            if primary:
                logs[-1].append(LoggedRows(run_dir.MetricsLog(folder, resume_iteration=host.iteration), log_every, n))
                logs[-1].append(LoggedRows(run_dir.TensorBoardLog(folder, resume_step=host.env_steps), log_every, n))
    except BaseException:
        for callback in (c for seed in logs for c in seed):
            callback.close()
        raise
    shared: list[Callback] = []
    if progress and primary:
        spi = schedule.steps_per_iteration
        shared.append(ProgressBar(len(group) * n * spi, sum(h.env_steps for h in group.hosts), spi, stream))
    return logs, shared


def finish_rows(host: HostState, rows: list[dict[str, Any]], lr: float, temperature: float | None,
                times: tuple[float, ...], schedule: Schedule, compile_s: dict[str, float]) -> None:
    """The lr, temperature and wall-clock fields of one seed's rows of a call."""
    t_start, t_call, t_run, t_end, compile_total, start_steps = times
    for j, row in enumerate(rows):
        last = j == len(rows) - 1
        row["lr"] = host.lr_state.lr if last else row.get("lr", lr)  # the lr after the row's iteration
        if host.lr_state.sa is not None:
            row.setdefault("temperature", host.lr_state.sa.temperature if last else temperature)
        elapsed = (t_end if last else t_call + (j + 1) / len(rows) * (t_run - t_call)) - t_start
        done = row["iteration"] + 1
        rate = (done * schedule.steps_per_iteration - start_steps) / max(elapsed, 1e-9)
        row.update(time_s=elapsed, compile_s=compile_total, compile_iteration_s=compile_s["iteration"],
                   compile_eval_s=compile_s["eval"],
                   eta_s=(schedule.num_iterations - done) * schedule.steps_per_iteration / max(rate, 1e-9))


def summary(host: HostState, rule: lr_schedule.Rule, row: dict[str, Any], steps: int) -> str:
    """One line for the end of a run: speed, compile time, SA counts, last evaluation."""
    sa, lr = host.lr_state.sa, host.lr_state.lr
    schedule = (f"SA accept {sa.n_accept}, accept-worse {sa.n_accept_worse}, reject {sa.n_reject}, "
                f"decays {sa.decays}, lr {sa.lr:.3g}" if sa is not None else
                f"{rule.name} lr schedule, lr {lr:.3g}" + (" (PPO)" if rule.name == "constant" else ""))
    stop = (f"stopped by the stopping rule at {host.stopped_at:,} env steps (the last {len(host.recent_evals)} "
            f"evaluations: {100 * sum(host.recent_evals) / len(host.recent_evals):.2f} % success); ") if host.stopped_at else ""
    return (stop + f"{steps:,} env steps this session, {row['time_s']:.1f} s training ({steps / max(row['time_s'], 1e-9):,.0f} "
            f"steps/s incl. evaluation) + {row['compile_s']:.1f} s compile; {schedule}; "
            f"non-finite {host.nonfinite}; last eval success {fmt(row.get('eval_success'))}, "
            f"return {fmt(row.get('eval_return'))}")


def fmt(value: Any) -> str:
    return "-" if value is None else f"{value:.3g}"
