"""What the commands share on the command line: short refusals of a mistyped option, and Ctrl-C.

``Parser`` is ``argparse.ArgumentParser`` with one-line refusals: an option it does not know is named with the
nearest one it does (``unknown option --polcy (did you mean --policy?)``), and no refusal prints the usage (the
deploy command's is twenty lines that hide the one that matters); exit status 2 as argparse's.

Ctrl-C (SIGINT) ends a command with one line on stderr saying what was stopped and what was kept, exit status
130, no traceback, nothing partial left behind.  Two ways, by what runs when it comes:

* ``at_safe_points``: Ctrl-C only records that it was pressed, and the code stops at its next safe point
  (``check``: before each command to the robot, between scenes), where ``Interrupted`` unwinds through the
  robot session's own ``with`` (the AUBO's servo mode is left, its session closed; the twin disconnected).
  No library sees a KeyboardInterrupt in the middle of its work: one raised inside a garbage-collector
  callback (jax registers one) is swallowed and the command runs on.
* ``exit_on_interrupt``: for work with no safe point inside (jax's tracing, XLA's compile, a jitted
  evaluation).  A KeyboardInterrupt there is swallowed by a gc callback or ends the process in SIGSEGV at
  exit, with XLA's compile threads still running; instead a thread woken by the signal itself
  (``signal.set_wakeup_fd``: within milliseconds, even while XLA compiles) runs the block's cleanup, prints
  the line and leaves with ``os._exit(130)``, unwinding nothing.  ``deferred`` holds the exit back while a
  block that must finish runs (a result's write), and the line is made when the exit comes, so it can say
  what was written.

No jax, no NumPy: the robot side uses it.
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import os
import signal
import sys
import threading
import typing
from collections.abc import Callable, Iterator, Sequence
from typing import Any

INTERRUPTED = 130  # the exit status of a command stopped by Ctrl-C (128 + SIGINT), as a shell reports one


# ---------------------------------------------------------------------------------------------- argparse

def unknown_option_message(option: str, known: Sequence[str]) -> str:
    """``unknown option --polcy (did you mean --policy?)``, or without a suggestion when none is close."""
    near = difflib.get_close_matches(option, list(known), n=1, cutoff=0.6)
    return f"unknown option {option}" + (f" (did you mean {near[0]}?)" if near else "; --help lists the options")


class Parser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` with one-line refusals (module docstring).  Options are checked before
    argparse parses, so a mistyped one is named even where argparse would first complain that a required
    option is missing (``--polcy P`` leaves ``--policy`` missing)."""

    def parse_known_args(self, args: Sequence[str] | None = None,  # type: ignore[override]
                         namespace: argparse.Namespace | None = None) -> tuple[argparse.Namespace, list[str]]:
        tokens = list(sys.argv[1:] if args is None else args)
        self.check_options(tokens)
        return super().parse_known_args(tokens, namespace)

    def long_options(self) -> list[str]:
        return [s for action in self._actions for s in action.option_strings if s.startswith("--")]

    def check_options(self, tokens: Sequence[str]) -> None:
        """Refuse the first ``--word`` token that names no option (nor, with ``allow_abbrev``, starts one)."""
        known = self.long_options()
        for token in tokens:
            if token == "--":
                break
            if not token.startswith("--") or len(token) == 2:
                continue
            name = token.split("=", 1)[0]
            if name in known or (self.allow_abbrev and any(k.startswith(name) for k in known)):
                continue  # an abbreviation: argparse takes it, or names the options it could be
            self.error(unknown_option_message(name, known))

    def error(self, message: str) -> typing.NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


# ---------------------------------------------------------------------------------------------- Ctrl-C

class Interrupted(KeyboardInterrupt):
    """Ctrl-C, raised at a safe point (``check``) while ``at_safe_points`` is on; ``done`` may say how far the
    work got (set by whoever knows, e.g. scenes finished)."""

    done: Any = None


_pressed = threading.Event()


def pressed() -> bool:
    """Whether Ctrl-C was pressed since ``at_safe_points`` began."""
    return _pressed.is_set()


def check() -> None:
    """A safe point: raise ``Interrupted`` if Ctrl-C was pressed (a no-op outside ``at_safe_points``)."""
    if _pressed.is_set():
        raise Interrupted()


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextlib.contextmanager
def at_safe_points() -> Iterator[None]:
    """While the block runs, Ctrl-C sets a flag that ``check`` turns into ``Interrupted`` (module docstring).
    Outside the main thread (where no signal handler can be set) it changes nothing."""
    if not _main_thread():
        yield
        return
    _pressed.clear()
    previous = signal.signal(signal.SIGINT, lambda signum, frame: _pressed.set())
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _pressed.clear()


def ignore_interrupts() -> None:
    """For worker processes: Ctrl-C at the terminal reaches the whole process group, and the parent stops
    its workers itself (``Pool.terminate``); a worker must not die of it with a traceback of its own."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


class _ExitAtOnce:
    def __init__(self, message: Callable[[], str], cleanup: Callable[[], None] | None) -> None:
        self.message, self.cleanup = message, cleanup
        self.lock = threading.RLock()
        self.deferred = 0
        self.pending = False

    def fire(self) -> None:
        with self.lock:
            if self.deferred:
                self.pending = True
                return
            self.exit()

    def exit(self) -> typing.NoReturn:
        try:
            if self.cleanup is not None:
                self.cleanup()
            line = self.message()
        except BaseException as exc:  # noqa: BLE001 - the exit must come whatever the cleanup meets
            line = f"interrupted (Ctrl-C); cleaning up failed: {exc}"
        with contextlib.suppress(BaseException):
            sys.stdout.flush()
        with contextlib.suppress(OSError):
            os.write(2, (line.rstrip("\n") + "\n").encode("utf-8", "replace"))
        os._exit(INTERRUPTED)


_exit_at_once: _ExitAtOnce | None = None


@contextlib.contextmanager
def exit_on_interrupt(message: Callable[[], str], cleanup: Callable[[], None] | None = None) -> Iterator[None]:
    """While the block runs, Ctrl-C calls ``cleanup()`` (remove what would be left partial), prints
    ``message()`` as one line on stderr and ends the process with status 130 at once (module docstring).
    Outside the main thread it changes nothing."""
    global _exit_at_once
    if not _main_thread() or _exit_at_once is not None:
        yield
        return
    state = _ExitAtOnce(message, cleanup)
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)

    def watch() -> None:
        while True:
            data = os.read(read_fd, 64)
            if not data or 0 in data:  # 0: the block ended
                return
            if signal.SIGINT in data:
                state.fire()

    previous = signal.signal(signal.SIGINT, lambda signum, frame: state.fire())
    previous_fd = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    watcher = threading.Thread(target=watch, name="sigint-watcher", daemon=True)
    watcher.start()
    _exit_at_once = state
    try:
        yield
    finally:
        with state.lock:  # a Ctrl-C from here on is the default's again
            _exit_at_once = None
            signal.set_wakeup_fd(previous_fd)
            signal.signal(signal.SIGINT, previous)
        os.write(write_fd, b"\0")
        watcher.join()
        os.close(read_fd)
        os.close(write_fd)


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Inside ``exit_on_interrupt``: a Ctrl-C during the block ends the process only when the block is done
    (e.g. a result's write: written whole, and the line says so).  Elsewhere it changes nothing."""
    state = _exit_at_once
    if state is None:
        yield
        return
    with state.lock:
        state.deferred += 1
    try:
        yield
    finally:
        with state.lock:
            state.deferred -= 1
            if not state.deferred and state.pending:
                state.exit()


def interrupted_line(stopped: str, kept: str) -> str:
    """The one line a command prints when Ctrl-C stopped it."""
    return f"interrupted (Ctrl-C): {stopped}; {kept}"
