"""device/pi/vision/core.py and detect.c: the compiled pin detection gives the numpy
(OpenCV) path's smoothed box, binary image, pins, areas and blob count to the byte."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from device.pi.vision import core, native
from device.pi.vision.extract import PinDetector
from device.profile import VisionParams
from tests import REPO_ROOT
from tests.realdata import real_data_dir


@pytest.fixture(scope="module")
def lib(tmp_path_factory):
    """The loaded library's functions (``.detect``, ``.grid``): built into a private
    folder, or the one TACFOOT_NATIVE_DIR names (the sanitizer run's)."""
    if native.active() and os.environ.get("TACFOOT_NATIVE_DIR"):
        return native._FN
    if shutil.which(os.environ.get("CC", "cc")) is None:
        pytest.skip("no C compiler here: detection runs on OpenCV")
    return native.kernel(native.build(folder=tmp_path_factory.mktemp("native")))


@pytest.fixture(scope="module")
def fn(lib):
    """tf_detect."""
    return lib.detect


def image(kind: str, h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if kind == "black":
        return np.zeros((h, w), np.uint8)
    if kind == "white":
        return np.full((h, w), 255, np.uint8)
    if kind == "noise":
        return rng.integers(0, 256, (h, w), dtype=np.uint8)
    if kind == "salt":
        a = np.full((h, w), 60, np.uint8)
        a[rng.random((h, w)) < 0.05] = 255
        return a
    a = rng.integers(30, 80, (h, w), dtype=np.uint8)          # a dome: dots on a floor
    for cx, cy, r in zip(rng.uniform(0, w, 200), rng.uniform(0, h, 200), rng.uniform(1, 6, 200)):
        cv2.circle(a, (int(cx), int(cy)), int(r), int(rng.integers(120, 256)), -1)
    return a


def both(fn, det: PinDetector, crop: np.ndarray):
    """(numpy's, the core's) outputs of one crop on one detector."""
    xy, areas = det.detect_numpy(crop)
    want = (xy, areas, det._smooth.copy(), det._binary_even.copy(), det.n_blobs)
    c = core.DetectCore(fn, det)
    det._smooth[:] = 7
    det._binary_even[:] = 0
    n = c.detect(crop)
    assert n >= 0
    return want, (c.xy[:n].copy(), c.areas[:n].copy(), det._smooth.copy(),
                  det._binary_even.copy(), c.n_blobs)


def assert_same(want, got):
    for name, a, b in zip(("pins", "areas", "smooth", "binary", "blobs"), want, got):
        assert np.array_equal(a, b), name


@settings(max_examples=int(os.environ.get("TACFOOT_FUZZ_EXAMPLES", "150")), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(h=st.integers(8, 120), w=st.integers(8, 120), seed=st.integers(0, 2**31),
       kind=st.sampled_from(["dots", "noise", "salt", "black", "white"]),
       block=st.sampled_from([3, 5, 7, 9, 11, 13, 15]),
       sigma=st.sampled_from([0.0, 0.5, 1.0, 1.7, 3.0]), offset=st.floats(0, 60),
       min_area=st.integers(1, 30), extra=st.integers(0, 300),
       dome=st.one_of(st.none(), st.tuples(st.floats(0.2, 0.8), st.floats(0.2, 0.8),
                                           st.floats(0.1, 0.7))),
       shrink=st.floats(0.5, 1.0))
def test_the_core_gives_opencvs_bytes(fn, h, w, seed, kind, block, sigma, offset, min_area,
                                      extra, dome, shrink):
    params = VisionParams(block=block, offset=offset, blur_sigma_px=sigma, min_area_px=min_area,
                          max_area_px=min_area + extra, roi_shrink=shrink)
    d = None if dome is None else (dome[0] * w, dome[1] * h, dome[2] * min(h, w))
    det = PinDetector(params, (h, w), d)
    frame = image(kind, h, w, seed)
    crop = det.gray_crop(frame)
    assert_same(*both(fn, det, crop))


@pytest.mark.parametrize("block", [3, 5, 7, 9, 11, 13, 15])
def test_the_threshold_without_a_division_is_the_rounded_mean_threshold(block):
    """detect.c compares S + h < N * max(p - f, 0) in 16 bits instead of dividing out
    the mean: the same answer as OpenCV's rounded mean for every sum, pixel and
    offset, and nothing leaves 16 bits."""
    n = block * block
    s = np.arange(n * 255 + 1, dtype=np.int64)[:, None]
    mean = np.floor(s / n + 0.5).astype(np.int64)
    for f in (0, 1, 14, 60, 254, 255):
        p = np.arange(256, dtype=np.int64)[None, :]
        want = np.maximum(p - mean, 0) > f
        got = s + (n - 1) // 2 < n * np.maximum(p - f, 0)
        assert np.array_equal(got, want), f
    assert n * 255 + (n - 1) // 2 < 65536


@pytest.mark.parametrize("ksize, sigma", [(3, 0.5), (5, 1.0), (7, 1.5), (15, 3.5)])
def test_the_taps_are_opencvs_fixed_point_kernel(ksize, sigma):
    taps = core.gaussian_taps(ksize, sigma)
    assert int(taps.sum()) == 256 and np.array_equal(taps, taps[::-1])
    # a bright row pixel spreads as the taps: the row pass of a one-row image
    a = np.zeros((1, 64), np.uint8)
    a[0, 32] = 255
    out = cv2.GaussianBlur(a, (ksize, 1), sigma)
    r = ksize // 2
    assert np.array_equal(out[0, 32 - r:33 + r], (taps.astype(np.int64) * 255 * 256 + 32768) >> 16)


def test_a_detector_whose_core_disagrees_keeps_opencv(fn, monkeypatch):
    """The self-check at start: a core with a wrong blur is refused, and why is said."""
    real = core.gaussian_taps
    monkeypatch.setattr(core, "gaussian_taps", lambda k, s: np.roll(real(k, s), 1))
    monkeypatch.setattr(native, "detect_fn", lambda: fn)
    det = PinDetector(VisionParams(), (200, 240), (120.0, 100.0, 80.0))
    assert not det.compiled
    assert "differ from OpenCV" in det.compiled_why
    monkeypatch.setattr(core, "gaussian_taps", real)
    det = PinDetector(VisionParams(), (200, 240), (120.0, 100.0, 80.0))
    assert det.compiled and det.compiled_why == ""


def test_a_dropped_detector_is_freed_at_once_with_its_core(fn, monkeypatch):
    """No reference cycle between a detector and its core: dropping the detector
    frees its buffers at once, not at the cyclic collector's next pass (a
    calibration trying many settings on a whole frame peaked at 678 MB before)."""
    import gc
    import weakref
    monkeypatch.setattr(native, "detect_fn", lambda: fn)
    det = PinDetector(VisionParams(), (200, 240), (120.0, 100.0, 80.0))
    assert det.compiled
    gone = weakref.ref(det)
    core_gone = weakref.ref(det._compiled)
    gc.disable()
    try:
        del det
        assert gone() is None and core_gone() is None
    finally:
        gc.enable()


def test_a_negative_offset_goes_back_to_opencv(fn, monkeypatch):
    monkeypatch.setattr(native, "detect_fn", lambda: fn)
    det = PinDetector(VisionParams(), (200, 240), (120.0, 100.0, 80.0))
    assert det.compiled
    det.set_offset(-3.0)
    assert not det.compiled and "negative" in det.compiled_why
    frame = image("dots", 200, 240, 1)
    xy, _ = det.detect(frame)
    assert np.isfinite(xy).all()


def _pipeline_digest(clip, compiled: bool) -> str:
    from device.pi.vision.pipeline import MarkerStream
    cap = cv2.VideoCapture(str(clip))
    ms, h, n = MarkerStream("roboskin"), hashlib.sha256(), 0
    while n < 200:
        ok, f = cap.read()
        if not ok:
            break
        if not compiled and ms.detector is not None:
            ms.detector._compiled = None
        if not compiled:
            ms.grid._compiled = None
        ff = ms.process(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY))
        for a in (ff.pins, ff.vectors, ff.lost, ff.grid):
            h.update(np.ascontiguousarray(a).tobytes())
        h.update(repr((ff.contact, ff.shear_x, ff.shear_y, ff.magnitude_sum, ff.faults)).encode())
        n += 1
    assert n > 100 and ms.detector.compiled == compiled
    assert (ms.grid._compiled is not None) == compiled
    return h.hexdigest()


@pytest.mark.real
@pytest.mark.parametrize("clip", ["lego_train.avi", "smooth.avi"])
def test_real_clips_are_identical_with_the_compiled_detection_and_grid(lib, monkeypatch, clip):
    path = real_data_dir(f"roboskin/{clip}") / "roboskin" / clip
    monkeypatch.setattr(native, "detect_fn", lambda: lib.detect)
    monkeypatch.setattr(native, "grid_fn", lambda: lib.grid)
    assert _pipeline_digest(path, True) == _pipeline_digest(path, False)


# Every C entry point (detect.c's tf_detect, tf_grid and tf_shear, match.c's tf_match,
# tf_grow, tf_advance and tf_track, winfeat.c's tf_winfeat, frame.c's tf_frame) under
# AddressSanitizer and UndefinedBehaviorSanitizer: the library is built with both, and
# the hypothesis equivalence tests of this file and test_native.py run against it in a
# child Python (the sanitizer runtime preloaded). Any error report fails the child.
SAN_FLAGS = "-fsanitize=address,undefined -fno-sanitize-recover=all -fno-omit-frame-pointer -g"


def _runtime(name: str) -> str | None:
    cc = shutil.which(os.environ.get("CC", "cc"))
    if cc is None:
        return None
    out = subprocess.run([cc, f"-print-file-name={name}"], capture_output=True, text=True).stdout.strip()
    return out if os.path.isabs(out) and os.path.exists(out) else None


@pytest.mark.slow
def test_the_c_entry_points_under_asan_and_ubsan(tmp_path):
    asan = _runtime("libasan.so")
    if asan is None:
        pytest.skip("the C compiler has no AddressSanitizer runtime (libasan) here")
    env = dict(os.environ, TACFOOT_NATIVE_DIR=str(tmp_path), TACFOOT_NATIVE_CFLAGS=SAN_FLAGS,
               PYTHONPATH=str(REPO_ROOT), LD_PRELOAD=asan,
               ASAN_OPTIONS="detect_leaks=0:abort_on_error=1",
               UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1", TACFOOT_FUZZ_EXAMPLES="80")
    build = subprocess.run([sys.executable, "-m", "device.pi.vision.native", "build"], env=env,
                           capture_output=True, text=True, cwd=REPO_ROOT, timeout=300)
    if build.returncode != 0 and "sanitize" in build.stderr:
        pytest.skip(f"the compiler cannot build with sanitizers: {build.stderr.strip()[-200:]}")
    assert build.returncode == 0, build.stderr
    tests = ["tests/device/pi/vision/test_core.py::test_the_core_gives_opencvs_bytes",
             "tests/device/pi/vision/test_core.py::test_a_negative_offset_goes_back_to_opencv",
             "tests/device/pi/vision/test_core.py::test_the_compiled_grid_gives_numpys_grid_and_contact_to_the_bit",
             "tests/device/pi/vision/test_core.py::test_the_compiled_advance_is_numpys_to_the_bit",
             "tests/device/pi/vision/test_core.py::test_the_compiled_shear_is_numpys_to_the_bit",
             "tests/device/pi/vision/test_core.py::test_the_compiled_tracker_update_is_numpys_to_the_bit",
             "tests/device/pi/vision/test_native.py::test_the_kernel_gives_the_numpy_assignment",
             "tests/device/pi/vision/test_native.py::test_large_layouts_match_as_numpy_does",
             "tests/device/pi/vision/test_native.py::test_the_compiled_growth_gives_numpys_pins_and_vectors",
             "tests/device/pi/models/test_winfeat.py::test_the_compiled_features_are_numpys_to_the_bit_and_finite",
             "tests/device/pi/models/test_winfeat.py::test_the_kernel_refuses_a_bad_context_and_writes_nothing",
             "tests/device/pi/vision/test_frame.py::test_any_box_and_pin_count_give_the_sequential_bytes",
             "tests/device/pi/vision/test_frame.py::test_fused_and_sequential_streams_give_the_same_bytes",
             "tests/device/pi/vision/test_frame.py::test_a_refused_context_runs_nothing",
             "tests/device/pi/vision/test_frame.py::test_each_refused_kernel_hands_back_its_stage"]
    run = subprocess.run([sys.executable, "-m", "pytest", "-x", "-p", "no:cacheprovider",
                          "-p", "no:xdist", *tests], env=env, capture_output=True, text=True,
                         cwd=REPO_ROOT, timeout=900)
    out = run.stdout + run.stderr
    assert run.returncode == 0, out[-3000:]
    assert "ERROR: AddressSanitizer" not in out and "runtime error:" not in out
    assert " passed" in out


# -- the contact grid (detect.c's tf_grid, ContactGrid's compiled update) ----------

@settings(max_examples=int(os.environ.get("TACFOOT_FUZZ_EXAMPLES", "150")), deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(h=st.integers(1, 90), w=st.integers(1, 90), n=st.integers(1, 20), seed=st.integers(0, 2**31),
       gamma=st.floats(0, 0.2), thr=st.floats(0, 0.5), p=st.floats(0, 1), frames=st.integers(1, 6),
       stride_pad=st.integers(0, 3))
def test_the_compiled_grid_gives_numpys_grid_and_contact_to_the_bit(lib, monkeypatch, h, w, n, seed,
                                                                   gamma, thr, p, frames, stride_pad):
    from device.pi.vision.features import ContactGrid
    rng = np.random.default_rng(seed)
    ref = np.where(rng.random((h, w)) < 0.3, 255, 0).astype(np.uint8)
    monkeypatch.setattr(native, "grid_fn", lambda: lib.grid)
    a, b = ContactGrid(n, gamma, thr), ContactGrid(n, gamma, thr)
    a.set_reference(ref)
    monkeypatch.setattr(native, "grid_fn", lambda: None)
    b.set_reference(ref)
    assert a._compiled is not None and b._compiled is None
    for _ in range(frames):
        big = np.where(rng.random((h, w + stride_pad)) < p, 255, 0).astype(np.uint8)
        img = big[:, :w]                       # rows of any stride, as the detector's
        ga, ca = a.update(img)
        gb, cb = b.update(img)
        assert ca == cb and ga.tobytes() == gb.tobytes()


# -- the tracker's prediction state and the shear features (tf_advance, tf_shear) --

finite_or_not = st.one_of(st.floats(-1e9, 1e9), st.sampled_from([np.nan, np.inf, -np.inf, 0.0, -0.0]))


@settings(max_examples=int(os.environ.get("TACFOOT_FUZZ_EXAMPLES", "150")), deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(m=st.integers(0, 60), seed=st.integers(0, 2**31), steps=st.integers(1, 5),
       frac=st.floats(0, 1), pitch=st.floats(0.5, 30), odd=st.lists(finite_or_not, max_size=6))
def test_the_compiled_advance_is_numpys_to_the_bit(lib, monkeypatch, m, seed, steps, frac, pitch, odd):
    from device.pi.vision.tracking import Tracker
    rng = np.random.default_rng(seed)
    layout = rng.uniform(0, 200, (max(m, 3), 2))
    out = []
    for compiled in (True, False):
        monkeypatch.setattr(native, "advance_fn", (lambda: lib.advance) if compiled else (lambda: None))
        t = Tracker(max_dist_px=5.0, pitch_px=pitch)
        t.set_reference(layout)
        r2 = np.random.default_rng(seed + 1)
        t._disp[:] = r2.normal(0, 3, t._disp.shape)
        t._vel[:] = r2.normal(0, 3, t._vel.shape)
        work = r2.normal(0, 5, t._disp.shape)
        work.flat[:len(odd)] = odd[:work.size]
        lost = r2.random(len(work)) < 0.3
        n_ok = int(frac * len(work))
        t._advance(work, lost, n_ok, steps)
        out.append((t._disp.tobytes(), t._vel.tobytes()))
    assert out[0] == out[1]


@settings(max_examples=int(os.environ.get("TACFOOT_FUZZ_EXAMPLES", "150")), deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(m=st.integers(0, 300), seed=st.integers(0, 2**31), scale=st.sampled_from([0.01, 3.0, 1e5, 1e9]),
       odd=st.lists(finite_or_not, max_size=8), p_lost=st.floats(0, 1))
def test_the_compiled_shear_is_numpys_to_the_bit(lib, monkeypatch, m, seed, scale, odd, p_lost):
    from device.pi.vision import features
    rng = np.random.default_rng(seed)
    v = rng.normal(0, scale, (m, 2)).astype(np.float32)
    v.flat[:len(odd)] = np.array(odd[:v.size], np.float64).astype(np.float32)
    lost = rng.random(m) < p_lost
    monkeypatch.setattr(native, "shear_fn", lambda: lib.shear)
    got = features.shear_and_sum_lost(v, lost)
    want = features.shear_and_sum(v, ~lost)
    assert np.array(got).tobytes() == np.array(want).tobytes()
    assert all(np.isfinite(got))


def test_the_detection_context_has_the_librarys_slot_count():
    assert core.S_SLOTS == native.DETECT_SLOTS


# -- the tracker's usual frame (match.c's tf_track, Tracker._update_compiled) -------

@settings(max_examples=int(os.environ.get("TACFOOT_FUZZ_EXAMPLES", "100")), deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**31), m=st.integers(3, 150), frames=st.integers(1, 8),
       fill=st.sampled_from(["predict", "hold", "zero"]), drop=st.floats(0, 0.7),
       extra=st.integers(0, 20), move=st.floats(0, 8), steps=st.lists(st.integers(1, 3), min_size=8),
       odd=st.sampled_from([None, np.nan, np.inf, 2e6]))
def test_the_compiled_tracker_update_is_numpys_to_the_bit(lib, monkeypatch, seed, m, frames, fill,
                                                        drop, extra, move, steps, odd):
    from device.pi.vision.tracking import Tracker
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(m)))
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:m]
    ref = (grid * 11.7 + rng.normal(0, 0.5, (m, 2)) + 50).astype(np.float64)
    trackers = {}
    for compiled in (True, False):
        t = Tracker(pitch_px=11.7, fill=fill)
        t.set_reference(ref)
        trackers[compiled] = t
    shift = np.zeros(2)
    for f in range(frames):
        shift += rng.normal(0, move, 2)
        cur = ref + shift + rng.normal(0, 0.4, ref.shape)
        cur = cur[rng.random(m) >= drop]
        cur = np.vstack([cur, rng.uniform(0, side * 12 + 60, (extra, 2))])
        rng.shuffle(cur)
        cur = cur.astype(np.float32)
        if odd is not None and f == frames - 1 and len(cur):
            cur[0, 0] = odd
        out = {}
        for compiled, t in trackers.items():
            monkeypatch.setattr(native, "track_fn", (lambda: lib.track) if compiled else (lambda: None))
            before = t._update_compiled
            hits = []
            monkeypatch.setattr(t, "_update_compiled",
                                lambda c, s, b=before: hits.append(b(c, s)) or hits[-1])
            v, lost = t.update(cur, steps[f])
            out[compiled] = (v.tobytes(), lost.tobytes(), t.idx.tobytes(), t.n_tracked, t.faults,
                             t._disp.tobytes(), t._vel.tobytes(), t.reacquisitions)
        assert out[True] == out[False]


def test_a_smooth_drag_runs_every_frame_through_the_compiled_update(lib, monkeypatch):
    """The usual frame (no jump, usable pins) takes tf_track, not numpy's path."""
    from device.pi.vision.tracking import Tracker
    monkeypatch.setattr(native, "track_fn", lambda: lib.track)
    rng = np.random.default_rng(1)
    ref = np.stack(np.meshgrid(np.arange(12), np.arange(12)), -1).reshape(-1, 2) * 11.7 + 40.0
    t = Tracker(pitch_px=11.7)
    t.set_reference(ref)
    ran = []
    real = t._update_compiled
    monkeypatch.setattr(t, "_update_compiled", lambda c, s: ran.append(real(c, s)) or ran[-1])
    for f in range(20):
        cur = (ref + [0.3 * f, 0.1 * f] + rng.normal(0, 0.2, ref.shape)).astype(np.float32)
        v, lost = t.update(cur[rng.permutation(len(cur))])
        assert not lost.any() and abs(float(v[:, 0].mean()) - 0.3 * f) < 0.2
    assert all(r is not None for r in ran) and len(ran) == 20
