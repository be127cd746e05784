"""The texture robustness proxies: frame-rate replay, exposure, the held-out windows
after a gap, the block-bootstrap interval, and an end-to-end run on real clips."""
from __future__ import annotations

import numpy as np
import pytest

from host.learn.sessions import exposure as expose  # the proxies' exposure
from host.bench.texture_robust import (Variant, block_bootstrap, clip_windows,
                                       format_robustness, keep_indices, main, model_trainer,
                                       robustness)
from host.data.extract import ClipFeatures
from host.data.windows import DataError


def test_3of5_replays_200_fps_as_120_fps_evenly_in_time():
    idx = keep_indices(200, "3of5")
    assert len(idx) == 120
    assert set(np.diff(idx)) == {1, 2}
    # the k-th kept frame is the 200 fps frame nearest k / 120 s
    k = np.arange(len(idx))
    assert np.abs(idx - k * 200 / 120).max() <= 1


def test_random_drops_are_seeded_keep_the_rest_frame_and_drop_about_the_share():
    a, b = keep_indices(5000, "3of5+drop10", seed=3), keep_indices(5000, "3of5+drop10", seed=3)
    assert np.array_equal(a, b)
    assert a[0] == 0
    assert 0.85 * 3000 < len(a) < 0.95 * 3000
    assert not np.array_equal(a, keep_indices(5000, "3of5+drop10", seed=4))


@pytest.mark.parametrize("keep", ["2of3", "3of5+drop", "3of5+drop100", "3of5+dropx"])
def test_an_unknown_keep_rule_is_an_error_naming_it(keep):
    with pytest.raises(DataError, match="keep"):
        keep_indices(100, keep)


def test_exposure_gain_offset_and_gamma():
    img = np.arange(256, dtype=np.uint8).reshape(16, 16)
    assert np.array_equal(expose(img), img)
    assert expose(img, gain=2.0)[15, 15] == 255            # saturates
    assert expose(img, gain=0.5)[8, 0] == 64
    assert expose(img, offset=25.0)[0, 0] == 25
    dark = expose(img, gamma=1.4).astype(int)
    assert (dark <= img.astype(int)).all() and dark[0, 0] == 0 and dark[15, 15] == 255
    with pytest.raises(DataError, match="gain"):
        expose(img, gain=0.0)


def test_the_interval_holds_the_accuracy_even_for_a_short_blocky_set():
    # 21 windows, blocks of T = 15: the moving-block bootstrap put [0.77, 0.93]
    # around an accuracy of 0.76; the circular one, with shorter blocks, holds it
    right = np.r_[np.zeros(5), np.ones(16)]
    lo, hi = block_bootstrap(right, 15)
    assert lo <= right.mean() <= hi
    assert block_bootstrap(np.ones(30), 15) == (1.0, 1.0)
    # dependent windows (runs of 10) give a wider interval than the iid bound
    runs = np.repeat(np.arange(40) % 2, 10).astype(float)
    lo_b, hi_b = block_bootstrap(runs, 10)
    lo_i, hi_i = block_bootstrap(runs, 1)
    assert hi_b - lo_b > hi_i - lo_i
    with pytest.raises(DataError, match="block"):
        block_bootstrap(right, 0)


def _clip(n=60, m=4):
    rng = np.random.default_rng(0)
    contact = np.ones(n, bool)
    contact[20:25] = False
    return ClipFeatures(vectors=rng.normal(size=(n, m, 2)).astype(np.float32),
                        lost=np.zeros((n, m), bool), grids=np.zeros((n, 2, 2), np.float32),
                        frames=None, contact=contact, ready=np.ones(n, bool),
                        faults=np.zeros(n, np.int32), fps=None)


def test_windows_lie_inside_the_frame_range_of_the_recording_and_end_in_contact():
    clip = _clip()
    orig = keep_indices(100, "3of5")             # 60 delivered frames of 100
    ws = clip_windows(clip, orig, "lego", 5, 40, 90, "x")
    pos = {int(o): i for i, o in enumerate(orig)}
    for t_end in ws.t_index:
        i = pos[int(t_end)]
        assert orig[i - 4] >= 40 and orig[i] < 90
        assert clip.contact[i]
    assert set(ws.labels) == {"lego"}
    assert ws.vectors.shape[1:] == (5, 4, 2)
    assert clip_windows(clip, orig, "lego", 5, 95, 100, "x") is None


def test_an_unknown_task_is_an_error_naming_it(tmp_path):
    with pytest.raises(DataError, match="lego-vs-concrete"):
        robustness(tmp_path, tasks=("lego-vs-concrete",))


def test_a_model_to_score_must_be_a_texture_model_of_vectors_alone(tmp_path, capsys):
    with pytest.raises(DataError, match="manifest"):
        model_trainer(tmp_path)
    assert main(["--data", str(tmp_path), "--model", str(tmp_path)]) == 2
    assert "--model" in capsys.readouterr().err


@pytest.mark.real
@pytest.mark.slow
def test_robustness_on_the_real_clips_reports_each_proxy_with_counts_and_intervals(tmp_path):
    from tests.realdata import real_data_dir
    data = real_data_dir("roboskin/lego_train.avi", "roboskin/smooth.avi",
                         "roboskin/concrete.avi")

    def trainer(tr, te, seed):              # a stand-in model: the mean |v| of the window
        mag = np.linalg.norm(tr.vectors, axis=3).mean(axis=(1, 2))
        cut = float(np.median(mag))
        hi = "smooth" if mag[tr.labels == "smooth"].mean() > cut else "lego"
        classes = sorted({"lego", "smooth"})

        def predict(ws):
            m = np.linalg.norm(ws.vectors, axis=3).mean(axis=(1, 2))
            lab = np.where(m > cut, hi, "smooth" if hi == "lego" else "lego")
            return np.array([classes.index(x) for x in lab])
        return predict, classes

    res = robustness(data, tmp_path, tasks=("lego-vs-smooth",), identity=False,
                     variants=(Variant("later"), Variant("rate-3of5", "3of5")),
                     trainer=trainer)
    later = res["tasks"]["lego-vs-smooth"]["proxies"]["later"]["per_recording"]
    slow = res["tasks"]["lego-vs-smooth"]["proxies"]["rate-3of5"]["per_recording"]
    for lab in ("lego", "smooth"):
        assert later[lab]["n"] >= 15 and 0 < slow[lab]["n"] < later[lab]["n"]
        lo, hi = later[lab]["ci95"]
        assert lo <= later[lab]["accuracy"] <= hi
    # the figure over both recordings has its interval and count too
    pooled = res["tasks"]["lego-vs-smooth"]["proxies"]["later"]
    assert pooled["n"] == later["lego"]["n"] + later["smooth"]["n"]
    assert pooled["ci95"][0] <= pooled["accuracy"] <= pooled["ci95"][1]
    assert f"n={pooled['n']}" in format_robustness(res)
    assert "rate-3of5" in format_robustness(res)
    assert any(p.suffix == ".npz" for p in tmp_path.iterdir())     # features cached


def test_the_rates_option_reaches_the_trained_model(monkeypatch, capsys):
    """--rates names the frame-rate copies the trained model fits ('none': none);
    without it host train's default (None) is used."""
    import host.bench.texture_robust as tr
    seen = []

    def fake(*a, **kw):
        seen.append(kw["rates"])
        return {"T": 15, "train_frac": 0.7, "tasks": {}, "identity": {}}
    monkeypatch.setattr(tr, "robustness", fake)
    for arg, want in ((["--rates", "none"], ()), (["--rates", "3of5,3of5+drop10"],
                                                  ("3of5", "3of5+drop10")), ([], None)):
        assert main(["--data", "x", "--no-identity", *arg]) == 0
        assert seen[-1] == want


def test_the_profile_option_reaches_the_pipeline_and_a_bad_one_is_exit_2(monkeypatch, tmp_path,
                                                                         capsys):
    """--profile (default roboskin) is the profile every clip goes through, e.g. one
    with [vision] contrast_ref; a profile that does not load is one line and exit 2."""
    import host.bench.texture_robust as tr
    seen = []

    def fake(*a, **kw):
        seen.append(kw["profile"])
        return {"T": 15, "train_frac": 0.7, "tasks": {}, "identity": {}}
    monkeypatch.setattr(tr, "robustness", fake)
    assert main(["--data", "x", "--no-identity"]) == 0
    assert main(["--data", "x", "--no-identity", "--profile", "my.toml"]) == 0
    assert seen == ["roboskin", "my.toml"]
    monkeypatch.undo()
    bad = tmp_path / "bad.toml"
    bad.write_text("[vision]\npitch_px = 10\nn_pins = 5\ncontrast_ref = 0\n")
    (tmp_path / "roboskin").mkdir()
    for clip in ("concrete.avi", "smooth.avi", "lego_train.avi"):
        (tmp_path / "roboskin" / clip).write_bytes(b"")
    assert main(["--data", str(tmp_path), "--profile", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "contrast_ref" in err and "Traceback" not in err


def test_the_sessions_option_and_the_held_out_stand_ins(monkeypatch):
    """--sessions none trains without session copies (default: host train's); the
    stand-ins the copies never draw (blur, noise, a layout turned further than they
    turn it) change the frames or the layout they say."""
    import host.bench.texture_robust as tr
    from host.learn.sessions import DEFAULT_SESSIONS
    seen = []

    def fake(*a, **kw):
        seen.append(kw["sessions"])
        return {"T": 15, "train_frac": 0.7, "tasks": {}, "identity": {}}
    monkeypatch.setattr(tr, "robustness", fake)
    for arg, want in ((["--sessions", "none"], False), ([], None)):
        assert main(["--data", "x", "--no-identity", *arg]) == 0
        assert seen[-1] is want
    monkeypatch.undo()
    v = {x.name: x for x in tr.VARIANTS}
    assert v["gain-0.6"].gain < DEFAULT_SESSIONS["gain"][0]
    assert v["layout-rot4"].layout_deg > DEFAULT_SESSIONS["rotate_deg"]
    assert v["layout-rot4"].layout_px > DEFAULT_SESSIONS["shift_px"]
    img = np.zeros((40, 40), np.uint8)
    img[20, 20] = 255
    rng = np.random.default_rng(0)
    blurred = tr._changed(img, v["blur-1.5"], rng)
    assert blurred[20, 20] < 255 and blurred[20, 22] > 0
    assert tr._changed(img, v["noise-6"], rng).std() > 3
    lay = tr._variant_mapper(v["layout-rot4"], "roboskin").layout_px
    from host.data.extract import layout_for_profile
    base = layout_for_profile("roboskin")
    assert np.allclose((lay - base).mean(axis=0), [6.0, 0.0], atol=1e-6)
    assert tr._variant_mapper(v["later"], "roboskin") is None
