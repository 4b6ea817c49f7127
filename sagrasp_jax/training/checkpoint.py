"""Checkpoint files: everything an exact resume needs, written atomically, validated on load.

Layout of a ``.ckpt`` file::

    MAGIC (13 bytes) | header length (uint64 little-endian) | header JSON | payload

The payload is ``flax.serialization.msgpack_serialize`` of ``{tree name: {leaf path: ndarray}}``
(any pytree, flattened by ``jax.tree_util`` key paths, so brax/MJX/optax states need no
special handling).  The header holds the format and package versions, the full config, host
side state (counters, SA schedule, RNG states) and the payload's length and SHA-256.  Loading
checks all of them and raises :class:`CheckpointError` naming the file and the problem: a
damaged or mismatched checkpoint must stop the run, never silently restart it.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import hashlib
import json
import re
import struct
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np
from flax import serialization

from sagrasp_jax import __version__
from sagrasp_jax.base import fileio
from sagrasp_jax.task.config import Config, ConfigError, config_to_dict
from sagrasp_jax.task.config_parse import config_from_dict

MAGIC = b"SAGRASP-CKPT\n"
FORMAT_VERSION = 1
_LEN = struct.Struct("<Q")


class CheckpointError(RuntimeError):
    """A checkpoint that is missing, corrupt, truncated or incompatible with the run."""


@dataclass(frozen=True)
class Checkpoint:
    header: dict[str, Any]
    trees: dict[str, dict[str, np.ndarray]]  # tree name -> {leaf path: array}
    path: str

    @property
    def host(self) -> dict[str, Any]:
        return self.header["host"]


def _is_key(x: Any) -> bool:
    return isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def flatten_tree(tree: Any) -> dict[str, np.ndarray]:
    """{key path: host ndarray}; typed PRNG keys are stored as their raw key data."""
    leaves, _ = jax.tree_util.tree_flatten_with_path(tree)
    out: dict[str, np.ndarray] = {}
    for path, leaf in leaves:
        if _is_key(leaf):
            leaf = jax.random.key_data(leaf)
        out[jax.tree_util.keystr(path)] = np.asarray(leaf)
    return out


# A reward term's episode sum in the env state's tracker, and where checkpoints written before the reward-term
# registry (reward.terms) kept it: ``….info['tracker'].r_distance``, now ``….info['tracker'].term_sums['r_distance']``.
_TERM_SUM_PATH = re.compile(r"(.*\.info\['tracker'\])\.term_sums\['(r_\w+)'\]")


def _with_moved_paths(keys: list[str], flat: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``flat`` with the leaves a checkpoint wrote under an older path (``_TERM_SUM_PATH``) under today's, so
    a run started before the move still resumes exactly."""
    moved = {}
    for key in keys:
        match = _TERM_SUM_PATH.fullmatch(key)
        if key not in flat and match and f"{match[1]}.{match[2]}" in flat:
            moved[key] = f"{match[1]}.{match[2]}"
    if not moved:
        return flat
    old = set(moved.values())
    return {k: v for k, v in flat.items() if k not in old} | {new: flat[o] for new, o in moved.items()}


# The lr in checkpoints written while the optimizer held it (``optax.inject_hyperparams(optax.adam)``); today the
# host owns the lr (``lr_schedule.ScheduleState``) and the optimizer state is otherwise laid out as it was then.
_INJECTED_LR = re.compile(r"\.opt_state\[1\]\.hyperparams\['learning_rate'\]")


def _without_injected_lr(flat: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``flat`` without the lr a checkpoint wrote into the optimizer state before the host owned it."""
    return {k: v for k, v in flat.items() if not _INJECTED_LR.fullmatch(k)}


def restore_tree(template: Any, flat: dict[str, np.ndarray], name: str, path: str) -> Any:
    """Fill ``template``'s structure with the saved leaves; paths, shapes and dtypes must match (leaves an older
    version wrote elsewhere are moved: ``_with_moved_paths``, ``_without_injected_lr``)."""
    leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
    keys = [jax.tree_util.keystr(p) for p, _ in leaves]
    flat = _with_moved_paths(keys, _without_injected_lr(flat))
    missing = sorted(set(keys) - set(flat))
    extra = sorted(set(flat) - set(keys))
    if missing or extra:
        raise CheckpointError(
            f"{path}: incompatible checkpoint: '{name}' has a different structure "
            f"(missing {missing[:5]}, unexpected {extra[:5]}); was it written by another version or config?")
    values = []
    for key, (_, leaf) in zip(keys, leaves):
        saved = flat[key]
        python_scalar = type(leaf) in (bool, int, float)  # not np.float64, a float subclass
        if isinstance(leaf, jax.ShapeDtypeStruct) and not jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key):
            # a jax.eval_shape template: shapes and dtypes, no arrays made
            ref: Any = np.empty(leaf.shape, leaf.dtype)
        elif _is_key(leaf):
            ref = jax.random.key_data(leaf)
        else:
            ref = np.asarray(jax.numpy.asarray(leaf) if python_scalar else leaf)
        if saved.shape != ref.shape or saved.dtype != ref.dtype:
            raise CheckpointError(
                f"{path}: incompatible checkpoint: {name}{key} is {saved.dtype}{list(saved.shape)}, "
                f"this run expects {ref.dtype}{list(ref.shape)}")
        if _is_key(leaf):
            saved = jax.random.wrap_key_data(saved, impl=jax.random.key_impl(leaf))
        elif (python_scalar or getattr(leaf, "weak_type", False)) and saved.shape == ():
            saved = saved.item()  # a Python scalar stays weakly typed: same jit signature, no recompile
        values.append(saved)
    return jax.tree_util.tree_unflatten(treedef, values)


atomic_write_bytes = fileio.atomic_write_bytes


def save(path: str, *, trees: dict[str, Any], host: dict[str, Any], config: Config) -> None:
    """Write a checkpoint: ``trees`` are pytrees of arrays, ``host`` is JSON-safe host state."""
    payload = serialization.msgpack_serialize({name: flatten_tree(t) for name, t in trees.items()})
    header = {
        "format_version": FORMAT_VERSION,
        "package_version": __version__,
        "config": config_to_dict(config),
        "host": host,
        "payload_bytes": len(payload),
        "payload_sha256": hashlib.sha256(payload).hexdigest(),
    }
    head = json.dumps(header, sort_keys=True, allow_nan=False).encode()
    atomic_write_bytes(path, MAGIC + _LEN.pack(len(head)) + head + payload)


def load(path: str) -> Checkpoint:
    """Read and verify a checkpoint (magic, format version, lengths, checksum); only a regular file is read."""
    try:
        blob = fileio.read_regular(path)  # a FIFO or device is refused before it is opened
    except FileNotFoundError:
        raise CheckpointError(f"{path}: no checkpoint found") from None
    except fileio.NotRegularFile as exc:
        raise CheckpointError(f"{path} is {exc.kind}, not a checkpoint file") from None
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot read the checkpoint ({exc.strerror or exc})") from None
    if not blob.startswith(MAGIC):
        raise CheckpointError(f"{path}: not a sagrasp_jax checkpoint (bad magic bytes); the file is corrupt")
    start = len(MAGIC) + _LEN.size
    if len(blob) < start:
        raise CheckpointError(f"{path}: truncated checkpoint (header length missing)")
    (head_len,) = _LEN.unpack(blob[len(MAGIC):start])
    if len(blob) < start + head_len:
        raise CheckpointError(f"{path}: truncated checkpoint (header cut off)")
    try:
        header = json.loads(blob[start:start + head_len].decode())
        version = header["format_version"]
        size, digest = header["payload_bytes"], header["payload_sha256"]
    except (ValueError, KeyError, TypeError, RecursionError) as exc:  # ValueError: bad UTF-8 or JSON, 5,000-digit ints
        raise CheckpointError(f"{path}: corrupt checkpoint header ({exc})") from None
    if version != FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint format version {version} (package {header.get('package_version')}), "
            f"this sagrasp_jax {__version__} reads version {FORMAT_VERSION}")
    payload = blob[start + head_len:]
    if len(payload) != size:
        raise CheckpointError(f"{path}: truncated checkpoint: payload has {len(payload)} of {size} bytes")
    if hashlib.sha256(payload).hexdigest() != digest:
        raise CheckpointError(f"{path}: corrupt checkpoint: payload checksum mismatch")
    try:
        trees = serialization.msgpack_restore(payload)
    except Exception as exc:  # msgpack raises several unrelated types on bad data
        raise CheckpointError(f"{path}: corrupt checkpoint payload ({exc})") from None
    return Checkpoint(header=header, trees=trees, path=path)


def config_differences(saved: dict[str, Any], current: dict[str, Any], prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two config dicts."""
    diffs: list[str] = []
    for key in sorted(set(saved) | set(current)):
        a, b = saved.get(key), current.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            diffs += config_differences(a, b, f"{prefix}{key}.")
        elif (list(a) if isinstance(a, (list, tuple)) else a) != (list(b) if isinstance(b, (list, tuple)) else b):
            diffs.append(f"{prefix}{key}: checkpoint {a!r}, now {b!r}")
    return diffs


def check_config(ckpt: Checkpoint, config: Config) -> None:
    """Refuse to resume a run with a different config (the result would not be that run)."""
    try:  # a checkpoint written before a key existed means that key's legacy value (config_history.LEGACY_VALUES)
        saved = config_to_dict(config_from_dict(ckpt.header["config"]))
    except (ConfigError, TypeError, ValueError, AttributeError) as exc:
        raise CheckpointError(f"{ckpt.path}: the checkpoint's config does not load ({exc})") from None
    diffs = config_differences(saved, config_to_dict(config))
    if diffs:
        raise CheckpointError(f"{ckpt.path}: incompatible checkpoint: config differs: " + "; ".join(diffs))
