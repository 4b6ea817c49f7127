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

from sagrasp_jax import collision, control, observation, reward, robot, sampling
from sagrasp_jax.config import EnvConfig

MJCF_SCENE = os.path.join(os.path.dirname(robot.URDF_PATH), "..", "mjcf", "scene.xml")

EPISODE_KEYS = reward.EPISODE_KEYS

OBS_SIZE = observation.OBS_SIZE
ACTION_SIZE = 6


class GraspEnv:
    """AUBO-i5 + EG2 gripper reaching a cuboid among random obstacles (SPEC §1-§2)."""

    observation_size = OBS_SIZE
    action_size = ACTION_SIZE

    def __init__(self, cfg: EnvConfig):
        if cfg.control.mode not in ("kinematic", "dynamic"):
            raise ValueError(f"env.control.mode must be 'kinematic' or 'dynamic', got {cfg.control.mode!r}")
        self.cfg = cfg
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
        rng, key_noise = jax.random.split(rng)
        obs = self._observe(q0, kin.gripper_centre, spec, col, tilt, key_noise, jnp.zeros((), dtype))
        zero = jnp.zeros((), dtype)
        info = {
            "rng": rng,
            "progress": zero,
            "steps": jnp.zeros((), jnp.int32),
            "q_target": q0,
            "reset": spec,
            "d_prev": d0,
            "clean": jnp.ones((), dtype),
            "acc": {k: zero for k in ("return", "r_distance", "r_success", "r_obstacle")}
            | {"min_obstacle_dist": col.nearest_obstacle_dist},
            "episode": {k: zero for k in EPISODE_KEYS},
        }
        metrics = {k: zero for k in ("r_distance", "r_success", "r_obstacle", "distance", "tilt", "slowed", "finetuned")}
        return State(
            pipeline_state=self._initial_pipeline(q0),
            obs=obs,
            reward=zero,
            done=zero,
            metrics=metrics,
            info=info,
        )

    def _observe(self, q: Any, centre: Any, spec: Any, col: Any, tilt: Any, key: Any, progress: Any) -> jax.Array:
        task = self.cfg.task
        std = task.obs_noise_std * (1.0 + task.obs_noise_growth * progress)
        noisy_q = q + std * jax.random.normal(key, q.shape, q.dtype)
        return observation.assemble(jnp, noisy_q, centre, spec.target_pos, col, tilt)

    def step(self, state: State, action: jax.Array) -> State:
        cfg, info = self.cfg, state.info
        spec = info["reset"]
        dtype = info["d_prev"].dtype
        action = action.astype(dtype)
        q_now = info["q_target"] if self._mjx_model is None else state.pipeline_state.qpos[:6].astype(dtype)
        ctl = control.control_step(jnp, self.robot, cfg.control, info["q_target"], q_now, spec.target_pos, action)
        pipeline, q_meas = self._advance(state.pipeline_state, ctl.q_target)
        kin = robot.forward_kinematics(jnp, self.robot, q_meas)
        col = collision.check(jnp, self.robot, kin, spec, cfg)
        tilt = robot.tilt(jnp, kin.approach_axis)
        d_now = jnp.linalg.norm(kin.gripper_centre - spec.target_pos)
        steps = info["steps"] + 1
        success_raw = reward.success_flag(jnp, cfg.task, kin.gripper_centre, spec.target_pos, tilt)
        timeout = steps >= cfg.task.max_steps
        outcome = reward.resolve_outcome(jnp, col.any_collision, success_raw, timeout)
        near = cfg.reward.near_miss_distance
        obstacle_present = jnp.any(spec.obstacle_active)
        clean = info["clean"] * jnp.where(obstacle_present & (col.nearest_obstacle_dist < near), 0.0, 1.0)
        total, terms = reward.step_reward(
            jnp,
            cfg.reward,
            progress=info["progress"],
            d_prev=info["d_prev"],
            d_now=d_now,
            collision=outcome.collision,
            success=outcome.success,
            timeout=outcome.timeout,
            obstacle_dist=col.nearest_obstacle_dist,
            obstacle_present=obstacle_present,
            clean_so_far=clean > 0.5,
        )
        done = (outcome.collision | outcome.success | outcome.timeout).astype(dtype)
        rng, key_noise = jax.random.split(info["rng"])
        obs = self._observe(q_meas, kin.gripper_centre, spec, col, tilt, key_noise, info["progress"])
        acc = {
            "return": info["acc"]["return"] + total,
            "r_distance": info["acc"]["r_distance"] + terms.r_distance,
            "r_success": info["acc"]["r_success"] + terms.r_success,
            "r_obstacle": info["acc"]["r_obstacle"] + terms.r_obstacle,
            "min_obstacle_dist": jnp.minimum(info["acc"]["min_obstacle_dist"], col.nearest_obstacle_dist),
        }
        episode = {
            "return": acc["return"],
            "r_distance": acc["r_distance"],
            "r_success": acc["r_success"],
            "r_obstacle": acc["r_obstacle"],
            "success": outcome.success.astype(dtype),
            "collision": outcome.collision.astype(dtype),
            "timeout": outcome.timeout.astype(dtype),
            "steps": steps.astype(dtype),
            "obstacle_present": obstacle_present.astype(dtype),
            "redraws": jnp.asarray(spec.redraws, dtype),
            "fallback": jnp.asarray(spec.fallback, dtype),
            "min_obstacle_dist": acc["min_obstacle_dist"],
        } | {f"hit_{name}": (outcome.collision & hit).astype(dtype) for name, hit in col.hits.items()}
        new_info = dict(info)
        new_info.update(
            rng=rng,
            steps=steps,
            q_target=ctl.q_target,
            d_prev=d_now,
            clean=clean,
            acc=acc,
            episode=episode,
        )
        metrics = {
            "r_distance": terms.r_distance,
            "r_success": terms.r_success,
            "r_obstacle": terms.r_obstacle,
            "distance": d_now,
            "tilt": tilt,
            "slowed": ctl.slowed.astype(dtype),
            "finetuned": ctl.finetuned.astype(dtype),
        }
        return state.replace(pipeline_state=pipeline, obs=obs, reward=total, done=done, metrics=metrics, info=new_info)
