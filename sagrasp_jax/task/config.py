"""Every tunable constant of the project, in one place, with named presets: the config's declarations.

The config is a tree of frozen dataclasses.  Each key is declared once, by ``key(default, doc,
valid)``: its type (the annotation; a ``Literal`` lists its choices), its meaning (``doc``, which
``--list-keys`` prints) and, for a number, its valid ``Range``.  ``get_config(preset)`` returns a
preset, ``key_specs`` reads the declarations back, ``validate`` checks a config against them and the
rules across keys, and ``config_to_dict`` gives the dict run folders and checkpoints store.  Values
come from ``docs/task.md`` §2-§3; where a number is ours, not the paper's, the key says so.

Two modules sit on this one: ``config_history`` (the layouts configs were written in before, how an
old config upgrades, and the hashes that identify a config across layouts) and ``config_parse``
(``--set``, ``--config`` files, saved configs read back, ``--list-keys``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import typing
from dataclasses import dataclass, field
from typing import Any, Literal

from sagrasp_jax.task import robots
from sagrasp_jax.task import shapes

Q_LIMIT = 3.0543  # ±175° on every AUBO-i5 joint (docs/task.md §1); the URDF holds the same value.

# The default robot's home pose: damped-least-squares IK seeded from docs/task.md §2's vector, solved once by
# ``sagrasp_jax.task.robot.solve_home_pose`` and pasted into its registry entry (tests re-solve and compare).
HOME_SEED = robots.AUBO_I5.home_seed
HOME_Q = robots.AUBO_I5.home_q
HOME_GRIPPER_CENTRE = (0.0, -0.30, 0.35)
Joints = tuple[float, ...]  # one value per arm joint of env.robot (validate checks the count)

# The choices of every string key, declared once; the modules that act on them import these.
ControlMode = Literal["kinematic", "dynamic", "lagged"]  # env.control.mode (env.py)
PhysicsImpl = Literal["jax", "warp"]  # env.control.impl
RcMode = Literal["entry", "per_step"]  # env.reward.rc_mode (reward.py)
NearMissMode = Literal["change", "per_step"]  # env.reward.near_miss_mode (reward.py)
ObsLayout = Literal["paper", "relative", "relative_lag"]  # env.task.obs_layout (observation.py)
FusionEmitters = Literal["legacy", "new"]  # train.cpu_fusion_emitters (training/trainer.py, base/xla_flags.py)
ObstacleGeometry = Literal["fine", "cover"]  # env.task.obstacle_geometry (collision.py)
ShapeName = Literal[shapes.NAMES]  # type: ignore[valid-type]  # env.sampling.obstacle_kinds (shapes.py; live: _kinds_changed)
RobotName = Literal[robots.names()]  # type: ignore[valid-type]  # env.robot (robots.py; live: _robots_changed)
Activation = Literal["tanh", "relu", "silu", "elu"]  # ppo.network.activation (ppo.py: flax.linen's functions)
LRSchedule = Literal["constant", "sa", "kl-adaptive", "cosine", "linear"]  # lr.schedule (lr_schedule.py)
SAMetric = Literal["return", "success"]  # sa.metric

CONTROL_MODES: tuple[str, ...] = typing.get_args(ControlMode)
RC_MODES: tuple[str, ...] = typing.get_args(RcMode)
NEAR_MISS_MODES: tuple[str, ...] = typing.get_args(NearMissMode)
OBS_LAYOUTS: tuple[str, ...] = typing.get_args(ObsLayout)
ACTIVATIONS: tuple[str, ...] = typing.get_args(Activation)
LR_SCHEDULES: tuple[str, ...] = typing.get_args(LRSchedule)


class ConfigError(ValueError):
    """A preset, key or value that the config does not accept."""


@dataclass(frozen=True)
class Range:
    """The sane values of a numeric key (a tuple key: of each entry), inclusive unless ``open_low``.
    Wide on purpose: it catches NaN, inf, a sign slip or a units slip (1e30, 50 for 0.05) at the
    command line, not tuning choices."""

    lo: float
    hi: float
    open_low: bool = False

    def __contains__(self, v: Any) -> bool:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            return False
        return (v > self.lo if self.open_low else v >= self.lo) and v <= self.hi

    def __str__(self) -> str:
        return f"{'(' if self.open_low else '['}{format_number(self.lo)}, {format_number(self.hi)}]"


def within(lo: float, hi: float) -> Range:
    """[lo, hi]."""
    return Range(lo, hi)


def above(lo: float, hi: float) -> Range:
    """(lo, hi]: e.g. a length that must be positive."""
    return Range(lo, hi, open_low=True)


def key(default: Any, doc: str, valid: Range | None = None) -> Any:
    """A config key's declaration: its default, what it means, and its valid range (choices are the
    annotation's ``Literal``)."""
    return field(default=default, metadata={"doc": doc, "range": valid})


SEED_RANGE = (0, 2**32 - 1)  # jax.random.PRNGKey wraps larger seeds silently (2**32 gives seed 0's key)
SEEDS = within(*SEED_RANGE)
_BIG = 10**12  # an upper bound for counts that only has to stop overflow and runaway runs
_REWARD = within(-1e3, 1e3)


@dataclass(frozen=True)
class ControlConfig:
    """One control step (docs/task.md §2 steps 1-5)."""

    q_max: float = key(0.05, "rad: joint change per step at |action| = 1 (docs/task.md §2 step 1)", above(0, 0.5))
    slowdown_enabled: bool = key(True, "proximity slow-down on (step 2)")
    d_slow: float = key(0.08, "m: slow down when the gripper centre is this close to the target centre", within(0, 1))
    slow_factor: float = key(0.3, "Δq is multiplied by this inside d_slow", above(0, 1))
    finetune_enabled: bool = key(True, "vertical-alignment fine-tuning of joints 4, 5 on (step 3)")
    d_fine: float = key(0.10, "m: fine-tune within this distance of the target centre", within(0, 1))
    fine_tilt_deg: float = key(10.0, "deg: fine-tune only when the gripper tilt θgz exceeds this", within(0, 90))
    fine_gain: float = key(1.0, "k: gain of the damped least-squares wrist correction", within(0, 100))
    fine_damping: float = key(0.05, "λ: damping of that least-squares step", above(0, 10))
    fine_clip: float = key(0.015, "rad: the correction is clipped to ±this (c = 0.3·q_max)", within(0, 0.5))
    q_limit: float = key(
        Q_LIMIT, "rad: joint targets are clipped to ±this and to the URDF's limits of env.robot (the AUBO-i5's: ±175°)",
        above(0, math.pi))
    mode: ControlMode = key(
        "kinematic", '"kinematic": qpos = q_target, no physics; "dynamic": MuJoCo servos track q_target; "lagged": '
        "no physics, the joints follow q_target through the per-step servo model below (lag_gain, lag_momentum), "
        'fitted to the dynamic mode\'s servos: as cheap as "kinematic", with the servo lag and the command latency '
        'of "dynamic"')
    control_dt: float = key(0.05, "s: control period (20 Hz)", above(0, 1))
    physics_dt: float = key(0.01, "s: physics step of the dynamic mode", above(0, 0.1))
    substeps: int = key(5, "physics steps per control step in the dynamic mode", within(1, 1000))
    impl: PhysicsImpl = key(
        "jax", 'Physics backend of the dynamic mode: "jax" (MJX\'s JAX implementation, any device) or "warp" '
        '(MuJoCo Warp through MJX: needs the warp extra, pip install "sagrasp_jax[warp]", and is meant for CUDA GPUs)')
    lag_gain: Joints = key(
        robots.AUBO_I5.servo.lag_gain,
        '"lagged" mode, per joint: each control step the joint closes this fraction of its distance to the command '
        "(q ← q + lag_gain·(c − q) + lag_momentum·(q − q_prev)); fitted by least squares to the dynamic mode's "
        "servos (python -m experiments.robot_grade servo-fit, experiments/results/fit_servo_lag.json)", above(0, 1))
    lag_momentum: Joints = key(
        robots.AUBO_I5.servo.lag_momentum, '"lagged" mode: carry-over of the last step\'s motion',
        within(0, 0.9))


@dataclass(frozen=True)
class RewardConfig:
    """R = F_d·R_distance + F_s·R_success + F_o·R_obstacle (docs/task.md §2)."""

    ratio: float = key(10.0, "R_distance per metre of approach to the target", within(0, 1e3))
    rc: float = key(0.05, "grab-zone bonus RC", _REWARD)
    d_grab: float = key(0.05, "m: radius of the grab zone around the target centre", within(0, 1))
    rc_mode: RcMode = key(
        "entry", '"entry": RC paid on entering the grab zone and taken back on leaving (potential-based); '
        '"per_step": the paper\'s RC on every step inside it (kept for the ablation: PPO learns to hover, '
        "docs/task.md §2)")
    success_reward: float = key(1.0, "R_success on success", _REWARD)
    failure_reward: float = key(-1.0, "R_success on a collision or a timeout", _REWARD)
    collision_penalty: float = key(-1.0, "R_obstacle on any collision", _REWARD)
    near_miss_distance: float = key(0.05, "m: Δpo under this is a near miss", within(0, 1))
    near_miss_scale: float = key(0.5, "weight of the near-miss term (see near_miss_mode)", _REWARD)
    near_miss_mode: NearMissMode = key(
        "change", '"change" (default): on every step without a collision pay −scale·(c_t − c_{t−1}), c = clip(1 − '
        "Δpo/near_miss_distance, 0, 1), c_0 from the start state — a potential, so lingering near an obstacle costs "
        'nothing extra and moving away repays it.  "per_step": the paper\'s literal −scale·c_t on every step, which '
        "accumulates without bound against a bounded collision penalty and teaches crashing early (docs/task.md §2; "
        "kept for the ablation).")
    clean_success_bonus: float = key(
        1.0, "R_obstacle at a success in an obstacle episode whose Δpo stayed ≥ near_miss_distance", _REWARD)
    f_d0: float = key(2.0, "F_d = f_d0 + f_d1·p (p = training progress in [0, 1])", _REWARD)
    f_d1: float = key(-1.0, "slope of F_d in p", _REWARD)
    f_s0: float = key(0.5, "F_s = f_s0 + f_s1·p", _REWARD)
    f_s1: float = key(1.0, "slope of F_s in p", _REWARD)
    f_o: float = key(0.5, "F_o, the weight of R_obstacle", _REWARD)
    tilt_weight: float = key(
        0.0, "m/rad: R_distance's approach shaping measures progress on the distance to the target plus this much per "
        "radian of gripper tilt beyond tilt_free_deg (reward.approach_potential).  0 = the paper's distance alone, "
        "which pays nothing for righting a tilted gripper that hovers over the cube: the hovering trap "
        "(docs/design.md)", within(0, 10))
    tilt_free_deg: float = key(
        5.0, "deg: tilt up to this costs nothing in the approach potential (success needs ≤ 10°)", within(0, 90))
    tilt_near: float = key(
        0.0, "m: > 0: the tilt part fades in linearly as the gripper centre closes in from this distance to the "
        "target, so the approach far from the cube is free to tilt (around obstacles); 0: it counts everywhere",
        within(0, 10))


@dataclass(frozen=True)
class TaskConfig:
    """Start state, observation, success and episode length (docs/task.md §2)."""

    home_q: Joints = key(
        HOME_Q, "rad: start pose, gripper centre at (0, −0.30, 0.35) pointing down (setting env.robot sets its robot's)",
        within(-math.pi, math.pi))
    start_noise: float = key(0.05, "rad: uniform noise added to every start joint", within(0, 1))
    obs_noise_std: float = key(0.005, "rad: Gaussian noise on the observed joints", within(0, 1))
    obs_noise_growth: float = key(0.0, "the noise std is multiplied by 1 + this × progress (0 = fixed)", within(0, 100))
    max_steps: int = key(200, "steps before a timeout (terminal, R_success = failure_reward)", within(1, 100_000))
    success_xy: float = key(
        0.010, "m: success needs the gripper centre this close to the target centre horizontally", above(0, 0.5))
    success_dz_min: float = key(0.005, "m: ... and at least this high above it", within(-0.5, 0.5))
    success_dz_max: float = key(0.020, "m: ... and at most this high above it", within(-0.5, 0.5))
    success_tilt_deg: float = key(10.0, "deg: ... with the gripper tilt θgz at most this", within(0, 180))
    obstacle_dist_clip: float = key(1.0, "m: Δpo is clipped to this (its value with no obstacle)", above(0, 10))
    no_obstacle_pos: tuple[float, float, float] = key(
        (0.0, 0.0, -1.0), 'layout "paper": the obstacle xyz seen when there is none', within(-100, 100))
    obs_layout: ObsLayout = key(
        "paper", 'Observation layout (observation.LAYOUTS): "paper" = the paper\'s 17 numbers (absolute obstacle '
        'centre, sentinel when absent); "relative" = per obstacle slot, nearest first, a presence flag, the vectors '
        "gripper centre → obstacle surface and closest robot point → obstacle surface, and a closeness that is 0 "
        'when absent, all hand-scaled (docs/design.md, "Observation layouts"); "relative_lag" = "relative" and each '
        "joint's pending command q_target − q_reading (obs_pending_clip)")
    obs_vector_scale: float = key(
        0.25, 'm: "relative" obstacle vectors are divided by this (clipped to ±obs_vector_clip)', above(0, 10))
    obs_vector_clip: float = key(3.0, '"relative" obstacle vectors, after scaling, are clipped to ±this', above(0, 1e3))
    obs_closeness_range: float = key(0.15, 'm: "relative" closeness = max(0, 1 − distance / this)', above(0, 10))
    obs_pending_clip: float = key(
        5.0, '"relative_lag" layout: the pending command q_target − q_reading of each joint, divided by '
        "control.q_max (one full step = 1) and clipped to ±this; it shows the policy what its last commands still "
        "have to do", above(0, 1e3))
    obs_obstacle_shape: bool = key(
        False, '"relative" layouts: each obstacle slot also carries the vector from the gripper centre to the '
        "obstacle's centre (/ obs_vector_scale, clipped like the others) and the half-extents of its world-aligned "
        "bounding box (/ observation.EXTENT_SCALE = 0.1 m): how far the obstacle reaches, which the nearest-surface "
        "vectors alone do not say; 0 when the slot is empty")
    obstacle_geometry: ObstacleGeometry = key(
        "fine", 'Robot-obstacle distance (Δpo, obstacle collisions): "fine" = a sphere set within ±4 mm of the '
        'robot\'s URDF primitives (collision.py); "cover" = the first landing\'s conservative cover, which '
        "over-reports contact by up to 2.5 cm near the flange (kept for the ablation and old runs).")


@dataclass(frozen=True)
class SamplingConfig:
    """Target and dynamic-obstacle sampling (docs/task.md §1)."""

    target_size: tuple[float, float, float] = key(
        (0.02, 0.02, 0.05), "m: full extents of the target cuboid", above(0, 0.5))
    target_x: tuple[float, float] = key((-0.35, 0.35), "m: range of the target centre x", within(-2, 2))
    target_y: tuple[float, float] = key((-0.60, -0.25), "m: range of the target centre y", within(-2, 2))
    target_yaw: tuple[float, float] = key(
        (-math.pi / 4, math.pi / 4), "rad: range of the target yaw", within(-math.pi, math.pi))
    target_radius: tuple[float, float] = key(
        (0.25, 0.65), "m: a target centre farther from / nearer to the base is redrawn", within(0, 2))
    target_candidates: int = key(
        16, "target draws per scene attempt; the first inside target_radius wins", within(1, 4096))
    obstacle_prob: float = key(
        0.2, "probability of an episode with dynamic obstacles: the evaluation mix (docs/task.md §1), and the "
        "training mix unless train.obstacle_prob is set", within(0, 1))
    max_obstacles: Literal[2] = key(
        2, "obstacle slots (the MJCF has 2); an obstacle episode has 1 or 2, equally likely")
    sphere_radius: tuple[float, float] = key((0.03, 0.06), "m: range of a sphere's radius", above(0, 0.5))
    sphere_z: tuple[float, float] = key((0.12, 0.30), "m: range of a (floating) sphere's centre height", within(0, 2))
    cylinder_radius: tuple[float, float] = key((0.02, 0.05), "m: range of an upright cylinder's radius", above(0, 0.5))
    cylinder_height: tuple[float, float] = key(
        (0.10, 0.30), "m: range of its full height (it stands on the table)", above(0, 2))
    box_half: tuple[float, float] = key(
        (0.02, 0.06), "m: range of each half-extent of a box (on the table, yaw uniform)", above(0, 0.5))
    capsule_radius: tuple[float, float] = key(
        (0.02, 0.05), "m: range of a capsule's radius (lying on the table, yawed)", above(0, 0.5))
    capsule_length: tuple[float, float] = key(
        (0.10, 0.30), "m: range of its axis between the cap centres (tip to tip + 2 r)", above(0, 2))
    obstacle_kinds: tuple[ShapeName, ...] = key(
        shapes.PAPER_KINDS, "Obstacle shapes drawn, names of shapes.SHAPES; each slot's candidates are split evenly "
        "among them.  The default is the paper's mix (docs/task.md §1).")
    obstacle_disc_radius: float = key(
        0.15, "m: obstacles are placed uniformly in a disc this wide around the approach midpoint", within(0, 2))
    home_xy: tuple[float, float] = key(
        (0.0, -0.30), "m: the start gripper centre's xy, one end of that midpoint", within(-2, 2))
    target_clearance: float = key(
        0.10, "m: an obstacle's footprint keeps this far from the target centre (docs/task.md §1 (a))", within(0, 1))
    robot_clearance: float = key(
        0.10, "m: an obstacle keeps this far from every robot geometry at the start pose", within(0, 1))
    obstacle_candidates: int = key(
        9, "draws per slot and attempt, split evenly among obstacle_kinds; the first feasible wins", within(1, 4096))
    scene_redraws: int = key(2, "whole-scene re-draws before falling back to \"no obstacle\"", within(0, 1000))
    blocking_prob: float = key(
        0.0, 'Fraction of obstacle scenes whose obstacles are placed on the straight approach path (sampling.py, '
        '"blocking" placement) instead of the disc around the path\'s midpoint (docs/task.md §1.5): the evaluation '
        "mix's (0), and the training mix's unless train.blocking_prob is set", within(0, 1))
    blocking_margin: float = key(
        0.03, 'm: an obstacle scene is "blocking" if the straight path passes this close', above(0, 1))


@dataclass(frozen=True)
class RandomizeConfig:
    """Domain randomisation for transfer to the real arm: every knob off (0) by default; each episode
    draws its own values at reset (docs/design.md, "Dynamic mode and domain randomisation")."""

    servo_gain: float = key(
        0.0, "Servo gains: each arm joint's kp and kv are scaled by their own factors, uniform in [1 − this, "
        "1 + this] per episode (0.2 = ±20 %); dynamic mode (lagged mode: lag_gain is scaled by the kp factor)",
        within(0, 0.9))
    latency: float = key(
        0.0, "Command latency in control steps: per episode uniform in [0, this]; a queue of the last commands "
        "delays each by the whole steps, and the fraction of a step holds the command before it for that share of "
        "the control period (1 = a whole step late, 2.5 = two and a half); dynamic and lagged modes only",
        within(0, 3))
    joint_offset: float = key(
        0.0, "rad: per-episode offset of each joint reading, uniform in ±this (calibration error)", within(0, 0.2))
    joint_noise: float = key(
        0.0, "rad: extra Gaussian noise on the joint readings, its std drawn per episode uniformly in [0, this] "
        "(on top of env.task.obs_noise_std)", within(0, 0.2))
    target_error: float = key(
        0.0, "m: per-episode error of the detected target position, uniform in ±this on each axis: the policy "
        "and the control step's slow-down and fine-tuning see it, the reward and the success test use the true "
        "target", within(0, 0.05))


@dataclass(frozen=True)
class EnvConfig:
    robot: RobotName = key(
        robots.DEFAULT, "The arm (robots.py's registry): its URDF, MJCF, joint roles and servo model.  Setting it "
        "(--set robot=NAME) also sets the keys that hold one value per joint (ROBOT_KEYS: env.task.home_q, "
        "env.control.lag_gain, env.control.lag_momentum) to that robot's, unless they are set too")
    control: ControlConfig = field(default_factory=ControlConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    randomize: RandomizeConfig = field(default_factory=RandomizeConfig)


@dataclass(frozen=True)
class NetworkConfig:
    policy_hidden: tuple[int, ...] = key((64, 64), "hidden layer widths of the policy MLP", within(1, 65_536))
    value_hidden: tuple[int, ...] = key((64, 64), "hidden layer widths of the value MLP", within(1, 65_536))
    activation: Activation = key("tanh", "hidden-layer activation of both networks")


@dataclass(frozen=True)
class PPOConfig:
    num_envs: int = key(16, "parallel envs stepped in one batch", within(1, 2**24))
    unroll_length: int = key(128, "steps per env per PPO iteration (rollout length)", within(1, 100_000))
    num_minibatches: int = key(8, "minibatches per epoch; must divide num_envs × unroll_length", within(1, 2**24))
    num_epochs: int = key(10, "passes over each rollout", within(1, 10_000))
    late_epochs: int = key(
        0, "Fewer passes late in the run (docs/design.md, \"Fewer SGD passes late\"): from training progress "
        "ppo.late_from on, each rollout gets this many passes instead of ppo.num_epochs.  0 = off, and a count "
        "not below ppo.num_epochs changes nothing: ppo.num_epochs throughout", within(0, 10_000))
    late_from: float = key(
        0.3, "training progress (env steps / train.total_steps) from which ppo.late_epochs applies", within(0, 1))
    clip_eps: float = key(0.2, "PPO ratio clip ε", above(0, 10))
    gamma: float = key(0.99, "discount factor γ of the returns", above(0, 1))
    gae_lambda: float = key(0.95, "λ of the generalised advantage estimate", within(0, 1))
    entropy_coef: float = key(0.0, "weight of the entropy bonus in the loss", within(0, 100))
    value_coef: float = key(0.5, "weight of the value loss", within(0, 1e3))
    max_grad_norm: float = key(0.5, "global gradient-norm clip", above(0, 1e6))
    learning_rate: float = key(
        3e-4, 'initial Adam learning rate of every lr schedule (lr.schedule); constant under "constant"', above(0, 1))
    normalize_advantages: bool = key(True, "advantages to zero mean, unit std per minibatch")
    obs_std_floor: float = key(0.01, "the observation normaliser's std is floored at this (docs/task.md §2)",
                               above(0, 1e3))
    obs_clip: float = key(5.0, "normalised observations are clipped to ±this", above(0, 1e6))
    privileged_critic: bool = key(
        False, "Asymmetric actor-critic: the value network also reads privileged inputs (training progress, time "
        "left, every obstacle's kind, size and position; observation.privileged).  The policy, and so the exported "
        "file, never needs them.")
    network: NetworkConfig = field(default_factory=NetworkConfig)


@dataclass(frozen=True)
class LRConfig:
    """Learning-rate schedule (sagrasp_jax/training/lr_schedule.py, docs/design.md); every one starts at ppo.learning_rate."""

    schedule: LRSchedule = key(
        "sa", '"constant": the paper\'s PPO baseline (--algo ppo); "sa": docs/task.md §3\'s simulated-annealing '
        'plateau schedule, the sa.* keys (--algo sa-ppo, the default); "kl-adaptive": brax\'s / rsl_rl\'s rule, '
        "after every minibatch lr ÷ kl_factor when its KL > 2·desired_kl, × kl_factor when KL < desired_kl / 2, "
        'kept in [kl_lr_min, kl_lr_max]; "cosine" / "linear": from ppo.learning_rate at progress 0 to lr.final at '
        "progress 1 (env steps / budget)")
    final: float = key(
        1e-6, "cosine / linear: the learning rate at the end of the env-step budget (the paper's 1e-6 floor)",
        within(0, 1))
    desired_kl: float = key(
        0.01, "kl-adaptive: the target KL(old ‖ new policy) of a minibatch (brax / rsl_rl default)", above(0, 100))
    kl_factor: float = key(
        1.5, "kl-adaptive: the factor the lr is multiplied or divided by outside the KL band", above(1, 100))
    kl_lr_min: float = key(1e-5, "kl-adaptive: the lowest learning rate it may reach", above(0, 1))
    kl_lr_max: float = key(1e-2, "kl-adaptive: the highest learning rate it may reach", above(0, 1))


@dataclass(frozen=True)
class EvalConfig:
    """The fixed-seed evaluation that ends every cycle, under every lr schedule (SA reads its metric,
    the others log it), and the cycles' length."""

    cycle_steps: int = key(
        0, "env steps per cycle, each ended by an evaluation; 0 = train.total_steps / eval.num_cycles", within(0, _BIG))
    num_cycles: int = key(200, "cycles over the run when eval.cycle_steps = 0", within(1, 10**6))
    episodes: int = key(
        128, "episodes of the fixed evaluation set run at the end of each cycle (in one batch)", within(1, 100_000))
    seed: int = key(
        12345, "seed of that evaluation set (the same episodes every cycle; evaluate's default is this + 1)", SEEDS)


@dataclass(frozen=True)
class SAConfig:
    """Simulated-annealing learning-rate plateau schedule (docs/task.md §3), under lr.schedule = sa."""

    metric: SAMetric = key(
        "return", 'cycle metric M read from each cycle\'s evaluation: "return" (mean return with the p = 1 reward '
        'weights) | "success" (rate)')
    decay: float = key(
        0.98, "lr ← max(lr·decay, lr_min) at a plateau (SA starts at ppo.learning_rate)", above(0, 1))
    lr_min: float = key(1e-6, "the SA schedule's learning-rate floor", above(0, 1))
    tol: float = key(
        0.2, "A cycle within this of the accepted metric is accepted outright.  Calibrated: on the fixed "
        "128-episode evaluation set the metric moves by ≈ 0.10 (std) from cycle to cycle of a run that is still "
        "improving, so 0.05 rejected ≈ 40 % of cycles on noise; 0.2 (2 σ) rejects ≈ 5 %.", within(0, 1e6))
    min_delta: float = key(
        0.02, "a gain over the best metric by more than this resets the stall counter", within(0, 1e6))
    patience: int = key(5, "stalled cycles before the learning rate decays", within(1, 10**6))
    max_rollbacks: int = key(3, "rejections in a row before the learning rate decays", within(1, 10**6))
    t0: float = key(0.1, "temperature scale T_0 of the Metropolis acceptance of a worse cycle", above(0, 1e6))
    kappa: float = key(1.0, "κ: T = T_0·exp(κ·(H − H_0)/n_actions), H the policy entropy", within(0, 1e6))
    # Ablation switches (docs/design.md, "SA ablation switches"); all true is docs/task.md §3.
    metropolis: bool = key(
        True, "accept a worse cycle with probability exp(−ΔE/T); false: every worse cycle is rejected")
    rollback: bool = key(
        True, "a rejected cycle restores the snapshot; false: its updates are kept (still counted a reject)")
    plateau_decay: bool = key(
        True, "rule 3 decays the lr (stall or rejections in a row); false: only a non-finite step decays it")
    entropy_temperature: bool = key(True, "T follows the policy entropy (κ); false: T = T_0 throughout")


@dataclass(frozen=True)
class TrainConfig:
    total_steps: int = key(20_000_000, "env steps of the whole run", within(1, _BIG))
    seed: int = key(0, "seed of the parameters, the envs and the sampling", SEEDS)
    obstacle_prob: float | None = key(
        None, "Training scene mix: the probability of an obstacle episode while training; none (unset) = the "
        "evaluation mix, env.sampling.obstacle_prob (docs/task.md §1: 0.2)", within(0, 1))
    blocking_prob: float | None = key(
        None, "fraction of training obstacle scenes with the blocking placement; none (unset) = the evaluation "
        "mix's, env.sampling.blocking_prob", within(0, 1))
    curriculum_replay: float = key(
        0.0, "Learnability curriculum (wrappers.AutoReset): each training env remembers a scene it failed and starts "
        "it again instead of a fresh one with probability this × 4p(1 − p), p its success rate so far (most often "
        "the scenes solved sometimes but not always); 0 = off, every training start fresh", within(0, 1))
    curriculum_max_replays: int = key(
        8, "learnability curriculum: a remembered scene is retired after this many replays (one solved half the time "
        "keeps its score and would otherwise be replayed for ever)", within(1, 10**6))
    stop_success: float = key(
        0.0, "Stopping rule (docs/design.md, \"Stopping when the evaluation holds\"): end the run, before "
        "train.total_steps, at the end of a cycle whose policy SA kept when the fixed-seed evaluations of the last "
        "train.stop_cycles cycles, pooled, succeeded at least this often; the reward weights and the cycles stay those of "
        "the whole budget, so the run is the full run's first part.  0 = off (train to total_steps)", within(0, 1))
    stop_cycles: int = key(20, "stopping rule: cycles (fixed-seed evaluations) pooled, the current one included",
                           within(1, 10**6))
    log_every: int = key(1, "iterations between JSONL rows", within(1, 10**9))
    checkpoint_every_cycles: int = key(10, "cycles between checkpoints", within(1, 10**9))
    metrics_window: int = key(256, "finished episodes in the training-episode window", within(1, 10**7))
    init_from: str = key(
        "", "Run folder whose final checkpoint's policy, value network and observation normaliser start this run "
        "(train --init-from; e.g. a kinematic run fine-tuned in dynamic mode); optimizer and SA schedule start "
        'fresh.  "" = none')
    cpu_fusion_emitters: FusionEmitters = key(
        "legacy", "XLA's CPU fusion emitters for the trainer's programs (the training call, the SA evaluation, the first "
        "reset, the initial state): new = XLA's fusion emitters, 15-20 % less time per cycle of the lagged or kinematic "
        "env on 2 cores for a few seconds more compile, other numbers than legacy at the same quality over 5 seeds "
        "(docs/results-archive.md §25-26); legacy = the process's emitter, which the package sets to XLA's legacy one "
        "because MJX's physics step (the dynamic mode) runs 1.5x faster with it.  The CPU only; a jaxlib >= 0.11 "
        "cannot set it per program, and the trainer says so and keeps the process's")


@dataclass(frozen=True)
class Config:
    env: EnvConfig = field(default_factory=EnvConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    lr: LRConfig = field(default_factory=LRConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    sa: SAConfig = field(default_factory=SAConfig)
    train: TrainConfig = field(default_factory=TrainConfig)


def _paper() -> Config:
    return Config()


def _obstacle_aware(base: Config) -> Config:
    """What the obstacle ablation chose (docs/design.md, docs/results.md): the relative observation
    layout, a training mix of 80 % obstacle scenes with 60 % of those on the approach path, and a
    privileged critic.  Evaluation keeps the evaluation mix (docs/task.md §2.8) (env.sampling)."""
    return dataclasses.replace(
        base,
        env=dataclasses.replace(base.env, task=dataclasses.replace(base.env.task, obs_layout="relative")),
        ppo=dataclasses.replace(base.ppo, privileged_critic=True),
        train=dataclasses.replace(base.train, obstacle_prob=0.8, blocking_prob=0.6),
    )


def _upright_approach(base: Config) -> Config:
    """The hovering trap's fix (docs/design.md, "The hovering trap"): within 10 cm of the cube the approach
    shaping also counts the gripper's tilt beyond the success test's 10°, at 0.05 m per radian, so righting the
    gripper over the cube pays; further away the approach is free to tilt around obstacles."""
    return dataclasses.replace(base, env=dataclasses.replace(
        base.env, reward=dataclasses.replace(base.env.reward, tilt_weight=0.05, tilt_free_deg=10.0, tilt_near=0.10)))


def _robot_grade(base: Config) -> Config:
    """What makes a policy take to the real arm (docs/design.md, "Robot-grade policy"): it trains in the
    ``lagged`` mode (the dynamic mode's servo lag and command latency at the kinematic mode's cost), observes
    its pending command (``relative_lag``) and meets every transfer error in training, at or above the real
    arm's levels (ROBOT_KNOBS): servo gains ±20 %, latency up to 2 steps, joint offset ±5 mrad, joint noise
    σ ≤ 5 mrad, detected target ±6 mm."""
    env = base.env
    return dataclasses.replace(base, env=dataclasses.replace(
        env,
        control=dataclasses.replace(env.control, mode="lagged"),
        task=dataclasses.replace(env.task, obs_layout="relative_lag"),
        randomize=RandomizeConfig(servo_gain=0.2, latency=2.0, joint_offset=0.005, joint_noise=0.005, target_error=0.006),
    ))


def _sized(base: Config, *, num_envs: int, num_minibatches: int, network: NetworkConfig, eval_episodes: int,
           total_steps: int, num_epochs: int = 4, entropy_coef: float = 1e-3, learning_rate: float = 3e-4,
           sa_decay: float = 0.98, late_epochs: int = 0) -> Config:
    """The PPO shape ``cpu-quick`` and ``gpu`` share (16-step unrolls) at a machine's size."""
    return dataclasses.replace(
        base,
        ppo=dataclasses.replace(base.ppo, num_envs=num_envs, unroll_length=16, num_minibatches=num_minibatches,
                                num_epochs=num_epochs, entropy_coef=entropy_coef, network=network,
                                learning_rate=learning_rate, late_epochs=late_epochs),
        sa=dataclasses.replace(base.sa, decay=sa_decay),
        eval=dataclasses.replace(base.eval, episodes=eval_episodes),
        train=dataclasses.replace(base.train, total_steps=total_steps),
    )


def _cpu_quick() -> Config:
    # Eight SGD passes, a 3e-3 entropy bonus and a 64×4 policy reach 98 / 99 % in a third of the env steps of
    # four passes, 1e-3 and 32×4 (docs/results-archive.md §10, "The levers together"); the critic stays 64×3. SA starts
    # at lr 6e-4 and decays ×0.96 at a plateau (not ×0.98 from 3e-4): 99.4-99.9 % in `robot` over two groups of
    # five seeds, better than constant lr on every seed (docs/results-archive.md §10, "SA from lr 6e-4 with a
    # twice-as-steep plateau decay" and the README command's rows after it). After 30 % of the budget (the climb
    # to 98 % is over by then on every seed) four of the eight passes: the same policy over five seeds at 0.68x
    # the iteration's time (docs/results-archive.md §15). The trainer's programs compile with XLA's new fusion
    # emitters: 15-20 % less time per cycle on 2 cores, the same quality over 5 seeds (docs/results-archive.md §25-26).
    sized = _sized(_robot_grade(_obstacle_aware(_upright_approach(Config()))), num_envs=256, num_minibatches=4,
                   network=NetworkConfig(policy_hidden=(64, 64, 64, 64), value_hidden=(64, 64, 64)),
                   eval_episodes=128, total_steps=10_000_000, num_epochs=8, entropy_coef=3e-3,
                   learning_rate=6e-4, sa_decay=0.96, late_epochs=4)  # ppo.late_from: its default, 0.3
    return dataclasses.replace(sized, train=dataclasses.replace(sized.train, cpu_fusion_emitters="new"))


def _gpu() -> Config:
    # The preset trains in the lagged mode (no physics; env.control.impl stays "jax"); a dynamic-mode GPU run
    # adds env.control.mode=dynamic and env.control.impl=warp (pip install "sagrasp_jax[warp]").
    return _sized(_robot_grade(_obstacle_aware(_upright_approach(Config()))), num_envs=4096, num_minibatches=16,
                  network=NetworkConfig(policy_hidden=(128, 128, 128), value_hidden=(256, 256, 256)),
                  eval_episodes=1024, total_steps=20_000_000)


def _physics(base: Config) -> Config:
    """The same preset trained in the ``dynamic`` mode: MJX's servo physics (PD-driven joints with their
    armature, damping and contacts) instead of the ``lagged`` mode's fitted servo model, with the robot-grade
    transfer errors on top, so the policy meets in training the physics it is judged in (the ``robot``
    condition, the twin).  On a GPU the physics step costs little (docs/results.md); on 2 CPU cores it
    trains at ≈ 0.7× the lagged mode's env-steps/s (docs/results-archive.md §25)."""
    return dataclasses.replace(base, env=dataclasses.replace(
        base.env, control=dataclasses.replace(base.env.control, mode="dynamic")),
        train=dataclasses.replace(base.train, cpu_fusion_emitters="legacy"))  # MJX's physics: the legacy emitter


def _cpu_physics() -> Config:
    # cpu-quick's every setting, in the MJX servo physics: the CPU form of gpu-physics (issue 55, item 3)
    return _physics(_cpu_quick())


def _gpu_physics() -> Config:
    # gpu's every setting, in the MJX servo physics (env.control.impl stays "jax"; "warp" is MuJoCo Warp)
    return _physics(_gpu())


PRESETS: dict[str, typing.Callable[[], Config]] = {
    "paper": _paper,
    "cpu-quick": _cpu_quick,
    "gpu": _gpu,
    "cpu-physics": _cpu_physics,
    "gpu-physics": _gpu_physics,
}


# The transfer knobs at the levels a real AUBO-i5 cell needs (servo gains ±20 %, command latency 0-1 step,
# joint offset ±5 mrad, joint noise σ ≤ 5 mrad, detected target ±5 mm): "every knob on" in docs/results.md.
ROBOT_KNOBS: tuple[str, ...] = ("env.randomize.servo_gain=0.2", "env.randomize.latency=1",
                                "env.randomize.joint_offset=0.005", "env.randomize.joint_noise=0.005",
                                "env.randomize.target_error=0.005")
KNOBS_OFF: tuple[str, ...] = tuple(item.split("=")[0] + "=0" for item in ROBOT_KNOBS)  # every transfer knob off

# Named evaluation conditions (evaluate --condition NAME): env overrides applied over a run's own config, so a
# policy trained with randomisation is judged without it, or with it at fixed levels, in the physics of choice.
EVAL_CONDITIONS: dict[str, tuple[str, ...]] = {
    "kinematic": ("env.control.mode=kinematic", *KNOBS_OFF),  # exact joint tracking, no transfer error
    "dynamic": ("env.control.mode=dynamic", *KNOBS_OFF),  # MJX servos, no transfer error
    "robot": ("env.control.mode=dynamic", *ROBOT_KNOBS),  # MJX servos and every transfer knob on
    "robot-latency2": ("env.control.mode=dynamic", *ROBOT_KNOBS[:1], "env.randomize.latency=2", *ROBOT_KNOBS[2:]),
    "kinematic-target-error": ("env.control.mode=kinematic", *KNOBS_OFF[:-1], ROBOT_KNOBS[-1]),
    # 1.5× the robot condition's gain and detection errors and twice its latency: the margin a cell may need
    "robot-wide": ("env.control.mode=dynamic", "env.randomize.servo_gain=0.3", "env.randomize.latency=2",
                   *ROBOT_KNOBS[2:4], "env.randomize.target_error=0.0075"),
}


def get_config(preset: str = "cpu-quick") -> Config:
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; valid presets: {', '.join(PRESETS)}")
    return PRESETS[preset]()


# ---------------------------------------------------------------------- the declarations, read back


class KeySpec(typing.NamedTuple):
    """What a key's declaration says: the type of one value (of each entry of a list key), whether it is
    a list (of ``length`` entries if fixed) or may be unset (none), its meaning, range and choices."""

    kind: type
    listed: bool
    length: int | None
    optional: bool
    doc: str
    range: Range | None
    choices: tuple[Any, ...] | None

    @property
    def type_name(self) -> str:
        listed = f"list of {f'{self.length} ' if self.length else ''}" if self.listed else ""
        return listed + self.kind.__name__ + (" or none" if self.optional else "")


def _spec(hint: Any, f: dataclasses.Field) -> KeySpec:
    listed = typing.get_origin(hint) is tuple
    args = typing.get_args(hint)
    one = args[0] if listed else hint
    values = [a for a in typing.get_args(one) if a is not type(None)]
    literal = typing.get_origin(one) is Literal
    optional = not literal and len(values) < len(typing.get_args(one))
    kind = type(values[0]) if literal else values[0] if optional else one
    length = len(args) if listed and args[-1] is not Ellipsis else None
    return KeySpec(kind, listed, length, optional, f.metadata.get("doc", ""), f.metadata.get("range"),
                   tuple(values) if literal else None)


@functools.cache
def key_specs() -> dict[str, KeySpec]:
    """Every dotted key, in declaration order, with its declaration."""
    out: dict[str, KeySpec] = {}

    def walk(cls: type, prefix: str) -> None:
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if dataclasses.is_dataclass(hints[f.name]):
                walk(hints[f.name], f"{prefix}{f.name}.")
            else:
                out[prefix + f.name] = _spec(hints[f.name], f)

    walk(Config, "")
    return out


def _kinds_changed() -> None:
    """A kind registered (``shapes.register``) or the registry restored: ``env.sampling.obstacle_kinds`` takes the
    registry's names (the annotations are read back at ``key_specs`` time, through this module's ``ShapeName``)."""
    global ShapeName
    ShapeName = Literal[shapes.NAMES]  # type: ignore[valid-type]
    key_specs.cache_clear()


shapes.on_change(_kinds_changed)


def _robots_changed() -> None:
    """A robot registered: ``env.robot`` takes the registry's names."""
    global RobotName
    RobotName = Literal[robots.names()]  # type: ignore[valid-type]
    key_specs.cache_clear()


robots.on_change(_robots_changed)

# The keys that hold one value per arm joint, and where a robot's registry entry keeps its own.
ROBOT_KEYS: dict[str, typing.Callable[[robots.RobotSpec], tuple[float, ...]]] = {
    "env.task.home_q": lambda spec: spec.home_q,
    "env.control.lag_gain": lambda spec: spec.servo.lag_gain,
    "env.control.lag_momentum": lambda spec: spec.servo.lag_momentum,
}


def robot_defaults(name: str) -> dict[str, tuple[float, ...]]:
    """{dotted key: value} of the per-joint keys for robot ``name`` (what setting env.robot=name sets)."""
    spec = robots.get(name)
    return {key_name: value(spec) for key_name, value in ROBOT_KEYS.items()}


def valid_keys() -> list[str]:
    """All dotted keys that ``apply_overrides`` accepts."""
    return list(key_specs())


def key_descriptions() -> dict[str, str]:
    """Every dotted key's description, from its declaration."""
    return {name: spec.doc for name, spec in key_specs().items()}


def get_key(cfg: Any, name: str) -> Any:
    for part in name.split("."):
        cfg = getattr(cfg, part)
    return cfg


def check_fields(section: Any, prefix: str = "") -> None:
    """Every key of ``section`` (the config, or its part at ``prefix``, e.g. ``"env."``) lies in its range and
    is one of its choices (a list key: each entry, and as many as declared)."""
    for f in dataclasses.fields(section):
        value, name = getattr(section, f.name), prefix + f.name
        if dataclasses.is_dataclass(value):
            check_fields(value, name + ".")
            continue
        spec = key_specs()[name]
        if spec.listed and (not isinstance(value, tuple) or spec.length not in (None, len(value))):
            raise ConfigError(f"invalid value for {name}: {value!r} (expected a {spec.type_name})")
        for v in value if spec.listed else (value,):
            if spec.range and not (v is None and spec.optional) and v not in spec.range:
                raise ConfigError(f"invalid value for {name}: {value!r} ({'each entry ' * spec.listed}must be in {spec.range})")
            if spec.choices and v not in spec.choices:
                entry = f" (entry {v!r})" if spec.listed else ""
                raise ConfigError(f"{name}={value!r}{entry} is not one of {', '.join(map(str, spec.choices))}")


def check_range(name: str, value: Any, lo: float, hi: float) -> Any:
    """Refuse a command-line option ``value`` outside ``[lo, hi]``, NaN, inf or not a number, naming ``name``."""
    if value not in within(lo, hi):
        raise ConfigError(f"{name}={value!r} is outside the allowed range {within(lo, hi)}")
    return value


def format_number(v: float) -> str:
    """A number as ``--list-keys`` and the range messages write it: an int as is, a float in ``%g``."""
    return str(v) if isinstance(v, int) else f"{v:g}"


# ---------------------------------------------------------------------- rules across keys


def validate(cfg: Config) -> None:
    """Reject values that would make training meaningless or crash later: each key's declaration
    (``check_fields``), then what one key's declaration cannot say."""
    check_fields(cfg)
    dof = robots.get(cfg.env.robot).dof
    for name in ROBOT_KEYS:
        if len(get_key(cfg, name)) != dof:
            raise ConfigError(f"{name} has {len(get_key(cfg, name))} values; env.robot={cfg.env.robot} has {dof} joints "
                              f"(one value each; setting env.robot alone sets its own)")
    kinds = cfg.env.sampling.obstacle_kinds
    checks = [
        ("sa.lr_min", cfg.lr.schedule != "sa" or cfg.sa.lr_min <= cfg.ppo.learning_rate),  # SA starts above its floor
        ("lr.kl_lr_min", cfg.lr.kl_lr_min <= cfg.lr.kl_lr_max),
        ("env.sampling.obstacle_kinds", 0 < len(set(kinds)) == len(kinds)),  # some, none twice
        ("env.sampling.obstacle_candidates", cfg.env.sampling.obstacle_candidates >= len(kinds)),  # ≥ one of each kind
    ]
    for name, ok in checks:
        if not ok:
            raise ConfigError(f"invalid value for {name}: {get_key(cfg, name)!r}")
    if cfg.env.task.obs_obstacle_shape and cfg.env.task.obs_layout == "paper":
        raise ConfigError("env.task.obs_obstacle_shape=true needs a relative observation layout (env.task.obs_layout="
                          "relative or relative_lag); the paper's layout has no obstacle slots")
    if cfg.env.control.impl != "jax" and cfg.env.control.mode != "dynamic":  # a physics backend: servo physics only
        raise ConfigError(f"env.control.impl={cfg.env.control.impl!r} needs env.control.mode=dynamic (no physics runs otherwise)")
    for name in ("env.randomize.servo_gain", "env.randomize.latency"):  # servos: simulated or modelled
        if get_key(cfg, name) != 0 and cfg.env.control.mode == "kinematic":
            raise ConfigError(f"{name}={get_key(cfg, name)!r} needs env.control.mode=dynamic or lagged "
                              "(the kinematic mode has no servos)")
    for name in ("ppo.network.policy_hidden", "ppo.network.value_hidden"):  # `--set KEY=` leaves no layer
        if not get_key(cfg, name):
            raise ConfigError(f"{name} is empty: give at least one hidden layer width (e.g. {name}=64,64); "
                              "no hidden layer would make the network linear")
    if (cfg.ppo.num_envs * cfg.ppo.unroll_length) % cfg.ppo.num_minibatches:
        raise ConfigError(f"ppo.num_minibatches={cfg.ppo.num_minibatches} must divide ppo.num_envs × ppo.unroll_length "
                          f"= {cfg.ppo.num_envs} × {cfg.ppo.unroll_length}")


# ---------------------------------------------------------------------- derived envs

BLOCKING_SCENE_REDRAWS = 11  # whole-scene re-draws when blocking scenes are wanted (their fallbacks stay < 2 %)


def blocking_sampling(s: SamplingConfig, obstacle_prob: float, blocking_prob: float) -> SamplingConfig:
    """``s`` with another obstacle / blocking mix; blocking placements are rejected more often, so
    they get more whole-scene re-draws (a fallback would turn an obstacle scene into a free one)."""
    redraws = max(s.scene_redraws, BLOCKING_SCENE_REDRAWS) if blocking_prob > 0 else s.scene_redraws
    return dataclasses.replace(s, obstacle_prob=obstacle_prob, blocking_prob=blocking_prob, scene_redraws=redraws)


def training_env_config(cfg: Config) -> EnvConfig:
    """The env the trainer samples episodes from: env.sampling with the training mix of ``train`` (an
    unset key: the evaluation mix's)."""
    s, t = cfg.env.sampling, cfg.train
    obstacle_prob = s.obstacle_prob if t.obstacle_prob is None else t.obstacle_prob
    blocking_prob = s.blocking_prob if t.blocking_prob is None else t.blocking_prob
    return dataclasses.replace(cfg.env, sampling=blocking_sampling(s, obstacle_prob, blocking_prob))


def randomization_enabled(env: EnvConfig) -> bool:
    """Whether any ``env.randomize`` knob is on (then each episode draws its values at reset)."""
    return any(getattr(env.randomize, f.name) != 0 for f in dataclasses.fields(env.randomize))


# ---------------------------------------------------------------------- the config as dotted keys


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """The config (or a section) as nested dicts: what run folders, checkpoints and policy files store
    (``config_parse.config_from_dict`` reads it back)."""
    return dataclasses.asdict(cfg)


def flatten_keys(data: Any, prefix: str, where: str) -> dict[str, Any]:
    """A nested mapping of config keys as {dotted key: value}."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: {prefix.rstrip('.') or 'it'} must be a mapping of config keys, got {data!r}")
    out: dict[str, Any] = {}
    for name, value in data.items():
        out.update(flatten_keys(value, f"{prefix}{name}.", where) if isinstance(value, dict) else {prefix + name: value})
    return out


def nest_keys(flat: dict[str, Any]) -> dict[str, Any]:
    """{dotted key: value} as the nested mapping ``config_to_dict`` writes (``flatten_keys`` undone)."""
    out: dict[str, Any] = {}
    for name, value in flat.items():
        *path, leaf = name.split(".")
        node = out
        for part in path:
            node = node.setdefault(part, {})
        node[leaf] = value
    return out
