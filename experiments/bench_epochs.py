"""What fewer SGD passes late in the run save: the README preset's training call per iteration with
eight passes throughout (the preset before it adopted ``ppo.late_epochs=4``) against ``ppo.late_epochs``
(4, 2) applied from the first iteration, and against a fixed four-pass scan (``ppo.num_epochs=4``: the
run-time loop's own cost), the calls interleaved so that each sees the same load.  Then what that makes
of the README run's training time, from these per-iteration costs alone (``ppo.late_from`` of the budget at
eight passes, the rest at the late count; evaluation and compile not included).

    python -m experiments.bench_epochs --out experiments/results/bench_epochs_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from typing import Any, Sequence

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

VARIANTS: dict[str, tuple[str, ...]] = {
    "8 passes throughout": ("ppo.late_epochs=0",),
    "late_epochs=4 (from the start)": ("ppo.late_epochs=4", "ppo.late_from=0"),
    "late_epochs=2 (from the start)": ("ppo.late_epochs=2", "ppo.late_from=0"),
    "num_epochs=4 (fixed scan)": ("ppo.num_epochs=4", "ppo.late_epochs=0"),
}
PRESET = "8 passes throughout"  # the reference every other row is a fraction of


def _is_late(sets: tuple[str, ...]) -> bool:
    """A variant whose passes drop at ppo.late_from: the README run's projection applies to it."""
    return any(item.startswith("ppo.late_epochs=") and item != "ppo.late_epochs=0" for item in sets)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.bench_epochs", description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="cpu-quick")
    p.add_argument("--reps", type=int, default=6, help="timed calls of one cycle per variant (median)")
    p.add_argument("--late-from", type=float, default=0.3, help="ppo.late_from of the projected README run")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for every variant (before the variant's own), repeatable")
    p.add_argument("--out", default=None, help="JSON result file")
    args = p.parse_args(argv)
    if args.reps < 1 or not 0.0 <= args.late_from <= 1.0:
        p.error("--reps must be >= 1 and --late-from in [0, 1]")

    import jax
    import numpy as np

    from sagrasp_jax import train
    from sagrasp_jax.task.config import ConfigError
    from sagrasp_jax.training import launch

    try:
        configs = {name: launch.build_config(args.preset, "sa-ppo", 0, None, [*args.overrides, *sets])
                   for name, sets in VARIANTS.items()}
    except ConfigError as exc:
        p.error(str(exc))
    base = configs[PRESET]
    launch.use_cpu_devices(base)
    # one trainer at a time built, compiled and warmed up: programs with cross-device collectives that are
    # enqueued on the devices in different orders (one trainer's start beside another's) can wait on each other
    trainers: dict[str, Any] = {}
    for name, cfg in configs.items():
        tr = trainers[name] = train.Trainer(cfg, tempfile.mkdtemp(prefix="bench_epochs."), progress=False)
        tr.compile()
        tr.run_iterations(tr.schedule.iterations_per_cycle)  # warm-up
        print(f"  {name}: compiled and warmed up", flush=True)
    k = next(iter(trainers.values())).schedule.iterations_per_cycle
    wall: dict[str, list[float]] = {name: [] for name in trainers}
    for _ in range(args.reps):
        for name, tr in trainers.items():
            t = time.perf_counter()
            tr.run_iterations(k)
            wall[name].append((time.perf_counter() - t) / k)
    steps = base.ppo.num_envs * base.ppo.unroll_length
    iterations = next(iter(trainers.values())).schedule.num_iterations
    ms = {name: 1e3 * float(np.median(w)) for name, w in wall.items()}
    eight = ms[PRESET]
    rows = []
    for name, value in ms.items():
        projected = (iterations * (args.late_from * eight + (1 - args.late_from) * value) / 1e3
                     if _is_late(VARIANTS[name]) else None)
        rows.append({"variant": name, "overrides": list(VARIANTS[name]), "ms_per_iteration": value,
                     "env_steps_per_s": steps / (value / 1e3), "vs_eight_passes": value / eight,
                     "projected_readme_training_s": projected})
    load = os.getloadavg()
    print(f"\n{args.preset}: {steps} env steps an iteration, {iterations} iterations in the budget, "
          f"{len(jax.devices())} device(s), load {load[0]:.2f}")
    print("| variant | ms / iteration | env-steps/s | × 8 passes | README training, projected (s) |")
    print("|---|---|---|---|---|")
    for r in rows:
        proj = "–" if r["projected_readme_training_s"] is None else f"{r['projected_readme_training_s']:.0f}"
        print(f"| {r['variant']} | {r['ms_per_iteration']:.1f} | {r['env_steps_per_s']:,.0f} | "
              f"{r['vs_eight_passes']:.3f} | {proj} |")
    print(f"(8 passes throughout, projected the same way: {iterations * eight / 1e3:.0f} s; "
          f"late passes from progress {args.late_from})")
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        result: dict[str, Any] = {"preset": args.preset, "overrides": args.overrides, "reps": args.reps, "late_from": args.late_from,
                                  "iteration_env_steps": steps, "iterations": iterations,
                                  "devices": len(jax.devices()), "load": list(load), "machine": platform.processor()
                                  or platform.machine(), "cpus": os.cpu_count(), "rows": rows,
                                  "preset_projected_training_s": iterations * eight / 1e3,
                                  "command": "python -m experiments.bench_epochs " + " ".join(sys.argv[1:])}
        tmp = args.out + ".tmp"
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(result, f, indent=1)
        os.replace(tmp, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
