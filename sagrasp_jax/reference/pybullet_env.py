"""PyBullet reference implementation of the grasping MDP (docs/task.md §1-§2), as a Gymnasium env.

Why it exists: the MJX/JAX env (``sagrasp_jax.envs.grasp_env.GraspEnv``) is fast but new; this env
rebuilds the same task in the simulator the paper used, from the same URDF and the same
scene description, so ``sagrasp_jax.reference.parity`` can show step by step that both are one task.

What is shared, never re-typed: the control step (``control.control_step``), the reward,
success test and outcome precedence (``reward``), the collision rules
(``collision.check``) and the reset sampler (``sampling.sample_reset``) all run here with
``xp = numpy``.  What is PyBullet's own: the robot's pose.  After every control step the
link frames are read back from PyBullet (``getLinkStates`` with forward kinematics) and
packed into a ``robot.Kinematics``; the collision rules, tilt, distances and the
observation are computed from that, not from the project's FK.

Modes (``cfg.control.mode``):

* ``kinematic``: joints are set with ``resetJointState`` (no physics step), the
  equivalent of the MJX env's ``qpos = q_target``.
* ``dynamic``: ``POSITION_CONTROL`` motors with forces = the URDF effort limits and
  ``cfg.control.substeps`` × ``stepSimulation`` of ``physics_dt`` per 0.05 s control
  period.  PyBullet's motor is a velocity constraint (after a substep
  v = kp·(q* − q)/h + (1 − kd)·v), not MuJoCo's force servo; the default gains
  (``DYNAMIC_POSITION_GAINS`` / ``DYNAMIC_VELOCITY_GAINS``) were fitted so that its
  tracking lag matches the MJCF servos of the MJX env (kp 3000 / kv 150 on joints 1-3,
  300 / 10 on 4-6, with gravity compensation); see ``docs/parity.md`` for the fit and
  the remaining gap.

The arm's weight is compensated exactly, as the MJCF's ``gravcomp`` does (the AUBO controller
compensates gravity): the robot is the only dynamic body, so the world runs without gravity
unless ``gravity_compensation=False``.  Contacts of the robot are switched off (collision
filter mask 0) in both modes, as in the MJX env: collisions are the analytic rules of
``collision.check``.  The scene bodies keep their collision shapes, so PyBullet's own distance
queries (``pybullet_distance``) can cross-check those rules.  A timeout ends the episode with
``truncated=True, terminated=False`` (Gymnasium's time-limit convention) and still pays the task's
−1 verdict; collision and success are ``terminated``.

gymnasium is needed only for the env class (the ``reference`` extra); the PyBullet helpers here
(shapes, quaternions, ``disconnect``) are shared with the deployment twin, which needs pybullet
alone (the ``twin`` extra).
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
from typing import Any, SupportsFloat

import numpy as np

from sagrasp_jax.base import extras

extras.require("twin", what="the PyBullet reference env")
from sagrasp_jax.reference import bullet  # noqa: E402  (imports pybullet with its banner kept off the terminal)
import pybullet as pb  # noqa: E402

try:
    import gymnasium as gym
    from gymnasium import spaces
except ImportError:  # the twin uses this module's PyBullet helpers without gymnasium
    gym = spaces = None

from sagrasp_jax.reference import EPISODE_INFO
from sagrasp_jax.base import assets
from sagrasp_jax.task import collision
from sagrasp_jax.task import config
from sagrasp_jax.task import control
from sagrasp_jax.task import episode
from sagrasp_jax.task import observation
from sagrasp_jax.task import reward
from sagrasp_jax.task import robot
from sagrasp_jax.task import sampling
from sagrasp_jax.task import shapes
from sagrasp_jax.task.config import EnvConfig
from sagrasp_jax.task.robot import BOX, Kinematics
from sagrasp_jax.task.scene import SCENE
from sagrasp_jax.reference.bullet import disconnect, quaternions_to_rotations, rotation_to_quaternion, shape_kwargs  # noqa: F401

ENV_ID = "SAGrasp-PyBullet-v0"

# POSITION_CONTROL gains of servo="position_control", per arm joint: positionGain kp and velocityGain kd of
# PyBullet's motor constraint (after a substep h: v = kp·(q* − q)/h + (1 − kd)·v, whatever the arm's inertia).
# Refitted to the MJX env's servos by linear least squares over 19,200 physics substeps of scripted episodes
# (the position-control fit, docs/parity.md).  That law cannot follow MuJoCo's force servo (pose-dependent inertia,
# armature, torque limits), and parity fails with it (docs/parity.md); the default servo="mujoco" is exact.
DYNAMIC_POSITION_GAINS = (0.126, 0.087, 0.115, 0.142, 0.134, 0.143)  # fitted to the AUBO-i5's servos only
DYNAMIC_VELOCITY_GAINS = (0.636, 0.439, 0.584, 0.517, 0.493, 0.523)
GAINS_FITTED_FOR = "aubo_i5"  # the robot these position_control gains were fitted to (others must pass their own)
GRAVITY = 9.81  # m/s²: the world's gravity when the arm's weight is not left out (see _build_world)
UNLIMITED = 1e3  # a joint range no motion reaches (rad or m)
SERVOS = ("mujoco", "position_control")  # dynamic-mode motor models (PyBulletGraspEnv's ``servo``)
FINGER_FORCE_FALLBACK = 20.0  # N, used only if the URDF gives a finger no effort limit


def _as_numpy_spec(spec: sampling.ResetSpec, dof: int) -> sampling.ResetSpec:
    """A ResetSpec with plain float64 / bool / int NumPy leaves (it may come from JAX); ``dof`` joints."""
    return sampling.ResetSpec(
        q0=np.asarray(spec.q0, dtype=np.float64).reshape(dof),
        target_pos=np.asarray(spec.target_pos, dtype=np.float64).reshape(3),
        target_yaw=np.asarray(spec.target_yaw, dtype=np.float64).reshape(()),
        obstacle_active=np.asarray(spec.obstacle_active).astype(bool),
        obstacle_kind=np.asarray(spec.obstacle_kind).astype(np.int32),
        obstacle_pos=np.asarray(spec.obstacle_pos, dtype=np.float64),
        obstacle_yaw=np.asarray(spec.obstacle_yaw, dtype=np.float64),
        obstacle_size=np.asarray(spec.obstacle_size, dtype=np.float64),
        redraws=np.asarray(spec.redraws).astype(np.int64).reshape(()),
        fallback=np.asarray(spec.fallback).astype(bool).reshape(()),
    )



@dataclasses.dataclass(frozen=True)
class ServoModel:
    """The MJX env's arm position servos, read from the robot's MJCF (``spec.mjcf_robot``, e.g. ``aubo_i5_eg2.xml``).

    MuJoCo's law per joint i (``mjx.forward.fwd_actuation``): f_i = clip(kp_i·(u_i − q_i) − kv_i·v_i,
    forcerange_i), plus the gravity torque where ``actgravcomp_i`` (the servo carries the arm's
    weight), clipped again to the joint's ``actfrcrange_i``; the joint damping −d_i·v_i and, where the
    gravity torque is not the servo's, passive gravity compensation.  The implicitfast integrator
    solves the velocity step with (M + diag(armature) + h·diag(kv + d)) — the servo's damping is
    implicit, clamped or not (``mjx.derivative.deriv_smooth_vel``)."""

    kp: np.ndarray
    kv: np.ndarray
    ctrlrange: np.ndarray  # (n, 2)
    forcerange: np.ndarray  # (n, 2)
    actfrcrange: np.ndarray  # (n, 2)
    actgravcomp: np.ndarray  # (n,) bool
    armature: np.ndarray
    damping: np.ndarray


def load_servo_model(arm: robot.RobotModel, xml_path: str | None = None) -> ServoModel:
    """The servo constants of ``arm``'s MJCF, the one the MJX env loads (one source: the robot's
    ``robots.RobotSpec.servo``, which ``tools/urdf_to_mjcf.py`` writes into it)."""
    import mujoco

    path = xml_path or assets.path("mjcf", arm.spec.mjcf_robot)
    m = mujoco.MjModel.from_xml_path(path)
    rows = []
    for name in arm.spec.arm_joints:
        j = m.joint(name).id
        dof = int(m.jnt_dofadr[j])
        (act,) = [a for a in range(m.nu) if m.actuator_trnid[a, 0] == j]
        kp, kv = float(m.actuator_gainprm[act, 0]), -float(m.actuator_biasprm[act, 2])
        if m.actuator_biasprm[act, 1] != -kp or m.actuator_biasprm[act, 0] != 0:
            raise ValueError(f"{path}: actuator of {name} is not a position servo")
        limited = lambda flag, rng: rng if flag else np.array([-np.inf, np.inf])  # noqa: E731
        rows.append((kp, kv, limited(m.actuator_ctrllimited[act], m.actuator_ctrlrange[act]),
                     limited(m.actuator_forcelimited[act], m.actuator_forcerange[act]),
                     limited(m.jnt_actfrclimited[j], m.jnt_actfrcrange[j]), bool(m.jnt_actgravcomp[j]),
                     float(m.dof_armature[dof]), float(m.dof_damping[dof])))
    cols = list(zip(*rows))
    return ServoModel(*(np.asarray(c, dtype=bool if i == 5 else float) for i, c in enumerate(cols)))


RENDER_MODES = ("human", "rgb_array")
RENDER_WIDTH = 640  # px: rgb_array frames (the scene camera's field of view at 640 × 400)


def _advertised_render_modes() -> list[str]:
    """``human`` needs a display: a headless Linux machine advertises ``rgb_array`` only (so that
    ``gymnasium.utils.env_checker.check_env`` with its defaults does not open a GUI there)."""
    headless = sys.platform.startswith("linux") and not os.environ.get("DISPLAY")
    return [m for m in RENDER_MODES if not (headless and m == "human")]


class PyBulletGraspEnv(gym.Env if gym is not None else object):  # type: ignore[misc]
    """AUBO-i5 + EG2 gripper reaching a cuboid among random obstacles, simulated in PyBullet.

    ``reset(options={"reset_spec": spec})`` starts from an explicit ``sampling.ResetSpec``
    (what ``GraspEnv.reset_to`` takes); otherwise a reset is sampled from ``np_random``
    uniforms with the shared sampler.  ``progress`` (training progress p ∈ [0, 1] of the
    reward weights) is an attribute, or ``options={"progress": p}`` at reset.
    """

    metadata = {"render_modes": _advertised_render_modes(), "render_fps": 20}

    def __init__(
        self,
        cfg: EnvConfig | None = None,
        render_mode: str | None = None,
        mode: str | None = None,
        position_gains: tuple[float, ...] | None = None,
        velocity_gains: tuple[float, ...] | None = None,
        gravity_compensation: bool = True,
        servo: str = "mujoco",
        obs_layout: str | None = None,
    ) -> None:
        if gym is None:
            raise extras.MissingExtra(("reference",), ["gymnasium"], "the PyBullet reference env (a Gymnasium env)")
        cfg = cfg if cfg is not None else config.get_config("paper").env
        if obs_layout is not None:
            observation.layout(obs_layout)  # refuses an unknown name, listing the valid ones
            cfg = dataclasses.replace(cfg, task=dataclasses.replace(cfg.task, obs_layout=obs_layout))
        if mode is not None:
            cfg = dataclasses.replace(cfg, control=dataclasses.replace(cfg.control, mode=mode))
        if cfg.control.mode not in ("kinematic", "dynamic"):
            raise ValueError(f"control mode must be 'kinematic' or 'dynamic', got {cfg.control.mode!r}")
        if servo not in SERVOS:
            raise ValueError(f"servo must be one of {', '.join(SERVOS)}, got {servo!r}")
        if render_mode is not None and render_mode not in RENDER_MODES:
            raise ValueError(f"render_mode must be one of {list(RENDER_MODES)} or None, got {render_mode!r}")
        if cfg.sampling.max_obstacles != SCENE.obstacles.count:
            raise ValueError(f"the scene has {SCENE.obstacles.count} obstacle slots, config asks for {cfg.sampling.max_obstacles}")
        self.cfg = cfg
        self.render_mode = render_mode
        self.robot = robot.load_robot(cfg.robot)
        self.n_uniforms = sampling.uniforms_needed(cfg.sampling, self.robot.dof)
        fitted = self.robot.name == GAINS_FITTED_FOR
        if servo == "position_control" and not fitted and (position_gains is None or velocity_gains is None):
            raise ValueError(f"servo='position_control' has fitted gains for {GAINS_FITTED_FOR!r} only; robot "
                             f"{self.robot.name!r} needs position_gains and velocity_gains ({self.robot.dof} each)")
        self.position_gains = np.asarray(position_gains or (DYNAMIC_POSITION_GAINS if fitted else ()), dtype=float)
        self.velocity_gains = np.asarray(velocity_gains or (DYNAMIC_VELOCITY_GAINS if fitted else ()), dtype=float)
        self.gravity_compensation = gravity_compensation
        self.servo = servo
        self.servo_model = load_servo_model(self.robot) if cfg.control.mode == "dynamic" and servo == "mujoco" else None
        self.progress = 0.0

        self.action_space = spaces.Box(-1.0, 1.0, (self.robot.dof,), dtype=np.float32)
        self.obs_layout = observation.layout_of(cfg)
        self.observation_space = spaces.Box(-np.inf, np.inf, (len(self.obs_layout),), dtype=np.float64)

        if render_mode == "human" and sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
            # PyBullet's GUI would kill the whole process when it cannot open a window.
            raise RuntimeError("render_mode='human' needs a display (DISPLAY is not set); use 'rgb_array' or None")
        self._client = bullet.connect(pb.GUI if render_mode == "human" else pb.DIRECT)
        if self._client < 0:
            raise RuntimeError("could not connect to a PyBullet physics server")
        self._obstacle_bodies: list[int] = []
        self._spec: sampling.ResetSpec | None = None
        self._build_world()

    # -- world -----------------------------------------------------------------------------
    def _pb(self, fn: Any, *args: Any, **kwargs: Any) -> Any:
        return fn(*args, physicsClientId=self._client, **kwargs)

    def _static_body(self, kind: int, size: Any, pos: Any, rot: np.ndarray, rgba: Any) -> tuple[int, int]:
        """A fixed (mass 0) primitive body; returns (body, collision shape)."""
        col = self._pb(pb.createCollisionShape, **shape_kwargs(kind, size, visual=False))
        vis = -1
        if self.render_mode is not None:  # DIRECT runs need no visuals (PyBullet never frees them)
            vis = self._pb(pb.createVisualShape, rgbaColor=list(rgba), **shape_kwargs(kind, size, visual=True))
        body = self._pb(
            pb.createMultiBody,
            baseMass=0.0,
            baseCollisionShapeIndex=col,
            baseVisualShapeIndex=vis,
            basePosition=[float(v) for v in pos],
            baseOrientation=rotation_to_quaternion(rot),
        )
        return body, col

    def _build_world(self) -> None:
        """Robot from the project URDF, cell from ``scene.SCENE`` (the one description the MJCF uses too)."""
        ctl = self.cfg.control
        self._pb(pb.resetSimulation)
        # The MJCF compensates the arm's weight exactly (gravcomp="1" on every body, as the AUBO
        # controller does); PyBullet has no such attribute, and its motor constraint under gravity
        # sags by ~3.5 mrad at these gains.  The robot is the only dynamic body here (target and
        # obstacles are static), so exact compensation is the same as no gravity.
        # The "mujoco" servo carries the arm's weight itself (as the MJCF's actuator gravity compensation
        # does), so that world has gravity.
        weightless = self.gravity_compensation and self.servo_model is None
        self._pb(pb.setGravity, 0.0, 0.0, 0.0 if weightless else -GRAVITY)
        self._pb(pb.setTimeStep, ctl.physics_dt)
        if self.render_mode == "human":
            self._pb(pb.configureDebugVisualizer, pb.COV_ENABLE_GUI, 0)

        table = SCENE.table
        plane = self._pb(pb.createCollisionShape, shapeType=pb.GEOM_PLANE)
        vis = -1
        if self.render_mode is not None:
            vis = self._pb(pb.createVisualShape, shapeType=pb.GEOM_BOX, halfExtents=list(table.half_extents), rgbaColor=list(table.rgba),
                           visualFramePosition=[table.centre_xy[0], table.centre_xy[1], -table.half_extents[2]])
        self.table_body = self._pb(pb.createMultiBody, baseMass=0.0, baseCollisionShapeIndex=plane, baseVisualShapeIndex=vis,
                                   basePosition=[0.0, 0.0, table.top_z])
        self.static_bodies = {part.name: self._static_body(part.kind, part.size, part.pos, part.rot, part.rgba)[0]
                              for part in SCENE.static_parts}
        half = [s / 2 for s in self.cfg.sampling.target_size]
        self.target_body, _ = self._static_body(BOX, half, (0.0, 0.0, -1.0), np.eye(3), SCENE.target_rgba)

        flags = pb.URDF_USE_INERTIA_FROM_FILE  # else PyBullet recomputes inertias from the collision shapes
        # PyBullet warns about each link without <inertial> (fixed below); load_urdf keeps those warnings quiet
        self.robot_body = bullet.load_urdf(self._client, self.robot.urdf_path, basePosition=[0, 0, 0], useFixedBase=True,
                                           flags=flags)
        joints, links = {}, {}
        efforts = {}
        for j in range(self._pb(pb.getNumJoints, self.robot_body)):
            info = self._pb(pb.getJointInfo, self.robot_body, j)
            joints[info[1].decode()] = j
            links[info[12].decode()] = j  # a child link's index is its joint's index
            efforts[j] = float(info[10])
        movable = [j for j in range(self._pb(pb.getNumJoints, self.robot_body))
                   if self._pb(pb.getJointInfo, self.robot_body, j)[2] != pb.JOINT_FIXED]
        self.arm_joints = [joints[name] for name in self.robot.spec.arm_joints]
        self.finger_joints = [joints[name] for name in self.robot.spec.finger_joints]
        self._movable = movable  # PyBullet's dof order (mass matrix, inverse dynamics)
        self._servo_dofs = np.array([movable.index(j) for j in self.arm_joints])
        self.arm_links = [links[name] for name in self.robot.link_names[1:]]
        self.flange_link = joints[self.robot.spec.flange_joint]  # a fixed joint's index is its child link's index
        self.centre_link = joints[self.robot.spec.gripper_centre_joint]
        self._fk_links = self.arm_links + [self.flange_link, self.centre_link]
        self.arm_forces = [efforts[j] for j in self.arm_joints]
        self.finger_forces = [efforts[j] or FINGER_FORCE_FALLBACK for j in self.finger_joints]
        if not np.allclose(self.arm_forces, self.robot.effort_limit):
            raise RuntimeError("PyBullet read effort limits that differ from robot.load_robot()")
        # Frame-only links (flange, gripper_center) have no <inertial>; PyBullet would give them 1 kg and
        # a 1 kg·m² inertia.  They are massless in the URDF's intent and in the MJCF.
        for link in (self.flange_link, self.centre_link):
            self._pb(pb.changeDynamics, self.robot_body, link, mass=0.0, localInertiaDiagonal=[0.0, 0.0, 0.0])

        # Base link frame = base COM frame ∘ inverse(local inertial frame): PyBullet reports the COM.
        com_pos, com_quat = self._pb(pb.getBasePositionAndOrientation, self.robot_body)
        dyn = self._pb(pb.getDynamicsInfo, self.robot_body, -1)
        inv_pos, inv_quat = pb.invertTransform(dyn[3], dyn[4])
        base_pos, base_quat = pb.multiplyTransforms(com_pos, com_quat, inv_pos, inv_quat)
        self._base_pos = np.asarray(base_pos, dtype=float)
        self._base_rot = quaternions_to_rotations(np.asarray(base_quat))

        # Robot contacts off (as in the MJX env): collisions are the analytic rules.
        for link in range(-1, self._pb(pb.getNumJoints, self.robot_body)):
            self._pb(pb.setCollisionFilterGroupMask, self.robot_body, link, 0, 0)
            self._pb(pb.changeDynamics, self.robot_body, link, linearDamping=0.0, angularDamping=0.0)
        # Release PyBullet's default velocity motors (they act as joint friction).
        all_joints = self.arm_joints + self.finger_joints
        self._pb(pb.setJointMotorControlArray, self.robot_body, all_joints, pb.VELOCITY_CONTROL, forces=[0.0] * len(all_joints))
        if self.servo_model is not None:
            # The MJX env's dynamic mode runs without constraints (no joint-limit solver: the servo targets
            # are clipped to the limits); no limit here either (the fingers rest at theirs).
            for j in all_joints:
                self._pb(pb.changeDynamics, self.robot_body, j, jointLowerLimit=-UNLIMITED, jointUpperLimit=UNLIMITED)

    def _place_episode_bodies(self, spec: sampling.ResetSpec) -> None:
        """Target as a static multibody at its sampled pose; a fresh body per active obstacle slot."""
        self._pb(pb.resetBasePositionAndOrientation, self.target_body, spec.target_pos.tolist(),
                 rotation_to_quaternion(shapes.yaw_rotation(np, spec.target_yaw)))
        for body in self._obstacle_bodies:
            self._pb(pb.removeBody, body)
        # (PyBullet cannot free a collision shape once a body used it: a few hundred bytes per obstacle.)
        self._obstacle_bodies = []
        for slot in np.nonzero(spec.obstacle_active)[0]:
            kind = int(spec.obstacle_kind[slot])
            body, _ = self._static_body(
                shapes.BY_ID[kind].primitive, spec.obstacle_size[slot], spec.obstacle_pos[slot],
                shapes.world_rotation(kind, spec.obstacle_yaw[slot]), SCENE.obstacles.rgba,
            )
            self._obstacle_bodies.append(body)

    # -- robot state -----------------------------------------------------------------------
    def _set_joints(self, q: np.ndarray, qd: np.ndarray | None = None) -> None:
        qd = np.zeros(self.robot.dof) if qd is None else qd
        for j, value, vel in zip(self.arm_joints, q, qd):
            self._pb(pb.resetJointState, self.robot_body, j, float(value), float(vel))
        for j in self.finger_joints:
            self._pb(pb.resetJointState, self.robot_body, j, self.robot.finger_open, 0.0)

    def _measure(self) -> tuple[np.ndarray, np.ndarray]:
        states = self._pb(pb.getJointStates, self.robot_body, self.arm_joints)
        return np.array([s[0] for s in states], dtype=float), np.array([s[1] for s in states], dtype=float)

    def kinematics(self) -> Kinematics:
        """``robot.Kinematics`` built from PyBullet's own link frames (what every rule here sees)."""
        states = self._pb(pb.getLinkStates, self.robot_body, self._fk_links, computeForwardKinematics=True)
        pos = np.array([s[4] for s in states], dtype=float)
        rot = quaternions_to_rotations(np.array([s[5] for s in states], dtype=float))
        link_pos = np.concatenate([self._base_pos[None], pos[:self.robot.dof]])
        link_rot = np.concatenate([self._base_rot[None], rot[:self.robot.dof]])
        return Kinematics(
            link_pos=link_pos,
            link_rot=link_rot,
            joint_axes=link_rot[1:, :, 2],  # every arm joint turns about its child link's local z
            joint_pos=link_pos[1:],
            flange_pos=pos[self.robot.dof],
            gripper_centre=pos[self.robot.dof + 1],
            approach_axis=rot[self.robot.dof][:, 2],  # flange local +z
        )

    def _servo_substep(self, ctrl: np.ndarray) -> None:
        """One physics step of the MJX env's servos (``ServoModel``) on PyBullet's rigid-body dynamics:
        PyBullet gives the mass matrix M, the bias forces (Coriolis and gravity) and integrates; the
        arm's acceleration is MuJoCo's implicitfast step a = (M + diag(armature) + h·diag(kv + d))⁻¹·f,
        applied as the joint torques that produce it (PyBullet's inverse dynamics), the fingers' is zero
        (the MJX model welds them open).  PyBullet has no rotor inertia (armature), and its
        POSITION_CONTROL motor is a velocity constraint, not a force law (docs/parity.md)."""
        sm, h = self.servo_model, self.cfg.control.physics_dt
        assert sm is not None
        states = self._pb(pb.getJointStates, self.robot_body, self._movable)
        q_all = [s[0] for s in states]
        v_all = [s[1] for s in states]
        zero = [0.0] * len(self._movable)
        idx = self._servo_dofs
        mass = np.asarray(self._pb(pb.calculateMassMatrix, self.robot_body, q_all))[np.ix_(idx, idx)]
        bias = np.asarray(self._pb(pb.calculateInverseDynamics, self.robot_body, q_all, v_all, zero))[idx]
        gravity = np.asarray(self._pb(pb.calculateInverseDynamics, self.robot_body, q_all, zero, zero))[idx]
        q, v = np.asarray(q_all)[idx], np.asarray(v_all)[idx]
        force = np.clip(sm.kp * (ctrl - q) - sm.kv * v, sm.forcerange[:, 0], sm.forcerange[:, 1])
        force = np.clip(force + np.where(sm.actgravcomp, gravity, 0.0), sm.actfrcrange[:, 0], sm.actfrcrange[:, 1])
        smooth = force - sm.damping * v + np.where(sm.actgravcomp, 0.0, gravity) - bias
        acc = np.linalg.solve(mass + np.diag(sm.armature + h * (sm.kv + sm.damping)), smooth)
        acc_all = np.zeros(len(self._movable))
        acc_all[idx] = acc
        tau = np.asarray(self._pb(pb.calculateInverseDynamics, self.robot_body, q_all, v_all, acc_all.tolist()))
        self._pb(pb.setJointMotorControlArray, self.robot_body, self._movable, pb.TORQUE_CONTROL, forces=tau.tolist())
        self._pb(pb.stepSimulation)

    def _apply(self, q_target: np.ndarray) -> None:
        if self.cfg.control.mode == "kinematic":
            self._set_joints(q_target)
            return
        if self.servo_model is not None:
            sm = self.servo_model
            ctrl = np.clip(q_target, sm.ctrlrange[:, 0], sm.ctrlrange[:, 1])
            for _ in range(self.cfg.control.substeps):
                self._servo_substep(ctrl)
            return
        self._pb(
            pb.setJointMotorControlArray, self.robot_body, self.arm_joints, pb.POSITION_CONTROL,
            targetPositions=q_target.tolist(), targetVelocities=[0.0] * self.robot.dof, forces=self.arm_forces,
            positionGains=self.position_gains.tolist(), velocityGains=self.velocity_gains.tolist(),
        )
        self._pb(
            pb.setJointMotorControlArray, self.robot_body, self.finger_joints, pb.POSITION_CONTROL,
            targetPositions=[self.robot.finger_open] * len(self.finger_joints), forces=self.finger_forces,
        )
        for _ in range(self.cfg.control.substeps):
            self._pb(pb.stepSimulation)

    def _observe(self, q: np.ndarray, kin: Kinematics, col: collision.CollisionResult, tilt: Any) -> np.ndarray:
        task = self.cfg.task
        dof = self.robot.dof
        noise = self.np_random.normal(size=dof) if observation.noise_std(task, self.progress) > 0 else np.zeros(dof)
        assert self._spec is not None
        noisy_q = observation.noisy_joints(task, q, self.progress, noise)
        return observation.assemble(np, self.cfg, noisy_q, kin.gripper_centre, self._spec, col, tilt,
                                    self._q_target).astype(np.float64)

    # -- Gymnasium API ---------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        options = options or {}
        if "progress" in options:
            self.progress = float(options["progress"])
        spec = options.get("reset_spec")
        if spec is None:
            u = self.np_random.random(self.n_uniforms)
            spec = sampling.sample_reset(np, self.robot, self.cfg.sampling, self.cfg.task, u)
        spec = _as_numpy_spec(spec, self.robot.dof)
        self._spec = spec
        self._place_episode_bodies(spec)
        self._set_joints(spec.q0)
        self._q_target = spec.q0.copy()
        self._q, self._qd = self._measure()
        kin = self.kinematics()
        col = collision.check(np, self.robot, kin, spec, self.cfg)
        tilt = float(robot.tilt(np, kin.approach_axis))
        d0 = float(np.linalg.norm(kin.gripper_centre - spec.target_pos))
        blocking = bool(sampling.is_blocking(np, self.robot, self.cfg.sampling, self.cfg.task, spec))
        self._tracker = episode.start(np, self.cfg, np.float64(d0), np.float64(tilt), col, blocking)
        self._done = False
        obs = self._observe(self._q, kin, col, tilt)
        info = {"reset_spec": spec, "gripper_centre": kin.gripper_centre.copy(), "distance": d0, "tilt": tilt}
        return obs, info

    def step(self, action: Any) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        if self._spec is None or self._done:
            raise RuntimeError("call reset() before step() (the episode has ended)")
        cfg, spec = self.cfg, self._spec
        action = np.asarray(action, dtype=np.float64).reshape(self.robot.dof)
        ctl = control.control_step(np, self.robot, cfg.control, self._q_target, self._q, spec.target_pos, action)
        self._q_target = np.asarray(ctl.q_target, dtype=float)
        self._apply(self._q_target)
        self._q, self._qd = self._measure()
        kin = self.kinematics()
        col = collision.check(np, self.robot, kin, spec, cfg)
        tilt = float(robot.tilt(np, kin.approach_axis))
        d_now = float(np.linalg.norm(kin.gripper_centre - spec.target_pos))
        step = episode.advance(np, cfg, self._tracker, spec, progress=self.progress, d_now=np.float64(d_now), col=col,
                               gripper_centre=kin.gripper_centre, tilt=tilt)
        self._tracker = step.tracker
        total, terms, outcome = float(step.reward), step.terms, step.outcome
        # Gymnasium's convention: a time limit truncates; collision and success terminate
        # (on one step collision > success > timeout, so a timeout flag means neither happened)
        truncated = bool(step.done) and bool(outcome.timeout) and not (bool(outcome.collision) or bool(outcome.success))
        terminated = bool(step.done) and not truncated
        self._done = terminated or truncated
        obs = self._observe(self._q, kin, col, tilt)
        info: dict[str, Any] = {
            "gripper_centre": kin.gripper_centre.copy(),
            "distance": d_now,
            "tilt": tilt,
            **{key: float(value) for key, value in terms.values.items()},  # each reward term (reward.term_keys)
            "success": bool(outcome.success),
            "collision": bool(outcome.collision),
            "timeout": bool(outcome.timeout),
            "hits": {name: bool(hit) for name, hit in col.hits.items()},
            "slowed": bool(ctl.slowed),
            "finetuned": bool(ctl.finetuned),
            "q_target": self._q_target.copy(),
        }
        if self._done:
            # not info["episode"]: Gymnasium's RecordEpisodeStatistics (and SB3's Monitor) own that key
            info[EPISODE_INFO] = {k: float(v) for k, v in step.episode.items()}
            info["is_success"] = bool(outcome.success)  # what Stable-Baselines3 logs as success rate
        if self.render_mode == "human":
            self.render()
        return obs, total, terminated, truncated, info

    # -- extras ----------------------------------------------------------------------------
    def force_state(
        self,
        q: Any,
        q_target: Any,
        qd: Any | None = None,
        *,
        steps: int | None = None,
        d_prev: float | None = None,
        clean: bool | None = None,
        obstacle_dist_prev: float | None = None,
    ) -> None:
        """Put the episode mid-way into a given state: joints ``q`` (velocities ``qd``), accumulated
        target ``q_target``, step count, previous distance, clean-so-far flag and previous Δpo.  For single-step
        comparisons from a state forced identical to the other simulator's (docs/task.md §2 parity rules)."""
        if self._spec is None:
            raise RuntimeError("call reset() before force_state()")
        q = np.asarray(q, dtype=float)
        self._set_joints(q, None if qd is None else np.asarray(qd, dtype=float))
        self._q, self._qd = self._measure()
        self._q_target = np.asarray(q_target, dtype=float).copy()
        if d_prev is None:
            kin = self.kinematics()
            d_prev = float(reward.approach_potential(np, self.cfg.reward, np.linalg.norm(kin.gripper_centre - self._spec.target_pos),
                                                     robot.tilt(np, kin.approach_axis)))
        tracker = self._tracker._replace(d_prev=np.float64(d_prev))
        if steps is not None:
            tracker = tracker._replace(steps=np.int32(steps))
        if clean is not None:
            tracker = tracker._replace(clean=np.bool_(clean))
        if obstacle_dist_prev is not None:
            tracker = tracker._replace(obstacle_dist_prev=np.float64(obstacle_dist_prev))
        self._tracker = tracker
        self._done = False

    def pybullet_distance(self, max_distance: float = 0.5) -> dict[str, float]:
        """PyBullet's own closest distance (``getClosestPoints``, exact primitives) from the robot to
        the target, each obstacle and the table: an independent check of ``collision.check``, whose
        sphere cover is conservative by up to its bulge.  The base and shoulder, which stand on the
        table, are left out of the table distance (as in the collision rules)."""
        standing = {-1, self.arm_links[0]}
        bodies = {"target": self.target_body, "table": self.table_body}
        bodies |= {f"obstacle_{i}": b for i, b in enumerate(self._obstacle_bodies)}
        out = {}
        for name, body in bodies.items():
            points = self._pb(pb.getClosestPoints, self.robot_body, body, max_distance)
            dists = [p[8] for p in points if not (name == "table" and p[3] in standing)]
            out[name] = min(dists, default=math.inf)
        return out

    @property
    def client(self) -> int:
        return self._client

    @property
    def reset_spec(self) -> sampling.ResetSpec | None:
        return self._spec

    def render(self) -> np.ndarray | None:
        """``rgb_array``: an image from the calibrated scene camera (its field of view, ``RENDER_WIDTH`` wide); ``human``: the GUI shows itself."""
        if self.render_mode != "rgb_array":
            return None
        cam = SCENE.camera
        k = cam.model.intrinsics.scaled(RENDER_WIDTH / cam.resolution[0])  # the camera's field of view, 640 px wide
        width, height = k.width, k.height
        eye = np.asarray(cam.pos)
        view = self._pb(pb.computeViewMatrix, eye.tolist(), (eye + cam.optical_axis).tolist(), (-cam.rot[:, 1]).tolist())
        proj = self._pb(pb.computeProjectionMatrixFOV, cam.fovy_deg, width / height, 0.05, 3.0)
        img = self._pb(pb.getCameraImage, width, height, view, proj, renderer=pb.ER_TINY_RENDERER)
        return np.asarray(img[2], dtype=np.uint8).reshape(height, width, 4)[..., :3]

    def close(self) -> None:
        self._client = disconnect(getattr(self, "_client", -1))
