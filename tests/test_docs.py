"""The docs stay true and self-contained.

* Every ```` ```python ```` block of ``README.md`` and ``docs/architecture.md`` runs (in order, one
  namespace per file, from a scratch folder); ```` ```python no-run ```` blocks are shown only.
  Shell blocks (```` ```bash ````) are a user's commands and are not run; every
  ``python -m sagrasp_jax.X`` in them must name a module that exists.
* No tracked file refers to a path outside the repository: the specification the project was
  written from, sibling folders, absolute paths of the machines it was developed on.  Recorded
  measurements (``experiments/results/``) and the 0.1 release's files (``tests/data/``) are
  exempt: they log where each run was made, as it was written, and are not references to follow.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOCS_WITH_EXAMPLES = ("README.md", "docs/architecture.md")
FENCE = re.compile(r"^```([^\n`]*)\n(.*?)^```\s*$", re.M | re.S)

# What a reference outside the repository looks like (assembled, so this file does not match itself).
_SPEC = "SPEC"
OUTSIDE = re.compile("|".join([
    re.escape("../" + "shared"),
    re.escape(_SPEC + ".md"),
    re.escape(_SPEC) + r"\s*§",
    r"(?<![\w.])/" + "work/",
    r"(?<![\w.])/" + "root/",
    r"(?<![\w.])/" + "home/",
    re.escape("seed/" + "sensors"),
]))
EXEMPT = ("experiments/results/", "tests/data/")


def blocks(path: str) -> list[tuple[str, str]]:
    with open(os.path.join(REPO, path), encoding="utf-8") as f:
        return [(m.group(1).strip(), m.group(2)) for m in FENCE.finditer(f.read())]


@pytest.mark.parametrize("path", DOCS_WITH_EXAMPLES)
def test_python_examples_run(path, tmp_path, monkeypatch):
    code = [body for info, body in blocks(path) if info.split()[:1] == ["python"] and "no-run" not in info.split()]
    if path == "docs/architecture.md":
        assert code, f"{path} has no python example"
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": f"doc_example_{os.path.basename(path)}"}
    for i, body in enumerate(code):
        exec(compile(body, f"{path} python block {i + 1}", "exec"), namespace)  # noqa: S102


@pytest.mark.parametrize("path", DOCS_WITH_EXAMPLES)
def test_shell_examples_name_existing_modules(path):
    infos = {info.split()[0] if info else "" for info, _ in blocks(path)}
    assert infos <= {"python", "bash", "text", ""}, f"{path}: unexpected code block kinds {infos}"
    modules = {m for info, body in blocks(path) if info.startswith("bash")
               for m in re.findall(r"python3? -m (sagrasp_jax(?:\.\w+)*)", body)}
    for module in modules:
        assert importlib.util.find_spec(module) is not None, f"{path}: python -m {module} names no module"


def tracked_text_files() -> list[str]:
    try:
        out = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO, capture_output=True,
                             text=True, check=True).stdout.split("\n")
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    files = []
    for name in filter(None, out):
        if name.startswith(EXEMPT) or not os.path.isfile(os.path.join(REPO, name)):
            continue
        with open(os.path.join(REPO, name), "rb") as f:
            head = f.read()
        if b"\0" in head[:8192]:
            continue  # binary
        files.append(name)
    return files


def test_no_file_refers_to_a_path_outside_the_repository():
    files = tracked_text_files()
    assert "docs/task.md" in files and "README.md" in files
    hits = []
    for name in files:
        with open(os.path.join(REPO, name), encoding="utf-8", errors="replace") as f:
            for n, line in enumerate(f, 1):
                if OUTSIDE.search(line):
                    hits.append(f"{name}:{n}: {line.strip()[:120]}")
    assert not hits, "references outside the repository:\n" + "\n".join(hits)


def test_task_sections_cited_exist():
    """Every ``docs/task.md §N[.M]`` cited in the repository is a section of docs/task.md."""
    with open(os.path.join(REPO, "docs", "task.md"), encoding="utf-8") as f:
        sections = set(re.findall(r"^#{2,3} (\d+(?:\.\d+)?)\.? ", f.read(), re.M))
    cited = set()
    for name in tracked_text_files():
        with open(os.path.join(REPO, name), encoding="utf-8", errors="replace") as f:
            text = f.read()
        for m in re.finditer(r"task\.md`{0,2} (§[\d.§\-–, ]+)", text):
            cited |= {s.rstrip(".") for s in re.findall(r"§(\d+(?:\.\d+)?)", m.group(1))}
    assert cited and cited <= sections, f"cited but missing: {sorted(cited - sections)}"


def _readme_bash_lines() -> list[str]:
    return [line.strip() for info, body in blocks("README.md") if info.startswith("bash") for line in body.splitlines()]


def test_ci_runs_the_readmes_commands_on_every_python():
    """``.ci/run`` runs ``.ci/python_matrix.sh`` (3.11, 3.12, 3.13) before the suite, and the matrix installs with
    the README's own install commands: the pretrained try's and the training line's."""
    with open(os.path.join(REPO, ".ci", "run"), encoding="utf-8") as f:
        ci = f.read()
    with open(os.path.join(REPO, ".ci", "python_matrix.sh"), encoding="utf-8") as f:
        matrix = f.read()
    assert ci.index("python_matrix.sh") < ci.index("python -m pytest -q")
    assert 'pythons="${SAGRASP_PYTHONS:-3.11 3.12 3.13}"' in matrix
    lines = _readme_bash_lines()
    try_line = next(line for line in lines if line.startswith("python3 -m venv") and "[twin]" in line)
    train_line = next(line for line in lines if line.startswith("python3 -m venv") and "sagrasp_jax.train" in line)
    twin_install = try_line.split("&&")[-1].strip()
    train_install = train_line.split("&&")[2].strip()
    assert twin_install.startswith("pip install") and f"step install-twin {twin_install.replace('pip install', 'pip install -q', 1)}" in matrix
    assert train_install.startswith("pip install") and f"step install-train {train_install.replace('pip install', 'pip install -q', 1)}" in matrix
    assert "sagrasp_jax.deploy --policy pretrained" in matrix and "sagrasp_jax.export --run runs/quick" in matrix


def test_readme_leads_with_the_pretrained_try_and_installs_what_its_commands_need():
    """The first commands a newcomer meets run the packaged policy (no training); no line asks pip for a package
    the index does not have; the block after training installs the extras its commands import."""
    bash = [body for info, body in blocks("README.md") if info.startswith("bash")]
    assert "sagrasp_jax.deploy --policy pretrained" in bash[0] and "sagrasp_jax.train" not in bash[0]
    with open(os.path.join(REPO, "README.md"), encoding="utf-8") as f:
        text = f.read()
    assert not re.search(r"pip install sagrasp_jax(?![\w\[-])", text), "the package is not on the index"
    after = next(body for body in bash if "sagrasp_jax.render" in body)
    first = after.splitlines()[0]
    assert first.startswith("pip install") and all(x in first for x in ("train", "twin", "render", "plots"))
