"""Writing figures (host/analysis/figures.py)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402

from host.analysis.figures import save_figure  # noqa: E402


def test_save_figure_writes_titles_and_closes(tmp_path):
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    n_open = len(plt.get_fignums())
    out = save_figure(fig, tmp_path / "deep" / "f.png", title="a title")
    assert out == tmp_path / "deep" / "f.png"
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert fig.get_suptitle() == "a title"
    assert len(plt.get_fignums()) == n_open - 1
