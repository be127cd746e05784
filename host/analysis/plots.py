"""Plots people would rather look at than read.

``host plot directions`` draws average-vector directions as a scatter, like the
paper's figure 5: one panel per input, points coloured by sensation (the
direction the foot was pushed) and sized by pressure level. With ``--compare``
each ``host analyse --localiser`` input gives two panels: the tracked vectors'
average vector and the localiser pins' (:mod:`host.analysis.directions`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from host.analysis.directions import compare_directions, direction_series, read_lines
from host.analysis.figures import pyplot, save_figure
from device.errors import InputError

SENSATIONS = ("left", "right", "centre")


def load_directions(path: Path | str) -> dict:
    """Vectors from a paper-layout ``.npy`` (trials, sensations, pressures, 2) or
    from ``host analyse`` JSON lines (contact frames' shear_x, shear_y)."""
    path = Path(path)
    if path.suffix == ".npy":
        try:
            a = np.load(path, allow_pickle=False)
        except EOFError:            # zero-length or cut short
            raise InputError(f"{path}: the file is empty or cut short (no .npy array)") from None
        if not isinstance(a, np.ndarray) or a.ndim != 4 or a.shape[-1] != 2:
            raise InputError(f"{path}: expected shape (trials, sensations, pressures, 2), "
                             f"got {getattr(a, 'shape', type(a).__name__)}")
        if a.size == 0:
            raise InputError(f"{path}: no vectors to plot (shape {a.shape})")
        t, s, p, _ = a.shape
        sens = np.broadcast_to(np.arange(s)[None, :, None], (t, s, p)).reshape(-1)
        pres = np.broadcast_to(np.arange(p)[None, None, :], (t, s, p)).reshape(-1)
        return {"label": path.stem, "xy": a.reshape(-1, 2), "sensation": sens, "pressure": pres}
    lines = _lines(path)
    xs = [(d["shear_x"], d["shear_y"]) for d in lines if d.get("contact")]
    if not xs:
        raise InputError(f"{path}: no contact frame to plot (of {len(lines)} frame lines)")
    xy = np.asarray(xs, dtype=float).reshape(-1, 2)
    return {"label": path.stem, "xy": xy, "sensation": np.zeros(len(xy), int),
            "pressure": np.zeros(len(xy), int)}


def _lines(path: Path) -> list[dict]:
    """The frame lines of ``path``; an empty file is a ValueError naming it (an empty
    plot would look like a result)."""
    lines = read_lines(path)
    if not lines:
        raise InputError(f"{path}: the file holds no frame lines (empty)")
    return lines


def plot_directions(inputs: list[dict], out: Path | str, title: str = "") -> Path:
    plt = pyplot()

    n = len(inputs)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 4.4), squeeze=False)
    lim = max([float(np.nanmax(np.abs(d["xy"]))) if d["xy"].size else 1.0
               for d in inputs] + [1e-6]) * 1.1
    colours = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")
    for ax, d in zip(axes[0], inputs):
        xy = d["xy"]
        ok = np.isfinite(xy).all(axis=1)
        groups = np.unique(d["sensation"])
        for s in groups:
            m = ok & (d["sensation"] == s)
            if len(groups) == 1:
                name = "contact frames"
            else:
                name = SENSATIONS[s] if s < len(SENSATIONS) else f"sensation {s}"
            ax.scatter(xy[m, 0], xy[m, 1], s=12 + 14 * d["pressure"][m], alpha=0.6,
                       color=colours[int(s) % len(colours)], label=name)
        ax.axhline(0, color="0.8", lw=0.8)
        ax.axvline(0, color="0.8", lw=0.8)
        ax.set_xlim(-lim, lim)
        ax.set_ylim(lim, -lim)          # image y points down
        ax.set_aspect("equal")
        ax.set_title(d["label"])
        ax.set_xlabel("average vector x [px]")
        ax.legend(fontsize=7, loc="lower right")
    axes[0][0].set_ylabel("average vector y [px] (down)")
    return save_figure(fig, out, title)


def load_comparison(path: Path | str) -> tuple[list[dict], dict]:
    """The two direction series of one ``host analyse --localiser`` file as
    :func:`plot_directions` inputs, and how well they agree."""
    path = Path(path)
    lines = _lines(path)
    try:
        series = direction_series(lines)
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None
    n = len(series["frame"])
    if n == 0:
        raise InputError(f"{path}: no contact frame with a sound localisation to compare")
    zeros = np.zeros(n, int)
    inputs = [{"label": f"{path.stem}: tracked vectors", "xy": series["vectors_px"],
               "sensation": zeros, "pressure": zeros},
              {"label": f"{path.stem}: localiser pins", "xy": series["localised_px"],
               "sensation": zeros, "pressure": zeros}]
    stats = compare_directions(series)
    stats.update(source=str(path), rest_frame=series["rest_frame"])
    return inputs, stats
