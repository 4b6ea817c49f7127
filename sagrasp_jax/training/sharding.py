"""Data parallelism over a 1-D device mesh: placing arrays, gathering them, and collectives.

The env batch is split over a ``Mesh`` of devices (the local ones, or every process's under
``jax.distributed``); params and optimizer state are replicated.  Each device runs its share
inside ``shard_map`` (axis ``BATCH_AXIS``) and averages statistics, gradients and metrics over
the mesh, so the maths is that of one global batch.  Random normals are drawn for the global
batch and sliced (``batch_normal``), so a sample does not depend on the device count.  The
training step (``ppo``), the rollout and the evaluation all place and reduce through here.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

from typing import Any, Callable

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

BATCH_AXIS = "batch"


def make_mesh(devices: list[jax.Device] | None = None) -> Mesh:
    """1-D mesh over ``devices`` (default: every device of every process; the local ones without
    ``jax.distributed``)."""
    return Mesh(np.array(devices if devices is not None else jax.devices()), (BATCH_AXIS,))


def batch_sharding(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec(BATCH_AXIS))


def seed_batch_spec() -> PartitionSpec:
    """A seed group's env arrays, [S, B, ...]: the seed axis whole on every device, B split."""
    return PartitionSpec(None, BATCH_AXIS)


def seed_batch_sharding(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, seed_batch_spec())


def replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec())


def placeable(tree: Any) -> Any:
    """Under several processes ``device_put`` onto a global sharding wants host arrays (the same on
    every process); each process keeps its own slices."""
    if jax.process_count() == 1:
        return tree
    return jax.tree_util.tree_map(lambda x: np.asarray(x) if isinstance(x, jax.Array) and x.is_fully_addressable
                                  else x, tree)


def shard_batch(tree: Any, mesh: Mesh) -> Any:
    """Place a pytree whose leaves all lead with the env-batch axis, split over the mesh."""
    return jax.device_put(placeable(tree), batch_sharding(mesh))


def replicate(tree: Any, mesh: Mesh) -> Any:
    return jax.device_put(placeable(tree), replicated(mesh))


def to_host(tree: Any) -> Any:
    """NumPy copy of a pytree of arrays.  Leaves split over several processes are gathered from all
    of them, so under ``jax.distributed`` every process must call this at the same point."""

    def get(x: Any) -> Any:
        if not isinstance(x, jax.Array) or jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            return x
        if x.is_fully_addressable:
            return np.asarray(x)
        if x.is_fully_replicated:
            return np.asarray(x.addressable_data(0))
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))

    return jax.tree_util.tree_map(get, tree)


def pmean(x: Any, axis_name: str | None) -> Any:
    return x if axis_name is None else jax.lax.pmean(x, axis_name)


def psum(x: Any, axis_name: str | None) -> Any:
    return x if axis_name is None else jax.lax.psum(x, axis_name)


def sharded(fn: Callable[..., Any], mesh: Mesh, in_specs: Any, out_specs: Any) -> Callable[..., Any]:
    """``shard_map`` without replication checks: the cycle's collectives keep replicated values equal."""
    return jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False)


def batch_normal(key: jax.Array, shape: tuple[int, ...], axis_name: str | None = None) -> jax.Array:
    """Standard normals for this device's rows of a batch split over ``axis_name``: its slice of one
    draw for the whole batch, so a sample does not depend on how many devices share the batch."""
    if axis_name is None:
        return jax.random.normal(key, shape)
    n = jax.lax.axis_size(axis_name)
    full = jax.random.normal(key, (n * shape[0],) + tuple(shape[1:]))
    return jax.lax.dynamic_slice_in_dim(full, jax.lax.axis_index(axis_name) * shape[0], shape[0])

