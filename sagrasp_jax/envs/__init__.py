"""The JAX envs: the MJX grasp env (`grasp_env`: kinematic, dynamic and lagged control), the training
auto-reset (`auto_reset`), and the brax adapter with the registry of tasks by name (`brax_adapter`).

``sagrasp_jax.envs.load("grasp-kinematic")`` and the adapter's other names (``ENVS``, ``BraxGraspEnv``,
``register_with_brax``, ...) are read from `brax_adapter` on first use, so importing `grasp_env` alone does
not import brax.  Imports `base` and `task`.
"""

from __future__ import annotations

import importlib
from typing import Any


_SUBMODULES = ("grasp_env", "auto_reset", "brax_adapter")


def __getattr__(name: str) -> Any:
    if name.startswith("__") or name in _SUBMODULES:  # a submodule not imported yet: the import system's to find
        raise AttributeError(name)
    brax_adapter = importlib.import_module("sagrasp_jax.envs.brax_adapter")
    try:
        return getattr(brax_adapter, name)
    except AttributeError:
        raise AttributeError(f"module 'sagrasp_jax.envs' has no attribute {name!r}") from None
