"""One study driver: variants × seeds × evaluations, run / resume / skip, summaries with 95 % CIs and
paired tests across seeds, JSON.

A study is a table of variants, each a name and the ``--set`` config overrides that make it (as
MuJoCo Playground's ``manipulation_params.py`` is a table of hyper-parameters); ``obstacle_ablation``,
``compare_schedules`` and ``reproduce_paper`` are such tables over this module.  Run them from the
repository root as ``python -m experiments.NAME`` (``experiments`` is a package: no ``sys.path`` edits).

* **Training.** Each variant's seeds go to ``<runs-dir>/<variant>/seed<S>/``, the layout of
  ``python -m sagrasp_jax.train --seeds``; ``train_variant`` trains one variant's seeds (in process,
  ``train.run``, one seed after another: the one place that a multi-seed program replaces).
* **The folder rule.** Every run folder is checked before anything is trained: one trained with
  another config is refused; a finished one is skipped; one stopped before it finished (killed, out
  of time) continues only with ``--resume`` (from its checkpoint, or from the beginning when it
  stopped before its first one), and without ``--resume`` the study stops with exit 2, untouched.
* **Screens.** ``--screen-steps N`` trains each run only to the SA cycle that holds N env steps of
  its full ``--total-steps`` schedule (the lr decays as they would in the full run, which a shorter
  budget would not give), checkpointed there, and evaluates nothing (``screen_study``); the same
  study without it and with ``--resume`` continues every run to the end, a seed group as one group.
* **Evaluations.** A study's ``measure(folder, variant, seed)`` returns the run's record; ``Evaluation``
  plays fixed-seed episodes through ``evaluation.evaluate_run`` in the run's env or in a named
  ``config.EVAL_CONDITIONS`` condition (what ``python -m sagrasp_jax.evaluate --condition NAME`` plays),
  and ``--condition NAME`` adds such an evaluation to every study.  The record is saved in the run
  folder and re-used while its identity (episode counts, conditions) is unchanged.
* **Summaries** (``sagrasp_jax.training.stats``, SciPy's distributions): ``mean_ci`` (mean, 95 % Student-t interval
  across seeds), ``paired`` (paired t-test against a reference variant, seed by seed), curve bands.
* **JSON** through ``sagrasp_jax.base.fileio`` (``write_json``: atomic, sorted keys, no NaN).
* **A trainer in a subprocess** (``watch_trainer``): the benchmarks' way to run ``python -m sagrasp_jax.train``,
  read its metrics.jsonl as it goes and stop it by their own rule (``bench_train``, ``bench_vs_paper_stack``,
  ``gpu_check``).  Shared helpers live here or in ``bench_env``, below the scripts that use them: no script
  imports one that imports it back.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import argparse
import bisect
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

from sagrasp_jax import train
from sagrasp_jax.training import evaluation
from sagrasp_jax.base import fileio
from sagrasp_jax.training import run_dir
from sagrasp_jax.training.checkpoint import CheckpointError
from sagrasp_jax.task.config import EVAL_CONDITIONS, Config, ConfigError, config_to_dict, get_config
from sagrasp_jax.task.config_parse import config_from_dict
from sagrasp_jax.training.run_dir import RunDirError

SEED_FOLDER = "seed{seed}"  # a seed's run folder inside its variant's, as `sagrasp_jax.train --seeds` names it
Variants = Mapping[str, Sequence[str]]  # variant name -> its config overrides (`--set` strings)
Measure = Callable[[str, str, int], dict[str, Any]]  # (run folder, variant, seed) -> the run's record fields


class StudyError(RuntimeError):
    """A run folder or an argument that the study cannot use."""


ERRORS = (StudyError, ConfigError, CheckpointError, RunDirError)  # what a study reports as a message and exit 2


# ---------------------------------------------------------------------- the study's settings

@dataclass(frozen=True)
class Study:
    """Where and how every run of a study trains: preset, step budget, seeds, extra overrides."""
    preset: str
    total_steps: int
    seeds: tuple[int, ...]
    runs_dir: str
    overrides: tuple[str, ...] = ()
    resume: bool = False
    progress: bool = True
    group: bool = True  # a variant's new seeds train as one seed group (train.run(seeds=...)); False: one by one
    screen_steps: int | None = None  # train each run only this far under its full budget's schedule (screen_study)

    def folder(self, variant: str, seed: int) -> str:
        return os.path.join(self.runs_dir, variant, SEED_FOLDER.format(seed=seed))

    def config(self, sets: Sequence[str], seed: int) -> Config:
        return train.build_config(self.preset, None, seed, self.total_steps, [*sets, *self.overrides])

    def stop_after_cycles(self, cfg: Config) -> int | None:
        """The cycles of ``cfg``'s schedule that hold ``screen_steps`` env steps (None: train to the end)."""
        if self.screen_steps is None:
            return None
        sched = train.make_schedule(cfg)
        ends = [end * sched.steps_per_iteration for end in sched.cycle_ends]
        return min(bisect.bisect_left(ends, self.screen_steps) + 1, sched.num_cycles)

    def screen_horizon(self, cfg: Config) -> int:
        """The env steps a screened run of ``cfg`` has trained: the end of the cycle that holds the screen."""
        sched = train.make_schedule(cfg)
        return sched.cycle_ends[(self.stop_after_cycles(cfg) or sched.num_cycles) - 1] * sched.steps_per_iteration


def parse_seeds(text: str) -> tuple[int, ...]:
    """``K`` (seeds 0 … K−1), ``A-B`` (A … B) or a comma list ``1,3``."""
    try:
        if "," in text:
            seeds = tuple(int(s) for s in text.split(",") if s.strip())
        elif "-" in text.strip()[1:]:
            first, last = text.split("-", 1)
            seeds = tuple(range(int(first), int(last) + 1))
        else:
            seeds = tuple(range(int(text)))
    except ValueError:
        raise StudyError(f"--seeds {text!r}: give a count K, a range A-B or a list A,B,...") from None
    if not seeds or min(seeds) < 0 or len(set(seeds)) != len(seeds):
        raise StudyError(f"--seeds {text!r}: at least one seed, none negative, none twice")
    return seeds


def pick_variants(table: Variants, chosen: str | None, default: Sequence[str]) -> dict[str, tuple[str, ...]]:
    """The variants named in the comma list ``chosen`` (else ``default``), unknown names refused."""
    names = [v.strip() for v in chosen.split(",") if v.strip()] if chosen else list(default)
    unknown = [v for v in names if v not in table]
    if unknown or not names:
        raise StudyError(f"unknown variant(s) {', '.join(unknown) or '(none given)'}; valid: {', '.join(table)}")
    return {v: tuple(table[v]) for v in names}


def add_arguments(p: argparse.ArgumentParser, seeds: int, runs_dir: str | None, variants: bool = True) -> None:
    """The options every study shares (``--variants`` where the study lets the user choose them)."""
    p.add_argument("--preset", default="cpu-quick", help="trainer preset (cpu-quick, gpu, paper)")
    p.add_argument("--total-steps", type=int, default=None, help="env steps per run (default: the preset's)")
    p.add_argument("--seeds", default=str(seeds), help=f"K (seeds 0..K-1), A-B or A,B,... (default {seeds})")
    if variants:
        p.add_argument("--variants", default=None, help="comma list of variants (default: the study's)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="extra config override for every run, repeatable")
    p.add_argument("--condition", dest="conditions", action="append", default=[], choices=sorted(EVAL_CONDITIONS),
                   help="also evaluate every run in this named condition (config.EVAL_CONDITIONS), repeatable")
    p.add_argument("--runs-dir", default=runs_dir, help="run folders: RUNS_DIR/<variant>/seed<S>/"
                   + (f" (default {runs_dir})" if runs_dir else ""))
    p.add_argument("--resume", action="store_true",
                   help="continue run folders that stopped before they finished (without it they are refused)")
    p.add_argument("--no-progress", action="store_true", help="no live training progress bar")
    p.add_argument("--screen-steps", type=int, default=None, metavar="N",
                   help="a screen: train each run only to N env steps under its full --total-steps schedule "
                        "(checkpointed: the same command without it, with --resume, continues to the end) and "
                        "report the time to each success level within them; no final evaluation")
    p.add_argument("--one-by-one", action="store_true",
                   help="train a variant's seeds one after another instead of as one seed group (one program)")


def study_from_args(args: argparse.Namespace) -> Study:
    """The Study of parsed ``add_arguments`` options (bad values raise StudyError / ConfigError)."""
    total = args.total_steps if args.total_steps is not None else get_config(args.preset).train.total_steps
    if total < 1:
        raise StudyError("--total-steps must be >= 1")
    screen = getattr(args, "screen_steps", None)
    if screen is not None and not 1 <= screen < total:
        raise StudyError(f"--screen-steps {screen}: give 1 <= N < the budget ({total:,} env steps)")
    return Study(args.preset, total, parse_seeds(args.seeds), args.runs_dir, tuple(args.overrides), args.resume,
                 not args.no_progress, not getattr(args, "one_by_one", False), screen)


# ---------------------------------------------------------------------- one run folder

def run_state(out: str) -> str:
    """'new' | 'trained' (a final policy) | 'partial' (a checkpoint, not finished) | 'stale' (neither)."""
    if not os.path.isdir(out) or not os.listdir(out):
        return "new"
    if os.path.isfile(os.path.join(out, run_dir.POLICY_FILE)):
        return "trained"
    if os.path.isfile(os.path.join(out, run_dir.CHECKPOINT_FILE)):
        return "partial"
    return "stale"


def _dict_diff(a: Any, b: Any, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out: list[str] = []
        for k in sorted(set(a) | set(b)):
            out += _dict_diff(a.get(k), b.get(k), f"{prefix}{k}.")
        return out
    return [] if a == b else [f"{prefix[:-1]}: {a!r} != {b!r}"]


def check_same_config(out: str, cfg: Config) -> None:
    """Refuse to reuse a run folder trained with another config."""
    path = os.path.join(out, run_dir.CONFIG_FILE)
    try:
        with open(path, encoding="utf-8") as f:
            saved = json.load(f)
    except (FileNotFoundError, json.JSONDecodeError) as exc:
        raise StudyError(f"{path}: unreadable run config ({exc}); delete {out} to retrain it") from None
    want = json.loads(json.dumps(config_to_dict(cfg)))
    try:  # a config saved before a key was added or renamed means what config_from_dict makes of it
        saved = json.loads(json.dumps(config_to_dict(config_from_dict(saved))))
    except (ConfigError, TypeError, ValueError):
        pass  # compared as written (and refused below)
    if saved != want:
        diffs = _dict_diff(saved, want)
        raise StudyError(f"{out} was trained with another config ({'; '.join(diffs[:5])}); "
                         f"use another --runs-dir or delete the folder")


def check_run(out: str, cfg: Config, resume: bool) -> str:
    """The folder's ``run_state`` once it passed the folder rule: another config is refused (before
    anything is deleted), an unfinished run without ``resume`` too."""
    state = run_state(out)
    config_written = os.path.isfile(os.path.join(out, run_dir.CONFIG_FILE))
    if state != "new" and (state != "stale" or config_written):  # killed before its config: nothing to compare
        check_same_config(out, cfg)
    if state in ("partial", "stale") and not resume:
        raise StudyError(f"{out} holds a run that stopped before it finished; pass --resume to continue it "
                         "(or delete the folder)")
    return state


def trained_steps(out: str) -> int:
    """Env steps a run folder's metrics.jsonl has reached (0: none logged)."""
    try:
        rows = run_dir.read_metrics(os.path.join(out, run_dir.METRICS_FILE))
    except (OSError, ValueError):
        return 0
    return max((int(r["env_steps"]) for r in rows if "env_steps" in r), default=0)


def ensure_trained(out: str, cfg: Config, tag: str, progress: bool, resume: bool,
                   stop_after_cycles: int | None = None) -> float | None:
    """Bring the run folder ``out`` to a finished training of ``cfg`` (``train.run``, in process) under
    the folder rule (``check_run``): a finished one is skipped, one with a checkpoint resumed, one
    stopped before its first checkpoint started again.  Returns this call's training wall time
    (None: it was finished already)."""
    state = check_run(out, cfg, resume)
    if state == "trained":
        return None
    if state == "stale":
        print(f"{tag}: {out} has no checkpoint (stopped before the first one): starting it again", flush=True)
        shutil.rmtree(out)
    print(f"{tag}: {'resuming' if state == 'partial' else 'training'} {cfg.train.total_steps:,} env steps -> {out}",
          flush=True)
    t = time.perf_counter()
    train.run(cfg, out, resume=state == "partial", progress=progress, stop_after_cycles=stop_after_cycles)
    wall = time.perf_counter() - t
    print(f"{tag}: trained in {wall:.0f} s", flush=True)
    return wall


def train_variant(study: Study, variant: str, configs: Mapping[int, Config]) -> dict[int, float | None]:
    """Train one variant's seeds (``configs``: seed -> config, differing only in ``train.seed``) into
    ``study.folder(variant, seed)``; returns each seed's training wall time of this call (a group's wall
    time is given to each of its seeds).  When every folder is new and there are several seeds (and
    ``study.group``), they train as one seed group, one compiled program (``train.run(seeds=…)``, what
    ``python -m sagrasp_jax.train --seeds`` runs; equal to separate runs within the tolerance
    docs/design.md "Seed groups" states, not bit for bit); otherwise one after another under the folder
    rule (``ensure_trained``)."""
    seeds = list(configs)
    variant_dir = os.path.dirname(study.folder(variant, seeds[0])) if seeds else ""
    states = {run_state(study.folder(variant, s)) for s in seeds}
    fresh = states == {"new"}
    others = os.path.isdir(variant_dir) and set(os.listdir(variant_dir)) - {SEED_FOLDER.format(seed=s) for s in seeds}
    stop = study.stop_after_cycles(configs[seeds[0]]) if seeds else None
    if study.group and len(seeds) > 1 and states == {"partial"} and study.resume and not others:
        # a group stopped part way (a screen, a kill after a checkpoint) continues as the group it was
        for s in seeds:
            check_run(study.folder(variant, s), configs[s], True)
        print(f"{variant}: resuming seeds {', '.join(map(str, seeds))} as one group -> {variant_dir}", flush=True)
        t = time.perf_counter()
        train.run(configs[seeds[0]], variant_dir, resume=True, progress=study.progress, seeds=seeds,
                  stop_after_cycles=stop)
        wall = time.perf_counter() - t
        print(f"{variant}: group trained in {wall:.0f} s", flush=True)
        return {s: wall for s in seeds}
    if study.group and len(seeds) > 1 and fresh and not others:
        for s in seeds:  # an empty seed folder left by an earlier check would make the group refuse its folder
            folder = study.folder(variant, s)
            if os.path.isdir(folder) and not os.listdir(folder):
                os.rmdir(folder)
        group_cfg = configs[seeds[0]]
        print(f"{variant}: training seeds {', '.join(map(str, seeds))} as one group, "
              f"{group_cfg.train.total_steps:,} env steps each -> {variant_dir}", flush=True)
        t = time.perf_counter()
        train.run(group_cfg, variant_dir, progress=study.progress, seeds=seeds, stop_after_cycles=stop)
        wall = time.perf_counter() - t
        print(f"{variant}: group trained in {wall:.0f} s", flush=True)
        return {s: wall for s in seeds}
    return {seed: ensure_trained(study.folder(variant, seed), cfg, f"{variant} seed {seed}", study.progress,
                                 study.resume, stop) for seed, cfg in configs.items()}


def screen_study(study: Study, variants: Variants) -> dict[str, dict[int, str]]:
    """A screen (``study.screen_steps``): every run trained to at least that many env steps under its full
    budget's schedule, checkpointed there, and nothing evaluated.  The folder rule holds (another config is
    refused; a run screened that far or finished is not trained again; one short of it continues only with
    ``--resume``, or when it has no checkpoint yet).  Returns variant -> seed -> run folder."""
    assert study.screen_steps is not None
    todo: dict[str, dict[int, Config]] = {}
    for variant, sets in variants.items():
        for seed in study.seeds:
            out, cfg = study.folder(variant, seed), study.config(sets, seed)
            state = check_run(out, cfg, True)
            short = state in ("partial", "stale") and trained_steps(out) < study.screen_steps
            if state == "partial" and short and not study.resume:
                raise StudyError(f"{out} stopped at {trained_steps(out):,} env steps, before the screen's "
                                 f"{study.screen_steps:,}; pass --resume to continue it")
            if state == "new" or short:
                todo.setdefault(variant, {})[seed] = cfg
    for variant, configs in todo.items():
        train_variant(study, variant, configs)
    return {variant: {seed: study.folder(variant, seed) for seed in study.seeds} for variant in variants}


# ---------------------------------------------------------------------- evaluations and records

@dataclass(frozen=True)
class Evaluation:
    """``episodes`` fixed-seed held-out episodes (deterministic policy, reward weights at p = 1) of a
    scene set, in the run's env or in the named ``config.EVAL_CONDITIONS`` condition."""
    episodes: int
    scenes: str = "mix"
    condition: str | None = None

    def __post_init__(self) -> None:
        if self.condition is not None and self.condition not in EVAL_CONDITIONS:
            raise ConfigError(f"unknown evaluation condition {self.condition!r}; valid: {', '.join(EVAL_CONDITIONS)}")
        if self.episodes < 1:
            raise StudyError("evaluation episodes must be >= 1")

    def __call__(self, folder: str) -> dict[str, Any]:
        overrides = list(EVAL_CONDITIONS[self.condition]) if self.condition else None
        return evaluation.evaluate_run(folder, self.episodes, scenes=self.scenes, overrides=overrides)


def current_record(out: str, record_file: str, identity: Mapping[str, Any]) -> dict[str, Any] | None:
    """The run's saved record if it was made with ``identity`` (the same episode counts), else None."""
    path = os.path.join(out, record_file)
    try:
        with open(path, encoding="utf-8") as f:
            done = json.load(f)
    except (FileNotFoundError, json.JSONDecodeError):
        return None
    return done if isinstance(done, dict) and all(done.get(k) == v for k, v in identity.items()) else None


def run_study(study: Study, variants: Variants, measure: Measure, identity: Mapping[str, Any], record_file: str,
              conditions: Sequence[str] = (), episodes: int = 1000, train_missing: bool = True
              ) -> dict[str, list[dict[str, Any]]]:
    """Every variant × seed brought to a saved record: check every folder first (nothing is trained
    while one is refused), then per variant train the seeds that need it (``train_variant``) and
    evaluate the ones without a current record (``measure``, and ``episodes`` in each of
    ``conditions``).  ``train_missing=False`` only collects records (a missing one is refused).
    Returns variant -> records in seed order."""
    identity = {**identity, **({"condition_episodes": {c: episodes for c in conditions}} if conditions else {})}
    plan: dict[tuple[str, int], str] = {}
    for variant, sets in variants.items():
        for seed in study.seeds:
            out, cfg = study.folder(variant, seed), study.config(sets, seed)
            if current_record(out, record_file, identity) is not None:
                check_same_config(out, cfg)
                plan[variant, seed] = "recorded"
            elif not train_missing:
                raise StudyError(f"{out} has no current {record_file}; run the study without --plots-only first")
            else:
                plan[variant, seed] = check_run(out, cfg, study.resume)
    records: dict[str, list[dict[str, Any]]] = {v: [] for v in variants}
    count = len(plan)
    for variant, sets in variants.items():
        todo = {s: study.config(sets, s) for s in study.seeds if plan[variant, s] not in ("recorded", "trained")}
        walls = train_variant(study, variant, todo) if todo else {}
        for seed in study.seeds:
            out = study.folder(variant, seed)
            tag = f"[{list(plan).index((variant, seed)) + 1}/{count}] {variant} seed {seed}"
            if plan[variant, seed] == "recorded":
                print(f"{tag}: done already, skipped", flush=True)
                records[variant].append(current_record(out, record_file, identity))
                continue
            print(f"{tag}: evaluating", flush=True)
            record = {"variant": variant, "overrides": list(sets), "seed": seed, **identity,
                      **measure(out, variant, seed), "train_wall_s": walls.get(seed)}
            if conditions:
                record["conditions"] = {c: Evaluation(episodes, condition=c)(out) for c in conditions}
            write_json(os.path.join(out, record_file), record)
            records[variant].append(record)
    return records


def condition_rates(record: dict[str, Any]) -> dict[str, float | None]:
    """Success % of each ``--condition`` evaluation of a record, as per-seed metrics."""
    return {f"success_condition_{name}": rate(res["overall"]) for name, res in record.get("conditions", {}).items()}


def kind_rates(record: dict[str, Any]) -> dict[str, float | None]:
    """What a study judges a run by, from its record's evaluation mix (``mix``) and blocking-only scenes
    (``blocking_scenes``, None when not played): success % per episode kind and steps per success."""
    mix, blocking = record["mix"], record.get("blocking_scenes")
    return {
        "success_overall": rate(mix["overall"]),
        "success_no_obstacle": rate(mix["obstacle_absent"]),
        "success_obstacle": rate(mix["obstacle_present"]),
        "success_blocking_in_mix": rate(mix["blocking"]),
        "success_blocking_scenes": None if blocking is None else rate(blocking["blocking"]),
        "steps_per_success": mix["overall"].get("mean_steps_per_success"),
    }


def rate(group: dict[str, Any], key: str = "success_rate") -> float | None:
    """A group's rate in %, None when the group had no episodes."""
    return None if not group.get("episodes") else 100.0 * group[key]


# ---------------------------------------------------------------------- curves

def load_curves(study: Study, variant: str) -> list[list[dict[str, Any]]]:
    """metrics.jsonl rows of each seed's run of ``variant``."""
    return [run_dir.read_metrics(os.path.join(study.folder(variant, s), run_dir.METRICS_FILE)) for s in study.seeds]


# ---------------------------------------------------------------------- a trainer in a subprocess

def watch_trainer(cmd: list[str], cwd: str, log_path: str, metrics_path: str, poll_s: float,
                  stop_reason: Callable[[list[dict[str, Any]], float], str | None],
                  env: dict[str, str] | None = None, on_poll: Callable[[int], None] | None = None,
                  grace_s: float = 120.0) -> tuple[list[dict[str, Any]], str | None, int | None, float]:
    """Run a trainer command (output to ``log_path``), reading its ``metrics.jsonl`` every ``poll_s``
    seconds; ``stop_reason(rows, seconds since launch)`` returning a reason SIGTERMs it (it
    checkpoints and exits), and one still running ``grace_s`` later is killed (a caller under a deadline
    cannot wait long).  ``on_poll(pid)`` samples the process (e.g. its memory).  Returns the final metric
    rows, the stop reason (None: it exited by itself), its exit code (negative: the signal that ended it)
    and the wall time."""
    stopped: str | None = None
    t0 = time.perf_counter()
    with open(log_path, "w", encoding="utf-8") as log:
        proc = subprocess.Popen(cmd, cwd=cwd, stdout=log, stderr=subprocess.STDOUT, env=env)
        try:
            while proc.poll() is None:
                time.sleep(poll_s)
                if on_poll is not None:
                    on_poll(proc.pid)
                rows = run_dir.read_metrics(metrics_path) if os.path.exists(metrics_path) else []
                stopped = stop_reason(rows, time.perf_counter() - t0)
                if stopped:
                    proc.send_signal(signal.SIGTERM)
                    break
            try:
                proc.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    rows = run_dir.read_metrics(metrics_path) if os.path.exists(metrics_path) else []
    return rows, stopped, proc.returncode, time.perf_counter() - t0


# ---------------------------------------------------------------------- output

def write_json(path: str, data: Any) -> str:
    """Atomic JSON write through ``fileio`` (sorted keys, no NaN), its folder made if missing."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    return fileio.atomic_write_json(path, data, sort_keys=True)


def report(path: str, result: Any, table: str, extra: Sequence[str] = ()) -> int:
    """The end of every study: the JSON written, its table printed, where it went said; exit status 0."""
    write_json(path, result)
    print(table)
    print(f"written to {path}" + "".join(f", {p}" for p in extra))
    return 0


def git_state() -> str:
    """``<commit>`` of the checkout, ``+dirty`` when tracked files are modified (or 'unknown')."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def machine() -> str:
    return f"{platform.machine()}, {os.cpu_count()} CPU cores"


def command(module: str, argv: Sequence[str] | None) -> str:
    """The command line that ran a study, for its JSON."""
    return f"python -m experiments.{module} " + " ".join(sys.argv[1:] if argv is None else argv)
