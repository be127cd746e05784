"""The docs name only things that exist: every dotted ``host.``/``device.`` path in
docs/ and the READMEs is an importable module or an attribute of one, every
repository-relative file path (``host/...``, ``device/...``, ``tests/...``,
``docs/...``, ``models/...``, ``trials/...``) exists, every ``tests/...py::name``
names a test in that file, and every relative Markdown link points at a file.

Not checked: text inside URLs (``https://...``, ``sim://...``, ``v4l2://...``),
paths the docs write to (the argument of ``--out``, ``--work``, ``--json-log``,
``--status``), and paths under ``out/`` or outside the repository (``../shared``).
"""
from __future__ import annotations

import dataclasses
import importlib
import re
from pathlib import Path

import pytest

from tests import REPO_ROOT

DOC_GLOBS = ("README.md", "docs/*.md", "docs/*.json", "device/*/README.md")

#: anything with a scheme: https://..., sim://walk, v4l2:///dev/video0, file://...
URL = re.compile(r"\b[a-z][a-z0-9+.-]*://\S*")
#: host.x.y / device.x.Y, not part of a longer name or a path
DOTTED = re.compile(r"(?<![\w./-])((?:host|device)(?:\.[A-Za-z_]\w*)+)")
#: from host.x import a, b
FROM_IMPORT = re.compile(r"\bfrom ((?:host|device)(?:\.\w+)*) import (\w+(?:, *\w+)*)")
#: repository-relative paths, with an optional ::test_name
PATH = re.compile(r"(?<![\w./:-])((?:host|device|tests|docs|models|trials)/[\w./*-]*)"
                  r"(?:::(\w+))?")
#: paths a command writes rather than reads
OUTPUT_OPTION = re.compile(r"--(?:out|work|json-log|status)[ =]$")
#: [text](target) with a relative target
LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)]*)?\)")


def doc_files() -> list[Path]:
    files = []
    for pattern in DOC_GLOBS:
        files += sorted(REPO_ROOT.glob(pattern))
    return files


def references(text: str):
    """(kind, reference, line number) for everything ``text`` names: kind is
    ``module``, ``import`` (module, name), ``path`` (path, test name or None) or
    ``link``."""
    for ln, raw in enumerate(text.splitlines(), 1):
        for m in LINK.finditer(raw):
            if not URL.match(m.group(1)) and not m.group(1).startswith("mailto:"):
                yield "link", m.group(1), ln
        line = URL.sub(" ", raw)
        for m in FROM_IMPORT.finditer(line):
            for name in re.split(r", *", m.group(2)):
                yield "import", (m.group(1), name), ln
        for m in DOTTED.finditer(line):
            yield "module", m.group(1), ln
        for m in PATH.finditer(line):
            if OUTPUT_OPTION.search(line[:m.start()]):
                continue
            yield "path", (m.group(1).rstrip("."), m.group(2)), ln


def resolves(dotted: str) -> bool:
    """True when ``dotted`` is a module, or an attribute chain on the longest
    importable module prefix of it."""
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for name in parts[i:]:
            if hasattr(obj, name):
                obj = getattr(obj, name)
            elif dataclasses.is_dataclass(obj) and name in {f.name for f in
                                                             dataclasses.fields(obj)}:
                obj = None                  # a field: exists on every instance
            else:
                return False
        return True
    return False


def path_exists(path: str) -> bool:
    return (REPO_ROOT / path).exists() or any(REPO_ROOT.glob(path))


def problems(doc: Path) -> list[str]:
    out = []
    rel = doc.relative_to(REPO_ROOT)
    for kind, ref, ln in references(doc.read_text(encoding="utf-8")):
        where = f"{rel}:{ln}"
        if kind == "module" and not resolves(ref):
            out.append(f"{where}: no module or attribute {ref}")
        elif kind == "import" and not (resolves(f"{ref[0]}.{ref[1]}")):
            out.append(f"{where}: from {ref[0]} import {ref[1]}: no such name")
        elif kind == "path":
            path, test = ref
            if not path_exists(path):
                out.append(f"{where}: no file {path}")
            elif test and not re.search(rf"^\s*def {test}\(", (REPO_ROOT / path).read_text(),
                                        re.M):
                out.append(f"{where}: {path} has no test {test}")
        elif kind == "link" and not (doc.parent / ref).exists():
            out.append(f"{where}: broken link {ref}")
    return out


@pytest.mark.parametrize("doc", doc_files(), ids=lambda p: str(p.relative_to(REPO_ROOT)))
def test_every_module_and_path_the_docs_name_exists(doc):
    assert problems(doc) == []


def test_the_docs_are_found():
    names = {str(p.relative_to(REPO_ROOT)) for p in doc_files()}
    assert {"README.md", "docs/architecture.md", "docs/pipeline.md",
            "docs/sim-benchmarks.json"} <= names


def test_references_skip_urls_and_outputs_and_keep_the_rest():
    text = ("see https://github.com/x/host/device.py and sim://walk?host.x=1\n"
            "host train --data models/surface --out models/new-model\n"
            "`host.learn.train.train_model` in `host/learn/train.py`, run device.pi, not\n"
            "`tests/host/learn/test_train.py::test_x`; [a](pipeline.md) [b](https://e.org)\n"
            "python -c \"from host.bench.benchmarks import sim_benchmarks, BENCH_MODELS\"\n"
            "out/demo/packets.jsonl and ../shared/data/roboskin, the host. End.\n")
    refs = [(k, r) for k, r, _ in references(text)]
    assert refs == [
        ("path", ("models/surface", None)),
        ("module", "host.learn.train.train_model"),
        ("module", "device.pi"),
        ("path", ("host/learn/train.py", None)),
        ("link", "pipeline.md"),
        ("path", ("tests/host/learn/test_train.py", "test_x")),
        ("import", ("host.bench.benchmarks", "sim_benchmarks")),
        ("import", ("host.bench.benchmarks", "BENCH_MODELS")),
        ("module", "host.bench.benchmarks"),
    ]


def test_resolves_modules_and_attributes_only():
    assert resolves("device.pi.models.regressor.Regressor.predict_window")
    assert resolves("host.bench.scenes.SURFACE_RANGES")
    assert resolves("host.data.windows.WindowSet.frames")          # a dataclass field
    assert not resolves("host.learn.train.SURFACE_RANGES")
    assert not resolves("host.nowhere")
