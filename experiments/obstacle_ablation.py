"""Which lever wins the obstacle episodes?  Train each lever alone and the combination, K seeds each.

Levers (obstacle issue; docs/task.md §2 "Layouts" and "Near-miss term"), each a config switch:

* ``layout``    env.task.obs_layout: paper (17 numbers, sentinel when absent) → relative
                (presence, gripper/robot → obstacle vectors, closeness; hand-scaled);
* ``near_miss`` env.reward.near_miss_mode: per_step (the paper's) → change (a potential);
* ``geometry``  env.task.obstacle_geometry: cover (conservative, up to 2.5 cm off) → fine (±4 mm);
* ``mix``       training scenes: the evaluation mix (0.2 obstacle, disc placement) → obstacle_prob
                0.8 with 60 % of obstacle scenes placed on the approach path (train.obstacle_prob,
                train.blocking_prob); evaluation always uses the evaluation mix;
* ``critic``    ppo.privileged_critic: off → on (the value net also reads progress, time left and
                every obstacle's kind, size and position).

Variants: ``base`` (all off = the first landing, with the calibrated SA tolerance), each lever
alone, ``all`` (= the cpu-quick preset), and with
``--leave-one-out`` each lever removed from ``all``.  Every run trains ``--total-steps`` env steps
of ``--preset`` (in process, ``train.run``), then is evaluated on ``--eval-episodes`` fixed-seed
episodes of the evaluation mix and of blocking-only scenes (``evaluate.evaluate_run``), and its
exported policy is played seeing vs blind on ``--blind-episodes`` obstacle and blocking episodes
(``obstacle_blind_eval.blind_study``).  Re-running skips finished runs.  Prints a table and writes
JSON with per-seed numbers, means and 95 % t-intervals across seeds.

    python experiments/obstacle_ablation.py --seeds 3 \\
        --runs-dir runs/obstacle_ablation --out experiments/results/obstacle_ablation_cpu.json
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import argparse
import json
import os
import platform
import sys
from typing import Any, Sequence

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from obstacle_blind_eval import blind_study  # noqa: E402
from reproduce_paper import check_same_config, ensure_trained, git_state, mean_ci, write_json  # noqa: E402

from sagrasp_jax import evaluate, run_dir, runtime, train  # noqa: E402
from sagrasp_jax.checkpoint import CheckpointError  # noqa: E402
from sagrasp_jax.config import ConfigError  # noqa: E402

LEVERS: dict[str, tuple[list[str], list[str]]] = {  # name -> (off, on) overrides
    "layout": (["env.task.obs_layout=paper"], ["env.task.obs_layout=relative"]),
    "near_miss": (["env.reward.near_miss_mode=per_step"], ["env.reward.near_miss_mode=change"]),
    "geometry": (["env.task.obstacle_geometry=cover"], ["env.task.obstacle_geometry=fine"]),
    "mix": (["train.obstacle_prob=none", "train.blocking_prob=none"], ["train.obstacle_prob=0.8", "train.blocking_prob=0.6"]),
    "critic": (["ppo.privileged_critic=false"], ["ppo.privileged_critic=true"]),
}
RESULT_FILE = "ablation_eval.json"
LEARNED = 50.0  # % overall success: below it a run never learned to grasp (hovering near the cube, timeouts)
LEARNED_KEYS = ("success_overall", "success_obstacle", "success_blocking_scenes", "steps_per_success")  # their means


def variants(leave_one_out: bool) -> dict[str, set[str]]:
    """Variant name -> the levers switched on."""
    out = {"base": set()} | {f"+{lever}": {lever} for lever in LEVERS} | {"all": set(LEVERS)}
    if leave_one_out:
        out |= {f"all-{lever}": set(LEVERS) - {lever} for lever in LEVERS}
    return out


def overrides_for(on: set[str]) -> list[str]:
    return [item for lever, (off, on_sets) in LEVERS.items() for item in (on_sets if lever in on else off)]


def finished_record(out: str, cfg: Any, result_file: str, wanted: dict[str, Any], tag: str) -> dict[str, Any] | None:
    """The run's saved result record if it exists and was made with ``wanted`` (e.g. the same episode
    counts) by a run of ``cfg`` (another config is refused), else None."""
    result_path = os.path.join(out, result_file)
    if not os.path.isfile(result_path):
        return None
    check_same_config(out, cfg)
    with open(result_path, encoding="utf-8") as f:
        done = json.load(f)
    if all(done.get(k) == v for k, v in wanted.items()):
        print(f"{tag}: done already, skipped", flush=True)
        return done
    return None


def run_one(name: str, on: set[str], seed: int, args: argparse.Namespace, tag: str) -> dict[str, Any]:
    """Train (or resume / skip) one run and evaluate it; returns its result record."""
    out = os.path.join(args.runs_dir, f"{name}-s{seed}")
    cfg = train.build_config(args.preset, args.algo, seed, args.total_steps, overrides_for(on) + args.overrides)
    result_path = os.path.join(out, RESULT_FILE)
    done = finished_record(out, cfg, RESULT_FILE, {"eval_episodes": args.eval_episodes,
                                                   "blind_episodes": args.blind_episodes}, tag)
    if done is not None:
        return done
    wall = ensure_trained(out, cfg, tag, not args.no_progress)
    print(f"{tag}: evaluating", flush=True)
    mix = evaluate.evaluate_run(out, args.eval_episodes)
    blocking = evaluate.evaluate_run(out, args.eval_episodes, scenes="blocking")
    blind = blind_study(runtime.load_policy(os.path.join(out, run_dir.POLICY_FILE)), args.blind_episodes, seed=5)
    with open(os.path.join(out, run_dir.METRICS_FILE), encoding="utf-8") as f:
        last = [json.loads(line) for line in f if line.strip()][-1]
    record = {
        "variant": name, "levers": sorted(on), "seed": seed, "eval_episodes": args.eval_episodes,
        "blind_episodes": args.blind_episodes, "mix": mix, "blocking_scenes": blocking, "blind": blind,
        "train_wall_s": wall, "train_time_s": last.get("time_s"), "compile_s": last.get("compile_s"),
        "env_steps": last.get("env_steps"),
    }
    write_json(result_path, record)
    ov, ob, bl = mix["overall"], mix["obstacle_present"], blocking["blocking"]
    print(f"{tag}: success {100 * ov['success_rate']:.1f} % (obstacle {100 * ob['success_rate']:.1f} %, "
          f"blocking scenes {100 * bl['success_rate']:.1f} %)", flush=True)
    return record


def _rate(group: dict[str, Any], key: str = "success_rate") -> float | None:
    return None if not group.get("episodes") else 100.0 * group[key]


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Means and 95 % t-intervals across seeds of what the obstacle issue is judged by."""
    metrics = {
        "success_overall": [_rate(r["mix"]["overall"]) for r in records],
        "success_obstacle": [_rate(r["mix"]["obstacle_present"]) for r in records],
        "success_blocking_in_mix": [_rate(r["mix"]["blocking"]) for r in records],
        "success_blocking_scenes": [_rate(r["blocking_scenes"]["blocking"]) for r in records],
        "success_no_obstacle": [_rate(r["mix"]["obstacle_absent"]) for r in records],
        "steps_per_success": [r["mix"]["overall"]["mean_steps_per_success"] for r in records],
        "collision_obstacle_episodes": [_rate(r["mix"]["obstacle_present"], "collision_rate") for r in records],
        "seeing_minus_blind_obstacle": [100.0 * r["blind"]["obstacle"]["seeing_minus_blind"] for r in records],
        "seeing_minus_blind_blocking": [100.0 * r["blind"]["blocking"]["seeing_minus_blind"] for r in records],
        "train_time_s": [r.get("train_time_s") for r in records],
    }
    out = {k: mean_ci([v for v in vals if v is not None]) for k, vals in metrics.items()}
    hits: dict[str, list[float]] = {}
    for r in records:
        for kind, rate in r["mix"]["obstacle_present"].get("collision_by", {}).items():
            hits.setdefault(kind, []).append(100.0 * rate)
    out["collision_by_in_obstacle_episodes"] = {k: mean_ci(v) for k, v in hits.items()}
    out["per_seed"] = [{"seed": r["seed"], **{k: v[i] for k, v in metrics.items()}} for i, r in enumerate(records)]
    # a run that never learned to grasp drags every mean down; say how many did, and how the others fared
    learned = [i for i, v in enumerate(metrics["success_overall"]) if v is not None and v >= LEARNED]
    out["runs_learned"] = {"learned": len(learned), "runs": len(records), "threshold_pct": LEARNED}
    out["learned_only"] = {k: mean_ci([metrics[k][i] for i in learned]) for k in LEARNED_KEYS}
    return out


def _cell(stat: dict[str, Any], digits: int = 1) -> str:
    if stat["mean"] is None:
        return "-"
    lo, hi = stat["ci95"]
    return f"{stat['mean']:.{digits}f}" + ("" if lo is None else f" [{lo:.{digits}f}, {hi:.{digits}f}]")


def markdown(summary: dict[str, dict[str, Any]]) -> str:
    cols = [("success_overall", "overall %"), ("success_obstacle", "obstacle %"),
            ("success_blocking_scenes", "blocking scenes %"), ("success_no_obstacle", "no obstacle %"),
            ("steps_per_success", "steps/success"), ("seeing_minus_blind_obstacle", "seeing − blind (obstacle)")]
    lines = ["| variant | " + " | ".join(c[1] for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for name, s in summary.items():
        lines.append(f"| {name} | " + " | ".join(_cell(s[k]) for k, _ in cols) + " |")
    lines += ["", f"Runs that learned to grasp (overall success ≥ {LEARNED:.0f} %), and their means:", "",
              "| variant | learned | overall % | obstacle % | blocking scenes % | steps/success |", "|---" * 6 + "|"]
    for name, s in summary.items():
        lo, n = s["learned_only"], s["runs_learned"]
        lines.append(f"| {name} | {n['learned']} of {n['runs']} | " + " | ".join(_cell(lo[k]) for k in LEARNED_KEYS) + " |")
    hit_kinds = sorted({k for s in summary.values() for k in s["collision_by_in_obstacle_episodes"]})
    lines += ["", "Collisions in obstacle episodes of the evaluation mix, by what was hit (% of those episodes):", "",
              "| variant | " + " | ".join(hit_kinds) + " |", "|---" * (len(hit_kinds) + 1) + "|"]
    for name, s in summary.items():
        by = s["collision_by_in_obstacle_episodes"]
        lines.append(f"| {name} | " + " | ".join(_cell(by[k]) if k in by else "-" for k in hit_kinds) + " |")
    return "\n".join(lines)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python experiments/obstacle_ablation.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="cpu-quick")
    p.add_argument("--algo", default="sa-ppo", choices=train.ALGOS)
    p.add_argument("--total-steps", type=int, default=None, help="env steps per run (default: the preset's)")
    p.add_argument("--seeds", type=int, default=3, help="seeds 0..K-1")
    p.add_argument("--variants", default=None, help="comma list (default: every variant)")
    p.add_argument("--leave-one-out", action="store_true", help="also each lever removed from 'all'")
    p.add_argument("--eval-episodes", type=int, default=1000)
    p.add_argument("--blind-episodes", type=int, default=200)
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="extra config override for every run")
    p.add_argument("--runs-dir", default="runs/obstacle_ablation")
    p.add_argument("--out", default="experiments/results/obstacle_ablation_cpu.json")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    if args.total_steps is None:
        from sagrasp_jax.config import get_config

        args.total_steps = get_config(args.preset).train.total_steps
    if args.seeds < 1 or args.total_steps < 1 or args.eval_episodes < 1 or args.blind_episodes < 1:
        p.error("--seeds, --total-steps, --eval-episodes and --blind-episodes must be >= 1")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    table = variants(args.leave_one_out)
    if args.variants:
        wanted = [v.strip() for v in args.variants.split(",") if v.strip()]
        unknown = [v for v in wanted if v not in variants(True)]
        if unknown:
            print(f"error: unknown variant(s) {', '.join(unknown)}; valid: {', '.join(variants(True))}", file=sys.stderr)
            return 2
        table = {v: variants(True)[v] for v in wanted}
    seeds = list(range(args.seeds))
    jobs = [(name, on, seed) for seed in seeds for name, on in table.items()]  # seed-major: every variant early
    records: dict[str, list[dict[str, Any]]] = {name: [] for name in table}
    try:
        for i, (name, on, seed) in enumerate(jobs, 1):
            records[name].append(run_one(name, on, seed, args, f"[{i}/{len(jobs)}] {name} seed {seed}"))
    except (ConfigError, CheckpointError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    summary = {name: summarise(sorted(recs, key=lambda r: r["seed"])) for name, recs in records.items()}
    result = {
        "preset": args.preset, "algo": args.algo, "total_steps": args.total_steps, "seeds": seeds,
        "eval_episodes": args.eval_episodes, "blind_episodes": args.blind_episodes, "extra_overrides": args.overrides,
        "levers": {k: {"off": v[0], "on": v[1]} for k, v in LEVERS.items()},
        "variants": {name: sorted(on) for name, on in table.items()}, "summary": summary,
        "runs": {name: recs for name, recs in records.items()},
        "git": git_state(), "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores",
    }
    write_json(args.out, result)
    print(markdown(summary))
    print(f"written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
