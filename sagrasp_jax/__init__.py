"""sagrasp_jax: the SA-PPO obstacle-aware grasping task of Li et al. (Sensors 2025) in MuJoCo-MJX / JAX.

Importing the package adds to ``XLA_FLAGS`` the switch to XLA's legacy CPU fusion emitter that the
installed jaxlib knows (``base/xla_flags``: MJX on CPU compiles and runs faster with it; jaxlib 0.11
renamed it and aborts on the old name), where jax will run on the CPU and the user has not set it,
and points jax's persistent compilation cache at ``~/.cache/sagrasp_jax/jax`` unless
``JAX_COMPILATION_CACHE_DIR`` is set.  Neither imports jax.

It also silences one known line of noise: when the optional NVIDIA Warp backend is not
installed, ``mujoco.mjx.warp`` prints "Failed to import warp: No module named 'warp'" and
"Failed to import mujoco_warp: No module named 'warp'" (to stdout, on every import of
mujoco, brax or our env).  Users read it as an error; it is the normal state on CPU.  A
one-shot import hook runs that module with its prints captured and passes on every line
except exactly those two, so a broken Warp install (any other message) still shows.
"""

from __future__ import annotations

import contextlib
import importlib.abc
import importlib.util
import io
import os
import re
import sys
from typing import Any

__version__ = "0.1.0"

from sagrasp_jax.base import xla_flags as _xla_flags  # noqa: E402  (stdlib only)

_xla_flags.apply(os.environ)
os.environ.setdefault(
    "JAX_COMPILATION_CACHE_DIR", os.path.join(os.path.expanduser("~"), ".cache", "sagrasp_jax", "jax")
)
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1")


from sagrasp_jax.base import extras as _extras  # noqa: E402  (stdlib only)

_WARP_MODULE = "mujoco.mjx.warp"
_WARP_ABSENT = re.compile(r"^Failed to import (warp|mujoco_warp): No module named 'warp'$")


def filter_warp_noise(text: str) -> str:
    """``text`` without the two lines mjx prints when the optional Warp backend is absent."""
    return "".join(line for line in text.splitlines(keepends=True) if not _WARP_ABSENT.match(line.rstrip("\n")))


class _QuietLoader(_extras.WrappingLoader):
    """Runs ``mujoco.mjx.warp`` with stdout captured, then re-prints all but the known noise."""

    def exec_module(self, module: Any) -> None:
        buffer = io.StringIO()
        try:
            with contextlib.redirect_stdout(buffer):
                self._loader.exec_module(module)
        finally:
            sys.stdout.write(filter_warp_noise(buffer.getvalue()))


class _QuietWarpImport(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname: str, path: Any, target: Any = None) -> Any:
        if fullname != _WARP_MODULE:
            return None
        sys.meta_path.remove(self)  # one shot, and no recursion through the lookup below
        spec = importlib.util.find_spec(fullname)
        if spec is not None and spec.loader is not None:
            spec.loader = _QuietLoader(spec.loader)
        return spec


if _WARP_MODULE not in sys.modules and not any(isinstance(f, _QuietWarpImport) for f in sys.meta_path):
    sys.meta_path.insert(0, _QuietWarpImport())

# A module of the package that meets an absent optional package raises extras.MissingExtra naming the
# extra to install (``pip install "sagrasp_jax[train]"``), not a bare ModuleNotFoundError.
_extras.install_import_hints()


# Modules that moved into the layer folders (docs/architecture.md) still import at their old paths,
# with a DeprecationWarning naming the new one: ``import sagrasp_jax.ppo`` (or
# ``sagrasp_jax.training.ppo``) is ``sagrasp_jax.training.agents.ppo.ppo``.
MOVED_MODULES = {
    "fileio": "base.fileio", "assets": "base.assets", "extras": "base.extras", "run_files": "base.run_files",
    "config": "task.config", "robot": "task.robot", "scene": "task.scene", "shapes": "task.shapes",
    "geometry": "task.geometry", "collision": "task.collision", "control": "task.control",
    "reward": "task.reward", "observation": "task.observation", "episode": "task.episode",
    "sampling": "task.sampling", "scripted": "task.scripted", "runtime": "task.policy_file",
    "env": "envs.grasp_env", "wrappers": "envs.auto_reset",
    "actor_critic": "training.agents.ppo.actor_critic", "losses": "training.agents.ppo.losses",
    "rollout": "training.agents.ppo.rollout", "ppo": "training.agents.ppo.ppo",
    "sharding": "training.sharding", "lr_schedule": "training.lr_schedule", "sa_schedule": "training.sa_schedule",
    "metrics_window": "training.metrics_window", "checkpoint": "training.checkpoint",
    "distributed": "training.distributed", "run_dir": "training.run_dir", "policy_eval": "training.fixed_seed_eval",
    "physical": "reference.grasp_check",
    # PPO's maths moved from the flat training/ into training/agents/ppo/, as brax keeps it (issue 56)
    "training.actor_critic": "training.agents.ppo.actor_critic", "training.losses": "training.agents.ppo.losses",
    "training.rollout": "training.agents.ppo.rollout", "training.ppo": "training.agents.ppo.ppo",
}


class _MovedModuleLoader(importlib.abc.Loader):
    """Gives the module at its new path for an old one (the same module object, so patches agree)."""

    def __init__(self, new_name: str) -> None:
        self.new_name = new_name

    def create_module(self, spec: Any) -> Any:
        import importlib
        import warnings

        warnings.warn(f"{spec.name} moved to {self.new_name}; import it from there",
                      DeprecationWarning, stacklevel=3)
        return importlib.import_module(self.new_name)

    def exec_module(self, module: Any) -> None:
        pass


class _MovedModules(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname: str, path: Any, target: Any = None) -> Any:
        head, _, tail = fullname.partition(".")
        if head != "sagrasp_jax" or tail not in MOVED_MODULES:
            return None
        return importlib.util.spec_from_loader(fullname, _MovedModuleLoader(f"sagrasp_jax.{MOVED_MODULES[tail]}"))


if not any(isinstance(f, _MovedModules) for f in sys.meta_path):
    sys.meta_path.insert(0, _MovedModules())
