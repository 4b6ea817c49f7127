"""Every change of the config's layout has its history entry, so a config written before it upgrades cleanly.

The recorded layout is ``tests/data/config_before_renames.json``: a config as the code wrote it before the
evaluation cadence left the ``sa`` section (test_config_renames.py pins its hashes), the layout that every
later change is counted from.  A key of today's layout that it lacks was added since and needs an
``ADDED_KEYS`` entry (or is a renamed key's new name); a key of it that is gone needs a ``REMOVED_KEYS`` or
``RENAMED_KEYS`` entry.  The record is a file old code wrote, pinned by its keys' digest below, so it cannot
be edited to take in a new key: the way to pass is the history entry.
"""

from __future__ import annotations

import hashlib
import json
import os

from sagrasp_jax.task.config import config_to_dict, flatten_keys, get_key, key_specs, valid_keys
from sagrasp_jax.task.config_history import (
    ADDED_KEYS, LEGACY_VALUES, REMOVED_KEYS, RENAMED_KEYS, RESPELLED_VALUES, config_hash, env_dict_hash, identity_dict,
)
from sagrasp_jax.task.config_parse import config_from_dict
from paths import DATA  # noqa: E402

RECORDED = os.path.join(DATA, "config_before_renames.json")
RECORDED_KEYS = 129  # keys of the recorded layout, and the digest of their sorted names: the record does not move
RECORDED_KEYS_SHA256 = "e19ce5c6d55bdb4b"
HISTORY = "sagrasp_jax/task/config_history.py"


def _recorded() -> dict:
    with open(RECORDED, encoding="utf-8") as f:
        return json.load(f)


def _recorded_keys() -> set[str]:
    return set(flatten_keys(_recorded(), "", "recorded layout"))


def test_the_recorded_layout_is_the_one_old_code_wrote():
    keys = sorted(_recorded_keys())
    digest = hashlib.sha256("\n".join(keys).encode()).hexdigest()[:16]
    assert (len(keys), digest) == (RECORDED_KEYS, RECORDED_KEYS_SHA256), (
        f"{RECORDED} is a config written by old code, the layout the history counts from: leave it as it is "
        f"and give a new key its entry in {HISTORY} instead")


def test_every_key_added_since_the_recorded_layout_has_its_value_for_old_configs():
    added = set(valid_keys()) - _recorded_keys() - set(RENAMED_KEYS.values())
    missing = sorted(added - set(ADDED_KEYS))
    assert not missing, (
        f"config keys added without a history entry: {', '.join(missing)}.  Add each to ADDED_KEYS in {HISTORY} "
        "with the value that does what a config written before it did (usually the key's default; if that is not "
        "its default, put the same value in LEGACY_VALUES too): runs, checkpoints and policy files written before "
        "the key then upgrade to their old behaviour and keep their identity and config hashes")


def test_every_key_removed_since_the_recorded_layout_says_what_replaced_it():
    gone = sorted(_recorded_keys() - set(valid_keys()) - set(REMOVED_KEYS) - set(RENAMED_KEYS))
    assert not gone, (
        f"config keys removed without a history entry: {', '.join(gone)}.  Add each to RENAMED_KEYS in {HISTORY} "
        "(old name -> new name) or to REMOVED_KEYS (what replaced it; and teach upgrade_flat to turn an old "
        "config's value into the same training), so a saved config, --set or --config file that has it still reads")


def test_an_old_config_upgrades_to_the_added_keys_old_values_and_keeps_its_hashes():
    cfg = config_from_dict(_recorded())
    wrong = {name: (get_key(cfg, name), old) for name, old in ADDED_KEYS.items() if get_key(cfg, name) != old}
    assert not wrong, (f"an old config reads these added keys (as read, as meant) at another value: {wrong}; put "
                       f"them in LEGACY_VALUES ({HISTORY}) at the value ADDED_KEYS gives")
    assert config_to_dict(cfg)["ppo"]["late_epochs"] == 0 and cfg.train.stop_cycles == 20  # e.g. two of them
    assert set(ADDED_KEYS).isdisjoint(flatten_keys(identity_dict(cfg), "", "identity"))  # its identity: as written
    as_stored = json.loads(json.dumps(config_to_dict(cfg.env)))  # how a policy file stores the env (tuples: lists)
    assert env_dict_hash(as_stored) == config_hash(cfg) == "3ac7c6501b2e"


def test_the_history_names_keys_of_the_right_layout():
    current = set(valid_keys())
    today = [*ADDED_KEYS, *LEGACY_VALUES, *RENAMED_KEYS.values(), *RESPELLED_VALUES]
    assert [name for name in today if name not in current] == [], "history entries for keys that do not exist"
    assert [name for name in [*REMOVED_KEYS, *RENAMED_KEYS] if name in current] == [], "an old name is a key again"
    for name, old in {**ADDED_KEYS, **LEGACY_VALUES}.items():  # an old config's value is one the key accepts
        spec = key_specs()[name]
        for value in old if spec.listed else (old,):
            assert spec.range is None or value in spec.range, name
            assert spec.choices is None or value in spec.choices, name
