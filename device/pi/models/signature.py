"""Ed25519 signatures of model manifests, checked before a model is loaded.

A manifest names its ONNX file and that file's SHA-256, so a signature over the
manifest's bytes covers the model: replacing ``model.onnx`` and re-hashing the
manifest breaks the signature. ``host deploy`` signs every manifest it ships with
the host's key (:mod:`host.deploy.signing`) and writes the signature beside it::

    <manifest>.sig   (e.g. the model's manifest, with .sig added to its name)
    {"format": "tacfoot-signature", "version": 1, "algorithm": "ed25519",
     "key_id": "<first 16 hex of SHA-256 of the public key>", "signature": "<base64>"}

The leg's config holds the public key (``[signing] public_key``, base64 of the 32
raw bytes). :func:`check_manifest` refuses a manifest whose signature does not
verify with that key, and an unsigned one unless ``allow_unsigned`` is true.

The signatures of single manifests cannot tell a model that was removed from one
that was never shipped, so ``host deploy`` also signs the set: ``models-set.json``
at the top of the models folder names every model folder it ships and the SHA-256
of each of its manifests::

    {"format": "tacfoot-models-set", "version": 1,
     "models": {"surface": {"<manifest file>": "<sha256>", ...}, ...}}

:func:`check_model_set` refuses a models folder where a model it names is missing
or changed, where a model it does not name appears, or, when signatures are
required, where the set file is missing or not signed by the configured key.
The signature arithmetic is the ``cryptography`` package's.
"""
from __future__ import annotations

import base64
import binascii
import hashlib
import json
from pathlib import Path

from device.pi.models.artefact import ModelError

FORMAT = "tacfoot-signature"
SET_FORMAT = "tacfoot-models-set"
SET_FILE = "models-set.json"
#: folders that hold a model even before a manifest is found in them
MODEL_TASKS = ("surface", "texture", "slip", "pressure")
VERSION = 1
ALGORITHM = "ed25519"
SUFFIX = ".sig"


class SignatureError(ModelError):
    """A model manifest is unsigned, signed by another key, or altered after signing."""


def signature_path(manifest: Path | str) -> Path:
    """Where the signature of ``manifest`` lives: the same name plus ``.sig``."""
    manifest = Path(manifest)
    return manifest.with_name(manifest.name + SUFFIX)


def decode_public_key(text) -> bytes:
    """The 32 raw bytes of an Ed25519 public key given as base64; ValueError if not."""
    if not isinstance(text, str):
        raise ValueError(f"must be base64 text, got {text!r}")
    try:
        raw = base64.b64decode(text.strip(), validate=True)
    except (binascii.Error, ValueError):
        raise ValueError(f"is not base64: {text!r}") from None
    if len(raw) != 32:
        raise ValueError(f"must be a 32-byte Ed25519 public key, got {len(raw)} bytes")
    return raw


def key_id(public_raw: bytes) -> str:
    """A short name of a public key: the first 16 hex digits of its SHA-256."""
    return hashlib.sha256(public_raw).hexdigest()[:16]


def signature_doc(signature: bytes, public_raw: bytes) -> dict:
    """The JSON document a ``.sig`` file holds."""
    return {"format": FORMAT, "version": VERSION, "algorithm": ALGORITHM,
            "key_id": key_id(public_raw), "signature": base64.b64encode(signature).decode()}


def verify(data: bytes, sig_file: Path, public_raw: bytes, what: Path | str) -> None:
    """Check that ``sig_file`` signs ``data`` with the key ``public_raw``;
    SignatureError naming ``what`` if not."""
    try:
        from cryptography.exceptions import InvalidSignature
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey
    except ImportError:
        raise SignatureError(f"{what}: cannot check its signature: the cryptography package "
                             f"is not installed (pip install cryptography)") from None
    try:
        doc = json.loads(Path(sig_file).read_text())
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise ValueError("not a tacfoot signature")
        if doc.get("algorithm") != ALGORITHM:
            raise ValueError(f"algorithm {doc.get('algorithm')!r}, expected {ALGORITHM!r}")
        sig = base64.b64decode(str(doc.get("signature", "")), validate=True)
    except (OSError, ValueError, UnicodeDecodeError, binascii.Error) as exc:
        raise SignatureError(f"{sig_file}: unreadable signature ({exc})") from None
    try:
        Ed25519PublicKey.from_public_bytes(public_raw).verify(sig, data)
    except InvalidSignature:
        other = doc.get("key_id") != key_id(public_raw)
        raise SignatureError(
            f"{what}: signature does not verify with the configured key {key_id(public_raw)}"
            + (f" (signed by key {doc.get('key_id')})" if other else
               "; the file was changed after it was signed")) from None


def check_manifest(manifest: Path | str, public_key: str, allow_unsigned: bool) -> bool:
    """Check a model manifest's signature before the model is loaded. True when
    it carries a signature that verifies with ``public_key`` (base64); False when
    it is unsigned (or no key is configured) and ``allow_unsigned``. Raises
    SignatureError for a signature that does not verify, and for an unsigned
    manifest when ``allow_unsigned`` is false."""
    manifest = Path(manifest)
    sig = signature_path(manifest)
    if not public_key:
        if allow_unsigned:
            return False
        raise SignatureError(f"{manifest}: no signing.public_key is configured to check it "
                             f"with, and signing.allow_unsigned is false")
    if not sig.is_file():
        if allow_unsigned:
            return False
        raise SignatureError(f"{manifest}: unsigned model ({sig.name} not found); the leg's "
                             f"config has signing.allow_unsigned = false")
    try:
        data = manifest.read_bytes()
    except OSError as exc:
        raise ModelError(f"{manifest}: cannot read the manifest ({exc})") from None
    verify(data, sig, decode_public_key(public_key), manifest)
    return True


def model_folders(models_dir: Path | str) -> dict[str, dict[str, str]]:
    """Every model folder under ``models_dir`` (one holding a ``manifest*.json``, or a
    non-empty task folder) and the SHA-256 of each of its manifests."""
    from device.pi.models.artefact import sha256_file

    d = Path(models_dir)
    out = {}
    for f in sorted(p for p in d.iterdir() if p.is_dir()):
        manifests = sorted(f.glob("manifest*.json"))
        if manifests or (f.name in MODEL_TASKS and any(f.iterdir())):
            out[f.name] = {m.name: sha256_file(m) for m in manifests if m.is_file()}
    return out


def model_set_doc(models_dir: Path | str) -> dict:
    """The models-set document for the models folder as it is now."""
    return {"format": SET_FORMAT, "version": VERSION, "models": model_folders(models_dir)}


def check_model_set(models_dir: Path | str, public_key: str, allow_unsigned: bool) -> bool:
    """Check the models folder against its signed ``models-set.json`` before any model
    is loaded. True when the set file is signed by ``public_key`` and the folder
    matches it; False when signatures are not required (``allow_unsigned``: the set
    is not checked then, as unsigned models may load). SignatureError naming the
    folder and the model otherwise: the set file missing or unsigned, a signature
    that does not verify, a model it names missing or changed, a model it does not
    name present."""
    if allow_unsigned:
        return False
    d = Path(models_dir)
    f = d / SET_FILE
    sig = signature_path(f)
    if not f.is_file() or not sig.is_file() or not public_key:
        what = (f"no {SET_FILE} (the signed list of the models a deploy shipped)"
                if not f.is_file() else f"{SET_FILE} is unsigned ({sig.name} not found)"
                if not sig.is_file() else "no signing.public_key is configured to check it with")
        raise SignatureError(f"{d}: {what}, and signing.allow_unsigned is false")
    try:
        data = f.read_bytes()
    except OSError as exc:
        raise SignatureError(f"{f}: cannot read it ({exc})") from None
    verify(data, sig, decode_public_key(public_key), f)
    try:
        doc = json.loads(data)
        want = doc["models"] if doc.get("format") == SET_FORMAT else None
        if not isinstance(want, dict) or not all(
                isinstance(v, dict) and all(isinstance(h, str) for h in v.values())
                for v in want.values()):
            raise ValueError("not a tacfoot models set")
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        raise SignatureError(f"{f}: unreadable models set ({exc})") from None
    have = model_folders(d)
    for name in sorted(want):
        if name not in have:
            raise SignatureError(f"{d}: signed model {name!r} is missing (named in {SET_FILE})")
        if have[name] != want[name]:
            diff = sorted(set(have[name]) ^ set(want[name]) |
                          {m for m in have[name] if have[name][m] != want[name].get(m)})
            raise SignatureError(f"{d / name}: model changed since it was signed "
                                 f"({', '.join(diff)} differ from {SET_FILE})")
    extra = sorted(set(have) - set(want))
    if extra:
        raise SignatureError(f"{d / extra[0]}: model not named in the signed {SET_FILE} "
                             f"(an unsigned model was added)")
    return True
