"""Rollout video: mp4 + png when an offscreen GL backend works; a clear error when none does."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tiny_run import REPO, tiny_run

PROBE = (
    "import mujoco; from sagrasp_jax.base import assets; m = mujoco.MjModel.from_xml_path(assets.MJCF_SCENE); r = mujoco.Renderer(m, 32, 32); "
    "d = mujoco.MjData(m); mujoco.mj_forward(m, d); r.update_scene(d); r.render(); r.close()"
)


def _egl_works() -> str | None:
    """None if MuJoCo renders offscreen with EGL here, else why not."""
    res = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120, cwd=REPO,
                         env=dict(os.environ, MUJOCO_GL="egl"))
    return None if res.returncode == 0 else (res.stderr.strip().splitlines() or ["unknown error"])[-1]


def _render(*args: str, gl: str | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    if gl is not None:
        env["MUJOCO_GL"] = gl
    return subprocess.run([sys.executable, "-m", "sagrasp_jax.render", *args], capture_output=True, text=True,
                          timeout=300, cwd=REPO, env=env)


def test_render_writes_mp4_and_png(tmp_path_factory: pytest.TempPathFactory, tmp_path) -> None:
    imageio = pytest.importorskip("imageio.v2", reason="the render extra (imageio, imageio-ffmpeg) is not installed")
    pytest.importorskip("imageio_ffmpeg", reason="the render extra (imageio, imageio-ffmpeg) is not installed")
    why = _egl_works()
    if why:
        pytest.skip(f"no offscreen GL backend (MUJOCO_GL=egl failed: {why}); install libegl1 libegl-mesa0 libopengl0 libgl1-mesa-dri")
    policy = os.path.join(tiny_run(str(tmp_path_factory.getbasetemp())), "policy.npz")
    video, still = tmp_path / "clip" / "rollout.mp4", tmp_path / "still.png"
    res = _render("--policy", policy, "--out", str(video), "--png", str(still), "--episodes", "2", "--max-steps", "5",
                  "--width", "160", "--height", "128", "--camera", "depth_camera")
    assert res.returncode == 0, res.stderr[-3000:]
    assert "MUJOCO_GL=egl" in res.stdout and "episode 2:" in res.stdout
    frames = imageio.mimread(str(video), memtest=False)
    # per episode: 10 hold frames, one per control step (5), 10 hold frames (the tiny policy does not grasp)
    assert len(frames) == 2 * (10 + 5 + 10)
    assert frames[0].shape == (128, 160, 3) and frames[0].std() > 5  # a picture, not a blank frame
    png = imageio.imread(str(still))
    assert png.shape == (128, 160, 3) and png.std() > 5
    assert sorted(os.listdir(video.parent)) == ["rollout.mp4"]  # no temp files left


def test_missing_gl_backend_is_a_clear_error(tmp_path_factory: pytest.TempPathFactory, tmp_path) -> None:
    policy = os.path.join(tiny_run(str(tmp_path_factory.getbasetemp())), "policy.npz")  # valid input: the GL fails
    res = _render("--policy", policy, "--out", str(tmp_path / "x.mp4"), gl="no-such-backend")
    assert res.returncode == 2
    assert "MUJOCO_GL='no-such-backend'" in res.stderr and "libegl1" in res.stderr
    assert "Traceback" not in res.stderr
    assert not os.path.exists(tmp_path / "x.mp4")


def test_bad_arguments_refused(tmp_path) -> None:
    res = _render("--policy", "unused.npz", "--out", str(tmp_path / "x.avi"))
    assert res.returncode == 2 and "must end in .mp4" in res.stderr
    res = _render("--policy", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "x.mp4"))
    assert res.returncode == 2 and "policy file not found" in res.stderr


def test_render_a_run_folder_writes_a_video_and_a_still(tmp_path_factory: pytest.TempPathFactory, tmp_path) -> None:
    """``--run RUN``: the run's policy.npz; the still lands beside the video by default."""
    imageio = pytest.importorskip("imageio.v2", reason="the render extra (imageio, imageio-ffmpeg) is not installed")
    pytest.importorskip("imageio_ffmpeg", reason="the render extra (imageio, imageio-ffmpeg) is not installed")
    why = _egl_works()
    if why:
        pytest.skip(f"no offscreen GL backend (MUJOCO_GL=egl failed: {why})")
    run = tiny_run(str(tmp_path_factory.getbasetemp()))
    res = _render("--run", run, "--out", str(tmp_path / "rollout.mp4"), "--episodes", "1", "--max-steps", "3",
                  "--width", "160", "--height", "128")
    assert res.returncode == 0, res.stderr[-3000:]
    assert sorted(os.listdir(tmp_path)) == ["rollout.mp4", "rollout.png"]
    assert len(imageio.mimread(str(tmp_path / "rollout.mp4"), memtest=False)) == 10 + 3 + 10
    assert imageio.imread(str(tmp_path / "rollout.png")).shape == (128, 160, 3)


def test_run_folders_render_cannot_use_are_refused(tmp_path) -> None:
    """A seed group, a run without its final policy, a folder that is no run: exit 2 saying what to pass."""
    (tmp_path / "group" / "seed0").mkdir(parents=True)
    (tmp_path / "group" / "seed0" / "config.json").write_text("{}")
    (tmp_path / "stopped").mkdir()
    (tmp_path / "stopped" / "config.json").write_text("{}")
    (tmp_path / "other").mkdir()
    for folder, message in (("group", "is a seed group (1 seeds): pass one seed's folder, e.g. "),
                            ("stopped", "has no policy.npz (a training writes it when it finishes); for a stopped run "
                                        "export its latest checkpoint: python -m sagrasp_jax.export --run "),
                            ("other", "is not a run folder (no config.json"), ("missing", "not found")):
        res = _render("--run", str(tmp_path / folder), "--out", str(tmp_path / "v.mp4"))
        assert res.returncode == 2 and message in res.stderr and "Traceback" not in res.stderr, res.stderr
    res = _render("--run", str(tmp_path / "stopped"), "--policy", "p.npz", "--out", str(tmp_path / "v.mp4"))
    assert res.returncode == 2 and "not allowed with argument" in res.stderr
    assert sorted(os.listdir(tmp_path)) == ["group", "other", "stopped"]
