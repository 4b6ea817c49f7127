"""Renamed keys keep old configs, run folders, checkpoints and evaluation files working.

``tests/data/config_before_renames.json`` is a config as written before the evaluation cadence left
the ``sa`` section and the training mix lost its −1 sentinel (the paper preset with
``train.blocking_prob=0.3``, ``sa.eval_episodes=64``, ``sa.num_cycles=50``); the digests below were
computed by that code.
"""

from __future__ import annotations

import json
import os

import pytest

from sagrasp_jax.training import evaluation
from sagrasp_jax.task import config
from sagrasp_jax.task import config_history
from sagrasp_jax.task import config_parse
from sagrasp_jax.training import run_dir
from paths import DATA  # noqa: E402

LEGACY_RUN = os.path.join(DATA, "legacy_v0_1")


def _before() -> dict:
    with open(os.path.join(DATA, "config_before_renames.json"), encoding="utf-8") as f:
        return json.load(f)


def test_an_old_layout_loads_under_the_new_names():
    raw = _before()
    assert raw["sa"]["num_cycles"] == 50 and raw["train"]["obstacle_prob"] == -1.0  # the old layout
    cfg = config_parse.config_from_dict(raw)
    assert (cfg.eval.num_cycles, cfg.eval.episodes, cfg.eval.seed, cfg.eval.cycle_steps) == (50, 64, 12345, 0)
    assert cfg.train.obstacle_prob is None and cfg.train.blocking_prob == 0.3  # −1 meant "the evaluation mix"
    train_env = config.training_env_config(cfg)
    assert train_env.sampling.obstacle_prob == cfg.env.sampling.obstacle_prob == 0.2
    assert train_env.sampling.blocking_prob == 0.3
    assert config_parse.config_from_dict(config.config_to_dict(cfg)) == cfg  # the new layout round-trips
    assert config_parse.config_from_dict(config_history.identity_dict(cfg)) == cfg  # and the old one, read back


def test_hashes_of_old_configs_do_not_change():
    cfg = config_parse.config_from_dict(_before())
    assert config_history.config_hash(cfg) == "3ac7c6501b2e"  # the env part: no env key was renamed
    assert json.loads(json.dumps(config_history.identity_dict(cfg))) == _before()
    legacy = run_dir.load_config(LEGACY_RUN)
    ckpt = run_dir.load_checkpoint(LEGACY_RUN, legacy)  # its checkpoint's saved config still matches
    assert evaluation.trained_identity(legacy, ckpt)["config_sha256"] == "3b75a691daca2740"


def test_an_evaluation_file_written_before_the_renames_still_matches(tmp_path):
    cfg = run_dir.load_config(LEGACY_RUN)
    ckpt = run_dir.load_checkpoint(LEGACY_RUN, cfg)
    identity = {"run": LEGACY_RUN, "episodes": 8, **evaluation.trained_identity(cfg, ckpt)}
    old = tmp_path / "evaluation.json"
    old.write_text(json.dumps({**identity, "config_sha256": "3b75a691daca2740", "overall": {}}))
    run_dir.check_replace(str(old), identity)  # the same evaluation: no refusal
    with pytest.raises(run_dir.RunDirError, match="holds a different result"):
        run_dir.check_replace(str(old), {**identity, "config_sha256": "0000000000000000"})


def test_old_key_names_on_the_command_line_and_in_files(tmp_path):
    base = config.get_config("paper")
    cfg = config_parse.apply_overrides(base, ["sa.num_cycles=7", "sa.eval_episodes=16", "sa.eval_seed=3",
                                              "sa.cycle_steps=0"])
    assert (cfg.eval.num_cycles, cfg.eval.episodes, cfg.eval.seed) == (7, 16, 3)
    path = tmp_path / "old.json"
    path.write_text(json.dumps({"sa": {"num_cycles": 9, "metric": "success"}, "train": {"obstacle_prob": None}}))
    cfg = config_parse.apply_overrides(base, config_parse.file_overrides(str(path)))
    assert cfg.eval.num_cycles == 9 and cfg.sa.metric == "success" and cfg.train.obstacle_prob is None


def test_the_training_mix_is_unset_or_a_probability():
    base = config.get_config("cpu-quick")
    assert base.train.obstacle_prob == 0.8
    cfg = config_parse.apply_overrides(base, ["train.obstacle_prob=none", "train.blocking_prob=0.1"])
    assert cfg.train.obstacle_prob is None and cfg.train.blocking_prob == 0.1
    with pytest.raises(config.ConfigError, match=r"invalid value for train.obstacle_prob: -1.0 \(must be in \[0, 1\]\)"):
        config_parse.apply_overrides(base, ["train.obstacle_prob=-1"])  # the old sentinel is spelled none now
    with pytest.raises(config.ConfigError, match="bad value 'nan'|train.obstacle_prob"):
        config_parse.apply_overrides(base, ["train.obstacle_prob=nan"])


def test_max_obstacles_declares_the_one_value_the_scene_has():
    assert config.key_specs()["env.sampling.max_obstacles"].choices == (2,)
    with pytest.raises(config.ConfigError, match="env.sampling.max_obstacles=3 is not one of 2"):
        config_parse.apply_overrides(config.get_config("paper"), ["env.sampling.max_obstacles=3"])


def test_choices_are_declared_once_and_used_by_the_modules_that_act_on_them():
    from sagrasp_jax.training.agents.ppo import actor_critic
    from sagrasp_jax.training import lr_schedule
    from sagrasp_jax.task import observation
    from sagrasp_jax.task import reward

    assert observation.LAYOUT_NAMES is config.OBS_LAYOUTS and lr_schedule.SCHEDULES is config.LR_SCHEDULES
    assert reward.RC_MODES is config.RC_MODES and reward.NEAR_MISS_MODES is config.NEAR_MISS_MODES
    assert tuple(actor_critic._ACTIVATIONS) == config.ACTIVATIONS
    assert config.key_specs()["env.control.mode"].choices == config.CONTROL_MODES


def test_an_env_config_built_in_code_is_checked_against_the_same_declarations():
    import dataclasses

    from sagrasp_jax.envs.grasp_env import GraspEnv

    env = config.EnvConfig()
    bad = dataclasses.replace(env, control=dataclasses.replace(env.control, mode="fast"))
    with pytest.raises(config.ConfigError, match="env.control.mode='fast' is not one of kinematic, dynamic, lagged"):
        GraspEnv(bad)
    bad = dataclasses.replace(env, sampling=dataclasses.replace(env.sampling, obstacle_prob=1.5))
    with pytest.raises(config.ConfigError, match=r"env.sampling.obstacle_prob: 1.5 \(must be in \[0, 1\]\)"):
        GraspEnv(bad)
