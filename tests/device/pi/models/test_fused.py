"""device/pi/models/fused.py: the fused graph runs only for the models it was built
from, and gives each of them the result of its own predict_window, fault flags too."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from device.pi.models.classifier import Classifier
from device.pi.models.fused import FUSED_DIR, load_fused
from device.pi.models.regressor import Regressor
from device.pi.models.signature import SignatureError
from device.pi.models.window import RollingWindow
from host.learn.fuse import fuse_models


@pytest.fixture()
def fused_dir(model_dir, tmp_path):
    """The tiny surface fnn (int8) and pressure ridge, with their fused graph."""
    d = tmp_path / "models"
    for t in ("surface", "pressure"):
        shutil.copytree(model_dir / t, d / t)
    fuse_models(d)
    return d


def _loaded(d, variant="int8"):
    return {"surface": Classifier.load(d / "surface" / ("manifest.json" if variant == "int8"
                                                        else "manifest.float.json")),
            "pressure": Regressor.load(d / "pressure")}


def test_the_fused_run_is_each_models_predict_window_value_for_value(fused_dir):
    for variant in ("int8", "float"):
        ones, mine = _loaded(fused_dir, variant), _loaded(fused_dir, variant)
        fused, why = load_fused(fused_dir, variant, mine)
        assert fused is not None and why == "" and fused.tasks == ("surface", "pressure")
        w = RollingWindow(3, 133)
        rng = np.random.default_rng(1)
        for i in range(12):
            v = rng.normal(0, 4, (133, 2))
            if i == 7:
                v[:40] = 500.0                  # beyond the pressure model's training range
            w.push(vectors=v, imu=rng.normal(0, 1, 6))
            if not w.full:
                continue
            got = fused.run({"surface": w, "pressure": w})
            cid, p = ones["surface"].predict_window(w)
            assert got["surface"][0] == cid
            np.testing.assert_array_equal(got["surface"][1], p)
            assert mine["surface"].fault == ones["surface"].fault
            assert got["pressure"] == ones["pressure"].predict_window(w)
            assert mine["pressure"].fault == ones["pressure"].fault
        only = fused.run({"pressure": w})        # a member not due is not read
        assert set(only) == {"pressure"}


def test_a_member_other_than_the_loaded_model_falls_back_naming_it(fused_dir, tmp_path):
    assert load_fused(tmp_path, "int8", _loaded(fused_dir)) == (None, f"no {FUSED_DIR}/ graph "
                                                                      f"in {tmp_path}")
    fused, why = load_fused(fused_dir, "int8", {"surface": _loaded(fused_dir)["surface"]})
    assert fused is None and "built from ['pressure', 'surface'], the leg loaded ['surface']" \
        in why
    mf = fused_dir / FUSED_DIR / "manifest.json"
    doc = json.loads(mf.read_text())
    doc["members"][0]["sha256"] = "0" * 64       # surface retrained since the fuse
    mf.write_text(json.dumps(doc))
    fused, why = load_fused(fused_dir, "int8", _loaded(fused_dir))
    assert fused is None and "surface member is not the loaded" in why and "rebuild" in why
    (fused_dir / FUSED_DIR / "fused.onnx").write_bytes(b"junk")
    fused, why = load_fused(fused_dir, "int8", _loaded(fused_dir))
    assert fused is None and "checksum does not match" in why


def test_a_signature_that_fails_refuses_rather_than_falls_back(fused_dir):
    def check(manifest):
        raise SignatureError(f"{manifest}: signature does not verify")

    with pytest.raises(SignatureError, match="fused/manifest.json"):
        load_fused(fused_dir, "int8", _loaded(fused_dir), check=check)
