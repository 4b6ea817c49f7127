"""Evaluate a trained run: ``python -m sagrasp_jax.evaluate --run runs/NAME --episodes 1000``.

The run's latest checkpoint is played with the deterministic policy (tanh of the Gaussian
mean) and reward weights frozen at p = 1, one episode per seed from a held-out evaluation
seed (by default ``eval.seed + 1``, so the SA selection set is not reused).  Reported:
success rate with its 95 % Wilson interval, mean steps per successful grasp, collision rate
(and what was hit, from the episodes' ``hit_*`` flags), timeout rate, each overall and split by
obstacle present / absent.  The JSON goes atomically into the run folder, named by episodes and
seed (``run_dir.evaluation_file``: ``evaluation-1000ep-seed12346.json``), or to ``--out``.  An
existing file is replaced only if it holds the same evaluation (same run, checkpoint, episodes,
seed, step cap, physical check, and what was trained: the config hash and the checkpoint's
digest) or with ``--force``.  The result file is locked while the evaluation runs (``run_dir.
ResultLock``: evaluations of other runs may write into the same folder meanwhile, a training may
not), and its folder is checked to be writable, full disks included, before it starts; a write
that still fails afterwards prints the result and exits 2.

``--physical`` also replays every kinematic success through the physical grasp check
(``evaluate_physical``, ``sagrasp_jax.reference.grasp_check``).  ``--set env.KEY=VALUE`` evaluates the run's
policy in another env than it was trained in (e.g. ``env.control.mode=dynamic`` for a kinematic
policy, or ``env.randomize.*``); the result file's name then carries a short hash of those changes.

This module is the command: its options, the result file's name, lock and replacement rule, the twin
backend's dispatch, the table and exit codes.  The evaluation itself is ``sagrasp_jax.training.evaluation``
(``evaluate_run``, ``summarise``, ``wilson_interval``, ``trained_identity``, ...).  Only the physical check's
composition stays here (``evaluate_physical``, ``physical_grasp_pose``): it joins the training layer's replay,
the deploy loop's closing slide (``deploy.loop.centring_pose``) and the reference layer's MuJoCo check, and
only the commands sit above all three (docs/architecture.md, "Layers").
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import argparse
import os
import sys
from typing import Any

from sagrasp_jax.base import cli, extras

if __name__ == "__main__":  # a missing extra ends in one line naming it (exit 2), not an import traceback
    extras.require_cli("train", prog="python -m sagrasp_jax.evaluate")

import numpy as np  # noqa: E402

from sagrasp_jax.training import evaluation
from sagrasp_jax.training import run_dir
from sagrasp_jax.training.checkpoint import CheckpointError
from sagrasp_jax.task.config import EVAL_CONDITIONS, ConfigError
from sagrasp_jax.task.config_parse import file_overrides
from sagrasp_jax.training.run_dir import RunDirError


def overrides_tag(overrides: list[str] | None) -> str | None:
    """A short, stable name for a set of ``--set`` changes (None: none)."""
    import hashlib

    if not overrides:
        return None
    return "set" + hashlib.sha256("\n".join(sorted(o.strip() for o in overrides)).encode()).hexdigest()[:8]


def evaluate_physical(run: str, episodes: int, seed: int, max_steps: int, lift: float | None = None,
                      overrides: list[str] | None = None, scenes: str = "mix") -> dict[str, Any]:
    """Replay ``evaluate_run``'s episodes (same keys, same jitted evaluator, same scene set) recording each
    final pose, and run the physical grasp check (``grasp_check.physical_grasp_check``) on every kinematic
    success.

    The replay goes through ``fixed_seed_eval.evaluate_policy`` with the env wrapped to copy the final
    joints into the episode record, so it is the evaluation's own code path; the kinematic
    success count is reported next to the physical one so a mismatch would show.  As the
    deployment loop does (docs/design.md, "One grasp"), the gripper first slides, its orientation
    kept, over the cube the policy saw (the true cube plus the episode's horizontal detection error;
    its height is known) in collision-checked steps (``physical_grasp_pose``), then closes on the true
    cube and lifts keeping its orientation.
    """
    from sagrasp_jax.reference import grasp_check as physical
    from sagrasp_jax.task.robot import load_robot

    lift = physical.LIFT_HEIGHT if lift is None else lift
    replay = evaluation.replay_final_poses(run, episodes, seed, max_steps, overrides, scenes)
    successes = np.nonzero(replay.episodes["success"] > 0)[0]
    arm = load_robot(replay.env_cfg.robot)
    checks = [physical.physical_grasp_check(physical_grasp_pose(replay, i), replay.spec(i), lift=lift, arm=arm)
              for i in successes]
    held = sum(c["success"] for c in checks)
    names = dict.fromkeys(name for c in checks for name in c["criteria"])
    failures = {name: sum(not c["criteria"].get(name, True) for c in checks) for name in names}
    blocking = replay.episodes["blocking"] > 0 if "blocking" in replay.episodes else np.zeros(episodes, bool)
    held_mask = np.zeros(episodes, bool)
    held_mask[successes] = [c["success"] for c in checks]
    return {
        "episodes": episodes,
        "kinematic_successes": int(len(successes)),
        "physical_successes": int(held),
        "physical_success_rate": held / episodes,
        "physical_given_kinematic": held / len(successes) if len(successes) else None,
        "blocking_episodes": int(blocking.sum()),
        "blocking_physical_success_rate": float(held_mask[blocking].mean()) if blocking.any() else None,
        "mean_cube_rise": float(np.mean([c["cube_rise"] for c in checks if "cube_rise" in c])) if checks else None,
        "failed_criteria": failures,
        "lift": lift,
    }


SLIDE_CHECKS = 8  # collision checks along the final slide (it moves a few mm)


def physical_grasp_pose(replay: evaluation.FinalPoses, i: int) -> np.ndarray:
    """Where the deploy loop closes after episode ``i``: its final pose slid over the detected cube
    (``deploy.loop.centring_pose``), stopped before the first step that collides (the safety layer's
    refusal), or the final pose itself when no slide is found."""
    from sagrasp_jax.task import collision
    from sagrasp_jax.task import robot
    from sagrasp_jax.deploy.loop import centring_pose

    cfg, spec, q = replay.env_cfg, replay.spec(i), replay.q_final[i]
    model = robot.load_robot(cfg.robot)  # the run's arm
    detected = np.asarray(spec.target_pos, float) + replay.target_error[i] * np.array([1.0, 1.0, 0.0])
    try:
        goal = centring_pose(model, cfg, q, detected)
    except robot.IKError:
        return q
    last = q
    for t in np.linspace(0.0, 1.0, SLIDE_CHECKS + 1)[1:]:
        pose = q + t * (goal - q)
        if bool(collision.check(np, model, robot.forward_kinematics(np, model, pose), spec, cfg).any_collision):
            return last
        last = pose
    return last


def format_table(results: dict[str, Any]) -> str:
    """A plain-text table: one column per episode group."""
    groups = [("all", results["overall"]), ("obstacle", results["obstacle_present"])]
    groups += [("blocking", results["blocking"])] if "blocking" in results else []
    groups += [("no obstacle", results["obstacle_absent"])]
    hit_keys = sorted({k for _, g in groups for k in g.get("collision_by", {})})

    def pct(v: Any) -> str:
        return "-" if v is None else f"{100 * v:.1f} %"

    rows: list[tuple[str, list[str]]] = [
        ("episodes", [str(g["episodes"]) for _, g in groups]),
        ("success", [pct(g.get("success_rate")) for _, g in groups]),
        ("  95 % CI (Wilson)", [("-" if "success_ci95" not in g else
                                 f"{100 * g['success_ci95'][0]:.1f}-{100 * g['success_ci95'][1]:.1f} %")
                                for _, g in groups]),
        ("steps / success", [("-" if g.get("mean_steps_per_success") is None else f"{g['mean_steps_per_success']:.1f}")
                             for _, g in groups]),
        ("collision", [pct(g.get("collision_rate")) for _, g in groups]),
    ]
    rows += [(f"  hit {k}", [pct(g.get("collision_by", {}).get(k)) for _, g in groups]) for k in hit_keys]
    rows += [("timeout", [pct(g.get("timeout_rate")) for _, g in groups]),
             ("mean return (p=1)", [("-" if g.get("mean_return") is None else f"{g['mean_return']:.3f}")
                                    for _, g in groups])]
    width = max(len(r[0]) for r in rows) + 2
    scenes = results.get("scenes", "mix")
    kind = "blocking-only scenes" if scenes == "blocking" else "the evaluation mix"
    lines = [f"{results['episodes']} episodes of {kind}, seed {results['seed']}, deterministic policy, reward weights at p = 1",
             "".ljust(width) + "".join(name.rjust(14) for name, _ in groups)]
    lines += [label.ljust(width) + "".join(c.rjust(14) for c in cells) for label, cells in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from sagrasp_jax.task.policy_file import POLICY_HELP

    p = cli.Parser(prog="python -m sagrasp_jax.evaluate", description=__doc__.split("\n\n")[0])
    p.add_argument("--run", default=None, help="run folder written by sagrasp_jax.train (required but with "
                   "--backend twin --policy)")
    p.add_argument("--policy", default=None, help="--backend twin, instead of --run: " + POLICY_HELP[len("the policy: "):]
                   + " (no result file unless --out)")
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--seed", type=int, default=None, help="evaluation seed (default eval.seed + 1)")
    p.add_argument("--max-steps", type=int, default=None, help="step cap per episode (default env.task.max_steps)")
    p.add_argument("--scenes", default="mix", choices=evaluation.SCENE_SETS,
                   help="mix: the task's evaluation mix (20 %% obstacle episodes); blocking: every episode has an obstacle "
                        "on the straight approach path (the file name says so)")
    p.add_argument("--out", default=None,
                   help="result JSON (default RUN/evaluation-<EPISODES>ep-seed<SEED>[-<MAX_STEPS>steps].json; --backend "
                        "twin: RUN/evaluation-<EPISODES>ep-seed<SEED>-twin-<CONDITION>.json); an existing file is "
                        "replaced only if it holds the same evaluation")
    p.add_argument("--force", action="store_true", help="replace an existing result file that holds another evaluation "
                   "(never a file that is no evaluation result, such as the run's config.json)")
    p.add_argument("--physical", action="store_true",
                   help="also replay each kinematic success through the MuJoCo physical grasp check (close, lift 5 cm)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="env.KEY=VALUE",
                   help="evaluate in a changed env, repeatable (e.g. env.control.mode=dynamic, env.randomize.latency=1)")
    p.add_argument("--condition", choices=sorted(EVAL_CONDITIONS), default=None,
                   help="a named evaluation env (config.EVAL_CONDITIONS), applied before --set: kinematic, dynamic "
                        "(every transfer knob off), robot (dynamic, every knob on at the real arm's levels), "
                        "robot-latency2 (the same with up to 2 steps of latency), kinematic-target-error")
    p.add_argument("--config", default=None, metavar="FILE",
                   help="env.* keys from a JSON (or YAML) file, applied before --set (same rules as --set)")
    p.add_argument("--backend", choices=("mjx", "twin"), default="mjx",
                   help="mjx: the JAX env (default); twin: the run's policy.npz through the deploy loop on the PyBullet "
                        "twin, judged by the cube held after the lift (sagrasp_jax.deploy.rehearse; --episodes scenes, "
                        "--condition, --scenes, --seed, --workers, --out)")
    p.add_argument("--workers", type=int, default=1, help="twin backend: processes (default 1; one per core)")
    args = p.parse_args(argv)
    if args.backend == "twin":
        return _twin_backend(args)
    if args.run is None or args.policy is not None:
        p.error("--run RUN is required (--policy only with --backend twin)")
    # What Ctrl-C stopped and what it kept: the line is made at the exit (cli.exit_on_interrupt).
    state: dict[str, Any] = {"path": None, "lock": None, "written": False}

    def stopped() -> str:
        path = state["path"]
        if state["written"]:
            kept = f"its result was written to {path} before the exit"
        else:
            kept = "nothing was written" + (f" ({path} left as it was)" if path and os.path.exists(path) else "")
        return cli.interrupted_line(f"the evaluation of {args.run} was stopped", kept)

    def cleanup() -> None:  # the result's lock file; the flocks go with the process
        if state["lock"] is not None:
            state["lock"].release()

    # No safe point inside jax's tracing, XLA's compile or the jitted evaluation: from here on Ctrl-C ends the
    # process at once, its lock file removed; the result's write is finished first (cli.deferred).
    with cli.exit_on_interrupt(stopped, cleanup):
        try:
            results, path = _evaluate_cli(args, state)
        except (ConfigError, CheckpointError, RunDirError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    print(format_table(results))
    if "physical" in results:
        ph = results["physical"]
        print(f"physical grasp check: {ph['physical_successes']} of {ph['kinematic_successes']} kinematic successes held "
              f"the cube when lifted {ph['lift'] * 100:.0f} cm ({100 * ph['physical_success_rate']:.1f} % of all episodes)")
    print(f"written to {path}")
    return 0


def _evaluate_cli(args: argparse.Namespace, state: dict[str, Any]) -> tuple[dict[str, Any], str]:
    """The MJX evaluation of the command line: checks, lock, evaluate, write; (results, the file written).
    ``state`` tells ``main``'s Ctrl-C line and cleanup where it got (the result file, its lock, written)."""
    if args.config is not None:
        args.overrides = file_overrides(args.config) + list(args.overrides)
    if args.condition:  # the named condition first, then the file, then --set
        args.overrides = [*EVAL_CONDITIONS[args.condition], *args.overrides]
    evaluation.check_options(args.episodes, args.seed, args.max_steps)
    cfg = run_dir.load_config(args.run)
    ckpt = run_dir.load_checkpoint(args.run, cfg)
    counters = run_dir.checkpoint_counters(ckpt)
    evaluation.env_overrides(cfg, args.overrides)  # refused before any work
    seed, steps = evaluation.resolve_options(cfg, args.seed, args.max_steps)
    path = args.out or run_dir.path(args.run, run_dir.evaluation_file(
        args.episodes, seed, None if steps == cfg.env.task.max_steps else steps, args.scenes,
        overrides_tag(args.overrides)))
    identity = {"run": os.path.abspath(args.run), "episodes": args.episodes, "seed": seed, "max_steps": steps,
                "checkpoint_iteration": counters.get("iteration"),
                "checkpoint_env_steps": counters.get("env_steps"), **evaluation.trained_identity(cfg, ckpt),
                "physical_check": args.physical,
                "scenes": args.scenes, **({"env_overrides": list(args.overrides)} if args.overrides else {})}
    folder = os.path.dirname(os.path.abspath(path))
    run_dir.check_output_file(path)  # a FIFO or device: refused before the lock file or anything is made
    state["path"] = path
    lock = state["lock"] = run_dir.ResultLock(path, what="output folder")  # other results may go into its folder
    with lock:
        run_dir.check_writable(folder, "output folder")  # before the evaluation, not after it
        run_dir.check_replace(path, identity, args.force)
        results = evaluation.evaluate_run(args.run, args.episodes, seed, steps, scenes=args.scenes, overrides=args.overrides)
        results["physical_check"] = args.physical
        if args.physical:
            results["physical"] = evaluate_physical(args.run, args.episodes, seed, steps, overrides=args.overrides,
                                                    scenes=args.scenes)
        try:
            with cli.deferred():
                evaluation.write_results(path, results)
                state["written"] = True
        except OSError as exc:  # e.g. the disk filled up meanwhile: show what was evaluated, then refuse
            print(format_table(results))
            raise RunDirError(f"{exc}; the evaluation above was not saved") from None
    return results, path


def _twin_backend(args: argparse.Namespace) -> int:
    """``--backend twin``: the run's exported ``policy.npz`` (or ``--policy``) through ``deploy.rehearse`` (no jax
    needed).  With ``--run`` the result goes into the run folder as the MJX evaluation's does
    (``twin_result_file``), under the same rules: locked while it runs, replaced only when it holds the same
    result (or another twin result, with ``--force``), written atomically."""
    from sagrasp_jax.base import run_files
    from sagrasp_jax.deploy import rehearse

    unsupported = [flag for flag, on in (("--physical", args.physical), ("--set", args.overrides),
                                         ("--config", args.config), ("--max-steps", args.max_steps)) if on]
    if unsupported:
        print(f"error: --backend twin takes no {', '.join(unsupported)} (the twin judges the held cube itself; "
              "conditions are named with --condition)", file=sys.stderr)
        return 2
    args.condition = args.condition or "robot"
    args.seed = 0 if args.seed is None else args.seed
    if (args.run is None) == (args.policy is None):
        print("error: --backend twin needs --run RUN (its policy.npz) or --policy FILE|NAME, not both", file=sys.stderr)
        return 2
    if args.policy is not None:
        return rehearse.run_cli(args.policy, args)
    try:
        policy = run_files.policy_of_run(args.run)
        out = args.out or run_dir.path(args.run, twin_result_file(args.episodes, args.seed, args.scenes, args.condition))
        run_dir.check_output_file(out)
        with run_dir.ResultLock(out, what="output folder"):
            return rehearse.run_cli(policy, args, out=out)
    except (run_files.RunFolderError, RunDirError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def twin_result_file(episodes: int, seed: int, scenes: str, condition: str) -> str:
    """The file name of a twin evaluation in its run folder: the MJX evaluation's scheme (``run_dir.
    evaluation_file``) tagged with the backend and the condition, ``evaluation-500ep-seed0-twin-robot.json``."""
    return run_dir.evaluation_file(episodes, seed, None, scenes, f"twin-{condition}")


if __name__ == "__main__":
    sys.exit(main())
