"""The README's training command, exactly as written, from a fresh clone with a cold compilation cache; and
where the training command's start-up and the evaluation command's seconds go.

    python -m experiments.readme_line line --out experiments/results/readme_line.json
    python -m experiments.readme_line startup --out experiments/results/readme_startup.json
    python -m experiments.readme_line eval-slots --run runs/quick --out experiments/results/eval_slots.json
    python -m experiments.readme_line compile --cycles 2 --out experiments/results/compile_breakdown.json
    python -m experiments.readme_line compile --cache cold --no-eval --serial-compiles --out experiments/results/compile_breakdown_serial.json
    python -m experiments.readme_line options --option xla_backend_optimization_level=1 --out experiments/results/compile_options_o1.json

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
  venv holding another jax) to compare jax versions on one machine: ``docs/results-archive.md`` §19.
* ``eval-slots``: the evaluation command's program on ``--run``'s policy (``--condition``, 1,000 episodes) at
  several episode-slot counts: compile and run seconds, and how far each one's per-episode results are from
  all episodes at once.
* ``compile``: every program the README line's two commands compile (``CompileRecorder``): its training command
  (the README's arguments, ``--out`` a temporary folder, ``--stop-after-cycles --cycles``, ``--no-progress``) and
  its evaluation command on that run, each in a fresh process, first on an empty compilation cache (``cold``),
  then again on the cache the first pass filled (``warm``).  Per program: jax's trace, lowering and XLA compile
  seconds (wall, and the calling thread's CPU), the persistent cache's answer (hit, miss, or not written: under
  ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS``), its size (StableHLO ops, optimised HLO instructions, the cache
  entry's bytes, the optimised HLO's instructions by the source file that made them); per pass the processes'
  wall and CPU seconds.  ``--serial-compiles``: one XLA compile at a time, for each program's compile CPU alone.
  It only measures: the package runs as is.
* ``options``: the README trainer's four programs (its initial state, first batched reset, training call and
  evaluation) compiled again under XLA compile options (``--option KEY=VALUE``, repeatable; none: XLA's defaults),
  in a fresh process on an empty cache: each one's compile CPU seconds, a second call's CPU seconds, and a digest of
  its outputs.  A digest equal to the defaults' says the option leaves that program's numbers as they were (issue 55:
  ``xla_backend_optimization_level=0`` keeps the initial state's, not the reset's, the training call's).

Every mode prints a table and writes the JSON with the machine's load average beside the numbers.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import importlib.metadata
import json
import logging
import math
import os
import platform
import resource
import shlex
import shutil
import subprocess
import sys
import tempfile
import threading
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
            rows.append(_fresh_process_json(tmp, f"m._startup_once({tmp!r}, {cycles})"))
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

    from sagrasp_jax.training import evaluation as ev
    from sagrasp_jax.task.config import EVAL_CONDITIONS
    from sagrasp_jax.training import restore, run_dir
    from sagrasp_jax.training.agents.ppo import actor_critic
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


# ---------------------------------------------------------------------------------------------------- compile
COMPILE_EVENTS = {"/jax/core/compile/jaxpr_trace_duration": "trace",
                  "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
                  "/jax/core/compile/backend_compile_duration": "compile"}
# jax._src.compiler's log lines about the persistent cache (DEBUG unless jax_log_compiles / explain_cache_misses)
CACHE_LINES = {"Persistent compilation cache hit": "hit", "PERSISTENT COMPILATION CACHE MISS": "miss",
               "because it took <": "not_written", "took at least": "written"}


def readme_commands(readme: str) -> dict[str, list[str]]:
    """The README line's ``python -m`` commands' arguments: ``{"train": [...], "evaluate": [...]}``."""
    out = {}
    for part in readme_line(readme).split("&&"):
        words = shlex.split(part)
        if words[:2] == ["python", "-m"] and words[2] in ("sagrasp_jax.train", "sagrasp_jax.evaluate"):
            out[words[2].rsplit(".", 1)[1]] = words[3:]
    return out


def with_option(args: list[str], option: str, value: str | None = None) -> list[str]:
    """``args`` with ``option``'s value set to ``value`` (a flag without value: added once)."""
    args = list(args)
    if option in args:
        if value is not None:
            args[args.index(option) + 1] = value
        return args
    return args + [option] + ([] if value is None else [value])


class CompileRecorder:
    """Every program jax compiles in this process, from what jax reports: the trace, lowering and XLA compile
    durations it sends to ``jax.monitoring`` (with the calling thread's and the process's CPU seconds taken at
    the event's start and end), the persistent cache's answer (``jax._src.compiler``'s log lines, which name the
    module and its cache key), and each module and executable (kept for ``sizes``, measured after the timed
    part; ``compiler.compile_or_get_cached`` is wrapped to see them, and to take the process's CPU seconds around
    the compile itself).  XLA compiles on its own threads, so a program's compile CPU is the process's while it
    compiled: exact when nothing ran beside it; ``serial``: one compile at a time (a lock around the wrapped
    call; the training command's two ahead-of-time compiles then run one after the other instead of side by
    side, the same programs), to measure each one's CPU alone."""

    def __init__(self, t0: float, serial: bool = False) -> None:
        self.t0 = t0
        self._serial = threading.Lock() if serial else None
        self.events: list[dict[str, Any]] = []  # trace / lower / compile, in the order they ended
        self.compiles: list[dict[str, Any]] = []  # one per compile_or_get_cached call
        self.unmatched: list[dict[str, Any]] = []
        self._kept: list[tuple[Any, Any]] = []
        self._open: dict[tuple[int, str, str], tuple[float, float, str | None]] = {}
        self._local = threading.local()

    def install(self) -> CompileRecorder:
        import jax
        from jax._src import compiler
        from jax._src.lib.mlir import ir

        jax.monitoring.register_scalar_listener(self._started)  # jax records an event's start time as a scalar
        jax.monitoring.register_event_duration_secs_listener(self._ended)
        recorder = self

        class Lines(logging.Handler):
            def emit(self, record: logging.LogRecord) -> None:
                recorder._line(record)

        class Warnings(logging.Handler):  # what jax's compiler says at WARNING and above, on its usual way
            def emit(self, record: logging.LogRecord) -> None:
                if log.parent is not None:
                    log.parent.handle(record)

        # DEBUG for the recorder only: where something set up a root handler (mujoco-mjx logs a root-level debug
        # message, which gives root a stderr handler), the compiler's debug lines would flood the command's log
        log = logging.getLogger("jax._src.compiler")
        log.setLevel(logging.DEBUG)
        log.propagate = False
        log.addHandler(Lines(logging.DEBUG))
        log.addHandler(Warnings(logging.WARNING))
        original = compiler.compile_or_get_cached

        def compile_or_get_cached(backend: Any, computation: Any, *args: Any, **kwargs: Any) -> Any:
            entry = {"module": ir.StringAttr(computation.operation.attributes["sym_name"]).value,
                     "thread": threading.current_thread().name, "start_s": time.perf_counter() - self.t0,
                     "cache": "off", "cache_lines": []}
            self.compiles.append(entry)
            self._local.entry = entry
            try:
                with self._serial or contextlib.nullcontext():
                    entry["own_start_s"], cpu = time.perf_counter() - self.t0, time.process_time()
                    executable = original(backend, computation, *args, **kwargs)
                    entry["own_cpu_s"], entry["own_end_s"] = time.process_time() - cpu, time.perf_counter() - self.t0
            finally:
                self._local.entry = None
            entry["kept"], entry["end_s"] = len(self._kept), time.perf_counter() - self.t0
            self._kept.append((computation, executable))
            return executable

        compiler.compile_or_get_cached = compile_or_get_cached  # pxla calls it as compiler.compile_or_get_cached
        return self

    def _started(self, event: str, value: float, **kwargs: Any) -> None:
        if event in COMPILE_EVENTS:
            self._open[(threading.get_ident(), event, str(kwargs.get("fun_name")))] = (
                time.thread_time(), time.process_time(), _package_caller() if event.endswith("trace_duration") else None)

    def _ended(self, event: str, duration: float, **kwargs: Any) -> None:
        entry = getattr(self._local, "entry", None)
        if event.startswith("/jax/compilation_cache/") and entry is not None:
            entry[event.rsplit("/", 1)[1]] = duration  # compile_time_saved_sec, cache_retrieval_time_sec
        if event not in COMPILE_EVENTS:
            return
        name = str(kwargs.get("fun_name"))
        start = self._open.pop((threading.get_ident(), event, name), None)
        self.events.append({
            "kind": COMPILE_EVENTS[event], "name": name, "thread": threading.current_thread().name,
            "wall_s": duration, "end_s": time.perf_counter() - self.t0,
            "thread_cpu_s": None if start is None else time.thread_time() - start[0],
            # every thread's CPU meanwhile: with XLA's own threads, and whatever else ran beside it
            "process_cpu_s": None if start is None else time.process_time() - start[1],
            "called_at": None if start is None else start[2]})

    def _line(self, record: logging.LogRecord) -> None:
        entry = getattr(self._local, "entry", None)
        if entry is None:
            return
        message = record.getMessage()
        for needle, what in CACHE_LINES.items():
            if needle in message:
                entry["cache_lines"].append(what)
                if what in ("hit", "miss"):
                    entry["cache"] = what
                    entry["cache_key"] = record.args[1] if isinstance(record.args, tuple) else None
                if what == "written":  # the executable's serialisation and the entry's write follow this line
                    entry["write_from_s"] = time.perf_counter() - self.t0

    def programs(self) -> list[dict[str, Any]]:
        """One row per compiled program: its XLA compile (the compile event that ends next in the thread that
        called ``compile_or_get_cached``, once it returned), the latest lowering of the same name before it, and
        the trace that ended last before that lowering began in the lowering's thread (a ``jit`` call or
        ``.lower()`` traces and lowers in one thread; ``.compile()`` may run in another)."""
        by_kind: dict[str, list[dict[str, Any]]] = {"trace": [], "lower": [], "compile": []}
        for e in self.events:
            by_kind[e["kind"]].append(e)
        used: set[int] = set()
        rows = []
        for entry in self.compiles:
            done = next((e for e in by_kind["compile"] if id(e) not in used and e["thread"] == entry["thread"]
                         and e["end_s"] >= entry.get("end_s", float("inf"))), None)
            lower = trace = None
            if done is not None:
                began = done["end_s"] - done["wall_s"]
                lower = next((e for e in reversed(by_kind["lower"]) if id(e) not in used and e["name"] == done["name"]
                              and e["end_s"] <= began + 1e-3), None)
            if lower is not None:
                began = lower["end_s"] - lower["wall_s"]
                trace = next((e for e in reversed(by_kind["trace"]) if id(e) not in used and e["thread"] == lower["thread"]
                              and e["end_s"] <= began + 1e-3), None)
            row: dict[str, Any] = {"program": entry["module"] if done is None else done["name"], "module": entry["module"],
                                   "traced": None if trace is None else trace["name"],
                                   "called_at": None if trace is None else trace["called_at"],
                                   "compile_thread": entry["thread"], "cache": entry["cache"],
                                   "cache_lines": entry["cache_lines"], "cache_key": entry.get("cache_key")}
            for kind, e in (("trace", trace), ("lower", lower), ("compile", done)):
                if e is not None:
                    used.add(id(e))
                for field in ("wall_s", "thread_cpu_s", "process_cpu_s"):
                    row[f"{kind}_{field}"] = None if e is None else e[field]
            first = trace or lower or done
            row["start_s"] = None if first is None else first["end_s"] - first["wall_s"]
            row["end_s"] = None if done is None else done["end_s"]
            # the compile alone (after the serial lock): its wall and the process's CPU seconds meanwhile; others:
            # the compiles that ran beside it (their CPU is in its own_cpu_s too).  A compile the run's stop
            # (SIGTERM's Terminated) interrupted has no end: None, and it ran beside everything after its start.
            span = _own_span(entry)
            row["own_compile_s"] = entry["own_end_s"] - entry["own_start_s"] if "own_end_s" in entry else None
            row["own_compile_cpu_s"] = entry.get("own_cpu_s")
            row["beside"] = [other["module"] for other in self.compiles if other is not entry and span is not None
                             and (o := _own_span(other)) is not None and o[0] < span[1] and o[1] > span[0]]
            row["cache_write_s"] = None if "write_from_s" not in entry else entry["end_s"] - entry["write_from_s"]
            row["cache_retrieval_s"] = entry.get("cache_retrieval_time_sec")
            row["compile_time_saved_s"] = entry.get("compile_time_saved_sec")
            row["kept"] = entry.get("kept")
            rows.append(row)
        # traces that lowered nothing here (jax.eval_shape; a jit whose lowering jax had cached) and the like
        self.unmatched = [dict(e) for e in self.events if id(e) not in used]
        return rows

    def sizes(self, row: dict[str, Any], cache_dir: str | None) -> None:
        """The program's size: the StableHLO module's operations (nested ones included), the optimised HLO's
        instructions and text length (a cache hit's, deserialised, too), the cache entry's bytes."""
        from jax._src.lib.mlir import ir

        if row.get("kept") is None:
            return
        computation, executable = self._kept[row.pop("kept")]
        count = [0]

        def walk(op: Any) -> Any:
            count[0] += 1
            return ir.WalkResult.ADVANCE

        computation.operation.walk(walk)
        row["stablehlo_ops"] = count[0]
        texts = [m.to_string() for m in executable.hlo_modules()]
        text = "\n".join(texts)
        row["hlo_instructions"] = sum(1 for line in text.splitlines() if " = " in line)
        row["hlo_text_chars"] = len(text)
        row["hlo_by_source"] = hlo_by_source(texts)
        # the gradient's share: jax names what it made by transposing the loss's linearisation "transpose(...)"
        row["hlo_in_transpose"] = sum(1 for line in text.splitlines() if " = " in line and "transpose(jvp(" in line)
        entry = os.path.join(cache_dir or "", f"{row.get('cache_key')}-cache")
        row["cache_entry_bytes"] = os.path.getsize(entry) if cache_dir and os.path.isfile(entry) else None


def _own_span(entry: dict[str, Any]) -> tuple[float, float] | None:
    """A compile's own (start, end) seconds; one interrupted by the run's stop ends never (inf), one stopped
    before it began (waiting for the serial lock) has none."""
    if "own_start_s" not in entry:
        return None
    return entry["own_start_s"], entry.get("own_end_s", math.inf)


def hlo_by_source(texts: list[str], top: int = 15) -> dict[str, int]:
    """The optimised HLO's instructions counted by the Python file of the innermost frame jax kept for them (their
    metadata's ``stack_frame_id`` through the module's ``StackFrames``, ``FileLocations`` and ``FileNames``
    tables), from the package folder on (``mujoco/mjx/_src/smooth.py``); the ``top`` largest, the rest summed."""
    counts: dict[str, int] = {}
    for text in texts:
        tables: dict[str, dict[int, str]] = {}
        section = None
        for line in text.splitlines():
            if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
                section = line
                tables[section] = {}
                continue
            if section and line.strip() and line.split(" ", 1)[0].isdigit():
                number, rest = line.split(" ", 1)
                tables[section][int(number)] = rest
                continue
            section = None
            if " = " not in line:
                continue
            source = "(none)"
            if "stack_frame_id=" in line:
                frame_id = int(line.split("stack_frame_id=", 1)[1].split("}")[0].split()[0])
                frame = tables.get("StackFrames", {}).get(frame_id, "")
                location = tables.get("FileLocations", {}).get(_field(frame, "file_location_id") or 0, "")
                source = tables.get("FileNames", {}).get(_field(location, "file_name_id") or 0, '"(none)"').strip('"')
            for root in ("site-packages" + os.sep, os.sep + "sagrasp_jax" + os.sep):
                if root in source:
                    source = ("sagrasp_jax" + os.sep if root.startswith(os.sep) else "") + source.rsplit(root, 1)[1]
                    break
            counts[source] = counts.get(source, 0) + 1
    ranked = sorted(counts.items(), key=lambda kv: -kv[1])
    out = dict(ranked[:top])
    if len(ranked) > top:
        out["(other files)"] = sum(n for _, n in ranked[top:])
    return out


def _field(entry: str, name: str) -> int | None:
    """``name``'s number in an HLO table entry such as ``{file_location_id=3 parent_frame_id=1}``."""
    if name + "=" not in entry:
        return None
    return int(entry.split(name + "=", 1)[1].split()[0].rstrip("}"))


def _package_caller() -> str | None:
    """The innermost frame of the package's code on this thread's stack: ``training/trainer.py:118 compile``."""
    frame = sys._getframe(1)
    marker = os.sep + "sagrasp_jax" + os.sep
    while frame is not None:
        name = frame.f_code.co_filename
        if marker in name:
            return f"{name.rsplit(marker, 1)[1]}:{frame.f_lineno} {frame.f_code.co_name}"
        frame = frame.f_back  # type: ignore[assignment]
    return None


def _compile_once(command: str, args: list[str], out: str, serial: bool = False) -> None:
    """One process: the README line's ``command`` (train / evaluate) with ``args``, every compile recorded;
    the record goes to ``out`` (JSON)."""
    t0, c0 = time.perf_counter(), time.process_time()
    import sagrasp_jax  # noqa: F401  (XLA_FLAGS and the cache folder, before jax starts)

    recorder = CompileRecorder(t0, serial).install()
    if command == "train":
        from sagrasp_jax import train as cli
    else:
        from sagrasp_jax import evaluate as cli  # type: ignore[no-redef]
    import jax

    t1, c1 = time.perf_counter(), time.process_time()
    status = cli.main(args)
    t2, c2 = time.perf_counter(), time.process_time()
    rows = recorder.programs()
    cache_dir = jax.config.jax_compilation_cache_dir
    memory = jax.devices()[0].memory_stats()  # None on CPUs
    for row in rows:
        recorder.sizes(row, cache_dir)
    with open(out, "w") as f:
        json.dump({"command": command, "args": args, "exit": status, "serial_compiles": serial,
                   "imports_s": t1 - t0, "imports_cpu_s": c1 - c0,
                   "main_s": t2 - t1, "main_cpu_s": c2 - c1, "cache_dir": cache_dir,
                   "cache_min_compile_time_s": jax.config.jax_persistent_cache_min_compile_time_secs,
                   "programs": rows, "unmatched_events": recorder.unmatched,
                   "versions": {"jax": jax.__version__, "jaxlib": importlib.metadata.version("jaxlib"),
                                "mujoco": importlib.metadata.version("mujoco")},
                   "xla_flags": os.environ.get("XLA_FLAGS", ""), "devices": jax.device_count(),
                   "device": str(jax.devices()[0]),
                   "peak_device_memory_bytes": memory.get("peak_bytes_in_use") if memory else None}, f, indent=1)


def cache_files(cache_dir: str) -> tuple[int, int]:
    """(entries, bytes) of a compilation cache folder."""
    files = [os.path.join(cache_dir, f) for f in os.listdir(cache_dir)] if os.path.isdir(cache_dir) else []
    files = [f for f in files if f.endswith("-cache")]
    return len(files), sum(os.path.getsize(f) for f in files)


def record_command(command: str, args: list[str], out: str, serial: bool = False) -> list[str]:
    """The argv of a fresh Python that runs ``command`` (train / evaluate) with ``args`` under the
    ``CompileRecorder`` and writes its record to ``out`` (``_compile_once``); run it from ``ROOT``."""
    code = f"import experiments.readme_line as m; m._compile_once({command!r}, {args!r}, {out!r}, {serial!r})"
    return [sys.executable, "-c", code]


def _run_recorded(command: str, args: list[str], cache_dir: str, out: str, serial: bool = False) -> dict[str, Any]:
    """``command`` in a fresh process on ``cache_dir``; its record, with the process's wall and CPU seconds."""
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=cache_dir)
    before, load_before, t = resource.getrusage(resource.RUSAGE_CHILDREN), os.getloadavg(), time.perf_counter()
    done = subprocess.run(record_command(command, args, out, serial), cwd=ROOT, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode:
        tail = (done.stdout + done.stderr)[-3000:]
        raise SystemExit(f"{command} {' '.join(args)} failed (exit {done.returncode}):\n{tail}")
    record = json.load(open(out))
    record.update({"process_wall_s": wall, "process_user_s": after.ru_utime - before.ru_utime,
                   "process_sys_s": after.ru_stime - before.ru_stime, "load_before": load_before,
                   "load_after": os.getloadavg(), "output_tail": (done.stdout + done.stderr)[-1500:]})
    return record


def measure_compile(cycles: int, cache: str, evaluate: bool, cache_dir: str | None = None,
                    serial: bool = False) -> dict[str, Any]:
    """The README line's programs on a cold cache and then on the cache that pass filled (``cache``: cold, warm,
    both).  ``cache_dir``: that folder instead of a new empty one (warm: used as it is).  ``serial``: one compile
    at a time (``CompileRecorder``), for each program's own CPU seconds."""
    commands = readme_commands(os.path.join(ROOT, "README.md"))
    tmp = tempfile.mkdtemp(prefix="compile_breakdown_")
    cache_dir = os.path.abspath(cache_dir or os.path.join(tmp, "jax-cache"))
    filled = cache_files(cache_dir)[0] > 0
    passes = {"cold": ["cold"], "both": ["cold", "warm"], "warm": ["warm"] if filled else ["fill", "warm"]}[cache]
    if "cold" in passes and filled:
        raise SystemExit(f"{cache_dir} holds cache entries: a cold pass needs an empty folder")
    out: dict[str, Any] = {"cycles": cycles, "cache_dir": cache_dir, "readme_commands": commands, "serial_compiles": serial,
                           "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                                       "python": platform.python_version(), "nice": os.nice(0)},
                           "passes": {}}
    try:
        for label in passes:
            run = os.path.join(tmp, f"run-{label}")
            train_args = with_option(with_option(with_option(commands["train"], "--out", run), "--stop-after-cycles",
                                                 str(cycles)), "--no-progress")
            steps = [("train", train_args)]
            if evaluate:
                steps.append(("evaluate", with_option(commands["evaluate"], "--run", run)))
            records = {}
            for command, args in steps:
                records[command] = _run_recorded(command, args, cache_dir, os.path.join(tmp, f"{label}-{command}.json"),
                                                 serial)
            metrics = [json.loads(r) for r in open(os.path.join(run, "metrics.jsonl"))]
            records["train"]["trainer_compile"] = {k: metrics[-1].get(k) for k in
                                                   ("compile_s", "compile_iteration_s", "compile_eval_s")}
            records["cache_after"] = dict(zip(("entries", "bytes"), cache_files(cache_dir)))
            out["passes"][label] = records
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def compile_totals(record: dict[str, Any]) -> dict[str, Any]:
    rows = record["programs"]
    total = lambda key: sum(r[key] or 0.0 for r in rows)  # noqa: E731
    return {"programs": len(rows), "hits": sum(r["cache"] == "hit" for r in rows),
            "trace_s": total("trace_wall_s"), "lower_s": total("lower_wall_s"), "compile_s": total("own_compile_s"),
            "compile_cpu_s": total("own_compile_cpu_s"),
            "trace_cpu_s": total("trace_thread_cpu_s"), "lower_cpu_s": total("lower_thread_cpu_s"),
            "process_wall_s": record["process_wall_s"],
            "process_cpu_s": record["process_user_s"] + record["process_sys_s"]}


def spent(row: dict[str, Any]) -> float:
    """A program's trace + lower + compile (or cache load) seconds, wall: what it cost the start-up."""
    return sum(row[k] or 0.0 for k in ("trace_wall_s", "lower_wall_s", "own_compile_s"))


def print_compile(data: dict[str, Any], smallest_s: float = 0.5) -> None:
    """Per pass and command: every program over ``smallest_s`` (trace + lower + compile, wall), the rest summed,
    and the largest programs' HLO by source file.  trace, lower: jax's seconds (wall; the calling thread's CPU
    is in the JSON); compile: the XLA compile or cache load itself (wall, after the ``serial`` lock; jax's own
    duration, lock included, is ``compile_wall_s`` in the JSON) and the process's CPU seconds meanwhile (``*``:
    another compile ran beside it, whose CPU is in both)."""
    f = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    for label, records in data["passes"].items():
        for command in ("train", "evaluate"):
            if command not in records:
                continue
            record = records[command]
            print(f"\n{label} cache, {command} ({record['process_wall_s']:.1f} s wall, "
                  f"{record['process_user_s'] + record['process_sys_s']:.1f} s CPU, load {record['load_before'][0]:.1f} -> "
                  f"{record['load_after'][0]:.1f})")
            print(f"{'program':22s} {'called at':34s} {'trace s':>7s} {'lower s':>7s} {'compile s':>9s} {'(CPU s)':>8s} "
                  f"{'cache':>11s} {'StableHLO':>9s} {'HLO instr':>9s} {'entry kB':>8s}")
            rows = sorted(record["programs"], key=lambda r: -spent(r))
            for r in rows:
                if spent(r) < smallest_s:
                    continue
                kb = "-" if r.get("cache_entry_bytes") is None else f"{r['cache_entry_bytes'] / 1e3:.0f}"
                cpu = f(r["own_compile_cpu_s"]) + ("*" if r["beside"] else " ")
                print(f"{r['program'][:22]:22s} {(r['called_at'] or '-')[:34]:34s} {f(r['trace_wall_s']):>7s} "
                      f"{f(r['lower_wall_s']):>7s} {f(r['own_compile_s']):>9s} {cpu:>8s} {r['cache']:>11s} "
                      f"{r.get('stablehlo_ops', 0):9d} {r.get('hlo_instructions', 0):9d} {kb:>8s}")
            rest = [r for r in rows if spent(r) < smallest_s]
            if rest:
                s = lambda k: sum(r.get(k) or 0.0 for r in rest)  # noqa: E731
                hits = sum(r["cache"] == "hit" for r in rest)
                print(f"{f'{len(rest)} programs under {smallest_s} s':57s} {s('trace_wall_s'):7.2f} "
                      f"{s('lower_wall_s'):7.2f} {s('own_compile_s'):9.2f} {s('own_compile_cpu_s'):7.2f}  {hits:6d} hits "
                      f"{s('stablehlo_ops'):9.0f} {s('hlo_instructions'):9.0f}")
            t = compile_totals(record)
            print(f"{'all ' + str(t['programs']) + ' programs':57s} {t['trace_s']:7.2f} {t['lower_s']:7.2f} "
                  f"{t['compile_s']:9.2f} {'':8s} {t['hits']:6d} hits")
            for r in rows:
                if r.get("hlo_by_source") and r.get("hlo_instructions", 0) >= 5000:
                    top = ", ".join(f"{k} {n}" for k, n in list(r["hlo_by_source"].items())[:6])
                    print(f"  {r['program']} ({r['called_at']}), HLO instructions by file: {top}")


# ---------------------------------------------------------------------------------------------------- options
TRAINER_PROGRAMS = ("init", "reset", "cycle", "eval")  # the README trainer's four programs, in the order it compiles them


def parse_options(items: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` strings as XLA compile options: true / false as booleans, integers as ints, the rest as text."""
    options: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise SystemExit(f"--option {item!r}: expected KEY=VALUE, e.g. xla_backend_optimization_level=1")
        lowered = value.lower()
        options[key] = {"true": True, "false": False}.get(lowered, int(value) if value.lstrip("-").isdigit() else value)
    return options


def measure_options(options: dict[str, Any], programs: list[str]) -> dict[str, Any]:
    """``programs`` of the README trainer compiled under ``options`` in a fresh process on an empty compilation cache."""
    with tempfile.TemporaryDirectory() as tmp:
        return _fresh_process_json(tmp, f"m._options_once({tmp!r}, {options!r}, {programs!r})")


def _fresh_process_json(tmp: str, call: str) -> dict[str, Any]:
    """``call`` (an expression on this module as ``m``) in a fresh Python with its compilation cache in ``tmp``
    (empty: a cold start), its JSON result read from the last line of its output; its stderr tail on failure."""
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=os.path.join(tmp, "cache"))
    code = f"import experiments.readme_line as m, json; print(json.dumps({call}))"
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(done.stderr[-3000:])
    return json.loads(done.stdout.strip().splitlines()[-1])


def _options_once(tmp: str, options: dict[str, Any], programs: list[str]) -> dict[str, Any]:
    """One process: the README preset's trainer built (its own programs as the package compiles them), then each of
    ``programs`` lowered again and compiled under ``options`` with the persistent cache off: the compile's process CPU,
    a second call's CPU, and a digest of its outputs (equal digests: the same numbers as XLA's defaults give)."""
    from sagrasp_jax import train  # first: it sets XLA_FLAGS before jax starts

    import jax
    import numpy as np

    from sagrasp_jax.task.config import get_config
    from sagrasp_jax.training import sharding

    cfg = get_config("cpu-quick")
    train.use_cpu_devices(cfg)
    tr = train.Trainer(cfg, os.path.join(tmp, "run"), progress=False)
    jax.config.update("jax_enable_compilation_cache", False)
    k_params, k_env, _ = jax.random.split(jax.random.PRNGKey(cfg.train.seed), 3)
    ts = tr.seed_group.train_state_of(0)
    calls = {"init": (tr._init_state, (k_params,)),
             "reset": (tr._reset, (sharding.shard_batch(jax.random.split(k_env, cfg.ppo.num_envs), tr.mesh),)),
             "cycle": (tr._cycle, tr._cycle_args([tr.schedule.iterations_per_cycle])),
             "eval": (tr._evaluate, (ts.params, ts.normaliser, tr.eval_keys))}
    rows = {}
    for name in programs:
        fn, args = calls[name]
        lowered = fn.lower(*args)
        c = time.process_time()
        # with no option, XLA's default spelled out: jax would otherwise hand back the trainer's own compile
        compiled = lowered.compile(compiler_options=options or {"xla_cpu_enable_fast_math": False})
        compile_cpu = time.process_time() - c
        jax.block_until_ready(compiled(*args))
        c = time.process_time()
        out = jax.block_until_ready(compiled(*args))
        run_cpu = time.process_time() - c
        leaves = jax.tree_util.tree_leaves(jax.device_get(out))
        rows[name] = {"compile_cpu_s": compile_cpu, "run_cpu_s": run_cpu,
                      "digest": hashlib.sha256(b"".join(np.asarray(x).tobytes() for x in leaves)).hexdigest()[:16]}
    return {"options": {k: str(v) for k, v in options.items()}, "programs": rows, "load": os.getloadavg(),
            "xla_flags": os.environ.get("XLA_FLAGS", "")}


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
    d = sub.add_parser("compile", help="every program the README line compiles, cold cache and warm, in fresh processes")
    d.add_argument("--cycles", type=int, default=2, help="training cycles (--stop-after-cycles)")
    d.add_argument("--cache", choices=("cold", "warm", "both"), default="both")
    d.add_argument("--cache-dir", default=None, help="this compilation cache folder (default: a new empty one)")
    d.add_argument("--no-eval", action="store_true", help="without the evaluation command")
    d.add_argument("--serial-compiles", action="store_true",
                   help="one XLA compile at a time (the trainer's two then run one after the other): each one's CPU alone")
    e = sub.add_parser("options", help="the README trainer's programs compiled under XLA options: CPU seconds, digests")
    e.add_argument("--option", action="append", default=[], help="KEY=VALUE, an XLA compile option (repeatable)")
    e.add_argument("--programs", default=",".join(TRAINER_PROGRAMS), help="comma-separated, of " + ", ".join(TRAINER_PROGRAMS))
    for q in (a, b, c, d, e):
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
    elif args.mode == "options":
        programs = args.programs.split(",")
        unknown = [p for p in programs if p not in TRAINER_PROGRAMS]
        if unknown:
            raise SystemExit(f"--programs: unknown {unknown}; choose from {', '.join(TRAINER_PROGRAMS)}")
        data = measure_options(parse_options(args.option), programs)
        print(f"options {data['options'] or 'none (defaults)'}, load {data['load'][0]:.1f}")
        print(f"{'program':8s} {'compile CPU s':>14s} {'run CPU s':>10s}  digest")
        for name, r in data["programs"].items():
            print(f"{name:8s} {r['compile_cpu_s']:14.2f} {r['run_cpu_s']:10.3f}  {r['digest']}")
    elif args.mode == "compile":
        data = measure_compile(args.cycles, args.cache, not args.no_eval, args.cache_dir, args.serial_compiles)
        print_compile(data)
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
