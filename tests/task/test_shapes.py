"""The obstacle-shape registry (``shapes.py``): every entry's maths against exact references, the
default kinds' resets pinned to what they were before the registry, and the capsule kind (lying on
the table, yawed) through sampling, blocking placement, collision and the builders.

The pinned resets (``tests/data/pinned_resets.npz``) were written by the sampler as it was before
the registry (commit 3562c70), NumPy float64, uniforms from ``default_rng(2024)``; the refactor
must reproduce them (it did bit for bit; floats are compared to 1e-12 so a different libm cannot
make the test flaky, the discrete fields exactly).
"""

from __future__ import annotations

import os

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401
import jax
import jax.numpy as jnp

from sagrasp_jax.base import assets
from sagrasp_jax.task import collision
from sagrasp_jax.task import config
from sagrasp_jax.task import config_parse
from sagrasp_jax.task import reward
from sagrasp_jax.task import robot
from sagrasp_jax.task import sampling
from sagrasp_jax.task import shapes
import exact_geometry as geometry
from paths import DATA  # noqa: E402

ROBOT = robot.load_robot()
PINS = os.path.join(DATA, "pinned_resets.npz")
PIN_CASES = {  # name -> --set overrides of the paper preset
    "paper": [],
    "obstacles": ["env.sampling.obstacle_prob=1.0"],
    "blocking": ["env.sampling.obstacle_prob=1.0", "env.sampling.blocking_prob=0.5", "env.sampling.scene_redraws=11"],
}
ALL_KINDS = ["env.sampling.obstacle_kinds=sphere,cylinder,box,capsule", "env.sampling.obstacle_candidates=12"]


def _cfg(sets: list[str]) -> config.EnvConfig:
    return config_parse.apply_overrides(config.get_config("paper"), sets).env


# ------------------------------------------------------------------ default kinds: nothing moved


@pytest.mark.parametrize("case", sorted(PIN_CASES))
def test_default_kind_resets_are_pinned(case):
    """The paper's kinds consume the same uniforms and give the same resets as before the registry."""
    pins = np.load(PINS)
    cfg = _cfg(PIN_CASES[case])
    assert cfg.sampling.obstacle_kinds == ("sphere", "cylinder", "box")
    n = sampling.uniforms_needed(cfg.sampling)
    assert n == int(pins[f"{case}/n_uniforms"])
    u = np.random.default_rng(2024).random((16, n))
    got = [sampling.sample_reset(np, ROBOT, cfg.sampling, cfg.task, u[i]) for i in range(16)]
    for field in sampling.ResetSpec._fields:
        value, pinned = np.stack([np.asarray(getattr(g, field)) for g in got]), pins[f"{case}/{field}"]
        if pinned.dtype.kind == "f":
            np.testing.assert_allclose(value, pinned, rtol=0, atol=1e-12, err_msg=f"{case}: {field}")
        else:
            np.testing.assert_array_equal(value, pinned, err_msg=f"{case}: {field}")
    if case != "paper":
        assert pins[f"{case}/obstacle_active"].sum() > 15  # the pins exercise obstacles of every kind
        assert set(pins[f"{case}/obstacle_kind"][pins[f"{case}/obstacle_active"]]) == {robot.SPHERE, robot.CYLINDER, robot.BOX}


def test_registry_is_consistent():
    assert [s.name for s in shapes.SHAPES] == list(shapes.NAMES) and len(set(shapes.BY_ID)) == len(shapes.SHAPES)
    assert shapes.PAPER_KINDS == config.SamplingConfig().obstacle_kinds
    for shape in shapes.SHAPES:
        assert shape.primitive in (robot.SPHERE, robot.CAPSULE, robot.BOX, robot.CYLINDER)
        tilt = shape.tilt_matrix
        np.testing.assert_allclose(tilt @ tilt.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(tilt) == pytest.approx(1.0)
        for key in shape.size_keys + ((shape.float_z,) if shape.float_z else ()):
            assert config.key_specs()[f"env.sampling.{key}"].range  # its size ranges are real, range-checked keys


# ------------------------------------------------------------------ every entry against exact references


def _random_obstacle(shape: shapes.ObstacleShape, rng: np.random.Generator):
    cfg = config.SamplingConfig()
    size = np.asarray(shape.sample_size(np, cfg, *rng.random(3)))
    yaw = rng.uniform(-np.pi, np.pi) if shape.yawed else 0.0
    pos = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.5, -0.2), float(shape.half_height(size))])
    return pos, yaw, size


@pytest.mark.parametrize("shape", shapes.SHAPES, ids=lambda s: s.name)
def test_entry_maths_against_the_exact_primitive(shape):
    """SDF = the exact point distance to the entry's primitive placed at ``world_rotation``; the
    surface point lies on the surface at that distance; the bounding sphere holds the surface; a
    shape resting at ``half_height`` touches the table."""
    rng = np.random.default_rng(shape.id)
    for _ in range(6):
        pos, yaw, size = _random_obstacle(shape, rng)
        rot = shapes.world_rotation(shape.id, yaw)
        points = pos + rng.normal(0.0, 0.08, (400, 3))
        d = shapes.sdf(np, shape.id, pos, yaw, size, points)
        exact = geometry.point_distance(np, shape.primitive, points, pos, rot, size)
        np.testing.assert_allclose(d, exact, atol=1e-12)
        surface = shapes.surface_point(np, shape.id, pos, yaw, size, points)
        np.testing.assert_allclose(geometry.point_distance(np, shape.primitive, surface, pos, rot, size), 0.0, atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(surface - points, axis=-1), np.abs(exact), atol=1e-12)
        assert np.all(np.linalg.norm(surface - pos, axis=-1) <= shapes.bounding_radius(np, shape.id, size) + 1e-12)
        if shape.float_z is None:
            assert geometry.plane_distance(np, shape.primitive, pos, rot, size) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("shape", shapes.SHAPES, ids=lambda s: s.name)
def test_footprint_is_the_distance_to_the_outline_seen_from_above(shape):
    """The horizontal distance from a point to the footprint is the distance from the vertical line
    through it to the shape: the minimum over heights of the exact point distance."""
    rng = np.random.default_rng(10 + shape.id)
    zs = np.linspace(-0.2, 0.6, 4001)
    for _ in range(4):
        pos, yaw, size = _random_obstacle(shape, rng)
        rot = shapes.world_rotation(shape.id, yaw)
        targets = pos[:2] + rng.uniform(-0.25, 0.25, (60, 2))
        gap = shapes.footprint_gap(np, shape.id, pos, yaw, size, targets)
        lines = np.concatenate([np.broadcast_to(targets[:, None], (60, len(zs), 2)),
                                np.broadcast_to(zs[None, :, None], (60, len(zs), 1))], -1)
        brute = geometry.point_distance(np, shape.primitive, lines, pos, rot, size).min(axis=1)
        outside = gap > 0
        assert outside.sum() > 30
        np.testing.assert_allclose(gap[outside], brute[outside], atol=1e-6)
        assert np.all(brute[~outside] <= 1e-9)  # a point inside the footprint lies under (or in) the shape


def test_kind_arrays_select_each_entry_and_only_the_given_kinds():
    rng = np.random.default_rng(5)
    kinds = np.array([s.id for s in shapes.SHAPES])
    obs = [_random_obstacle(s, rng) for s in shapes.SHAPES]
    pos, yaw, size = (np.stack([o[i] for o in obs]) for i in range(3))
    p = rng.normal(0, 0.1, (len(kinds), 3)) + pos
    mixed = shapes.sdf(np, kinds, pos, yaw, size, p)
    for i, s in enumerate(shapes.SHAPES):
        assert mixed[i] == shapes.sdf(np, s.id, pos[i], yaw[i], size[i], p[i])
    rot = shapes.primitive_rotations(np, kinds, yaw)
    for i, s in enumerate(shapes.SHAPES):
        np.testing.assert_allclose(rot[i], shapes.world_rotation(s.id, yaw[i]), atol=1e-15)


def test_collision_check_refuses_a_kind_the_config_does_not_compute():
    cfg = config.get_config("paper").env
    q = np.array(config.HOME_Q)
    spec = sampling.ResetSpec(
        q0=q, target_pos=np.array([0.3, -0.45, 0.025]), target_yaw=np.array(0.0), obstacle_active=np.array([True, False]),
        obstacle_kind=np.array([robot.CAPSULE, robot.SPHERE]), obstacle_pos=np.array([[0.1, -0.4, 0.03], [0, 0, -5]]),
        obstacle_yaw=np.zeros(2), obstacle_size=np.array([[0.03, 0.1, 0.0], [0.01, 0, 0]]), redraws=np.array(0),
        fallback=np.array(False),
    )
    kin = robot.forward_kinematics(np, ROBOT, q)
    with pytest.raises(ValueError, match="not in env.sampling.obstacle_kinds"):
        collision.check(np, ROBOT, kin, spec, cfg)
    res = collision.check(np, ROBOT, kin, spec, _cfg(ALL_KINDS))
    assert 0 < float(res.nearest_obstacle_dist) < 1.0


# ------------------------------------------------------------------ the capsule through sampling


@pytest.fixture(scope="module")
def capsule_resets():
    cfg = _cfg(ALL_KINDS + ["env.sampling.obstacle_prob=1.0"])
    n = sampling.uniforms_needed(cfg.sampling)
    u = jax.random.uniform(jax.random.PRNGKey(3), (3000, n))
    fn = jax.jit(jax.vmap(lambda x: sampling.sample_reset(jnp, ROBOT, cfg.sampling, cfg.task, x)))
    return cfg, jax.tree_util.tree_map(np.asarray, fn(u))


def test_config_selects_the_kinds():
    with pytest.raises(config.ConfigError, match="'cone'\\) is not one of sphere, cylinder, box, capsule"):
        _cfg(["env.sampling.obstacle_kinds=sphere,cone"])
    with pytest.raises(config.ConfigError, match="env.sampling.obstacle_kinds"):
        _cfg(["env.sampling.obstacle_kinds=box,box"])
    with pytest.raises(config.ConfigError, match="env.sampling.obstacle_candidates"):
        _cfg(["env.sampling.obstacle_kinds=sphere,cylinder,box,capsule", "env.sampling.obstacle_candidates=3"])
    assert _cfg(['env.sampling.obstacle_kinds=["capsule"]']).sampling.obstacle_kinds == ("capsule",)
    cfg = _cfg(ALL_KINDS)
    assert sampling.uniforms_needed(cfg.sampling) > sampling.uniforms_needed(_cfg([]).sampling)  # 12 candidates


def test_capsules_are_drawn_lying_on_the_table_and_feasible(capsule_resets):
    cfg, spec = capsule_resets
    s = cfg.sampling
    active = spec.obstacle_active
    # every scene wants obstacles here: 3 % fallbacks are 0.6 % of resets at the paper's 0.2 (docs/task.md §2.8: < 1 %)
    assert spec.fallback.mean() < 0.03 and np.array_equal(active[:, 0], spec.fallback == 0)
    kinds = spec.obstacle_kind[active]
    for k in (robot.SPHERE, robot.CYLINDER, robot.BOX, robot.CAPSULE):  # uniform draw, filtered by feasibility
        assert 0.12 < np.mean(kinds == k) < 0.4
    rows, slots = np.nonzero(active & (spec.obstacle_kind == robot.CAPSULE))
    size, pos, yaw = spec.obstacle_size[rows, slots], spec.obstacle_pos[rows, slots], spec.obstacle_yaw[rows, slots]
    assert np.all((size[:, 0] >= s.capsule_radius[0] - 1e-6) & (size[:, 0] <= s.capsule_radius[1] + 1e-6))
    assert np.all((2 * size[:, 1] >= s.capsule_length[0] - 1e-6) & (2 * size[:, 1] <= s.capsule_length[1] + 1e-6))
    np.testing.assert_allclose(pos[:, 2], size[:, 0], atol=1e-6)  # lying on the table
    assert yaw.min() < -2.5 and yaw.max() > 2.5  # yaw uniform in [−π, π)
    for i, j in list(zip(rows, slots))[:150]:  # docs/task.md §1 (a), (b) against the exact robot geometry
        p, w, z = spec.obstacle_pos[i, j], spec.obstacle_yaw[i, j], spec.obstacle_size[i, j]
        assert shapes.footprint_gap(np, robot.CAPSULE, p, w, z, spec.target_pos[i, :2]) >= s.target_clearance - 1e-5
        kin = robot.forward_kinematics(np, ROBOT, spec.q0[i].astype(float))
        pp, pr = robot.primitive_poses(np, ROBOT, kin)
        d = geometry.obstacle_distance_matrix(np, ROBOT.prim_kind, pp, pr, ROBOT.prim_size, np.array([robot.CAPSULE]),
                                              p[None].astype(float), shapes.world_rotation(robot.CAPSULE, w)[None],
                                              z[None].astype(float), obstacle_kinds=(robot.CAPSULE,))
        assert d.min() >= s.robot_clearance - 1e-5
    both = np.nonzero(active[:, 1])[0]
    for i in both[:300]:  # two obstacles never overlap
        r = shapes.bounding_radius(np, spec.obstacle_kind[i], spec.obstacle_size[i])
        assert np.linalg.norm(spec.obstacle_pos[i, 0] - spec.obstacle_pos[i, 1]) > r.sum() - 1e-6


def test_blocking_placement_puts_capsules_on_the_approach_path():
    """Slot 0's candidates of every kind go onto the approach segment (a horizontal offset of at most
    BLOCKING_OFFSET), floating kinds at its height, capsules still lying on the table.  A lying
    capsule (≤ 10 cm tall) can pass within the margin of the path only near the grasp end, where the
    target clearance forbids it, so blocking scenes hold spheres, tall cylinders and boxes: measured
    over 4,000 blocking resets with all four kinds, slot 0 was never a capsule."""
    cfg = _cfg(ALL_KINDS + ["env.sampling.obstacle_prob=1.0", "env.sampling.blocking_prob=1.0",
                            "env.sampling.scene_redraws=11"])
    s = cfg.sampling
    u = np.random.default_rng(0).random(sampling.uniforms_needed(s))
    attempts = s.scene_redraws + 1
    body = u[8:-1].reshape(attempts, -1)
    groups = sampling._kind_groups(s)
    u_obs = body[:, s.target_candidates * 3:].reshape(attempts, s.max_obstacles, s.obstacle_candidates, 8)[..., :groups.count, :]
    target_xy, _, _ = sampling._draw_targets(np, s, body[:, :s.target_candidates * 3].reshape(attempts, -1, 3))
    cand = sampling._draw_obstacles(np, s, groups, u_obs, target_xy)
    kin = robot.forward_kinematics(np, ROBOT, np.array(cfg.task.home_q))
    pos, ok = sampling._blocking_placement(np, s, cfg.task, groups, kin, u_obs, cand, target_xy, np.True_)
    start = kin.gripper_centre
    end = reward.grasp_centre(np, cfg.task, np.concatenate([target_xy, np.full((attempts, 1), 0.025)], -1))
    heading = (end - start)[:, :2] / np.linalg.norm((end - start)[:, :2], axis=-1, keepdims=True)
    rel = pos[:, 0, :, :2] - start[:2]
    lateral = np.abs(rel[..., 0] * heading[:, None, 1] - rel[..., 1] * heading[:, None, 0])
    assert lateral.max() <= sampling.BLOCKING_OFFSET + 1e-9
    capsule = cand.kind[:, 0] == robot.CAPSULE
    assert capsule.sum() == attempts * groups.per_kind
    np.testing.assert_allclose(pos[:, 0][capsule][:, 2], cand.size[:, 0][capsule][:, 0])  # lying on the table
    np.testing.assert_array_equal(pos[:, 1], cand.pos[:, 1])  # slot 1 keeps the disc placement
    assert ok[:, 0].any() and ok[:, 1].all()


# ------------------------------------------------------------------ the capsule in the builders


def test_capsule_in_the_mjcf_slots_and_the_physical_scene():
    import mujoco

    from sagrasp_jax.reference.grasp_check import GraspScene

    model = mujoco.MjModel.from_xml_path(assets.MJCF_SCENE)
    for slot in range(2):
        for shape in shapes.SHAPES:
            assert model.geom(f"obstacle_{slot}_{shape.name}").type[0] == {
                robot.SPHERE: mujoco.mjtGeom.mjGEOM_SPHERE, robot.CAPSULE: mujoco.mjtGeom.mjGEOM_CAPSULE,
                robot.BOX: mujoco.mjtGeom.mjGEOM_BOX, robot.CYLINDER: mujoco.mjtGeom.mjGEOM_CYLINDER}[shape.primitive]
    q = np.array(config.HOME_Q)
    spec = sampling.ResetSpec(
        q0=q, target_pos=np.array([0.3, -0.45, 0.025]), target_yaw=np.array(0.0), obstacle_active=np.array([True, False]),
        obstacle_kind=np.array([robot.CAPSULE, robot.SPHERE]), obstacle_pos=np.array([[0.0, -0.5, 0.03], [0, 0, -5]]),
        obstacle_yaw=np.array([0.7, 0.0]), obstacle_size=np.array([[0.03, 0.08, 0.0], [0.01, 0, 0]]),
        redraws=np.array(0), fallback=np.array(False),
    )
    scene = GraspScene(spec, q)
    geom = scene.model.geom("obstacle_0_capsule")
    np.testing.assert_allclose(geom.size[:2], [0.03, 0.08])
    assert geom.contype == 1 and geom.rgba[3] == 1.0 and scene.model.geom("obstacle_0_box").contype == 0
    np.testing.assert_allclose(scene.data.geom_xmat[geom.id].reshape(3, 3), shapes.world_rotation(robot.CAPSULE, 0.7),
                               atol=1e-6)
    np.testing.assert_allclose(scene.data.geom_xpos[geom.id], [0.0, -0.5, 0.03], atol=1e-9)


def _capsule_spec(q, centre, yaw, size=(0.03, 0.08, 0.0)) -> sampling.ResetSpec:
    return sampling.ResetSpec(
        q0=np.asarray(q, float), target_pos=np.array([0.3, -0.45, 0.025]), target_yaw=np.array(0.0),
        obstacle_active=np.array([True, False]), obstacle_kind=np.array([robot.CAPSULE, robot.SPHERE]),
        obstacle_pos=np.array([centre, [0, 0, -5]], float), obstacle_yaw=np.array([yaw, 0.0]),
        obstacle_size=np.array([size, [0.01, 0, 0]], float), redraws=np.array(0), fallback=np.array(False),
    )


def test_capsule_in_the_pybullet_reference_env_and_the_twin():
    """Both PyBullet builders place the capsule where the maths has it: PyBullet's own closest
    distance equals the exact one, and the twin's body has the registry's world rotation."""
    pytest.importorskip("pybullet")
    pytest.importorskip("gymnasium")
    import pybullet as pb

    from sagrasp_jax.deploy.twin import PyBulletTwin
    from sagrasp_jax.reference.pybullet_env import PyBulletGraspEnv, quaternions_to_rotations

    cfg = _cfg(ALL_KINDS + ["env.task.obs_noise_std=0.0"])
    q = np.array(config.HOME_Q)
    kin = robot.forward_kinematics(np, ROBOT, q)
    pp, pr = robot.primitive_poses(np, ROBOT, kin)
    env = PyBulletGraspEnv(cfg)
    try:
        # beside the upper arm (capsule-capsule: PyBullet is exact) and under the gripper (its
        # box-vs-round queries are good to ~2e-4, the same for a sphere there)
        for offset, tol in (((0.0, 0.2, -0.1), 1e-9), ((0.05, -0.04, -0.12), 5e-4)):
            centre = kin.gripper_centre + np.array(offset)
            spec = _capsule_spec(q, centre, 0.9)
            exact = geometry.obstacle_distance_matrix(
                np, ROBOT.prim_kind, pp, pr, ROBOT.prim_size, np.array([robot.CAPSULE]), centre[None],
                shapes.world_rotation(robot.CAPSULE, 0.9)[None], np.array([[0.03, 0.08, 0.0]]), obstacle_kinds=(robot.CAPSULE,),
            ).min()
            assert 0.005 < exact < 0.1
            obs, _ = env.reset(options={"reset_spec": spec})
            assert env.pybullet_distance()["obstacle_0"] == pytest.approx(exact, abs=tol)
            assert abs(obs[15] - exact) <= collision.FINE_ERROR + 1e-6  # Δpo from the shared rules
    finally:
        env.close()
    with PyBulletTwin(spec, cfg, q0=q) as twin:
        _, quat = pb.getBasePositionAndOrientation(twin.obstacle_bodies[0], physicsClientId=twin._client)
        np.testing.assert_allclose(quaternions_to_rotations(np.asarray(quat)), shapes.world_rotation(robot.CAPSULE, 0.9),
                                   atol=1e-6)


def test_privileged_critic_one_hot_follows_the_kinds():
    """The critic's kind one-hot has one entry per kind of env.sampling.obstacle_kinds (the paper's three by default)."""
    from sagrasp_jax.task import observation

    assert observation.privileged_layout(_cfg([]))[3:8] == (
        "obstacle0_present", "obstacle0_sphere", "obstacle0_cylinder", "obstacle0_box", "obstacle0_size_x")
    cfg = _cfg(ALL_KINDS)
    names = observation.privileged_layout(cfg)
    assert len(names) == 3 + 2 * (1 + 4 + 7)
    q = np.array(config.HOME_Q)
    kin = robot.forward_kinematics(np, ROBOT, q)
    spec = _capsule_spec(q, kin.gripper_centre + np.array([0.0, 0.2, -0.1]), 0.9)
    col = collision.check(np, ROBOT, kin, spec, cfg)
    extra = dict(zip(names, observation.privileged(np, cfg, spec, col, kin.gripper_centre, 0, 0.0, False)))
    assert [extra[f"obstacle0_{k}"] for k in ("sphere", "cylinder", "box", "capsule")] == [0.0, 0.0, 0.0, 1.0]
