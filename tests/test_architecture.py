"""The architecture is guarded, not only described (docs/architecture.md).

import-linter's contracts in pyproject.toml hold the layers (``make test`` runs
``lint-imports``); these tests hold what a layer contract cannot see: no import cycle
between any two modules (imports inside functions included) and no module that has
grown past what one can read in a sitting.
"""
from __future__ import annotations

import grimp
import pytest

from tests import REPO_ROOT

MAX_MODULE_LINES = 600
#: modules still being split; this list only shrinks
@pytest.fixture(scope="module")
def graph():
    return grimp.build_graph("host", "device", include_external_packages=False,
                             exclude_type_checking_imports=True)


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
