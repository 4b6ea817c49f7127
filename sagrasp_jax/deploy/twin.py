"""PyBullet digital twin of the cell: a ``deploy.loop.RobotInterface`` to rehearse deployment on.

Built from the same sources as the training scene, never a hand-kept copy: the robot from
the URDF of the config's ``env.robot`` (``robot.load_robot(env_cfg.robot)``: any registered arm), the table,
gantry and camera from ``scene.SCENE``;
the cube and the obstacles are placed at the given (true) positions.  DIRECT mode by default
(headless), ``gui=True`` opens PyBullet's viewer.

The approach is simulated, not teleported: each command's motion (after latency and servo lag, below)
is played through ``SUBSTEPS`` physics steps, the arm driven along it joint by joint (a stiff
position-controlled arm, as the AUBO's servos are), the cube a free body on the table.  Every arm link
pushes the cube it touches, so a cube knocked on the way moves; contacts with an obstacle or the table
are recorded from the links' URDF shapes (``approach_faults``: a brushed obstacle, a knocked cube, an
arm link on the table), which the deployment loop counts as a failed grasp.  Once the gripper has
closed, commands are tracked by the joint motors under physics for one control period each, so the
cube, squeezed between the pads, is carried by friction and ``object_position`` tells whether the
grasp held.  Nothing here imports jax.

Transfer errors to rehearse under (``deploy.transfer.TransferErrors``, one episode's draw of a named
condition's ``env.randomize`` knobs, or deploy's ``--twin-*`` flags): a command latency of whole and
fractional control steps (a queue of commands, as in training), servo lag (the arm follows its commands
through the lagged mode's fitted servo model, ``control.servo_model_step``, with a gain error per joint),
joint readings off by a per-joint offset and noisy.  The detection error is the caller's: the twin's cube
is the true one, the loop is handed the detection.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from sagrasp_jax.base import extras

extras.require("twin", what="the PyBullet twin")
# PyBullet's C code prints banners and URDF warnings on the file descriptors; bullet keeps them off the terminal
# (stdout stays for reports, --json) and passes real messages on to stderr.  It imports pybullet.
from sagrasp_jax.reference import bullet  # noqa: E402
import pybullet as pb  # noqa: E402

from sagrasp_jax.task import control
from sagrasp_jax.task import shapes
from sagrasp_jax.task import robot as robot_mod
from sagrasp_jax.task.config import EnvConfig
from sagrasp_jax.deploy.transfer import TransferErrors
from sagrasp_jax.reference.bullet import disconnect, rotation_to_quaternion, shape_kwargs
from sagrasp_jax.task.robot import BOX
from sagrasp_jax.task.sampling import ResetSpec
from sagrasp_jax.task.scene import SCENE

PHYSICS_HZ = 240  # PyBullet's default step; 12 substeps per 0.05 s control period
FINGER_FORCE = 20.0  # N per finger (EG2: the MJCF actuator's force range)
PAD_FRICTION = 1.5  # same as the MJCF pads and target
TARGET_MASS = 0.05  # kg, same as the MJCF target
GRIPPER_SETTLE_S = 0.6  # s of physics for a gripper open/close
ARM_POSITION_GAIN = 0.3  # PyBullet POSITION_CONTROL gains while carrying (stiff, AUBO-like tracking)
ARM_VELOCITY_GAIN = 1.0
KNOCK_SHIFT = 0.003  # m: a cube moved this far on the table before the gripper closed was knocked
KNOCK_TILT_DEG = 5.0  # deg: ... or tipped this far


def _yaw_xyzw(yaw: float) -> tuple[float, float, float, float]:
    return rotation_to_quaternion(shapes.yaw_rotation(np, float(yaw)))


class PyBulletTwin:
    """The cell in PyBullet with the cube and obstacles of one scene (``deploy.loop.scene_spec``)."""

    def __init__(self, spec: ResetSpec, env_cfg: EnvConfig | None = None, q0: Any = None, gui: bool = False,
                 realtime: bool | None = None, errors: TransferErrors | None = None, seed: int = 0) -> None:
        """The arm is ``env_cfg.robot`` (a policy's config: its arm), starting at ``q0`` (default its
        ``env.task.home_q``)."""
        self.cfg = env_cfg or EnvConfig()
        self.robot = robot_mod.load_robot(self.cfg.robot)
        self.errors = errors or TransferErrors(dof=self.robot.dof)
        if self.errors.dof != self.robot.dof:
            raise ValueError(f"transfer errors are for {self.errors.dof} joints; {self.robot.name} has "
                             f"{self.robot.dof}")
        q0 = np.asarray(self.cfg.task.home_q if q0 is None else q0, dtype=float)
        if q0.shape != (self.robot.dof,) or not np.isfinite(q0).all():
            raise ValueError(f"twin start pose must be {self.robot.dof} finite joint angles ({self.robot.name}), "
                             f"got {q0!r}")
        size = control.latency_queue_size(self.errors.latency)
        self._queue = np.repeat(q0[None], max(size, 2), axis=0)  # commands, newest first
        self._q_prev = q0.copy()  # the servo model's joints one step ago
        self._offsets = np.asarray(self.errors.offsets, dtype=float)
        self._rng = np.random.default_rng(seed)  # joint-reading noise
        self.gui = gui
        self.realtime = gui if realtime is None else realtime
        self.control_dt = float(self.cfg.control.control_dt)
        self.substeps = max(1, round(self.control_dt * PHYSICS_HZ))
        self.carrying = False  # True once the gripper has closed: commands go through the motors
        self._contacts: dict[str, int] = {}  # what an arm link touched during the approach -> substeps
        self._max_shift = 0.0  # m, the cube's largest move on the table before the gripper closed
        self._max_tip = 0.0  # deg
        with bullet.native_output_filtered():
            self._client = pb.connect(pb.GUI if gui else pb.DIRECT)
            if self._client < 0:
                raise RuntimeError("could not connect to a PyBullet physics server" + (" (no display for --gui?)" if gui else ""))
            try:
                self._build(spec)
                self._set_arm(np.asarray(q0, dtype=float))
                self._cube0 = self._cube_pose()
                self._resting = self._links_touching(self.table_body)  # the base stands on the table
            except BaseException:
                self.close()
                raise

    # -- world -----------------------------------------------------------------------------
    def _pb(self, fn: Any, *args: Any, **kwargs: Any) -> Any:
        return fn(*args, physicsClientId=self._client, **kwargs)

    def _body(self, kind: int, size: Any, pos: Any, orn: Any, rgba: Any, mass: float = 0.0) -> int:
        """A primitive body (MuJoCo size convention, shapes as the reference env builds them)."""
        return self._pb(
            pb.createMultiBody,
            baseMass=mass,
            baseCollisionShapeIndex=self._pb(pb.createCollisionShape, **shape_kwargs(kind, size, visual=False)),
            baseVisualShapeIndex=self._pb(pb.createVisualShape, rgbaColor=list(rgba), **shape_kwargs(kind, size, visual=True)),
            basePosition=[float(v) for v in pos],
            baseOrientation=list(orn),
        )

    def _build(self, spec: ResetSpec) -> None:
        """Robot from the URDF, cell from SCENE, cube and obstacles from the scene spec."""
        self._pb(pb.resetSimulation)
        self._pb(pb.setGravity, 0.0, 0.0, -9.81)
        self._pb(pb.setTimeStep, 1.0 / PHYSICS_HZ)
        table = SCENE.table
        self.table_body = self._pb(
            pb.createMultiBody,
            baseMass=0.0,
            baseCollisionShapeIndex=self._pb(pb.createCollisionShape, shapeType=pb.GEOM_PLANE),
            baseVisualShapeIndex=self._pb(
                pb.createVisualShape, shapeType=pb.GEOM_BOX, halfExtents=list(table.half_extents), rgbaColor=list(table.rgba),
                visualFramePosition=[table.centre_xy[0], table.centre_xy[1], -table.half_extents[2]],
            ),
            basePosition=[0.0, 0.0, table.top_z],
        )
        for part in SCENE.static_parts:
            self._body(part.kind, part.size, part.pos, rotation_to_quaternion(part.rot), part.rgba)
        half = [s / 2 for s in self.cfg.sampling.target_size]
        target_pos = np.asarray(spec.target_pos, dtype=float)
        self.target_body = self._body(BOX, half, target_pos, _yaw_xyzw(float(spec.target_yaw)), SCENE.target_rgba, TARGET_MASS)
        self._pb(pb.changeDynamics, self.target_body, -1, lateralFriction=PAD_FRICTION)
        self.obstacle_bodies = [
            self._body(shapes.BY_ID[int(spec.obstacle_kind[i])].primitive, spec.obstacle_size[i], spec.obstacle_pos[i],
                       rotation_to_quaternion(shapes.world_rotation(int(spec.obstacle_kind[i]), spec.obstacle_yaw[i])),
                       SCENE.obstacles.rgba)
            for i in np.nonzero(np.asarray(spec.obstacle_active))[0]
        ]

        self.robot_body = bullet.load_urdf(self._client, self.robot.urdf_path, useFixedBase=True, flags=pb.URDF_USE_INERTIA_FROM_FILE)
        joints: dict[str, int] = {}
        efforts: dict[int, float] = {}
        for j in range(self._pb(pb.getNumJoints, self.robot_body)):
            info = self._pb(pb.getJointInfo, self.robot_body, j)
            joints[info[1].decode()] = j
            efforts[j] = float(info[10])
        self.arm_joints = [joints[n] for n in self.robot.spec.arm_joints]
        self.finger_joints = [joints[n] for n in self.robot.spec.finger_joints]
        self.arm_forces = [efforts[j] for j in self.arm_joints]
        # Only the finger pads collide with everything; every other link collides with the cube alone (it pushes
        # a cube it meets); contacts with obstacles and the table are measured geometrically (_record_contacts).
        for link in range(-1, self._pb(pb.getNumJoints, self.robot_body)):
            if link not in self.finger_joints:
                self._pb(pb.setCollisionFilterGroupMask, self.robot_body, link, 0, 0)
                self._pb(pb.setCollisionFilterPair, self.robot_body, self.target_body, link, -1, 1)
        for j in self.finger_joints:
            self._pb(pb.changeDynamics, self.robot_body, j, lateralFriction=PAD_FRICTION)
        self._fingers(self.robot.finger_open)
        for j in self.finger_joints:
            self._pb(pb.resetJointState, self.robot_body, j, self.robot.finger_open)
        self.link_names = {-1: "base_link"} | {
            j: self._pb(pb.getJointInfo, self.robot_body, j)[12].decode() for j in range(self._pb(pb.getNumJoints, self.robot_body))}

    def _fingers(self, opening: float) -> None:
        self._pb(pb.setJointMotorControlArray, self.robot_body, self.finger_joints, pb.POSITION_CONTROL,
                 targetPositions=[opening] * 2, forces=[FINGER_FORCE] * 2)

    def _set_arm(self, q: np.ndarray, velocity: np.ndarray | None = None) -> None:
        v = np.zeros(self.robot.dof) if velocity is None else velocity
        for j, value, dv in zip(self.arm_joints, q, v):
            self._pb(pb.resetJointState, self.robot_body, j, float(value), float(dv))
        self._hold_arm(q, v)

    def _hold_arm(self, q: np.ndarray, velocity: np.ndarray | None = None) -> None:
        v = [0.0] * self.robot.dof if velocity is None else [float(x) for x in velocity]
        self._pb(pb.setJointMotorControlArray, self.robot_body, self.arm_joints, pb.POSITION_CONTROL,
                 targetPositions=[float(v) for v in q], targetVelocities=v, forces=self.arm_forces,
                 positionGains=[ARM_POSITION_GAIN] * self.robot.dof,
                 velocityGains=[ARM_VELOCITY_GAIN] * self.robot.dof)

    def _simulate(self, seconds: float) -> None:
        for _ in range(max(1, round(seconds * PHYSICS_HZ))):
            self._pb(pb.stepSimulation)
            if self.realtime:
                time.sleep(1.0 / PHYSICS_HZ)

    # -- contacts during the approach ---------------------------------------------------------
    def _links_touching(self, body: int) -> set[int]:
        """Arm links (not the finger pads' own contacts with the cube) whose URDF shapes touch ``body`` now."""
        return {int(c[3]) for c in self._pb(pb.getClosestPoints, self.robot_body, body, 0.0)}

    def _cube_pose(self) -> tuple[np.ndarray, np.ndarray]:
        pos, orn = self._pb(pb.getBasePositionAndOrientation, self.target_body)
        return np.asarray(pos, dtype=float), np.asarray(self._pb(pb.getMatrixFromQuaternion, orn), dtype=float).reshape(3, 3)

    def _record_contacts(self) -> None:
        for i, body in enumerate(self.obstacle_bodies):
            for link in self._links_touching(body):
                name = f"obstacle {i + 1} ({self.link_names[link]})"
                self._contacts[name] = self._contacts.get(name, 0) + 1
        for link in self._links_touching(self.table_body) - self._resting:
            name = f"table ({self.link_names[link]})"
            self._contacts[name] = self._contacts.get(name, 0) + 1
        pos, rot = self._cube_pose()
        pos0, rot0 = self._cube0
        self._max_shift = max(self._max_shift, float(np.linalg.norm(pos - pos0)))
        self._max_tip = max(self._max_tip, float(np.degrees(np.arccos(np.clip(rot[:, 2] @ rot0[:, 2], -1.0, 1.0)))))

    def approach_faults(self) -> list[str]:
        """What went wrong physically before the gripper closed: an arm link on an obstacle or the table, the
        cube knocked (moved ≥ KNOCK_SHIFT or tipped ≥ KNOCK_TILT_DEG).  Empty when the approach was clean."""
        faults = [f"touched {name} for {n} physics steps" for name, n in self._contacts.items()]
        if self._max_shift >= KNOCK_SHIFT or self._max_tip >= KNOCK_TILT_DEG:
            faults.append(f"cube knocked before closing: moved {self._max_shift * 1000:.1f} mm, tipped {self._max_tip:.1f}°")
        return faults

    # -- RobotInterface ----------------------------------------------------------------------
    def true_joints(self) -> np.ndarray:
        """The arm's joints as they are (no reading offset or noise)."""
        return np.array([s[0] for s in self._pb(pb.getJointStates, self.robot_body, self.arm_joints)], dtype=float)

    def read_joints(self) -> np.ndarray:
        """The joints as the controller reports them: off by this episode's offset, with reading noise."""
        noise = self.errors.joint_noise * self._rng.standard_normal(self.robot.dof) if self.errors.joint_noise else 0.0
        return self.true_joints() + self._offsets + noise

    def command_joint_targets(self, q: np.ndarray) -> None:
        q = np.asarray(q, dtype=float)
        if q.shape != (self.robot.dof,) or not np.isfinite(q).all():
            raise ValueError(f"joint target must be {self.robot.dof} finite values, got {q!r}")
        if self.carrying:
            self._hold_arm(q)
            self._simulate(self.control_dt)
            return
        q_start, q_end = self.true_joints(), self._executed(q)
        velocity = (q_end - q_start) / self.control_dt
        for k in range(1, self.substeps + 1):  # the motion through the period, the cube and contacts under physics
            self._set_arm(q_start + (q_end - q_start) * k / self.substeps, velocity)
            self._pb(pb.stepSimulation)
            self._record_contacts()
            if self.realtime:
                time.sleep(1.0 / PHYSICS_HZ)
        self._set_arm(q_end)

    def _executed(self, q: np.ndarray) -> np.ndarray:
        """Where the arm is one control period after the command ``q``, under this twin's latency and servo lag
        (commands are in the servos' own frame: the reading offset does not move the arm)."""
        e = self.errors
        self._queue = np.concatenate([q[None], self._queue[:-1]], axis=0)
        if e.latency == 0 and not e.servo_lag:
            return q
        current, previous, fraction = control.delayed_commands(np, self._queue, float(e.latency))
        if not e.servo_lag:  # exact tracking: the older command for the fraction, then the newer one
            return current
        q_now = self.true_joints()
        nominal = np.asarray(self.cfg.control.lag_gain, dtype=float)
        gain = np.clip(nominal * np.asarray(e.servo_gains), 0.0, 1.0)
        weight = control.held_command_weight(np, fraction, nominal)  # the fraction's weight: the nominal servo (as MJX)
        command = (1.0 - weight) * current + weight * previous
        q_next = control.servo_model_step(np, self.robot, self.cfg.control, q_now, self._q_prev, command, gain)
        self._q_prev = q_now
        return q_next

    def open_gripper(self) -> None:
        self._fingers(self.robot.finger_open)
        self._simulate(GRIPPER_SETTLE_S)

    def close_gripper(self) -> None:
        self.carrying = True
        self._hold_arm(self.true_joints())
        self._fingers(0.0)
        self._simulate(GRIPPER_SETTLE_S)

    # -- extras ----------------------------------------------------------------------------
    def object_position(self) -> np.ndarray:
        """The cube's centre now (world frame)."""
        return np.asarray(self._pb(pb.getBasePositionAndOrientation, self.target_body)[0], dtype=float)

    def finger_positions(self) -> np.ndarray:
        return np.array([s[0] for s in self._pb(pb.getJointStates, self.robot_body, self.finger_joints)], dtype=float)

    def close(self) -> None:
        self._client = disconnect(getattr(self, "_client", -1))

    def __enter__(self) -> "PyBulletTwin":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
