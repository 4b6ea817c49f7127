"""A tiny real-env training run shared by the export, deploy, physical and render tests.

Training quality does not matter to those tests (they check plumbing and agreement, not
success), so the run is as small as the trainer allows: ≈ 45 s cold on 2 cores, mostly
compilation, ≈ 12 s with jax's persistent cache warm.  ``env.task.max_steps=50`` keeps the
deployment and render episodes short.  Created once per pytest session.
"""

from __future__ import annotations

import os
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TINY_ARGS = [
    "--preset", "cpu-quick", "--total-steps", "1024", "--seed", "0", "--no-progress",
    "--set", "eval.num_cycles=1", "--set", "eval.episodes=8", "--set", "ppo.num_envs=64",
    "--set", "ppo.num_epochs=1", "--set", "ppo.num_minibatches=1", "--set", "ppo.network.policy_hidden=32,32,32,32",
    "--set", "ppo.learning_rate=3e-4", "--set", "sa.decay=0.98", "--set", "env.task.max_steps=50",
]  # fmt: skip
_RUNS: dict[str, str] = {}


def tiny_run(base: str) -> str:
    """Path of the session's tiny run folder (trained under ``base`` on first use)."""
    if "run" not in _RUNS:
        out = os.path.join(base, "tiny_run")
        res = subprocess.run([sys.executable, "-m", "sagrasp_jax.train", "--out", out, *TINY_ARGS],
                             capture_output=True, text=True, timeout=600, cwd=REPO)
        assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
        _RUNS["run"] = out
    return _RUNS["run"]
