"""What the failed episodes of a study's runs were: per variant, summed over its seeds, the episodes of each kind
(the ``robot`` condition's obstacle and no-obstacle episodes, the run's own blocking-only scenes) that hit the
obstacle, the table, the cube, anything else, or timed out, from a ``compare_schedules`` / ``sooner`` result file.

    python -m experiments.failures experiments/results/sooner_combo_10M.json [--condition robot]
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any, Sequence

_NAMED = ("obstacle", "table", "target")  # collision parts reported by name; the rest are "other"


def failures(group: dict[str, Any]) -> dict[str, int]:
    """Episode counts of one evaluated group (``episodes``, rates of success, timeout and each collision part)."""
    n = int(group["episodes"])
    by = group.get("collision_by", {})
    out = {"episodes": n, "failed": round(n * (1.0 - group["success_rate"])), "timeout": round(n * group["timeout_rate"])}
    for part in _NAMED:
        out[part] = round(n * by.get(part, 0.0))
    out["other"] = max(0, round(n * group["collision_rate"]) - sum(out[p] for p in _NAMED))  # rounding: never < 0
    return out


def table(result: dict[str, Any], condition: str | None) -> dict[str, dict[str, dict[str, int]]]:
    """variant -> episode kind -> summed counts over the variant's recorded runs."""
    out: dict[str, dict[str, dict[str, int]]] = {}
    for variant, runs in result.get("runs", {}).items():
        kinds: dict[str, dict[str, int]] = {}
        for run in runs:
            source = run["conditions"][condition] if condition else run["mix"]
            groups = {"obstacle": source["obstacle_present"], "no obstacle": source["obstacle_absent"]}
            if run.get("blocking_scenes"):
                groups["blocking scenes (own env)"] = run["blocking_scenes"]["blocking"]
            for kind, group in groups.items():
                counts = failures(group)
                kinds[kind] = {k: kinds.get(kind, {}).get(k, 0) + v for k, v in counts.items()}
        out[variant] = kinds
    return out


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.failures", description=__doc__.split("\n\n")[0])
    p.add_argument("result", help="a compare_schedules / sooner result JSON")
    p.add_argument("--condition", default=None, help="the evaluation condition the mix rows come from (e.g. robot)")
    args = p.parse_args(argv)
    try:
        with open(args.result, encoding="utf-8") as f:
            result = json.load(f)
        rows = table(result, args.condition)
    except (OSError, ValueError) as exc:
        print(f"error: {args.result}: cannot read it ({exc})", file=sys.stderr)
        return 2
    except KeyError as exc:
        print(f"error: {args.result}: no {exc} in its run records (is --condition one it evaluated?)", file=sys.stderr)
        return 2
    print("| variant | episodes | failed | obstacle | timeouts | cube | table | other |")
    print("|---|---|---|---|---|---|---|---|")
    for variant, kinds in rows.items():
        for kind, c in kinds.items():
            print(f"| {variant}, {kind} | {c['episodes']} | {c['failed']} | {c['obstacle']} | {c['timeout']} | "
                  f"{c['target']} | {c['table']} | {c['other']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
