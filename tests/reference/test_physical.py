"""Physical grasp check: a scripted kinematic success holds the cube when lifted; 3 cm off it does not."""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import dataclasses
import json
import os

import numpy as np
import pytest

from sagrasp_jax.task.config import get_config
from sagrasp_jax.reference.grasp_check import GraspScene, PhysicalCheckError, physical_grasp_check
from sagrasp_jax.task.robot import BOX, CYLINDER
from sagrasp_jax.task.sampling import ResetSpec
from tiny_run import tiny_run


@pytest.fixture(scope="module")
def scripted_grasp() -> tuple[np.ndarray, ResetSpec]:
    """Final joints and scene of an episode that tests/scripted.py's controller drives to kinematic
    success through the JAX env (noise off)."""
    import jax

    from scripted import scripted_action
    from sagrasp_jax.envs.grasp_env import GraspEnv

    cfg = get_config("cpu-quick").env
    cfg = dataclasses.replace(cfg, task=dataclasses.replace(cfg.task, obs_noise_std=0.0))
    env = GraspEnv(cfg)

    @jax.jit
    def step(state):
        return env.step(state, scripted_action(cfg, state.info["q_target"], state.info["reset"].target_pos))

    for seed in range(5):
        state = jax.jit(env.reset)(jax.random.PRNGKey(seed))
        for _ in range(cfg.task.max_steps):
            state = step(state)
            if float(state.done):
                break
        if float(state.info["episode"]["success"]):
            spec = ResetSpec(*(np.asarray(v) for v in jax.device_get(state.info["reset"])))
            return np.asarray(state.info["q_target"], dtype=float), spec
    pytest.fail("the scripted controller reached no kinematic success in 5 episodes")


def test_scripted_success_holds_the_cube(scripted_grasp) -> None:
    q, spec = scripted_grasp
    result = physical_grasp_check(q, spec)
    assert result["success"], result
    assert result["criteria"] == {"rose_with_gripper": True, "both_pads_touch": True, "between_pads": True}
    assert abs(result["gripper_rise"] - 0.05) < 0.003
    assert result["cube_rise"] > 0.04
    assert all(0.0 < f < 0.012 for f in result["finger_opening"])  # closed on a 2 cm cube, not on nothing
    json.dumps(result)


def test_three_cm_off_fails(scripted_grasp) -> None:
    """Same pose, cube moved 3 cm sideways (across the finger axis, so the open pads do not touch it)."""
    q, spec = scripted_grasp
    scene = GraspScene(spec, q)
    across = scene.data.site("gripper_center").xmat.reshape(3, 3)[:, 1]
    across[2] = 0.0
    shifted = spec._replace(target_pos=spec.target_pos + 0.03 * across / np.linalg.norm(across))
    result = physical_grasp_check(q, shifted)
    assert not result["success"]
    assert not result["criteria"]["rose_with_gripper"] and not result["criteria"]["both_pads_touch"]
    assert abs(result["cube_rise"]) < 0.005
    assert "pad not touching the cube" in result["reason"]
    assert max(result["finger_opening"]) < 0.001  # the fingers closed on nothing


def test_scene_places_the_episode_obstacles(scripted_grasp) -> None:
    q, spec = scripted_grasp
    spec = spec._replace(
        obstacle_active=np.array([True, True]),
        obstacle_kind=np.array([CYLINDER, BOX]),
        obstacle_pos=np.array([[0.3, -0.3, 0.1], [-0.3, -0.5, 0.04]]),
        obstacle_yaw=np.array([0.0, 0.5]),
        obstacle_size=np.array([[0.03, 0.1, 0.0], [0.02, 0.03, 0.04]]),
    )
    model = GraspScene(spec, q).model
    cyl, box, sph = (model.geom(f"obstacle_{i}_{k}") for i, k in ((0, "cylinder"), (1, "box"), (0, "sphere")))
    np.testing.assert_allclose(cyl.size[:2], [0.03, 0.1])
    np.testing.assert_allclose(box.size, [0.02, 0.03, 0.04])
    assert cyl.contype == 1 and cyl.rgba[3] == 1.0 and sph.contype == 0 and sph.rgba[3] == 0.0
    np.testing.assert_allclose(model.body("obstacle_1").pos, [-0.3, -0.5, 0.04])
    np.testing.assert_allclose(model.body("obstacle_1").quat, [np.cos(0.25), 0, 0, np.sin(0.25)])
    assert model.body("target").jntnum == 1 and model.nmocap == 2  # the target is free, obstacles stay mocap


def test_bad_input_refused(scripted_grasp) -> None:
    q, spec = scripted_grasp
    with pytest.raises(PhysicalCheckError, match="arm joints must be 6 finite numbers"):
        physical_grasp_check(np.full(6, np.nan), spec)
    with pytest.raises(PhysicalCheckError, match="target_pos must be 3 finite numbers"):
        physical_grasp_check(q, spec._replace(target_pos=np.array([0.1, np.nan, 0.025])))


def test_evaluate_physical_flag(tmp_path_factory: pytest.TempPathFactory, tmp_path) -> None:
    """``evaluate --physical`` adds the physical success rate next to the kinematic one."""
    from sagrasp_jax import evaluate

    run_dir = tiny_run(str(tmp_path_factory.getbasetemp()))
    out = tmp_path / "eval.json"
    assert evaluate.main(["--run", run_dir, "--episodes", "8", "--physical", "--out", str(out)]) == 0
    results = json.loads(out.read_text())
    phys = results["physical"]
    assert phys["episodes"] == 8
    assert phys["kinematic_successes"] == round(results["overall"]["success_rate"] * 8)
    assert 0 <= phys["physical_successes"] <= phys["kinematic_successes"]
    assert os.path.exists(out)
