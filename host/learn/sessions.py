"""Training windows as another recording session of the same surface would give them.

A model that scores well on later frames of its own recordings can still drop on a
second session of the same surface, because a session changes what the model reads
without changing the surface (:mod:`host.learn.identity` tells the recordings of one
surface apart by exactly these): the exposure, the frame interval, the pins the
detector misses, and where the dome sits on the pin layout. :func:`augment_sessions`
adds ``copies`` copies of the training windows, each a new draw of such a session:

``gain``, ``gamma``, ``offset``  the exposure: every frame of the recording, the rest
        (reference) frame too as in a real session, becomes
        ``255 * clip((gain x + offset) / 255) ** gamma`` before the marker pipeline;
        ``gain`` and ``gamma`` are drawn log-uniform in their [low, high], ``offset``
        (grey levels) uniform;
``shift_px``, ``scale``, ``rotate_deg``  the pin layout the reference pins are
        assigned to (:func:`device.pi.vision.layout.layout_assignment`) moved by up to
        ``shift_px`` in a random direction, scaled by 1 +- up to ``scale`` and rotated
        by up to +-``rotate_deg`` about its centre: two calibrations of one sensor
        agree to a median 0.1-0.3 px, the dome can sit a few px elsewhere;
``lost``  in each copied window a share of pins, uniform in [low, high], lost for the
        whole window (vector zero, lost flag set, as
        :func:`device.pi.vision.layout.to_layout` gives a pin the detector misses).

The copies are re-extracted from the recording's frames through the Pi's own frame
encoder (:func:`host.data.extract.extract_features`, the code the Pi runs), from its
first frame up to the last frame a training window needs, so each copy holds the
same windows (same trial, last frame, label and contact flag) as that session would
have given them; a window whose frames have no reference in the copy is left out.
A recording whose frames cannot be read again (an ``.npz`` of vectors, windows
handed in directly) gets its copies with lost pins only; ``source["augmented_sessions"]``
counts both. The interval between frames is varied by :mod:`host.learn.rates`.
Re-extracted recordings are kept in memory (:data:`CACHE_SIZE` of them) for the
next run in the process.

The ranges are what a second session plausibly changes, not tuned on any clip; the
defaults (:data:`DEFAULT_SESSIONS`) are recorded in the model's spec and train.toml.
"""
from __future__ import annotations

import math
import zlib
from collections import OrderedDict
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from host.learn.tasks import TrainError

__all__ = ["DEFAULT_SESSIONS", "SessionDraw", "session_settings", "draw_session", "exposure",
           "perturbed_layout", "lose_pins", "session_clip", "augment_sessions", "CACHE_SIZE"]

#: the settings ``sessions = true`` (or the task default) means: two copies; exposure
#: within about a third of a stop of gain, gamma 0.8-1.25 and +-15 grey levels; the
#: layout a few px, 1 % and 1 degree off; up to 10 % of the pins lost
DEFAULT_SESSIONS = {"copies": 2, "gain": [0.8, 1.25], "gamma": [0.8, 1.25],
                    "offset": [-15.0, 15.0], "shift_px": 3.0, "scale": 0.01,
                    "rotate_deg": 1.0, "lost": [0.0, 0.1]}
#: re-extracted recordings kept in memory
CACHE_SIZE = 24
_CACHE: OrderedDict = OrderedDict()
#: trial kinds (``source["trials"][i]["kind"]``) whose frames can be read again
FRAME_KINDS = ("clip", "sim", "dataset")
#: the per-window parts a copy carries over or replaces
_PARTS = ("vectors", "lost", "imu", "contact", "labels", "targets", "groups", "t_index",
          "trial_len", "recordings", "frame_index", "session")


@dataclass(frozen=True)
class SessionDraw:
    """One drawn session: exposure (``gain``, ``gamma``, ``offset``) and the layout's
    shift (``dx``, ``dy`` px), ``scale`` and rotation ``rot_deg``."""
    gain: float = 1.0
    gamma: float = 1.0
    offset: float = 0.0
    dx: float = 0.0
    dy: float = 0.0
    scale: float = 1.0
    rot_deg: float = 0.0

    def key(self) -> tuple:
        return tuple(round(float(v), 6) for v in (self.gain, self.gamma, self.offset,
                                                 self.dx, self.dy, self.scale, self.rot_deg))


def _range(name: str, v, lo_ok, hi_max: float) -> list:
    if (not isinstance(v, (list, tuple)) or len(v) != 2
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                       and math.isfinite(x) for x in v)
            or not lo_ok(float(v[0])) or not float(v[0]) <= float(v[1]) <= hi_max):
        raise TrainError(f"sessions.{name} must be [low, high] with low <= high within the "
                         f"allowed range, got sessions.{name}={v!r}")
    return [float(v[0]), float(v[1])]


def _number(name: str, v, hi: float) -> float:
    if (not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v)
            or not 0.0 <= float(v) <= hi):
        raise TrainError(f"sessions.{name} must be a number in [0, {hi}], got "
                         f"sessions.{name}={v!r}")
    return float(v)


def session_settings(value):
    """The checked ``sessions`` setting: None (the task's default), False (no copies),
    or the full settings dict (:data:`DEFAULT_SESSIONS` with the given keys changed;
    ``true`` means the defaults). A TrainError names the bad key and value."""
    if value is None:
        return None
    if value is False or (isinstance(value, str) and value.strip().lower() == "none"):
        return False
    if value is True:
        return dict(DEFAULT_SESSIONS)
    if not isinstance(value, dict):
        raise TrainError(f"sessions must be true, false or a table of "
                         f"{sorted(DEFAULT_SESSIONS)}, got sessions={value!r}")
    unknown = sorted(set(value) - set(DEFAULT_SESSIONS))
    if unknown:
        raise TrainError(f"sessions: unknown setting(s) {unknown}; sessions takes "
                         f"{sorted(DEFAULT_SESSIONS)}")
    s = dict(DEFAULT_SESSIONS, **value)
    c = s["copies"]
    if not isinstance(c, int) or isinstance(c, bool) or not 0 <= c <= 20:
        raise TrainError(f"sessions.copies must be a whole number 0..20, got "
                         f"sessions.copies={c!r}")
    if c == 0:
        return False
    pos = lambda x: x > 0  # noqa: E731
    s["gain"] = _range("gain", s["gain"], pos, 10.0)
    s["gamma"] = _range("gamma", s["gamma"], pos, 10.0)
    s["offset"] = _range("offset", s["offset"], lambda x: x >= -255.0, 255.0)
    s["lost"] = _range("lost", s["lost"], lambda x: x >= 0.0, 0.9)
    s["shift_px"] = _number("shift_px", s["shift_px"], 50.0)
    s["scale"] = _number("scale", s["scale"], 0.5)
    s["rotate_deg"] = _number("rotate_deg", s["rotate_deg"], 45.0)
    return s


def draw_session(settings: dict, rng: np.random.Generator) -> SessionDraw:
    """One session drawn from ``settings`` (module doc)."""
    def log_uniform(lo, hi):
        return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
    th = rng.uniform(0.0, 2.0 * math.pi)
    r = settings["shift_px"] * math.sqrt(rng.uniform())        # uniform over the disc
    return SessionDraw(gain=log_uniform(*settings["gain"]),
                       gamma=log_uniform(*settings["gamma"]),
                       offset=float(rng.uniform(*settings["offset"])),
                       dx=r * math.cos(th), dy=r * math.sin(th),
                       scale=1.0 + float(rng.uniform(-1, 1)) * settings["scale"],
                       rot_deg=float(rng.uniform(-1, 1)) * settings["rotate_deg"])


def exposure(image: np.ndarray, gain: float = 1.0, gamma: float = 1.0,
             offset: float = 0.0) -> np.ndarray:
    """``image`` (uint8) as a camera of another exposure gives it:
    ``255 * clip((gain x + offset) / 255, 0, 1) ** gamma``, uint8, in float32 (the
    training copies here and the bench's proxies, :mod:`host.bench.texture_robust`)."""
    from host.data.windows import DataError
    if not (gain > 0 and gamma > 0 and np.isfinite(offset)):
        raise DataError(f"exposure needs gain > 0, gamma > 0 and a finite offset, got "
                        f"gain={gain!r}, gamma={gamma!r}, offset={offset!r}")
    if (gain, gamma, offset) == (1.0, 1.0, 0.0):
        return image
    x = np.clip((np.arange(256, dtype=np.float32) * np.float32(gain) + np.float32(offset))
                / np.float32(255.0), 0.0, 1.0)
    if gamma != 1.0:
        x = x ** np.float32(gamma)
    return np.round(x * 255.0).astype(np.uint8)[np.asarray(image, np.uint8)]


def perturbed_layout(layout_px, draw: SessionDraw) -> np.ndarray:
    """The layout (M, 2) px scaled, rotated about its centre and shifted as ``draw``
    says."""
    from device.pi.vision.layout import similarity
    p = np.asarray(layout_px, np.float64).reshape(-1, 2)
    return similarity(p, p.mean(axis=0), draw.scale, math.radians(draw.rot_deg),
                      np.array([draw.dx, draw.dy]))


def lose_pins(vectors: np.ndarray, lost: np.ndarray, share: tuple, rng) -> None:
    """In place: in each window of ``vectors`` (N, T, M, 2) / ``lost`` (N, T, M), a
    share of the pins uniform in ``share`` = [low, high] lost for the whole window
    (vector zero, flag set)."""
    N, _, M = lost.shape
    k = np.floor(rng.uniform(share[0], share[1], N) * M + rng.random(N)).astype(np.int64)
    k = np.minimum(k, M)
    order = np.argsort(rng.random((N, M)), axis=1)
    pick = np.arange(M)[None, :] < k[:, None]                  # the first k of a shuffle
    gone = np.zeros((N, M), bool)
    np.put_along_axis(gone, order, pick, axis=1)
    lost |= gone[:, None, :]
    vectors[np.broadcast_to(gone[:, None, :], lost.shape)] = 0.0


class _Frame:
    __slots__ = ("image", "t_s")

    def __init__(self, image, t_s):
        self.image, self.t_s = image, t_s


def _frames(trial: dict, end: int):
    """(frames 0 .. end-1 of a trial, as objects with ``image`` and ``t_s``; fps) or
    None when its frames cannot be read again."""
    kind, path = trial.get("kind"), trial.get("path")
    if kind not in FRAME_KINDS or not path:
        return None
    if kind == "dataset":
        from host.data.dataset import load_trial, read_index
        folder = Path(path).parent
        names = [e.get("file") for e in read_index(folder, check_files=False)["trials"]]
        if Path(path).name not in names:
            return None
        tr = load_trial(folder, names.index(Path(path).name))
        t_s = tr.get("t_s")
        n = min(end, len(tr["frames"]))
        return ([_Frame(tr["frames"][i], None if t_s is None else float(t_s[i]))
                 for i in range(n)], float(trial.get("fps") or 0) or None)
    from device.pi.sources.camera import open_camera
    cam = open_camera(path, end_frame=int(end))

    def gen():
        with cam:
            for fr in cam:
                yield fr
    return gen(), cam.fps


def _fingerprint(path: str) -> tuple:
    try:
        st = Path(path).stat()
        return (st.st_size, st.st_mtime_ns)
    except (OSError, ValueError):
        return ()


def session_clip(trial: dict, draw: SessionDraw, profile: str, end: int):
    """The features (:class:`host.data.extract.ClipFeatures`) of frames 0 .. end-1 of
    ``trial`` (a ``source["trials"]`` entry) as session ``draw`` gives them, or None
    when its frames cannot be read again. Cached in memory (:data:`CACHE_SIZE`)."""
    from device.pi.vision.layout import LayoutMapper
    from device.profile import load_pipeline_profile
    from host.data.extract import extract_features, layout_for_profile

    key = (trial.get("kind"), str(trial.get("path")), _fingerprint(str(trial.get("path"))),
           draw.key(), str(profile))
    hit = _CACHE.get(key)
    if hit is not None and hit[1] >= end:
        _CACHE.move_to_end(key)
        return hit[0]
    got = _frames(trial, end)
    if got is None:
        return None
    frames, fps = got
    layout = perturbed_layout(layout_for_profile(profile), draw)
    mapper = LayoutMapper(layout, load_pipeline_profile(profile).match_gate_px)
    exposed = (_Frame(exposure(getattr(f, "image", f), draw.gain, draw.gamma, draw.offset),
                      getattr(f, "t_s", None)) for f in frames)
    clip = extract_features(exposed, profile, None, progress=False, fps=fps, mapper=mapper)
    _CACHE[key] = (clip, int(end))
    while len(_CACHE) > CACHE_SIZE:
        _CACHE.popitem(last=False)
    return clip


def _trial_seed(trial: dict | None, group: int) -> int:
    """A seed of the recording itself (its file name), so one recording gets the same
    sessions whichever set or split it is in."""
    name = Path(str(trial.get("path"))).name if trial else f"group-{group}"
    return zlib.crc32(name.encode("utf-8"))


def _copy_rows(ws, rows: np.ndarray, clip, span_start: int) -> tuple[np.ndarray, dict]:
    """(the rows of ``rows`` the session ``clip`` has a reference for, their per-frame
    parts from ``clip``)."""
    T = ws.window
    ends = np.asarray(ws.t_index[rows], np.int64) + int(span_start)
    ok = (ends >= T - 1) & (ends < clip.n_frames)
    ix = np.clip(ends[:, None] + np.arange(-T + 1, 1)[None, :], 0, max(clip.n_frames - 1, 0))
    ok &= clip.ready[ix].all(axis=1) if clip.n_frames else False
    ix = ix[ok]
    parts = {"vectors": clip.vectors[ix].astype(np.float32), "lost": clip.lost[ix].copy()}
    if ws.session is not None and clip.session is not None:
        parts["session"] = clip.session[ix]
    return rows[ok], parts


def _one_copy(ws, settings: dict, profile: str, seed: int, k: int):
    """Copy ``k``: (the WindowSet of its windows or None, frame-level trials, lost-pins
    only trials)."""
    trials = {int(t["group"]): t for t in ws.source.get("trials", []) if "group" in t}
    timed = np.asarray(ws.t_index) >= 0
    picks, per = [], {"vectors": [], "lost": [], "session": []}
    framed = lost_only = 0
    for g in np.unique(ws.groups):
        rows = np.flatnonzero(ws.groups == g)
        tr = trials.get(int(g))
        rng = np.random.default_rng([seed, k, _trial_seed(tr, int(g))])
        draw = draw_session(settings, rng)
        clip = None
        if tr is not None and timed[rows].all():
            end = int(ws.t_index[rows].max()) + int(tr.get("span_start") or 0) + 1
            clip = session_clip(tr, draw, profile, end)
        if clip is not None:
            rows, parts = _copy_rows(ws, rows, clip, int(tr.get("span_start") or 0))
            framed += 1
        else:
            parts = {"vectors": ws.vectors[rows].copy(), "lost": ws.lost[rows].copy()}
            lost_only += 1
        if not len(rows):
            continue
        lose_pins(parts["vectors"], parts["lost"], settings["lost"], rng)
        picks.append(rows)
        for name in per:
            per[name].append(parts.get(name, None if ws.session is None
                                       else ws.session[rows]))
    if not picks:
        return None, framed, lost_only
    sub = ws.subset(np.concatenate(picks))
    new = {n: np.concatenate(v) for n, v in per.items() if v and v[0] is not None}
    return replace(sub, grids=None, frames=None, **new), framed, lost_only


def augment_sessions(ws, settings, profile: str = "roboskin", seed: int = 0, onto=None):
    """``onto`` (default ``ws``) plus ``settings["copies"]`` session copies of the
    windows ``ws`` (module doc), labels, contact flags, trials and IMU rows kept.
    Grids and frame crops are left out of the result, as by
    :func:`host.learn.rates.augment_rates`. ``source["augmented_sessions"]`` records
    the settings and how many trials were re-extracted."""
    settings = session_settings(settings)
    onto = ws if onto is None else onto
    if not settings:
        return onto
    if ws.vectors is None:
        raise TrainError("sessions needs windows with pin vectors")
    parts = [replace(onto, grids=None, frames=None)]
    framed = lost_only = 0
    for k in range(settings["copies"]):
        got, f, lo = _one_copy(ws, settings, profile, seed, k)
        framed, lost_only = framed + f, lost_only + lo
        if got is not None:
            parts.append(got)
    record = dict(settings, frame_level_trials=framed, lost_pins_only_trials=lost_only,
                  windows=int(sum(len(p) for p in parts[1:])))
    cat = {}
    for name in _PARTS:
        vals = [getattr(p, name) for p in parts]
        cat[name] = None if any(v is None for v in vals) else np.concatenate(vals)
    return replace(onto, **cat, grids=None, frames=None,
                   source=dict(onto.source, augmented_sessions=record))
