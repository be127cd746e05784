"""The shipped default models in models/: present, small, loadable by the Pi's code,
and sane on data they never saw (a fresh simulated trial of each surface)."""
from __future__ import annotations
from tests import REPO_ROOT

import json

import numpy as np
import pytest

from device.pi.models.manifest import MANIFEST
from device.pi.models.classifier import Classifier
from device.pi.models.regressor import Regressor
from device.pi.models.window import RollingWindow

ROOT = REPO_ROOT
MODELS = ROOT / "models"
CLASSES = {"surface": ["hard", "no-touch", "slippery", "soft"],
           "texture": ["concrete", "lego", "smooth"],
           "slip": ["no-slip", "slip"]}


def manifest(name: str) -> dict:
    return json.loads((MODELS / name / MANIFEST).read_text())


@pytest.mark.parametrize("name", ["localiser-roboskin", "surface", "texture", "slip",
                                  "pressure"])
def test_each_default_is_present_under_1_mb_with_its_manifest(name):
    folder = MODELS / name
    assert (folder / MANIFEST).is_file(), f"{folder} missing: run make models"
    size = sum(p.stat().st_size for p in folder.iterdir() if p.is_file())
    assert 0 < size < 1 << 20, (name, size)
    doc = manifest(name)
    for fname in doc.get("sha256", {}):
        assert (folder / fname).is_file(), (name, fname)


def test_the_surface_default_is_an_int8_fnn_that_passed_its_check():
    doc = manifest("surface")
    assert doc["model"] == "fnn" and doc["variant"] == "int8"
    assert doc["onnx"] == "model.int8.onnx"
    assert doc["int8"]["passed"] and doc["int8"]["agreement"] >= 0.99


@pytest.mark.parametrize("name", ["surface", "texture", "slip"])
def test_classifiers_load_on_the_pi_and_stay_finite_on_extreme_windows(name):
    clf = Classifier.load(MODELS / name, expect_kind=name)
    doc = manifest(name)
    assert clf.classes == CLASSES[name]
    M = 133
    w = RollingWindow(doc["T"], M)
    for fill in (0.0, 1e6, -1e6):
        for _ in range(doc["T"]):
            w.push(vectors=np.full((M, 2), fill, np.float32), imu=np.full(6, fill, np.float32))
        k, p = clf.predict(w.encode(doc["input_layout"], with_imu=bool(doc.get("uses_imu"))))
        assert 0 <= k < len(CLASSES[name]) and np.isfinite(p).all()
        assert abs(p.sum() - 1.0) < 1e-4


def test_the_pressure_default_loads_and_reads_more_load_for_larger_vectors():
    reg = Regressor.load(MODELS / "pressure")
    doc = manifest("pressure")
    M = 133
    out = []
    for mag in (0.0, 2.0, 6.0):
        w = RollingWindow(doc["T"], M)
        for _ in range(doc["T"]):
            # pins pushed outwards from the centre, as a press does
            ang = np.linspace(0, 2 * np.pi, M, endpoint=False)
            w.push(vectors=np.stack([np.cos(ang), np.sin(ang)], 1).astype(np.float32) * mag)
        x = w.encode(doc["input_layout"], with_imu=bool(doc.get("uses_imu")))
        out.append(reg.predict_one(x))
    assert all(np.isfinite(out))
    lo, hi = manifest("pressure")["target_range"]
    assert abs(out[0]) < 0.05 * (hi - lo), out          # no displacement: about no load
    assert out[0] < out[1] < out[2], out                 # a deeper press reads more load


@pytest.mark.slow
def test_the_surface_default_classifies_unseen_simulated_trials(tmp_path):
    """One fresh trial per surface, seeds and surface parameters never used in
    training (drawn from the wider test ranges), through the Pi's pipeline."""
    from host.data.load import load_spec
    from host.learn.evaluate import evaluate_model
    from host.bench.scenes import simulate_scenes

    data = simulate_scenes(tmp_path / "s", ["hard", "soft", "wet", "no-touch"], 1, 777, True,
                           progress=False)
    ws = load_spec(str(data), "surface", manifest("surface")["T"], progress=False)
    ev = evaluate_model(MODELS / "surface", ws)
    assert ev["variant"] == "int8"
    assert ev["metrics"]["accuracy"] >= 0.95, ev["metrics"]["confusion"]


def test_the_texture_default_is_trained_on_real_recordings_and_says_so():
    doc = manifest("texture")
    assert doc["trained_on"]["data"] == "real"
    assert doc["trained_on"]["real_accuracy"] >= 0.9
    for name in ("surface", "slip", "pressure"):
        assert manifest(name)["trained_on"]["data"] == "simulated"


@pytest.mark.parametrize("clip,label,imu,floor", [
    ("concrete.avi", "concrete", "concrete_gyro.npy", 0.9),
    ("smooth.avi", "smooth", None, 0.9),
    ("lego_train.avi", "lego", "lego_gyro_train.npy", 0.65),   # short of 0.9: see README
])
def test_the_runtime_names_the_texture_on_held_out_real_frames(tmp_path, clip, label, imu,
                                                               floor):
    """python -m device.pi run on a whole real clip with the shipped models; on the
    contact frames of its last 30 % (after the model's T frames), which the texture
    model never trained on, the texture it names."""
    import cv2

    from device.pi.__main__ import main
    from tests.realdata import real_data_dir
    root = real_data_dir(f"roboskin/{clip}") / "roboskin"
    log = tmp_path / "d.jsonl"
    assert main(["run", "--camera", str(root / clip), "--imu",
                 f"file://{root / imu}" if imu else "none", "--serial", "loop://",
                 "--json-log", str(log)]) == 0
    n = int(cv2.VideoCapture(str(root / clip)).get(cv2.CAP_PROP_FRAME_COUNT))
    start = int(0.7 * n) + manifest("texture")["T"]
    ds = [json.loads(x) for x in log.read_text().splitlines()]
    held = [d for d in ds if d["index"] >= start and d["contact"]]
    assert len(held) >= 20
    right = sum(d["texture"] == label for d in held) / len(held)
    assert right >= floor, right


def test_the_texture_graph_holds_no_feature_node_and_its_manifest_the_roughness():
    """The shipped texture fnn reads its window features (features version 2): the
    roughness' neighbours are in its manifest, not a Gather of its graph."""
    import onnx

    doc = manifest("texture")
    assert doc["features"]["neighbours"] == doc["training"]["temporal"]["neighbours"]
    for name in doc["variants"].values():
        ops = {n.op_type for n in onnx.load(str(MODELS / "texture" / name)).graph.node}
        assert not ops & {"Gather", "Transpose", "ReduceMean", "Slice"}, name


def test_regraph_of_a_model_whose_features_run_outside_its_graph_is_refused(tmp_path, capsys):
    """host.bench.shipped --regraph on a copy of the shipped texture model (features
    version 2): nothing to rewrite, one line, exit 2, no file changed."""
    import shutil

    from host.bench.shipped import main

    shutil.copytree(MODELS / "texture", tmp_path / "texture")
    before = {p.name: p.read_bytes() for p in (tmp_path / "texture").iterdir()}
    assert main(["--out", str(tmp_path), "--regraph", "texture"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "outside the graph" in err[0]
    assert {p.name: p.read_bytes() for p in (tmp_path / "texture").iterdir()} == before


def test_regraph_of_a_folder_without_a_temporal_layer_is_one_line_and_exit_2(tmp_path, capsys):
    from host.bench.shipped import main

    assert main(["--out", str(tmp_path), "--regraph", "texture"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "texture" in err[0]


def test_regraph_writes_no_file_unless_every_file_passes(tmp_path, capsys):
    """A folder whose int8 file is not the float model's twin: the float file passes
    its check, the int8 one fails, and the float file is left as it was (the manifests'
    checksums still hold)."""
    import shutil

    from host.bench.shipped import main

    shutil.copytree(MODELS / "texture", tmp_path / "texture")
    int8 = manifest("texture")["variants"]["int8"]
    shutil.copy(MODELS / "surface" / manifest("surface")["variants"]["int8"],
                tmp_path / "texture" / int8)
    before = {p.name: p.read_bytes() for p in (tmp_path / "texture").iterdir()}
    assert main(["--out", str(tmp_path), "--regraph", "texture"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    after = {p.name: p.read_bytes() for p in (tmp_path / "texture").iterdir()}
    assert after == before
