"""Optional parts of the install and the one message for a missing one.

The core install (``pip install .`` or the wheel) needs only NumPy: the policy runtime, export
readers, calibration, safety and the deployment loop.  Everything else is an extra; a
command that needs one it lacks stops with exit status 2 and names the extra in the syntax
a wheel user types (``pip install "sagrasp_jax[twin]"``), never a traceback.
"""

from __future__ import annotations

import importlib.abc
import importlib.util
import sys
from typing import Any, NoReturn, Sequence

# extra -> the import names it provides that the package uses (pyproject.toml's optional-dependencies,
# with BUNDLED; tests/base/test_extras.py checks they agree).  A missing package is hinted with the first extra
# listing it.
EXTRAS: dict[str, tuple[str, ...]] = {
    "train": ("jax", "mujoco", "brax", "flax", "optax", "tensorboardX", "tqdm"),
    "twin": ("pybullet",),
    "reference": ("pybullet", "gymnasium"),
    "export": ("onnx", "onnxruntime"),
    "render": ("mujoco", "imageio", "imageio_ffmpeg"),
    "plots": ("matplotlib",),
    "warp": ("warp",),
    "playground": ("mujoco_playground",),
    "yolo": ("ultralytics",),  # the YOLO option of the perception (sagrasp_jax/deploy/yolo.py)
    # hardware adapters (sagrasp_jax/deploy/aubo.py, cameras.py): the vendors' own SDKs
    "aubo": ("pyaubo_sdk",),
    "mecheye": ("mecheye",),
    "realsense": ("pyrealsense2",),
}

# extra -> the other extras whose packages its install also brings: ``train`` carries ``export``'s, so that
# the command after a training, the export (ONNX included), runs as written.
BUNDLED: dict[str, tuple[str, ...]] = {"train": ("export",)}


class MissingExtra(ImportError):
    """An optional part of the install is absent; the message says which extra brings it."""

    def __init__(self, extras: Sequence[str], missing: Sequence[str], what: str) -> None:
        self.extras, self.missing = tuple(extras), tuple(missing)
        verb = "is" if len(self.missing) == 1 else "are"
        super().__init__(f"{what} needs {_and(self.missing)}, which {verb} not installed: {install_hint(self.extras)}")


def _and(names: Sequence[str]) -> str:
    """'a', 'a and b', 'a, b and c'."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"


def install_hint(extras: Sequence[str]) -> str:
    return f'pip install "sagrasp_jax[{",".join(extras)}]"'


def _absent(name: str) -> bool:
    if name in sys.modules:
        return sys.modules[name] is None
    try:
        return importlib.util.find_spec(name) is None
    except (ImportError, ValueError):
        return True


def missing(*extras: str) -> list[str]:
    """Import names of ``extras`` that are not installed."""
    names = dict.fromkeys(n for e in extras for n in EXTRAS[e])
    return [n for n in names if _absent(n)]


def require(*extras: str, what: str) -> None:
    """Raise ``MissingExtra`` unless every package of ``extras`` is installed."""
    absent = missing(*extras)
    if absent:
        raise MissingExtra(extras, absent, what)


def exit_missing(exc: MissingExtra, prog: str) -> NoReturn:
    """The command-line ending for a missing extra: one line on stderr, exit status 2."""
    print(f"{prog}: error: {exc}", file=sys.stderr)
    raise SystemExit(2)


def require_cli(*extras: str, prog: str) -> None:
    """For an entry point, before its imports: exit 2 naming the extras when any is absent."""
    try:
        require(*extras, what=prog)
    except MissingExtra as exc:
        exit_missing(exc, prog)


def extra_providing(package: str) -> str | None:
    """The extra whose install brings the import name ``package`` (its root), the first in ``EXTRAS`` order."""
    root = package.partition(".")[0]
    return next((extra for extra, names in EXTRAS.items() if root in names), None)


class WrappingLoader(importlib.abc.Loader):
    """A loader that runs another one's module its own way (``exec_module``) and passes on the rest."""

    def __init__(self, loader: Any) -> None:
        self._loader = loader

    def create_module(self, spec: Any) -> Any:
        return self._loader.create_module(spec)

    def __getattr__(self, name: str) -> Any:  # get_source, get_resource_reader, ... for tools and resources
        return getattr(self._loader, name)


class _HintingLoader(WrappingLoader):
    """Runs a ``sagrasp_jax`` module; an absent optional package it imports becomes ``MissingExtra``."""

    def exec_module(self, module: Any) -> None:
        try:
            self._loader.exec_module(module)
        except ModuleNotFoundError as exc:
            extra = extra_providing(exc.name or "")
            if extra is None:
                raise
            absent = missing(extra) or [exc.name.partition(".")[0]]
            raise MissingExtra((extra,), absent, module.__name__) from None  # the hint says it all


class ImportHints(importlib.abc.MetaPathFinder):
    """Finds ``sagrasp_jax.*`` modules through the other finders and wraps their loaders (``_HintingLoader``)."""

    def find_spec(self, fullname: str, path: Any, target: Any = None) -> Any:
        if not fullname.startswith("sagrasp_jax."):
            return None
        for finder in sys.meta_path:
            if finder is self or isinstance(finder, ImportHints) or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                if spec.loader is not None and hasattr(spec.loader, "exec_module"):
                    spec.loader = _HintingLoader(spec.loader)
                return spec
        return None


def install_import_hints() -> None:
    """Put :class:`ImportHints` first on ``sys.meta_path`` (once)."""
    if not any(isinstance(f, ImportHints) for f in sys.meta_path):
        sys.meta_path.insert(0, ImportHints())
