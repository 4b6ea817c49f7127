"""Does ``sagrasp_jax.sysid`` recover known arm parameters?  Logs synthesised by the dynamic env.

Each case sets one arm's servo gains (kp and kv scaled alike per joint), command latency and joint-reading
offsets, drives the dynamic (MJX) env with scripted reach-and-descend actions plus noise, records the log
the deploy loop would (time, commanded targets, readings with Gaussian noise), runs the identification
and compares: latency (ms), offsets (mrad) and the servo gain.  The servo gain's truth for the lagged model is
the per-step model fitted to a noise-free, latency-free log of the same arm (``truth_model``): what the
lagged mode can represent of that arm.  Prints a table and writes JSON.

    python -m experiments.sysid_check --out experiments/results/sysid_check.json
"""

from __future__ import annotations

import argparse
import csv
import sys
from typing import Any

import sagrasp_jax  # noqa: F401  (XLA flags before jax)
import jax
import jax.numpy as jnp
import numpy as np

from sagrasp_jax import config, scripted, sysid
from sagrasp_jax.env import GraspEnv
from sagrasp_jax.fileio import atomic_write_json

CASES: dict[str, dict[str, Any]] = {
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
    cfg = config.apply_overrides(config.get_config("cpu-quick"), overrides).env
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


def check(name: str, case: dict[str, Any]) -> dict[str, Any]:
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="experiments/results/sysid_check.json")
    args = parser.parse_args(argv)
    rows = [check(name, case) for name, case in CASES.items()]
    print("| case | latency truth (steps) | latency error (ms) | max offset error (mrad) | max lag_gain error (%) |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['case']} | {r['latency']:g} | {r['latency_error_ms']:.2f} | {max(r['offset_error_mrad']):.3f} | "
              f"{100 * max(r['lag_gain_error_rel']):.1f} |")
    atomic_write_json(args.out, {"cases": rows})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
