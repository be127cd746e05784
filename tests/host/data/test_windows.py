"""host/data/windows.py: the WindowSet (subset, concat, summary) and cutting windows."""
from __future__ import annotations

import numpy as np
import pytest

from host.data.windows import DataError, WindowSet, check_labels, window_ends, window_labels
from tests.windows import synthetic


def test_subset_takes_rows_by_index_or_mask_and_checks_them():
    ws = synthetic(n_groups=3, per_group=4)
    sub = ws.subset([0, 5, 11])
    assert len(sub) == 3 and sub.groups.tolist() == [0, 1, 2]
    assert np.array_equal(sub.vectors[1], ws.vectors[5])
    assert sub.classes == ws.classes and sub.source["subset_of"] == 12
    mask = ws.groups == 1
    assert np.array_equal(ws.subset(mask).labels, ws.labels[mask])
    with pytest.raises(ValueError, match=r"mask must have shape \(12,\)"):
        ws.subset(np.ones(3, bool))
    with pytest.raises(ValueError, match="out of range for 12 windows"):
        ws.subset([12])


def test_concat_keeps_groups_apart_and_drops_what_one_set_lacks():
    a = synthetic(n_groups=2, per_group=3, classes=("a", "b"))
    b = synthetic(n_groups=3, per_group=2, classes=("b", "c"), imu=False)
    ws = WindowSet.concat([a, b])
    assert len(ws) == len(a) + len(b)
    assert sorted(set(ws.groups.tolist())) == [0, 1, 2, 3, 4]
    assert ws.classes == ["a", "b", "c"]
    assert ws.imu is None and any("imu dropped" in n for n in ws.source["notes"])
    assert ws.grids.shape[0] == len(ws)
    assert WindowSet.concat([a]) is a
    with pytest.raises(DataError, match="window T=4, set 0 T=3"):
        WindowSet.concat([a, synthetic(Tn=4)])
    with pytest.raises(ValueError, match="at least one"):
        WindowSet.concat([])


def test_summary_counts_windows_trials_and_classes():
    ws = synthetic(n_groups=4, per_group=5)
    d = ws.summary()
    assert d["windows"] == 20 and d["trials"] == 4 and d["pins"] == ws.n_pins
    assert d["class_counts"] == {"a": 10, "b": 10} and d["imu"] is True
    pr = synthetic(n_groups=2, per_group=5, targets=True).summary()
    assert pr["target_range"][0] <= pr["target_range"][1] and "class_counts" not in pr


def test_window_ends_skip_windows_without_a_reference():
    ready = np.array([False, False, True, True, True, True, False, True, True, True])
    ends, dropped = window_ends(ready, 0, 10, 3, 1)
    assert ends.tolist() == [4, 5, 9]
    assert dropped == 5
    ends, dropped = window_ends(ready, 2, 10, 2, 2)
    assert ends.tolist() == [3, 5, 9] and dropped == 1
    assert window_ends(ready, 0, 2, 3, 1)[0].size == 0


def test_window_labels_mark_no_touch_only_for_surface_and_texture():
    lab = np.array(["hard", "hard", "soft"], object)
    contact = np.array([True, False, True])
    assert window_labels("surface", lab, contact).tolist() == ["hard", "no-touch", "soft"]
    assert window_labels("slip", lab, contact).tolist() == ["hard", "hard", "soft"]
    assert window_labels("surface", None, contact) is None


def test_fixed_class_tasks_refuse_a_label_that_is_not_a_class_naming_where():
    check_labels("surface", "hard", "m.csv row 1")
    check_labels("slip", np.array(["slip", "no-slip"], object), "v.npz: labels", indexed=True)
    check_labels("texture", "lava", "m.csv row 1")          # texture names are the user's
    check_labels("pressure", None, "m.csv row 1")
    with pytest.raises(DataError, match=r"^m\.csv row 2: 'lava' is not a surface class; the "
                                        r"surface classes are no-touch, hard, soft, slippery$"):
        check_labels("surface", "lava", "m.csv row 2")
    with pytest.raises(DataError, match=r"^v\.npz: labels\[1\]: 'slipping' is not a slip class"):
        check_labels("slip", np.array(["slip", "slipping"], object), "v.npz: labels",
                     indexed=True)


@pytest.mark.parametrize("label", ["no-touch", "none", "x" * 5000, "smooth\nlego", "", "-a",
                                   "a b", 5])
def test_a_texture_label_follows_the_rule_host_record_applies(label):
    """no-touch would merge with the windows without contact (losing the class); a
    newline or a 5,000-character name has no place in a manifest or a log line."""
    with pytest.raises(DataError, match=r"^m\.csv row 1: a texture label must be 1-64 letters"):
        check_labels("texture", label, "m.csv row 1")


def test_texture_labels_name_the_first_bad_window_and_an_npz_may_mark_no_touch():
    check_labels("texture", "x" * 64, "m.csv row 1")
    check_labels("texture", "concrete_2.wet-A", "m.csv row 1")
    labels = np.array(["smooth", "no-touch", "lego"], object)
    check_labels("texture", labels, "v.npz: labels", indexed=True, allow_no_touch=True)
    with pytest.raises(DataError, match=r"^v\.npz: labels\[1\]: a texture label .* got "
                                        r"'no-touch'$"):
        check_labels("texture", labels, "v.npz: labels", indexed=True)
    with pytest.raises(DataError, match=r"labels\[2\]: .* got 'xxxxxxx"):
        check_labels("texture", np.array(["a", "a", "x" * 5000], object), "v.npz: labels",
                     indexed=True, allow_no_touch=True)
