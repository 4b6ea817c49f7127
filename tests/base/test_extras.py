"""The chain a user types: ``python -m sagrasp_jax``, the console scripts, the extras and their hints.

A missing package is simulated in a fresh interpreter by ``sys.modules[name] = None`` (Python then
raises ``ModuleNotFoundError`` for ``import name``, as in an install without it); nothing is
uninstalled.  ``tests/test_install.py`` checks the same paths from real venvs built from the wheel.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tomllib

import pytest

from sagrasp_jax import __main__ as cli
from sagrasp_jax.base import extras
from paths import REPO  # noqa: E402

PACKAGE = os.path.join(REPO, "sagrasp_jax")
# distribution (pyproject) -> the import name the package uses, where it is not the name with '_' for '-'
IMPORT_NAME = {"mujoco-mjx": "mujoco", "warp-lang": "warp", "tensorboard": None, "playground": "mujoco_playground",
               "mecheyeapi": "mecheye"}
EVERY_OPTIONAL = sorted({n for names in extras.EXTRAS.values() for n in names} | {"jaxlib"})


def _pyproject() -> dict:
    with open(os.path.join(REPO, "pyproject.toml"), "rb") as f:
        return tomllib.load(f)["project"]


def _python(code: str, *args: str, blocked: tuple[str, ...] = ()) -> subprocess.CompletedProcess[str]:
    """Run ``code`` in a fresh interpreter where the packages ``blocked`` are not importable."""
    prelude = f"import sys\nfor _n in {list(blocked)!r}:\n    sys.modules[_n] = None\n"
    return subprocess.run([sys.executable, "-c", prelude + code, *args], cwd=REPO, capture_output=True, text=True,
                          timeout=300)


def _modules() -> list[str]:
    out = []
    for folder, _, files in os.walk(PACKAGE):
        for name in sorted(files):
            if name.endswith(".py") and "__pycache__" not in folder:
                rel = os.path.relpath(os.path.join(folder, name), REPO)[:-3].replace(os.sep, ".")
                out.append(re.sub(r"\.__init__$", "", rel))
    return sorted(out)


# ---------------------------------------------------------------------- the extras

def test_extras_table_matches_pyproject():
    """extras.EXTRAS names, per extra of pyproject (the vendors' robot SDKs are not on the index and
    only in EXTRAS), the import names of its optional dependencies."""
    deps = _pyproject()["optional-dependencies"]
    assert set(deps) - {"test", "baseline"} <= set(extras.EXTRAS)
    for extra, names in extras.EXTRAS.items():
        if extra not in deps:
            continue
        dists = [re.split(r"[<>=!~\[ ]", r, maxsplit=1)[0] for r in deps[extra]]
        imported = {IMPORT_NAME.get(d, d.replace("-", "_")) for d in dists} - {None}
        bundled = {n for other in extras.BUNDLED.get(extra, ()) for n in extras.EXTRAS[other]}
        assert set(names) | bundled == imported, (extra, names, dists)


def test_train_install_covers_export():
    """The export after a training, ONNX included, needs nothing beyond ``[train]``."""
    deps = _pyproject()["optional-dependencies"]
    assert set(deps["export"]) <= set(deps["train"])
    assert extras.BUNDLED["train"] == ("export",)
    outside_train = sorted(set(EVERY_OPTIONAL) - set(extras.EXTRAS["train"]) - set(extras.EXTRAS["export"]) - {"jaxlib"})
    res = _python("from sagrasp_jax import export; sys.exit(export.main(['--run', 'no-such-run', '--out', 'x']))",
                  blocked=tuple(outside_train))
    assert res.returncode == 2, res.stderr
    assert "no-such-run" in res.stderr and "pip install" not in res.stderr, res.stderr  # past the extras check


@pytest.mark.parametrize("missing, wording", [
    (["jax"], "needs jax, which is not installed"),
    (["onnx", "onnxruntime"], "needs onnx and onnxruntime, which are not installed"),
    (["jax", "mujoco", "brax"], "needs jax, mujoco and brax, which are not installed"),
])
def test_hint_wording(missing, wording):
    exc = extras.MissingExtra(("train",), missing, "it")
    assert str(exc) == f'it {wording}: pip install "sagrasp_jax[train]"'


def test_missing_extra_is_named_per_package():
    assert [extras.extra_providing(n) for n in ("jax", "mujoco.mjx", "pybullet", "gymnasium", "onnx", "matplotlib",
                                                "imageio_ffmpeg", "warp", "numpy")] == \
        ["train", "train", "twin", "reference", "export", "plots", "render", "warp", None]


CORE_IMPORTS = r'''
import importlib, json
from sagrasp_jax.base import extras
out = {}
for name in sys.argv[1:]:
    try:
        importlib.import_module(name)
        out[name] = "ok"
    except extras.MissingExtra as exc:
        out[name] = "hint: " + str(exc)
    except BaseException as exc:
        out[name] = f"bare {type(exc).__name__}: {exc}"
    for mod in [m for m in sys.modules if m.startswith("sagrasp_jax.") and m != "sagrasp_jax.base.extras"]:
        del sys.modules[mod]  # the next import runs its dependencies afresh
print(json.dumps(out))
'''


def test_every_module_in_a_core_install_imports_or_names_its_extra():
    """With every optional package absent (the core install), each package module either imports (the
    robot side) or raises MissingExtra with the install hint; none ends in a bare ModuleNotFoundError."""
    res = _python(CORE_IMPORTS, *_modules(), blocked=tuple(EVERY_OPTIONAL))
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.splitlines()[-1])
    bare = {m: v for m, v in out.items() if v.startswith("bare")}
    assert bare == {}
    for name in ("sagrasp_jax.task.policy_file", "sagrasp_jax.deploy.loop", "sagrasp_jax.deploy.safety", "sagrasp_jax.render",
                 "sagrasp_jax.plot", "sagrasp_jax.deploy.sysid", "sagrasp_jax.__main__", "sagrasp_jax.deploy.__main__"):
        assert out[name] == "ok", (name, out[name])
    assert out["sagrasp_jax.envs"] == "ok"  # the folder's names load on first use (``envs.load``: see LIBRARY_CASES)
    assert out["sagrasp_jax.envs.brax_adapter"] == (
        "hint: sagrasp_jax.envs.brax_adapter needs jax, mujoco, brax, flax, optax, tensorboardX and "
        'tqdm, which are not installed: pip install "sagrasp_jax[train]"')
    assert out["sagrasp_jax.deploy.twin"].endswith('pip install "sagrasp_jax[twin]"')
    hinted = [m for m, v in out.items() if v.startswith("hint")]
    assert len(hinted) >= 15 and all('pip install "sagrasp_jax[' in out[m] for m in hinted)


LIBRARY_CASES = {  # absent package: (code that needs it, the extra the hint names)
    "jax": ("from sagrasp_jax import envs\nenvs.load('grasp-kinematic')", "train"),
    "gymnasium": ("from sagrasp_jax.reference.pybullet_env import PyBulletGraspEnv\nPyBulletGraspEnv()", "reference"),
    "pybullet": ("import sagrasp_jax.deploy.twin", "twin"),
    "matplotlib": ("from sagrasp_jax import plot\nplot.require_matplotlib()", "plots"),
}


@pytest.mark.parametrize("package", sorted(LIBRARY_CASES))
def test_library_use_names_the_extra(package):
    """With one package absent, the library call that needs it raises MissingExtra naming its extra."""
    code, extra = LIBRARY_CASES[package]
    indented = "\n".join("    " + line for line in code.splitlines())
    res = _python(f"from sagrasp_jax.base import extras\ntry:\n{indented}\nexcept extras.MissingExtra as exc:\n    print(exc)\n",
                  blocked=(package,))
    assert res.returncode == 0, res.stderr[-3000:]
    assert f"needs {package}, which is not installed" in res.stdout, res.stdout
    assert res.stdout.strip().endswith(f'pip install "sagrasp_jax[{extra}]"'), res.stdout


def test_export_without_onnx_names_the_extra():
    res = _python("from sagrasp_jax import export\nsys.exit(export.main(['--run', 'r', '--out', 'o']))",
                  blocked=("onnx", "onnxruntime"))
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert res.stderr.strip().endswith('needs onnx and onnxruntime, which are not installed: '
                                       'pip install "sagrasp_jax[export]"'), res.stderr


# ---------------------------------------------------------------------- python -m sagrasp_jax and the scripts

def test_python_m_sagrasp_jax_lists_every_command_on_one_line():
    res = subprocess.run([sys.executable, "-m", "sagrasp_jax"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    for name, cmd in cli.COMMANDS.items():
        (line,) = [ln for ln in res.stdout.splitlines() if ln.split()[:1] == [name]]
        assert cmd.summary in line and len(line) <= 120
        path = os.path.join(PACKAGE, *cmd.module.split("."))
        assert os.path.exists(path + ".py") or os.path.exists(os.path.join(path, "__main__.py"))
    assert {"train", "evaluate", "render", "plot", "export", "deploy", "sysid"} <= set(cli.COMMANDS)
    bad = subprocess.run([sys.executable, "-m", "sagrasp_jax", "trian"], cwd=REPO, capture_output=True, text=True,
                         timeout=60)
    assert bad.returncode == 2 and "unknown command 'trian'" in bad.stderr


def test_console_scripts_point_at_the_launchers():
    scripts = _pyproject()["scripts"]
    assert set(scripts) == {f"sagrasp-{name}" for name in cli.COMMANDS}
    for script, target in scripts.items():
        module, _, attr = target.partition(":")
        assert module == "sagrasp_jax.__main__" and callable(getattr(cli, attr)) and script == f"sagrasp-{attr}"


def test_a_launcher_runs_its_command_and_a_missing_extra_is_one_line():
    """sagrasp-sysid --help is python -m sagrasp_jax.sysid --help; sagrasp-train in a core install exits 2
    with the hint and no traceback."""
    launch = "sys.argv = ['sagrasp-{0}', *sys.argv[1:]]\nfrom sagrasp_jax.__main__ import {0}\n{0}()\n"
    res = _python(launch.format("sysid"), "--help")
    assert res.returncode == 0 and res.stdout.startswith("usage: python -m sagrasp_jax.sysid"), res.stdout + res.stderr
    res = _python(launch.format("train"), "--help", blocked=tuple(EVERY_OPTIONAL))
    assert res.returncode == 2 and res.stdout == "", res.stdout
    assert res.stderr.strip() == ('python -m sagrasp_jax.train: error: python -m sagrasp_jax.train needs '
                                  + ", ".join(extras.EXTRAS["train"][:-1]) + f" and {extras.EXTRAS['train'][-1]}, "
                                  'which are not installed: pip install "sagrasp_jax[train]"'), res.stderr
