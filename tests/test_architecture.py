"""The architecture is guarded, not only described (docs/architecture.md).

import-linter's contracts in pyproject.toml hold the layers (``make test`` runs
``lint-imports``); these tests hold what a layer contract cannot see: no import cycle
between any two modules (imports inside functions and under ``TYPE_CHECKING``
included: a type-only import still ties the two modules together), no module longer than
one can read in a sitting, and a test tree that mirrors the code: each
``tests/<path>/test_<name>.py`` tests ``<path>/<name>.py`` (or the package
``<path>/<name>/``; ``test_main.py`` tests ``__main__.py``), and no test module
imports another (shared helpers live in non-test modules and conftest.py).
"""
from __future__ import annotations

import ast

import grimp
import pytest

from tests import REPO_ROOT

MAX_MODULE_LINES = 600
TESTS = REPO_ROOT / "tests"


@pytest.fixture(scope="module")
def graph():
    # type-checking imports included; no cache: grimp's cache does not key on that flag,
    # so a cache written by lint-imports (which excludes them) would hide them
    return grimp.build_graph("host", "device", include_external_packages=False,
                             exclude_type_checking_imports=False, cache_dir=None)


def _cycles(graph) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on, stack, out = {}, {}, set(), [], []
    counter = [0]
    for root in sorted(graph.modules):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root))))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            nxt = next(it, None)
            if nxt is not None:
                if nxt not in index:
                    index[nxt] = low[nxt] = counter[0]
                    counter[0] += 1
                    stack.append(nxt)
                    on.add(nxt)
                    work.append((nxt, iter(sorted(graph.find_modules_directly_imported_by(nxt)))))
                elif nxt in on:
                    low[v] = min(low[v], index[nxt])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_cycle_finder_finds_a_cycle():
    g = grimp.ImportGraph()
    for m in ("p", "p.a", "p.b", "p.c"):
        g.add_module(m)
    g.add_import(importer="p.a", imported="p.b")
    g.add_import(importer="p.b", imported="p.a")
    g.add_import(importer="p.c", imported="p.a")
    assert _cycles(g) == [["p.a", "p.b"]]


def test_no_import_cycles_between_modules(graph):
    # a package's __init__ importing its own modules is not a cycle of design
    cycles = [c for c in _cycles(graph)
              if not any(a != b and b.startswith(a + ".") for a in c for b in c)]
    assert cycles == [], "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_no_module_over_the_size_limit():
    too_long = {}
    for pkg in ("host", "device"):
        for f in sorted((REPO_ROOT / pkg).rglob("*.py")):
            n = len(f.read_text(encoding="utf-8").splitlines())
            if n > MAX_MODULE_LINES:
                too_long[str(f.relative_to(REPO_ROOT))] = n
    assert too_long == {}, f"modules over {MAX_MODULE_LINES} lines: {too_long}"


def mirrored(test_file):
    """The module (or package) a test file under tests/ tests, or None for the
    repository-wide tests at the top of tests/."""
    rel = test_file.relative_to(TESTS)
    if rel.parent == rel.parent.parent:
        return None
    name = rel.stem[len("test_"):]
    name = "__main__" if name == "main" else name
    module = REPO_ROOT / rel.parent / f"{name}.py"
    return module if module.exists() else REPO_ROOT / rel.parent / name


def test_mirrored_names_the_module_under_test():
    assert mirrored(TESTS / "device" / "pi" / "test_main.py") == (
        REPO_ROOT / "device" / "pi" / "__main__.py")
    assert mirrored(TESTS / "host" / "learn" / "test_train.py") == (
        REPO_ROOT / "host" / "learn" / "train.py")
    assert mirrored(TESTS / "test_docs.py") is None


def test_each_test_file_mirrors_a_module():
    missing = [str(f.relative_to(REPO_ROOT)) for f in sorted(TESTS.rglob("test_*.py"))
               if mirrored(f) is not None and not mirrored(f).exists()]
    assert missing == [], f"test files with no module at the mirrored path: {missing}"


def test_no_test_module_imports_another():
    found = []
    for f in sorted(TESTS.rglob("*.py")):
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = ("." * node.level) + (node.module or "")
                names = [base] + [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            if any(n.rsplit(".", 1)[-1].startswith("test_") for n in names):
                found.append(f"{f.relative_to(REPO_ROOT)}:{node.lineno}")
    assert found == [], f"test modules imported by: {found}"


# ----------------------------------------------------------------------------
# docs/architecture.md names every module and draws only real arrows
# ----------------------------------------------------------------------------

ARCH_DOC = REPO_ROOT / "docs" / "architecture.md"
#: a tree line's name column ends before this column; deeper lines continue a description
DESCRIPTION_COLUMN = 28


def code_block(text: str, heading: str) -> list[str]:
    """The lines of the first fenced block after the ``## heading`` line of ``text``."""
    lines = text.splitlines()
    start = lines.index(f"## {heading}")
    opens = next(i for i in range(start, len(lines)) if lines[i].startswith("```"))
    closes = next(i for i in range(opens + 1, len(lines)) if lines[i].startswith("```"))
    return lines[opens + 1:closes]


def tree_paths(block: list[str]) -> list[str]:
    """Repository paths the tree names: the first word of each line that starts before
    the description column, below the folder line (``name/``) of the indent above it
    (two spaces a level)."""
    folders: list[str] = []
    out = []
    for line in block:
        indent = len(line) - len(line.lstrip(" "))
        if not line.strip() or indent >= DESCRIPTION_COLUMN:
            continue
        level = indent // 2
        name = line.split()[0]
        folders = folders[:level]
        path = "/".join(folders + [name.rstrip("/")])
        out.append(path)
        if name.endswith("/"):
            folders.append(name.rstrip("/"))
    return out


def code_modules() -> list[str]:
    """Every module of device/ and host/: each .py but __init__.py, and each C file."""
    found = set()
    for pkg in ("device", "host"):
        for pattern in ("*.py", "*.c"):
            for f in (REPO_ROOT / pkg).rglob(pattern):
                if f.name != "__init__.py" and "__pycache__" not in f.parts:
                    found.add(f.relative_to(REPO_ROOT).as_posix())
    return sorted(found)


def arrows(block: list[str]) -> list[tuple[str, str]]:
    """(importer, imported) for each ``a -> b`` of the arrow chains, one chain a line."""
    out = []
    for line in block:
        chain = [part.strip() for part in line.split("->")]
        out += list(zip(chain, chain[1:]))
    return out


def test_tree_paths_follow_the_indent():
    block = ["host/                        the toolkit",
             "  data/                      data specs",
             "    errors.py                the error",
             "                             windows.py (a continuation, not a module)",
             "  monitor.py                 live packets",
             "device/",
             "  pi/",
             "    vision/",
             "      detect.c               pin detection"]
    assert tree_paths(block) == ["host", "host/data", "host/data/errors.py", "host/monitor.py",
                                 "device", "device/pi", "device/pi/vision",
                                 "device/pi/vision/detect.c"]
    assert arrows(["a -> b -> c", "d -> b"]) == [("a", "b"), ("b", "c"), ("d", "b")]


def test_the_architecture_page_names_every_module():
    """docs/architecture.md's tree (the block under "## The tree") names each module of
    device/ and host/ (every .py but __init__.py, and every .c) on a line of its own:
    the file name as the line's first word, indented two spaces a level under its
    folder's ``name/`` line, then a few words on what it does. Lines indented to the
    description column or further continue the description. Every path the tree
    names exists."""
    named = tree_paths(code_block(ARCH_DOC.read_text(encoding="utf-8"), "The tree"))
    missing = [m for m in code_modules() if m not in named]
    assert missing == [], f"docs/architecture.md's tree does not name: {missing}"
    stale = [p for p in named if not (REPO_ROOT / p).exists()]
    assert stale == [], f"docs/architecture.md's tree names what does not exist: {stale}"


def test_the_architecture_page_draws_only_real_imports(graph):
    """Each ``a -> b`` in the first block under "## Which way imports go" is an import
    the code has: some module of ``a`` imports some module of ``b``."""
    block = code_block(ARCH_DOC.read_text(encoding="utf-8"), "Which way imports go")
    pairs = arrows(block)
    assert pairs, "no arrows found"
    unknown = sorted({m for pair in pairs for m in pair if m not in graph.modules})
    assert unknown == [], f"arrows name modules that do not exist: {unknown}"
    absent = [f"{a} -> {b}" for a, b in pairs
              if not graph.direct_import_exists(importer=a, imported=b, as_packages=True)]
    assert absent == [], f"docs/architecture.md draws imports the code does not have: {absent}"
