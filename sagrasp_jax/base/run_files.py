"""The run folder's file names and its metrics log, for readers without jax.

``run_dir`` owns the run folder (writing, locking, checkpoints) and needs jax; the commands that
only read a finished run on any machine — ``plot`` (metrics.jsonl, the ``plots`` extra) and
``render --run`` (policy.npz, the ``render`` extra) — read it through this module, which is
NumPy-free and jax-free.  ``run_dir`` takes these names from here.
"""

from __future__ import annotations

import json
import os
import re
from typing import Any

from sagrasp_jax.base import fileio

CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.jsonl"
POLICY_FILE = "policy.npz"
SEED_FOLDER = re.compile(r"seed\d+$")  # a seed group's folders (train --seeds: OUT/seed<S>/)
MAX_METRICS_BYTES = 1 << 30  # a metrics log read for the plots (one row of ~1 kB per iteration): bounded like every input


class RunFolderError(ValueError):
    """Not a readable run folder or metrics log; the message names the path and what to do."""


def seed_folders(folder: str) -> list[str]:
    """``folder``'s seed-group subfolders (``seed0``, ``seed1``, ...) in seed order; [] if none."""
    try:
        names = [n for n in os.listdir(folder) if SEED_FOLDER.match(n) and os.path.isdir(os.path.join(folder, n))]
    except OSError:
        return []
    return [os.path.join(folder, n) for n in sorted(names, key=lambda n: int(n[4:]))]


def check_run(folder: str) -> str:
    """``folder`` if it is a run folder (it has ``config.json``), else RunFolderError saying what it is."""
    if not os.path.isdir(folder):
        raise RunFolderError(f"run folder {folder} not found")
    if os.path.isfile(os.path.join(folder, CONFIG_FILE)):
        return folder
    seeds = seed_folders(folder)
    if seeds:
        raise RunFolderError(f"{folder} is a seed group ({len(seeds)} seeds): pass one seed's folder, e.g. {seeds[0]}")
    raise RunFolderError(f"{folder} is not a run folder (no {CONFIG_FILE}; python -m sagrasp_jax.train --out writes one)")


def policy_of_run(folder: str) -> str:
    """The run's final ``policy.npz``; RunFolderError if the training has not written it (yet)."""
    file = os.path.join(check_run(folder), POLICY_FILE)
    if not os.path.isfile(file):
        raise RunFolderError(f"{folder} has no {POLICY_FILE} (a training writes it when it finishes); for a stopped "
                             f"run export its latest checkpoint: python -m sagrasp_jax.export --run {folder} --out DIR, "
                             f"then pass --policy DIR/{POLICY_FILE}")
    return file


def read_metrics(folder: str) -> list[dict[str, Any]]:
    """The rows of the run's ``metrics.jsonl``.  A last line cut short by a kill is dropped (as
    ``run_dir.read_metrics`` does); any other damage raises RunFolderError naming the line."""
    file = os.path.join(check_run(folder), METRICS_FILE)
    try:  # bounded, and a FIFO or device named, not opened
        data = fileio.read_regular(file, MAX_METRICS_BYTES, "metrics log")
    except (fileio.NotRegularFile, fileio.FileTooLarge) as exc:
        raise RunFolderError(f"{exc} (the metrics log)") from None
    except OSError as exc:
        raise RunFolderError(f"{file}: cannot read the metrics log ({exc.strerror or exc})") from None
    return parse_metrics(data, file, RunFolderError, need_env_steps=True)


def parse_metrics(data: bytes, file: str, error: type[Exception], need_env_steps: bool = False) -> list[dict[str, Any]]:
    """The rows of a ``metrics.jsonl``'s bytes: JSON objects with an integer ``iteration`` ≥ 0 (and
    ``env_steps``, for the plots).  The last line may be cut short by a kill and is then dropped; any other
    damage (a bad line, binary bytes, a row without its counters) raises ``error`` naming the file and line."""
    lines = [(i + 1, line) for i, line in enumerate(data.split(b"\n")) if line.strip()]
    what = "integer 'iteration' and 'env_steps'" if need_env_steps else "an integer 'iteration'"
    rows = []
    for k, (number, line) in enumerate(lines):
        try:
            row = json.loads(line.decode("utf-8"))
            if (not isinstance(row, dict) or type(row.get("iteration")) is not int or row["iteration"] < 0
                    or need_env_steps and type(row.get("env_steps")) is not int):
                raise ValueError(f"not a metrics row (a JSON object with {what})")
        except (UnicodeDecodeError, ValueError, RecursionError) as exc:
            if k == len(lines) - 1:
                break  # the last row, cut short by a kill mid-write
            raise error(f"{file}: damaged metrics log at line {number} ({exc})") from None
        rows.append(row)
    return rows
