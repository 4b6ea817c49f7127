"""Test helper: the package's scripted controller with the JAX backend."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from sagrasp_jax.task import scripted
from sagrasp_jax.task.config import EnvConfig


def scripted_action(cfg: EnvConfig, q: jax.Array, target: jax.Array) -> jax.Array:
    return scripted.scripted_action(jnp, cfg, q, target)
