"""Seed groups (``--seeds``): several seeds in one compiled program, each into a run folder of its own.

One toy config and one group shape throughout, so the group program compiles once per session
(and comes from jax's persistent cache after that).
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import toy_config, toy_factory

from sagrasp_jax import train
from sagrasp_jax.training import evaluation
from sagrasp_jax.training.agents.ppo import actor_critic
from sagrasp_jax.training import lr_schedule
from sagrasp_jax.training import run_dir
from sagrasp_jax.task import policy_file as runtime

GROUP = [0, 2]
ALONE = 2  # the group's second seed, also trained alone
# A group's seed and the same seed alone run the same maths, but vmapped reductions round
# differently (float32): after one iteration the parameters agree to this absolute tolerance, but for
# the first-layer weights of an input whose std sits at the floor (the toy's constant feature): its
# normalised value is the mean's rounding error / the floor, noise that Adam turns into full steps.
FIRST_ITERATION_ATOL = 2e-5


def _cfg():
    return toy_config(cycles=3, extra=["sa.tol=0.0", "sa.t0=0.5"])


def _rows(folder: str) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in train.TIME_FIELDS}
            for r in run_dir.read_metrics(os.path.join(folder, run_dir.METRICS_FILE))]


def _seed(tree, i: int):
    return jax.tree_util.tree_map(lambda x: np.asarray(x)[i], tree)


def _leaves_equal(a, b) -> bool:
    return all(np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True)
               for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, train.Trainer, str]:
    """A finished toy group of seeds 0 and 2, and seed 2 trained alone."""
    root = tmp_path_factory.mktemp("seed_group")
    group = train.run(_cfg(), str(root / "group"), env_factory=toy_factory(), progress=False, seeds=GROUP)
    alone = str(root / "alone")
    train.run(train.seed_config(_cfg(), ALONE), alone, env_factory=toy_factory(), progress=False)
    return str(root / "group"), group, alone


def test_each_seed_gets_a_run_folder_like_a_single_run(runs):
    out, group, alone = runs
    assert sorted(os.listdir(out)) == [f"seed{s}" for s in GROUP]
    folder = train.seed_dir(out, ALONE)
    assert sorted(os.listdir(folder)) == sorted(os.listdir(alone))
    with open(os.path.join(folder, run_dir.CONFIG_FILE)) as f, open(os.path.join(alone, run_dir.CONFIG_FILE)) as g:
        assert json.load(f) == json.load(g)  # its own seed, otherwise the group's config
    rows, alone_rows = _rows(folder), _rows(alone)
    assert [sorted(r) for r in rows] == [sorted(r) for r in alone_rows]  # the same row keys, row by row
    assert [r.get("sa_decision") for r in rows] == [r.get("sa_decision") for r in alone_rows]
    for r, a in zip(rows, alone_rows):
        if "eval_success" in r:
            assert abs(r["eval_success"] - a["eval_success"]) <= 0.005  # within half a point
    runtime.load_policy(os.path.join(folder, run_dir.POLICY_FILE))  # a valid policy file
    with np.load(os.path.join(folder, run_dir.POLICY_FILE)) as a, np.load(os.path.join(alone, run_dir.POLICY_FILE)) as b:
        assert sorted(a.files) == sorted(b.files)
        for key in (k for k in a.files if k.startswith("layer_")):
            np.testing.assert_allclose(a[key], b[key], atol=0.05, err_msg=key)  # 6 iterations of float32 rounding apart
    # every seed folder is a run folder: it evaluates and resumes on its own
    results = [evaluation.evaluate_run(f, episodes=64, env_factory=lambda cfg: toy_factory()(cfg)[1])["overall"]
               for f in (folder, alone)]
    assert abs(results[0]["success_rate"] - results[1]["success_rate"]) <= 0.005
    resumed = train.Trainer(train.seed_config(_cfg(), ALONE), folder, env_factory=toy_factory(), progress=False,
                            resume=True)
    assert resumed.host.iteration == train.make_schedule(_cfg()).num_iterations
    np.testing.assert_array_equal(np.asarray(resumed.train_state.normaliser.mean),
                                  np.asarray(group.train_state.normaliser.mean)[GROUP.index(ALONE)])


def test_first_iteration_matches_the_separate_run_within_float_rounding(tmp_path):
    group = train.Trainer(_cfg(), str(tmp_path / "g"), env_factory=toy_factory(), progress=False, seeds=GROUP)
    alone = train.Trainer(train.seed_config(_cfg(), ALONE), str(tmp_path / "a"), env_factory=toy_factory(),
                          progress=False)
    np.testing.assert_array_equal(np.asarray(group.env_state.obs)[1], np.asarray(alone.env_state.obs))  # same start
    group_rows = group.run_calls([1, 1])
    alone_row = alone.run_iteration()
    assert group_rows[1][0]["loss"] == pytest.approx(alone_row["loss"], rel=1e-4)
    ts = _seed(group.train_state, 1)
    np.testing.assert_allclose(ts.normaliser.std, alone.train_state.normaliser.std, rtol=1e-5)
    informative = np.asarray(ts.normaliser.std) > _cfg().ppo.obs_std_floor * 1.001
    assert informative.sum() == 6  # the toy's 7th observation entry is constant
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(ts.params), jax.tree_util.tree_leaves(alone.train_state.params)):
        a, b = np.asarray(a), np.asarray(b)
        rows = informative if a.ndim == 2 and a.shape[0] == informative.size else slice(None)
        np.testing.assert_allclose(a[rows], b[rows], atol=FIRST_ITERATION_ATOL, rtol=0, err_msg=jax.tree_util.keystr(path))


def test_killed_group_resumes_bit_for_bit(runs, tmp_path):
    out, full, _ = runs
    half = str(tmp_path / "half")
    stopped = train.run(_cfg(), half, env_factory=toy_factory(), progress=False, seeds=GROUP, stop_after_cycles=1)
    assert [h.lr_state.cycle for h in stopped.hosts] == [1, 1]
    assert not os.path.exists(os.path.join(train.seed_dir(half, 0), run_dir.POLICY_FILE))
    with open(os.path.join(train.seed_dir(half, 0), run_dir.METRICS_FILE), "a") as f:  # a kill after the checkpoint
        f.write(json.dumps({"iteration": 10**6, "env_steps": 0}) + "\n" + '{"iteration": 1')
    assert train.group_seeds_in(half) == GROUP  # --resume on the group folder finds its seeds
    resumed = train.run(_cfg(), half, env_factory=toy_factory(), progress=False, seeds=GROUP, resume=True)
    for s in GROUP:
        assert _rows(train.seed_dir(half, s)) == _rows(train.seed_dir(out, s))
    assert _leaves_equal(resumed.runner, full.runner)
    assert [h.lr_state for h in resumed.hosts] == [h.lr_state for h in full.hosts]


def test_a_non_finite_seed_rolls_back_alone(tmp_path):
    cfg = _cfg()
    reference = train.Trainer(cfg, str(tmp_path / "r"), env_factory=toy_factory(), progress=False, seeds=GROUP)
    tr = train.Trainer(cfg, str(tmp_path / "t"), env_factory=toy_factory(), progress=False, seeds=GROUP)
    for t in (reference, tr):
        t.run_calls([1, 1])
        t.end_cycles([True, True])  # both accept: the snapshot is this state
    bad = jnp.array([False, True])
    poison = lambda x: jnp.where(bad.reshape((2,) + (1,) * (x.ndim - 1)), jnp.nan, x)  # noqa: E731
    ts = tr.train_state
    tr.runner = tr.runner._replace(train_state=ts._replace(params=jax.tree_util.tree_map(poison, ts.params)))
    rows = tr.run_calls([1, 1])
    reference.run_calls([1, 1])
    assert "event" not in rows[0][-1] and rows[1][-1]["event"] == "nonfinite"
    assert [h.nonfinite for h in tr.hosts] == [0, 1]
    assert _leaves_equal(_seed(tr.train_state, 0), _seed(reference.train_state, 0))  # seed 0 ran on undisturbed
    restored, snapshot = _seed(tr.train_state, 1), _seed(tr.snapshot, 1)  # seed 1 back at its snapshot ...
    assert _leaves_equal((restored.params, restored.normaliser, restored.opt_state),
                         (snapshot.params, snapshot.normaliser, snapshot.opt_state))
    lrs = [h.lr_state.lr for h in tr.hosts]  # the host's schedule owns each seed's lr
    assert lrs[0] == cfg.ppo.learning_rate
    assert lrs[1] == pytest.approx(cfg.ppo.learning_rate * cfg.sa.decay)  # ... with SA's forced reject and decay


def test_seed_lists():
    assert train.parse_seeds("0-4") == [0, 1, 2, 3, 4]
    assert train.parse_seeds("0,2,5") == [0, 2, 5]
    assert train.parse_seeds("7, 0-1") == [7, 0, 1]


@pytest.mark.parametrize("argv,message", [
    (["--seeds", "3-1"], "the range 3-1 is empty"),
    (["--seeds", "0,2,2"], "seed 2 given twice"),
    (["--seeds", "0-2", "--seed", "1"], "--seed and --seeds: give one"),
    (["--seeds", "a-b"], "is not a seed or a range"),
    (["--seeds", "0-2", "--coordinator", "localhost:1234"], "does not combine with --coordinator"),
])
def test_bad_seed_lists_fail_clearly_and_write_nothing(tmp_path, capsys, argv, message):
    out = tmp_path / "group"
    assert train.main(["--out", str(out), *argv]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_a_group_refuses_a_folder_in_use(tmp_path, capsys):
    out = tmp_path / "group"
    (out / "seed1").mkdir(parents=True)
    (out / "seed1" / "notes.txt").write_text("mine")
    assert train.main(["--out", str(out), "--seeds", "0-1", "--total-steps", "1000"]) == 2
    assert "exists and is not empty" in capsys.readouterr().err
    assert sorted(os.listdir(out)) == ["seed1"]  # nothing added


@pytest.mark.parametrize("schedule", ["kl-adaptive", "cosine"])
def test_every_seed_keeps_its_own_learning_rate(tmp_path, schedule):
    """Each seed's host schedule owns its lr: kl-adaptive adapts each seed's to its own KL inside the call,
    which returns it to the host; cosine gives each seed's from its own progress to each iteration."""
    cfg = toy_config(cycles=3, extra=[f"lr.schedule={schedule}"])
    tr = train.Trainer(cfg, str(tmp_path), env_factory=toy_factory(), progress=False, seeds=GROUP)
    tr.run_calls([2, 1])
    rows = tr.run_calls([1, 1])  # seed 0 after 3 iterations, seed 2 after 2
    assert [h.iteration for h in tr.hosts] == [3, 2]
    lrs = [h.lr_state.lr for h in tr.hosts]
    assert lrs[0] != lrs[1]
    if schedule == "kl-adaptive":  # the host keeps the lr each seed's call ended at
        assert [r[-1]["lr"] for r in rows] == lrs and lrs[0] != cfg.ppo.learning_rate
        return
    n = train.make_schedule(cfg).num_iterations
    lr_at = lambda iteration: float(lr_schedule.progress_lr(np, tr.rule, np.float32(iteration / n)))  # noqa: E731
    for host in tr.hosts:
        assert host.lr_state.lr == pytest.approx(lr_at(host.iteration), rel=1e-5)  # what its next one starts from
