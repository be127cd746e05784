"""Pictures people would rather look at than read: frames with pin vectors drawn
over them (the paper's figure 3), animated GIF or a PNG contact sheet, and a
ground-truth timeline plot."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from device.sim.scene import SURFACE_LABELS, TEXTURE_LABELS
from host.analysis.figures import pyplot, save_figure


def to_bgr(frame: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR) if frame.ndim == 2 else frame.copy()


def draw_vectors(frame: np.ndarray, rest: np.ndarray, pins: np.ndarray,
                 visible: np.ndarray | None = None, gain: float = 2.0,
                 text: str = "") -> np.ndarray:
    """Arrows from each pin's rest position along its displacement (x ``gain``)."""
    img = to_bgr(frame)
    if visible is None:
        visible = np.ones(len(pins), bool)
    disp = pins - rest
    mags = np.hypot(disp[:, 0], disp[:, 1])
    top = max(float(np.nanmax(mags, initial=0.0)), 1.0)
    for (x0, y0), (dx, dy), m, v in zip(rest, disp, mags, visible):
        if not (np.isfinite(x0) and np.isfinite(y0) and np.isfinite(dx) and np.isfinite(dy)):
            continue
        if not v:
            cv2.drawMarker(img, (int(x0), int(y0)), (0, 0, 255), cv2.MARKER_TILTED_CROSS, 5, 1)
            continue
        hue = int(120 - 120 * min(m / top, 1.0))          # green -> red with magnitude
        colour = cv2.cvtColor(np.uint8([[[hue, 255, 255]]]), cv2.COLOR_HSV2BGR)[0, 0].tolist()
        p0 = (int(round(x0)), int(round(y0)))
        p1 = (int(round(x0 + gain * dx)), int(round(y0 + gain * dy)))
        if m * gain >= 1.0:
            cv2.arrowedLine(img, p0, p1, colour, 1, cv2.LINE_AA, tipLength=0.3)
        else:
            cv2.circle(img, p0, 1, colour, -1)
    if text:
        (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.6, 1)
        cv2.rectangle(img, (4, 4), (12 + tw, 12 + th + base), (255, 255, 255), -1)
        cv2.putText(img, text, (8, 8 + th), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (160, 40, 0), 1,
                    cv2.LINE_AA)
    return img


def truth_caption(truth: dict, i: int) -> str:
    surf = SURFACE_LABELS[int(truth["surface"][i])]
    tex = TEXTURE_LABELS[int(truth["texture"][i])]
    s = f"#{i} {surf}"
    if truth["contact"][i]:
        s += f"/{tex} {truth['load_n'][i]:.1f}N"
    if truth["slip"][i]:
        s += " SLIP"
    return s


def pick_frames(n: int, most: int) -> np.ndarray:
    if n <= most:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, most).round().astype(int))


def save_images(images: list[np.ndarray], out: Path, fps: float = 15.0, width: int = 400) -> Path:
    """A GIF (all images, animated) or a PNG contact sheet, by ``out``'s suffix."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not images:
        raise ValueError("no frames to draw")
    scale = width / images[0].shape[1]
    small = [cv2.resize(im, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
             for im in images]
    suffix = out.suffix.lower()
    if suffix == ".gif":
        from PIL import Image
        pics = [Image.fromarray(cv2.cvtColor(im, cv2.COLOR_BGR2RGB)) for im in small]
        pics[0].save(out, save_all=True, append_images=pics[1:], loop=0,
                     duration=int(1000 / max(fps, 1)), optimize=False)
    elif suffix == ".png":
        cols = min(3, len(small))
        rows = -(-len(small) // cols)
        h, w = small[0].shape[:2]
        sheet = np.full((rows * h, cols * w, 3), 255, np.uint8)
        for k, im in enumerate(small):
            r, c = divmod(k, cols)
            sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = im
        cv2.imwrite(str(out), sheet)
    else:
        raise ValueError(f"--out must end in .gif or .png, got {out.name!r}")
    return out


def truth_plot(truth: dict, out: Path, title: str = "") -> Path:
    """Ground truth over time: load, shear, contact/slip and the surface label."""
    plt = pyplot()

    t = truth["t_s"]
    fig, ax = plt.subplots(4, 1, figsize=(9, 7.5), sharex=True)
    ax[0].plot(t, truth["load_n"], label="normal load [N]")
    ax[0].plot(t, truth["depth_mm"], label="indentation [mm]")
    ax[0].legend(loc="upper right")
    ax[1].plot(t, truth["shear_px"][:, 0], label="shear x [px]")
    ax[1].plot(t, truth["shear_px"][:, 1], label="shear y [px]")
    ax[1].legend(loc="upper right")
    ax[2].fill_between(t, 0, truth["contact"].astype(float), step="mid", alpha=0.3,
                       label="contact")
    ax[2].plot(t, truth["slip"].astype(float), drawstyle="steps-mid", color="r", label="slip")
    ax[2].set_yticks([0, 1])
    ax[2].legend(loc="upper right")
    ax[3].plot(t, truth["surface"], drawstyle="steps-mid", label="surface")
    ax[3].plot(t, truth["texture"] + 0.05, drawstyle="steps-mid", label="texture")
    ax[3].set_yticks(range(len(SURFACE_LABELS)))
    ax[3].set_yticklabels([f"{a} | {b}" for a, b in zip(SURFACE_LABELS, TEXTURE_LABELS)],
                          fontsize=7)
    ax[3].legend(loc="upper right")
    ax[3].set_xlabel("time [s]")
    return save_figure(fig, out, title)
