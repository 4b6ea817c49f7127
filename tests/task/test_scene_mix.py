"""Blocking scenes and the training mix (obstacle issue items 3 and 5).

* ``sampling.path_clearance`` / ``is_blocking``: the straight segment from the start gripper centre
  to the grasp point, against obstacles built by hand;
* the blocking placement generator: every scene it accepts blocks and obeys docs/task.md §1's feasibility
  rules;
* the training mix (``train.obstacle_prob`` / ``blocking_prob``) differs from the evaluation mix
  when configured, and evaluation stays at the task's 0.2.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401
import jax
import jax.numpy as jnp

from sagrasp_jax import train
from sagrasp_jax.task import config
from sagrasp_jax.task import robot
from sagrasp_jax.task import sampling
from sagrasp_jax.task import shapes
import exact_geometry as geometry

ROBOT = robot.load_robot()
HOME = np.array(config.HOME_Q)
TARGET = np.array([0.3, -0.45, 0.025])
TASK = config.TaskConfig()
START = robot.forward_kinematics(np, ROBOT, HOME).gripper_centre  # (0, −0.30, 0.35)
GRASP = TARGET + np.array([0.0, 0.0, 0.0125])  # mid success band above the cube centre


def scene(kind: int, centre, size, yaw: float = 0.0) -> sampling.ResetSpec:
    return sampling.ResetSpec(
        q0=HOME, target_pos=TARGET, target_yaw=np.array(0.0), obstacle_active=np.array([True, False]),
        obstacle_kind=np.array([kind, robot.SPHERE]), obstacle_pos=np.array([centre, [0.0, 0.0, -5.0]], float),
        obstacle_yaw=np.array([yaw, 0.0]), obstacle_size=np.array([size, [0.01, 0, 0]], float), redraws=np.array(0),
        fallback=np.array(False),
    )


def brute_clearance(spec: sampling.ResetSpec) -> float:
    """Independent oracle: the obstacle's exact point distance at 20,001 points along the segment."""
    t = np.linspace(0.0, 1.0, 20_001)[:, None]
    pts = START + t * (GRASP - START)
    rot = shapes.yaw_rotation(np, float(spec.obstacle_yaw[0]))
    return float(geometry.point_distance(np, int(spec.obstacle_kind[0]), pts, spec.obstacle_pos[0], rot,
                                         spec.obstacle_size[0]).min())


MID = START + 0.5 * (GRASP - START)
_dir = (GRASP - START)[:2] / np.linalg.norm((GRASP - START)[:2])
PERP = np.array([-_dir[1], _dir[0], 0.0])

CASES = [  # (name, kind, centre, size, yaw, blocking?)
    ("sphere on the path", robot.SPHERE, MID, (0.04, 0, 0), 0.0, True),
    ("sphere 2 cm beside the path", robot.SPHERE, MID + 0.06 * PERP, (0.04, 0, 0), 0.0, True),
    ("sphere 4 cm beside the path", robot.SPHERE, MID + 0.08 * PERP, (0.04, 0, 0), 0.0, False),
    ("tall cylinder under the path", robot.CYLINDER, np.array([*MID[:2], 0.15]), (0.03, 0.15, 0), 0.0, True),
    ("short cylinder under the path", robot.CYLINDER, np.array([*MID[:2], 0.05]), (0.03, 0.05, 0), 0.0, False),
    ("yawed box near the grasp end", robot.BOX, np.array([0.22, -0.42, 0.05]), (0.03, 0.02, 0.05), 0.7, True),
    ("box far off the path", robot.BOX, np.array([-0.2, -0.55, 0.05]), (0.03, 0.03, 0.05), 0.3, False),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_blocking_classification(case):
    _, kind, centre, size, yaw, blocking = case
    spec = scene(kind, centre, size, yaw)
    got = sampling.path_clearance(np, ROBOT, TASK, spec)
    oracle = brute_clearance(spec)
    assert got[0] == pytest.approx(oracle, abs=1e-4)
    assert np.isinf(got[1])  # empty slot
    assert bool(sampling.is_blocking(np, ROBOT, config.SamplingConfig(), TASK, spec)) == blocking
    assert (oracle < 0.03) == blocking  # the hand-built case says what it claims


def test_no_obstacle_never_blocks():
    spec = scene(robot.SPHERE, MID, (0.04, 0, 0))._replace(obstacle_active=np.array([False, False]))
    assert not bool(sampling.is_blocking(np, ROBOT, config.SamplingConfig(), TASK, spec))


def _resets(sampling_cfg: config.SamplingConfig, n: int, seed: int) -> sampling.ResetSpec:
    u = jax.random.uniform(jax.random.PRNGKey(seed), (n, sampling.uniforms_needed(sampling_cfg)))
    fn = jax.jit(jax.vmap(lambda x: sampling.sample_reset(jnp, ROBOT, sampling_cfg, TASK, x)))
    return jax.tree_util.tree_map(np.asarray, fn(u))


def test_blocking_generator_obeys_feasibility_and_blocks():
    cfg = dataclasses.replace(config.SamplingConfig(), obstacle_prob=1.0, blocking_prob=1.0, scene_redraws=11)
    spec = _resets(cfg, 2000, seed=5)
    present = spec.obstacle_active[:, 0]
    assert present.mean() > 0.97  # the few fallbacks are counted, not hidden
    assert np.array_equal(~present, spec.fallback)
    clear = jax.jit(jax.vmap(lambda s: sampling.path_clearance(jnp, ROBOT, TASK, s)))(jax.tree_util.tree_map(jnp.asarray, spec))
    assert np.all(np.asarray(clear)[present, 0] < cfg.blocking_margin)
    for i in np.nonzero(present)[0][:300]:  # docs/task.md §1 (a) and (b), against the exact robot geometry
        kind, pos, yaw, size = spec.obstacle_kind[i, 0], spec.obstacle_pos[i, 0], spec.obstacle_yaw[i, 0], spec.obstacle_size[i, 0]
        assert shapes.footprint_gap(np, kind, pos, yaw, size, spec.target_pos[i, :2]) >= cfg.target_clearance - 1e-5
        kin = robot.forward_kinematics(np, ROBOT, spec.q0[i].astype(float))
        pp, pr = robot.primitive_poses(np, ROBOT, kin)
        d = geometry.obstacle_distance_matrix(np, ROBOT.prim_kind, pp, pr, ROBOT.prim_size, np.array([kind]), pos[None],
                                              shapes.yaw_rotation(np, np.array([float(yaw)])), size[None])
        assert d.min() >= cfg.robot_clearance - 1e-5


def test_training_mix_differs_from_the_evaluation_mix():
    cfg = train.build_config("cpu-quick", overrides=["train.obstacle_prob=0.6", "train.blocking_prob=0.5"])
    assert cfg.env.sampling.obstacle_prob == 0.2 and cfg.env.sampling.blocking_prob == 0.0  # evaluation: the task's mix
    train_env = config.training_env_config(cfg)
    assert train_env.sampling.obstacle_prob == 0.6 and train_env.sampling.blocking_prob == 0.5
    assert train_env.sampling.scene_redraws == config.BLOCKING_SCENE_REDRAWS  # blocking placements need more tries
    assert dataclasses.replace(train_env, sampling=cfg.env.sampling) == cfg.env  # nothing else differs
    trained, evaluated = train.default_envs(cfg)
    assert trained.env.cfg == train_env and evaluated.cfg == cfg.env
    for env_cfg, rate in ((train_env, 0.6), (cfg.env, 0.2)):
        spec = _resets(env_cfg.sampling, 4000, seed=1)
        assert abs(spec.obstacle_active[:, 0].mean() - rate) < 0.03
        assert spec.fallback.mean() < 0.02
    # unset (none, the default) means "the evaluation mix"
    same = train.build_config("paper", overrides=["env.sampling.obstacle_prob=0.3"])
    assert config.training_env_config(same).sampling.obstacle_prob == 0.3
    with pytest.raises(config.ConfigError, match="train.obstacle_prob"):
        train.build_config("cpu-quick", overrides=["train.obstacle_prob=1.5"])
