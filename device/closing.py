"""Context-manager use for anything with a ``close()``: ``with`` closes it, and so
does garbage collection, quietly, for an object its owner forgot to close."""
from __future__ import annotations


class Closing:
    """Mix-in for a class with an idempotent ``close()``."""

    def close(self) -> None:          # the class using the mix-in provides its own
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass
