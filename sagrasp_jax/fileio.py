"""Atomic file writes: a temp file in the target folder, fsync, then ``os.replace``.

Every file the project writes (checkpoints, policies, MJCF, JSON results, videos) goes
through here, so a crash or a refused input never leaves a half-written file, and the
result gets the usual ``0666 & ~umask`` mode rather than ``mkstemp``'s private 0600.  Also the one
redirect of file descriptor 1 that keeps C libraries' chatter off stdout (``stdout_fd_to``).
No jax import (the deployment runtime uses it).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import sys
import tempfile
from collections.abc import Callable, Iterator
from typing import Any


def _umask_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


# ``atomic_write``'s temp names: ".<file name>.<8 random chars from mkstemp>.tmp<extension>".
_TEMP_NAME = re.compile(r"^\.(?P<target>.+)\.[a-z0-9_]{8}\.tmp(\.[^./]+)?$")


def temp_files(folder: str) -> list[str]:
    """Temp files ``atomic_write`` left in ``folder`` (a process killed between writing and
    renaming leaves one): full paths, sorted.  Only the caller knows no write is in flight."""
    try:
        names = os.listdir(folder)
    except (FileNotFoundError, NotADirectoryError):
        return []
    return sorted(os.path.join(folder, n) for n in names
                  if _TEMP_NAME.match(n) and os.path.isfile(os.path.join(folder, n)))


class NotWritable(OSError):
    """An output location this process cannot write into; the message names it and why."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else "not writable"


class OutOfSpace(NotWritable):
    """A write that found its file system full (ENOSPC, or over quota: EDQUOT)."""


_FULL = (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC))
PROBE_BYTES = 64 * 1024  # what check_writable writes: an empty probe file still fits on a full disk


def is_out_of_space(exc: BaseException) -> bool:
    return isinstance(exc, OSError) and exc.errno in _FULL


def _write_probe(fd: int, size: int) -> None:
    """Write ``size`` bytes to ``fd`` and flush them to the disk (a full disk fails here)."""
    block = b"\0" * min(size, 1 << 16)
    left = size
    while left > 0:
        left -= os.write(fd, block[:left])
    os.fsync(fd)


def check_writable(path: str, what: str = "output folder", is_folder: bool = True, size: int = PROBE_BYTES) -> None:
    """Refuse, before any expensive work, an output this process could not write: ``path`` is
    the folder (or with ``is_folder=False`` the file) to be written.  A probe file of ``size``
    bytes is written, synced and removed in the folder, or in its nearest existing parent when it
    does not exist yet (it would be made there), so read-only mounts, permissions and full disks
    all show (``OutOfSpace`` for the last)."""
    folder = os.path.abspath(path if is_folder else os.path.dirname(os.path.abspath(path)))
    while not os.path.exists(folder):
        folder = os.path.dirname(folder)
    if not os.path.isdir(folder):
        raise NotWritable(f"cannot write {path}: {folder} is a file, not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".write-probe-", dir=folder)
    except OSError as exc:
        kind = OutOfSpace if is_out_of_space(exc) else NotWritable
        raise kind(f"cannot write into {what} {folder}: {exc.strerror or exc}") from None
    try:
        _write_probe(fd, size)
    except OSError as exc:
        kind = OutOfSpace if is_out_of_space(exc) else NotWritable
        raise kind(f"cannot write into {what} {folder}: {exc.strerror or exc} (a {size}-byte test write failed)") from None
    finally:
        os.close(fd)
        os.unlink(probe)


def atomic_write(path: str, write: Callable[[str], None]) -> str:
    """Call ``write(tmp_path)`` (the temp name keeps the extension, for writers that pick the
    format by it), then rename over ``path``; the temp file is removed on any error.
    Out of space (ENOSPC / EDQUOT) anywhere on the way raises ``OutOfSpace`` naming ``path``;
    the old file, if any, is left as it was."""
    folder = os.path.dirname(os.path.abspath(path))
    try:
        os.makedirs(folder, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=f".tmp{os.path.splitext(path)[1]}",
                                   dir=folder)
    except OSError as exc:
        if is_out_of_space(exc):
            raise out_of_space_error(path, exc) from None
        raise
    os.close(fd)
    try:
        write(tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, _umask_mode())
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if is_out_of_space(exc) and not isinstance(exc, OutOfSpace):
            raise out_of_space_error(path, exc) from None
        raise
    return path


def out_of_space_error(path: str, exc: OSError) -> OutOfSpace:
    error = OutOfSpace(f"cannot write {path}: {exc.strerror or 'no space left on device'} (the file was left as it "
                       "was)")
    error.errno = exc.errno
    return error


def atomic_write_bytes(path: str, data: bytes) -> str:
    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            fh.write(data)

    return atomic_write(path, write)


def atomic_write_text(path: str, text: str) -> str:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str, data: Any, indent: int = 2, sort_keys: bool = False,
                      default: Callable[[Any], Any] | None = None, allow_nan: bool = False) -> str:
    """JSON, strict by default (NaN refused: write ``None`` for missing numbers)."""
    text = json.dumps(data, indent=indent, sort_keys=sort_keys, allow_nan=allow_nan, default=default)
    return atomic_write_text(path, text + "\n")


@contextlib.contextmanager
def stdout_fd_to(target: str) -> Iterator[None]:
    """Send file descriptor 1 (C libraries' stdout: PyBullet's banners and URDF warnings) to
    ``"stderr"`` or ``"devnull"`` for the block, so stdout keeps only what the command reports
    (``--json``).  Python's own ``sys.stdout`` is flushed first and lands there too meanwhile."""
    if target not in ("stderr", "devnull"):
        raise ValueError(f"target must be 'stderr' or 'devnull', got {target!r}")
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        if target == "stderr":
            os.dup2(2, 1)
        else:
            with open(os.devnull, "w") as devnull:
                os.dup2(devnull.fileno(), 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
