"""Every tunable constant of the project, in one place, with named presets.

The config is a tree of frozen dataclasses.  ``get_config(preset)`` returns a
preset, ``apply_overrides(cfg, ["ppo.num_envs=512", ...])`` changes keys with
type checking, and ``config_to_dict`` / ``config_from_dict`` round-trip it
through JSON (run folders and checkpoints store it).  Values come from
``docs/task.md`` §2-§3; where a number is ours, not the paper's, the field says so.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import hashlib
import io
import json
import math
import textwrap
import tokenize
import typing
from dataclasses import dataclass, field
from typing import Any

from sagrasp_jax import shapes

Q_LIMIT = 3.0543  # ±175° on every AUBO-i5 joint (docs/task.md §1); the URDF holds the same value.

# Home pose: damped-least-squares IK seeded from docs/task.md §2's vector, solved once by
# ``sagrasp_jax.robot.solve_home_pose`` and pasted here (tests re-solve and compare).
HOME_SEED = (1.1538, -0.4919, -1.8145, 0.2482, -1.5708, 0.0)
HOME_Q = (
    1.1538174961752017,
    -0.49293447743928726,
    -1.8197668542055943,
    0.2439639500285898,
    -1.5707963267948966,
    0.0,
)
HOME_GRIPPER_CENTRE = (0.0, -0.30, 0.35)


@dataclass(frozen=True)
class ControlConfig:
    """One control step (docs/task.md §2 steps 1-5)."""

    q_max: float = 0.05  # rad: joint change per step at |action| = 1 (docs/task.md §2 step 1)
    slowdown_enabled: bool = True  # proximity slow-down on (step 2)
    d_slow: float = 0.08  # m: slow down when the gripper centre is this close to the target centre
    slow_factor: float = 0.3  # Δq is multiplied by this inside d_slow
    finetune_enabled: bool = True  # vertical-alignment fine-tuning of joints 4, 5 on (step 3)
    d_fine: float = 0.10  # m: fine-tune within this distance of the target centre
    fine_tilt_deg: float = 10.0  # deg: fine-tune only when the gripper tilt θgz exceeds this
    fine_gain: float = 1.0  # k: gain of the damped least-squares wrist correction
    fine_damping: float = 0.05  # λ: damping of that least-squares step
    fine_clip: float = 0.015  # rad: the correction is clipped to ±this (c = 0.3·q_max)
    q_limit: float = Q_LIMIT  # rad: joint targets are clipped to ±this (the URDF limit, ±175°)
    # "kinematic": qpos = q_target, no physics; "dynamic": MuJoCo servos track q_target; "lagged": no physics, the
    # joints follow q_target through the per-step servo model below (lag_gain, lag_momentum), fitted to the dynamic
    # mode's servos: as cheap as "kinematic", with the servo lag and the command latency of "dynamic"
    mode: str = "kinematic"
    control_dt: float = 0.05  # s: control period (20 Hz)
    physics_dt: float = 0.01  # s: physics step of the dynamic mode
    substeps: int = 5  # physics steps per control step in the dynamic mode
    # Physics backend of the dynamic mode: "jax" (MJX's JAX implementation, any device) or "warp" (MuJoCo
    # Warp through MJX: needs the warp extra, pip install "sagrasp_jax[warp]", and is meant for CUDA GPUs)
    impl: str = "jax"
    # "lagged" mode, per joint: each control step the joint closes this fraction of its distance to the command
    # (q ← q + lag_gain·(c − q) + lag_momentum·(q − q_prev)); fitted by least squares to the dynamic mode's servos
    # (experiments/fit_servo_lag.py, experiments/results/fit_servo_lag.json)
    lag_gain: tuple[float, ...] = (0.639, 0.601, 0.632, 0.806, 0.785, 0.798)
    lag_momentum: tuple[float, ...] = (0.070, 0.143, 0.080, 0.037, 0.077, 0.059)  # "lagged" mode: carry-over of the last step's motion


@dataclass(frozen=True)
class RewardConfig:
    """R = F_d·R_distance + F_s·R_success + F_o·R_obstacle (docs/task.md §2)."""

    ratio: float = 10.0  # R_distance per metre of approach to the target
    rc: float = 0.05  # grab-zone bonus RC
    d_grab: float = 0.05  # m: radius of the grab zone around the target centre
    # "entry": RC paid on entering the grab zone and taken back on leaving (potential-based); "per_step": the
    # paper's RC on every step inside it (kept for the ablation: PPO learns to hover, docs/task.md §2)
    rc_mode: str = "entry"
    success_reward: float = 1.0  # R_success on success
    failure_reward: float = -1.0  # R_success on a collision or a timeout
    collision_penalty: float = -1.0  # R_obstacle on any collision
    near_miss_distance: float = 0.05  # m: Δpo under this is a near miss
    near_miss_scale: float = 0.5  # weight of the near-miss term (see near_miss_mode)
    # "change" (default): on every step without a collision pay −scale·(c_t − c_{t−1}), c = clip(1 −
    # Δpo/near_miss_distance, 0, 1), c_0 from the start state — a potential, so lingering near an
    # obstacle costs nothing extra and moving away repays it.  "per_step": the paper's literal
    # −scale·c_t on every step, which accumulates without bound against a bounded collision penalty
    # and teaches crashing early (docs/task.md §2; kept for the ablation).
    near_miss_mode: str = "change"
    clean_success_bonus: float = 1.0  # R_obstacle at a success in an obstacle episode whose Δpo stayed ≥ near_miss_distance
    f_d0: float = 2.0  # F_d = f_d0 + f_d1·p (p = training progress in [0, 1])
    f_d1: float = -1.0  # slope of F_d in p
    f_s0: float = 0.5  # F_s = f_s0 + f_s1·p
    f_s1: float = 1.0  # slope of F_s in p
    f_o: float = 0.5  # F_o, the weight of R_obstacle
    # m/rad: R_distance's approach shaping measures progress on the distance to the target plus this much per radian
    # of gripper tilt beyond tilt_free_deg (reward.approach_potential).  0 = the paper's distance alone, which pays
    # nothing for righting a tilted gripper that hovers in place over the cube: the hovering trap (docs/design.md)
    tilt_weight: float = 0.0
    tilt_free_deg: float = 5.0  # deg: tilt up to this costs nothing in the approach potential (success needs ≤ 10°)
    # m: > 0: the tilt part fades in linearly as the gripper centre closes in from this distance to the target, so
    # the approach far from the cube is free to tilt (around obstacles); 0: the tilt part counts everywhere
    tilt_near: float = 0.0


@dataclass(frozen=True)
class TaskConfig:
    """Start state, observation, success and episode length (docs/task.md §2)."""

    home_q: tuple[float, ...] = HOME_Q  # rad: start pose, gripper centre at (0, −0.30, 0.35) pointing down
    start_noise: float = 0.05  # rad: uniform noise added to every start joint
    obs_noise_std: float = 0.005  # rad: Gaussian noise on the observed joints
    obs_noise_growth: float = 0.0  # the noise std is multiplied by 1 + this × progress (0 = fixed)
    max_steps: int = 200  # steps before a timeout (terminal, R_success = failure_reward)
    success_xy: float = 0.010  # m: success needs the gripper centre this close to the target centre horizontally
    success_dz_min: float = 0.005  # m: ... and at least this high above it
    success_dz_max: float = 0.020  # m: ... and at most this high above it
    success_tilt_deg: float = 10.0  # deg: ... with the gripper tilt θgz at most this
    obstacle_dist_clip: float = 1.0  # m: Δpo is clipped to this (its value with no obstacle)
    no_obstacle_pos: tuple[float, float, float] = (0.0, 0.0, -1.0)  # layout "paper": the obstacle xyz seen when there is none
    # Observation layout (observation.LAYOUTS): "paper" = the paper's 17 numbers (absolute obstacle
    # centre, sentinel when absent); "relative" = per obstacle slot, nearest first, a presence flag,
    # the vectors gripper centre → obstacle surface and closest robot point → obstacle surface, and a
    # closeness that is 0 when absent, all hand-scaled (docs/design.md, "Observation layouts");
    # "relative_lag" = "relative" and each joint's pending command q_target − q_reading (obs_pending_clip)
    obs_layout: str = "paper"
    obs_vector_scale: float = 0.25  # m: "relative" obstacle vectors are divided by this (clipped to ±obs_vector_clip)
    obs_vector_clip: float = 3.0  # "relative" obstacle vectors, after scaling, are clipped to ±this
    obs_closeness_range: float = 0.15  # m: "relative" closeness = max(0, 1 − distance / this)
    # "relative_lag" layout: the pending command q_target − q_reading of each joint, divided by control.q_max (one
    # full step = 1) and clipped to ±this; it shows the policy what its last commands still have to do
    obs_pending_clip: float = 5.0
    # Robot-obstacle distance (Δpo, obstacle collisions): "fine" = a sphere set within ±4 mm of the
    # robot's URDF primitives (collision.py); "cover" = the first landing's conservative cover, which
    # over-reports contact by up to 2.5 cm near the flange (kept for the ablation and old runs).
    obstacle_geometry: str = "fine"


@dataclass(frozen=True)
class SamplingConfig:
    """Target and dynamic-obstacle sampling (docs/task.md §1)."""

    target_size: tuple[float, float, float] = (0.02, 0.02, 0.05)  # m: full extents of the target cuboid
    target_x: tuple[float, float] = (-0.35, 0.35)  # m: range of the target centre x
    target_y: tuple[float, float] = (-0.60, -0.25)  # m: range of the target centre y
    target_yaw: tuple[float, float] = (-math.pi / 4, math.pi / 4)  # rad: range of the target yaw
    target_radius: tuple[float, float] = (0.25, 0.65)  # m: a target centre farther from / nearer to the base is redrawn
    target_candidates: int = 16  # target draws per scene attempt; the first inside target_radius wins
    obstacle_prob: float = 0.2  # probability of an episode with dynamic obstacles (docs/task.md §1; the evaluation mix)
    max_obstacles: int = 2  # obstacle slots; an obstacle episode has 1 or 2, equally likely (the MJCF has 2)
    sphere_radius: tuple[float, float] = (0.03, 0.06)  # m: range of a sphere's radius
    sphere_z: tuple[float, float] = (0.12, 0.30)  # m: range of a (floating) sphere's centre height
    cylinder_radius: tuple[float, float] = (0.02, 0.05)  # m: range of an upright cylinder's radius
    cylinder_height: tuple[float, float] = (0.10, 0.30)  # m: range of its full height (it stands on the table)
    box_half: tuple[float, float] = (0.02, 0.06)  # m: range of each half-extent of a box (on the table, yaw uniform)
    capsule_radius: tuple[float, float] = (0.02, 0.05)  # m: range of a capsule's radius (lying on the table, yawed)
    capsule_length: tuple[float, float] = (0.10, 0.30)  # m: range of its axis between the cap centres (tip to tip + 2 r)
    # Obstacle shapes drawn, names of shapes.SHAPES (sphere, cylinder, box, capsule); each slot's candidates are
    # split evenly among them.  The default is the paper's mix (docs/task.md §1).
    obstacle_kinds: tuple[str, ...] = shapes.PAPER_KINDS
    obstacle_disc_radius: float = 0.15  # m: obstacles are placed uniformly in a disc this wide around the approach midpoint
    home_xy: tuple[float, float] = (0.0, -0.30)  # m: the start gripper centre's xy, one end of that midpoint
    target_clearance: float = 0.10  # m: an obstacle's footprint keeps this far from the target centre (docs/task.md §1 (a))
    robot_clearance: float = 0.10  # m: an obstacle keeps this far from every robot geometry at the start pose
    obstacle_candidates: int = 9  # draws per slot and attempt, split evenly among obstacle_kinds; the first feasible wins
    scene_redraws: int = 2  # whole-scene re-draws before falling back to "no obstacle"
    # Fraction of obstacle scenes whose obstacles are placed on the straight approach path (sampling.py,
    # "blocking" placement) instead of the disc around the path's midpoint (docs/task.md §1.5).  0 = the evaluation mix.
    blocking_prob: float = 0.0
    blocking_margin: float = 0.03  # m: an obstacle scene is "blocking" if the straight path passes this close


@dataclass(frozen=True)
class RandomizeConfig:
    """Domain randomisation for transfer to the real arm: every knob off (0) by default; each episode
    draws its own values at reset (docs/design.md, "Dynamic mode and domain randomisation")."""

    # Servo gains: each arm joint's kp and kv are scaled by their own factors, uniform in [1 − this, 1 + this]
    # per episode (0.2 = ±20 %); dynamic mode (lagged mode: lag_gain is scaled by the kp factor)
    servo_gain: float = 0.0
    # Command latency in control steps: per episode uniform in [0, this]; a queue of the last commands delays each
    # by the whole steps, and the fraction of a step holds the command before it for that share of the control
    # period (1 = a whole step late, 2.5 = two and a half); dynamic and lagged modes only
    latency: float = 0.0
    joint_offset: float = 0.0  # rad: per-episode offset of each joint reading, uniform in ±this (calibration error)
    # rad: extra Gaussian noise on the joint readings, its std drawn per episode uniformly in [0, this] (on top of
    # env.task.obs_noise_std)
    joint_noise: float = 0.0
    # m: per-episode error of the detected target position, uniform in ±this on each axis: the policy and the
    # control step's slow-down and fine-tuning see it, the reward and the success test use the true target
    target_error: float = 0.0


@dataclass(frozen=True)
class EnvConfig:
    control: ControlConfig = field(default_factory=ControlConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    randomize: RandomizeConfig = field(default_factory=RandomizeConfig)


@dataclass(frozen=True)
class NetworkConfig:
    policy_hidden: tuple[int, ...] = (64, 64)  # hidden layer widths of the policy MLP
    value_hidden: tuple[int, ...] = (64, 64)  # hidden layer widths of the value MLP
    activation: str = "tanh"  # hidden-layer activation of both networks


@dataclass(frozen=True)
class PPOConfig:
    num_envs: int = 16  # parallel envs stepped in one batch
    unroll_length: int = 128  # steps per env per PPO iteration (rollout length)
    num_minibatches: int = 8  # minibatches per epoch; must divide num_envs × unroll_length
    num_epochs: int = 10  # passes over each rollout
    clip_eps: float = 0.2  # PPO ratio clip ε
    gamma: float = 0.99  # discount factor γ of the returns
    gae_lambda: float = 0.95  # λ of the generalised advantage estimate
    entropy_coef: float = 0.0  # weight of the entropy bonus in the loss
    value_coef: float = 0.5  # weight of the value loss
    max_grad_norm: float = 0.5  # global gradient-norm clip
    learning_rate: float = 3e-4  # initial Adam learning rate of every lr schedule (lr.schedule); constant under "constant"
    normalize_advantages: bool = True  # advantages to zero mean, unit std per minibatch
    obs_std_floor: float = 0.01  # the observation normaliser's std is floored at this (docs/task.md §2)
    obs_clip: float = 5.0  # normalised observations are clipped to ±this
    # Asymmetric actor-critic: the value network also reads privileged inputs (training progress, time
    # left, every obstacle's kind, size and position; observation.privileged).  The policy, and so the
    # exported file, never needs them.
    privileged_critic: bool = False
    network: NetworkConfig = field(default_factory=NetworkConfig)


CONTROL_MODES = ("kinematic", "dynamic", "lagged")  # env.control.mode (env.py)
OBS_LAYOUTS = ("paper", "relative", "relative_lag")  # env.task.obs_layout (observation.py)
LR_SCHEDULES = ("constant", "sa", "kl-adaptive", "cosine", "linear")  # the names lr.schedule accepts (lr_schedule.py)


@dataclass(frozen=True)
class LRConfig:
    """Learning-rate schedule (sagrasp_jax/lr_schedule.py, docs/design.md); every one starts at ppo.learning_rate."""

    # "constant": the paper's PPO baseline (--algo ppo); "sa": docs/task.md §3's simulated-annealing plateau schedule, the
    # sa.* keys (--algo sa-ppo, the default); "kl-adaptive": brax's / rsl_rl's rule, after every minibatch lr ÷
    # kl_factor when its KL > 2·desired_kl, × kl_factor when KL < desired_kl / 2, kept in [kl_lr_min, kl_lr_max];
    # "cosine" / "linear": from ppo.learning_rate at progress 0 to lr.final at progress 1 (env steps / budget)
    schedule: str = "sa"
    final: float = 1e-6  # cosine / linear: the learning rate at the end of the env-step budget (the paper's 1e-6 floor)
    desired_kl: float = 0.01  # kl-adaptive: the target KL(old ‖ new policy) of a minibatch (brax / rsl_rl default)
    kl_factor: float = 1.5  # kl-adaptive: the factor the lr is multiplied or divided by outside the KL band
    kl_lr_min: float = 1e-5  # kl-adaptive: the lowest learning rate it may reach
    kl_lr_max: float = 1e-2  # kl-adaptive: the highest learning rate it may reach


@dataclass(frozen=True)
class SAConfig:
    """Simulated-annealing learning-rate plateau schedule (docs/task.md §3).  The cycle and evaluation keys
    (cycle_steps … eval_seed) set every schedule's evaluation cadence; the rest act under lr.schedule = sa."""

    cycle_steps: int = 0  # env steps per cycle; 0 = total_steps / num_cycles
    num_cycles: int = 200  # SA cycles over the run when cycle_steps = 0
    metric: str = "return"  # cycle metric M: "return" (mean return with the p = 1 reward weights) | "success" (rate)
    eval_episodes: int = 128  # episodes of the fixed evaluation set that measures M each cycle
    eval_seed: int = 12345  # seed of that evaluation set (the same episodes every cycle)
    decay: float = 0.98  # lr ← max(lr·decay, lr_min) at a plateau (SA starts at ppo.learning_rate)
    lr_min: float = 1e-6  # the SA schedule's learning-rate floor
    # A cycle within this of the accepted metric is accepted outright.  Calibrated: on the fixed
    # 128-episode evaluation set the metric moves by ≈ 0.10 (std) from cycle to cycle of a run that is
    # still improving, so 0.05 rejected ≈ 40 % of cycles on noise; 0.2 (2 σ) rejects ≈ 5 %.
    tol: float = 0.2
    min_delta: float = 0.02  # a gain over the best metric by more than this resets the stall counter
    patience: int = 5  # stalled cycles before the learning rate decays
    max_rollbacks: int = 3  # rejections in a row before the learning rate decays
    t0: float = 0.1  # temperature scale T_0 of the Metropolis acceptance of a worse cycle
    kappa: float = 1.0  # κ: T = T_0·exp(κ·(H − H_0)/n_actions), H the policy entropy
    # Ablation switches (docs/design.md, "SA ablation switches"); all true is docs/task.md §3.
    metropolis: bool = True  # accept a worse cycle with probability exp(−ΔE/T); false: every worse cycle is rejected
    rollback: bool = True  # a rejected cycle restores the snapshot; false: its updates are kept (still counted a reject)
    plateau_decay: bool = True  # rule 3 decays the lr (stall or rejections in a row); false: only a non-finite step decays it
    entropy_temperature: bool = True  # T follows the policy entropy (κ); false: T = T_0 throughout


@dataclass(frozen=True)
class TrainConfig:
    total_steps: int = 20_000_000  # env steps of the whole run
    seed: int = 0  # seed of the parameters, the envs and the sampling
    # Training scene mix (the evaluation mix is env.sampling's, docs/task.md §1: 0.2 and no blocking placement).
    # −1 = the same as env.sampling.obstacle_prob / blocking_prob.
    obstacle_prob: float = -1.0
    blocking_prob: float = -1.0  # fraction of training obstacle scenes with the blocking placement; −1 = env.sampling's
    log_every: int = 1  # iterations between JSONL rows
    checkpoint_every_cycles: int = 10  # SA cycles between checkpoints
    metrics_window: int = 256  # finished episodes in the training-episode window
    # Run folder whose final checkpoint's policy, value network and observation normaliser start this run (train
    # --init-from; e.g. a kinematic run fine-tuned in dynamic mode); optimizer and SA schedule start fresh.  "" = none
    init_from: str = ""


@dataclass(frozen=True)
class Config:
    env: EnvConfig = field(default_factory=EnvConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    lr: LRConfig = field(default_factory=LRConfig)
    sa: SAConfig = field(default_factory=SAConfig)
    train: TrainConfig = field(default_factory=TrainConfig)


class ConfigError(ValueError):
    """A preset, key or value that the config does not accept."""


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


def _cpu_quick() -> Config:
    base = _robot_grade(_obstacle_aware(_upright_approach(Config())))
    return dataclasses.replace(
        base,
        ppo=dataclasses.replace(
            base.ppo,
            num_envs=256,
            unroll_length=16,
            num_minibatches=4,
            num_epochs=4,
            entropy_coef=1e-3,
            network=NetworkConfig(policy_hidden=(32, 32, 32, 32), value_hidden=(64, 64, 64)),
        ),
        sa=dataclasses.replace(base.sa, eval_episodes=128),
        train=dataclasses.replace(base.train, total_steps=10_000_000),
    )


def _gpu() -> Config:
    # Physics backend: none runs, the preset trains in kinematic mode (env.control.impl stays "jax"); a
    # The preset trains in the lagged mode (no physics; env.control.impl stays "jax"); a dynamic-mode GPU run
    # adds env.control.mode=dynamic and env.control.impl=warp (pip install "sagrasp_jax[warp]").
    base = _robot_grade(_obstacle_aware(_upright_approach(Config())))
    return dataclasses.replace(
        base,
        ppo=dataclasses.replace(
            base.ppo,
            num_envs=4096,
            unroll_length=16,
            num_minibatches=16,
            num_epochs=4,
            entropy_coef=1e-3,
            network=NetworkConfig(policy_hidden=(128, 128, 128), value_hidden=(256, 256, 256)),
        ),
        sa=dataclasses.replace(base.sa, eval_episodes=1024),
        train=dataclasses.replace(base.train, total_steps=20_000_000),
    )


PRESETS: dict[str, typing.Callable[[], Config]] = {
    "paper": _paper,
    "cpu-quick": _cpu_quick,
    "gpu": _gpu,
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
}


def get_config(preset: str = "cpu-quick") -> Config:
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; valid presets: {', '.join(PRESETS)}")
    return PRESETS[preset]()


def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _parse_value(text: str, annotation: Any, key: str) -> Any:
    origin = typing.get_origin(annotation)
    try:
        if annotation is bool:
            lowered = text.strip().lower()
            if lowered in ("true", "1", "yes"):
                return True
            if lowered in ("false", "0", "no"):
                return False
            raise ValueError("expected true/false")
        if annotation is int:
            value = float(text) if any(c in text for c in ".eE") else int(text)
            if isinstance(value, float):
                if not value.is_integer():
                    raise ValueError("expected an integer")
                value = int(value)
            return value
        if annotation is float:
            value = float(text)
            if not math.isfinite(value):
                raise ValueError("expected a finite number")
            return value
        if annotation is str:
            return text
        if origin is tuple:
            args = typing.get_args(annotation)
            elem = args[0]
            if elem is str and not text.strip().startswith("["):  # a,b,c: bare words
                return tuple(t.strip() for t in text.split(",") if t.strip())
            parsed = json.loads(text if text.strip().startswith("[") else f"[{text}]")
            return tuple(_parse_value(json.dumps(v), elem, key) if not isinstance(v, str) else v for v in parsed)
    except (ValueError, json.JSONDecodeError) as exc:
        raise ConfigError(f"bad value {text!r} for {key} ({annotation}): {exc}") from None
    raise ConfigError(f"key {key} has a type that cannot be set from the command line")


_CHOICES = {
    "env.control.mode": CONTROL_MODES,
    "env.control.impl": ("jax", "warp"),
    "env.reward.rc_mode": ("entry", "per_step"),
    "env.reward.near_miss_mode": ("change", "per_step"),
    "env.task.obs_layout": OBS_LAYOUTS,
    "env.task.obstacle_geometry": ("fine", "cover"),
    "env.sampling.obstacle_kinds": shapes.NAMES,  # a tuple key: each entry
    "sa.metric": ("return", "success"),
    "lr.schedule": LR_SCHEDULES,
    "ppo.network.activation": ("tanh", "relu", "silu", "elu"),
}


SEED_RANGE = (0, 2**32 - 1)  # jax.random.PRNGKey wraps larger seeds silently (2**32 gives seed 0's key)
_BIG = 10**12  # an upper bound for counts that only has to stop overflow and runaway runs

# The sane range of every numeric key (inclusive; a tuple key: each element).  ``validate`` refuses
# a value outside it naming the key, so NaN, inf, a sign slip or a units slip (1e30, 50 for 0.05)
# stops at the command line instead of crashing or silently misbehaving later.  The ranges are
# wide: they catch nonsense, not tuning choices.  A ``>`` prefix on the low end makes it exclusive.
_RANGES: dict[str, tuple[float | str, float]] = {
    "env.control.q_max": (">0", 0.5),
    "env.control.d_slow": (0.0, 1.0),
    "env.control.slow_factor": (">0", 1.0),
    "env.control.d_fine": (0.0, 1.0),
    "env.control.fine_tilt_deg": (0.0, 90.0),
    "env.control.fine_gain": (0.0, 100.0),
    "env.control.fine_damping": (">0", 10.0),
    "env.control.fine_clip": (0.0, 0.5),
    "env.control.q_limit": (">0", math.pi),
    "env.control.control_dt": (">0", 1.0),
    "env.control.physics_dt": (">0", 0.1),
    "env.control.substeps": (1, 1000),
    "env.control.lag_gain": (">0", 1.0),
    "env.control.lag_momentum": (0.0, 0.9),
    "env.reward.ratio": (0.0, 1e3),
    "env.reward.rc": (-1e3, 1e3),
    "env.reward.d_grab": (0.0, 1.0),
    "env.reward.success_reward": (-1e3, 1e3),
    "env.reward.failure_reward": (-1e3, 1e3),
    "env.reward.collision_penalty": (-1e3, 1e3),
    "env.reward.near_miss_distance": (0.0, 1.0),
    "env.reward.near_miss_scale": (-1e3, 1e3),
    "env.reward.clean_success_bonus": (-1e3, 1e3),
    "env.reward.f_d0": (-1e3, 1e3),
    "env.reward.f_d1": (-1e3, 1e3),
    "env.reward.f_s0": (-1e3, 1e3),
    "env.reward.f_s1": (-1e3, 1e3),
    "env.reward.f_o": (-1e3, 1e3),
    "env.reward.tilt_weight": (0.0, 10.0),
    "env.reward.tilt_free_deg": (0.0, 90.0),
    "env.reward.tilt_near": (0.0, 10.0),
    "env.task.home_q": (-math.pi, math.pi),
    "env.task.start_noise": (0.0, 1.0),
    "env.task.obs_noise_std": (0.0, 1.0),
    "env.task.obs_noise_growth": (0.0, 100.0),
    "env.task.max_steps": (1, 100_000),
    "env.task.success_xy": (">0", 0.5),
    "env.task.success_dz_min": (-0.5, 0.5),
    "env.task.success_dz_max": (-0.5, 0.5),
    "env.task.success_tilt_deg": (0.0, 180.0),
    "env.task.obstacle_dist_clip": (">0", 10.0),
    "env.task.no_obstacle_pos": (-100.0, 100.0),
    "env.sampling.target_size": (">0", 0.5),
    "env.sampling.target_x": (-2.0, 2.0),
    "env.sampling.target_y": (-2.0, 2.0),
    "env.sampling.target_yaw": (-math.pi, math.pi),
    "env.sampling.target_radius": (0.0, 2.0),
    "env.sampling.target_candidates": (1, 4096),
    "env.sampling.obstacle_prob": (0.0, 1.0),
    "env.sampling.max_obstacles": (0, 16),
    "env.sampling.sphere_radius": (">0", 0.5),
    "env.sampling.sphere_z": (0.0, 2.0),
    "env.sampling.cylinder_radius": (">0", 0.5),
    "env.sampling.cylinder_height": (">0", 2.0),
    "env.sampling.box_half": (">0", 0.5),
    "env.sampling.capsule_radius": (">0", 0.5),
    "env.sampling.capsule_length": (">0", 2.0),
    "env.sampling.obstacle_disc_radius": (0.0, 2.0),
    "env.sampling.home_xy": (-2.0, 2.0),
    "env.sampling.target_clearance": (0.0, 1.0),
    "env.sampling.robot_clearance": (0.0, 1.0),
    "env.sampling.obstacle_candidates": (1, 4096),
    "env.sampling.scene_redraws": (0, 1000),
    "env.sampling.blocking_prob": (0.0, 1.0),
    "env.sampling.blocking_margin": (">0", 1.0),
    "env.task.obs_vector_scale": (">0", 10.0),
    "env.task.obs_vector_clip": (">0", 1e3),
    "env.task.obs_closeness_range": (">0", 10.0),
    "env.task.obs_pending_clip": (">0", 1e3),
    "ppo.num_envs": (1, 2**24),
    "ppo.unroll_length": (1, 100_000),
    "ppo.num_minibatches": (1, 2**24),
    "ppo.num_epochs": (1, 10_000),
    "ppo.clip_eps": (">0", 10.0),
    "ppo.gamma": (">0", 1.0),
    "ppo.gae_lambda": (0.0, 1.0),
    "ppo.entropy_coef": (0.0, 100.0),
    "ppo.value_coef": (0.0, 1e3),
    "ppo.max_grad_norm": (">0", 1e6),
    "ppo.learning_rate": (">0", 1.0),
    "ppo.obs_std_floor": (">0", 1e3),
    "ppo.obs_clip": (">0", 1e6),
    "ppo.network.policy_hidden": (1, 65_536),
    "ppo.network.value_hidden": (1, 65_536),
    "lr.final": (0.0, 1.0),
    "lr.desired_kl": (">0", 100.0),
    "lr.kl_factor": (">1", 100.0),
    "lr.kl_lr_min": (">0", 1.0),
    "lr.kl_lr_max": (">0", 1.0),
    "sa.cycle_steps": (0, _BIG),
    "sa.num_cycles": (1, 10**6),
    "sa.eval_episodes": (1, 100_000),  # evaluated in one batch
    "sa.eval_seed": SEED_RANGE,
    "sa.decay": (">0", 1.0),
    "sa.lr_min": (">0", 1.0),
    "sa.tol": (0.0, 1e6),
    "sa.min_delta": (0.0, 1e6),
    "sa.patience": (1, 10**6),
    "sa.max_rollbacks": (1, 10**6),
    "sa.t0": (">0", 1e6),
    "sa.kappa": (0.0, 1e6),
    "train.total_steps": (1, _BIG),
    "train.seed": SEED_RANGE,
    "train.log_every": (1, 10**9),
    "train.checkpoint_every_cycles": (1, 10**9),
    "train.metrics_window": (1, 10**7),
    "train.obstacle_prob": (-1.0, 1.0),  # −1 = env.sampling's; validate also refuses (−1, 0)
    "train.blocking_prob": (-1.0, 1.0),
    "env.randomize.servo_gain": (0.0, 0.9),
    "env.randomize.latency": (0.0, 3.0),
    "env.randomize.joint_offset": (0.0, 0.2),
    "env.randomize.joint_noise": (0.0, 0.2),
    "env.randomize.target_error": (0.0, 0.05),
}


def _num(v: float) -> str:
    return str(v) if isinstance(v, int) else f"{v:g}"


def _range_text(lo: float | str, hi: float) -> str:
    return f"({lo[1:]}, {_num(hi)}]" if isinstance(lo, str) else f"[{_num(lo)}, {_num(hi)}]"


def _in_range(value: float, lo: float | str, hi: float) -> bool:
    low = float(lo[1:]) if isinstance(lo, str) else lo
    return math.isfinite(value) and (value > low if isinstance(lo, str) else value >= low) and value <= hi


def check_range(name: str, value: Any, lo: float | str, hi: float) -> Any:
    """Refuse ``value`` (a command-line option or a config key) outside ``[lo, hi]`` (``">x"``: an
    exclusive low end), NaN, inf or not a number, with a ConfigError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not _in_range(value, lo, hi):
        raise ConfigError(f"{name}={value!r} is outside the allowed range {_range_text(lo, hi)}")
    return value


def _type_problem(value: Any, annotation: Any) -> str | None:
    """What is wrong with ``value`` for a field annotated ``annotation`` (None: nothing)."""
    if annotation is bool:
        return None if isinstance(value, bool) else "expected true/false"
    if annotation is int:
        return None if isinstance(value, int) and not isinstance(value, bool) else "expected an integer"
    if annotation is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        return None if ok else "expected a finite number"
    if annotation is str:
        return None if isinstance(value, str) else "expected a string"
    if typing.get_origin(annotation) is tuple:
        args = typing.get_args(annotation)
        if not isinstance(value, tuple):
            return "expected a list"
        variadic = len(args) == 2 and args[1] is Ellipsis
        if not variadic and len(value) != len(args):
            return f"expected {len(args)} values, got {len(value)}"
        for v, a in zip(value, [args[0]] * len(value) if variadic else args):
            problem = _type_problem(v, a)
            if problem:
                return f"{problem} in each entry"
        return None
    return None


def _check_types(obj: Any, prefix: str = "") -> None:
    """Every field holds its declared type (a hand-edited config.json can hold anything)."""
    hints = _field_types(type(obj))
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(hints[f.name]):
            if not dataclasses.is_dataclass(value):
                raise ConfigError(f"invalid value for {prefix}{f.name}: {value!r} (expected a section)")
            _check_types(value, f"{prefix}{f.name}.")
            continue
        problem = _type_problem(value, hints[f.name])
        if problem:
            raise ConfigError(f"invalid value for {prefix}{f.name}: {value!r} ({problem})")


def _check_ranges(cfg: "Config") -> None:
    for key, (lo, hi) in _RANGES.items():
        value = get_key(cfg, key)
        for v in value if isinstance(value, tuple) else (value,):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not _in_range(v, lo, hi):
                each = "each entry " if isinstance(value, tuple) else ""
                raise ConfigError(f"invalid value for {key}: {value!r} ({each}must be in {_range_text(lo, hi)})")


@functools.lru_cache(maxsize=1)
def _declared_comments() -> dict[str, dict[str, str]]:
    """{class name: {field: description}} read from this file: the comment on a field's declaration
    (its line or, for a declaration over several lines, any of them), else the block of comment lines
    right above it.  One place documents a key: where it is declared."""
    try:
        with open(__file__, encoding="utf-8") as f:
            source = f.read()
    except OSError:  # pragma: no cover - an install without sources: no descriptions
        return {}
    comments: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = tok.string.lstrip("#").strip()
    lines = source.splitlines()
    out: dict[str, dict[str, str]] = {}
    for node in ast.parse(source).body:
        if not isinstance(node, ast.ClassDef):
            continue
        fields = out.setdefault(node.name, {})
        for item in node.body:
            if not (isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name)):
                continue
            own = [comments[n] for n in range(item.lineno, (item.end_lineno or item.lineno) + 1) if n in comments]
            above, n = [], item.lineno - 1
            while n in comments and lines[n - 1].lstrip().startswith("#"):
                above.insert(0, comments[n])
                n -= 1
            fields[item.target.id] = " ".join(own or above)
    return out


def key_descriptions(cfg: Config | None = None) -> dict[str, str]:
    """Every dotted key's description, from the comments where its field is declared ('' if none)."""
    docs = _declared_comments()
    out: dict[str, str] = {}

    def walk(obj: Any, prefix: str) -> None:
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            if dataclasses.is_dataclass(value):
                walk(value, f"{prefix}{f.name}.")
            else:
                out[f"{prefix}{f.name}"] = docs.get(type(obj).__name__, {}).get(f.name, "")

    walk(cfg or Config(), "")
    return out


def _shown(value: Any) -> str:
    if isinstance(value, tuple):
        return ",".join(_shown(v) for v in value)
    return _num(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else str(value).lower() \
        if isinstance(value, bool) else str(value)


def describe_keys(preset: str = "cpu-quick") -> str:
    """``--list-keys``: every key with its type, its value in ``preset``, its valid values (range or
    choices), the other presets' values where they differ, and its description."""
    cfg = get_config(preset)
    others = {name: get_config(name) for name in PRESETS if name != preset}
    lines = [f"config keys (values of preset {preset!r}; set with --set KEY=VALUE, a list as a,b,c):", ""]
    for key, text in key_descriptions(cfg).items():
        *path, leaf = key.split(".")
        section: Any = cfg
        for name in path:
            section = getattr(section, name)
        annotation = _field_types(type(section))[leaf]
        kind = getattr(annotation, "__name__", None) if typing.get_origin(annotation) is not tuple else \
            "list of " + getattr(typing.get_args(annotation)[0], "__name__", "value")
        value = get_key(cfg, key)
        valid = ""
        if key in _RANGES:
            valid = ("each in " if isinstance(value, tuple) else "in ") + _range_text(*_RANGES[key])
        elif key in _CHOICES:
            valid = ("each one of " if isinstance(value, tuple) else "one of ") + ", ".join(_CHOICES[key])
        differ = [f"{name} {_shown(get_key(c, key))}" for name, c in others.items() if get_key(c, key) != value]
        head = f"{key} = {_shown(value)}  ({kind}{'; ' + valid if valid else ''})"
        lines.append(head + (f"  [{'; '.join(differ)}]" if differ else ""))
        lines += textwrap.wrap(text, 100, initial_indent="    ", subsequent_indent="    ") or ["    (no description)"]
    return "\n".join(lines)


def valid_keys(cfg: Config | None = None) -> list[str]:
    """All dotted keys that ``apply_overrides`` accepts."""
    cfg = cfg or Config()
    keys: list[str] = []

    def walk(obj: Any, prefix: str) -> None:
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            if dataclasses.is_dataclass(value):
                walk(value, f"{prefix}{f.name}.")
            else:
                keys.append(f"{prefix}{f.name}")

    walk(cfg, "")
    return keys


def _set(obj: Any, path: list[str], text: str, full_key: str) -> Any:
    names = {f.name for f in dataclasses.fields(obj)}
    head = path[0]
    if full_key in REMOVED_KEYS:
        raise ConfigError(f"config key {full_key!r} was replaced by {REMOVED_KEYS[full_key]}")
    if head not in names:
        raise ConfigError(unknown_key_message(full_key))
    current = getattr(obj, head)
    if len(path) == 1:
        if dataclasses.is_dataclass(current):
            raise ConfigError(f"{full_key!r} is a section, not a value; set one of its keys")
        value = _parse_value(text, _field_types(type(obj))[head], full_key)
    else:
        if not dataclasses.is_dataclass(current):
            raise ConfigError(unknown_key_message(full_key))
        value = _set(current, path[1:], text, full_key)
    return dataclasses.replace(obj, **{head: value})


def unknown_key_message(key: str) -> str:
    """An unknown key names the nearest valid keys (difflib), not all of them."""
    import difflib

    keys = valid_keys()
    leaf = key.rsplit(".", 1)[-1]
    near = difflib.get_close_matches(key, keys, n=4, cutoff=0.6)
    near += [k for k in keys if k not in near and difflib.SequenceMatcher(None, leaf, k.rsplit(".", 1)[-1]).ratio() >= 0.8]
    hint = f"; did you mean {', '.join(near[:5])}?" if near else ""
    return f"unknown config key {key!r}{hint} (--list-keys lists every key)"


CONFIG_FILE_SUFFIXES = (".json", ".yaml", ".yml")


def _flatten(data: Any, prefix: str, path: str) -> list[tuple[str, Any]]:
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: {prefix.rstrip('.') or 'the file'} must be a mapping of config keys, got {data!r}")
    out: list[tuple[str, Any]] = []
    for name, value in data.items():
        key = f"{prefix}{name}"
        out += _flatten(value, key + ".", path) if isinstance(value, dict) else [(key, value)]
    return out


def _override_text(key: str, value: Any, path: str) -> str:
    """A file's value as the ``--set`` text that means it (so both are checked alike)."""
    if value is None:
        raise ConfigError(f"{path}: {key} has no value (null)")
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return json.dumps(list(value))
    return str(value)


def file_overrides(path: str) -> list[str]:
    """``--config FILE``: the file's keys as ``key=value`` overrides, applied over the chosen preset
    like ``--set`` (keys it leaves out keep the preset's values).  JSON; YAML (``.yaml``/``.yml``)
    when PyYAML is installed.  Sections may nest (``{"ppo": {"num_envs": 512}}``) or be dotted
    (``{"ppo.num_envs": 512}``).  A file that cannot be read or parsed raises ConfigError."""
    if not path.lower().endswith(CONFIG_FILE_SUFFIXES):
        raise ConfigError(f"--config {path}: expected a {', '.join(CONFIG_FILE_SUFFIXES)} file")
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"--config {path}: cannot read it ({exc})") from None
    if path.lower().endswith(".json"):
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"--config {path}: not valid JSON ({exc})") from None
    else:
        try:
            import yaml
        except ImportError:
            raise ConfigError(f"--config {path}: reading YAML needs PyYAML (pip install pyyaml), or use JSON") from None
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ConfigError(f"--config {path}: not valid YAML ({exc})") from None
    return [f"{key}={_override_text(key, value, path)}" for key, value in _flatten(data, "", f"--config {path}")]


def apply_overrides(cfg: Config, overrides: list[str]) -> Config:
    """Apply ``key=value`` strings, e.g. ``ppo.num_envs=512``; validates the result."""
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} is not of the form key=value")
        key, text = item.split("=", 1)
        cfg = _set(cfg, key.strip().split("."), text.strip(), key.strip())
    validate(cfg)
    return cfg


def validate(cfg: Config) -> None:
    """Reject values that would make training meaningless or crash later."""
    _check_types(cfg)
    _check_ranges(cfg)
    for key, choices in _CHOICES.items():
        value = get_key(cfg, key)
        for v in value if isinstance(value, tuple) else (value,):
            if v not in choices:
                entry = f" (entry {v!r})" if isinstance(value, tuple) else ""
                raise ConfigError(f"{key}={value!r}{entry} is not one of {', '.join(choices)}")
    # What the ranges above cannot say: rules across keys and lengths (single values are in _RANGES)
    kinds = cfg.env.sampling.obstacle_kinds
    checks = [
        ("sa.lr_min", cfg.lr.schedule != "sa" or cfg.sa.lr_min <= cfg.ppo.learning_rate),  # SA starts above its floor
        ("lr.kl_lr_min", cfg.lr.kl_lr_min <= cfg.lr.kl_lr_max),
        ("env.task.home_q", len(cfg.env.task.home_q) == 6),
        ("env.sampling.max_obstacles", cfg.env.sampling.max_obstacles == 2),  # the MJCF has two slots
        ("env.sampling.obstacle_kinds", 0 < len(set(kinds)) == len(kinds)),  # some, none twice
        ("env.sampling.obstacle_candidates", cfg.env.sampling.obstacle_candidates >= len(kinds)),  # ≥ one of each kind
        ("train.obstacle_prob", cfg.train.obstacle_prob == -1 or 0 <= cfg.train.obstacle_prob <= 1),
        ("train.blocking_prob", cfg.train.blocking_prob == -1 or 0 <= cfg.train.blocking_prob <= 1),
    ]
    for key, ok in checks:
        if not ok:
            raise ConfigError(f"invalid value for {key}: {get_key(cfg, key)!r}")
    if cfg.env.control.impl != "jax" and cfg.env.control.mode != "dynamic":  # a physics backend: servo physics only
        raise ConfigError(f"env.control.impl={cfg.env.control.impl!r} needs env.control.mode=dynamic (no physics runs otherwise)")
    for key in ("env.randomize.servo_gain", "env.randomize.latency"):  # servos: simulated or modelled
        if get_key(cfg, key) != 0 and cfg.env.control.mode == "kinematic":
            raise ConfigError(f"{key}={get_key(cfg, key)!r} needs env.control.mode=dynamic or lagged "
                              "(the kinematic mode has no servos)")
    for key in ("env.control.lag_gain", "env.control.lag_momentum"):
        if len(get_key(cfg, key)) != 6:
            raise ConfigError(f"invalid value for {key}: {get_key(cfg, key)!r} (one value per arm joint: 6)")
    for key in ("ppo.network.policy_hidden", "ppo.network.value_hidden"):  # `--set KEY=` leaves no layer
        if not get_key(cfg, key):
            raise ConfigError(f"{key} is empty: give at least one hidden layer width (e.g. {key}=64,64); "
                              "no hidden layer would make the network linear")
    if (cfg.ppo.num_envs * cfg.ppo.unroll_length) % cfg.ppo.num_minibatches:
        raise ConfigError(f"ppo.num_minibatches={cfg.ppo.num_minibatches} must divide ppo.num_envs × ppo.unroll_length "
                          f"= {cfg.ppo.num_envs} × {cfg.ppo.unroll_length}")


def get_key(cfg: Config, key: str) -> Any:
    obj: Any = cfg
    for name in key.split("."):
        obj = getattr(obj, name)
    return obj


def config_to_dict(cfg: Any) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


def _from_dict(cls: type, data: dict[str, Any], prefix: str) -> Any:
    hints = _field_types(cls)
    kwargs = {}
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - known
    if unknown:
        raise ConfigError(f"unknown config keys in saved config: {', '.join(prefix + u for u in sorted(unknown))}")
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        value = data[f.name]
        hint = hints[f.name]
        if dataclasses.is_dataclass(hint):
            if not isinstance(value, dict):
                raise ConfigError(f"saved config: {prefix}{f.name} must be a section (a JSON object), got {value!r}")
            kwargs[f.name] = _from_dict(hint, value, f"{prefix}{f.name}.")
        elif typing.get_origin(hint) is tuple:
            if not isinstance(value, (list, tuple)):
                raise ConfigError(f"saved config: {prefix}{f.name} must be a list, got {value!r}")
            kwargs[f.name] = tuple(value)
        else:
            kwargs[f.name] = value
    return cls(**kwargs)


# Keys added after the first release, with the value that reproduces what a saved config without
# them meant (run folders, checkpoints and policy files of version 0.1 keep their behaviour).
LEGACY_VALUES: dict[str, Any] = {
    "env.reward.near_miss_mode": "per_step",
    "env.task.obs_layout": "paper",
    "env.task.obstacle_geometry": "cover",
}


# Keys removed since the first release, with what replaced them (``apply_overrides`` names the new key;
# ``upgrade_config_dict`` turns a saved config that has them into the same training).
REMOVED_KEYS: dict[str, str] = {
    "sa.enabled": "lr.schedule (sa or constant; or --algo / --lr-schedule)",
    "sa.lr0": "ppo.learning_rate (the initial learning rate of every lr schedule)",
}


def _upgrade_lr_keys(out: dict[str, Any]) -> None:
    """``sa.enabled`` / ``sa.lr0`` (before lr.schedule): SA ran from sa.lr0, plain PPO at ppo.learning_rate."""
    sa = out.get("sa")
    if not isinstance(sa, dict) or not ({"enabled", "lr0"} & set(sa)):
        return
    enabled = sa.pop("enabled", True)
    lr0 = sa.pop("lr0", None)
    if not isinstance(enabled, bool):
        raise ConfigError(f"invalid value for sa.enabled in a saved config: {enabled!r} (expected true/false)")
    lr = out.setdefault("lr", {})
    if isinstance(lr, dict):
        lr.setdefault("schedule", "sa" if enabled else "constant")
    if enabled and lr0 is not None and isinstance(out.setdefault("ppo", {}), dict):
        out["ppo"]["learning_rate"] = lr0


def upgrade_config_dict(data: dict[str, Any]) -> dict[str, Any]:
    """A saved config dict with every key added since it was written set to its legacy value, and every
    removed key replaced by what now means the same (``REMOVED_KEYS``)."""
    out = json.loads(json.dumps(data))
    if isinstance(out, dict):
        _upgrade_lr_keys(out)
    for key, value in LEGACY_VALUES.items():
        *sections, name = key.split(".")
        node = out
        for section in sections:
            node = node.get(section) if isinstance(node, dict) else None
        if isinstance(node, dict) and name not in node:
            node[name] = value
    return out


def config_from_dict(data: dict[str, Any]) -> Config:
    """Build and validate a Config from its dict; keys a saved config lacks get their legacy value."""
    if not isinstance(data, dict):
        raise ConfigError(f"saved config must be a JSON object, got {type(data).__name__}")
    cfg = _from_dict(Config, upgrade_config_dict(data), "")
    validate(cfg)
    return cfg


BLOCKING_SCENE_REDRAWS = 11  # whole-scene re-draws when blocking scenes are wanted (their fallbacks stay < 2 %)


def blocking_sampling(s: SamplingConfig, obstacle_prob: float, blocking_prob: float) -> SamplingConfig:
    """``s`` with another obstacle / blocking mix; blocking placements are rejected more often, so
    they get more whole-scene re-draws (a fallback would turn an obstacle scene into a free one)."""
    redraws = max(s.scene_redraws, BLOCKING_SCENE_REDRAWS) if blocking_prob > 0 else s.scene_redraws
    return dataclasses.replace(s, obstacle_prob=obstacle_prob, blocking_prob=blocking_prob, scene_redraws=redraws)


def training_env_config(cfg: Config) -> EnvConfig:
    """The env the trainer samples episodes from: env.sampling with the training mix of ``train``."""
    s = cfg.env.sampling
    obstacle_prob = s.obstacle_prob if cfg.train.obstacle_prob < 0 else cfg.train.obstacle_prob
    blocking_prob = s.blocking_prob if cfg.train.blocking_prob < 0 else cfg.train.blocking_prob
    return dataclasses.replace(cfg.env, sampling=blocking_sampling(s, obstacle_prob, blocking_prob))


def randomization_enabled(env: EnvConfig) -> bool:
    """Whether any ``env.randomize`` knob is on (then each episode draws its values at reset)."""
    return any(getattr(env.randomize, f.name) != 0 for f in dataclasses.fields(env.randomize))


def config_hash(cfg: Config) -> str:
    """Short stable hash of the env part: what a policy was trained on."""
    return env_dict_hash(config_to_dict(cfg.env))


def env_dict_hash(env: dict[str, Any]) -> str:
    """``config_hash`` of a saved config's env dict as written (a policy file's integrity check)."""
    blob = json.dumps(env, sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:12]
