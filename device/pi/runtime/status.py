"""The leg runtime's status file: a JSON health summary rewritten atomically (a
temporary file, then ``os.replace``), so a reader never sees half a file."""
from __future__ import annotations

import json
import os
from pathlib import Path


def write_status_file(path: str | Path, doc: dict) -> bool:
    """Replace ``path`` with ``doc`` as JSON; False (and nothing written) when the
    file system refuses."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(json.dumps(doc))
        os.replace(tmp, path)
    except OSError:
        return False
    return True
