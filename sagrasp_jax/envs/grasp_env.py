"""The grasping MDP of docs/task.md §2 as a pure-JAX environment (MuJoCo-MJX physics).

``GraspEnv(cfg).reset(rng)`` / ``.step(state, action)`` work on one env; ``jax.vmap``
them for batches (``auto_reset.AutoReset`` does, with fresh-sample auto-reset).  Its states are
``brax.envs.base.State`` but it is not a brax env: brax's wrappers (``training.wrap``) need
``brax_adapter.BraxGraspEnv`` (``envs.load("grasp-kinematic")``), which keeps their conventions.  The
control step, reward, sampling and collision maths come from the backend-agnostic
modules that the PyBullet reference env and the deployment runtime share.

Modes (``cfg.control.mode``): ``kinematic`` sets qpos = q_target (what the AUBO
controller's precise joint tracking amounts to) and needs no physics; ``dynamic``
runs ``mjx.step`` with position servos tracking q_target under gravity
(``substeps`` × ``physics_dt`` per 0.05 s control period, contacts off — collisions are
computed analytically in every mode); ``lagged`` needs no physics either: the joints follow
the command through a per-step servo model fitted to the dynamic mode's servos
(``control.servo_model_step``), so that a policy can train for servo lag and command latency at the
kinematic mode's speed.  Command latency (``env.randomize.latency``, in control steps) is a
queue of the last commands in ``info["commands"]`` (newest first) in both servo modes.
"""

from __future__ import annotations

import functools
import os
from typing import Any, NamedTuple

import sagrasp_jax  # noqa: F401  (XLA flags before jax)
import jax
import jax.numpy as jnp
from brax.envs.base import State

from sagrasp_jax.base import assets
from sagrasp_jax.task import collision
from sagrasp_jax.task import control
from sagrasp_jax.task import episode
from sagrasp_jax.task import observation
from sagrasp_jax.task import reward
from sagrasp_jax.task import robot
from sagrasp_jax.task import sampling
from sagrasp_jax.task import config as config_mod
from sagrasp_jax.task.config import EnvConfig

MJCF_SCENE = assets.MJCF_SCENE  # the default robot's; an env's own: GraspEnv.mjcf_scene
MJCF_ROBOT = assets.MJCF_ROBOT  # the default robot's dynamic-mode model; an env's own: GraspEnv.mjcf_robot

OBS_SIZE = observation.OBS_SIZE  # the paper layout's 17; an env's own size is ``GraspEnv.observation_size``
POSE_METRICS = ("distance", "tilt", "slowed", "finetuned")  # state.metrics besides the reward terms (step_metric_keys)


def step_metric_keys() -> tuple[str, ...]:
    """``state.metrics`` of a step: each registered reward term's value (``reward.term_keys``) and
    ``POSE_METRICS`` (distance to the target, tilt, the slow-down and fine-tune flags)."""
    return reward.term_keys() + POSE_METRICS


class ServoState(NamedTuple):
    """The dynamic mode's physics state between control steps (JAX backend): all that persists.

    Everything else in MJX's ``Data`` is recomputed from the joint positions and velocities at every
    substep (no activations, mocap bodies, contacts or constraint warm-start in the lean model), so an env
    state carries these two arrays instead of the ~90 of a ``Data``: the auto-reset's per-env selects and
    the pending starts' refills then touch two leaves, not ninety.  ``.qpos`` / ``.qvel`` read as on a Data."""

    qpos: jax.Array
    qvel: jax.Array


def servo_physics_step(model: Any, data: Any) -> Any:
    """``mjx.step`` for the dynamic mode's lean model (JAX backend), without the stages it has nothing for.

    The model has no geoms, tendons, cameras, sensors, contacts or constraints, and integrates with
    implicitfast, which solves its own (M − h·∂f/∂v) system: so this is ``mjx.step``'s ``forward`` minus
    camlight, tendons, collision, the constraint rows, sensors and the factorisation / solve of M that
    ``fwd_acceleration`` makes for ``qacc_smooth`` (which implicitfast overwrites), then its ``implicit``.
    Every stage left is MJX's own function, in MJX's order, so the state is ``mjx.step``'s bit for bit
    (``tests/envs/test_dynamic.py``; ``qacc``, mjx.step's unused ``qacc_smooth``, is left as it was) at ≈ 7 %
    less work.  mujoco-mjx is pinned to the version this was read from (3.17.0: its ``_src`` modules are
    not a public API)."""
    from mujoco.mjx._src import derivative, passive, smooth
    from mujoco.mjx._src import forward as mjx_forward

    d = smooth.kinematics(model, data)
    d = smooth.com_pos(model, d)
    d = smooth.crb(model, d)
    d = smooth.transmission(model, d)
    d = d.tree_replace({"_impl.actuator_velocity": d._impl.actuator_moment @ d.qvel})
    d = smooth.com_vel(model, d)
    d = passive.passive(model, d)
    d = smooth.rne(model, d)
    d = mjx_forward.fwd_actuation(model, d)
    qfrc_smooth = d.qfrc_passive - d.qfrc_bias + d.qfrc_actuator + d.qfrc_applied
    d = d.replace(qfrc_smooth=qfrc_smooth)
    qm = d._impl.M - model.opt.timestep * derivative.deriv_smooth_vel(model, d)
    factor, _ = jax.scipy.linalg.cho_factor(qm)
    qacc = jax.scipy.linalg.cho_solve((factor, False), qfrc_smooth)
    return mjx_forward._advance(model, d, d.act_dot, qacc)


class GraspEnv:
    """A registered arm (``env.robot``: the AUBO-i5 + EG2 gripper by default) reaching a cuboid among random
    obstacles (docs/task.md §1-§2)."""

    def __init__(self, cfg: EnvConfig, privileged: bool = False):
        config_mod.check_fields(cfg, "env.")  # each key's declared type, range and choices (an EnvConfig built in code)
        self.cfg = cfg
        self.obs_layout = observation.layout_of(cfg)
        self.observation_size = len(self.obs_layout)
        # entries the trainer's running normaliser leaves at mean 0, std 1 (hand-scaled)
        self.hand_scaled_mask = observation.hand_scaled_mask(self.obs_layout)
        # privileged critic inputs in info["privileged"] (ppo.privileged_critic); the policy never sees them
        self.privileged = privileged
        self.privileged_size = len(observation.privileged_layout(cfg)) if privileged else 0
        self.robot = robot.load_robot(cfg.robot)
        self.action_size = self.robot.dof  # one joint-target increment per arm joint
        self.mjcf_scene = assets.path("mjcf", self.robot.spec.mjcf_scene)
        self.mjcf_robot = assets.path("mjcf", self.robot.spec.mjcf_robot)
        self.n_uniforms = sampling.uniforms_needed(cfg.sampling, self.robot.dof)
        self._mjx_model = None
        self.randomized = config_mod.randomization_enabled(cfg)  # env.randomize: per-episode draws in info["randomize"]
        self.queue_size = control.latency_queue_size(cfg.randomize.latency)  # commands kept in info["commands"] (0: no latency, no queue)
        self.lagged = cfg.control.mode == "lagged"  # servo model state in info["servo"]
        if cfg.control.mode == "dynamic":
            self._mjx_model = self._load_mjx_model()

    # -- physics ---------------------------------------------------------------------------
    def _load_mjx_model(self) -> Any:
        """The dynamic mode's model: the robot alone, lean (docs/parity.md, "Dynamic mode").

        The cell is static and contacts are off, so it adds cost and nothing else; the geoms and sites
        only matter to contacts and rendering (inertias are explicit); the fingers, held open during
        episodes, are welded open (their servo held them rigid) and every joint-less body is fused into
        its parent.  No constraints either: collisions are analytic and the servo targets are clipped
        to the joint limits, so no joint-limit solver runs.  What is left is the arm's joints, their position
        servos (with armature, damping and actuator gravity compensation) and implicitfast."""
        import mujoco
        from mujoco import mjx

        spec = mujoco.MjSpec.from_file(os.path.normpath(self.mjcf_robot))
        for geom in list(spec.geoms):
            spec.delete(geom)
        for site in list(spec.sites):
            spec.delete(site)
        fingers = self.robot.spec.finger_joints
        finger_joints = [spec.joint(name) for name in fingers]
        for body in spec.bodies:
            for joint in body.joints:
                if joint.name in fingers:
                    body.pos = [p + self.robot.finger_open * a for p, a in zip(body.pos, joint.axis)]
        for act in list(spec.actuators):
            if act.target in fingers:
                spec.delete(act)
        for joint in finger_joints:
            spec.delete(joint)
        spec.compiler.fusestatic = True
        model = spec.compile()
        model.opt.timestep = self.cfg.control.physics_dt
        model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
        dof = self.robot.dof
        if model.nq != dof or model.nu != dof:
            raise RuntimeError(f"{self.mjcf_robot}: expected the {dof}-joint arm after welding the fingers, got nq={model.nq}")
        self._mj_model = model  # Warp's make_data takes the MuJoCo model
        # servo_physics_step's premises (else mjx.step): the JAX backend, implicitfast, nothing but the servos
        self._lean_physics = (self.cfg.control.impl == "jax" and model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
                              and model.ngeom == model.nsite == model.ntendon == model.nsensor == model.ncam == 0
                              and model.neq == model.nlight == model.nflex == model.na == model.nmocap == 0)
        self._servo_kp = jnp.asarray(model.actuator_gainprm[:, 0])  # for the servo-gain randomisation
        self._servo_kv = jnp.asarray(-model.actuator_biasprm[:, 2])
        return mjx.put_model(model, impl=self.cfg.control.impl)

    def _initial_pipeline(self, q0: jax.Array) -> Any:
        if self._mjx_model is None:
            return None
        from mujoco import mjx

        if self._lean_physics:
            dtype = self._mjx_model.qpos0.dtype
            return ServoState(qpos=q0.astype(dtype), qvel=jnp.zeros(q0.shape, dtype))
        impl = self.cfg.control.impl
        data = mjx.make_data(self._mj_model if impl == "warp" else self._mjx_model, impl=impl)
        return data.replace(qpos=q0.astype(data.qpos.dtype), ctrl=q0.astype(data.ctrl.dtype))

    def _advance(self, state: State, q_target: jax.Array, queue: jax.Array | None,
                 randomize: dict[str, Any] | None) -> tuple[Any, jax.Array, dict[str, Any]]:
        """Apply the new command ``q_target``: returns the new pipeline state, the measured joints and the
        servo-model info of the lagged mode ({} otherwise).

        ``queue`` (K, dof), newest first, holds the commands up to this one when there is command latency:
        the servos then track the command ``n`` steps old and, for the fraction ``f`` of the control period
        (latency = n + f), the one before it (``control.delayed_commands``).  Randomisation scales the servo gains."""
        info = state.info
        if self.cfg.control.mode == "kinematic":
            return None, q_target, {}
        dtype = q_target.dtype
        current, previous, fraction = q_target, info["q_target"], jnp.zeros((), dtype)
        if queue is not None:
            current, previous, fraction = control.delayed_commands(jnp, queue, randomize["latency"].astype(dtype))
        if self.lagged:
            nominal = jnp.asarray(self.cfg.control.lag_gain, dtype)
            gain = nominal if randomize is None else jnp.clip(nominal * randomize["kp_scale"].astype(dtype), 0.0, 1.0)
            servo = info["servo"]
            weight = control.held_command_weight(jnp, fraction, nominal)  # the fraction's weight: the nominal servo
            command = (1.0 - weight) * current + weight * previous
            q_new = control.servo_model_step(jnp, self.robot, self.cfg.control, servo["q"], servo["q_prev"], command, gain)
            return None, q_new, {"servo": {"q": q_new, "q_prev": servo["q"]}}
        from mujoco import mjx

        model = self._mjx_model
        if randomize is not None:
            kp, kv = self._servo_kp * randomize["kp_scale"], self._servo_kv * randomize["kv_scale"]
            model = model.replace(actuator_gainprm=model.actuator_gainprm.at[:, 0].set(kp.astype(model.actuator_gainprm.dtype)),
                                  actuator_biasprm=model.actuator_biasprm.at[:, 1].set(-kp.astype(model.actuator_biasprm.dtype))
                                  .at[:, 2].set(-kv.astype(model.actuator_biasprm.dtype)))
        delay = jnp.round(fraction * self.cfg.control.substeps).astype(jnp.int32)
        pipeline = state.pipeline_state
        if self._lean_physics:  # the substeps' Data, rebuilt from the only state that persists
            pipeline = mjx.make_data(self._mjx_model).replace(qpos=pipeline.qpos, qvel=pipeline.qvel)
        ctrl_dtype = pipeline.ctrl.dtype
        physics_step = servo_physics_step if self._lean_physics else mjx.step

        def substep(data: Any, i: Any) -> tuple[Any, None]:
            ctrl = jnp.where(i < delay, previous, current)
            return physics_step(model, data.replace(ctrl=ctrl.astype(ctrl_dtype))), None

        pipeline, _ = jax.lax.scan(substep, pipeline, jnp.arange(self.cfg.control.substeps))
        if self._lean_physics:
            pipeline = ServoState(qpos=pipeline.qpos, qvel=pipeline.qvel)
        return pipeline, pipeline.qpos[:self.robot.dof].astype(dtype), {}

    def measured_joints(self, state: State) -> jax.Array:
        """The arm's actual joint positions in ``state`` (no sensor noise), in every mode."""
        if self.cfg.control.mode == "dynamic":
            return state.pipeline_state.qpos[..., :self.robot.dof].astype(state.info["q_target"].dtype)
        if self.lagged:
            return state.info["servo"]["q"]
        return state.info["q_target"]

    # -- domain randomisation (env.randomize; off by default: no draw, no state) --------------
    def _draw_randomization(self, key: jax.Array, dtype: Any) -> dict[str, jax.Array]:
        """One episode's draws: servo-gain factors, command latency, joint-reading offset and noise
        level, detected-target error (each 0 or 1 when its knob is 0)."""
        r = self.cfg.randomize
        k = jax.random.split(key, 6)
        u = lambda kk, shape, half: half * jax.random.uniform(kk, shape, dtype, -1.0, 1.0)  # noqa: E731
        return {
            "kp_scale": 1.0 + u(k[0], (self.robot.dof,), r.servo_gain),
            "kv_scale": 1.0 + u(k[1], (self.robot.dof,), r.servo_gain),
            "latency": r.latency * jax.random.uniform(k[2], (), dtype),  # control steps (delayed_commands)
            "joint_offset": u(k[3], (self.robot.dof,), r.joint_offset),
            "joint_noise": r.joint_noise * jax.random.uniform(k[4], (), dtype),
            "target_error": u(k[5], (3,), r.target_error),
        }

    def _seen(self, spec: sampling.ResetSpec, randomize: dict[str, Any] | None) -> sampling.ResetSpec:
        """The scene as the robot's sensors report it: the detected target carries this episode's error."""
        if randomize is None:
            return spec
        return spec._replace(target_pos=spec.target_pos + randomize["target_error"].astype(spec.target_pos.dtype))

    # -- API -------------------------------------------------------------------------------
    # reset / reset_to / step are jitted per env (static self): each is traced once per env, not once per
    # caller (the trainer's reset, auto-reset, rollout and evaluation); the programs are the same.
    @functools.partial(jax.jit, static_argnums=0)
    def reset(self, rng: jax.Array) -> State:
        """Sample a fresh episode start (target, obstacles, start noise) and build its state."""
        return self.reset_to(*self.sample_spec(rng))

    def sample_spec(self, rng: jax.Array) -> tuple[sampling.ResetSpec, jax.Array]:
        """A fresh scene drawn from ``rng`` and the key ``reset_to`` builds its state with: ``reset`` in two
        halves, so that a training curriculum (``auto_reset.AutoReset``) can put a remembered scene in its place."""
        rng, key_sample = jax.random.split(rng)
        u = jax.random.uniform(key_sample, (self.n_uniforms,))
        return sampling.sample_reset(jnp, self.robot, self.cfg.sampling, self.cfg.task, u), rng

    @functools.partial(jax.jit, static_argnums=0)
    def reset_to(self, spec: sampling.ResetSpec, rng: jax.Array) -> State:
        """Start from an explicit ResetSpec (parity with PyBullet, deployment twins)."""
        dtype = jnp.result_type(float)
        spec = jax.tree_util.tree_map(jnp.asarray, spec)
        q0 = spec.q0.astype(dtype)
        kin = robot.forward_kinematics(jnp, self.robot, q0)
        col = collision.check(jnp, self.robot, kin, spec, self.cfg)
        tilt = robot.tilt(jnp, kin.approach_axis)
        d0 = jnp.linalg.norm(kin.gripper_centre - spec.target_pos)
        blocking = sampling.is_blocking(jnp, self.robot, self.cfg.sampling, self.cfg.task, spec)
        randomize = None
        if self.randomized:
            rng, key_randomize = jax.random.split(rng)
            randomize = self._draw_randomization(key_randomize, dtype)
        rng, key_noise = jax.random.split(rng)
        zero = jnp.zeros((), dtype)
        obs = self._observe(q0, kin, spec, col, tilt, key_noise, zero, randomize, q0)
        info = {
            "rng": rng,
            "progress": zero,
            "steps": jnp.zeros((), jnp.int32),
            "q_target": q0,
            "reset": spec,
            "tracker": episode.start(jnp, self.cfg, d0, tilt, col, blocking),
            "episode": {k: zero for k in episode.episode_keys()},
        }
        if randomize is not None:
            info["randomize"] = randomize
        if self.queue_size:
            info["commands"] = jnp.broadcast_to(q0, (self.queue_size, q0.shape[0]))
        if self.lagged:
            info["servo"] = {"q": q0, "q_prev": q0}
        if self.privileged:
            info["privileged"] = observation.privileged(jnp, self.cfg, spec, col, kin.gripper_centre, info["steps"], zero,
                                                        blocking)
        metrics = {k: zero for k in step_metric_keys()}
        return State(
            pipeline_state=self._initial_pipeline(q0),
            obs=obs,
            reward=zero,
            done=zero,
            metrics=metrics,
            info=info,
        )

    def _observe(self, q: Any, kin: Any, spec: Any, col: Any, tilt: Any, key: Any, progress: Any,
                 randomize: dict[str, Any] | None, q_command: Any) -> jax.Array:
        """The policy's observation: joint readings with noise (and this episode's offset), the detected target,
        and the last command ``q_command``.  The servos track commands in their own frame and the readings are
        off by the offset, so the pending command (command − reading) shows the offset as a real arm would."""
        if randomize is not None:  # joint readings with this episode's offset and extra noise; the detected target
            key, key_extra = jax.random.split(key)
            q = q + randomize["joint_offset"] + randomize["joint_noise"] * jax.random.normal(key_extra, q.shape, q.dtype)
        noisy_q = observation.noisy_joints(self.cfg.task, q, progress, jax.random.normal(key, q.shape, q.dtype))
        return observation.assemble(jnp, self.cfg, noisy_q, kin.gripper_centre, self._seen(spec, randomize), col, tilt,
                                    q_command)

    @functools.partial(jax.jit, static_argnums=0)
    def step(self, state: State, action: jax.Array) -> State:
        cfg, info = self.cfg, state.info
        spec = info["reset"]
        dtype = info["q_target"].dtype
        action = action.astype(dtype)
        randomize = info.get("randomize")
        q_now = self.measured_joints(state)
        ctl = control.control_step(jnp, self.robot, cfg.control, info["q_target"], q_now,
                                   self._seen(spec, randomize).target_pos, action)
        queue = None
        if self.queue_size:
            queue = jnp.concatenate([ctl.q_target[None], info["commands"][:-1]], axis=0)
        pipeline, q_meas, servo_info = self._advance(state, ctl.q_target, queue, randomize)
        kin = robot.forward_kinematics(jnp, self.robot, q_meas)
        col = collision.check(jnp, self.robot, kin, spec, cfg)
        tilt = robot.tilt(jnp, kin.approach_axis)
        d_now = jnp.linalg.norm(kin.gripper_centre - spec.target_pos)
        step = episode.advance(jnp, cfg, info["tracker"], spec, progress=info["progress"], d_now=d_now, col=col,
                               gripper_centre=kin.gripper_centre, tilt=tilt)
        rng, key_noise = jax.random.split(info["rng"])
        obs = self._observe(q_meas, kin, spec, col, tilt, key_noise, info["progress"], randomize, ctl.q_target)
        new_info = dict(info)
        new_info.update(rng=rng, steps=step.tracker.steps, q_target=ctl.q_target, tracker=step.tracker,
                        episode=step.episode, **servo_info)
        if queue is not None:
            new_info["commands"] = queue
        if self.privileged:
            new_info["privileged"] = observation.privileged(jnp, cfg, spec, col, kin.gripper_centre, step.tracker.steps,
                                                            info["progress"], step.tracker.blocking)
        metrics = {
            **step.terms.values,
            "distance": d_now,
            "tilt": tilt,
            "slowed": ctl.slowed.astype(dtype),
            "finetuned": ctl.finetuned.astype(dtype),
        }
        return state.replace(pipeline_state=pipeline, obs=obs, reward=step.reward, done=step.done.astype(dtype),
                             metrics=metrics, info=new_info)

