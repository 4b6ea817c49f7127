"""Camera models are a registry (``task/camera.py``: ``register``, ``registered``, ``names``, ``camera_model``).

A toy model (a 640 × 400 structured-light camera with its own intrinsics, the ``industrial`` noise and the
``mecheye`` driver) registered for a block is accepted wherever a camera model is named: the rehearsal's
``--camera-model`` (a parser built before the block included; refused again after it), the twin camera the
rehearsal's ``--camera twin`` renders with (the cube in its view at the toy's intrinsics), a capture file
written with it (read back); and malformed models are refused, naming the problem.
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import pytest

from sagrasp_jax.task import camera
from sagrasp_jax.task.camera import CameraModel, Intrinsics

TOY = CameraModel("toy_structured_light", "a toy 640 × 400 structured-light camera",
                  Intrinsics(640, 400, 610.0, 608.0, 321.5, 198.25), "industrial", "mecheye", (0.5, 2.5))


def _rehearse_parser() -> argparse.ArgumentParser:
    from sagrasp_jax.deploy import rehearse

    p = argparse.ArgumentParser(prog="rehearse")
    rehearse.add_arguments(p)
    return p


def test_a_registered_model_is_listed_and_looked_up_only_in_its_block() -> None:
    before = camera.names()
    assert before[0] == camera.DEFAULT_CAMERA and TOY.name not in before
    with camera.registered(TOY) as added:
        assert added == (TOY,)
        assert camera.names() == (*before, TOY.name)
        assert camera.camera_model(TOY.name) is TOY and TOY.name in camera.CHOICES
    assert camera.names() == before and TOY.name not in camera.CHOICES
    with pytest.raises(ValueError, match="unknown camera model 'toy_structured_light'; known: mecheye_pro_m"):
        camera.camera_model(TOY.name)


def test_the_registry_is_restored_after_an_error_in_the_block() -> None:
    before = camera.names()
    with pytest.raises(RuntimeError, match="inside"):
        with camera.registered(TOY):
            raise RuntimeError("inside")
    assert camera.names() == before
    with pytest.raises(ValueError, match="name 'mecheye_pro_m' is taken"):  # the second one fails: the first goes too
        with camera.registered(TOY, dataclasses.replace(TOY, name="mecheye_pro_m")):
            pass
    assert camera.names() == before


def test_the_drivers_are_one_list() -> None:
    from sagrasp_jax.deploy import cameras

    assert cameras.CAMERAS == camera.DRIVERS
    assert all(camera.camera_model(n).driver in camera.DRIVERS for n in camera.names())
    with pytest.raises(cameras.CameraError, match="is not one of mecheye, realsense"):
        cameras.open_camera("toy")


def test_the_rehearsal_accepts_the_model_in_the_block_and_refuses_it_after(capsys) -> None:
    from sagrasp_jax.deploy import rehearse

    early = _rehearse_parser()  # built before the model exists: its choices are the registry when parsing
    argv = ["--camera", "twin", "--camera-model", TOY.name]
    with camera.registered(TOY):
        for p in (early, _rehearse_parser()):
            args = p.parse_args(argv)
            settings = rehearse.camera_settings(args)
            assert (settings.model, settings.noise) == (TOY.name, "industrial")  # the noise defaults to the model's
        assert TOY.name in early.format_help()
    for p in (early, _rehearse_parser()):
        with pytest.raises(SystemExit):
            p.parse_args(argv)
        assert f"invalid choice: '{TOY.name}'" in capsys.readouterr().err


def test_the_twin_renders_the_model_and_its_capture_file_reads_back(tmp_path) -> None:
    pytest.importorskip("pybullet")
    from sagrasp_jax.deploy import capture_file, rehearse
    from sagrasp_jax.deploy.twin import PyBulletTwin
    from sagrasp_jax.deploy.twin_camera import TwinCamera
    from sagrasp_jax.task.config import EnvConfig

    env_cfg = EnvConfig()
    scene_cfg = rehearse.scene_env(env_cfg, "mix")
    spec, rng = rehearse.draw_scene(scene_cfg, 0, 3)
    with camera.registered(TOY):
        settings = rehearse.camera_settings(_rehearse_parser().parse_args(
            ["--camera", "twin", "--camera-model", TOY.name, "--camera-resolution", "0.25"]))
        k = TOY.intrinsics.scaled(0.25)
        assert (k.width, k.height) == (160, 100)
        with PyBulletTwin(spec, env_cfg, q0=spec.q0, seed=3) as twin:
            cap = rehearse.twin_capture(twin, spec, settings, rng, rehearse.episode_kind(spec, scene_cfg), "toy twin")
            frame = TwinCamera(settings.resolution, model=settings.model).capture(twin, hide_robot=True)
            cube = frame.segmentation == twin.target_body
        assert cap.camera == TOY.name and cap.intrinsics == k
        assert cap.rgb.shape == (100, 160, 3) and cap.cloud_mm.shape == (100, 160, 3)
        assert frame.intrinsics == k and cube.sum() >= 4
        z = frame.cloud_mm[cube][:, 2]
        assert np.isfinite(z).all() and 500.0 < z.min() < z.max() < 2500.0  # inside the toy's depth range
        path = capture_file.save_capture(str(tmp_path / "toy.npz"), cap)
        back = capture_file.load_capture(path)
        assert back.camera == TOY.name and back.intrinsics == k
        assert np.array_equal(back.rgb, cap.rgb) and np.array_equal(back.cloud_mm, cap.cloud_mm, equal_nan=True)
    with pytest.raises(capture_file.CaptureFormatError, match="camera 'toy_structured_light' is not one of"):
        capture_file.load_capture(path)  # the model is gone with its block


def _tampered(k: Intrinsics, **fields: float) -> Intrinsics:
    """``k`` with fields changed behind its own check (the only way to a malformed Intrinsics)."""
    k = dataclasses.replace(k)
    for name, value in fields.items():
        object.__setattr__(k, name, value)
    return k


@pytest.mark.parametrize("change, message", [
    ({"name": "mecheye_pro_m"}, "name 'mecheye_pro_m' is taken"),
    ({"name": "toy camera"}, "name 'toy camera' must be an identifier"),
    ({"noise": "fuzzy"}, "noise model 'fuzzy' is not one of none, industrial, consumer"),
    ({"driver": "zivid"}, "driver 'zivid' is not one of mecheye, realsense"),
    ({"intrinsics": _tampered(TOY.intrinsics, fx=-610.0)}, "focal lengths positive"),
    ({"intrinsics": _tampered(TOY.intrinsics, fy=float("nan"))}, "must be finite"),
    ({"intrinsics": _tampered(TOY.intrinsics, width=0)}, "the size and the focal lengths positive"),
    ({"intrinsics": [640, 400, 610.0, 608.0, 321.5, 198.25]}, "intrinsics must be a task.camera.Intrinsics, got list"),
    ({"depth_range_m": (2.5, 0.5)}, "depth range (2.5, 0.5) must be two finite distances, m, with 0 < near < far"),
    ({"depth_range_m": (0.0, 2.5)}, "0 < near < far"),
    ({"depth_range_m": (0.5, float("inf"))}, "0 < near < far"),
    ({"depth_range_m": (0.5,)}, "0 < near < far"),
])
def test_a_malformed_model_is_refused_naming_the_problem(change, message) -> None:
    before = camera.names()
    bad = dataclasses.replace(TOY, **change)
    with pytest.raises(ValueError, match="cannot be registered") as err:
        camera.register(bad)
    assert message in str(err.value)
    assert camera.names() == before


def test_every_problem_is_named_at_once_and_intrinsics_check_themselves() -> None:
    with pytest.raises(ValueError) as err:
        camera.register(dataclasses.replace(TOY, noise="fuzzy", driver="zivid", depth_range_m=(1.0, 1.0)))
    assert all(m in str(err.value) for m in ("noise model 'fuzzy'", "driver 'zivid'", "depth range (1.0, 1.0)"))
    with pytest.raises(ValueError, match="the focal lengths positive"):
        Intrinsics(640, 400, -610.0, 608.0, 321.5, 198.25)
    with pytest.raises(ValueError, match="must be a task.camera.CameraModel"):
        camera.register(TOY.name)  # type: ignore[arg-type]
