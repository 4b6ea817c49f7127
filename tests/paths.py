"""Where the tests' files are, for test modules at any depth under tests/ (they mirror the package's folders)."""

from __future__ import annotations

import os

TESTS = os.path.dirname(os.path.abspath(__file__))  # tests/: the shared helpers (toy_env, tiny_run, ...) live here
REPO = os.path.dirname(TESTS)
DATA = os.path.join(TESTS, "data")  # recorded files the tests read (old runs, pinned resets, ...)
