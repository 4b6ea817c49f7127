"""The layer rules of docs/architecture.md hold for the package's real import graph.

The table in the doc is the source of truth: this test parses it, derives every import of every
package module with ``ast`` (imports inside functions too: a lazy import is still a dependency)
and checks that each module is listed once, nothing imports a layer above its own, entry points
do not import each other, there is no import cycle, and jax-free modules stay jax-free.
"""

from __future__ import annotations

import ast
import os
import re

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGE = os.path.join(REPO, "sagrasp_jax")
DOC = os.path.join(REPO, "docs", "architecture.md")
JAX_ROOTS = ("jax", "jaxlib", "flax", "optax", "brax", "mujoco.mjx")


def _expand(token: str) -> list[str]:
    """`deploy/{a,b}` -> ['deploy.a', 'deploy.b']; `deploy/__init__` -> 'deploy'."""
    m = re.fullmatch(r"(.*)\{(.*)\}(.*)", token)
    names = [m.group(1) + part + m.group(3) for part in m.group(2).split(",")] if m else [token]
    return [re.sub(r"\.__init__$", "", n.replace("/", ".")) for n in names]


def _names(cell: str) -> list[str]:
    return [n for tok in re.findall(r"`([^`]+)`", cell) for n in _expand(tok)]


def doc_layers() -> tuple[list[str], dict[str, int], set[str]]:
    """(layer titles top to bottom, module -> layer index, jax-free modules) from the doc's table."""
    with open(DOC, encoding="utf-8") as f:
        text = f.read()
    rows = re.findall(r"^\|(.+)\|(.+)\|(.+)\|$", text.split("## Layers", 1)[1].split("\n## ", 1)[0], re.M)
    rows = [r for r in rows if not set(r[0].strip()) <= {"-"} and r[0].strip() != "layer"]
    titles, layer_of, jax_free = [], {}, set()
    for index, (title, modules, free) in enumerate(rows):
        titles.append(title.strip())
        names = _names(modules)
        for name in names:
            assert name not in layer_of, f"{name} is listed twice in {DOC}"
            layer_of[name] = index
        free = free.strip()
        if free == "all":
            jax_free |= set(names)
        elif free.startswith("all but"):
            jax_free |= set(names) - set(_names(free))
        else:
            jax_free |= set(_names(free))
    return titles, layer_of, jax_free


def package_modules() -> dict[str, str]:
    """Dotted module name (without 'sagrasp_jax.'; a package by its name) -> file path."""
    out = {}
    for folder, _, files in os.walk(PACKAGE):
        for name in files:
            if name.endswith(".py") and "__pycache__" not in folder:
                rel = os.path.relpath(os.path.join(folder, name), PACKAGE)[:-3]
                mod = re.sub(r"(^|\.)__init__$", "", rel.replace(os.sep, "."))
                if mod:  # the package root only sets environment variables; everything imports it
                    out[mod] = os.path.join(folder, name)
    return out


def imports(file: str, module: str, known: set[str]) -> tuple[set[str], set[str]]:
    """(package modules, external top-level names) imported anywhere in ``file``."""
    with open(file, encoding="utf-8") as f:
        tree = ast.parse(f.read(), file)
    inner, outer = set(), set()
    package = module if file.endswith("__init__.py") else module.rpartition(".")[0]

    def add(name: str) -> None:
        if name == "sagrasp_jax":
            return
        if name.startswith("sagrasp_jax."):
            name = name[len("sagrasp_jax."):]
            while name and name not in known:  # `from sagrasp_jax.x import y`: x (y may be a name)
                name = name.rpartition(".")[0]
            if name:
                inner.add(name)
        else:
            outer.add(name)

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".") if package else []
                base = base[: len(base) - node.level + 1]
                target = ".".join(["sagrasp_jax", *base, *([node.module] if node.module else [])])
            else:
                target = node.module or ""
            for alias in node.names:  # `from sagrasp_jax import x`: x is a module when the package has one
                full = f"{target}.{alias.name}"
                add(full if full.startswith("sagrasp_jax.") and full[len("sagrasp_jax."):] in known else target)
            if target == "mujoco" and any(a.name == "mjx" for a in node.names):
                outer.add("mujoco.mjx")
    inner.discard(module)
    return inner, outer


@pytest.fixture(scope="module")
def graph() -> dict[str, tuple[set[str], set[str]]]:
    mods = package_modules()
    return {m: imports(f, m, set(mods)) for m, f in mods.items()}


def test_every_module_is_in_exactly_one_layer(graph):
    _, layer_of, _ = doc_layers()
    assert sorted(set(graph) - set(layer_of)) == [], f"modules missing from the table in {DOC}"
    assert sorted(set(layer_of) - set(graph)) == [], f"{DOC} lists modules that do not exist"


def test_no_module_imports_a_layer_above_its_own(graph):
    titles, layer_of, _ = doc_layers()
    upward = [f"{m} ({titles[layer_of[m]]}) imports {d} ({titles[layer_of[d]]})"
              for m, (deps, _) in sorted(graph.items()) for d in sorted(deps) if layer_of[d] < layer_of[m]]
    assert upward == []


def test_entry_points_do_not_import_each_other(graph):
    _, layer_of, _ = doc_layers()
    sideways = [f"{m} imports {d}" for m, (deps, _) in sorted(graph.items()) if layer_of[m] == 0
                for d in sorted(deps) if layer_of[d] == 0]
    assert sideways == []


def test_no_import_cycle(graph):
    state: dict[str, int] = {}
    cycles: list[str] = []

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for d in sorted(graph[m][0]):
            if state.get(d) == 1:
                cycles.append(" -> ".join(stack[stack.index(d):] + [d]))
            elif d not in state:
                visit(d, stack + [d])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert cycles == []


def test_jax_free_modules_stay_jax_free(graph):
    _, _, jax_free = doc_layers()
    bad = []
    for m in sorted(jax_free):
        deps, external = graph[m]
        bad += [f"{m} imports {e}" for e in sorted(external) if e.split(".")[0] in JAX_ROOTS[:-1] or e == "mujoco.mjx"]
        bad += [f"{m} imports {d}, which is not jax-free" for d in sorted(deps - jax_free)]
    assert bad == []


def test_the_exact_geometry_oracle_stays_outside_the_package():
    """tests/exact_geometry.py holds the exact pair distances the tests check the per-step rules
    against; production code uses geometry's few queries and never imports the oracle."""
    assert os.path.isfile(os.path.join(REPO, "tests", "exact_geometry.py"))
    def imported(file: str) -> set[str]:
        tree = ast.parse(open(file, encoding="utf-8").read())
        names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        names |= {f"{n.module}.{a.name}" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names}
        return names

    users = sorted(m for m, file in package_modules().items() if any("exact_geometry" in i for i in imported(file)))
    assert users == []


def test_the_checker_sees_lazy_and_relative_imports(tmp_path):
    """The graph includes imports inside functions (the kind issue 17 found evaluate <-> physical by)."""
    file = tmp_path / "mod.py"
    file.write_text("import os\ndef f():\n    from sagrasp_jax.train import run\n    from sagrasp_jax import ppo\n"
                    "    from mujoco import mjx\n")
    inner, outer = imports(str(file), "physical", {"train", "ppo", "physical"})
    assert inner == {"train", "ppo"} and {"os", "mujoco.mjx"} <= outer


# ---------------------------------------------------------------------- import noise (issue 17, item 6)

def _import_output(tmp_path, extra_path: str | None = None) -> str:
    import subprocess
    import sys

    env = dict(os.environ)
    if extra_path:
        env["PYTHONPATH"] = extra_path + os.pathsep + env.get("PYTHONPATH", "")
    code = "import sagrasp_jax.env, sagrasp_jax.train, sagrasp_jax.evaluate, sagrasp_jax.physical; print('imported')"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stdout + res.stderr


def test_no_warp_noise_when_warp_is_not_installed(tmp_path):
    pytest.importorskip("mujoco")
    out = _import_output(tmp_path)
    assert "imported" in out and "Failed to import" not in out, out


def test_a_broken_warp_install_still_shows(tmp_path):
    """Only the 'warp is not installed' lines are dropped; any other warp failure is printed."""
    import sagrasp_jax

    fake = tmp_path / "warp"
    fake.mkdir()
    (fake / "__init__.py").write_text('raise ImportError("libcuda.so.1: cannot open shared object file")\n')
    out = _import_output(tmp_path, str(tmp_path))
    assert "Failed to import warp: libcuda.so.1: cannot open shared object file" in out, out
    text = ("Failed to import warp: No module named 'warp'\nFailed to import mujoco_warp: No module named 'warp'\n"
            "Failed to import warp: CUDA 12.4 required\nsomething else\n")
    assert sagrasp_jax.filter_warp_noise(text) == "Failed to import warp: CUDA 12.4 required\nsomething else\n"
