"""The run folder: its layout, its lock, and reading and writing everything in it.

A run folder (``python -m sagrasp_jax.train --out RUN``) holds:

=============================================  ==============================================
``config.json``                                the run's full config (written once, at start)
``metrics.jsonl``                              one JSON row per logged iteration (appended)
``tb/``                                        TensorBoard event files
``checkpoint.ckpt``                            everything an exact resume needs (``checkpoint``)
``policy.npz``                                 the final policy, ``policy_file`` format
``evaluation-<E>ep-seed<S>[-<N>steps].json``   ``evaluate``'s result for E episodes from seed S
=============================================  ==============================================

Every file is written through ``fileio`` (temp file + rename), so a kill leaves either the old
or the new file, plus at worst a temp file that the next writer removes; ``metrics.jsonl`` is
appended by :class:`MetricsLog` (a line cut short by a kill is dropped when it is read back).

**Lock.** A command that writes into a folder (``train`` into its run, ``export`` into its
output folder) holds :class:`FolderLock` on it for as long as it writes; a second writer is
refused at once with a message naming the holder.  ``evaluate`` holds :class:`ResultLock` on
its result file (and a shared lock on the folder), so evaluations of other runs may write into
the same folder meanwhile.  The lock is
``fcntl.flock`` on the folder itself: nothing is added to the folder, and the kernel drops
it when the process dies, so a killed run never leaves a stale lock.

**Starting a training** (:func:`prepare_training`, under the lock):

* a fresh start needs a missing or empty folder (temp files of a killed write do not count);
* ``--resume`` continues from ``checkpoint.ckpt`` after checking it, ``config.json`` and
  ``metrics.jsonl``; it removes stale temp files;
* a run killed before its first checkpoint (``config.json``, maybe ``metrics.jsonl`` and
  ``tb/``, no checkpoint) is restarted from the beginning by ``--resume``: there is nothing to
  continue from, and a restart with the same config is exactly the uninterrupted run.  Its
  partial logs are removed first.  A fresh start into such a folder is refused and says so.

Every reader raises :class:`RunDirError` (or ``checkpoint.CheckpointError``) naming the file
and what is wrong with it; nothing here writes before all checks have passed.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import errno
import fcntl
import json
import math
import os
import shutil
import stat
from typing import Any

import numpy as np

from sagrasp_jax.training import checkpoint
from sagrasp_jax.base import fileio
from sagrasp_jax.task.config import Config, ConfigError, config_to_dict
from sagrasp_jax.task.config_parse import MAX_CONFIG_BYTES, config_from_dict, parse_json
from sagrasp_jax.base import run_files
from sagrasp_jax.base.run_files import CONFIG_FILE, METRICS_FILE, POLICY_FILE  # shared with the jax-free readers

CHECKPOINT_FILE = "checkpoint.ckpt"
TB_DIR = "tb"
EVALUATION_PREFIX = "evaluation-"
MAX_RESULT_BYTES = fileio.MAX_RESULT_BYTES  # an earlier evaluation read back to compare (bounded like every input)
# What a training writes; the other files of a run folder are evaluations.
TRAINING_FILES = (CONFIG_FILE, METRICS_FILE, CHECKPOINT_FILE, POLICY_FILE, TB_DIR)
_WHAT = {CONFIG_FILE: "run config file", METRICS_FILE: "metrics log", CHECKPOINT_FILE: "checkpoint file",
         POLICY_FILE: "policy file", TB_DIR: "TensorBoard folder"}


class RunDirError(RuntimeError):
    """A run folder, run file or output location that cannot be used; the message names it."""


def path(run: str, name: str) -> str:
    return os.path.join(run, name)


# ---------------------------------------------------------------------- lock and output location

def _lock_holder(folder: str) -> str:
    """' (pid N: command)' of the process holding the flock on ``folder``, from /proc/locks
    (Linux); '' where that cannot be told."""
    try:
        st = os.stat(folder)
        ident = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
        with open("/proc/locks", encoding="ascii") as f:
            for line in f:
                fields = line.split()
                if "FLOCK" in fields and ident in fields:
                    pid = fields[fields.index(ident) - 1]
                    with open(f"/proc/{pid}/cmdline", "rb") as c:
                        cmd = c.read().replace(b"\0", b" ").decode(errors="replace").strip()
                    return f" (pid {pid}: {cmd[:200]})"
    except (OSError, ValueError, IndexError):
        pass
    return ""


class FolderLock:
    """Exclusive, non-blocking lock on a folder while this process writes into it.

    ``create=True`` makes the folder (and its parents) if needed; a folder made here and still
    empty at release is removed again, so a refused command leaves nothing behind.
    """

    def __init__(self, folder: str, create: bool = False, what: str = "folder", shared: bool = False) -> None:
        self.folder = folder
        self.create = create
        self.what = what
        self.shared = shared  # a shared lock: other shared holders are welcome, an exclusive one is not
        self.created = False
        self._fd: int | None = None

    def acquire(self) -> "FolderLock":
        folder = self.folder
        if os.path.exists(folder) and not os.path.isdir(folder):
            raise RunDirError(f"{folder} exists and is not a folder")
        if not os.path.isdir(folder):
            if not self.create:
                raise RunDirError(f"{folder}: {self.what} not found")
            try:
                os.makedirs(folder)
                self.created = True
            except FileExistsError:
                pass  # made by a concurrent writer; the lock below decides which of us goes on
            except OSError as exc:
                raise RunDirError(f"cannot create {self.what} {folder}: {exc.strerror or exc}") from None
        try:
            fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        except OSError as exc:
            raise RunDirError(f"cannot open {self.what} {folder}: {exc.strerror or exc}") from None
        _flock_or_refuse(fd, fcntl.LOCK_SH if self.shared else fcntl.LOCK_EX,
                         f"{folder} is in use by another process{_lock_holder(folder)} that is writing into it; "
                         "wait until it has finished or choose another folder", f"{self.what} {folder}")
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is None:
            return
        if self.created:
            try:
                os.rmdir(self.folder)  # only succeeds while empty: a refused start leaves nothing
            except OSError:
                pass
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> "FolderLock":
        return self.acquire()

    def __exit__(self, *exc: Any) -> None:
        self.release()


def _flock_or_refuse(fd: int, mode: int, busy: str, what: str) -> None:
    """``flock`` ``fd`` without waiting; a lock held elsewhere is a RunDirError saying ``busy`` (``fd`` is closed
    on any failure)."""
    try:
        fcntl.flock(fd, mode | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(fd)
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise RunDirError(busy) from None
        raise RunDirError(f"cannot lock {what}: {exc.strerror or exc}") from None


class ResultLock:
    """Lock on one result file (``evaluate``'s output) rather than on its folder, so that evaluations
    of different runs can write into one results folder at once.

    The folder gets a shared :class:`FolderLock` (refused while a training or an export holds it), the
    file an exclusive ``flock`` on a lock file next to it, ``.<name>.evallock.tmp``: removed at release,
    and named like ``fileio``'s temp files, so one left by a killed evaluation counts as a temp file
    (ignored, and removed by the next training of that folder)."""

    def __init__(self, file: str, what: str = "output folder") -> None:
        self.file = file
        self.folder_lock = FolderLock(os.path.dirname(os.path.abspath(file)), create=True, what=what, shared=True)
        self.lock_path = os.path.join(self.folder_lock.folder, f".{os.path.basename(file)}.evallock.tmp")
        self._fd: int | None = None

    def acquire(self) -> "ResultLock":
        self.folder_lock.acquire()
        try:
            for _ in range(10):  # the holder removes the lock file as it releases: lock the file the path names
                try:
                    fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0)
                                 | getattr(os, "O_NONBLOCK", 0), 0o644)
                except OSError as exc:
                    raise RunDirError(f"cannot write into {self.folder_lock.what} {self.folder_lock.folder}: "
                                      f"{exc.strerror or exc}") from None
                _flock_or_refuse(fd, fcntl.LOCK_EX,
                                 f"{self.file} is being written by another process{_lock_holder(self.lock_path)}; "
                                 "wait until it has finished or choose another --out", self.file)
                try:
                    same = os.path.samestat(os.fstat(fd), os.stat(self.lock_path))
                except FileNotFoundError:
                    same = False
                if same:
                    self._fd = fd
                    return self
                os.close(fd)
            raise RunDirError(f"cannot lock {self.file}: its lock file keeps changing")
        except BaseException:
            self.folder_lock.release()
            raise

    def release(self) -> None:
        if self._fd is not None:
            try:
                os.unlink(self.lock_path)
            except OSError:
                pass
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None
        self.folder_lock.release()

    def __enter__(self) -> "ResultLock":
        return self.acquire()

    def __exit__(self, *exc: Any) -> None:
        self.release()


def check_writable(folder: str, what: str = "folder") -> None:
    """Refuse a folder this process cannot write into (read-only mount, permissions, full disk),
    by writing a probe file, before any expensive work starts."""
    try:
        fileio.check_writable(folder, what)
    except fileio.NotWritable as exc:
        raise RunDirError(str(exc)) from None


def remove_temp_files(folder: str) -> list[str]:
    """Remove the temp files killed writes left in ``folder`` (call with its lock held)."""
    removed = fileio.temp_files(folder)
    for name in removed:
        os.unlink(name)
    return removed


# ---------------------------------------------------------------------- config

def load_config(run: str) -> Config:
    """The run's ``config.json``, validated; RunDirError naming the file if missing or damaged."""
    file = path(run, CONFIG_FILE)
    try:
        blob = fileio.read_regular(file, MAX_CONFIG_BYTES, "run config")
    except FileNotFoundError:
        raise RunDirError(f"{file}: not a run folder (no {CONFIG_FILE})") from None
    except (fileio.NotRegularFile, fileio.FileTooLarge) as exc:
        raise RunDirError(f"{exc} (damaged run config)") from None
    except OSError as exc:
        raise RunDirError(f"{file}: cannot read ({exc.strerror or exc})") from None
    if not blob.strip():
        raise RunDirError(f"{file}: damaged run config (the file is empty)")
    try:
        data = parse_json(blob.decode("utf-8"))
    except ValueError as exc:  # UnicodeDecodeError and json.JSONDecodeError among them
        raise RunDirError(f"{file}: damaged run config, not valid JSON ({exc})") from None
    try:
        return config_from_dict(data)
    except (ConfigError, TypeError, ValueError, AttributeError) as exc:
        raise RunDirError(f"{file}: damaged run config ({exc})") from None


def write_config(run: str, cfg: Config) -> str:
    text = json.dumps(config_to_dict(cfg), indent=2, sort_keys=True) + "\n"
    return fileio.atomic_write_text(path(run, CONFIG_FILE), text)


# ---------------------------------------------------------------------- metrics

def read_metrics(file: str) -> list[dict[str, Any]]:
    """Rows of ``metrics.jsonl`` (``run_files.parse_metrics``: the last line may be cut short by a kill and is
    then dropped; any other damage raises RunDirError naming the file and the line)."""
    try:
        data = fileio.read_regular(file)
    except fileio.NotRegularFile as exc:
        raise RunDirError(f"{exc} (the metrics log)") from None
    except OSError as exc:
        raise RunDirError(f"{file}: cannot read the metrics log ({exc.strerror or exc})") from None
    return run_files.parse_metrics(data, file, RunDirError)


def _json_safe(value: Any) -> Any:
    """Strict-JSON form of a metrics value: NaN and ±inf (also inside lists) become null."""
    if isinstance(value, (np.generic, np.ndarray)):
        value = value.item() if np.ndim(value) == 0 else value.tolist()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


class MetricsLog:
    """metrics.jsonl, one row per line; on resume drops rows past the checkpoint so the log stays exact."""

    def __init__(self, out_dir: str, resume_iteration: int) -> None:
        self.path = os.path.join(out_dir, METRICS_FILE)
        if os.path.exists(self.path):
            keep = [line for line in read_metrics(self.path) if line.get("iteration", -1) < resume_iteration]
            # NaN / Infinity in a row (Python's json reads them; this logger writes null) are kept as null
            text = "".join(json.dumps(_json_safe(r), allow_nan=False) + "\n" for r in keep)
            fileio.atomic_write_text(self.path, text)  # under the run folder's lock
        self.file = open(self.path, "ab", buffering=0)  # unbuffered: a failed row is cut off at once

    def write(self, row: dict[str, Any]) -> None:
        clean = {k: _json_safe(v) for k, v in row.items()}
        line = memoryview((json.dumps(clean, allow_nan=False) + "\n").encode("utf-8"))
        start = self.file.seek(0, os.SEEK_END)
        try:
            while line:
                line = line[self.file.write(line):]
        except OSError as exc:  # a full disk: no partial row stays behind
            self.file.truncate(start)
            raise _write_error(self.path, exc) from None

    def close(self) -> None:
        self.file.close()


class TensorBoardLog:
    """tb/: every numeric field of a row as a scalar at its env step; on resume purges the steps past the checkpoint."""

    def __init__(self, out_dir: str, resume_step: int) -> None:
        from tensorboardX import SummaryWriter
        from tensorboardX.proto.summary_pb2 import Summary

        self.summary = Summary
        self.folder = os.path.join(out_dir, TB_DIR)
        try:
            self.tb = SummaryWriter(self.folder, purge_step=resume_step + 1 if resume_step else None)
        except OSError as exc:
            raise _write_error(self.folder, exc) from None

    def write(self, row: dict[str, Any]) -> None:
        """The row's scalars as one event (one ``Summary`` of many values): ``add_scalar`` per field made an
        event each, 2.4 ms a row of ~50 fields, ≈ 6 s of the README run's wall in which the devices idle."""
        values = []
        for key, value in row.items():
            value = _json_safe(value)
            if isinstance(value, (int, float)) and not isinstance(value, bool) and key not in ("iteration", "env_steps"):
                values.append(self.summary.Value(tag=f"train/{key}", simple_value=float(value)))
        self.tb._get_file_writer().add_summary(self.summary(value=values), int(row["env_steps"]))
        try:
            self.tb.flush()  # here, not only in tensorboardX's writer thread: a full disk shows in this one
        except OSError as exc:
            raise _write_error(self.folder, exc) from None

    def close(self) -> None:
        try:
            self.tb.close()
        except OSError:
            pass  # TensorBoard's last events on a full disk: metrics.jsonl and the checkpoint hold the run


def _write_error(file: str, exc: OSError) -> OSError:
    """A failed write into the run folder, as ``fileio.OutOfSpace`` when the disk is full."""
    return fileio.out_of_space_error(file, exc) if fileio.is_out_of_space(exc) else exc


def check_metrics_reach(run: str, iteration: int, log_every: int) -> list[dict[str, Any]]:
    """The log's rows before ``iteration`` (a checkpoint's); refuse a log that lost rows the
    checkpoint covers, since a resume would leave that gap in it for good."""
    file = path(run, METRICS_FILE)
    rows = read_metrics(file) if os.path.exists(file) else []
    kept = [r for r in rows if r["iteration"] < iteration]
    last = max((r["iteration"] for r in kept), default=-1)
    if iteration > 0 and last < iteration - log_every:
        state = "is missing" if not os.path.exists(file) else f"ends at iteration {last}"
        raise RunDirError(
            f"{file} {state}, but the checkpoint is at iteration {iteration}: rows are missing (was it truncated, "
            "emptied or deleted?); resuming would leave that gap in the log. Restore the file, or start a new run")
    return kept


# ---------------------------------------------------------------------- checkpoint

def load_checkpoint(run: str, cfg: Config | None = None) -> checkpoint.Checkpoint:
    """The run's checkpoint, verified (and checked against ``cfg`` when given)."""
    ckpt = checkpoint.load(path(run, CHECKPOINT_FILE))
    if cfg is not None:
        checkpoint.check_config(ckpt, cfg)
    return ckpt


def checkpoint_counters(ckpt: checkpoint.Checkpoint) -> dict[str, Any]:
    counters = ckpt.host.get("counters", {}) if isinstance(ckpt.host, dict) else {}
    if not isinstance(counters, dict) or type(counters.get("iteration")) is not int:
        raise checkpoint.CheckpointError(f"{ckpt.path}: incompatible checkpoint host state (no iteration counter)")
    return counters


# ---------------------------------------------------------------------- starting a training

def prepare_training(out: str, cfg: Config, resume: bool) -> str:
    """Check the (locked) run folder for a training with ``cfg`` and say how it starts:
    ``"fresh"``, ``"resume"`` (from the checkpoint) or ``"restart"`` (a run killed before its first
    checkpoint, from the beginning).  Refusals raise RunDirError / CheckpointError and change
    nothing; once all checks pass, stale temp files (and a restarted run's partial logs) go."""
    temps = set(fileio.temp_files(out))
    entries = sorted(n for n in os.listdir(out) if path(out, n) not in temps)
    has_config = os.path.isfile(path(out, CONFIG_FILE))
    has_ckpt = os.path.exists(path(out, CHECKPOINT_FILE))  # a folder there is refused by load_checkpoint
    if not resume:
        if has_config and not has_ckpt and set(entries) <= {CONFIG_FILE, METRICS_FILE, TB_DIR}:
            raise RunDirError(f"{out} holds a run that stopped before its first checkpoint; pass --resume to restart "
                              "it from the beginning with its config.json, or choose a new --out")
        if entries:
            raise RunDirError(f"{out} exists and is not empty; choose a new --out or pass --resume")
        mode = "fresh"
    else:
        check_training_entries(out)
        ckpt = load_checkpoint(out, cfg) if has_ckpt else None
        if has_config:
            saved = load_config(out)
            diffs = checkpoint.config_differences(config_to_dict(saved), config_to_dict(cfg))
            if diffs:
                raise RunDirError(f"{path(out, CONFIG_FILE)}: the run was started with another config ("
                                  + "; ".join(d.replace("checkpoint", "run") for d in diffs[:8])
                                  + "); resume it without config options, or with the same ones")
        if ckpt is not None:
            check_metrics_reach(out, checkpoint_counters(ckpt)["iteration"], cfg.train.log_every)
            mode = "resume"
        elif not entries or (has_config and set(entries) <= {CONFIG_FILE, METRICS_FILE, TB_DIR}):
            mode = "restart"
        elif not has_config:
            raise RunDirError(f"{out}: cannot resume, no {CHECKPOINT_FILE} and no {CONFIG_FILE} (not a run folder?)")
        else:
            others = ", ".join(e for e in entries if e not in (CONFIG_FILE, METRICS_FILE, TB_DIR))
            raise RunDirError(f"{path(out, CHECKPOINT_FILE)}: cannot resume, no checkpoint found, but the folder also "
                              f"holds {others}: the checkpoint was moved or deleted? Restore it or start a new run")
    check_writable(out, "run folder")
    remove_temp_files(out)
    if mode == "restart":
        if os.path.exists(path(out, METRICS_FILE)):
            os.unlink(path(out, METRICS_FILE))
        shutil.rmtree(path(out, TB_DIR), ignore_errors=True)
    return mode


def check_training_entries(out: str) -> None:
    """Refuse a run folder whose training entries (``TRAINING_FILES``) a resume would read or write
    through: a symbolic link (a training writes only inside its run folder, and ``tb/`` or
    ``metrics.jsonl`` are appended to in place, so a link would take its writes elsewhere), or an entry
    of another kind than the training writes (a FIFO or device where a file belongs: its read would
    block or never end)."""
    for name in TRAINING_FILES:
        entry = path(out, name)
        if os.path.islink(entry):
            raise RunDirError(f"{entry} is a symbolic link (to {os.readlink(entry)}): a training writes only inside "
                              f"its run folder; put the {'folder' if name == TB_DIR else 'file'} itself there, or "
                              "start a new run")
        try:
            mode = os.lstat(entry).st_mode
        except FileNotFoundError:
            continue
        if not (stat.S_ISDIR(mode) if name == TB_DIR else stat.S_ISREG(mode)):
            raise RunDirError(f"{entry} is {fileio.file_kind(mode)}, not a {_WHAT[name]}")


# ---------------------------------------------------------------------- evaluation outputs

def evaluation_file(episodes: int, seed: int, max_steps: int | None = None, scenes: str = "mix",
                    variant: str | None = None) -> str:
    """File name of an evaluation in the run folder: by scene set (if not the evaluation mix), episodes
    and seed (and a non-default step cap, and a tag of a changed env: ``evaluate --set``)."""
    kind = "" if scenes == "mix" else f"{scenes}-"
    return (f"{EVALUATION_PREFIX}{kind}{episodes}ep-seed{seed}" + (f"-{max_steps}steps" if max_steps else "")
            + (f"-{variant}" if variant else "") + ".json")


# What makes a file an evaluation result of ``evaluate`` (``fileio.check_result_output``'s ``kind``).
EVALUATION_KIND = {"episodes": None, "overall": None}


def check_replace(file: str, identity: dict[str, Any], force: bool = False) -> None:
    """Refuse to replace ``file`` unless it holds the same evaluation (every ``identity`` entry
    equal: re-running it gives the same numbers), or another (or a damaged) evaluation and ``force``
    is set; a file that is no evaluation result (the run's config, a policy) is never replaced
    (``fileio.check_result_output``)."""
    try:
        fileio.check_result_output(file, identity, EVALUATION_KIND, "evaluation result", force)
    except fileio.NotWritable as exc:
        raise RunDirError(str(exc)) from None


def check_output_file(file: str) -> None:
    """Refuse an output file path that is a FIFO, device, socket or folder (``fileio.check_output_file``)
    as a RunDirError, before anything is locked or written."""
    try:
        fileio.check_output_file(file)
    except fileio.NotWritable as exc:
        raise RunDirError(str(exc)) from None


def write_json(file: str, data: Any) -> str:
    return fileio.atomic_write_json(file, data, sort_keys=True)
