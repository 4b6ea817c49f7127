"""The grasping MDP of SPEC §2 as a pure-JAX, Brax-compatible environment (MuJoCo-MJX physics).

``GraspEnv(cfg).reset(rng)`` / ``.step(state, action)`` work on one env; ``jax.vmap``
them for batches (``wrappers.AutoReset`` does, with fresh-sample auto-reset).  The
control step, reward, sampling and collision maths come from the backend-agnostic
modules that the PyBullet reference env and the deployment runtime share.

Modes (``cfg.control.mode``): ``kinematic`` sets qpos = q_target (what the AUBO
controller's precise joint tracking amounts to) and needs no physics; ``dynamic``
runs ``mjx.step`` with position servos tracking q_target under gravity
(``substeps`` × ``physics_dt`` per 0.05 s control period, contacts off — collisions are
computed analytically in both modes).
"""

from __future__ import annotations

import os
from typing import Any

import sagrasp_jax  # noqa: F401  (XLA flags before jax)
import jax
import jax.numpy as jnp
from brax.envs.base import State

from sagrasp_jax import collision, control, episode, observation, robot, sampling
from sagrasp_jax.config import EnvConfig

MJCF_SCENE = os.path.join(os.path.dirname(robot.URDF_PATH), "..", "mjcf", "scene.xml")

EPISODE_KEYS = episode.EPISODE_KEYS

OBS_SIZE = observation.OBS_SIZE  # the paper layout's 17; an env's own size is ``GraspEnv.observation_size``


class GraspEnv:
    """AUBO-i5 + EG2 gripper reaching a cuboid among random obstacles (SPEC §1-§2)."""

    action_size = control.ACTION_SIZE

    def __init__(self, cfg: EnvConfig, privileged: bool = False):
        if cfg.control.mode not in ("kinematic", "dynamic"):
            raise ValueError(f"env.control.mode must be 'kinematic' or 'dynamic', got {cfg.control.mode!r}")
        self.cfg = cfg
        self.obs_layout = observation.layout_of(cfg)
        self.observation_size = len(self.obs_layout)
        # entries the trainer's running normaliser leaves at mean 0, std 1 (hand-scaled)
        self.hand_scaled_mask = observation.hand_scaled_mask(self.obs_layout)
        # privileged critic inputs in info["privileged"] (ppo.privileged_critic); the policy never sees them
        self.privileged = privileged
        self.privileged_size = len(observation.privileged_layout(cfg)) if privileged else 0
        self.robot = robot.load_robot()
        self.n_uniforms = sampling.uniforms_needed(cfg.sampling)
        self._mjx_model = None
        if cfg.control.mode == "dynamic":
            self._mjx_model = self._load_mjx_model()

    # -- physics ---------------------------------------------------------------------------
    def _load_mjx_model(self) -> Any:
        import mujoco
        from mujoco import mjx

        model = mujoco.MjModel.from_xml_path(os.path.normpath(MJCF_SCENE))
        model.opt.timestep = self.cfg.control.physics_dt
        model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
        return mjx.put_model(model)

    def _initial_pipeline(self, q0: jax.Array) -> Any:
        if self._mjx_model is None:
            return None
        from mujoco import mjx

        qpos = jnp.concatenate([q0, jnp.full(2, self.robot.finger_open, q0.dtype)])
        data = mjx.make_data(self._mjx_model)
        data = data.replace(qpos=qpos.astype(data.qpos.dtype), ctrl=qpos.astype(data.ctrl.dtype))
        return data

    def _advance(self, pipeline: Any, q_target: jax.Array) -> tuple[Any, jax.Array]:
        """Apply q_target; returns the new pipeline state and the measured joints."""
        if self._mjx_model is None:
            return None, q_target
        from mujoco import mjx

        ctrl = jnp.concatenate([q_target, jnp.full(2, self.robot.finger_open, q_target.dtype)]).astype(pipeline.ctrl.dtype)
        pipeline = pipeline.replace(ctrl=ctrl)

        def substep(data: Any, _: Any) -> tuple[Any, None]:
            return mjx.step(self._mjx_model, data), None

        pipeline, _ = jax.lax.scan(substep, pipeline, None, length=self.cfg.control.substeps)
        return pipeline, pipeline.qpos[:6].astype(q_target.dtype)

    # -- API -------------------------------------------------------------------------------
    def reset(self, rng: jax.Array) -> State:
        """Sample a fresh episode start (target, obstacles, start noise) and build its state."""
        rng, key_sample = jax.random.split(rng)
        u = jax.random.uniform(key_sample, (self.n_uniforms,))
        spec = sampling.sample_reset(jnp, self.robot, self.cfg.sampling, self.cfg.task, u)
        return self.reset_to(spec, rng)

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
        rng, key_noise = jax.random.split(rng)
        zero = jnp.zeros((), dtype)
        obs = self._observe(q0, kin, spec, col, tilt, key_noise, zero)
        info = {
            "rng": rng,
            "progress": zero,
            "steps": jnp.zeros((), jnp.int32),
            "q_target": q0,
            "reset": spec,
            "tracker": episode.start(jnp, d0, col, blocking),
            "episode": {k: zero for k in EPISODE_KEYS},
        }
        if self.privileged:
            info["privileged"] = observation.privileged(jnp, self.cfg, spec, col, kin.gripper_centre, info["steps"], zero,
                                                        blocking)
        metrics = {k: zero for k in ("r_distance", "r_success", "r_obstacle", "distance", "tilt", "slowed", "finetuned")}
        return State(
            pipeline_state=self._initial_pipeline(q0),
            obs=obs,
            reward=zero,
            done=zero,
            metrics=metrics,
            info=info,
        )

    def _observe(self, q: Any, kin: Any, spec: Any, col: Any, tilt: Any, key: Any, progress: Any) -> jax.Array:
        noisy_q = observation.noisy_joints(self.cfg.task, q, progress, jax.random.normal(key, q.shape, q.dtype))
        return observation.assemble(jnp, self.cfg, noisy_q, kin.gripper_centre, spec, col, tilt)

    def step(self, state: State, action: jax.Array) -> State:
        cfg, info = self.cfg, state.info
        spec = info["reset"]
        dtype = info["q_target"].dtype
        action = action.astype(dtype)
        q_now = info["q_target"] if self._mjx_model is None else state.pipeline_state.qpos[:6].astype(dtype)
        ctl = control.control_step(jnp, self.robot, cfg.control, info["q_target"], q_now, spec.target_pos, action)
        pipeline, q_meas = self._advance(state.pipeline_state, ctl.q_target)
        kin = robot.forward_kinematics(jnp, self.robot, q_meas)
        col = collision.check(jnp, self.robot, kin, spec, cfg)
        tilt = robot.tilt(jnp, kin.approach_axis)
        d_now = jnp.linalg.norm(kin.gripper_centre - spec.target_pos)
        step = episode.advance(jnp, cfg, info["tracker"], spec, progress=info["progress"], d_now=d_now, col=col,
                               gripper_centre=kin.gripper_centre, tilt=tilt)
        rng, key_noise = jax.random.split(info["rng"])
        obs = self._observe(q_meas, kin, spec, col, tilt, key_noise, info["progress"])
        new_info = dict(info)
        new_info.update(rng=rng, steps=step.tracker.steps, q_target=ctl.q_target, tracker=step.tracker,
                        episode=step.episode)
        if self.privileged:
            new_info["privileged"] = observation.privileged(jnp, cfg, spec, col, kin.gripper_centre, step.tracker.steps,
                                                            info["progress"], step.tracker.blocking)
        metrics = {
            "r_distance": step.terms.r_distance,
            "r_success": step.terms.r_success,
            "r_obstacle": step.terms.r_obstacle,
            "distance": d_now,
            "tilt": tilt,
            "slowed": ctl.slowed.astype(dtype),
            "finetuned": ctl.finetuned.astype(dtype),
        }
        return state.replace(pipeline_state=pipeline, obs=obs, reward=step.reward, done=step.done.astype(dtype),
                             metrics=metrics, info=new_info)
