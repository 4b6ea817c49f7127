"""A new obstacle kind is one registry entry: a toy kind, an upright capsule ("post"), added here by one
``shapes.ObstacleShape`` entry and its shape maths through ``shapes.registered`` (the registry is restored
after), runs through the config, the scene MJCF, the MJX env, the PyBullet twin and reference env, and
perception, with no package file naming it (docs/architecture.md, "Obstacle shapes")."""

from __future__ import annotations

import math

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401
from sagrasp_jax.task import collision
from sagrasp_jax.task import config, config_history, config_parse
from sagrasp_jax.task import robot
from sagrasp_jax.task import sampling
from sagrasp_jax.task import shapes
from sagrasp_jax.task.point_fits import fit_sphere

ROBOT = robot.load_robot()
POST_ID = 4  # the first id no shipped kind uses


# ---------------------------------------------------------------------- the toy kind: its shape maths and entry


def _post_size(xp, cfg, u1, u2, u3):
    """Radius from cylinder_radius, full height (tip to tip) from cylinder_height: no config key of its own."""
    r = cfg.cylinder_radius[0] + (cfg.cylinder_radius[1] - cfg.cylinder_radius[0]) * u1
    height = cfg.cylinder_height[0] + (cfg.cylinder_height[1] - cfg.cylinder_height[0]) * u2
    return xp.stack([r, xp.maximum(height / 2 - r, 0.0), xp.zeros_like(u1)], axis=-1)


def _post_sdf(xp, v, size):
    """Distance to the vertical axis segment |z| ≤ half axis, minus the radius."""
    return xp.sqrt(v[0] ** 2 + v[1] ** 2 + xp.maximum(xp.abs(v[2]) - size[..., 1], 0.0) ** 2) - size[..., 0]


def _post_surface(xp, v, size):
    r, h = size[..., 0], size[..., 1]
    az = xp.clip(v[2], -h, h)  # nearest point of the axis
    dz = v[2] - az
    n = xp.sqrt(v[0] ** 2 + v[1] ** 2 + dz**2)
    scale = r / xp.maximum(n, 1e-12)
    on_axis = n < 1e-12
    return (xp.where(on_axis, r, v[0] * scale), xp.where(on_axis, 0.0, v[1] * scale), xp.where(on_axis, az, az + dz * scale))


def _post_fit(seen):
    """Its axis through the centre of a sphere fitted to the rounded top (the points within 15 mm of the top), its
    radius the points' farthest horizontal reach from that axis (98th percentile, plus half a pixel); it stands
    on the table as tall as the object's top."""
    band = seen.height >= seen.top - min(0.015, seen.top / 3)
    if band.sum() < 10:
        return None
    c, _ = fit_sphere(seen.points[band])
    reach = np.linalg.norm(seen.points[:, :2] - c[:2], axis=1)
    r = float(np.percentile(reach, 98)) + seen.face.pitch / 2
    half = seen.top / 2
    if not 0.005 < r <= half:
        return None
    return np.array([c[0], c[1], seen.base_z + half]), np.array([r, half - r, 0.0]), 0.0


def _post_cover(box):
    """Round the box, its caps past the table and the top."""
    r = box.round_r
    return np.array([r, box.top / 2, 0.0]), 0.0, math.pi * r**2 * box.top + 4.0 / 3.0 * math.pi * r**3


POST = shapes.ObstacleShape(
    id=POST_ID, name="post", primitive=robot.CAPSULE, tilt=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    yawed=False, float_z=None, size_keys=("cylinder_radius", "cylinder_height"), sample_size=_post_size,
    half_height=lambda size: size[..., 0] + size[..., 1], sdf=_post_sdf, surface=_post_surface,
    bounding_radius=lambda xp, size: size[..., 0] + size[..., 1],
    footprint=lambda xp, d, yaw, size: xp.sqrt(xp.sum(d**2, axis=-1)) - size[..., 0],
    extent=lambda xp, yaw, size: xp.stack([size[..., 0], size[..., 0], size[..., 0] + size[..., 1]], axis=-1),
    cli_lengths=("R", "H"), from_lengths=lambda ls: (ls[0], ls[1] / 2 - ls[0], 0.0),
    perception=shapes.Perceived(
        fit=_post_fit, cover=_post_cover, reach=lambda size: float(size[0]),
        hull_points=lambda c, size, yaw: shapes.ring_points([c[:2]], float(size[0]), c[2] - size[0] - size[1],
                                                            c[2] + size[0] + size[1])),
)

# a post beside the approach, clear of the cube at (0.05, -0.45): radius 4 cm, 20 cm tall
POST_SIZE = np.array([0.04, 0.06, 0.0])
POST_POS = np.array([0.20, -0.32, 0.10])
TARGET = np.array([0.08, -0.48, 0.025])


@pytest.fixture
def post():
    with shapes.registered(POST):
        yield POST


def _cfg(overrides=()):
    return config_parse.apply_overrides(config.get_config("paper"), ["env.sampling.obstacle_kinds=sphere,cylinder,box,post",
                                                               *overrides])


def _spec(q=config.HOME_Q):
    return sampling.ResetSpec(
        q0=np.asarray(q, float), target_pos=TARGET.copy(), target_yaw=np.array(0.2),
        obstacle_active=np.array([True, False]), obstacle_kind=np.array([POST_ID, robot.SPHERE]),
        obstacle_pos=np.array([POST_POS, [0.0, 0.0, -5.0]]), obstacle_yaw=np.array([0.0, 0.0]),
        obstacle_size=np.array([POST_SIZE, [0.01, 0.0, 0.0]]), redraws=np.array(0), fallback=np.array(False),
    )


def _exact_distance(q, pos=POST_POS, size=POST_SIZE):
    """Δpo by hand: the fine sphere set of the arm at ``q`` against the toy's own sdf (not through the registry)."""
    kin = robot.forward_kinematics(np, ROBOT, np.asarray(q, float))
    cover = collision.fine_cover(ROBOT)
    centres = collision.cover_centres(np, ROBOT, kin, cover)
    v = centres - pos
    return float(np.min(_post_sdf(np, (v[:, 0], v[:, 1], v[:, 2]), size) - cover.radius))


# ---------------------------------------------------------------------- the registry and the config


def test_a_registered_kind_is_known_everywhere_and_forgotten_after():
    assert "post" not in shapes.NAMES
    with pytest.raises(config.ConfigError, match="'post'\\) is not one of sphere, cylinder, box, capsule"):
        _cfg()
    with shapes.registered(POST):
        assert shapes.NAMES[-1] == "post" and shapes.BY_ID[POST_ID] is POST
        cfg = _cfg()
        assert cfg.env.sampling.obstacle_kinds[-1] == "post"
        assert "post" in config.key_specs()["env.sampling.obstacle_kinds"].choices
        assert "env.sampling.obstacle_kinds" not in config_history.ADDED_KEYS  # no config key of its own: nothing to add
        from sagrasp_jax.deploy import yolo
        assert yolo.classes()[-1] == "post" and yolo.CLASSES == yolo.classes()
        with pytest.raises(ValueError, match="name 'post' is taken"):
            shapes.register(POST)
    import dataclasses

    with pytest.raises(ValueError, match="'cone' cannot be registered: id 3 is taken by 'cylinder'; primitive 7 is not one of"):
        shapes.register(dataclasses.replace(POST, id=robot.CYLINDER, name="cone", primitive=7))
    assert "post" not in shapes.NAMES and POST_ID not in shapes.BY_ID
    with pytest.raises(config.ConfigError, match="is not one of sphere, cylinder, box, capsule"):
        _cfg()


def test_its_sampled_sizes_and_placement(post):
    cfg = _cfg(["env.sampling.obstacle_kinds=post", "env.sampling.obstacle_prob=1.0"]).env
    u = np.random.default_rng(0).random((200, sampling.uniforms_needed(cfg.sampling)))
    specs = [sampling.sample_reset(np, ROBOT, cfg.sampling, cfg.task, x) for x in u]
    posts = [(s.obstacle_pos[i], s.obstacle_size[i]) for s in specs for i in np.nonzero(s.obstacle_active)[0]]
    assert len(posts) > 100 and all(int(s.obstacle_kind[i]) == POST_ID for s in specs for i in np.nonzero(s.obstacle_active)[0])
    for pos, size in posts:
        assert 0.02 <= size[0] <= 0.05 and 0.10 - 1e-9 <= 2 * (size[0] + size[1]) <= 0.30 + 1e-9
        assert pos[2] == pytest.approx(size[0] + size[1])  # standing on the table


# ---------------------------------------------------------------------- the scene MJCF


def test_the_scene_mjcf_gets_its_slot_geoms_when_loaded(post):
    import mujoco

    from sagrasp_jax.base import assets
    from sagrasp_jax.reference.grasp_check import GraspScene
    from sagrasp_jax.task import scene_mjcf

    packaged = mujoco.MjModel.from_xml_path(assets.MJCF_SCENE)  # the shipped file does not know the toy kind
    assert mujoco.mj_name2id(packaged, mujoco.mjtObj.mjOBJ_GEOM, "obstacle_0_post") == -1
    model = scene_mjcf.load_scene_model()
    assert model.ngeom == packaged.ngeom + 2
    for slot in range(2):
        assert model.geom(f"obstacle_{slot}_post").type[0] == mujoco.mjtGeom.mjGEOM_CAPSULE
    scene = GraspScene(_spec(), config.HOME_Q)  # the physical check's scene, compiled by MuJoCo
    geom = scene.model.geom("obstacle_0_post")
    assert geom.contype == 1 and geom.rgba[3] == 1.0 and scene.model.geom("obstacle_0_cylinder").contype == 0
    np.testing.assert_allclose(geom.size[:2], POST_SIZE[:2])
    np.testing.assert_allclose(scene.data.geom_xpos[geom.id], POST_POS, atol=1e-9)
    np.testing.assert_allclose(scene.data.geom_xmat[geom.id].reshape(3, 3), np.eye(3), atol=1e-9)  # upright
    # MuJoCo's own ray cast down onto it meets the surface where the toy's sdf is zero
    for dx, dy in ((0.0, 0.0), (0.02, -0.01), (-0.03, 0.0)):
        start = POST_POS + np.array([dx, dy, 0.5 - POST_POS[2]])
        hit = np.zeros(1, np.int32)
        t = mujoco.mj_ray(scene.model, scene.data, start, np.array([0.0, 0.0, -1.0]), None, 1, -1, hit)
        assert hit[0] == geom.id
        v = start + np.array([0.0, 0.0, -t]) - POST_POS
        assert abs(float(_post_sdf(np, tuple(v), POST_SIZE))) < 1e-9
        assert v[2] == pytest.approx(POST_SIZE[1] + math.sqrt(POST_SIZE[0] ** 2 - dx**2 - dy**2))


def test_a_stale_slot_geom_is_refused_naming_the_command():
    """A scene whose geom for a kind no longer draws it as its entry says (the entry changed since) is refused."""
    import dataclasses

    from sagrasp_jax.task import scene_mjcf

    with shapes.registered(POST):
        spec = scene_mjcf.load_scene_spec()  # upright post geoms added
    lying = dataclasses.replace(POST, tilt=((0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0)))
    with shapes.registered(lying):
        with pytest.raises(ValueError, match="'obstacle_0_post' .*stale, run python tools/urdf_to_mjcf.py"):
            scene_mjcf.complete_obstacle_slots(spec)


# ---------------------------------------------------------------------- the MJX env


def test_the_mjx_env_draws_it_and_measures_its_distance(post):
    import jax
    import jax.numpy as jnp

    from sagrasp_jax.envs.grasp_env import GraspEnv

    cfg = _cfg(["env.sampling.obstacle_kinds=post", "env.sampling.obstacle_prob=1.0", "env.control.mode=kinematic",
                "env.task.obs_layout=paper", "env.task.obstacle_geometry=fine", "env.task.obs_noise_std=0.0"]).env
    env = GraspEnv(cfg)
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    checked = 0
    for seed in range(4):
        state = reset(jax.random.PRNGKey(seed))
        spec = jax.tree_util.tree_map(np.asarray, state.info["reset"])
        active = np.nonzero(spec.obstacle_active)[0]
        assert len(active) and all(int(spec.obstacle_kind[i]) == POST_ID for i in active)
        for _ in range(4):
            q = np.asarray(env.measured_joints(state), float)
            exact = min(_exact_distance(q, spec.obstacle_pos[i], spec.obstacle_size[i]) for i in active)
            assert float(state.obs[15]) == pytest.approx(min(exact, 1.0), abs=2e-5)  # Δpo, float32
            assert np.isfinite(np.asarray(state.obs)).all()
            state = step(state, jnp.full(6, 0.5))
            checked += 1
    assert checked == 16


# ---------------------------------------------------------------------- PyBullet: the twin and the reference env


def test_the_twin_builds_it_where_its_sdf_says(post):
    pb = pytest.importorskip("pybullet")
    from sagrasp_jax.deploy.twin import PyBulletTwin

    cfg = _cfg().env
    with PyBulletTwin(_spec(), cfg, q0=config.HOME_Q) as twin:
        client = twin._client
        probe_r = 0.005
        shape = pb.createCollisionShape(pb.GEOM_SPHERE, radius=probe_r, physicsClientId=client)
        for p in ([-0.05, -0.40, 0.12], [-0.12, -0.42, 0.25], [-0.10, -0.35, 0.03]):
            body = pb.createMultiBody(0, shape, basePosition=p, physicsClientId=client)
            hits = pb.getClosestPoints(body, twin.obstacle_bodies[0], 1.0, physicsClientId=client)
            v = np.asarray(p) - POST_POS
            assert min(h[8] for h in hits) == pytest.approx(float(_post_sdf(np, tuple(v), POST_SIZE)) - probe_r, abs=1e-6)


def test_the_reference_env_measures_it_as_the_shared_rules_do(post):
    pytest.importorskip("pybullet")
    pytest.importorskip("gymnasium")
    from sagrasp_jax.reference.pybullet_env import PyBulletGraspEnv

    env = PyBulletGraspEnv(_cfg(["env.task.obs_noise_std=0.0", "env.task.obstacle_geometry=fine"]).env)
    try:
        obs, _ = env.reset(options={"reset_spec": _spec()})
        exact = _exact_distance(config.HOME_Q)
        assert obs[15] == pytest.approx(exact, abs=1e-6)
        assert env.pybullet_distance()["obstacle_0"] == pytest.approx(exact, abs=collision.FINE_ERROR + 1e-6)
    finally:
        env.close()


# ---------------------------------------------------------------------- perception


def test_perception_returns_it_from_a_twin_render(post):
    """Rendered by the twin camera (the arm out of view), the post is perceived as a post: its own fit (the axis
    through its rounded top, the radius its reach) beats the other kinds' surfaces and holds every point seen.
    PyBullet draws a capsule's caps flatter than the capsule (its visual mesh: the top lies up to 11 mm inside the
    true cap, 6 mm low at the tip), so the height comes out that much short; the side, radius and axis are exact."""
    pytest.importorskip("pybullet")
    from sagrasp_jax.deploy import perception as P
    from sagrasp_jax.deploy import twin_camera as tc
    from sagrasp_jax.deploy.calibration import CameraCalibration
    from sagrasp_jax.deploy.twin import PyBulletTwin

    cfg = _cfg().env
    with PyBulletTwin(_spec(), cfg, q0=config.HOME_Q) as twin:
        frame = tc.TwinCamera(0.25).capture(twin, hide_robot=True)
    settings = P.PerceptionSettings.for_policy(cfg)
    assert settings.kinds[-1] == "post"
    det = P.detect_scene(frame.cloud_mm, frame.rgb, CameraCalibration.default(), settings=settings)
    assert np.linalg.norm(det.target_centre - TARGET) < 2e-3
    (ob,) = det.obstacles
    assert ob.kind == "post" and not det.diagnostics["obstacles"][0]["conservative"]
    assert np.linalg.norm(np.asarray(ob.centre)[:2] - POST_POS[:2]) < 1e-3 and abs(ob.centre[2] - POST_POS[2]) < 5e-3
    assert abs(ob.size[0] - POST_SIZE[0]) < 3e-3  # radius
    assert abs(2 * (ob.size[0] + ob.size[1]) - 2 * (POST_SIZE[0] + POST_SIZE[1])) < 10e-3  # tip to tip: the flat cap
    # without the toy kind allowed (a paper-mix policy) it is a covering shape of an allowed kind that holds it
    det = P.detect_scene(frame.cloud_mm, frame.rgb, CameraCalibration.default())
    (ob,) = det.obstacles
    assert ob.kind in shapes.PAPER_KINDS and det.diagnostics["obstacles"][0]["conservative"]
    turn, z = np.meshgrid(np.linspace(0, 2 * math.pi, 24, endpoint=False), np.linspace(-1, 1, 9))
    r, h = POST_SIZE[:2]
    lift = np.sqrt(np.maximum(r**2 - (r * np.maximum(np.abs(z) * 2 - 1, 0)) ** 2, 0))  # a ring on the caps too
    ring = np.c_[(lift * np.cos(turn)).ravel(), (lift * np.sin(turn)).ravel(),
                 (np.sign(z) * (np.minimum(np.abs(z) * 2, 1) * h + r * np.maximum(np.abs(z) * 2 - 1, 0))).ravel()]
    surface = POST_POS + ring[ring[:, 2] + POST_POS[2] >= 0.0]  # the post's surface above the table
    gap = shapes.sdf(np, shapes.BY_NAME[ob.kind].id, np.asarray(ob.centre), np.asarray(ob.yaw), np.asarray(ob.size), surface)
    assert gap.max() < 1e-3
