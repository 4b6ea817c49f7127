"""PyBullet reference implementation of the task, registered with Gymnasium.

Importing this package registers one env id per observation layout
(``observation.LAYOUT_NAMES``): ``SAGrasp-PyBullet-paper-v0`` (the paper's 17 numbers),
``SAGrasp-PyBullet-relative-v0`` (29, the second landing's policies), ``SAGrasp-PyBullet-relative_lag-v0``
(35, what ``cpu-quick`` and ``gpu`` policies see: ``relative`` and the pending command), and any layout
added later; ``SAGrasp-PyBullet-v0`` stays the paper layout.  The ids are registered
when gymnasium is installed (the ``reference`` extra), so ``gymnasium.make(ENV_ID)`` works
after ``import sagrasp_jax.reference`` and ``gymnasium.make("sagrasp_jax.reference:SAGrasp-PyBullet-v0")``
works without it.  Timeouts end an episode with ``truncated=True`` (Gymnasium's time-limit
convention; the −1 timeout reward is still paid, docs/task.md §2.7); each id registers
``max_episode_steps`` = the paper preset's ``env.task.max_steps``, the step the env's own timeout
ends it on, so ``gymnasium.wrappers.TimeLimit`` agrees with it (an env made with another
``cfg.task.max_steps`` passes ``max_episode_steps=`` to ``gymnasium.make`` too).  The finished
episode's task metrics are ``info["task_episode"]`` (``EPISODE_INFO``) on its last step:
``info["episode"]`` belongs to Gymnasium's ``RecordEpisodeStatistics`` (and SB3's Monitor).
PyBullet itself is imported only when an env is built.  Nothing here imports jax.
"""

from __future__ import annotations

from sagrasp_jax.task.config import get_config
from sagrasp_jax.task.observation import LAYOUT_NAMES

ENV_ID = "SAGrasp-PyBullet-v0"  # the paper layout
EPISODE_INFO = "task_episode"  # info key of a finished episode's task metrics (episode.episode_keys())
MAX_EPISODE_STEPS = get_config("paper").env.task.max_steps  # the registered TimeLimit: the env's own timeout
ENTRY_POINT = "sagrasp_jax.reference.pybullet_env:PyBulletGraspEnv"


def env_id(layout: str) -> str:
    """The registered id of the env observing through ``layout``."""
    return f"SAGrasp-PyBullet-{layout}-v0"


ENV_IDS = {name: env_id(name) for name in LAYOUT_NAMES}

try:
    import gymnasium as _gym
except ImportError:  # pragma: no cover - the reference extra is not installed
    _gym = None

if _gym is not None:
    for _name, _id in {**ENV_IDS, ENV_ID: ENV_ID}.items():
        if _id not in _gym.registry:
            _gym.register(id=_id, entry_point=ENTRY_POINT, max_episode_steps=MAX_EPISODE_STEPS,
                          kwargs={"obs_layout": "paper" if _id == ENV_ID else _name})
