"""The MuJoCo scene's dynamic-obstacle slots, from the obstacle-kind registry (``shapes.SHAPES``).

``sagrasp_jax/mjcf/scene.xml`` (written by ``tools/urdf_to_mjcf.py``) has, in each obstacle slot (a mocap body
``obstacle_<slot>``), one geom per registered kind, ``obstacle_<slot>_<kind>``, the entry's primitive at unit
size with the entry's tilt; the physical check and the renderer size the episode's geom and hide the others.
Those geoms are built here, for the tool and for a loaded scene alike.

A scene is loaded through ``load_scene_spec``, which adds the geoms of any registered kind the XML lacks (a kind
registered after the XML was written: a plugin's, a test's) and refuses, naming the command that regenerates it,
an XML whose geom for a kind disagrees with that kind's entry (its primitive or tilt changed since).  Why at load
time and not only by regenerating the file: the file ships in the wheel, where a user cannot regenerate it, and a
kind a user registers must not need package data edited; the shipped kinds stay in the file so that MuJoCo's own
viewer and ``MjModel.from_xml_path`` show them, and ``tests/mjcf/test_mjcf.py`` keeps the file what the tool writes.
"""

from __future__ import annotations

import mujoco
import numpy as np

from sagrasp_jax.base import assets
from sagrasp_jax.task import shapes
from sagrasp_jax.task.robot import BOX, CAPSULE, CYLINDER, SPHERE
from sagrasp_jax.task.scene import SCENE

GEOM_TYPES = {SPHERE: mujoco.mjtGeom.mjGEOM_SPHERE, CAPSULE: mujoco.mjtGeom.mjGEOM_CAPSULE,
              BOX: mujoco.mjtGeom.mjGEOM_BOX, CYLINDER: mujoco.mjtGeom.mjGEOM_CYLINDER}  # robot primitive -> MuJoCo
REGENERATE = "python tools/urdf_to_mjcf.py"  # the command that rewrites the packaged MJCF
UNIT_SIZE = (0.05, 0.05, 0.05)  # a slot geom's size in the XML; the physical check and the renderer set the episode's


def slot_body_name(slot: int) -> str:
    return f"obstacle_{slot}"


def obstacle_geom_name(slot: int, shape: shapes.ObstacleShape) -> str:
    """The geom that draws ``shape`` in obstacle slot ``slot``."""
    return f"obstacle_{slot}_{shape.name}"


def tilt_quat(shape: shapes.ObstacleShape) -> np.ndarray | None:
    """The geom's quaternion in its slot body (the entry's tilt; the body carries the yaw), None for no tilt."""
    if np.allclose(shape.tilt_matrix, np.eye(3)):
        return None
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, shape.tilt_matrix.flatten())
    return quat


def add_obstacle_geom(body: mujoco.MjsBody, slot: int, shape: shapes.ObstacleShape) -> mujoco.MjsGeom:
    """``shape``'s geom in a slot body: its primitive at unit size, its tilt, the obstacles' colour, no contacts."""
    geom = body.add_geom(
        name=obstacle_geom_name(slot, shape),
        type=GEOM_TYPES[shape.primitive],
        size=list(UNIT_SIZE),
        rgba=list(SCENE.obstacles.rgba),
        contype=0,
        conaffinity=0,
    )
    quat = tilt_quat(shape)
    if quat is not None:
        geom.quat = quat.tolist()
    return geom


def _check_geom(geom: mujoco.MjsGeom, shape: shapes.ObstacleShape, where: str) -> None:
    """Refuse a slot geom that does not draw ``shape`` as its entry says (a stale XML)."""
    want = tilt_quat(shape)
    want = np.array([1.0, 0.0, 0.0, 0.0]) if want is None else want
    have = np.asarray(geom.quat, float)
    have = have / max(float(np.linalg.norm(have)), 1e-12)
    if geom.type != GEOM_TYPES[shape.primitive] or abs(float(have @ want)) < 1.0 - 1e-6:
        raise ValueError(f"{where}: geom {geom.name!r} is a {geom.type.name} at quat {np.round(have, 6).tolist()}, but "
                         f"shapes.BY_NAME[{shape.name!r}] draws a {GEOM_TYPES[shape.primitive].name} at quat "
                         f"{np.round(want, 6).tolist()}: the scene is stale, run {REGENERATE}")


def complete_obstacle_slots(spec: mujoco.MjSpec, where: str = "the scene") -> tuple[str, ...]:
    """Give every obstacle slot of a scene spec a geom for every registered kind: adds those missing (returns
    their names), checks the others against their entries (``_check_geom``).  ValueError names ``where``."""
    added = []
    for slot in range(SCENE.obstacles.count):
        body = spec.body(slot_body_name(slot))
        if body is None:
            raise ValueError(f"{where} has no obstacle slot {slot} (body {slot_body_name(slot)!r}): run {REGENERATE}")
        for shape in shapes.SHAPES:
            geom = spec.geom(obstacle_geom_name(slot, shape))
            if geom is None:
                added.append(add_obstacle_geom(body, slot, shape).name)
            else:
                _check_geom(geom, shape, where)
    return tuple(added)


def load_scene_spec(xml_path: str = assets.MJCF_SCENE) -> mujoco.MjSpec:
    """The scene (robot and cell) as an ``MjSpec``, with every registered kind's geom in every obstacle slot."""
    spec = mujoco.MjSpec.from_file(xml_path)
    complete_obstacle_slots(spec, xml_path)
    return spec


def load_scene_model(xml_path: str = assets.MJCF_SCENE) -> mujoco.MjModel:
    """``load_scene_spec`` compiled."""
    return load_scene_spec(xml_path).compile()
