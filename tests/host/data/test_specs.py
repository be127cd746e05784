"""host/data/specs.py: data specs -> windows of T frames; splits that never leak; errors."""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from host.data.simulate import simulate_to_dataset
from host.data.specs import (NO_TOUCH, SLIP_LABELS, DataError, LayoutMapper, WindowSet,
                       group_kfold, layout_for_profile, load_spec, load_specs,
                       split_grouped, split_time)
from host.data.dataset import load_trial


@pytest.fixture(scope="module")
def sim_ds(tmp_path_factory):
    """A dataset folder: press-hard (seeds 0, 1) and press-soft (seed 0), 96 frames each."""
    out = tmp_path_factory.mktemp("data") / "ds"
    simulate_to_dataset("press-hard", out, seed=0, trials=2, progress=False)
    simulate_to_dataset("press-soft", out, seed=0, trials=1, progress=False)
    return out


@pytest.fixture(scope="module")
def cache():
    return {}


def write_csv(path: Path, rows: list[str]) -> Path:
    path.write_text("\n".join(rows) + "\n")
    return path


# -- dataset folder ----------------------------------------------------------

def test_dataset_windows_have_the_right_shapes_and_truth_labels(sim_ds, cache):
    T = 4
    ws = load_spec(str(sim_ds), "surface", T, progress=False, cache=cache)
    n = len(ws)
    assert ws.vectors.shape == (n, T, 133, 2) and ws.vectors.dtype == np.float32
    assert ws.lost.shape == (n, T, 133) and ws.lost.dtype == bool
    assert ws.imu.shape == (n, T, 6) and ws.imu.dtype == np.float32
    assert ws.grids.shape == (n, T, 8, 8) and ws.frames.shape == (n, T, 32, 32)
    assert ws.frames.dtype == np.uint8 and ws.frames.max() > 0
    assert np.isfinite(ws.vectors).all() and np.isfinite(ws.grids).all()
    assert ws.classes == ["hard", "no-touch", "soft"]
    assert sorted(np.unique(ws.groups)) == [0, 1, 2]
    # each label, contact flag, imu row is the truth of the window's last frame
    trials = [load_trial(sim_ds, i) for i in range(3)]
    names = ["no-touch", "hard", "soft", "slippery"]
    for i in range(0, n, 7):
        tr, t = trials[ws.groups[i]], ws.t_index[i]
        assert ws.trial_len[i] == len(tr["frames"])
        assert ws.contact[i] == tr["contact"][t]
        want = names[tr["surface"][t]] if tr["contact"][t] else NO_TOUCH
        assert ws.labels[i] == want
        assert np.allclose(ws.imu[i], tr["imu"][t - T + 1:t + 1])
    # stride 1: consecutive windows of a trial share T-1 frames
    same = (ws.groups[1:] == ws.groups[:-1]) & (ws.t_index[1:] == ws.t_index[:-1] + 1)
    k = np.flatnonzero(same)[5]
    assert np.array_equal(ws.vectors[k, 1:], ws.vectors[k + 1, :-1])
    # no-touch windows exist, and pins move far more under contact than in the air
    assert (ws.labels == NO_TOUCH).any() and (ws.labels != NO_TOUCH).any()
    mag = np.hypot(*np.moveaxis(ws.vectors[:, -1], -1, 0)).mean(axis=1)
    assert mag[ws.contact].mean() > 5 * mag[~ws.contact].mean()


def test_dataset_features_are_the_pipelines_own(sim_ds, cache):
    """The windows hold exactly what MarkerStream + the layout mapping give."""
    from device.pi.vision.pipeline import MarkerStream

    ws = load_spec(str(sim_ds), "surface", 3, progress=False, cache=cache)
    frames = load_trial(sim_ds, 1)["frames"]
    stream = MarkerStream("roboskin")
    mapper = LayoutMapper(layout_for_profile("roboskin"), stream.profile.match_gate_px)
    got = {}
    for i, f in enumerate(frames):
        ff = stream.process(f, i / 120)
        v, lo = mapper(stream, ff)
        got[i] = (v.copy(), lo.copy(), ff.grid.copy(), ff.contact)
    assert (mapper.assignment >= 0).sum() >= 120          # most layout pins map to a pin
    sel = np.flatnonzero(ws.groups == 1)
    for w in sel[::9]:
        t = ws.t_index[w]
        v, lo, g, c = got[t]
        assert np.array_equal(ws.vectors[w, -1], v) and np.array_equal(ws.lost[w, -1], lo)
        assert np.array_equal(ws.grids[w, -1], g)


def test_dataset_contact_only_drops_no_touch_and_records_the_fraction(sim_ds, cache):
    full = load_spec(str(sim_ds), "surface", 4, progress=False, cache=cache)
    ws = load_spec(str(sim_ds), "surface", 4, contact_only=True, progress=False, cache=cache)
    assert ws.contact.all() and NO_TOUCH not in ws.classes
    assert len(ws) == int(full.contact.sum())
    assert ws.kept_fraction == pytest.approx(len(ws) / len(full))
    assert 0.2 < ws.kept_fraction < 0.9


def test_dataset_texture_slip_and_pressure_tasks(sim_ds, cache):
    tex = load_spec(str(sim_ds), "texture", 2, progress=False, cache=cache)
    assert set(tex.classes) == {"smooth", NO_TOUCH}
    assert (tex.labels[~tex.contact] == NO_TOUCH).all()
    slip = load_spec(str(sim_ds), "slip", 2, progress=False, cache=cache, min_classes=1)
    assert set(slip.labels) <= set(SLIP_LABELS)
    pr = load_spec(str(sim_ds), "pressure", 2, progress=False, cache=cache)
    assert pr.labels is None and pr.targets.dtype == np.float64
    load = load_trial(sim_ds, 0)["load_n"]
    sel = np.flatnonzero(pr.groups == 0)
    assert np.allclose(pr.targets[sel], load[pr.t_index[sel]])
    assert pr.targets.max() > 1.0 and pr.targets.min() == 0.0


# -- CSV manifest ------------------------------------------------------------

def test_manifest_with_sim_path_frame_range_and_imu(tmp_path):
    rng = np.random.default_rng(0)
    imu = rng.normal(size=(100, 6))
    np.save(tmp_path / "imu.npy", imu)
    T = 3
    m = write_csv(tmp_path / "m.csv", [
        "path,label,start_frame,end_frame,imu",
        "sim://press-hard?seed=1,hard,20,60,imu.npy",
        "sim://press-hard?seed=1,hard,60,90,imu.npy",
        "sim://no-touch,air,,,",
    ])
    ws = load_spec(str(m), "surface", T, progress=False, frame_size=16)
    assert ws.frames.shape[2:] == (16, 16)
    # the two press-hard rows are one recording (one group), no-touch another
    assert len(np.unique(ws.groups)) == 2
    g_hard = ws.groups[0]
    hard = ws.groups == g_hard
    t = ws.t_index[hard]
    assert t.min() == T - 1 and t.max() == 89 - 20      # counted from the span start
    assert ws.trial_len[hard][0] == 70 and ws.source["trials"][0]["span_start"] == 20
    for w in np.flatnonzero(hard)[::5]:            # imu rows follow the frame numbers
        f = ws.t_index[w] + 20
        assert np.allclose(ws.imu[w], imu[f - T + 1:f + 1], atol=1e-6)
    # the no-touch row takes the simulator's own imu
    from device.sim import Simulator, load_scene
    sim_imu = Simulator(load_scene("no-touch"), seed=0).truth["imu"]
    w = np.flatnonzero(~hard)[0]
    t0 = ws.t_index[w]
    assert np.allclose(ws.imu[w], sim_imu[t0 - T + 1:t0 + 1], atol=1e-5)
    # labels: the row's label under contact, no-touch without
    assert set(ws.labels[hard & ws.contact]) == {"hard"}
    assert set(ws.labels[~ws.contact]) <= {NO_TOUCH}
    assert "air" not in ws.classes          # no-touch scene never has contact
    assert ws.source["contact_from"] == "pipeline"


def test_manifest_pressure_targets_and_npz_rows(tmp_path):
    v = np.random.default_rng(1).normal(size=(4, 3, 133, 2)).astype(np.float32)
    np.savez(tmp_path / "w.npz", vectors=v, targets=np.arange(4.0))
    m = write_csv(tmp_path / "m.csv", [
        "path,label,start_frame,end_frame",
        "sim://press-soft,2.5,0,60",
        "w.npz,,,",
    ])
    ws = load_spec(str(m), "pressure", 3, progress=False)
    n_npz = 4
    assert np.allclose(ws.targets[:-n_npz], 2.5)
    assert np.allclose(ws.targets[-n_npz:], np.arange(4.0))
    assert ws.grids is None and ws.frames is None       # the npz has none
    assert (ws.t_index[-n_npz:] == -1).all()
    assert len(np.unique(ws.groups)) == 1 + n_npz


# -- .npz spec -----------------------------------------------------------------

def test_npz_spec_takes_the_last_T_frames_and_marks_nan_pins_lost(tmp_path):
    rng = np.random.default_rng(2)
    v = rng.normal(scale=3.0, size=(6, 4, 10, 2))
    v[0, 3, 2] = np.nan
    labels = np.array(["hard", "soft"] * 3)
    imu = rng.normal(size=(6, 4, 6))
    groups = np.array([7, 7, 9, 9, 11, 11])
    p = tmp_path / "v.npz"
    np.savez(p, vectors=v, labels=labels, imu=imu, groups=groups)
    ws = load_spec(str(p), "surface", 3)
    assert ws.vectors.shape == (6, 3, 10, 2) and ws.imu.shape == (6, 3, 6)
    assert np.allclose(ws.vectors[1], v[1, 1:]) and np.allclose(ws.imu[3], imu[3, 1:])
    assert ws.lost[0, 2, 2] and ws.vectors[0, 2, 2].tolist() == [0.0, 0.0]
    assert np.isfinite(ws.vectors).all()
    assert ws.groups.tolist() == [0, 0, 1, 1, 2, 2]
    assert list(ws.labels) == list(labels) and ws.classes == ["hard", "soft"]
    assert ws.source["contact_from"] == "vectors" and ws.contact.all()
    with pytest.raises(DataError, match="longer than"):
        load_spec(str(p), "surface", 5)
    with pytest.raises(DataError, match="targets"):
        load_spec(str(p), "pressure", 2)


# -- splits --------------------------------------------------------------------

def synthetic(trial_lens, T, stride=1, labels=("a", "b")):
    """A WindowSet with only the bookkeeping arrays filled in."""
    g, t, L = [], [], []
    for k, n in enumerate(trial_lens):
        ends = np.arange(T - 1, n, stride)
        g += [k] * len(ends)
        t += list(ends)
        L += [n] * len(ends)
    N = len(g)
    lab = np.array([labels[x % len(labels)] for x in g], object)
    return WindowSet(task="surface", window=T, vectors=np.zeros((N, T, 1, 2), np.float32),
                     lost=np.zeros((N, T, 1), bool), imu=None, grids=None, frames=None,
                     contact=np.ones(N, bool), labels=lab, targets=None,
                     groups=np.array(g, np.int64), t_index=np.array(t, np.int64),
                     trial_len=np.array(L, np.int64), classes=sorted(set(labels)))


def assert_time_split_ok(ws, tr, te, gap):
    assert len(np.intersect1d(tr, te)) == 0
    T = ws.window
    for g in np.unique(ws.groups):
        a = tr[ws.groups[tr] == g]
        b = te[ws.groups[te] == g]
        if len(a) and len(b):
            last_train = ws.t_index[a].max()
            first_test = (ws.t_index[b] - T + 1).min()
            assert first_test - last_train > gap


@settings(max_examples=80, deadline=None)
@given(st.lists(st.integers(30, 300), min_size=1, max_size=4), st.integers(1, 10),
       st.integers(1, 3), st.floats(0.3, 0.9), st.integers(0, 15))
def test_time_split_never_overlaps_and_keeps_the_gap(lens, T, stride, frac, gap):
    ws = synthetic(lens, T, stride)
    b = np.floor(frac * ws.trial_len)
    n_train = int((ws.t_index < b).sum())
    n_test = int((ws.t_index - T + 1 >= b + gap).sum())
    if n_train == 0 or n_test == 0:                 # trials too short: a clear error
        with pytest.raises(DataError, match="too short"):
            split_time(ws, frac, gap)
        return
    tr, te = split_time(ws, frac, gap)
    assert (len(tr), len(te)) == (n_train, n_test)
    assert_time_split_ok(ws, tr, te, gap)
    for i in tr:      # train windows lie in the first frac of their trial
        assert ws.t_index[i] < np.floor(frac * ws.trial_len[i])


def test_time_split_default_gap_is_T():
    ws = synthetic([100, 80], 5)
    tr, te = split_time(ws)
    assert_time_split_ok(ws, tr, te, 5)
    first_test = ws.t_index[te] - 4
    assert first_test[ws.groups[te] == 0].min() == 70 + 5


@settings(max_examples=60, deadline=None)
@given(st.integers(2, 30), st.floats(0.1, 0.6), st.integers(0, 1000))
def test_grouped_split_never_shares_a_trial(n_trials, frac, seed):
    ws = synthetic([20 + 3 * k for k in range(n_trials)], 3)
    tr, te = split_grouped(ws, frac, seed)
    assert len(tr) and len(te) and len(tr) + len(te) == len(ws)
    assert not set(ws.groups[tr]) & set(ws.groups[te])


def test_grouped_split_spreads_labels_and_kfold_covers_each_trial_once():
    ws = synthetic([30] * 10, 3)               # 5 trials of 'a', 5 of 'b'
    tr, te = split_grouped(ws, 0.4, seed=3)
    assert set(ws.labels[te]) == {"a", "b"} and set(ws.labels[tr]) == {"a", "b"}
    seen = []
    for tr, te in group_kfold(ws, 5):
        assert not set(ws.groups[tr]) & set(ws.groups[te])
        assert len(tr) + len(te) == len(ws)
        seen += sorted(set(ws.groups[te]))
    assert sorted(seen) == list(range(10))


def test_grouped_split_on_a_simulated_dataset(sim_ds, cache):
    ws = load_spec(str(sim_ds), "surface", 3, progress=False, cache=cache)
    tr, te = split_grouped(ws, 0.34, seed=0)
    assert not set(ws.groups[tr]) & set(ws.groups[te])
    tr, te = split_time(ws)
    assert_time_split_ok(ws, tr, te, 3)


# -- errors --------------------------------------------------------------------

def test_too_few_groups_for_k_folds():
    ws = synthetic([30, 30, 30], 3)
    with pytest.raises(DataError, match="too few groups for 5 folds.*3 trials"):
        group_kfold(ws, 5)
    with pytest.raises(DataError, match="at least 2 groups"):
        split_grouped(synthetic([30], 3), 0.3)
    with pytest.raises(DataError, match="no time order"):
        split_time(_untimed(ws))


def _untimed(ws):
    ws = ws.subset(np.arange(len(ws)))
    ws.t_index[:] = -1
    return ws


def test_window_longer_than_the_clip(tmp_path, sim_ds):
    m = write_csv(tmp_path / "m.csv", ["path,label,start_frame,end_frame",
                                       "sim://no-touch,a,10,14"])
    with pytest.raises(DataError, match=r"row 1 \(line 2\).*T=5.*longer than.*4 frames"):
        load_spec(str(m), "surface", 5, progress=False)
    with pytest.raises(DataError, match="longer than the trial"):
        load_spec(str(sim_ds), "surface", 500, progress=False)


def test_a_single_class_is_refused_unless_asked_for(tmp_path):
    p = tmp_path / "v.npz"
    np.savez(p, vectors=np.ones((3, 2, 5, 2)), labels=np.array(["hard"] * 3))
    with pytest.raises(DataError, match="at least 2 classes.*'hard'"):
        load_spec(str(p), "surface", 2)
    assert load_spec(str(p), "surface", 2, min_classes=1).classes == ["hard"]


@pytest.mark.parametrize("rows, match", [
    (["path,label,start_frame", "sim://no-touch,a,abc"],
     r"row 1 \(line 2\), column start_frame: 'abc' is not a whole number"),
    (["path,label,start_frame,end_frame", "sim://no-touch,a,0,1", "sim://no-touch,a,9,3"],
     r"row 2 \(line 3\), column end_frame: 3 is not after start_frame 9"),
    (["path,label", "sim://no-touch,"], r"row 1 \(line 2\), column label: empty"),
    (["path,label,colour", "x.avi,a,red"], "unknown column 'colour'"),
    (["path,start_frame", "x.avi,3"], "no 'label' column"),
    (["path,label", ",a"], r"row 1 \(line 2\), column path: empty"),
    (["path,label"], "no rows"),
])
def test_bad_manifest_rows_name_the_row_and_column(tmp_path, rows, match):
    m = write_csv(tmp_path / "m.csv", rows)
    with pytest.raises(DataError, match=match):
        load_spec(str(m), "surface", 2, progress=False)


def test_missing_files_are_named(tmp_path):
    m = write_csv(tmp_path / "m.csv", ["path,label", "nowhere/clip.avi,a"])
    with pytest.raises(DataError, match=r"row 1.*column path: no such file.*nowhere/clip\.avi"):
        load_spec(str(m), "surface", 2)
    m = write_csv(tmp_path / "m2.csv", ["path,label,imu", "sim://no-touch,a,gone.npy"])
    with pytest.raises(DataError, match=r"column imu: no such file.*gone\.npy"):
        load_spec(str(m), "surface", 2)
    with pytest.raises(DataError, match=r"no such data spec.*absent_dir"):
        load_spec(str(tmp_path / "absent_dir"), "surface", 2)
    with pytest.raises(DataError, match=r"no such manifest.*absent\.csv"):
        load_spec(str(tmp_path / "absent.csv"), "surface", 2)


def test_bad_arguments_and_imu_files(tmp_path):
    with pytest.raises(DataError, match="task must be one of.*'colour'"):
        load_spec(str(tmp_path), "colour", 2)
    with pytest.raises(DataError, match="window must be.*window=0"):
        load_spec(str(tmp_path), "surface", 0)
    m = write_csv(tmp_path / "m.csv", ["path,label", "sim://no-touch,heavy"])
    with pytest.raises(DataError, match=r"column label: 'heavy' is not a finite number"):
        load_spec(str(m), "pressure", 2)
    np.save(tmp_path / "imu5.npy", np.zeros((60, 5)))
    np.save(tmp_path / "short.npy", np.zeros((10, 6)))
    m = write_csv(tmp_path / "m3.csv", ["path,label,imu", "sim://no-touch,a,imu5.npy"])
    with pytest.raises(DataError, match=r"imu5\.npy has shape \(60, 5\), expected \(frames, 6\)"):
        load_spec(str(m), "surface", 2, progress=False, min_classes=1)
    m = write_csv(tmp_path / "m4.csv", ["path,label,imu", "sim://no-touch,a,short.npy"])
    with pytest.raises(DataError, match=r"short\.npy has 10 rows, the clip part needs 60"):
        load_spec(str(m), "surface", 2, progress=False, min_classes=1)
    m = write_csv(tmp_path / "m5.csv", ["path,label,end_frame", "sim://no-touch,a,999"])
    with pytest.raises(DataError, match=r"column end_frame: 999 is past the end.*60 frames"):
        load_spec(str(m), "surface", 2, progress=False, min_classes=1)


# -- real recordings -------------------------------------------------------------

@pytest.mark.real
def test_real_roboskin_smooth_vs_concrete_manifest(tmp_path):
    from tests.realdata import real_data_dir
    base = real_data_dir("roboskin/smooth.avi", "roboskin/concrete.avi",
                         "roboskin/concrete_gyro.npy") / "roboskin"
    rel = Path(os.path.relpath(base, tmp_path))       # paths relative to the manifest
    m = write_csv(tmp_path / "real.csv", [
        "path,label,imu",
        f"{rel / 'smooth.avi'},smooth,",
        f"{rel / 'concrete.avi'},concrete,{rel / 'concrete_gyro.npy'}",
    ])
    cache = {}
    T = 5
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ws = load_spec(str(m), "texture", T, contact_only=True, progress=False, cache=cache)
    # smooth.avi has no IMU: imu is dropped for all rather than leaking the label
    assert ws.imu is None and any("imu dropped" in str(w.message) for w in caught)
    assert ws.classes == ["concrete", "smooth"]
    assert ws.vectors.shape[1:] == (T, 133, 2) and np.isfinite(ws.vectors).all()
    assert np.isfinite(ws.grids).all() and ws.frames.shape[1:] == (T, 32, 32)
    assert 0.5 < ws.kept_fraction < 1.0
    assert (~ws.lost).mean() > 0.7           # most layout pins are tracked
    mag = np.hypot(*np.moveaxis(ws.vectors[:, -1], -1, 0)).mean(axis=1)
    assert np.median(mag) > 0.5              # pins are dragged
    tr, te = split_time(ws)
    assert_time_split_ok(ws, tr, te, T)
    assert set(ws.labels[tr]) == set(ws.labels[te]) == {"concrete", "smooth"}
    # concrete alone keeps its gyro, row for row, from the shared feature cache
    m2 = write_csv(tmp_path / "concrete.csv", [
        "path,label,imu", f"{rel / 'concrete.avi'},concrete,{rel / 'concrete_gyro.npy'}"])
    c = load_spec(str(m2), "texture", T, progress=False, cache=cache, min_classes=1)
    gyro = np.load(base / "concrete_gyro.npy")
    w = len(c) // 2
    t = c.t_index[w]
    assert np.allclose(c.imu[w], gyro[t - T + 1:t + 1], atol=1e-5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        both = load_specs([str(m2), str(m)], "texture", T, contact_only=True,
                          progress=False, cache=cache)
    assert len(both) == len(ws) + int(c.contact.sum()) and len(np.unique(both.groups)) == 3
