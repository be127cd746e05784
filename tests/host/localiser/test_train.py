"""The pin localiser trainer (host/localiser/train.py) and the artefact it writes, run
by the Pi's Localiser: its manifest, ONNX against scikit-learn, and its accuracy on
unseen simulated and real frames. The Localiser itself on hard inputs is tested in
tests/device/pi/models/test_localiser.py.

One small model is trained once (``trained`` in conftest.py) and all tests
share it. The real no-contact test uses smooth.avi and concrete.avi, which that
model never saw.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from device.pi.models.localiser import Localiser, localiser_input
from device.pi.vision.extract import ROBOSKIN_PARAMS, PinDetector, find_dome
from device.sim import Simulator, load_profile, parse_scene
from host.localiser.labels import fit_layout, read_clip
from host.localiser.sim import random_scene_doc
from host.localiser.train import main, train_localiser
from tests.realdata import real_data_dir

N_PINS = 133


# --------------------------------------------------------------------------
# Artefact
# --------------------------------------------------------------------------


def test_artefact_manifest_and_size(trained):
    m = json.loads((trained["dir"] / "manifest.json").read_text())
    assert m["kind"] == "localiser"
    p = m["params"]                                 # the localiser's typed parameters
    assert p["n_pins"] == N_PINS and m["training"]["alpha"] == 150.0
    assert p["size"] == 32 and 0.5 <= p["crop_factor"] <= 1.0
    assert np.asarray(p["mean_layout_norm"]).shape == (N_PINS, 2)
    assert m["input"]["shape"] == [None, p["size"] ** 2]
    for key in ("sim_frames", "real_frames", "rejected"):
        assert key in m["training"]
    for key in ("median_px", "p90_px"):
        assert key in m["metrics"]["test"]["sim_heldout"]
    assert set(m["metrics"]) == {"train", "test", "cv"} and m["crop_size"] == p["size"]
    assert m["profile"]["n_pins"] == N_PINS and m["measured"]["trained_on"]["data"] in (
        "simulated", "real", "real+simulated")
    # under 1 MB (float16 weights, cast once by onnxruntime)
    assert trained["res"]["size_bytes"] < 1_000_000
    assert (trained["dir"] / "model.onnx").stat().st_size == trained["res"]["size_bytes"]


def test_onnx_matches_sklearn(trained):
    est = trained["res"]["estimator"]
    loc: Localiser = trained["loc"]
    rng = np.random.default_rng(1)
    size = loc.size
    # real-looking inputs from a simulated frame, plus random ones
    sim = Simulator(parse_scene(random_scene_doc(np.random.default_rng(77))), seed=77)
    frame = sim.render(sim.n_frames // 2)
    dome = find_dome(sim.render(0))
    det = PinDetector(ROBOSKIN_PARAMS, frame.shape, dome)
    det.threshold(frame)
    xs = [localiser_input(det.binary, det.box, dome, size, loc.crop_factor)]
    xs += [rng.random((1, size * size), np.float32) * rng.random() for _ in range(7)]
    X = np.concatenate(xs).astype(np.float32)
    onnx_y = loc.predict_normalised(X)
    skl_y = est.predict(X)
    np.testing.assert_allclose(onnx_y, skl_y, atol=1e-3)


# --------------------------------------------------------------------------
# Accuracy
# --------------------------------------------------------------------------


def test_simulated_heldout_error(trained):
    """Unseen seeds and scenes, through the Pi path (PinDetector -> Localiser, ONNX)."""
    loc: Localiser = trained["loc"]
    errs, disp, faults = [], [], 0
    for seed in range(9000, 9006):   # presses up to 3 mm: deeper than in training
        sim = Simulator(parse_scene(random_scene_doc(np.random.default_rng(seed))), seed=seed)
        dome = find_dome(sim.render(0))
        det = PinDetector(ROBOSKIN_PARAMS, (sim.height, sim.width), dome)
        for i in range(0, sim.n_frames, max(1, sim.n_frames // 12)):
            det.threshold(sim.render(i))
            pins, fault = loc.locate(det.binary, dome, box=det.box)
            faults += fault
            truth = sim.truth["pins_px"][i]
            errs.append(np.hypot(*(pins - truth).T))
            disp.append(np.median(np.hypot(*(truth - sim.rest_pins_px).T)))
    e, disp = np.stack(errs), np.array(disp)
    small = disp < 11.7          # pins moved less than one pitch
    print(f"sim held-out pin error: median {np.median(e):.2f} px, "
          f"p90 {np.percentile(e, 90):.2f} px "
          f"over {e.size} pins; within a pitch of rest ({small.sum()}/{len(disp)} frames): median "
          f"{np.median(e[small]):.2f} px, p90 {np.percentile(e[small], 90):.2f} px; beyond: "
          f"median {np.median(e[~small]) if (~small).any() else 0:.2f} px")
    assert faults == 0
    assert np.median(e) <= 1.5
    assert np.median(e[small]) <= 1.0
    assert np.percentile(e[small], 90) <= 4.0


@pytest.mark.real
@pytest.mark.parametrize("clip, n_rest", [("smooth", 16), ("concrete", 14)])
def test_real_no_contact_frames(trained, clip, n_rest):
    if not trained["real"]:
        real_data_dir("roboskin/north.avi", "roboskin/east.avi")
    d = real_data_dir(f"roboskin/{clip}.avi")
    frames = read_clip(d / "roboskin" / f"{clip}.avi", limit=n_rest)
    loc: Localiser = trained["loc"]
    dome = find_dome(frames[0])
    assert dome is not None
    det = PinDetector(ROBOSKIN_PARAMS, frames[0].shape, dome)
    prof = load_profile("roboskin")
    s = dome[2] / prof.dome_radius_px
    layout = (prof.pins_px - prof.dome_centre_px) * s + dome[:2]
    near_visible, near_all, near_layout = [], [], []
    for f in frames:
        xy, _ = det.detect(f)
        pins, fault = loc.locate(det.binary, dome, box=det.box)
        assert pins.shape == (N_PINS, 2) and pins.dtype == np.float32
        assert np.isfinite(pins).all() and not fault
        d_all = np.hypot(*(pins[:, None] - xy[None]).transpose(2, 0, 1)).min(1)
        near_all.append(np.mean(d_all <= 3.0))
        # the pins the detector does see (glare hides ~15 of 133): the layout
        # fitted to this frame's blobs, one to one within 3 px
        fit = fit_layout(layout, xy, gate_px=3.0)
        vis = fit["idx"] >= 0
        d_vis = np.hypot(*(pins[vis] - xy[fit["idx"][vis]]).T)
        near_visible.append(np.mean(d_vis <= 3.0))
        near_layout.append(np.mean(vis))
    print(f"{clip}: localiser pins within 3 px of their visible pin {np.mean(near_visible):.3f}; "
          f"of any blob {np.mean(near_all):.3f} "
          f"(the fitted layout itself: {np.mean(near_layout):.3f})")
    assert min(near_visible) >= 0.90
    # glare hides pins from the detector, not from the localiser: all 133 are
    # returned, and about as many lie on a blob as the best-fitting layout has
    assert np.mean(near_all) >= 0.95 * np.mean(near_layout)


@pytest.mark.parametrize("kwargs, field", [
    ({"alpha": -1.0}, "alpha"), ({"size": 4}, "size"), ({"crop_factor": 5.0}, "crop_factor"),
    ({"n_aug": 0}, "n_aug"), ({"real_weight": 0.0}, "real_weight"),
    ({"profile": "nope"}, "profile"), ({"real_data": "/nonexistent/folder"}, "real_data"),
])
def test_train_bad_arguments_name_the_field(tmp_path, kwargs, field):
    args = {"n_sim_scenes": 1, "frames_per_scene": 2, "n_test_scenes": 1, "progress": False}
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        train_localiser(tmp_path / "m", **args)


def test_command_line_rejects_bad_arguments_with_exit_code_2(tmp_path, capsys):
    rc = main(["--out", str(tmp_path / "m"), "--alpha", "-1", "--sim-scenes", "1", "--quiet"])
    assert rc == 2
    assert "alpha" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()
