"""device/pi/models/fused.py: the fused graph runs only for the models it was built
from, and gives each of them the result of its own predict_window, fault flags too."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from device.pi.models.classifier import Classifier
from device.pi.models.artefact import ModelError
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


def assert_member_results(got: dict, due: dict, ones: dict, w) -> None:
    """Each member's fused result is its own ``predict_window``'s (labels and
    probabilities to the bit, the regressor's value and fault flag)."""
    for task in due:
        want = ones[task].predict_window(w)
        if task == "pressure":
            assert got[task] == want
        else:
            assert got[task][0] == want[0]
            np.testing.assert_array_equal(got[task][1], want[1])


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
    doc["params"]["members"][0]["sha256"] = "0" * 64       # surface retrained since the fuse
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


@pytest.fixture()
def with_texture(model_dir, tmp_path):
    """surface, a texture member (the surface fnn under the texture task) and
    pressure, fused: the folder holds the graph without texture too."""
    d = tmp_path / "models3"
    for t in ("surface", "pressure"):
        shutil.copytree(model_dir / t, d / t)
    shutil.copytree(model_dir / "surface", d / "texture")
    fuse_models(d)
    return d


def test_frames_without_texture_run_the_graph_without_it_value_for_value(with_texture):
    """Issue #25: out of contact (no texture due) the frame runs the fused graph
    cut down to the other members, whose results are still each model's own."""
    def loaded():
        return {**_loaded(with_texture), "texture": Classifier.load(with_texture / "texture")}
    ones, mine = loaded(), loaded()
    fused, why = load_fused(with_texture, "int8", mine)
    assert fused is not None and why == "" and fused.tasks == ("surface", "texture", "pressure")
    rest = fused._runner_for({"surface", "pressure"})
    assert rest is not fused._runner and fused._runner_for(fused.tasks) is fused._runner
    assert [i.name for i in rest.session.get_inputs()] == ["surface/x", "pressure/x"]
    w = RollingWindow(3, 133)
    rng = np.random.default_rng(2)
    for i in range(14):
        w.push(vectors=rng.normal(0, 3 + i, (133, 2)), imu=rng.normal(0, 1, 6))
        if not w.full:
            continue
        due = {"surface": w, "pressure": w} if i % 2 else {"surface": w, "texture": w,
                                                           "pressure": w}
        got = fused.run(due)
        assert set(got) == set(due)
        assert_member_results(got, due, ones, w)
        for task in due:
            assert mine[task].fault == ones[task].fault


def test_a_bad_subset_graph_leaves_the_individual_sessions_naming_it(with_texture):
    loaded = {**_loaded(with_texture), "texture": Classifier.load(with_texture / "texture")}
    (with_texture / FUSED_DIR / "fused.notexture.onnx").write_bytes(b"junk")
    fused, why = load_fused(with_texture, "int8", loaded)
    assert fused is None and "fused.notexture.onnx" in why and "checksum" in why
    mf = with_texture / FUSED_DIR / "manifest.json"
    doc = json.loads(mf.read_text())
    doc["params"]["subsets"][0]["tasks"] = ["surface", "depth"]
    mf.write_text(json.dumps(doc))
    fused, why = load_fused(with_texture, "int8", loaded)
    assert fused is None and "subset's tasks" in why and "depth" in why


def test_members_that_read_one_window_encoding_share_one_input(model_dir, tmp_path):
    """Issue #25: surface and slip read the same encoding of the same window; the
    fused graph has one input for both (written once a frame) and their results
    are still each model's own. Two different windows for them, or loaded models
    that read the window differently, are refused."""
    d = tmp_path / "shared"
    for t in ("surface", "pressure"):
        shutil.copytree(model_dir / t, d / t)
    shutil.copytree(model_dir / "surface", d / "slip")      # the same encoding as surface

    def loaded():
        return {**_loaded(d), "slip": Classifier.load(d / "slip")}
    fuse_models(d)
    ones, mine = loaded(), loaded()
    fused, why = load_fused(d, "int8", mine)
    assert fused is not None and why == ""
    assert [i.name for i in fused.model.session.get_inputs()] == ["surface/x", "pressure/x"]
    assert fused.shared_inputs == {"slip": "surface"}
    w = RollingWindow(3, 133)
    rng = np.random.default_rng(6)
    for i in range(10):
        w.push(vectors=rng.normal(0, 2 + i, (133, 2)), imu=rng.normal(0, 1, 6))
        if not w.full:
            continue
        due = {"slip": w, "pressure": w} if i == 5 else {"slip": w, "surface": w,
                                                          "pressure": w}
        got = fused.run(due)
        assert_member_results(got, due, ones, w)
    other = RollingWindow(3, 133)
    other.push(vectors=np.ones((133, 2)), imu=np.zeros(6))
    with pytest.raises(ModelError, match="slip and surface read one input"):
        fused.run({"surface": w, "slip": other})
    odd = loaded()
    odd["slip"].uses_imu = not odd["slip"].uses_imu
    fused, why = load_fused(d, "int8", odd)
    assert fused is None and "surface member shares the input of ['slip']" in why
