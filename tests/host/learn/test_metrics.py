"""host/learn/metrics.py: classification and regression metrics (one schema) and the
slip detection latency."""
from __future__ import annotations

import numpy as np
import pytest

from host.learn.metrics import (classification_metrics, label_metrics, regression_metrics,
                                slip_latency)
from tests.windows import synthetic


def test_slip_latency_counts_frames_from_each_true_onset():
    lab = np.array(["no-slip"] * 3 + ["slip"] * 4 + ["no-slip"] * 2 + ["slip"] * 3
                   + ["no-slip"] * 2 + ["slip"] * 2, object)
    n = len(lab)
    ws = synthetic(n_groups=1, per_group=n)
    ws.labels = lab
    pred = np.zeros(n, bool)
    pred[[4, 5]] = True          # onset at 3, detected at 4: 1 frame
    pred[[9]] = True             # onset at 9, detected at once: 0 frames
    # the third onset (14) is never detected: missed
    res = slip_latency(ws, pred)
    assert res["onsets"] == 3 and res["detected"] == 2 and res["missed"] == 1
    assert res["latencies_frames"] == [1, 0] and res["median_frames"] == 0.5


def test_classification_metrics_count_unseen_labels_as_errors_in_their_own_row():
    classes = ["a", "b"]
    true = ["a", "a", "b", "b", "c"]
    pred = np.array([0, 1, 1, 1, 0])
    m = label_metrics(true, pred, classes)
    assert m == classification_metrics(np.array([0, 0, 1, 1, -1]), pred, classes, true)
    assert m["n"] == 5 and m["accuracy"] == pytest.approx(0.6)
    assert m["confusion"]["labels"] == ["a", "b", "c"]
    assert m["confusion"]["predicted"] == ["a", "b"]
    assert m["confusion"]["matrix"] == [[1, 1], [0, 2], [1, 0]]
    assert m["per_class"]["a"] == {"precision": 0.5, "recall": 0.5, "f1": 0.5, "support": 2}
    assert m["per_class"]["b"]["precision"] == pytest.approx(2 / 3, abs=1e-6)
    assert m["per_class"]["b"]["recall"] == 1.0
    assert m["macro_f1"] == pytest.approx((0.5 + 0.8) / 2, abs=1e-6)


def test_classification_metrics_of_no_windows_are_zero_not_nan():
    m = classification_metrics(np.zeros(0, np.int64), np.zeros(0, np.int64), ["a", "b"])
    assert m["n"] == 0 and m["accuracy"] == 0.0 and m["macro_f1"] == 0.0
    assert np.array(m["confusion"]["matrix"]).sum() == 0


def test_regression_metrics_give_mae_rmse_and_share_of_range():
    y = np.array([0.0, 1.0, 2.0, 4.0])
    m = regression_metrics(y, y + np.array([1.0, -1.0, 1.0, -1.0]))
    assert m["n"] == 4 and m["mae"] == 1.0 and m["rmse"] == 1.0
    assert m["target_range"] == 4.0 and m["mae_of_range"] == 0.25
    assert m["mae_predict_mean"] == pytest.approx(np.abs(y - y.mean()).mean())
    flat = regression_metrics(np.ones(3), np.ones(3))
    assert flat["mae_of_range"] is None and flat["mae"] == 0.0


def test_block_bootstrap_interval_holds_the_estimate_and_widens_with_autocorrelation():
    """The same 70 % accuracy over 2 recordings of 400 windows: errors scattered at
    random give a narrow interval, errors in runs of 40 consecutive windows a wider
    one (an i.i.d. bootstrap would give both the same width)."""
    from host.learn.metrics import add_intervals
    ws = synthetic(n_groups=2, per_group=400)
    rng = np.random.default_rng(1)
    iid = np.ones(800)
    iid[rng.choice(800, 240, replace=False)] = 0
    runs = np.ones(800)
    for start in rng.choice(np.arange(0, 800, 40), 6, replace=False):
        runs[start:start + 40] = 0
    widths = []
    for v in (iid, runs):
        m = add_intervals({}, ws, v)
        lo, hi = m["accuracy_ci95"]
        assert lo <= v.mean() <= hi and m["n_windows"] == 800
        assert set(m["by_recording"]) == {"trial:0", "trial:1"}
        assert sum(r["n_windows"] for r in m["by_recording"].values()) == 800
        widths.append(hi - lo)
    assert widths[1] > 1.5 * widths[0]


def test_class_report_carries_intervals_and_per_recording_accuracy():
    from host.learn.metrics import class_report
    ws = synthetic(n_groups=3, per_group=30)
    ws.recordings = np.array(["r0"] * 30 + ["r1"] * 30 + ["r2"] * 30, object)
    true = np.array([0 if x == "a" else 1 for x in ws.labels])
    probs = np.zeros((90, 2))
    probs[np.arange(90), true] = 1
    probs[30:40] = probs[30:40, ::-1]          # ten errors in r1
    m = class_report("surface", ws, true, probs, ["a", "b"])
    assert m["accuracy"] == pytest.approx(80 / 90, abs=1e-6)
    assert m["by_recording"]["r1"]["accuracy"] == pytest.approx(2 / 3, abs=1e-6)
    assert m["by_recording"]["r0"]["accuracy_ci95"] == [1.0, 1.0]
    lo, hi = m["by_recording"]["r1"]["accuracy_ci95"]
    assert lo < 2 / 3 < hi and m["n_windows"] == 90
