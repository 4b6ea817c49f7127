"""A policy rebuilt from a run: its checkpoint's params and normaliser (for ``evaluate``, ``export`` and
``train --init-from``) and the deterministic policy written as ``policy.npz``.

The restore template is the policy's networks alone (``actor_critic.init_policy``, no optimizer), or, for
``--init-from``, the starting run's own fresh train state, which has the same networks.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import numpy as np

from sagrasp_jax.task import observation
from sagrasp_jax.task import policy_file as runtime
from sagrasp_jax.task.config import Config, config_to_dict
from sagrasp_jax.task import robots
from sagrasp_jax.training import checkpoint, run_dir, sharding
from sagrasp_jax.training.agents.ppo import actor_critic


class PolicyState(NamedTuple):
    """The policy part of a checkpoint's ``train_state`` (its tree paths are ``.params…`` and ``.normaliser…``
    there too, so a checkpoint's policy restores into this without the optimizer state)."""

    params: actor_critic.Params
    normaliser: actor_critic.Normaliser


def restore_into(template: PolicyState, ckpt: checkpoint.Checkpoint) -> PolicyState:
    """The checkpoint's params and normaliser in ``template``'s structure (paths, shapes and dtypes checked)."""
    flat = {k: v for k, v in ckpt.trees.get("train_state", {}).items() if not k.startswith(".opt_state")}
    return checkpoint.restore_tree(template, flat, "train_state", ckpt.path)


def restore_policy(cfg: Config, ckpt: checkpoint.Checkpoint, obs_size: int,
                   action_size: int) -> tuple[actor_critic.Params, actor_critic.Normaliser]:
    """Params and normaliser from a loaded checkpoint (the template: ``cfg``'s networks, no optimizer)."""
    networks = actor_critic.make_networks(cfg.ppo.network, obs_size, action_size, cfg.ppo.obs_clip,
                                          observation.critic_extra_size(cfg))
    # the template's shapes only (jax.eval_shape): an eager init compiled ~40 small programs, ≈ 1.5 s cold
    template = jax.eval_shape(lambda: PolicyState(*actor_critic.init_policy(jax.random.PRNGKey(0), networks, obs_size)))
    restored = restore_into(template, ckpt)
    return restored.params, restored.normaliser


def load_policy_state(run: str, obs_size: int | None = None, action_size: int | None = None
                      ) -> tuple[Config, actor_critic.Params, actor_critic.Normaliser, dict[str, Any]]:
    """Config, params and normaliser of the run's latest checkpoint (and its counters); the observation
    and action sizes default to those of the run's observation layout and robot."""
    cfg = run_dir.load_config(run)
    ckpt = run_dir.load_checkpoint(run, cfg)
    obs_size = len(observation.layout_of(cfg.env)) if obs_size is None else obs_size
    action_size = robots.get(cfg.env.robot).dof if action_size is None else action_size
    params, normaliser = restore_policy(cfg, ckpt, obs_size, action_size)
    return cfg, params, normaliser, run_dir.checkpoint_counters(ckpt)


def check_init_from(cfg: Config) -> tuple[Config, checkpoint.Checkpoint]:
    """The config and verified checkpoint of ``cfg.train.init_from`` (``train --init-from RUN``), if its
    networks can start this run.  Refused (RunDirError / CheckpointError, naming the run) when RUN is
    no run folder, has no readable checkpoint, or has another observation layout, network shape or
    critic input."""
    run = cfg.train.init_from
    src = run_dir.load_config(run)
    ckpt = run_dir.load_checkpoint(run, src)
    problems = []
    mine, theirs = observation.layout_of(cfg.env), observation.layout_of(src.env)
    if mine != theirs:
        problems.append(f"observation layout {src.env.task.obs_layout!r} ({len(theirs)} entries) vs this run's "
                        f"{cfg.env.task.obs_layout!r} ({len(mine)} entries)")
    if src.ppo.network != cfg.ppo.network:
        problems.append(f"networks {config_to_dict(src.ppo.network)} vs this run's {config_to_dict(cfg.ppo.network)}")
    if src.ppo.privileged_critic != cfg.ppo.privileged_critic:
        problems.append(f"ppo.privileged_critic={src.ppo.privileged_critic} vs this run's {cfg.ppo.privileged_critic}")
    elif cfg.ppo.privileged_critic and observation.privileged_layout(src.env) != observation.privileged_layout(cfg.env):
        problems.append(f"privileged critic inputs for env.sampling.obstacle_kinds={list(src.env.sampling.obstacle_kinds)}"
                        f", max_obstacles={src.env.sampling.max_obstacles} vs this run's "
                        f"{list(cfg.env.sampling.obstacle_kinds)}, {cfg.env.sampling.max_obstacles}")
    if problems:
        raise run_dir.RunDirError(f"--init-from {run}: its policy cannot start this run: " + "; ".join(problems))
    return src, ckpt


def init_policy_state(ts: actor_critic.TrainingState, cfg: Config, obs_size: int, action_size: int
                      ) -> actor_critic.TrainingState:
    """``ts`` with the policy, value network and normaliser of ``cfg.train.init_from``'s checkpoint: a
    fine-tuning start, e.g. a kinematic run continued in dynamic mode.  The optimizer state stays
    ``ts``'s (fresh), and so does everything else of the run (SA schedule, envs, counters)."""
    _, ckpt = check_init_from(cfg)  # same networks as this run's: ts is the template
    restored = restore_into(PolicyState(ts.params, ts.normaliser), ckpt)
    return ts._replace(params=restored.params, normaliser=restored.normaliser)


def export_policy(file: str, cfg: Config, params: actor_critic.Params, normaliser: actor_critic.Normaliser, obs_size: int) -> str:
    """Write the deterministic policy (weights + normaliser) as ``policy_file``'s ``policy.npz``."""
    layers = sharding.to_host(params.policy["params"])
    weights = [(np.asarray(layers[f"hidden_{i}"]["kernel"]), np.asarray(layers[f"hidden_{i}"]["bias"]))
               for i in range(len(layers))]
    names = observation.layout_of(cfg.env)
    layout = names if obs_size == len(names) else tuple(f"obs_{i}" for i in range(obs_size))  # (toy envs)
    return runtime.save_policy_npz(file, weights=weights, activation=cfg.ppo.network.activation,
                                   obs_mean=np.asarray(normaliser.mean), obs_std=np.asarray(normaliser.std),
                                   config=cfg, obs_layout=layout)
