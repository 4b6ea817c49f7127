"""Take one depth-camera capture and save it: ``python -m sagrasp_jax.capture``.

    python -m sagrasp_jax.capture --camera mecheye --camera-address IP --out capture.npz
    python -m sagrasp_jax.capture --camera realsense [--camera-address SERIAL|RECORDING] --out capture.npz
    python -m sagrasp_jax.capture --camera twin [--seed S] [--scene N] [--scene-set mix|blocking]
        [--camera-model mecheye_pro_m|realsense_d435] [--depth-noise MODEL] [--camera-resolution F] --out capture.npz

The file (``deploy.capture_file``) holds the organized point cloud (camera frame, mm, NaN where no return),
the colour image on the same pixel grid, the intrinsics (the SDK's for a real camera, the model's for the
twin), the camera model, what took it and when; a twin capture also holds its true scene.  ``python -m
sagrasp_jax.deploy --camera replay:capture.npz`` perceives and deploys from it (on the twin, or as a dry run),
so what a real cell saw can be run again at a desk.

``--camera twin`` renders scene ``--scene`` of ``--seed`` as ``deploy.rehearse`` draws it (the same scenes
as ``deploy --camera twin --scenes N --seed S``), with the PyBullet twin (``pip install "sagrasp_jax[twin]"``).

Exit status: 0 written; 2 refused (bad options, an absent or silent camera, an output that exists without
``--force``), nothing written.
"""

from __future__ import annotations

import math
import os
import sys
from typing import Sequence

import numpy as np

from sagrasp_jax.base import cli, extras, fileio
from sagrasp_jax.deploy import capture_file
from sagrasp_jax.deploy.cameras import CameraError, capture_once
from sagrasp_jax.task.camera import CHOICES, DEFAULT_CAMERA, NOISE_MODELS
from sagrasp_jax.task import robots

SOURCES = ("mecheye", "realsense", "twin")


def _parser() -> cli.Parser:
    p = cli.Parser(prog="python -m sagrasp_jax.capture", description=__doc__.split("\n\n")[0])
    p.add_argument("--camera", choices=SOURCES, required=True, help="the camera: mecheye, realsense or twin")
    p.add_argument("--camera-address", default=None, metavar="ADDRESS",
                   help="mecheye: its IP address (required); realsense: its serial number or a recording (.db3 or .bag) "
                        "(default the first connected)")
    p.add_argument("--robot", choices=robots.names(), default=robots.DEFAULT,
                   help=f"the arm in the cell (env.robot; default {robots.DEFAULT}): --arm-joints takes one angle per "
                        "joint of it; --camera twin renders its scene")
    p.add_argument("--arm-joints", nargs="+", type=float, default=None, metavar="Q",
                   help="mecheye/realsense: the arm's joint angles (rad, one per joint of --robot) while the capture "
                        "is taken, saved with it so "
                        "that perception leaves the arm out (deploy --camera reads them from the controller itself); "
                        "without them the arm must be out of the camera's view")
    p.add_argument("--out", required=True, help="the capture file to write (.npz)")
    p.add_argument("--force", action="store_true", help="replace an existing --out file")
    twin = p.add_argument_group("--camera twin")
    twin.add_argument("--seed", type=int, default=0, help="scene draws (default 0)")
    twin.add_argument("--scene", type=int, default=0, help="the scene's index within the seed (default 0)")
    twin.add_argument("--scene-set", choices=("mix", "blocking"), default="mix",
                      help="mix (default: the evaluation mix) or blocking (an obstacle on every approach)")
    twin.add_argument("--camera-model", choices=CHOICES, default=DEFAULT_CAMERA,  # the registry when parsed
                      help=f"the camera the twin renders (task.camera's registered models; default {DEFAULT_CAMERA})")
    twin.add_argument("--depth-noise", choices=tuple(NOISE_MODELS), default=None,
                      help="depth-noise model (default the camera model's: industrial for the Mech-Eye)")
    twin.add_argument("--camera-resolution", type=float, default=0.25,
                      help="fraction of the camera model's pixels (default 0.25: 480 × 300 for the Mech-Eye)")
    return p


def _twin(args: object) -> capture_file.Capture:
    from sagrasp_jax.deploy import rehearse
    from sagrasp_jax.deploy.twin import PyBulletTwin
    from sagrasp_jax.task.config import Config
    from sagrasp_jax.task.config_parse import apply_overrides

    env_cfg = apply_overrides(Config(), [f"robot={args.robot}"]).env  # the arm's config (its home pose)
    scene_cfg = rehearse.scene_env(env_cfg, args.scene_set)
    spec, rng = rehearse.draw_scene(scene_cfg, args.seed, args.scene)
    camera = rehearse.camera_settings(args)  # the noise defaults to the camera model's
    kind = rehearse.episode_kind(spec, scene_cfg)
    with PyBulletTwin(spec, env_cfg, q0=spec.q0, seed=args.scene) as twin:
        return rehearse.twin_capture(twin, spec, camera, rng, kind,
                                     f"twin seed {args.seed} scene {args.scene} ({args.scene_set})")


def _check(args: object) -> None:
    if args.camera != "twin":
        given = [f for f, v in (("--seed", args.seed), ("--scene", args.scene), ("--scene-set", args.scene_set != "mix"),
                                ("--depth-noise", args.depth_noise), ("--camera-model", args.camera_model != DEFAULT_CAMERA),
                                ("--camera-resolution", args.camera_resolution != 0.25)) if v]
        if given:
            raise ValueError(f"{', '.join(given)} {'is' if len(given) == 1 else 'are'} only for --camera twin")
        if args.camera == "mecheye" and not args.camera_address:
            raise ValueError("--camera mecheye needs --camera-address IP")
        dof = robots.get(args.robot).dof
        if args.arm_joints is not None and not (len(args.arm_joints) == dof and all(
                math.isfinite(q) and abs(q) <= 2 * math.pi for q in args.arm_joints)):
            raise ValueError(f"--arm-joints {args.arm_joints} must be {dof} finite joint angles in rad (within "
                             f"±2π), one per joint of {args.robot}")
    else:
        if args.camera_address is not None or args.arm_joints is not None:
            raise ValueError("--camera-address and --arm-joints are for a real camera, not the twin (its arm is parked "
                             "out of view for the capture)")
        if not (0 <= args.seed < 2**31 and 0 <= args.scene < 2**31):
            raise ValueError(f"--seed and --scene must be in [0, 2^31), got {args.seed} and {args.scene}")
        if not 0.05 <= args.camera_resolution <= 1.0:
            raise ValueError(f"--camera-resolution must be in [0.05, 1], got {args.camera_resolution}")
        extras.require("twin", what="--camera twin (the PyBullet twin)")
    if os.path.exists(args.out) and not args.force:
        raise ValueError(f"--out {args.out} exists (add --force to replace it)")
    fileio.check_output_file(args.out)
    fileio.check_writable(os.path.dirname(os.path.abspath(args.out)))


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    with cli.at_safe_points():
        try:
            try:
                _check(args)
                if args.camera == "twin":
                    capture = _twin(args)
                else:
                    capture = capture_once(args.camera, args.camera_address, args.arm_joints)
                cli.check()
                capture_file.save_capture(args.out, capture)
            except (ValueError, CameraError, extras.MissingExtra, OSError) as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 2
        except cli.Interrupted:
            print(cli.interrupted_line("the capture was stopped", "nothing was written"), file=sys.stderr)
            return cli.INTERRUPTED
    valid = np.isfinite(capture.cloud_mm).all(axis=-1)
    h, w = valid.shape
    print(f"wrote {args.out}: {capture.camera or 'camera unknown'}, {w} × {h} px, {valid.mean():.1%} of the pixels with "
          f"a return, {capture.source}, {capture.time_utc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
