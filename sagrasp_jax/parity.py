"""``python -m sagrasp_jax.parity``: the MJX env against the PyBullet reference, step for step.

The harness is :mod:`sagrasp_jax.reference.parity` (what is compared, the tolerances, the report); this is
its command line.
"""

from __future__ import annotations

import sys

from sagrasp_jax.base import cli
from sagrasp_jax.base import extras

if __name__ == "__main__":  # a missing extra ends in one line naming it (exit 2), not an import traceback
    extras.require_cli("train", "reference", prog="python -m sagrasp_jax.parity")

from sagrasp_jax.base import fileio  # noqa: E402
from sagrasp_jax.reference import parity as harness  # noqa: E402
from sagrasp_jax.task.config import ConfigError, check_range  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = cli.Parser(prog="python -m sagrasp_jax.parity", description=harness.__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=None, help="episodes per action source (default 1000; --quick 50)")
    parser.add_argument("--quick", action="store_true", help="50 episodes of at most 100 steps: a CI-sized check")
    parser.add_argument("--mode", choices=tuple(harness.TOLERANCES), default="kinematic")
    parser.add_argument("--policy", default=None, help="policy.npz: also compare its closed-loop episodes")
    parser.add_argument("--actions", default="random,scripted", help="comma list of action sources: random, scripted")
    parser.add_argument("--out", default="parity.json", help="JSON report path ('' = do not write)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-steps", type=int, default=None, help="episode length for both envs (default: config, 200)")
    parser.add_argument("--batch", type=int, default=50, help="episodes stepped in lockstep (one PyBullet env each)")
    parser.add_argument("--single-step", dest="single_step", action="store_true", default=None,
                        help="also compare single steps from forced identical states (default: dynamic mode only)")
    parser.add_argument("--no-single-step", dest="single_step", action="store_false")
    parser.add_argument("--preset", default="paper", help="config preset of both envs (default paper; a --policy brings its own)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="config override for both envs, e.g. env.task.obs_layout=relative")
    parser.add_argument("--reference-set", action="append", default=[], metavar="KEY=VALUE",
                        help="config override for the reference env only (e.g. env.reward.ratio=10.5): a deliberate mismatch")
    parser.add_argument("--reference-servo", choices=("mujoco", "position_control"), default="mujoco",
                        help="dynamic mode: the reference env's motor model (position_control: PyBullet's own "
                             "POSITION_CONTROL motor with the fitted gains; docs/parity.md)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    args = parser.parse_args(argv)

    episodes = args.episodes if args.episodes is not None else (50 if args.quick else 1000)
    max_steps = args.max_steps if args.max_steps is not None else (100 if args.quick else None)
    sources = tuple(s.strip() for s in args.actions.split(",") if s.strip())
    try:
        check_range("--episodes", episodes, 1, 100_000)
        check_range("--batch", args.batch, 1, 1000)
        check_range("--seed", args.seed, 0, 2**31 - 1)  # seed + episode index must stay a distinct jax seed
        if max_steps is not None:
            check_range("--max-steps", max_steps, 1, 100_000)
        if args.out:
            fileio.check_writable(args.out, "output folder", is_folder=False)
    except (ConfigError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    bad = [s for s in sources if s not in ("random", "scripted")]
    if bad:
        print(f"error: unknown action source(s) {', '.join(bad)}; --actions takes random, scripted "
              "(the policy source comes with --policy)", file=sys.stderr)
        return 2
    log = (lambda s: None) if args.quiet else (lambda s: print(s, file=sys.stderr, flush=True))
    try:
        report = harness.run_parity(
            mode=args.mode, episodes=episodes, seed=args.seed, sources=sources, policy_path=args.policy,
            max_steps=max_steps, batch=args.batch, single_step=args.single_step,
            reference_overrides=args.reference_set, log=log, preset=args.preset, overrides=args.overrides,
            reference_servo=args.reference_servo,
        )
    except (ConfigError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(harness.format_report(report))
    if args.out:
        harness.write_json(args.out, report)
        print(f"report written to {args.out}")
    return 0 if report["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
