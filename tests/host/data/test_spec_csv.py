"""host/data/spec_csv.py: a CSV manifest -> windows; bad rows name the row and column."""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import pytest

from host.data.load import load_spec, load_specs
from host.data.splits import split_time
from host.data.windows import NO_TOUCH, DataError



def test_manifest_with_sim_path_frame_range_and_imu(tmp_path, write_csv):
    rng = np.random.default_rng(0)
    imu = rng.normal(size=(100, 6))
    np.save(tmp_path / "imu.npy", imu)
    T = 3
    m = write_csv(tmp_path / "m.csv", [
        "path,label,start_frame,end_frame,imu",
        "sim://press-hard?seed=1,hard,20,60,imu.npy",
        "sim://press-hard?seed=1,hard,60,90,imu.npy",
        "sim://no-touch,no-touch,,,",
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
    assert ws.classes == ["hard", "no-touch"]
    assert ws.source["contact_from"] == "pipeline"


def test_manifest_pressure_targets_and_npz_rows(tmp_path, write_csv):
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


def test_window_longer_than_the_clip(tmp_path, sim_ds, write_csv):
    m = write_csv(tmp_path / "m.csv", ["path,label,start_frame,end_frame",
                                       "sim://no-touch,hard,10,14"])
    with pytest.raises(DataError, match=r"row 1 \(line 2\).*T=5.*longer than.*4 frames"):
        load_spec(str(m), "surface", 5, progress=False)
    with pytest.raises(DataError, match="longer than the trial"):
        load_spec(str(sim_ds), "surface", 500, progress=False)


@pytest.mark.parametrize("rows, match", [
    (["path,label,start_frame", "sim://no-touch,hard,abc"],
     r"row 1 \(line 2\), column start_frame: 'abc' is not a whole number"),
    (["path,label,start_frame,end_frame", "sim://no-touch,hard,0,1", "sim://no-touch,hard,9,3"],
     r"row 2 \(line 3\), column end_frame: 3 is not after start_frame 9"),
    (["path,label", "sim://no-touch,"], r"row 1 \(line 2\), column label: empty"),
    (["path,label,colour", "x.avi,hard,red"], "unknown column 'colour'"),
    (["path,start_frame", "x.avi,3"], "no 'label' column"),
    (["path,label", ",hard"], r"row 1 \(line 2\), column path: empty"),
    (["path,label"], "no rows"),
])
def test_bad_manifest_rows_name_the_row_and_column(tmp_path, rows, match, write_csv):
    m = write_csv(tmp_path / "m.csv", rows)
    with pytest.raises(DataError, match=match):
        load_spec(str(m), "surface", 2, progress=False)


def test_bad_pressure_labels_and_imu_files(tmp_path, write_csv):
    m = write_csv(tmp_path / "m.csv", ["path,label", "sim://no-touch,heavy"])
    with pytest.raises(DataError, match=r"column label: 'heavy' is not a finite number"):
        load_spec(str(m), "pressure", 2)
    np.save(tmp_path / "imu5.npy", np.zeros((60, 5)))
    np.save(tmp_path / "short.npy", np.zeros((10, 6)))
    m = write_csv(tmp_path / "m3.csv", ["path,label,imu", "sim://no-touch,hard,imu5.npy"])
    with pytest.raises(DataError, match=r"imu5\.npy has shape \(60, 5\), expected \(frames, 6\)"):
        load_spec(str(m), "surface", 2, progress=False, min_classes=1)
    m = write_csv(tmp_path / "m4.csv", ["path,label,imu", "sim://no-touch,hard,short.npy"])
    with pytest.raises(DataError, match=r"short\.npy has 10 rows, the clip part needs 60"):
        load_spec(str(m), "surface", 2, progress=False, min_classes=1)
    m = write_csv(tmp_path / "m5.csv", ["path,label,end_frame", "sim://no-touch,hard,999"])
    with pytest.raises(DataError, match=r"column end_frame: 999 is past the end.*60 frames"):
        load_spec(str(m), "surface", 2, progress=False, min_classes=1)


# -- real recordings -------------------------------------------------------------

@pytest.mark.real
def test_real_roboskin_smooth_vs_concrete_manifest(tmp_path, write_csv,
                                                   assert_time_split_ok, caplog):
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
    with warnings.catch_warnings(record=True) as caught, caplog.at_level("WARNING"):
        warnings.simplefilter("always")
        ws = load_spec(str(m), "texture", T, contact_only=True, progress=False, cache=cache)
    # smooth.avi has no IMU: imu is dropped for all rather than leaking the label, said
    # in one log line naming the rows (no Python UserWarning with its source line)
    assert ws.imu is None and not [w for w in caught if "imu" in str(w.message)]
    said = [r.getMessage() for r in caplog.records if "imu dropped" in r.getMessage()]
    assert len(said) == 1 and "rows [1]" in said[0] and "\n" not in said[0]
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



def test_a_mistyped_surface_or_slip_label_is_refused_naming_the_row(tmp_path, write_csv):
    m = write_csv(tmp_path / "m.csv", ["path,label", "sim://press-hard,hard",
                                       "sim://press-soft,lava"])
    for task in ("surface", "slip"):
        with pytest.raises(DataError, match=rf"m\.csv row \d \(line \d\), column label: '\w+' "
                                            rf"is not a {task} class"):
            load_spec(str(m), task, 2, progress=False)
    with pytest.raises(DataError, match=r"row 2 \(line 3\), column label: 'lava' is not a "
                                        r"surface class; the surface classes are no-touch, "
                                        r"hard, soft, slippery"):
        load_spec(str(m), "surface", 2, progress=False)
    tex = load_spec(str(m), "texture", 2, progress=False)       # texture names are the user's
    assert "lava" in tex.classes


@pytest.mark.parametrize("label, shown", [("no-touch", "'no-touch'"),
                                          ('"smooth\nlego"', r"'smooth\\nlego'"),
                                          ("x" * 5000, "'xxxx")])
def test_a_texture_label_host_record_refuses_is_refused_naming_the_row(tmp_path, write_csv,
                                                                       label, shown):
    m = write_csv(tmp_path / "m.csv", ["path,label", "sim://press-hard,smooth",
                                       f"sim://press-soft,{label}"])
    with pytest.raises(DataError, match=rf"row 2 \(line [34]\), column label: a texture label "
                                        rf"must be 1-64 .* got {shown}"):
        load_spec(str(m), "texture", 2, progress=False)
