"""PyBullet reference implementation of the task, registered with Gymnasium as ``SAGrasp-PyBullet-v0``.

Importing this package registers the env id (when gymnasium is installed: it is in the
``reference`` extra), so ``gymnasium.make("SAGrasp-PyBullet-v0")`` works after
``import sagrasp_jax.reference``, and ``gymnasium.make("sagrasp_jax.reference:SAGrasp-PyBullet-v0")``
works without it.  PyBullet itself is imported only when the env is built.  Nothing here
imports jax.
"""

from __future__ import annotations

ENV_ID = "SAGrasp-PyBullet-v0"
ENTRY_POINT = "sagrasp_jax.reference.pybullet_env:PyBulletGraspEnv"

try:
    import gymnasium as _gym
except ImportError:  # pragma: no cover - the reference extra is not installed
    _gym = None

if _gym is not None and ENV_ID not in _gym.registry:
    # No max_episode_steps: the env ends its own episodes (a timeout is a terminal verdict, SPEC §2).
    _gym.register(id=ENV_ID, entry_point=ENTRY_POINT)
