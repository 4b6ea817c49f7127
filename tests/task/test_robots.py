"""The robot registry: every entry agrees with its URDF (home pose, joint count, fine-tune joints, self-collision
groups, limits), the Panda's primitives cover Franka's collision meshes, its top-down grasps are reachable, and
``register`` refuses a malformed entry naming the problem."""

import dataclasses
import os
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from sagrasp_jax.base import assets
from sagrasp_jax.task import collision, config, geometry, robot, robots, sampling

HOME_MARGIN = 0.3  # rad: every joint of a home pose at least this far inside its limits
NAMES = robots.names()


def _revolute_chain(urdf: str) -> list[str]:
    """The URDF's revolute joints from its root link down (the arm chain the action drives)."""
    root = ET.parse(assets.path("urdf", urdf)).getroot()
    joints = root.findall("joint")
    children = {j.find("child").get("link") for j in joints}
    link = next(lk.get("name") for lk in root.findall("link") if lk.get("name") not in children)
    chain = []
    while True:
        nxt = [j for j in joints if j.find("parent").get("link") == link and j.get("type") == "revolute"]
        if not nxt:
            return chain
        chain.append(nxt[0].get("name"))
        link = nxt[0].find("child").get("link")


def _empty_reset(cfg: config.EnvConfig, q: np.ndarray, target: np.ndarray) -> sampling.ResetSpec:
    slots = cfg.sampling.max_obstacles
    return sampling.ResetSpec(
        q0=q, target_pos=np.asarray(target, float), target_yaw=np.asarray(0.0), obstacle_active=np.zeros(slots, bool),
        obstacle_kind=np.zeros(slots, np.int32), obstacle_pos=np.tile([0.0, 0.0, -5.0], (slots, 1)),
        obstacle_yaw=np.zeros(slots), obstacle_size=np.tile([0.01, 0.0, 0.0], (slots, 1)), redraws=np.asarray(0),
        fallback=np.asarray(False))


def _hits(model: robot.RobotModel, q: np.ndarray, target: np.ndarray) -> list[str]:
    cfg = config.get_config("paper").env
    kin = robot.forward_kinematics(np, model, q)
    result = collision.check(np, model, kin, _empty_reset(cfg, q, target), cfg)
    return [kind for kind, hit in result.hits.items() if bool(hit)]


@pytest.mark.parametrize("name", NAMES)
def test_every_robot_parses_with_its_urdf_arm_chain(name):
    spec = robots.get(name)
    model = robot.load_robot(name)
    assert model.spec is spec and model.dof == spec.dof
    assert list(spec.arm_joints) == _revolute_chain(spec.urdf)
    assert os.path.isfile(assets.path("mjcf", spec.mjcf_robot)) and os.path.isfile(assets.path("mjcf", spec.mjcf_scene))


@pytest.mark.parametrize("name", NAMES)
def test_home_pose_resolves_to_the_pasted_values_inside_the_limits(name):
    spec = robots.get(name)
    model = robot.load_robot(name)
    q = robot.solve_home_pose(spec.home_seed, (0.0, -0.30, 0.35), model)
    np.testing.assert_allclose(q, spec.home_q, atol=1e-6)
    kin = robot.forward_kinematics(np, model, np.array(spec.home_q))
    np.testing.assert_allclose(kin.gripper_centre, (0.0, -0.30, 0.35), atol=1e-6)
    np.testing.assert_allclose(kin.approach_axis, (0.0, 0.0, -1.0), atol=1e-6)
    margin = np.minimum(np.array(spec.home_q) - model.q_lower, model.q_upper - np.array(spec.home_q))
    assert margin.min() >= HOME_MARGIN, f"{name}: home is {margin.min():.3f} rad from joint {margin.argmin() + 1}'s limit"


@pytest.mark.parametrize("name", NAMES)
def test_fine_tune_joints_axes_have_full_rank_at_home(name):
    spec = robots.get(name)
    kin = robot.forward_kinematics(np, robot.load_robot(name), np.array(spec.home_q))
    axes = kin.joint_axes[list(spec.fine_tune_joints)]  # (2, 3)
    assert np.linalg.svd(axes, compute_uv=False).min() > 0.5


@pytest.mark.parametrize("name", NAMES)
def test_home_is_collision_free(name):
    spec = robots.get(name)
    assert _hits(robot.load_robot(name), np.array(spec.home_q), np.array([0.3, -0.45, 0.025])) == []


def test_panda_top_down_grasps_over_the_target_region_are_reachable_and_collision_free():
    """IK from home in 12 waypoints to the cube centre, pointing down: within the limits, nothing touched
    (24 targets here; 520 of 520 when this entry was made, the least margin 0.044 rad on joint 4)."""
    model = robot.load_robot("panda")
    s = config.SamplingConfig()
    rng = np.random.default_rng(1)
    home = np.array(model.spec.home_q)
    start = robot.forward_kinematics(np, model, home).gripper_centre
    done = 0
    while done < 24:
        x, y = rng.uniform(*s.target_x), rng.uniform(*s.target_y)
        if not s.target_radius[0] <= np.hypot(x, y) <= s.target_radius[1]:
            continue
        target = np.array([x, y, s.target_size[2] / 2])
        q = home
        for a in np.linspace(0, 1, 13)[1:]:
            q = robot.approach_pose(model, q, start + (target - start) * a)
        assert np.all(q >= model.q_lower) and np.all(q <= model.q_upper), (target, q)
        assert _hits(model, q, target) == [], target
        done += 1


# Franka's collision meshes (pybullet_data/franka_panda/meshes/collision) and the pose of each in the frame of the
# link that hosts its primitives in RobotModel (the hand and the open fingers ride on link7): pybullet_data's
# panda.urdf frames.
def _rz(angle: float, xyz=(0.0, 0.0, 0.0)) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = robot.rpy_to_matrix((0.0, 0.0, angle))
    t[:3, 3] = xyz
    return t


_HAND = np.eye(4)
_HAND[2, 3] = 0.107
_HAND = _HAND @ _rz(-np.pi / 4)
MESHES = {f"link{i}": (i, np.eye(4)) for i in range(8)}
MESHES["hand"] = (7, _HAND)
MESHES["finger"] = (7, _HAND @ _rz(0.0, (0.0, 0.04, 0.0584)))
MESHES["finger_right"] = (7, _HAND @ _rz(np.pi, (0.0, -0.04, 0.0584)))


def _obj_vertices(path: str) -> np.ndarray:
    with open(path) as f:
        return np.array([[float(v) for v in line.split()[1:4]] for line in f if line.startswith("v ")])


def _uncovered(model: robot.RobotModel, vertices: np.ndarray, link: int) -> float:
    """The largest distance (m) of a vertex (in the link's frame) outside the union of the link's primitives."""
    sdf = [geometry.point_distance(np, p.kind, vertices, p.local[:3, 3], p.local[:3, :3], np.array(p.size))
           for p in model.primitives if p.link == link]
    return float(np.min(sdf, axis=0).max())


@pytest.mark.parametrize("mesh", sorted(MESHES))
def test_panda_primitives_cover_frankas_collision_meshes(mesh):
    pybullet_data = pytest.importorskip("pybullet_data")
    link, pose = MESHES[mesh]
    path = os.path.join(pybullet_data.getDataPath(), "franka_panda", "meshes", "collision",
                        mesh.replace("_right", "") + ".obj")
    vertices = _obj_vertices(path) @ pose[:3, :3].T + pose[:3, 3]
    assert _uncovered(robot.load_robot("panda"), vertices, link) < 0.003  # every vertex inside or within 3 mm


@pytest.mark.parametrize("change, message", [
    ({"home_q": (0.0,) * 6}, "home_q and home_seed need 7 values"),
    ({"servo": dataclasses.replace(robots.PANDA.servo, kp=(1.0,) * 6)}, "servo.kp needs 7 values"),
    ({"fine_tune_joints": (4, 6)}, "must be two consecutive joints"),
    ({"self_static_to_link": 5}, "the static group below the moving one"),
    ({"reach_link": 8}, "reach_link must be link indices in 1..7"),
])
def test_register_refuses_a_malformed_spec_naming_the_problem(change, message):
    bad = dataclasses.replace(robots.PANDA, name="panda_bad", **change)
    with pytest.raises(ValueError, match=message.replace(".", r"\.")) as err:
        robots.register(bad)
    assert "panda_bad" in str(err.value)
    assert "panda_bad" not in robots.names()
