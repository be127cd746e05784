"""The host's signing key, and what ``host deploy`` signs with it.

The key is an Ed25519 private key in a PEM file (PKCS#8, unencrypted, mode 0600),
created on first use at ``--signing-key PATH``, else ``$TACFOOT_SIGNING_KEY``, else
``$XDG_CONFIG_HOME/tacfoot/signing-key.pem`` (``~/.config/tacfoot/signing-key.pem``).
A key file that group or others may read is refused, as ssh refuses one.

What a deploy signs (:mod:`device.pi.models.signature` has the format):

- every model manifest it ships (its ``.sig`` beside it, :mod:`device.pi.models.signature`),
  after checking that each file the manifest lists lies inside the model's folder
  and has the SHA-256 the manifest gives;
- the set of models: ``models/models-set.json`` names every model folder and the
  SHA-256 of each of its manifests (``models-set.json.sig``), so a model removed,
  emptied, changed or added on the leg is refused at start;
- the release's ``release.json`` (which lists the SHA-256 of every file of the
  release) as ``release.json.sig``.

The leg's config that ships gets the public key (``[signing] public_key``) and
``allow_unsigned = false`` unless the deploy is told ``--allow-unsigned``.
The signature arithmetic is the ``cryptography`` package's.
"""
from __future__ import annotations

import base64
import json
import os
import re
import stat
from pathlib import Path

from device.config import tomllib
from device.pi.models.artefact import ModelError, checked_model_file
from device.pi.models.manifest import MANIFEST, read_spec
from device.pi.models.signature import (SET_FILE, decode_public_key, key_id,
                                        model_set_doc, signature_doc, signature_path,
                                        verify)
from host.deploy.options import DeployInputError

KEY_ENV = "TACFOOT_SIGNING_KEY"


def default_key_path() -> Path:
    """Where the host's signing key lives unless ``--signing-key`` says otherwise."""
    if os.environ.get(KEY_ENV):
        return Path(os.environ[KEY_ENV])
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "tacfoot" / "signing-key.pem"


class SigningKey:
    """The host's Ed25519 key: :meth:`load` reads it, creating it on first use."""

    def __init__(self, private_key, path: Path):
        self._key = private_key
        self.path = path
        from cryptography.hazmat.primitives import serialization
        self.public_raw = private_key.public_key().public_bytes(
            serialization.Encoding.Raw, serialization.PublicFormat.Raw)

    @property
    def public_key(self) -> str:
        """The public key as the leg's config holds it (base64 of 32 bytes)."""
        return base64.b64encode(self.public_raw).decode()

    @property
    def key_id(self) -> str:
        return key_id(self.public_raw)

    @classmethod
    def load(cls, path: Path | str | None = None, create: bool = True) -> "SigningKey":
        """The key at ``path`` (default :func:`default_key_path`); a new one is
        written there (mode 0600, its folder 0700) when none exists and ``create``."""
        try:
            from cryptography.hazmat.primitives import serialization
            from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
        except ImportError:
            raise DeployInputError("host deploy signs with the cryptography package, which "
                                   "is not installed (pip install cryptography)") from None
        path = Path(path) if path is not None else default_key_path()
        if not path.exists():
            if not create:
                raise DeployInputError(f"signing key {path} not found")
            key = Ed25519PrivateKey.generate()
            pem = key.private_bytes(serialization.Encoding.PEM,
                                    serialization.PrivateFormat.PKCS8,
                                    serialization.NoEncryption())
            try:
                path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
                fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
                with os.fdopen(fd, "wb") as fh:
                    fh.write(pem)
            except FileExistsError:
                pass                        # another deploy made it first: read theirs
            except OSError as exc:
                raise DeployInputError(f"cannot create the signing key {path}: {exc}") from None
        try:
            mode = path.stat().st_mode
            if not stat.S_ISREG(mode):
                raise DeployInputError(f"signing key {path} is not a file")
            if mode & 0o077:
                raise DeployInputError(f"signing key {path} may be read by others (mode "
                                       f"{stat.S_IMODE(mode):o}); chmod 600 it")
            key = serialization.load_pem_private_key(path.read_bytes(), password=None)
        except OSError as exc:
            raise DeployInputError(f"cannot read the signing key {path}: {exc}") from None
        except (ValueError, TypeError) as exc:
            raise DeployInputError(f"signing key {path} is not a PEM private key "
                                   f"({exc})") from None
        if not isinstance(key, Ed25519PrivateKey):
            raise DeployInputError(f"signing key {path} is not an Ed25519 key")
        return cls(key, path)

    def sign(self, data: bytes) -> bytes:
        return self._key.sign(data)

    def sign_file(self, path: Path) -> Path:
        """Write ``path.sig`` signing the file's current bytes."""
        out = signature_path(path)
        out.write_text(json.dumps(signature_doc(self.sign(path.read_bytes()),
                                                self.public_raw)) + "\n")
        return out

    def verify_file(self, path: Path) -> None:
        """SignatureError unless ``path.sig`` signs ``path`` with this key."""
        verify(path.read_bytes(), signature_path(path), self.public_raw, path)


def check_listed_files(manifest: Path) -> None:
    """Every file a model manifest lists (``onnx``, none for a rule model, and the
    ``sha256`` table) lies inside its folder and has the SHA-256 given
    (:func:`device.pi.models.artefact.checked_model_file`); DeployInputError naming
    it if not."""
    try:
        spec, mpath = read_spec(manifest)
        folder = mpath.parent
        hashes = spec.sha256
        names = set(hashes) | ({spec.onnx} if spec.onnx is not None else set())
        for name in sorted(names):
            checked_model_file(folder, name, hashes, manifest)
    except (ModelError, TypeError) as exc:
        raise DeployInputError(f"will not sign: {exc}") from None


def sign_models(models: Path, key: SigningKey) -> list[Path]:
    """Sign every model manifest under ``models`` (each file checked first by
    :func:`check_listed_files`), then the set of them (``models-set.json`` naming
    every model folder and the SHA-256 of its manifests); the manifests signed."""
    done = []
    for manifest in sorted(models.glob("*/manifest*.json")):
        check_listed_files(manifest)
        key.sign_file(manifest)
        done.append(manifest)
    doc = model_set_doc(models)
    empty = sorted(name for name, manifests in doc["models"].items() if not manifests)
    if empty:
        raise DeployInputError(f"will not sign: {models / empty[0]} holds no {MANIFEST}")
    (models / SET_FILE).write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
    key.sign_file(models / SET_FILE)
    return done


_HEADER = re.compile(r"^\s*\[\s*([A-Za-z0-9_.\"' -]+?)\s*\]\s*(#.*)?$")


def config_with_key(text: str, key: SigningKey, allow_unsigned: bool, where: str) -> str:
    """The leg config ``text`` with ``[signing] public_key`` set to ``key``'s and
    ``allow_unsigned`` as given. DeployInputError when the config already names
    another key (that leg trusts another host) or the result does not parse."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise DeployInputError(f"{where}: not valid TOML ({exc})") from None
    have = doc.get("signing", {}).get("public_key", "") if isinstance(
        doc.get("signing"), dict) else ""
    if isinstance(have, str) and have.strip() and have.strip() != key.public_key:
        try:
            other = key_id(decode_public_key(have))
        except ValueError:
            other = "unreadable"
        raise DeployInputError(
            f"{where}: signing.public_key is key {other}, not this host's key {key.key_id} "
            f"({key.path}); deploy with --signing-key set to that key, or clear the field")
    lines = text.splitlines()
    want = {"public_key": f'public_key = "{key.public_key}"',
            "allow_unsigned": f"allow_unsigned = {'true' if allow_unsigned else 'false'}"}
    start = next((i for i, l in enumerate(lines)
                  if (m := _HEADER.match(l)) and m[1].strip() == "signing"), None)
    if start is None:
        lines += ["", "[signing]"] + list(want.values())
    else:
        end = next((i for i in range(start + 1, len(lines)) if _HEADER.match(lines[i])),
                   len(lines))
        for name, line in want.items():
            hit = next((i for i in range(start + 1, end)
                        if re.match(rf"^\s*{name}\s*=", lines[i])), None)
            if hit is not None:
                lines[hit] = line
            else:
                lines.insert(start + 1, line)
                end += 1
    out = "\n".join(lines) + "\n"
    try:
        got = tomllib.loads(out).get("signing", {})
    except tomllib.TOMLDecodeError:
        got = {}
    if got.get("public_key") != key.public_key or got.get("allow_unsigned") != allow_unsigned:
        raise DeployInputError(f"{where}: cannot set [signing] public_key in this config; "
                               f"write it as a [signing] table")
    return out
