"""The config's history: the layouts configs were written in before, and what keeps them working.

Run folders, checkpoints, policy files and ``--config`` files written by older code hold keys that were
since removed (``REMOVED_KEYS``), renamed (``RENAMED_KEYS``) or respelled (``RESPELLED_VALUES``), and lack
keys added since (``LEGACY_VALUES``, ``ADDED_KEYS``).  ``upgrade_flat`` / ``upgrade_config_dict`` read such a
config in today's layout with the behaviour it was written with; ``identity_dict``, ``config_hash`` and
``env_dict_hash`` identify a config the way it was first written, so a rename or a new key at its old value
changes no earlier run's identity, evaluation file or policy hash.  ``tests/task/test_config_history.py`` fails
when a key is added or removed without an entry here.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any

from sagrasp_jax.task.config import Config, ConfigError, config_to_dict, flatten_keys, nest_keys

# Keys added after the first release, with the value that reproduces what a saved config without
# them meant (run folders, checkpoints and policy files of version 0.1 keep their behaviour).
LEGACY_VALUES: dict[str, Any] = {
    "env.reward.near_miss_mode": "per_step",
    "env.task.obs_layout": "paper",
    "env.task.obstacle_geometry": "cover",
}

# Keys removed since the first release, with what replaced them (``apply_overrides`` names the new key;
# ``upgrade_config_dict`` turns a saved config that has them into the same training).
REMOVED_KEYS: dict[str, str] = {
    "sa.enabled": "lr.schedule (sa or constant; or --algo / --lr-schedule)",
    "sa.lr0": "ppo.learning_rate (the initial learning rate of every lr schedule)",
}

# Keys renamed, old name -> new: a saved config, a ``--set`` or a ``--config`` file with the old name means the
# new key.  The evaluation cadence of every lr schedule left the sa section.
RENAMED_KEYS: dict[str, str] = {
    "sa.cycle_steps": "eval.cycle_steps",
    "sa.num_cycles": "eval.num_cycles",
    "sa.eval_episodes": "eval.episodes",
    "sa.eval_seed": "eval.seed",
}

# Values spelled differently now, key -> (old value, new value): the training mix was −1 for "the evaluation
# mix's"; it is unset (none) now.
RESPELLED_VALUES: dict[str, tuple[Any, Any]] = {"train.obstacle_prob": (-1.0, None), "train.blocking_prob": (-1.0, None)}

# Keys added after run folders were written, with the value that does what a config without them did: a run's
# identity and config hash leave them out at that value, so adding a key changes no earlier run's hash.  A saved
# config without such a key reads its default, so a value that is not the default goes into LEGACY_VALUES too.
# Every key added since the layout of tests/data/config_before_renames.json needs an entry (test_config_history).
# (The curriculum was off in every earlier run, which makes its retirement count moot there: the default stands in.)
ADDED_KEYS: dict[str, Any] = {"env.reward.tilt_weight": 0.0, "env.reward.tilt_free_deg": 5.0, "env.reward.tilt_near": 0.0,
                              "train.curriculum_replay": 0.0, "train.curriculum_max_replays": 8,
                              "env.task.obs_obstacle_shape": False, "train.stop_success": 0.0, "train.stop_cycles": 20,
                              "ppo.late_epochs": 0, "ppo.late_from": 0.3, "env.robot": "aubo_i5",
                              "train.cpu_fusion_emitters": "legacy"}


def current_name(name: str) -> str:
    """A key as spelled now: a renamed key's new name (``RENAMED_KEYS``); a removed key is refused."""
    if name in REMOVED_KEYS:
        raise ConfigError(f"config key {name!r} was replaced by {REMOVED_KEYS[name]}")
    return RENAMED_KEYS.get(name, name)


def upgrade_flat(flat: dict[str, Any]) -> dict[str, Any]:
    """A flattened saved config in today's layout (``upgrade_config_dict``; ``config_parse.config_from_dict``
    reads a saved config through it)."""
    out = dict(flat)
    if "sa.enabled" in out or "sa.lr0" in out:  # before lr.schedule: SA ran from sa.lr0, plain PPO at ppo.learning_rate
        enabled, lr0 = out.pop("sa.enabled", True), out.pop("sa.lr0", None)
        if not isinstance(enabled, bool):
            raise ConfigError(f"invalid value for sa.enabled in a saved config: {enabled!r} (expected true/false)")
        out.setdefault("lr.schedule", "sa" if enabled else "constant")
        if enabled and lr0 is not None:
            out["ppo.learning_rate"] = lr0
    for old, new in RENAMED_KEYS.items():
        if old in out:
            out.setdefault(new, out.pop(old))
    for name, (old, new) in RESPELLED_VALUES.items():
        if name in out and out[name] == old:
            out[name] = new
    for name, value in LEGACY_VALUES.items():
        if any(k.startswith(name.rsplit(".", 1)[0] + ".") for k in flat):  # its section was saved
            out.setdefault(name, value)
    return out


def upgrade_config_dict(data: dict[str, Any]) -> dict[str, Any]:
    """A saved config dict in today's layout: removed keys replaced by what means the same (``REMOVED_KEYS``),
    renamed keys under their new names (``RENAMED_KEYS``), old spellings of values respelled
    (``RESPELLED_VALUES``), and every key added since it was written at its legacy value (``LEGACY_VALUES``)."""
    return nest_keys(upgrade_flat(flatten_keys(data, "", "saved config")))


def identity_dict(cfg: Config) -> dict[str, Any]:
    """``config_to_dict(cfg)`` with renamed keys and respelled values as they were first written: what a
    run's identity hashes (``training.evaluation.trained_identity``), so a rename leaves it, and the evaluation files
    that record it, unchanged."""
    flat = flatten_keys(config_to_dict(cfg), "", "config")
    for name, (old, new) in RESPELLED_VALUES.items():
        if name in flat and flat[name] == new:
            flat[name] = old
    for old, new in RENAMED_KEYS.items():
        flat[old] = flat.pop(new)
    return nest_keys(_without_added(flat))


def _without_added(flat: dict[str, Any]) -> dict[str, Any]:
    """``flat`` without the ``ADDED_KEYS`` that hold the value a config without them meant."""
    return {k: v for k, v in flat.items() if k not in ADDED_KEYS or v != ADDED_KEYS[k]}


def config_hash(cfg: Config) -> str:
    """Short stable hash of the env part: what a policy was trained on."""
    return env_dict_hash(config_to_dict(cfg.env))


def env_dict_hash(env: dict[str, Any]) -> str:
    """``config_hash`` of a saved config's env dict as written (a policy file's integrity check); ``ADDED_KEYS``
    at the value that means their absence are left out, so older files and runs keep their hashes."""
    env = nest_keys(_without_added(flatten_keys(env, "env.", "env")))["env"] if env else env
    blob = json.dumps(env, sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:12]
