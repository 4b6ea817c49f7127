"""``--config FILE``: a JSON (or YAML) file of config keys over the chosen preset, refused like
``--set``; ``--list-keys`` survives a closed pipe; a typo key names its nearest keys."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import pytest

from sagrasp_jax import evaluate, train
from sagrasp_jax.task import config_parse
from sagrasp_jax.task.config import ConfigError, get_config
from paths import REPO  # noqa: E402

LEGACY_RUN = os.path.join(REPO, "tests", "data", "legacy_v0_1")


def write(tmp_path, data, name="cfg.json") -> str:
    path = tmp_path / name
    path.write_text(json.dumps(data) if name.endswith(".json") else data)
    return str(path)


def test_a_partial_file_keeps_the_chosen_presets_other_values(tmp_path):
    path = write(tmp_path, {"ppo": {"num_envs": 512}, "env.task.max_steps": 150, "sa": {"metric": "success"}})
    for preset in ("cpu-quick", "paper"):
        cfg = train.build_config(preset, config_file=path)
        base = get_config(preset)
        assert cfg.ppo.num_envs == 512 and cfg.env.task.max_steps == 150 and cfg.sa.metric == "success"
        assert cfg.ppo.network == base.ppo.network and cfg.env.task.obs_layout == base.env.task.obs_layout
        assert cfg.train.total_steps == base.train.total_steps


def test_lists_booleans_and_precedence(tmp_path):
    path = write(tmp_path, {"env": {"sampling": {"obstacle_kinds": ["sphere", "box"]}, "control": {"slowdown_enabled": False}},
                            "lr": {"schedule": "constant"}, "train": {"seed": 3}})
    cfg = train.build_config("cpu-quick", config_file=path)
    assert cfg.env.sampling.obstacle_kinds == ("sphere", "box") and cfg.env.control.slowdown_enabled is False
    assert cfg.lr.schedule == "constant" and cfg.train.seed == 3  # the file's schedule wins over the default
    cfg = train.build_config("cpu-quick", algo="sa-ppo", seed=7, config_file=path, overrides=["train.seed=9"])
    assert cfg.lr.schedule == "sa" and cfg.train.seed == 9  # options over the file, --set over everything


def test_yaml_file(tmp_path):
    pytest.importorskip("yaml")
    path = write(tmp_path, "ppo:\n  num_envs: 256\nenv.task.max_steps: 120\n", name="cfg.yaml")
    cfg = train.build_config("cpu-quick", config_file=path)
    assert cfg.ppo.num_envs == 256 and cfg.env.task.max_steps == 120


@pytest.mark.parametrize("data,message", [
    ({"ppo": {"num_env": 512}}, "did you mean ppo.num_envs"),
    ({"ppo": {"num_envs": "many"}}, "bad value 'many' for ppo.num_envs"),
    ({"ppo": {"num_envs": 0}}, "ppo.num_envs"),
    ({"ppo": 5}, "is a section"),
    ({"ppo": {"num_envs": None}}, "has no value"),
    ([1, 2], "must be a mapping"),
    ("{not json", "not valid JSON"),
])
def test_bad_files_exit_2_and_write_nothing(tmp_path, capsys, data, message):
    path = tmp_path / "cfg.json"
    path.write_text(data if isinstance(data, str) else json.dumps(data))
    out = tmp_path / "run"
    assert train.main(["--out", str(out), "--config", str(path)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_missing_file_and_wrong_suffix_exit_2(tmp_path, capsys):
    out = tmp_path / "run"
    assert train.main(["--out", str(out), "--config", str(tmp_path / "absent.json")]) == 2
    assert "cannot read it" in capsys.readouterr().err
    assert train.main(["--out", str(out), "--config", str(tmp_path / "cfg.toml")]) == 2
    assert "expected a .json" in capsys.readouterr().err
    assert not out.exists()


def test_typo_key_suggests_the_nearest_keys_not_all_of_them():
    with pytest.raises(ConfigError) as info:
        config_parse.apply_overrides(get_config("cpu-quick"), ["ppo.learning_rte=1e-4"])
    text = str(info.value)
    assert "did you mean ppo.learning_rate" in text and text.count(",") < 5
    with pytest.raises(ConfigError, match="did you mean env.task.max_steps"):
        config_parse.apply_overrides(get_config("cpu-quick"), ["task.max_steps=10"])  # the section left out


def test_evaluate_config_file_takes_env_keys_only(tmp_path, capsys):
    bad = write(tmp_path, {"ppo": {"num_envs": 64}})
    assert evaluate.main(["--run", LEGACY_RUN, "--config", bad, "--episodes", "8", "--out", str(tmp_path / "e.json")]) == 2
    assert "env.* keys" in capsys.readouterr().err
    typo = write(tmp_path, {"env": {"control": {"mod": "dynamic"}}}, name="typo.json")
    assert evaluate.main(["--run", LEGACY_RUN, "--config", typo, "--episodes", "8", "--out", str(tmp_path / "e.json")]) == 2
    assert "did you mean env.control.mode" in capsys.readouterr().err
    assert not (tmp_path / "e.json").exists()


def test_list_keys_survives_a_closed_pipe():
    """``--list-keys | head``: the reader closes the pipe first; no BrokenPipeError traceback, exit 0."""
    proc = subprocess.Popen([sys.executable, "-m", "sagrasp_jax.train", "--list-keys"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # before it writes anything: the write must meet a closed pipe
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 0, err
    assert "BrokenPipeError" not in err and "Traceback" not in err


def test_yaml_yields_json_types_only():
    """YAML through the config's narrowed SafeLoader: dates stay strings, sets, binary, ordered maps and
    aliases are refused, integers are bounded like JSON's (issue 40)."""
    pytest.importorskip("yaml")
    import yaml

    assert config_parse.parse_yaml("a: 2001-12-14\nb: yes\nc: &x 3\nd: [1.5, null]\n") == {
        "a": "2001-12-14", "b": True, "c": 3, "d": [1.5, None]}  # an anchor alone is harmless
    for text, message in [("a: !!set {x, y}", "tag:yaml.org,2002:set is not allowed"),
                          ("a: !!binary aGVsbG8=", "tag:yaml.org,2002:binary is not allowed"),
                          ("a: !!omap [x: 1]", "tag:yaml.org,2002:omap is not allowed"),
                          ("a: !!timestamp 2001-12-14", "tag:yaml.org,2002:timestamp is not allowed"),
                          ("a: &x [1]\nb: *x", "an alias (*x) is not allowed"),
                          ("a: 1" + "0" * 64, "an integer of 65 digits (at most 64)")]:
        with pytest.raises((ValueError, yaml.YAMLError), match=re.escape(message)):
            config_parse.parse_yaml(text)
    for depth in (32, 100_000):  # refused as it is scanned (PyYAML's scanner slows down as depth²), or after
        with pytest.raises((ValueError, yaml.YAMLError), match="nested deeper than 32 levels"):
            config_parse.parse_yaml("a: " + "[" * depth + "]" * depth)
    deepest = config_parse.parse_yaml("a: " + "[" * 31 + "]" * 31)  # 32 levels with the mapping: the bound itself
    assert json.dumps(deepest) == '{"a": ' + "[" * 31 + "]" * 31 + "}"


def test_json_numbers_and_nesting_are_bounded():
    assert config_parse.parse_json('{"a": ' + "9" * 64 + "}") == {"a": int("9" * 64)}
    with pytest.raises(ValueError, match="an integer of 65 digits"):
        config_parse.parse_json('{"a": ' + "9" * 65 + "}")
    with pytest.raises(ValueError, match="nested deeper than 32 levels"):
        config_parse.parse_json("[" * 33 + "]" * 33)
    assert json.dumps(config_parse.parse_json("[" * 32 + "]" * 32)) == "[" * 32 + "]" * 32  # the bound itself


@pytest.mark.parametrize("literal, digits", [
    ("0x" + "f" * 4000, 4000),  # 4,816 decimal digits: str() of it stops at Python's 4,300-digit limit
    ("-0x" + "F" * 65, 65), ("0x" + "f" * 64, 78),  # a hex literal's letters are digits; its value is bounded too
    ("0b" + "1" * 65, 65), ("0" + "7" * 64, 65), ("1_" * 64 + "1", 65), ("+" + "9" * 65, 65),
    ("1" + ":59" * 32, 65),  # base 60
])
def test_every_yaml_integer_notation_is_bounded(literal, digits):
    pytest.importorskip("yaml")
    import yaml

    with pytest.raises((ValueError, yaml.YAMLError), match=re.escape(f"an integer of {digits} digits (at most 64)")):
        config_parse.parse_yaml(f"a: {literal}\n")
    for ok, value in [("0x" + "f" * 53, 16**53 - 1), ("-0x1F", -31), ("0b101", 5), ("017", 15), ("1_000", 1000),
                      ("1:20", 80), ("+" + "9" * 64, int("9" * 64))]:
        assert config_parse.parse_yaml(f"a: {ok}") == {"a": value}
    for empty in ('""', '"-"'):  # PyYAML's own IndexError on an empty explicit integer: a YAML error too
        with pytest.raises(yaml.YAMLError, match="is not an integer"):
            config_parse.parse_yaml(f"a: !!int {empty}")


@pytest.mark.parametrize("command", ["train", "evaluate"])
def test_a_hex_integer_in_a_config_file_exits_2(tmp_path, command):
    """``num_envs: 0xfff…`` (4,000 digits) got past the bound, which counted decimal digits only, and ended in a
    ValueError traceback ("Exceeds the limit (4300 digits)") when the value was written out as --set text."""
    pytest.importorskip("yaml")
    key = "ppo:\n  num_envs" if command == "train" else "env:\n  task:\n    max_steps"
    path = write(tmp_path, f"{key}: 0x{'f' * 4000}\n", name="cfg.yaml")
    out = tmp_path / ("run" if command == "train" else "e.json")
    args = ["--out", str(out), "--config", path] + (["--run", LEGACY_RUN, "--episodes", "8"] if command == "evaluate" else [])
    res = subprocess.run([sys.executable, "-m", f"sagrasp_jax.{command}", *args], cwd=REPO, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 2 and "an integer of 4000 digits (at most 64)" in res.stderr, res.stderr
    assert f"--config {path}" in res.stderr and "Traceback" not in res.stderr and not out.exists()
