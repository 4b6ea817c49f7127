"""The grasp task as a ``brax.envs.Env``, and a registry: ``load("grasp-kinematic")``.

``GraspEnv`` (``grasp_env.py``) is this project's env for its own trainer (``auto_reset.AutoReset``,
``ppo``).  ``BraxGraspEnv`` is a thin adapter around it that keeps brax's conventions, so that
``brax.envs.training.wrap(env, episode_length, action_repeat)`` (vmap, episode and auto-reset
wrappers) and ``brax.training.acting.generate_unroll`` run the task correctly:

* **Per-episode state lives in ``pipeline_state``.**  brax's ``AutoResetWrapper`` restores only
  ``obs`` and ``pipeline_state`` when an episode is done; ``state.info`` carries on.  So the whole
  ``GraspEnv`` info dict (step counter, joint target, reset, episode tracker, privileged inputs,
  randomisation draws) travels in ``pipeline_state = {"physics", "episode", "pending"}``, and a
  done episode restarts with its own counters, never with the old episode's.
* **Restarts are fresh scenes.**  brax restores each slot's *first* reset, which would replay one
  scene forever (docs/task.md §2.9).  The adapter keeps a never-played start in the wrapper's
  ``info["first_pipeline_state"]`` / ``info["first_obs"]`` instead (MuJoCo Playground's
  ``BraxAutoResetWrapper``: ``info["AutoResetWrapper_first_data"]`` / ``..._first_obs``): whenever
  the state it steps is such a start (``pipeline_state["pending"]``), it draws the next one from its
  own key chain (``info["reset_key"]``).  Under ``vmap`` the draw is a select, so it costs a reset per
  step; ``auto_reset.AutoReset`` (the project trainer's) refills lazily instead.
* **MuJoCo Playground** (``mujoco_playground.wrapper.wrap_for_brax_training``, PyPI ``playground``,
  the ``playground`` extra): its wrappers read and replace the physics as ``state.data``, brax's as
  ``state.pipeline_state``; the states here (:class:`GraspState`) answer to both names.
* **Stable dtypes and keys.**  The top-level ``info`` holds only what survives restarts
  (``reset_key``, ``progress``, the finished ``episode`` metrics), so brax's ``EpisodeWrapper``
  owns ``info["steps"]`` (float32) and ``info["truncation"]`` without a clash with
  ``GraspEnv``'s int32 counter.  ``step`` keeps every metric key of its input state (a wrapper
  may add one at reset, as brax's ``EvalWrapper`` adds ``reward``), so scan carries match.
* **Progress** (the reward weights' p) is ``state.info["progress"]``, as for ``GraspEnv``.
* **Finished episodes**: on the step where ``done == 1``, ``state.info["episode"]`` holds that
  episode's metrics (``episode.episode_keys()``), as in ``GraspEnv``.
* **Privileged critic** (``privileged=True``): the observation is the dict MuJoCo Playground
  uses, ``{"state": policy observation, "privileged_state": policy observation + privileged
  inputs}`` (brax's PPO: ``policy_obs_key="state"``, ``value_obs_key="privileged_state"``).

**brax's own PPO** (``brax.training.agents.ppo.train.train``, brax 0.14.2) calls
``jax.device_put_replicated``, which jax 0.10 removed; ``jax_compat_for_brax_ppo()`` adds an
equivalent (a stacked copy per device, sharded over them) when it is missing, and then
``ppo.train(environment=load("grasp-kinematic"), ...)`` trains (``tests/envs/test_brax_envs.py``).

Timeouts (``env.task.max_steps``) end an episode with ``done = 1`` as the task defines
(docs/task.md §2.7); an ``EpisodeWrapper`` shorter than that truncates (``info["truncation"]``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import sagrasp_jax  # noqa: F401  (XLA flags before jax)
import jax
import jax.numpy as jnp
from brax.envs.base import Env, State
from flax import struct

from sagrasp_jax.task import config as config_mod
from sagrasp_jax.envs.grasp_env import GraspEnv
from sagrasp_jax.task.episode import episode_keys

# name -> env.control.mode: exact tracking, MJX servos, the fitted servo model (the presets' training mode)
ENVS = {"grasp-kinematic": "kinematic", "grasp-dynamic": "dynamic", "grasp-lagged": "lagged"}
BRAX_NAMES = {name: "sagrasp_" + name.replace("-", "_") for name in ENVS}  # ids in brax's own registry
INNER_KEYS_ON_TOP = ("progress",)  # GraspEnv info keys the adapter keeps at the top level
# (pipeline state, observation) info keys where an auto-reset wrapper keeps the start it restores:
# brax's AutoResetWrapper, MuJoCo Playground's BraxAutoResetWrapper
FIRST_STATE_KEYS = (("first_pipeline_state", "first_obs"), ("AutoResetWrapper_first_data", "AutoResetWrapper_first_obs"))


@struct.dataclass
class GraspState(State):
    """brax's ``State`` that also answers to MuJoCo Playground's name for the physics, ``data``
    (read and ``replace(data=...)``), so Playground's wrappers run the env unchanged."""

    @property
    def data(self) -> Any:
        return self.pipeline_state


def _replace(self: GraspState, **changes: Any) -> GraspState:
    if "data" in changes:
        changes["pipeline_state"] = changes.pop("data")
    return dataclasses.replace(self, **changes)


GraspState.replace = _replace  # after the decorator, which installs flax's own replace


class BraxGraspEnv(Env):
    """``GraspEnv`` with brax's conventions (module doc)."""

    def __init__(self, cfg: config_mod.EnvConfig, privileged: bool = False) -> None:
        self.inner = GraspEnv(cfg, privileged=privileged)
        self.cfg = cfg
        self.privileged = privileged

    # -- brax.envs.Env interface -------------------------------------------------------------
    @property
    def observation_size(self) -> Any:
        n = self.inner.observation_size
        if self.privileged:
            return {"state": (n,), "privileged_state": (n + self.inner.privileged_size,)}
        return n

    @property
    def action_size(self) -> int:
        return self.inner.action_size

    @property
    def backend(self) -> str:
        return "mjx"

    def reset(self, rng: jax.Array) -> State:
        key_start, key_chain = jax.random.split(rng)
        inner = self.inner.reset(key_start)
        zero = inner.reward
        info = {"reset_key": key_chain, "progress": zero, "episode": {k: zero for k in episode_keys()}}
        return GraspState(pipeline_state=self._pack(inner, pending=True), obs=self._obs(inner), reward=zero,
                          done=inner.done, metrics=dict(inner.metrics), info=info)

    def step(self, state: State, action: jax.Array) -> State:
        info = dict(state.info)
        for first_state, first_obs in FIRST_STATE_KEYS:
            if first_state in info:  # under an auto-reset wrapper: keep a never-played start there
                pending = state.pipeline_state["pending"]
                key_chain, key_start = jax.random.split(info["reset_key"])
                fresh = self.inner.reset(key_start)
                keep = lambda new, old: jax.tree.map(lambda a, b: jnp.where(pending, a, b), new, old)  # noqa: E731
                info[first_state] = keep(self._pack(fresh, pending=True), info[first_state])
                info[first_obs] = keep(self._obs(fresh), info[first_obs])
                info["reset_key"] = jnp.where(pending, key_chain, info["reset_key"])
        inner = self._unpack(state, info)
        nxt = self.inner.step(inner, action)
        info["episode"] = nxt.info["episode"]
        metrics = dict(state.metrics)
        metrics.update(nxt.metrics)
        return state.replace(pipeline_state=self._pack(nxt, pending=False), obs=self._obs(nxt),
                             reward=nxt.reward, done=nxt.done, metrics=metrics, info=info)

    # -- packing -------------------------------------------------------------------------------
    def _pack(self, inner: State, pending: bool) -> dict[str, Any]:
        episode = {k: v for k, v in inner.info.items() if k not in INNER_KEYS_ON_TOP}
        return {"physics": inner.pipeline_state, "episode": episode, "pending": jnp.asarray(pending)}

    def _unpack(self, state: State, info: dict[str, Any]) -> State:
        packed = state.pipeline_state
        inner_info = dict(packed["episode"], progress=jnp.asarray(info["progress"], state.reward.dtype))
        obs = state.obs["state"] if self.privileged else state.obs
        return State(pipeline_state=packed["physics"], obs=obs, reward=state.reward, done=state.done,
                     metrics={}, info=inner_info)

    def _obs(self, inner: State) -> Any:
        if not self.privileged:
            return inner.obs
        return {"state": inner.obs, "privileged_state": jnp.concatenate([inner.obs, inner.info["privileged"]])}


def load(name: str, config: config_mod.Config | config_mod.EnvConfig | None = None,
         privileged: bool = False) -> BraxGraspEnv:
    """The task ``name`` (``grasp-kinematic``, ``grasp-dynamic`` or ``grasp-lagged``) as a brax env.

    ``config``: a ``Config`` (its env section) or an ``EnvConfig``; default the ``cpu-quick``
    preset.  The name sets ``env.control.mode``.  ``privileged=True``: the dict observation
    ``{"state", "privileged_state"}`` for an asymmetric critic."""
    if name not in ENVS:
        raise ValueError(f"unknown env {name!r}; valid envs: {', '.join(ENVS)}")
    cfg = config if config is not None else config_mod.get_config("cpu-quick")
    if isinstance(cfg, config_mod.Config):
        cfg = cfg.env
    env_cfg = dataclasses.replace(cfg, control=dataclasses.replace(cfg.control, mode=ENVS[name]))
    if env_cfg.control.mode == "kinematic":  # no servos: their knobs (latency, servo gains) do not apply
        env_cfg = dataclasses.replace(env_cfg, randomize=dataclasses.replace(env_cfg.randomize, latency=0.0, servo_gain=0.0))
    return BraxGraspEnv(env_cfg, privileged=privileged)


def _device_put_replicated(x: Any, devices: Any) -> Any:
    """What ``jax.device_put_replicated`` did: ``x`` copied onto each device, stacked on a new axis 0."""
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    devices = list(devices)
    sharding = NamedSharding(Mesh(np.array(devices), ("replica",)), PartitionSpec("replica"))
    return jax.tree.map(lambda a: jax.device_put(jnp.stack([jnp.asarray(a)] * len(devices)), sharding), x)


def jax_compat_for_brax_ppo() -> bool:
    """Give jax back ``device_put_replicated`` (removed in jax 0.10, still called by brax 0.14.2's
    ``ppo.train``, ``sac.train``, ``apg.train`` and ``brax.training.pmap``); True if it was added.
    Everything else those trainers use still exists in jax 0.10-0.11."""
    if hasattr(jax, "device_put_replicated"):
        return False
    jax.device_put_replicated = _device_put_replicated  # type: ignore[attr-defined]
    return True


def register_with_brax() -> None:
    """Make ``brax.envs.get_environment("sagrasp_grasp_kinematic", config=..., privileged=...)`` work."""
    from brax import envs as brax_envs

    for name, brax_name in BRAX_NAMES.items():
        brax_envs.register_environment(brax_name, lambda n=name, **kwargs: load(n, **kwargs))  # type: ignore[misc]


register_with_brax()
