"""Dynamic mode and domain randomisation: evaluate trained runs in the dynamic env, with and without
randomisation (issue 18, items 3-4; docs/results.md, "Dynamic mode").

Each ``--run NAME=FOLDER`` is evaluated on 1,000 episodes of the evaluation mix and 1,000 blocking-only
scenes (``evaluate.evaluate_run``, seed ``eval.seed + 1``, deterministic policy) in the dynamic env
(``env.control.mode=dynamic``) and in the dynamic env with the transfer randomisation (``RANDOMIZE``);
``--kinematic NAME`` also in the kinematic env.  The training budget of each run comes from its
``metrics.jsonl`` (env steps, training and compile seconds) and, when the run was started through
``experiments/cputime.py`` (``--cpu NAME=FILE``: a JSON with ``cpu_user_s``, ``cpu_sys_s``, ``wall_s``,
``load_start``, ``load_end``), its process CPU time.  Prints a Markdown table and writes JSON.

    python -m experiments.dynamic_transfer --run a=runs/kin --run b=runs/ft --run c=runs/scratch \\
        --kinematic a --out experiments/results/dynamic_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import sagrasp_jax  # noqa: F401  (XLA flags)

from sagrasp_jax import evaluate, run_dir
from sagrasp_jax.config import config_to_dict
from sagrasp_jax.fileio import atomic_write_json

RANDOMIZE = ["env.randomize.servo_gain=0.2", "env.randomize.latency=1", "env.randomize.joint_offset=0.005",
             "env.randomize.joint_noise=0.005", "env.randomize.target_error=0.005"]
OFF = [item.split("=")[0] + "=0" for item in RANDOMIZE]
ENVS = {"kinematic": ["env.control.mode=kinematic", *OFF], "dynamic": ["env.control.mode=dynamic", *OFF],
        "dynamic+randomize": ["env.control.mode=dynamic", *RANDOMIZE]}


def budget(run: str, cpu_file: str | None) -> dict:
    rows = run_dir.read_metrics(run_dir.path(run, run_dir.METRICS_FILE))
    last = rows[-1]
    cfg = run_dir.load_config(run)
    out = {"mode": cfg.env.control.mode, "init_from": cfg.train.init_from or None, "env_steps": last["env_steps"],
           "train_s": round(last["time_s"], 1), "compile_s": round(last["compile_s"], 1),
           "randomize": {k: v for k, v in config_to_dict(cfg)["env"]["randomize"].items() if v}}
    if cpu_file:
        with open(cpu_file, encoding="utf-8") as f:
            cpu = json.load(f)
        out.update(cpu_s=round(cpu["cpu_user_s"] + cpu["cpu_sys_s"], 1), wall_s=round(cpu["wall_s"], 1),
                   load=[round(cpu["load_start"], 2), round(cpu["load_end"], 2)])
    return out


def split(result: dict) -> dict:
    def rate(group: dict) -> float | None:
        return group.get("success_rate")

    return {"overall": rate(result["overall"]), "obstacle": rate(result["obstacle_present"]),
            "blocking_in_mix": rate(result["blocking"]), "blocking_in_mix_n": result["blocking"]["episodes"],
            "collision": result["overall"]["collision_rate"], "steps_per_success": result["overall"]["mean_steps_per_success"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", action="append", default=[], metavar="NAME=FOLDER", required=True)
    parser.add_argument("--cpu", action="append", default=[], metavar="NAME=FILE", help="CPU-time bookkeeping of a run")
    parser.add_argument("--kinematic", action="append", default=[], metavar="NAME", help="also evaluate in the kinematic env")
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--out", default="experiments/results/dynamic_cpu.json")
    args = parser.parse_args(argv)
    runs = dict(item.split("=", 1) for item in args.run)
    cpus = dict(item.split("=", 1) for item in args.cpu)
    report: dict = {"episodes": args.episodes, "randomize": RANDOMIZE, "runs": {}}
    for name, folder in runs.items():
        entry = {"folder": os.path.abspath(folder), "budget": budget(folder, cpus.get(name)), "eval": {}}
        envs = [e for e in ENVS if e != "kinematic" or name in args.kinematic]
        for env in envs:
            mix = evaluate.evaluate_run(folder, args.episodes, overrides=ENVS[env])
            blocking = evaluate.evaluate_run(folder, args.episodes, overrides=ENVS[env], scenes="blocking")
            entry["eval"][env] = {**split(mix), "blocking_scenes": blocking["overall"]["success_rate"]}
            print(f"{name} {env}: {entry['eval'][env]}", file=sys.stderr, flush=True)
        report["runs"][name] = entry
    folders = {os.path.abspath(f): n for n, f in runs.items()}
    for name, entry in report["runs"].items():  # a fine-tuned run's budget includes its starting run's
        b = entry["budget"]
        src = folders.get(os.path.abspath(b["init_from"])) if b["init_from"] else None
        if src is not None:
            s = report["runs"][src]["budget"]
            b["total"] = {k: round(b[k] + s[k], 1) for k in ("env_steps", "train_s", "cpu_s") if k in b and k in s}
            b["total"]["from"] = src
    atomic_write_json(args.out, report)
    pct = lambda v: "–" if v is None else f"{100 * v:.1f} %"  # noqa: E731
    print("| policy | budget | evaluated in | overall | obstacle | blocking (in mix) | blocking scenes | steps/success |")
    print("|---|---|---|---|---|---|---|---|")
    for name, entry in report["runs"].items():
        b = entry["budget"]
        cost = f"{b['env_steps'] / 1e6:.2f}M steps {b['mode']}, {b['train_s']:.0f} s" + (
            f" ({b['cpu_s']:.0f} s CPU)" if "cpu_s" in b else "")
        if "total" in b:
            t = b["total"]
            cost = f"{t['from']} + {cost}: {t['train_s']:.0f} s" + (f" ({t['cpu_s']:.0f} s CPU)" if "cpu_s" in t else "")
        for env, e in entry["eval"].items():
            print(f"| {name} | {cost} | {env} | {pct(e['overall'])} | {pct(e['obstacle'])} | "
                  f"{pct(e['blocking_in_mix'])} (n={e['blocking_in_mix_n']}) | {pct(e['blocking_scenes'])} | "
                  f"{e['steps_per_success']:.1f} |")
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
