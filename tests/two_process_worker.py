"""Worker of tests/training/test_distributed.py: the first iteration's gradients (by the training call,
``conftest.first_gradients``), either in one process with
two CPU devices (``single``) or as one of two ``jax.distributed`` processes with one CPU device
each (``proc``; gloo collectives), which then also train a tiny toy run together.

    python tests/two_process_worker.py single OUT
    python tests/two_process_worker.py proc OUT --port P --process-id I
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("mode", choices=("single", "proc"))
    p.add_argument("out")
    p.add_argument("--port", type=int, default=0)
    p.add_argument("--process-id", type=int, default=0)
    args = p.parse_args()
    from sagrasp_jax.training import distributed

    if args.mode == "proc":
        distributed.initialize(f"localhost:{args.port}", 2, args.process_id)
    import jax
    import numpy as np

    from conftest import FIRST_GRADIENT_SETS, first_gradients, toy_config, toy_factory
    from sagrasp_jax import train
    from sagrasp_jax.training import sharding

    assert len(jax.devices()) == 2, jax.devices()
    cfg = toy_config(cycles=2)
    env, _ = toy_factory()(cfg)
    grad_cfg = toy_config(cycles=2, extra=FIRST_GRADIENT_SETS)

    def leaves(mesh):
        return {f"leaf{i}": np.asarray(x) for i, x in enumerate(first_gradients(env, grad_cfg, mesh))}

    result = {f"two_{k}": v for k, v in leaves(sharding.make_mesh()).items()}
    if args.mode == "single":
        result.update({f"one_{k}": v for k, v in leaves(sharding.make_mesh(jax.devices()[:1])).items()})
    if args.mode == "proc":  # the trainer's multi-process plumbing: gathered checkpoint, process 0 writes
        train.run(cfg, os.path.join(args.out, "run_proc"), env_factory=toy_factory(), progress=False)
    if jax.process_index() == 0:
        np.savez(os.path.join(args.out, f"grads_{args.mode}.npz"), **result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
