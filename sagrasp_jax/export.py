"""Export a trained run for deployment: ``python -m sagrasp_jax.export --run runs/NAME --out policy/``.

Writes, each atomically (temp file + rename), into ``--out``:

* ``policy.npz`` — the ``sagrasp_jax.task.policy_file`` format (weights, normaliser with its std floor
  and clip, action scale, observation layout, training config and its hash, package
  version), from the run's latest checkpoint (its final params at the end of training), via
  ``restore.export_policy``;
* ``policy.onnx`` — the same deterministic policy as an ONNX graph (opset ≥ 17), built with
  ``onnx.helper`` from the npz weights: ``clip((obs − mean)/std, ±clip)``, the dense layers
  with their activation, the ``action_size`` loc outputs, ``tanh``.  Input ``obs`` float32
  (batch, obs_size) (17 for layout ``paper``, 29 for ``relative``), output ``action`` float32 (batch, action_size).  No torch involved;
* ``export.json`` — what was exported from where (run, checkpoint counters, config hash,
  file checksums) and the measured largest action difference between the two files.

Why both: ``policy.npz`` runs with NumPy alone on the robot PC (``policy_file.load_policy``);
ONNX serves any other runtime.  Both come from the same arrays, and the exporter checks that
they agree (``onnxruntime``, when installed) before it reports success.

The run is read and checked first; then ``--out`` is locked (``run_dir.FolderLock``: a second
export or a training writing there is refused) and checked to be writable.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import hashlib
import json
import os
import sys
from typing import Any, Sequence

import numpy as np

from sagrasp_jax import __version__
from sagrasp_jax.base import cli
from sagrasp_jax.base import extras
from sagrasp_jax.base import fileio
from sagrasp_jax.task import policy_file as runtime
from sagrasp_jax.task.policy_file import NumpyPolicy

NPZ_FILE = "policy.npz"
ONNX_FILE = "policy.onnx"
MANIFEST_FILE = "export.json"
DEFAULT_OPSET = 17
ONNX_IR_VERSION = 8  # the oldest IR that carries opset 17: loads in any onnxruntime since 1.10
AGREEMENT_TOL = 1e-5  # max |a_npz − a_onnx| accepted at export
CHECK_OBSERVATIONS = 1000


class ExportError(RuntimeError):
    """A run folder that cannot be exported, or an export that fails its own check."""


def _sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def onnx_model(policy: NumpyPolicy, opset: int = DEFAULT_OPSET) -> Any:
    """The deterministic policy as an ``onnx.ModelProto``, float32, dynamic batch.

    The last dense layer keeps only its first ``action_size`` columns: the loc half of the
    brax tanh-normal output (the scale half does not enter the deterministic action), which
    is the same as computing all outputs and slicing, without the unused work.
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    if opset < 17:
        raise ExportError(f"opset {opset} < 17 is not supported")
    f32 = np.float32
    inits = [
        numpy_helper.from_array(policy.obs_mean.astype(f32), "obs_mean"),
        numpy_helper.from_array(policy.obs_std.astype(f32), "obs_std"),
        numpy_helper.from_array(np.array(-policy.obs_clip, f32), "clip_lo"),
        numpy_helper.from_array(np.array(policy.obs_clip, f32), "clip_hi"),
    ]
    nodes = [
        helper.make_node("Sub", ["obs", "obs_mean"], ["centred"], name="normalise_sub"),
        helper.make_node("Div", ["centred", "obs_std"], ["scaled"], name="normalise_div"),
        helper.make_node("Clip", ["scaled", "clip_lo", "clip_hi"], ["x0"], name="normalise_clip"),
    ]
    last = len(policy.weights) - 1
    x = "x0"
    for i, (w, b) in enumerate(policy.weights):
        if i == last:
            w, b = w[:, : policy.action_size], b[: policy.action_size]
        inits += [numpy_helper.from_array(w.astype(f32), f"layer_{i}_w"), numpy_helper.from_array(b.astype(f32), f"layer_{i}_b")]
        nodes += [
            helper.make_node("MatMul", [x, f"layer_{i}_w"], [f"mm_{i}"], name=f"dense_{i}_matmul"),
            helper.make_node("Add", [f"mm_{i}", f"layer_{i}_b"], [f"pre_{i}"], name=f"dense_{i}_add"),
        ]
        x = f"pre_{i}"
        if i < last:
            out = f"h_{i}"
            if policy.activation == "tanh":
                nodes.append(helper.make_node("Tanh", [x], [out], name=f"act_{i}"))
            elif policy.activation == "relu":
                nodes.append(helper.make_node("Relu", [x], [out], name=f"act_{i}"))
            elif policy.activation == "elu":
                nodes.append(helper.make_node("Elu", [x], [out], name=f"act_{i}", alpha=1.0))
            elif policy.activation == "silu":
                nodes += [
                    helper.make_node("Sigmoid", [x], [f"sig_{i}"], name=f"act_{i}_sigmoid"),
                    helper.make_node("Mul", [x, f"sig_{i}"], [out], name=f"act_{i}_mul"),
                ]
            else:  # pragma: no cover - load_policy accepts only the four above
                raise ExportError(f"activation {policy.activation!r} has no ONNX mapping")
            x = out
    nodes.append(helper.make_node("Tanh", [x], ["action"], name="squash"))
    graph = helper.make_graph(
        nodes,
        "sagrasp_policy",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", policy.obs_size])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", policy.action_size])],
        initializer=inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)], producer_name="sagrasp_jax",
                              producer_version=__version__, doc_string=f"deterministic SA-PPO grasp policy: obs ({policy.obs_size}) -> action in [-1, 1]^{policy.action_size}")
    model.ir_version = ONNX_IR_VERSION
    meta = {
        "format": "sagrasp_jax policy",
        "config_hash": policy.config_hash,
        "package_version": policy.package_version,
        "obs_layout": ",".join(policy.obs_layout),
        "action_scale": repr(policy.action_scale),
        "obs_std_floor": repr(policy.obs_std_floor),
        "obs_clip": repr(policy.obs_clip),
        "activation": policy.activation,
    }
    onnx.helper.set_model_props(model, meta)
    onnx.checker.check_model(model, full_check=True)
    return model


def write_onnx(policy: NumpyPolicy, path: str, opset: int = DEFAULT_OPSET) -> str:
    """Build, check and atomically write ``policy.onnx``."""
    from sagrasp_jax.training.checkpoint import atomic_write_bytes

    atomic_write_bytes(path, onnx_model(policy, opset).SerializeToString())
    return path


def check_observations(policy: NumpyPolicy, n: int = CHECK_OBSERVATIONS, seed: int = 0) -> np.ndarray:
    """Observations spread over what the normaliser has seen (mean ± 3 std) plus clipped extremes."""
    rng = np.random.default_rng(seed)
    obs = policy.obs_mean + policy.obs_std * rng.normal(0.0, 1.5, (n, policy.obs_size))
    obs[: n // 10] = policy.obs_mean + policy.obs_std * rng.uniform(-8, 8, (n // 10, policy.obs_size))
    return obs


def onnx_actions(path: str, obs: np.ndarray) -> np.ndarray:
    """Run ``policy.onnx`` with onnxruntime (CPU)."""
    import onnxruntime as ort

    session = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
    return session.run(["action"], {"obs": np.asarray(obs, dtype=np.float32)})[0]


def check_opset(opset: int) -> int:
    """17 ≤ opset ≤ the newest opset the installed onnx knows."""
    try:
        import onnx

        newest = int(onnx.defs.onnx_opset_version())
    except ImportError:
        newest = 100  # checked again by onnx itself when it is installed
    if isinstance(opset, bool) or not isinstance(opset, int) or not DEFAULT_OPSET <= opset <= newest:
        raise ExportError(f"--opset={opset!r} is outside the supported range [{DEFAULT_OPSET}, {newest}]")
    return opset


def load_run(run: str) -> tuple[Any, Any, Any, dict[str, Any]]:
    """Config, final params, normaliser and counters of a run folder, with clear errors."""
    from sagrasp_jax.training import restore, run_dir
    from sagrasp_jax.training.checkpoint import CheckpointError

    if not os.path.exists(run):
        raise ExportError(f"{run}: run folder not found")
    if not os.path.isdir(run):
        raise ExportError(f"{run}: not a folder (pass the run folder written by sagrasp_jax.train)")
    try:
        return restore.load_policy_state(run)
    except (CheckpointError, run_dir.RunDirError) as exc:
        raise ExportError(f"cannot export {run}: {exc}") from None


def export_run(run: str, out_dir: str, *, onnx: bool = True, opset: int = DEFAULT_OPSET) -> dict[str, Any]:
    """Export a run folder's policy into ``out_dir``; returns the manifest (also written there)."""
    from sagrasp_jax.training import run_dir

    if onnx:
        check_opset(opset)
    if not os.path.isdir(run):
        load_run(run)  # says what is wrong with it
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise ExportError(f"{out_dir}: exists and is not a folder")
    for name in (NPZ_FILE, ONNX_FILE, MANIFEST_FILE):  # a FIFO or device there: refused before anything is made
        fileio.check_output_file(os.path.join(out_dir, name))
    try:
        with run_dir.FolderLock(out_dir, create=True, what="output folder"):
            run_dir.check_writable(out_dir, "output folder")
            cfg, params, normaliser, counters = load_run(run)
            return _export(run, out_dir, cfg, params, normaliser, counters, onnx, opset)
    except run_dir.RunDirError as exc:
        raise ExportError(str(exc)) from None


def _export(run: str, out_dir: str, cfg: Any, params: Any, normaliser: Any, counters: dict[str, Any], onnx: bool,
            opset: int) -> dict[str, Any]:
    from sagrasp_jax.training import restore
    from sagrasp_jax.training.agents.ppo import ppo
    from sagrasp_jax.training.checkpoint import atomic_write_bytes

    npz_path = restore.export_policy(os.path.join(out_dir, NPZ_FILE), cfg, params, normaliser, int(normaliser.mean.shape[-1]))
    policy = runtime.load_policy(npz_path)
    planned = ppo.num_iterations(cfg.train.total_steps, cfg.ppo)
    manifest: dict[str, Any] = {
        "run": os.path.abspath(run),
        "checkpoint_iteration": counters.get("iteration"),
        "checkpoint_env_steps": counters.get("env_steps"),
        "finished": counters.get("iteration") == planned or bool(counters.get("stopped_at")),
        "stopped_by_rule_at": counters.get("stopped_at") or None,
        "config_hash": policy.config_hash,
        "package_version": policy.package_version,
        "obs_layout": list(policy.obs_layout),
        "action_size": policy.action_size,
        "action_scale": policy.action_scale,
        "activation": policy.activation,
        "hidden": [int(w.shape[1]) for w, _ in policy.weights[:-1]],
        "files": {NPZ_FILE: {"sha256": _sha256(npz_path), "bytes": os.path.getsize(npz_path)}},
    }
    if onnx:
        onnx_path = write_onnx(policy, os.path.join(out_dir, ONNX_FILE), opset)
        manifest["files"][ONNX_FILE] = {"sha256": _sha256(onnx_path), "bytes": os.path.getsize(onnx_path), "opset": opset}
        try:
            obs = check_observations(policy)
            diff = float(np.abs(onnx_actions(onnx_path, obs) - policy(obs)).max())
        except ImportError:
            manifest["onnx_check"] = f"skipped: onnxruntime not installed ({extras.install_hint(('export',))})"
        else:
            manifest["onnx_check"] = {"observations": len(obs), "max_abs_action_diff": diff}
            if not diff <= AGREEMENT_TOL:
                raise ExportError(f"{onnx_path}: ONNX and npz actions differ by {diff:.3g} > {AGREEMENT_TOL:g}")
    atomic_write_bytes(os.path.join(out_dir, MANIFEST_FILE), (json.dumps(manifest, indent=2) + "\n").encode())
    return manifest


def main(argv: Sequence[str] | None = None) -> int:
    p = cli.Parser(prog="python -m sagrasp_jax.export", description=__doc__.split("\n\n")[0])
    p.add_argument("--run", required=True, help="run folder written by sagrasp_jax.train")
    p.add_argument("--out", required=True, help="output folder (created; existing export files are replaced)")
    p.add_argument("--no-onnx", action="store_true", help="write only policy.npz")
    p.add_argument("--opset", type=int, default=DEFAULT_OPSET, help=f"ONNX opset (>= 17, default {DEFAULT_OPSET})")
    args = p.parse_args(argv)
    try:
        extras.require("train", what="reading a run's checkpoint")
        extras.require(*(() if args.no_onnx else ("export",)), what="ONNX export (--no-onnx writes policy.npz only)")
    except extras.MissingExtra as exc:
        extras.exit_missing(exc, p.prog)
    try:
        manifest = export_run(args.run, args.out, onnx=not args.no_onnx, opset=args.opset)
    except (ExportError, runtime.PolicyFormatError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not manifest["finished"]:
        print(f"warning: {args.run} is not finished (checkpoint at iteration {manifest['checkpoint_iteration']}); "
              "exported its latest checkpoint", file=sys.stderr)
    for name, info in manifest["files"].items():
        print(f"wrote {os.path.join(args.out, name)} ({info['bytes']} bytes, sha256 {info['sha256'][:12]})")
    check = manifest.get("onnx_check")
    if isinstance(check, dict):
        print(f"ONNX vs npz on {check['observations']} observations: max |Δaction| = {check['max_abs_action_diff']:.2e}")
    elif check:
        print(f"ONNX check {check}")
    print(f"config hash {manifest['config_hash']}, checkpoint iteration {manifest['checkpoint_iteration']}, "
          f"{manifest['checkpoint_env_steps']} env steps; manifest {os.path.join(args.out, MANIFEST_FILE)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
