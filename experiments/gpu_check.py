"""GPU check: what one lent GPU has to tell this project, in one run of at most ~8 minutes.

Sections, in this order; each becomes one row of the table and one entry of the JSON, and a
section that fails is recorded as an error row (its message kept) while the others still run:

1. ``dynamic``: env-steps/s of the dynamic mode (MJX servo physics, bare ``jax.vmap(env.step)``
   in a jitted scan, ``experiments.bench_env.bench_jax``) with ``env.control.impl=jax`` and
   ``env.control.impl=warp`` (MuJoCo Warp through MJX), and their equality: the same envs from the
   same keys under the same actions, joint positions equal within ``EQUAL_ATOL`` (the tolerance of
   ``tests/envs/test_dynamic.py``).  Without the ``warp`` package the warp rows say "not installed".
2. ``train``: the ``gpu`` preset for its 20M env steps (the whole check's budget assumes an H200), in process (``train.run``): compile time,
   env-steps/s (median iteration and overall, SA evaluations included), wall time, success on
   1,000 held-out episodes (``evaluation.evaluate_run``) and peak device memory
   (``jax.Device.memory_stats()["peak_bytes_in_use"]``; CPUs report none).
3. ``seeds``: a 5-seed group of the README preset as one program,
   ``python -m sagrasp_jax.train --preset cpu-quick --seeds 0-4 --out DIR``, in a subprocess that is
   stopped (SIGTERM: it checkpoints) when the check's time budget (``--budget-s``) is spent: wall
   time, env steps and env-steps/s of the group, the seeds' folders.  A trainer without
   ``--seeds`` is an error row.

``--quick`` shrinks every section to CPU-smoke size: the dynamic rate at batch 16, the training of
``tests/tiny_run.py`` (``cpu-quick``, 64 envs, 1,024 steps: jax's persistent compilation cache from
the tests that train it serves it) evaluated on 8 episodes, a group of 2 such seeds, a budget of
60 s; it is run by ``tests/test_gpu_check.py`` in the normal suite.

    python -m experiments.gpu_check --out experiments/results/gpu_check_h200.json
    python -m experiments.gpu_check --quick --out /tmp/gpu_check_quick.json

No environment variable is needed anywhere: importing ``sagrasp_jax`` adds its CPU XLA flag only where jax
runs on the CPU, in the form the installed jaxlib knows (``sagrasp_jax/base/xla_flags.py``; a GPU machine's
CUDA plugin keeps it off).

**On a bare GPU machine** (the lent H200: Python 3.12 with jax 0.11 and its CUDA plugin, flax, optax,
numpy, absl-py, etils, scipy, pillow, tqdm, protobuf, but nothing else of the project's) the
checkout travels with the command and ``python3 -m`` from its root imports ``sagrasp_jax`` and
``experiments`` from it (a wheel of the project, ``pip wheel --no-deps -w .whl .``, is needed only
where the checkout is not).  Carry the third-party wheels it imports that the machine lacks and install
them offline without dependency resolution (pip would otherwise try to replace the machine's jax).
Here, from the repository root (``.whl/`` kept out of git by ``.git/info/exclude``):

    echo /.whl/ >> .git/info/exclude
    python -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d .whl \
        mujoco==3.17.0 mujoco-mjx==3.17.0 brax==0.14.2 jaxopt==0.8.5 trimesh==5.2.0 glfw==2.11.0 \
        tensorboardX==2.6.5 warp-lang==1.18.0

(the distributions that ``sagrasp_jax.train``, ``evaluate`` and ``env`` import, less what the machine
has).  Sizes: mujoco 26.7 MB, mujoco-mjx 7.3 MB, the others under 1 MB each, 36 MB in all, under the
64 MiB that one device call carries; warp-lang is 149 MB, over it, so leave it out (delete it from
``.whl``) and the warp rows say "not installed", unless it reaches the machine another way.  Then on
the GPU machine, with ``.whl`` carried:

    python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl
    export PYTHONPATH=/tmp/site
    python3 -m experiments.gpu_check --out $OUT/gpu_check.json
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS and the compile cache before jax is imported)

import argparse
import importlib.util
import os
import platform
import sys
import time
import traceback
from typing import Any, Callable, Sequence

import jax
import numpy as np

from experiments import bench_env, study
from experiments.study import watch_trainer
from sagrasp_jax import train
from sagrasp_jax.training import evaluation
from sagrasp_jax.task import config
from sagrasp_jax.task import config_parse
from sagrasp_jax.training import run_dir
from sagrasp_jax.envs.grasp_env import GraspEnv

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EQUAL_ATOL = 1e-5  # |Δ joint position| (rad) between the jax and warp backends, as tests/envs/test_dynamic.py
# --quick trains tests/tiny_run.py's run (cpu-quick, 1,024 steps, these overrides), so that jax's persistent
# compilation cache, filled by the tests that train it, serves the smoke test too
TINY = ("eval.num_cycles=1", "eval.episodes=8", "ppo.num_envs=64", "ppo.num_epochs=1", "ppo.num_minibatches=1",
        "ppo.network.policy_hidden=32,32,32,32", "env.task.max_steps=50")
# (full, --quick) sizes of every section
SIZES: dict[str, tuple[Any, Any]] = {
    "train_preset": ("gpu", "cpu-quick"), "train_sets": ((), TINY), "train_steps": (None, 1024),
    "eval_episodes": (1000, 8), "dynamic_batch": (4096, 16), "dynamic_steps": (100, 10), "equal_envs": (8, 4),
    "equal_steps": (4, 4), "seeds": ("0-4", "0-1"), "seeds_sets": ((), TINY), "seeds_steps": (None, 1024),
    "budget_s": (480.0, 60.0),
}


def size(name: str, quick: bool) -> Any:
    return SIZES[name][1 if quick else 0]


def warp_installed() -> bool:
    """MuJoCo Warp is usable through MJX (the ``warp`` package imports)."""
    if importlib.util.find_spec("warp") is None:
        return False
    try:
        from mujoco.mjx import warp as mjx_warp
    except ImportError:
        return False
    return bool(getattr(mjx_warp, "WARP_INSTALLED", False))


def section(name: str, fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """Run one section; its failure becomes an error row instead of ending the check."""
    print(f"[{name}] ...", flush=True)
    t = time.perf_counter()
    try:
        row = {"status": "ok", **fn()}
    except Exception as exc:  # noqa: BLE001 - any failure is a recorded result of the check
        row = {"status": "error", "error": f"{type(exc).__name__}: {exc}",
               "traceback": traceback.format_exc(limit=6).splitlines()[-12:]}
    row["section_s"] = time.perf_counter() - t
    print(f"[{name}] {row['status']} in {row['section_s']:.0f} s" + (f": {row['error']}" if "error" in row else ""),
          flush=True)
    return row


# ---------------------------------------------------------------------- dynamic mode, jax vs warp

def joint_rollout(impl: str, envs: int, steps: int) -> np.ndarray:
    """Joint positions [step, env, joint] of ``envs`` dynamic-mode envs (paper preset, no noise, no
    obstacle) from fixed keys under fixed random actions, physics ``impl``."""
    cfg = config_parse.apply_overrides(config.get_config("paper"), [
        "env.control.mode=dynamic", f"env.control.impl={impl}", "env.task.obs_noise_std=0",
        "env.sampling.obstacle_prob=0"])
    env = GraspEnv(cfg.env)
    actions = jax.random.uniform(jax.random.PRNGKey(3), (steps, envs, 6), minval=-1.0, maxval=1.0)

    def run(keys: jax.Array) -> jax.Array:
        def body(st: Any, action: jax.Array) -> tuple[Any, jax.Array]:
            st = jax.vmap(env.step)(st, action)
            return st, st.pipeline_state.qpos[:, :6]

        return jax.lax.scan(body, jax.vmap(env.reset)(keys), actions)[1]

    return np.asarray(jax.device_get(jax.jit(run)(jax.random.split(jax.random.PRNGKey(7), envs))))


def dynamic_section(quick: bool) -> dict[str, Any]:
    batch, steps = size("dynamic_batch", quick), size("dynamic_steps", quick)
    envs, equal_steps = size("equal_envs", quick), size("equal_steps", quick)
    out: dict[str, Any] = {"batch": batch, "steps": steps}
    out["jax"] = bench_env.bench_jax("dynamic", batch, steps, auto_reset=False, overrides=["env.control.impl=jax"])
    if not warp_installed():
        out["warp"] = "not installed"
        out["equal"] = "not installed"
        return out
    out["warp"] = section("dynamic impl=warp", lambda: bench_env.bench_jax(
        "dynamic", batch, steps, auto_reset=False, overrides=["env.control.impl=warp"]))
    out["equal"] = section("jax == warp", lambda: backends_equal(envs, equal_steps))
    if out["warp"]["status"] == "ok":
        out["warp_over_jax"] = out["warp"]["env_steps_per_s"] / out["jax"]["env_steps_per_s"]
    return out


def backends_equal(envs: int, steps: int) -> dict[str, Any]:
    """The warp and jax backends' joint positions over the same rollout, within EQUAL_ATOL."""
    diff = float(np.max(np.abs(joint_rollout("warp", envs, steps) - joint_rollout("jax", envs, steps))))
    return {"envs": envs, "steps": steps, "max_abs_joint_diff": diff, "atol": EQUAL_ATOL, "passed": diff <= EQUAL_ATOL}


# ---------------------------------------------------------------------- the gpu preset

def peak_device_memory() -> int | None:
    """Peak bytes in use on the first device since the process started (None: not reported)."""
    stats = jax.devices()[0].memory_stats()
    return None if not stats else stats.get("peak_bytes_in_use")


def train_section(quick: bool, work: str) -> dict[str, Any]:
    preset = size("train_preset", quick)
    cfg = train.build_config(preset, None, 0, size("train_steps", quick), list(size("train_sets", quick)))
    out = os.path.join(work, "gpu")
    t = time.perf_counter()
    train.run(cfg, out, progress=False)
    wall = time.perf_counter() - t
    rows = run_dir.read_metrics(os.path.join(out, run_dir.METRICS_FILE))
    last = rows[-1]
    rates = sorted(r["steps_per_s"] for r in rows if r.get("steps_per_s"))
    res = evaluation.evaluate_run(out, size("eval_episodes", quick))
    return {
        "preset": preset, "overrides": list(size("train_sets", quick)), "total_steps": cfg.train.total_steps,
        "num_envs": cfg.ppo.num_envs, "env_steps": last["env_steps"], "wall_s": wall, "train_s": last["time_s"],
        "compile_s": last.get("compile_s"), "median_iteration_env_steps_per_s": rates[len(rates) // 2] if rates else None,
        "overall_env_steps_per_s": last["env_steps"] / last["time_s"], "last_eval_success": next(
            (r["eval_success"] for r in reversed(rows) if r.get("eval_success") is not None), None),
        "eval_episodes": res["episodes"], "success_rate": res["overall"]["success_rate"],
        "obstacle_success_rate": res["obstacle_present"].get("success_rate"),
        "mean_steps_per_success": res["overall"]["mean_steps_per_success"], "eval_wall_s": res["wall_s"],
        "peak_device_memory_bytes": peak_device_memory(),
    }


# ---------------------------------------------------------------------- a seed group of the README preset

def seeds_section(quick: bool, work: str, deadline: float) -> dict[str, Any]:
    seeds = study.parse_seeds(size("seeds", quick))
    out = os.path.join(work, "seeds")
    args = ["--preset", "cpu-quick", "--seeds", size("seeds", quick), "--out", out, "--no-progress"]
    if size("seeds_steps", quick):
        args += ["--total-steps", str(size("seeds_steps", quick))]
    args += [a for item in size("seeds_sets", quick) for a in ("--set", item)]
    cmd = [sys.executable, "-m", "sagrasp_jax.train", *args]
    first = os.path.join(out, study.SEED_FOLDER.format(seed=seeds[0]), run_dir.METRICS_FILE)
    budget = deadline - time.perf_counter()
    if budget <= 0:
        raise TimeoutError("no time left in --budget-s for the seed group")
    stop = lambda rows, since: f"budget of {budget:.0f} s" if since > budget else None  # noqa: E731
    log = os.path.join(work, "seeds.log")
    rows, stopped, code, wall = watch_trainer(cmd, ROOT, log, first, 1.0, stop)
    if stopped is None and code != 0:
        with open(log, encoding="utf-8") as f:
            tail = f.read().strip().splitlines()[-3:]
        raise RuntimeError(f"`python -m sagrasp_jax.train {' '.join(args)}` exited {code}: {' | '.join(tail)}")
    per_seed = {}
    for seed in seeds:
        folder = os.path.join(out, study.SEED_FOLDER.format(seed=seed))
        file = os.path.join(folder, run_dir.METRICS_FILE)
        metrics = run_dir.read_metrics(file) if os.path.exists(file) else []
        per_seed[str(seed)] = {"env_steps": metrics[-1]["env_steps"] if metrics else 0,
                               "policy": os.path.isfile(os.path.join(folder, run_dir.POLICY_FILE)),
                               "last_eval_success": next((r["eval_success"] for r in reversed(metrics)
                                                          if r.get("eval_success") is not None), None)}
    steps = sum(s["env_steps"] for s in per_seed.values())
    return {"command": "python -m sagrasp_jax.train " + " ".join(args), "stopped_by": stopped or "finished",
            "wall_s": wall, "env_steps_all_seeds": steps, "env_steps_per_s_all_seeds": steps / wall,
            "train_s_seed0": rows[-1]["time_s"] if rows else None, "per_seed": per_seed}


# ---------------------------------------------------------------------- report

def _num(value: Any, spec: str = ",.0f") -> str:
    return "-" if value is None else format(value, spec)


def table(result: dict[str, Any]) -> str:
    s = result["sections"]
    lines = [f"gpu_check{' --quick' if result['quick'] else ''} on {result['device']} ({result['backend']}), "
             f"{result['wall_s']:.0f} s", ""]
    d = s["dynamic"]
    if d["status"] == "ok":
        for impl in ("jax", "warp"):
            row = d[impl]
            lines.append(f"dynamic impl={impl:<5} " + (row if isinstance(row, str) else f"ERROR {row['error']}"
                         if row.get("status") == "error" else f"{_num(row['env_steps_per_s'])} env-steps/s "
                         f"(batch {d['batch']}, compile {row['compile_s']:.1f} s)"))
        eq = d["equal"]
        lines.append("jax == warp            " + (eq if isinstance(eq, str) else f"ERROR {eq['error']}"
                     if eq["status"] == "error" else f"{'passed' if eq['passed'] else 'FAILED'}: max |dq| "
                     f"{eq['max_abs_joint_diff']:.2e} (atol {eq['atol']:g})"))
    t = s["train"]
    if t["status"] == "ok":
        mem = t["peak_device_memory_bytes"]
        lines += [f"{t['preset']} preset, {t['env_steps']:,} steps  compile {t['compile_s']:.1f} s, "
                  f"{_num(t['median_iteration_env_steps_per_s'])} env-steps/s per iteration, "
                  f"{_num(t['overall_env_steps_per_s'])} overall, wall {t['wall_s']:.0f} s",
                  f"                       success {100 * t['success_rate']:.1f} % on {t['eval_episodes']} episodes, "
                  f"peak device memory {'not reported' if mem is None else f'{mem / 2**30:.2f} GiB'}"]
    g = s["seeds"]
    if g["status"] == "ok":
        lines.append(f"seed group ({len(g['per_seed'])} seeds)  {g['stopped_by']}, wall {g['wall_s']:.0f} s, "
                     f"{g['env_steps_all_seeds']:,} env steps, {_num(g['env_steps_per_s_all_seeds'])} env-steps/s")
    for name, row in s.items():
        if row["status"] != "ok":
            lines.append(f"{name:<22} ERROR {row['error']}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.gpu_check", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="every section at CPU-smoke size (about a minute)")
    p.add_argument("--budget-s", type=float, default=None,
                   help="the seed group is stopped when the check has run this long (default 480, with --quick 60)")
    p.add_argument("--work", default=None, help="folder for the runs (default a new folder under /tmp, kept)")
    p.add_argument("--out", default="gpu_check.json", help="result JSON")
    args = p.parse_args(argv)
    if args.budget_s is None:
        args.budget_s = size("budget_s", args.quick)
    if args.budget_s <= 0:
        p.error("--budget-s must be > 0")
    t0 = time.perf_counter()
    work = args.work or os.path.join("/tmp", f"gpu_check.{os.getpid()}")
    os.makedirs(work, exist_ok=True)
    train.use_cpu_devices(train.build_config("cpu-quick"))  # on a CPU: one device per core, as the trainer
    result: dict[str, Any] = {
        "quick": args.quick, "device": str(jax.devices()[0]), "backend": jax.default_backend(),
        "device_count": len(jax.devices()), "machine": f"{platform.node()} {study.machine()}",
        "versions": {"python": sys.version.split()[0], "jax": jax.__version__, "sagrasp_jax": sagrasp_jax.__version__,
                     "warp": "installed" if warp_installed() else "not installed"},
        "command": study.command("gpu_check", argv), "git": study.git_state(), "work": work, "sections": {},
    }
    result["sections"]["dynamic"] = section("dynamic", lambda: dynamic_section(args.quick))
    result["sections"]["train"] = section("train", lambda: train_section(args.quick, work))
    result["sections"]["seeds"] = section("seeds", lambda: seeds_section(args.quick, work, t0 + args.budget_s))
    result["wall_s"] = time.perf_counter() - t0
    text = table(result)
    result["table"] = text.splitlines()
    study.write_json(args.out, result)
    print("\n" + text + f"\n\nwritten to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
