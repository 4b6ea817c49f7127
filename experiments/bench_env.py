"""Env throughput: env-steps/s of the JAX env for batch sizes 1…4096 in both modes.

Measures (a) the bare env (``jax.vmap(env.step)``, no auto-reset) and (b) the training
path (``AutoReset.batch_step``, fresh-sample resets) inside a jitted ``lax.scan`` of
random actions; compile time is reported separately.  The machine may be shared: every row
records the 1-minute load average before and after it and the process CPU time per env step
beside the wall-clock rate (under contention the wall clock suffers, the CPU time much less).
Every cell runs on 1 jax device and, split over them with ``shard_map`` as the trainer does, on
all CPU devices (one per core, ``train.use_cpu_devices``; ``--devices`` picks the counts).  With
``--pybullet`` it also times the PyBullet reference env (raw stepping, one env, kinematic and dynamic) when the
``reference`` extra is installed.  Prints a table and writes JSON.  ``bench_bare_pybullet`` times a bare PyBullet
AUBO-i5 chain, the paper stack's raw stepping (``bench_train``'s sb3 section, ``bench_vs_paper_stack raw``).

    python -m experiments.bench_env --out experiments/results/bench_env_cpu.json
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time

import sagrasp_jax  # noqa: F401  (XLA flags)
import jax

from jax.sharding import PartitionSpec

from sagrasp_jax import train
from sagrasp_jax.task import config
from sagrasp_jax.task import config_parse
from sagrasp_jax.training import sharding
from sagrasp_jax.envs.grasp_env import GraspEnv
from sagrasp_jax.base.fileio import atomic_write_json
from sagrasp_jax.envs.auto_reset import AutoReset


def bench_jax(mode: str, batch: int, steps: int, auto_reset: bool, overrides: list[str] | None = None,
              devices: int = 1) -> dict:
    sets = [f"env.control.mode={mode}"] + list(overrides or [])
    cfg = config_parse.apply_overrides(config.get_config("paper"), sets).env
    base = GraspEnv(cfg)
    env = AutoReset(base) if auto_reset else base
    step = env.batch_step if auto_reset else jax.vmap(base.step)

    local = batch // devices

    def rollout(state, key):
        def body(st, k):
            st = step(st, jax.random.uniform(k, (local, base.action_size), minval=-1.0, maxval=1.0))
            return st, st.done.sum()

        return jax.lax.scan(body, state, jax.random.split(key, steps))

    reset = jax.jit(jax.vmap(env.reset))
    if devices == 1:
        run = jax.jit(rollout)
    else:  # each device steps its share of the batch (its own random actions), as in training
        mesh = sharding.make_mesh(jax.devices()[:devices])
        shard, rep = PartitionSpec(sharding.BATCH_AXIS), PartitionSpec()

        def per_device(state, key):
            return rollout(state, jax.random.fold_in(key, jax.lax.axis_index(sharding.BATCH_AXIS)))

        sharded = jax.jit(sharding.sharded(per_device, mesh, (shard, rep), (shard, shard)))
        run = lambda state, key: sharded(state, sharding.replicate(key, mesh))  # noqa: E731
    t0 = time.perf_counter()
    state = reset(jax.random.split(jax.random.PRNGKey(0), batch))
    jax.block_until_ready(state.obs)
    if devices > 1:
        state = sharding.shard_batch(state, mesh)
    out = run(state, jax.random.PRNGKey(1))
    jax.block_until_ready(out)
    compile_s = time.perf_counter() - t0
    state = out[0]
    best = best_cpu = float("inf")
    load_before = os.getloadavg()[0]
    for rep in range(3):
        t0, c0 = time.perf_counter(), time.process_time()
        state, dones = run(state, jax.random.PRNGKey(2 + rep))
        jax.block_until_ready(dones)
        best = min(best, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    return {
        "mode": mode,
        "auto_reset": auto_reset,
        "batch": batch,
        "devices": devices,
        "steps": steps,
        "overrides": list(overrides or []),
        "compile_s": round(compile_s, 2),
        "env_steps_per_s": round(batch * steps / best, 1),
        "cpu_us_per_env_step": round(1e6 * best_cpu / (batch * steps), 2),
        "load_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
    }


def bench_pybullet(mode: str, steps: int) -> dict | None:
    try:
        from sagrasp_jax.reference.pybullet_env import PyBulletGraspEnv
    except ImportError as exc:  # reference extra missing
        print(f"skipping PyBullet ({exc})", file=sys.stderr)
        return None
    cfg = config.get_config("paper").env
    cfg = dataclasses.replace(cfg, control=dataclasses.replace(cfg.control, mode=mode))
    env = PyBulletGraspEnv(cfg)
    env.reset(seed=0)
    rng = jax.random.PRNGKey(0)
    actions = jax.device_get(jax.random.uniform(rng, (steps, env.robot.dof), minval=-1.0, maxval=1.0))
    t0 = time.perf_counter()
    for a in actions:
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()
    elapsed = time.perf_counter() - t0
    env.close()
    return {"mode": mode, "backend": "pybullet", "batch": 1, "steps": steps, "env_steps_per_s": round(steps / elapsed, 1)}


def bench_bare_pybullet(steps: int = 20_000, physics_steps: int = 0, robot_name: str = "aubo_i5") -> dict | None:
    """Raw stepping of a bare PyBullet AUBO-i5 chain (docs/task.md §6's anchor, no learning): per step
    the 6 arm joints' new targets, the gripper link's pose, one closest-point query to an obstacle, a
    17-number observation.  ``physics_steps`` 0 sets the joints (``resetJointState``: the kinematic
    stepping); N > 0 is the paper stack's dynamic stepping: position control of the 6 joints under
    gravity and N ``stepSimulation`` calls of 1/240 s (12: one 0.05 s control period).  ``robot_name``: another
    registered arm's chain instead (its URDF, joints and home pose)."""
    try:
        import pybullet as pb
    except ImportError:
        return None
    import numpy as np

    from sagrasp_jax.task import robot

    cid = pb.connect(pb.DIRECT)
    try:
        model = robot.load_robot(robot_name)
        arm = pb.loadURDF(model.urdf_path, useFixedBase=True, physicsClientId=cid)
        joints = [j for j in range(pb.getNumJoints(arm, physicsClientId=cid))
                  if pb.getJointInfo(arm, j, physicsClientId=cid)[2] == pb.JOINT_REVOLUTE][:model.dof]
        tip = pb.getNumJoints(arm, physicsClientId=cid) - 1
        shape = pb.createCollisionShape(pb.GEOM_SPHERE, radius=0.05, physicsClientId=cid)
        obstacle = pb.createMultiBody(0, shape, basePosition=[0.0, -0.45, 0.2], physicsClientId=cid)
        rng = np.random.default_rng(0)
        actions = rng.uniform(-1, 1, (steps, model.dof))
        q = np.array(model.spec.home_q)
        for j, qj in zip(joints, q):
            pb.resetJointState(arm, j, qj, physicsClientId=cid)
        if physics_steps:
            pb.setGravity(0, 0, -9.81, physicsClientId=cid)
            pb.setTimeStep(1.0 / 240.0, physicsClientId=cid)
        target = np.array([0.1, -0.45, 0.025])
        t = time.perf_counter()
        for a in actions:
            q = np.clip(q + 0.05 * a, -config.Q_LIMIT, config.Q_LIMIT)
            if physics_steps:
                pb.setJointMotorControlArray(arm, joints, pb.POSITION_CONTROL, targetPositions=q.tolist(),
                                             forces=[150.0] * model.dof, physicsClientId=cid)
                for _ in range(physics_steps):
                    pb.stepSimulation(physicsClientId=cid)
            else:
                for j, qj in zip(joints, q):
                    pb.resetJointState(arm, j, qj, physicsClientId=cid)
            pos = pb.getLinkState(arm, tip, physicsClientId=cid)[0]
            close = pb.getClosestPoints(arm, obstacle, 1.0, physicsClientId=cid)
            d = min((c[8] for c in close), default=1.0)
            np.concatenate([q, pos, target, [0.0, -0.45, 0.2, d, 0.0]])
        elapsed = time.perf_counter() - t
    finally:
        pb.disconnect(physicsClientId=cid)
    how = (f"position control, {physics_steps} x stepSimulation(1/240 s)" if physics_steps
           else "resetJointState x6")
    return {"what": f"bare PyBullet AUBO-i5 chain: {how}, link pose, one closest-point query, 17-d observation",
            "steps": steps, "physics_steps": physics_steps, "env_steps_per_s": steps / elapsed}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", default="1,16,64,256,1024,4096", help="comma-separated batch sizes")
    parser.add_argument("--modes", default="kinematic,dynamic")
    parser.add_argument("--env-steps", type=int, default=100_000, help="env steps timed per cell (capped by --max-steps)")
    parser.add_argument("--max-steps", type=int, default=200, help="max scan length per cell")
    parser.add_argument("--dynamic-max-batch", type=int, default=1024, help="largest batch for dynamic mode on CPU")
    parser.add_argument("--pybullet", action="store_true", help="also time the PyBullet reference env")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="config override of the env for every JAX row (e.g. env.control.substeps=2)")
    parser.add_argument("--no-auto-reset", action="store_true", help="time the bare env only")
    parser.add_argument("--devices", default="1,all",
                        help="comma-separated jax device counts per cell; 'all' = one CPU device per core")
    parser.add_argument("--out", default="experiments/results/bench_env.json")
    args = parser.parse_args(argv)
    train.use_cpu_devices(config.get_config("cpu-quick"))  # one CPU device per core, as the trainer
    try:
        counts = sorted({len(jax.devices()) if d == "all" else int(d) for d in args.devices.split(",")})
    except ValueError:
        parser.error(f"--devices must be comma-separated integers or 'all', got {args.devices!r}")
    if not counts or counts[0] < 1 or counts[-1] > len(jax.devices()):
        parser.error(f"--devices must be in [1, {len(jax.devices())}], got {args.devices!r}")
    try:
        batches = [int(b) for b in args.batches.split(",")]
    except ValueError:
        parser.error(f"--batches must be comma-separated integers, got {args.batches!r}")
    modes = args.modes.split(",")
    for m in modes:
        if m not in ("kinematic", "dynamic"):
            parser.error(f"unknown mode {m!r}; choose kinematic, dynamic")
    rows = []
    print(f"{'mode':10s} {'reset':>6s} {'batch':>6s} {'dev':>4s} {'steps':>6s} {'compile s':>10s} {'env-steps/s':>12s}")
    for mode in modes:
        for batch in batches:
            if mode == "dynamic" and jax.default_backend() == "cpu" and batch > args.dynamic_max_batch:
                continue
            steps = max(5, min(args.max_steps, args.env_steps // batch))
            if mode == "dynamic":
                steps = max(5, steps // 2)
            for auto in (False,) if args.no_auto_reset else (False, True):
                for devices in (d for d in counts if batch % d == 0):
                    row = bench_jax(mode, batch, steps, auto, args.overrides, devices)
                    rows.append(row)
                    print(f"{mode:10s} {'auto' if auto else 'none':>6s} {batch:6d} {devices:4d} {steps:6d} "
                          f"{row['compile_s']:10.1f} {row['env_steps_per_s']:12.0f} {row['cpu_us_per_env_step']:8.1f} us cpu"
                          f"  load {row['load_1min']}", flush=True)
    if args.pybullet:
        for mode in modes:
            row = bench_pybullet(mode, 2000 if mode == "kinematic" else 500)
            if row:
                rows.append(row)
                print(f"{mode:10s} {'pyb':>6s} {1:6d} {1:4d} {row['steps']:6d} {'-':>10s} {row['env_steps_per_s']:12.0f}")
    result = {
        "machine": {"platform": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count(),
                    "jax_backend": jax.default_backend(), "devices": [str(d) for d in jax.devices()]},
        "versions": {"jax": jax.__version__, "sagrasp_jax": sagrasp_jax.__version__},
        "rows": rows,
    }
    atomic_write_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
