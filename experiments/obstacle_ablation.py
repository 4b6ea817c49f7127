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

Variants (``VARIANTS``, a table over ``experiments.study``): ``base`` (all off = the first landing,
with the calibrated SA tolerance), each lever alone, ``all`` (= the cpu-quick preset), and with
``--leave-one-out`` each lever removed from ``all``.  Every run trains ``--total-steps`` env steps
of ``--preset`` into ``--runs-dir/<variant>/seed<S>/``, then is evaluated on ``--eval-episodes``
fixed-seed episodes of the evaluation mix and of blocking-only scenes (``evaluation.evaluate_run``),
and its exported policy is played seeing vs blind on ``--blind-episodes`` obstacle and blocking
episodes (``blind_study``, below: every obstacle entry replaced by its "no obstacle" value, ``observation.blind``).  Re-running skips finished runs (``--resume``
continues stopped ones).  Prints a table and writes JSON with per-seed numbers, means and 95 %
t-intervals across seeds, and every variant paired with ``all`` seed by seed.  Run from the
repository root:

    python -m experiments.obstacle_ablation --seeds 3 \\
        --runs-dir runs/obstacle_ablation --out experiments/results/obstacle_ablation_cpu.json
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from typing import Any, Sequence

import numpy as np

import sagrasp_jax  # noqa: F401  (XLA flags before jax)
import jax
import jax.numpy as jnp

from experiments import study
from sagrasp_jax.envs.grasp_env import GraspEnv
from sagrasp_jax.task import observation
from sagrasp_jax.task.config import blocking_sampling
from sagrasp_jax.training import stats
from sagrasp_jax import train
from sagrasp_jax.training import run_dir
from sagrasp_jax.task import policy_file as runtime

LEVERS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {  # name -> (off, on) overrides
    "layout": (("env.task.obs_layout=paper",), ("env.task.obs_layout=relative",)),
    "near_miss": (("env.reward.near_miss_mode=per_step",), ("env.reward.near_miss_mode=change",)),
    "geometry": (("env.task.obstacle_geometry=cover",), ("env.task.obstacle_geometry=fine",)),
    "mix": (("train.obstacle_prob=none", "train.blocking_prob=none"), ("train.obstacle_prob=0.8", "train.blocking_prob=0.6")),
    "critic": (("ppo.privileged_critic=false",), ("ppo.privileged_critic=true",)),
}
RESULT_FILE = "ablation_eval.json"
REFERENCE = "all"  # every other variant is compared with this one, seed by seed
LEARNED = 50.0  # % overall success: below it a run never learned to grasp (hovering near the cube, timeouts)
LEARNED_KEYS = ("success_overall", "success_obstacle", "success_blocking_scenes", "steps_per_success")  # their means
# metrics compared with the reference, seed by seed: (key, larger is better)
PAIRED = (("success_overall", True), ("success_obstacle", True), ("success_blocking_scenes", True),
          ("steps_per_success", False))


# ---------------------------------------------------------------------- seeing vs blind (a policy, no training)

BLIND_SCENES = ("obstacle", "blocking")


def blind_evaluate(policy: runtime.NumpyPolicy, episodes: int, seed: int, blind: bool, scenes: str = "obstacle") -> dict:
    cfg = policy.env_config()
    cfg = dataclasses.replace(
        cfg,
        sampling=blocking_sampling(cfg.sampling, 1.0, 1.0 if scenes == "blocking" else 0.0),
        task=dataclasses.replace(cfg.task, obs_noise_std=0.0),
    )
    env = GraspEnv(cfg)
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(seed), episodes))
    state = state.replace(info=dict(state.info, progress=jnp.ones(episodes)))
    step = jax.jit(jax.vmap(env.step))
    alive = np.ones(episodes, bool)
    record: dict[str, np.ndarray] = {}
    for _ in range(cfg.task.max_steps):
        obs = np.asarray(state.obs, dtype=float)
        if blind:
            obs = observation.blind(np, cfg, obs)
        state = step(state, jnp.asarray(policy(obs), jnp.float32))
        done = np.asarray(state.done) > 0
        ended = alive & done
        for key, value in state.info["episode"].items():
            record[key] = np.where(ended, np.asarray(value), record.get(key, np.zeros(episodes)))
        alive &= ~done
        if not alive.any():
            break
    success = record["success"]
    return {
        "scenes": scenes,
        "episodes": episodes,
        "obstacle_episodes": int((record["obstacle_present"] > 0).sum()),
        "success_rate": float(success.mean()),
        "collision_rate": float(record["collision"].mean()),
        "collision_by": {k[4:]: float(v.mean()) for k, v in record.items() if k.startswith("hit_")},
        "mean_steps_per_success": float(record["steps"][success > 0].mean()) if success.any() else None,
    }


def blind_study(policy: runtime.NumpyPolicy, episodes: int, seed: int) -> dict:
    """Seeing vs blind on obstacle-only scenes (disc placement, docs/task.md §1.5) and on blocking-only scenes."""
    result: dict = {"seed": seed, "obs_layout": policy.env_config().task.obs_layout}
    for scenes in BLIND_SCENES:
        seeing = blind_evaluate(policy, episodes, seed, False, scenes)
        blinded = blind_evaluate(policy, episodes, seed, True, scenes)
        result[scenes] = {"seeing": seeing, "blind": blinded,
                          "seeing_minus_blind": seeing["success_rate"] - blinded["success_rate"]}
    return result


def variants(leave_one_out: bool) -> dict[str, set[str]]:
    """Variant name -> the levers switched on."""
    out = {"base": set()} | {f"+{lever}": {lever} for lever in LEVERS} | {"all": set(LEVERS)}
    if leave_one_out:
        out |= {f"all-{lever}": set(LEVERS) - {lever} for lever in LEVERS}
    return out


def overrides_for(on: set[str]) -> tuple[str, ...]:
    """Every lever pinned, on or off."""
    return tuple(item for lever, (off, on_sets) in LEVERS.items() for item in (on_sets if lever in on else off))


VARIANTS: dict[str, tuple[str, ...]] = {name: overrides_for(on) for name, on in variants(True).items()}


def measure(eval_episodes: int, blind_episodes: int) -> study.Measure:
    """A run's record: the evaluation mix, blocking-only scenes and the seeing-vs-blind study."""
    def run(folder: str, variant: str, seed: int) -> dict[str, Any]:
        mix = study.Evaluation(eval_episodes)(folder)
        blocking = study.Evaluation(eval_episodes, scenes="blocking")(folder)
        blind = blind_study(runtime.load_policy(os.path.join(folder, run_dir.POLICY_FILE)), blind_episodes, seed=5)
        last = run_dir.read_metrics(os.path.join(folder, run_dir.METRICS_FILE))[-1]
        ov, ob, bl = mix["overall"], mix["obstacle_present"], blocking["blocking"]
        print(f"{variant} seed {seed}: success {100 * ov['success_rate']:.1f} % (obstacle {100 * ob['success_rate']:.1f} %, "
              f"blocking scenes {100 * bl['success_rate']:.1f} %)", flush=True)
        return {"levers": sorted(variants(True)[variant]), "mix": mix, "blocking_scenes": blocking, "blind": blind,
                "train_time_s": last.get("time_s"), "compile_s": last.get("compile_s"), "env_steps": last.get("env_steps")}
    return run


def per_seed_metrics(r: dict[str, Any]) -> dict[str, Any]:
    """What the obstacle issue is judged by, for one run."""
    return {
        **study.kind_rates(r),
        "collision_obstacle_episodes": study.rate(r["mix"]["obstacle_present"], "collision_rate"),
        "seeing_minus_blind_obstacle": 100.0 * r["blind"]["obstacle"]["seeing_minus_blind"],
        "seeing_minus_blind_blocking": 100.0 * r["blind"]["blocking"]["seeing_minus_blind"],
        "train_time_s": r.get("train_time_s"),
        **study.condition_rates(r),
    }


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Means and 95 % t-intervals across seeds of what the obstacle issue is judged by."""
    per_seed = [{"seed": r["seed"], **per_seed_metrics(r)} for r in records]
    out = stats.summarise(per_seed)
    hits: dict[str, list[float]] = {}
    for r in records:
        for kind, value in r["mix"]["obstacle_present"].get("collision_by", {}).items():
            hits.setdefault(kind, []).append(100.0 * value)
    out["collision_by_in_obstacle_episodes"] = {k: stats.mean_ci(v) for k, v in hits.items()}
    out["per_seed"] = per_seed
    # a run that never learned to grasp drags every mean down; say how many did, and how the others fared
    learned = [p for p in per_seed if p["success_overall"] is not None and p["success_overall"] >= LEARNED]
    out["runs_learned"] = {"learned": len(learned), "runs": len(records), "threshold_pct": LEARNED}
    out["learned_only"] = {k: stats.mean_ci([p[k] for p in learned]) for k in LEARNED_KEYS}
    return out


def markdown(summary: dict[str, dict[str, Any]]) -> str:
    cell = stats.cell
    cols = [("success_overall", "overall %"), ("success_obstacle", "obstacle %"),
            ("success_blocking_scenes", "blocking scenes %"), ("success_no_obstacle", "no obstacle %"),
            ("steps_per_success", "steps/success"), ("seeing_minus_blind_obstacle", "seeing − blind (obstacle)")]
    lines = ["| variant | " + " | ".join(c[1] for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for name, s in summary.items():
        lines.append(f"| {name} | " + " | ".join(cell(s[k]) for k, _ in cols) + " |")
    lines += ["", f"Runs that learned to grasp (overall success ≥ {LEARNED:.0f} %), and their means:", "",
              "| variant | learned | overall % | obstacle % | blocking scenes % | steps/success |", "|---" * 6 + "|"]
    for name, s in summary.items():
        lo, n = s["learned_only"], s["runs_learned"]
        lines.append(f"| {name} | {n['learned']} of {n['runs']} | " + " | ".join(cell(lo[k]) for k in LEARNED_KEYS) + " |")
    hit_kinds = sorted({k for s in summary.values() for k in s["collision_by_in_obstacle_episodes"]})
    lines += ["", "Collisions in obstacle episodes of the evaluation mix, by what was hit (% of those episodes):", "",
              "| variant | " + " | ".join(hit_kinds) + " |", "|---" * (len(hit_kinds) + 1) + "|"]
    for name, s in summary.items():
        by = s["collision_by_in_obstacle_episodes"]
        lines.append(f"| {name} | " + " | ".join(cell(by[k]) if k in by else "-" for k in hit_kinds) + " |")
    return "\n".join(lines)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m experiments.obstacle_ablation", description=__doc__.split("\n\n")[0])
    study.add_arguments(p, seeds=3, runs_dir="runs/obstacle_ablation")
    p.add_argument("--algo", default="sa-ppo", choices=train.ALGOS)
    p.add_argument("--leave-one-out", action="store_true", help="also each lever removed from 'all'")
    p.add_argument("--eval-episodes", type=int, default=1000)
    p.add_argument("--blind-episodes", type=int, default=200)
    p.add_argument("--out", default="experiments/results/obstacle_ablation_cpu.json")
    args = p.parse_args(argv)
    if args.eval_episodes < 1 or args.blind_episodes < 1:
        p.error("--eval-episodes and --blind-episodes must be >= 1")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    default = list(variants(args.leave_one_out))
    args.overrides = [f"lr.schedule={train.ALGO_SCHEDULES[args.algo]}", *args.overrides]
    try:
        spec = study.study_from_args(args)
        table = study.pick_variants(VARIANTS, args.variants, default)
        identity = {"eval_episodes": args.eval_episodes, "blind_episodes": args.blind_episodes}
        records = study.run_study(spec, table, measure(args.eval_episodes, args.blind_episodes), identity, RESULT_FILE,
                                  args.conditions, args.eval_episodes)
    except study.ERRORS as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    summary = {name: summarise(recs) for name, recs in records.items()}
    versus = stats.compare_with_reference({v: s["per_seed"] for v, s in summary.items()}, REFERENCE, PAIRED)
    result = {
        "preset": spec.preset, "algo": args.algo, "total_steps": spec.total_steps, "seeds": list(spec.seeds),
        "eval_episodes": args.eval_episodes, "blind_episodes": args.blind_episodes, "extra_overrides": args.overrides[1:],
        "levers": {k: {"off": list(v[0]), "on": list(v[1])} for k, v in LEVERS.items()},
        "variants": {name: sorted(variants(True)[name]) for name in table}, "summary": summary,
        "reference": REFERENCE, "paired_vs_reference": versus, "runs": records,
        "command": study.command("obstacle_ablation", argv), "git": study.git_state(), "machine": study.machine(),
    }
    return study.report(args.out, result, markdown(summary))


if __name__ == "__main__":
    sys.exit(main())
