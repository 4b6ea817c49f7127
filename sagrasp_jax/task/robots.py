"""The arms the task runs on: one registry entry per robot, chosen by the config key ``env.robot``.

A robot is its URDF (``sagrasp_jax/urdf/``: kinematics, limits, collision primitives, the gripper) plus what
a URDF cannot say and the task needs: which joints are the arm and which the fingers, the frames of the
flange and of the grasp point, the start pose, the two wrist joints the vertical fine-tuning corrects, the
self-collision groups, the servo model of the MJCF and of the ``lagged`` mode, and the generated MJCF files
(``python tools/urdf_to_mjcf.py --robot NAME``).  Everything else (the joint count, the observation and
action sizes, the sphere covers, the MJX env, the PyBullet reference and twin, the safety layer, the deploy
loop) is read from here and from ``robot.load_robot(name)``: a new arm is a URDF and one ``register`` call
(``tests/task/test_robots.py`` keeps every entry consistent with its URDF and MJCF).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

DEFAULT = "aubo_i5"


@dataclass(frozen=True)
class ServoModel:
    """Position servos of the generated MJCF (the ``dynamic`` mode) and the ``lagged`` mode's fit of them."""

    kp: tuple[float, ...]  # N·m/rad per arm joint (gravity is compensated: the servo fights inertia only)
    kv: tuple[float, ...]  # N·m·s/rad velocity feedback per arm joint
    armature: tuple[float, ...]  # kg·m² reflected rotor inertia per arm joint
    damping: float = 1.0  # N·m·s/rad joint damping
    # "lagged" mode, per joint: q ← q + lag_gain·(c − q) + lag_momentum·(q − q_prev), fitted by least squares to
    # the dynamic mode's servos (python -m experiments.robot_grade servo-fit --robot NAME)
    lag_gain: tuple[float, ...] = ()
    lag_momentum: tuple[float, ...] = ()


@dataclass(frozen=True)
class RobotSpec:
    """One arm and its gripper, as the task uses them (the URDF holds the rest)."""

    name: str  # the value of env.robot
    summary: str  # one line for --list-keys and the docs
    urdf: str  # file name in sagrasp_jax/urdf/
    mjcf_robot: str  # file name in sagrasp_jax/mjcf/: the arm alone (the dynamic mode's model)
    mjcf_scene: str  # file name in sagrasp_jax/mjcf/: the arm in the cell (kinematic env, physical check, renderer)
    arm_joints: tuple[str, ...]  # revolute, about local z, base to wrist: the action has one entry per joint
    finger_joints: tuple[str, str]  # prismatic, left then right; their upper limit is the open finger
    flange_joint: str  # fixed joint whose child is the flange (approach axis = its local +z)
    gripper_centre_joint: str  # fixed joint whose child is the grasp point, midway between the open finger pads
    contact_links: tuple[str, str]  # the finger links that touch the cube in the physical grasp check
    home_seed: tuple[float, ...]  # rad: IK seed that picks the start pose's branch
    home_q: tuple[float, ...]  # rad: solve_home_pose(home_seed), pasted (tests re-solve and compare)
    fine_tune_joints: tuple[int, int]  # zero-based, consecutive: the wrist joints that right a tilted gripper
    # Link indices (0 = the base, i = the link arm joint i turns): self-collision is the moving group (this link to
    # the wrist's, the flange and gripper riding on it) against the static group (the base to this link).
    self_moving_from_link: int
    self_static_to_link: int
    reach_link: int  # link index: primitives of this link on can touch the table, posts and target
    servo: ServoModel

    @property
    def dof(self) -> int:
        """The arm's joint count (the action size)."""
        return len(self.arm_joints)


AUBO_I5 = RobotSpec(
    name="aubo_i5",
    summary="AUBO-i5 with the EG2 two-finger gripper: the paper's arm (6 joints)",
    urdf="aubo_i5_eg2.urdf",
    mjcf_robot="aubo_i5_eg2.xml",
    mjcf_scene="scene.xml",
    arm_joints=("shoulder_joint", "upperArm_joint", "foreArm_joint", "wrist1_joint", "wrist2_joint", "wrist3_joint"),
    finger_joints=("left_finger_joint", "right_finger_joint"),
    flange_joint="flange_joint",
    gripper_centre_joint="gripper_center_joint",
    contact_links=("left_finger", "right_finger"),
    # docs/task.md §2's vector, solved once by robot.solve_home_pose (gripper centre (0, −0.30, 0.35), pointing down)
    home_seed=(1.1538, -0.4919, -1.8145, 0.2482, -1.5708, 0.0),
    home_q=(1.1538174961752017, -0.49293447743928726, -1.8197668542055943, 0.2439639500285898,
            -1.5707963267948966, 0.0),
    fine_tune_joints=(3, 4),  # docs/task.md §2 step 3: "joints 4 and 5"
    self_moving_from_link=4,  # wrist1, wrist2, wrist3 (flange and gripper ride on wrist3)
    self_static_to_link=2,  # base, shoulder, upper arm
    reach_link=2,  # from the upper arm on
    servo=ServoModel(
        kp=(3000.0, 3000.0, 3000.0, 300.0, 300.0, 300.0),
        kv=(150.0, 150.0, 150.0, 10.0, 10.0, 10.0),
        armature=(0.2, 0.2, 0.2, 0.1, 0.1, 0.1),  # wrist armature 0.02 let a full 0.05 rad step limit-cycle
        lag_gain=(0.639, 0.601, 0.632, 0.806, 0.785, 0.798),  # experiments/results/fit_servo_lag.json
        lag_momentum=(0.070, 0.143, 0.080, 0.037, 0.077, 0.059),
    ),
)

PANDA = RobotSpec(
    name="panda",
    summary="Franka Emika Panda with the Franka hand (7 joints)",
    urdf="panda.urdf",
    mjcf_robot="panda.xml",
    mjcf_scene="scene_panda.xml",
    arm_joints=tuple(f"panda_joint{i}" for i in range(1, 8)),
    finger_joints=("panda_finger_joint1", "panda_finger_joint2"),
    flange_joint="panda_joint8",  # panda_link8, 0.107 m past link7: Franka's flange
    gripper_centre_joint="panda_grasptarget_hand",
    contact_links=("panda_leftfinger", "panda_rightfinger"),
    # elbow up, the arm in the y-z plane (joints 3 and 5 at 0), every joint >= 0.4 rad inside its limits
    home_seed=(-1.5708, -0.8318, 0.0, -2.7327, 0.0, 1.9009, 0.7854),
    home_q=(-1.5707979980527682, -0.831828851125138, 1.441343513827482e-06, -2.7327045416640114,
            1.1261920348188903e-06, 1.9008756905391966, 0.7854),
    fine_tune_joints=(4, 5),  # joints 5 and 6: their axes span the gripper's tilt about home
    self_moving_from_link=5,  # link5 (the forearm), link6, link7 (the hand and fingers ride on link7)
    self_static_to_link=2,  # base, link1, link2 (the shoulder)
    reach_link=2,  # from link2 on
    servo=ServoModel(
        kp=(3000.0, 3000.0, 3000.0, 3000.0, 400.0, 400.0, 400.0),
        kv=(150.0, 150.0, 150.0, 150.0, 20.0, 20.0, 20.0),
        armature=(0.2, 0.2, 0.2, 0.2, 0.1, 0.1, 0.1),
        lag_gain=(0.6,) * 7,
        lag_momentum=(0.1,) * 7,
    ),
)

_REGISTRY: dict[str, RobotSpec] = {AUBO_I5.name: AUBO_I5, PANDA.name: PANDA}
_LISTENERS: list[Callable[[], None]] = []


class UnknownRobot(KeyError):
    """``env.robot`` names no registered robot."""

    def __str__(self) -> str:
        return f"unknown robot {self.args[0]!r}; registered: {', '.join(_REGISTRY)}"


def register(spec: RobotSpec) -> RobotSpec:
    """Add (or replace) a robot; the config's ``env.robot`` choices and every cache keyed on robots follow."""
    if len(spec.home_q) != spec.dof or len(spec.home_seed) != spec.dof:
        raise ValueError(f"robot {spec.name!r}: home_q and home_seed need {spec.dof} values (one per arm joint)")
    for what in ("kp", "kv", "armature", "lag_gain", "lag_momentum"):
        if len(getattr(spec.servo, what)) != spec.dof:
            raise ValueError(f"robot {spec.name!r}: servo.{what} needs {spec.dof} values (one per arm joint)")
    if not 0 < spec.self_static_to_link < spec.self_moving_from_link <= spec.dof or not 0 < spec.reach_link <= spec.dof:
        raise ValueError(f"robot {spec.name!r}: self-collision groups and reach_link must be link indices in 1..{spec.dof}, "
                         "the static group below the moving one")
    lo, hi = spec.fine_tune_joints
    if not (0 <= lo and hi == lo + 1 and hi < spec.dof):
        raise ValueError(f"robot {spec.name!r}: fine_tune_joints {spec.fine_tune_joints} must be two consecutive joints")
    _REGISTRY[spec.name] = spec
    for listener in _LISTENERS:
        listener()
    return spec


def on_change(listener: Callable[[], None]) -> None:
    """Call ``listener`` after every ``register`` (caches of robot models, the config's choices)."""
    _LISTENERS.append(listener)


DEFAULT_DOF = AUBO_I5.dof  # the default robot's joint count: the action size where a library call names no robot


def names() -> tuple[str, ...]:
    """The registered robots, the default first."""
    return tuple(_REGISTRY)


def get(name: str) -> RobotSpec:
    """The registered robot ``name``; ``UnknownRobot`` names the choices."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise UnknownRobot(name) from None
