"""Refit PyBullet's POSITION_CONTROL gains to the MJX env's servos (docs/parity.md, "Dynamic mode").

PyBullet's motor is a velocity constraint: after a physics step h, v⁺ = kp·(q* − q)/h + (1 − kd)·v per
joint (when its force limit is not reached), whatever the arm's inertia.  This script records physics
substeps of the MJX dynamic model (x64; scripted reach-and-descend actions with noise, the parity
harness's ``scripted`` source) and fits kp, kd per joint by linear least squares of v⁺ on
((q* − q)/h, v): the best that law can do against MuJoCo's.  It prints the gains (paste them into
``DYNAMIC_POSITION_GAINS`` / ``DYNAMIC_VELOCITY_GAINS``) and the fit's residual, and writes JSON.

    python -m experiments.fit_position_control --out experiments/results/fit_position_control.json
"""

from __future__ import annotations

import argparse
import sys

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

import sagrasp_jax  # noqa: F401
from sagrasp_jax import config, scripted
from sagrasp_jax.env import GraspEnv
from sagrasp_jax.fileio import atomic_write_json


def record(episodes: int, steps: int, seed: int) -> dict[str, np.ndarray]:
    cfg = config.apply_overrides(config.get_config("paper"), ["env.control.mode=dynamic", "env.task.obs_noise_std=0"]).env
    env = GraspEnv(cfg)
    model, n_sub, h = env._mjx_model, cfg.control.substeps, cfg.control.physics_dt

    def run(keys, noise):
        state = jax.vmap(env.reset)(keys)

        def body(st, eps):
            q = st.pipeline_state.qpos
            act = jnp.clip(jax.vmap(lambda qq, t: scripted.scripted_action(jnp, cfg, qq, t))(q, st.info["reset"].target_pos)
                           + eps, -1.0, 1.0)
            nxt = jax.vmap(env.step)(st, act)

            def sub(d, _):
                d2 = jax.vmap(mjx.step, (None, 0))(model, d)
                return d2, (d.qpos, d.qvel, d.ctrl, d2.qvel)

            data = st.pipeline_state.replace(ctrl=nxt.info["q_target"])
            _, rows = jax.lax.scan(sub, data, None, length=n_sub)
            return nxt, rows

        _, rows = jax.lax.scan(body, state, noise)
        return rows

    keys = jax.random.split(jax.random.PRNGKey(seed), episodes)
    noise = 0.3 * jax.random.uniform(jax.random.PRNGKey(seed + 1), (steps, episodes, 6), minval=-1.0, maxval=1.0)
    q, v, ctrl, v_next = (np.asarray(a).reshape(-1, 6) for a in jax.jit(run)(keys, noise))
    return {"e_over_h": (ctrl - q) / h, "v": v, "v_next": v_next}


def parse_recording_args(argv: list[str] | None, description: str, out: str) -> argparse.Namespace:
    """The options of a fit over scripted episodes: how many, how long, their seed, where the JSON goes."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=out)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_recording_args(argv, __doc__.splitlines()[0], "experiments/results/fit_position_control.json")
    # the fit is in float64; switched on here, not at import, so that importing this module for
    # parse_recording_args (fit_servo_lag, the tests) leaves the importer's precision alone
    jax.config.update("jax_enable_x64", True)
    data = record(args.episodes, args.steps, args.seed)
    kp, kd, rms, scale = [], [], [], []
    for j in range(6):
        a = np.stack([data["e_over_h"][:, j], data["v"][:, j]], axis=1)
        coef, *_ = np.linalg.lstsq(a, data["v_next"][:, j], rcond=None)
        kp.append(float(coef[0]))
        kd.append(float(1.0 - coef[1]))
        rms.append(float(np.sqrt(np.mean((a @ coef - data["v_next"][:, j]) ** 2))))
        scale.append(float(np.sqrt(np.mean(data["v_next"][:, j] ** 2))))
    print("DYNAMIC_POSITION_GAINS =", tuple(round(k, 3) for k in kp))
    print("DYNAMIC_VELOCITY_GAINS =", tuple(round(k, 3) for k in kd))
    print("residual rms of v⁺ per joint (rad/s):", [f"{r:.3f} of {s:.3f}" for r, s in zip(rms, scale)])
    atomic_write_json(args.out, {"samples": int(data["v"].shape[0]), "episodes": args.episodes, "steps": args.steps,
                                 "position_gains": kp, "velocity_gains": kd, "residual_rms": rms, "v_next_rms": scale})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
