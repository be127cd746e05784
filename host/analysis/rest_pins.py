"""The sensor's rest pins, found in many no-contact frames (``host calibrate``).

Every frame gives candidate spots: local maxima of a white top-hat (the frame
minus its grey opening with a disc a little wider than a pin), which keeps
pin-sized bright spots and drops the broad LED glare that hides pins from a plain
threshold. Spots are tracked from frame to frame (one-to-one within 0.4 pitch);
each track is one blob at its median position. Blobs are then kept or rejected,
and every rejection has a reason:

* ``unstable``: found in fewer than ``MIN_SEEN`` of the frames, or moving by more
  than ``MAX_SPREAD`` pitch (median distance from its median position);
* ``edge``: within half a pitch of the region's boundary (the dome's search disc
  or the frame) and weaker than the pins (``EDGE_STRENGTH``): cut by it, or a rim
  glint;
* ``duplicate``: closer than ``DUP_PITCH`` pitch to a stronger kept blob (one
  pin found twice);
* ``glare``: a spot far weaker than the pins (``MIN_STRENGTH`` of their
  median), or off the lattice: no other kept blob within ``LATTICE_PITCH``
  pitch (a glint between the rows); or a faint spot (under ``FAINT_STRENGTH`` of
  the pins' median) that is no lattice site: none of the sites its kept
  neighbours predict (a row continued a step, the midpoint of two pins) lies
  within ``SITE_PITCH`` pitch of it (:func:`lattice_error_px`).

A spot seen in fewer than ``MIN_SEEN`` but at least ``SITE_SEEN`` of the frames
(a pin the peak search misses now and then) is kept when it is steady, inside,
not a duplicate, not faint (``FAINT_STRENGTH``), and on a lattice site its kept
neighbours predict (within ``SITE_PITCH`` pitch).

Centres are sub-pixel (:func:`centres`): the centroid of what stands above a plane
fitted to a ring around each spot, so the glare's gradient does not shift a faint
pin's centre.

A kept pin is ``loose`` when its rest centre cannot be measured to a small share
of the pitch: its core is clipped at the camera's full scale in most frames (an
LED glare core: the centroid of a flat, saturated top snaps between frames), or
its centre wanders across the rest frames by more than ``WANDER_PITCH`` pitch
(80th percentile of its distance from the median). Loose pins stay in the layout
(they are pins, and a model needs every pin), but layouts of one sensor are
compared on the steady ones (:func:`agreement`).

Nothing here knows how many pins a sensor has: the pitch and the pin size come
from the threshold search, the thresholds from the spots' own distribution.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from device.pi.vision.matching import match_pins
from host.analysis.spot_scale import local_pitch_px, multiscale_spots
from device.errors import InputError

#: a rest pin is found in at least this share of the frames
MIN_SEEN = 0.8
#: ... and its median distance from its median position is at most this many pitches
MAX_SPREAD = 0.1
#: two blobs closer than this many pitches are one pin
DUP_PITCH = 0.7
#: a spot weaker than this share of the pins' median top-hat strength is glare texture
MIN_STRENGTH = 0.1
#: a kept pin has another within this many pitches (the lattice)
LATTICE_PITCH = 2.2
#: blobs within this many pitches of the region's boundary are cut by it
EDGE_PITCH = 0.5
#: ... and weaker than this share of the pins' median strength (a whole pin on the
#: boundary is as strong as the others)
EDGE_STRENGTH = 0.6

#: a spot weaker than this share of the pins' median strength must sit on a lattice site
FAINT_STRENGTH = 0.3
#: ... within this many pitches of where its neighbours' rows predict a pin
SITE_PITCH = 0.2

#: a kept pin whose centre wanders by more than this many pitches (80th percentile
#: over the rest frames of its distance from its median position) is loose
WANDER_PITCH = 0.04
#: ... and so is one whose core is clipped at the camera's full scale in more than
#: this share of the frames (a saturated glare core has no measurable centre)
CLIPPED_SHARE = 0.5
#: "full scale" is this share of the frame type's largest value (compression noise
#: keeps a clipped area a few levels under it)
FULL_SCALE = 0.98

#: a spot seen in at least this share of the frames (under MIN_SEEN) is kept when it
#: sits on a lattice site its kept neighbours predict (within SITE_PITCH)
SITE_SEEN = 0.5

REASONS = ("kept", "glare", "duplicate", "edge", "unstable")


@dataclass(frozen=True)
class Region:
    """Where pins are searched: a disc (``cx, cy, r`` px) or, with ``disc`` None,
    the whole ``width`` x ``height`` frame."""
    width: int
    height: int
    disc: tuple[float, float, float] | None = None

    def mask(self) -> np.ndarray:
        m = np.zeros((self.height, self.width), np.uint8)
        if self.disc is None:
            m[:] = 255
        else:
            cx, cy, r = self.disc
            cv2.circle(m, (int(round(cx)), int(round(cy))), max(1, int(round(r))), 255, -1)
        return m

    def inset_px(self, xy: np.ndarray) -> np.ndarray:
        """Distance (n,) px from each point to the region's boundary (or the frame's)."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        frame = np.minimum.reduce([xy[:, 0], xy[:, 1], self.width - 1 - xy[:, 0],
                                   self.height - 1 - xy[:, 1]])
        if self.disc is None:
            return frame
        cx, cy, r = self.disc
        return np.minimum(frame, r - np.hypot(xy[:, 0] - cx, xy[:, 1] - cy))


@dataclass
class RestPins:
    """Tracked blobs of the rest frames: median position ``xy`` (K, 2) px, the share
    of frames ``seen`` (K,), median ``strength`` (K,) and ``reason`` (K,) from
    :data:`REASONS`; ``pins`` are the kept ones. ``wander_px`` (K,) is how far each
    blob's centre wanders over the frames (80th percentile of its distance from its
    median position), ``clipped`` (K,) the share of frames with its core at full
    scale, and ``loose`` (K,) marks the kept pins whose centre is uncertain (see the
    module's rules)."""
    xy: np.ndarray
    seen: np.ndarray
    strength: np.ndarray
    reason: np.ndarray
    pitch_px: float
    frames: int
    wander_px: np.ndarray | None = None
    clipped: np.ndarray | None = None
    loose: np.ndarray | None = None

    @property
    def pins(self) -> np.ndarray:
        return self.xy[self.reason == "kept"]

    @property
    def pins_loose(self) -> np.ndarray:
        """(len(pins),) bool: which kept pins are loose (all False without flags)."""
        kept = self.reason == "kept"
        if self.loose is None:
            return np.zeros(int(kept.sum()), bool)
        return np.asarray(self.loose, bool)[kept]

    def counts(self) -> dict:
        return {r: int(np.count_nonzero(self.reason == r)) for r in REASONS}


def spots(gray: np.ndarray, pin_d_px: float, pitch_px: float, mask: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray]:
    """Candidate pin centres (n, 2) px (sub-pixel, :func:`centres`) and their top-hat
    strength (n,)."""
    f = gray.astype(np.float32)
    f = cv2.GaussianBlur(f, (0, 0), max(0.8, 0.3 * pin_d_px))
    k = int(2 * round(0.75 * pin_d_px) + 1)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    hat = f - cv2.morphologyEx(f, cv2.MORPH_OPEN, disc)
    w = int(2 * round(0.35 * pitch_px) + 1)
    peak = (hat >= cv2.dilate(hat, np.ones((w, w), np.uint8))) & (hat > 0.5) & (mask > 0)
    ys, xs = np.nonzero(peak)
    return centres(gray, xs, ys, pin_d_px, pitch_px), hat[ys, xs].astype(np.float64)


#: the centring window's radius, in pitches (the background ring lies just inside it)
WINDOW_PITCH = 0.45
#: weighted-centroid iterations
CENTRE_ROUNDS = 4
#: the centroid's Gaussian weight has a sigma of this many pin diameters
WEIGHT_PIN = 0.5


def centres(gray: np.ndarray, xs: np.ndarray, ys: np.ndarray, pin_d_px: float,
            pitch_px: float) -> np.ndarray:
    """Sub-pixel centres (n, 2) px of the pins whose brightest pixels are ``xs, ys``.

    In a window of ``WINDOW_PITCH`` pitch around each, the background is a plane
    fitted to the window's outer ring (where no pin is): the LED glare's gradient
    then neither lifts one side of a faint pin nor drags its centre. The centre is
    the centroid of what stands above that plane, weighted by a Gaussian of the
    pin's size around the current estimate (a few rounds, starting at the peak)."""
    n = len(xs)
    if n == 0:
        return np.zeros((0, 2))
    r = max(2, int(math.ceil(WINDOW_PITCH * pitch_px)))
    f = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 0.7).astype(np.float64)
    pad = np.pad(f, r, mode="edge")
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1]
    patch = pad[ys[:, None, None] + r + dy, xs[:, None, None] + r + dx]      # (n, P, P)
    rr = np.hypot(dx, dy)
    ring = rr >= max(r - 1.5, 0.5 * pin_d_px + 0.5)
    a = np.column_stack([np.ones(ring.sum()), dx[ring], dy[ring]])
    coef = patch[:, ring] @ np.linalg.pinv(a).T                               # (n, 3)
    plane = coef[:, 0, None, None] + coef[:, 1, None, None] * dx + coef[:, 2, None, None] * dy
    above = np.clip(patch - plane, 0.0, None)
    above[:, rr > r] = 0.0
    sigma = max(1.0, WEIGHT_PIN * pin_d_px)
    off = np.zeros((n, 2))
    for _ in range(CENTRE_ROUNDS):
        g = np.exp(-((dx - off[:, 0, None, None]) ** 2 + (dy - off[:, 1, None, None]) ** 2)
                   / (2.0 * sigma ** 2))
        wgt = above * g
        s = wgt.sum(axis=(1, 2))
        ok = s > 0
        new = np.column_stack([(wgt * dx).sum(axis=(1, 2)), (wgt * dy).sum(axis=(1, 2))])
        off[ok] = np.clip(new[ok] / s[ok, None], -r / 2.0, r / 2.0)
    return np.column_stack([xs + off[:, 0], ys + off[:, 1]]).astype(np.float64)


def _track(found: list[tuple[np.ndarray, np.ndarray]], gate_px: float):
    """One track per blob over the frames: (positions (F, K, 2) NaN where unseen,
    strengths (F, K))."""
    tracks_xy: list[list] = []
    tracks_s: list[list] = []
    centre = np.zeros((0, 2))
    for k, (xy, s) in enumerate(found):
        taken = np.zeros(len(xy), bool)
        if len(centre) and len(xy):
            idx = match_pins(centre, xy, gate_px)
            for t, j in enumerate(idx):
                if j >= 0:
                    tracks_xy[t].append((k, xy[j]))
                    tracks_s[t].append(s[j])
                    taken[j] = True
        for j in np.flatnonzero(~taken):
            tracks_xy.append([(k, xy[j])])
            tracks_s.append([s[j]])
        centre = np.array([np.mean([p for _, p in t], axis=0) for t in tracks_xy]).reshape(-1, 2)
    pos = np.full((len(found), len(tracks_xy), 2), np.nan)
    strength = np.full((len(found), len(tracks_xy)), np.nan)
    for t, (tx, ts) in enumerate(zip(tracks_xy, tracks_s)):
        for (k, p), v in zip(tx, ts):
            pos[k, t] = p
            strength[k, t] = v
    return pos, strength


def nn_px(xy: np.ndarray) -> np.ndarray:
    """Each point's distance to its nearest other point (inf for a lone point)."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    if len(xy) < 2:
        return np.full(len(xy), np.inf)
    d = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    return d.min(axis=1)


def lattice_error_px(p: np.ndarray, others: np.ndarray, pitch_px: float) -> float:
    """How far (px) ``p`` lies from the nearest site its neighbours predict: a row
    continued one step (``2a - b`` for neighbours ``a`` of ``p`` and ``b`` of ``a``
    0.6..1.6 pitch apart) or the midpoint of two neighbours more than 1.4 pitch
    apart. Inf when no neighbour is within 1.6 pitch."""
    others = np.asarray(others, np.float64).reshape(-1, 2)
    p = np.asarray(p, np.float64)
    near = others[np.hypot(*(others - p).T) < 1.6 * pitch_px]
    if len(near) == 0:
        return math.inf
    best = math.inf
    d_ab = np.hypot(*(near[:, None] - others[None]).transpose(2, 0, 1))     # (a, b)
    step = (d_ab > 0.6 * pitch_px) & (d_ab < 1.6 * pitch_px)
    pred = 2.0 * near[:, None] - others[None]
    err = np.hypot(*(pred - p).transpose(2, 0, 1))
    if step.any():
        best = float(err[step].min())
    if len(near) > 1:
        d_nn = np.hypot(*(near[:, None] - near[None]).transpose(2, 0, 1))
        mid = (near[:, None] + near[None]) / 2.0
        e = np.hypot(*(mid - p).transpose(2, 0, 1))
        wide = d_nn > 1.4 * pitch_px
        if wide.any():
            best = min(best, float(e[wide].min()))
    return best


def find_rest_pins(grays: list[np.ndarray], region: Region, pin_d_px: float,
                   pitch_px: float, multiscale: bool = False) -> RestPins:
    """The rest pins of no-contact gray frames (see the module's rules).

    With ``multiscale`` the spots come from :func:`multiscale_spots` (each pin at
    its own size) and every rule's pitch is the blob's local pitch
    (:func:`local_pitch_px` of the steady blobs); ``pin_d_px`` is then unused and
    ``pitch_px`` only sets the tracking gate."""
    if not grays:
        raise ValueError("find_rest_pins needs at least one frame")
    if not (math.isfinite(pitch_px) and pitch_px > 0):
        raise ValueError(f"pitch_px must be a positive number, got pitch_px={pitch_px!r}")
    mask = region.mask()
    if multiscale:
        found = [multiscale_spots(g, mask)[:2] for g in grays]
    else:
        found = [spots(g, pin_d_px, pitch_px, mask) for g in grays]
    pos, strength = _track(found, 0.4 * pitch_px)
    seen = np.isfinite(pos[..., 0]).mean(axis=0)
    with np.errstate(all="ignore"):
        xy = np.nanmedian(pos, axis=0).reshape(-1, 2)
        spread = np.nanmedian(np.hypot(*(pos - xy[None]).transpose(2, 0, 1)), axis=0)
        med_s = np.nanmedian(strength, axis=0)
    pitch = np.full(len(xy), float(pitch_px))
    steady = seen >= MIN_SEEN
    if multiscale and steady.sum() >= 3:
        local = local_pitch_px(xy[steady])
        nearest = match_nearest(xy, xy[steady])
        pitch = local[nearest]
    reason = np.full(len(xy), "kept", dtype=object)
    reason[~steady | ~(spread <= MAX_SPREAD * pitch)] = "unstable"
    kept = reason == "kept"
    typical = float(np.median(med_s[kept])) if kept.any() else 0.0
    near = region.inset_px(xy) < EDGE_PITCH * pitch
    reason[kept & near & (med_s < EDGE_STRENGTH * typical)] = "edge"
    reason[(reason == "kept") & (med_s < MIN_STRENGTH * typical)] = "glare"
    # one pin found twice: the stronger of two close blobs stays
    for i in np.argsort(-np.nan_to_num(med_s)):
        if reason[i] != "kept":
            continue
        d = np.hypot(*(xy - xy[i]).T)
        reason[(reason == "kept") & (d < DUP_PITCH * pitch[i]) & (np.arange(len(xy)) != i)] \
            = "duplicate"
    # off the lattice: no kept neighbour within LATTICE_PITCH pitches
    kept = reason == "kept"
    lone = nn_px(xy[kept]) > LATTICE_PITCH * pitch[kept]
    reason[np.flatnonzero(kept)[lone]] = "glare"
    # a faint spot is a pin only where its neighbours' lattice predicts one (weakest first)
    faint = np.flatnonzero((reason == "kept") & (med_s < FAINT_STRENGTH * typical))
    for i in faint[np.argsort(med_s[faint])]:
        others = xy[(reason == "kept") & (np.arange(len(xy)) != i)]
        if lattice_error_px(xy[i], others, pitch[i]) > SITE_PITCH * pitch[i]:
            reason[i] = "glare"
    # a pin seen in fewer frames is still a pin where the lattice predicts one
    rescue = np.flatnonzero((reason == "unstable") & (seen >= SITE_SEEN)
                            & (spread <= MAX_SPREAD * pitch) & (med_s >= FAINT_STRENGTH * typical)
                            & ~(region.inset_px(xy) < EDGE_PITCH * pitch))
    for i in rescue[np.argsort(-seen[rescue] - 1e-3 * med_s[rescue])]:
        kept_xy = xy[reason == "kept"]
        if len(kept_xy) and np.hypot(*(kept_xy - xy[i]).T).min() < DUP_PITCH * pitch[i]:
            continue
        if lattice_error_px(xy[i], kept_xy, pitch[i]) <= SITE_PITCH * pitch[i]:
            reason[i] = "kept"
    kept = reason == "kept"
    typical_pitch = float(np.median(pitch[kept])) if kept.any() else float(pitch_px)
    wander = wander_px(pos, xy)
    clipped = clipped_share(grays, pos)
    loose = kept & ((clipped > CLIPPED_SHARE) | ~(wander <= WANDER_PITCH * pitch))
    return RestPins(xy=xy, seen=seen, strength=np.nan_to_num(med_s), reason=reason.astype(str),
                    pitch_px=typical_pitch, frames=len(grays), wander_px=wander,
                    clipped=clipped, loose=loose)


def wander_px(pos: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """How far each track's centre wanders (K,) px: the 80th percentile over the
    frames that saw it of its distance from ``xy`` (its median position); 0 for a
    track seen once."""
    d = np.hypot(*(pos - xy[None]).transpose(2, 0, 1))                       # (F, K)
    out = np.zeros(d.shape[1])
    seen = np.isfinite(d)
    for k in np.flatnonzero(seen.sum(axis=0) > 0):
        out[k] = float(np.percentile(d[seen[:, k], k], 80))
    return out


def clipped_share(grays: list[np.ndarray], pos: np.ndarray) -> np.ndarray:
    """The share (K,) of the frames that saw each track in which the brightest pixel
    of its core (3 x 3 px around its centre in that frame) is at full scale
    (``FULL_SCALE`` of the frame type's largest value; never for float frames)."""
    hits = np.zeros(pos.shape[1])
    seen = np.zeros(pos.shape[1])
    for g, p in zip(grays, pos):
        ok = np.flatnonzero(np.isfinite(p[:, 0]))
        seen[ok] += 1
        if not np.issubdtype(g.dtype, np.integer) or not len(ok):
            continue
        level = FULL_SCALE * np.iinfo(g.dtype).max
        h, w = g.shape[:2]
        xs = np.clip(np.round(p[ok, 0]).astype(np.int64), 1, w - 2)
        ys = np.clip(np.round(p[ok, 1]).astype(np.int64), 1, h - 2)
        core = np.max([g[ys + dy, xs + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)
        hits[ok] += core >= level
    return np.where(seen > 0, hits / np.maximum(seen, 1), 0.0)


def match_nearest(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each point of ``a`` the row of its nearest point in ``b``."""
    return np.argmin(np.hypot(*(a[:, None] - b[None]).transpose(2, 0, 1)), axis=1)


def align(a: np.ndarray, b: np.ndarray, gate_px: float, rounds: int = 5):
    """Shift ``a`` onto ``b`` (start: their centroids; then the median offset of the
    one-to-one nearest pairs within ``gate_px``). Returns (shift (2,), idx (len(a),)
    the row of ``b`` each pin of ``a`` matches or -1, distances (len(a),) px, NaN
    where unmatched)."""
    a = np.asarray(a, np.float64).reshape(-1, 2)
    b = np.asarray(b, np.float64).reshape(-1, 2)
    shift = (b.mean(axis=0) - a.mean(axis=0)) if len(a) and len(b) else np.zeros(2)
    idx = np.full(len(a), -1, np.int64)
    for _ in range(rounds):
        idx = match_pins(a + shift, b, gate_px)
        ok = idx >= 0
        if not ok.any():
            break
        shift = np.median(b[idx[ok]] - a[ok], axis=0)
    idx = match_pins(a + shift, b, gate_px)
    dist = np.full(len(a), np.nan)
    ok = idx >= 0
    dist[ok] = np.hypot(*(b[idx[ok]] - a[ok] - shift).T)
    return shift, idx, dist


def agreement(a: np.ndarray, b: np.ndarray, pitch_px: float, loose_a=None, loose_b=None
              ) -> dict:
    """How two rest layouts of one sensor agree, aligned by a shift: pins matched
    one-to-one within 0.4 pitch, the count difference, and the matched distances;
    ``steady`` the same figures over the matched pins loose in neither layout
    (``loose_a`` (len(a),), ``loose_b`` (len(b),) bool; none loose when not given)."""
    a = np.asarray(a, np.float64).reshape(-1, 2)
    b = np.asarray(b, np.float64).reshape(-1, 2)
    la = np.zeros(len(a), bool) if loose_a is None else np.asarray(loose_a, bool)
    lb = np.zeros(len(b), bool) if loose_b is None else np.asarray(loose_b, bool)
    if la.shape != (len(a),) or lb.shape != (len(b),):
        raise ValueError(f"loose flags must have one entry per pin: loose_a {la.shape} for "
                         f"{len(a)} pins, loose_b {lb.shape} for {len(b)} pins")
    shift, idx, dist = align(a, b, 0.4 * pitch_px)
    ok = np.isfinite(dist)
    steady = ok.copy()
    steady[ok] = ~la[ok] & ~lb[idx[ok]]

    def figures(sel):
        d = dist[sel]
        return {"matched": int(len(d)),
                "median_px": round(float(np.median(d)), 3) if len(d) else None,
                "max_px": round(float(d.max()), 3) if len(d) else None}

    return {"pins": [int(len(a)), int(len(b))], "count_difference": int(abs(len(a) - len(b))),
            "shift_px": [round(float(v), 2) for v in shift], **figures(ok),
            "steady": figures(steady)}


def merge_layouts(layouts: list[np.ndarray], pitch_px: float) -> np.ndarray:
    """One layout from several clips' rest layouts of one sensor, in the first one's
    coordinates: each other layout is shifted onto it; a pin stays when more than
    half the clips found it, at its mean position."""
    return merge_with_flags(layouts, pitch_px)[0]


def merge_with_flags(layouts: list[np.ndarray], pitch_px: float, loose=None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`merge_layouts` and, for each merged pin, whether it is loose: loose in
    at least half of the clips that found it (``loose``: one bool array per layout;
    none loose when not given). A loose pin's position is the mean over the clips
    where it was steady, when there are any."""
    lays = [np.asarray(lay, np.float64).reshape(-1, 2) for lay in layouts]
    flags = [np.zeros(len(lay), bool) if loose is None else np.asarray(f, bool)
             for lay, f in zip(lays, loose if loose is not None else lays)]
    gate = 0.4 * pitch_px
    pts = [lays[0]]
    for lay in lays[1:]:
        shift, _, _ = align(lay, lays[0], gate)
        pts.append(lay + shift)
    # union by greedy matching to a growing list of clusters
    centre = pts[0].copy()
    members = [[(p, f)] for p, f in zip(centre, flags[0])]
    for p, fl in zip(pts[1:], flags[1:]):
        idx = match_pins(p, centre, gate)
        for j, t in enumerate(idx):
            if t >= 0:
                members[t].append((p[j], fl[j]))
            else:
                members.append([(p[j], fl[j])])
        centre = np.array([np.mean([q for q, _ in m], axis=0) for m in members])
    need = len(layouts) / 2.0
    out, out_loose = [], []
    for m in members:
        if len(m) <= need:
            continue
        steady = [q for q, f in m if not f]
        out.append(np.mean(steady if steady else [q for q, _ in m], axis=0))
        out_loose.append(2 * len(steady) <= len(m))
    return np.asarray(out, np.float64).reshape(-1, 2), np.asarray(out_loose, bool)


#: overlay colours (BGR) of each kind of blob
COLOURS = {"kept": (0, 200, 0), "glare": (0, 140, 255), "duplicate": (255, 0, 255),
           "edge": (255, 255, 0), "unstable": (0, 0, 255), "loose": (0, 255, 255)}
#: the overlay is drawn at this many times the frame's size
OVERLAY_SCALE = 2


def overlay_image(frame: np.ndarray, rest: RestPins, region: Region) -> np.ndarray:
    """A BGR image ``OVERLAY_SCALE`` times the frame's size: the rest frame with the
    search region, each kept pin (a green circle) and each rejected blob (a cross in
    its reason's colour), and a legend with the count of each kind."""
    s = OVERLAY_SCALE
    img = frame if frame.ndim == 3 else cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
    img = cv2.resize(img[..., :3], None, fx=s, fy=s, interpolation=cv2.INTER_CUBIC)
    if region.disc is not None:
        cx, cy, r = region.disc
        cv2.circle(img, (int(round(cx * s)), int(round(cy * s))), int(round(r * s)),
                   (255, 128, 0), 1, cv2.LINE_AA)
    rad = max(3, int(round(0.3 * rest.pitch_px * s)))
    loose = np.zeros(len(rest.xy), bool) if rest.loose is None else np.asarray(rest.loose, bool)
    for (x, y), why, lo in zip(rest.xy, rest.reason, loose):
        c = (int(round(x * s)), int(round(y * s)))
        if why == "kept":
            cv2.circle(img, c, rad, COLOURS["loose" if lo else why], 1, cv2.LINE_AA)
        else:
            cv2.drawMarker(img, c, COLOURS[why], cv2.MARKER_TILTED_CROSS, 2 * rad, 1, cv2.LINE_AA)
    counts = rest.counts()
    lines = [(f"kept pins: {counts['kept']}", "kept"),
             (f"  of them loose (glare-clipped or wandering): {int(loose.sum())}", "loose")] + [
        (f"rejected, {why}: {counts[why]}", why) for why in REASONS[1:]]
    cv2.rectangle(img, (4, 4), (400, 10 + 20 * len(lines)), (0, 0, 0), -1)
    for i, (text, why) in enumerate(lines):
        y = 22 + 20 * i
        cv2.circle(img, (16, y - 5), 6, COLOURS[why], -1)
        cv2.putText(img, text, (30, y), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1,
                    cv2.LINE_AA)
    return img


def write_overlay(path, frame: np.ndarray, rest: RestPins, region: Region):
    """Write :func:`overlay_image` as a PNG; returns the path."""
    from pathlib import Path
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), overlay_image(frame, rest, region)):
        raise InputError(f"could not write the overlay PNG {path}")
    return path
