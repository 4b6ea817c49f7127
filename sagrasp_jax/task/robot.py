"""Robot facts read from a robot's URDF, and forward kinematics for NumPy and JAX.

Each registered robot's URDF (``task/robots.py``; the default ``sagrasp_jax/urdf/aubo_i5_eg2.urdf``) is the
only place where its joint origins, limits and collision geometry are written.  ``load_robot(name)`` parses
it once into plain NumPy constants; ``forward_kinematics(xp, robot, q)`` then runs with ``xp = numpy`` (the
PyBullet reference env, the deployment runtime) or ``xp = jax.numpy`` (the MJX env)
and broadcasts over any leading batch dimensions of ``q``.
"""

from __future__ import annotations

import functools
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from sagrasp_jax.base import assets
from sagrasp_jax.task import robots

URDF_PATH = assets.URDF  # the default robot's, shipped in the package (sagrasp_jax/urdf/), found through importlib.resources

# The default robot's (the AUBO-i5's) joints; code that serves every arm reads RobotModel.spec / .dof instead.
ARM_JOINTS = robots.AUBO_I5.arm_joints
FINGER_JOINTS = robots.AUBO_I5.finger_joints
ARM_DOF = robots.AUBO_I5.dof  # the AUBO-i5's joint count: its driver and its packaged policy's files

# Primitive kinds (sizes in MuJoCo's convention), shared with geometry.py and shapes.py.
SPHERE, CAPSULE, BOX, CYLINDER = 0, 1, 2, 3


class URDFError(ValueError):
    """The URDF is missing, malformed, or lacks something the project needs."""


class IKError(RuntimeError):
    """Inverse kinematics found no acceptable joint vector for the requested pose."""


def rpy_to_matrix(rpy: Any) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw: R = Rz(yaw)·Ry(pitch)·Rx(roll)."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _transform(rot: np.ndarray, pos: Any) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = np.asarray(pos, dtype=float)
    return t


@dataclass(frozen=True)
class Primitive:
    """One collision primitive fixed to a robot link (sizes in MuJoCo's convention)."""

    name: str
    link: int  # index into RobotModel.link_names (0 = base)
    kind: int  # SPHERE | CAPSULE | BOX | CYLINDER
    size: tuple[float, float, float]  # sphere (r,0,0); capsule/cylinder (r, half-length, 0); box half-extents
    local: np.ndarray  # 4x4 pose in the link frame


@dataclass(frozen=True)
class RobotModel:
    link_names: tuple[str, ...]  # base + one link per arm joint
    joint_origins: np.ndarray  # (dof, 4, 4) parent-link -> joint frame, before rotation about local z
    q_lower: np.ndarray
    q_upper: np.ndarray
    velocity_limit: np.ndarray  # rad/s
    effort_limit: np.ndarray
    link_masses: dict[str, float]
    flange_local: np.ndarray  # 4x4 pose of the flange in the wrist3 frame
    gripper_centre_local: np.ndarray  # (3,) midpoint of the finger pads in the wrist3 frame
    finger_open: float  # finger joint value when fully open
    primitives: tuple[Primitive, ...]
    urdf_path: str
    spec: robots.RobotSpec = robots.AUBO_I5  # the registry entry: joint roles, home pose, servo model

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def self_moving_links(self) -> tuple[int, ...]:
        """Link indices of the self-collision group that moves against the static one (wrist and gripper)."""
        return tuple(range(self.spec.self_moving_from_link, self.dof + 1))

    @property
    def self_static_links(self) -> tuple[int, ...]:
        """Link indices of the base and the first links, which the moving group must not touch."""
        return tuple(range(0, self.spec.self_static_to_link + 1))

    @property
    def dof(self) -> int:
        """The arm's joint count as parsed from the URDF (ARM_DOF for the shipped arm)."""
        return len(self.joint_origins)

    @property
    def prim_kind(self) -> np.ndarray:
        return np.array([p.kind for p in self.primitives], dtype=np.int32)

    @property
    def prim_size(self) -> np.ndarray:
        return np.array([p.size for p in self.primitives], dtype=float)

    @property
    def prim_link(self) -> np.ndarray:
        return np.array([p.link for p in self.primitives], dtype=np.int32)

    @property
    def prim_local(self) -> np.ndarray:
        return np.stack([p.local for p in self.primitives])

    def prim_index(self, name: str) -> int:
        for i, p in enumerate(self.primitives):
            if p.name == name:
                return i
        raise KeyError(name)


def _floats(text: str | None, n: int, what: str, path: str) -> tuple[float, ...]:
    if text is None:
        return (0.0,) * n
    try:
        values = tuple(float(v) for v in text.split())
    except ValueError:
        raise URDFError(f"{path}: {what} has a non-numeric value {text!r}") from None
    if len(values) != n:
        raise URDFError(f"{path}: {what} needs {n} numbers, got {text!r}")
    return values


def _origin(elem: ET.Element | None, path: str, what: str) -> np.ndarray:
    if elem is None:
        return np.eye(4)
    xyz = _floats(elem.get("xyz"), 3, f"{what} origin xyz", path)
    rpy = _floats(elem.get("rpy"), 3, f"{what} origin rpy", path)
    return _transform(rpy_to_matrix(rpy), xyz)


def _geometry(elem: ET.Element, path: str, what: str) -> tuple[int, tuple[float, float, float]]:
    geo = elem.find("geometry")
    if geo is None or len(geo) == 0:
        raise URDFError(f"{path}: {what} has no <geometry>")
    shape = geo[0]
    try:
        if shape.tag == "sphere":
            return SPHERE, (float(shape.get("radius")), 0.0, 0.0)
        if shape.tag == "capsule":
            return CAPSULE, (float(shape.get("radius")), float(shape.get("length")) / 2, 0.0)
        if shape.tag == "cylinder":
            return CYLINDER, (float(shape.get("radius")), float(shape.get("length")) / 2, 0.0)
        if shape.tag == "box":
            sx, sy, sz = _floats(shape.get("size"), 3, f"{what} box size", path)
            return BOX, (sx / 2, sy / 2, sz / 2)
    except (TypeError, ValueError):
        raise URDFError(f"{path}: {what} <{shape.tag}> is missing a size attribute") from None
    raise URDFError(f"{path}: {what} uses <{shape.tag}>; only sphere, capsule, cylinder and box are supported")


def parse_urdf(path: str, spec: robots.RobotSpec = robots.AUBO_I5) -> RobotModel:
    """Parse a robot's URDF, its joints' roles named by ``spec``; raises URDFError naming the file and the problem."""
    if not os.path.isfile(path):
        raise URDFError(f"{path}: URDF file not found")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise URDFError(f"{path}: malformed XML ({exc})") from None
    if root.tag != "robot":
        raise URDFError(f"{path}: root element is <{root.tag}>, expected <robot>")
    links = {link.get("name"): link for link in root.findall("link")}
    joints = {joint.get("name"): joint for joint in root.findall("joint")}
    arm_joints = spec.arm_joints
    for name in arm_joints + spec.finger_joints + (spec.flange_joint, spec.gripper_centre_joint):
        if name not in joints:
            raise URDFError(f"{path}: joint {name!r} is missing")

    def child_of(jname: str) -> str:
        child = joints[jname].find("child")
        if child is None or child.get("link") not in links:
            raise URDFError(f"{path}: joint {jname!r} has no valid <child>")
        return child.get("link")

    def parent_of(jname: str) -> str:
        parent = joints[jname].find("parent")
        if parent is None or parent.get("link") not in links:
            raise URDFError(f"{path}: joint {jname!r} has no valid <parent>")
        return parent.get("link")

    base = parent_of(arm_joints[0])
    link_names = [base]
    origins, lower, upper, vel, eff = [], [], [], [], []
    for jname in arm_joints:
        joint = joints[jname]
        if joint.get("type") != "revolute":
            raise URDFError(f"{path}: joint {jname!r} must be revolute")
        if parent_of(jname) != link_names[-1]:
            raise URDFError(f"{path}: joint {jname!r} does not continue the arm chain")
        axis = _floats(joint.find("axis").get("xyz") if joint.find("axis") is not None else "0 0 1", 3, f"{jname} axis", path)
        if not np.allclose(axis, (0, 0, 1)):
            raise URDFError(f"{path}: joint {jname!r} axis must be local z, got {axis}")
        limit = joint.find("limit")
        if limit is None:
            raise URDFError(f"{path}: joint {jname!r} has no <limit>")
        try:
            lower.append(float(limit.get("lower")))
            upper.append(float(limit.get("upper")))
            vel.append(float(limit.get("velocity")))
            eff.append(float(limit.get("effort")))
        except (TypeError, ValueError):
            raise URDFError(f"{path}: joint {jname!r} <limit> needs lower, upper, velocity and effort") from None
        origins.append(_origin(joint.find("origin"), path, jname))
        link_names.append(child_of(jname))

    wrist3 = link_names[-1]
    link_index = {name: i for i, name in enumerate(link_names)}

    # Links rigidly attached to wrist3 (flange, gripper, fingers at the open position), as wrist3-frame poses.
    attached: dict[str, np.ndarray] = {wrist3: np.eye(4)}
    finger_open = None
    changed = True
    while changed:
        changed = False
        for jname, joint in joints.items():
            parent, child = parent_of(jname), child_of(jname)
            if parent in attached and child not in attached and child not in link_index:
                local = _origin(joint.find("origin"), path, jname)
                if joint.get("type") == "prismatic":
                    limit = joint.find("limit")
                    opening = float(limit.get("upper"))
                    finger_open = opening
                    axis = np.array(_floats(joint.find("axis").get("xyz"), 3, f"{jname} axis", path))
                    local = local @ _transform(np.eye(3), axis * opening)
                elif joint.get("type") != "fixed":
                    raise URDFError(f"{path}: joint {jname!r} below the wrist must be fixed or prismatic")
                attached[child] = attached[parent] @ local
                changed = True
    flange = child_of(spec.flange_joint)
    gripper_center = child_of(spec.gripper_centre_joint)
    fingers = [child_of(j) for j in spec.finger_joints]
    for name in (flange, gripper_center, *fingers):
        if name not in attached:
            raise URDFError(f"{path}: link {name!r} is not attached below {wrist3!r}")
    pad_mid = 0.5 * (attached[fingers[0]][:3, 3] + attached[fingers[1]][:3, 3])
    if not np.allclose(pad_mid, attached[gripper_center][:3, 3], atol=1e-9):
        raise URDFError(f"{path}: gripper_center frame is not the midpoint of the finger pads")

    primitives = []
    masses = {}
    for lname, link in links.items():
        inertial = link.find("inertial")
        if inertial is not None and inertial.find("mass") is not None:
            masses[lname] = float(inertial.find("mass").get("value"))
        if lname in link_index:
            host, to_host = link_index[lname], np.eye(4)
        elif lname in attached:
            host, to_host = link_index[wrist3], attached[lname]
        else:
            continue
        for k, coll in enumerate(link.findall("collision")):
            kind, size = _geometry(coll, path, f"link {lname!r} collision {k}")
            local = to_host @ _origin(coll.find("origin"), path, f"link {lname!r} collision {k}")
            primitives.append(Primitive(f"{lname}/{k}", host, kind, size, local))
    if not primitives:
        raise URDFError(f"{path}: no collision geometry found")
    return RobotModel(
        link_names=tuple(link_names),
        joint_origins=np.stack(origins),
        q_lower=np.array(lower),
        q_upper=np.array(upper),
        velocity_limit=np.array(vel),
        effort_limit=np.array(eff),
        link_masses=masses,
        flange_local=attached[flange],
        gripper_centre_local=pad_mid,
        finger_open=float(finger_open),
        primitives=tuple(primitives),
        urdf_path=path,
        spec=spec,
    )


def load_robot(robot: str = robots.DEFAULT) -> RobotModel:
    """The registered robot ``robot`` (``env.robot``), parsed once; a path to a ``.urdf`` file is read with the
    default robot's joint names (a variant of its URDF)."""
    if robot.endswith(".urdf"):
        return _load(robot, robots.DEFAULT)
    spec = robots.get(robot)
    return _load(assets.path("urdf", spec.urdf), spec.name)


@functools.lru_cache(maxsize=8)
def _load(path: str, name: str) -> RobotModel:
    return parse_urdf(path, robots.get(name))


robots.on_change(_load.cache_clear)


class Kinematics(NamedTuple):
    """World-frame poses for a joint vector (leading batch dims of q are kept)."""

    link_pos: Any  # (..., dof + 1, 3) base + one link per arm joint
    link_rot: Any  # (..., dof + 1, 3, 3)
    joint_axes: Any  # (..., dof, 3) world axis of each arm joint
    joint_pos: Any  # (..., dof, 3)
    flange_pos: Any  # (..., 3)
    gripper_centre: Any  # (..., 3)
    approach_axis: Any  # (..., 3) gripper approach (flange local +z)


def _rot_z(xp: Any, angle: Any) -> Any:
    c, s = xp.cos(angle), xp.sin(angle)
    zero, one = xp.zeros_like(angle), xp.ones_like(angle)
    rows = [xp.stack([c, -s, zero], -1), xp.stack([s, c, zero], -1), xp.stack([zero, zero, one], -1)]
    return xp.stack(rows, -2)


def forward_kinematics(xp: Any, robot: RobotModel, q: Any) -> Kinematics:
    """Forward kinematics of the arm; ``xp`` is numpy or jax.numpy."""
    q = xp.asarray(q)
    batch = q.shape[:-1]
    rot = xp.broadcast_to(xp.eye(3, dtype=q.dtype), batch + (3, 3))
    pos = xp.zeros(batch + (3,), dtype=q.dtype)
    rots, poss = [rot], [pos]
    for i in range(robot.dof):
        origin = robot.joint_origins[i]
        pos = pos + rot @ xp.asarray(origin[:3, 3], dtype=q.dtype)
        rot = rot @ xp.asarray(origin[:3, :3], dtype=q.dtype) @ _rot_z(xp, q[..., i])
        rots.append(rot)
        poss.append(pos)
    link_rot = xp.stack(rots, -3)
    link_pos = xp.stack(poss, -2)
    wrist_rot, wrist_pos = rots[-1], poss[-1]
    flange_pos = wrist_pos + wrist_rot @ xp.asarray(robot.flange_local[:3, 3], dtype=q.dtype)
    flange_rot = wrist_rot @ xp.asarray(robot.flange_local[:3, :3], dtype=q.dtype)
    gripper_centre = wrist_pos + wrist_rot @ xp.asarray(robot.gripper_centre_local, dtype=q.dtype)
    return Kinematics(
        link_pos=link_pos,
        link_rot=link_rot,
        joint_axes=link_rot[..., 1:, :, 2],
        joint_pos=link_pos[..., 1:, :],
        flange_pos=flange_pos,
        gripper_centre=gripper_centre,
        approach_axis=flange_rot[..., :, 2],
    )


def primitive_poses(xp: Any, robot: RobotModel, kin: Kinematics) -> tuple[Any, Any]:
    """World position (..., G, 3) and rotation (..., G, 3, 3) of every robot collision primitive."""
    local = robot.prim_local
    link = robot.prim_link
    rot = kin.link_rot[..., link, :, :]
    pos = kin.link_pos[..., link, :]
    dtype = kin.link_pos.dtype
    prim_pos = pos + xp.einsum("...gij,gj->...gi", rot, xp.asarray(local[:, :3, 3], dtype=dtype))
    prim_rot = xp.einsum("...gij,gjk->...gik", rot, xp.asarray(local[:, :3, :3], dtype=dtype))
    return prim_pos, prim_rot


def tilt(xp: Any, approach_axis: Any) -> Any:
    """θgz: angle (rad) between the gripper approach axis and world −z."""
    cos = xp.clip(-approach_axis[..., 2] / xp.linalg.norm(approach_axis, axis=-1), -1.0, 1.0)
    return xp.arccos(cos)


def solve_home_pose(
    seed: Any,
    target: Any = (0.0, -0.30, 0.35),
    robot: RobotModel | None = None,
    iterations: int = 200,
    damping: float = 1e-3,
) -> np.ndarray:
    """Damped-least-squares IK: gripper centre at ``target``, approach axis along −z.

    Seeded from docs/task.md §2's vector so that the solver stays on the branch the task
    pins (other branches reach the same pose at a joint limit).
    """
    robot = robot or load_robot()
    q = np.array(seed, dtype=float)
    target = np.asarray(target, dtype=float)

    def error(qv: np.ndarray) -> np.ndarray:
        kin = forward_kinematics(np, robot, qv)
        axis = kin.approach_axis
        return np.concatenate([kin.gripper_centre - target, axis[:2]])

    return _damped_least_squares(error, q, iterations, 1e-13, damping)


def _damped_least_squares(error: Any, q: np.ndarray, iterations: int, tol: float, damping: float) -> np.ndarray:
    """Joints that drive ``error(q)`` (a vector) to zero: damped least squares on a central-difference
    Jacobian, stopping once ``|error| < tol``."""
    n = len(error(q))
    for _ in range(iterations):
        e = error(q)
        if np.linalg.norm(e) < tol:
            break
        jac = np.zeros((n, len(q)))
        for j in range(len(q)):
            dq = np.zeros(len(q))
            dq[j] = 1e-7
            jac[:, j] = (error(q + dq) - error(q - dq)) / 2e-7
        q = q + jac.T @ np.linalg.solve(jac @ jac.T + damping**2 * np.eye(n), -e)
    return q


LIFT_MAX_JOINT_MOVE = 0.5  # rad; a lift pose further than this from the grasp pose means IK left the branch


def lift_pose(model: RobotModel, q: Any, height: float, max_joint_move: float = LIFT_MAX_JOINT_MOVE) -> np.ndarray:
    """Joints that put the gripper centre ``height`` m straight above where it is at ``q``, the gripper
    keeping its orientation (``translated_pose``): the grasp is lifted as it was closed, never swung
    upright on the way (a tilted grasp's wrist would sweep sideways).  Used by the deployment loop's lift
    and the physical grasp check; raises IKError if the solution misses the goal by more than 1 mm or
    moves a joint by more than ``max_joint_move``."""
    return translated_pose(model, q, (0.0, 0.0, height), max_joint_move, what="lift pose")


def _orientation_error(rot: np.ndarray, rot_goal: np.ndarray) -> np.ndarray:
    """Small-angle rotation vector that turns ``rot`` into ``rot_goal`` (both 3×3, world frame)."""
    return 0.5 * sum(np.cross(rot[:, i], rot_goal[:, i]) for i in range(3))


def translated_pose(model: RobotModel, q: Any, delta: Any, max_joint_move: float = LIFT_MAX_JOINT_MOVE,
                    what: str = "pose", iterations: int = 100, damping: float = 1e-4) -> np.ndarray:
    """Joints that move the gripper centre by ``delta`` (m, world) from where it is at ``q`` with the gripper's
    orientation unchanged: damped-least-squares IK on position and orientation, seeded at ``q`` (the arm stays
    on its branch).  IKError if it misses by more than 1 mm or 0.1°, or moves a joint by more than
    ``max_joint_move``."""
    q = np.asarray(q, dtype=float)
    kin0 = forward_kinematics(np, model, q)
    goal = kin0.gripper_centre + np.asarray(delta, dtype=float)
    rot_goal = kin0.link_rot[-1]

    def residual(qv: np.ndarray) -> np.ndarray:
        kin = forward_kinematics(np, model, qv)
        return np.concatenate([goal - kin.gripper_centre, _orientation_error(kin.link_rot[-1], rot_goal)])

    qv = _damped_least_squares(lambda v: -residual(v), q.copy(), iterations, 1e-12, damping)
    r = residual(qv)
    move = float(np.abs(qv - q).max())
    if not (np.isfinite(qv).all() and np.linalg.norm(r[:3]) <= 1e-3 and np.linalg.norm(r[3:]) <= np.radians(0.1)
            and move <= max_joint_move):
        raise IKError(f"no {what} found near the grasp pose (IK error {np.linalg.norm(r[:3]) * 1000:.1f} mm, "
                      f"{np.degrees(np.linalg.norm(r[3:])):.2f}°, joint move {move:.3f} rad)")
    return qv


def approach_pose(model: RobotModel, q: Any, goal: Any, max_joint_move: float = LIFT_MAX_JOINT_MOVE,
                  what: str = "pose") -> np.ndarray:
    """Joints that put the gripper centre at ``goal`` pointing down, by IK seeded at ``q`` (the grasp's
    final centring and the lift); IKError if it misses by more than 1 mm or moves a joint by more than
    ``max_joint_move``."""
    q = np.asarray(q, dtype=float)
    goal = np.asarray(goal, dtype=float)
    q_goal = solve_home_pose(q, goal, model)
    kin = forward_kinematics(np, model, q_goal)
    error = float(np.linalg.norm(kin.gripper_centre - goal))
    move = float(np.abs(q_goal - q).max())
    if not (error <= 1e-3 and move <= max_joint_move and np.isfinite(q_goal).all()):
        raise IKError(f"no {what} found near the grasp pose (IK error {error * 1000:.1f} mm, joint move {move:.3f} rad)")
    return q_goal
