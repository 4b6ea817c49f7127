"""The commands of the package: ``python -m sagrasp_jax`` lists them, ``python -m sagrasp_jax COMMAND ...``
runs one (the same as ``python -m sagrasp_jax.COMMAND ...``), and each has a console script
(``sagrasp-COMMAND``, pyproject.toml's ``[project.scripts]``) pointing at a launcher here.

A launcher runs the command's module as a program (``runpy``, as ``python -m`` does), so a missing
extra ends in the module's own one-line hint (exit 2), never an import traceback, and this module
imports none of them: it stays instant and jax-free, and entry points still do not import each other.
"""

from __future__ import annotations

import runpy
import sys
from typing import Callable, NamedTuple, Sequence


class Command(NamedTuple):
    module: str  # under sagrasp_jax
    extras: str  # what to install beyond the core, as the hint names it
    summary: str  # one line


# In the order a newcomer uses them.
COMMANDS: dict[str, Command] = {
    "train": Command("train", "train", "train a policy into a run folder (SA-PPO; --preset cpu-quick on a laptop)"),
    "evaluate": Command("evaluate", "train", "play a run's policy on held-out episodes: success, collisions, steps"),
    "render": Command("render", "render", "watch a run (--run) or a policy (--policy): an mp4 video and a PNG still"),
    "plot": Command("plot", "plots", "plot a run's learning curves (success per episode kind, return, lr, SA) to PNG"),
    "export": Command("export", "train", "export a run's policy for the robot: policy.npz (NumPy) and ONNX"),
    "capture": Command("capture", "core; twin for --camera twin", "save one depth capture (Mech-Eye, RealSense or the twin) to replay"),
    "deploy": Command("deploy", "core; twin for --backend twin", "run a policy on one detected cube: robot or twin"),
    "rehearse": Command("deploy.rehearse", "twin", "the deploy loop over N random twin scenes: the cube held, per kind"),
    "calibrate": Command("calibrate", "core", "fit the hand-eye matrix T_cam_base from camera / TCP point pairs"),
    "sysid": Command("sysid", "core", "fit the servo model, latency and joint offsets from a robot log (CSV)"),
    "parity": Command("parity", "train, reference", "run the MJX env and the PyBullet reference side by side"),
}


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: python -m sagrasp_jax COMMAND [ARGS...]   (or sagrasp-COMMAND; COMMAND --help for its options)",
             "", "commands (extra to install beyond the core: pip install \"sagrasp_jax[EXTRA]\"):"]
    lines += [f"  {name:<{width}}  {cmd.summary}  [{cmd.extras}]" for name, cmd in COMMANDS.items()]
    return "\n".join(lines)


def run_command(name: str, argv: Sequence[str]) -> None:
    """Run ``python -m sagrasp_jax.<module> ARGV`` in this process (raises its SystemExit)."""
    sys.argv = [f"sagrasp-{name}", *argv]
    runpy.run_module(f"sagrasp_jax.{COMMANDS[name].module}", run_name="__main__", alter_sys=True)


def _launcher(name: str) -> Callable[[], None]:
    def launch() -> None:
        run_command(name, sys.argv[1:])

    launch.__name__ = launch.__qualname__ = name
    launch.__doc__ = f"Console script sagrasp-{name}: python -m sagrasp_jax.{name}."
    return launch


# the console scripts' targets (pyproject.toml: sagrasp-train = "sagrasp_jax.__main__:train", ...)
train, evaluate, render, plot, export = (_launcher(n) for n in ("train", "evaluate", "render", "plot", "export"))
deploy, rehearse, calibrate, sysid, parity = (_launcher(n) for n in ("deploy", "rehearse", "calibrate", "sysid", "parity"))
capture = _launcher("capture")


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help", "help"):
        print(usage())
        return 0
    if args[0] not in COMMANDS:
        print(f"{usage()}\n\npython -m sagrasp_jax: error: unknown command {args[0]!r}", file=sys.stderr)
        return 2
    run_command(args[0], args[1:])
    return 0


if __name__ == "__main__":
    sys.exit(main())
