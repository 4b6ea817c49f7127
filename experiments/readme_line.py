"""The README's training command, exactly as written, from a fresh clone with a cold compilation cache; and
where the training command's start-up and the evaluation command's seconds go.

    python -m experiments.readme_line line --out experiments/results/readme_line.json
    python -m experiments.readme_line startup --out experiments/results/readme_startup.json
    python -m experiments.readme_line eval-slots --run runs/quick --out experiments/results/eval_slots.json

* ``line``: ``git clone`` of this checkout's HEAD into a temporary folder, then its README's training line
  (``readme_line``; ``--python`` says which interpreter its ``python3`` is) run there by ``bash -c`` (venv, ``pip install --no-compile -e ".[train]"``, training, the 1,000-episode `robot`
  evaluation), with ``JAX_COMPILATION_CACHE_DIR`` on an empty folder and ``PYTHONPATH`` / ``VIRTUAL_ENV``
  unset; timed launch to exit.  Its parts come from the clone's files (the venv's, the run folder's) and the
  run's own log (compile, training seconds); the policy's success from the evaluation file.  pip's cache is
  the user's (warm on a machine that installed before; say so when it is not).
* ``startup``: the README preset's ``Trainer`` built and compiled in this process on an empty compilation
  cache (``--repeats`` fresh processes), then ``--cycles`` cycles: build and compile seconds (wall and process
  CPU), the compile's parts, the jax / jaxlib / mujoco versions and XLA flags, and a digest of the parameters
  after them (equal digests: the same program and numbers).  Run it with another interpreter's python (its
  venv holding another jax) to compare jax versions on one machine: ``docs/results.md`` §19.
* ``eval-slots``: the evaluation command's program on ``--run``'s policy (``--condition``, 1,000 episodes) at
  several episode-slot counts: compile and run seconds, and how far each one's per-episode results are from
  all episodes at once.

Every mode prints a table and writes the JSON with the machine's load average beside the numbers.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.metadata
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from typing import Any

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def readme_line(readme: str) -> str:
    """The README's training command: the first line of a ``bash`` block that installs and trains
    (``python3 -m venv`` ... ``sagrasp_jax.train``; the README leads with the pretrained try, which trains nothing)."""
    inside = False
    for line in open(readme, encoding="utf-8"):
        if line.startswith("```"):
            inside = line.startswith("```bash") and not inside
        elif inside and line.startswith("python3 -m venv") and "sagrasp_jax.train" in line:
            return line.strip()
    raise ValueError(f"{readme}: no ```bash line that installs and trains")


def _mtime(path: str) -> float | None:
    return os.path.getmtime(path) if os.path.exists(path) else None


def measure_line(workdir: str, keep: bool, python: str | None = None) -> dict[str, Any]:
    """``python``: the interpreter the line's ``python3`` means (a folder holding a ``python3`` link to it goes
    first on PATH); default the one on PATH."""
    clone = os.path.join(workdir, "clone")
    cache = os.path.join(workdir, "jax-cache")
    head = subprocess.run(["git", "-C", ROOT, "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    subprocess.run(["git", "clone", "-q", ROOT, clone], check=True)
    line = readme_line(os.path.join(clone, "README.md"))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["JAX_COMPILATION_CACHE_DIR"] = cache
    if python is not None:
        shim = os.path.join(workdir, "python-shim")
        os.makedirs(shim, exist_ok=True)
        os.symlink(os.path.abspath(python), os.path.join(shim, "python3"))
        env["PATH"] = shim + os.pathsep + env.get("PATH", "")
    interpreter = subprocess.run(["bash", "-c", "python3 -c 'import platform; print(platform.python_version())'"],
                                 env=env, capture_output=True, text=True, check=True).stdout.strip()
    load_before = os.getloadavg()
    start = time.time()
    done = subprocess.run(["bash", "-c", line], cwd=clone, env=env, capture_output=True, text=True)
    end = time.time()
    log = done.stdout + done.stderr
    if done.returncode:
        raise SystemExit(f"the README line failed (exit {done.returncode}):\n{log[-3000:]}")
    run = os.path.join(clone, "runs", "quick")
    rows = [json.loads(r) for r in open(os.path.join(run, "metrics.jsonl"))]
    first98 = next((r for r in rows if r.get("eval_success", 0.0) >= 0.98), None)
    (evaluation,) = [f for f in os.listdir(run) if f.startswith("evaluation-") and f.endswith(".json")]
    result = json.load(open(os.path.join(run, evaluation)))
    # pip writes each distribution's RECORD last, the editable's .pth among the first: the install ends at
    # the latest RECORD (the .pth's time, used before, came ≈ 10 s before pip's end)
    records = [os.path.join(root, "RECORD") for root, _, files in os.walk(os.path.join(clone, ".venv", "lib"))
               if root.endswith(".dist-info") and "RECORD" in files]
    rel = lambda t: None if t is None else t - start  # noqa: E731
    config_at, policy_at = rel(_mtime(os.path.join(run, "config.json"))), rel(_mtime(os.path.join(run, "policy.npz")))
    compile_s, training_s = rows[-1]["compile_s"], rows[-1]["time_s"]
    out = {
        "commit": head, "line": line, "python": interpreter, "total_s": end - start, "load_before": load_before, "load_after": os.getloadavg(),
        "venv_at_s": rel(_mtime(os.path.join(clone, ".venv", "pyvenv.cfg"))),
        "package_installed_at_s": rel(max(_mtime(r) or 0.0 for r in records)) if records else None,
        "trainer_built_at_s": config_at,  # config.json is written once the trainer is built
        "compile_s": compile_s, "compile_iteration_s": rows[-1]["compile_iteration_s"],
        "compile_eval_s": rows[-1]["compile_eval_s"],
        "training_s": training_s, "training_end_at_s": policy_at,
        "evaluation_s": end - start - policy_at if policy_at is not None else None,
        "first_98_env_steps": first98["env_steps"] if first98 else None,
        "first_98_from_launch_s": (config_at + compile_s + first98["time_s"]) if first98 and config_at else None,
        "first_98_note": "from the line's launch; the training command's own launch is the install earlier",
        "robot_success": result["overall"]["success_rate"],
        "robot_obstacle_success": result["obstacle_present"]["success_rate"],
        "steps_per_success": result["overall"].get("steps_to_success"),
    }
    if not keep:
        shutil.rmtree(workdir, ignore_errors=True)
    return out


def measure_startup(repeats: int, cycles: int) -> list[dict[str, Any]]:
    rows = []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as tmp:
            env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=os.path.join(tmp, "cache"))
            code = f"import experiments.readme_line as m, json; print(json.dumps(m._startup_once({tmp!r}, {cycles})))"
            done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True)
            if done.returncode:
                raise SystemExit(done.stderr[-3000:])
            rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    return rows


def _startup_once(tmp: str, cycles: int) -> dict[str, Any]:
    """One process: import, build the README preset's trainer, compile, run ``cycles`` cycles."""
    t0, c0 = time.perf_counter(), time.process_time()
    from sagrasp_jax import train  # first: it sets XLA_FLAGS before jax starts

    import jax
    import numpy as np

    from sagrasp_jax.task.config import get_config

    cfg = get_config("cpu-quick")
    train.use_cpu_devices(cfg)
    t1, c1 = time.perf_counter(), time.process_time()
    tr = train.Trainer(cfg, os.path.join(tmp, "run"), progress=False)
    t2, c2 = time.perf_counter(), time.process_time()
    parts = tr.compile()
    t3, c3 = time.perf_counter(), time.process_time()
    for _ in range(cycles):
        tr.run_iterations(tr.schedule.iterations_per_cycle)
    jax.block_until_ready(tr.train_state.params)
    t4, c4 = time.perf_counter(), time.process_time()
    leaves = jax.tree_util.tree_leaves(jax.device_get(tr.train_state.params))
    digest = hashlib.sha256(b"".join(np.asarray(x).tobytes() for x in leaves)).hexdigest()[:16]
    return {"imports_s": t1 - t0, "trainer_build_s": t2 - t1, "compile_s": t3 - t2, "compile_parts": parts,
            "cycles": cycles, "cycles_s": t4 - t3, "params_digest": digest, "devices": tr.mesh.size,
            # process CPU seconds of each part (all threads): under a loaded machine they move far less than the wall
            "cpu_s": {"imports": c1 - c0, "build": c2 - c1, "compile": c3 - c2, "cycles": c4 - c3},
            "versions": {"python": platform.python_version(), "jax": jax.__version__,
                         "jaxlib": importlib.metadata.version("jaxlib"), "mujoco": importlib.metadata.version("mujoco")},
            "xla_flags": os.environ.get("XLA_FLAGS", ""), "load": os.getloadavg()}


def measure_eval_slots(run: str, condition: str, episodes: int, slot_counts: list[int | None]) -> list[dict[str, Any]]:
    import jax
    import numpy as np

    from sagrasp_jax import evaluate as ev
    from sagrasp_jax.task.config import EVAL_CONDITIONS
    from sagrasp_jax.training import actor_critic, restore, run_dir
    from sagrasp_jax.training import fixed_seed_eval as policy_eval

    cfg = run_dir.load_config(run)
    ckpt = run_dir.load_checkpoint(run, cfg)
    env = ev.default_eval_env(ev.scene_config(ev.env_overrides(cfg, list(EVAL_CONDITIONS[condition])), "mix"))
    params, normaliser = restore.restore_policy(cfg, ckpt, env.observation_size, env.action_size)
    networks = actor_critic.make_networks(cfg.ppo.network, env.observation_size, env.action_size, cfg.ppo.obs_clip)
    seed, steps = ev.resolve_options(cfg, None, None)
    keys = policy_eval.eval_keys(seed, episodes)
    rows, reference = [], None
    for slots in slot_counts:
        t = time.perf_counter()
        compiled = policy_eval.make_evaluator(networks, env, steps, slots=slots).lower(params, normaliser, keys).compile()
        compile_s = time.perf_counter() - t
        runs = []
        for _ in range(3):
            t = time.perf_counter()
            result = jax.device_get(compiled(params, normaliser, keys))
            runs.append(time.perf_counter() - t)
        eps = {k: np.asarray(v, np.float64) for k, v in result.episodes.items()}
        if reference is None:
            reference = eps
        flags = ("success", "collision", "timeout", "steps", "finished")
        rows.append({"slots": slots, "compile_s": compile_s, "run_s": min(runs), "success": float(result.success_rate),
                     "flags_equal_to_first": all(np.array_equal(eps[k], reference[k]) for k in flags if k in eps),
                     "max_abs_diff_to_first": max(float(np.max(np.abs(eps[k] - reference[k]))) for k in reference),
                     "load": os.getloadavg()})
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="mode", required=True)
    a = sub.add_parser("line", help="the README's training command from a fresh clone, cold cache")
    a.add_argument("--workdir", default=None, help="where the clone goes (default: a new temporary folder)")
    a.add_argument("--keep", action="store_true", help="keep the clone and its run")
    a.add_argument("--python", default=None, help="the interpreter the line's python3 is (default: python3 on PATH)")
    b = sub.add_parser("startup", help="the README trainer's build and compile, cold cache, in fresh processes")
    b.add_argument("--repeats", type=int, default=2)
    b.add_argument("--cycles", type=int, default=20)
    c = sub.add_parser("eval-slots", help="the evaluation command's program at several episode-slot counts")
    c.add_argument("--run", required=True)
    c.add_argument("--condition", default="robot")
    c.add_argument("--episodes", type=int, default=1000)
    c.add_argument("--slots", default="all,32,64,128", help="comma-separated counts; all: every episode at once")
    for q in (a, b, c):
        q.add_argument("--out", required=True)
    args = p.parse_args(argv)
    if args.mode == "line":
        workdir = args.workdir or tempfile.mkdtemp(prefix="readme_line_")
        data: Any = measure_line(workdir, args.keep, args.python)
        for key in ("python", "total_s", "venv_at_s", "package_installed_at_s", "trainer_built_at_s", "compile_s",
                    "training_s", "training_end_at_s", "evaluation_s", "first_98_env_steps", "first_98_from_launch_s",
                    "robot_success", "robot_obstacle_success"):
            value = data[key]
            print(f"{key:26s} {value:.3f}" if isinstance(value, float) else f"{key:26s} {value}")
    elif args.mode == "startup":
        data = measure_startup(args.repeats, args.cycles)
        print(f"{'imports':>8s} {'build':>7s} {'compile':>8s} {'(call':>7s} {'eval)':>6s} {'cycles s':>9s}  digest")
        for r in data:
            c_ = r["compile_parts"]
            print(f"{r['imports_s']:8.2f} {r['trainer_build_s']:7.2f} {r['compile_s']:8.2f} {c_['iteration']:7.2f} "
                  f"{c_['eval']:6.2f} {r['cycles_s']:9.2f}  {r['params_digest']}")
    else:
        counts = [None if s == "all" else int(s) for s in args.slots.split(",")]
        data = measure_eval_slots(args.run, args.condition, args.episodes, counts)
        print(f"{'slots':>6s} {'compile s':>10s} {'run s':>7s} {'success':>8s}  same flags  max |diff|")
        for r in data:
            print(f"{str(r['slots'] or 'all'):>6s} {r['compile_s']:10.2f} {r['run_s']:7.2f} {r['success']:8.4f}  "
                  f"{str(r['flags_equal_to_first']):10s}  {r['max_abs_diff_to_first']:.2e}")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump({"mode": args.mode, "argv": sys.argv[1:], "results": data}, f, indent=2)
    print(f"written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
