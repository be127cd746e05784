"""device/pi/vision/frame.py and frame.c: the marker pipeline's usual frame in one
compiled call (tf_frame) gives what the sequential path gives (MarkerStream.process with
tf_frame off: tf_detect, the plausibility check in Python, tf_track, tf_grid, tf_shear),
to the byte, and every stage it hands back to Python continues from the same state."""
from __future__ import annotations

import os
import re
import shutil

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from device.pi.vision import core, frame, native, tracking
from device.pi.vision.pipeline import MarkerStream
from device.profile import parse_pipeline_profile
from tests import REPO_ROOT
from tests.domes import DOME, render, ring_layout
from tests.realdata import real_data_dir

VISION = REPO_ROOT / "device" / "pi" / "vision"
KERNELS = ("detect", "grid", "track", "shear", "advance", "frame")
FUZZ = int(os.environ.get("TACFOOT_FUZZ_EXAMPLES", "40"))


@pytest.fixture(scope="module")
def lib(tmp_path_factory):
    """The loaded library's functions: built into a private folder, or the one
    TACFOOT_NATIVE_DIR names (the sanitizer run's)."""
    if native.active() and os.environ.get("TACFOOT_NATIVE_DIR"):
        return native._FN
    if shutil.which(os.environ.get("CC", "cc")) is None:
        pytest.skip("no C compiler here: the pipeline runs on numpy")
    return native.kernel(native.build(folder=tmp_path_factory.mktemp("native")))


def use(monkeypatch, lib, fused: bool) -> None:
    """Every kernel compiled; tf_frame on or off."""
    for k in KERNELS:
        f = None if (k == "frame" and not fused) else getattr(lib, k)
        monkeypatch.setattr(native, f"{k}_fn", lambda f=f: f)


@pytest.fixture
def statuses(monkeypatch):
    """The status of every tf_frame call."""
    seen = []
    real = frame.FrameCore.run
    monkeypatch.setattr(frame.FrameCore, "run",
                        lambda self, *a: seen.append(real(self, *a)) or seen[-1])
    return seen


def state(ff, s) -> str:
    """Everything a frame gives and the state it leaves, as text (floats by repr, so
    -0.0 is not 0.0)."""
    t, g = s.tracker, s.grid
    return repr((ff.index, ff.pins.tobytes(), ff.vectors.tobytes(), ff.lost.tobytes(),
                 ff.grid.tobytes(), ff.contact, ff.shear_x, ff.shear_y, ff.magnitude,
                 ff.magnitude_sum, ff.faults, s.implausible, s.reference_index,
                 None if s.reference is None else s.reference.tobytes(),
                 t.idx.tobytes(), t.n_tracked, t.faults, t.reacquired, t.reacquisitions,
                 t._disp.tobytes(), t._vel.tobytes(), g.grid.tobytes(), g.bad_input,
                 s.detector and s.detector.n_blobs,
                 s.detector and s.detector.sums and s.detector.sums()))


def run(monkeypatch, lib, fused, prof, frames) -> list[str]:
    use(monkeypatch, lib, fused)
    s = MarkerStream(prof)
    return [state(s.process(f, steps=k), s) for f, k in frames]


# -- the context's slots -------------------------------------------------------------

def _enum(text: str, first: str) -> list[str]:
    body = re.search(r"enum\s*{([^}]*\b" + first + r"\b[^}]*)}", text).group(1)
    body = re.sub(r"/\*.*?\*/", "", body, flags=re.S)
    return [n.split("=")[0].strip() for n in body.split(",") if n.strip()]


def test_the_slots_frame_c_reads_are_those_of_detect_c_and_match_c():
    """frame.c names the other kernels' slots it reads by number; each is the index of
    the enum member it names."""
    src = (VISION / "frame.c").read_text()
    enums = {"detect.c": _enum((VISION / "detect.c").read_text(), "TF_D_GRAY"),
             "match.c": _enum((VISION / "match.c").read_text(), "TF_T_CUR")}
    found = re.findall(r"#define F_\w+ (\d+)\s+/\* (\w+\.c)'s (TF_\w+) \*/", src)
    assert len(found) == 12
    for num, where, name in found:
        assert enums[where].index(name) == int(num), (where, name)
    assert enums["detect.c"].index("TF_D_N_SLOTS") == core.S_SLOTS


def test_the_frame_context_has_the_librarys_slot_count(lib):
    assert (frame.F_SLOTS, frame.FD_SLOTS) == native.FRAME_SLOTS
    fields = _enum((VISION / "frame.c").read_text(), "TF_F_DETECT")
    assert fields.index("TF_F_SLOTS") == frame.F_SLOTS
    assert fields.index("TF_F_CONTACT") == frame.F_CONTACT
    doubles = _enum((VISION / "frame.c").read_text(), "TF_FD_BLOB_FACTOR")
    assert doubles.index("TF_FD_MSUM") == frame.FD_MSUM


# -- simulated dome sequences ----------------------------------------------------------

def synth_profile(grid_contact: float = 0.03):
    """The simulated dome's profile; ``grid_contact`` 1.0: the grid never says contact,
    only the pins' mean magnitude does."""
    v = {"block": 11, "offset": 14.0, "min_area_px": 6, "max_area_px": 100,
         "roi_shrink": 0.9, "pitch_px": 10.0, "n_pins": len(ring_layout()),
         "dome_px": list(DOME), "grid_contact": grid_contact}
    return parse_pipeline_profile({"vision": v}, source="synth.toml")


EVENTS = ("still", "drag", "press", "jump", "back", "drop", "empty", "glare", "noise",
          "black", "bright", "moved")


def sequence(seed: int, events) -> list:
    """(frame, steps): five still frames (the reference), then one frame an event."""
    rng = np.random.default_rng(seed)
    ref = ring_layout()
    shift = np.zeros(2)
    out = [(render(ref + rng.normal(0, 0.05, ref.shape)), 1) for _ in range(5)]
    for ev, steps in events:
        if ev == "drag":
            shift += rng.uniform(-1.5, 1.5, 2)
        elif ev == "jump":
            shift += rng.choice([-1.0, 1.0], 2) * rng.uniform(5, 14, 2)
        elif ev == "back":
            shift[:] = 0.0
        pins = ref + shift + rng.normal(0, 0.1, ref.shape)
        if ev == "press":                      # pins pushed out around a point
            c = np.asarray(DOME[:2]) + rng.uniform(-30, 30, 2)
            d = pins - c
            pins = pins + d * 0.2 * np.exp(-(d ** 2).sum(1) / 600.0)[:, None]
        if ev == "drop":
            pins = pins[rng.random(len(pins)) > 0.4]
        if ev == "empty":
            pins = pins[:0]
        if ev == "noise":
            img = rng.integers(0, 256, (240, 320), dtype=np.uint8)
        elif ev == "black":
            img = np.zeros((240, 320), np.uint8)
        elif ev == "bright":
            img = render(pins, inside=150.0)
        elif ev == "moved":
            img = render(pins, dome=(DOME[0] + 45.0, DOME[1], DOME[2]))
        elif ev == "glare":
            img = render(pins, glare=[(rng.uniform(120, 200), rng.uniform(80, 160),
                                       rng.uniform(4, 20))])
        else:
            img = render(pins)
        out.append((img, steps))
    return out


@settings(max_examples=FUZZ, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31),
       events=st.lists(st.tuples(st.sampled_from(EVENTS), st.sampled_from([1, 1, 1, 2, 3])),
                       min_size=1, max_size=10),
       grid_contact=st.sampled_from([0.03, 1.0]))
def test_fused_and_sequential_streams_give_the_same_bytes(lib, monkeypatch, seed, events,
                                                         grid_contact):
    """Random simulated dome sequences (drags, presses, jumps the tracker's numpy path
    takes, lost and missing pins, glare, and frames that fail plausibility: noise,
    black, too bright, the dome moved; frames dropped between them): the same pins,
    vectors, lost flags, grid, contact, shear, faults and tracker state, frame by frame."""
    frames = sequence(seed, events)
    prof = synth_profile(grid_contact)
    assert run(monkeypatch, lib, True, prof, frames) == run(monkeypatch, lib, False, prof, frames)


def test_a_sequence_takes_every_stage_the_fused_call_can_hand_back(lib, monkeypatch, statuses):
    """The fused call does the usual frame, and hands back an implausible frame, a jump
    and a frame without pins to the Python path, with the same bytes as without it."""
    ev = [("drag", 1), ("drag", 1), ("noise", 1), ("drag", 1), ("jump", 1), ("drag", 1),
          ("empty", 1), ("press", 1), ("black", 1), ("drag", 2), ("still", 1)]
    frames = sequence(3, ev)
    prof = synth_profile()
    fused = run(monkeypatch, lib, True, prof, frames)
    seen = list(statuses)
    assert fused == run(monkeypatch, lib, False, prof, frames)
    assert {frame.DONE, frame.IMPLAUS, frame.TRACK} <= set(seen)
    assert seen.count(frame.DONE) >= 5


def test_contact_from_the_pins_mean_magnitude_alone(lib, monkeypatch, statuses):
    """With a grid that never says contact, a slow drag gives contact once the mean
    magnitude passes contact_px, on fused frames, as the sequential path gives it."""
    ref = ring_layout()
    frames = [(render(ref + [0.2 * max(0, k - 5), 0.1 * max(0, k - 5)]), 1) for k in range(16)]
    prof = synth_profile(1.0)
    fused = run(monkeypatch, lib, True, prof, frames)
    assert fused == run(monkeypatch, lib, False, prof, frames)
    use(monkeypatch, lib, True)
    s = MarkerStream(prof)
    contact = [s.process(f).contact for f, _ in frames]
    assert not any(contact[:8]) and all(contact[-3:])
    assert statuses.count(frame.DONE) >= 20


def test_a_fused_frame_reports_the_core_timer(lib, monkeypatch):
    use(monkeypatch, lib, True)
    s = MarkerStream(synth_profile())
    outs = [s.process(f) for f, _ in sequence(1, [("drag", 1)] * 4)]
    assert "core" not in outs[0].timings_ms and "detect" in outs[0].timings_ms
    last = outs[-1].timings_ms
    assert {"gray", "core", "localise", "total"} <= set(last) and "detect" not in last
    assert all(v >= 0 for v in last.values())


def test_a_copied_stream_makes_its_own_frame_context(lib, monkeypatch):
    """A deep copy's frame context points at no buffer of the original."""
    import copy
    use(monkeypatch, lib, True)
    frames = sequence(2, [("drag", 1)] * 6)
    s = MarkerStream(synth_profile())
    for f, _ in frames[:7]:
        s.process(f)
    assert s._frame_core is not None and s._frame_core.fn is lib.frame
    c = copy.deepcopy(s._frame_core)
    assert c.fn is None and not c.ctx[frame.F_DETECT]


# -- the fused context refused, and boxes of any size ------------------------------------

def _ready(monkeypatch, lib):
    use(monkeypatch, lib, True)
    s = MarkerStream(synth_profile())
    frames = sequence(4, [("drag", 1)] * 3)
    for f, _ in frames:
        s.process(f)
    assert s._frame_core is not None
    return s, frames[-1][0]


@pytest.mark.parametrize("slot", [frame.F_DETECT, frame.F_TRACK_I, frame.F_TRACK_D, frame.F_GRID,
                                  frame.F_MAGS, frame.F_DBL, frame.F_MAGS_CAP, frame.F_TRACK_CAP])
def test_a_refused_context_runs_nothing(lib, monkeypatch, slot):
    s, f = _ready(monkeypatch, lib)
    fc = s._frame_core
    ctx = fc.ctx.copy()
    ctx[slot] = -1 if slot == frame.F_TRACK_CAP else 0
    before = s.detector._smooth.copy(), s.tracker._disp.copy(), s.grid.grid.copy()
    assert lib.frame(ctx.ctypes.data) == -1
    after = s.detector._smooth, s.tracker._disp, s.grid.grid
    assert all(np.array_equal(a, b) for a, b in zip(before, after))


def test_each_refused_kernel_hands_back_its_stage(lib, monkeypatch):
    """A detection context tf_detect refuses: DETECT, nothing else run; a grid context
    tf_grid refuses: GRID, tracking done and the grid untouched."""
    s, f = _ready(monkeypatch, lib)
    fc, det = s._frame_core, s.detector
    crop = det.gray_crop(f)
    args = s.tracker.compiled_args(1)
    disp = s.tracker._disp.copy()
    bh = det._compiled.ctx[core.S_BH]
    det._compiled.ctx[core.S_BH] = 0
    assert fc.run(det._compiled, crop, s.tracker, *args[:2], s.grid, s.plausibility,
                  det.binary) == frame.DETECT
    assert np.array_equal(s.tracker._disp, disp)
    det._compiled.ctx[core.S_BH] = bh
    grid = s.grid.grid.copy()
    n = s.grid._ctx[5]
    s.grid._ctx[5] = 0
    assert fc.run(det._compiled, crop, s.tracker, *args[:2], s.grid, s.plausibility,
                  det.binary) == frame.GRID
    s.grid._ctx[5] = n
    assert np.array_equal(s.grid.grid, grid)


def _same_neighbours_once(monkeypatch) -> None:
    """The tracker's layout neighbours (numpy, O(m^2) for a reference of m pins) worked
    out once per layout and handed to both streams: the fused and the sequential
    stream set the same reference, and a 5,000-pin one took most of this test's time.
    Each caller gets its own copy, so neither stream can change the other's."""
    real, seen = tracking.layout_neighbours, {}

    def once(ref, k=6, max_dist_px=None):
        r = np.ascontiguousarray(ref)
        key = (r.dtype.str, r.shape, r.tobytes(), k, max_dist_px)
        if key not in seen:
            seen[key] = real(ref, k, max_dist_px)
        return tuple(a.copy() for a in seen[key])
    monkeypatch.setattr(tracking, "layout_neighbours", once)


@settings(max_examples=FUZZ, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(h=st.integers(8, 48), w=st.integers(8, 48), seed=st.integers(0, 2**31),
       r=st.sampled_from([0.3, 0.5, 1.0, 3.0, 10.0, 40.0]),
       kind=st.sampled_from(["dots", "noise", "black", "white", "flat"]),
       m=st.sampled_from([1, 2, 5, 60, 5000]), n_pins=st.integers(1, 200),
       grid_n=st.integers(1, 9), n_frames=st.integers(1, 4))
def test_any_box_and_pin_count_give_the_sequential_bytes(lib, monkeypatch, h, w, seed, r, kind,
                                                        m, n_pins, grid_n, n_frames):
    """Boxes from a few pixels to the frame, 0 to hundreds of pins found, references of
    1 to 5,000 pins, garbage frames: the fused stream's bytes are the sequential
    one's (the sanitizer run fuzzes tf_frame with this)."""
    rng = np.random.default_rng(seed)
    v = {"block": 3, "offset": 4.0, "min_area_px": 1, "max_area_px": 30, "roi_shrink": 1.0,
         "pitch_px": 5.0, "n_pins": n_pins, "dome_px": [w / 2, h / 2, r], "grid_n": grid_n}
    prof = parse_pipeline_profile({"vision": v}, source="fuzz.toml")
    frames = []
    for _ in range(n_frames + 1):
        a = rng.integers(20, 60, (h, w), dtype=np.uint8)
        if kind == "dots":
            for _ in range(h * w // 20):
                cv2.circle(a, (int(rng.integers(0, w)), int(rng.integers(0, h))), 1,
                           int(rng.integers(100, 256)), -1)
        elif kind == "noise":
            a = rng.integers(0, 256, (h, w), dtype=np.uint8)
        elif kind in ("black", "white", "flat"):
            a[:] = {"black": 0, "white": 255, "flat": 90}[kind]
        frames.append(a)
    layout = rng.uniform(0, max(h, w), (m, 2))
    _same_neighbours_once(monkeypatch)
    out = {}
    for fused in (True, False):
        use(monkeypatch, lib, fused)
        s = MarkerStream(prof)
        s.process(frames[0])
        if s.detector is None:
            return
        # the reference set as _maybe_choose_reference sets it
        s.reference = layout.astype(np.float32)
        s.reference_index = 0
        s.tracker.set_reference(s.reference)
        s.grid.set_reference(s.detector.binary.copy())
        s.plausibility.set_reference(s.plausibility.stats(s.detector.smooth, s.detector.n_blobs))
        out[fused] = [state(s.process(f), s) for f in frames[1:]]
    assert out[True] == out[False]


# -- the real clips --------------------------------------------------------------------

@pytest.mark.real
@pytest.mark.parametrize("clip", ["lego_train.avi", "north.avi"])
def test_real_clips_give_the_same_bytes_with_and_without_the_fused_call(lib, monkeypatch,
                                                                       statuses, clip):
    """150 frames of a real clip: identical pins, vectors, lost flags, grid, contact,
    shear, magnitude sum, faults and tracker state; the fused call takes most frames."""
    path = real_data_dir(f"roboskin/{clip}") / "roboskin" / clip
    cap = cv2.VideoCapture(str(path))
    frames = []
    while len(frames) < 150:
        ok, f = cap.read()
        if not ok:
            break
        frames.append((cv2.cvtColor(f, cv2.COLOR_BGR2GRAY), 1))
    assert len(frames) == 150
    fused = run(monkeypatch, lib, True, "roboskin", frames)
    assert statuses.count(frame.DONE) > 100
    assert fused == run(monkeypatch, lib, False, "roboskin", frames)
