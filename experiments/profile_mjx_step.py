"""Profile ``mjx.step`` for the dynamic mode's model: cost per physics substep at batch 256 (CPU).

Each variant strips one more thing the dynamic mode does not need (docs/parity.md, "Dynamic mode"):

* ``scene``: ``sagrasp_jax/mjcf/scene.xml`` with contacts off — the first landing's dynamic model (8 DoF, joint
  limits as constraints, so the constraint solver runs);
* ``+noconstraint``: constraints off (no joint-limit rows, no solver: the targets are clipped to the limits);
* ``robot``: the robot MJCF alone (no cell, cameras, mocap bodies);
* ``lean``: no geoms and sites (inertias are explicit), joint-less bodies fused;
* ``lean+weld``: fingers welded open (6 DoF) — what ``GraspEnv._load_mjx_model`` builds;
* ``...+euler``, ``...+nogravity``: the integrator and gravity, for comparison (not used).

Reports wall-clock and process CPU time per substep (the machine may be shared: CPU time suffers
less from other jobs) with the 1-minute load average, prints a table and writes JSON.

    python -m experiments.profile_mjx_step --out experiments/results/profile_mjx_step_cpu.json
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import sagrasp_jax  # noqa: F401  (XLA flags)
import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

from sagrasp_jax import config, robot
from sagrasp_jax.env import MJCF_ROBOT, MJCF_SCENE, GraspEnv
from sagrasp_jax.fileio import atomic_write_json

VARIANTS = ("scene", "scene+noconstraint", "robot+noconstraint", "lean+noconstraint", "lean+weld+noconstraint",
            "lean+weld+noconstraint+euler", "lean+weld+noconstraint+nogravity")


def build(variant: str) -> mujoco.MjModel:
    if "weld" in variant:  # exactly the env's dynamic model
        cfg = config.apply_overrides(config.get_config("paper"), ["env.control.mode=dynamic"]).env
        model = GraspEnv(cfg)._mj_model
    elif variant.startswith("lean"):
        spec = mujoco.MjSpec.from_file(os.path.normpath(MJCF_ROBOT))
        for element in list(spec.geoms) + list(spec.sites):
            spec.delete(element)
        spec.compiler.fusestatic = True
        model = spec.compile()
    else:
        model = mujoco.MjModel.from_xml_path(os.path.normpath(MJCF_ROBOT if variant.startswith("robot") else MJCF_SCENE))
    model.opt.timestep = 0.01
    model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    if "noconstraint" in variant:
        model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    if "nogravity" in variant:
        model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_GRAVITY
    if "euler" in variant:
        model.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    return model


def bench(variant: str, batch: int, substeps: int, reps: int) -> dict:
    model = build(variant)
    mx = mjx.put_model(model)
    q0 = jnp.concatenate([jnp.asarray(config.HOME_Q), jnp.full(model.nq - 6, robot.load_robot().finger_open)])
    data = mjx.make_data(mx).replace(qpos=q0, ctrl=q0)
    batched = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), data)
    ctrl = q0 + 0.05 * jax.random.uniform(jax.random.PRNGKey(0), (substeps, batch, model.nq), minval=-1.0, maxval=1.0)

    def run(ds, ctrl):
        def body(ds, c):
            return jax.vmap(mjx.step, (None, 0))(mx, ds.replace(ctrl=c)), None

        return jax.lax.scan(body, ds, ctrl)[0]

    fn = jax.jit(run)
    t0 = time.perf_counter()
    jax.block_until_ready(fn(batched, ctrl).qpos)
    compile_s = time.perf_counter() - t0
    wall = cpu = float("inf")
    load = os.getloadavg()[0]
    for _ in range(reps):
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(batched, ctrl).qpos)
        wall, cpu = min(wall, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
    return {"variant": variant, "nq": model.nq, "nbody": model.nbody, "ngeom": model.ngeom, "batch": batch,
            "compile_s": round(compile_s, 2), "wall_ms_per_substep": round(1e3 * wall / substeps, 3),
            "cpu_ms_per_substep": round(1e3 * cpu / substeps, 3),
            "substeps_per_s": round(batch * substeps / wall), "load_1min": [round(load, 2), round(os.getloadavg()[0], 2)]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--substeps", type=int, default=50, help="substeps timed per repetition")
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--out", default="experiments/results/profile_mjx_step.json")
    args = parser.parse_args(argv)
    rows = []
    print(f"{'variant':34s} {'nq':>3s} {'compile s':>9s} {'wall ms':>8s} {'cpu ms':>7s} {'substeps/s':>11s}  load")
    for variant in args.variants.split(","):
        if variant not in VARIANTS:
            parser.error(f"unknown variant {variant!r}; choose from {', '.join(VARIANTS)}")
        row = bench(variant, args.batch, args.substeps, args.reps)
        rows.append(row)
        print(f"{variant:34s} {row['nq']:3d} {row['compile_s']:9.1f} {row['wall_ms_per_substep']:8.2f} "
              f"{row['cpu_ms_per_substep']:7.2f} {row['substeps_per_s']:11d}  {row['load_1min']}", flush=True)
    atomic_write_json(args.out, {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                                             "jax_backend": jax.default_backend()},
                                 "versions": {"jax": jax.__version__, "mujoco": mujoco.__version__},
                                 "batch": args.batch, "rows": rows})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
