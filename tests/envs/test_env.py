"""The MJX/JAX grasp env (docs/task.md §2): sampling, observation, collisions, solvability, batching, auto-reset."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401
import jax
import jax.numpy as jnp

from sagrasp_jax.task import collision
from sagrasp_jax.task import config
from sagrasp_jax.task import config_parse
from sagrasp_jax.task import robot
from sagrasp_jax.task import sampling
from sagrasp_jax.task import shapes
import exact_geometry as geometry
from sagrasp_jax.envs.grasp_env import GraspEnv, OBS_SIZE
from sagrasp_jax.task.scene import SCENE
from sagrasp_jax.envs.auto_reset import AutoReset
from scripted import scripted_action

ROBOT = robot.load_robot()


def env_config(mode: str = "kinematic", obstacle_prob: float | None = None) -> config.EnvConfig:
    cfg = config.get_config("paper").env
    sampling_cfg = cfg.sampling if obstacle_prob is None else dataclasses.replace(cfg.sampling, obstacle_prob=obstacle_prob)
    return dataclasses.replace(cfg, control=dataclasses.replace(cfg.control, mode=mode), sampling=sampling_cfg)


@pytest.fixture(scope="module")
def resets_10k():
    cfg = env_config()
    n = sampling.uniforms_needed(cfg.sampling)
    u = jax.random.uniform(jax.random.PRNGKey(7), (10_000, n))
    fn = jax.jit(jax.vmap(lambda x: sampling.sample_reset(jnp, ROBOT, cfg.sampling, cfg.task, x)))
    return cfg, jax.tree_util.tree_map(np.asarray, fn(u))


def test_obstacle_frequency_and_fallback(resets_10k):
    _, spec = resets_10k
    freq = spec.obstacle_active[:, 0].mean()
    assert abs(freq - 0.20) <= 0.02
    two = spec.obstacle_active[:, 1].sum() / spec.obstacle_active[:, 0].sum()
    assert abs(two - 0.5) < 0.06  # 1 or 2 obstacles, equally likely
    assert spec.fallback.mean() < 0.01
    kinds = spec.obstacle_kind[spec.obstacle_active]
    for k in (robot.SPHERE, robot.CYLINDER, robot.BOX):  # uniform draw; feasibility favours compact shapes a little
        assert abs(np.mean(kinds == k) - 1 / 3) < 0.07


def test_targets_inside_the_region(resets_10k):
    cfg, spec = resets_10k
    s = cfg.sampling
    x, y, z = spec.target_pos.T
    assert np.all((x >= s.target_x[0]) & (x <= s.target_x[1]) & (y >= s.target_y[0]) & (y <= s.target_y[1]))
    r = np.hypot(x, y)
    assert np.all((r >= s.target_radius[0]) & (r <= s.target_radius[1]))
    np.testing.assert_allclose(z, 0.025)
    assert np.all(np.abs(spec.target_yaw) <= math.pi / 4 + 1e-6)
    assert np.all(np.abs(spec.q0 - np.array(cfg.task.home_q)) <= cfg.task.start_noise + 1e-6)


def test_accepted_obstacles_are_feasible(resets_10k):
    """No accepted obstacle within 0.10 m of the target (horizontally) or of the robot at its start pose."""
    cfg, spec = resets_10k
    rows, slots = np.nonzero(spec.obstacle_active)
    assert len(rows) > 1500
    for i, j in zip(rows[:600], slots[:600]):
        kind, pos, yaw, size = spec.obstacle_kind[i, j], spec.obstacle_pos[i, j], spec.obstacle_yaw[i, j], spec.obstacle_size[i, j]
        gap = shapes.footprint_gap(np, kind, pos, yaw, size, spec.target_pos[i, :2])
        assert gap >= cfg.sampling.target_clearance - 1e-5
        kin = robot.forward_kinematics(np, ROBOT, spec.q0[i].astype(float))
        prim_pos, prim_rot = robot.primitive_poses(np, ROBOT, kin)
        d = geometry.obstacle_distance_matrix(
            np, ROBOT.prim_kind, prim_pos, prim_rot, ROBOT.prim_size,
            np.array([kind]), pos[None].astype(float), shapes.yaw_rotation(np, np.array([float(yaw)])), size[None].astype(float),
        )
        assert d.min() >= cfg.sampling.robot_clearance - 1e-5
    # two obstacles never overlap
    both = np.nonzero(spec.obstacle_active[:, 1])[0]
    for i in both[:300]:
        r = shapes.bounding_radius(np, spec.obstacle_kind[i], spec.obstacle_size[i])
        assert np.linalg.norm(spec.obstacle_pos[i, 0] - spec.obstacle_pos[i, 1]) > r.sum() - 1e-6
    # standing obstacles stand on the table, spheres float in their band
    for i, j in zip(rows, slots):
        kind, pos, size = spec.obstacle_kind[i, j], spec.obstacle_pos[i, j], spec.obstacle_size[i, j]
        if kind == robot.SPHERE:
            assert 0.12 - 1e-6 <= pos[2] <= 0.30 + 1e-6
        elif kind == robot.CYLINDER:
            assert pos[2] == pytest.approx(size[1], abs=1e-6)
        else:
            assert pos[2] == pytest.approx(size[2], abs=1e-6)


def test_numpy_and_jax_sampling_agree():
    cfg = env_config()
    n = sampling.uniforms_needed(cfg.sampling)
    u = np.random.default_rng(3).random((50, n))
    jx = jax.jit(jax.vmap(lambda x: sampling.sample_reset(jnp, ROBOT, cfg.sampling, cfg.task, x)))(jnp.asarray(u, jnp.float32))
    for i in range(50):
        ref = sampling.sample_reset(np, ROBOT, cfg.sampling, cfg.task, u[i].astype(np.float32).astype(float))
        np.testing.assert_allclose(np.asarray(jx.target_pos[i]), ref.target_pos, atol=1e-5)
        np.testing.assert_array_equal(np.asarray(jx.obstacle_active[i]), ref.obstacle_active)
        np.testing.assert_allclose(np.asarray(jx.obstacle_pos[i]), ref.obstacle_pos, atol=1e-5)


def test_observation_layout_at_reset():
    cfg = env_config(obstacle_prob=1.0)
    env = GraspEnv(cfg)
    state = jax.jit(env.reset)(jax.random.PRNGKey(11))
    obs = np.asarray(state.obs)
    assert obs.shape == (OBS_SIZE,)
    spec = state.info["reset"]
    q0 = np.asarray(spec.q0, float)
    kin = robot.forward_kinematics(np, ROBOT, q0)
    assert np.abs(obs[:6] - q0).max() < 0.03  # joint noise σ = 0.005
    np.testing.assert_allclose(obs[6:9], kin.gripper_centre, atol=1e-5)
    np.testing.assert_allclose(obs[9:12], spec.target_pos, atol=1e-6)
    assert bool(spec.obstacle_active[0])
    assert 0.0 < obs[15] < 1.0  # Δpo of a real obstacle, ≥ 0.10 at the start
    assert obs[15] >= 0.10 - collision.sphere_cover(ROBOT).bulge.max() - 1e-6
    assert math.degrees(obs[16]) < 4.0  # start noise ±0.05 rad tilts the gripper a little


def test_no_obstacle_observation():
    env = GraspEnv(env_config(obstacle_prob=0.0))
    obs = np.asarray(jax.jit(env.reset)(jax.random.PRNGKey(0)).obs)
    np.testing.assert_allclose(obs[12:15], [0.0, 0.0, -1.0])
    assert obs[15] == pytest.approx(1.0)


def _spec(q0, target=(0.1, -0.45, 0.025), obstacle=None) -> sampling.ResetSpec:
    active = np.array([obstacle is not None, False])
    kind = np.array([obstacle[0] if obstacle else robot.SPHERE, robot.SPHERE])
    pos = np.array([obstacle[1] if obstacle else (0, 0, -5), (0, 0, -5)], float)
    size = np.array([obstacle[2] if obstacle else (0.05, 0, 0), (0.05, 0, 0)], float)
    return sampling.ResetSpec(
        q0=np.asarray(q0, float), target_pos=np.asarray(target, float), target_yaw=np.array(0.0),
        obstacle_active=active, obstacle_kind=kind, obstacle_pos=pos, obstacle_yaw=np.zeros(2),
        obstacle_size=size, redraws=np.array(0), fallback=np.array(False),
    )


def _check(q, spec):
    kin = robot.forward_kinematics(np, ROBOT, np.asarray(q, float))
    return collision.check(np, ROBOT, kin, spec, env_config())


def test_home_pose_is_collision_free():
    res = _check(config.HOME_Q, _spec(config.HOME_Q))
    assert not bool(res.any_collision)
    assert all(not bool(v) for v in res.hits.values())


def test_collision_flags_fire():
    home = np.array(config.HOME_Q)
    kin = robot.forward_kinematics(np, ROBOT, home)
    centre = kin.gripper_centre
    # a sphere obstacle right at the gripper centre
    res = _check(home, _spec(home, obstacle=(robot.SPHERE, centre, (0.03, 0, 0))))
    assert bool(res.hits["obstacle"]) and float(res.nearest_obstacle_dist) < 0
    np.testing.assert_allclose(res.nearest_obstacle_pos, centre)
    # 4 cm from the pads' outer faces along x: a near miss, no collision
    near = centre + np.array([0.0, 0.0, -0.0165 - 0.04 - 0.03])
    res = _check(home, _spec(home, obstacle=(robot.SPHERE, near, (0.03, 0, 0))))
    assert not bool(res.hits["obstacle"])
    assert 0.0 < float(res.nearest_obstacle_dist) < 0.05
    # arm folded down into the table
    down = home.copy()
    down[1] += 1.2  # gripper centre ≈ 6 cm below the table top
    assert bool(_check(down, _spec(down)).hits["table"])
    # the cube between the open pads touches nothing; raised 3.5 cm it runs into the gripper body
    assert not bool(_check(home, _spec(home, target=centre)).hits["target"])
    res = _check(home, _spec(home, target=centre + np.array([0, 0, 0.035])))
    assert bool(res.hits["target"]) and bool(res.any_collision)
    # gripper centre in the success pose above the cube: no target collision
    res = _check(home, _spec(home, target=centre - np.array([0, 0, 0.0125])))
    assert not bool(res.hits["target"])


def test_gantry_hit_and_camera_unreachable():
    q = np.zeros(6)
    q[1] = math.pi / 2  # arm stretched horizontally at shoulder height, reach 0.8865 m > 0.72 m to the posts
    hits = []
    for q1 in np.linspace(-math.pi, math.pi, 73):
        q[0] = q1
        hits.append(bool(_check(q, _spec(q)).hits["gantry"]))
    assert 2 <= sum(hits) <= 20
    # no pose of the arm reaches the camera, its bracket or the beam
    qs = np.random.default_rng(0).uniform(-3.05, 3.05, (20_000, 6))
    kin = robot.forward_kinematics(np, ROBOT, qs)
    centres = collision.cover_centres(np, ROBOT, kin)
    top = (centres[..., 2] + collision.sphere_cover(ROBOT).radius).max()
    unreachable = [p for i, p in enumerate(SCENE.static_parts) if i not in collision.reachable_parts()]
    assert {p.name for p in unreachable} == {"gantry_beam", "camera_bracket", "camera_body"}
    assert top < min(collision.lowest_z(p) for p in unreachable) - 0.1


def test_box_overlap_test_agrees_with_exact_box_distance():
    rng = np.random.default_rng(0)
    overlaps = 0
    for _ in range(1500):
        rot_a, rot_b = (np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(2))
        half_a, half_b = rng.uniform(0.01, 0.06, 3), rng.uniform(0.01, 0.06, 3)
        pos_b = rng.uniform(-0.12, 0.12, 3)
        exact = geometry.box_box_distance(np, np.zeros(3), rot_a, half_a, pos_b, rot_b, half_b)
        overlap = bool(collision.boxes_overlap(np, np.zeros(3), rot_a, half_a, pos_b, rot_b, half_b))
        overlaps += overlap
        if abs(exact) > 1e-7:
            assert overlap == (exact < 0)
    assert 200 < overlaps < 1300


def test_cover_distance_bounds_exact_distance():
    """Δpo from the sphere cover lies within [exact − bulge, exact + capsule dip]."""
    rng = np.random.default_rng(5)
    cover = collision.sphere_cover(ROBOT)
    bulge = cover.bulge[1:].max()
    checked = 0
    for trial in range(60):
        q = np.array(config.HOME_Q) + rng.uniform(-0.6, 0.6, 6)
        kin = robot.forward_kinematics(np, ROBOT, q)
        kind = [robot.SPHERE, robot.CYLINDER, robot.BOX][trial % 3]
        size = {robot.SPHERE: (0.05, 0, 0), robot.CYLINDER: (0.04, 0.1, 0), robot.BOX: (0.04, 0.05, 0.06)}[kind]
        pos = kin.gripper_centre + rng.uniform(-0.15, 0.15, 3)
        spec = _spec(q, obstacle=(kind, pos, size))
        res = collision.check(np, ROBOT, kin, spec, env_config())
        prim_pos, prim_rot = robot.primitive_poses(np, ROBOT, kin)
        exact = geometry.obstacle_distance_matrix(
            np, ROBOT.prim_kind[1:], prim_pos[1:], prim_rot[1:], ROBOT.prim_size[1:],
            np.array([kind]), pos[None], np.eye(3)[None], np.array([size], float),
        ).min()
        got = float(res.nearest_obstacle_dist)
        if exact >= 1.0:
            continue
        if exact > 0:
            assert exact - bulge - 1e-9 <= got <= exact + collision.CAPSULE_DIP + 1e-9
            checked += 1
        elif exact < -collision.CAPSULE_DIP:
            assert got < 0  # overlap is always reported as a collision
    assert checked >= 10


@pytest.mark.parametrize("mode", ["kinematic", "dynamic"])
def test_scripted_controller_solves_the_task(mode):
    """A scripted IK controller driven through ``step`` succeeds in ≥ 95 % of 200 obstacle-free episodes."""
    cfg = env_config(mode=mode, obstacle_prob=0.0)
    env = GraspEnv(cfg)
    n = 200

    def run(keys):
        state = jax.vmap(env.reset)(keys)

        def body(carry, _):
            st, alive, success, steps = carry
            q = st.pipeline_state.qpos[:, :6] if mode == "dynamic" else st.info["q_target"]
            action = jax.vmap(lambda qq, t: scripted_action(cfg, qq, t))(q, st.info["reset"].target_pos)
            nxt = jax.vmap(env.step)(st, action)
            ended = alive & (nxt.done > 0)
            success = jnp.where(ended, nxt.info["episode"]["success"], success)
            steps = jnp.where(ended, nxt.info["episode"]["steps"], steps)
            return (nxt, alive & ~ended, success, steps), None

        zero = jnp.zeros(n)
        (_, alive, success, steps), _ = jax.lax.scan(body, (state, jnp.ones(n, bool), zero, zero), None, length=cfg.task.max_steps)
        return success, steps

    success, steps = jax.jit(run)(jax.random.split(jax.random.PRNGKey(42), n))
    success, steps = np.asarray(success), np.asarray(steps)
    assert success.mean() >= 0.95
    assert 17 <= steps[success > 0].mean() <= 60  # physical limit ≈ 17.6 steps (docs/task.md §6)


def test_vmap_equals_single_env():
    env = GraspEnv(env_config(obstacle_prob=0.5))
    keys = jax.random.split(jax.random.PRNGKey(9), 64)
    actions = jax.random.uniform(jax.random.PRNGKey(10), (20, 64, 6), minval=-1, maxval=1)
    step_b, step_1 = jax.jit(jax.vmap(env.step)), jax.jit(env.step)
    batch = jax.jit(jax.vmap(env.reset))(keys)
    singles = [jax.jit(env.reset)(k) for k in keys[:8]]
    for t in range(20):
        batch = step_b(batch, actions[t])
        singles = [step_1(s, actions[t, i]) for i, s in enumerate(singles)]
    for i, s in enumerate(singles):
        np.testing.assert_allclose(np.asarray(batch.obs[i]), np.asarray(s.obs), atol=1e-5)
        assert float(batch.reward[i]) == pytest.approx(float(s.reward), abs=1e-5)
        assert float(batch.done[i]) == float(s.done)


def test_auto_reset_starts_are_the_wrapped_envs_resets_bit_for_bit():
    """AutoReset.reset draws its env's start and pending start through one copy of the sampler (a 2-step loop):
    each is exactly the wrapped env's reset of its key, batched as the trainer resets (64 envs)."""
    inner = GraspEnv(env_config(obstacle_prob=0.5))
    env = AutoReset(inner)
    keys = jax.random.split(jax.random.PRNGKey(5), 64)
    state = jax.jit(jax.vmap(env.reset))(keys)
    split = jax.vmap(lambda k: jax.random.split(k, 3))(keys)
    own = jax.jit(jax.vmap(inner.reset))
    for got, want in ((state, own(split[:, 0])), (state.info["pending"], own(split[:, 1]))):
        for a, b in zip(jax.tree_util.tree_leaves(_core_of(got)), jax.tree_util.tree_leaves(want)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(state.info["reset_key"]), np.asarray(split[:, 2]))


def _core_of(state):
    """The wrapped env's own state inside an AutoReset state: without the wrapper's info keys and counters."""
    from sagrasp_jax.envs.auto_reset import RESET_METRICS, _core
    return _core(state).replace(metrics={k: v for k, v in state.metrics.items() if k not in RESET_METRICS})


def test_no_nan_after_1000_random_steps():
    env = AutoReset(GraspEnv(env_config(obstacle_prob=0.5)))
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(1), 256))

    def body(st, key):
        st = env.batch_step(st, jax.random.uniform(key, (256, 6), minval=-1, maxval=1))
        return st, (jnp.all(jnp.isfinite(st.obs)) & jnp.all(jnp.isfinite(st.reward)), st.done.sum())

    state, (finite, dones) = jax.jit(lambda s, k: jax.lax.scan(body, s, jax.random.split(k, 1000)))(state, jax.random.PRNGKey(2))
    assert bool(np.all(np.asarray(finite)))
    assert int(np.asarray(dones).sum()) > 256  # episodes ended and restarted


@pytest.mark.parametrize("batched", [True, False])
def test_auto_reset_draws_fresh_episodes(batched):
    """Consecutive episodes of one slot get different targets; the finished episode's metrics survive."""
    cfg = env_config()
    # every env times out together: the batched refill (1 per step for 16 envs) must keep up
    horizon = 17
    cfg = dataclasses.replace(cfg, task=dataclasses.replace(cfg.task, max_steps=horizon))
    env = AutoReset(GraspEnv(cfg))
    n = 16
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(3), n))
    step = jax.jit(env.batch_step if batched else jax.vmap(env.step))
    targets = [np.asarray(state.info["reset"].target_pos)]
    for t in range(3 * horizon):
        state = step(state, jnp.zeros((n, 6)))
        assert float(state.metrics["reset_replays"].sum()) == 0.0
        if t % horizon == horizon - 1:
            assert np.all(np.asarray(state.done) == 1.0)
            np.testing.assert_allclose(np.asarray(state.info["episode"]["timeout"]), 1.0)
            np.testing.assert_allclose(np.asarray(state.info["episode"]["steps"]), horizon)
            assert np.all(np.asarray(state.info["steps"]) == 0)
            targets.append(np.asarray(state.info["reset"].target_pos))
    targets = np.stack(targets)  # (episodes, envs, 3)
    assert np.all(np.linalg.norm(np.diff(targets, axis=0), axis=-1) > 1e-6)


def _starts(state) -> np.ndarray:
    """One row per env identifying its current episode start (start joints, target, obstacles)."""
    spec = state.info["reset"]
    parts = [spec.q0, spec.target_pos, spec.target_yaw[:, None], spec.obstacle_pos.reshape(len(spec.q0), -1)]
    return np.concatenate([np.asarray(p, np.float64) for p in parts], axis=1)


def test_auto_reset_never_replays_a_scene_with_short_episodes():
    """16 envs, 5-step episodes: every env finishes every 5 steps, far faster than the 1-per-step
    refill; the overflow path must still give every episode a start never used before."""
    cfg = env_config(obstacle_prob=0.5)
    cfg = dataclasses.replace(cfg, task=dataclasses.replace(cfg.task, max_steps=5))
    env = AutoReset(GraspEnv(cfg))
    n = 16
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(11), n))
    step = jax.jit(env.batch_step)
    actions = jax.random.uniform(jax.random.PRNGKey(12), (40, n, 6), minval=-1, maxval=1)
    starts = [_starts(state)]
    overflow = replays = 0.0
    for a in actions:
        state = step(state, a)
        done = np.asarray(state.done) > 0.5
        overflow += float(state.metrics["reset_overflow"].sum())
        replays += float(state.metrics["reset_replays"].sum())
        if done.any():
            starts.append(_starts(state)[done])
    starts = np.concatenate(starts)
    assert len(starts) >= n + 40 // 5 * n  # every env restarted at least 8 times
    assert len(np.unique(starts.round(9), axis=0)) == len(starts), "a scene was replayed"
    assert replays == 0.0
    assert overflow > 0  # the refill alone could not have kept up
    # The key chain makes the scenes independent of the refill timing: the per-env vmapped
    # step (which samples on every finish) plays exactly the same starts.
    state_v = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(11), n))
    step_v = jax.jit(jax.vmap(env.step))
    starts_v = [_starts(state_v)]
    for a in actions:
        state_v = step_v(state_v, a)
        done = np.asarray(state_v.done) > 0.5
        if done.any():
            starts_v.append(_starts(state_v)[done])
    np.testing.assert_allclose(np.concatenate(starts_v), starts, atol=1e-6)


def test_dynamic_mode_tracks_kinematic_mode():
    """Same actions: the dynamic (servo) gripper centre stays within a few cm of the kinematic one."""
    keys = jax.random.PRNGKey(4)
    kin_env, dyn_env = GraspEnv(env_config("kinematic", 0.0)), GraspEnv(env_config("dynamic", 0.0))
    sk, sd = jax.jit(kin_env.reset)(keys), jax.jit(dyn_env.reset)(keys)
    actions = 0.3 * jax.random.uniform(jax.random.PRNGKey(5), (30, 6), minval=-1, maxval=1)
    step_k, step_d = jax.jit(kin_env.step), jax.jit(dyn_env.step)
    gaps = []
    for a in actions:
        sk, sd = step_k(sk, a), step_d(sd, a)
        gaps.append(np.linalg.norm(np.asarray(sk.obs[6:9]) - np.asarray(sd.obs[6:9])))
    assert max(gaps) < 0.03
    assert max(gaps) > 1e-5  # the servo really lags


@pytest.mark.parametrize("rc_mode, hovering_wins", [("entry", False), ("per_step", True)])
def test_hovering_inside_the_grab_zone_does_not_pay_by_default(rc_mode, hovering_wins):
    """End to end through ``step`` (docs/task.md §2): from one state with the cube 4 cm below the gripper,
    hovering until timeout earns less than grasping under rc_mode='entry', more under 'per_step'."""
    cfg = env_config(obstacle_prob=0.0)
    cfg = dataclasses.replace(cfg, reward=dataclasses.replace(cfg.reward, rc_mode=rc_mode),
                              task=dataclasses.replace(cfg.task, obs_noise_std=0.0))
    env = GraspEnv(cfg)
    target = np.array([0.05, -0.45, 0.025])
    low = robot.solve_home_pose(config.HOME_Q, target + np.array([0.0, 0.0, 0.04]))  # pointing down, 4 cm above
    spec = jax.tree_util.tree_map(jnp.asarray, _spec(low, target=target))
    start = env.reset_to(spec, jax.random.PRNGKey(0))
    assert float(start.info["tracker"].d_prev) == pytest.approx(0.04, abs=1e-4)
    step = jax.jit(env.step)
    action = jax.jit(lambda q, t: scripted_action(cfg, q, t))

    def episode(policy):
        state, total = start, 0.0
        for _ in range(cfg.task.max_steps):
            state = step(state, policy(state))
            total += float(state.reward)
            if float(state.done):
                return total, state.info["episode"]
        raise AssertionError("episode did not end")

    grasp_return, grasp_ep = episode(lambda s: action(s.info["q_target"], s.info["reset"].target_pos))
    hover_return, hover_ep = episode(lambda s: jnp.zeros(6))
    assert float(grasp_ep["success"]) == 1.0 and float(hover_ep["timeout"]) == 1.0
    assert (hover_return > grasp_return) == hovering_wins, (grasp_return, hover_return)


# ---------------------------------------------------------------------- learnability curriculum

def test_learnability_scores_sometimes_solved_scenes_highest():
    """p̂(1 − p̂) with p̂ = (s + ½)/(n + 1): one success in two is the most learnable, a scene failed once scores
    FAILED_ONCE, and scenes always solved or never solved fall towards 0 the more they are tried."""
    from sagrasp_jax.envs.auto_reset import FAILED_ONCE, learnability

    assert learnability(1.0, 0.0) == pytest.approx(FAILED_ONCE) == pytest.approx(0.1875)
    assert learnability(2.0, 1.0) == pytest.approx(0.25)
    always = [learnability(n, n) for n in (1.0, 3.0, 10.0)]
    never = [learnability(n, 0.0) for n in (1.0, 3.0, 10.0)]
    assert always == sorted(always, reverse=True) and never == sorted(never, reverse=True)
    assert always[-1] == pytest.approx(never[-1]) == pytest.approx(0.5 / 11 * 10.5 / 11)


def test_curriculum_memory_counts_replays_and_keeps_the_more_learnable_scene():
    """One step of the curriculum's bookkeeping on six envs, each a case of its rules (wrappers.py)."""
    env = AutoReset(GraspEnv(env_config()), replay=1.0, max_replays=8)
    scene = lambda *v: {"x": jnp.asarray(v, jnp.float32)}  # noqa: E731  (any pytree stands for a ResetSpec)
    info = {
        "reset": scene(10.0, 11.0, 12.0, 13.0, 14.0, 15.0),  # the scenes that just ended
        "replay_spec": scene(0.0, 1.0, 2.0, 3.0, 4.0, 5.0),  # each env's remembered scene
        "replay_tries": jnp.asarray([1.0, 2.0, 5.0, 1.0, 1.0, 9.0]),
        "replay_successes": jnp.asarray([0.0, 1.0, 5.0, 0.0, 0.0, 4.0]),
        "replay_gen": jnp.asarray([3, 0, 0, 0, 2, 0], jnp.int32),
        "scene_gen": jnp.asarray([3, -1, -1, -1, 1, -1], jnp.int32),  # env 0 replays gen 3, env 4 an older gen
    }
    done = jnp.ones(6, bool)
    success = jnp.asarray([True, False, False, True, False, False])
    out = env._remember(info, done, success)
    np.testing.assert_allclose(out["replay_tries"], [2.0, 2.0, 1.0, 1.0, 1.0, 1.0])  # 0: a try; 2, 5: replaced
    np.testing.assert_allclose(out["replay_successes"], [1.0, 1.0, 0.0, 0.0, 0.0, 0.0])
    # 1 keeps its 1-in-2 scene (0.25 > a new failure's 0.1875); 2 drops a scene solved 5 of 5 for the new failure;
    # 3 succeeded on a fresh scene (nothing to learn); 4's replay was of a scene it no longer remembers;
    # 5's scene, 4 of 9 (0.2475), was retired after its 8 replays
    np.testing.assert_allclose(out["replay_spec"]["x"], [0.0, 1.0, 12.0, 3.0, 4.0, 15.0])
    np.testing.assert_array_equal(out["replay_gen"], [3, 0, 1, 0, 2, 1])
    np.testing.assert_array_equal(env._held(info["replay_gen"], info["replay_tries"]), [True] * 5 + [False])
    idle = env._remember(info, jnp.zeros(6, bool), success)  # nothing finished: nothing changes
    np.testing.assert_array_equal(idle["replay_gen"], info["replay_gen"])
    np.testing.assert_allclose(idle["replay_tries"], info["replay_tries"])


def test_curriculum_replays_failed_scenes_and_never_a_used_state():
    """Episodes that all time out (5 steps, zero actions) fill every env's memory; some later starts are then
    replays: their scene is one the same env played and failed before, they are counted in curriculum_starts
    and marked replays when they finish, and no used state is ever swapped in again."""
    cfg = env_config(obstacle_prob=0.5)
    cfg = dataclasses.replace(cfg, task=dataclasses.replace(cfg.task, max_steps=5))
    env = AutoReset(GraspEnv(cfg), replay=1.0)
    n = 16
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(21), n))
    step = jax.jit(env.batch_step)
    played = [[row] for row in _starts(state)]
    started = replayed_starts = finished_replays = 0
    for _ in range(60):
        previous_scene_gen = np.asarray(state.info["scene_gen"])
        state = step(state, jnp.zeros((n, 6)))
        done = np.asarray(state.done) > 0.5
        starts = np.asarray(state.metrics["curriculum_starts"]) > 0.5
        assert not np.any(starts & ~done) and float(state.metrics["reset_replays"].sum()) == 0.0
        np.testing.assert_array_equal(np.asarray(state.info["episode"]["replay"])[done], previous_scene_gen[done] >= 0)
        finished_replays += int(np.sum(np.asarray(state.info["episode"]["replay"])[done]))
        rows = _starts(state)
        for i in np.flatnonzero(done):
            if starts[i]:
                assert any(np.allclose(rows[i], old, atol=1e-6) for old in played[i]), f"env {i} replayed a scene it never played"
                replayed_starts += 1
            else:
                assert not any(np.allclose(rows[i], old, atol=1e-6) for old in played[i])
            played[i].append(rows[i])
            started += 1
    assert np.all(np.asarray(state.info["replay_gen"]) >= 0)  # every env remembers a failure
    # a scene failed once is replayed with probability 0.75, one failed twice 0.56: neither all nor none
    assert 0.25 * started < replayed_starts < 0.85 * started, (replayed_starts, started)
    assert finished_replays > 0


def test_curriculum_needs_a_scene_env_and_a_probability():
    from toy_env import PointReach

    with pytest.raises(ValueError, match="sample_spec and reset_to"):
        AutoReset(PointReach(), replay=0.5)
    with pytest.raises(ValueError, match=r"in \[0, 1\]"):
        AutoReset(GraspEnv(env_config()), replay=1.5)
    with pytest.raises(ValueError, match="at least one replay"):
        AutoReset(GraspEnv(env_config()), replay=0.5, max_replays=0)


def test_the_trainer_env_carries_the_configured_curriculum():
    """train.curriculum_replay reaches the training env's AutoReset; the evaluation env never replays."""
    from sagrasp_jax.train import default_envs

    cfg = config_parse.apply_overrides(config.get_config("cpu-quick"), ["train.curriculum_replay=0.5"])
    train_env, eval_env = default_envs(cfg)
    assert train_env.replay == 0.5 and not isinstance(eval_env, AutoReset)
    assert default_envs(config.get_config("cpu-quick"))[0].replay == 0.0  # off in the presets
