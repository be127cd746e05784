"""device/pi/vision/layout.py: the fixed pin layout of a profile, without the simulator."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from device.pi.vision.layout import LayoutError, layout_assignment, layout_for_profile
from device.profile import load_pipeline_profile, load_profile

REPO = Path(__file__).resolve().parents[4]


def test_layout_for_profile_is_the_profile_pins_in_order():
    for name, m in (("roboskin", 133), ("tactip331", 331)):
        lay = layout_for_profile(name)
        assert lay.shape == (m, 2) and lay.dtype == np.float64
        assert np.array_equal(lay, load_profile(name).pins_px)


def test_layout_for_profile_does_not_load_the_simulator():
    code = ("import sys; from device.pi.vision.layout import layout_for_profile; "
            "layout_for_profile('roboskin'); "
            "print(sorted(m for m in sys.modules if m.startswith('device.sim')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                         env={"PYTHONPATH": str(REPO)}, check=True)
    assert out.stdout.strip() == "[]"


def test_a_vision_only_profile_is_a_layout_error(tmp_path):
    p = tmp_path / "cal.toml"
    p.write_text("[vision]\npitch_px=12.0\nn_pins=133\n")
    with pytest.raises(LayoutError, match="cal.toml"):
        layout_for_profile(str(p))


def test_layout_assignment_follows_a_shifted_reference():
    lay = layout_for_profile("roboskin")
    ref = lay[::-1] + [3.0, -2.0]
    idx = layout_assignment(ref, lay, 4.0)
    assert (idx == np.arange(len(lay))[::-1]).all()


# --------------------------------------------------------------------------
# The rest layout aligned to the profile: shift, scale and rotation (issue 33)
# --------------------------------------------------------------------------

def _similar(lay, scale, deg, shift):
    """``lay`` scaled and rotated about its centroid, then shifted."""
    c = lay.mean(axis=0)
    th = np.radians(deg)
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    return (lay - c) @ R.T * scale + c + np.asarray(shift, np.float64)


def test_a_reference_scaled_rotated_and_shifted_keeps_every_pin():
    """A second session whose camera sits 4 % nearer, whose dome is turned 3 degrees
    and shifted 5 px: every layout pin goes to its own pin (the median shift alone
    lost the outer rings: 72 of 133 right)."""
    lay = layout_for_profile("roboskin")
    gate = load_pipeline_profile("roboskin").match_gate_px
    perm = np.random.default_rng(3).permutation(len(lay))
    ref = _similar(lay, 1.04, 3.0, [5.0, 0.0])[perm]
    idx = layout_assignment(ref, lay, gate)
    assert (idx == np.argsort(perm)).all()
    from device.pi.vision.layout import fit_layout_alignment
    a = fit_layout_alignment(ref, lay, gate)
    assert a.kind == "similarity" and a.reason == "" and a.matched == len(lay)
    assert abs(a.scale - 1.04) < 1e-6 and abs(a.rotation_deg - 3.0) < 1e-4
    assert np.allclose(a.shift_px, (5.0, 0.0), atol=1e-4) and a.residual_px < 1e-6


def test_an_alignment_beyond_what_a_new_session_changes_is_refused_with_a_reason():
    """A scale outside 0.9..1.1 or a rotation beyond 5 degrees is a bad reference:
    the layout is only shifted, and the alignment says why."""
    from device.pi.vision.layout import fit_layout_alignment
    lay = layout_for_profile("roboskin")
    for scale, deg, word in ((1.13, 0.0, "scale 1.130"), (1.0, 8.0, "rotation 8.00")):
        a = fit_layout_alignment(_similar(lay, scale, deg, [2.0, -1.0]), lay, 4.68)
        assert a.kind == "shift" and word in a.reason, a
        assert a.scale == 1.0 and a.rotation_deg == 0.0
        assert np.array_equal(a.assignment, layout_assignment(
            _similar(lay, scale, deg, [2.0, -1.0]), lay, 4.68))


def test_few_pins_fall_back_to_the_shift_and_say_so():
    from device.pi.vision.layout import MIN_FIT_PINS, fit_layout_alignment
    lay = layout_for_profile("roboskin")
    a = fit_layout_alignment(lay[:3] + [1.0, 0.5], lay, 4.68)
    assert a.kind == "shift" and f"need {MIN_FIT_PINS}" in a.reason
    assert list(a.assignment[:3]) == [0, 1, 2] and (a.assignment[3:] == -1).all()
    none = fit_layout_alignment(np.zeros((0, 2)), lay, 4.68)
    assert none.kind == "none" and none.matched == 0 and (none.assignment == -1).all()
    assert "no usable reference pins" in none.reason


def _old_median_shift(ref, lay, gate, rounds=3):
    """The layout mapping before issue 33: the median shift alone."""
    from device.pi.vision.matching import match_pins
    shift = np.zeros(2)
    for r in range(rounds):
        idx = match_pins(lay + shift, ref, gate * (1.5 if r == 0 else 1.0))
        ok = idx >= 0
        if ok.sum() < 3:
            break
        shift = np.median(ref[idx[ok]] - lay[ok], axis=0)
    return match_pins(lay + shift, ref, gate)


def test_a_real_rest_frame_keeps_the_assignment_the_shift_got_right():
    """The rest frame of a real recording (smooth.avi, its first frame through the
    Pi's marker pipeline) against the roboskin layout: the fit is near the identity
    and every pin the median shift assigned keeps its pin."""
    from device.pi.vision.layout import fit_layout_alignment
    from device.pi.vision.pipeline import MarkerStream
    from tests.realdata import read_video, real_data_dir
    data = real_data_dir("roboskin/smooth.avi")
    stream = MarkerStream("roboskin")
    for im in read_video(data / "roboskin" / "smooth.avi", 0, 30):
        stream.process(im)
        if stream.reference is not None:
            break
    assert stream.reference is not None
    ref = np.asarray(stream.reference, np.float64)
    lay = layout_for_profile("roboskin")
    gate = stream.profile.match_gate_px
    old = _old_median_shift(ref, lay, gate)
    a = fit_layout_alignment(ref, lay, gate)
    assert a.kind == "similarity" and abs(a.scale - 1.0) < 0.005 and abs(a.rotation_deg) < 0.5
    kept = old >= 0
    assert kept.sum() >= 100
    assert np.array_equal(a.assignment[kept], old[kept])
    assert a.matched >= int(kept.sum())


def test_the_mapper_keeps_the_references_alignment():
    from types import SimpleNamespace

    from device.pi.vision.layout import LayoutMapper
    lay = layout_for_profile("roboskin")
    m = LayoutMapper(lay, 4.68)
    assert m.alignment is None
    ref = _similar(lay, 0.97, -2.0, [-3.0, 4.0])
    stream = SimpleNamespace(reference=ref)
    ff = SimpleNamespace(vectors=np.ones((len(ref), 2), np.float32),
                         lost=np.zeros(len(ref), bool))
    v, lost = m(stream, ff)
    assert not lost.any() and (v == 1.0).all()
    s = m.alignment.summary()
    assert s["kind"] == "similarity" and s["matched"] == len(lay) == s["layout_pins"]
    assert s["scale"] == 0.97 and s["rotation_deg"] == -2.0 and s["shift_px"] == [-3.0, 4.0]


_coord = st.one_of(st.floats(-400, 800), st.just(float("nan")), st.just(float("inf")),
                   st.just(1e12))


@settings(max_examples=100, deadline=None)
@given(ref=st.lists(st.tuples(_coord, _coord), max_size=30),
       kind=st.sampled_from(["free", "line", "same", "layout"]),
       gate=st.floats(0.5, 20.0))
def test_any_reference_gives_a_one_to_one_assignment_and_finite_numbers(ref, kind, gate):
    """Zero pins, one pin, pins in a line, one point repeated, NaN / inf / huge
    coordinates, a piece of the layout: a valid assignment and finite numbers."""
    from device.pi.vision.layout import fit_layout_alignment
    lay = layout_for_profile("roboskin")
    r = np.asarray(ref, np.float64).reshape(-1, 2)
    if kind == "line" and len(r):
        r = np.column_stack((r[:, 0], 0.5 * r[:, 0] + 3.0))
    elif kind == "same" and len(r):
        r = np.repeat(r[:1], len(r), axis=0)
    elif kind == "layout":
        r = np.concatenate((lay[: len(r) * 4] * 1.02 + 1.5, r))
    with np.errstate(all="ignore"):
        a = fit_layout_alignment(r, lay, gate)
    idx = a.assignment
    assert idx.shape == (len(lay),) and idx.dtype == np.int64
    got = idx[idx >= 0]
    assert len(set(got.tolist())) == len(got) and ((got >= 0) & (got < len(r))).all()
    assert np.isfinite(r[got]).all()
    assert a.matched == len(got)
    assert np.isfinite([*a.shift_px, a.scale, a.rotation_deg, a.residual_px]).all()
    assert 0.9 <= a.scale <= 1.1 and abs(a.rotation_deg) <= 5.0
    assert a.kind in ("similarity", "shift", "none")
