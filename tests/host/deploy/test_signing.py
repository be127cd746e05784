"""host/deploy/signing.py: the host's key (created once, mode 0600), signing the
manifests a deploy ships, and the public key written into the leg's config."""
from __future__ import annotations

import json
import os

import pytest

from device.config import tomllib
from device.pi.models.artefact import sha256_file
from device.pi.models.signature import check_manifest
from host.deploy.options import DeployInputError
from host.deploy.signing import SigningKey, config_with_key, default_key_path, sign_models


def test_key_is_created_once_private_and_reused(tmp_path):
    p = tmp_path / "cfg" / "tacfoot" / "signing-key.pem"
    a = SigningKey.load(p)
    assert p.is_file() and os.stat(p).st_mode & 0o777 == 0o600
    assert os.stat(p.parent).st_mode & 0o777 == 0o700
    b = SigningKey.load(p)
    assert a.public_key == b.public_key and len(a.key_id) == 16
    os.chmod(p, 0o644)
    with pytest.raises(DeployInputError, match="may be read by others"):
        SigningKey.load(p)
    q = tmp_path / "garbage.pem"
    q.write_text("not a key")
    q.chmod(0o600)
    with pytest.raises(DeployInputError, match="not a PEM private key"):
        SigningKey.load(q)
    with pytest.raises(DeployInputError, match="not found"):
        SigningKey.load(tmp_path / "none.pem", create=False)


def test_default_key_path_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv("TACFOOT_SIGNING_KEY", raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    assert default_key_path() == tmp_path / "tacfoot" / "signing-key.pem"
    monkeypatch.setenv("TACFOOT_SIGNING_KEY", str(tmp_path / "k.pem"))
    assert default_key_path() == tmp_path / "k.pem"


def _model(folder, onnx="model.onnx", data=b"x"):
    folder.mkdir(parents=True)
    (folder / "model.onnx").write_bytes(data)
    from host.learn.onnx_io import new_spec
    (folder / "manifest.json").write_text(json.dumps(new_spec(
        4, {"kind": "surface", "T": 1, "classes": ["a", "b"]}, onnx,
        sha256_file(folder / "model.onnx")).to_manifest()))


def test_sign_models_signs_checked_manifests_only(tmp_path):
    key = SigningKey.load(tmp_path / "k.pem")
    _model(tmp_path / "models" / "surface")
    done = sign_models(tmp_path / "models", key)
    assert [p.parent.name for p in done] == ["surface"]
    assert check_manifest(done[0], key.public_key, allow_unsigned=False)
    # a manifest naming a file outside its folder is never signed
    from host.learn.onnx_io import new_spec
    (tmp_path / "models" / "surface" / "manifest.json").write_text(json.dumps(new_spec(
        4, {"kind": "surface", "T": 1, "classes": ["a", "b"]}, "/etc/hostname",
        "0").to_manifest()))
    with pytest.raises(DeployInputError, match="outside the model folder"):
        sign_models(tmp_path / "models", key)
    # nor one whose file does not match its hash
    _model(tmp_path / "m2" / "slip")
    (tmp_path / "m2" / "slip" / "model.onnx").write_bytes(b"changed")
    with pytest.raises(DeployInputError, match="checksum does not match"):
        sign_models(tmp_path / "m2", key)


@pytest.mark.parametrize("text", [
    "[camera]\nfps = 90\n",
    '[signing]\npublic_key = ""\nallow_unsigned = true\n[status]\ninterval_s = 0.5\n',
    "[signing] # trust\n\n[camera]\nfps = 90\n",
])
def test_config_gets_the_public_key(tmp_path, text):
    key = SigningKey.load(tmp_path / "k.pem")
    out = tomllib.loads(config_with_key(text, key, allow_unsigned=False, where="leg.toml"))
    assert out["signing"] == {"public_key": key.public_key, "allow_unsigned": False}
    assert out.get("camera", {}).get("fps", 90) == 90


def test_config_naming_another_key_is_refused(tmp_path):
    key = SigningKey.load(tmp_path / "k.pem")
    other = SigningKey.load(tmp_path / "o.pem")
    text = f'[signing]\npublic_key = "{other.public_key}"\n'
    with pytest.raises(DeployInputError, match=f"key {other.key_id}, not this host's"):
        config_with_key(text, key, allow_unsigned=False, where="leg.toml")
    same = config_with_key(f'[signing]\npublic_key = "{key.public_key}"\n', key, True, "x")
    assert tomllib.loads(same)["signing"]["allow_unsigned"] is True


def test_a_rule_model_without_an_onnx_file_is_signed(tmp_path):
    """A rule model (``host train --model rule``) lists no ONNX file: it is signed
    like any other model, and its signature verifies."""
    from device.pi.models.manifest import write_spec
    from host.learn.onnx_io import new_spec

    key = SigningKey.load(tmp_path / "k.pem")
    write_spec(tmp_path / "models" / "surface",
               new_spec(6, {"kind": "surface", "model": "rule", "T": 1, "classes": ["a", "b"],
                            "n_pins": 3, "rule": {}, "rule_sha256": "x"}))
    done = sign_models(tmp_path / "models", key)
    assert [p.parent.name for p in done] == ["surface"]
    assert check_manifest(done[0], key.public_key, allow_unsigned=False)


def test_sign_models_signs_the_set_of_models(tmp_path):
    """models-set.json names every model folder with its manifests' SHA-256, signed."""
    from device.pi.models.signature import SET_FILE, check_model_set
    key = SigningKey.load(tmp_path / "k.pem")
    d = tmp_path / "models"
    _model(d / "surface")
    _model(d / "pressure", data=b"other")
    sign_models(d, key)
    doc = json.loads((d / SET_FILE).read_text())
    assert doc["models"] == {n: {"manifest.json": sha256_file(d / n / "manifest.json")}
                             for n in ("pressure", "surface")}
    assert check_model_set(d, key.public_key, allow_unsigned=False) is True
    # a folder that holds a model but no manifest is not signed as part of the set
    (d / "slip").mkdir()
    (d / "slip" / "model.onnx").write_bytes(b"x")
    with pytest.raises(DeployInputError, match="slip holds no manifest.json"):
        sign_models(d, key)
