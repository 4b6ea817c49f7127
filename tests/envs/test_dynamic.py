"""Dynamic mode (issue 18): the fine-tune path (``train --init-from``), the domain-randomisation knobs
(``env.randomize``: on, the quantity varies; off, nothing is drawn and the run is the plain one), the
lean MJX model and the physics backend choice.  Small on purpose: a handful of short jitted rollouts."""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import toy_config, toy_factory
from sagrasp_jax import train
from sagrasp_jax.task import config
from sagrasp_jax.task import config_parse
from sagrasp_jax.task import observation
from sagrasp_jax.task import robot
from sagrasp_jax.training import run_dir
from sagrasp_jax.training import restore
from sagrasp_jax.envs.grasp_env import GraspEnv

N, T = 8, 4  # envs, steps


def _cfg(mode: str, *sets: str) -> config.Config:
    return config_parse.apply_overrides(config.get_config("paper"), [f"env.control.mode={mode}", "env.task.obs_noise_std=0",
                                                                 "env.sampling.obstacle_prob=0", *sets])


def _rollout(cfg: config.Config, action: float = 0.5):
    """N envs from the same keys, T steps of one constant action; every state kept."""
    env = GraspEnv(cfg.env)

    def run(keys):
        state = jax.vmap(env.reset)(keys)

        def body(st, _):
            st = jax.vmap(env.step)(st, jnp.full((N, 6), action))
            return st, st

        return state, jax.lax.scan(body, state, None, length=T)[1]

    return jax.device_get(jax.jit(run)(jax.random.split(jax.random.PRNGKey(7), N)))


def _q(states, mode):
    return states.pipeline_state.qpos[..., :6] if mode == "dynamic" else states.info["q_target"]


# --------------------------------------------------------------------------------------- off by default

@pytest.mark.parametrize("mode", ["kinematic", "dynamic"])
def test_randomisation_is_off_by_default_and_draws_nothing(mode):
    cfg = config_parse.apply_overrides(config.get_config("paper"), [f"env.control.mode={mode}"])
    assert not config.randomization_enabled(cfg.env)
    env = GraspEnv(cfg.env)
    key = jax.random.PRNGKey(3)
    state = jax.jit(env.reset)(key)
    assert "randomize" not in state.info
    rng, _ = jax.random.split(key)  # the sample draw ...
    rng, _ = jax.random.split(rng)  # ... and the observation noise: nothing else
    np.testing.assert_array_equal(np.asarray(state.info["rng"]), np.asarray(rng))


def test_servo_and_latency_knobs_need_the_dynamic_mode():
    for key in ("env.randomize.servo_gain=0.2", "env.randomize.latency=1", "env.control.impl=warp"):
        with pytest.raises(config.ConfigError, match="needs env.control.mode=dynamic"):
            config_parse.apply_overrides(config.get_config("paper"), [key])
    for key in ("env.randomize.servo_gain=1.5", "env.randomize.target_error=-0.001"):
        with pytest.raises(config.ConfigError, match="env.randomize"):
            config_parse.apply_overrides(config.get_config("paper"), ["env.control.mode=dynamic", key])


# --------------------------------------------------------------------------------------- sensing knobs

def test_joint_offset_and_target_error_on_joint_noise_off():
    cfg = _cfg("kinematic", "env.randomize.joint_offset=0.01", "env.randomize.target_error=0.005")
    start, states = _rollout(cfg)
    r = start.info["randomize"]
    seen_q = states.obs[..., :6] - _q(states, "kinematic")  # (T, N, 6)
    np.testing.assert_allclose(seen_q, np.broadcast_to(r["joint_offset"], seen_q.shape), atol=1e-6)  # constant
    assert np.abs(r["joint_offset"]).max() <= 0.01 and np.std(r["joint_offset"]) > 1e-3  # on: varies
    np.testing.assert_array_equal(r["joint_noise"], 0.0)  # off: no extra noise
    seen_target = states.obs[..., 9:12] - states.info["reset"].target_pos
    np.testing.assert_allclose(seen_target, np.broadcast_to(r["target_error"], seen_target.shape), atol=1e-6)
    assert np.abs(r["target_error"]).max() <= 0.005 and np.std(r["target_error"]) > 5e-4
    # the reward and the success test use the true target
    true_d = np.linalg.norm(states.obs[..., 6:9] - states.info["reset"].target_pos, axis=-1)
    np.testing.assert_allclose(states.metrics["distance"], true_d, atol=1e-6)


def test_joint_noise_on_offset_and_target_error_off():
    cfg = _cfg("kinematic", "env.randomize.joint_noise=0.01")
    start, states = _rollout(cfg)
    r = start.info["randomize"]
    seen_q = states.obs[..., :6] - _q(states, "kinematic")
    assert np.std(seen_q, axis=0).min() > 0  # changes from step to step
    assert 0 < r["joint_noise"].max() <= 0.01
    np.testing.assert_array_equal(r["joint_offset"], 0.0)
    np.testing.assert_allclose(states.obs[..., 9:12], states.info["reset"].target_pos, atol=1e-7)


# --------------------------------------------------------------------------------------- servo knobs

@pytest.fixture(scope="module")
def plain_dynamic():
    return _rollout(_cfg("dynamic"))


def test_servo_gain_and_latency_on(plain_dynamic):
    start, states = _rollout(_cfg("dynamic", "env.randomize.servo_gain=0.2", "env.randomize.latency=1"))
    r = start.info["randomize"]
    for name in ("kp_scale", "kv_scale"):
        assert 0.8 <= r[name].min() and r[name].max() <= 1.2 and np.std(r[name]) > 0.02
    assert 0 <= r["latency"].min() and r["latency"].max() <= 1 and np.std(r["latency"]) > 0.1
    _, plain = plain_dynamic
    assert np.abs(_q(states, "dynamic") - _q(plain, "dynamic")).max() > 1e-3  # the servos track differently


def test_latency_holds_the_previous_target_for_its_share_of_the_substeps():
    """The first command after a reset, with latency 0, 0.4 and 1 step (0, 2 and 5 of the 5 substeps on the
    previous target, the start pose): the later, the less the arm has moved; a whole step late, not at all."""
    env = GraspEnv(_cfg("dynamic", "env.randomize.latency=1").env)
    start = env.reset(jax.random.PRNGKey(0))
    draws = dict(start.info["randomize"], kp_scale=jnp.ones(6), kv_scale=jnp.ones(6))
    step = jax.jit(env.step)
    q0 = env.measured_joints(start)
    moved = []
    for latency in (0.0, 0.4, 1.0):
        state = start.replace(info=dict(start.info, randomize=dict(draws, latency=jnp.float32(latency))))
        moved.append(float(jnp.abs(env.measured_joints(step(state, jnp.ones(6))) - q0).max()))
    plain = GraspEnv(_cfg("dynamic").env)
    plain_start = plain.reset(jax.random.PRNGKey(0))
    q_plain = plain.measured_joints(jax.jit(plain.step)(plain_start, jnp.ones(6)))
    assert moved[0] == pytest.approx(float(jnp.abs(q_plain - plain.measured_joints(plain_start)).max()), abs=1e-6)
    assert moved[0] > moved[1] > 0 and moved[2] < 1e-4  # a whole step late: the arm has not moved yet


def test_servo_knobs_off_track_like_the_plain_env(plain_dynamic):
    """Randomisation on (a joint-reading offset, which the servos never see) with servo gains and
    latency off: the arm moves as without randomisation."""
    start, states = _rollout(_cfg("dynamic", "env.randomize.joint_offset=0.01"))
    np.testing.assert_array_equal(start.info["randomize"]["kp_scale"], 1.0)
    np.testing.assert_array_equal(start.info["randomize"]["latency"], 0.0)
    _, plain = plain_dynamic
    np.testing.assert_allclose(_q(states, "dynamic"), _q(plain, "dynamic"), atol=1e-6)


def test_lean_dynamic_model_is_the_six_joint_arm():
    """Geoms, sites and the cell gone, fingers welded open and fused: every moving kilogram is still there."""
    m = GraspEnv(_cfg("dynamic").env)._mjx_model
    assert (m.nq, m.nv, m.nu, m.ngeom, m.nsite) == (6, 6, 6, 0, 0)
    masses = robot.load_robot().link_masses
    assert float(np.sum(m.body_mass)) == pytest.approx(sum(masses.values()) - masses["base_link"], abs=1e-5)


def test_servo_physics_step_is_mjx_step_bit_for_bit():
    """The dynamic mode's physics step leaves out MJX stages its model has nothing for: from random joint
    states, targets and randomised servo gains, 20 substeps give mjx.step's qpos, qvel, actuator forces and
    time exactly (``qacc``, mjx.step's qacc_smooth, is not computed: nothing reads it)."""
    from mujoco import mjx

    from sagrasp_jax.envs.grasp_env import servo_physics_step

    env = GraspEnv(_cfg("dynamic").env)
    assert env._lean_physics
    k = jax.random.split(jax.random.PRNGKey(3), 4)
    n = 16
    data = jax.vmap(lambda q, v: mjx.make_data(env._mjx_model).replace(qpos=q, qvel=v))(
        jax.random.uniform(k[0], (n, 6), minval=-2.0, maxval=2.0), jax.random.uniform(k[1], (n, 6), minval=-1.0, maxval=1.0))
    ctrl = jax.random.uniform(k[2], (n, 6), minval=-2.5, maxval=2.5)
    kp = env._servo_kp * jax.random.uniform(k[3], (n, 6), minval=0.7, maxval=1.3)

    def run(step):
        def one(d, c, gain):
            m = env._mjx_model
            m = m.replace(actuator_gainprm=m.actuator_gainprm.at[:, 0].set(gain),
                          actuator_biasprm=m.actuator_biasprm.at[:, 1].set(-gain))
            return jax.lax.scan(lambda dd, _: (step(m, dd.replace(ctrl=c)), None), d, None, length=20)[0]
        return jax.device_get(jax.jit(jax.vmap(one))(data, ctrl, kp))

    lean, full = run(servo_physics_step), run(mjx.step)
    for field in ("qpos", "qvel", "qfrc_actuator", "qfrc_bias", "time"):
        np.testing.assert_array_equal(getattr(lean, field), getattr(full, field), err_msg=field)
    assert float(np.max(np.abs(full.qpos - data.qpos))) > 0.05  # the arm moved


def test_compact_servo_state_steps_the_env_as_a_full_mjx_data():
    """The env carries only qpos / qvel between control steps (``ServoState``) and rebuilds MJX's Data for its
    substeps: with latency and servo-gain randomisation on, 6 steps of N envs give the joints, observations and
    rewards of the same env carrying the whole Data through mjx.step to float32 rounding (≤ 1e-6: XLA fuses the
    two programs differently, ulp moves; the reward, which scales a distance change by ``ratio``, ≤ 1e-5), and the
    same done flags."""
    from sagrasp_jax.envs.grasp_env import ServoState

    cfg = _cfg("dynamic", "env.randomize.servo_gain=0.3", "env.randomize.latency=1.5").env
    lean, full = GraspEnv(cfg), GraspEnv(cfg)
    full._lean_physics = False  # the path before the compact state: a whole Data, mjx.step

    def run(env):
        state = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(11), N))
        actions = jax.random.uniform(jax.random.PRNGKey(12), (6, N, 6), minval=-1.0, maxval=1.0)
        return state, jax.lax.scan(lambda st, a: (jax.vmap(env.step)(st, a),) * 2, state, actions)[1]

    (start, states), (_, ref) = jax.device_get(jax.jit(lambda: run(lean))()), jax.device_get(jax.jit(lambda: run(full))())
    assert isinstance(start.pipeline_state, ServoState) and not isinstance(ref.pipeline_state, ServoState)
    for got, want in ((states.pipeline_state.qpos, ref.pipeline_state.qpos), (states.pipeline_state.qvel, ref.pipeline_state.qvel),
                      (states.obs, ref.obs)):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    # the reward pays ratio (10) × the change of a distance, so it carries the distances' rounding ×10 and more
    # (measured on an AVX-512 Xeon: 1.19e-6 on rewards of 0.061, where the AMD EPYC VMs gave ≤ 1e-6)
    np.testing.assert_allclose(states.reward, ref.reward, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(states.done, ref.done)
    assert float(np.max(np.abs(states.pipeline_state.qpos[-1] - start.pipeline_state.qpos))) > 0.01


# --------------------------------------------------------------------------------------- fine-tune path

def test_init_from_continues_policy_and_normaliser_with_a_fresh_optimizer(toy_run, tmp_path):
    cfg = toy_config(cycles=2, extra=[f"train.init_from={toy_run}", "env.control.mode=dynamic"])
    trainer = train.Trainer(cfg, str(tmp_path / "ft"), env_factory=toy_factory(), progress=False)
    _, params, normaliser, _ = restore.load_policy_state(toy_run, trainer.obs_size, trainer.action_size)
    ts = jax.device_get(trainer.train_state)
    for got, want in zip(jax.tree_util.tree_leaves((ts.params, ts.normaliser)),
                         jax.tree_util.tree_leaves((params, normaliser))):
        np.testing.assert_array_equal(got, want)
    adam = ts.opt_state[1].inner_state[0]
    assert int(adam.count) == 0  # fresh optimizer ...
    assert trainer.sa_state.cycle == 0 and trainer.lr == cfg.ppo.learning_rate  # ... and SA schedule
    train.run(cfg, str(tmp_path / "run"), env_factory=toy_factory(), progress=False)
    assert run_dir.load_config(str(tmp_path / "run")).train.init_from == toy_run


def test_init_from_carries_a_privileged_critic(tmp_path):
    """A run with a privileged critic (cpu-quick's) starts another one: the value network, whose first
    layer also reads the privileged inputs, comes across with the policy and the normaliser."""
    sets = ["ppo.privileged_critic=true"]
    source = str(tmp_path / "source")
    train.run(toy_config(cycles=2, extra=sets), source, env_factory=toy_factory(), progress=False)
    cfg = toy_config(cycles=2, extra=[*sets, f"train.init_from={source}", "env.control.mode=dynamic"])
    trainer = train.Trainer(cfg, str(tmp_path / "ft"), env_factory=toy_factory(), progress=False)
    assert trainer.critic_extra == observation.critic_extra_size(cfg) > 0
    _, params, normaliser, _ = restore.load_policy_state(source, trainer.obs_size, trainer.action_size)
    ts = jax.device_get(trainer.train_state)
    widths = {leaf.shape[0] for leaf in jax.tree_util.tree_leaves(ts.params.value) if leaf.ndim == 2}
    assert trainer.obs_size + trainer.critic_extra in widths  # the critic's input layer
    for got, want in zip(jax.tree_util.tree_leaves((ts.params, ts.normaliser)),
                         jax.tree_util.tree_leaves((params, normaliser))):
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("sets, message", [
    ([], "not a run folder"),
    (["--set", "ppo.privileged_critic=false", "--set", "ppo.network.policy_hidden=16"],
     "its policy cannot start this run: networks"),
    (["--set", "ppo.privileged_critic=false", "--set", "env.task.obs_layout=paper"],
     "observation layout 'relative_lag' ("),
    ([], "ppo.privileged_critic=False vs this run's True"),  # cpu-quick has a privileged critic, the toy run none
])
def test_init_from_refuses_an_unusable_run_with_exit_2(toy_run, tmp_path, capsys, sets, message):
    source = str(tmp_path / "missing") if message == "not a run folder" else toy_run
    out = tmp_path / "out"
    assert train.main(["--out", str(out), "--init-from", source, *sets]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_init_from_refuses_other_privileged_inputs(monkeypatch):
    """Same critic width is not enough: the privileged inputs must mean the same (the kinds' one-hot)."""
    def with_kinds(kinds: str) -> config.Config:
        return config_parse.apply_overrides(config.get_config("cpu-quick"), [f"env.sampling.obstacle_kinds={kinds}",
                                                                       "train.init_from=/somewhere"])

    source = with_kinds("sphere,cylinder,box")
    monkeypatch.setattr(run_dir, "load_config", lambda run: source)
    monkeypatch.setattr(run_dir, "load_checkpoint", lambda run, cfg=None: None)
    restore.check_init_from(with_kinds("sphere,cylinder,box"))  # the same: accepted
    with pytest.raises(run_dir.RunDirError, match="privileged critic inputs"):
        restore.check_init_from(with_kinds("sphere,capsule,box"))


# --------------------------------------------------------------------------------------- physics backend

def test_warp_backend_matches_jax_over_a_few_steps():
    mjx_warp = pytest.importorskip("mujoco.mjx.warp")
    if not getattr(mjx_warp, "WARP_INSTALLED", False):
        pytest.skip('the warp extra is not installed (pip install "sagrasp_jax[warp]")')
    try:
        warp_env = GraspEnv(_cfg("dynamic", "env.control.impl=warp").env)
        _, w = _rollout(_cfg("dynamic", "env.control.impl=warp"))
    except Exception as exc:  # noqa: BLE001 - Warp's CPU path depends on the machine's compiler and drivers
        pytest.skip(f"MuJoCo Warp does not run on this machine's CPU: {type(exc).__name__}: {exc}")
    del warp_env
    _, j = _rollout(_cfg("dynamic"))
    np.testing.assert_allclose(_q(w, "dynamic"), _q(j, "dynamic"), atol=1e-5)


# --------------------------------------------------------------------------------------- nearest obstacle

def test_nearest_slot_tie_break_is_the_lower_slot_in_numpy_and_jax():
    from sagrasp_jax.task import collision

    rows = np.array([[0.3, 0.3], [0.2, 0.5], [0.5, 0.2], [np.inf, np.inf], [0.1, np.inf], [-0.01, -0.01]])
    for row in rows:
        got_np = collision.nearest_slot(np, row)
        got_jax = np.asarray(jax.jit(lambda r: collision.nearest_slot(jnp, r))(jnp.asarray(row)))
        np.testing.assert_array_equal(got_np, got_jax)
        np.testing.assert_array_equal(got_np, np.arange(2) == np.argmin(row))  # argmin's first-minimum rule
        assert got_np.sum() == 1


def test_reference_servo_is_the_mjx_servo_on_pybullet_dynamics(x64):
    """servo="mujoco": the same servo law on PyBullet's own mass matrix, bias forces and integrator
    follows MJX to float64 rounding (docs/parity.md, "Dynamic mode")."""
    from sagrasp_jax.reference.pybullet_env import PyBulletGraspEnv

    cfg = _cfg("dynamic")
    env = GraspEnv(cfg.env)
    ref = PyBulletGraspEnv(cfg.env)
    try:
        q0 = np.asarray(config.HOME_Q)
        target = q0 + np.array([0.05, -0.05, 0.05, -0.05, 0.05, -0.05])  # large enough to hit the torque limits
        pipeline = env._initial_pipeline(jnp.asarray(q0))
        ref.reset(seed=0)
        ref._set_joints(q0)
        from brax.envs.base import State

        def step(p, t):  # one control period of the servos towards t, previous command t (no latency)
            state = State(pipeline_state=p, obs=jnp.zeros(1), reward=jnp.zeros(()), done=jnp.zeros(()), metrics={},
                          info={"q_target": t})
            pipeline, q, _ = env._advance(state, t, None, None)
            return pipeline, q

        advance = jax.jit(step)
        for _ in range(3):
            pipeline, q = advance(pipeline, jnp.asarray(target))
            ref._apply(target)
            np.testing.assert_allclose(ref._measure()[0], np.asarray(q), atol=1e-10)
        assert np.abs(np.asarray(q) - q0).max() > 0.02  # it moved
    finally:
        ref.close()


@pytest.mark.parametrize("mode", ["kinematic", "dynamic"])
def test_parity_compares_the_plain_simulators_for_a_randomised_policy(mode):
    """A policy trained with randomisation (its config has the knobs on) is compared with every knob off:
    the reference env does not randomise (and the kinematic mode refuses the servo knobs)."""
    from sagrasp_jax.reference import parity

    trained = _cfg("dynamic", "env.randomize.servo_gain=0.2", "env.randomize.latency=1",
                   "env.randomize.target_error=0.005")
    jax_cfg, ref_cfg = parity.parity_configs(trained, mode)
    assert jax_cfg.control.mode == ref_cfg.control.mode == mode
    assert not config.randomization_enabled(jax_cfg) and not config.randomization_enabled(ref_cfg)
