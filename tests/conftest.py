"""Shared fixtures: a toy-env trainer setup for fast unit tests and a trained grasp policy.

``toy_config`` keeps every toy test on the same array shapes, so one compilation (cached by
jax's persistent cache) serves the whole session.  ``trained_run`` trains the real grasp env
once per session (cpu-quick, a few minutes on 2 cores) for tests that need a working policy.
"""

from __future__ import annotations

import os

# Cache every compilation, not only those over 1 s (the package's default): the suite compiles
# hundreds of small programs, many of them again in subprocesses (CLI tests), which inherit this;
# measured on a 2-core VM with a cold cache, the fault and deploy tests ran 9 % faster (266 -> 243 s).
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")

import sagrasp_jax  # noqa: E402,F401  (sets XLA_FLAGS before jax is imported)

import sys
from typing import Any

import pytest

sys.path.insert(0, os.path.dirname(__file__))

from toy_env import AutoReset, PointReach  # noqa: E402

from sagrasp_jax import train  # noqa: E402
from sagrasp_jax.task.config import KNOBS_OFF, Config  # noqa: E402

TOY_ITER_STEPS = 32 * 16  # num_envs × unroll_length


@pytest.fixture(autouse=True)
def _precision_is_left_alone(request: pytest.FixtureRequest):
    """Fail the test that leaves jax_enable_x64 changed (an import that switches it, a missing restore):
    every later float32 test in the session would otherwise fail with dtype errors far from the cause."""
    import jax

    before = jax.config.jax_enable_x64
    yield
    after = jax.config.jax_enable_x64
    if after != before:
        jax.config.update("jax_enable_x64", before)
        pytest.fail(f"{request.node.nodeid} left jax_enable_x64 {before} -> {after}", pytrace=False)


@pytest.fixture
def x64():
    """jax with float64 enabled for one test (parity-style exact comparisons), restored after."""
    import jax

    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    yield jax
    jax.config.update("jax_enable_x64", previous)


# The PPO shape `cpu-quick` had before its time-to-quality levers (experiments.sooner.BEFORE): 4 epochs, entropy
# 1e-3, a 32×4 policy, SA from lr 3e-4 decaying ×0.98, the same passes throughout.  The suite's short runs keep it: their checks were sized
# with it, and eight epochs of a policy twice as wide would make every short run half again as slow without
# testing anything more.  They keep the legacy CPU fusion emitter too (the numbers their checks were sized on);
# tests/training/test_train.py checks that the preset's new emitters reach every program the trainer compiles.
SUITE_PPO = ["ppo.num_epochs=4", "ppo.entropy_coef=1e-3", "ppo.network.policy_hidden=32,32,32,32",
             "ppo.learning_rate=3e-4", "sa.decay=0.98", "ppo.late_epochs=0", "train.cpu_fusion_emitters=legacy"]


def toy_config(cycles: int = 6, algo: str = "sa-ppo", extra: list[str] | None = None,
               iterations_per_cycle: int = 2) -> Config:
    """Small PPO batch on the toy env; ``cycles`` SA cycles of ``iterations_per_cycle`` iterations."""
    total = TOY_ITER_STEPS * iterations_per_cycle * cycles
    sets = ["ppo.num_envs=32", "ppo.unroll_length=16", "ppo.num_minibatches=4", "ppo.num_epochs=2",
            f"eval.num_cycles={cycles}", "eval.episodes=32", "env.task.max_steps=30",
            "train.checkpoint_every_cycles=2", "train.metrics_window=64",
            "ppo.privileged_critic=false"]  # toy runs: no privileged critic unless a test sets it (toy_factory)
    return train.build_config("cpu-quick", algo, 0, total, SUITE_PPO + sets + list(extra or []))


FIRST_GRADIENT_SETS = ["ppo.num_minibatches=1", "ppo.num_epochs=1", "ppo.entropy_coef=0.0"]


def first_gradients(env: Any, cfg: Config, mesh: Any) -> list[Any]:
    """The first iteration's loss and gradients by the training call itself (``ppo.make_cycle``, one
    iteration): with plain SGD at lr 1 the update is minus the gradient.  ``cfg`` has one minibatch,
    one epoch and no entropy bonus (``FIRST_GRADIENT_SETS``): each device shuffles its own rows, and
    the entropy estimate's noise follows the shuffle, so only then is the update the whole batch's
    gradient whatever the device count."""
    import jax
    import numpy as np
    import optax

    from sagrasp_jax.training.agents.ppo import actor_critic
    from sagrasp_jax.training import metrics_window
    from sagrasp_jax.training.agents.ppo import ppo
    from sagrasp_jax.training.agents.ppo import rollout
    from sagrasp_jax.training import sharding

    assert (cfg.ppo.num_minibatches, cfg.ppo.num_epochs, cfg.ppo.entropy_coef) == (1, 1, 0.0)
    nets = actor_critic.make_networks(cfg.ppo.network, env.observation_size, env.action_size, cfg.ppo.obs_clip)
    sgd = optax.clip_by_global_norm(1e30)  # plain SGD at the call's lr of 1 (the cycle applies −lr)
    ts = sharding.replicate(actor_critic.init_training_state(jax.random.PRNGKey(0), nets, sgd, env.observation_size),
                            mesh)
    es = rollout.make_reset(env, mesh)(sharding.shard_batch(jax.random.split(jax.random.PRNGKey(1), cfg.ppo.num_envs),
                                                            mesh))
    window = metrics_window.init_window(("return", "success", "steps"), 8)
    args = (window, jax.random.PRNGKey(2), np.int32(0), np.int32(1), np.zeros(1, np.float32), np.ones(1, np.float32))
    cycle = ppo.make_cycle(env, nets, sgd, cfg.ppo, mesh, 1)
    new, _, _, metrics = cycle(ts, es, *sharding.replicate(args, mesh))
    before, after = sharding.to_host((ts.params, new.params))
    grads = jax.tree_util.tree_map(lambda a, b: np.asarray(a, np.float64) - b, before, after)
    assert bool(sharding.to_host(metrics["executed"])[0])
    return [np.asarray(sharding.to_host(metrics["loss"])[0])] + jax.tree_util.tree_leaves(grads)


def toy_factory(nan_progress: tuple[float, float] | None = None) -> Any:
    """The toy envs; the training env reports privileged critic inputs when the config has a privileged
    critic (as many as ``observation.critic_extra_size`` asks for)."""
    from sagrasp_jax.task import observation

    def factory(cfg: Config) -> tuple[Any, Any]:
        extra = observation.critic_extra_size(cfg)
        return AutoReset(PointReach(max_steps=cfg.env.task.max_steps, nan_progress=nan_progress,
                                    privileged_size=extra)), PointReach(max_steps=cfg.env.task.max_steps)
    return factory


@pytest.fixture(scope="session")
def toy_run(tmp_path_factory: pytest.TempPathFactory) -> str:
    """A finished toy run folder (config, metrics, checkpoint, policy)."""
    out = str(tmp_path_factory.mktemp("toy") / "run")
    train.run(toy_config(), out, env_factory=toy_factory(), progress=False)
    return out


TRAINED_STEPS = 600_000  # cpu-quick batch; ≈ 1.5-2 min on 2 cores plus compile
TRAINED_ARGS = ["--preset", "cpu-quick", "--algo", "sa-ppo", "--seed", "0", "--total-steps", str(TRAINED_STEPS),
                "--set", "eval.num_cycles=30", "--no-progress", *(f"--set={item}" for item in SUITE_PPO),
                *(f"--set={item}" for item in KNOBS_OFF)]  # learns fast: transfer errors off


@pytest.fixture(scope="session")
def trained_run(tmp_path_factory: pytest.TempPathFactory) -> str:
    """Run folder of a short real-env SA-PPO run via the CLI (config, metrics, checkpoint, policy.npz).

    It learns the grasp well past the untrained policy (≈ 65 % evaluated success after
    600k steps); tests needing a working policy share it.
    """
    import subprocess

    out = str(tmp_path_factory.mktemp("trained") / "run")
    res = subprocess.run([sys.executable, "-m", "sagrasp_jax.train", "--out", out, *TRAINED_ARGS],
                         capture_output=True, text=True, timeout=900,
                         cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return out
