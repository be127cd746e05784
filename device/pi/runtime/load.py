"""The leg runtime's model set: every model in the models folder, loaded once and
checked against the pin layout before the loop starts. Each manifest's signature is
checked against the config's ``[signing]`` key before its model is loaded
(:func:`device.pi.models.signature.check_manifest`), and, when signatures are
required, the folder as a whole against its signed ``models-set.json``
(:func:`device.pi.models.signature.check_model_set`): a signed model missing,
emptied or changed, or an unsigned one added, and the leg refuses to start.

Every model carries the sensor profile it was trained for (its model spec,
:mod:`device.pi.models.spec`), and the models' profile is the one the runtime runs:
:attr:`Models.profile` is its record and :attr:`Models.profile_source` the name or
path the pipeline and the pin layout load. Models of one folder that carry different
profiles, or a config that sets ``models.profile`` to another profile, are refused,
naming both files and hashes; a config that does not set it runs the models'
profile (``models.profile``'s default, roboskin, only without models)."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from device.pi.models.artefact import ModelError
from device.pi.models.manifest import MANIFEST, has_manifest, manifest_for, manifest_path
from device.pi.models.spec import SpecError, check_same_profiles, profile_record, profile_source
from device.pi.models.classifier import Classifier
from device.pi.models.fused import FUSED_DIR, FUSED_TASKS, load_fused
from device.pi.models.regressor import Regressor
from device.pi.models.rules import SURFACE_CLASSES, RuleClassifier
from device.pi.models.window import RollingWindow
from device.pi.runtime.config import LegConfig
from device.pi.vision.layout import layout_for_profile
from device.pi.models.localiser import Localiser
from device.shipped import models_dir
from device.pi.models.signature import check_manifest, check_model_set

_log = logging.getLogger(__name__)

#: the classifier tasks, each loaded from the folder of that name
CLASSIFIER_TASKS = ("surface", "texture", "slip")


@dataclass
class Models:
    surface: object | None = None       # Classifier or RuleClassifier
    texture: object | None = None
    slip: object | None = None
    pressure: object | None = None
    localiser: object | None = None     # only with models.localiser = true
    rule: object | None = None          # the rule classifier (always present)
    loaded: tuple = ()
    profile: dict | None = None         # the models' sensor profile record (None: none loaded)
    profile_source: str | None = None   # the profile name or .toml path the runtime runs
    fused: object | None = None         # the per-frame models as one graph (FusedModels)
    fused_note: str = ""                # why the fused graph is not used ("" when it is)


def default_models_dir() -> Path:
    """The shipped default models: ``models/`` of a checkout, or the copy an installed
    wheel carries (:mod:`device.shipped`)."""
    return models_dir()


def rule_from_config(cfg: LegConfig, n_pins: int) -> RuleClassifier:
    """The surface rule with the config's nominal gait context, in the SURFACE class
    order."""
    dc = cfg.decision
    rule = {"contact_px": 1.0, "expected_mag_px": dc.nominal_load_n * dc.mag_px_per_n,
            "soft_ratio": 0.6,
            "expected_motion_px": dc.nominal_speed_mm_s * dc.motion_px_per_mm / cfg.camera.fps,
            "wet_ratio": 0.3}
    return RuleClassifier(rule, SURFACE_CLASSES, cfg.models.window_T, n_pins)


def _pick_localiser(folder: Path, profile: str) -> Path | None:
    locs = sorted(p for p in folder.glob("localiser*") if p.is_dir())
    if not locs:
        return None
    return next((p for p in locs if p.name == f"localiser-{profile}"), locs[0])


def _specs(m: Models) -> dict:
    """{manifest path: spec} of every model loaded from a folder."""
    out = {}
    for name in ("surface", "texture", "slip", "pressure", "localiser"):
        mod = getattr(m, name)
        if mod is None:
            continue
        inner = getattr(mod, "model", None)
        spec = getattr(inner, "spec", None) or getattr(mod, "spec", None)
        where = getattr(inner, "source", None) or (
            manifest_path(mod.path) if getattr(mod, "path", None) is not None else None)
        if spec is not None and where is not None:
            out[str(where)] = spec
    return out


def check_profiles(m: Models, profile: str | None) -> dict | None:
    """The one sensor profile of the loaded models; ModelError naming both files and
    hashes when two models carry different profiles, or when ``profile`` (the
    config's ``models.profile``) is another one."""
    try:
        recs = {w: spec.profile for w, spec in _specs(m).items()}
        given = profile_record(profile) if profile is not None and recs else None
        return check_same_profiles(recs, given) if recs else None
    except (SpecError, ValueError) as exc:
        raise ModelError(str(exc).replace(
            "drop --profile", "remove models.profile from the leg config (the runtime then "
                              "runs the models' profile)")) from None


def runtime_profile(m: Models, cfg: LegConfig) -> tuple[dict | None, str]:
    """(the models' profile record, the profile name or path the runtime runs): the
    models' profile, checked against ``models.profile`` when the config sets it;
    the config's (default) profile when no model is loaded."""
    given = cfg.models.profile if cfg.models.profile_set else None
    rec = check_profiles(m, given)
    if rec is None or given is not None:
        return rec, cfg.models.profile
    return rec, profile_source(rec)


def layout_pins(profile: str) -> int:
    """M, the pins of a profile's fixed layout (LayoutError naming the profile)."""
    return int(len(layout_for_profile(profile)))


def _check_inputs(m: Models, n_pins: int) -> None:
    """Each learned model's input size against the window it will be given."""
    for name in ("surface", "texture", "slip", "pressure"):
        mod = getattr(m, name)
        if mod is None or isinstance(mod, RuleClassifier):
            continue
        spec, where = mod.model.spec, mod.model.source
        try:
            x = RollingWindow(spec.T, n_pins).encode(spec.input_layout, with_imu=spec.uses_imu)
        except ValueError as exc:
            raise ModelError(f"{where}: {exc}") from None
        if x.size != mod.n_features:
            raise ModelError(f"{where}: the model takes {mod.n_features} inputs, but a "
                             f"{spec.input_layout} window of T={spec.T} over the {n_pins}-pin "
                             f"layout gives {x.size}")


def load_models(models_dir: Path | str | None, variant: str, profile_n_pins: int | None,
                cfg: LegConfig, *, rules_only: bool = False) -> Models:
    """Every model present in ``models_dir`` (surface, texture, slip, pressure, and
    the localiser when ``cfg.models.localiser``), loaded once. Raises ModelError
    naming the file for a bad one, and naming both when the models carry different
    sensor profiles or the config sets a ``models.profile`` that is not theirs.
    ``profile_n_pins`` None: the pins of the profile the runtime runs
    (:func:`runtime_profile`). ``rules_only``: load none (the surface rule alone)."""
    m = Models()
    loaded = []
    d = Path(models_dir) if models_dir is not None else default_models_dir()
    if models_dir is not None and not d.is_dir():
        raise ModelError(f"{d}: models folder not found")
    sig = cfg.signing
    present = d.is_dir() and not rules_only

    def checked(manifest: Path) -> Path:
        if manifest.is_file():
            check_manifest(manifest, sig.public_key, sig.allow_unsigned)
        return manifest

    if present:
        check_model_set(d, sig.public_key, sig.allow_unsigned)
        for kind in CLASSIFIER_TASKS:
            f = d / kind
            if has_manifest(f) or (f.is_dir() and any(f.iterdir())):
                setattr(m, kind, Classifier.load(checked(manifest_for(f, variant)),
                                                 expect_kind=kind))
                loaded.append(kind)
        f = d / "pressure"
        if f.is_dir():
            m.pressure = Regressor.load(checked(manifest_for(f, variant)))
            loaded.append("pressure")
    m.profile, m.profile_source = runtime_profile(m, cfg)
    if present and cfg.models.localiser:
        # the localiser of the profile the leg runs: the models' own when the config
        # names none (then checked against the models' profile with the rest)
        name = (m.profile or {}).get("name") or cfg.models.profile
        pick = _pick_localiser(d, name)
        if pick is not None:
            m.localiser = Localiser.load(checked(manifest_path(pick)))
            loaded.append(pick.name)
            m.profile, m.profile_source = runtime_profile(m, cfg)
    if profile_n_pins is None:
        profile_n_pins = layout_pins(m.profile_source)
    s = m.surface
    if isinstance(s, RuleClassifier) and list(s.classes) == list(SURFACE_CLASSES):
        m.rule = s
    elif isinstance(s, RuleClassifier):
        # a rule file listing its classes in another order: the same thresholds,
        # evaluated in the SURFACE class order
        m.rule = m.surface = RuleClassifier(s.rule, SURFACE_CLASSES, s.T, s.n_pins,
                                            spec=s.spec, path=s.path)
    else:
        m.rule = rule_from_config(cfg, profile_n_pins)
    _check_inputs(m, profile_n_pins)
    m.loaded = tuple(loaded)
    if present:
        _use_fused(m, d, variant, checked)
    return m


def _use_fused(m: Models, d: Path, variant: str, checked) -> None:
    """The fused graph of the loaded ONNX models (one call per frame) when it
    matches them; otherwise the individual sessions, and, when a fused graph is
    there but does not match, one line on stderr saying why."""
    members = {t: getattr(m, t) for t in FUSED_TASKS
               if getattr(m, t) is not None and not isinstance(getattr(m, t), RuleClassifier)}
    if len(members) < 2:
        m.fused_note = "fewer than two ONNX models: nothing to fuse"
        return
    m.fused, why = load_fused(d, variant, members, check=checked)
    m.fused_note = why
    if m.fused is None and (d / FUSED_DIR).is_dir():      # absent: nothing to say
        _log.info("device.pi run: note: models: %s; running one session per model", why)


def check_models_folder(models_dir, fail) -> None:
    """Refuse one model's folder given for the models folder (it would load nothing
    and run the rules alone). A folder with no model is refused by the caller
    (:func:`~device.pi.runtime.start.build_runtime`) unless the rules alone are asked for."""
    d = Path(models_dir)
    if not d.is_dir():
        return                                # load_models names the missing folder
    if has_manifest(d) or any(d.glob("*.onnx")):
        fail(f"--models {str(models_dir)!r} is one model's folder (it holds "
             f"{MANIFEST if has_manifest(d) else 'an .onnx file'}); "
             f"give the folder that holds surface/, texture/, slip/ and pressure/, "
             f"e.g. {d.parent}")
