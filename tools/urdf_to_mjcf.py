"""Regenerate each registered robot's MJCF (the arm alone and the arm in the cell) from its URDF.

MuJoCo's own importer (``mujoco.MjSpec``) reads the URDF; this tool adds what MJCF
needs and URDF lacks: position actuators tuned for 20 Hz joint-target control,
joint armature and damping, gravity compensation (the AUBO controller compensates
gravity), ``flange`` and ``gripper_center`` sites, and, for the scene, the table,
gantry, camera (body and MJCF camera), the target and the dynamic-obstacle slots,
all from ``sagrasp_jax.task.scene.SCENE``.

The robot's registry entry (``sagrasp_jax.task.robots``) names the joints, the servo model (kp, kv, armature,
damping: ``spec.servo``), the finger links that touch the cube (``spec.contact_links``) and the two output
files (``spec.mjcf_robot``, ``spec.mjcf_scene``).

Usage: ``python tools/urdf_to_mjcf.py [--robot NAME] [--urdf PATH] [--out-dir DIR]``: without ``--robot`` it
writes every registered robot's files; ``--urdf`` reads another URDF with one robot's joint names (default
out-dir: the package's ``sagrasp_jax/mjcf/``, which ships in the wheel).  On a
missing or malformed URDF it exits non-zero naming the file and writes nothing.
"""

from __future__ import annotations

import argparse
import os
import sys
import xml.etree.ElementTree as ET

import mujoco
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from sagrasp_jax.base import assets  # noqa: E402
from sagrasp_jax.base.fileio import atomic_write_text  # noqa: E402
from sagrasp_jax.task import robots  # noqa: E402
from sagrasp_jax.task.robot import URDFError, parse_urdf  # noqa: E402
from sagrasp_jax.task.scene import SCENE  # noqa: E402
from sagrasp_jax.task import scene_mjcf  # noqa: E402
from sagrasp_jax.task import shapes  # noqa: E402

# The arm's position servos are the robot's (spec.servo: with gravity compensation on they only fight
# inertia and track a 0.05 rad step within one 0.05 s control period, tests/mjcf/test_mjcf.py); the
# fingers' are the same for every gripper.
FINGER_KP, FINGER_KV, FINGER_FORCE = 400.0, 10.0, 20.0
PARK_Z = -5.0  # unused obstacle slots wait below the floor


def _quat(rot: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.asarray(rot, dtype=float).reshape(9))
    return q


def _urdf_colours(path: str) -> dict[str, list[float]]:
    colours = {}
    for link in ET.parse(path).getroot().findall("link"):
        colour = link.find("visual/material/color")
        if colour is not None:
            colours[link.get("name")] = [float(v) for v in colour.get("rgba").split()]
    return colours


def build_robot_spec(urdf_path: str, robot_spec: robots.RobotSpec = robots.AUBO_I5) -> mujoco.MjSpec:
    """The robot alone: URDF import plus actuators, sites and joint dynamics (``robot_spec``: joint names, servos)."""
    robot = parse_urdf(urdf_path, robot_spec)  # validates the URDF with messages that name the file
    servo = robot_spec.servo
    try:
        spec = mujoco.MjSpec.from_file(urdf_path)
    except Exception as exc:  # mujoco raises ValueError with its own parser message
        raise URDFError(f"{urdf_path}: MuJoCo could not import the URDF ({exc})") from None
    spec.modelname = os.path.splitext(robot_spec.mjcf_robot)[0]
    spec.compiler.fusestatic = False
    spec.compiler.discardvisual = False  # keep contype-0 geoms: they are the collision primitives
    spec.option.timestep = 0.01
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    colours = _urdf_colours(urdf_path)
    for body in spec.bodies:
        if body.name == "world":
            continue
        body.gravcomp = 1.0
        for k, geom in enumerate(body.geoms):  # one per URDF collision primitive (MuJoCo merges identical visuals)
            geom.name = f"{body.name}_geom" + (f"_{k}" if k else "")
            geom.rgba = colours.get(body.name, [0.8, 0.8, 0.8, 1.0])
            touching = body.name in robot_spec.contact_links
            geom.contype = 1 if touching else 0
            geom.conaffinity = 1 if touching else 0
            geom.friction = [1.5, 0.01, 0.001] if touching else geom.friction
    for i, name in enumerate(robot_spec.arm_joints):
        joint = spec.joint(name)
        joint.armature = servo.armature[i]
        joint.damping = [servo.damping, 0.0, 0.0]
        joint.actgravcomp = True
        act = spec.add_actuator(name=f"{name}_servo", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=servo.kp[i], kv=servo.kv[i])
        act.ctrlrange = [float(robot.q_lower[i]), float(robot.q_upper[i])]
        act.ctrllimited = True
        act.forcerange = [-float(robot.effort_limit[i]), float(robot.effort_limit[i])]
        act.forcelimited = True
    for name in robot_spec.finger_joints:
        joint = spec.joint(name)
        joint.armature = 0.01
        joint.damping = [1.0, 0.0, 0.0]
        act = spec.add_actuator(name=f"{name}_servo", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=FINGER_KP, kv=FINGER_KV)
        act.ctrlrange = [0.0, robot.finger_open]
        act.ctrllimited = True
        act.forcerange = [-FINGER_FORCE, FINGER_FORCE]
        act.forcelimited = True
    wrist3 = spec.body(robot.link_names[-1])
    wrist3.add_site(name="flange", pos=robot.flange_local[:3, 3], quat=_quat(robot.flange_local[:3, :3]), size=[0.005, 0, 0])
    wrist3.add_site(name="gripper_center", pos=robot.gripper_centre_local, size=[0.005, 0, 0], rgba=[0, 1, 0, 1])
    return spec


def add_scene(spec: mujoco.MjSpec) -> None:
    """Add the cell of ``SCENE`` to a robot spec."""
    world = spec.worldbody
    spec.modelname = "sagrasp_scene"
    spec.visual.headlight.ambient = [0.4, 0.4, 0.4]
    spec.visual.global_.offwidth = SCENE.camera.resolution[0]
    spec.visual.global_.offheight = SCENE.camera.resolution[1]
    world.add_light(name="sun", pos=[0, -0.3, 2.5], dir=[0, 0, -1], diffuse=[0.7, 0.7, 0.7])
    table = SCENE.table
    world.add_geom(
        name="table",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        pos=[table.centre_xy[0], table.centre_xy[1], table.top_z],
        size=[table.half_extents[0], table.half_extents[1], 0.01],
        rgba=list(table.rgba),
        contype=1,
        conaffinity=1,
    )
    for part in SCENE.static_parts:
        world.add_geom(
            name=part.name,
            type=scene_mjcf.GEOM_TYPES[part.kind],
            pos=list(part.pos),
            quat=_quat(part.rot),
            size=list(part.size),
            rgba=list(part.rgba),
            contype=0,
            conaffinity=0,
        )
    cam = SCENE.camera
    world.add_camera(
        name="depth_camera",
        pos=list(cam.pos),
        quat=_quat(cam.mujoco_rot),
        fovy=cam.fovy_deg,
        resolution=list(cam.resolution),
    )
    world.add_camera(name="overview", pos=[1.3, -1.6, 1.1], xyaxes=[0.78, 0.63, 0, -0.25, 0.31, 0.92], fovy=50)
    target = world.add_body(name="target", mocap=True, pos=[0.0, -0.45, SCENE.target_size[2] / 2])
    target.add_geom(
        name="target_geom",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[s / 2 for s in SCENE.target_size],
        rgba=list(SCENE.target_rgba),
        mass=0.05,
        contype=1,
        conaffinity=1,
        friction=[1.5, 0.01, 0.001],
    )
    for slot in range(SCENE.obstacles.count):
        body = world.add_body(name=scene_mjcf.slot_body_name(slot), mocap=True, pos=[0.0, 0.0, PARK_Z])
        for shape in shapes.SHAPES:  # one geom per registered kind; the body carries the yaw, the geom the tilt
            scene_mjcf.add_obstacle_geom(body, slot, shape)  # unit size: the renderer and the physical check size it


def generate(urdf_path: str | None = None, robot: str = robots.DEFAULT) -> dict[str, str]:
    """Return {filename: xml text} of robot ``robot`` (its URDF, or ``urdf_path``); raises URDFError on a bad URDF."""
    spec = robots.get(robot)
    urdf_path = urdf_path or assets.path("urdf", spec.urdf)
    arm = build_robot_spec(urdf_path, spec)
    arm.compile()
    scene_spec = build_robot_spec(urdf_path, spec)
    add_scene(scene_spec)
    scene_spec.compile()
    header = f"<!-- Generated by tools/urdf_to_mjcf.py from sagrasp_jax/urdf/{spec.urdf} and sagrasp_jax/task/scene.py; do not edit. -->\n"
    return {spec.mjcf_robot: header + arm.to_xml(), spec.mjcf_scene: header + scene_spec.to_xml()}


def write_atomically(files: dict[str, str], out_dir: str) -> None:
    """Write every file or none: all are rendered in memory first, each lands by rename."""
    for name, text in files.items():
        atomic_write_text(os.path.join(out_dir, name), text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot", choices=robots.names(), help="the registered robot to write (default: every one)")
    parser.add_argument("--urdf", help="input URDF, read with --robot's joint names (default: the robot's own URDF)")
    parser.add_argument("--out-dir", default=assets.MJCF_DIR, help="output folder (default: the package's mjcf/)")
    args = parser.parse_args(argv)
    if args.urdf and not args.robot and len(robots.names()) > 1:
        args.robot = robots.DEFAULT  # a URDF variant is read with the default robot's joint names
    files: dict[str, str] = {}
    try:
        for name in [args.robot] if args.robot else robots.names():
            files.update(generate(args.urdf, name))
    except URDFError as exc:
        print(f"urdf_to_mjcf: error: {exc}", file=sys.stderr)
        return 2
    write_atomically(files, args.out_dir)
    for name in files:
        print(f"wrote {os.path.join(args.out_dir, name)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
