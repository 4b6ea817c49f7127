"""Optional parts of the install and the one message for a missing one.

The core install (``pip install sagrasp_jax``) needs only NumPy: the policy runtime, export
readers, calibration, safety and the deployment loop.  Everything else is an extra; a
command that needs one it lacks stops with exit status 2 and names the extra in the syntax
a wheel user types (``pip install "sagrasp_jax[twin]"``), never a traceback.
"""

from __future__ import annotations

import importlib.util
import sys
from typing import NoReturn, Sequence

# extra -> the import names it provides that the package uses (pyproject.toml's optional-dependencies)
EXTRAS: dict[str, tuple[str, ...]] = {
    "train": ("jax", "mujoco", "brax", "flax", "optax", "tensorboardX", "tqdm"),
    "twin": ("pybullet",),
    "reference": ("pybullet", "gymnasium"),
    "export": ("onnx", "onnxruntime"),
    "render": ("mujoco", "imageio", "imageio_ffmpeg"),
    "plots": ("matplotlib",),
    "warp": ("warp",),
    # hardware adapters (sagrasp_jax/deploy/aubo.py, cameras.py): the vendors' own SDKs
    "aubo": ("pyaubo_sdk",),
    "mecheye": ("mecheye",),
    "realsense": ("pyrealsense2",),
}


class MissingExtra(ImportError):
    """An optional part of the install is absent; the message says which extra brings it."""

    def __init__(self, extras: Sequence[str], missing: Sequence[str], what: str) -> None:
        self.extras, self.missing = tuple(extras), tuple(missing)
        super().__init__(f"{what} needs {', '.join(self.missing)}, which is not installed: {install_hint(self.extras)}")


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
