"""Every config key is documented where it is declared, and ``train --list-keys`` shows it all."""

from __future__ import annotations

import pytest

from sagrasp_jax import train
from sagrasp_jax.task import config
from sagrasp_jax.task import config_history
from sagrasp_jax.task import config_parse


def test_every_key_has_a_description():
    """A new field needs a comment on its declaration line (or a comment block right above it)."""
    docs = config.key_descriptions()
    assert list(docs) == config.valid_keys()
    bare = [key for key, text in docs.items() if len(text.split()) < 3]  # a unit alone is not a meaning
    assert bare == [], f"config keys without a description in sagrasp_jax/task/config.py: {bare}"


def test_list_keys_shows_meaning_value_and_valid_values(capsys):
    with pytest.raises(SystemExit) as exit_info:
        train.main(["--preset", "gpu", "--list-keys"])  # no --out needed
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    cfg = config.get_config("gpu")
    for key, doc in config.key_descriptions().items():
        assert f"\n{key} = " in text, key
        assert doc.split()[0] in text
    assert "ppo.num_envs = 4096  (int; in [1, 16777216])  [paper 16; cpu-quick 256; cpu-physics 256]" in text
    assert "env.sampling.obstacle_kinds = sphere,cylinder,box  (list of str; each one of sphere, cylinder, box, capsule)" in text
    assert ("env.control.mode = lagged  (str; one of kinematic, dynamic, lagged)  [paper kinematic; cpu-physics dynamic; "
            "gpu-physics dynamic]") in text
    assert f"eval.episodes = {cfg.eval.episodes}" in text


def test_string_lists_parse_from_bare_words_and_json():
    base = config.get_config("paper")
    for text in ("capsule,box", '["capsule", "box"]', " capsule , box "):
        cfg = config_parse.apply_overrides(base, [f"env.sampling.obstacle_kinds={text}"])
        assert cfg.env.sampling.obstacle_kinds == ("capsule", "box")
    saved = config.config_to_dict(cfg)
    assert config_parse.config_from_dict(saved) == cfg
    del saved["env"]["sampling"]["obstacle_kinds"]  # a config saved before the key existed: the paper's kinds
    assert config_parse.config_from_dict(saved).env.sampling.obstacle_kinds == ("sphere", "cylinder", "box")


def test_minibatches_must_divide_the_batch():
    with pytest.raises(config.ConfigError, match="ppo.num_minibatches"):
        config_parse.apply_overrides(config.get_config("paper"),
                                     ["ppo.num_envs=10", "ppo.unroll_length=3", "ppo.num_minibatches=4"])


def test_cpu_quick_takes_four_passes_late_and_a_lower_pass_count_keeps_its_own():
    from sagrasp_jax.training.agents.ppo import ppo

    cfg = config.get_config("cpu-quick")
    assert (cfg.ppo.late_epochs, cfg.ppo.late_from, cfg.ppo.num_epochs) == (4, 0.3, 8)
    assert [int(ppo.epochs_at(cfg.ppo, p)) for p in (0.0, 0.29, 0.3, 1.0)] == [8, 8, 4, 4]
    assert config_history.identity_dict(cfg)["ppo"]["late_epochs"] == 4  # the preset's runs are new runs
    # fewer passes than the late count: refused before the preset set the key; now the run's own count throughout
    two = config_parse.apply_overrides(cfg, ["ppo.num_epochs=2"])
    assert two.ppo.late_epochs == 4 and ppo.epochs_at(two.ppo, 0.9) is None  # the fixed scan of 2 passes
    assert ppo.epochs_at(config_parse.apply_overrides(cfg, ["ppo.late_epochs=8"]).ppo, 0.9) is None
    # off: the preset before the key (its recorded runs keep their identity, the key left out at 0)
    before = config_parse.apply_overrides(cfg, ["ppo.late_epochs=0"])
    assert ppo.epochs_at(before.ppo, 0.9) is None
    assert {"late_epochs", "late_from"}.isdisjoint(config_history.identity_dict(before)["ppo"])
    with pytest.raises(config.ConfigError, match="ppo.late_from"):
        config_parse.apply_overrides(cfg, ["ppo.late_from=1.5"])


@pytest.mark.parametrize("physics,base", [("cpu-physics", "cpu-quick"), ("gpu-physics", "gpu")])
def test_a_physics_preset_is_its_base_preset_in_the_dynamic_mode(physics, base):
    """The physics presets differ from theirs in the control mode (MJX's servos instead of the fitted lag model),
    so a physics-trained policy is compared with the lagged one at every other setting equal; and cpu-physics
    compiles with the legacy CPU fusion emitter, which MJX's physics step runs 1.5x faster with (cpu-quick's
    lagged env trains faster with the new ones)."""
    flat, ref = ({k: config.get_key(config.get_config(name), k) for k in config.valid_keys()} for name in (physics, base))
    emitters = {"train.cpu_fusion_emitters"} if base == "cpu-quick" else set()
    assert {k for k in flat if flat[k] != ref[k]} == {"env.control.mode"} | emitters
    assert (flat["env.control.mode"], ref["env.control.mode"]) == ("dynamic", "lagged")
    assert flat["train.cpu_fusion_emitters"] == "legacy"
    assert flat["env.randomize.latency"] == 2.0 and flat["env.task.obs_layout"] == "relative_lag"
