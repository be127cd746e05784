"""The leg runtime's status file: a JSON health summary rewritten atomically (a
temporary file, then ``os.replace``), so a reader never sees half a file; and its
decision log (``--json-log``), whose failures never stop the runtime."""
from __future__ import annotations

import logging
import io
import json
import os
from pathlib import Path

_log = logging.getLogger(__name__)


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


class JsonLog:
    """The decision log: one JSON line per :meth:`write`, on a text or binary file.

    The log is not the job: a line the file system refuses (a full disk, a vanished
    mount) is counted in ``lines_lost`` and warned about once on stderr, and the
    runtime goes on. A line cut short by a failed write is ended by the next line's
    leading newline, so every whole line stays one JSON document."""

    def __init__(self, fh, name: str | None = None):
        self.fh = fh
        self.name = name or str(getattr(fh, "name", "the decision log"))
        self.text = isinstance(fh, io.TextIOBase)
        self.lines_written = 0
        self.lines_lost = 0
        self.warned = False
        self._cut = False            # the last write may have stopped mid-line

    def write(self, doc: dict) -> bool:
        """Append ``doc`` as one line; False when it was lost."""
        line = ("\n" if self._cut else "") + json.dumps(doc) + "\n"
        data = line if self.text else line.encode()
        try:
            n = self.fh.write(data)
            ok = n is None or n >= len(data)
            err = None if ok else "a short write"
            self._cut = not ok
        except (OSError, ValueError) as exc:     # ValueError: the file was closed
            ok, err = False, getattr(exc, "strerror", None) or str(exc)
            # a raw file took nothing; a text file may have buffered part of the line
            self._cut = self._cut or self.text
        if ok:
            self.lines_written += 1
            return True
        self.lines_lost += 1
        if not self.warned:
            self.warned = True
            _log.warning("device.pi run: warning: --json-log %s: cannot write (%s); running "
                         "on, counting the lost lines in the status (json_log_lines_lost)",
                         self.name, err)
        return False

    def flush(self) -> None:
        try:
            self.fh.flush()
        except (OSError, ValueError):
            pass
