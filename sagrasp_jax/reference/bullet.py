"""PyBullet helpers the reference env and the deploy twin share: primitives in MuJoCo's size convention,
quaternions, connecting, loading a URDF and a client's disconnect, with PyBullet's native chatter kept out of
the user's terminal.  Needs only pybullet (the ``twin`` extra); no gymnasium, no mujoco.

PyBullet's C++ code prints straight to the process's file descriptors, past Python's ``sys.stdout``: a
"pybullet build time" banner on stderr when it is imported, and on stdout, for each URDF link without an
``<inertial>`` (the robot's frame-only links ``flange`` and ``gripper_center``), a ``b3Warning[...]: No
inertial data for link ...`` pair.  ``native_output_filtered`` sends both descriptors to a temporary file for
a block and afterwards passes on to stderr everything but those known-harmless messages
(``filter_native_output``), so a real message (a URDF not found, a failed connection) still shows, and
stdout keeps only what a command reports (deploy's ``--json``).  ``connect`` and ``load_urdf`` run inside it,
and so does the import of pybullet here.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import sys
import xml.etree.ElementTree as ET
from typing import Any, Collection, Iterator

import numpy as np

from sagrasp_jax.base import extras
from sagrasp_jax.base.native_output import held_native_output

# A native message: its header ("b3Warning[file,line]:" and a newline), then its text (not always ended by a newline).
_NATIVE_HEADER = re.compile(r"(b3(?:Warning|Error|Printf)\[[^\]\n]*\]:\n)")
NO_INERTIAL = "No inertial data for link"  # a warning in two messages: this, then the link's name
_LINK_NAME = re.compile(r"[A-Za-z0-9_.\-]+")
HARMLESS_LINES = ("pybullet build time:",)  # lines (not b3 messages) that say nothing to a user


def _pass_lines(text: str) -> str:
    return "".join(line for line in text.splitlines(keepends=True) if not line.startswith(HARMLESS_LINES))


def _link_name(message: str, frame_links: Collection[str] | None) -> str | None:
    """The link name a "No inertial data" warning's second message starts with (it ends with no newline, so
    what is printed next may follow it on the line): one of ``frame_links``, or with None the whole message
    when it looks like a name; None when it is not one."""
    if frame_links is None:
        return message if _LINK_NAME.fullmatch(message) else None
    return max((name for name in frame_links if message.startswith(name)), key=len, default=None)


def filter_native_output(text: str, frame_links: Collection[str] | None = None) -> str:
    """``text`` as PyBullet's native code printed it, less the known-harmless messages: the import banner and
    the "No inertial data for link" warnings, each with the link-name message that follows it (only the links
    of ``frame_links`` when given: those of the URDF loaded without ``<inertial>``, ``urdf_frame_links``)."""
    parts = _NATIVE_HEADER.split(text)
    out = [_pass_lines(parts[0])]
    name_follows = None  # the header of a "No inertial data" warning whose link name comes next
    for header, body in zip(parts[1::2], parts[2::2]):
        message, newline, rest = body.partition("\n")
        name = _link_name(message, frame_links) if header == name_follows else None
        name_follows = None
        if message.startswith(NO_INERTIAL):
            name_follows = header
        elif name is not None:
            rest = message[len(name) :] + newline + rest
        else:
            out.append(header + message + newline)
        out.append(_pass_lines(rest))
    return "".join(out)


def urdf_frame_links(path: str) -> tuple[str, ...] | None:
    """The links of the URDF at ``path`` without ``<inertial>`` (PyBullet warns about each); None if unreadable."""
    try:
        return tuple(link.get("name", "") for link in ET.parse(path).getroot().iter("link") if link.find("inertial") is None)
    except (OSError, ET.ParseError):
        return None


@contextlib.contextmanager
def native_output_filtered(frame_links: Collection[str] | None = None) -> Iterator[None]:
    """Run the block with file descriptors 1 and 2 going to a temporary file, then write what it holds, less
    PyBullet's known-harmless messages (``filter_native_output``), to stderr.  Python's own output in the block
    (``sys.stdout`` too) goes the same way; stdout is left to what the command reports."""
    held: list[str] = []
    try:
        with held_native_output() as held:
            yield
    finally:  # what the block printed reaches stderr even when it raised
        passed = filter_native_output(held[0] if held else "", frame_links)
        if passed and sys.stderr is not None:
            sys.stderr.write(passed)
            sys.stderr.flush()
        elif passed:
            os.write(2, passed.encode())


extras.require("twin", what="the PyBullet helpers")
with native_output_filtered():  # the "pybullet build time" banner
    import pybullet as pb  # noqa: E402

from sagrasp_jax.task.robot import BOX, CAPSULE, CYLINDER, SPHERE  # noqa: E402


def connect(mode: int) -> int:
    """``pybullet.connect(mode)`` (``pb.DIRECT`` or ``pb.GUI``) with its native output filtered; the client id, -1
    when no server could be reached."""
    with native_output_filtered():
        return pb.connect(mode)


def load_urdf(client: int, path: str, **kwargs: Any) -> int:
    """``pybullet.loadURDF(path, **kwargs)`` on ``client``, its native warnings filtered: the frame-only links'
    "No inertial data" warnings are dropped, anything else (a file not found) reaches stderr."""
    with native_output_filtered(urdf_frame_links(path)):
        return pb.loadURDF(path, physicsClientId=client, **kwargs)


def rotation_to_quaternion(rot: np.ndarray) -> tuple[float, float, float, float]:
    """3×3 rotation → PyBullet quaternion (x, y, z, w); Shepperd's method, stable for any angle."""
    m = np.asarray(rot, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        w, x, y, z = 0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        w, x, y, z = (m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        w, x, y, z = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        w, x, y, z = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s
    return (x, y, z, w)


def quaternions_to_rotations(quats: np.ndarray) -> np.ndarray:
    """(..., 4) PyBullet quaternions (x, y, z, w) → (..., 3, 3) rotations, vectorised."""
    q = np.asarray(quats, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ]
    return np.stack(rows, -2)


def shape_kwargs(kind: int, size: Any, visual: bool) -> dict[str, Any]:
    """createCollisionShape / createVisualShape arguments for a primitive in MuJoCo's size convention."""
    size = [float(v) for v in size]
    if kind == SPHERE:
        return {"shapeType": pb.GEOM_SPHERE, "radius": size[0]}
    if kind == BOX:
        return {"shapeType": pb.GEOM_BOX, "halfExtents": size}
    if kind in (CYLINDER, CAPSULE):
        length_key = "length" if visual else "height"  # PyBullet names the same thing differently
        shape = pb.GEOM_CYLINDER if kind == CYLINDER else pb.GEOM_CAPSULE
        return {"shapeType": shape, "radius": size[0], length_key: 2 * size[1]}
    raise ValueError(f"unknown primitive kind {kind}")


def disconnect(client: int) -> int:
    """Disconnect a PyBullet client if it is connected (idempotent); returns -1, the "closed" id."""
    if client >= 0:
        try:
            pb.disconnect(physicsClientId=client)
        except pb.error:
            pass
    return -1
