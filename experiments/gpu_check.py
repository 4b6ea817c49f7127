"""GPU check v2: what one lent GPU has to tell this project, in one command of at most 9 minutes.

Sections, in this order; each becomes one row of the table and one entry of the JSON.  A section that fails
is an error row (its message kept) and the others still run; one that the budget leaves no time for is a
``skipped`` row that says so.  The parent process never starts a jax backend (on a GPU jax would take 75 %
of its memory from the commands it runs): the device's name comes from a short child (``device``), every
section runs in fresh processes of its own.

1. ``dynamic``: env-steps/s of the dynamic mode (MJX servo physics, bare ``jax.vmap(env.step)`` in a
   jitted scan, ``experiments.bench_env.bench_jax``) with ``env.control.impl=jax`` and ``=warp`` (MuJoCo
   Warp through MJX), and their equality: the same envs from the same keys under the same actions, joint
   positions equal within ``EQUAL_ATOL`` (the tolerance of ``tests/envs/test_dynamic.py``).  Without the
   ``warp`` package the warp rows say "not installed".
2. ``cold``: ``python -m sagrasp_jax.train --preset gpu --seed 0 --out W/cold`` in a fresh process on an
   EMPTY compilation cache folder (``JAX_COMPILATION_CACHE_DIR``), under ``readme_line``'s
   ``CompileRecorder`` (``readme_line.record_command``): the **compile breakdown** (per program: its name and
   where the package called it, jax's trace / lower seconds, the XLA compile's seconds, the persistent
   cache's answer, StableHLO ops and optimised HLO instructions; totals) and the run: launch → exit wall,
   the trainer's compile seconds, training seconds, env-steps/s (median iteration and overall), peak
   device memory and the **time from launch to the first fixed-seed evaluation ≥ 99 %** (and ≥ 98 %).
   The launch-relative clock: the check reads the run's ``metrics.jsonl`` every ``POLL_S`` seconds
   (``study.watch_trainer``) and stamps each row with the seconds since the launch at which it was first
   seen, so a level's time is when the row saying so existed (late by at most ``POLL_S``; rows written
   between the last poll and the exit get the exit's time).
3. ``warm``: the same command again on the cache ``cold`` filled: the same breakdown (its programs cache
   hits), launch → exit and launch → 99 %.
4. ``envs16k``: the same with ``--set ppo.num_envs=16384`` on its own empty cache folder (a cold number,
   comparable to ``cold``).
5. ``physics``: ``--preset gpu-physics`` (the ``gpu`` preset in the dynamic mode) recorded as ``cold`` on its
   own empty cache, then ``python -m sagrasp_jax.evaluate --run RUN --episodes 1000 --condition robot``
   (and ``--condition robot-latency2`` when the time left holds another evaluation as long): success
   overall / with an obstacle / blocking (episodes and successes as evaluate reports them), steps per
   success.  Training is stopped ``EVAL_RESERVE_S`` before the section's end so that evaluation has time.
6. ``paper``: ``python -m experiments.reproduce_paper --preset paper --seeds 5 --out-dir W/paper
   --runs-dir W/paper/runs --no-progress`` (the paper's PPO vs SA-PPO, 20M env steps per run, each
   algorithm's seeds one seed group) on its own empty cache, stopped (SIGTERM, killed ``GRACE_S`` later)
   when the budget is spent: finished or stopped (said plainly), env steps reached per algorithm and seed
   (the runs' ``metrics.jsonl``) and, finished, its table (``results.json``: each algorithm's pooled
   success with its Wilson 95 % interval, steps per success, the paired seed-by-seed comparison, and
   ``results.md``).  At 16 envs per seed it cannot finish in this budget on one GPU: the row says how far
   it got; ``--sections paper --budget-s 540`` gives it a command of its own.

**Policies come back.**  Every trained run's small files, a stopped or failed section's too (``policy.npz``,
``config.json``, ``metrics.jsonl``, evaluation JSONs; not checkpoints, nothing over ``MAX_COPY_BYTES``), are
copied to ``--policies`` (default ``policies/`` beside ``--out``): ``policies/<section>/`` and
``policies/paper/<algo>/seed<S>/`` (the study's ``results.json`` / ``.md`` in ``policies/paper/``), folders that
``python -m sagrasp_jax.deploy.rehearse --policy FOLDER`` (and ``evaluate --backend twin --policy``) take as
they are (a folder means its ``policy.npz``).  A run stopped before its end has a checkpoint but no
``policy.npz`` yet: its folder holds the rest.

**Budget** (``--budget-s``, default 540 s): every section sees what is left of it less what the sections after
it need at least (``MIN_S``); a training is SIGTERMed at its section's end (killed ``GRACE_S`` later), and a
section with less than its minimum left is skipped with the reason.  The JSON (``"complete": false`` until the
end) and the policies are written after every section, so a check killed from outside still leaves them.
Estimated from v1's H200 numbers (the ``gpu`` preset 27.4 s training + 26.2 s compile, 99.0 %; at 16,384 envs
10.3 s + 27.3 s; the dynamic mode 60.0 s + 28.1 s), each with ≈ 10 s of process start and imports: device 5 s,
dynamic 30 s, cold 65 s, warm 45 s (its compiles cache loads), envs16k 50 s, physics 100 s of training + 2 × 30 s
of evaluation, and the paper what is left (≈ 185 s, stopped).  The whole check ends within the budget plus
``GRACE_S``.

``--quick`` runs every section at CPU-smoke size (``tests/test_gpu_check.py`` in the normal suite): the
dynamic rate at batch 16; cold, warm and the second env count with ``tests/tiny_run.py``'s training
(``TINY``: ``cpu-quick``, 64 envs, 1,024 steps) at 64 and 32 envs on the user's shared compilation cache
(``"cache": "shared"`` in the JSON: not a cold number) so that the suite's other tests serve its compiles;
``cpu-physics`` + ``TINY`` evaluated in ``robot`` on 8 episodes; the paper study as
``tests/test_experiments.py``'s smoke (``cpu-quick``, 2 seeds, 8,192 steps, 16 evaluation episodes).

    python -m experiments.gpu_check --out experiments/results/gpu_check_h200.json
    python -m experiments.gpu_check --quick --out /tmp/gpu_check_quick.json
    python -m experiments.gpu_check --sections paper --budget-s 540 --out $OUT/gpu_check_paper.json

No environment variable is needed anywhere: importing ``sagrasp_jax`` adds its CPU XLA flag only where jax
runs on the CPU, in the form the installed jaxlib knows (``sagrasp_jax/base/xla_flags.py``; a GPU machine's
CUDA plugin keeps it off).

**On a bare GPU machine** (the lent H200's documented image: Python 3.12.3, jax and jaxlib 0.11.2 with
the CUDA plugin, numpy 2.5.2, flax, optax, chex, absl-py, etils, scipy, pillow, tqdm, protobuf, matplotlib
and its dependencies, tensorboard, orbax-checkpoint and a few more; no mujoco, mujoco-mjx, brax, jaxopt,
trimesh, glfw or tensorboardX, and no network) the checkout travels with the command and ``python3 -m``
from its root imports ``sagrasp_jax`` and ``experiments`` from it (a wheel of the project,
``pip wheel --no-deps -w .whl .``, is needed only where the checkout is not).  Carry the third-party wheels
it imports that the machine lacks and install them offline without dependency resolution (pip would otherwise
try to replace the machine's jax).
Here, from the repository root (``.gitignore`` keeps ``.whl/`` out of git already: a device call takes it
only where named in its carry):

    python -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \\
        --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \\
        --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d .whl \\
        mujoco==3.17.0 mujoco-mjx==3.17.0 brax==0.14.2 jaxopt==0.8.5 trimesh==5.2.0 glfw==2.11.0 \\
        tensorboardX==2.6.5 warp-lang==1.18.0

(the distributions that ``sagrasp_jax.train``, ``evaluate`` and ``env`` import, less what the machine
has.  The paper section's plots take the image's own matplotlib: ``--quick --sections paper,physics`` ran
on the rehearsed image with only these wheels carried.  Carrying matplotlib and its dependencies as well
(an earlier form of this list) shadows the image's copies through ``PYTHONPATH``: packaging, six and
python-dateutil among them, which the image's other packages import too.  brax's and mujoco's declared
dependencies that the image lacks, flask, flask-cors, ml-collections, pyopengl and websockets, are imported
on none of the check's paths.)  Sizes: mujoco 26.7 MB, mujoco-mjx 7.3 MB, the others under 1 MB each,
36 MB in all, under the 64 MiB that one device call carries; warp-lang is 149 MB, over it, so leave it out
(delete it from ``.whl``) and the warp rows say "not installed", unless it reaches the machine another way.
Then on the GPU machine, with ``.whl`` carried, one command (the check's own children inherit
``PYTHONPATH``):

    python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl && \\
    PYTHONPATH=/tmp/site timeout 580 python3 -m experiments.gpu_check --out $OUT/gpu_check.json

(``--out $OUT/...`` puts the policies in ``$OUT/policies``, so they come back with the JSON.)
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS and the compile cache before jax is imported)

import argparse
import importlib.util
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from experiments import readme_line, study
from experiments.study import watch_trainer
from sagrasp_jax.task import config
from sagrasp_jax.training import run_dir

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EQUAL_ATOL = 1e-5  # |Δ joint position| (rad) between the jax and warp backends, as tests/envs/test_dynamic.py
# --quick trains tests/tiny_run.py's run (cpu-quick, 1,024 steps, its overrides), so that jax's persistent
# compilation cache, filled by the tests that train it, serves the smoke test too
TINY = ("eval.num_cycles=1", "eval.episodes=8", "ppo.num_envs=64", "ppo.num_epochs=1", "ppo.num_minibatches=1",
        "ppo.network.policy_hidden=32,32,32,32", "ppo.learning_rate=3e-4", "sa.decay=0.98", "env.task.max_steps=50")
# --quick's paper study is tests/test_experiments.py's reproduce_paper smoke (its overrides, 8,192 steps, 2 seeds)
PAPER_TINY = ("ppo.network.policy_hidden=32,32,32,32", "ppo.learning_rate=3e-4", "sa.decay=0.98", "ppo.num_envs=64",
              "ppo.num_epochs=1", "ppo.num_minibatches=1", "env.task.max_steps=50", "eval.episodes=8",
              "eval.num_cycles=4")
SECTIONS = ("dynamic", "cold", "warm", "envs16k", "physics", "paper")
TRAINING_SECTIONS = ("cold", "warm", "envs16k", "physics")  # each trains one run, into W/<section>
# (full, --quick) sizes of every section
SIZES: dict[str, tuple[Any, Any]] = {
    "dynamic_batch": (4096, 16), "dynamic_steps": (100, 10), "equal_envs": (8, 4), "equal_steps": (4, 4),
    "train_preset": ("gpu", "cpu-quick"), "physics_preset": ("gpu-physics", "cpu-physics"),
    "train_sets": ((), TINY), "train_steps": (None, 1024), "big_envs": (16384, 32),
    "eval_episodes": (1000, 8), "eval_conditions": (("robot", "robot-latency2"), ("robot",)),
    "paper_preset": ("paper", "cpu-quick"), "paper_sets": ((), PAPER_TINY), "paper_steps": (None, 8192),
    "paper_seeds": (5, 2), "paper_eval_episodes": (1000, 16),
    "budget_s": (540.0, 900.0),
}
# the least time (s) a section is worth starting with: what the sections before it leave the ones after it
MIN_S: dict[str, tuple[float, float]] = {"dynamic": (20.0, 0.0), "cold": (50.0, 0.0), "warm": (35.0, 0.0),
                                         "envs16k": (40.0, 0.0), "physics": (90.0, 0.0), "paper": (30.0, 0.0)}
EVAL_RESERVE_S = (35.0, 0.0)  # physics: its training stops this long before the section's end, for evaluation
POLL_S = 0.25  # how often a training's metrics.jsonl is read: the launch-relative clock's resolution
GRACE_S = 15.0  # a stopped training (SIGTERM) is killed if it has not exited this much later
LEVELS = (0.99, 0.98)  # the fixed-seed evaluation levels timed from the launch
MAX_COPY_BYTES = 4 * 2**20  # a file bigger than this is not copied into --policies (it must come back in $OUT)
PROGRAM_ROWS = 8  # the table shows each breakdown's programs that took longest, this many


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


# ---------------------------------------------------------------------- the budget

@dataclass(frozen=True)
class Budget:
    """The check's deadline: ``total_s`` from ``start`` (``time.perf_counter``), shared out over ``sections``."""
    start: float
    total_s: float
    sections: tuple[str, ...]
    quick: bool

    def section_end(self, name: str) -> float:
        """When ``name`` must be done: the deadline less the minimum of every section after it."""
        later = self.sections[self.sections.index(name) + 1:]
        return self.start + self.total_s - sum(MIN_S[s][self.quick] for s in later)

    def skip_reason(self, name: str, now: float) -> str | None:
        """Why ``name`` is not started at ``now`` (None: it is)."""
        left, least = self.section_end(name) - now, MIN_S[name][self.quick]
        if left > 0 and left >= least:
            return None
        return (f"skipped: {max(left, 0.0):.0f} s of --budget-s {self.total_s:.0f} left for it, it needs at least "
                f"{least:.0f} s (the sections after it keep {self.start + self.total_s - self.section_end(name):.0f} s)")


def section(name: str, fn: Callable[[], dict[str, Any]], skip: str | None = None) -> dict[str, Any]:
    """Run one section; its failure becomes an error row instead of ending the check."""
    if skip is not None:
        print(f"[{name}] {skip}", flush=True)
        return {"status": "skipped", "reason": skip, "section_s": 0.0}
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


# ---------------------------------------------------------------------- children

def child_json(call: str, timeout: float, env: dict[str, str] | None = None) -> Any:
    """``call`` (an expression on this module as ``g``) in a fresh Python from the repository root, its JSON
    result read from its output's last line; a failure raises with the output's tail."""
    code = f"import json; from experiments import gpu_check as g; print(json.dumps(g.{call}, default=float))"
    try:
        done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                              timeout=max(timeout, 1.0))
    except subprocess.TimeoutExpired:
        raise TimeoutError(f"{call} still running after {timeout:.0f} s (the section's share of --budget-s)") from None
    if done.returncode:
        raise RuntimeError(f"{call} exited {done.returncode}: {(done.stdout + done.stderr)[-1500:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def device_info() -> dict[str, Any]:
    """(In a child.) The device the commands run on, and the versions that matter."""
    import jax

    from sagrasp_jax import train

    train.use_cpu_devices(train.build_config("cpu-quick"))  # on a CPU: one device per core, as the trainer
    return {"device": str(jax.devices()[0]), "backend": jax.default_backend(), "device_count": len(jax.devices()),
            "versions": {"python": sys.version.split()[0], "jax": jax.__version__,
                         "sagrasp_jax": sagrasp_jax.__version__,
                         "warp": "installed" if warp_installed() else "not installed"}}


def child_env(cache_dir: str | None) -> dict[str, str]:
    """The environment of a command: this one's, with ``cache_dir`` as jax's compilation cache (None: the
    shared one, the folder ``sagrasp_jax`` chose)."""
    return dict(os.environ) if cache_dir is None else dict(os.environ, JAX_COMPILATION_CACHE_DIR=cache_dir)


def cache_before(cache_dir: str | None) -> tuple[str, int]:
    """The compilation cache folder a command will use (``cache_dir``, made if missing, or the shared one
    ``sagrasp_jax`` chose) and how many entries it holds before the command runs."""
    if cache_dir is not None:
        os.makedirs(cache_dir, exist_ok=True)
    path = cache_dir or os.environ["JAX_COMPILATION_CACHE_DIR"]
    return path, readme_line.cache_files(path)[0]


def log_tail(log: str, lines: int = 4) -> str:
    """A command log's last lines, joined for an error message."""
    with open(log, encoding="utf-8") as f:
        return " | ".join(f.read().strip().splitlines()[-lines:])


def cache_label(cache_dir: str | None, entries_before: int) -> str:
    """What a run's compilation cache was at its launch: ``shared`` (the user's), ``empty`` or ``filled``."""
    return "shared" if cache_dir is None else ("empty" if entries_before == 0 else "filled")


# ---------------------------------------------------------------------- dynamic mode, jax vs warp

def joint_rollout(impl: str, envs: int, steps: int) -> Any:
    """Joint positions [step, env, joint] of ``envs`` dynamic-mode envs (paper preset, no noise, no
    obstacle) from fixed keys under fixed random actions, physics ``impl``."""
    import jax
    import numpy as np

    from sagrasp_jax.envs.grasp_env import GraspEnv
    from sagrasp_jax.task import config_parse

    cfg = config_parse.apply_overrides(config.get_config("paper"), [
        "env.control.mode=dynamic", f"env.control.impl={impl}", "env.task.obs_noise_std=0",
        "env.sampling.obstacle_prob=0"])
    env = GraspEnv(cfg.env)
    dof = env.action_size  # one action per arm joint
    actions = jax.random.uniform(jax.random.PRNGKey(3), (steps, envs, dof), minval=-1.0, maxval=1.0)

    def run(keys: jax.Array) -> jax.Array:
        def body(st: Any, action: jax.Array) -> tuple[Any, jax.Array]:
            st = jax.vmap(env.step)(st, action)
            return st, st.pipeline_state.qpos[:, :dof]

        return jax.lax.scan(body, jax.vmap(env.reset)(keys), actions)[1]

    return np.asarray(jax.device_get(jax.jit(run)(jax.random.split(jax.random.PRNGKey(7), envs))))


def dynamic_section(quick: bool) -> dict[str, Any]:
    """(In a child.) The dynamic mode's bare-env rate, jax and warp, and their equality."""
    from experiments import bench_env
    from sagrasp_jax import train

    train.use_cpu_devices(train.build_config("cpu-quick"))
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
    import numpy as np

    diff = float(np.max(np.abs(joint_rollout("warp", envs, steps) - joint_rollout("jax", envs, steps))))
    return {"envs": envs, "steps": steps, "max_abs_joint_diff": diff, "atol": EQUAL_ATOL, "passed": diff <= EQUAL_ATOL}


# ---------------------------------------------------------------------- a recorded training

class RowClock:
    """Launch-relative stamps of a run's metrics rows: each row gets the seconds since the launch at which a
    poll first saw it (``stamp`` is called with every poll's rows)."""

    def __init__(self) -> None:
        self.seen_at: list[float] = []

    def stamp(self, rows: Sequence[dict[str, Any]], since_launch: float) -> None:
        self.seen_at.extend(since_launch for _ in range(len(self.seen_at), len(rows)))


def first_at_level(rows: Sequence[dict[str, Any]], seen_at: Sequence[float], level: float) -> dict[str, Any] | None:
    """The first row whose fixed-seed evaluation reached ``level``: its env steps, the trainer's own training
    seconds and the seconds from the launch at which it was seen (None: not reached)."""
    for row, seen in zip(rows, seen_at):
        if row.get("eval_success") is not None and row["eval_success"] >= level:
            return {"eval_success": row["eval_success"], "env_steps": row["env_steps"], "train_s": row["time_s"],
                    "from_launch_s": seen}
    return None


def last_eval_success(rows: Sequence[dict[str, Any]]) -> float | None:
    """The latest fixed-seed evaluation's success among a run's metrics rows (None: none yet)."""
    return next((r["eval_success"] for r in reversed(rows) if r.get("eval_success") is not None), None)


def run_summary(rows: Sequence[dict[str, Any]], seen_at: Sequence[float]) -> dict[str, Any]:
    """A training's numbers from its metrics rows and their launch-relative stamps."""
    if not rows:
        return {"env_steps": 0, "rows": 0, **{f"first_{round(100 * lv)}": None for lv in LEVELS}}
    last = rows[-1]
    rates = sorted(r["steps_per_s"] for r in rows if r.get("steps_per_s"))
    return {
        "rows": len(rows), "env_steps": last["env_steps"], "train_s": last["time_s"],
        "compile_s": last.get("compile_s"), "compile_iteration_s": last.get("compile_iteration_s"),
        "compile_eval_s": last.get("compile_eval_s"),
        "median_iteration_env_steps_per_s": rates[len(rates) // 2] if rates else None,
        "overall_env_steps_per_s": last["env_steps"] / last["time_s"] if last.get("time_s") else None,
        "last_eval_success": last_eval_success(rows),
        **{f"first_{round(100 * lv)}": first_at_level(rows, seen_at, lv) for lv in LEVELS},
    }


def compile_breakdown(record: dict[str, Any]) -> dict[str, Any]:
    """The recorder's programs (longest first) and totals, in the check's compact form."""
    programs = [{"program": r["program"], "called_at": r["called_at"], "trace_s": r["trace_wall_s"],
                 "lower_s": r["lower_wall_s"], "compile_s": r["own_compile_s"], "compile_cpu_s": r["own_compile_cpu_s"],
                 "cache": r["cache"], "stablehlo_ops": r.get("stablehlo_ops"),
                 "hlo_instructions": r.get("hlo_instructions"), "cache_entry_bytes": r.get("cache_entry_bytes")}
                for r in sorted(record["programs"], key=lambda r: -readme_line.spent(r))]
    return {"programs": programs, "totals": readme_line.compile_totals(record), "imports_s": record["imports_s"],
            "main_s": record["main_s"], "exit": record["exit"], "devices": record["devices"],
            "device": record.get("device"), "versions": record["versions"],
            "cache_min_compile_time_s": record["cache_min_compile_time_s"]}


def recorded_training(work: str, name: str, args: Sequence[str], cache_dir: str | None, stop_at: float) -> dict[str, Any]:
    """``python -m sagrasp_jax.train --out W/<name> --no-progress ARGS`` in a fresh process on ``cache_dir``
    under the compile recorder, its metrics stamped as they appear, SIGTERMed at ``stop_at``."""
    run = os.path.join(work, name)
    record_path, log = os.path.join(work, f"{name}.record.json"), os.path.join(work, f"{name}.log")
    train_args = [*args, "--out", run, "--no-progress"]
    cache_path, entries_before = cache_before(cache_dir)
    clock = RowClock()

    def stop(rows: list[dict[str, Any]], since: float) -> str | None:
        clock.stamp(rows, since)
        return f"the budget (its section's end, {since:.0f} s after launch)" if time.perf_counter() >= stop_at else None

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    rows, stopped, code, wall = watch_trainer(readme_line.record_command("train", train_args, record_path), ROOT, log,
                                              os.path.join(run, run_dir.METRICS_FILE), POLL_S, stop,
                                              env=child_env(cache_dir), grace_s=GRACE_S)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    clock.stamp(rows, wall)  # rows written after the last poll: seen at the exit
    record = None
    if os.path.isfile(record_path):
        with open(record_path, encoding="utf-8") as f:
            record = json.load(f)
        code = record["exit"] if code == 0 else code  # the recorder's process ends 0 whatever train.main returned
    if stopped is None and code != 0:
        raise RuntimeError(f"`python -m sagrasp_jax.train {' '.join(train_args)}` exited {code}: {log_tail(log)}")
    config_file = os.path.join(run, run_dir.CONFIG_FILE)
    out: dict[str, Any] = {
        "command": "python -m sagrasp_jax.train " + " ".join(train_args), "run": run,
        "preset": args[args.index("--preset") + 1],
        "num_envs": run_dir.load_config(run).ppo.num_envs if os.path.isfile(config_file) else None,
        "cache": cache_label(cache_dir, entries_before), "cache_dir": cache_path, "cache_entries_before": entries_before,
        "cache_entries_after": readme_line.cache_files(cache_path)[0],
        "stopped_by": stopped or "finished", "exit": code, "process_wall_s": wall,
        "process_cpu_s": after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime,
        "load": os.getloadavg(), "clock": f"metrics rows stamped when first seen, polled every {POLL_S} s",
        **run_summary(rows, clock.seen_at),
    }
    if record is not None:
        record.update(process_wall_s=wall, process_user_s=after.ru_utime - before.ru_utime,
                      process_sys_s=after.ru_stime - before.ru_stime)
        out["compile"] = compile_breakdown(record)
        out["peak_device_memory_bytes"] = record.get("peak_device_memory_bytes")
    else:  # killed before the recorder wrote its record
        out["compile"] = out["peak_device_memory_bytes"] = None
    return out


def training_args(quick: bool, preset_key: str = "train_preset", extra: Sequence[str] = ()) -> list[str]:
    """The train command's arguments of a section: preset, seed 0, the quick size's steps and overrides."""
    args = ["--preset", size(preset_key, quick), "--seed", "0"]
    if size("train_steps", quick):
        args += ["--total-steps", str(size("train_steps", quick))]
    return args + [a for item in (*size("train_sets", quick), *extra) for a in ("--set", item)]


# ---------------------------------------------------------------------- physics: its training and evaluations

def evaluate_condition(run: str, condition: str, episodes: int, cache_dir: str | None, timeout: float) -> dict[str, Any]:
    """``python -m sagrasp_jax.evaluate --run RUN --episodes N --condition C`` (result into the run folder):
    success per episode group as evaluate reports it, steps per success, the command's wall."""
    path = os.path.join(run, f"{run_dir.EVALUATION_PREFIX}{episodes}ep-{condition}.json")
    args = ["--run", run, "--episodes", str(episodes), "--condition", condition, "--out", path, "--force"]
    t = time.perf_counter()
    try:
        done = subprocess.run([sys.executable, "-m", "sagrasp_jax.evaluate", *args], cwd=ROOT, env=child_env(cache_dir),
                              capture_output=True, text=True, timeout=max(timeout, 1.0))
    except subprocess.TimeoutExpired:
        raise TimeoutError(f"the {condition} evaluation stopped at the budget after {timeout:.0f} s") from None
    wall = time.perf_counter() - t
    if done.returncode:
        raise RuntimeError(f"evaluate {' '.join(args)} exited {done.returncode}: {(done.stdout + done.stderr)[-800:]}")
    with open(path, encoding="utf-8") as f:
        res = json.load(f)
    groups = {"overall": res["overall"], "obstacle": res["obstacle_present"], "blocking": res.get("blocking")}
    return {"command": "python -m sagrasp_jax.evaluate " + " ".join(args), "wall_s": wall,
            "steps_per_success": res["overall"].get("mean_steps_per_success"),
            **{name: None if g is None else {"episodes": g["episodes"], "success_rate": g.get("success_rate"),
                                             "successes": round((g.get("success_rate") or 0.0) * g["episodes"])}
               for name, g in groups.items()}}


def physics_section(quick: bool, work: str, cache_dir: str | None, end: float) -> dict[str, Any]:
    out = recorded_training(work, "physics", training_args(quick, "physics_preset"), cache_dir,
                            end - EVAL_RESERVE_S[quick])
    evals: dict[str, Any] = {}
    longest = 0.0
    for condition in size("eval_conditions", quick):
        left = end - time.perf_counter()
        if evals and left < 1.2 * longest:
            evals[condition] = {"status": "skipped",
                                "reason": f"{left:.0f} s left, the last evaluation took {longest:.0f} s"}
            continue
        evals[condition] = section(f"physics {condition}", lambda c=condition: evaluate_condition(
            out["run"], c, size("eval_episodes", quick), cache_dir, left))
        longest = max(longest, evals[condition]["section_s"])
    out["evaluations"] = evals
    return out


# ---------------------------------------------------------------------- the paper's 5-seed reproduction

def paper_args(quick: bool, work: str) -> list[str]:
    out_dir = os.path.join(work, "paper")
    args = ["--preset", size("paper_preset", quick), "--seeds", str(size("paper_seeds", quick)), "--out-dir", out_dir,
            "--runs-dir", os.path.join(out_dir, "runs"), "--no-progress",
            "--eval-episodes", str(size("paper_eval_episodes", quick))]
    if size("paper_steps", quick):
        args += ["--total-steps", str(size("paper_steps", quick))]
    return args + [a for item in size("paper_sets", quick) for a in ("--set", item)]


def paper_progress(runs_dir: str, seeds: int) -> dict[str, dict[str, Any]]:
    """Per algorithm and seed: env steps reached, policy written, last fixed-seed evaluation (the runs' files)."""
    from experiments.reproduce_paper import ALGOS

    out: dict[str, dict[str, Any]] = {}
    for algo in ALGOS:
        out[algo] = {}
        for seed in range(seeds):
            folder = os.path.join(runs_dir, algo, study.SEED_FOLDER.format(seed=seed))
            file = os.path.join(folder, run_dir.METRICS_FILE)
            rows = run_dir.read_metrics(file) if os.path.exists(file) else []
            out[algo][str(seed)] = {"env_steps": rows[-1]["env_steps"] if rows else 0,
                                    "policy": os.path.isfile(os.path.join(folder, run_dir.POLICY_FILE)),
                                    "last_eval_success": last_eval_success(rows)}
    return out


def paper_table(out_dir: str) -> dict[str, Any]:
    """The finished study's table: each algorithm's pooled success (Wilson 95 %), steps per success, the
    paired seed-by-seed comparison, and ``results.md``'s lines."""
    from experiments.reproduce_paper import ALGOS, RESULTS_JSON, RESULTS_MD

    with open(os.path.join(out_dir, RESULTS_JSON), encoding="utf-8") as f:
        results = json.load(f)
    with open(os.path.join(out_dir, RESULTS_MD), encoding="utf-8") as f:
        md = f.read().splitlines()
    algos = {a: {k: results["algos"][a]["pooled"][k] for k in
                 ("episodes", "success_pct", "success_ci95_wilson_pct", "steps_per_success", "collision_pct")}
             for a in ALGOS}
    paired = results.get("paired_ppo_minus_sa_ppo", {})
    return {"algos": algos, "paired_ppo_minus_sa_ppo": {k: paired.get(k) for k in ("seeds", "success_pct",
                                                                                    "steps_per_success")},
            "results_md": md}


def paper_section(quick: bool, work: str, cache_dir: str | None, end: float) -> dict[str, Any]:
    args = paper_args(quick, work)
    out_dir = args[args.index("--out-dir") + 1]
    runs_dir = os.path.join(out_dir, "runs")
    seeds = size("paper_seeds", quick)
    entries_before = cache_before(cache_dir)[1]
    first = os.path.join(runs_dir, "ppo", study.SEED_FOLDER.format(seed=0), run_dir.METRICS_FILE)
    stop = lambda rows, since: ("the budget"  # noqa: E731
                                if time.perf_counter() >= end else None)
    log = os.path.join(work, "paper.log")
    rows, stopped, code, wall = watch_trainer([sys.executable, "-m", "experiments.reproduce_paper", *args], ROOT, log,
                                              first, 2.0, stop, env=child_env(cache_dir), grace_s=GRACE_S)
    total = size("paper_steps", quick) or config.get_config(size("paper_preset", quick)).train.total_steps
    progress = paper_progress(runs_dir, seeds)
    if stopped is None and code != 0:  # e.g. the report's plots without matplotlib, after every run trained
        reached = "; ".join(f"{a} " + ", ".join(f"{r['env_steps']:,}" for r in runs.values()) for a, runs in progress.items())
        raise RuntimeError(f"`python -m experiments.reproduce_paper {' '.join(args)}` exited {code} (env steps "
                           f"reached: {reached} of {total:,} per run): {log_tail(log)}")
    out: dict[str, Any] = {"command": "python -m experiments.reproduce_paper " + " ".join(args),
                           "finished": stopped is None, "stopped_by": stopped or "finished", "exit": code,
                           "wall_s": wall, "env_steps_per_run": total, "seeds": seeds, "runs_dir": runs_dir,
                           "out_dir": out_dir, "cache": cache_label(cache_dir, entries_before),
                           "progress": progress}
    out["table"] = paper_table(out_dir) if stopped is None else None
    return out


# ---------------------------------------------------------------------- policies come back

def copy_run_files(run: str, dest: str) -> dict[str, list[str]]:
    """A run folder's small files (policy, config, metrics, evaluation JSONs: evaluate's ``evaluation-*.json``,
    a study's ``evaluation.json``; no checkpoint, nothing over ``MAX_COPY_BYTES``) copied into ``dest``: a folder ``rehearse --policy`` takes when it holds a policy."""
    names = sorted(n for n in os.listdir(run) if n in (run_dir.POLICY_FILE, run_dir.CONFIG_FILE, run_dir.METRICS_FILE)
                   or (n.startswith("evaluation") and n.endswith(".json"))) if os.path.isdir(run) else []
    copied, left_out = [], []
    os.makedirs(dest, exist_ok=True)
    for name in names:
        src = os.path.join(run, name)
        if os.path.getsize(src) > MAX_COPY_BYTES:
            left_out.append(f"{name} ({os.path.getsize(src):,} bytes)")
            continue
        shutil.copy2(src, os.path.join(dest, name))
        copied.append(name)
    return {"copied": copied, "left_out": left_out}


def run_folders(work: str) -> dict[str, str]:
    """Every run folder the check's sections trained under ``work`` (whatever their status: a stopped or
    failed run's files are results too), by the folder its files go to under ``--policies``:
    ``<section>`` for the recorded trainings, ``paper/<algo>/seed<S>`` for the paper's runs."""
    out = {name: os.path.join(work, name) for name in TRAINING_SECTIONS if os.path.isdir(os.path.join(work, name))}
    runs = os.path.join(work, "paper", "runs")
    for algo in sorted(os.listdir(runs)) if os.path.isdir(runs) else []:
        for seed in sorted(os.listdir(os.path.join(runs, algo))):
            if os.path.isdir(os.path.join(runs, algo, seed)):
                out[f"paper/{algo}/{seed}"] = os.path.join(runs, algo, seed)
    return out


def collect_policies(work: str, policies: str) -> dict[str, Any]:
    """Every run folder of ``work`` (``run_folders``) copied into ``policies``, and the paper's results beside
    its runs: folder -> what was copied."""
    out = {dest: copy_run_files(run, os.path.join(policies, dest)) for dest, run in run_folders(work).items()}
    for file in ("results.json", "results.md"):
        if os.path.isfile(os.path.join(work, "paper", file)):
            os.makedirs(os.path.join(policies, "paper"), exist_ok=True)
            shutil.copy2(os.path.join(work, "paper", file), os.path.join(policies, "paper", file))
    return out


# ---------------------------------------------------------------------- report

def _num(value: Any, spec: str = ",.0f") -> str:
    return "-" if value is None else format(value, spec)


def _pct(value: Any) -> str:
    return "-" if value is None else f"{100 * value:.1f} %"


def training_lines(name: str, t: dict[str, Any]) -> list[str]:
    """A recorded training's row, its compile totals, and its longest programs."""
    levels = ", ".join(f"{round(100 * lv)} % " + ("not reached" if t[f"first_{round(100 * lv)}"] is None else
                                                  f"at {t[f'first_{round(100 * lv)}']['from_launch_s']:.1f} s")
                       for lv in LEVELS)
    mem = t.get("peak_device_memory_bytes")
    lines = [f"{name:<9} {t['preset']} preset, {_num(t['num_envs'])} envs: "
             f"{t['stopped_by']}, cache {t['cache']}; launch->exit {t['process_wall_s']:.1f} s, trainer compile "
             f"{_num(t.get('compile_s'), '.1f')} s, training {_num(t.get('train_s'), '.1f')} s, {t['env_steps']:,} env "
             f"steps, {_num(t.get('median_iteration_env_steps_per_s'))} env-steps/s per iteration, "
             f"{_num(t.get('overall_env_steps_per_s'))} overall",
             f"{'':9} from launch: {levels}; last eval {_pct(t.get('last_eval_success'))}; peak device memory "
             f"{'not reported' if mem is None else f'{mem / 2**30:.2f} GiB'}"]
    c = t.get("compile")
    if c is None:
        return lines + [f"{'':9} no compile record (the process was killed before it wrote one)"]
    tot = c["totals"]
    lines.append(f"{'':9} {tot['programs']} programs, {tot['hits']} cache hits: trace {tot['trace_s']:.1f} s, lower "
                 f"{tot['lower_s']:.1f} s, XLA compile {tot['compile_s']:.1f} s; imports {c['imports_s']:.1f} s")
    for p in c["programs"][:PROGRAM_ROWS]:
        lines.append(f"{'':11}{p['program'][:26]:26s} {(p['called_at'] or '-')[:38]:38s} {_num(p['trace_s'], '6.2f')} "
                     f"{_num(p['lower_s'], '6.2f')} {_num(p['compile_s'], '7.2f')} {p['cache']:>11s} "
                     f"{_num(p['hlo_instructions'], '8d')} HLO")
    return lines


def table(result: dict[str, Any]) -> str:
    s = result["sections"]
    lines = [f"gpu_check{' --quick' if result['quick'] else ''} on {result['device']} ({result['backend']}), "
             f"{result['wall_s']:.0f} s of --budget-s {result['budget_s']:.0f}", ""]
    for name, row in s.items():
        if row["status"] == "skipped":
            lines.append(f"{name:<9} {row['reason']}")
        elif row["status"] == "error":
            lines.append(f"{name:<9} ERROR {row['error']}")
        elif name == "dynamic":
            for impl in ("jax", "warp"):
                r = row[impl]
                lines.append(f"dynamic   impl={impl:<5} " + (r if isinstance(r, str) else f"ERROR {r['error']}"
                             if r.get("status") == "error" else f"{_num(r['env_steps_per_s'])} env-steps/s "
                             f"(batch {row['batch']}, compile {r['compile_s']:.1f} s)"))
            eq = row["equal"]
            lines.append("          jax == warp " + (eq if isinstance(eq, str) else f"ERROR {eq['error']}"
                         if eq["status"] == "error" else f"{'passed' if eq['passed'] else 'FAILED'}: max |dq| "
                         f"{eq['max_abs_joint_diff']:.2e} (atol {eq['atol']:g})"))
        elif name == "paper":
            done = sum(r["env_steps"] for seeds in row["progress"].values() for r in seeds.values())
            reach = "; ".join(f"{algo} " + ", ".join(f"{r['env_steps']:,}" for r in seeds.values())
                              for algo, seeds in row["progress"].items())
            head = (f"finished in {row['wall_s']:.0f} s" if row["finished"] else
                    f"STOPPED at {row['stopped_by']} after {row['wall_s']:.0f} s, NOT finished (no table)")
            lines.append(f"paper     {row['seeds']} seeds x 2 algorithms, {row['env_steps_per_run']:,} env steps per run: "
                         f"{head}; env steps reached {reach} ({done:,} in all)")
            if row["table"] is not None:
                for algo, a in row["table"]["algos"].items():
                    lo, hi = a["success_ci95_wilson_pct"]
                    lines.append(f"{'':9} {algo:<7} success {a['success_pct']:.1f} % [{lo:.1f}, {hi:.1f}] on "
                                 f"{a['episodes']} episodes, {_num(a['steps_per_success'], '.1f')} steps/success")
                paired = row["table"]["paired_ppo_minus_sa_ppo"].get("success_pct") or {}
                lines.append(f"{'':9} PPO - SA-PPO success, seed by seed: {_num(paired.get('mean_diff'), '+.1f')} points,"
                             f" p {_num(paired.get('p'), '.3f')}")
        else:
            lines += training_lines(name, row)
            for condition, ev in row.get("evaluations", {}).items():
                if ev["status"] != "ok":
                    lines.append(f"{'':9} {condition}: {ev.get('reason') or 'ERROR ' + ev.get('error', '')}")
                    continue
                groups = ", ".join(f"{g} {_pct(ev[g]['success_rate'])} ({ev[g]['successes']}/{ev[g]['episodes']})"
                                   for g in ("overall", "obstacle", "blocking") if ev[g] is not None)
                lines.append(f"{'':9} {condition}: {groups}; {_num(ev['steps_per_success'], '.1f')} steps/success, "
                             f"{ev['wall_s']:.0f} s")
    lines.append(f"policies  {result['policies_dir']}: " + (", ".join(
        k for k, v in result["policies"].items() if run_dir.POLICY_FILE in v["copied"]) or "none"))
    return "\n".join(lines)


def parse_sections(text: str) -> tuple[str, ...]:
    """A comma list of ``SECTIONS`` in the check's order; an unknown name raises ValueError naming it."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in SECTIONS]
    if unknown or not names:
        raise ValueError(f"unknown section(s) {', '.join(unknown) or '(none given)'}; valid: {', '.join(SECTIONS)}")
    return tuple(n for n in SECTIONS if n in names)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.gpu_check", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="every section at CPU-smoke size (the test suite's form)")
    p.add_argument("--budget-s", type=float, default=None,
                   help="the whole check's deadline in seconds (default 540, with --quick 900)")
    p.add_argument("--sections", default=",".join(SECTIONS), help=f"comma list of {', '.join(SECTIONS)} (default all)")
    p.add_argument("--work", default=None, help="folder for the runs and caches (default a new folder under /tmp, kept)")
    p.add_argument("--out", default="gpu_check.json", help="result JSON")
    p.add_argument("--policies", default=None, help="where the runs' policies are copied (default policies/ beside --out)")
    args = p.parse_args(argv)
    try:
        chosen = parse_sections(args.sections)
    except ValueError as exc:
        p.error(f"--sections: {exc}")
    if args.budget_s is None:
        args.budget_s = size("budget_s", args.quick)
    if args.budget_s <= 0:
        p.error("--budget-s must be > 0")
    budget = Budget(time.perf_counter(), args.budget_s, chosen, args.quick)
    work = os.path.abspath(args.work or os.path.join("/tmp", f"gpu_check.{os.getpid()}"))
    policies = os.path.abspath(args.policies or os.path.join(os.path.dirname(os.path.abspath(args.out)), "policies"))
    os.makedirs(work, exist_ok=True)
    quick = args.quick
    own_cache = lambda name: None if quick else os.path.join(work, f"cache-{name}")  # noqa: E731
    try:
        info = child_json("device_info()", 120.0)
    except (RuntimeError, TimeoutError) as exc:  # the sections still run and say what they can
        info = {"device": f"unknown ({str(exc)[-300:]})", "backend": "unknown", "device_count": None, "versions": {}}
    result: dict[str, Any] = {
        "complete": False, "quick": quick, **info, "machine": f"{platform.node()} {study.machine()}", "budget_s": args.budget_s,
        "command": study.command("gpu_check", argv), "git": study.git_state(), "work": work, "sections": {},
        "load_before": os.getloadavg(),
    }
    runs: dict[str, Callable[[float], dict[str, Any]]] = {
        "dynamic": lambda end: child_json(f"dynamic_section({quick})", end - time.perf_counter()),
        "cold": lambda end: recorded_training(work, "cold", training_args(quick), own_cache("gpu"), end),
        "warm": lambda end: recorded_training(work, "warm", training_args(quick), own_cache("gpu"), end),
        "envs16k": lambda end: recorded_training(work, "envs16k", training_args(
            quick, extra=[f"ppo.num_envs={size('big_envs', quick)}"]), own_cache("envs16k"), end),
        "physics": lambda end: physics_section(quick, work, own_cache("physics"), end),
        "paper": lambda end: paper_section(quick, work, own_cache("paper"), end),
    }
    result["policies_dir"] = policies
    for name in chosen:
        end = budget.section_end(name)
        result["sections"][name] = section(name, lambda: runs[name](end), budget.skip_reason(name, time.perf_counter()))
        # after every section: a check killed from outside (the device call's limit) still leaves what it measured
        result["policies"] = collect_policies(work, policies)
        study.write_json(args.out, {**result, "complete": False, "wall_s": time.perf_counter() - budget.start})
    result["complete"] = True
    result["wall_s"] = time.perf_counter() - budget.start
    result["load_after"] = os.getloadavg()
    text = table(result)
    result["table"] = text.splitlines()
    study.write_json(args.out, result)
    print("\n" + text + f"\n\nwritten to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
