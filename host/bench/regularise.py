"""How the fnn is regularised: the L2 penalty it ships with against the paper's
dropout 0.2, on the same windows.

Two variants of the texture fnn share everything but the regulariser: the
inputs (:func:`host.learn.inputs.model_inputs`), the first layer of frame-to-frame
changes and roughness with the pins that a training recording keeps losing masked
out (:func:`host.learn.train.fnn_temporal_spec`), the clipped scaling, two logistic
hidden layers of the texture fnn's sizes (``TASK_HIDDEN``), Adam at 1e-3, mini-batches of ``min(128, n / 8)`` and
early stopping when the training loss has not improved for 15 epochs (at most 300):

* ``fnn`` (in the sweep: :func:`host.learn.train.train_model`): L2 penalty
  ``alpha = 1e-3`` (scikit-learn's MLP), the shipped setting;
* ``fnn-dropout``: no penalty, dropout 0.2 after each hidden layer, as in the
  paper (PyTorch, the optional extra ``cnn``; scored in PyTorch, not exported).
"""
from __future__ import annotations

import math

import numpy as np

from host.learn.estimators import Plateau

__all__ = ["REGULARISERS", "DROPOUT", "fit_fnn_variant", "fit_dropout_mlp"]

#: the kinds this module trains, beside the sweep's ``fnn`` (L2)
REGULARISERS = ("fnn-dropout",)
#: the paper's dropout rate
DROPOUT = 0.2


def fnn_features(tr, te, profile: str = "roboskin") -> tuple[np.ndarray, np.ndarray]:
    """The texture fnn's scaled inputs for ``tr`` and ``te``, fitted on ``tr``: the
    temporal layer of :func:`host.learn.train.fnn_temporal_spec` (T >= 2: lost pins
    masked, roughness on the profile's layout) and the clipped scaler, as
    :func:`host.learn.train.train_model` builds them."""
    from host.learn.estimators import default_uses_imu
    from host.learn.inputs import model_inputs
    from host.learn.layers import scaler_class, temporal_class
    from host.learn.train import fnn_temporal_spec

    uses_imu = default_uses_imu("fnn", tr)
    X, Xt = model_inputs(tr, "vectors", uses_imu), model_inputs(te, "vectors", uses_imu)
    if tr.window >= 2:
        spec = fnn_temporal_spec("texture", tr, tr.window, uses_imu, profile)
        tf = temporal_class()(**spec).fit(X)
        X, Xt = tf.transform(X), tf.transform(Xt)
    sc = scaler_class()().fit(X)
    return sc.transform(X).astype(np.float32), sc.transform(Xt).astype(np.float32)


def fit_dropout_mlp(X: np.ndarray, y: np.ndarray, n_classes: int, seed: int,
                    dropout: float = DROPOUT, hidden=None, epochs: int = 300,
                    patience: int = 15, tol: float = 1e-4):
    """A logistic MLP with ``dropout`` after each hidden layer (sizes ``hidden``,
    by default the texture fnn's), fitted with Adam (one thread, seeded); returns
    (predict_proba, epochs run)."""
    import torch

    from host.learn.tasks import TASK_HIDDEN
    hidden = hidden or TASK_HIDDEN["texture"]

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        gen = torch.Generator().manual_seed(int(seed))
        torch.manual_seed(int(seed))
        nn = torch.nn
        net = nn.Sequential(nn.Linear(X.shape[1], hidden[0]), nn.Sigmoid(), nn.Dropout(dropout),
                            nn.Linear(hidden[0], hidden[1]), nn.Sigmoid(), nn.Dropout(dropout),
                            nn.Linear(hidden[1], n_classes))
        opt = torch.optim.Adam(net.parameters(), lr=1e-3)
        xt = torch.from_numpy(np.ascontiguousarray(X, np.float32))
        yt = torch.from_numpy(np.asarray(y, np.int64))
        batch = int(min(128, max(4, len(X) // 8)))
        plateau, n = Plateau(tol, patience), 0
        for n in range(1, epochs + 1):
            net.train()
            order = torch.randperm(len(X), generator=gen)
            total = 0.0
            for i in range(0, len(X), batch):
                idx = order[i:i + batch]
                opt.zero_grad()
                loss = nn.functional.cross_entropy(net(xt[idx]), yt[idx])
                loss.backward()
                opt.step()
                total += float(loss.detach()) * len(idx)
            loss = total / len(X)
            if not math.isfinite(loss):
                raise ValueError(f"the dropout MLP diverged (loss {loss}) after {n} epochs")
            if plateau.reached(loss):
                break
        net.eval()

        def predict_proba(Z: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                return torch.softmax(net(torch.from_numpy(np.asarray(Z, np.float32))), 1).numpy()
    finally:
        torch.set_num_threads(threads)
    return predict_proba, n


def fit_fnn_variant(kind: str, tr, te, seed: int) -> dict:
    """Train the texture fnn variant ``kind`` (:data:`REGULARISERS`) on ``tr`` and
    score it on ``te``: {"accuracy", "mae": None, "epochs"}."""
    from host.learn.tasks import label_ids

    if kind not in REGULARISERS:
        raise ValueError(f"kind must be one of {REGULARISERS}, got {kind!r}")
    classes = sorted({str(x) for x in tr.labels})
    X, Xt = fnn_features(tr, te)
    proba, n = fit_dropout_mlp(X, label_ids(tr.labels, classes), len(classes), seed)
    pred = proba(Xt).argmax(axis=1)
    truth = label_ids(te.labels, classes)
    return {"accuracy": float(np.mean(pred == truth)), "mae": None, "epochs": n}
