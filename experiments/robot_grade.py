"""Is a trained policy robot-grade?  Evaluate runs in every transfer condition (docs/results.md, §7).

Each ``--run NAME=FOLDER`` is evaluated on ``--episodes`` fixed-seed episodes of the evaluation mix (seed
``eval.seed + 1``, deterministic policy) in the named conditions of ``config.EVAL_CONDITIONS``
(kinematic, dynamic, robot = dynamic with every transfer knob on at the real arm's levels, robot-latency2 =
the same with up to 2 steps of latency), optionally in the dynamic env with one knob on at a time
(``--per-knob``, the rows of the robot-grade issue's table), on blocking-only scenes in the robot condition
(``--blocking``), and through the physical grasp check with and without detection error (``--physical``).
Prints a Markdown table and writes JSON.

Two subcommands check the model the robot-grade preset trains in (their results: docs/results-archive.md §7):
``servo-fit`` fits the lagged mode's per-step servo model to the dynamic env's MJX servos (the
``env.control.lag_gain`` / ``lag_momentum`` defaults) and measures its open-loop drift; ``sysid-check`` runs
``sagrasp_jax.deploy.sysid`` on logs the dynamic env synthesises for arms with known gains, latency and offsets.
``twin-vs-mjx`` (was ``twin_vs_mjx``) plays the runs through the deploy loop on the PyBullet twin beside their
MJX evaluation, condition by condition (``TWIN_DOC``).

    python -m experiments.robot_grade --run s0=runs/robot_s0 --run s1=runs/robot_s1 --run s2=runs/robot_s2 \\
        --blocking --physical --out experiments/results/robot_grade_cpu.json
    python -m experiments.robot_grade servo-fit --out experiments/results/fit_servo_lag.json
    python -m experiments.robot_grade servo-fit --set env.robot=panda --out experiments/results/fit_servo_lag_panda.json
    python -m experiments.robot_grade sysid-check --out experiments/results/sysid_check.json
    python -m experiments.robot_grade twin-vs-mjx --run s0=runs/quick_s0 --cases kinematic:mix robot:mix \\
        kinematic:blocking robot:blocking robot-wide:mix --twin-episodes 500 --mjx-episodes 1000 --physical \\
        --workers 2 --out experiments/results/twin_vs_mjx_s0.json
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from typing import Any

import sagrasp_jax  # noqa: F401  (XLA flags)
import jax
import jax.numpy as jnp
import numpy as np

from sagrasp_jax import evaluate
from sagrasp_jax.training import evaluation
from sagrasp_jax.deploy import sysid
from sagrasp_jax.envs.grasp_env import GraspEnv
from sagrasp_jax.task import config, config_parse, robot, scripted
from sagrasp_jax.training import run_dir
from sagrasp_jax.task.config import EVAL_CONDITIONS, ROBOT_KNOBS
from sagrasp_jax.base.fileio import atomic_write_json

CONDITIONS = ("kinematic", "dynamic", "robot", "robot-latency2")


def per_knob_conditions() -> dict[str, tuple[str, ...]]:
    """The dynamic env with one transfer knob on at a time (the others off)."""
    base = EVAL_CONDITIONS["dynamic"]
    out = {}
    for knob in ROBOT_KNOBS:
        key = knob.split("=")[0]
        out["dynamic+" + key.rsplit(".", 1)[1]] = tuple(o for o in base if not o.startswith(key + "=")) + (knob,)
    return out


def summary(result: dict[str, Any]) -> dict[str, Any]:
    overall, obstacle = result["overall"], result["obstacle_present"]
    by = overall.get("collision_by", {})
    return {"overall": overall.get("success_rate"), "obstacle": obstacle.get("success_rate"),
            "obstacle_n": obstacle.get("episodes", 0), "no_obstacle": result["obstacle_absent"].get("success_rate"),
            "collision": overall["collision_rate"], "hit_table": by.get("table", 0.0), "hit_target": by.get("target", 0.0),
            "hit_obstacle": by.get("obstacle", 0.0), "timeout": overall["timeout_rate"],
            "steps_per_success": overall["mean_steps_per_success"]}


def evaluate_conditions(folder: str, episodes: int, conditions: dict[str, tuple[str, ...]], blocking: bool,
                        physical: bool) -> dict[str, Any]:
    cfg = run_dir.load_config(folder)
    seed, steps = evaluation.resolve_options(cfg, None, None)
    out: dict[str, Any] = {}
    for name, overrides in conditions.items():
        out[name] = summary(evaluation.evaluate_run(folder, episodes, overrides=list(overrides)))
        print(f"{folder} {name}: {out[name]}", file=sys.stderr, flush=True)
    if blocking:
        res = evaluation.evaluate_run(folder, episodes, overrides=list(EVAL_CONDITIONS["robot"]), scenes="blocking")
        out["robot_blocking_scenes"] = summary(res)
        res = evaluation.evaluate_run(folder, episodes, overrides=list(EVAL_CONDITIONS["kinematic"]), scenes="blocking")
        out["kinematic_blocking_scenes"] = summary(res)
    if physical:
        for name in ("kinematic", "kinematic-target-error"):
            ph = evaluate.evaluate_physical(folder, episodes, seed, steps, overrides=list(EVAL_CONDITIONS[name]))
            out["physical_" + name] = {k: ph[k] for k in ("kinematic_successes", "physical_successes", "physical_success_rate")}
            out["physical_" + name]["held_of_successes"] = ph["physical_successes"] / max(1, ph["kinematic_successes"])
            print(f"{folder} physical {name}: {out['physical_' + name]}", file=sys.stderr, flush=True)
    return out


def _pct(v: Any) -> str:
    return "-" if v is None else f"{100 * v:.1f}"


def table(report: dict[str, Any]) -> str:
    lines = ["| run | condition | overall % | obstacle % | no obstacle % | collisions % (table / cube / obstacle) | "
             "timeout % | steps / success |", "|---|---|---|---|---|---|---|---|"]
    for run, entry in report["runs"].items():
        for cond, s in entry["eval"].items():
            if cond.startswith("physical_"):
                continue
            steps = "-" if s["steps_per_success"] is None else f"{s['steps_per_success']:.1f}"
            lines.append(f"| {run} | {cond} | {_pct(s['overall'])} | {_pct(s['obstacle'])} | {_pct(s['no_obstacle'])} | "
                         f"{_pct(s['collision'])} ({_pct(s['hit_table'])} / {_pct(s['hit_target'])} / "
                         f"{_pct(s['hit_obstacle'])}) | {_pct(s['timeout'])} | {steps} |")
        for cond in ("physical_kinematic", "physical_kinematic-target-error"):
            if cond in entry["eval"]:
                ph = entry["eval"][cond]
                lines.append(f"| {run} | {cond} | held {ph['physical_successes']} of {ph['kinematic_successes']} "
                             f"successes ({_pct(ph['held_of_successes'])} %) | | | | | |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["servo-fit"]:
        return servo_fit_main(argv[1:])
    if argv[:1] == ["sysid-check"]:
        return sysid_check_main(argv[1:])
    if argv[:1] == ["twin-vs-mjx"]:
        return twin_vs_mjx_main(argv[1:])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     epilog="subcommands (each with --help): servo-fit, sysid-check, twin-vs-mjx")
    parser.add_argument("--run", action="append", default=[], metavar="NAME=FOLDER", required=True)
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--conditions", default=",".join(CONDITIONS),
                        help=f"comma-separated names of config.EVAL_CONDITIONS (default {','.join(CONDITIONS)})")
    parser.add_argument("--per-knob", action="store_true", help="also the dynamic env with one knob on at a time")
    parser.add_argument("--blocking", action="store_true", help="also blocking-only scenes (robot and kinematic)")
    parser.add_argument("--physical", action="store_true", help="also the physical grasp check, with and without target error")
    parser.add_argument("--out", default="experiments/results/robot_grade_cpu.json")
    args = parser.parse_args(argv)
    names = [c for c in args.conditions.split(",") if c]
    unknown = [c for c in names if c not in EVAL_CONDITIONS]
    if unknown:
        parser.error(f"unknown condition(s) {', '.join(unknown)}; valid: {', '.join(EVAL_CONDITIONS)}")
    conditions = {c: EVAL_CONDITIONS[c] for c in names}
    if args.per_knob:
        conditions.update(per_knob_conditions())
    report: dict[str, Any] = {"episodes": args.episodes, "conditions": {k: list(v) for k, v in conditions.items()},
                              "runs": {}}
    for item in args.run:
        name, folder = item.split("=", 1)
        report["runs"][name] = {"folder": os.path.abspath(folder),
                                "eval": evaluate_conditions(folder, args.episodes, conditions, args.blocking, args.physical)}
        atomic_write_json(args.out, report)  # after every run: a long study keeps what it has
    print(table(report))
    print(f"wrote {args.out}")
    return 0


# ---------------------------------------------------------------------- servo-fit (the lagged model)

SERVO_FIT_DOC = """Fit the lagged mode's per-step servo model to the dynamic mode's MJX servos, and check it.

The ``lagged`` control mode (env.control.mode=lagged) replaces MuJoCo's servo physics with one update per
control step: q ← q + g·(c − q) + m·(q − q_prev) per joint (``control.servo_model_step``).  This script
records control steps of the dynamic env (scripted reach-and-descend actions with uniform noise, every
randomisation knob off), fits g (``env.control.lag_gain``) and m (``env.control.lag_momentum``) per joint by
linear least squares of the step q⁺ − q on (c − q, q − q_prev), and then replays the same action sequences
open-loop in the dynamic and lagged envs (with and without command latency) and reports how far their
gripper centres drift apart: the cheap model is what the policy trains in, the dynamic env is the judge."""


SERVO_SETS: list[str] = []  # servo-fit's --set overrides (e.g. env.robot=panda), applied to every env it builds


def _servo_env(mode: str, extra: list[str], gains: dict[str, tuple[float, ...]] | None = None) -> GraspEnv:
    overrides = [*SERVO_SETS, *config.KNOBS_OFF,  # the preset trains with them on
                 f"env.control.mode={mode}", "env.task.obs_noise_std=0", "env.task.obs_layout=relative_lag",
                 *extra]
    if gains:
        overrides += [f"env.control.{k}={','.join(f'{v:.6f}' for v in vals)}" for k, vals in gains.items()]
    return GraspEnv(config_parse.apply_overrides(config.get_config("cpu-quick"), overrides).env)


def record(env: GraspEnv, episodes: int, steps: int, seed: int, scripted_actions: bool) -> dict[str, np.ndarray]:
    """Per control step: measured joints before, the command, measured joints after, gripper centre after."""
    cfg = env.cfg

    def run(keys: Any, noise: Any) -> Any:
        state = jax.vmap(env.reset)(keys)

        def body(st: Any, eps: Any) -> Any:
            q = jax.vmap(env.measured_joints)(st)
            act = eps
            if scripted_actions:
                act = jax.vmap(lambda qq, t: scripted.scripted_action(jnp, cfg, qq, t))(q, st.info["reset"].target_pos) + eps
            nxt = jax.vmap(env.step)(st, jnp.clip(act, -1.0, 1.0))
            q_next = jax.vmap(env.measured_joints)(nxt)
            centre = jax.vmap(lambda qq: robot.forward_kinematics(jnp, env.robot, qq).gripper_centre)(q_next)
            return nxt, (q, nxt.info["q_target"], q_next, centre)

        return jax.lax.scan(body, state, noise)[1]

    keys = jax.random.split(jax.random.PRNGKey(seed), episodes)
    noise = 0.6 * jax.random.uniform(jax.random.PRNGKey(seed + 1), (steps, episodes, env.robot.dof), minval=-1.0, maxval=1.0)
    q, command, q_next, centre = (np.asarray(a) for a in jax.jit(run)(keys, noise))
    return {"q": q, "command": command, "q_next": q_next, "centre": centre}


def fit(data: dict[str, np.ndarray]) -> dict[str, list[float]]:
    q, c, qn = data["q"], data["command"], data["q_next"]
    q_prev = np.concatenate([q[:1], q[:-1]], axis=0)  # the first step of an episode starts at rest
    gain, momentum, rms, rms_first_order, step_rms = [], [], [], [], []
    for j in range(q.shape[-1]):
        x = np.stack([(c - q)[..., j].ravel(), (q - q_prev)[..., j].ravel()], axis=1)
        y = (qn - q)[..., j].ravel()
        coef, *_ = np.linalg.lstsq(x, y, rcond=None)
        a1 = float(x[:, 0] @ y / (x[:, 0] @ x[:, 0]))
        gain.append(float(coef[0]))
        momentum.append(float(coef[1]))
        rms.append(float(np.sqrt(np.mean((y - x @ coef) ** 2))))
        rms_first_order.append(float(np.sqrt(np.mean((y - a1 * x[:, 0]) ** 2))))
        step_rms.append(float(np.sqrt(np.mean(y**2))))
    return {"lag_gain": gain, "lag_momentum": momentum, "residual_rms_rad": rms,
            "residual_rms_first_order_rad": rms_first_order, "step_rms_rad": step_rms}


def drift(episodes: int, steps: int, seed: int, latency: float, gains: dict[str, tuple[float, ...]]) -> dict[str, float]:
    """The same random action sequences, open loop, in the dynamic and the lagged env: gripper-centre gap."""
    extra = [f"env.randomize.latency={latency}"] if latency else []
    dyn = record(_servo_env("dynamic", extra), episodes, steps, seed, scripted_actions=False)
    lag = record(_servo_env("lagged", extra, gains), episodes, steps, seed, scripted_actions=False)
    kin = record(_servo_env("kinematic", []), episodes, steps, seed, scripted_actions=False)
    gap = np.linalg.norm(dyn["centre"] - lag["centre"], axis=-1)
    gap_kin = np.linalg.norm(dyn["centre"] - kin["centre"], axis=-1)
    return {"latency": latency, "lagged_vs_dynamic_mean_m": float(gap.mean()), "lagged_vs_dynamic_p95_m":
            float(np.percentile(gap, 95)), "kinematic_vs_dynamic_mean_m": float(gap_kin.mean()),
            "kinematic_vs_dynamic_p95_m": float(np.percentile(gap_kin, 95))}


def servo_fit_main(argv: list[str] | None = None) -> int:
    """``servo-fit``: the lagged model's g and m per joint, fitted to the dynamic env's servos, and its open-loop drift."""
    parser = argparse.ArgumentParser(prog="python -m experiments.robot_grade servo-fit", description=SERVO_FIT_DOC)
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="experiments/results/fit_servo_lag.json")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="config override for every env the fit builds, e.g. env.robot=panda (repeatable)")
    args = parser.parse_args(argv)
    SERVO_SETS[:] = args.set
    data = record(_servo_env("dynamic", []), args.episodes, args.steps, args.seed, scripted_actions=True)
    result = fit(data)
    gains = {"lag_gain": tuple(result["lag_gain"]), "lag_momentum": tuple(result["lag_momentum"])}
    print("env.control.lag_gain =", tuple(round(v, 3) for v in result["lag_gain"]))
    print("env.control.lag_momentum =", tuple(round(v, 3) for v in result["lag_momentum"]))
    print("residual rms per joint, mrad (2nd order | 1st order | step):")
    for j in range(len(result["lag_gain"])):
        print(f"  q{j + 1}: {1e3 * result['residual_rms_rad'][j]:.2f} | {1e3 * result['residual_rms_first_order_rad'][j]:.2f}"
              f" | {1e3 * result['step_rms_rad'][j]:.1f}")
    checks = [drift(args.episodes, 40, args.seed + 7, lat, gains) for lat in (0.0, 1.0, 2.0)]
    print("open-loop gripper-centre gap to the dynamic env, 40 random steps (mean / p95, mm):")
    print("| latency | lagged | kinematic |\n|---|---|---|")
    for c in checks:
        print(f"| 0-{c['latency']:g} | {1e3 * c['lagged_vs_dynamic_mean_m']:.1f} / {1e3 * c['lagged_vs_dynamic_p95_m']:.1f} | "
              f"{1e3 * c['kinematic_vs_dynamic_mean_m']:.1f} / {1e3 * c['kinematic_vs_dynamic_p95_m']:.1f} |")
    atomic_write_json(args.out, {"episodes": args.episodes, "steps": args.steps, "seed": args.seed, **result,
                                 "open_loop_gap": checks})
    print(f"wrote {args.out}")
    return 0


# ---------------------------------------------------------------------- sysid-check

SYSID_CHECK_DOC = """Does ``sagrasp_jax.deploy.sysid`` recover known arm parameters?  Logs synthesised by the dynamic env.

Each case sets one arm's servo gains (kp and kv scaled alike per joint), command latency and joint-reading
offsets, drives the dynamic (MJX) env with scripted reach-and-descend actions plus noise, records the log
the deploy loop would (time, commanded targets, readings with Gaussian noise), runs the identification
and compares: latency (ms), offsets (mrad) and the servo gain.  The servo gain's truth for the lagged model is
the per-step model fitted to a noise-free, latency-free log of the same arm (``truth_model``): what the
lagged mode can represent of that arm.  Prints a table and writes JSON."""


SYSID_CASES: dict[str, dict[str, Any]] = {
    "nominal": {"kp_scale": [1.0] * 6, "latency": 0.0, "offset": [0.0] * 6},
    "whole-step": {"kp_scale": [1.0] * 6, "latency": 1.0, "offset": [0.004, -0.003, 0.002, -0.005, 0.001, 0.003]},
    "slow-late": {"kp_scale": [0.8, 0.85, 0.9, 0.8, 0.85, 0.9], "latency": 1.2,
                  "offset": [0.004, -0.003, 0.002, -0.005, 0.001, 0.003]},
    "stiff-later": {"kp_scale": [1.2, 1.15, 1.1, 1.2, 1.15, 1.1], "latency": 2.4,
                    "offset": [-0.002, 0.005, -0.004, 0.003, -0.001, 0.0]},
}


def synthesize(kp_scale: Any, latency: float, offset: Any, noise: float = 0.0005, episodes: int = 1, steps: int = 400,
               seed: int = 0) -> sysid.RobotLog:
    """A log of ``episodes`` × ``steps`` control periods of the dynamic env with these arm parameters (several
    episodes are logged one after another: each jump between them is a period the fit cannot explain)."""
    overrides = ["env.control.mode=dynamic", "env.task.obs_noise_std=0", "env.randomize.latency=3",
                 "env.randomize.servo_gain=0.2"]  # knobs on so the env keeps a command queue and a draw to overwrite
    cfg = config_parse.apply_overrides(config.get_config("cpu-quick"), overrides).env
    env = GraspEnv(cfg)
    kp = jnp.asarray(kp_scale, jnp.float32)
    known = {"kp_scale": kp, "kv_scale": kp, "latency": jnp.asarray(latency, jnp.float32),
             "joint_offset": jnp.zeros(6), "joint_noise": jnp.zeros(()), "target_error": jnp.zeros(3)}

    def run(keys: Any, eps: Any) -> Any:
        state = jax.vmap(env.reset)(keys)
        info = dict(state.info, randomize={k: jnp.broadcast_to(v, (keys.shape[0], *v.shape)) for k, v in known.items()})
        state = state.replace(info=info)

        def body(st: Any, e: Any) -> Any:
            q = jax.vmap(env.measured_joints)(st)
            act = jax.vmap(lambda qq, t: scripted.scripted_action(jnp, cfg, qq, t))(q, st.info["reset"].target_pos)
            nxt = jax.vmap(env.step)(st, jnp.clip(act + e, -1.0, 1.0))
            nxt = nxt.replace(done=jnp.zeros_like(nxt.done))  # no auto-reset here: one long trajectory per episode
            return nxt, (q, nxt.info["q_target"])

        return jax.lax.scan(body, state, eps)[1]

    keys = jax.random.split(jax.random.PRNGKey(seed), episodes)
    eps = 0.5 * jax.random.uniform(jax.random.PRNGKey(seed + 1), (steps, episodes, 6), minval=-1.0, maxval=1.0)
    q, command = (np.asarray(a, dtype=float) for a in jax.jit(run)(keys, eps))
    rng = np.random.default_rng(seed)
    # one log: the episodes one after another (each starts from rest at its own pose: a short pause in the log)
    q = np.concatenate([q[:, e] for e in range(episodes)], axis=0)
    command = np.concatenate([command[:, e] for e in range(episodes)], axis=0)
    readings = q + np.asarray(offset) + noise * rng.standard_normal(q.shape)
    time = np.arange(q.shape[0]) * cfg.control.control_dt
    return sysid.RobotLog(time, command, readings)


def write_csv(log: sysid.RobotLog, path: str) -> None:
    with open(path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(sysid.COLUMNS)
        for t, c, y in zip(log.time, log.command, log.measured):
            writer.writerow([f"{t:.4f}", *(f"{v:.6f}" for v in c), *(f"{v:.6f}" for v in y)])


def truth_model(kp_scale: Any) -> sysid.SysIdResult:
    """The lagged model of an arm with these gains: fitted to its noise-free, latency-free log."""
    return sysid.identify(synthesize(kp_scale, 0.0, [0.0] * 6, noise=0.0))


def sysid_case(name: str, case: dict[str, Any]) -> dict[str, Any]:
    log = synthesize(case["kp_scale"], case["latency"], case["offset"])
    fit = sysid.identify(log)
    truth = truth_model(case["kp_scale"])
    dt = float(np.median(np.diff(log.time)))
    return {
        "case": name, **case,
        "latency_error_ms": 1000 * abs(fit.latency_steps - case["latency"]) * dt,
        "offset_error_mrad": (1000 * np.abs(fit.joint_offset - np.asarray(case["offset"]))).tolist(),
        "lag_gain": fit.lag_gain.tolist(), "lag_gain_truth": truth.lag_gain.tolist(),
        "lag_gain_error_rel": (np.abs(fit.lag_gain / truth.lag_gain - 1)).tolist(),
        "lag_momentum": fit.lag_momentum.tolist(), "lag_momentum_truth": truth.lag_momentum.tolist(),
        "residual_rms_mrad": (1000 * fit.residual_rms).tolist(),
    }


def sysid_check_main(argv: list[str] | None = None) -> int:
    """``sysid-check``: does ``deploy.sysid`` recover known arm parameters from logs the dynamic env synthesises?"""
    parser = argparse.ArgumentParser(prog="python -m experiments.robot_grade sysid-check", description=SYSID_CHECK_DOC)
    parser.add_argument("--out", default="experiments/results/sysid_check.json")
    args = parser.parse_args(argv)
    rows = [sysid_case(name, case) for name, case in SYSID_CASES.items()]
    print("| case | latency truth (steps) | latency error (ms) | max offset error (mrad) | max lag_gain error (%) |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['case']} | {r['latency']:g} | {r['latency_error_ms']:.2f} | {max(r['offset_error_mrad']):.3f} | "
              f"{100 * max(r['lag_gain_error_rel']):.1f} |")
    atomic_write_json(args.out, {"cases": rows})
    print(f"wrote {args.out}")
    return 0


# ---------------------------------------------------------------------- twin-vs-mjx (the deploy loop on the twin)

TWIN_DOC = """The robot's grasp against the simulator's: MJX success and physical hold beside the twin's held cube.

For each ``--run NAME=FOLDER`` and each named condition (``config.EVAL_CONDITIONS``) on each scene set
(the evaluation mix, blocking-only scenes): the MJX evaluation (``evaluation.evaluate_run``: kinematic
success; with ``--physical``, every success closed and lifted in CPU MuJoCo, ``evaluate.evaluate_physical``)
and the deployment at scale on the PyBullet twin (``deploy.rehearse``: the run's ``policy.npz`` through the
deploy loop, judged by the cube held after the lift).  Prints a Markdown table and writes JSON (the twin's
per-episode records included)."""

TWIN_CASES = ("kinematic:mix", "robot:mix", "kinematic:blocking", "robot:blocking", "robot-wide:mix")


def mjx_case(folder: str, condition: str, scenes: str, episodes: int, physical: bool) -> dict[str, Any]:
    """MJX success (and physical hold) of one run in one condition on one scene set."""
    overrides = list(EVAL_CONDITIONS[condition])
    res = evaluation.evaluate_run(folder, episodes, overrides=overrides, scenes=scenes)
    key = "blocking" if scenes == "blocking" else "overall"
    out = {"success": res[key].get("success_rate"), "obstacle_success": res["obstacle_present"].get("success_rate"),
           "episodes": episodes, "steps_per_success": res[key].get("mean_steps_per_success")}
    if physical:
        seed, steps = evaluation.resolve_options(run_dir.load_config(folder), None, None)
        ph = evaluate.evaluate_physical(folder, episodes, seed, steps, overrides=overrides, scenes=scenes)
        out["physical"] = ph["physical_success_rate"]
        out["physical_given_kinematic"] = ph["physical_given_kinematic"]
    return out


def twin_case(folder: str, condition: str, scenes: str, episodes: int, seed: int, workers: int) -> dict[str, Any]:
    from sagrasp_jax.deploy import rehearse  # the twin's deploy loop: only this subcommand needs it

    res = rehearse.rehearse(os.path.join(folder, "policy.npz"), episodes, condition, scenes, seed, workers,
                            progress=False)
    print(rehearse.format_table(res), file=sys.stderr, flush=True)
    return res


def twin_table(results: dict[str, Any]) -> str:
    head = ("| run | condition | scenes | MJX success | MJX physical hold | twin held (95 % CI) | twin obstacle scenes "
            "| twin reached | twin failures | twin − MJX physical |")
    lines = [head, "|---" * (head.count("|") - 1) + "|"]
    for run, cases in results.items():
        for name, case in cases.items():
            mjx, twin = case["mjx"], case["twin"]["summary"]
            t = twin["all"]
            ob = twin["obstacle"]
            pct = lambda v: "-" if v is None else f"{100 * v:.1f} %"  # noqa: E731
            fails = ", ".join(f"{k} {v}" for k, v in t["failures"].items()) or "none"
            ref = mjx.get("physical", mjx["success"])
            gap = "-" if ref is None or t["held_rate"] is None else f"{100 * (t['held_rate'] - ref):+.1f}"
            cond, scenes = name.split(":")
            lines.append(f"| {run} | {cond} | {scenes} | {pct(mjx['success'])} | {pct(mjx.get('physical'))} | "
                         f"{pct(t['held_rate'])} ({100 * t['held_ci95'][0]:.1f}-{100 * t['held_ci95'][1]:.1f}, "
                         f"n={t['episodes']}) | {pct(ob['held_rate'])} (n={ob['episodes']}) | {pct(t['reached_rate'])} "
                         f"| {fails} | {gap} |")
    return "\n".join(lines)


def twin_vs_mjx_main(argv: list[str] | None = None) -> int:
    """``twin-vs-mjx``: each run on the PyBullet twin through the deploy loop beside its MJX evaluation (``TWIN_DOC``)."""
    from sagrasp_jax.deploy import rehearse

    p = argparse.ArgumentParser(prog="python -m experiments.robot_grade twin-vs-mjx", description=TWIN_DOC.split("\n\n")[0])
    p.add_argument("--run", action="append", required=True, metavar="NAME=FOLDER")
    p.add_argument("--cases", nargs="+", default=list(TWIN_CASES), metavar="CONDITION:SCENES")
    p.add_argument("--twin-episodes", type=int, default=500)
    p.add_argument("--mjx-episodes", type=int, default=1000)
    p.add_argument("--twin-seed", type=int, default=0)
    p.add_argument("--physical", action="store_true", help="also the MJX physical grasp check")
    p.add_argument("--no-mjx", action="store_true", help="the twin alone")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    for case in args.cases:
        cond, _, scenes = case.partition(":")
        if cond not in EVAL_CONDITIONS or scenes not in rehearse.SCENE_SETS:
            p.error(f"--cases {case}: CONDITION:SCENES with a condition of {', '.join(EVAL_CONDITIONS)} and scenes "
                    f"{' or '.join(rehearse.SCENE_SETS)}")
    results: dict[str, Any] = {}
    for item in args.run:
        name, _, folder = item.partition("=")
        results[name] = {}
        for case in args.cases:
            cond, _, scenes = case.partition(":")
            t0 = time.perf_counter()
            mjx = {"success": None} if args.no_mjx else mjx_case(folder, cond, scenes, args.mjx_episodes, args.physical)
            twin = twin_case(folder, cond, scenes, args.twin_episodes, args.twin_seed, args.workers)
            results[name][case] = {"mjx": mjx, "twin": twin, "wall_s": time.perf_counter() - t0}
            print(f"{name} {case}: MJX {mjx}, twin held {twin['summary']['all']['held_rate']}", file=sys.stderr, flush=True)
            atomic_write_json(args.out, {"args": vars(args), "results": results}, indent=1)
    print(twin_table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
