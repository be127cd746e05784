"""Loading the leg runtime's model set (device/pi/runtime/load.py): the rule in the
SURFACE class order, the localiser only when the config asks for it, and a runtime
that calls the localiser only then."""
from __future__ import annotations

import json
import shutil
import time

import numpy as np
import pytest

from device.pi.models.artefact import ModelError
from device.pi import protocol as P
from device.pi.runtime.config import LegConfig, parse_leg_config
from device.pi.runtime.load import default_models_dir, load_models, rule_from_config
from device.pi.runtime.loop import LegRuntime
from device.pi.sources.camera import open_camera
from tests.device.pi.runtime.standins import NullImu, RecordingPort

SHIPPED_LOCALISER = default_models_dir() / "localiser-roboskin"


@pytest.fixture(scope="module")
def localiser_dir(tmp_path_factory):
    """A models folder holding only the shipped roboskin localiser."""
    if not (SHIPPED_LOCALISER / "manifest.json").is_file():
        pytest.skip("no shipped localiser-roboskin model")
    d = tmp_path_factory.mktemp("models")
    shutil.copytree(SHIPPED_LOCALISER, d / "localiser-roboskin")
    return d


def _runtime(models_dir, cfg, frames=12):
    models = load_models(models_dir, "int8", 133, cfg)
    rt = LegRuntime(cfg, lambda: open_camera("sim://press-hard"), NullImu(), RecordingPort(), models,
                    lossless=True, fps=120.0, notify=lambda s: None, max_frames=frames)
    return rt, models


def test_an_empty_folder_gives_the_rule_alone_in_the_surface_class_order(tmp_path):
    m = load_models(tmp_path, "int8", 133, LegConfig())
    assert m.surface is None and m.localiser is None and m.loaded == ()
    assert list(m.rule.classes) == list(P.SURFACE_CLASSES)
    assert m.rule.T == LegConfig().models.window_T and m.rule.n_pins == 133


def test_rule_from_config_takes_the_nominal_gait_context():
    cfg = LegConfig()
    rule = rule_from_config(cfg, 133).rule
    dc = cfg.decision
    assert rule["expected_mag_px"] == pytest.approx(dc.nominal_load_n * dc.mag_px_per_n)
    assert rule["expected_motion_px"] == pytest.approx(
        dc.nominal_speed_mm_s * dc.motion_px_per_mm / cfg.camera.fps)


def test_a_missing_folder_names_it(tmp_path):
    with pytest.raises(ModelError, match="models folder not found"):
        load_models(tmp_path / "nope", "int8", 133, LegConfig())


def test_localiser_is_off_by_default_and_loaded_when_asked(localiser_dir):
    off = load_models(localiser_dir, "int8", 133, LegConfig())
    assert off.localiser is None and "localiser-roboskin" not in off.loaded
    cfg = parse_leg_config({"models": {"localiser": True}})
    on = load_models(localiser_dir, "int8", 133, cfg)
    assert on.localiser is not None and on.loaded == ("localiser-roboskin",)


def _count_locate_calls(rt):
    calls = []
    loc = rt.stream.localiser
    if loc is not None:
        real = loc.locate

        def spy(*a, **kw):
            calls.append(time.monotonic())
            return real(*a, **kw)
        loc.locate = spy
    rt.run()
    return calls


def test_runtime_does_not_run_the_localiser_by_default(localiser_dir):
    rt, _ = _runtime(localiser_dir, LegConfig())
    calls = _count_locate_calls(rt)
    assert rt.frames == 12 and rt.stream.localiser is None and calls == []
    assert "localiser-roboskin" not in rt.status()["models"]


def test_runtime_runs_the_localiser_on_every_frame_when_asked(localiser_dir):
    cfg = parse_leg_config({"models": {"localiser": True}})
    rt, models = _runtime(localiser_dir, cfg)
    calls = _count_locate_calls(rt)
    assert rt.stream.localiser is models.localiser
    assert rt.frames == 12 and len(calls) == 12
    assert rt.latency_ms.count > 0 and np.isfinite(rt.latency_ms.recent()).all()


def test_learned_models_load_int8_by_default_and_float_on_request(model_dir, tmp_path):
    from device.pi.__main__ import main
    log = tmp_path / "d.jsonl"
    rc = main(["run", "--camera", "sim://press-hard", "--imu", "sim://press-hard", "--serial",
               "loop://", "--models", str(model_dir), "--frames", "30", "--json-log", str(log)])
    assert rc == 0
    ds = [json.loads(x) for x in log.read_text().splitlines()]
    assert len(ds) == 30 and any(d["pressure"] is not None for d in ds)
    cfg = LegConfig()
    m8 = load_models(model_dir, "int8", 133, cfg)
    mf = load_models(model_dir, "float", 133, cfg)
    assert m8.surface.onnx_path.name == "model.int8.onnx"
    assert mf.surface.onnx_path.name == "model.onnx"
    assert set(m8.loaded) == {"surface", "pressure"} and m8.rule is not m8.surface



def test_a_float_model_that_does_not_fit_the_layout_names_the_float_manifest(model_dir):
    """The loader reads the spec of the manifest it loaded: with the float variant,
    an error names manifest.float.json, not manifest.json."""
    with pytest.raises(ModelError, match=r"surface/manifest\.float\.json: the model takes"):
        load_models(model_dir, "float", 131, LegConfig())
    with pytest.raises(ModelError, match=r"surface/manifest\.json: the model takes"):
        load_models(model_dir, "int8", 131, LegConfig())


def _signing_cfg(key, allow_unsigned):
    return parse_leg_config({"signing": {"public_key": key.public_key,
                                         "allow_unsigned": allow_unsigned}})


def test_signed_models_load_and_altered_or_unsigned_ones_do_not(model_dir, tmp_path):
    from device.pi.models.signature import SignatureError, signature_path
    from device.pi.models.artefact import sha256_file
    from host.deploy.signing import SigningKey, sign_models

    d = tmp_path / "models"
    shutil.copytree(model_dir, d)
    key = SigningKey.load(tmp_path / "key.pem")
    signed = {p.relative_to(d).as_posix() for p in sign_models(d, key)}
    assert signed == {"surface/manifest.json", "surface/manifest.float.json",
                      "pressure/manifest.json"}
    strict = _signing_cfg(key, allow_unsigned=False)
    assert set(load_models(d, "int8", 133, strict).loaded) == {"surface", "pressure"}
    # signed by another host's key
    other = _signing_cfg(SigningKey.load(tmp_path / "other.pem"), allow_unsigned=True)
    with pytest.raises(SignatureError, match="surface/manifest.json: signature does not"):
        load_models(d, "int8", 133, other)
    # the onnx replaced and the manifest re-hashed to match it
    onnx = d / "pressure" / "model.onnx"
    onnx.write_bytes((model_dir / "surface" / "model.onnx").read_bytes())
    doc = json.loads((d / "pressure" / "manifest.json").read_text())
    doc["sha256"]["model.onnx"] = sha256_file(onnx)
    (d / "pressure" / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(SignatureError, match="pressure/manifest.json: .*changed after"):
        load_models(d, "int8", 133, _signing_cfg(key, allow_unsigned=True))
    # unsigned: refused when the config says so, loaded in development
    shutil.rmtree(d / "pressure")
    sign_models(d, key)
    signature_path(d / "surface" / "manifest.json").unlink()
    with pytest.raises(SignatureError, match="unsigned model"):
        load_models(d, "int8", 133, strict)
    assert load_models(d, "int8", 133, LegConfig()).loaded == ("surface",)


@pytest.fixture()
def signed_set(model_dir, tmp_path):
    """A copy of the models folder signed as a deploy signs it, its key, and the
    config that requires signatures."""
    from host.deploy.signing import SigningKey, sign_models
    d = tmp_path / "models"
    shutil.copytree(model_dir, d)
    key = SigningKey.load(tmp_path / "key.pem")
    sign_models(d, key)
    return d, key, _signing_cfg(key, allow_unsigned=False)


def _remove(d):
    shutil.rmtree(d / "surface")


def _empty(d):
    for f in (d / "surface").iterdir():
        f.unlink()


def _change(d):
    m = d / "surface" / "manifest.float.json"
    m.write_text(m.read_text() + " ")


def _add(d):
    shutil.copytree(d / "pressure", d / "slip")
    for f in (d / "slip").glob("*.sig"):
        f.unlink()


def _unsigned_set(d):
    (d / "models-set.json.sig").unlink()


def _no_set(d):
    (d / "models-set.json").unlink()


@pytest.mark.parametrize("spoil, match", [
    (_remove, "signed model 'surface' is missing"),
    (_empty, "signed model 'surface' is missing"),
    (_change, "surface: model changed since it was signed .*manifest.float.json"),
    (_add, "slip: model not named in the signed models-set.json"),
    (_unsigned_set, "models-set.json is unsigned"),
    (_no_set, "no models-set.json"),
])
def test_a_leg_requiring_signatures_refuses_a_models_folder_unlike_its_signed_set(
        signed_set, spoil, match, capsys):
    from device.pi.__main__ import main
    from device.pi.models.signature import SignatureError
    d, key, strict = signed_set
    assert set(load_models(d, "int8", 133, strict).loaded) == {"surface", "pressure"}
    spoil(d)
    with pytest.raises(SignatureError, match=match):
        load_models(d, "int8", 133, strict)
    # the runtime refuses to start: one line, exit 2 (not rule-only decisions)
    cfg = d.parent / "leg.toml"
    cfg.write_text(f'[signing]\npublic_key = "{key.public_key}"\nallow_unsigned = false\n')
    rc = main(["run", "--camera", "sim://press-hard", "--imu", "none", "--serial", "loop://",
               "--models", str(d), "--config", str(cfg), "--frames", "5"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "models-set.json" in err, err
    # in development (allow_unsigned) the set is not required
    from device.pi.models.signature import check_model_set
    assert check_model_set(d, key.public_key, allow_unsigned=True) is False


def test_signing_config_is_checked():
    from device.config import ConfigError
    with pytest.raises(ConfigError, match="signing.public_key"):
        parse_leg_config({"signing": {"public_key": "not a key"}})
    with pytest.raises(ConfigError, match="signing.allow_unsigned"):
        parse_leg_config({"signing": {"allow_unsigned": False}})
    assert LegConfig().signing.allow_unsigned is True


def _with_profile(src, dst, profile: str):
    """A copy of the model folder ``src`` whose manifests carry ``profile``."""
    from device.pi.models.spec import ModelSpec, profile_record
    shutil.copytree(src, dst)
    for mf in dst.glob("manifest*.json"):
        spec = ModelSpec.from_manifest(json.loads(mf.read_text()), mf)
        spec.profile = {k: v for k, v in profile_record(profile).items() if k != "path"}
        mf.write_text(json.dumps(spec.to_manifest()))


def test_models_carrying_different_profiles_or_another_than_the_configs_are_refused(
        model_dir, tmp_path):
    cfg = LegConfig()
    m = load_models(model_dir, "int8", 133, cfg)
    assert m.profile["name"] == "roboskin" and m.profile["n_pins"] == 133
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    shutil.copytree(model_dir / "surface", mixed / "surface")
    _with_profile(model_dir / "pressure", mixed / "pressure", "tactip331")
    with pytest.raises(ModelError, match=r"different sensor profiles: .*surface/manifest\.json "
                                         r"\(roboskin, 133 pins.* vs .*pressure/manifest\.json "
                                         r"\(tactip331, 331 pins"):
        load_models(mixed, "int8", 133, cfg)
    other = tmp_path / "other"
    other.mkdir()
    _with_profile(model_dir / "pressure", other / "pressure", "tactip331")
    explicit = parse_leg_config({"models": {"profile": "roboskin"}})
    with pytest.raises(ModelError, match=r"roboskin\.toml \(roboskin, 133 pins.*is not the "
                                         r"model's: .*pressure/manifest\.json \(tactip331"):
        load_models(other, "int8", 133, explicit)


@pytest.fixture(scope="module")
def tactip331_models(tmp_path_factory):
    """A models folder whose pressure ridge was trained for the 331-pin tactip331
    profile (not the config's default roboskin)."""
    from host.learn.train import train_model
    from tests.windows import synthetic

    d = tmp_path_factory.mktemp("models331")
    wp = synthetic(n_groups=4, per_group=6, n_pins=331, Tn=2, targets=True, imu=False)
    train_model("pressure", "ridge", wp, out_dir=d / "pressure", progress=False,
                profile="tactip331")
    return d


def test_a_config_without_a_profile_runs_the_models_profile(tactip331_models, tmp_path):
    """Issue #23: models written for tactip331 run under a config that names no
    profile: the models' profile is the runtime's, its pipeline maps onto the 331-pin
    layout, and the pressure model gets a window of its size."""
    from device.pi.runtime.start import build_runtime
    from device.pi.vision.layout import layout_for_profile

    cfg = parse_leg_config({})
    assert cfg.models.profile == "roboskin" and not cfg.models.profile_set
    m = load_models(tactip331_models, "int8", None, cfg)
    assert m.profile["name"] == "tactip331" and m.profile["n_pins"] == 331
    assert m.profile_source == "tactip331"
    rt = build_runtime("sim://press-hard", "none", "loop://", models_dir=tactip331_models,
                       frames=3, notify=lambda s: None)
    assert rt.n_pins == 331 and rt.encoder.n_pins == 331
    np.testing.assert_array_equal(rt.encoder.mapper.layout_px, layout_for_profile("tactip331"))
    assert rt.models.pressure.n_features == rt.windows[rt.models.pressure.T].encode(
        "vectors").size
    assert rt.run() == 0 and rt.frames == 3


def test_a_config_that_sets_another_profile_than_the_models_is_refused(tactip331_models):
    """An explicit models.profile that is not the models' stays an error naming both
    files, pin counts and hashes, and saying how to fix it."""
    explicit = parse_leg_config({"models": {"profile": "roboskin"}})
    assert explicit.models.profile_set
    with pytest.raises(ModelError, match=r"roboskin\.toml \(roboskin, 133 pins.*is not the "
                                         r"model's: .*pressure/manifest\.json \(tactip331, "
                                         r"331 pins.*remove models\.profile"):
        load_models(tactip331_models, "int8", None, explicit)
    same = parse_leg_config({"models": {"profile": "tactip331"}})
    assert load_models(tactip331_models, "int8", None, same).profile_source == "tactip331"


def test_without_models_the_configs_profile_runs(tmp_path):
    m = load_models(tmp_path, "int8", None, parse_leg_config({}))
    assert m.profile is None and m.profile_source == "roboskin" and m.rule.n_pins == 133


def test_the_fused_graph_is_used_when_it_matches_and_else_one_line_says_why(
        model_dir, tmp_path, caplog):
    import logging

    from host.learn.fuse import fuse_models

    caplog.set_level(logging.INFO, logger="device")

    def said() -> str:                                 # the notes logged since last asked
        text = "".join(r.getMessage() + "\n" for r in caplog.records)
        caplog.clear()
        return text

    d = tmp_path / "models"
    for t in ("surface", "pressure"):
        shutil.copytree(model_dir / t, d / t)
    m = load_models(d, "int8", 133, LegConfig())
    assert m.fused is None and "no fused/ graph" in m.fused_note
    assert said() == ""               # no fused graph: nothing to say
    fuse_models(d)
    for variant in ("int8", "float"):
        m = load_models(d, variant, 133, LegConfig())
        assert m.fused is not None and m.fused_note == ""
        assert m.fused.members == {"surface": m.surface, "pressure": m.pressure}
    assert said() == ""
    from host.learn.train import train_model
    from tests.windows import synthetic

    shutil.rmtree(d / "pressure")                     # pressure retrained since the fuse
    train_model("pressure", "ridge", synthetic(n_groups=4, per_group=8, n_pins=133, Tn=3,
                                               targets=True, imu=False, seed=9),
                out_dir=d / "pressure", progress=False)
    m = load_models(d, "int8", 133, LegConfig())
    assert m.fused is None and m.pressure is not None
    err = said()
    assert err.startswith("device.pi run: note: models: ") and "pressure member" in err
    assert "rebuild it" in err and err.count("\n") == 1


def test_the_shipped_models_run_as_one_fused_graph():
    """models/fused is built from the shipped models as they are (make models
    rebuilds it): the default leg makes one model call per frame, both variants."""
    for variant in ("int8", "float"):
        m = load_models(None, variant, 133, LegConfig())
        assert m.fused is not None, m.fused_note
        assert m.fused.tasks == ("surface", "texture", "slip", "pressure")


def test_the_localiser_is_the_models_profiles_when_the_config_names_none(
        tactip331_models, monkeypatch):
    """With localisers for two profiles in the folder and no models.profile set, the
    leg picks the one of the profile its models carry (tactip331), not the default
    config's (roboskin)."""
    import device.pi.runtime.load as L
    for name in ("localiser-roboskin", "localiser-tactip331"):
        (tactip331_models / name).mkdir()
    picked = []
    real = L._pick_localiser

    def spy(folder, profile):
        picked.append(real(folder, profile).name)
        return None                            # load none: the pick is the test

    monkeypatch.setattr(L, "_pick_localiser", spy)
    cfg = parse_leg_config({"models": {"localiser": True}})
    assert cfg.models.profile == "roboskin" and not cfg.models.profile_set
    load_models(tactip331_models, "int8", None, cfg)
    assert picked == ["localiser-tactip331"]
