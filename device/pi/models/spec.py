"""The model spec: the one schema of a model folder's ``manifest.json``.

Every writer (``host train``, the CNN, the localiser, the pressure model, the
shipped-model builder) builds a :class:`ModelSpec` and writes
:meth:`ModelSpec.to_manifest`; every loader parses the manifest with
:meth:`ModelSpec.from_manifest`, whose errors name the file and the field.

A spec holds:

* what the model decides: ``kind`` (the folder's task: surface, texture, slip,
  pressure, localiser), ``task``, ``model`` (the estimator: fnn, ridge, rule,
  cnn, ...) and ``classes`` (empty for a regressor);
* what it reads and gives: ``T`` (frames per window), ``input_layout``
  (vectors, frames, image), ``n_inputs``, ``input_name``, ``output`` (the ONNX
  output's name), ``output_kind``, ``uses_imu`` and ``crop_size`` (the image
  side of a frame- or image-reading model, else None);
* ``metrics``: exactly the keys ``train``, ``test`` and ``cv``, each a dict (any
  content: accuracy, intervals, counts) or None;
* ``profile``: the sensor the model was trained for: ``name``, ``n_pins``,
  ``sha256`` (of its parsed content, see :func:`profile_hash`) and ``toml`` (the
  profile file's full text), so a model carries its sensor;
* ``trained_on``: the training data: ``data`` (real, simulated or unknown),
  ``recordings`` (a list of ``{"path", "sha256", "frames"}``; sha256 or frames
  may be null where unknown), ``split`` (the protocol, in words) and any more
  keys (scenes, ...);
* ``config``: the training config that made the model (also written as
  ``train.toml`` beside the manifest by the host), and ``training``: the run's
  record (data summary, hyperparameters, fit times);
* the artefact: ``onnx``, ``sha256``, ``size_bytes``, ``files``, ``variants``,
  ``variant``, ``int8`` (the int8 check) and ``feature_spec`` (the version of the
  window encoding);
* ``features``: for a model whose graph reads window features rather than the
  window, the record of what the runtime computes (``version``, ``kind`` and the
  kind's parameters, :mod:`device.pi.models.winfeat`); absent (None) for a model
  that reads the encoded window itself;
* ``params``: kind-specific parameters the loaders read (``ignored_pins``,
  ``roughness``, ``input_clip``, ``target_mean``, ``rule``, the localiser's
  layout ...), written as top-level keys of the manifest.

Version 2 of the manifest is this schema; the key variants of version 1
(``window`` for ``T``, ``heldout``/``held_out`` for ``test``, a profile given by
name only) are refused.
"""
from __future__ import annotations

import hashlib
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10 on Raspberry Pi OS bookworm
    import tomli as tomllib

from device.config import ConfigError
from device.profile import PROFILE_DIR, builtin_toml, parse_pipeline_profile
from device.errors import TacfootError

__all__ = ["ModelSpec", "SpecError", "SPEC_VERSION", "METRIC_KEYS", "DATA_SOURCES",
           "profile_record", "profile_hash", "profile_from_text", "same_profile",
           "check_same_profiles", "profile_source"]

#: the manifest version this schema reads and writes
SPEC_VERSION = 2
#: the one key each for training, held-out test and cross-validation metrics
METRIC_KEYS = ("train", "test", "cv")
DATA_SOURCES = ("real", "simulated", "real+simulated", "unknown")
#: keys of version 1 manifests that have one name now
LEGACY_KEYS = {"window": "T", "heldout": "metrics.test", "held_out": "metrics.test",
               "test_data": "training.test_data"}
_CORE = ("format", "version", "feature_spec", "kind", "task", "model", "classes", "T",
         "input_layout", "input", "output", "output_kind", "uses_imu", "crop_size", "onnx",
         "sha256", "size_bytes", "files", "variants", "variant", "metrics", "int8", "profile",
         "trained_on", "config", "training", "features")


class SpecError(TacfootError, ValueError):
    """A manifest does not follow the model spec; the message names the file and
    the field. (:class:`device.pi.models.artefact.ModelError` derives from it.)"""


def _canonical(doc) -> bytes:
    return json.dumps(doc, sort_keys=True, separators=(",", ":"), default=str).encode()


def profile_hash(doc: dict) -> str:
    """SHA-256 of a parsed profile TOML (canonical JSON of the parsed tables), so
    comments and key order do not change it."""
    return hashlib.sha256(_canonical(doc)).hexdigest()


def profile_from_text(text: str, name: str, where: str = "") -> dict:
    """The spec's profile record of a profile TOML's text: name, n_pins (its
    ``[vision] n_pins``), sha256 and the text. SpecError naming ``where`` when the
    text is not a pipeline profile."""
    try:
        doc = tomllib.loads(text)
        pp = parse_pipeline_profile(doc, source=f"{where or name}.toml")
    except (tomllib.TOMLDecodeError, ConfigError, ValueError) as exc:
        raise SpecError(f"{where}: profile: not a sensor profile ({exc})") from None
    return {"name": str(doc.get("profile", {}).get("name", pp.name) or name),
            "n_pins": int(pp.n_pins), "sha256": profile_hash(doc), "toml": text}


def profile_record(name_or_path: str | Path) -> dict:
    """The profile record of a built-in profile name or a ``.toml`` path, with
    ``path`` (the file it was read from)."""
    p = builtin_toml(name_or_path, PROFILE_DIR, "profile", "profile", ConfigError)
    try:
        text = Path(p).read_text()
    except OSError as exc:
        raise SpecError(f"{p}: cannot read the profile: {exc.strerror or exc}") from None
    rec = profile_from_text(text, Path(p).stem, str(p))
    if rec["name"] in ("", "custom"):
        rec["name"] = Path(p).stem
    return dict(rec, path=str(p))


def profile_source(profile: dict) -> str:
    """A profile name or ``.toml`` path that loads the spec's ``profile`` record: the
    built-in of that name when its content is the same (same hash), else the
    record's text written once to a file named by its hash under the temp folder
    (so the pipeline, the layout and the runtime read the model's own sensor)."""
    import os
    import tempfile

    name = str(profile["name"])
    if (PROFILE_DIR / f"{name}.toml").is_file() and \
            profile_record(name)["sha256"] == profile["sha256"]:
        return name
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in name) or "profile"
    path = Path(tempfile.gettempdir()) / "tacfoot-profiles" / str(profile["sha256"])[:16] / \
        f"{safe}.toml"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        tmp.write_text(profile["toml"])
        os.replace(tmp, path)          # another process reading it sees all or nothing
    return str(path)


def same_profile(a: dict, b: dict) -> bool:
    return a.get("sha256") == b.get("sha256")


def _profile_label(rec: dict) -> str:
    return (f"{rec.get('where') or rec.get('path') or rec.get('name')} "
            f"({rec.get('name')}, {rec.get('n_pins')} pins, sha256 {str(rec.get('sha256'))[:12]})")


def check_same_profiles(models: dict, given: dict | None = None) -> dict | None:
    """The one profile of several models (``{manifest path: profile record}``), and
    of ``given`` (a profile the user named) when there is one. SpecError naming
    both files and hashes when two differ. None for no models and no profile."""
    items = list(models.items())
    first = None
    for where, rec in items:
        rec = dict(rec, where=str(where))
        if first is None:
            first = rec
        elif not same_profile(first, rec):
            raise SpecError(f"models carry different sensor profiles: {_profile_label(first)} "
                            f"vs {_profile_label(rec)}; models of one folder must be "
                            f"trained for one sensor")
    if given is not None and first is not None and not same_profile(first, given):
        raise SpecError(f"the profile given, {_profile_label(given)}, is not the model's: "
                        f"{_profile_label(first)}; drop --profile (the model carries its "
                        f"sensor) or retrain the model for this profile")
    return first if first is not None else given


def _empty_metrics() -> dict:
    return {k: None for k in METRIC_KEYS}


@dataclass
class ModelSpec:
    kind: str
    task: str
    model: str
    classes: list
    T: int
    input_layout: str
    n_inputs: int
    profile: dict
    input_name: str = "x"
    #: the input's dimensions after the batch when more than one (a CNN's T, S, S)
    input_dims: list | None = None
    output: str = "probabilities"
    output_kind: str = "probabilities"
    uses_imu: bool = False
    crop_size: int | None = None
    metrics: dict = field(default_factory=_empty_metrics)
    int8: dict | None = None
    trained_on: dict = field(default_factory=lambda: {"data": "unknown", "recordings": [],
                                                      "split": None})
    config: dict = field(default_factory=dict)
    training: dict = field(default_factory=dict)
    params: dict = field(default_factory=dict)
    onnx: str | None = None
    sha256: dict = field(default_factory=dict)
    size_bytes: int = 0
    files: dict | None = None
    variants: dict | None = None
    variant: str = "float"
    feature_spec: int = 1
    features: dict | None = None

    def __post_init__(self) -> None:
        self.check("ModelSpec")

    # -- checks ----------------------------------------------------------------
    def check(self, where) -> None:
        """SpecError naming ``where`` and the field for a bad field."""
        def bad(f, why, v):
            raise SpecError(f"{where}: {f} {why}, got {v!r}")

        for f in ("kind", "task", "model", "input_layout", "input_name", "output", "output_kind",
                  "variant"):
            v = getattr(self, f)
            if not isinstance(v, str) or not v.strip():
                bad(f, "must be a non-empty name", v)
        if not isinstance(self.classes, list) or not all(isinstance(c, str)
                                                         for c in self.classes):
            bad("classes", "must be a list of class names", self.classes)
        for f, lo in (("T", 1), ("n_inputs", 1), ("feature_spec", 0), ("size_bytes", 0)):
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                bad(f, f"must be a whole number >= {lo}", v)
        if self.input_dims is not None:
            dims = self.input_dims
            if (not isinstance(dims, list) or not dims or not all(
                    isinstance(d, int) and not isinstance(d, bool) and d >= 1 for d in dims)
                    or _prod(dims) != self.n_inputs):
                bad("input.shape", f"must be [batch, sizes...] whose product is n_inputs "
                                   f"{self.n_inputs}", dims)
        if self.crop_size is not None and (isinstance(self.crop_size, bool)
                                           or not isinstance(self.crop_size, int)
                                           or self.crop_size < 1):
            bad("crop_size", "must be a whole number of pixels or null", self.crop_size)
        if not isinstance(self.uses_imu, bool):
            bad("uses_imu", "must be true or false", self.uses_imu)
        m = self.metrics
        if not isinstance(m, dict) or set(m) != set(METRIC_KEYS):
            extra = sorted(set(m) - set(METRIC_KEYS)) if isinstance(m, dict) else m
            hint = "".join(f"; {k!r} is now {LEGACY_KEYS[k]!r}" for k in (extra or [])
                           if isinstance(extra, list) and k in LEGACY_KEYS)
            bad("metrics", f"must have exactly the keys {list(METRIC_KEYS)}{hint}",
                sorted(m) if isinstance(m, dict) else m)
        for k in METRIC_KEYS:
            if m[k] is not None and not isinstance(m[k], dict):
                bad(f"metrics.{k}", "must be a table or null", m[k])
        p = self.profile
        if not isinstance(p, dict) or not all(k in p for k in ("name", "n_pins", "sha256",
                                                                  "toml")):
            bad("profile", "must be a table with name, n_pins, sha256 and toml (the sensor "
                           "profile's text)", p if not isinstance(p, dict) else sorted(p))
        if not isinstance(p["toml"], str):
            bad("profile.toml", "must be the profile file's text", p["toml"])
        got = profile_from_text(p["toml"], str(p["name"]), str(where))
        if got["sha256"] != p["sha256"]:
            bad("profile.sha256", f"does not match the profile's content ({got['sha256'][:12]}"
                                  f"...); the manifest was edited", str(p["sha256"])[:12])
        if got["n_pins"] != p["n_pins"]:
            bad("profile.n_pins", f"does not match the profile's [vision] n_pins "
                                  f"{got['n_pins']}", p["n_pins"])
        t = self.trained_on
        if not isinstance(t, dict) or t.get("data") not in DATA_SOURCES:
            bad("trained_on.data", f"must be one of {list(DATA_SOURCES)}",
                t.get("data") if isinstance(t, dict) else t)
        if "held_out" in t or "heldout" in t:
            bad("trained_on", "names its protocol under 'split' (not held_out)", sorted(t))
        recs = t.get("recordings", [])
        if not isinstance(recs, list):
            bad("trained_on.recordings", "must be a list", recs)
        for i, r in enumerate(recs):
            if not isinstance(r, dict) or not isinstance(r.get("path"), str):
                bad(f"trained_on.recordings[{i}]", "must be a table with a path "
                                                   "(sha256, frames)", r)
        for f in ("config", "training", "params", "sha256"):
            if not isinstance(getattr(self, f), dict):
                bad(f, "must be a table", getattr(self, f))
        for k in ("data", "test_data"):
            if isinstance(self.training.get(k), dict) and "window" in self.training[k]:
                bad(f"training.{k}.window", "is an old key; the model spec names it 'T'",
                    self.training[k]["window"])
        for k in self.params:
            if k in _CORE or k in LEGACY_KEYS:
                bad(f"params.{k}", "is a spec field or an old key variant, not a parameter", k)
        f = self.features
        if f is not None and (not isinstance(f, dict) or isinstance(f.get("version"), bool)
                              or not isinstance(f.get("version"), int)
                              or not isinstance(f.get("kind"), str)):
            bad("features", "must be a table with a whole-number version and a kind, or absent",
                f)
        if self.onnx is None and self.model != "rule":
            bad("onnx", "must be the model file's name (null only for a rule model)", None)

    # -- (de)serialise ---------------------------------------------------------
    def to_manifest(self, fmt: str = "tacfoot-model") -> dict:
        """The manifest.json document (version :data:`SPEC_VERSION`)."""
        self.check("ModelSpec")
        return {"format": fmt, "version": SPEC_VERSION, "feature_spec": self.feature_spec,
                "kind": self.kind, "task": self.task, "model": self.model,
                "classes": list(self.classes), "T": self.T, "input_layout": self.input_layout,
                "input": {"name": self.input_name,
                          "shape": [None, *(self.input_dims or [self.n_inputs])],
                          "dtype": "float32"},
                "output": self.output, "output_kind": self.output_kind,
                "uses_imu": self.uses_imu, "crop_size": self.crop_size, "onnx": self.onnx,
                "sha256": dict(self.sha256), "size_bytes": self.size_bytes,
                "files": self.files, "variants": self.variants, "variant": self.variant,
                "metrics": {k: self.metrics[k] for k in METRIC_KEYS}, "int8": self.int8,
                "profile": {k: self.profile[k] for k in ("name", "n_pins", "sha256", "toml")},
                "trained_on": self.trained_on, "config": self.config,
                "training": self.training,
                **({"features": self.features} if self.features is not None else {}),
                **self.params}

    @classmethod
    def from_manifest(cls, doc: dict, where) -> "ModelSpec":
        """The spec of a manifest document; SpecError naming ``where`` (the file) and
        the field when it does not follow the schema."""
        if not isinstance(doc, dict):
            raise SpecError(f"{where}: a manifest must be a JSON table, got {type(doc).__name__}")
        ver = doc.get("version")
        if ver != SPEC_VERSION:
            raise SpecError(f"{where}: manifest version {ver!r} is not the model spec's "
                            f"{SPEC_VERSION}; re-export the model with this tacfoot")
        for k, new in LEGACY_KEYS.items():
            if k in doc:
                raise SpecError(f"{where}: {k}: an old key; the model spec names it {new!r}")
        for k in ("kind", "T", "input", "metrics", "profile", "onnx", "sha256",
                  "feature_spec"):
            if k not in doc:
                raise SpecError(f"{where}: manifest lacks {k!r}")
        inp = doc["input"]
        shape = inp.get("shape") if isinstance(inp, dict) else None
        if (not isinstance(shape, list) or len(shape) < 2
                or not all(isinstance(d, int) and not isinstance(d, bool) for d in shape[1:])):
            raise SpecError(f"{where}: input.shape must be [batch, size, ...], got {shape!r}")
        kw = {k: doc[k] for k in ("kind", "T", "metrics", "profile", "onnx", "sha256",
                                  "feature_spec")}
        kw.update({k: doc[k] for k in ("task", "model", "classes", "input_layout", "output",
                                       "output_kind", "uses_imu", "crop_size", "int8",
                                       "trained_on", "config", "training", "size_bytes",
                                       "files", "variants", "variant", "features")
                   if k in doc})
        kw.setdefault("task", doc["kind"])
        kw.setdefault("model", "")
        kw.setdefault("classes", [])
        kw.setdefault("input_layout", "vectors")
        kw.update(n_inputs=_prod(shape[1:]), input_name=inp.get("name", "x"),
                  input_dims=list(shape[1:]) if len(shape) > 2 else None,
                  params={k: v for k, v in doc.items() if k not in _CORE})
        spec = cls.__new__(cls)
        try:
            _init_no_check(spec, kw)
        except TypeError as exc:
            raise SpecError(f"{where}: {exc}") from None
        spec.check(where)
        return spec

    # -- helpers ---------------------------------------------------------------
    @property
    def n_pins(self) -> int:
        return int(self.profile["n_pins"])

    def pipeline_profile(self, where: str = ""):
        """The model's :class:`device.profile.PipelineProfile`, parsed from its text."""
        doc = tomllib.loads(self.profile["toml"])
        return parse_pipeline_profile(doc, source=where or f"{self.profile['name']}.toml")


def _prod(dims) -> int:
    n = 1
    for d in dims:
        n *= int(d)
    return n


def _init_no_check(spec: ModelSpec, kw: dict) -> None:
    """Fill ``spec`` from ``kw`` with the dataclass defaults, without the check
    (:meth:`ModelSpec.from_manifest` checks naming the file)."""
    import dataclasses
    names = {f.name for f in dataclasses.fields(ModelSpec)}
    unknown = sorted(set(kw) - names)
    if unknown:
        raise TypeError(f"unknown spec fields {unknown}")
    for f in dataclasses.fields(ModelSpec):
        if f.name in kw:
            setattr(spec, f.name, kw[f.name])
        elif f.default is not dataclasses.MISSING:
            setattr(spec, f.name, f.default)
        elif f.default_factory is not dataclasses.MISSING:
            setattr(spec, f.name, f.default_factory())
        else:
            raise TypeError(f"missing field {f.name!r}")
