"""Safety layer between the policy and the real arm: refuse, never clip (docs/task.md §5).

Every joint target the deployment loop is about to send passes ``SafetyLayer.check``.
A command that breaks a rule raises ``SafetyViolation`` naming the joint or axis, the
value and the limit; the loop must then stop the arm.  Clipping silently would hide a
policy, calibration or control-step bug behind a motion nobody asked for.

Every limit comes from the robot description (the URDF of the policy's ``env.robot``, e.g.
``sagrasp_jax/urdf/aubo_i5_eg2.urdf``, via ``robot.load_robot``) and the deployment's own settings
(``DeploySettings``: the controller's
command period and the largest joint-target change per command, docs/task.md §2; the cell's cube
size, target region and obstacle clearance, docs/task.md §1.4-1.5), **never from a policy file**: a
policy is data from elsewhere, and an edited one must not be able to loosen a limit.  A policy trained
with other control constants or for another cell is refused before anything moves
(``check_policy_constants``, ``check_policy_scene``).

Rules (all NumPy):

1. joint limits: ``q_lower ≤ q ≤ q_upper`` per joint (URDF);
2. per-step motion: ``|q − q_prev| ≤ min(velocity_limit·control_dt, max_step)`` per joint
   (URDF velocity limits, ``DeploySettings``), with ``q_prev`` the previous commanded target
   (the target accumulates, docs/task.md §2 step 4); with the defaults max_step = 0.05 rad is the
   binding bound (2.5964 rad/s × 0.05 s = 0.13 rad);
3. workspace box for the gripper centre (``WorkspaceBox``, derivation below);
4. table: every primitive on a moving link above the shoulder (upper arm, forearm, wrists,
   flange, gripper body, fingers) stays above the table top z = 0 (+ ``table_clearance``).
   The base and shoulder are excluded: their height never changes (joint 1 turns about z)
   and the shoulder capsule of the URDF dips 1 cm into the table by construction;
5. optionally, a caller-supplied ``collision_check(q) -> message | None``: the deployment loop
   wires ``collision.check`` (self-collision, the cell, the obstacles and the cube) here.

Default workspace box (world = URDF base frame, metres), derived from docs/task.md §1:

* x ∈ [−0.50, 0.50]: the gantry posts' inner faces are at |x| = 0.58; 0.50 keeps the
  gripper body (half-width 0.045) 3.5 cm clear of them, and leaves 0.13 m beyond the
  trained target range |x| ≤ 0.35 (+0.02 detection margin).
* y ∈ [−0.85, 0.30]: targets lie in y ∈ [−0.60, −0.25] and the home gripper centre at
  y = −0.30; −0.85 leaves room for approach swings past the far edge, +0.30 lets the
  gripper pass the base side but not swing behind the robot.
* z ∈ [0.0, 1.0]: above the table; the camera body's bottom is at ≈ 1.37 m, so with the
  gripper pointing down its flange (0.128 m above the centre) and wrist stay ≥ 0.2 m below it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

import dataclasses

from sagrasp_jax.task.config import ControlConfig, EnvConfig, SamplingConfig
from sagrasp_jax.task.scene import SCENE
from sagrasp_jax.task.robot import (
    BOX,
    CAPSULE,
    CYLINDER,
    SPHERE,
    RobotModel,
    forward_kinematics,
    load_robot,
    primitive_poses,
)

_TOL = 1e-9  # float slack: the control step clips to the limit exactly, do not refuse that


class SafetyViolation(RuntimeError):
    """A joint command that must not reach the robot; the message says which rule and by how much."""


class PolicyMismatch(ValueError):
    """A policy trained with control constants other than this robot's and deployment's."""


@dataclass(frozen=True)
class WorkspaceBox:
    """Axis-aligned box the gripper centre must stay in (world frame, m); see module docstring."""

    lower: tuple[float, float, float] = (-0.50, -0.85, 0.0)
    upper: tuple[float, float, float] = (0.50, 0.30, 1.0)

    def __post_init__(self) -> None:
        if not all(lo < hi for lo, hi in zip(self.lower, self.upper)):
            raise ValueError(f"workspace box lower {self.lower} must be below upper {self.upper} on every axis")


_TASK_CONTROL = ControlConfig()  # docs/task.md §2's constants: the code's, not a policy file's
_TASK_SAMPLING = SamplingConfig()  # docs/task.md §1.4's trained region and clearance: the code's, not a policy file's
# The cell facts a policy file records and the deployment checks with (env.sampling keys): units for messages.
SCENE_KEYS = {"target_size": "m, full extents", "target_x": "m", "target_y": "m", "target_radius": "m",
              "target_clearance": "m"}


@dataclass(frozen=True)
class DeploySettings:
    """The deployment's own constants (docs/task.md §2, §5), fixed here and not read from any policy.

    ``control_dt``: the controller's command period (s, 20 Hz); ``max_step``: the largest change
    of one joint's target per command (rad, docs/task.md §2's q_max).  A policy must have been trained
    with exactly these (``check_policy_constants``).
    """

    control_dt: float = _TASK_CONTROL.control_dt
    max_step: float = _TASK_CONTROL.q_max
    workspace: WorkspaceBox = WorkspaceBox()
    table_clearance: float = 0.0
    # The cell (docs/task.md §1, ``scene.SCENE``): the cube's full extents, the region its centre may be in and the
    # closest an obstacle may stand to it.  Targets, obstacles and collisions are checked with these.
    target_size: tuple[float, float, float] = SCENE.target_size
    target_x: tuple[float, float] = _TASK_SAMPLING.target_x
    target_y: tuple[float, float] = _TASK_SAMPLING.target_y
    target_radius: tuple[float, float] = _TASK_SAMPLING.target_radius
    target_clearance: float = _TASK_SAMPLING.target_clearance

    def __post_init__(self) -> None:
        for name in ("control_dt", "max_step"):
            value = getattr(self, name)
            if not (np.isfinite(value) and 0 < value <= 1.0):
                raise ValueError(f"deployment setting {name} = {value!r} must be in (0, 1]")
        if not (np.isfinite(self.table_clearance) and 0 <= self.table_clearance <= 0.5):
            raise ValueError(f"deployment setting table_clearance = {self.table_clearance!r} m must be in [0, 0.5]")


def deployment_q_limit(robot: RobotModel) -> tuple[float, str]:
    """The joint-target cap (``env.control.q_limit``, rad) a policy for ``robot`` must have been trained with, and
    what it is: the URDF's bound where every joint has the same symmetric limit ±L (the AUBO-i5: ±175°), so that the
    policy's clip is the robot's limit; otherwise (the Panda's limits differ per joint and are not symmetric) the
    config's default cap, the one training applies on top of the URDF's limits."""
    bound = float(np.min(np.minimum(-robot.q_lower, robot.q_upper)))
    if np.allclose(-robot.q_lower, bound, rtol=0, atol=1e-12) and np.allclose(robot.q_upper, bound, rtol=0, atol=1e-12):
        return bound, "URDF joint limit"
    return float(ControlConfig().q_limit), f"default cap ({robot.name}'s URDF limits are not one symmetric bound)"


def check_policy_constants(env_cfg: EnvConfig, settings: DeploySettings | None = None,
                           robot: RobotModel | None = None, source: str = "policy") -> None:
    """Refuse a policy whose control constants differ from the deployment's and the robot's:
    its actions would not mean what they meant in training, and its joint clip would not be the
    robot's limit.  Raises PolicyMismatch naming each constant, the policy's value and ours."""
    settings = settings or DeploySettings()
    robot = robot or load_robot(env_cfg.robot)
    if env_cfg.robot != robot.name:
        raise PolicyMismatch(f"{source} was trained for the robot {env_cfg.robot!r}; this robot is {robot.name!r}")
    ctl = env_cfg.control
    q_limit, q_limit_what = deployment_q_limit(robot)
    problems = [
        f"{name} {ours_name}: policy {theirs!r}, {where} {ours!r}"
        for name, theirs, ours, ours_name, where in (
            ("env.control.q_max", ctl.q_max, settings.max_step, "(rad per step)", "deployment"),
            ("env.control.control_dt", ctl.control_dt, settings.control_dt, "(s)", "deployment"),
            ("env.control.q_limit", ctl.q_limit, q_limit, "(rad)", q_limit_what),
        )
        if not np.isclose(float(theirs), float(ours), rtol=1e-9, atol=0.0)
    ]
    if problems:
        raise PolicyMismatch(f"{source} was trained with control constants this robot does not use: "
                             + "; ".join(problems))


def check_policy_scene(env_cfg: EnvConfig, settings: DeploySettings | None = None, source: str = "policy") -> None:
    """Refuse a policy that records another cell than the deployment's (``SCENE_KEYS``: the cube's
    size, the trained target region, the obstacle clearance): the deployment checks targets, obstacles
    and collisions with its own values, and a file edited to widen the region or shrink the cube must
    not get past them.  Raises PolicyMismatch naming each key, the policy's value and ours."""
    settings = settings or DeploySettings()
    problems = []
    for key, unit in SCENE_KEYS.items():
        theirs, ours = getattr(env_cfg.sampling, key), getattr(settings, key)
        if np.shape(theirs) != np.shape(ours) or not np.allclose(theirs, ours, rtol=1e-9, atol=0.0):
            show = (lambda v: [float(x) for x in v]) if np.ndim(ours) else float
            problems.append(f"env.sampling.{key} ({unit}): policy {show(theirs)}, deployment {show(ours)}")
    if problems:
        raise PolicyMismatch(f"{source} was trained for a cell this deployment does not have: " + "; ".join(problems)
                             + " (deploy.safety.DeploySettings)")


def deployment_env(env_cfg: EnvConfig, settings: DeploySettings | None = None) -> EnvConfig:
    """``env_cfg`` with the cell facts (``SCENE_KEYS``) of the deployment, not of the policy file."""
    settings = settings or DeploySettings()
    sampling = dataclasses.replace(env_cfg.sampling, **{key: getattr(settings, key) for key in SCENE_KEYS})
    return dataclasses.replace(env_cfg, sampling=sampling)


def lowest_points(robot: RobotModel, prim_pos: np.ndarray, prim_rot: np.ndarray) -> np.ndarray:
    """Lowest world z (G,) of every robot primitive at the given poses (exact for each shape)."""
    kind = robot.prim_kind
    size = robot.prim_size
    rz = prim_rot[:, 2, :]  # world z component of each local axis
    centre_z = prim_pos[:, 2]
    box = np.sum(np.abs(rz) * size, axis=-1)
    axial = np.abs(rz[:, 2])
    sphere = size[:, 0]
    capsule = axial * size[:, 1] + size[:, 0]
    cylinder = axial * size[:, 1] + size[:, 0] * np.sqrt(np.clip(1.0 - axial**2, 0.0, 1.0))
    extent = np.select([kind == SPHERE, kind == CAPSULE, kind == BOX, kind == CYLINDER], [sphere, capsule, box, cylinder])
    return centre_z - extent


class SafetyLayer:
    """Checks joint commands against the robot's limits and the cell; raises SafetyViolation."""

    def __init__(
        self,
        settings: DeploySettings | None = None,
        robot: RobotModel | None = None,
        workspace: WorkspaceBox | None = None,
        table_clearance: float | None = None,
        collision_check: Callable[[np.ndarray], str | None] | None = None,
    ) -> None:
        if settings is not None and not isinstance(settings, DeploySettings):
            raise TypeError(f"SafetyLayer takes DeploySettings, got {type(settings).__name__}: its limits come from "
                            "the URDF and the deployment settings, never from a policy's config")
        self.settings = settings or DeploySettings()
        self.robot = robot or load_robot()
        self.workspace = workspace or self.settings.workspace
        self.table_clearance = float(self.settings.table_clearance if table_clearance is None else table_clearance)
        self.collision_check = collision_check
        self.joint_names = tuple(f"joint {i + 1} ({name})" for i, name in enumerate(self.robot.spec.arm_joints))
        self.control_dt = float(self.settings.control_dt)
        self.max_step = float(self.settings.max_step)
        # Per-joint bound on one control step's change of the commanded target.
        self.step_limit = np.minimum(self.robot.velocity_limit * self.control_dt, self.max_step)
        # the table rule checks the links that can reach it (the robot's reach_link on: the AUBO's upper arm)
        self._checked_prims = np.nonzero(self.robot.prim_link >= self.robot.spec.reach_link)[0]

    def _as_q(self, q: Any, what: str) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        if q.shape != (self.robot.dof,):
            raise SafetyViolation(f"{what} must be {self.robot.dof} joint values, got shape {q.shape}")
        if not np.isfinite(q).all():
            bad = ", ".join(self.joint_names[i] for i in np.nonzero(~np.isfinite(q))[0])
            raise SafetyViolation(f"{what} has NaN/inf for {bad}")
        return q

    def check_pose(self, q: Any, what: str = "commanded target") -> np.ndarray:
        """Static rules (limits, workspace, table, collision hook) for one joint vector."""
        q = self._as_q(q, what)
        lo, hi = self.robot.q_lower, self.robot.q_upper
        for i in range(self.robot.dof):
            if not lo[i] - _TOL <= q[i] <= hi[i] + _TOL:
                raise SafetyViolation(
                    f"{what}: {self.joint_names[i]} = {q[i]:.4f} rad is outside its limit [{lo[i]:.4f}, {hi[i]:.4f}] rad"
                )
        kin = forward_kinematics(np, self.robot, q)
        centre = kin.gripper_centre
        for axis, name in enumerate("xyz"):
            a, b = self.workspace.lower[axis], self.workspace.upper[axis]
            if not a <= centre[axis] <= b:
                raise SafetyViolation(
                    f"{what}: gripper centre {name} = {centre[axis]:.4f} m is outside the workspace box "
                    f"[{a:.3f}, {b:.3f}] m (gripper centre at {np.round(centre, 4).tolist()})"
                )
        prim_pos, prim_rot = primitive_poses(np, self.robot, kin)
        low = lowest_points(self.robot, prim_pos, prim_rot)[self._checked_prims]
        worst = int(np.argmin(low))
        floor = self.table_clearance
        if low[worst] <= floor:
            name = self.robot.primitives[self._checked_prims[worst]].name
            raise SafetyViolation(
                f"{what}: {name} reaches z = {low[worst]:.4f} m, not above the table top + clearance {floor:.4f} m"
            )
        if self.collision_check is not None:
            message = self.collision_check(q)
            if message:
                raise SafetyViolation(f"{what}: {message}")
        return q

    def check(self, q_cmd: Any, q_prev: Any) -> np.ndarray:
        """All rules for a command following ``q_prev`` (previous command, or the measured q at start).

        Returns the command unchanged (as a float array) so the caller sends exactly what passed.
        """
        q_prev = self._as_q(q_prev, "previous target")
        q = self._as_q(q_cmd, "commanded target")
        step = np.abs(q - q_prev)
        for i in range(self.robot.dof):
            if step[i] > self.step_limit[i] + _TOL:
                raise SafetyViolation(
                    f"commanded target: {self.joint_names[i]} moves {step[i]:.4f} rad in one step, over the limit "
                    f"{self.step_limit[i]:.4f} rad = min(velocity {self.robot.velocity_limit[i]:.4f} rad/s × "
                    f"{self.control_dt:g} s, max step {self.max_step:g} rad)"
                )
        return self.check_pose(q, "commanded target")
