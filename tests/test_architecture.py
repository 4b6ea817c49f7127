"""The layer rules of docs/architecture.md (by folder) hold for the package's real import graph.

The table in the doc is the source of truth: this test parses it, derives every import of every
package module with ``ast`` (imports inside functions too: a lazy import is still a dependency)
and checks that each module is listed once, nothing imports a layer above its own, entry points
do not import each other, there is no import cycle, and jax-free modules stay jax-free.

``experiments/`` (the studies, above the package and outside its wheel) is checked the same way: its
scripts' import graph has no cycle, no package module imports it, and it holds at most
``MAX_EXPERIMENT_SCRIPTS`` scripts (the count the doc states).
"""

from __future__ import annotations

import ast
import os
import re

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGE = os.path.join(REPO, "sagrasp_jax")
DOC = os.path.join(REPO, "docs", "architecture.md")
EXPERIMENTS = os.path.join(REPO, "experiments")
MAX_EXPERIMENT_SCRIPTS = 12  # issue 56: the live studies only; fold a new one into the script it belongs with
JAX_ROOTS = ("jax", "jaxlib", "flax", "optax", "brax", "mujoco.mjx")


def _expand(token: str) -> list[str]:
    """`reference/parity` -> 'reference.parity'; `deploy/` -> 'deploy'; `sagrasp_jax/*.py` -> '' (the commands)."""
    if token == "sagrasp_jax/*.py":
        return [""]
    return [token.rstrip("/").replace("/", ".")]


def _names(cell: str) -> list[str]:
    return [n for tok in re.findall(r"`([^`]+)`", cell) for n in _expand(tok)]


def doc_layers() -> tuple[list[str], dict[str, int], set[str]]:
    """(layer titles top to bottom, folder -> layer index, jax-free module names: a folder's name stands for
    all its modules) from the doc's table."""
    with open(DOC, encoding="utf-8") as f:
        text = f.read()
    rows = re.findall(r"^\|(.+)\|(.+)\|(.+)\|$", text.split("## Layers", 1)[1].split("\n## ", 1)[0], re.M)
    rows = [r for r in rows if not set(r[0].strip()) <= {"-"} and r[0].strip() != "layer"]
    titles, layer_of, jax_free = [], {}, set()
    for index, (title, folders, free) in enumerate(rows):
        titles.append(title.strip())
        (folder,) = _names(folders)
        assert folder not in layer_of, f"{folder or 'the commands'} are listed twice in {DOC}"
        layer_of[folder] = index
        free = free.strip()
        if free == "all":
            jax_free.add(folder)
        elif free.startswith("all but"):
            jax_free.add(folder)
            jax_free |= {"!" + n for n in _names(free)}
        elif free.startswith("none but"):
            jax_free |= set(_names(free))
        elif free != "none":
            jax_free |= {n if "." in n or not folder else f"{folder}.{n}" for n in _names(free)}
    return titles, layer_of, jax_free


def is_jax_free(module: str, jax_free: set[str]) -> bool:
    if "!" + module in jax_free:
        return False
    return module in jax_free or _folder(module) in jax_free and _folder(module) != ""


def _folder(module: str) -> str:
    """The module's folder ('' for the commands at the top; a subpackage's own __init__ is in its folder)."""
    return module.split(".")[0] if module.split(".")[0] in SUBPACKAGES else ""


SUBPACKAGES = {n for n in os.listdir(PACKAGE) if os.path.isfile(os.path.join(PACKAGE, n, "__init__.py"))}


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


def test_every_folder_is_in_exactly_one_layer(graph):
    _, layer_of, _ = doc_layers()
    folders = {_folder(m) for m in graph}
    assert sorted(folders - set(layer_of)) == [], f"folders missing from the table in {DOC}"
    assert sorted(set(layer_of) - folders) == [], f"{DOC} lists folders that do not exist"


def test_no_module_imports_a_folder_above_its_own(graph):
    titles, layer_of, _ = doc_layers()
    upward = [f"{m} ({titles[layer_of[_folder(m)]]}) imports {d} ({titles[layer_of[_folder(d)]]})"
              for m, (deps, _) in sorted(graph.items()) for d in sorted(deps)
              if layer_of[_folder(d)] < layer_of[_folder(m)]]
    assert upward == []


def test_commands_do_not_import_each_other(graph):
    sideways = [f"{m} imports {d}" for m, (deps, _) in sorted(graph.items()) if _folder(m) == ""
                for d in sorted(deps) if _folder(d) == ""]
    assert sideways == []


def import_cycles(deps: dict[str, set[str]]) -> list[str]:
    """Every cycle a depth-first walk of ``deps`` (module -> the modules it imports) closes, as 'a -> b -> a'."""
    state: dict[str, int] = {}
    cycles: list[str] = []

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for d in sorted(deps[m]):
            if state.get(d) == 1:
                cycles.append(" -> ".join(stack[stack.index(d):] + [d]))
            elif d not in state:
                visit(d, stack + [d])
        state[m] = 2

    for m in sorted(deps):
        if m not in state:
            visit(m, [m])
    return cycles


def test_no_import_cycle(graph):
    assert import_cycles({m: deps for m, (deps, _) in graph.items()}) == []


def test_jax_free_modules_stay_jax_free(graph):
    _, _, jax_free = doc_layers()
    free = {m for m in graph if is_jax_free(m, jax_free)}
    assert {"task.config", "deploy.loop", "reference.pybullet_env", "training.sa_schedule", "plot"} <= free
    assert not {"reference.parity", "training.agents.ppo.ppo", "envs.grasp_env", "train"} & free
    bad = []
    for m in sorted(free):
        deps, external = graph[m]
        bad += [f"{m} imports {e}" for e in sorted(external) if e.split(".")[0] in JAX_ROOTS[:-1] or e == "mujoco.mjx"]
        bad += [f"{m} imports {d}, which is not jax-free" for d in sorted(deps - free)]
    assert bad == []


def test_the_robot_side_imports_no_jax_mujoco_or_brax(graph):
    """Everything deploy/ imports, directly or through other package modules, runs without jax, brax and mujoco."""
    seen: set[str] = set()
    todo = [m for m in graph if _folder(m) == "deploy"]
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo.extend(graph[m][0])
    bad = sorted(f"{m} imports {e}" for m in seen for e in graph[m][1]
                 if e.split(".")[0] in ("jax", "jaxlib", "flax", "optax", "brax", "mujoco"))
    assert len(seen) > 20 and bad == []


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
    inner, outer = imports(str(file), "reference.grasp_check", {"train", "ppo", "reference.grasp_check"})
    assert inner == {"train", "ppo"} and {"os", "mujoco.mjx"} <= outer


# ---------------------------------------------------------------------- experiments/ (issue 56, item 5)

def experiment_modules(root: str = EXPERIMENTS) -> dict[str, str]:
    """The scripts of ``experiments/`` (dotted name below ``experiments``; its ``__init__`` is no script) -> file."""
    out = {}
    for folder, _, files in os.walk(root):
        for name in files:
            if name.endswith(".py") and name != "__init__.py" and "__pycache__" not in folder:
                rel = os.path.relpath(os.path.join(folder, name), root)[:-3]
                out[rel.replace(os.sep, ".")] = os.path.join(folder, name)
    return out


def experiment_imports(file: str, module: str, known: set[str]) -> set[str]:
    """Every name ``file`` imports anywhere (inside functions too), dotted in full: experiments modules as
    'experiments.NAME' (relative imports resolved), everything else as written."""
    with open(file, encoding="utf-8") as f:
        tree = ast.parse(f.read(), file)
    package = ["experiments", *module.split(".")[:-1]]
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = ".".join(package[: len(package) - node.level + 1] + ([node.module] if node.module else [])) \
                if node.level else node.module or ""
            for alias in node.names:  # `from experiments import study`: study is a module
                full = f"{base}.{alias.name}"
                out.add(full if full.startswith("experiments.") and full[len("experiments."):] in known else base)
    return out


def experiments_graph(root: str = EXPERIMENTS) -> dict[str, set[str]]:
    """experiments module -> the experiments modules it imports."""
    mods = experiment_modules(root)
    graph = {}
    for m, file in mods.items():
        deps = set()
        for name in experiment_imports(file, m, set(mods)):
            if name.startswith("experiments."):
                name = name[len("experiments."):]
                while name and name not in mods:  # `from experiments.study import watch_trainer`: study
                    name = name.rpartition(".")[0]
                if name and name != m:
                    deps.add(name)
        graph[m] = deps
    return graph


def test_experiments_hold_at_most_twelve_scripts():
    scripts = sorted(experiment_modules())
    assert "study" in scripts and len(scripts) <= MAX_EXPERIMENT_SCRIPTS, (
        f"experiments/ holds {len(scripts)} scripts ({', '.join(scripts)}); at most {MAX_EXPERIMENT_SCRIPTS}: "
        "fold a new one into the script it belongs with as a subcommand")
    with open(DOC, encoding="utf-8") as f:
        stated = re.findall(r"\((\d+) scripts\)", f.read())
    assert stated == [str(len(scripts))], f"{DOC} says ({', '.join(stated)} scripts); experiments/ holds {len(scripts)}"


def test_no_import_cycle_among_experiments():
    graph = experiments_graph()
    assert sum(map(len, graph.values())) > 5  # the checker sees the scripts' shared imports
    assert import_cycles(graph) == []


def test_no_package_module_imports_experiments(graph):
    """The studies sit above the package and outside its wheel: nothing in sagrasp_jax imports them."""
    upward = sorted(f"{m} imports {e}" for m, (_, external) in graph.items() for e in external
                    if e.split(".")[0] == "experiments")
    assert upward == []


def test_the_checker_sees_experiments_cycles_and_upward_imports(tmp_path):
    """A cycle through a lazy or relative import is found, and so is a package module importing a study."""
    root = tmp_path / "experiments"
    root.mkdir()
    (root / "__init__.py").write_text("")
    (root / "study.py").write_text("import os\n")
    (root / "a.py").write_text("from experiments import study\ndef f():\n    from experiments.b import g\n")
    (root / "b.py").write_text("from .a import f\nfrom . import study\n")
    graph = experiments_graph(str(root))
    assert graph == {"study": set(), "a": {"study", "b"}, "b": {"a", "study"}}
    assert import_cycles(graph) == ["a -> b -> a"]
    file = tmp_path / "mod.py"
    file.write_text("def f():\n    from experiments.study import watch_trainer\n")
    _, outer = imports(str(file), "train", {"train"})
    assert "experiments.study" in outer


# ---------------------------------------------------------------------- import noise (issue 17, item 6)

def _import_output(tmp_path, extra_path: str | None = None) -> str:
    import subprocess
    import sys

    env = dict(os.environ)
    if extra_path:
        env["PYTHONPATH"] = extra_path + os.pathsep + env.get("PYTHONPATH", "")
    code = "import sagrasp_jax.envs.grasp_env, sagrasp_jax.train, sagrasp_jax.evaluate, sagrasp_jax.reference.grasp_check; print('imported')"
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


def test_old_flat_module_paths_import_with_a_message_naming_the_new_one():
    """Modules moved into the layer folders still import at the paths the docs and users had, as the same
    module object (a patch on one is a patch on the other), with a DeprecationWarning naming the new path."""
    import importlib
    import subprocess
    import sys

    import sagrasp_jax

    assert sagrasp_jax.MOVED_MODULES["runtime"] == "task.policy_file"
    for old, new in sagrasp_jax.MOVED_MODULES.items():  # every target exists in the tree
        assert os.path.isfile(os.path.join(PACKAGE, *new.split(".")) + ".py"), new
    code = ("import warnings, importlib\nwarnings.simplefilter('error')\n"
            "try:\n    import sagrasp_jax.runtime\nexcept DeprecationWarning as w:\n    print(w)\n"
            "warnings.simplefilter('ignore')\nimport sagrasp_jax.runtime as old, sagrasp_jax.task.policy_file as new\n"
            "from sagrasp_jax import config\nprint(old is new, config.__name__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == ["sagrasp_jax.runtime moved to sagrasp_jax.task.policy_file; import it from there",
                                       "True sagrasp_jax.task.config"]
    assert importlib.import_module("sagrasp_jax.envs").load.__module__ == "sagrasp_jax.envs.brax_adapter"


def test_ppo_maths_at_their_old_training_paths_import_with_a_message_naming_the_new_one():
    """PPO's modules moved from the flat ``training/`` into ``training/agents/ppo/`` (issue 56): the old
    ``sagrasp_jax.training.ppo`` is the new module, with a DeprecationWarning naming it."""
    import subprocess
    import sys

    code = ("import warnings\nwarnings.simplefilter('error')\n"
            "try:\n    import sagrasp_jax.training.ppo\nexcept DeprecationWarning as w:\n    print(w)\n"
            "warnings.simplefilter('ignore')\nimport sagrasp_jax.training.losses as old\n"
            "import sagrasp_jax.training.agents.ppo.losses as new\n"
            "from sagrasp_jax.training.actor_critic import make_networks\n"
            "print(old is new, make_networks.__module__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == [
        "sagrasp_jax.training.ppo moved to sagrasp_jax.training.agents.ppo.ppo; import it from there",
        "True sagrasp_jax.training.agents.ppo.actor_critic"]


# tests/ mirrors the package: tests/<folder>/ for each of sagrasp_jax's folders that has code, tests/commands/ for the
# top-level command modules (train, evaluate, export, ...); at the top only the checks of the whole checkout and
# the shared helpers (conftest, toy_env, tiny_run, paths, ...).
TESTS = os.path.join(REPO, "tests")
REPO_LEVEL_TESTS = {"test_architecture.py", "test_docs.py", "test_experiments.py", "test_gpu_check.py", "test_install.py"}


def _test_layout_problems(tests: str, package: str) -> list[str]:
    """What breaks the mirror: a test folder with no package folder of that name, a test module at the top that
    is not a repository-level check, a test module nested deeper than one folder."""
    folders = {n for n in os.listdir(package) if os.path.isfile(os.path.join(package, n, "__init__.py"))}
    folders |= {"mjcf", "commands"}  # mjcf/ holds the generated scene (data, no code); commands: the top-level modules
    problems = []
    for name in sorted(os.listdir(tests)):
        path = os.path.join(tests, name)
        if os.path.isdir(path) and name not in ("data", "__pycache__"):
            if name not in folders:
                problems.append(f"tests/{name}/ mirrors no folder of sagrasp_jax/")
            for sub in sorted(os.listdir(path)):
                if os.path.isdir(os.path.join(path, sub)) and sub != "__pycache__":
                    problems.append(f"tests/{name}/{sub}/ is nested deeper than the package's folders")
        elif name.startswith("test_") and name.endswith(".py") and name not in REPO_LEVEL_TESTS:
            problems.append(f"tests/{name} belongs in the tests/ folder of the package folder it tests")
    return problems


def test_tests_mirror_the_package_folders():
    assert _test_layout_problems(TESTS, PACKAGE) == []
    assert {n for n in os.listdir(TESTS) if n.startswith("test_")} == REPO_LEVEL_TESTS
    assert len([f for d in ("task", "deploy", "training") for f in os.listdir(os.path.join(TESTS, d))
                if f.startswith("test_")]) >= 30  # the folders hold the tests, not just the names


def test_the_layout_check_sees_a_misplaced_test(tmp_path):
    (tmp_path / "pkg" / "task").mkdir(parents=True)
    (tmp_path / "pkg" / "task" / "__init__.py").write_text("")
    (tmp_path / "tests" / "task").mkdir(parents=True)
    (tmp_path / "tests" / "gadgets").mkdir()
    (tmp_path / "tests" / "test_reward.py").write_text("")
    assert _test_layout_problems(str(tmp_path / "tests"), str(tmp_path / "pkg")) == [
        "tests/gadgets/ mirrors no folder of sagrasp_jax/", "tests/test_reward.py belongs in the tests/ folder of "
        "the package folder it tests"]


def test_the_wheel_lists_every_package_folder():
    """pyproject's explicit package list ships every folder of sagrasp_jax that holds code: a subpackage left out
    installs from the checkout (editable) but is missing from the wheel a robot PC installs (it happened to
    training/agents/ppo)."""
    import tomllib

    with open(os.path.join(REPO, "pyproject.toml"), "rb") as f:
        listed = set(tomllib.load(f)["tool"]["setuptools"]["packages"])
    code = {os.path.relpath(d, REPO).replace(os.sep, ".") for d, _, files in os.walk(PACKAGE)
            if "__init__.py" in files and "__pycache__" not in d}
    assert code - listed == set(), "add these to [tool.setuptools] packages in pyproject.toml"
    assert {"sagrasp_jax", "sagrasp_jax.training.agents.ppo"} <= code
