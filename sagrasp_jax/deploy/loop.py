"""The closed deployment loop: observe, act with the exported policy, check, command (docs/task.md §5).

Why it is built the way it is: a policy only transfers if it sees what it saw in training and
its actions mean what they meant there.  So every number here comes from the modules the
training env runs, with NumPy:

* observation: ``observation.observe`` in the layout the policy was trained with (its config's
  ``env.task.obs_layout``: the paper's 17 numbers or the relative obstacle encoding), from the
  measured joints, no noise (a test compares them with ``grasp_env.GraspEnv``'s);
* action: ``policy_file.NumpyPolicy`` with the normaliser it was trained with;
* joint target: ``control.control_step`` (slow-down, wrist fine-tuning, target accumulation,
  joint-limit clip) with the policy's own ``env.control`` constants, which must equal the
  deployment's and the URDF's (``safety.check_policy_constants``; the safety limits never come
  from the policy);
* stop: ``reward.success_flag`` with no collision, a collision, ``env.task.max_steps``, or a
  refusal by the ``SafetyLayer``, which checks every command before it is sent.  The layer
  here also refuses a command whose pose would collide with the cell, the detected
  obstacles or the cube (``collision.check``), so the arm stops instead of touching them.

After a success the gripper slides, its orientation kept, over the cube's centre to the middle of
the success band's heights (``reward.grasp_centre``, a few mm, ``robot.translated_pose``) in small
safety-checked steps, holds there for ``SETTLE_STEPS`` periods while latency and servo lag die out,
the gripper closes and the arm lifts the gripper centre by ``lift_height`` (0.05 m), still keeping the
grasp's orientation (``robot.lift_pose``).  Nothing re-orients the wrist between the policy and the
grasp, so nothing swings it into the obstacle the policy avoided; a slide step the safety layer
refuses is not sent, and the gripper closes where the arm stands.  The MJX evaluation's physical
check performs the same slide, collision-checked, before it closes (``evaluate.evaluate_physical``;
docs/design.md, "One grasp").  The cube's centre is taken on the table: a detected height off by up
to ``calibration.TARGET_Z_TOLERANCE`` is replaced by the height of a cube standing there
(``calibration.standing_cube_centre``), a larger one is refused.  Whether the cube is held is
measured, not inferred from the pose: by the backend's cube position (simulators) or its finger
opening (a gripper that reports it); a backend that also reports contacts during the approach (the
twin, ``approach_faults``) fails a grasp whose approach knocked the cube or touched an obstacle.
Nothing here imports jax.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, NamedTuple, Protocol, Sequence, runtime_checkable

import numpy as np

from sagrasp_jax.base import cli
from sagrasp_jax.task import collision
from sagrasp_jax.task import control
from sagrasp_jax.task import observation
from sagrasp_jax.task import reward
from sagrasp_jax.task import shapes
from sagrasp_jax.task.config import EnvConfig
from sagrasp_jax.deploy.calibration import standing_cube_centre, validate_obstacle_clearance, validate_target
from sagrasp_jax.deploy.safety import (
    PolicyMismatch, SafetyLayer, SafetyViolation, check_policy_constants, check_policy_scene, deployment_env,
)
from sagrasp_jax.task.robot import IKError, RobotModel, forward_kinematics, lift_pose, load_robot, translated_pose
from sagrasp_jax.task.policy_file import NumpyPolicy
from sagrasp_jax.task.sampling import ResetSpec

LIFT_HEIGHT = 0.05  # m, docs/task.md §2/§5: lift after closing the gripper
LIFT_MIN_STEPS = 10  # control periods the lift takes at least (0.5 s: ≤ 0.1 m/s)
CENTRE_MIN_STEPS = 4  # control periods the final slide over the cube's centre takes at least (it moves a few mm)
CENTRE_MAX_JOINT_MOVE = 0.1  # rad: a slide of a few mm moves no joint further; more means IK left the branch
SETTLE_STEPS = 6  # control periods the grasp pose is held before closing (3 steps of latency, servo lag)
HOLD_TOLERANCE = 0.01  # m the cube may lag behind the lift and still count as held (physical.HOLD_TOLERANCE)
HELD_MIN_OPENING = 0.004  # m per finger: closed fingers stopped at least this far apart hold something (the cube: 0.01)


class DeployError(RuntimeError):
    """The loop cannot start or continue (bad robot reading, IK failure); nothing more is sent."""


@runtime_checkable
class RobotInterface(Protocol):
    """What the loop needs from a robot: the real AUBO-i5 SDK, the PyBullet twin or MuJoCo.

    ``command_joint_targets`` sends one absolute joint target (rad, one per arm joint) and returns
    after one control period (``env.control.control_dt``); the controller tracks it.  The
    gripper calls block until the fingers have settled.  A backend may also offer
    ``object_position() -> (3,)`` (simulators: the cube's centre) so the report can say
    whether the cube came along when lifting.
    """

    def read_joints(self) -> np.ndarray: ...

    def command_joint_targets(self, q: np.ndarray) -> None: ...

    def open_gripper(self) -> None: ...

    def close_gripper(self) -> None: ...


@dataclass(frozen=True)
class Obstacle:
    """A detected obstacle in the world (robot base) frame, MuJoCo size convention."""

    kind: str  # a shapes.SHAPES name: sphere | cylinder | box | capsule
    centre: tuple[float, float, float]
    size: tuple[float, float, float]  # sphere (r, 0, 0); cylinder (r, half-height, 0); box half-extents; capsule (r, half axis, 0)
    yaw: float = 0.0  # rad about world z (boxes, capsules)


def with_obstacle_kinds(env_cfg: EnvConfig, obstacles: Sequence[Obstacle]) -> EnvConfig:
    """``env_cfg`` whose ``sampling.obstacle_kinds`` also holds the kinds of ``obstacles``: the shared
    collision rules compute the configured kinds only, and a detected shape the policy never trained
    with (a capsule for a paper-mix policy) is still an obstacle to observe and avoid."""
    kinds = env_cfg.sampling.obstacle_kinds
    extra = tuple(dict.fromkeys(ob.kind for ob in obstacles if ob.kind not in kinds))
    if not extra:
        return env_cfg
    return dataclasses.replace(env_cfg, sampling=dataclasses.replace(env_cfg.sampling, obstacle_kinds=kinds + extra))


def scene_spec(q0: Any, target_pos: Any, target_yaw: float, obstacles: Sequence[Obstacle], env_cfg: EnvConfig) -> ResetSpec:
    """The episode as the shared maths sees it (``sampling.ResetSpec``), from detections."""
    slots = env_cfg.sampling.max_obstacles
    if len(obstacles) > slots:
        raise ValueError(f"{len(obstacles)} obstacles given; the policy was trained with at most {slots}")
    active = np.zeros(slots, bool)
    kind = np.full(slots, shapes.BY_NAME[env_cfg.sampling.obstacle_kinds[0]].id, np.int32)  # empty slots
    pos = np.zeros((slots, 3))
    pos[:, 2] = -5.0  # parked like the MJCF's unused slots
    yaw = np.zeros(slots)
    size = np.full((slots, 3), 0.01)
    for i, ob in enumerate(obstacles):
        if ob.kind not in shapes.BY_NAME:
            raise ValueError(f"obstacle {i}: kind {ob.kind!r} is not one of {', '.join(shapes.NAMES)}")
        values = np.array([*ob.centre, *ob.size, ob.yaw], dtype=float)
        if not np.isfinite(values).all():
            raise ValueError(f"obstacle {i} ({ob.kind}) has NaN/inf in its position, size or yaw")
        active[i], kind[i], pos[i], yaw[i], size[i] = True, shapes.BY_NAME[ob.kind].id, ob.centre, ob.yaw, ob.size
    n = len(obstacles)
    error = env_cfg.randomize.target_error  # the detection error training showed the policy (per axis)
    validate_obstacle_clearance(target_pos, kind[:n], pos[:n], yaw[:n], size[:n], env_cfg.sampling,
                                [f"obstacle {i + 1} ({ob.kind})" for i, ob in enumerate(obstacles)],
                                tolerance=math.hypot(error, error))
    return ResetSpec(
        q0=np.asarray(q0, dtype=float),
        target_pos=np.asarray(target_pos, dtype=float),
        target_yaw=np.asarray(float(target_yaw)),
        obstacle_active=active,
        obstacle_kind=kind,
        obstacle_pos=pos,
        obstacle_yaw=yaw,
        obstacle_size=size,
        redraws=np.asarray(0),
        fallback=np.asarray(False),
    )


def obstacles_from_spec(spec: ResetSpec) -> list[Obstacle]:
    """The active obstacles of a sampled ``ResetSpec`` (simulated deployments of training scenes)."""
    return [
        Obstacle(shapes.BY_ID[int(spec.obstacle_kind[i])].name, tuple(float(v) for v in spec.obstacle_pos[i]),
                 tuple(float(v) for v in spec.obstacle_size[i]), float(spec.obstacle_yaw[i]))
        for i in np.nonzero(np.asarray(spec.obstacle_active))[0]
    ]


class Observation(NamedTuple):
    obs: np.ndarray  # in the policy's observation layout (observation.layout_of(env_cfg))
    gripper_centre: np.ndarray
    tilt: float
    collision: collision.CollisionResult


def build_observation(model: RobotModel, env_cfg: EnvConfig, q: Any, spec: ResetSpec, q_command: Any = None) -> Observation:
    """The training observation (``observation.observe``, shared with both envs) at measured joints ``q``, no
    noise; ``q_command`` is the joint target last sent (the ``relative_lag`` layout's pending command)."""
    seen = observation.observe(np, model, env_cfg, np.asarray(q, dtype=float), spec, q_command=q_command)
    return Observation(seen.obs, seen.kin.gripper_centre, float(seen.tilt), seen.col)


def collision_hook(model: RobotModel, env_cfg: EnvConfig, spec: ResetSpec,
                   ignore: Sequence[str] = ()) -> Callable[[np.ndarray], str | None]:
    """``SafetyLayer`` hook: a message naming what the pose ``q`` would hit, or None."""

    def check(q: np.ndarray) -> str | None:
        col = collision.check(np, model, forward_kinematics(np, model, q), spec, env_cfg)
        hits = [name for name in collision.HIT_KINDS if name not in ignore and bool(col.hits[name])]
        return f"pose would collide with: {', '.join(hits)}" if hits else None

    return check


@dataclass
class DeployReport:
    """What one deployment episode did; ``to_dict`` is the ``--json`` output."""

    outcome: str  # success | timeout | collision | refused
    success: bool
    steps: int
    message: str
    target: list[float]
    target_yaw: float
    obstacles: int
    min_obstacle_clearance: float | None  # m, smallest Δpo seen (None without obstacles)
    final_distance: float  # m, gripper centre to cube centre
    final_horizontal_offset: float
    final_height_above_target: float
    final_tilt_deg: float
    final_q: list[float]
    slowed_steps: int
    finetuned_steps: int
    wall_s: float
    # per control step, ms: the loop's own work (read, observe, policy, control step) and the whole period
    # including the safety check and the robot's command call (which returns after one control period on a real controller)
    step_compute_ms_mean: float = 0.0
    step_compute_ms_max: float = 0.0
    step_period_ms_mean: float = 0.0
    step_period_ms_max: float = 0.0
    grasp: dict[str, Any] | None = None  # closed / lifted / rises / faults, when a grasp was attempted
    hits: list[str] = field(default_factory=list)
    # the deployment's verdict: the cube held after the lift (None: not attempted, or the backend cannot tell)
    held: bool | None = None
    detected_target: list[float] = field(default_factory=list)  # the cube centre as given, before it was put on the table

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def send_checked(robot: RobotInterface, safety: SafetyLayer, q_cmd: Any, q_prev: Any) -> np.ndarray:
    """The one path by which the loop moves the arm: the safety layer first, then the robot.

    Raises ``SafetyViolation`` (and sends nothing) for a refused command, and ``cli.Interrupted`` (sending
    nothing) when Ctrl-C was pressed under ``cli.at_safe_points``: every command is a safe point to stop at.
    """
    cli.check()
    q = safety.check(q_cmd, q_prev)
    robot.command_joint_targets(q.copy())
    return q


def _read(robot: RobotInterface, model: RobotModel) -> np.ndarray:
    q = np.asarray(robot.read_joints(), dtype=float)
    if q.shape != (model.dof,) or not np.isfinite(q).all():
        raise DeployError(f"robot reported joints {q!r}; expected {model.dof} finite values ({model.name})")
    return q


def run_episode(
    robot: RobotInterface,
    policy: NumpyPolicy,
    target_pos: Any,
    target_yaw: float = 0.0,
    obstacles: Sequence[Obstacle] = (),
    *,
    safety: SafetyLayer | None = None,
    max_steps: int | None = None,
    grasp: bool = True,
    lift_height: float = LIFT_HEIGHT,
) -> DeployReport:
    """Run the policy from the robot's current pose until success, collision, timeout or refusal.

    ``target_pos`` is the cube centre in the world (URDF base) frame; it is validated against
    the trained region before anything moves (``TargetRejected``), and so are the obstacles
    (``ObstacleRejected``: inside the training clearance of the target) and the policy's control
    constants (``PolicyMismatch``: they must be the deployment's and the robot's).  ``safety``
    defaults to a ``SafetyLayer`` with the default ``DeploySettings`` and a collision hook for
    this scene; its limits never come from the policy.
    """
    t0 = time.perf_counter()
    policy.check_grasp_inputs()  # a policy of another env would fail at its first observation
    env_cfg = with_obstacle_kinds(policy.env_config(), obstacles)
    model = load_robot(env_cfg.robot)  # the policy's arm (its file's env.robot), never a module default
    settings = safety.settings if safety is not None else None
    if safety is not None and safety.robot.name != model.name:
        raise PolicyMismatch(f"{policy.path} was trained for the robot {model.name!r}; "
                             f"the safety layer guards {safety.robot.name!r}")
    check_policy_constants(env_cfg, settings, model, policy.path)
    check_policy_scene(env_cfg, settings, policy.path)
    env_cfg = deployment_env(env_cfg, settings)  # the cell's facts are the deployment's, never the file's
    detected = validate_target(target_pos, env_cfg.sampling)
    target = standing_cube_centre(detected, env_cfg.sampling)
    q0 = _read(robot, model)
    spec = scene_spec(q0, target, target_yaw, obstacles, env_cfg)
    if safety is None:
        safety = SafetyLayer(robot=model, collision_check=collision_hook(model, env_cfg, spec))
    steps_limit = env_cfg.task.max_steps if max_steps is None else int(max_steps)
    safety.check_pose(q0, "start pose")  # refuses a start that already breaks a rule

    q_target = q0.copy()
    steps = slowed = finetuned = 0
    clearance = math.inf
    outcome, message = "timeout", ""
    compute_ms: list[float] = []
    period_ms: list[float] = []
    while True:
        t_step = time.perf_counter()
        q = _read(robot, model)
        ob = build_observation(model, env_cfg, q, spec, q_target)
        clearance = min(clearance, float(ob.collision.nearest_obstacle_dist))
        if bool(ob.collision.any_collision):
            outcome = "collision"
            break
        if bool(reward.success_flag(np, env_cfg.task, ob.gripper_centre, target, ob.tilt)):
            outcome, message = "success", f"grasp pose reached after {steps} steps"
            break
        if steps >= steps_limit:
            outcome, message = "timeout", f"no grasp pose within {steps_limit} steps; stopped"
            break
        action = policy(ob.obs)
        ctl = control.control_step(np, model, env_cfg.control, q_target, q, target, action)
        compute_ms.append(1e3 * (time.perf_counter() - t_step))
        try:
            q_target = send_checked(robot, safety, ctl.q_target, q_target)
            period_ms.append(1e3 * (time.perf_counter() - t_step))
        except SafetyViolation as exc:
            outcome, message = "refused", f"safety layer refused step {steps + 1}: {exc}; robot stopped"
            break
        steps += 1
        slowed += bool(ctl.slowed)
        finetuned += bool(ctl.finetuned)

    hits = [n for n in collision.HIT_KINDS if bool(ob.collision.hits[n])]
    if outcome == "collision":
        message = f"measured pose collides with: {', '.join(hits)}; stopped"
    offset = ob.gripper_centre - target
    report = DeployReport(
        outcome=outcome,
        success=outcome == "success",
        steps=steps,
        message=message,
        target=[float(v) for v in target],
        detected_target=[float(v) for v in detected],
        target_yaw=float(target_yaw),
        obstacles=len(obstacles),
        min_obstacle_clearance=float(clearance) if obstacles else None,
        final_distance=float(np.linalg.norm(offset)),
        final_horizontal_offset=float(np.linalg.norm(offset[:2])),
        final_height_above_target=float(offset[2]),
        final_tilt_deg=math.degrees(ob.tilt),
        final_q=[float(v) for v in q],
        slowed_steps=slowed,
        finetuned_steps=finetuned,
        wall_s=0.0,
        step_compute_ms_mean=float(np.mean(compute_ms)) if compute_ms else 0.0,
        step_compute_ms_max=float(np.max(compute_ms)) if compute_ms else 0.0,
        step_period_ms_mean=float(np.mean(period_ms)) if period_ms else 0.0,
        step_period_ms_max=float(np.max(period_ms)) if period_ms else 0.0,
        hits=hits,
    )
    if report.success and grasp:
        report.grasp = _grasp_and_lift(robot, model, env_cfg, spec, q, q_target, lift_height, safety)
        report.held = report.grasp.get("held")
    report.wall_s = time.perf_counter() - t0
    return report


class IdealArm:
    """A robot that stands exactly where it was last told (no latency, no servo lag, no readings' error) and
    records every command: what the loop would send an arm, computed without one (the dry run's plan)."""

    def __init__(self, q0: Any) -> None:
        self.q = np.array(q0, dtype=float)
        self.commands: list[np.ndarray] = []

    def read_joints(self) -> np.ndarray:
        return self.q.copy()

    def command_joint_targets(self, q: np.ndarray) -> None:
        self.q = np.array(q, dtype=float)
        self.commands.append(self.q.copy())

    def open_gripper(self) -> None:
        pass

    def close_gripper(self) -> None:
        pass


def plan_episode(policy: NumpyPolicy, q0: Any, target_pos: Any, target_yaw: float, obstacles: Sequence[Obstacle],
                 max_steps: int | None = None) -> tuple[DeployReport, list[np.ndarray]]:
    """The policy's episode on an ``IdealArm`` from ``q0`` to the grasp pose (no grasp): the report and the joint
    targets the loop would command, each through the same safety layer as on the robot."""
    arm = IdealArm(q0)
    report = run_episode(arm, policy, target_pos, target_yaw, obstacles, max_steps=max_steps, grasp=False)
    return report, arm.commands


def _ramp(robot: RobotInterface, safety: SafetyLayer, q_goal: np.ndarray, q_target: np.ndarray, min_steps: int) -> np.ndarray:
    """Move the commanded target to ``q_goal`` in safety-checked steps of at most half the step limit."""
    n = max(min_steps, math.ceil(float(np.max(np.abs(q_goal - q_target) / safety.step_limit)) * 2))
    for k in range(1, n + 1):
        q_target = send_checked(robot, safety, q_target + (q_goal - q_target) / (n - k + 1), q_target)
    return q_target


def centring_pose(model: RobotModel, env_cfg: EnvConfig, q: Any, target: Any) -> np.ndarray:
    """The joints of the final slide: the gripper centre at ``reward.grasp_centre`` of the cube centre ``target``
    (over it, mid band), the gripper's orientation that of ``q`` (``robot.translated_pose``).  Shared by the
    deploy loop and the MJX evaluation's physical check; IKError if no such pose lies near ``q``."""
    goal = reward.grasp_centre(np, env_cfg.task, np.asarray(target, dtype=float))
    start = forward_kinematics(np, model, np.asarray(q, dtype=float)).gripper_centre
    return translated_pose(model, q, goal - start, max_joint_move=CENTRE_MAX_JOINT_MOVE, what="centring pose")


def _centre(robot: RobotInterface, model: RobotModel, env_cfg: EnvConfig, spec: ResetSpec, q: np.ndarray,
            q_target: np.ndarray, safety: SafetyLayer) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Before closing: slide the gripper, its orientation kept, over the cube's centre to the middle of the
    band's heights (``reward.grasp_centre``; ``robot.translated_pose``: a few mm, no wrist swing), in
    safety-checked steps, then hold the command for ``SETTLE_STEPS`` periods (latency, servo lag).  A step
    the safety layer refuses is not sent: the slide stops there and the gripper closes where the arm stands
    (the success pose or a step nearer the centre).  Returns the measured joints, the commanded target and
    what happened."""
    goal = reward.grasp_centre(np, env_cfg.task, np.asarray(spec.target_pos, dtype=float))
    start = forward_kinematics(np, model, q).gripper_centre
    info: dict[str, Any] = {"centring_move_mm": float(1000 * np.linalg.norm(goal - start)), "centring": "done"}
    try:
        q_target = _ramp(robot, safety, centring_pose(model, env_cfg, q, spec.target_pos), q_target, CENTRE_MIN_STEPS)
    except IKError as exc:
        info["centring"] = f"skipped ({exc}); closing at the grasp pose"
    except SafetyViolation as exc:
        info["centring"] = f"stopped ({exc}); closing where the arm stands"
    for _ in range(SETTLE_STEPS):  # the last command was accepted: holding it is safe
        q_target = send_checked(robot, safety, q_target, q_target)
    return _read(robot, model), q_target, info


def _held(robot: RobotInterface, cube0: np.ndarray | None, height: float) -> tuple[bool | None, dict[str, Any]]:
    """Whether the cube came along, from what the backend can report: the cube's own rise (simulators), else
    the finger opening (closed fingers kept apart by the cube); None when it reports neither."""
    if cube0 is not None:  # the cube's own rise against the lift commanded (the arm's reading may be offset)
        rise = float(np.asarray(robot.object_position(), float)[2] - cube0[2])  # type: ignore[attr-defined]
        return bool(rise >= height - HOLD_TOLERANCE), {"object_rise": rise}
    opening = getattr(robot, "finger_opening", None)
    if opening is not None:
        fingers = np.asarray(opening(), float)
        return bool(np.all(fingers >= HELD_MIN_OPENING)), {"finger_opening": [float(v) for v in fingers]}
    return None, {}


def _grasp_and_lift(robot: RobotInterface, model: RobotModel, env_cfg: EnvConfig, spec: ResetSpec,
                    q: np.ndarray, q_target: np.ndarray, height: float, safety: SafetyLayer) -> dict[str, Any]:
    """Slide over the cube's centre (``_centre``), close the gripper, lift ``height`` m keeping the gripper's
    orientation, in safety-checked steps, and judge whether the cube is held (``_held``; a faulty approach
    fails it)."""
    locate = getattr(robot, "object_position", None)
    cube0 = np.asarray(locate(), float) if locate is not None else None
    result: dict[str, Any] = {"closed": False, "lift_commanded": float(height), "lifted": False, "held": False,
                              "message": ""}
    try:
        q, q_target, centring = _centre(robot, model, env_cfg, spec, q, q_target, safety)
        result.update(centring)
    except SafetyViolation as exc:
        result["message"] = f"holding the grasp pose stopped: {exc}; gripper not closed"
        return result
    kin = forward_kinematics(np, model, q)
    offset = kin.gripper_centre - np.asarray(spec.target_pos, dtype=float)
    result.update(closing_offset_mm=[float(1000 * v) for v in offset],
                  closing_tilt_deg=math.degrees(float(np.arccos(np.clip(-kin.approach_axis[2], -1.0, 1.0)))))
    robot.close_gripper()
    result["closed"] = True
    # The cube now rides between the pads: contact with it is the point, not a collision.
    lift_safety = SafetyLayer(safety.settings, model, workspace=safety.workspace, table_clearance=safety.table_clearance,
                              collision_check=collision_hook(model, env_cfg, spec, ignore=("target",)))
    try:
        _ramp(robot, lift_safety, lift_pose(model, q, height), q_target, LIFT_MIN_STEPS)
        result["lifted"] = True
    except (SafetyViolation, DeployError, IKError) as exc:
        result["message"] = f"lift stopped: {exc}"
    q_end = _read(robot, model)
    result["gripper_rise"] = float(forward_kinematics(np, model, q_end).gripper_centre[2] - kin.gripper_centre[2])
    held, evidence = _held(robot, cube0, height)
    result.update(evidence)
    faults = getattr(robot, "approach_faults", None)
    result["approach_faults"] = list(faults()) if faults is not None else None
    if held is not None:
        held = held and result["lifted"] and not result["approach_faults"]
    result["held"] = held
    if "object_rise" in result:  # the simulators' name for it, kept for older readers
        result["object_held"] = bool(held)
    return result


def format_report(report: DeployReport) -> str:
    """Plain-text report for the terminal."""
    lines = [
        f"outcome            {report.outcome}" + (f" ({report.message})" if report.message else ""),
        f"steps              {report.steps}",
        f"target (world, m)  ({report.target[0]:.4f}, {report.target[1]:.4f}, {report.target[2]:.4f}), "
        f"yaw {math.degrees(report.target_yaw):.1f}°",
        f"final offset       {report.final_distance * 1000:.1f} mm "
        f"(horizontal {report.final_horizontal_offset * 1000:.1f} mm, height {report.final_height_above_target * 1000:.1f} mm), "
        f"tilt {report.final_tilt_deg:.2f}°",
        f"obstacles          {report.obstacles}"
        + (f", min clearance {report.min_obstacle_clearance * 1000:.1f} mm" if report.min_obstacle_clearance is not None else ""),
        f"slow-down steps    {report.slowed_steps}, fine-tune steps {report.finetuned_steps}",
    ]
    if report.grasp is not None:
        g = report.grasp
        if not g["closed"]:
            text = f"grasp              gripper not closed: {g['message']}"
        else:
            text = f"grasp              closed, lift {'done' if g['lifted'] else 'NOT done'}: gripper rose {g['gripper_rise'] * 1000:.1f} mm"
            if "object_rise" in g:
                text += f", cube rose {g['object_rise'] * 1000:.1f} mm"
            if g["message"]:
                text += f"; {g['message']}"
        lines.append(text)
        verdict = {True: "HELD", False: "NOT held", None: "unknown (the backend reports neither the cube nor the fingers)"}
        text = f"cube               {verdict[g['held']]}"
        if g.get("approach_faults"):
            text += f" (approach: {'; '.join(g['approach_faults'])})"
        lines.append(text)
    lines.append(f"wall time          {report.wall_s:.2f} s")
    return "\n".join(lines)
