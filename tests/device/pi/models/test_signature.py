"""device/pi/models/signature.py: a manifest's Ed25519 signature is checked before
its model is loaded; unsigned, wrongly signed and altered manifests are refused."""
from __future__ import annotations

import json
import os

import pytest

from device.pi.models.artefact import sha256_file
from device.pi.models.signature import (SignatureError, check_manifest, decode_public_key,
                                        signature_path)
from host.deploy.signing import SigningKey


@pytest.fixture()
def signed(tmp_path):
    """A manifest and its onnx file, signed with a fresh key; (manifest, key)."""
    d = tmp_path / "m"
    d.mkdir()
    (d / "model.onnx").write_bytes(b"onnx bytes")
    m = d / "manifest.json"
    m.write_text(json.dumps({"format": "tacfoot-model", "version": 1, "onnx": "model.onnx",
                             "sha256": {"model.onnx": sha256_file(d / "model.onnx")}}))
    key = SigningKey.load(tmp_path / "key.pem")
    key.sign_file(m)
    return m, key


def test_a_signed_manifest_verifies_with_its_key(signed):
    m, key = signed
    assert check_manifest(m, key.public_key, allow_unsigned=False) is True
    assert check_manifest(m, key.public_key, allow_unsigned=True) is True


def test_unsigned_is_refused_unless_allowed(signed):
    m, key = signed
    signature_path(m).unlink()
    with pytest.raises(SignatureError, match="unsigned model"):
        check_manifest(m, key.public_key, allow_unsigned=False)
    assert check_manifest(m, key.public_key, allow_unsigned=True) is False
    # no key configured: only allow_unsigned lets it through
    assert check_manifest(m, "", allow_unsigned=True) is False
    with pytest.raises(SignatureError, match="no signing.public_key"):
        check_manifest(m, "", allow_unsigned=False)


def test_another_key_is_refused_even_when_unsigned_is_allowed(signed, tmp_path):
    m, _ = signed
    other = SigningKey.load(tmp_path / "other.pem")
    with pytest.raises(SignatureError, match="signed by key"):
        check_manifest(m, other.public_key, allow_unsigned=True)


def test_a_replaced_model_with_a_rehashed_manifest_is_refused(signed):
    m, key = signed
    onnx = m.parent / "model.onnx"
    onnx.write_bytes(b"another model")
    doc = json.loads(m.read_text())
    doc["sha256"]["model.onnx"] = sha256_file(onnx)
    m.write_text(json.dumps(doc))
    with pytest.raises(SignatureError, match="changed after it was signed"):
        check_manifest(m, key.public_key, allow_unsigned=True)


def test_a_garbled_signature_file_is_refused(signed):
    m, key = signed
    signature_path(m).write_text("{not json")
    with pytest.raises(SignatureError, match="unreadable signature"):
        check_manifest(m, key.public_key, allow_unsigned=True)


@pytest.mark.parametrize("text", ["", "abc", "!!!!", "AAAA", 5])
def test_decode_public_key_wants_32_bytes_of_base64(text):
    with pytest.raises(ValueError):
        decode_public_key(text)


def test_decode_public_key_round_trip(tmp_path):
    key = SigningKey.load(tmp_path / "k.pem")
    assert decode_public_key(key.public_key) == key.public_raw
    assert os.stat(tmp_path / "k.pem").st_mode & 0o777 == 0o600
