"""System identification from a robot log: ``python -m sagrasp_jax.sysid --log LOG.csv --out sysid.json``.

Fits, per joint, the servo model that the ``lagged`` control mode trains with, the command latency and the
joint-reading offset, so that a user centres training's randomisation on their own arm.

Log format (CSV, one header row, one row per control period, at least ``MIN_ROWS`` rows; comma-separated,
``#`` starts a comment line):

    time,cmd_q1,cmd_q2,cmd_q3,cmd_q4,cmd_q5,cmd_q6,q1,q2,q3,q4,q5,q6

(the AUBO-i5's six joints; ``--robot NAME`` reads a log of that registered robot, one ``cmd_qJ`` and ``qJ`` per
joint, and fits around its servo model)

* ``time``: seconds, strictly increasing, sampled at the policy's control period (``env.control.control_dt``,
  0.05 s; within ±20 %);
* ``cmd_q1..6``: the joint targets sent in that period (rad), i.e. what the deploy loop commands;
* ``q1..6``: the joints the controller reported at the start of that period (rad), before the command.

Model (the lagged mode's, ``control.servo_model_step``, with the latency queue of ``control.delayed_commands``):
the reading is y = x + o; x' = x + g·(c_d − x) + m·(x − x_prev), where c_d is the command ``d`` periods old
(whole periods from the queue, the fraction blends two commands).  ``d`` is shared by every joint and found
by a grid search; for each ``d`` the per-joint g, m and g·o are linear least squares.

Output JSON: ``lag_gain`` g, ``lag_momentum`` m, ``servo_gain`` (the kp scale the lagged mode would randomise
to explain m: m_nominal / m), ``latency_steps`` and ``latency_s``, ``joint_offset`` o (rad), the fit's
residual and ``explained`` share of each joint's step-to-step motion, and ``overrides``: ``--set`` items that
training accepts (``train --set KEY=VALUE`` for each, or the list as ``--config``), centring the lagged model on
this arm and sizing the latency and offset ranges.
Bad logs (NaN, time not increasing, wrong columns, too short, another sample period; not a regular file, or over
``MAX_LOG_BYTES``) exit 2 naming the problem, and so does a log the model cannot be fitted to: a joint that never
moves, a fit that explains less than ``MIN_EXPLAINED`` of a joint's step-to-step motion (noise, shuffled columns),
a latency beyond training's ``env.randomize.latency`` range (the search runs one step past it, so a longer one
shows), a fitted gain or carry-over outside the model's range, or an override that training would refuse (each
is checked by ``config_parse.apply_overrides`` on the ``cpu-quick`` preset): the message says what could not be
identified, and nothing is written.  Nothing here imports jax: it runs on the robot PC.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import sys
from typing import Any, NamedTuple, Sequence

import numpy as np

from sagrasp_jax.task import config
from sagrasp_jax.task import config_parse
from sagrasp_jax.task import control
from sagrasp_jax.base import cli
from sagrasp_jax.base import fileio
from sagrasp_jax.task.config import ControlConfig
from sagrasp_jax.task import robots


def columns(dof: int) -> tuple[str, ...]:
    """The log's header for an arm of ``dof`` joints."""
    return ("time", *(f"cmd_q{j}" for j in range(1, dof + 1)), *(f"q{j}" for j in range(1, dof + 1)))


COLUMNS = columns(robots.DEFAULT_DOF)  # the default robot's (the AUBO-i5's) log
MIN_ROWS = 100  # control periods: enough motion to separate gain, carry-over and latency
MAX_LOG_BYTES = 64 << 20  # ≈ 250,000 rows, 3.5 h at 20 Hz: refused before it is read beyond this
MAX_LATENCY_STEPS = 3.0  # the latency knob's range (env.randomize.latency ≤ 3): what training can centre on
FIT_LATENCY_STEPS = MAX_LATENCY_STEPS + 1.0  # the grid search's upper end: a longer latency shows as out of range
MIN_EXPLAINED = 0.9  # of each joint's step-to-step motion (R²); the model explains ≥ 0.98 of a servo log's
MIN_MOTION = 1e-3  # rad: a joint whose readings or commands span less never moved
GAIN_RANGE = (0.05, 1.0)  # lag_gain the model can mean (clipped to it within FIT_SLACK)
MOMENTUM_RANGE = (0.0, 0.9)  # lag_momentum's config range (clipped to it within FIT_SLACK)
FIT_SLACK = 0.05  # how far a fitted gain or carry-over may fall outside its range (noise) before it is refused
TRAINING_PRESET = "cpu-quick"  # the overrides must be accepted over this preset (train's default)
LATENCY_GRID_STEP = 0.02  # control steps (1 ms at 20 Hz); refined by a parabola through the best three
PERIOD_TOLERANCE = 0.2  # the median sample period must be within ±20 % of control_dt


class LogError(ValueError):
    """A log that cannot be identified from (named column, row or rule)."""


class RobotLog(NamedTuple):
    time: np.ndarray  # (T,)
    command: np.ndarray  # (T, dof)
    measured: np.ndarray  # (T, dof)


class SysIdResult(NamedTuple):
    lag_gain: np.ndarray  # (dof,)
    lag_momentum: np.ndarray  # (dof,)
    latency_steps: float
    joint_offset: np.ndarray  # (dof,) rad
    residual_rms: np.ndarray  # (dof,) rad per control step
    period_s: float
    explained: np.ndarray  # (dof,) share of each joint's step-to-step motion the fit explains (R²)
    motion: np.ndarray  # (dof,) rad: the smaller of each joint's reading and command spans


def robot_control(robot: str) -> ControlConfig:
    """The control constants of registered robot ``robot``: the defaults with its servo model (``ROBOT_KEYS``)."""
    spec = robots.get(robot)
    return dataclasses.replace(ControlConfig(), lag_gain=spec.servo.lag_gain, lag_momentum=spec.servo.lag_momentum)


def read_log(path: str, dof: int = robots.DEFAULT_DOF) -> RobotLog:
    """Parse and check a log file of an arm with ``dof`` joints (``LogError`` names what is wrong)."""
    expected = columns(dof)
    try:
        text = fileio.read_regular(path, MAX_LOG_BYTES, "robot log").decode("utf-8")
        rows = [r for r in csv.reader(io.StringIO(text, newline="")) if r and not r[0].lstrip().startswith("#")]
    except (fileio.NotRegularFile, fileio.FileTooLarge) as exc:
        raise LogError(str(exc)) from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise LogError(f"{path}: cannot read the log: {exc}") from None
    if not rows:
        raise LogError(f"{path}: empty log; expected a header row {','.join(expected)}")
    header = tuple(c.strip() for c in rows[0])
    if header != expected:
        missing = [c for c in expected if c not in header]
        extra = [c for c in header if c not in expected]
        raise LogError(f"{path}: columns must be {','.join(expected)} in this order; got {','.join(header)}"
                       + (f" (missing: {', '.join(missing)})" if missing else "")
                       + (f" (unexpected: {', '.join(extra)})" if extra else ""))
    values = np.empty((len(rows) - 1, len(expected)))
    for i, row in enumerate(rows[1:]):
        if len(row) != len(expected):
            raise LogError(f"{path}: row {i + 2} has {len(row)} values, expected {len(expected)}")
        try:
            values[i] = [float(v) for v in row]
        except ValueError:
            raise LogError(f"{path}: row {i + 2} has a value that is not a number: {row}") from None
        if not np.isfinite(values[i]).all():
            bad = [expected[k] for k in np.nonzero(~np.isfinite(values[i]))[0]]
            raise LogError(f"{path}: row {i + 2} has NaN or infinite {', '.join(bad)}")
    return check_log(RobotLog(values[:, 0], values[:, 1:dof + 1], values[:, dof + 1:]), path)


def check_log(log: RobotLog, what: str = "log") -> RobotLog:
    """Rules every log must meet (also for arrays built in memory)."""
    n = log.time.shape[0]
    if n < MIN_ROWS:
        raise LogError(f"{what}: {n} rows; at least {MIN_ROWS} control periods are needed")
    for name, arr in (("time", log.time), ("cmd_q", log.command), ("q", log.measured)):
        if not np.isfinite(arr).all():
            raise LogError(f"{what}: {name} has NaN or infinite values")
    dt = np.diff(log.time)
    if not (dt > 0).all():
        k = int(np.nonzero(dt <= 0)[0][0])
        raise LogError(f"{what}: time is not strictly increasing at row {k + 3} ({log.time[k]!r} then {log.time[k + 1]!r})")
    if np.abs(log.command).max() > 2 * math.pi or np.abs(log.measured).max() > 2 * math.pi:
        raise LogError(f"{what}: joint values beyond ±2π: the log must be in radians")
    return log


def _delayed(command: np.ndarray, latency: float, gain: np.ndarray) -> np.ndarray:
    """c_d per period: the command ``latency`` periods old, the fraction held as in the lagged mode
    (``control.held_command_weight``); before the log's start, its first command."""
    k = control.latency_queue_size(latency) or 2
    padded = np.concatenate([np.repeat(command[:1], k, axis=0), command], axis=0)
    whole = int(math.floor(latency))
    weight = control.held_command_weight(np, latency - whole, gain)
    t = np.arange(command.shape[0]) + k
    return (1.0 - weight) * padded[t - whole] + weight * padded[t - whole - 1]


def _fit_at(log: RobotLog, latency: float, gain: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-joint least squares at a given latency: (coefficients g, m, k (dof, 3), residual rms (dof,), sse);
    ``gain`` sets how a fraction of a period's latency weighs the older command."""
    y, c = log.measured, _delayed(log.command, latency, gain)
    dy_next = y[2:] - y[1:-1]  # x' − x for periods 1..T-2
    error = c[1:-1] - y[1:-1]
    carry = y[1:-1] - y[:-2]
    dof = log.command.shape[1]
    coef = np.empty((dof, 3))
    rms = np.empty(dof)
    for j in range(dof):
        a = np.stack([error[:, j], carry[:, j], np.ones(error.shape[0])], axis=1)
        coef[j], *_ = np.linalg.lstsq(a, dy_next[:, j], rcond=None)
        rms[j] = math.sqrt(float(np.mean((a @ coef[j] - dy_next[:, j]) ** 2)))
    return coef, rms, np.asarray(float(np.sum(rms**2)))


def identify(log: RobotLog, control_cfg: ControlConfig | None = None) -> SysIdResult:
    """Fit the lagged servo model, the latency and the offsets to ``log`` (see the module docstring).  The
    result is the least-squares fit whatever the log; ``not_identified`` says which parts of it mean nothing."""
    control_cfg = control_cfg or ControlConfig()
    log = check_log(log)
    if len(control_cfg.lag_gain) != log.command.shape[1]:
        raise LogError(f"log: {log.command.shape[1]} joints, but the control constants are for "
                       f"{len(control_cfg.lag_gain)} (name the arm: --robot)")
    period = float(np.median(np.diff(log.time)))
    if abs(period / control_cfg.control_dt - 1.0) > PERIOD_TOLERANCE:
        raise LogError(f"log: median sample period {period * 1000:.1f} ms; the log must be sampled once per control "
                       f"period ({control_cfg.control_dt * 1000:.0f} ms ±{PERIOD_TOLERANCE:.0%})")
    if float(np.abs(np.diff(log.command, axis=0)).max()) < 1e-4:
        raise LogError("log: the commands never move: a fit needs the arm in motion")
    grid = np.arange(0.0, FIT_LATENCY_STEPS + 1e-9, LATENCY_GRID_STEP)
    gain = np.asarray(control_cfg.lag_gain)
    for _ in range(2):  # the fraction's weight depends on the gain: fit, then fit again with the fitted gain
        sse = np.array([float(_fit_at(log, float(d), gain)[2]) for d in grid])
        gain = np.clip(_fit_at(log, float(grid[int(np.argmin(sse))]), gain)[0][:, 0], 0.05, 0.999)
    best = int(np.argmin(sse))
    latency = float(grid[best])
    if 0 < best < len(grid) - 1:  # parabola through the best three
        s0, s1, s2 = sse[best - 1 : best + 2]
        curvature = s0 - 2 * s1 + s2
        if curvature > 0:
            latency += 0.5 * LATENCY_GRID_STEP * (s0 - s2) / curvature
    coef, rms, _ = _fit_at(log, latency, gain)
    gain, momentum, constant = coef[:, 0], coef[:, 1], coef[:, 2]
    offset = np.where(np.abs(gain) > 1e-6, constant / np.where(np.abs(gain) > 1e-6, gain, 1.0), 0.0)
    step = np.diff(log.measured, axis=0)[1:]
    spread = np.sqrt(np.mean((step - step.mean(axis=0)) ** 2, axis=0))
    explained = 1.0 - (rms / np.maximum(spread, 1e-12)) ** 2
    motion = np.minimum(np.ptp(log.measured, axis=0), np.ptp(log.command, axis=0))
    return SysIdResult(gain, momentum, latency, offset, rms, period, explained, motion)


def not_identified(result: SysIdResult) -> list[str]:
    """What ``result`` could not identify, one sentence each (empty: every part of the fit holds): joints that
    never moved, joints whose motion the model does not explain, a latency beyond training's range, gains or
    carry-overs outside the model's."""
    dof = len(result.lag_gain)
    names = [f"q{j + 1}" for j in range(dof)]
    still = [j for j in range(dof) if result.motion[j] < MIN_MOTION]
    unexplained = [j for j in range(dof) if j not in still and not result.explained[j] >= MIN_EXPLAINED]
    problems = []
    if still:
        problems.append(f"{', '.join(names[j] for j in still)} never move{'s' * (len(still) == 1)} (readings or "
                        f"commands span under {MIN_MOTION:g} rad): no servo model can be identified from that; log a "
                        "motion of every joint")
    if unexplained:
        shares = ", ".join(f"{max(float(result.explained[j]), 0.0):.0%} of {names[j]}'s" for j in unexplained)
        problems.append(f"the servo model explains only {shares} step-to-step motion (≥ {MIN_EXPLAINED:.0%} in a servo "
                        "log): lag, carry-over and offset not identified there (is the log noise, are columns "
                        "swapped, or were the readings taken after the command?)")
    for what, values, (lo, hi) in (("lag_gain", result.lag_gain, GAIN_RANGE),
                                   ("lag_momentum", result.lag_momentum, MOMENTUM_RANGE)):
        outside = [f"{names[j]} {values[j]:.3f}" for j in range(dof)
                   if j not in still + unexplained and not lo - FIT_SLACK <= values[j] <= hi + FIT_SLACK]
        if outside:
            problems.append(f"fitted {what} outside the model's range [{lo:g}, {hi:g}] ({', '.join(outside)}): not "
                            "identified")
    if result.latency_steps > MAX_LATENCY_STEPS + LATENCY_GRID_STEP:
        at_end = result.latency_steps >= FIT_LATENCY_STEPS - LATENCY_GRID_STEP
        shown = f"at least {FIT_LATENCY_STEPS:g}" if at_end else f"{result.latency_steps:.2f}"
        problems.append(f"the command latency is {shown} control steps, beyond the {MAX_LATENCY_STEPS:g} steps "
                        "training can randomise (env.randomize.latency): not identified")
    return problems


def overrides(result: SysIdResult, control_cfg: ControlConfig | None = None, robot: str = robots.DEFAULT) -> list[str]:
    """``--set`` items for training centred on this arm: its servo model, and randomisation ranges that cover
    the measured latency and offsets with margin (latency up to twice the measured, at least one step;
    offsets ±1.5 × the largest measured, at least 5 mrad), led by ``robot=NAME`` for another robot than the
    default.  Raises LogError naming what the log could not
    identify (``not_identified``) or any item that training would refuse (``check_overrides``)."""
    problems = not_identified(result)
    if problems:
        raise LogError("log: cannot identify the arm from this log: " + "; ".join(problems))
    gain = np.clip(result.lag_gain, *GAIN_RANGE)
    momentum = np.clip(result.lag_momentum, *MOMENTUM_RANGE)
    latency = min(MAX_LATENCY_STEPS, max(1.0, round(2.0 * result.latency_steps, 2)))
    offset = max(0.005, round(1.5 * float(np.abs(result.joint_offset).max()), 4))
    items = [f"robot={robot}"] if robot != robots.DEFAULT else []
    items += [
        "env.control.lag_gain=" + ",".join(f"{v:.4f}" for v in gain),
        "env.control.lag_momentum=" + ",".join(f"{v:.4f}" for v in momentum),
        f"env.randomize.latency={latency:g}",
        f"env.randomize.joint_offset={offset:g}",
    ]
    return check_overrides(items)


def check_overrides(items: list[str]) -> list[str]:
    """``items`` if training accepts them over ``TRAINING_PRESET`` (``config_parse.apply_overrides``: each key's
    declared range and the rules across keys), else LogError naming each refused item and why."""
    base = config.get_config(TRAINING_PRESET)
    if items and items[0].startswith("robot="):  # another robot: the others are checked over its config
        base = config_parse.apply_overrides(base, items[:1])
    refused = []
    for item in items:
        try:
            config_parse.apply_overrides(base, [item])
        except config.ConfigError as exc:
            refused.append(f"--set {item} ({exc})")
    if not refused:
        try:
            config_parse.apply_overrides(base, items)
        except config.ConfigError as exc:
            refused.append(f"the overrides together ({exc})")
    if refused:
        raise LogError("log: the fit gives overrides that training would refuse, so it is not identified: "
                       + "; ".join(refused) + (" (a joint offset that large: calibrate the arm's zero first)"
                                               if any("joint_offset" in r for r in refused) else ""))
    return items


def to_dict(result: SysIdResult, control_cfg: ControlConfig | None = None,
            robot: str = robots.DEFAULT) -> dict[str, Any]:
    control_cfg = control_cfg or ControlConfig()
    nominal = np.asarray(control_cfg.lag_momentum)
    servo_gain = np.where(result.lag_momentum > 1e-4, nominal / np.maximum(result.lag_momentum, 1e-4), np.inf)
    return {
        "lag_gain": result.lag_gain.tolist(),
        "lag_momentum": result.lag_momentum.tolist(),
        "servo_gain": [float(v) if math.isfinite(v) else None for v in servo_gain],
        "latency_steps": result.latency_steps,
        "latency_s": result.latency_steps * result.period_s,
        "joint_offset": result.joint_offset.tolist(),
        "residual_rms": result.residual_rms.tolist(),
        "explained": result.explained.tolist(),
        "period_s": result.period_s,
        "overrides": overrides(result, control_cfg, robot),
    }


def main(argv: Sequence[str] | None = None) -> int:
    p = cli.Parser(prog="python -m sagrasp_jax.sysid", description=__doc__.split("\n\n")[0])
    p.add_argument("--log", required=True, help="robot log CSV: time,cmd_q1..cmd_qN,q1..qN, N the robot's joints (see "
                   "the module docstring)")
    p.add_argument("--robot", choices=robots.names(), default=robots.DEFAULT,
                   help=f"the arm the log is of (env.robot; default {robots.DEFAULT})")
    p.add_argument("--out", required=True, help="result JSON (written atomically)")
    args = p.parse_args(argv)
    try:
        fileio.check_output_file(args.out)  # /dev/full, a FIFO, a folder: refused before any work
        control_cfg = robot_control(args.robot)
        result = identify(read_log(args.log, robots.get(args.robot).dof), control_cfg)
        report = to_dict(result, control_cfg, args.robot)
        fileio.atomic_write_json(args.out, report)
    except (LogError, fileio.NotWritable) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"error: cannot write {args.out}: {exc}", file=sys.stderr)
        return 2
    print(f"latency {report['latency_steps']:.2f} control steps ({1000 * report['latency_s']:.1f} ms)")
    print("joint   lag_gain  momentum  servo_gain  offset_mrad  residual_mrad")
    for j in range(len(result.lag_gain)):
        sg = report["servo_gain"][j]
        print(f"q{j + 1}      {result.lag_gain[j]:8.3f}  {result.lag_momentum[j]:8.3f}  {'-' if sg is None else f'{sg:10.2f}'}"
              f"  {1000 * result.joint_offset[j]:11.2f}  {1000 * result.residual_rms[j]:13.2f}")
    print("training overrides: " + " ".join(f"--set {o}" for o in report["overrides"]))
    print(f"written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
