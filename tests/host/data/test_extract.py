"""host/data/extract.py: per-frame features are the Pi pipeline's own (its frame
encoder's), on the fixed pin layout."""
from __future__ import annotations

import numpy as np

from device.pi.vision.encoder import FrameEncoder
from device.pi.vision.layout import LayoutMapper
from device.pi.vision.pipeline import MarkerStream
from host.data.dataset import load_trial
from host.data.extract import extract_features, layout_for_profile
from host.data.load import load_spec


def test_dataset_features_are_the_pipelines_own(sim_ds, cache):
    """The windows hold exactly what MarkerStream + the layout mapping give."""
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


def test_loader_features_equal_the_encoders(drag_frames):
    enc = FrameEncoder("roboskin", crop_px=16)
    vecs, losts, crops = [], [], []
    for im in drag_frames:
        ef = enc.encode(im)
        vecs.append(ef.vectors.copy())
        losts.append(ef.lost.copy())
        crops.append(ef.crop)
    clip = extract_features(drag_frames, "roboskin", frame_size=16, progress=False)
    np.testing.assert_array_equal(clip.vectors, np.stack(vecs))
    np.testing.assert_array_equal(clip.lost, np.stack(losts))
    np.testing.assert_array_equal(clip.frames, np.stack(crops))
    assert clip.vectors.shape == (len(drag_frames), enc.n_pins, 2)
    # the drag moves the pins: the encoding is not all zeros once in contact
    assert np.abs(clip.vectors[-1]).max() > 0.5



def test_each_frame_carries_the_statistics_of_its_session(sim_ds, cache):
    """Brightness, contrast and the interval between frames, per frame, reach the
    windows (the recording-identity check reads them): a darker copy of a trial and
    its frames twice as far apart show in them."""
    from types import SimpleNamespace

    from host.data.extract import SESSION_STATS
    frames = load_trial(sim_ds, 0)["frames"][:20]
    a = extract_features([SimpleNamespace(image=f, t_s=i / 120) for i, f in enumerate(frames)],
                         progress=False)
    b = extract_features([SimpleNamespace(image=(f * np.float32(0.5)).astype(np.uint8),
                                          t_s=i / 60) for i, f in enumerate(frames)],
                         progress=False)
    assert a.session.shape == (20, len(SESSION_STATS))
    bright, contrast, dt = SESSION_STATS.index("brightness"), SESSION_STATS.index("contrast"), \
        SESSION_STATS.index("interval_s")
    np.testing.assert_allclose(b.session[:, bright], a.session[:, bright] / 2, atol=0.6)
    assert (b.session[:, contrast] < 0.6 * a.session[:, contrast]).all()
    np.testing.assert_allclose(a.session[:, dt], 1 / 120, rtol=1e-4)
    np.testing.assert_allclose(b.session[:, dt], 1 / 60, rtol=1e-4)
    ws = load_spec(str(sim_ds), "surface", 3, progress=False, cache=cache)
    assert ws.session is not None and ws.session.shape == (len(ws), 3, len(SESSION_STATS))
    assert ws.subset([0, 1]).session.shape[0] == 2
