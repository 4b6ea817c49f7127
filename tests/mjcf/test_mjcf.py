"""Generated MJCF: up to date with the URDF and scene, loads in MJX, camera where docs/task.md §1.3 says."""

import math
import os
import subprocess
import sys

import numpy as np
import pytest

import sagrasp_jax  # noqa: F401
from sagrasp_jax.base import assets
from sagrasp_jax.task import config
from sagrasp_jax.task import robot
from sagrasp_jax.task import robots
from sagrasp_jax.task import scene
from paths import REPO as ROOT  # noqa: E402

TOOL = os.path.join(ROOT, "tools", "urdf_to_mjcf.py")


def test_committed_mjcf_is_what_the_tool_generates(tmp_path):
    out = subprocess.run([sys.executable, TOOL, "--out-dir", str(tmp_path)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    files = [name for r in robots.names() for name in (robots.get(r).mjcf_robot, robots.get(r).mjcf_scene)]
    assert {"aubo_i5_eg2.xml", "scene.xml", "panda.xml", "scene_panda.xml"} <= set(files)
    assert sorted(os.listdir(tmp_path)) == sorted(files)  # every registered robot's two files, nothing else
    for name in files:
        with open(os.path.join(assets.MJCF_DIR, name)) as committed, open(tmp_path / name) as fresh:
            assert committed.read() == fresh.read(), f"sagrasp_jax/mjcf/{name} is stale: run python tools/urdf_to_mjcf.py"


@pytest.mark.parametrize("content, needle", [(None, "not found"), ("<robot><link>", "malformed"),
                                             ("<robot name='x'><link name='a'/></robot>", "missing")])
def test_bad_urdf_exits_nonzero_and_writes_nothing(tmp_path, content, needle):
    urdf = tmp_path / "bad.urdf"
    if content is not None:
        urdf.write_text(content)
    out_dir = tmp_path / "out"
    result = subprocess.run([sys.executable, TOOL, "--urdf", str(urdf), "--out-dir", str(out_dir)],
                            capture_output=True, text=True)
    assert result.returncode != 0
    assert "bad.urdf" in result.stderr and needle in result.stderr
    assert not out_dir.exists() or not any(out_dir.iterdir())


def test_scene_contents():
    import mujoco

    model = mujoco.MjModel.from_xml_path(assets.MJCF_SCENE)
    names = {model.geom(i).name for i in range(model.ngeom)}
    for part in scene.SCENE.static_parts:
        assert part.name in names
    assert {"table", "target_geom", "obstacle_1_box"} <= names
    assert model.nu == 8 and model.nmocap == 3
    post = model.geom("gantry_post_right")
    np.testing.assert_allclose(post.pos, [0.60, -0.40, 0.77])
    np.testing.assert_allclose(2 * post.size, [0.04, 0.04, 1.54])


def test_mjx_accepts_scene_and_steps_without_nan():
    import jax
    import jax.numpy as jnp
    import mujoco
    from mujoco import mjx

    model = mujoco.MjModel.from_xml_path(assets.MJCF_SCENE)
    model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    mx = mjx.put_model(model)
    home = jnp.concatenate([jnp.asarray(config.HOME_Q, jnp.float32), jnp.full(2, 0.033)])

    def one(noise):
        d = mjx.make_data(mx).replace(qpos=home + jnp.pad(noise, (0, 2)), ctrl=home)
        return mjx.step(mx, d)

    noise = jax.random.uniform(jax.random.PRNGKey(0), (8, 6), minval=-0.05, maxval=0.05)
    d = jax.jit(jax.vmap(one))(noise)
    assert d.qpos.shape == (8, 8)
    assert bool(jnp.all(jnp.isfinite(d.qpos)))


def test_camera_pose_and_field_of_view_cover_the_target_region():
    import mujoco

    model = mujoco.MjModel.from_xml_path(assets.MJCF_SCENE)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    cam = data.camera("depth_camera")
    np.testing.assert_allclose(cam.xpos, [-0.16208, -0.40337, 1.40824], atol=1e-9)
    view = -cam.xmat.reshape(3, 3)[:, 2]  # MuJoCo cameras look along their −z
    np.testing.assert_allclose(view, scene.SCENE.camera.optical_axis, atol=1e-6)  # quat printed to 1e-7
    s = config.SamplingConfig()
    worst = 0.0
    for x in np.linspace(*s.target_x, 36):
        for y in np.linspace(*s.target_y, 36):
            if not s.target_radius[0] <= math.hypot(x, y) <= s.target_radius[1]:
                continue
            ray = np.array([x, y, 0.025]) - cam.xpos
            worst = max(worst, math.degrees(math.acos(ray @ view / np.linalg.norm(ray))))
    assert 10.0 < worst < 20.0
    # the MJCF camera is the scene's camera model (task.camera): its field of view and pixels
    assert model.cam_fovy[cam.id] == pytest.approx(scene.SCENE.camera.model.fovy_deg, abs=1e-4)
    assert tuple(model.cam_resolution[cam.id]) == scene.SCENE.camera.resolution == (1920, 1200)
    # every sampled cube's top corners project inside the image, 10 px from its border
    k = scene.SCENE.camera.model.intrinsics
    xs, ys = np.meshgrid(np.linspace(*s.target_x, 36), np.linspace(*s.target_y, 36))
    inside = [(x, y) for x, y in zip(xs.ravel(), ys.ravel()) if s.target_radius[0] <= math.hypot(x, y) <= s.target_radius[1]]
    corners = np.array([[x + dx, y + dy, 0.05] for x, y in inside for dx in (-0.015, 0.015) for dy in (-0.015, 0.015)])
    uv = k.project((corners - scene.SCENE.camera.pos) @ scene.SCENE.camera.rot)
    assert len(inside) > 1000
    assert uv[:, 0].min() > 10 and uv[:, 0].max() < k.width - 10 and uv[:, 1].min() > 10 and uv[:, 1].max() < k.height - 10


@pytest.mark.parametrize("name", robots.names())
def test_dynamic_servo_tracks_a_small_step(name):
    """Position servos + gravity compensation: hold the home pose and follow a 0.05 rad step on every joint
    within two control periods, without overshooting or limit-cycling afterwards."""
    import mujoco

    spec = robots.get(name)
    model = mujoco.MjModel.from_xml_path(assets.path("mjcf", spec.mjcf_scene))
    data = mujoco.MjData(model)
    n, arm = spec.dof, robot.load_robot(name)
    home = np.array(spec.home_q)
    data.qpos[:n] = home
    data.qpos[n:n + 2] = arm.finger_open
    data.ctrl[:n] = home
    data.ctrl[n:n + 2] = arm.finger_open
    for _ in range(50):
        mujoco.mj_step(model, data)
    assert np.abs(data.qpos[:n] - home).max() < 1e-6  # gravity compensated
    data.ctrl[:n] = home + 0.05
    for _ in range(10):  # two control periods
        mujoco.mj_step(model, data)
    assert np.abs(data.qpos[:n] - (home + 0.05)).max() < 0.01
    after = []
    for _ in range(50):  # five more periods: settled, no limit cycle
        mujoco.mj_step(model, data)
        after.append(np.abs(data.qpos[:n] - (home + 0.05)).max())
    assert max(after) < 0.01 and after[-1] < 0.002
    mujoco.mj_kinematics(model, data)
    kin = robot.forward_kinematics(np, arm, data.qpos[:n])
    assert np.linalg.norm(kin.gripper_centre - data.site("gripper_center").xpos) < 1e-9
