"""Multi-process training through ``jax.distributed``: one process per host, the global env batch
split over every device of every process (docs/task.md §3 "Multiple devices").

Start the same command on every host, each with its ``--process-id``::

    # host 0 (the coordinator)                        # host 1
    python -m sagrasp_jax.train --out runs/big \\       python -m sagrasp_jax.train --out runs/big \\
        --coordinator host0:12355 --num-processes 2 \\      --coordinator host0:12355 --num-processes 2 \\
        --process-id 0 [--preset ... --set ...]              --process-id 1 [--preset ... --set ...]

Every process builds the same config, the same global env batch (``ppo.num_envs`` in all) and
the same replicated parameters; each steps only its own devices' envs (their keys are slices of
one global split, so the processes' envs are seeded apart), and gradients, normaliser and
advantage statistics are averaged over all devices (``ppo.make_cycle``).  The SA schedule runs
on every process on the same (replicated) evaluation, so all take the same decisions.  Only
process 0 writes the run folder; ``--resume`` needs its checkpoint readable by every process
(a shared file system or a copy).  On CPU the collectives go through gloo.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (XLA flags before jax)

import numpy as np

from sagrasp_jax.config import ConfigError


def initialize(coordinator: str, num_processes: int, process_id: int) -> None:
    """Join the distributed run (call before any jax computation)."""
    import jax

    if not 0 <= process_id < num_processes:
        raise ConfigError(f"--process-id {process_id} must lie in 0 … {num_processes - 1}")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")  # CPU collectives across processes
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes, process_id=process_id)


def all_ok(ok: bool) -> bool:
    """True on every process iff ``ok`` is true on every process (a collective when distributed)."""
    import jax

    if jax.process_count() == 1:
        return ok
    from jax.experimental import multihost_utils

    return bool(np.all(multihost_utils.process_allgather(np.int32(ok))))
