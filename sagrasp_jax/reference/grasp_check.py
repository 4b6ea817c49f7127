"""Physical grasp check (docs/task.md §2): does the kinematic success pose really hold the cube?

Training scores a grasp kinematically (gripper centre over the cube, pointing down, no
collision).  This check replays the end of an episode with physics on CPU MuJoCo, from
the robot's scene MJCF (``RobotSpec.mjcf_scene``: ``sagrasp_jax/mjcf/scene.xml`` for the AUBO-i5) adapted in
memory with ``mujoco.MjSpec`` for that episode:

* the target, a mocap body in the training model, gets a free joint (it can be lifted) and
  the episode's pose; the obstacle slots get the episode's shape, size and pose;
* the arm starts at the final joint vector, fingers open, and is held by its position servos;
* the fingers close (pad-cube contacts on), then the servos lift the gripper centre by
  ``lift`` metres along the same IK path the deployment loop uses (``robot.lift_pose``);
* success: the cube rose with the gripper (within ``HOLD_TOLERANCE``), both pads still touch
  it, and its centre lies between the pads.

``GraspScene`` is the adapted model with those operations; ``MujocoRobot`` implements the
deployment loop's ``RobotInterface`` protocol so the loop itself can run in MuJoCo (the renderer
uses it).  ``evaluate.evaluate_physical`` re-plays an evaluation's episodes with the JAX env and
checks every kinematic success here (``python -m sagrasp_jax.evaluate --physical``).  Nothing
here imports jax or the deployment package.
"""

from __future__ import annotations

import math
import os
from typing import Any, Callable

import mujoco
import numpy as np

from sagrasp_jax.base import assets
from sagrasp_jax.task import robot as robot_mod
from sagrasp_jax.task import scene_mjcf
from sagrasp_jax.task import shapes
from sagrasp_jax.task.robot import lift_pose
from sagrasp_jax.task.sampling import ResetSpec

PHYSICS_DT = 0.002  # s; finer than the training model's 0.01 s: pad-cube contacts under squeeze
SETTLE_S = 0.1  # s with fingers open before closing (the cube settles on the table)
CLOSE_S = 0.5  # s for the fingers to close and squeeze
LIFT_S = 1.0  # s ramp of the arm servo targets to the lift pose
HOLD_S = 0.5  # s holding the lifted pose before measuring
LIFT_HEIGHT = 0.05  # m, docs/task.md §2
HOLD_TOLERANCE = 0.01  # m the cube may lag behind the gripper's rise (soft contacts slip a few mm)
FrameCallback = Callable[["GraspScene"], None]


class PhysicalCheckError(ValueError):
    """Inputs the physical check cannot run from (wrong shapes, NaN, unknown obstacle kind)."""


def _yaw_quat(yaw: float) -> np.ndarray:
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def _as_numpy(spec: ResetSpec) -> ResetSpec:
    """Plain NumPy leaves (the spec may come from JAX), validated."""
    out = ResetSpec(*(np.asarray(v) for v in spec))
    if out.target_pos.shape != (3,) or not np.isfinite(out.target_pos).all():
        raise PhysicalCheckError(f"reset_spec.target_pos must be 3 finite numbers, got {out.target_pos!r}")
    if out.obstacle_pos.ndim != 2 or out.obstacle_pos.shape[1] != 3:
        raise PhysicalCheckError(f"reset_spec.obstacle_pos must be (slots, 3), got {out.obstacle_pos.shape}")
    return out


def scene_xml(arm: robot_mod.RobotModel) -> str:
    """The MJCF of ``arm`` in the cell (its registry entry's ``mjcf_scene``)."""
    return assets.path("mjcf", arm.spec.mjcf_scene)


class GraspScene:
    """The robot's scene MJCF for one episode: free-jointed target, obstacles placed, arm at ``q``.

    ``arm`` is the robot (``robot.load_robot(env_cfg.robot)``; default the default robot); ``xml_path`` defaults
    to its scene (``scene_xml``)."""

    def __init__(self, reset_spec: ResetSpec, q: Any, physics_dt: float = PHYSICS_DT, xml_path: str | None = None,
                 arm: robot_mod.RobotModel | None = None) -> None:
        spec = _as_numpy(reset_spec)
        self.robot = arm or robot_mod.load_robot()
        self.dof = self.robot.dof
        q = np.asarray(q, dtype=float)
        if q.shape != (self.dof,) or not np.isfinite(q).all():
            raise PhysicalCheckError(f"arm joints must be {self.dof} finite numbers ({self.robot.name}), got {q!r}")
        self.reset_spec = spec
        self.model = self._build_model(spec, xml_path or scene_xml(self.robot))
        self.model.opt.timestep = physics_dt
        self.data = mujoco.MjData(self.model)
        self.time_s = 0.0
        self._finger_qpos = self.model.jnt_qposadr[[self.model.joint(n).id for n in self.robot.spec.finger_joints]]
        self._target_qpos = int(self.model.jnt_qposadr[self.model.body("target").jntadr[0]])
        # the pads: the contact links' geoms (tools/urdf_to_mjcf.py names a link's geom LINK_geom), left then right
        self._pads = {self.model.geom(f"{link}_geom").id: side
                      for link, side in zip(self.robot.spec.contact_links, ("left", "right"))}
        self._target_geom = self.model.geom("target_geom").id
        self.set_fingers(self.robot.finger_open)
        self.set_arm(q)

    @staticmethod
    def _build_model(spec: ResetSpec, xml_path: str) -> mujoco.MjModel:
        """Compile the scene with the target made free and the episode's obstacles in their slots."""
        if not os.path.isfile(xml_path):
            raise FileNotFoundError(f"{xml_path}: MuJoCo scene not found")
        mj = scene_mjcf.load_scene_spec(xml_path)  # every registered kind's geom in every slot
        target = mj.body("target")
        target.mocap = False
        target.add_freejoint()
        target.pos = spec.target_pos.tolist()
        target.quat = _yaw_quat(float(spec.target_yaw)).tolist()
        for slot in range(spec.obstacle_pos.shape[0]):
            body = mj.body(scene_mjcf.slot_body_name(slot))
            if body is None:
                raise PhysicalCheckError(f"{xml_path} has no obstacle slot {slot}")
            active = bool(spec.obstacle_active[slot])
            kind = int(spec.obstacle_kind[slot])
            if active and kind not in shapes.BY_ID:
                raise PhysicalCheckError(f"obstacle slot {slot}: unknown kind {kind}")
            if active:
                body.pos = spec.obstacle_pos[slot].tolist()
                body.quat = _yaw_quat(float(spec.obstacle_yaw[slot])).tolist()
            for shape in shapes.SHAPES:  # the slot has one geom per kind (its tilt is the geom's own)
                geom = mj.geom(scene_mjcf.obstacle_geom_name(slot, shape))
                chosen = active and shape.id == kind
                size = spec.obstacle_size[slot]
                if chosen:
                    geom.size = [float(size[0]), float(size[1]), float(size[2])]
                # The chosen shape is solid against the pads and the cube; the others vanish.
                geom.contype = geom.conaffinity = int(chosen)
                geom.rgba = [*geom.rgba[:3], 1.0 if chosen else 0.0]
        return mj.compile()

    # -- state -----------------------------------------------------------------------------
    def set_arm(self, q: Any) -> None:
        """Put the arm at ``q`` at rest with its servos aimed there (kinematic placement)."""
        q = np.asarray(q, dtype=float)
        self.data.qpos[:self.dof] = q
        self.data.qvel[:] = 0.0
        self.data.ctrl[:self.dof] = q
        mujoco.mj_forward(self.model, self.data)

    def set_fingers(self, opening: float) -> None:
        """Put both fingers at ``opening`` (m per finger, 0 = closed) with their servos aimed there."""
        self.data.qpos[self._finger_qpos] = opening
        self.data.ctrl[self.dof:] = opening
        mujoco.mj_forward(self.model, self.data)

    @property
    def arm_q(self) -> np.ndarray:
        return self.data.qpos[:self.dof].copy()

    @property
    def fingers(self) -> np.ndarray:
        return self.data.qpos[self._finger_qpos].copy()

    @property
    def gripper_centre(self) -> np.ndarray:
        return self.data.site("gripper_center").xpos.copy()

    @property
    def cube_pos(self) -> np.ndarray:
        return self.data.qpos[self._target_qpos : self._target_qpos + 3].copy()

    def pad_contacts(self) -> dict[str, bool]:
        """Which finger pads touch the cube now."""
        touching = {"left": False, "right": False}
        for c in self.data.contact[: self.data.ncon]:
            pair = {int(c.geom1), int(c.geom2)}
            if self._target_geom in pair:
                for gid, side in self._pads.items():
                    if gid in pair:
                        touching[side] = True
        return touching

    def cube_in_gripper_frame(self) -> np.ndarray:
        """Cube centre in the gripper-centre frame (x: finger axis, z: approach axis)."""
        site = self.data.site("gripper_center")
        return site.xmat.reshape(3, 3).T @ (self.cube_pos - site.xpos)

    # -- physics ---------------------------------------------------------------------------
    def simulate(self, seconds: float, arm_ctrl: Callable[[float], np.ndarray] | None = None,
                 on_frame: FrameCallback | None = None, frame_dt: float = 0.05) -> None:
        """Step physics for ``seconds``; ``arm_ctrl(fraction)`` sets the arm servo targets over the
        interval; ``on_frame`` is called every ``frame_dt`` of simulated time (video frames)."""
        dt = self.model.opt.timestep
        n = max(1, int(round(seconds / dt)))
        per_frame = max(1, int(round(frame_dt / dt)))
        for k in range(n):
            if arm_ctrl is not None:
                self.data.ctrl[:self.dof] = arm_ctrl((k + 1) / n)
            mujoco.mj_step(self.model, self.data)
            self.time_s += dt
            if on_frame is not None and (k + 1) % per_frame == 0:
                on_frame(self)

    def close_fingers(self, on_frame: FrameCallback | None = None, frame_dt: float = 0.05) -> None:
        """Let the cube settle under the open fingers, then close them on it (servo target 0)."""
        self.simulate(SETTLE_S, on_frame=on_frame, frame_dt=frame_dt)
        self.data.ctrl[self.dof:] = 0.0
        self.simulate(CLOSE_S, on_frame=on_frame, frame_dt=frame_dt)

    def drive_arm(self, q_goal: Any, seconds: float, on_frame: FrameCallback | None = None) -> None:
        """Ramp the arm servo targets linearly from their current values to ``q_goal``."""
        start = self.data.ctrl[:self.dof].copy()
        goal = np.asarray(q_goal, dtype=float)
        self.simulate(seconds, lambda f: start + f * (goal - start), on_frame)


def physical_grasp_check(q_final: Any, reset_spec: ResetSpec, *, lift: float = LIFT_HEIGHT,
                         physics_dt: float = PHYSICS_DT, on_frame: FrameCallback | None = None,
                         arm: robot_mod.RobotModel | None = None) -> dict[str, Any]:
    """Close the fingers at ``q_final``, lift ``lift`` m, report whether the cube came along.

    Returns a JSON-safe dict: ``success``, ``reason`` (why not, or ""), ``cube_rise`` and
    ``gripper_rise`` (m), ``pad_contacts``, ``finger_opening`` (m per finger after closing),
    ``cube_in_gripper`` (cube centre in the gripper frame at the end, m).
    """
    q_final = np.asarray(q_final, dtype=float)
    scene = GraspScene(reset_spec, q_final, physics_dt, arm=arm)
    cube0, centre0 = scene.cube_pos, scene.gripper_centre
    scene.close_fingers(on_frame)
    closed = scene.fingers
    q_lift = lift_pose(scene.robot, q_final, lift)
    scene.drive_arm(q_lift, LIFT_S, on_frame)
    scene.simulate(HOLD_S, on_frame=on_frame)

    cube_rise = float(scene.cube_pos[2] - cube0[2])
    gripper_rise = float(scene.gripper_centre[2] - centre0[2])
    contacts = scene.pad_contacts()
    local = scene.cube_in_gripper_frame()
    # Pad inner faces sit at ±(finger joint value) along the finger axis (0 = closed, docs/task.md §1).
    half_gap = float(np.mean(scene.fingers))
    criteria = {
        "rose_with_gripper": cube_rise >= gripper_rise - HOLD_TOLERANCE,
        "both_pads_touch": all(contacts.values()),
        "between_pads": abs(float(local[0])) < half_gap + 1e-3,
    }
    reasons = []
    if not criteria["rose_with_gripper"]:
        reasons.append(f"cube rose {cube_rise * 1000:.1f} mm while the gripper rose {gripper_rise * 1000:.1f} mm")
    if not criteria["both_pads_touch"]:
        missing = " and ".join(side for side, on in contacts.items() if not on)
        reasons.append(f"{missing} pad not touching the cube")
    if not criteria["between_pads"]:
        reasons.append(f"cube centre {local[0] * 1000:.1f} mm along the finger axis, outside the pads (±{half_gap * 1000:.1f} mm)")
    return {
        "success": all(criteria.values()),
        "reason": "; ".join(reasons),
        "criteria": criteria,
        "cube_rise": cube_rise,
        "gripper_rise": gripper_rise,
        "lift": float(lift),
        "pad_contacts": contacts,
        "finger_opening": [float(v) for v in closed],
        "cube_in_gripper": [float(v) for v in local],
        "cube_shift_at_close": float(np.linalg.norm(scene.cube_pos[:2] - cube0[:2])),
    }


class MujocoRobot:
    """The deployment loop's ``RobotInterface`` on a ``GraspScene``: the loop run in MuJoCo.

    Joint targets are applied kinematically (``qpos = q``, training's default mode: the AUBO
    tracks targets precisely) until the gripper closes; from then on they are tracked by the
    arm servos with physics for one control period each, so a grasped cube is carried.
    """

    def __init__(self, scene: GraspScene, control_dt: float = 0.05, on_frame: FrameCallback | None = None) -> None:
        self.scene = scene
        self.control_dt = control_dt
        self.on_frame = on_frame
        self.physics = False

    def read_joints(self) -> np.ndarray:
        return self.scene.arm_q

    def command_joint_targets(self, q: np.ndarray) -> None:
        if self.physics:
            self.scene.drive_arm(q, self.control_dt)
        else:
            self.scene.set_arm(q)
        if self.on_frame is not None:
            self.on_frame(self.scene)

    def open_gripper(self) -> None:
        self.scene.set_fingers(self.scene.robot.finger_open)

    def close_gripper(self) -> None:
        self.physics = True
        self.scene.close_fingers(self.on_frame, self.control_dt)

    def object_position(self) -> np.ndarray:
        return self.scene.cube_pos
