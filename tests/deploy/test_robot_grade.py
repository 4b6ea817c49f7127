"""Robot-grade policy machinery: the pending-command observation, the lagged servo model and the command
queue against the dynamic env, system identification from logs, and the twin's transfer errors."""

from __future__ import annotations

import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sagrasp_jax.task import collision
from sagrasp_jax.task import config
from sagrasp_jax.task import control
from sagrasp_jax.task import observation
from sagrasp_jax.task import robot
from sagrasp_jax.task import sampling
from sagrasp_jax.deploy import sysid
from sagrasp_jax.task.config import ConfigError, ControlConfig, get_config
from sagrasp_jax.task.config_parse import apply_overrides
from sagrasp_jax.envs.grasp_env import GraspEnv
from paths import REPO  # noqa: E402

sys.path.insert(0, REPO)  # experiments/ is a package of the repository root


KNOBS_OFF = list(config.KNOBS_OFF)


def _env_cfg(*overrides: str) -> config.EnvConfig:
    """cpu-quick's env without noise or transfer errors, then ``overrides``."""
    return apply_overrides(get_config("cpu-quick"), ["env.task.obs_noise_std=0", *KNOBS_OFF, *overrides]).env


# -- observation ----------------------------------------------------------------------------------------


def test_relative_lag_layout_entries_by_hand() -> None:
    cfg = _env_cfg("env.task.obs_layout=relative_lag")
    names = observation.layout_of(cfg)
    assert len(names) == 35 and names[:29] == observation.layout("relative")
    assert names[29:] == tuple(f"pending{j}" for j in range(1, 7))  # one per AUBO joint
    assert observation.hand_scaled_mask(names)[29:].all()  # the normaliser leaves them alone
    model = robot.load_robot()
    u = np.full(sampling.uniforms_needed(cfg.sampling), 0.5)
    spec = sampling.sample_reset(np, model, cfg.sampling, cfg.task, u)
    q = np.asarray(cfg.task.home_q)
    command = q + np.array([0.05, -0.025, 0.0, 0.5, -0.5, 0.0125])  # 1, -0.5, 0, 10 (clipped to 5), -10, 0.25 steps
    seen = observation.observe(np, model, cfg, q, spec, q_command=command)
    np.testing.assert_allclose(seen.obs[29:], [1.0, -0.5, 0.0, 5.0, -5.0, 0.25], atol=1e-12)
    np.testing.assert_allclose(observation.observe(np, model, cfg, q, spec).obs[29:], 0.0)  # nothing pending
    kin = robot.forward_kinematics(np, model, q)
    col = collision.check(np, model, kin, spec, cfg)
    with pytest.raises(ValueError, match="q_command"):
        observation.assemble(np, cfg, q, kin.gripper_centre, spec, col, 0.0)
    relative = _env_cfg("env.task.obs_layout=relative")  # the 29-number layout ignores the command
    np.testing.assert_allclose(observation.observe(np, model, relative, q, spec, q_command=command).obs, seen.obs[:29])


def test_env_pending_command_is_what_the_arm_has_not_done() -> None:
    # kinematic mode: the arm is where it was sent, nothing pending
    env = GraspEnv(_env_cfg("env.task.obs_layout=relative_lag", "env.control.mode=kinematic"))
    state = env.step(env.reset(jax.random.PRNGKey(0)), jnp.full(6, 0.5))
    np.testing.assert_allclose(state.obs[29:], 0.0, atol=1e-6)
    # lagged mode, no latency: the servo model closed lag_gain of the step, the rest is pending
    env = GraspEnv(_env_cfg("env.task.obs_layout=relative_lag", "env.control.mode=lagged"))
    s0 = env.reset(jax.random.PRNGKey(0))
    s1 = env.step(s0, jnp.full(6, 0.5))
    step = np.asarray(s1.info["q_target"] - s0.info["q_target"])
    expected = (1 - np.asarray(ControlConfig().lag_gain)) * step / ControlConfig().q_max
    np.testing.assert_allclose(np.asarray(s1.obs[29:]), expected, atol=1e-5)
    np.testing.assert_allclose(np.asarray(env.measured_joints(s1)), np.asarray(s1.obs[:6]), atol=1e-6)


# -- command latency and the servo model --------------------------------------------------------------


def test_delayed_commands_and_held_weight() -> None:
    queue = np.arange(5.0)[:, None] * np.ones((1, 6))  # newest first: 0, 1, 2, 3, 4 steps old
    for latency, (now, before, fraction) in {0.0: (0, 1, 0.0), 1.0: (1, 2, 0.0), 2.5: (2, 3, 0.5), 3.0: (3, 4, 0.0)}.items():
        c, p, f = control.delayed_commands(np, queue, latency)
        assert (c[0], p[0], f) == (now, before, fraction)
    assert control.latency_queue_size(0.0) == 0 and control.latency_queue_size(1.0) == 3
    assert control.latency_queue_size(2.5) == 4 and control.latency_queue_size(3.0) == 5
    gain = np.array(ControlConfig().lag_gain)
    fractions = np.linspace(0, 1, 11)[:, None]
    w = control.held_command_weight(np, fractions, gain)
    np.testing.assert_allclose(w[0], 0.0, atol=1e-9)
    np.testing.assert_allclose(w[-1], 1.0, atol=1e-6)
    assert (np.diff(w, axis=0) > 0).all() and (w[1:-1] < fractions[1:-1]).all()


def test_latency_is_a_queue_of_commands() -> None:
    """With a latency of exactly 2 steps the lagged arm stays put for two steps and then follows the first command."""
    env = GraspEnv(_env_cfg("env.task.obs_layout=relative_lag", "env.control.mode=lagged", "env.randomize.latency=3"))
    state = env.reset(jax.random.PRNGKey(1))
    state = state.replace(info=dict(state.info, randomize=dict(state.info["randomize"], latency=jnp.asarray(2.0),
                                                                 kp_scale=jnp.ones(6))))
    q0 = np.asarray(env.measured_joints(state))
    assert state.info["commands"].shape == (5, 6)
    targets, measured = [], []
    for _ in range(3):
        state = env.step(state, jnp.full(6, 0.6))
        targets.append(np.asarray(state.info["q_target"]))
        measured.append(np.asarray(env.measured_joints(state)))
    np.testing.assert_allclose(measured[0], q0, atol=1e-7)
    np.testing.assert_allclose(measured[1], q0, atol=1e-7)
    gain = np.asarray(ControlConfig().lag_gain)
    np.testing.assert_allclose(measured[2], q0 + gain * (targets[0] - q0), atol=1e-6)
    with pytest.raises(ConfigError, match="latency"):  # the knob's range: whole steps up to 3
        apply_overrides(get_config("cpu-quick"), ["env.randomize.latency=3.5"])
    with pytest.raises(ConfigError, match="kinematic mode has no servos"):
        apply_overrides(get_config("cpu-quick"), ["env.control.mode=kinematic"])  # the preset randomises latency


def test_lagged_model_tracks_the_dynamic_env() -> None:
    """Open loop, random actions: the lagged mode's gripper stays within a few mm of the MJX servos', with and
    without latency, several times closer than exact tracking (`python -m experiments.robot_grade servo-fit` has the full fit)."""
    from experiments import robot_grade

    gains = {"lag_gain": ControlConfig().lag_gain, "lag_momentum": ControlConfig().lag_momentum}
    gap = robot_grade.drift(episodes=8, steps=16, seed=3, latency=1.0, gains=gains)
    assert gap["lagged_vs_dynamic_mean_m"] < 0.002, gap
    assert gap["lagged_vs_dynamic_mean_m"] < 0.3 * gap["kinematic_vs_dynamic_mean_m"], gap


# -- system identification --------------------------------------------------------------------------------


def _lagged_log(latency: float, offset: np.ndarray, noise: float, steps: int = 600, seed: int = 0) -> sysid.RobotLog:
    """A log of the lagged model itself (its own parameters known exactly), random commands."""
    cfg = ControlConfig()
    rng = np.random.default_rng(seed)
    command = np.cumsum(rng.uniform(-0.04, 0.04, (steps, 6)), axis=0)
    queue = np.zeros((control.latency_queue_size(3.0), 6))
    x = x_prev = np.zeros(6)
    readings = np.empty((steps, 6))
    gain = np.asarray(cfg.lag_gain)
    for t in range(steps):
        readings[t] = x + offset + noise * rng.standard_normal(6)
        queue = np.concatenate([command[t][None], queue[:-1]])
        c, p, f = control.delayed_commands(np, queue, latency)
        w = control.held_command_weight(np, f, gain)
        x, x_prev = control.servo_model_step(np, robot.load_robot(), cfg, x, x_prev, (1 - w) * c + w * p, gain), x
    return sysid.RobotLog(np.arange(steps) * cfg.control_dt, command, readings)


@pytest.mark.parametrize("latency", [0.0, 1.0, 2.0])
def test_sysid_recovers_the_lagged_model(latency: float) -> None:
    offset = np.array([0.004, -0.003, 0.002, -0.001, 0.0, 0.003])
    fit = sysid.identify(_lagged_log(latency, offset, noise=0.0003))
    cfg = ControlConfig()
    assert abs(fit.latency_steps - latency) * cfg.control_dt < 0.005
    np.testing.assert_allclose(fit.joint_offset, offset, atol=0.001)
    np.testing.assert_allclose(fit.lag_gain, cfg.lag_gain, rtol=0.10)
    items = sysid.overrides(fit)
    trained = apply_overrides(get_config("cpu-quick"), items)  # training accepts what sysid writes
    assert trained.env.randomize.latency >= max(1.0, latency)


def test_sysid_on_a_dynamic_env_log() -> None:
    """A log synthesised by the dynamic (MJX) env with known whole-step latency and offsets (`python -m experiments.robot_grade sysid-check`)."""
    from experiments import robot_grade

    offset = [0.004, -0.003, 0.002, -0.005, 0.001, 0.003]
    log = robot_grade.synthesize([1.0] * 6, 1.0, offset, episodes=1, steps=300)
    fit = sysid.identify(log)
    assert abs(fit.latency_steps - 1.0) * 0.05 < 0.005
    np.testing.assert_allclose(fit.joint_offset, offset, atol=0.001)
    np.testing.assert_allclose(fit.lag_gain, ControlConfig().lag_gain, rtol=0.10)


def _write(path: str, header: str, rows: list[list[float]]) -> str:
    with open(path, "w", encoding="utf-8") as f:
        f.write(header + "\n")
        f.writelines(",".join(repr(float(v)) for v in row) + "\n" for row in rows)
    return path


def test_sysid_cli_and_bad_logs(tmp_path, capsys) -> None:
    log = _lagged_log(1.0, np.zeros(6), 0.0002, steps=200)
    rows = [[t, *c, *y] for t, c, y in zip(log.time, log.command, log.measured)]
    header = ",".join(sysid.COLUMNS)
    good = _write(str(tmp_path / "good.csv"), header, rows)
    out = str(tmp_path / "sysid.json")
    assert sysid.main(["--log", good, "--out", out]) == 0 and os.path.exists(out)
    bad = {
        "nan": (header, [r if i != 50 else [r[0], float("nan"), *r[2:]] for i, r in enumerate(rows)], "NaN"),
        "time": (header, [r if i != 60 else [rows[58][0], *r[1:]] for i, r in enumerate(rows)], "not strictly increasing"),
        "columns": (header.replace("cmd_q3", "cmd_q9"), rows, "columns must be"),
        "short": (header, rows[:40], "at least"),
        "period": (header, [[r[0] * 10, *r[1:]] for r in rows], "sample period"),
    }
    for name, (head, body, message) in bad.items():
        target = str(tmp_path / f"{name}.json")
        assert sysid.main(["--log", _write(str(tmp_path / f"{name}.csv"), head, body), "--out", target]) == 2, name
        assert message in capsys.readouterr().err, name
        assert not os.path.exists(target), name  # nothing half-written


# -- the twin's transfer errors ---------------------------------------------------------------------------


def test_twin_latency_and_servo_lag() -> None:
    pytest.importorskip("pybullet")
    from sagrasp_jax.deploy.loop import scene_spec
    from sagrasp_jax.deploy.transfer import TransferErrors
    from sagrasp_jax.deploy.twin import PyBulletTwin

    env_cfg = _env_cfg()
    q0 = np.asarray(env_cfg.task.home_q)
    spec = scene_spec(q0, np.array([0.1, -0.45, 0.025]), 0.0, [], env_cfg)
    step = np.full(6, 0.02)
    with PyBulletTwin(spec, env_cfg, q0=q0, errors=TransferErrors(latency=1.0)) as twin:
        twin.command_joint_targets(q0 + step)
        np.testing.assert_allclose(twin.read_joints(), q0, atol=1e-9)  # one step late
        twin.command_joint_targets(q0 + 2 * step)
        np.testing.assert_allclose(twin.read_joints(), q0 + step, atol=1e-9)
    with PyBulletTwin(spec, env_cfg, q0=q0, errors=TransferErrors(servo_lag=True)) as twin:
        twin.command_joint_targets(q0 + step)
        np.testing.assert_allclose(twin.read_joints(), q0 + np.asarray(env_cfg.control.lag_gain) * step, atol=1e-9)
    with pytest.raises(ValueError, match="latency"):
        TransferErrors(latency=-1.0)


def test_a_29_number_policy_still_loads_evaluates_and_deploys(tmp_path) -> None:
    """Policies of the second landing (layout ``relative``, kinematic training, no pending command) keep
    working next to the robot-grade ones: the runtime reads their layout from the file, and the deploy
    loop builds their 29 numbers (the command is only passed on, never appended)."""
    pytest.importorskip("pybullet")
    from sagrasp_jax.task import policy_file as runtime
    from sagrasp_jax.deploy import run_episode, scene_spec
    from sagrasp_jax.deploy.twin import PyBulletTwin

    cfg = apply_overrides(get_config("cpu-quick"), [*KNOBS_OFF, "env.control.mode=kinematic", "env.task.obs_layout=relative"])
    names = observation.layout_of(cfg.env)
    rng = np.random.default_rng(0)
    sizes = [len(names), 32, 32, 12]  # the last layer: loc and scale of the 6 actions
    weights = [(0.1 * rng.standard_normal((a, b)), np.zeros(b)) for a, b in zip(sizes[:-1], sizes[1:])]
    path = runtime.save_policy_npz(str(tmp_path / "policy.npz"), weights=weights, activation="tanh",
                                   obs_mean=np.zeros(len(names)), obs_std=np.ones(len(names)),
                                   config=config.config_to_dict(cfg), obs_layout=names)
    policy = runtime.load_policy(path)
    assert policy.obs_layout == names and len(names) == 29
    seen = []
    original = policy.__call__

    class Recording:
        def __getattr__(self, name):  # the loop reads the policy's config and path
            return getattr(policy, name)

        def __call__(self, obs):
            seen.append(np.asarray(obs).shape)
            return original(obs)

    env_cfg = policy.env_config()
    target = np.array([0.10, -0.45, 0.025])
    q0 = np.asarray(config.HOME_Q)
    with PyBulletTwin(scene_spec(q0, target, 0.0, [], env_cfg), env_cfg, q0=q0) as twin:
        report = run_episode(twin, Recording(), target, 0.0, max_steps=5, grasp=False)
    assert seen and all(shape == (29,) for shape in seen), seen
    assert report.outcome in ("timeout", "collision", "refused"), report
