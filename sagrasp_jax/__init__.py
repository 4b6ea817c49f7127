"""sagrasp_jax: the SA-PPO obstacle-aware grasping task of Li et al. (Sensors 2025) in MuJoCo-MJX / JAX.

Importing the package sets ``XLA_FLAGS=--xla_cpu_use_fusion_emitters=false`` (MJX on
CPU compiles and runs 20-70x faster with it) unless the user already set XLA_FLAGS,
and points jax's persistent compilation cache at ``~/.cache/sagrasp_jax/jax`` unless
``JAX_COMPILATION_CACHE_DIR`` is set.  Neither imports jax.
"""

from __future__ import annotations

import os

__version__ = "0.1.0"

if "XLA_FLAGS" not in os.environ:
    os.environ["XLA_FLAGS"] = "--xla_cpu_use_fusion_emitters=false"
os.environ.setdefault(
    "JAX_COMPILATION_CACHE_DIR", os.path.join(os.path.expanduser("~"), ".cache", "sagrasp_jax", "jax")
)
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1")
