"""Robot-obstacle distance and contact (docs/task.md §2 "Collision", obstacle issue item 2).

The per-step obstacle query runs against ``collision.fine_cover``: spheres within FINE_ERROR (4 mm)
of the robot's URDF primitives both ways.  Checked against the exact primitive-pair distances of
``geometry`` (cylinders as 64-gon prisms, error < 0.3 mm) on random placements: Δpo within ±5 mm,
and no collision flag at an exact gap above 5 mm.  The first landing's conservative cover is kept
as ``obstacle_geometry="cover"``; the same test shows how far off it was.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401
from sagrasp_jax.task import collision
from sagrasp_jax.task import config
from sagrasp_jax.task import robot
from sagrasp_jax.task import sampling
from sagrasp_jax.task import shapes
import exact_geometry as geometry

ROBOT = robot.load_robot()
MOVING = [g for g in range(len(ROBOT.primitives)) if ROBOT.prim_link[g] >= 1]


def _random_surface_points(kind: int, size: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniform-ish random points on a primitive's surface (frame of the primitive)."""
    if kind == robot.BOX:
        face = rng.integers(0, 6, n)
        p = rng.uniform(-1, 1, (n, 3)) * size
        axis, sign = face // 2, np.where(face % 2, 1.0, -1.0)
        p[np.arange(n), axis] = sign * size[axis]
        return p
    r, h = size[0], size[1]
    t = rng.uniform(0, 2 * np.pi, n)
    if kind == robot.CYLINDER:
        side = rng.random(n) < 0.5
        rho = np.where(side, r, r * np.sqrt(rng.random(n)))
        z = np.where(side, rng.uniform(-h, h, n), np.where(rng.random(n) < 0.5, -h, h))
        return np.stack([rho * np.cos(t), rho * np.sin(t), z], -1)
    if kind == robot.CAPSULE:
        u = rng.normal(size=(n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        return r * u + np.stack([np.zeros(n), np.zeros(n), rng.uniform(-h, h, n)], -1)
    u = rng.normal(size=(n, 3))
    return r * u / np.linalg.norm(u, axis=1, keepdims=True)


def test_fine_cover_is_within_its_bound_of_every_primitive():
    """Hausdorff distance ≤ FINE_ERROR: every surface point within E of a sphere, no sphere sticks out > E."""
    cover = collision.fine_cover(ROBOT)
    rng = np.random.default_rng(0)
    assert set(np.unique(cover.prim)) == set(MOVING)
    for g in MOVING:
        prim = ROBOT.primitives[g]
        sel = cover.prim == g
        # sphere centres back in the primitive's frame
        local = (cover.local[sel] - prim.local[:3, 3]) @ prim.local[:3, :3]
        radius = cover.radius[sel]
        pts = _random_surface_points(prim.kind, np.asarray(prim.size, float), 4000, rng)
        gap = np.min(np.linalg.norm(pts[:, None] - local[None], axis=-1) - radius[None], axis=1)
        assert gap.max() <= collision.FINE_ERROR + 1e-9, (g, gap.max())
        # the farthest point of every sphere from the primitive
        dirs = rng.normal(size=(200, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        far = (local[:, None] + radius[:, None, None] * dirs[None]).reshape(-1, 3)
        sdf = geometry.point_distance(np, prim.kind, far, np.zeros(3), np.eye(3), np.asarray(prim.size, float))
        assert sdf.max() <= collision.FINE_ERROR + 1e-9, (g, sdf.max())
    assert len(cover.radius) < 350  # the per-step cost stays bounded


PAPER_KINDS = (robot.SPHERE, robot.CYLINDER, robot.BOX)


def _placements(n: int, seed: int, kinds: tuple[int, ...] = PAPER_KINDS):
    """Random arm poses with an obstacle placed near a random moving primitive (within ~10 cm)."""
    rng = np.random.default_rng(seed)
    q = np.array(config.HOME_Q) + rng.uniform(-1.2, 1.2, (n, 6))
    anchors = []
    for i in range(n):
        kin = robot.forward_kinematics(np, ROBOT, q[i])
        pos, _ = robot.primitive_poses(np, ROBOT, kin)
        anchors.append(pos[rng.choice(MOVING)])
    anchor = np.array(anchors) + rng.normal(0, 0.07, (n, 3))
    kind = rng.choice(list(kinds), n)
    size = np.stack([rng.uniform(0.02, 0.06, n), rng.uniform(0.02, 0.15, n), rng.uniform(0.02, 0.06, n)], -1)
    size[kind == robot.SPHERE, 1:] = 0.0
    size[(kind == robot.CYLINDER) | (kind == robot.CAPSULE), 2] = 0.0
    yaw = np.where(np.isin(kind, [s.id for s in shapes.SHAPES if s.yawed]), rng.uniform(-np.pi, np.pi, n), 0.0)
    return q, kind, anchor, yaw, size


def _exact(q, kind, pos, yaw, size) -> np.ndarray:
    """Exact robot-obstacle distances, NumPy batched over the placements (one call per primitive)."""
    kin = robot.forward_kinematics(np, ROBOT, q)
    pp, pr = robot.primitive_poses(np, ROBOT, kin)
    rot = shapes.primitive_rotations(np, kind, yaw)  # the obstacle's primitive: yaw ∘ tilt (capsules lie)
    prim = np.array([shapes.BY_ID[int(k)].primitive for k in kind])
    per_prim = [
        geometry.distance_to_obstacle(np, int(ROBOT.prim_kind[g]), pp[:, g], pr[:, g], np.broadcast_to(ROBOT.prim_size[g], size.shape),
                                      prim, pos, rot, size, obstacle_kinds=sorted(set(prim.tolist())), sides=64)
        for g in MOVING
    ]
    return np.min(np.stack(per_prim), axis=0)


def _spec(xp, q, kind, pos, yaw, size) -> sampling.ResetSpec:
    return sampling.ResetSpec(
        q0=q, target_pos=xp.asarray([0.3, -0.45, 0.025]), target_yaw=xp.asarray(0.0),
        obstacle_active=xp.asarray([True, False]), obstacle_kind=xp.stack([xp.asarray(kind), xp.asarray(robot.SPHERE)]),
        obstacle_pos=xp.stack([pos, xp.asarray([0.0, 0.0, -5.0])]), obstacle_yaw=xp.stack([yaw, xp.asarray(0.0)]),
        obstacle_size=xp.stack([size, xp.asarray([0.01, 0.0, 0.0])]), redraws=xp.asarray(0), fallback=xp.asarray(False),
    )


@pytest.fixture(scope="module")
def placements():
    q, kind, pos, yaw, size = _placements(1500, seed=3)
    return (q, kind, pos, yaw, size), _exact(q, kind, pos, yaw, size)


def _checked(geometry_kind: str, data, kinds: tuple[str, ...] = shapes.PAPER_KINDS):
    import jax
    import jax.numpy as jnp

    cfg = config.get_config("paper").env
    cfg = dataclasses.replace(cfg, task=dataclasses.replace(cfg.task, obstacle_geometry=geometry_kind, obstacle_dist_clip=10.0),
                              sampling=dataclasses.replace(cfg.sampling, obstacle_kinds=kinds))

    def one(q, kind, pos, yaw, size):
        kin = robot.forward_kinematics(jnp, ROBOT, q)
        res = collision.check(jnp, ROBOT, kin, _spec(jnp, q, kind, pos, yaw, size), cfg)
        return res.nearest_obstacle_dist, res.hits["obstacle"]

    dist, hit = jax.jit(jax.vmap(one))(*(jnp.asarray(a) for a in data))
    return np.asarray(dist, float), np.asarray(hit)


def test_fine_obstacle_distance_within_5mm_of_exact(x64, placements):
    data, exact = placements
    dist, hit = _checked("fine", data)
    apart = exact > 0
    assert apart.sum() > 500 and (exact < 0).sum() > 300  # both gaps and overlaps are exercised
    err = dist[apart] - exact[apart]
    assert np.abs(err).max() <= 0.005, np.abs(err).max()
    assert not np.any(hit & (exact > 0.005))  # no collision flagged at an exact gap above 5 mm
    assert np.all(hit[exact < -0.005])  # every overlap deeper than 5 mm is caught


def test_fine_distance_to_capsules_within_5mm_of_exact(x64):
    """The same bound for the fourth kind, a capsule lying on the table (yawed), checked alone."""
    data = _placements(500, seed=4, kinds=(robot.CAPSULE,))
    exact = _exact(*data)
    dist, hit = _checked("fine", data, ("capsule",))
    apart = exact > 0
    assert apart.sum() > 100 and (exact < 0).sum() > 100  # gaps and overlaps both exercised
    assert np.abs(dist[apart] - exact[apart]).max() <= 0.005
    assert not np.any(hit & (exact > 0.005)) and np.all(hit[exact < -0.005])


def test_old_cover_over_reported_contacts(x64, placements):
    """Why the fine set exists: the first landing's cover under-reported Δpo by up to ~2 cm."""
    data, exact = placements
    dist, hit = _checked("cover", data)
    apart = exact > 0
    assert (dist[apart] - exact[apart]).min() < -0.015
    assert np.any(hit & (exact > 0.01))


def test_robot_vector_points_from_the_robot_to_the_obstacle():
    q = np.array(config.HOME_Q)
    kin = robot.forward_kinematics(np, ROBOT, q)
    below = kin.gripper_centre - np.array([0.0, 0.0, 0.15])
    spec = _spec(np, q, robot.SPHERE, below, 0.0, np.array([0.03, 0.0, 0.0]))
    res = collision.check(np, ROBOT, kin, spec, config.get_config("paper").env)
    v = res.robot_to_obstacle[0]
    assert np.linalg.norm(v) == pytest.approx(float(res.obstacle_dist[0]), abs=1e-9)
    assert v[2] < 0  # the obstacle is below the robot's nearest point
    np.testing.assert_array_equal(res.robot_to_obstacle[1], 0.0)  # empty slot
    np.testing.assert_allclose(res.gripper_to_obstacle[0], [0.0, 0.0, -(0.15 - 0.03)], atol=1e-12)
    assert math.isclose(float(res.nearest_obstacle_dist), float(res.obstacle_dist[0]))
