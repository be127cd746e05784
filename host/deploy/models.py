"""What a release's models need before they ship: the sensor profile they carry,
checked against the leg config's, and their fused graph (one model call per frame
on the leg, :mod:`host.learn.fuse`). :mod:`host.deploy.release` runs both while it
stages a release."""
from __future__ import annotations

from pathlib import Path

from device.config import ConfigError, read_toml
from host.deploy.options import DeployInputError


def config_profile_file(cfg: Path) -> Path | None:
    """The sensor profile file a leg config names by a relative path (``[models]
    profile = "my-sensor.toml"``), which must sit beside the config; None for a
    built-in profile. A missing file is a ConfigError naming it."""
    doc = read_toml(cfg)
    prof = (doc.get("models") or {}).get("profile") if isinstance(doc, dict) else None
    if not isinstance(prof, str) or not prof.endswith(".toml") or Path(prof).is_absolute():
        return None
    if Path(prof).parent != Path("."):
        raise ConfigError(f"{cfg}: models.profile {prof!r}: put the profile file beside the "
                          f"config and name it without a folder")
    path = cfg.parent / prof
    if not path.is_file():
        raise ConfigError(f"{cfg}: models.profile {prof!r}: no such file {path}")
    return path

def check_models_profile(models: Path | None, cfg: Path | None) -> dict | None:
    """The one sensor profile the models of a release carry (their specs), checked
    against the profile the config sets (``models.profile``; a config that does not
    set it runs the models' profile): DeployInputError naming both files and hashes
    when they differ or when two models carry different profiles (the leg would
    refuse to start). None without models."""
    from device.pi.models.artefact import ModelError
    from device.pi.models.manifest import MANIFEST, read_spec
    from host.learn.onnx_io import models_profile

    if models is None:
        return None
    try:
        specs = {str(mf): read_spec(mf)[0] for mf in sorted(Path(models).glob(f"*/{MANIFEST}"))}
        if not specs:
            return None
        leg = _leg_profile(cfg)
        return models_profile(specs, leg)[1]
    except (ModelError, ConfigError, ValueError) as exc:
        raise DeployInputError(f"{cfg or 'the default leg config'}: models.profile: "
                               + str(exc).replace("drop --profile", "remove models.profile "
                                                                    "(the leg then runs the "
                                                                    "models' profile)")
                               ) from None


def _leg_profile(cfg: Path | None) -> str | None:
    """The ``models.profile`` the config sets (a relative .toml beside it), else the
    default config's; None when neither sets it (the leg runs the models' profile).
    Only this key is read here; the leg checks the rest of the config."""
    from device.pi.runtime.config import DEFAULT_CONFIG

    path = cfg if cfg is not None else DEFAULT_CONFIG
    try:
        doc = read_toml(path)
    except ConfigError:
        doc = {}
    models = doc.get("models") if isinstance(doc, dict) else None
    prof = models.get("profile") if isinstance(models, dict) else None
    if not isinstance(prof, str) or not prof.strip():
        return None
    if prof.endswith(".toml") and not Path(prof).is_absolute():
        return str(Path(path).parent / prof)
    return prof


def fuse_release_models(models: Path) -> dict:
    """Build the fused graph of the release's models (``models/fused``: one model
    call per frame on the leg, :mod:`host.learn.fuse`) from the artefacts it ships,
    replacing any fused graph that came with them, before they are signed.
    DeployInputError naming the file when a model cannot be fused."""
    from device.pi.models.artefact import ModelError
    from host.learn.fuse import fuse_models

    try:
        return fuse_models(models)
    except ModelError as exc:
        raise DeployInputError(f"cannot fuse the models: {exc}") from None
