"""Trainer loop on the toy env: exact resume, SA rollback, non-finite rollback, CLI refusals."""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import json
import math
import os

import jax
import numpy as np
import pytest

from conftest import toy_config, toy_factory

from sagrasp_jax import train
from sagrasp_jax.training.agents.ppo import actor_critic
from sagrasp_jax.training import lr_schedule
from sagrasp_jax.training import fixed_seed_eval as policy_eval
from sagrasp_jax.training import run_dir
from sagrasp_jax.task import policy_file as runtime
from sagrasp_jax.training.checkpoint import CheckpointError


def _leaves_equal(a, b) -> bool:
    return all(np.array_equal(np.asarray(x), np.asarray(y))
               for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))


def _rows(run):
    return [{k: v for k, v in r.items() if k not in train.TIME_FIELDS}
            for r in run_dir.read_metrics(run_dir.path(run, run_dir.METRICS_FILE))]


def test_run_folder_contents(toy_run):
    files = set(os.listdir(toy_run))
    assert {"config.json", "metrics.jsonl", "checkpoint.ckpt", "policy.npz", "tb"} <= files
    rows = run_dir.read_metrics(os.path.join(toy_run, run_dir.METRICS_FILE))
    sched = train.make_schedule(toy_config())
    assert [r["iteration"] for r in rows] == list(range(sched.num_iterations))
    for key in ("env_steps", "steps_per_s", "compile_s", "return", "r_distance", "r_success", "r_obstacle",
                "success", "collision", "timeout", "steps_to_success", "lr", "entropy", "loss", "policy_loss",
                "value_loss"):
        assert key in rows[-1], key
    cycle_rows = [r for r in rows if "sa_decision" in r]
    assert len(cycle_rows) == 6 and all("eval_return" in r and "temperature" in r for r in cycle_rows)
    assert os.listdir(os.path.join(toy_run, "tb"))
    policy = runtime.load_policy(os.path.join(toy_run, "policy.npz"))
    assert policy.obs_size == 7 and policy.action_size == 2


def test_tensorboard_holds_every_rows_scalars_at_its_env_step(toy_run):
    """Each metrics row is one TensorBoard event: every numeric field as ``train/<key>`` at the row's env
    step, equal to the JSONL value in float32 (what TensorBoard stores)."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    folder = os.path.join(toy_run, run_dir.TB_DIR)
    logged: dict[int, dict[str, float]] = {}
    for name in sorted(os.listdir(folder)):
        for event in EventFileLoader(os.path.join(folder, name)).Load():
            for value in event.summary.value:
                stored = value.simple_value if value.HasField("simple_value") else float(value.tensor.float_val[0])
                logged.setdefault(event.step, {})[value.tag] = stored
    rows = run_dir.read_metrics(os.path.join(toy_run, run_dir.METRICS_FILE))
    assert sorted(logged) == [r["env_steps"] for r in rows]
    for row in rows:
        numeric = {f"train/{k}": v for k, v in row.items() if isinstance(v, (int, float)) and not isinstance(v, bool)
                   and k not in ("iteration", "env_steps")}
        assert set(logged[row["env_steps"]]) == set(numeric)
        for tag, value in numeric.items():
            assert logged[row["env_steps"]][tag] == pytest.approx(np.float32(value), rel=1e-6, nan_ok=True), tag


def test_kill_and_resume_matches_an_uninterrupted_run(tmp_path):
    cfg = toy_config(cycles=6, extra=["sa.tol=0.0", "sa.t0=0.5"])
    full = train.run(cfg, str(tmp_path / "full"), env_factory=toy_factory(), progress=False)
    half_dir = str(tmp_path / "half")
    half = train.run(cfg, half_dir, env_factory=toy_factory(), progress=False, stop_after_cycles=3)
    assert half.sa_state.cycle == 3 and half.host.iteration < full.host.iteration
    assert not os.path.exists(os.path.join(half_dir, run_dir.POLICY_FILE))
    # A crash after the checkpoint leaves extra rows behind; the resume must drop them.
    with open(os.path.join(half_dir, run_dir.METRICS_FILE), "a") as f:
        f.write(json.dumps({"iteration": 10**6, "env_steps": 0}) + "\n" + '{"iteration": 10')
    resumed = train.run(cfg, half_dir, env_factory=toy_factory(), progress=False, resume=True)
    assert _rows(half_dir) == _rows(str(tmp_path / "full"))
    assert _leaves_equal(resumed.train_state, full.train_state)
    assert _leaves_equal(resumed.env_state, full.env_state)
    assert resumed.sa_state == full.sa_state
    decisions = [r["sa_decision"] for r in _rows(half_dir) if "sa_decision" in r]
    assert len(decisions) == 6


def test_the_trainer_traces_the_training_envs_reset_once(tmp_path):
    """Every trace of the training env's reset costs start-up time on every start, compile cache or not (≈ 1.2 s
    for the grasp env on 2 cores): the trainer traces it once, in its jitted batched reset, and reads the metrics
    window's keys off the state that reset made."""
    traces = []

    def counting(cfg):
        train_env, eval_env = toy_factory()(cfg)
        reset = train_env.reset
        train_env.reset = lambda rng: (traces.append(rng), reset(rng))[1]
        return train_env, eval_env

    tr = train.Trainer(toy_config(), str(tmp_path), env_factory=counting, progress=False)
    assert len(traces) == 1
    assert tr.window_keys == tuple(tr.env_state.info["episode"]) and "success" in tr.window_keys
    assert tuple(tr.runner.window["values"]) == tr.window_keys


def test_the_emitter_choice_reaches_every_program_the_trainer_compiles(tmp_path):
    """train.cpu_fusion_emitters=new compiles the training call, the SA evaluation, the first reset and the
    initial state with XLA's new fusion emitters (other executables than legacy's); legacy adds no option."""
    texts = {}
    for choice in ("legacy", "new"):
        cfg = toy_config(extra=[f"train.cpu_fusion_emitters={choice}"])
        tr = train.Trainer(cfg, str(tmp_path / choice), env_factory=toy_factory(), progress=False)
        assert tr.compiler_options == ({} if choice == "legacy" else {"xla_cpu_use_fusion_emitters": True})
        tr.compile()
        keys = jax.random.split(jax.random.PRNGKey(0), cfg.ppo.num_envs)
        texts[choice] = (tr._compiled_cycle.as_text(), tr._compiled_eval.as_text(),
                         tr._reset.lower(keys).compile().as_text(),
                         tr._init_state.lower(jax.random.PRNGKey(0)).compile().as_text())
    for program, legacy, new in zip(("training call", "evaluation", "reset", "initial state"), *texts.values()):
        assert legacy != new, program


def test_sa_reject_restores_the_snapshot_bit_for_bit(tmp_path):
    cfg = toy_config(extra=["sa.max_rollbacks=3", "sa.patience=5"])
    tr = train.Trainer(cfg, str(tmp_path), env_factory=toy_factory(), progress=False)
    tr.run_iteration()
    first = tr.anneal(metric=1.0, entropy=0.5)
    assert first.kind == "accept"
    accepted = tr.train_state
    assert tr.snapshot is accepted
    env_before = tr.env_state
    for _ in range(2):
        tr.run_iteration()
    assert not _leaves_equal(tr.train_state.params, accepted.params)
    decision = tr.anneal(metric=-1e9, entropy=0.5)
    assert decision.kind == "reject" and not decision.decayed
    assert _leaves_equal(tr.train_state.params, accepted.params)
    assert _leaves_equal(tr.train_state.opt_state, accepted.opt_state)
    assert _leaves_equal(tr.train_state.normaliser, accepted.normaliser)
    assert not _leaves_equal(tr.env_state.obs, env_before.obs)  # envs keep running
    # Three rejections in a row decay the lr: the host's, which the next call is given (no device copy to set).
    tr.anneal(metric=-1e9, entropy=0.5)
    third = tr.anneal(metric=-1e9, entropy=0.5)
    assert third.decayed and tr.lr == pytest.approx(cfg.ppo.learning_rate * cfg.sa.decay)
    assert np.asarray(tr._cycle_args([1])[-1]).tolist() == [np.float32(tr.lr)] * tr.schedule.iterations_per_cycle
    assert _leaves_equal(tr.train_state.params, accepted.params)


def test_nonfinite_iterations_are_rolled_back_and_training_continues(tmp_path):
    cfg = toy_config(cycles=4)
    out = str(tmp_path / "nan")
    tr = train.run(cfg, out, env_factory=toy_factory(nan_progress=(0.5, 0.6)), progress=False)
    rows = run_dir.read_metrics(os.path.join(out, run_dir.METRICS_FILE))
    events = [r for r in rows if r.get("event") == "nonfinite"]
    assert events and all(r["sa_decision"] == "reject" and r["sa_decayed"] for r in events)
    assert events[0]["loss"] is None  # NaN is logged as null, the JSON stays valid
    assert rows[-1]["iteration"] == train.make_schedule(cfg).num_iterations - 1
    assert rows[-1]["lr"] == pytest.approx(cfg.ppo.learning_rate * cfg.sa.decay ** tr.sa_state.decays)
    assert tr.host.nonfinite == len(events)
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree_util.tree_leaves(tr.train_state.params))


def test_ppo_baseline_keeps_a_constant_learning_rate(tmp_path):
    cfg = toy_config(cycles=3, algo="ppo", extra=["ppo.learning_rate=2e-4"])
    assert cfg.lr.schedule == "constant"
    out = str(tmp_path / "ppo")
    train.run(cfg, out, env_factory=toy_factory(), progress=False)
    rows = run_dir.read_metrics(os.path.join(out, run_dir.METRICS_FILE))
    assert {r["lr"] for r in rows} == {2e-4}
    assert {r["sa_decision"] for r in rows if "sa_decision" in r} == {"accept"}


@pytest.mark.parametrize("argv,message", [
    (["--preset", "nope"], "valid presets: paper, cpu-quick, gpu, cpu-physics, gpu-physics"),
    (["--algo", "a2c"], "valid algos: sa-ppo, ppo"),
    (["--set", "ppo.nonsense=3"], "--list-keys lists every key"),
    (["--set", "ppo.num_envs=many"], "bad value 'many' for ppo.num_envs"),
    (["--set", "sa.metric=reward"], "sa.metric='reward' is not one of return, success"),
    (["--set", "ppo.num_envs"], "not of the form key=value"),
])
def test_bad_options_fail_clearly_and_write_nothing(tmp_path, capsys, argv, message):
    out = tmp_path / "run"
    assert train.main(["--out", str(out), *argv]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_existing_output_and_resume_without_checkpoint_are_refused(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    assert train.main(["--out", str(out)]) == 2
    assert "not empty" in capsys.readouterr().err
    assert train.main(["--out", str(out), "--resume"]) == 2
    assert "cannot resume" in capsys.readouterr().err
    assert os.listdir(out) == ["notes.txt"]


@pytest.mark.parametrize("signal_name, raised", [("SIGTERM", train.Terminated), ("SIGINT", KeyboardInterrupt)])
def test_a_stop_that_lands_in_a_gc_callback_still_stops_the_run(signal_name, raised):
    """SIGTERM's ``Terminated`` or Ctrl-C's ``KeyboardInterrupt`` raised inside a gc callback (where jax's
    ``_xla_gc_callback`` runs) is dropped by Python, and the run went on to its end (the check's stop then waited for
    its kill); the block raises the same signal again in ordinary code (SIGINT a plain ``KeyboardInterrupt``, exit
    130, not ``Terminated``'s 143), and restores the hook it replaced."""
    import gc
    import signal
    import sys
    import time

    signum = getattr(signal, signal_name)
    sent = []

    def callback(phase, info):
        if not sent:
            sent.append(phase)
            signal.raise_signal(signum)  # the handler runs here, inside the gc

    hook = sys.unraisablehook
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # a test worker may ignore SIGINT
    gc.callbacks.append(callback)
    try:
        with pytest.raises(KeyboardInterrupt) as caught:
            with train._sigterm_as_interrupt():
                gc.collect()
                end = time.monotonic() + 5.0
                while time.monotonic() < end:  # ordinary code, where the signal raised again lands
                    pass
    finally:
        gc.callbacks.remove(callback)
        signal.signal(signal.SIGINT, previous)
    assert sent and type(caught.value) is raised and sys.unraisablehook is hook


def test_resume_refuses_a_corrupt_checkpoint_and_changes_nothing(toy_run, tmp_path):
    import shutil

    run = str(tmp_path / "copy")
    shutil.copytree(toy_run, run)
    ckpt = os.path.join(run, run_dir.CHECKPOINT_FILE)
    with open(ckpt, "r+b") as f:
        f.seek(-100, os.SEEK_END)
        f.write(b"\0" * 10)
    before = {name: os.path.getmtime(os.path.join(run, name)) for name in os.listdir(run)}
    with pytest.raises(CheckpointError, match="checksum"):
        train.run(toy_config(), run, env_factory=toy_factory(), progress=False, resume=True)
    assert {name: os.path.getmtime(os.path.join(run, name)) for name in os.listdir(run)} == before
    with pytest.raises(CheckpointError, match="config differs"):
        shutil.copy(os.path.join(toy_run, run_dir.CHECKPOINT_FILE), ckpt)
        train.run(toy_config(extra=["ppo.entropy_coef=0.01"]), run, env_factory=toy_factory(), progress=False,
                  resume=True)


@pytest.mark.parametrize("preset", ["cpu-quick", "gpu", "paper"])
def test_every_preset_anneals_over_exactly_num_cycles_cycles(preset):
    """Cycle k ends after round((k + 1)·N / num_cycles) of the N iterations: exactly 200 cycles
    (or eval.num_cycles) whatever the batch shape, lengths differing by at most one iteration."""
    for cycles, sets in ((200, []), (37, ["eval.num_cycles=37"])):
        sched = train.make_schedule(train.build_config(preset, overrides=sets))
        n = sched.num_iterations
        assert sched.num_cycles == cycles and sched.cycle_ends[-1] == n
        assert list(sched.cycle_ends) == [math.floor((k + 1) * n / cycles + 0.5) for k in range(cycles)]
        lengths = np.diff((0,) + sched.cycle_ends)
        assert lengths.min() >= 1 and lengths.max() - lengths.min() <= 1
        assert sched.iterations_per_cycle == lengths.max()
        assert [sched.cycle_end(i) for i in range(n)] == list(np.repeat(sched.cycle_ends, lengths))
    explicit = train.make_schedule(train.build_config("cpu-quick", overrides=["eval.cycle_steps=20000"]))
    assert explicit.iterations_per_cycle == 5 and set(np.diff((0,) + explicit.cycle_ends)[:-1]) == {5}


def test_uneven_cycles_run_one_call_each_and_log_every_iteration(tmp_path):
    """12 iterations in 5 cycles (2, 3, 2, 3, 2 iterations): five SA decisions, one row per
    iteration, the cycle rows at the fixed ends."""
    cfg = toy_config(cycles=6, extra=["eval.num_cycles=5"])
    sched = train.make_schedule(cfg)
    assert sched.cycle_ends == (2, 5, 7, 10, 12) and sched.iterations_per_cycle == 3
    tr = train.run(cfg, str(tmp_path / "run"), env_factory=toy_factory(), progress=False)
    rows = run_dir.read_metrics(os.path.join(str(tmp_path / "run"), run_dir.METRICS_FILE))
    assert [r["iteration"] for r in rows] == list(range(12))
    assert [r["iteration"] + 1 for r in rows if "sa_decision" in r] == list(sched.cycle_ends)
    assert tr.sa_state.cycle == 5
    assert all(r["reset_replays"] == 0.0 for r in rows)


@pytest.mark.slow
def test_short_cpu_quick_run_learns_to_grasp(trained_run):
    """The CLI run of the real env beats the untrained policy clearly on held-out episodes."""
    from sagrasp_jax import evaluate
    from sagrasp_jax.envs.grasp_env import GraspEnv

    assert train.main(["--out", trained_run]) == 2  # a finished run is not overwritten
    assert evaluate.main(["--run", trained_run, "--episodes", "256"]) == 0
    cfg = train.build_config("cpu-quick")
    with open(os.path.join(trained_run, run_dir.evaluation_file(256, cfg.eval.seed + 1))) as f:
        trained = json.load(f)["overall"]
    env = GraspEnv(cfg.env)
    nets = actor_critic.make_networks(cfg.ppo.network, env.observation_size, env.action_size, cfg.ppo.obs_clip)
    ts = actor_critic.init_training_state(jax.random.PRNGKey(0), nets, actor_critic.make_optimizer(cfg.ppo),
                                 env.observation_size)
    untrained = policy_eval.make_evaluator(nets, env, cfg.env.task.max_steps)(ts.params, ts.normaliser,
                                                                       policy_eval.eval_keys(cfg.eval.seed + 1, 256))
    rows = run_dir.read_metrics(os.path.join(trained_run, run_dir.METRICS_FILE))
    print(f"untrained success {float(untrained.success_rate):.3f}, trained {trained['success_rate']:.3f} "
          f"(CI {trained['success_ci95']}), steps/success {trained['mean_steps_per_success']}, "
          f"median train steps/s {np.median([r['steps_per_s'] for r in rows]):.0f}, compile {rows[-1]['compile_s']:.1f} s")
    assert trained["success_rate"] >= float(untrained.success_rate) + 0.3
    assert trained["success_ci95"][0] > float(untrained.success_rate)


# ---------------------------------------------------------------------- learning-rate schedules

@pytest.mark.parametrize("schedule,extra", [
    ("constant", []),
    ("kl-adaptive", []),
    ("cosine", []),
    ("linear", ["lr.final=1e-5"]),
    ("sa", ["sa.tol=0.0", "sa.t0=0.5", "sa.rollback=false", "sa.metropolis=false"]),
])
def test_every_schedule_resumes_exactly(tmp_path, schedule, extra):
    cfg = toy_config(cycles=6, extra=[f"lr.schedule={schedule}", *extra])
    full = train.run(cfg, str(tmp_path / "full"), env_factory=toy_factory(), progress=False)
    half_dir = str(tmp_path / "half")
    half = train.run(cfg, half_dir, env_factory=toy_factory(), progress=False, stop_after_cycles=3)
    assert half.lr_state.cycle == 3 and half.host.iteration < full.host.iteration
    resumed = train.run(cfg, half_dir, env_factory=toy_factory(), progress=False, resume=True)
    assert _rows(half_dir) == _rows(str(tmp_path / "full"))
    assert _leaves_equal(resumed.train_state, full.train_state)
    assert _leaves_equal(resumed.snapshot, full.snapshot)
    assert resumed.lr_state == full.lr_state and resumed.lr_state.cycle == 6
    assert (resumed.sa_state is None) == (schedule != "sa")
    rows = _rows(half_dir)
    lrs = [r["lr"] for r in rows]
    if schedule == "constant":
        assert set(lrs) == {cfg.ppo.learning_rate}
    elif schedule == "kl-adaptive":
        bounds = np.float32(cfg.lr.kl_lr_min), np.float32(cfg.lr.kl_lr_max)  # the call adapts it in float32
        assert len(set(lrs)) > 1 and all(bounds[0] <= np.float32(v) <= bounds[1] for v in lrs)
        assert lrs[-1] == full.lr_state.lr  # the host keeps the lr the last call ended at
    elif schedule in ("cosine", "linear"):
        assert all(a > b for a, b in zip(lrs, lrs[1:]))  # strictly falling, iteration by iteration
        assert lrs[-1] == pytest.approx(cfg.lr.final, rel=1e-4)  # progress 1 after the last iteration
        n = len(rows)
        rule = full.rule
        assert lrs[n // 2 - 1] == pytest.approx(float(lr_schedule.progress_lr(np, rule, (n // 2) / n)), rel=1e-5)
    else:
        assert {r["sa_decision"] for r in rows if "sa_decision" in r} <= {"accept", "reject"}


def test_kl_adaptive_adapts_after_every_minibatch(tmp_path):
    """KL far below the band: × 1.5 per minibatch; far above: ÷ 1.5; here 2 epochs × 4 minibatches,
    the first of which (KL 0 by definition) leaves the lr alone."""
    steps = 2 * 4 - 1
    for desired, expected in ((50.0, min(3e-4 * 1.5**steps, 1e-2)), (1e-9, max(3e-4 / 1.5**steps, 1e-5))):
        cfg = toy_config(extra=["lr.schedule=kl-adaptive", f"lr.desired_kl={desired}"])
        tr = train.Trainer(cfg, str(tmp_path / str(desired)), env_factory=toy_factory(), progress=False)
        row = tr.run_iteration()
        assert row["step_kl"] > 0.0 and row["approx_kl"] > row["step_kl"]  # approx_kl also sees the normaliser move
        assert tr.lr == pytest.approx(expected, rel=1e-5) and row["lr"] == tr.lr  # the lr the call returned, kept


def test_sa_without_rollback_keeps_the_rejected_parameters(tmp_path):
    cfg = toy_config(extra=["sa.rollback=false"])
    tr = train.Trainer(cfg, str(tmp_path), env_factory=toy_factory(), progress=False)
    tr.run_iteration()
    assert tr.anneal(metric=1.0, entropy=0.5).kind == "accept"
    accepted = tr.snapshot
    tr.run_iteration()
    current = tr.train_state
    decision = tr.anneal(metric=-1e9, entropy=0.5)
    assert decision.kind == "reject" and not decision.restore
    assert _leaves_equal(tr.train_state.params, current.params)  # kept, not restored
    assert tr.snapshot is accepted  # the snapshot stays the last accepted one
    assert tr.lr_state.rollbacks == 0 and tr.sa_state.n_reject == 1


def test_resume_reads_a_checkpoint_from_before_lr_schedules(tmp_path):
    """A checkpoint whose host state holds ``sa_state`` (no ``lr_state``) resumes as if uninterrupted."""
    from sagrasp_jax.training import checkpoint

    cfg = toy_config(cycles=4)
    full = train.run(cfg, str(tmp_path / "full"), env_factory=toy_factory(), progress=False)
    half_dir = str(tmp_path / "half")
    train.run(cfg, half_dir, env_factory=toy_factory(), progress=False, stop_after_cycles=2)
    path = os.path.join(half_dir, run_dir.CHECKPOINT_FILE)
    with open(path, "rb") as f:
        blob = f.read()
    start = len(checkpoint.MAGIC) + checkpoint._LEN.size
    (n,) = checkpoint._LEN.unpack(blob[len(checkpoint.MAGIC):start])
    header = json.loads(blob[start:start + n])
    header["host"]["sa_state"] = header["host"].pop("lr_state")["sa"]
    head = json.dumps(header, sort_keys=True).encode()
    with open(path, "wb") as f:
        f.write(checkpoint.MAGIC + checkpoint._LEN.pack(len(head)) + head + blob[start + n:])
    resumed = train.run(cfg, half_dir, env_factory=toy_factory(), progress=False, resume=True)
    assert _rows(half_dir) == _rows(str(tmp_path / "full"))
    assert resumed.lr_state == full.lr_state


def test_algo_and_lr_schedule_options(tmp_path, capsys):
    assert train.build_config("paper", "ppo").lr.schedule == "constant"
    assert train.build_config("paper", "sa-ppo").lr.schedule == "sa"
    assert train.build_config("paper").lr.schedule == "sa"
    assert train.build_config("paper", lr_schedule="cosine").lr.schedule == "cosine"
    assert train.build_config("paper", "ppo", lr_schedule="constant").lr.schedule == "constant"
    assert train.build_config("paper", "ppo", overrides=["lr.schedule=linear"]).lr.schedule == "linear"
    for argv, message in ((["--algo", "ppo", "--lr-schedule", "cosine"], "--algo ppo means --lr-schedule constant"),
                          (["--lr-schedule", "step"], "valid lr schedules: constant, sa, kl-adaptive, cosine, linear"),
                          (["--set", "sa.lr0=1e-4"], "replaced by ppo.learning_rate")):
        out = tmp_path / "run"
        assert train.main(["--out", str(out), *argv]) == 2
        assert message in capsys.readouterr().err
        assert not out.exists()


def test_stopping_rule_ends_the_run_as_the_full_runs_first_part(tmp_path, capsys):
    """``train.stop_success`` over ``train.stop_cycles``: the run stops at the first cycle whose policy SA kept
    with the window's pooled evaluation success at the level, its rows are the full budget's rows up to there,
    it records why (rows, checkpoint, summary), writes its policy, and a resume trains nothing more."""
    full_dir, stop_dir = str(tmp_path / "full"), str(tmp_path / "stop")
    base = ["sa.tol=0.0", "sa.t0=0.5"]
    train.run(toy_config(cycles=8, extra=base), full_dir, env_factory=toy_factory(), progress=False)
    cycles = [r for r in _rows(full_dir) if "sa_decision" in r]
    success = [r["eval_success"] for r in cycles]
    pooled = [float(np.mean(success[k - 2:k])) for k in range(2, 7)]
    level = max(pooled)
    assert 0 < level <= 1, success  # the toy learns something to stop on
    kept = [r["sa_decision"] != "reject" for r in cycles]
    expect = next(k for k in range(2, 9) if kept[k - 1] and np.mean(success[k - 2:k]) >= level)  # cycles run
    assert expect < 8

    stopped = train.run(toy_config(cycles=8, extra=base + [f"train.stop_success={level!r}", "train.stop_cycles=2"]),
                        stop_dir, env_factory=toy_factory(), progress=False)
    rows = _rows(stop_dir)
    last = [r for r in rows if "sa_decision" in r][-1]
    assert len([r for r in rows if "sa_decision" in r]) == expect and last["stopped_by_rule"]
    assert last["stop_window_cycles"] == 2 and last["stop_window_success"] >= level
    stop_keys = ("stop_window_success", "stop_window_cycles", "stopped_by_rule")
    assert [{k: v for k, v in r.items() if k not in stop_keys} for r in rows] == _rows(full_dir)[:len(rows)]
    assert stopped.host.stopped_at == rows[-1]["env_steps"] < train.make_schedule(toy_config(cycles=8)).num_iterations * 512
    assert "stopped by the stopping rule at" in capsys.readouterr().err
    assert os.path.exists(os.path.join(stop_dir, run_dir.POLICY_FILE))
    from sagrasp_jax.training.checkpoint import load as load_checkpoint
    assert load_checkpoint(os.path.join(stop_dir, run_dir.CHECKPOINT_FILE)).host["counters"]["stopped_at"] == stopped.host.stopped_at
    resumed = train.run(toy_config(cycles=8, extra=base + [f"train.stop_success={level!r}", "train.stop_cycles=2"]),
                        stop_dir, env_factory=toy_factory(), progress=False, resume=True)
    assert resumed.host.iteration == stopped.host.iteration and len(_rows(stop_dir)) == len(rows)
