"""host/data/extract.py: per-frame features are the Pi pipeline's own, on the fixed pin layout."""
from __future__ import annotations

import numpy as np

from device.pi.vision.layout import LayoutMapper
from device.pi.vision.pipeline import MarkerStream
from host.data.dataset import load_trial
from host.data.extract import layout_for_profile
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
