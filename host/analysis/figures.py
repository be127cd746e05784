"""Writing matplotlib figures of the analysis commands."""

from __future__ import annotations

from pathlib import Path

from host.extras import need

__all__ = ["pyplot", "save_figure"]


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend: the commands write files and never
    open a window."""
    need("matplotlib").use("Agg")
    return need("matplotlib.pyplot")


def save_figure(fig, out: Path | str, title: str = "", dpi: int = 90) -> Path:
    """Title ``fig`` (when ``title`` is given), lay it out, write it to ``out``
    (making its folder) and close it; returns ``out`` as a Path."""
    plt = pyplot()
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out
