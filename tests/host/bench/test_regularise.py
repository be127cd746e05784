"""host/bench/regularise.py: the fnn with the paper's dropout on the fnn's own inputs."""
from __future__ import annotations

import numpy as np
import pytest

from host.bench import regularise
from tests.windows import synthetic

pytest.importorskip("torch")


def texture(ws):
    ws.task = "texture"
    return ws


def test_the_dropout_fnn_learns_separable_windows_and_repeats_with_its_seed():
    tr = texture(synthetic(n_groups=4, per_group=16))
    te = texture(synthetic(n_groups=2, per_group=16, seed=1))
    a = regularise.fit_fnn_variant("fnn-dropout", tr, te, seed=3)
    b = regularise.fit_fnn_variant("fnn-dropout", tr, te, seed=3)
    assert a["accuracy"] >= 0.95 and a == b and a["epochs"] >= 1


def test_the_dropout_fnn_reads_the_fnn_inputs_with_lost_pins_masked():
    """A pin that a training recording keeps losing carries no input: its
    frame-to-frame features are zero in train and test alike."""
    tr = texture(synthetic(n_groups=4, per_group=16, n_pins=5))
    tr.lost[tr.groups == 0, :, 2] = True
    X, Xt = regularise.fnn_features(tr, tr)
    Xu, _ = regularise.fnn_features(texture(synthetic(n_groups=4, per_group=16, n_pins=5)),
                                    tr)
    assert X.shape == Xu.shape and X.dtype == np.float32
    dead = np.flatnonzero(np.all(X == 0, axis=0))
    assert len(dead) > len(np.flatnonzero(np.all(Xu == 0, axis=0)))
    assert np.all(Xt[:, dead] == 0)


def test_an_unknown_variant_is_refused():
    ws = texture(synthetic())
    with pytest.raises(ValueError, match="fnn-dropout"):
        regularise.fit_fnn_variant("fnn-l1", ws, ws, 0)
