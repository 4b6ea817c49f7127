"""Observation layouts (docs/task.md §2 "Layouts"): the paper's 17 numbers and the relative obstacle encoding,
hand-computed for no obstacle, one, and two (sorted nearest first); the normaliser leaves the
hand-scaled entries alone; NumPy and JAX build the same vector."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401
from sagrasp_jax.task import collision
from sagrasp_jax.task import config
from sagrasp_jax.task import config_parse
from sagrasp_jax.task import observation
from sagrasp_jax.task import robot
from sagrasp_jax.task import sampling
import exact_geometry as geometry

ROBOT = robot.load_robot()
HOME = np.array(config.HOME_Q)
TARGET = (0.2, -0.45, 0.025)


def env_cfg(layout: str) -> config.EnvConfig:
    cfg = config.get_config("paper").env
    return dataclasses.replace(cfg, task=dataclasses.replace(cfg.task, obs_layout=layout))


def spec(obstacles: list[tuple[int, tuple, tuple]] = ()) -> sampling.ResetSpec:
    """Up to two (kind, centre, size) obstacles in slots 0, 1; empty slots parked as the deploy loop does."""
    active, kind = np.zeros(2, bool), np.full(2, robot.SPHERE)
    pos, size = np.array([[0, 0, -5.0]] * 2), np.full((2, 3), 0.01)
    for i, (k, c, s) in enumerate(obstacles):
        active[i], kind[i], pos[i], size[i] = True, k, c, s
    return sampling.ResetSpec(q0=HOME, target_pos=np.array(TARGET), target_yaw=np.array(0.0), obstacle_active=active,
                              obstacle_kind=kind, obstacle_pos=pos, obstacle_yaw=np.zeros(2), obstacle_size=size,
                              redraws=np.array(0), fallback=np.array(False))


def observe(layout: str, scene: sampling.ResetSpec) -> tuple[dict[str, float], np.ndarray]:
    cfg = env_cfg(layout)
    seen = observation.observe(np, ROBOT, cfg, HOME, scene)
    names = observation.layout_of(cfg)
    assert seen.obs.shape == (len(names),)
    return dict(zip(names, seen.obs)), seen.kin.gripper_centre


def exact_distance(kind: int, centre, size) -> float:
    """Robot-to-obstacle distance from the exact primitive pair distances (the test oracle)."""
    kin = robot.forward_kinematics(np, ROBOT, HOME)
    prim_pos, prim_rot = robot.primitive_poses(np, ROBOT, kin)
    moving = ROBOT.prim_link >= 1
    d = geometry.obstacle_distance_matrix(np, ROBOT.prim_kind[moving], prim_pos[moving], prim_rot[moving],
                                          ROBOT.prim_size[moving], np.array([kind]), np.array([centre], float),
                                          np.eye(3)[None], np.array([size], float))
    return float(d.min())


def robot_sdf(point) -> float:
    """Exact signed distance from a point to the robot's moving primitives at the home pose."""
    kin = robot.forward_kinematics(np, ROBOT, HOME)
    prim_pos, prim_rot = robot.primitive_poses(np, ROBOT, kin)
    return min(float(geometry.point_distance(np, int(ROBOT.prim_kind[g]), np.asarray(point, float), prim_pos[g],
                                             prim_rot[g], ROBOT.prim_size[g]))
               for g in range(len(ROBOT.primitives)) if ROBOT.prim_link[g] >= 1)


def test_layout_names_and_sizes():
    assert observation.layout("paper") == observation.OBS_LAYOUT and len(observation.OBS_LAYOUT) == 17
    rel = observation.layout("relative")
    assert len(rel) == 29 and rel[:13] == observation.OBS_LAYOUT[:12] + ("theta_gz",)
    assert rel[13:21] == ("obstacle0_present", "obstacle0_gripper_dx", "obstacle0_gripper_dy", "obstacle0_gripper_dz",
                          "obstacle0_robot_dx", "obstacle0_robot_dy", "obstacle0_robot_dz", "obstacle0_closeness")
    mask = observation.hand_scaled_mask(rel)
    assert mask.sum() == 16 and mask[13:].all() and not mask[:13].any()
    assert not observation.hand_scaled_mask(observation.OBS_LAYOUT).any()
    with pytest.raises(ValueError, match="layout"):
        observation.layout("absolute")


def test_no_obstacle():
    paper, centre = observe("paper", spec())
    assert (paper["obstacle_x"], paper["obstacle_y"], paper["obstacle_z"], paper["d_po"]) == (0.0, 0.0, -1.0, 1.0)
    rel, _ = observe("relative", spec())
    assert all(rel[k] == 0.0 for k in rel if k.startswith("obstacle"))  # "absent" is all zeros
    np.testing.assert_allclose([rel["gripper_x"], rel["gripper_y"], rel["gripper_z"]], [0.0, -0.30, 0.35], atol=1e-9)
    np.testing.assert_allclose([rel["target_x"], rel["target_y"], rel["target_z"]], TARGET)
    assert rel["theta_gz"] == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose([rel[f"q{i + 1}"] for i in range(6)], HOME)


def test_one_sphere_below_the_gripper():
    """A sphere of radius 5 cm centred 25 cm straight below the gripper centre (0, −0.30, 0.35)."""
    centre, size = (0.0, -0.30, 0.10), (0.05, 0.0, 0.0)
    rel, _ = observe("relative", spec([(robot.SPHERE, centre, size)]))
    task = config.TaskConfig()
    assert rel["obstacle0_present"] == 1.0
    # gripper centre → nearest sphere point (0, −0.30, 0.15): (0, 0, −0.20), divided by 0.25 m
    np.testing.assert_allclose([rel["obstacle0_gripper_dx"], rel["obstacle0_gripper_dy"], rel["obstacle0_gripper_dz"]],
                               [0.0, 0.0, -0.20 / task.obs_vector_scale], atol=1e-9)
    exact = exact_distance(robot.SPHERE, centre, size)
    robot_vec = np.array([rel["obstacle0_robot_dx"], rel["obstacle0_robot_dy"], rel["obstacle0_robot_dz"]])
    assert np.linalg.norm(robot_vec) * task.obs_vector_scale == pytest.approx(exact, abs=collision.FINE_ERROR + 1e-9)
    # the vector ends on the sphere and points at its centre, so it starts at p_r = c − (|v| + r)·v/|v|:
    # that point must lie on the robot's surface
    v = robot_vec * task.obs_vector_scale
    p_r = np.array(centre) - (np.linalg.norm(v) + size[0]) * v / np.linalg.norm(v)
    assert robot_sdf(p_r) == pytest.approx(0.0, abs=collision.FINE_ERROR + 1e-9)
    assert rel["obstacle0_closeness"] == pytest.approx(max(0.0, 1 - exact / task.obs_closeness_range), abs=0.03)
    assert all(rel[k] == 0.0 for k in rel if k.startswith("obstacle1_"))
    paper, _ = observe("paper", spec([(robot.SPHERE, centre, size)]))
    assert (paper["obstacle_x"], paper["obstacle_y"], paper["obstacle_z"]) == centre
    assert paper["d_po"] == pytest.approx(exact, abs=collision.FINE_ERROR + 1e-9)


def test_two_obstacles_sorted_nearest_first_and_vectors_clipped():
    """Slot 0 holds the far obstacle, slot 1 the near one: the observation lists the near one first."""
    far = (robot.CYLINDER, (0.30, -0.55, 0.10), (0.03, 0.10, 0.0))  # 10 cm high, 25 cm off the home path
    near = (robot.BOX, (0.0, -0.30, 0.20), (0.04, 0.04, 0.04))  # 11 cm below the gripper centre
    rel, gripper = observe("relative", spec([far, near]))
    task = config.TaskConfig()
    # near box: the gripper centre is above its top face (z = 0.24): vector (0, 0, −0.11)
    np.testing.assert_allclose([rel["obstacle0_gripper_dx"], rel["obstacle0_gripper_dy"], rel["obstacle0_gripper_dz"]],
                               [0.0, 0.0, -0.11 / task.obs_vector_scale], atol=1e-9)
    # far cylinder: nearest surface point is on its rim, top at z = 0.20
    to_axis = np.array([0.30, -0.55]) - gripper[:2]
    rim = np.array([*(gripper[:2] + to_axis * (1 - 0.03 / np.linalg.norm(to_axis))), 0.20])
    expect = np.clip((rim - gripper) / task.obs_vector_scale, -task.obs_vector_clip, task.obs_vector_clip)
    np.testing.assert_allclose([rel["obstacle1_gripper_dx"], rel["obstacle1_gripper_dy"], rel["obstacle1_gripper_dz"]],
                               expect, atol=1e-9)
    assert rel["obstacle0_present"] == rel["obstacle1_present"] == 1.0
    assert rel["obstacle0_closeness"] > rel["obstacle1_closeness"]
    d_near, d_far = (exact_distance(k, c, s) for k, c, s in (near, far))
    for slot, d in (("obstacle0", d_near), ("obstacle1", d_far)):
        v = np.array([rel[f"{slot}_robot_dx"], rel[f"{slot}_robot_dy"], rel[f"{slot}_robot_dz"]]) * task.obs_vector_scale
        assert np.linalg.norm(v) == pytest.approx(d, abs=collision.FINE_ERROR + 1e-9)
    # swapping the slots changes nothing
    swapped, _ = observe("relative", spec([near, far]))
    np.testing.assert_allclose([swapped[k] for k in rel], [rel[k] for k in rel], atol=1e-12)
    # a vector longer than obs_vector_clip × scale is clipped
    high = (robot.SPHERE, (0.0, 0.60, 0.35), (0.03, 0.0, 0.0))
    rel, _ = observe("relative", spec([high]))
    assert rel["obstacle0_gripper_dy"] == task.obs_vector_clip


def test_numpy_and_jax_agree():
    import jax
    import jax.numpy as jnp

    scene = spec([(robot.BOX, (0.1, -0.4, 0.05), (0.03, 0.05, 0.05)), (robot.SPHERE, (-0.1, -0.35, 0.2), (0.04, 0, 0))])
    cfg = env_cfg("relative")
    ref = observation.observe(np, ROBOT, cfg, HOME, scene).obs
    fn = jax.jit(lambda q, s: observation.observe(jnp, ROBOT, cfg, q, s).obs)
    got = fn(jnp.asarray(HOME, jnp.float32), jax.tree_util.tree_map(jnp.asarray, scene))
    theta = observation.layout("relative").index("theta_gz")  # float32 arccos near 1 resolves ~3e-4 rad
    np.testing.assert_allclose(np.delete(np.asarray(got), theta), np.delete(ref, theta), atol=2e-5)
    assert abs(float(got[theta]) - ref[theta]) < 5e-4


def test_normaliser_leaves_hand_scaled_entries_alone():
    import jax.numpy as jnp
    from brax.training.acme import running_statistics

    from sagrasp_jax.training.agents.ppo import ppo

    mask = observation.hand_scaled_mask(observation.layout("relative"))
    obs = jnp.asarray(np.random.default_rng(0).normal(3.0, 2.0, (512, 29)), jnp.float32)
    state = running_statistics.init_state(jnp.zeros((29,), jnp.float32))
    state = ppo.update_normaliser(state, obs, config.PPOConfig(), mask)
    mean, std = np.asarray(state.mean), np.asarray(state.std)
    np.testing.assert_array_equal(mean[mask], 0.0)
    np.testing.assert_array_equal(std[mask], 1.0)
    assert np.all(np.abs(mean[~mask] - 3.0) < 0.3) and np.all(np.abs(std[~mask] - 2.0) < 0.3)


def test_privileged_critic_inputs():
    """What only the critic sees: progress, time fraction, blocking, and per slot kind/size/centre/distance."""
    cfg = env_cfg("relative")
    box = (robot.BOX, (0.0, -0.30, 0.20), (0.04, 0.05, 0.06))
    scene = spec([box])
    kin = robot.forward_kinematics(np, ROBOT, HOME)
    col = collision.check(np, ROBOT, kin, scene, cfg)
    names = observation.privileged_layout(cfg)
    extra = dict(zip(names, observation.privileged(np, cfg, scene, col, kin.gripper_centre, steps=50, progress=0.25,
                                                   blocking=True)))
    assert len(names) == 25
    assert (extra["progress"], extra["time_fraction"], extra["blocking"]) == (0.25, 0.25, 1.0)
    assert (extra["obstacle0_present"], extra["obstacle0_sphere"], extra["obstacle0_cylinder"], extra["obstacle0_box"]) \
        == (1.0, 0.0, 0.0, 1.0)
    np.testing.assert_allclose([extra["obstacle0_size_x"], extra["obstacle0_size_y"], extra["obstacle0_size_z"]],
                               [0.4, 0.5, 0.6])
    np.testing.assert_allclose([extra["obstacle0_dx"], extra["obstacle0_dy"], extra["obstacle0_dz"]],
                               [0.0, 0.0, -0.15 / 0.25], atol=1e-9)
    assert extra["obstacle0_distance"] == pytest.approx(float(col.obstacle_dist[0]) / 0.25)
    assert all(extra[n] == 0.0 for n in names if n.startswith("obstacle1_"))  # empty slot
    full = config_parse.apply_overrides(config.get_config("paper"), ["ppo.privileged_critic=true"])
    assert observation.critic_extra_size(full) == 25
    assert observation.critic_extra_size(config.get_config("paper")) == 0


def test_privileged_critic_trains_and_exports_a_policy_without_it(tmp_path):
    """The value network reads observation + privileged inputs; the policy and its export do not."""
    import jax
    import jax.numpy as jnp

    from sagrasp_jax import train
    from sagrasp_jax.training.agents.ppo import actor_critic
    from sagrasp_jax.training.agents.ppo import ppo
    from sagrasp_jax.task import policy_file as runtime
    from sagrasp_jax.envs.grasp_env import GraspEnv

    cfg = train.build_config("cpu-quick", overrides=["env.task.obs_layout=relative", "ppo.privileged_critic=true",
                                                     "ppo.num_envs=8", "ppo.unroll_length=4", "ppo.num_minibatches=1",
                                                     "ppo.num_epochs=1"])
    env = GraspEnv(cfg.env, privileged=True)
    state = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), 8))
    assert state.info["privileged"].shape == (8, 25) and state.obs.shape == (8, 29)
    nets = actor_critic.make_networks(cfg.ppo.network, 29, 6, cfg.ppo.obs_clip, critic_extra=25)
    ts = actor_critic.init_training_state(jax.random.PRNGKey(1), nets, actor_critic.make_optimizer(cfg.ppo), 29)
    assert ts.params.value["params"]["hidden_0"]["kernel"].shape[0] == 54
    assert ts.params.policy["params"]["hidden_0"]["kernel"].shape[0] == 29
    step = jax.jit(lambda t, s, k: ppo.iteration(t, s, k, jnp.float32(0.5), jnp.float32(3e-4), env=_Batched(env),
                                                 networks=nets,
                                                 optimizer=actor_critic.make_optimizer(cfg.ppo), cfg=cfg.ppo,
                                                 critic_extra=25))
    new_ts, _, metrics = step(ts, state, jax.random.PRNGKey(2))
    assert bool(metrics["finite"]) and float(metrics["value_loss"]) > 0
    path = runtime.save_policy_npz(tmp_path / "p.npz", weights=[(np.asarray(l["kernel"]), np.asarray(l["bias"]))
                                   for l in jax.device_get(new_ts.params.policy["params"]).values()],
                                   activation="tanh", obs_mean=np.zeros(29), obs_std=np.ones(29), config=cfg,
                                   obs_layout=observation.layout_of(cfg.env))
    assert runtime.load_policy(path).obs_size == 29


class _Batched:
    """vmap a single-env GraspEnv for the rollout (no auto-reset needed for one short rollout)."""

    def __init__(self, env):
        self.env, self.observation_size, self.action_size = env, env.observation_size, env.action_size

    def reset(self, rng):
        return self.env.reset(rng)

    def step(self, state, action):
        return self.env.step(state, action)


def shaped_cfg(layout: str = "relative") -> config.EnvConfig:
    cfg = env_cfg(layout)
    return dataclasses.replace(cfg, task=dataclasses.replace(cfg.task, obs_obstacle_shape=True))


def test_obstacle_shape_entries_give_centre_and_bounding_box():
    """``env.task.obs_obstacle_shape``: per slot the vector to the obstacle's centre and its world-aligned
    bounding box's half-extents, hand-computed for a yawed box and an upright cylinder, sorted with their slots."""
    box = (robot.BOX, (0.0, -0.30, 0.20), (0.04, 0.02, 0.03))  # yawed 30° below: reaches 0.0446 / 0.0373 in x / y
    cyl = (robot.CYLINDER, (0.30, -0.55, 0.10), (0.03, 0.10, 0.0))
    scene = spec([cyl, box])._replace(obstacle_yaw=np.array([0.0, np.pi / 6]))
    cfg = shaped_cfg()
    names = observation.layout_of(cfg)
    assert len(names) == 29 + 12 and names[21:27] == tuple(f"obstacle0_{e}" for e in (
        "centre_dx", "centre_dy", "centre_dz", "extent_x", "extent_y", "extent_z"))
    assert observation.hand_scaled_mask(names)[13:].all()
    seen = observation.observe(np, ROBOT, cfg, HOME, scene)
    rel, gripper = dict(zip(names, seen.obs)), seen.kin.gripper_centre
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
    task = cfg.task
    for slot, (kind, centre, size), half in (("obstacle0", box, (c * 0.04 + s * 0.02, s * 0.04 + c * 0.02, 0.03)),
                                             ("obstacle1", cyl, (0.03, 0.03, 0.10))):
        expect = np.clip((np.array(centre) - gripper) / task.obs_vector_scale, -task.obs_vector_clip, task.obs_vector_clip)
        np.testing.assert_allclose([rel[f"{slot}_centre_d{a}"] for a in "xyz"], expect, atol=1e-9)
        np.testing.assert_allclose([rel[f"{slot}_extent_{a}"] for a in "xyz"], np.array(half) / observation.EXTENT_SCALE,
                                   atol=1e-9)
    # the entries of the plain layout are unchanged, and an empty slot is all zeros
    plain = dict(zip(observation.layout_of(env_cfg("relative")), observation.observe(np, ROBOT, env_cfg("relative"),
                                                                                     HOME, scene).obs))
    assert all(rel[k] == v for k, v in plain.items())
    one = dict(zip(names, observation.observe(np, ROBOT, cfg, HOME, spec([box])).obs))
    assert all(one[k] == 0.0 for k in names if k.startswith("obstacle1_"))
    assert observation.blind(np, cfg, seen.obs)[13:].tolist() == [0.0] * 28


@pytest.mark.parametrize("kind", ["sphere", "cylinder", "box", "capsule"])
def test_obstacle_extent_holds_every_surface_point_and_is_reached(kind):
    """The bounding box of shapes.extent holds the shape and touches it on every axis: sampled points of the
    sampled sizes and yaws, inside by the SDF, never leave it, and the box is no more than 2 mm too wide."""
    from sagrasp_jax.task import shapes

    shape = shapes.BY_NAME[kind]
    rng = np.random.default_rng(3)
    u = rng.uniform(size=(3, 3))
    sizes = shape.sample_size(np, config.SamplingConfig(), u[:, 0], u[:, 1], u[:, 2])
    for size, yaw in zip(sizes, rng.uniform(-np.pi, np.pi, 3)):
        half = shapes.extent(np, shape.id, np.asarray(yaw), size)
        points = rng.uniform(-1, 1, (200_000, 3)) * (half + 0.01)
        inside = shapes.sdf(np, shape.id, np.zeros(3), np.asarray(yaw), size, points) <= 0
        reach = np.abs(points[inside]).max(axis=0)
        assert np.all(reach <= half + 1e-9) and np.all(reach >= half - 0.002), (size, yaw, reach, half)


def test_obstacle_shape_and_jax_agree_and_paper_layout_refuses_it():
    import jax
    import jax.numpy as jnp

    scene = spec([(robot.BOX, (0.1, -0.4, 0.05), (0.03, 0.05, 0.05)), (robot.CYLINDER, (-0.1, -0.35, 0.1), (0.03, 0.1, 0))])
    scene = scene._replace(obstacle_yaw=np.array([0.7, 0.0]))
    cfg = shaped_cfg("relative_lag")
    ref = observation.observe(np, ROBOT, cfg, HOME, scene).obs
    got = jax.jit(lambda q, s: observation.observe(jnp, ROBOT, cfg, q, s).obs)(
        jnp.asarray(HOME, jnp.float32), jax.tree_util.tree_map(jnp.asarray, scene))
    theta = observation.layout_of(cfg).index("theta_gz")
    np.testing.assert_allclose(np.delete(np.asarray(got), theta), np.delete(ref, theta), atol=2e-5)
    with pytest.raises(config.ConfigError, match="obs_obstacle_shape=true needs a relative observation layout"):
        config_parse.apply_overrides(config.get_config("paper"), ["env.task.obs_obstacle_shape=true"])
    with pytest.raises(ValueError, match="relative layout"):
        observation.layout("paper", 2, obstacle_shape=True)
