"""The one CPU XLA flag the package sets, chosen for the installed jaxlib without importing jax.

MJX on XLA's CPU backend compiles and runs much faster with the legacy elemental fusion emitter than
with the "new" fusion emitters (docs/architecture.md, "The jax version and the CPU flag"): MJX's
kinematic chains turn into fusion bodies that the new emitters recompute per use.  How to ask for the
legacy emitter changed with XLA:

* jaxlib < 0.11: the top-level flag ``--xla_cpu_use_fusion_emitters=false``.
* jaxlib >= 0.11: that flag is gone, and XLA aborts the process on an unknown flag
  (``Unknown flag in XLA_FLAGS``); the same switch is the backend option
  ``xla_cpu_disable_new_fusion_emitters``, passed through ``--xla_backend_extra_options``.
  Backend options are a key=value map that XLA does not validate, so a later XLA that drops the
  key ignores it instead of aborting.

The flag is added only where it can help and cannot hurt: the installed jaxlib is one whose flag we
know, the user has not set that flag (or ``--xla_backend_extra_options``) in ``XLA_FLAGS`` already,
and jax will run on the CPU (``JAX_PLATFORMS`` allows ``cpu`` first, or no GPU/TPU plugin is
installed).  Everything else in the user's ``XLA_FLAGS`` is kept.  Standard library only: it runs
in ``sagrasp_jax/__init__.py`` before anything can import jax.
"""

from __future__ import annotations

import importlib.util
import os
import re
from typing import Mapping, NamedTuple

LEGACY_FLAG = "--xla_cpu_use_fusion_emitters=false"
BACKEND_OPTION_FLAG = "--xla_backend_extra_options=xla_cpu_disable_new_fusion_emitters=true"


class FlagRule(NamedTuple):
    """``flag`` is the legacy-emitter switch for jaxlib versions in [since, before)."""

    since: tuple[int, int]
    before: tuple[int, int] | None
    flag: str


RULES: tuple[FlagRule, ...] = (
    FlagRule((0, 4), (0, 11), LEGACY_FLAG),
    FlagRule((0, 11), None, BACKEND_OPTION_FLAG),
)

# jax finds its accelerator plugins as modules of the ``jax_plugins`` namespace package (the CUDA
# plugins install ``jax_plugins/xla_cuda12``, ROCm ``xla_rocm*``); the TPU runtime is ``libtpu``.
ACCELERATOR_PLUGIN_PREFIXES = ("xla_cuda", "xla_rocm", "xla_tpu")
# ... and the kernels' packages beside them (jax-cuda12-plugin is jax_cuda12_plugin), the TPU runtime libtpu
TOP_LEVEL_PLUGINS = ("jax_cuda12_plugin", "jax_cuda13_plugin", "jax_rocm60_plugin", "jax_rocm7_plugin", "libtpu")
VERSION_LINE = re.compile(r"""^_version\s*(?::\s*str)?\s*=\s*["']([^"']+)["']""", re.M)


def parse_version(text: str) -> tuple[int, int]:
    """``"0.11.2"`` -> ``(0, 11)``; ``"0.12.0.1"``, ``"0.10.2.dev20260101"`` likewise."""
    match = re.match(r"(\d+)\.(\d+)", text)
    if not match:
        raise ValueError(f"not a version: {text!r}")
    return int(match.group(1)), int(match.group(2))


def flag_for(jaxlib_version: str) -> str | None:
    """The legacy-emitter flag this jaxlib knows, or None for a version before any rule."""
    version = parse_version(jaxlib_version)
    for rule in RULES:
        if rule.since <= version and (rule.before is None or version < rule.before):
            return rule.flag
    return None


def installed_jaxlib_version() -> str | None:
    """jaxlib's version from its ``version.py`` (``_version = "0.10.2"``), found without importing it
    (``importlib.metadata`` alone would add ~0.1 s to every command's start, the robot side's too)."""
    try:
        spec = importlib.util.find_spec("jaxlib")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    for folder in spec.submodule_search_locations:
        try:
            with open(os.path.join(folder, "version.py"), encoding="utf-8") as handle:
                match = VERSION_LINE.search(handle.read())
        except OSError:
            continue
        if match:
            return match.group(1)
    return None


def installed_accelerator_plugins() -> tuple[str, ...]:
    """The accelerator plugins jax will find (``jax_plugins`` modules, the CUDA / ROCm kernels, ``libtpu``)."""
    found: list[str] = []
    try:
        spec = importlib.util.find_spec("jax_plugins")
        folders = list(spec.submodule_search_locations or []) if spec is not None else []
    except (ImportError, ValueError):
        folders = []
    for folder in folders:
        try:
            names = os.listdir(folder)
        except OSError:
            continue
        found += sorted(n for n in names if n.startswith(ACCELERATOR_PLUGIN_PREFIXES))
    for module in TOP_LEVEL_PLUGINS:
        try:
            if importlib.util.find_spec(module) is not None:
                found.append(module)
        except (ImportError, ValueError):
            pass
    return tuple(found)


def runs_on_cpu(environ: Mapping[str, str], plugins: tuple[str, ...]) -> bool:
    """Whether jax's default backend will be the CPU: ``JAX_PLATFORMS`` names ``cpu`` first, or it is
    unset and no accelerator plugin is installed (``plugins``: the installed ones)."""
    platforms = environ.get("JAX_PLATFORMS", "").strip().lower()
    if platforms:
        return platforms.split(",")[0].strip() == "cpu"
    return not plugins


def choose_flags(environ: Mapping[str, str], jaxlib_version: str | None, plugins: tuple[str, ...]) -> str | None:
    """The ``XLA_FLAGS`` value to set, or None to leave the environment as it is."""
    if jaxlib_version is None or not runs_on_cpu(environ, plugins):
        return None
    flag = flag_for(jaxlib_version)
    if flag is None:
        return None
    current = environ.get("XLA_FLAGS", "")
    name = flag.split("=", 1)[0]
    if name in current or "xla_cpu_use_fusion_emitters" in current or "xla_cpu_disable_new_fusion_emitters" in current:
        return None  # the user chose this switch (or the backend options) already
    return f"{current} {flag}".strip()


def apply(environ: "os._Environ[str] | dict[str, str]" = os.environ) -> str | None:
    """Add the installed jaxlib's flag to ``environ['XLA_FLAGS']`` where ``choose_flags`` says so;
    returns the flag value set, or None."""
    value = choose_flags(environ, installed_jaxlib_version(), installed_accelerator_plugins())
    if value is not None:
        environ["XLA_FLAGS"] = value
    return value


# Per program, the other way (config key ``train.cpu_fusion_emitters``): the trainer's programs of the lagged and
# kinematic env run 15-20 % faster per cycle on 2 cores with XLA's new fusion emitters (docs/results-archive.md
# §25), which MJX's physics step does not; a compile option overrides the process's flag for one program.  Where
# the switch is ``LEGACY_FLAG`` (RULES) it is a DebugOptions field a compile option can set; where it is the
# backend-options map entry, a compile option cannot ("is not a valid message value"), so the process's stays.
NEW_EMITTERS_OPTION: dict[str, bool] = {"xla_cpu_use_fusion_emitters": True}


def emitter_options(choice: str, backend: str, jaxlib_version: str | None) -> tuple[dict[str, bool], str | None]:
    """The XLA compile options that give one program ``choice``'s CPU fusion emitters ("legacy": the
    process's, nothing to add; "new"), and a note for the log where the choice cannot be honoured."""
    if choice not in ("legacy", "new"):
        raise ValueError(f"cpu fusion emitters {choice!r}: valid are legacy, new")
    if choice == "legacy" or backend != "cpu":
        return {}, None
    if jaxlib_version is not None and flag_for(jaxlib_version) != LEGACY_FLAG:
        return {}, (f"train.cpu_fusion_emitters=new: jaxlib {jaxlib_version} cannot choose the emitter per program; "
                    "the trainer compiles with the process's (XLA_FLAGS)")
    return dict(NEW_EMITTERS_OPTION), None
