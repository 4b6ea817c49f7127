"""Atomic file writes: a temp file in the target folder, fsync, then ``os.replace``.

Every file the project writes (checkpoints, policies, MJCF, JSON results, videos) goes
through here, so a crash or a refused input never leaves a half-written file, and the
result gets the usual ``0666 & ~umask`` mode rather than ``mkstemp``'s private 0600. 
(PyBullet's C-level output is kept off the terminal by ``reference/bullet.native_output_filtered``.)

Files that are not files: every input the commands read goes through ``read_regular`` (or
``check_regular`` before a library opens it), which refuses a FIFO, device, socket or folder before
it is opened (a FIFO's open waits for a writer, ``/dev/zero`` never ends) and a file over the
reader's size cap before it is read; every output path goes through ``check_output_file`` (also
inside ``atomic_write`` and ``check_writable``): a regular file or absent, never a device node
the rename would replace.  No jax import (the deployment runtime uses it).
"""

from __future__ import annotations

import errno
import json
import os
import re
import stat
import tempfile
from collections.abc import Callable
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
    all show (``OutOfSpace`` for the last); a file ``path`` must be a regular file or absent
    (``check_output_file``).  An empty path (``--out ""``) is refused naming ``what``: it names no file or
    folder, and the write would fail only after the work."""
    if not os.fspath(path).strip():
        raise NotWritable(f"the {what} is an empty path {os.fspath(path)!r}: name the {'folder' if is_folder else 'file'} "
                          "to write")
    if not is_folder:
        check_output_file(path)
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
    the old file, if any, is left as it was.  A ``path`` that is a FIFO, device, socket or folder is
    refused (``NotWritable``) before anything is written."""
    check_output_file(path)
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


# ---------------------------------------------------------------------- files that are not files

class NotRegularFile(OSError):
    """A path that exists but is no regular file (a FIFO, device, socket or folder) where a file is
    read; ``kind`` says what it is ("a FIFO (named pipe)", "a folder", ...)."""

    def __init__(self, path: str, kind: str) -> None:
        super().__init__(f"{path} is {kind}, not a regular file")
        self.path, self.kind = path, kind

    def __str__(self) -> str:
        return str(self.args[0])


class FileTooLarge(OSError):
    """An input over its reader's size cap, refused before it is read."""

    def __str__(self) -> str:
        return str(self.args[0])


_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def file_kind(mode: int) -> str:
    """What a ``st_mode`` is, in words ("a regular file", "a FIFO (named pipe)", "a character device", ...)."""
    if stat.S_ISREG(mode):
        return "a regular file"
    return next((kind for test, kind in _KINDS if test(mode)), "not a regular file")


def check_regular(path: str) -> os.stat_result:
    """``os.stat`` of an input that must be a regular file (a symlink counts as what it points to):
    ``NotRegularFile`` for a FIFO, device, socket or folder, without opening it.  A missing file raises
    ``FileNotFoundError`` as ``os.stat`` does."""
    st = os.stat(path)
    if not stat.S_ISREG(st.st_mode):
        raise NotRegularFile(path, file_kind(st.st_mode))
    return st


def read_regular(path: str, max_bytes: int | None = None, what: str = "file") -> bytes:
    """The bytes of a regular file, in bounded time and memory: refused (``NotRegularFile``) before it
    is opened when it is a FIFO, device, socket or folder, and (``FileTooLarge``) before it is read
    when over ``max_bytes``.  The file is opened non-blocking and checked again on its descriptor (a
    path swapped meanwhile), and no more than ``max_bytes`` are read even from a file that grows."""
    check_regular(path)
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise NotRegularFile(path, file_kind(st.st_mode))
        if max_bytes is not None and st.st_size > max_bytes:
            raise FileTooLarge(f"{path}: {st.st_size} bytes, over the {max_bytes} bytes a {what} may hold; not read")
        limit = max_bytes + 1 if max_bytes is not None else None
        chunks, size = [], 0
        while limit is None or size < limit:
            chunk = os.read(fd, 1 << 20 if limit is None else min(1 << 20, limit - size))
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
        if max_bytes is not None and size > max_bytes:
            raise FileTooLarge(f"{path}: over the {max_bytes} bytes a {what} may hold (it grew while read); not read")
        return b"".join(chunks)
    finally:
        os.close(fd)


def read_input(path: str, max_bytes: int, what: str, error: type[Exception], not_found: str | None = None,
               too_large_note: str = "") -> bytes:
    """``read_regular`` for a command's input file, its refusals as ``error`` naming the file: "PATH is a FIFO, not
    a WHAT", the size bound (with ``too_large_note`` in brackets), ``not_found`` (default "PATH: WHAT not found")
    and "cannot read the WHAT".  The policy, calibration and capture readers."""
    try:
        return read_regular(path, max_bytes, what)
    except NotRegularFile as exc:
        raise error(f"{path} is {exc.kind}, not a {what}") from None
    except FileTooLarge as exc:
        raise error(f"{exc} ({too_large_note})" if too_large_note else str(exc)) from None
    except FileNotFoundError:
        raise error(not_found or f"{path}: {what} not found") from None
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None


def check_output_file(path: str) -> None:
    """Refuse (``NotWritable``) an output file path that exists and is not a regular file: a FIFO,
    device, socket or folder (a symlink counts as what it points to).  The rename of ``atomic_write``
    would replace a device node by a regular file, and reading an earlier result there would block on
    a FIFO.  An absent path (or a dangling symlink) is fine: it will be created."""
    try:
        st = os.stat(path)
    except OSError:
        return  # absent, or a parent that is no folder: check_writable / the write itself says so
    if not stat.S_ISREG(st.st_mode):
        raise NotWritable(f"cannot write {path}: it is {file_kind(st.st_mode)}; an output must be a regular file "
                          "or absent")


MAX_RESULT_BYTES = 64 << 20  # an earlier result read back to compare (a few kB; bounded like every input)


class ResultRefused(NotWritable):
    """An output path that names an existing file this command must not replace (see ``check_result_output``)."""


def check_result_output(path: str, identity: dict[str, Any], kind: dict[str, Any], what: str,
                        force: bool = False) -> None:
    """Refuse (``ResultRefused``) to write a result over an existing file unless that file is a result of the
    same kind holding the same result (every ``identity`` entry equal: writing it again changes nothing), or
    holds another result of this kind and ``force`` is set.

    A file is a result of this kind when it is a JSON object with every key of ``kind`` (a value other than
    None must match too: ``{"backend": "twin", "summary": None}``).  Anything else that is readable — a run's
    ``config.json``, another kind of result, a binary file — is refused even with ``force``: ``--force``
    replaces a result, never another file.  A result that is damaged (text that is no JSON object, or
    cut short) is replaced only with ``force``.  A FIFO, device or folder is refused as an output
    (``check_output_file``).  ``what`` names the kind in the messages ("twin evaluation result")."""
    check_output_file(path)
    if not os.path.exists(path):
        return
    try:
        data = read_regular(path, MAX_RESULT_BYTES, what)
    except FileTooLarge:
        raise ResultRefused(f"{path} exists and is over {MAX_RESULT_BYTES} bytes, not a {what}; --force replaces "
                            "only a result: choose another --out") from None
    except OSError as exc:
        raise ResultRefused(f"cannot read {path} to see what it holds ({exc}); choose another --out") from None
    try:
        text = data.decode("utf-8")
        if "\0" in text:
            raise UnicodeDecodeError("utf-8", data, 0, 1, "a NUL byte")
    except UnicodeDecodeError:
        raise ResultRefused(f"{path} exists and holds binary data, not a {what}; --force replaces only a result: "
                            "choose another --out") from None
    try:
        old, _ = json.JSONDecoder().raw_decode(text.lstrip())
        readable = isinstance(old, dict)
    except (ValueError, RecursionError):  # cut short or garbled: maybe a damaged result
        old, readable = None, False
    if not readable:
        if force:
            return
        raise ResultRefused(f"{path} exists and is not a readable {what}; pass --force to replace it, or choose "
                            "another --out")
    mismatch = [k for k, v in kind.items() if k not in old or (v is not None and old[k] != v)]
    if mismatch:
        raise ResultRefused(f"{path} exists and is not a {what} (it lacks the {', '.join(repr(k) for k in mismatch)} "
                            f"{'entry' if len(mismatch) == 1 else 'entries'} one has); --force replaces only a result: "
                            "choose another --out")
    diffs = [f"{key} {old.get(key)!r} -> {value!r}" for key, value in identity.items() if old.get(key) != value]
    if diffs and not force:
        raise ResultRefused(f"{path} holds a different result ({'; '.join(diffs)}); pass --force to replace it, or "
                            "choose another --out")


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
