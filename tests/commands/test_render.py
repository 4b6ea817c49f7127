"""Rollout video: mp4 + png when an offscreen GL backend works; a clear error when none does.  What the frames
show: the cube large enough to see, the obstacle scenes among the episodes, the banner with the outcome."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from tiny_run import REPO, tiny_run

from sagrasp_jax import render

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
    assert "MUJOCO_GL=egl" in res.stdout and "episode 2: blocking obstacle, timeout (timeout after 5 steps)" in res.stdout
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
    res = _render("--policy", "pretrained", "--out", str(tmp_path / "x.mp4"), "--camera", "top")
    assert res.returncode == 2 and "--camera must be one of tracking, overview, depth_camera, got 'top'" in res.stderr
    assert "Traceback" not in res.stderr and os.listdir(tmp_path) == []


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


# -- what the frames show -----------------------------------------------------------------------------------------

def _egl_or_skip() -> None:
    why = _egl_works()
    if why:
        pytest.skip(f"no offscreen GL backend (MUJOCO_GL=egl failed: {why}); install libegl1 libegl-mesa0 libopengl0 libgl1-mesa-dri")


def _cube_pixels(frame: np.ndarray) -> int:
    """Pixels of the red cube below the banner (nothing else in the scene is saturated red)."""
    r, g, b = (frame[..., i].astype(int) for i in range(3))
    mask = (r > 60) & (g < 0.4 * r) & (b < 0.4 * r)
    mask[: render.banner_height(frame.shape[0])] = False
    return int(mask.sum())


def _obstacle_pixels(frame: np.ndarray) -> int:
    """Pixels of the amber obstacles below the banner."""
    r, g, b = (frame[..., i].astype(int) for i in range(3))
    mask = (r > 80) & (g > 0.45 * r) & (g < 0.8 * r) & (b < 0.35 * r)
    mask[: render.banner_height(frame.shape[0])] = False
    return int(mask.sum())


def _in_subprocess(tmp_path, code: str) -> dict:
    """Run ``code`` (it writes ``out/result.json`` and ``out/*.npy``) in a fresh process with MUJOCO_GL=egl."""
    res = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=600,
                         cwd=REPO, env=dict(os.environ, MUJOCO_GL="egl"))
    assert res.returncode == 0, res.stderr[-3000:]
    with open(tmp_path / "result.json") as f:
        return json.load(f)


RENDERED = """
import json, sys
import numpy as np
from sagrasp_jax import render
frames, reports, still = render.render_episodes("pretrained", 2, "tracking", 0, 320, 240)
np.save(sys.argv[1] + "/frames.npy", np.stack(frames))
json.dump({"reports": reports, "still": still}, open(sys.argv[1] + "/result.json", "w"))
"""


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> tuple[np.ndarray, list[dict], int]:
    """The shipped policy's first two episodes (seed 0) at 320×240 with the tracking camera, run to their end."""
    _egl_or_skip()
    out = tmp_path_factory.mktemp("rendered")
    result = _in_subprocess(out, RENDERED)
    return np.load(out / "frames.npy"), result["reports"], result["still"]


def test_episode_scenes_cycle_through_the_kinds_deterministically() -> None:
    """Episode i of seed s: the i-th kind of EPISODE_KINDS (obstacle, blocking, none), the same scene every time."""
    from sagrasp_jax.task import sampling
    from sagrasp_jax.task.policy_file import load_policy
    from sagrasp_jax.task.robot import load_robot

    cfg, model = load_policy("pretrained").env_config(), load_robot()
    assert cfg.sampling.obstacle_prob < 0.5 and cfg.sampling.blocking_prob == 0  # left alone, most would be empty
    for seed in (0, 1, 2):
        targets = []
        for i in range(4):
            spec, kind = render.episode_scene(cfg, model, seed, i)
            assert kind == render.EPISODE_KINDS[i % 3]
            blocking = bool(sampling.is_blocking(np, model, cfg.sampling, cfg.task, spec))
            assert int(np.sum(spec.obstacle_active)) > 0 if kind != "no obstacle" else not np.any(spec.obstacle_active)
            assert blocking == (kind == "blocking")
            again, _ = render.episode_scene(cfg, model, seed, i)
            assert all(np.array_equal(a, b) for a, b in zip(spec, again))
            targets.append(tuple(spec.target_pos))
        assert len(set(targets)) == 4  # a new scene each episode


def test_tracking_camera_shows_the_cube_and_obstacles_large(tmp_path) -> None:
    """The first frame of each kind's scene: the cube covers many more pixels than from the overview camera, and
    the obstacles show (amber) where there are some; the overview sees the whole gantry, the tracking camera not."""
    _egl_or_skip()
    code = """
import json, sys
import mujoco
import numpy as np
from sagrasp_jax import render
from sagrasp_jax.reference.grasp_check import GraspScene
from sagrasp_jax.task.policy_file import load_policy
from sagrasp_jax.task.robot import load_robot
cfg, model = load_policy("pretrained").env_config(), load_robot()
frames = []
for i in range(3):
    spec, kind = render.episode_scene(cfg, model, 0, i)
    for camera in ("tracking", "overview"):
        scene = GraspScene(spec, spec.q0)
        frames.append(render.render_episode(mujoco, scene, [scene.data.qpos.copy()], ["start"], camera, 320, 240)[0])
np.save(sys.argv[1] + "/frames.npy", np.stack(frames))
json.dump({}, open(sys.argv[1] + "/result.json", "w"))
"""
    _in_subprocess(tmp_path, code)
    frames = np.load(tmp_path / "frames.npy").reshape(3, 2, 240, 320, 3)
    for i, kind in enumerate(render.EPISODE_KINDS):
        tracking, overview = frames[i]
        assert _cube_pixels(tracking) >= 80, (kind, _cube_pixels(tracking))
        assert _cube_pixels(tracking) >= 3 * _cube_pixels(overview) > 0, (kind, _cube_pixels(tracking), _cube_pixels(overview))
        if kind == "no obstacle":
            assert _obstacle_pixels(tracking) == 0
        else:
            assert _obstacle_pixels(tracking) >= 1000, (kind, _obstacle_pixels(tracking))


def test_rendered_episodes_show_the_task_and_its_outcome(rendered) -> None:
    """The episodes rendered: an obstacle scene and a blocking one; the cube and the obstacles in view all along;
    the banner names the step while the arm moves and the outcome, on its colour, on the last frames."""
    frames, reports, still = rendered
    assert [r["kind"] for r in reports] == ["obstacle", "blocking"]
    assert all(any(r["scene"]["obstacle_active"]) for r in reports)
    hold = render.HOLD_FRAMES
    bh = render.banner_height(240)
    start = 0
    for r in reports:
        expected = ("grasped" if r["held"] else "dropped") if r["outcome"] == "success" else r["outcome"]
        assert r["label"] == expected
        end = start + r["frames"]
        assert r["frames"] >= 2 * hold + r["steps"]
        episode = frames[start:end]
        cube = [_cube_pixels(f) for f in episode]
        assert min(cube) >= 40 and np.median(cube) >= 120, cube
        assert min(_obstacle_pixels(f) for f in episode) >= 300
        chip = np.asarray(render.OUTCOMES[r["label"]], dtype=np.uint8)
        on_chip = [int(np.all(f[:bh] == chip, axis=-1).sum()) for f in episode]
        assert all(n == 0 for n in on_chip[:-hold]) and all(n >= 100 for n in on_chip[-hold:]), on_chip
        steps = episode[hold : hold + r["steps"]]
        assert all(not np.array_equal(a[:bh], b[:bh]) for a, b in zip(steps, steps[1:]))  # the step count moves
        start = end
    assert start == len(frames)
    first_success = next(i for i, r in enumerate(reports) if r["success"])
    assert still == sum(r["frames"] for r in reports[: first_success + 1]) - 1


def test_banner_text_and_outcome_change_only_the_banner() -> None:
    """The outcome word and the step text are drawn in the banner rows; below it the frame is the scene's."""
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    bh = render.banner_height(240)
    plain = render.annotate(frame, "episode 1/3: obstacle", "step 3/200")
    outcomes = {k: render.annotate(frame, "episode 1/3: obstacle", "step 3", k) for k in render.OUTCOMES}
    other_step = render.annotate(frame, "episode 1/3: obstacle", "step 4/200")
    for img in (plain, other_step, *outcomes.values()):
        assert np.array_equal(img[bh:], frame[bh:]) and not np.array_equal(img[:bh], frame[:bh])
    assert not np.array_equal(plain[:bh], other_step[:bh])
    banners = [img[:bh].tobytes() for img in outcomes.values()]
    assert len(set(banners)) == len(banners)  # each outcome looks different
    for word, img in outcomes.items():
        chip = np.all(img[:bh] == np.asarray(render.OUTCOMES[word], np.uint8), axis=-1)
        assert chip.sum() >= render.text_width(word, 1) * 2
        assert not np.all(plain[:bh] == np.asarray(render.OUTCOMES[word], np.uint8), axis=-1).any()


def test_bitmap_font() -> None:
    """Each glyph is 5×7 and distinct; text is drawn at an integer scale, clipped at the edges; unknown as '?'."""
    glyphs = {c: rows for c, rows in render.FONT.items()}
    assert all(len(rows.split("|")) == 7 and all(len(r) == 5 for r in rows.split("|")) for rows in glyphs.values())
    assert len(set(glyphs.values())) == len(glyphs)
    for text in ("GRASPED", "COLLISION", "TIMEOUT", "STEP 12/200", "EPISODE 1/3: BLOCKING OBSTACLE"):
        assert set(text) <= set(glyphs)
    img = np.zeros((20, 40, 3), np.uint8)
    render.draw_text(img, "a", 1, 1, 2, (255, 255, 255))
    ink = np.argwhere(img[..., 0] == 255)
    assert ink.min(axis=0).tolist() == [1, 1] and ink.max(axis=0).tolist() == [14, 10]
    assert np.count_nonzero(img[..., 0]) == 4 * glyphs["A"].count("#")
    unknown, question = np.zeros((9, 7, 3), np.uint8), np.zeros((9, 7, 3), np.uint8)
    render.draw_text(unknown, "\u00e9", 1, 1, 1, (1, 1, 1))
    render.draw_text(question, "?", 1, 1, 1, (1, 1, 1))
    assert np.array_equal(unknown, question) and unknown.any()
    render.draw_text(img, "CLIPPED AT THE EDGE", 30, 15, 2, (9, 9, 9))  # no IndexError
    assert render.text_width("AB", 2) == 22
