"""Multi-process training through jax.distributed: two local CPU processes (gloo collectives) compute
the same first-iteration gradients as one process with two devices, and train a toy run together."""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import numpy as np

from conftest import toy_config, toy_factory

from sagrasp_jax import train
from sagrasp_jax.training import run_dir
from paths import TESTS  # noqa: E402

WORKER = os.path.join(TESTS, "two_process_worker.py")


def _env(devices: int) -> dict[str, str]:
    return dict(os.environ, JAX_PLATFORMS="cpu", JAX_ENABLE_X64="0",
                XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _rows(run: str) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in train.TIME_FIELDS}
            for r in run_dir.read_metrics(run_dir.path(run, run_dir.METRICS_FILE))]


def test_two_processes_match_one_process_with_two_devices(tmp_path):
    out = str(tmp_path)
    single = subprocess.Popen([sys.executable, WORKER, "single", out], env=_env(2), stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
    port = _free_port()
    procs = [subprocess.Popen([sys.executable, WORKER, "proc", out, "--port", str(port), "--process-id", str(i)],
                              env=_env(1), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for i in range(2)]
    for p in [single, *procs]:
        log, _ = p.communicate(timeout=600)
        assert p.returncode == 0, log[-4000:]
    a = np.load(os.path.join(out, "grads_single.npz"))
    b = np.load(os.path.join(out, "grads_proc.npz"))
    two = sorted(k for k in a.files if k.startswith("two_"))
    assert two and sorted(k for k in b.files) == two
    # the check: the first iteration's gradients (and loss) of 2 processes and of 1 process with
    # 2 devices agree within 1e-5 (float32; the same partitioned program, only the collectives differ)
    assert max(float(np.max(np.abs(a[k] - b[k]))) for k in two) < 1e-5
    # 1 device: a differently fused float32 program (test_ppo checks 1e-5 in float64)
    assert max(float(np.max(np.abs(a[k] - a["one_" + k[4:]]))) for k in two) < 1e-4
    # the two processes trained the toy run together; only process 0 wrote the folder
    run = os.path.join(out, "run_proc")
    rows = _rows(run)
    assert [r["iteration"] for r in rows] == list(range(train.make_schedule(toy_config(cycles=2)).num_iterations))
    assert sum("sa_decision" in r for r in rows) == 2 and all(np.isfinite(r["loss"]) for r in rows)
    assert {"checkpoint.ckpt", "policy.npz", "config.json"} <= set(os.listdir(run))
    resumed = train.Trainer(toy_config(cycles=2), run, env_factory=toy_factory(), progress=False, resume=True)
    assert resumed.host.iteration == len(rows)  # the gathered checkpoint loads in one process
