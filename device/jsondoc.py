"""The JSON documents tacfoot writes beside its data (a model's manifest, a
dataset's dataset.json): a ``format`` name and a ``version`` number, read with
errors that name the file."""
from __future__ import annotations

import json
from pathlib import Path

__all__ = ["read_json_doc"]


def read_json_doc(path: Path | str, name: str, fmt: str, version: int, kind: str, what: str,
                  error: type[ValueError] = ValueError) -> tuple[dict, Path]:
    """(document, its file) from ``path``: the file itself, or the folder holding
    ``name``. ``error`` (naming the file) when the file is missing or not JSON, its
    ``format`` is not ``fmt``, or its ``version`` is not a whole number or is newer
    than ``version``; ``kind`` and ``what`` name the thing and the document in it
    ("model", "manifest")."""
    path = Path(path)
    file = path / name if path.is_dir() else path
    try:
        doc = json.loads(file.read_text())
    except FileNotFoundError:
        raise error(f"{file}: not a tacfoot {kind}: {what} not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise error(f"{file}: corrupt {what} ({exc})") from None
    except OSError as exc:
        raise error(f"{file}: cannot read the {what}: {exc.strerror or exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != fmt:
        got = doc.get("format") if isinstance(doc, dict) else doc
        raise error(f"{file}: not a tacfoot {kind} {what} (format {got!r}, expected {fmt!r})")
    got = doc.get("version", 0)
    if isinstance(got, bool) or not isinstance(got, int) or got < 0:
        raise error(f"{file}: {what} version must be a whole number >= 0, got {got!r}")
    if got > version:
        raise error(f"{file}: {what} version {got} is newer than this tacfoot reads "
                    f"({version})")
    return doc, file
