"""host/data/spec_folder.py: a dataset folder -> windows with the simulator's truth labels."""
from __future__ import annotations

import numpy as np
import pytest

from host.data.dataset import load_trial
from host.data.load import load_spec
from host.data.windows import NO_TOUCH, SLIP_LABELS, DataError



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


def test_a_dataset_whose_surface_labels_hold_a_typo_is_refused_naming_the_trial(sim_ds,
                                                                                tmp_path):
    import json
    import shutil
    ds = tmp_path / "ds"
    shutil.copytree(sim_ds, ds)
    doc = json.loads((ds / "dataset.json").read_text())
    doc["surface_labels"] = [("lava" if x == "hard" else x) for x in doc["surface_labels"]]
    (ds / "dataset.json").write_text(json.dumps(doc))
    with pytest.raises(DataError, match=r"ds/trial_0000\.npz: surface code 1 \(surface_labels in "
                                        r".*dataset\.json\): 'lava' is not a surface class"):
        load_spec(str(ds), "surface", 2, progress=False)


def test_a_dataset_whose_texture_labels_name_a_contact_frame_no_touch_is_refused(sim_ds,
                                                                                 tmp_path):
    """The simulator's "none" names only frames without contact and passes; a texture
    name that reaches a contact window must be a name host record would accept."""
    import json
    import shutil
    ds = tmp_path / "ds"
    shutil.copytree(sim_ds, ds)
    doc = json.loads((ds / "dataset.json").read_text())
    assert doc["texture_labels"][0] == "none"
    doc["texture_labels"] = [("no-touch" if x == "smooth" else x) for x in doc["texture_labels"]]
    (ds / "dataset.json").write_text(json.dumps(doc))
    with pytest.raises(DataError, match=r"ds/trial_0000\.npz: texture code 1 \(texture_labels in "
                                        r".*dataset\.json\): a texture label must be .* got "
                                        r"'no-touch'"):
        load_spec(str(ds), "texture", 2, progress=False)


def test_a_dataset_listing_a_trial_twice_is_refused_before_any_window_leaks(sim_ds, tmp_path):
    import json
    import shutil
    ds = tmp_path / "ds"
    shutil.copytree(sim_ds, ds)
    doc = json.loads((ds / "dataset.json").read_text())
    doc["trials"].append(dict(doc["trials"][0]))
    (ds / "dataset.json").write_text(json.dumps(doc))
    with pytest.raises(DataError, match=r"listed twice: trials\[3\] trial_0000\.npz"):
        load_spec(str(ds), "surface", 2, progress=False)


def test_a_folder_mixing_trials_with_and_without_an_imu_is_refused_naming_them(
        sim_ds, tmp_path):
    """One trial with an IMU and one without would train without the IMU, silently:
    refused in one line naming the trials of each kind."""
    from host.data.dataset import DatasetWriter, read_index
    index = read_index(sim_ds)
    meta = {k: v for k, v in index.items() if k not in ("trials", "format", "version")}
    out = tmp_path / "mixed"
    with DatasetWriter(out, meta=meta) as w:
        for i, keep_imu in ((0, True), (2, False)):
            tr = load_trial(sim_ds, i)
            truth = {k: tr[k] for k in ("contact", "surface", "texture", "slip", "load_n",
                                         "imu") if k in tr and (k != "imu" or keep_imu)}
            w.add_trial(np.asarray(tr["frames"]), truth,
                        {k: v for k, v in tr["info"].items() if k not in ("file", "bytes",
                                                                          "frames")})
    with pytest.raises(DataError) as exc:
        load_spec(str(out), "surface", 3, progress=False)
    msg = str(exc.value)
    assert "\n" not in msg and "['trial_0000.npz'] have an IMU" in msg
    assert "['trial_0001.npz'] have none" in msg


def test_a_trial_recorded_for_another_profile_is_refused_even_as_a_toml(sim_ds, tmp_path):
    """host record keeps the profile's checksum: a folder recorded for roboskin and
    read with another sensor's .toml is refused naming both (issue 33: it was
    accepted without a word); the same description under another file name is not."""
    from device.profile import PROFILE_DIR
    from host.data.dataset import DatasetWriter, read_index
    from host.data.recordings import profile_ref
    index = read_index(sim_ds)
    meta = {k: v for k, v in index.items() if k not in ("trials", "format", "version")}
    out = tmp_path / "rec"
    with DatasetWriter(out, meta=meta) as w:
        tr = load_trial(sim_ds, 0)
        truth = {k: tr[k] for k in ("contact", "surface", "texture", "slip", "load_n")
                 if k in tr}
        info = {k: v for k, v in tr["info"].items() if k not in ("file", "bytes", "frames")}
        info.update(profile="roboskin", profile_sha256=profile_ref("roboskin")["sha256"])
        w.add_trial(np.asarray(tr["frames"]), truth, info)
    text = (PROFILE_DIR / "roboskin.toml").read_text()
    same = tmp_path / "copy-of-roboskin.toml"
    same.write_text(text)
    other = tmp_path / "mine.toml"
    other.write_text(text.replace('name = "roboskin"', 'name = "mine"'))
    with pytest.raises(DataError) as exc:
        load_spec(str(out), "surface", 3, progress=False, profile=str(other))
    msg = str(exc.value)
    assert "\n" not in msg and "recorded with profile 'roboskin'" in msg and "mine.toml" in msg
    ws = load_spec(str(out), "surface", 3, progress=False, profile=str(same),
                   min_classes=1)
    assert len(ws) > 0
