"""Data files shipped inside the package: the robot URDF, the MJCF generated from it, pretrained policies.

They live in ``sagrasp_jax/urdf/`` and ``sagrasp_jax/mjcf/`` and are found through the package
(``importlib.resources``), so a checkout, an editable install and an installed wheel all read
the same files; no code builds a path relative to the checkout.  ``tools/urdf_to_mjcf.py``
regenerates the MJCF into ``MJCF_DIR``.
"""

from __future__ import annotations

from importlib import resources


def path(*parts: str) -> str:
    """File-system path of a file shipped in the package (pybullet and mujoco need real paths)."""
    res = resources.files("sagrasp_jax")
    for part in parts:
        res = res / part
    return str(res)


URDF = path("urdf", "aubo_i5_eg2.urdf")  # the robot: the only place robot facts live
MJCF_DIR = path("mjcf")
MJCF_SCENE = path("mjcf", "scene.xml")  # robot + cell (the kinematic env, physical check, renderer)
MJCF_ROBOT = path("mjcf", "aubo_i5_eg2.xml")  # the robot alone (the dynamic mode's model, servo constants)
PRETRAINED_DIR = path("pretrained")  # exported policies shipped with the package, with their provenance (.json)
