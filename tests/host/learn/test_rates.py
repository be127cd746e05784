"""host/learn/rates.py: training windows re-cut as a camera of another frame rate
delivers them."""
from __future__ import annotations

import numpy as np
import pytest

from host.data.windows import WindowSet
from host.learn.rates import augment_rates, kept_frames
from host.learn.tasks import TrainError


def _trial_windows(n_frames=60, T=5, M=3, groups=(0, 1), stride=1):
    """Windows of trials whose frame f holds the value f (+1000 g) in every pin, so a
    window's frames can be read off its vectors."""
    sets = []
    for g in groups:
        ends = np.arange(T - 1, n_frames, stride)
        f = ends[:, None] - np.arange(T - 1, -1, -1)[None]            # (N, T) frame ids
        v = np.broadcast_to((f + 1000 * g)[:, :, None, None], (len(ends), T, M, 2))
        sets.append(WindowSet(task="texture", window=T, vectors=v.astype(np.float32).copy(),
                              lost=(f[:, :, None] % 7 == 0).repeat(M, 2), imu=None,
                              grids=None, frames=None, contact=np.ones(len(ends), bool),
                              labels=np.full(len(ends), f"c{g}", object), targets=None,
                              groups=np.full(len(ends), g, np.int64), t_index=ends,
                              trial_len=np.full(len(ends), n_frames, np.int64)))
    return WindowSet.concat(sets)


def test_kept_frames_follow_the_rule():
    assert kept_frames(10, "3of5").tolist() == [0, 2, 3, 5, 7, 8]
    assert kept_frames(4, "all").tolist() == [0, 1, 2, 3]
    d = kept_frames(1000, "3of5+drop10", seed=1)
    assert set(d) <= set(kept_frames(1000, "3of5")) and 0.85 < len(d) / 600 < 0.95
    with pytest.raises(TrainError, match="keep"):
        kept_frames(10, "2of3")


def test_re_cut_windows_hold_the_kept_frames_of_their_own_trial_in_order():
    ws = _trial_windows()
    T = ws.window
    out = augment_rates(ws, keeps=("3of5",))
    assert len(out) > len(ws)
    new = out.subset(np.arange(len(ws), len(out)))
    assert out.source["augmented_rates"] == ["3of5"]
    for i in range(len(new)):
        frames = new.vectors[i, :, 0, 0] - 1000 * new.groups[i]
        # the last frame is the window's own, the others are the kept frames before it
        assert frames[-1] == new.t_index[i]
        assert set(frames.astype(int) % 5) <= {0, 2, 3}
        assert np.all(np.diff(frames) > 0) and frames[-1] - frames[0] > T - 1
        assert str(new.labels[i]) == f"c{new.groups[i]}"
        assert np.array_equal(new.lost[i, :, 0], frames.astype(int) % 7 == 0)
    # every window ending on a kept frame with T kept frames before it is cut
    first_full = kept_frames(60, "3of5")[T - 1]
    want = sum(1 for e in ws.t_index if e % 5 in (0, 2, 3) and e >= first_full)
    assert len(new) == want


def test_windows_of_a_coarser_stride_and_drops_still_re_cut_only_known_frames():
    ws = _trial_windows(stride=3)
    out = augment_rates(ws, keeps=("3of5+drop10",), seed=2)
    new = out.subset(np.arange(len(ws), len(out)))
    assert len(new) > 0
    frames = new.vectors[:, :, 0, 0] - 1000 * new.groups[:, None]
    assert (np.diff(frames, axis=1) >= 1).all() and (np.diff(frames, axis=1) <= 5).all()
    assert np.array_equal(augment_rates(ws, keeps=("3of5+drop10",), seed=2).vectors,
                          out.vectors)                               # seeded


def test_windows_without_time_order_are_kept_but_not_re_cut():
    ws = _trial_windows()
    ws.t_index[:] = -1
    assert len(augment_rates(ws)) == len(ws)


@pytest.mark.real
@pytest.mark.slow
def test_re_cut_windows_are_close_to_the_recording_replayed_3_of_5(tmp_path):
    """On a real clip, the windows re-cut with 3 of 5 frames kept are close to those
    the marker pipeline gives when the camera delivers only those frames (pins are
    matched frame to frame, so they are not identical): under 0.5 px apart on the
    pins both track, and under 10 % of the lost flags differ."""
    from host.bench.texture_robust import Variant, clip_variant, clip_windows
    from tests.realdata import real_data_dir
    path = real_data_dir("roboskin/lego_train.avi") / "roboskin" / "lego_train.avi"
    c, o = clip_variant(path, Variant("later"), cache_dir=tmp_path)
    ws = clip_windows(c, o, "lego", 15, 0, len(o), "lego")
    aug = augment_rates(ws, ("3of5",))
    new = aug.subset(np.arange(len(ws), len(aug)))
    c3, o3 = clip_variant(path, Variant("rate-3of5", "3of5"), cache_dir=tmp_path)
    w3 = clip_windows(c3, o3, "lego", 15, 0, len(o), "lego")
    at = {int(t): j for j, t in enumerate(w3.t_index)}
    pairs = [(i, at[int(t)]) for i, t in enumerate(new.t_index) if int(t) in at]
    assert len(pairs) >= 0.8 * len(new) >= 40
    px = [np.linalg.norm(new.vectors[i] - w3.vectors[j], axis=2)[~new.lost[i] & ~w3.lost[j]]
          .mean() for i, j in pairs]
    flags = [(new.lost[i] != w3.lost[j]).mean() for i, j in pairs]
    assert np.mean(px) < 0.5 and np.mean(flags) < 0.1
