"""Run an exported policy with NumPy only, and the ``policy.npz`` format it reads.

Deployment machines (the AUBO controller PC) run the policy without JAX, so this
module imports nothing that imports jax: only NumPy, the config modules (``sagrasp_jax.task.config``,
``config_history``, ``config_parse``) and the standard library.  It is the single source of truth for the policy file:
``save_policy_npz`` writes it (the exporter calls it), ``load_policy`` reads and
validates it.

``policy.npz`` (format_version 1), a plain ``np.savez`` archive, no pickles:

================  ==========================  =================================================
key               dtype / shape               meaning
================  ==========================  =================================================
format_version    int64 ()                    1
layer_{i}_w       float (in_i, out_i)         dense layer i of the policy MLP, ``y = x @ W + b``
layer_{i}_b       float (out_i,)              i = 0 .. L-1; ``in_0 = obs_size``; hidden layers
                                              use ``activation``, the last layer is linear and
                                              has ``out = 2·action_size`` (brax tanh-normal:
                                              loc then pre-softplus scale)
activation        str ()                      tanh | relu | silu | elu
obs_mean          float64 (obs_size,)         observation normaliser mean
obs_std           float64 (obs_size,)         normaliser std, already floored (≥ obs_std_floor)
obs_std_floor     float64 ()                  the floor used in training (``ppo.obs_std_floor``)
obs_clip          float64 ()                  normalised obs are clipped to ±obs_clip
action_size       int64 ()                    6
obs_size          int64 ()                    17 (layout ``paper``) or 29 (``relative``)
obs_layout        str (obs_size,)             name of each observation entry (``observation.layout``)
action_scale      float64 ()                  q_max: rad per control step at |a| = 1
config_json       str ()                      the full training ``Config`` as JSON
config_hash       str ()                      ``config_history.env_dict_hash`` of that config's env part, as written
package_version   str ()                      ``sagrasp_jax.__version__`` that wrote the file
================  ==========================  =================================================

The deterministic action is ``tanh(loc)`` in [-1, 1]^action_size; the control step
(``sagrasp_jax.task.control``) turns it into a joint-target increment with the constants
of ``NumpyPolicy.env_config()``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
import zipfile
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from sagrasp_jax import __version__
from sagrasp_jax.base import fileio
from sagrasp_jax.task import observation
from sagrasp_jax.task import robots
from sagrasp_jax.task.config import Config, ConfigError, EnvConfig, config_to_dict
from sagrasp_jax.task.config_history import config_hash, env_dict_hash
from sagrasp_jax.task.config_parse import config_from_dict, parse_json

FORMAT_VERSION = 1
# The cell a policy was trained for (env.sampling keys): recorded by every policy file (version 0.1's too,
# tests/data/legacy_v0_1), and checked against the deployment's by ``deploy.safety.check_policy_scene``; a file
# without one is refused rather than read with today's default, which would pass that check unseen.
RECORDED_CELL_KEYS = ("target_clearance", "target_size", "target_x", "target_y", "target_radius")

OBS_LAYOUT = observation.OBS_LAYOUT  # re-exported: the paper layout's names (every version-0.1 policy)


def _silu(x: np.ndarray) -> np.ndarray:
    return x / (1.0 + np.exp(-x))


def _elu(x: np.ndarray) -> np.ndarray:
    return np.where(x > 0, x, np.expm1(np.minimum(x, 0.0)))


ACTIVATIONS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "tanh": np.tanh,
    "relu": lambda x: np.maximum(x, 0.0),
    "silu": _silu,
    "elu": _elu,
}

_SCALAR_KEYS = (
    "format_version", "activation", "obs_mean", "obs_std", "obs_std_floor", "obs_clip",
    "action_size", "obs_size", "obs_layout", "action_scale", "config_json", "config_hash",
    "package_version",
)  # fmt: skip


class PolicyFormatError(ValueError):
    """A policy file that cannot be run safely; the message names the file and the problem."""


@dataclass(frozen=True)
class NumpyPolicy:
    """A deterministic policy: normalise, MLP, tanh of the loc half of the output."""

    weights: tuple[tuple[np.ndarray, np.ndarray], ...]
    activation: str
    obs_mean: np.ndarray
    obs_std: np.ndarray
    obs_std_floor: float
    obs_clip: float
    action_size: int
    obs_size: int
    obs_layout: tuple[str, ...]
    action_scale: float
    config_json: str
    config_hash: str
    package_version: str
    path: str = "<memory>"
    file_sha256: str = ""  # of the file as read (load_policy): which policy a result was made with

    def normalise(self, obs: Any) -> np.ndarray:
        """clip((obs − mean)/std, ±clip): exactly the training normaliser, frozen."""
        obs = self._check_obs(obs)
        return np.clip((obs - self.obs_mean) / self.obs_std, -self.obs_clip, self.obs_clip)

    def forward(self, obs: Any) -> np.ndarray:
        """Raw MLP output (..., 2·action_size): loc then pre-softplus scale."""
        x = self.normalise(obs)
        act = ACTIVATIONS[self.activation]
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(self.weights):
            x = x @ w + b
            if i < last:
                x = act(x)
        return x

    def __call__(self, obs: Any) -> np.ndarray:
        """Deterministic action tanh(loc) in [-1, 1], shape (action_size,) or (N, action_size)."""
        return np.tanh(self.forward(obs)[..., : self.action_size])

    def config(self) -> Config:
        """The full training config the policy was exported with."""
        try:
            return config_from_dict(json.loads(self.config_json))
        except (ConfigError, ValueError, TypeError) as exc:
            raise PolicyFormatError(f"{self.path}: config_json does not load as a Config: {exc}") from None

    def env_config(self) -> EnvConfig:
        """The env config of training: the control-step constants the deployment loop must reuse."""
        return self.config().env

    def check_grasp_inputs(self) -> None:
        """Refuse (``PolicyFormatError``) a policy whose inputs are not the observation layout its config names:
        one exported from another env than the grasp task (``placeholder_layout``'s names), which
        ``load_policy`` lets through for inspection but nothing may run on the grasp task (the deploy loop,
        the twin, a rehearsal) — it would fail mid-episode, after the robot session is up."""
        if self.obs_layout != observation.layout_of(self.env_config()):
            raise PolicyFormatError(f"{self.path}: {input_mismatch(self.obs_layout, self.env_config())}; not a grasp "
                                    "policy, refused before anything connects")
        arm = robots.get(self.env_config().robot)
        if self.action_size != arm.dof:
            raise PolicyFormatError(f"{self.path}: {self.action_size} actions, but its robot {arm.name!r} has "
                                    f"{arm.dof} joints; refused before anything connects")

    def _check_obs(self, obs: Any) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        if obs.ndim not in (1, 2) or obs.shape[-1] != self.obs_size:
            raise ValueError(
                f"observation must have shape ({self.obs_size},) or (N, {self.obs_size}), got {obs.shape}"
            )
        bad = ~np.isfinite(obs)
        if bad.any():
            cols = sorted(set(np.nonzero(bad)[-1].tolist()))
            names = ", ".join(self.obs_layout[c] for c in cols)
            raise ValueError(f"observation has non-finite entries ({names}); refusing to act on it")
        return obs


def placeholder_layout(obs_size: int) -> tuple[str, ...]:
    """The input names of a policy exported from another env than the grasp task (``obs_0`` .. ``obs_N-1``: the
    tests' toy env, whose run config is a grasp config): such a file loads, and ``check_grasp_inputs`` keeps it
    off the grasp task."""
    return tuple(f"obs_{i}" for i in range(obs_size))


def input_mismatch(names: Sequence[str], env: EnvConfig) -> str:
    """What differs between a policy's input names and the observation layout its env config names."""
    expected = observation.layout_of(env)
    if len(names) != len(expected):
        head = f"{len(names)} inputs ({', '.join(names[:4])}{', ...' if len(names) > 4 else ''})"
        return (f"its {head} do not match its own config, whose {env.task.obs_layout!r} observation layout has "
                f"{len(expected)} ({', '.join(expected[:4])}, ...)")
    i = next(i for i, (a, b) in enumerate(zip(names, expected)) if a != b)
    return (f"its inputs do not match its own config's {env.task.obs_layout!r} observation layout: input {i} is "
            f"{names[i]!r} where the layout has {expected[i]!r}")


def _config_json(config: Config | Mapping[str, Any] | str) -> tuple[str, str]:
    """Canonical JSON of the training config and its hash; validates it loads back."""
    if isinstance(config, Config):
        cfg = config
    else:
        data = json.loads(config) if isinstance(config, str) else dict(config)
        cfg = config_from_dict(data)
    return json.dumps(config_to_dict(cfg), sort_keys=True), config_hash(cfg)


def save_policy_npz(
    path: str | os.PathLike[str],
    *,
    weights: Sequence[tuple[Any, Any]],
    activation: str,
    obs_mean: Any,
    obs_std: Any,
    config: Config | Mapping[str, Any] | str,
    obs_std_floor: float | None = None,
    obs_clip: float | None = None,
    action_scale: float | None = None,
    obs_layout: Sequence[str] = OBS_LAYOUT,
    package_version: str = __version__,
) -> str:
    """Write ``policy.npz`` atomically (temp file in the same folder, then ``os.replace``).

    ``weights`` are ``(W (in, out), b (out,))`` per dense layer, input to output.
    ``obs_std_floor``, ``obs_clip`` and ``action_scale`` default to the config's
    ``ppo.obs_std_floor``, ``ppo.obs_clip`` and ``env.control.q_max``; the std is
    floored here so the file holds exactly what the policy divides by.  The result
    is validated by the same checks as ``load_policy`` before anything is written, so
    a bad export fails at export time, not on the robot.  Returns the path.
    """
    path = os.fspath(path)
    cfg_json, cfg_hash = _config_json(config)
    cfg = config_from_dict(json.loads(cfg_json))
    floor = float(cfg.ppo.obs_std_floor if obs_std_floor is None else obs_std_floor)
    arrays: dict[str, np.ndarray] = {
        "format_version": np.asarray(FORMAT_VERSION, dtype=np.int64),
        "activation": np.asarray(activation),
        "obs_mean": np.asarray(obs_mean, dtype=np.float64),
        "obs_std": np.maximum(np.asarray(obs_std, dtype=np.float64), floor),
        "obs_std_floor": np.asarray(floor, dtype=np.float64),
        "obs_clip": np.asarray(cfg.ppo.obs_clip if obs_clip is None else obs_clip, dtype=np.float64),
        "obs_size": np.asarray(len(obs_layout), dtype=np.int64),
        "obs_layout": np.asarray(list(obs_layout), dtype=str),
        "action_scale": np.asarray(cfg.env.control.q_max if action_scale is None else action_scale, dtype=np.float64),
        "config_json": np.asarray(cfg_json),
        "config_hash": np.asarray(cfg_hash),
        "package_version": np.asarray(str(package_version)),
    }
    if not weights:
        raise PolicyFormatError(f"{path}: no policy layers given")
    out = np.asarray(weights[-1][0]).shape[-1]
    arrays["action_size"] = np.asarray(out // 2, dtype=np.int64)
    for i, (w, b) in enumerate(weights):
        w, b = np.asarray(w), np.asarray(b)
        if not (np.issubdtype(w.dtype, np.floating) and np.issubdtype(b.dtype, np.floating)):
            raise PolicyFormatError(f"{path}: layer {i} weights must be floating point, got {w.dtype}/{b.dtype}")
        arrays[f"layer_{i}_w"], arrays[f"layer_{i}_b"] = w, b
    _policy_from_arrays(arrays, path)  # refuse to write a file that would not load

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)

    fileio.atomic_write(path, write)
    return path


def _scalar(arrays: Mapping[str, np.ndarray], key: str, path: str, kind: type) -> Any:
    value = arrays[key]
    if value.shape != ():
        raise PolicyFormatError(f"{path}: {key} must be a scalar, got shape {value.shape}")
    if kind is str:
        if value.dtype.kind != "U":
            raise PolicyFormatError(f"{path}: {key} must be a string, got dtype {value.dtype}")
        return str(value)
    if kind is int:
        if value.dtype.kind not in "iu":
            raise PolicyFormatError(f"{path}: {key} must be an integer, got dtype {value.dtype}")
        return int(value)
    if value.dtype.kind not in "fiu":
        raise PolicyFormatError(f"{path}: {key} must be a number, got dtype {value.dtype}")
    number = float(value)
    if not np.isfinite(number):
        raise PolicyFormatError(f"{path}: {key} is {number}, expected a finite number")
    return number


def _policy_from_arrays(arrays: Mapping[str, np.ndarray], path: str) -> NumpyPolicy:
    """Every check that stands between a file and a robot moving on its output."""
    missing = [k for k in _SCALAR_KEYS if k not in arrays]
    if "layer_0_w" not in arrays:
        missing.append("layer_0_w")
    if missing:
        raise PolicyFormatError(f"{path}: missing keys {', '.join(missing)} (not a sagrasp_jax policy.npz?)")
    version = _scalar(arrays, "format_version", path, int)
    if version != FORMAT_VERSION:
        raise PolicyFormatError(
            f"{path}: format_version {version} is not supported (this sagrasp_jax {__version__} reads {FORMAT_VERSION})"
        )
    activation = _scalar(arrays, "activation", path, str)
    if activation not in ACTIVATIONS:
        raise PolicyFormatError(f"{path}: activation {activation!r} is not one of {', '.join(ACTIVATIONS)}")
    obs_size = _scalar(arrays, "obs_size", path, int)
    action_size = _scalar(arrays, "action_size", path, int)
    if obs_size < 1 or action_size < 1:
        raise PolicyFormatError(f"{path}: obs_size {obs_size} and action_size {action_size} must be positive")
    floor = _scalar(arrays, "obs_std_floor", path, float)
    clip = _scalar(arrays, "obs_clip", path, float)
    scale = _scalar(arrays, "action_scale", path, float)
    for key, value in (("obs_std_floor", floor), ("obs_clip", clip), ("action_scale", scale)):
        if value <= 0:
            raise PolicyFormatError(f"{path}: {key} = {value} must be > 0")

    layout = arrays["obs_layout"]
    if layout.dtype.kind != "U" or layout.shape != (obs_size,):
        raise PolicyFormatError(f"{path}: obs_layout must be {obs_size} strings, got {layout.dtype} {layout.shape}")
    vectors = {}
    for key in ("obs_mean", "obs_std"):
        v = arrays[key]
        if v.shape != (obs_size,) or v.dtype.kind not in "fiu":
            raise PolicyFormatError(f"{path}: {key} must be float ({obs_size},), got {v.dtype} {v.shape}")
        v = v.astype(np.float64)
        if not np.isfinite(v).all():
            bad = [str(layout[i]) for i in np.nonzero(~np.isfinite(v))[0]]
            raise PolicyFormatError(f"{path}: {key} has NaN/inf entries ({', '.join(bad)})")
        vectors[key] = v
    below = np.nonzero(vectors["obs_std"] < floor * (1 - 1e-6))[0]
    if below.size:
        i = int(below[0])
        raise PolicyFormatError(
            f"{path}: obs_std[{layout[i]}] = {vectors['obs_std'][i]:.3g} is below obs_std_floor {floor:g} "
            "(the file must hold the floored std)"
        )

    weights = []
    n_layers = 0
    while f"layer_{n_layers}_w" in arrays:
        n_layers += 1
    expected = {f"layer_{i}_{s}" for i in range(n_layers) for s in "wb"}
    extra = [k for k in arrays if k.startswith("layer_") and k not in expected]
    if extra:
        raise PolicyFormatError(f"{path}: layer keys {', '.join(sorted(extra))} do not follow layer_0..{n_layers - 1}")
    width = obs_size
    for i in range(n_layers):
        wk, bk = f"layer_{i}_w", f"layer_{i}_b"
        if bk not in arrays:
            raise PolicyFormatError(f"{path}: missing key {bk}")
        w, b = arrays[wk], arrays[bk]
        if w.ndim != 2 or w.shape[0] != width:
            raise PolicyFormatError(f"{path}: {wk} has shape {w.shape}, expected ({width}, out)")
        if b.shape != (w.shape[1],):
            raise PolicyFormatError(f"{path}: {bk} has shape {b.shape}, expected ({w.shape[1]},)")
        for key, arr in ((wk, w), (bk, b)):
            if arr.dtype.kind != "f":
                raise PolicyFormatError(f"{path}: {key} must be floating point, got {arr.dtype}")
            if not np.isfinite(arr).all():
                raise PolicyFormatError(f"{path}: {key} has {int((~np.isfinite(arr)).sum())} NaN/inf entries")
        weights.append((w.astype(np.float64), b.astype(np.float64)))
        width = w.shape[1]
    if width != 2 * action_size:
        raise PolicyFormatError(
            f"{path}: last layer outputs {width} numbers, expected 2·action_size = {2 * action_size} (loc, scale)"
        )

    cfg_json = _scalar(arrays, "config_json", path, str)
    stored_hash = _scalar(arrays, "config_hash", path, str)
    try:
        raw = parse_json(cfg_json)
        cfg = config_from_dict(raw)  # keys added since the file was written get their legacy values
        actual_hash = env_dict_hash(raw["env"])
    except (ConfigError, ValueError, TypeError, KeyError) as exc:
        raise PolicyFormatError(f"{path}: config_json does not load as a Config: {exc}") from None
    missing = [f"env.sampling.{k}" for k in RECORDED_CELL_KEYS
               if not isinstance(raw["env"].get("sampling"), dict) or k not in raw["env"]["sampling"]]
    if missing:  # filled from today's defaults they would pass the deployment's cell check unseen
        raise PolicyFormatError(
            f"{path}: config_json does not record {', '.join(missing)} (every policy file since format version 1 "
            "records the cell it was trained for: the obstacle clearance, the cube and the target region): file edited?"
        )
    if actual_hash != stored_hash:
        raise PolicyFormatError(
            f"{path}: config_hash {stored_hash} does not match its config_json ({actual_hash}): file edited?"
        )
    names = tuple(str(s) for s in layout)
    if names != observation.layout_of(cfg.env) and names != placeholder_layout(obs_size):
        raise PolicyFormatError(f"{path}: {input_mismatch(names, cfg.env)}")
    if not np.isclose(scale, cfg.env.control.q_max, rtol=1e-9, atol=0.0):
        raise PolicyFormatError(
            f"{path}: action_scale {scale} differs from the config's env.control.q_max {cfg.env.control.q_max}"
        )
    return NumpyPolicy(
        weights=tuple(weights),
        activation=activation,
        obs_mean=vectors["obs_mean"],
        obs_std=vectors["obs_std"],
        obs_std_floor=floor,
        obs_clip=clip,
        action_size=action_size,
        obs_size=obs_size,
        obs_layout=tuple(str(s) for s in layout),
        action_scale=scale,
        config_json=cfg_json,
        config_hash=stored_hash,
        package_version=_scalar(arrays, "package_version", path, str),
        path=path,
    )


# Policies shipped in the package (sagrasp_jax/pretrained/NAME.npz, provenance in NAME.json), by name: a robot PC
# with the core install deploys one without training.  "pretrained" is the README command's seed-0 policy.
PRETRAINED = {"cpu-quick-s0": "cpu_quick_s0", "pretrained": "cpu_quick_s0"}


def pretrained_path(name: str) -> str:
    """The packaged file of a pretrained policy's ``name`` (``PRETRAINED``)."""
    from sagrasp_jax.base import assets

    return os.path.join(assets.PRETRAINED_DIR, PRETRAINED[name] + ".npz")


def pretrained_provenance(name: str) -> dict[str, Any]:
    """What a pretrained policy is: its training command, config hash and measured figures."""
    from sagrasp_jax.base import assets

    with open(os.path.join(assets.PRETRAINED_DIR, PRETRAINED[name] + ".json"), encoding="utf-8") as fh:
        return json.load(fh)


POLICY_FILE_NAME = "policy.npz"  # what export writes into its --out folder and a training into its run folder
# What every command's --policy takes (resolve_policy), for their --help.
POLICY_HELP = ("the policy: a policy.npz file (export's output), a folder holding one (a finished run folder, or "
               "export's --out folder), or the name of a policy shipped in the package: pretrained (the README's "
               "policy, also named cpu-quick-s0). A name always means the packaged policy; a file or folder of that "
               "name in the working folder is given as a path, ./pretrained")


def resolve_policy(path: str | os.PathLike[str]) -> str:
    """A ``--policy`` argument as a file path.  A pretrained policy's name (``PRETRAINED``: ``pretrained``,
    ``cpu-quick-s0``) always means the packaged policy, whatever the working folder holds (a file or folder of
    that name is ``./pretrained``); a folder means its ``policy.npz`` (a run folder, or export's ``--out``);
    anything else is the policy file itself."""
    path = os.fspath(path)
    if path in PRETRAINED:
        return pretrained_path(path)
    if os.path.isdir(path):
        return os.path.join(path, POLICY_FILE_NAME)
    return path


MAX_POLICY_FILE_BYTES = 2 * 256 * 2**20  # a policy file's own size: its unpacked arrays' cap and the zip's headers


def load_policy(path: str | os.PathLike[str]) -> NumpyPolicy:
    """Read and validate ``policy.npz`` (or a pretrained policy by name, ``PRETRAINED``, or a folder holding a
    ``policy.npz``); raises PolicyFormatError naming the file and the problem.  The file is read whole through
    ``fileio.read_input`` (a FIFO, device or folder refused before it is opened, the size bounded), then its
    members as ``read_npz`` allows."""
    given = os.fspath(path)
    path = resolve_policy(given)
    if path != given:  # a folder without a policy file
        not_found = (f"{given} is a folder without a {POLICY_FILE_NAME} (a training writes one into its run folder "
                     "when it finishes; export writes one into its --out folder)")
    else:
        not_found = f"{path}: policy file not found (or a pretrained policy's name: {', '.join(sorted(PRETRAINED))})"
    data = fileio.read_input(path, MAX_POLICY_FILE_BYTES, "policy file", PolicyFormatError, not_found)
    try:
        arrays = read_npz(path, io.BytesIO(data))
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError, NotImplementedError,
            RuntimeError) as exc:
        if isinstance(exc, PolicyFormatError):
            raise
        raise PolicyFormatError(f"{path}: not a readable .npz archive ({type(exc).__name__}: {exc})") from None
    return dataclasses.replace(_policy_from_arrays(arrays, path), file_sha256=hashlib.sha256(data).hexdigest())


MAX_POLICY_BYTES = 256 * 2**20  # unpacked arrays of one policy file (a 4-layer 2048-wide float64 MLP is ≈ 100 MB)
MAX_POLICY_MEMBERS = 1024


def npy_header(stream: Any, total_bytes: int, holder: str) -> tuple[tuple[int, ...], bool, np.dtype, int]:
    """A ``.npy`` stream's header read and checked against the ``total_bytes`` the file (or zip member) holds,
    before anything is allocated: ``(shape, fortran_order, dtype, data_bytes)``, the stream left at the data.
    A header claiming more (or fewer) bytes than are there, another format version or pickled objects raise a
    ``ValueError`` saying which (the policy and calibration readers name the file; ``holder``: "file", "member")."""
    version = np.lib.format.read_magic(stream)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(stream)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(stream)
    else:
        raise ValueError(f"format version {version} is not read (.npy 1.0 and 2.0 are)")
    if dtype.hasobject:
        raise ValueError("array holds Python objects (pickles are not read)")
    size = int(np.prod(shape, dtype=object)) * dtype.itemsize
    stored = total_bytes - stream.tell()
    if size != stored:
        raise ValueError(f"header claims {dtype}{list(shape)} ({size} bytes) but the {holder} holds {stored} bytes; "
                         "not read")
    return shape, fortran, dtype, size


def read_npz(path: str, source: Any = None, *, max_bytes: int = MAX_POLICY_BYTES, max_members: int = MAX_POLICY_MEMBERS,
             error: type[ValueError] = PolicyFormatError, what: str = "a policy file") -> dict[str, np.ndarray]:
    """The arrays of an ``np.savez`` archive, reading no more than its sizes allow: the members'
    unpacked sizes (zip directory) and each ``.npy`` header's shape are checked against ``max_bytes``
    and against each other before any array is allocated, so a header claiming gigabytes or a zip bomb
    is refused (``error``, naming ``path``) instead of filling the memory.  The policy and capture readers."""
    arrays: dict[str, np.ndarray] = {}
    with zipfile.ZipFile(path if source is None else source) as zf:
        infos = zf.infolist()
        total = sum(info.file_size for info in infos)
        if len(infos) > max_members or total > max_bytes:
            raise error(f"{path}: {len(infos)} members of {total} bytes unpacked, over the "
                        f"{max_bytes} bytes {what} may hold (zip bomb?); not read")
        for info in infos:
            if not info.filename.endswith(".npy"):
                raise error(f"{path}: member {info.filename!r} is not a .npy array")
            with zf.open(info) as f:
                try:
                    shape, fortran, dtype, size = npy_header(f, info.file_size, "member")
                except ValueError as exc:
                    raise error(f"{path}: {info.filename}'s {exc}") from None
                data = f.read(size)
            if len(data) != size:
                raise error(f"{path}: {info.filename} is cut short")
            arr = np.frombuffer(data, dtype=dtype)
            arrays[info.filename[:-4]] = (arr.reshape(shape[::-1]).T if fortran else arr.reshape(shape)).copy()
    return arrays
