"""Fit the lagged mode's per-step servo model to the dynamic mode's MJX servos, and check it.

The ``lagged`` control mode (env.control.mode=lagged) replaces MuJoCo's servo physics with one update per
control step: q ← q + g·(c − q) + m·(q − q_prev) per joint (``control.servo_model_step``).  This script
records control steps of the dynamic env (scripted reach-and-descend actions with uniform noise, every
randomisation knob off), fits g (``env.control.lag_gain``) and m (``env.control.lag_momentum``) per joint by
linear least squares of the step q⁺ − q on (c − q, q − q_prev), and then replays the same action sequences
open-loop in the dynamic and lagged envs (with and without command latency) and reports how far their
gripper centres drift apart: the cheap model is what the policy trains in, the dynamic env is the judge.

    python -m experiments.fit_servo_lag --out experiments/results/fit_servo_lag.json
"""

from __future__ import annotations

import sys
from typing import Any

import sagrasp_jax  # noqa: F401  (XLA flags before jax)
import jax
import jax.numpy as jnp
import numpy as np

from experiments.fit_position_control import parse_recording_args
from sagrasp_jax import config, robot, scripted
from sagrasp_jax.env import GraspEnv
from sagrasp_jax.fileio import atomic_write_json


def _env(mode: str, extra: list[str], gains: dict[str, tuple[float, ...]] | None = None) -> GraspEnv:
    overrides = [*config.KNOBS_OFF,  # the preset trains with them on
                 f"env.control.mode={mode}", "env.task.obs_noise_std=0", "env.task.obs_layout=relative_lag",
                 *extra]
    if gains:
        overrides += [f"env.control.{k}={','.join(f'{v:.6f}' for v in vals)}" for k, vals in gains.items()]
    return GraspEnv(config.apply_overrides(config.get_config("cpu-quick"), overrides).env)


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
    noise = 0.6 * jax.random.uniform(jax.random.PRNGKey(seed + 1), (steps, episodes, 6), minval=-1.0, maxval=1.0)
    q, command, q_next, centre = (np.asarray(a) for a in jax.jit(run)(keys, noise))
    return {"q": q, "command": command, "q_next": q_next, "centre": centre}


def fit(data: dict[str, np.ndarray]) -> dict[str, list[float]]:
    q, c, qn = data["q"], data["command"], data["q_next"]
    q_prev = np.concatenate([q[:1], q[:-1]], axis=0)  # the first step of an episode starts at rest
    gain, momentum, rms, rms_first_order, step_rms = [], [], [], [], []
    for j in range(6):
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
    dyn = record(_env("dynamic", extra), episodes, steps, seed, scripted_actions=False)
    lag = record(_env("lagged", extra, gains), episodes, steps, seed, scripted_actions=False)
    kin = record(_env("kinematic", []), episodes, steps, seed, scripted_actions=False)
    gap = np.linalg.norm(dyn["centre"] - lag["centre"], axis=-1)
    gap_kin = np.linalg.norm(dyn["centre"] - kin["centre"], axis=-1)
    return {"latency": latency, "lagged_vs_dynamic_mean_m": float(gap.mean()), "lagged_vs_dynamic_p95_m":
            float(np.percentile(gap, 95)), "kinematic_vs_dynamic_mean_m": float(gap_kin.mean()),
            "kinematic_vs_dynamic_p95_m": float(np.percentile(gap_kin, 95))}


def main(argv: list[str] | None = None) -> int:
    args = parse_recording_args(argv, __doc__.splitlines()[0], "experiments/results/fit_servo_lag.json")
    data = record(_env("dynamic", []), args.episodes, args.steps, args.seed, scripted_actions=True)
    result = fit(data)
    gains = {"lag_gain": tuple(result["lag_gain"]), "lag_momentum": tuple(result["lag_momentum"])}
    print("env.control.lag_gain =", tuple(round(v, 3) for v in result["lag_gain"]))
    print("env.control.lag_momentum =", tuple(round(v, 3) for v in result["lag_momentum"]))
    print("residual rms per joint, mrad (2nd order | 1st order | step):")
    for j in range(6):
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


if __name__ == "__main__":
    sys.exit(main())
