"""Checkpoint files: exact round trip, atomic writes, and loud failures on damage or mismatch."""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import json
import os
import struct

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sagrasp_jax.training import checkpoint
from sagrasp_jax.training.checkpoint import CheckpointError
from sagrasp_jax.task.config import get_config
from sagrasp_jax.task.config_parse import apply_overrides
from paths import DATA  # noqa: E402


def _trees():
    return {
        "state": {"w": jnp.arange(6, dtype=jnp.float32).reshape(2, 3), "n": jnp.array(3, jnp.int32),
                  "flag": jnp.array([True, False]), "eps": jnp.asarray(0.0)},
        "keys": {"raw": jax.random.split(jax.random.PRNGKey(4), 3), "typed": jax.random.key(5)},
        "tuple": (jnp.ones(2, jnp.uint32), np.float64(2.5)),
    }


def _write(tmp_path, cfg=None):
    path = str(tmp_path / "c.ckpt")
    checkpoint.save(path, trees=_trees(), host={"iteration": 7, "sa": {"lr": 3e-4, "m_acc": None}},
                    config=cfg or get_config("cpu-quick"))
    return path


def test_round_trip_is_exact_and_leaves_no_temp_files(tmp_path):
    path = _write(tmp_path)
    assert os.listdir(tmp_path) == ["c.ckpt"]
    ck = checkpoint.load(path)
    assert ck.host == {"iteration": 7, "sa": {"lr": 3e-4, "m_acc": None}}
    assert ck.header["package_version"] == sagrasp_jax.__version__
    template = jax.tree_util.tree_map(lambda x: x, _trees())
    for name, tmpl in template.items():
        restored = checkpoint.restore_tree(tmpl, ck.trees[name], name, path)
        for a, b in zip(jax.tree_util.tree_leaves(restored), jax.tree_util.tree_leaves(tmpl)):
            if jax.dtypes.issubdtype(getattr(b, "dtype", np.float64), jax.dtypes.prng_key):
                np.testing.assert_array_equal(jax.random.key_data(a), jax.random.key_data(b))
            else:
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
                assert jnp.asarray(a).dtype == jnp.asarray(b).dtype


def test_weak_scalars_stay_weak_so_resumed_jit_signatures_match(tmp_path):
    path = _write(tmp_path)
    restored = checkpoint.restore_tree(_trees()["state"], checkpoint.load(path).trees["state"], "state", path)
    assert jax.device_put(restored["eps"]).weak_type


def _damage(path, fn):
    with open(path, "rb") as f:
        blob = bytearray(f.read())
    with open(path, "wb") as f:
        f.write(fn(blob))


@pytest.mark.parametrize("damage,message", [
    (lambda b: b[:-10], "truncated"),
    (lambda b: b[:20], "truncated"),
    (lambda b: b"X" + b[1:], "bad magic"),
    (lambda b: b[:-5] + bytes([b[-5] ^ 0xFF]) + b[-4:], "checksum"),
    (lambda b: b[:len(checkpoint.MAGIC) + 9] + b"X" + b[len(checkpoint.MAGIC) + 10:], "corrupt checkpoint header"),
    (lambda b: b"", "bad magic"),
])
def test_damaged_files_raise_checkpoint_error(tmp_path, damage, message):
    path = _write(tmp_path)
    _damage(path, damage)
    with pytest.raises(CheckpointError, match=message):
        checkpoint.load(path)


def test_other_format_version_is_refused(tmp_path):
    path = _write(tmp_path)
    with open(path, "rb") as f:
        blob = f.read()
    start = len(checkpoint.MAGIC) + 8
    (n,) = struct.unpack("<Q", blob[len(checkpoint.MAGIC):start])
    header = json.loads(blob[start:start + n])
    header["format_version"] = 99
    head = json.dumps(header).encode()
    with open(path, "wb") as f:
        f.write(checkpoint.MAGIC + struct.pack("<Q", len(head)) + head + blob[start + n:])
    with pytest.raises(CheckpointError, match="format version 99"):
        checkpoint.load(path)


def test_missing_file_and_incompatible_contents(tmp_path):
    with pytest.raises(CheckpointError, match="no checkpoint found"):
        checkpoint.load(str(tmp_path / "nothing.ckpt"))
    path = _write(tmp_path)
    ck = checkpoint.load(path)
    with pytest.raises(CheckpointError, match="config differs: ppo.num_envs"):
        checkpoint.check_config(ck, apply_overrides(get_config("cpu-quick"), ["ppo.num_envs=64"]))
    checkpoint.check_config(ck, get_config("cpu-quick"))
    wrong_shape = dict(_trees()["state"], w=jnp.zeros((3, 2), jnp.float32))
    with pytest.raises(CheckpointError, match="incompatible checkpoint"):
        checkpoint.restore_tree(wrong_shape, ck.trees["state"], "state", path)
    extra_leaf = dict(_trees()["state"], more=jnp.zeros(1))
    with pytest.raises(CheckpointError, match="different structure"):
        checkpoint.restore_tree(extra_leaf, ck.trees["state"], "state", path)
    # a template of shapes only (jax.eval_shape, as restore_policy builds it) restores the same arrays and
    # refuses the same mismatch
    shapes = jax.eval_shape(lambda: _trees()["state"])
    by_shape = checkpoint.restore_tree(shapes, ck.trees["state"], "state", path)
    by_array = checkpoint.restore_tree(_trees()["state"], ck.trees["state"], "state", path)
    for name, leaf in by_shape.items():
        np.testing.assert_array_equal(np.asarray(leaf), np.asarray(by_array[name]))
        assert np.asarray(leaf).dtype == np.asarray(by_array[name]).dtype
    with pytest.raises(CheckpointError, match=r"this run expects float32\[3, 2\]"):
        checkpoint.restore_tree(jax.eval_shape(lambda: dict(shapes, w=jnp.zeros((3, 2), jnp.float32))),
                                ck.trees["state"], "state", path)


def test_a_checkpoint_of_the_trainer_before_its_split_resumes_with_its_numbers(tmp_path):
    """``tests/data/pre_split_run`` is a toy run folder stopped after 2 of its 4 cycles by the trainer as it was
    before it was split into parts (one ``train.Trainer`` class, commit 3e79d11), with that trainer's finished
    run beside it (``expected_finished.json``: a digest of the final policy's arrays and every metrics row
    without its wall-clock fields).  Today's trainer resumes the folder and must finish with the same numbers:
    bit for bit (rows and policy digest) on a CPU that rounds as the recording's did; on another CPU model XLA's
    kernels round differently in the last bits (measured: ≤ 3e-6 relative on the resumed rows), so there every
    count and flag must still be equal and every float within 1e-4 relative — a resume that lost any state (a
    key, the normaliser, the schedule, a window) moves them by far more."""
    import hashlib
    import json
    import shutil

    import numpy as np

    from conftest import toy_factory
    from sagrasp_jax import train
    from sagrasp_jax.training import run_dir

    data = os.path.join(DATA, "pre_split_run")
    folder = str(tmp_path / "run")
    shutil.copytree(data, folder, ignore=shutil.ignore_patterns("expected_finished.json"))
    with open(os.path.join(data, "expected_finished.json"), encoding="utf-8") as f:
        expected = json.load(f)
    train.run(run_dir.load_config(folder), folder, resume=True, env_factory=toy_factory(), progress=False)
    policy = np.load(os.path.join(folder, "policy.npz"))
    digest = hashlib.sha256()
    for name in sorted(policy.files):
        if policy[name].dtype.kind in "fiub":
            digest.update(name.encode())
            digest.update(np.ascontiguousarray(policy[name]).tobytes())
    with open(os.path.join(folder, "metrics.jsonl"), encoding="utf-8") as f:
        rows = [{k: v for k, v in json.loads(line).items() if k not in train.TIME_FIELDS} for line in f]
    assert len(rows) == len(expected["metrics_rows"]) == 8
    if rows == expected["metrics_rows"]:  # the recording's rounding: the policy too, bit for bit
        assert digest.hexdigest() == expected["policy_arrays_sha256"]
        return
    for i, (row, want) in enumerate(zip(rows, expected["metrics_rows"])):
        assert row.keys() == want.keys(), i
        for key, value in row.items():
            if isinstance(value, float) and isinstance(want[key], float):
                assert value == pytest.approx(want[key], rel=1e-4, abs=1e-7), (i, key)
            else:
                assert value == want[key], (i, key)


def test_a_checkpoint_from_before_the_reward_term_registry_restores_its_term_sums(tmp_path):
    """Before ``reward.terms`` the env state's tracker held each term's episode sum as a field of its own
    (``….info['tracker'].r_distance``); now they sit in ``term_sums``.  Such a checkpoint restores into
    today's template with every leaf where it was, and a leaf missing from both places is still refused."""
    from typing import Any, NamedTuple

    from sagrasp_jax.task import episode, reward

    class OldTracker(NamedTuple):  # the tracker's fields as the checkpoints before the registry wrote them
        steps: Any
        d_prev: Any
        obstacle_dist_prev: Any
        clean: Any
        blocking: Any
        ret: Any
        r_distance: Any
        r_success: Any
        r_obstacle: Any
        min_obstacle_dist: Any

    class State(NamedTuple):
        info: Any

    f = lambda v: np.full(4, v, np.float32)  # noqa: E731
    old = State(info={"tracker": OldTracker(np.arange(4, dtype=np.int32), f(0.3), f(0.2), np.ones(4, bool),
                                            np.zeros(4, bool), f(1.5), f(0.75), f(-1.0), f(-0.25), f(0.1)),
                      "steps": np.arange(4, dtype=np.int32)})
    template = State(info={"tracker": episode.Tracker(np.zeros(4, np.int32), f(0), f(0), np.zeros(4, bool),
                                                      np.zeros(4, bool), f(0), {k: f(0) for k in reward.term_keys()},
                                                      f(0)),
                           "steps": np.zeros(4, np.int32)})
    flat = checkpoint.flatten_tree(old)
    assert ".info['tracker'].r_distance" in flat
    restored = checkpoint.restore_tree(template, flat, "env_state", "old.ckpt").info["tracker"]
    assert {k: float(v[0]) for k, v in restored.term_sums.items()} == {"r_distance": 0.75, "r_success": -1.0,
                                                                        "r_obstacle": -0.25}
    assert float(restored.ret[0]) == 1.5 and float(restored.min_obstacle_dist[0]) == np.float32(0.1)
    with reward.registered(reward.RewardTerm("r_new", "f_new", lambda xp, cfg, s: s.d_now, lambda p, cfg: p)):
        grown = template._replace(info=dict(template.info, tracker=template.info["tracker"]._replace(
            term_sums={k: f(0) for k in reward.term_keys()})))
        with pytest.raises(CheckpointError, match=r"missing \[\"\.info\['tracker'\]\.term_sums\['r_new'\]\"\]"):
            checkpoint.restore_tree(grown, flat, "env_state", "old.ckpt")


def test_a_checkpoint_whose_optimizer_held_the_lr_restores_without_it():
    """Before the host owned the lr the optimizer was ``optax.inject_hyperparams(optax.adam)``: its state held
    the lr.  Such a train state restores into today's (``actor_critic.make_optimizer``, no lr) with Adam's
    count and moments as they were and the old lr dropped; a moment missing is still refused."""
    from typing import Any, NamedTuple

    import optax

    from sagrasp_jax.training.agents.ppo import actor_critic

    class TrainState(NamedTuple):  # the train state's paths: ``.opt_state…``, ``.params…``
        opt_state: Any
        params: Any

    cfg = get_config("cpu-quick").ppo
    params = {"w": jnp.arange(6, dtype=jnp.float32).reshape(3, 2), "b": jnp.ones(2, jnp.float32)}
    grads = jax.tree_util.tree_map(lambda x: 0.5 * x - 1.0, params)
    old_opt = optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), optax.inject_hyperparams(optax.adam)(3e-4))
    old_state = old_opt.update(grads, old_opt.init(params), params)[1]
    old = TrainState(old_state, params)
    flat = checkpoint.flatten_tree(old)
    assert ".opt_state[1].hyperparams['learning_rate']" in flat and ".opt_state[1].inner_state[0].count" in flat
    new_opt = actor_critic.make_optimizer(cfg)
    template = TrainState(new_opt.init(params), params)
    restored = checkpoint.restore_tree(template, flat, "train_state", "old.ckpt")
    adam, old_adam = restored.opt_state[1].inner_state[0], old_state[1].inner_state[0]
    assert int(adam.count) == 1
    for got, want in zip(jax.tree_util.tree_leaves((adam.mu, adam.nu)),
                         jax.tree_util.tree_leaves((old_adam.mu, old_adam.nu))):
        np.testing.assert_array_equal(got, want)
    # the next step from the restored state is the old optimizer's next step at the host's lr, bit for bit
    want_updates = old_opt.update(grads, old_state, params)[0]
    got_updates = actor_critic.apply_learning_rate(new_opt.update(grads, restored.opt_state, params)[0],
                                                   jnp.float32(3e-4))
    for got, want in zip(jax.tree_util.tree_leaves(got_updates), jax.tree_util.tree_leaves(want_updates)):
        np.testing.assert_array_equal(got, want)
    del flat[".opt_state[1].inner_state[0].mu['w']"]
    with pytest.raises(CheckpointError, match=r"missing \[\"\.opt_state\[1\]\.inner_state\[0\]\.mu\['w'\]\"\]"):
        checkpoint.restore_tree(template, flat, "train_state", "old.ckpt")
