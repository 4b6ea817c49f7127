"""Deploy an exported policy on one detected cube: ``python -m sagrasp_jax.deploy``.

    python -m sagrasp_jax.deploy --policy policy/policy.npz --target-cam X Y Z [--units mm|m]
        [--target-yaw DEG] [--obstacle KIND X Y Z SIZE... ]... [--calibration FILE]
        [--backend twin] [--gui] [--json] [--dry-run]
    python -m sagrasp_jax.deploy ... --backend aubo --host IP [--port N] [--gripper-io SPEC] [--dry-run]
    python -m sagrasp_jax.deploy --backend aubo --host IP [--port N] --dry-run [--policy P] [--json]
    python -m sagrasp_jax.deploy --policy P --camera mecheye|realsense|replay:FILE [--camera-address A]
        [--record DIR] [--calibration FILE] [--backend twin|aubo --host IP] [--dry-run] [--json]

``--policy`` takes a ``policy.npz``, a folder holding one (a finished run folder, export's ``--out``) or the
name of a packaged policy, ``pretrained``; a name always means the packaged policy (``./pretrained`` for a
file or folder of that name).  ``--dry-run`` added to any deploy line checks everything the line says and
stops before the first motion, printing what it would do (the cube and obstacles in the world, the start
pose, the step cap; on the AUBO it also connects and says whether the arm stands at that pose).

Detections are camera-frame points as the depth camera reports them: the **top** of the cube
(and of each obstacle), in ``--units`` (default mm, the Mech-Eye's and the calibration's
unit).  They are mapped to the robot base frame with the hand-eye calibration, the top is
mapped to the centre, and the cube centre must lie in the trained region, every obstacle
outside the training clearance of the cube (``env.sampling.target_clearance``), and the
policy's control constants must be this robot's — all checked before the robot moves; bad
input exits with status 2 and says what is wrong (with ``--json``, as a JSON refusal).

From a camera (the paper's section 5, one command): ``--camera mecheye --camera-address IP`` (Mech-Eye,
``pip install "sagrasp_jax[mecheye]"``), ``--camera realsense [--camera-address SERIAL|RECORDING]`` (RealSense,
``[realsense]``) or ``--camera replay:FILE`` (a capture file: ``python -m sagrasp_jax.capture``, or the
``capture.npz`` an earlier run saved) takes the detections instead of ``--target-cam`` and ``--obstacle``: one
capture, perceived with the policy's obstacle kinds (``deploy.perception``), the calibration checked against the
table on the way (the table must come out at its height, within 10 mm, and level, within 2°, through
``--calibration``; else exit 2 naming the measured offset and tilt).  The capture and the report are saved in
``--record DIR`` (default ``deploy-records/<UTC time>-<camera>``; a replay saves the report only), so a grasp
that failed on the cell can be run again at a desk: ``--camera replay:DIR/capture.npz --backend twin`` (the
twin's cube stands where the detection says; a twin capture holds its true scene and the twin stands on it) or
``--dry-run``, which also prints the detection, perception's diagnostics and the first joint targets an ideal arm
would be sent.

Obstacles (``shapes.SHAPES``): ``--obstacle sphere X Y Z R``, ``--obstacle cylinder X Y Z R H``,
``--obstacle box X Y Z LX LY LZ [YAW_DEG]`` (full lengths; LX along the camera's x axis
turned by YAW_DEG about its optical axis), ``--obstacle capsule X Y Z R L [YAW_DEG]`` (lying on
the table, L tip to tip along the camera's x axis turned by YAW_DEG), at most two.

The twin's cube stands on the table where the detection says (its centre half its height above the
table: the loop takes the cube's height as known, ``calibration.standing_cube_centre``).  Rehearsing
transfer errors on the twin: ``--twin-latency STEPS`` delays every command by that many control steps
(fractions blend two commands, as in training), ``--twin-servo-lag`` makes the arm follow through the
fitted servo model (``--twin-servo-gain F`` scales its gain, one factor or one per joint),
``--twin-joint-offset RAD`` (one value or one per joint) and ``--twin-joint-noise RAD`` put a calibration
offset and noise on the joint readings, and ``--twin-target-error DX DY DZ`` (in ``--units``) moves the
detection the loop is handed away from the twin's cube, never the cube itself: the grasp-and-lift says
whether the cube came along anyway.  ``python -m sagrasp_jax.deploy.rehearse`` runs the same loop over
many random scenes in the MJX evaluation's named conditions.

The real AUBO-i5 (``--backend aubo --host IP``, ``pip install "sagrasp_jax[aubo]"``, ``deploy.aubo``): the
controller's RPC service (``--port``, default 30004; the login from $AUBO_USER / $AUBO_PASSWORD, default the
factory's), one ``servoJoint`` per control period, every target through the same safety layer.  The arm must
stand within ``--home-tolerance`` rad of the policy's home pose (else exit 2, nothing moved); the gripper is
driven by the tool outputs of ``--gripper-io`` (configurable, untested on hardware).  ``--dry-run`` alone
(no ``--target-cam``) only connects and reports the joints and whether the arm is at home (exit 0 at home, 1
not, 2 no connection).  A refused or silent controller exits 2 naming host and port.  Ctrl-C stops the episode
before its next command, closes the session (servo mode left, logged out) and exits 130 with one line saying so.

Exit status: 0 the cube is held after the lift (with --no-grasp: the grasp pose reached), 1 not held
(timeout, collision, a faulty approach, a dropped cube, or a backend that cannot tell: the JSON report's
``held`` says which), 2 input refused before anything moved (a refused camera, capture or perception too), 3 the
safety layer stopped the robot or the controller's connection was lost during the episode.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import typing
from typing import Any, Sequence

import numpy as np

from sagrasp_jax.deploy.calibration import (
    CalibrationError,
    CameraCalibration,
    TargetRejected,
    _unit_scale,
    detected_top_to_cube_centre,
    standing_cube_centre,
    validate_target,
)
from sagrasp_jax.base import cli, extras, fileio
from sagrasp_jax.deploy.cameras import CAMERAS, CameraError, capture_once
from sagrasp_jax.task import shapes
from sagrasp_jax.deploy.loop import (
    DeployError, Obstacle, format_report, plan_episode, run_episode, scene_spec, with_obstacle_kinds,
)
from sagrasp_jax.task import robot as robot_mod
from sagrasp_jax.task import robots
from sagrasp_jax.deploy import aubo
from sagrasp_jax.deploy.safety import SafetyViolation, check_policy_constants, check_policy_scene, deployment_env
from sagrasp_jax.deploy.transfer import TransferErrors
from sagrasp_jax.task.policy_file import POLICY_HELP, PRETRAINED, PolicyFormatError, load_policy

BACKENDS = ("twin", "aubo")
CAMERA_SOURCES = (*CAMERAS, "replay")  # --camera for one deploy (twin: deploy.rehearse's many scenes)
UNITS = ("mm", "m")
DETECTION_RANGE = (0.3, 3.0)  # m from the camera: where a depth camera over the table can see anything
OBSTACLE_SIZE_RANGE = (0.005, 0.5)  # m, any obstacle dimension
CELL_BOX = ((-1.0, -1.2, -0.05), (1.0, 0.6, 1.5))  # m, world box an obstacle centre must lie in
MAX_YAW_DEG = 360.0
MAX_BASE_Z_OFFSET = 0.5  # m; the controller base is within half a metre of the URDF's
MAX_STEPS = 100_000
RECORDS_DIR = "deploy-records"  # --camera's default --record parent folder, in the working directory
PLANNED_COMMANDS_SHOWN = 5  # --dry-run prints this many of the first joint targets an ideal arm would be sent


class InputRefused(ValueError):
    """Command-line input that must not reach the robot."""


def _camera_point(values: Sequence[float], units: str, what: str) -> np.ndarray:
    """A detected camera-frame point in metres, refused if NaN or implausibly near/far (units)."""
    p = np.asarray(values, dtype=float) * _unit_scale(units)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise InputRefused(f"{what}: camera point {list(values)} must be 3 finite numbers")
    dist = float(np.linalg.norm(p))
    if not DETECTION_RANGE[0] <= dist <= DETECTION_RANGE[1]:
        other = "m" if units == "mm" else "mm"
        raise InputRefused(
            f"{what}: camera point {list(values)} {units} is {dist:.4g} m from the camera, outside the "
            f"depth camera's range [{DETECTION_RANGE[0]}, {DETECTION_RANGE[1]}] m: wrong units? "
            f"(given --units {units}; try --units {other})"
        )
    return p


def camera_yaw_to_world(cal: CameraCalibration, yaw_cam: float, symmetry: float = 2 * math.pi) -> float:
    """A yaw about the camera's optical axis -> yaw about world z (the camera looks ≈ straight down),
    wrapped into [−symmetry/2, symmetry/2) for a shape that looks the same turned by ``symmetry``."""
    direction = cal.matrix[:3, :3] @ np.array([math.cos(yaw_cam), math.sin(yaw_cam), 0.0])
    yaw = math.atan2(direction[1], direction[0])
    return (yaw + symmetry / 2) % symmetry - symmetry / 2


def parse_obstacle(tokens: Sequence[str], cal: CameraCalibration, units: str, index: int) -> Obstacle:
    """``KIND X Y Z SIZE...`` (camera frame, top point) -> a world-frame ``Obstacle``."""
    what = f"--obstacle #{index + 1}"
    if not tokens or tokens[0] not in shapes.BY_NAME:
        raise InputRefused(f"{what}: first value must be one of {', '.join(shapes.NAMES)}, got {list(tokens)[:1]}")
    kind = tokens[0]
    shape = shapes.BY_NAME[kind]
    try:
        numbers = [float(t) for t in tokens[1:]]
    except ValueError:
        raise InputRefused(f"{what}: {' '.join(tokens)}: every value after the kind must be a number") from None
    n_lengths = len(shape.cli_lengths)
    if len(numbers) - 3 not in ((n_lengths, n_lengths + 1) if shape.yawed else (n_lengths,)):
        raise InputRefused(f"{what}: {kind} takes {shape.cli_usage}, got {len(numbers)} numbers")
    top = cal.cam_to_base(_camera_point(numbers[:3], units, what))
    scale = _unit_scale(units)
    lengths = [v * scale for v in numbers[3 : 3 + n_lengths]]
    for v in lengths:
        if not (math.isfinite(v) and OBSTACLE_SIZE_RANGE[0] <= v <= OBSTACLE_SIZE_RANGE[1]):
            raise InputRefused(
                f"{what}: {kind} dimension {v:.4g} m is outside [{OBSTACLE_SIZE_RANGE[0]}, {OBSTACLE_SIZE_RANGE[1]}] m "
                f"(given in {units})"
            )
    try:
        size = tuple(float(v) for v in shape.from_lengths(lengths))
    except ValueError as exc:
        raise InputRefused(f"{what}: {kind}: {exc}") from None
    yaw = 0.0
    if shape.yawed:
        yaw_deg = numbers[3 + n_lengths] if len(numbers) == 4 + n_lengths else 0.0
        if not (math.isfinite(yaw_deg) and abs(yaw_deg) <= MAX_YAW_DEG):
            raise InputRefused(f"{what}: {kind} yaw {yaw_deg} deg must be a finite angle within ±{MAX_YAW_DEG:g} deg")
        yaw = camera_yaw_to_world(cal, math.radians(yaw_deg), shapes.yaw_symmetry(shape))
    centre = top - np.array([0.0, 0.0, float(shape.half_height(np.asarray(size)))])
    lo, hi = CELL_BOX
    if not all(lo[i] <= centre[i] <= hi[i] for i in range(3)):
        raise InputRefused(
            f"{what}: {kind} centre {np.round(centre, 4).tolist()} m (world) is outside the cell {lo}..{hi} m: "
            "wrong units or calibration?"
        )
    return Obstacle(kind, tuple(float(v) for v in centre), size, yaw)


class _Parser(cli.Parser):
    """One-line refusals naming a mistyped option's nearest one (``cli.Parser``); with ``--json`` on the command
    line, argparse's own refusals are JSON refusals too."""

    json_argv: list[str] | None = None

    def error(self, message: str) -> typing.NoReturn:
        if self.json_argv is not None:
            print(json.dumps({"outcome": "input_refused", "message": message, "input": {"argv": self.json_argv}},
                             indent=2, allow_nan=False))
            print(f"error: refused before moving: {message}", file=sys.stderr)
            sys.exit(2)
        super().error(message)


def _obstacle_help() -> str:
    """--obstacle's help: every registered kind's numbers and what they mean (``shapes.SHAPES``' ``cli_lengths``
    and ``cli_help``)."""
    kinds = " | ".join(f"{s.name} {s.cli_usage}" for s in shapes.SHAPES)
    meanings: dict[str, str] = {}
    for shape in shapes.SHAPES:
        for letter, text in zip(shape.cli_lengths, shape.cli_help or shape.cli_lengths):
            meanings.setdefault(letter, text)
    meaning = ", ".join(m for m in meanings.values() if m)
    return ("a detected obstacle, repeatable (at most the policy's env.sampling.max_obstacles, 2): its kind, then X Y Z "
            "the top of the obstacle (the highest point the depth camera sees on it) in the camera frame, then its "
            f"sizes; every number but YAW_DEG (degrees) in --units: {kinds}; {meaning}")


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog="python -m sagrasp_jax.deploy", description=__doc__.split("\n\n")[0],
                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 2)[2])
    p.add_argument("--policy", required=True, help=POLICY_HELP)
    p.add_argument("--camera", default=None, metavar="SOURCE",
                   help="where the cube and the obstacles come from, instead of --target-cam and --obstacle: "
                        "mecheye (--camera-address IP), realsense (--camera-address SERIAL or a recording, .db3 or .bag; default "
                        "the first connected), or replay:FILE (a capture file of python -m sagrasp_jax.capture or of an "
                        "earlier deploy's --record folder); one capture, perceived (deploy.perception), the calibration "
                        "checked against the table.  (--camera twin --scenes N rehearses many rendered scenes)")
    p.add_argument("--camera-address", default=None, metavar="ADDRESS",
                   help="--camera mecheye: the camera's IP address; realsense: its serial number or a recording (.db3 as librealsense records, or .bag)")
    p.add_argument("--record", default=None, metavar="DIR",
                   help=f"with --camera: the folder the capture (capture.npz) and the report (report.json) are saved "
                        f"in (default {RECORDS_DIR}/<UTC time>-<camera>; a replay saves the report only); an existing "
                        "folder must be empty")
    p.add_argument("--target-cam", nargs=3, type=float, default=None, metavar=("X", "Y", "Z"),
                   help="the cube as the depth camera reports it: the centre of its top face, in the camera frame, in "
                        "--units (default mm); its centre is taken half the cube's height below, standing on the table "
                        "(or --camera)")
    p.add_argument("--target-yaw", type=float, default=0.0, metavar="DEG", help="cube yaw about the optical axis (default 0)")
    p.add_argument("--units", choices=UNITS, default="mm", help="units of the detections (default mm)")
    p.add_argument("--obstacle", nargs="+", action="append", default=[], metavar="VALUE",
                   help=_obstacle_help())
    p.add_argument("--calibration", default=None, help="4×4 camera->base matrix (.json/.npy/.txt, as python -m "
                   "sagrasp_jax.calibrate writes it; default the paper's printed calibration, built in)")
    p.add_argument("--calibration-units", choices=UNITS, default="mm", help="translation units of --calibration")
    p.add_argument("--base-z-offset", type=float, default=0.0, help="controller base height in the URDF frame, m")
    p.add_argument("--base-yaw", type=float, default=0.0, help="controller base yaw about z relative to the URDF, rad")
    p.add_argument("--backend", choices=BACKENDS, default="twin", help="robot backend (default: PyBullet twin)")
    p.add_argument("--gui", action="store_true", help="open the PyBullet viewer (twin)")
    p.add_argument("--host", default=None, help="aubo: the controller's IP address or host name")
    p.add_argument("--port", type=int, default=None, help=f"aubo: its RPC port (default {aubo.DEFAULT_PORT})")
    p.add_argument("--dry-run", action="store_true",
                   help="check everything and stop before the first motion: print what would be done (the cube and "
                        "obstacles in the world, the start pose, the step cap); with --backend aubo also connect and "
                        "report the joints and whether the arm is at home (exit 0 at home, 1 not); nothing is "
                        "commanded.  Without --target-cam: the AUBO's read-only check alone")
    p.add_argument("--gripper-io", default=None, metavar="SPEC",
                   help=f"aubo: tool outputs that drive the gripper (default {aubo.GripperIO().describe()}; untested)")
    p.add_argument("--home-tolerance", type=float, default=None, metavar="RAD",
                   help=f"aubo: largest joint distance from home to start from (default {aubo.HOME_TOLERANCE})")
    p.add_argument("--max-steps", type=int, default=None, help="step cap (default: the policy's env.task.max_steps)")
    p.add_argument("--no-grasp", action="store_true", help="stop at the grasp pose: do not close the gripper and lift")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--twin-latency", type=float, default=0.0, metavar="STEPS",
                   help="twin: command latency in control steps (default 0)")
    p.add_argument("--twin-servo-lag", action="store_true", help="twin: joints follow commands through the servo model")
    p.add_argument("--twin-servo-gain", type=float, nargs="+", default=[1.0], metavar="F",
                   help="twin: servo-model gain factor with --twin-servo-lag, one or one per joint (default 1)")
    p.add_argument("--twin-joint-offset", type=float, nargs="+", default=[0.0], metavar="RAD",
                   help="twin: offset of the joint readings, one or one per joint (default 0)")
    p.add_argument("--twin-joint-noise", type=float, default=0.0, metavar="RAD",
                   help="twin: std of the joint-reading noise (default 0)")
    p.add_argument("--twin-start-q", nargs="+", type=float, default=None, metavar="Q",
                   help="twin: the arm's start joints, rad, one per joint of the policy's robot (default the "
                        "policy's home pose)")
    p.add_argument("--twin-target-error", nargs=3, type=float, default=None, metavar=("DX", "DY", "DZ"),
                   help="twin: the detection's error, in --units (world axes): the loop is handed the detection "
                        "moved by this, the twin's cube stays where it stands")
    return p


MAX_TARGET_ERROR = 0.05  # m per axis: a larger detection error is a wrong detection, not an error to rehearse


def _json_safe(value: Any) -> Any:
    """NaN/inf as the strings "nan", "inf", "-inf" (strict JSON has no such numbers; a refusal
    must still echo what it was given)."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def _emit(args: argparse.Namespace, payload: dict[str, Any], text: str, error: bool = False) -> None:
    """The report on stdout (JSON with --json); a refusal's message also on stderr; with a ``--record`` folder
    (``--camera``) also its ``report.json``."""
    record = getattr(args, "record_dir", None)
    if record is not None:
        path = os.path.join(record, "report.json")
        try:
            fileio.atomic_write_json(path, _json_safe(payload))
            text += f"\nsaved {path}" if not error else ""
        except OSError as exc:
            print(f"warning: could not save {path}: {exc}", file=sys.stderr)
    if args.json:
        print(json.dumps(_json_safe(payload), indent=2, allow_nan=False))
    if error or not args.json:
        print(text, file=sys.stderr if error else sys.stdout)


def _twin_errors(args: argparse.Namespace, model: robot_mod.RobotModel) -> tuple[TransferErrors, np.ndarray]:
    """The twin's transfer errors for the policy's arm ``model`` and the detection error the loop is handed (m,
    world axes)."""
    for name in ("twin_servo_gain", "twin_joint_offset"):
        if len(getattr(args, name)) not in (1, model.dof):
            flag = "--" + name.replace("_", "-")
            raise InputRefused(f"{flag} takes one value or one per joint ({model.dof} for {model.name}), "
                               f"got {len(getattr(args, name))}")
    one = lambda v: v[0] if len(v) == 1 else tuple(v)  # noqa: E731
    try:
        errors = TransferErrors(latency=args.twin_latency, servo_lag=args.twin_servo_lag,
                                servo_gain=one(args.twin_servo_gain), joint_offset=one(args.twin_joint_offset),
                                joint_noise=args.twin_joint_noise, dof=model.dof)
    except ValueError as exc:
        raise InputRefused(f"--twin-*: {exc}") from None
    if args.twin_target_error is None:
        return errors, np.zeros(3)
    offset = np.asarray(args.twin_target_error, dtype=float) * _unit_scale(args.units)
    if not (np.isfinite(offset).all() and np.all(np.abs(offset) <= MAX_TARGET_ERROR)):
        raise InputRefused(f"--twin-target-error {args.twin_target_error} {args.units} must be finite and within "
                           f"±{MAX_TARGET_ERROR * 1000:g} mm per axis")
    return errors, offset


# ---- the real AUBO-i5 (deploy.aubo, the [aubo] extra) ----

AUBO_OPTIONS = ("host", "port", "gripper_io", "home_tolerance")


def _flags(names: Sequence[str]) -> str:
    return ", ".join("--" + n.replace("_", "-") for n in names)


def _aubo_settings(args: argparse.Namespace) -> aubo.AuboSettings | None:
    """The AUBO adapter's settings from the command line (None for another backend); refuses AUBO options
    without ``--backend aubo``, twin rehearsal options with it, a missing ``--host`` and a missing SDK."""
    if args.backend != "aubo":
        stray = [n for n in AUBO_OPTIONS if getattr(args, n, None) is not None]
        if stray:
            raise InputRefused(f"{_flags(stray)} {'is' if len(stray) == 1 else 'are'} only for --backend aubo")
        return None
    twin_flags = _twin_flags(args)
    if twin_flags:
        raise InputRefused(f"{_flags(twin_flags)} rehearse on the PyBullet twin; with --backend aubo they are refused")
    if not args.host:
        raise InputRefused("--backend aubo needs --host IP (the controller's address)")
    tolerance = aubo.HOME_TOLERANCE if args.home_tolerance is None else args.home_tolerance
    if not (math.isfinite(tolerance) and 0 < tolerance <= 0.5):
        raise InputRefused(f"--home-tolerance {tolerance} rad must be in (0, 0.5]")
    try:
        settings = aubo.AuboSettings(
            port=aubo.DEFAULT_PORT if args.port is None else args.port,
            user=os.environ.get("AUBO_USER", aubo.DEFAULT_USER),
            password=os.environ.get("AUBO_PASSWORD", aubo.DEFAULT_PASSWORD),
            gripper=aubo.GripperIO.parse(args.gripper_io) if args.gripper_io is not None else aubo.GripperIO())
    except ValueError as exc:
        raise InputRefused(f"--backend aubo: {exc}") from None
    aubo.import_sdk()  # a missing SDK is refused here (exit 2, the install hint), before anything connects
    return settings


def _twin_flags(args: argparse.Namespace) -> list[str]:
    """The twin-only options given a non-default value (``--gui``, ``--twin-*``)."""
    defaults = _parser()
    return [k for k, v in vars(args).items() if (k == "gui" or k.startswith("twin_")) and v != defaults.get_default(k)]


def _aubo_robot(args: argparse.Namespace, settings: aubo.AuboSettings, q_home: np.ndarray) -> aubo.AuboRobot:
    """Connect, refuse an arm that is not at the home pose the policy starts from, open the gripper."""
    robot = aubo.AuboRobot(args.host, settings=settings, log=lambda line: print(line, file=sys.stderr))
    try:
        tolerance = aubo.HOME_TOLERANCE if args.home_tolerance is None else args.home_tolerance
        check = aubo.home_check(robot.read_joints(), q_home, tolerance)
        if not check.at_home:
            raise aubo.AuboError(f"the arm is {math.degrees(check.max_error):.2f}° from the home pose on its farthest "
                                 f"joint (tolerance {math.degrees(tolerance):.2f}°): move it home on the teach "
                                 "pendant first (--dry-run shows the joints)")
        robot.open_gripper()
    except BaseException:
        robot.close()
        raise
    return robot


def _dry_run_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="python -m sagrasp_jax.deploy",
                description="Read-only check of the AUBO-i5: connect, report the joints and whether the arm is at the "
                            "home pose; nothing is commanded.  Exit 0 at home, 1 not at home, 2 no connection.  (A "
                            "whole deploy line with --dry-run added checks it all and stops before the first motion.)")
    p.add_argument("--dry-run", action="store_true", required=True)
    p.add_argument("--backend", choices=BACKENDS, required=True)
    p.add_argument("--host", required=True)
    p.add_argument("--port", type=int, default=None)
    p.add_argument("--policy", default=None, help="its env.task.home_q is the home pose (default: the config's); "
                   + POLICY_HELP[len("the policy: "):])
    p.add_argument("--home-tolerance", type=float, default=None, metavar="RAD")
    p.add_argument("--gripper-io", default=None, metavar="SPEC",
                   help="only echoed: the dry run never touches the gripper")
    p.add_argument("--json", action="store_true")
    return p


def _camera_scenes(tokens: list[str]) -> int:
    """``--backend twin --camera twin --policy P --scenes N``: render, perceive, deploy, grasp and lift over N
    random twin scenes (``deploy.rehearse`` with its camera): the held rate and perception's errors."""
    from sagrasp_jax.deploy import rehearse

    p = cli.Parser(prog="python -m sagrasp_jax.deploy --camera twin", description=_camera_scenes.__doc__.split("\n")[0])
    p.add_argument("--camera", choices=("twin",), required=True, help="the twin's rendered Mech-Eye capture")
    p.add_argument("--backend", choices=("twin",), default="twin", help="only the twin (a real camera and arm "
                   "run one scene at a time)")
    p.add_argument("--policy", required=True, help=POLICY_HELP)
    p.add_argument("--scenes", type=int, default=100, help="random scenes (default 100)")
    p.add_argument("--scene-set", dest="scenes_kind", choices=rehearse.SCENE_SETS, default="mix",
                   help="mix (default) or blocking")
    p.add_argument("--condition", choices=sorted(rehearse.EVAL_CONDITIONS), default="kinematic",
                   help="the arm's transfer errors, a named evaluation condition (default kinematic: none; the "
                        "detection error is the camera's own)")
    rehearse.add_camera_arguments(p)  # --camera-model, --depth-noise, --camera-resolution, --camera-driver
    p.add_argument("--seed", type=int, default=0, help="scene draws (default 0)")
    p.add_argument("--workers", type=int, default=1, help="processes (default 1)")
    p.add_argument("--save-captures", default=None, metavar="DIR",
                   help="save every scene's capture in DIR (replayable: --camera replay:FILE), read back and perceived "
                        "again; the result counts the replays that saw exactly the same")
    p.add_argument("--out", default=None, help="write the result as JSON here (an existing file only if it holds the "
                   "same twin result, or another one with --force)")
    p.add_argument("--force", action="store_true", help="replace an --out file that holds another twin result")
    args = p.parse_args(tokens)
    if not 1 <= args.scenes <= rehearse.MAX_EPISODES:
        print(f"error: --scenes must be in [1, {rehearse.MAX_EPISODES}], got {args.scenes}", file=sys.stderr)
        return 2
    args.episodes, args.scenes = args.scenes, args.scenes_kind
    return rehearse.run_cli(args.policy, args)


def _check_aubo_robot(env_cfg: Any, source: str) -> None:
    """Refuse a policy trained for another arm than the one the AUBO driver drives (its joints would not be
    the controller's)."""
    if env_cfg.robot != aubo.ROBOT:
        raise InputRefused(f"{source} was trained for the robot {env_cfg.robot!r}; --backend aubo drives the "
                           f"{aubo.ROBOT!r} only (the twin, --backend twin, serves every registered robot)")


def _home_of(policy_arg: str | None) -> np.ndarray:
    """The AUBO's home pose: the policy's ``env.task.home_q`` (refused unless it is an AUBO policy), else the
    AUBO's registered one."""
    if policy_arg is None:
        return np.asarray(robots.get(aubo.ROBOT).home_q, dtype=float)
    policy = load_policy(policy_arg)
    policy.check_grasp_inputs()
    _check_aubo_robot(policy.env_config(), policy_arg)
    return np.asarray(policy.env_config().task.home_q, dtype=float)


def _aubo_dry_run(tokens: list[str]) -> int:
    """``--backend aubo --host IP --dry-run`` without a detection: the controller's read-only check alone."""
    parser = _dry_run_parser()
    if "--json" in tokens:
        parser.json_argv = tokens
    args = parser.parse_args(tokens)
    if args.backend != "aubo":
        parser.error("--dry-run without --target-cam is the AUBO's read-only check (--backend aubo --host IP); to "
                     "check a deploy line on the twin without running it, add --dry-run to the whole line")
    given = {"backend": "aubo", "host": args.host, "port": args.port, "dry_run": True}
    with cli.at_safe_points():
        try:
            settings = _aubo_settings(args)
            home = _home_of(args.policy)
            with aubo.AuboRobot(args.host, settings=settings, log=lambda line: print(line, file=sys.stderr)) as robot:
                report = robot.dry_run(home, aubo.HOME_TOLERANCE if args.home_tolerance is None else args.home_tolerance)
            cli.check()
        except (InputRefused, PolicyFormatError, ValueError, extras.MissingExtra, DeployError) as exc:
            _emit(args, {"outcome": "input_refused", "message": str(exc), "input": given},
                  f"error: refused before moving: {exc}", error=True)
            return 2
        except cli.Interrupted:
            print(cli.interrupted_line("the read-only check was stopped and the controller session closed",
                                       "nothing was commanded or written"), file=sys.stderr)
            return cli.INTERRUPTED
    _emit(args, report.to_dict(), report.format())
    return 0 if report.home.at_home else 1


def _policy_name(arg: str) -> str:
    return arg if arg in PRETRAINED else os.path.abspath(arg)


def _plan(args: argparse.Namespace, given: dict[str, Any], q_home: np.ndarray, steps: int) -> tuple[dict[str, Any], str]:
    """What a deploy line would do (``--dry-run``), as JSON and as text."""
    where = "the PyBullet twin" if args.backend == "twin" else f"the AUBO-i5 at {args.host}"
    plan = {"backend": args.backend, "policy": _policy_name(args.policy), "start_q": [float(v) for v in q_home],
            "max_steps": steps, "grasp": not args.no_grasp, "calibration": given["calibration"],
            "target_world": given["target_world"], "target_yaw_world": given["target_yaw_world"],
            "obstacles_world": given["obstacles_world"]}
    fmt = lambda v: "(" + ", ".join(f"{x:.4f}" for x in v) + ")"  # noqa: E731
    lines = [f"dry run: would deploy {plan['policy']} on {where}; nothing was commanded",
             f"  cube centre    {fmt(given['target_world'])} m (world), yaw {math.degrees(given['target_yaw_world']):.1f}°",
             *(f"  obstacle       {o['kind']} at {fmt(o['centre'])} m, size {fmt(o['size'])} m, yaw "
               f"{math.degrees(o['yaw']):.1f}°" for o in given["obstacles_world"]),
             f"  start pose     [{', '.join(f'{math.degrees(v):.2f}' for v in q_home)}]° (the arm must stand there)",
             f"  at most        {steps} policy steps, then " + ("stop at the grasp pose (--no-grasp)" if args.no_grasp
                                                               else "slide over the cube, close and lift 5 cm"),
             f"  calibration    {given['calibration']}"]
    seen = given.get("perception")
    if seen is not None:
        capture = given["capture"]
        plan["perception"] = seen
        n = seen["table_normal"]
        lines += [f"  capture        {capture['camera'] or 'camera unknown'}, {capture['pixels'][0]} × {capture['pixels'][1]} px, "
                  f"{capture['source'] or 'source unknown'}, {capture['time_utc'] or 'time unknown'}",
                  f"  perception     cube by {seen['cube_by']}, top face {seen['cube_face_mm'][0]:.1f} × "
                  f"{seen['cube_face_mm'][1]:.1f} mm ({seen['cube_top_points']} points); {len(seen['obstacles_world'])} "
                  f"obstacle(s); table σ {seen['table_sigma_mm']:.2f} mm, "
                  f"{math.degrees(math.acos(min(1.0, n[2]))):.2f}° from level; {seen['seconds']:.2f} s"]
    planned = given.get("planned")
    if planned is not None:
        plan["planned"] = planned
        if planned["ideal_arm_outcome"] == "refused":
            lines.append(f"  planned        the loop refused on an ideal arm: {planned['message']}")
        else:
            lines.append(f"  planned        on an ideal arm: {planned['ideal_arm_outcome']} after {planned['ideal_arm_steps']} "
                         f"steps; the first joint targets (°):")
            lines += ["                 [" + ", ".join(f"{math.degrees(v):.2f}" for v in q) + "]"
                      for q in planned["first_commands_rad"]]
    return plan, "\n".join(lines)


def _option_value(tokens: Sequence[str], option: str) -> str | None:
    """The value given to ``option`` on a command line (``--opt V`` or ``--opt=V``), None when absent."""
    for i, token in enumerate(tokens):
        if token == option and i + 1 < len(tokens):
            return tokens[i + 1]
        if token.startswith(option + "="):
            return token.split("=", 1)[1]
    return None


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    tokens = list(sys.argv[1:] if argv is None else argv)
    if _option_value(tokens, "--camera") == "twin":  # end to end from the twin's camera over many scenes
        return _camera_scenes(tokens)
    if "--dry-run" in tokens and not any(t.split("=", 1)[0] in ("--target-cam", "--camera") for t in tokens):
        return _aubo_dry_run(tokens)  # the AUBO's read-only check: no policy or detection needed
    if "--json" in tokens:
        parser.json_argv = tokens
    args = parser.parse_args(tokens)
    with cli.at_safe_points():
        try:
            return _deploy(args)
        except cli.Interrupted as exc:
            print(exc.args[0] if exc.args else cli.interrupted_line("stopped before anything connected or moved",
                                                                     "nothing was written"), file=sys.stderr)
            return cli.INTERRUPTED


def _check_detection_source(args: argparse.Namespace) -> None:
    """Exactly one source of the detection: ``--target-cam`` (with ``--obstacle``s) typed, or ``--camera``."""
    if (args.camera is None) == (args.target_cam is None):
        raise InputRefused("give the cube either as --target-cam X Y Z (typed) or --camera SOURCE (captured and "
                           "perceived), " + ("not both" if args.camera is not None else "one of them"))
    if args.camera is None:
        for name in ("camera_address", "record"):
            if getattr(args, name) is not None:
                raise InputRefused(f"{_flags([name])} is only for --camera")
        return
    kind = args.camera.split(":", 1)[0]
    if kind not in CAMERA_SOURCES:
        raise InputRefused(f"--camera {args.camera!r}: one of mecheye, realsense, replay:FILE (or twin with --scenes)")
    if kind == "replay" and not args.camera[len("replay:"):]:
        raise InputRefused("--camera replay:FILE needs the capture file's path after the colon")
    if kind == "replay" and args.camera_address is not None:
        raise InputRefused("--camera-address is for a camera; a replay reads its FILE")
    if kind == "mecheye" and not args.camera_address:
        raise InputRefused("--camera mecheye needs --camera-address IP (the camera's address)")
    given = [flag for flag, value in (("--obstacle", args.obstacle), ("--target-yaw", args.target_yaw),
                                      ("--twin-target-error", args.twin_target_error)) if value]
    if given:
        raise InputRefused(f"{', '.join(given)}: with --camera the perception finds the cube, its yaw and the obstacles, "
                           "and its own error is the detection's; type them only with --target-cam")


def _record_dir(args: argparse.Namespace, kind: str) -> str:
    """The ``--record`` folder, created empty (an existing one must be empty: nothing of another run is mixed in)."""
    import datetime

    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%d-%H%M%S")
    folder = args.record or os.path.join(RECORDS_DIR, f"{stamp}-{kind}")
    if os.path.isdir(folder) and os.listdir(folder):
        raise InputRefused(f"--record {folder}: the folder is not empty (give a new one)")
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise InputRefused(f"--record {folder}: not a folder")
    fileio.check_writable(folder, "--record folder")
    return folder


def _arm_joints_now(args: argparse.Namespace, env_cfg: Any, aubo_settings: aubo.AuboSettings | None) -> np.ndarray:
    """Where the arm stands for a live capture, so that perception leaves it out of the scene: the AUBO's joints
    read from the controller (a read-only session), on the twin its start pose."""
    if args.backend == "aubo":
        with aubo.AuboRobot(args.host, settings=aubo_settings, log=lambda line: print(line, file=sys.stderr)) as robot:
            return np.asarray(robot.read_joints(), dtype=float)
    return np.asarray(env_cfg.task.home_q if args.twin_start_q is None else args.twin_start_q, dtype=float)


def _perceive_camera(args: argparse.Namespace, cal: CameraCalibration, env_cfg: Any, given: dict[str, Any],
                     aubo_settings: aubo.AuboSettings | None = None) -> tuple[Any, Any]:
    """One capture from ``--camera`` (saved into the record folder unless it is a replay), perceived with the
    policy's obstacle kinds and the arm left out where it stood (``Capture.robot_q``); the calibration is checked
    against the table on the way (``perception.fit_table``)."""
    from sagrasp_jax.deploy import capture_file, perception

    kind = args.camera.split(":", 1)[0]
    args.record_dir = _record_dir(args, kind)
    if kind == "replay":
        path = args.camera[len("replay:"):]
        capture = capture_file.load_capture(path)
        given["capture_file"] = os.path.abspath(path)
    else:
        # the arm is in the camera's view at home; a Ctrl-C meanwhile stops at the next safe point, after the capture
        capture = capture_once(kind, args.camera_address, _arm_joints_now(args, env_cfg, aubo_settings))
        path = capture_file.save_capture(os.path.join(args.record_dir, "capture.npz"), capture)
        given["capture_file"] = os.path.abspath(path)
        print(f"saved {path}", file=sys.stderr)
    given["capture"] = {"camera": capture.camera, "source": capture.source, "time_utc": capture.time_utc,
                        "pixels": [int(capture.cloud_mm.shape[1]), int(capture.cloud_mm.shape[0])],
                        "intrinsics": capture.intrinsics.as_list() if capture.intrinsics is not None else None,
                        "robot_q": list(capture.robot_q) if capture.robot_q is not None else None}
    settings = perception.PerceptionSettings.for_policy(env_cfg)
    seen = perception.detect_scene(capture.cloud_mm, capture.rgb, cal, env_cfg.sampling.target_size,
                                   robot_q=capture.robot_q, robot_model=robot_mod.load_robot(env_cfg.robot),
                                   settings=settings)
    d = seen.diagnostics
    given["perception"] = {
        "target_world": [float(v) for v in seen.target_centre], "target_yaw_world": float(seen.target_yaw),
        "obstacles_world": [{"kind": o.kind, "centre": list(o.centre), "size": list(o.size), "yaw": o.yaw}
                            for o in seen.obstacles],
        "table_normal": d["plane_normal"], "table_sigma_mm": d["plane_sigma_mm"], "valid_points": d["valid_points"],
        "cube_top_points": d["cube_top_points"], "cube_face_mm": d["cube_face_mm"], "cube_by": d["cube_by"],
        "obstacle_fits": d["obstacles"], "seconds": d["seconds"]}
    return capture, seen


def _deploy(args: argparse.Namespace) -> int:
    given: dict[str, Any] = {"target_cam": args.target_cam, "units": args.units, "target_yaw_cam_deg": args.target_yaw,
                             "obstacles_cam": args.obstacle, "backend": args.backend, "camera": args.camera}
    try:
        _check_detection_source(args)
        if args.max_steps is not None and not 1 <= args.max_steps <= MAX_STEPS:
            raise InputRefused(f"--max-steps must be in [1, {MAX_STEPS}], got {args.max_steps}")
        if not (math.isfinite(args.target_yaw) and abs(args.target_yaw) <= MAX_YAW_DEG):
            raise InputRefused(f"--target-yaw {args.target_yaw} must be a finite angle within ±{MAX_YAW_DEG:g} deg")
        if not (math.isfinite(args.base_z_offset) and abs(args.base_z_offset) <= MAX_BASE_Z_OFFSET):
            raise InputRefused(f"--base-z-offset {args.base_z_offset} must be finite and within ±{MAX_BASE_Z_OFFSET:g} m")
        if not (math.isfinite(args.base_yaw) and abs(args.base_yaw) <= math.pi):
            raise InputRefused(f"--base-yaw {args.base_yaw} must be finite and within ±π rad")
        policy = load_policy(args.policy)
        policy.check_grasp_inputs()  # inputs its own config names, before anything connects
        env_cfg = policy.env_config()
        if args.backend == "aubo":
            _check_aubo_robot(env_cfg, args.policy)
        model = robot_mod.load_robot(env_cfg.robot)  # the policy's arm: the twin's, the start pose's joint count
        if args.twin_start_q is not None and len(args.twin_start_q) != model.dof:
            raise InputRefused(f"--twin-start-q takes {model.dof} joint angles (one per joint of {model.name}, the "
                               f"policy's robot), got {len(args.twin_start_q)}")
        check_policy_constants(env_cfg, source=args.policy)
        check_policy_scene(env_cfg, source=args.policy)
        env_cfg = deployment_env(env_cfg)  # the cell's facts are the deployment's, never the file's
        if args.calibration:
            cal = CameraCalibration.from_file(args.calibration, args.calibration_units, args.base_z_offset, args.base_yaw)
        else:
            cal = CameraCalibration.default(args.base_z_offset, args.base_yaw)
        capture = None
        aubo_settings = _aubo_settings(args)
        if args.camera is not None:
            capture, seen = _perceive_camera(args, cal, env_cfg, given, aubo_settings)
            centre = validate_target(seen.target_centre, env_cfg.sampling)
            yaw, obstacles = float(seen.target_yaw), list(seen.obstacles)
        else:
            top = cal.cam_to_base(_camera_point(args.target_cam, args.units, "--target-cam"))
            centre = validate_target(detected_top_to_cube_centre(top), env_cfg.sampling)
            square = env_cfg.sampling.target_size[0] == env_cfg.sampling.target_size[1]
            # a square cube is the same turned by 90°: report its yaw in the trained range ±45°
            yaw = camera_yaw_to_world(cal, math.radians(args.target_yaw), math.pi / 2 if square else 2 * math.pi)
            obstacles = [parse_obstacle(tokens, cal, args.units, i) for i, tokens in enumerate(args.obstacle)]
        truth = capture.truth if capture is not None and args.backend == "twin" else None
        start_q = args.twin_start_q if args.twin_start_q is not None else (truth["q0"] if truth else env_cfg.task.home_q)
        q_home = np.asarray(start_q, dtype=float)
        if q_home.shape != (model.dof,):  # a replayed twin capture's start pose, of another robot's scene
            raise InputRefused(f"the start pose {[float(v) for v in q_home]} has {q_home.size} joints; the policy's "
                               f"robot {model.name} has {model.dof}")
        if not (np.isfinite(q_home).all() and np.all(np.abs(q_home) <= math.pi)):
            raise InputRefused(f"--twin-start-q {args.twin_start_q} must be {model.dof} finite joint angles within "
                               "±π rad")
        env_cfg = with_obstacle_kinds(env_cfg, obstacles)
        if truth:  # a twin capture replayed on the twin: the twin holds the true scene, the loop the detection
            true_obstacles = [Obstacle(o["kind"], tuple(o["centre"]), tuple(o["size"]), o["yaw"]) for o in truth["obstacles"]]
            env_cfg = with_obstacle_kinds(env_cfg, true_obstacles)
            spec = scene_spec(q_home, truth["target_pos"], truth["target_yaw"], true_obstacles, env_cfg)
        else:
            spec = scene_spec(q_home, standing_cube_centre(centre, env_cfg.sampling), yaw, obstacles, env_cfg)
        twin_errors, detection_error = _twin_errors(args, model)
        detection = validate_target(centre + detection_error, env_cfg.sampling)
        if args.backend == "twin" and not args.dry_run:
            extras.require("twin", what="--backend twin (the PyBullet digital twin)")
    except (InputRefused, TargetRejected, CalibrationError, PolicyFormatError, ValueError, extras.MissingExtra,
            DeployError, CameraError, fileio.NotWritable) as exc:
        _emit(args, {"outcome": "input_refused", "message": str(exc), "input": given},
              f"error: refused before moving: {exc}", error=True)
        return 2
    given.update(calibration=cal.source, target_world=[float(v) for v in centre], target_yaw_world=yaw,
                 obstacles_world=[{"kind": o.kind, "centre": list(o.centre), "size": list(o.size), "yaw": o.yaw}
                                  for o in obstacles])
    cli.check()  # Ctrl-C while the input was checked: stop before anything connects
    if args.dry_run:
        steps = env_cfg.task.max_steps if args.max_steps is None else args.max_steps
        try:  # what the loop would command an arm that follows exactly, through the same safety layer
            plan_report, commands = plan_episode(policy, q_home, detection, yaw, obstacles, max_steps=steps)
            given["planned"] = {"ideal_arm_outcome": plan_report.outcome, "ideal_arm_steps": plan_report.steps,
                                "first_commands_rad": [[float(v) for v in q] for q in commands[:PLANNED_COMMANDS_SHOWN]]}
        except (SafetyViolation, DeployError, TargetRejected, ValueError) as exc:
            given["planned"] = {"ideal_arm_outcome": "refused", "message": str(exc), "first_commands_rad": []}
        return _dry_run(args, given, q_home, steps, aubo_settings)

    if args.backend == "aubo":  # the real arm: connect, check it stands at home, open the gripper
        try:
            robot_cm: Any = _aubo_robot(args, aubo_settings, q_home)
        except (DeployError, extras.MissingExtra) as exc:  # no connection, not at home: the arm has not moved
            _emit(args, {"outcome": "input_refused", "message": str(exc), "input": given},
                  f"error: refused before moving: {exc}", error=True)
            return 2
        stopped = cli.interrupted_line(
            "the episode was stopped before its next command to the arm (it holds its last target) and the "
            "controller session closed (servo mode left, logged out)", "nothing was written")
    else:
        from sagrasp_jax.deploy.twin import PyBulletTwin  # PyBullet only when it is used

        given["twin_cube_world"] = [float(v) for v in spec.target_pos]
        robot_cm = PyBulletTwin(spec, env_cfg, q0=q_home, gui=args.gui, errors=twin_errors)
        stopped = cli.interrupted_line("the episode on the twin was stopped before its next command and the twin "
                                       "closed", "nothing was written")
    if args.twin_target_error is not None:
        given["detection_world"] = [float(v) for v in detection]
    try:
        with robot_cm as robot:
            try:
                cli.check()
                report = run_episode(robot, policy, detection, yaw, obstacles, max_steps=args.max_steps,
                                     grasp=not args.no_grasp)
            except (SafetyViolation, DeployError) as exc:
                _emit(args, {"outcome": "refused", "message": str(exc), "input": given}, f"error: stopped: {exc}",
                      error=True)
                return 3
    except cli.Interrupted:
        raise cli.Interrupted(stopped) from None  # the session is closed by now: say so
    payload = report.to_dict() | {"input": given}
    _emit(args, payload, format_report(report))
    if report.outcome == "refused":
        return 3
    if args.no_grasp:
        return 0 if report.success else 1
    return 0 if report.held is True else 1


def _dry_run(args: argparse.Namespace, given: dict[str, Any], q_home: np.ndarray, steps: int,
             aubo_settings: aubo.AuboSettings | None) -> int:
    """``--dry-run`` on a whole deploy line: everything above was checked; say what would be done and, on the
    AUBO, connect and report whether the arm stands at the start pose.  Nothing is commanded."""
    plan, text = _plan(args, given, q_home, steps)
    payload: dict[str, Any] = {"outcome": "dry_run", "commanded": False, "plan": plan, "input": given}
    if args.backend == "aubo":
        try:
            with aubo.AuboRobot(args.host, settings=aubo_settings, log=lambda line: print(line, file=sys.stderr)) as robot:
                report = robot.dry_run(q_home, aubo.HOME_TOLERANCE if args.home_tolerance is None else args.home_tolerance)
        except (DeployError, extras.MissingExtra) as exc:
            _emit(args, {"outcome": "input_refused", "message": str(exc), "input": given},
                  f"error: refused before moving: {exc}", error=True)
            return 2
        _emit(args, payload | report.to_dict(), text + "\n" + report.format())
        return 0 if report.home.at_home else 1
    _emit(args, payload, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
