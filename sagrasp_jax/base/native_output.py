"""Output that C libraries write straight to file descriptors 1 and 2, held off the terminal.

PyBullet prints its banner and warnings with the C library's ``printf``, and Mech-Eye API writes its logger's
lines and the shell's to the terminal: either would break a command's ``--json`` on stdout or its one-line
error.  ``held_native_output`` runs a block with descriptors 1 and 2 going to a temporary file and hands back
what was written there; the callers decide what of it reaches stderr (``reference.bullet``,
``deploy.cameras``).  Python's own output in the block goes the same way.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
import tempfile
from typing import Iterator


def flush_c_stdio() -> None:
    """Flush the C library's stdio buffers, so they land where fd 1 and 2 point now."""
    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError, TypeError):  # no C library to reach (not POSIX): nothing buffered there to lose
        pass


def _flush_all() -> None:
    for stream in (sys.stdout, sys.stderr):
        if stream is not None:
            stream.flush()
    flush_c_stdio()


@contextlib.contextmanager
def held_native_output() -> Iterator[list[str]]:
    """Descriptors 1 and 2 go to a temporary file for the block; the list yielded receives its text (one item)
    once the block has ended, normally or not.  Where the descriptors cannot be duplicated (none open) the block
    runs as it is and the list stays empty."""
    held: list[str] = []
    _flush_all()
    try:
        saved = os.dup(1), os.dup(2)
    except OSError:  # no such descriptors to redirect: nothing of ours to keep clean
        yield held
        return
    with tempfile.TemporaryFile() as captured:
        try:
            os.dup2(captured.fileno(), 1)
            os.dup2(captured.fileno(), 2)
            yield held
        finally:
            _flush_all()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
            captured.seek(0)
            held.append(captured.read().decode("utf-8", errors="replace"))
