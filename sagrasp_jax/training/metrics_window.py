"""The training-episode window: a device-side ring buffer of the last finished episodes' metrics.

The jitted cycle appends each iteration's finished episodes and returns the window means, so
the host logs smoothed training metrics without fetching per-episode arrays.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

from typing import Any

import jax
import jax.numpy as jnp


# success among the window's episodes of one kind: name -> (episode flag, the flag's value for the kind);
# NaN (null in metrics.jsonl) while the window holds no episode of that kind
KIND_SUCCESS = {"success_no_obstacle": ("obstacle_present", False), "success_obstacle": ("obstacle_present", True),
                "success_blocking": ("blocking", True)}


def kind_success_keys(keys: Any) -> list[str]:
    """The per-kind success means a window with metrics ``keys`` reports (it needs ``success`` and the flag)."""
    return [name for name, (flag, _) in KIND_SUCCESS.items() if "success" in keys and flag in keys]


def init_window(keys: tuple[str, ...], size: int) -> dict[str, Any]:
    """Device-side ring buffer of the last ``size`` finished training episodes' metrics."""
    return {"values": {k: jnp.zeros((size,), jnp.float32) for k in keys},
            "count": jnp.zeros((), jnp.int32), "ptr": jnp.zeros((), jnp.int32)}


def update_window(window: dict[str, Any], episodes: dict[str, jax.Array]) -> tuple[dict[str, Any], dict[str, jax.Array]]:
    """Append the episodes that finished in [T, B] ``episodes`` (time-major, then env order) and
    return the window means: every metric but ``steps``, ``episode_steps``, ``steps_to_success``
    (NaN without a success), ``window_episodes`` and the success per episode kind (``KIND_SUCCESS``)."""
    size = next(iter(window["values"].values())).shape[0]
    done = episodes["done"].reshape(-1) > 0.5
    rank = jnp.cumsum(done, dtype=jnp.int32) - 1  # int32 also under x64: the loop carry's type
    n_new = jnp.sum(done, dtype=jnp.int32)
    keep = done & (rank >= n_new - size)
    pos = jnp.where(keep, (window["ptr"] + rank) % size, size)
    values = {k: buf.at[pos].set(episodes[k].reshape(-1).astype(buf.dtype), mode="drop")
              for k, buf in window["values"].items()}
    count = jnp.minimum(window["count"] + n_new, size)
    new = {"values": values, "count": count, "ptr": (window["ptr"] + n_new) % size}
    valid = (jnp.arange(size) < count).astype(jnp.float32)
    n = jnp.maximum(count, 1).astype(jnp.float32)
    means = {k: jnp.sum(v * valid) / n for k, v in values.items() if k != "steps"}
    steps = values.get("steps", jnp.zeros((size,), jnp.float32))
    success = values.get("success", jnp.zeros((size,), jnp.float32)) * valid
    n_success = jnp.sum(success)
    means["episode_steps"] = jnp.sum(steps * valid) / n
    means["steps_to_success"] = jnp.where(n_success > 0, jnp.sum(steps * success) / jnp.maximum(n_success, 1.0),
                                          jnp.nan)
    means["window_episodes"] = count
    for name in kind_success_keys(values):
        flag, value = KIND_SUCCESS[name]
        member = ((values[flag] > 0.5) == value).astype(jnp.float32) * valid
        n_kind = jnp.sum(member)
        means[name] = jnp.where(n_kind > 0, jnp.sum(success * member) / jnp.maximum(n_kind, 1.0), jnp.nan)
    return new, means
