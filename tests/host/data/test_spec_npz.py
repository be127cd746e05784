"""host/data/spec_npz.py: an .npz of marker vectors -> windows; bad content is named."""
from __future__ import annotations

import numpy as np
import pytest

from host.data.load import load_spec
from host.data.windows import DataError



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


def test_a_single_class_is_refused_unless_asked_for(tmp_path):
    p = tmp_path / "v.npz"
    np.savez(p, vectors=np.ones((3, 2, 5, 2)), labels=np.array(["hard"] * 3))
    with pytest.raises(DataError, match="at least 2 classes.*'hard'"):
        load_spec(str(p), "surface", 2)
    assert load_spec(str(p), "surface", 2, min_classes=1).classes == ["hard"]


def test_a_mistyped_surface_label_is_refused_naming_the_window(tmp_path):
    p = tmp_path / "v.npz"
    np.savez(p, vectors=np.ones((3, 2, 5, 2)), labels=np.array(["hard", "soft", "lava"]))
    with pytest.raises(DataError, match=r"v\.npz: labels\[2\]: 'lava' is not a surface class"):
        load_spec(str(p), "surface", 2)
    assert "lava" in load_spec(str(p), "texture", 2).classes


def test_no_touch_marks_npz_windows_without_contact_but_not_a_texture_with_contact(tmp_path):
    p = tmp_path / "v.npz"
    labels = np.array(["smooth", "no-touch", "lego", "no-touch"])
    np.savez(p, vectors=np.ones((4, 2, 5, 2)), labels=labels,
             contact=np.array([True, False, True, False]))
    assert load_spec(str(p), "texture", 2).classes == ["lego", "no-touch", "smooth"]
    np.savez(p, vectors=np.ones((4, 2, 5, 2)), labels=labels,
             contact=np.array([True, False, True, True]))
    with pytest.raises(DataError, match=r"v\.npz: labels\[3\] \(a window with contact\): a "
                                        r"texture label must be .* got 'no-touch'"):
        load_spec(str(p), "texture", 2)
    np.savez(p, vectors=np.ones((2, 2, 5, 2)), labels=np.array(["smooth", "a\nb"]))
    with pytest.raises(DataError, match=r"labels\[1\]: a texture label .* got 'a\\nb'"):
        load_spec(str(p), "texture", 2)
