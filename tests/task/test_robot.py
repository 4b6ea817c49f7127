"""Robot facts: URDF-driven FK against the flange checkpoints of docs/task.md §1.2, standard DH, MuJoCo, MJX and PyBullet."""

import math

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax)
from sagrasp_jax.base import assets
from sagrasp_jax.task import config
from sagrasp_jax.task import robot
from sagrasp_jax.task import scene

ROBOT = robot.load_robot()


def dh_flange(q: np.ndarray) -> np.ndarray:
    """Standard DH of docs/task.md §1: (θ, d, a, α)."""
    rows = [
        (q[0], 0.122, 0.0, math.pi / 2),
        (q[1] + math.pi / 2, 0.0, 0.408, 0.0),
        (-q[2], 0.0, 0.376, 0.0),
        (q[3] - math.pi / 2, 0.1215, 0.0, -math.pi / 2),
        (q[4], 0.1025, 0.0, math.pi / 2),
        (q[5], 0.094, 0.0, 0.0),
    ]
    t = np.eye(4)
    for theta, d, a, alpha in rows:
        ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
        t = t @ np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1]])
    return t[:3, 3]


def random_qs(n: int = 200, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-3.0, 3.0, size=(n, 6))


@pytest.mark.parametrize(
    "q, expected",
    [
        ((0, 0, 0, 0, 0, 0), (0, -0.2155, 1.0085)),
        ((0, math.pi / 2, 0, 0, 0, 0), (-0.8865, -0.2155, 0.122)),
        ((0, math.pi / 2, 0, math.pi / 2, 0, 0), (-0.784, -0.2155, 0.0195)),
    ],
)
def test_flange_checkpoints(q, expected):
    kin = robot.forward_kinematics(np, ROBOT, np.array(q, dtype=float))
    np.testing.assert_allclose(kin.flange_pos, expected, atol=1e-6)


def test_fk_equals_standard_dh_at_random_poses():
    qs = random_qs()
    kin = robot.forward_kinematics(np, ROBOT, qs)  # batched
    dh = np.stack([dh_flange(q) for q in qs])
    assert np.abs(kin.flange_pos - dh).max() < 1e-6


def test_urdf_facts_match_spec():
    np.testing.assert_allclose(ROBOT.q_upper, 3.0543)
    np.testing.assert_allclose(ROBOT.q_lower, -3.0543)
    np.testing.assert_allclose(ROBOT.velocity_limit, [2.5964] * 3 + [3.1105] * 3)
    np.testing.assert_allclose(ROBOT.effort_limit, [133] * 3 + [13.5] * 3)
    assert ROBOT.link_masses["upperArm_Link"] == pytest.approx(10.836)
    assert ROBOT.link_masses["wrist3_Link"] == pytest.approx(0.198)
    assert ROBOT.finger_open == pytest.approx(0.033)
    # gripper centre on the flange axis, ≈ 0.13 m past the flange
    assert ROBOT.gripper_centre_local[:2] == pytest.approx([0, 0], abs=1e-12)
    assert 0.12 < ROBOT.gripper_centre_local[2] < 0.14


def test_jax_fk_equals_numpy_and_mjx_kinematics():
    import jax
    import jax.numpy as jnp
    import mujoco
    from mujoco import mjx

    qs = random_qs(64, seed=1)
    kin_np = robot.forward_kinematics(np, ROBOT, qs)
    kin_jx = jax.jit(jax.vmap(lambda q: robot.forward_kinematics(jnp, ROBOT, q)))(jnp.asarray(qs, jnp.float32))
    assert np.abs(np.asarray(kin_jx.gripper_centre) - kin_np.gripper_centre).max() < 1e-5  # float32

    model = mujoco.MjModel.from_xml_path(assets.MJCF_ROBOT)
    mx = mjx.put_model(model)

    def mjx_sites(q):
        d = mjx.make_data(mx)
        d = d.replace(qpos=jnp.concatenate([q, jnp.full(2, ROBOT.finger_open)]))
        d = mjx.kinematics(mx, d)
        return d.site_xpos

    sites = np.asarray(jax.jit(jax.vmap(mjx_sites))(jnp.asarray(qs, jnp.float32)))
    flange = sites[:, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "flange")]
    centre = sites[:, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "gripper_center")]
    assert np.abs(flange - kin_np.flange_pos).max() < 1e-5
    assert np.abs(centre - kin_np.gripper_centre).max() < 1e-5


def test_fk_equals_cpu_mujoco_in_float64():
    import mujoco

    model = mujoco.MjModel.from_xml_path(assets.MJCF_ROBOT)
    data = mujoco.MjData(model)
    qs = random_qs(200, seed=2)
    kin = robot.forward_kinematics(np, ROBOT, qs)
    prim_pos, _ = robot.primitive_poses(np, ROBOT, kin)
    for i, q in enumerate(qs):
        data.qpos[:6] = q
        data.qpos[6:8] = ROBOT.finger_open
        mujoco.mj_kinematics(model, data)
        assert np.abs(data.site("flange").xpos - kin.flange_pos[i]).max() < 1e-6
        assert np.abs(data.site("gripper_center").xpos - kin.gripper_centre[i]).max() < 1e-6
        for g, prim in enumerate(ROBOT.primitives):
            body = prim.name.split("/")[0]
            assert np.abs(data.geom(f"{body}_geom").xpos - prim_pos[i, g]).max() < 1e-6


def test_pybullet_matches_at_200_poses():
    pybullet = pytest.importorskip("pybullet")
    client = pybullet.connect(pybullet.DIRECT)
    try:
        body = pybullet.loadURDF(robot.URDF_PATH, useFixedBase=True, physicsClientId=client)
        names = {}
        for j in range(pybullet.getNumJoints(body, physicsClientId=client)):
            info = pybullet.getJointInfo(body, j, physicsClientId=client)
            names[info[1].decode()] = j
            names[info[12].decode()] = j  # child link name -> link index
        arm = [names[n] for n in robot.ARM_JOINTS]
        qs = random_qs(200, seed=3)
        kin = robot.forward_kinematics(np, ROBOT, qs)
        for i, q in enumerate(qs):
            for j, v in zip(arm, q):
                pybullet.resetJointState(body, j, v, physicsClientId=client)
            for f in robot.FINGER_JOINTS:
                pybullet.resetJointState(body, names[f], ROBOT.finger_open, physicsClientId=client)
            flange = pybullet.getLinkState(body, names["flange"], computeForwardKinematics=True, physicsClientId=client)[4]
            centre = pybullet.getLinkState(body, names["gripper_center"], computeForwardKinematics=True, physicsClientId=client)[4]
            assert np.abs(np.array(flange) - kin.flange_pos[i]).max() < 1e-5
            assert np.abs(np.array(centre) - kin.gripper_centre[i]).max() < 1e-5
    finally:
        pybullet.disconnect(client)


def test_home_pose():
    q = np.array(config.HOME_Q)
    solved = robot.solve_home_pose(config.HOME_SEED)
    np.testing.assert_allclose(q, solved, atol=1e-6)  # the stored pose is the IK solution
    assert np.all(np.abs(q - np.array(config.HOME_SEED)) < 0.05)
    assert np.all(ROBOT.q_upper - q >= 0.5) and np.all(q - ROBOT.q_lower >= 0.5)
    kin = robot.forward_kinematics(np, ROBOT, q)
    assert math.degrees(robot.tilt(np, kin.approach_axis)) < 1.0
    assert np.linalg.norm(kin.gripper_centre - np.array(config.HOME_GRIPPER_CENTRE)) < 0.005


def test_home_pose_clear_of_table_and_static_parts():
    """Every robot primitive is above the table (base excepted) and far from the gantry and camera."""
    kin = robot.forward_kinematics(np, ROBOT, np.array(config.HOME_Q))
    pos, _ = robot.primitive_poses(np, ROBOT, kin)
    sizes = ROBOT.prim_size
    for g, prim in enumerate(ROBOT.primitives):
        if prim.link >= 2:  # upper arm onwards can reach the table
            assert pos[g, 2] - np.max(sizes[g]) > 0.02
        for part in scene.SCENE.static_parts:
            gap = np.linalg.norm(pos[g] - np.array(part.pos)) - np.linalg.norm(part.size) - np.linalg.norm(sizes[g])
            if part.role == "camera":
                assert gap > 0.3
            # bounding-sphere gap is a lower bound of the true clearance
            assert gap > 0.0 or abs(pos[g, 0] - part.pos[0]) > part.size[0] + 0.1


def test_bad_urdf_is_refused(tmp_path):
    missing = tmp_path / "nope.urdf"
    with pytest.raises(robot.URDFError, match="nope.urdf"):
        robot.parse_urdf(str(missing))
    broken = tmp_path / "broken.urdf"
    broken.write_text("<robot><link name='a'>")
    with pytest.raises(robot.URDFError, match="malformed"):
        robot.parse_urdf(str(broken))
