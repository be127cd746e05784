"""The model spec: the one schema of a model folder's manifest.

The manifest files are read and written by :mod:`device.pi.models.manifest` only,
the one module that names them. Every writer (``host train``, the CNN, the localiser,
the pressure model, the fuser, the shipped-model builder) builds a
:class:`ModelSpec`, fills in what it measured and writes it once with
:func:`write_spec` (:func:`write_variant_specs` for both variants); every reader
gets a :class:`ModelSpec` from :func:`read_spec`, whose errors are one line naming
the file, the field and the value. A loaded model carries its spec
(:class:`device.pi.models.artefact.Model`).

A spec holds:

* what the model decides: ``kind`` (the folder's task: surface, texture, slip,
  pressure, localiser, fused), ``task``, ``model`` (the estimator: fnn, ridge, rule,
  cnn, ...) and ``classes`` (empty for a regressor);
* what it reads and gives: ``T`` (frames per window, required), ``input_layout``,
  ``n_inputs``, ``input_name``, ``output``, ``output_kind``, ``uses_imu`` and
  ``crop_size`` (the image side of a frame- or image-reading model, else None);
* ``metrics``: exactly the keys ``train``, ``test`` and ``cv``, each a table or null;
* ``profile``: the sensor the model was trained for (``name``, ``n_pins``,
  ``sha256`` of its parsed content, :func:`profile_hash`, and ``toml``, its text);
* ``config``: the training config that made the model, and ``training``: the run's
  record (data summary, hyperparameters, fit times, export checks);
* the artefact: ``onnx``, ``sha256``, ``size_bytes``, ``files``, ``variants``,
  ``variant`` and ``feature_spec``; ``features``, for a graph that reads window
  features, the record of what the runtime computes (:mod:`device.pi.models.winfeat`);
* ``params``: the kind's typed parameters, one dataclass per family of models
  registered in :data:`device.pi.models.params.PARAMS`;
* ``measured``: what the run measured (:class:`Measured`: ``trained_on``, the
  ``int8`` and ``identity`` verdicts, ``cost_per_decision``), never a parameter.

Version 3 is this schema. A version 2 manifest (parameters and measured facts as
top-level keys) is read into it; the key variants of version 1 (``window`` for
``T``, ``heldout`` for ``test``, a profile given by name only) are refused.
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
from device.pi.models.params import PARAMS, Params, family_of, field_names, parse_params
from device.profile import PROFILE_DIR, builtin_toml, parse_pipeline_profile
from device.errors import TacfootError

__all__ = ["ModelSpec", "Measured", "SpecError", "ModelError", "SPEC_VERSION", "FORMAT",
           "MAX_T", "METRIC_KEYS", "DATA_SOURCES", "profile_record", "profile_hash", "profile_from_text",
           "same_profile", "check_same_profiles", "profile_source"]

#: the manifest version this schema writes (version 2 is read as well)
SPEC_VERSION = 3
FORMAT = "tacfoot-model"
#: the longest window a model may read, frames (8 s at 120 fps)
MAX_T = 1000
#: the one key each for training, held-out test and cross-validation metrics
METRIC_KEYS = ("train", "test", "cv")
DATA_SOURCES = ("real", "simulated", "real+simulated", "unknown")
#: keys of version 1 manifests that have one name now
LEGACY_KEYS = {"window": "T", "heldout": "metrics.test", "held_out": "metrics.test",
               "test_data": "training.test_data"}
_CORE = ("format", "version", "feature_spec", "kind", "task", "model", "classes", "T",
         "input_layout", "input", "output", "output_kind", "uses_imu", "crop_size", "onnx",
         "sha256", "size_bytes", "files", "variants", "variant", "metrics", "profile",
         "config", "training", "features", "params", "measured")


class SpecError(TacfootError, ValueError):
    """A manifest does not follow the model spec; the message names the file and
    the field."""


class ModelError(SpecError):
    """A model artefact cannot be used; the message names the file."""


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


def _unknown_data() -> dict:
    return {"data": "unknown", "recordings": [], "split": None}


@dataclass
class Measured:
    """What a run measured of the model, one record apart from its parameters:
    ``trained_on`` (the training data), ``int8`` (the int8 check's verdict),
    ``identity`` (the recording-identity check's verdict, :mod:`host.learn.identity`)
    and ``cost_per_decision`` (timed at train time); null where not measured."""
    trained_on: dict = field(default_factory=_unknown_data)
    int8: dict | None = None
    identity: dict | None = None
    cost_per_decision: dict | None = None

    def to_doc(self) -> dict:
        return {k: getattr(self, k) for k in MEASURED_KEYS}

    def check(self, where) -> None:
        def bad(f, why, v):
            raise SpecError(f"{where}: measured.{f} {why}, got {v!r}")

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
        for f in ("int8", "identity", "cost_per_decision"):
            if getattr(self, f) is not None and not isinstance(getattr(self, f), dict):
                bad(f, "must be a table or null", getattr(self, f))

    @classmethod
    def from_doc(cls, doc, where) -> "Measured":
        if not isinstance(doc, dict):
            raise SpecError(f"{where}: measured must be a table, got {doc!r}")
        unknown = sorted(set(doc) - set(MEASURED_KEYS))
        if unknown:
            raise SpecError(f"{where}: measured.{unknown[0]} is not a measured fact (they are "
                            f"{list(MEASURED_KEYS)}), got {doc[unknown[0]]!r}")
        m = cls(**doc)
        m.check(where)
        return m


MEASURED_KEYS = ("trained_on", "int8", "identity", "cost_per_decision")


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
    config: dict = field(default_factory=dict)
    training: dict = field(default_factory=dict)
    #: the kind's typed parameters (:mod:`device.pi.models.params`); a dict is parsed
    params: Params | dict = field(default_factory=dict)
    #: what the run measured (:class:`Measured`); a dict is parsed
    measured: Measured | dict = field(default_factory=Measured)
    onnx: str | None = None
    sha256: dict = field(default_factory=dict)
    size_bytes: int = 0
    files: dict | None = None
    variants: dict | None = None
    variant: str = "float"
    feature_spec: int = 1
    features: dict | None = None

    def __post_init__(self) -> None:
        self._typed("ModelSpec")
        self.check("ModelSpec")

    def _typed(self, where) -> None:
        """``params`` and ``measured`` given as tables parsed into their records."""
        for f in ("kind", "model"):
            if not isinstance(getattr(self, f), str) or not getattr(self, f).strip():
                raise SpecError(f"{where}: {f} must be a non-empty name, got "
                                f"{getattr(self, f)!r}")
        if not isinstance(self.params, Params):
            try:
                self.params = parse_params(self.params, self.kind, self.model, str(where))
            except TypeError as exc:
                raise SpecError(f"{where}: params: {exc}") from None
            except ValueError as exc:
                raise SpecError(str(exc)) from None
        if not isinstance(self.measured, Measured):
            self.measured = Measured.from_doc(self.measured, where)

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
        for f, lo, hi, what in (("T", 1, MAX_T, f"of frames in [1, {MAX_T}]"),
                                ("n_inputs", 1, 1 << 30, ">= 1"),
                                ("feature_spec", 0, 1 << 30, ">= 0"),
                                ("size_bytes", 0, 1 << 40, ">= 0")):
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                bad(f, f"must be a whole number {what}", v)
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
        self._check_profile(where, bad)
        if not isinstance(self.measured, Measured) or not isinstance(self.params, Params):
            self._typed(where)
        self.measured.check(where)
        if not isinstance(self.params, PARAMS[family_of(self.kind, self.model)]):
            bad("params", f"must be the parameters of a {family_of(self.kind, self.model)} "
                          f"model", type(self.params).__name__)
        try:
            self.params.check(str(where))
            self.params.check_spec(self, str(where))
        except ValueError as exc:
            raise SpecError(str(exc)) from None
        sha = self.sha256
        if not isinstance(sha, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                for k, v in sha.items()):
            bad("sha256", "must map file names to SHA-256 hex digests", sha)
        for f in ("config", "training"):
            if not isinstance(getattr(self, f), dict):
                bad(f, "must be a table", getattr(self, f))
        for k in ("data", "test_data"):
            if isinstance(self.training.get(k), dict) and "window" in self.training[k]:
                bad(f"training.{k}.window", "is an old key; the model spec names it 'T'",
                    self.training[k]["window"])
        f = self.features
        if f is not None and (not isinstance(f, dict) or isinstance(f.get("version"), bool)
                              or not isinstance(f.get("version"), int)
                              or not isinstance(f.get("kind"), str)):
            bad("features", "must be a table with a whole-number version and a kind, or absent",
                f)
        if not (isinstance(self.onnx, str) and self.onnx.strip()) and \
                not (self.onnx is None and self.model == "rule"):
            bad("onnx", "must be the model file's name (null only for a rule model)", self.onnx)

    def _check_profile(self, where, bad) -> None:
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

    # -- (de)serialise ---------------------------------------------------------
    def to_manifest(self, fmt: str = FORMAT) -> dict:
        """The manifest document (version :data:`SPEC_VERSION`)."""
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
                "metrics": {k: self.metrics[k] for k in METRIC_KEYS},
                "profile": {k: self.profile[k] for k in ("name", "n_pins", "sha256", "toml")},
                "config": self.config, "training": self.training,
                **({"features": self.features} if self.features is not None else {}),
                "params": self.params.to_doc(), "measured": self.measured.to_doc()}

    @classmethod
    def from_manifest(cls, doc: dict, where) -> "ModelSpec":
        """The spec of a manifest document; SpecError naming ``where`` (the file), the
        field and the value when it does not follow the schema. A version 2
        manifest (params and measured facts as top-level keys) is read as well."""
        if not isinstance(doc, dict):
            raise SpecError(f"{where}: a manifest must be a JSON table, got {type(doc).__name__}")
        ver = doc.get("version")
        if ver == 2:
            doc = _from_version_2(doc)
        elif ver != SPEC_VERSION:
            raise SpecError(f"{where}: manifest version {ver!r} is not the model spec's "
                            f"{SPEC_VERSION}; re-export the model with this tacfoot")
        for k, new in LEGACY_KEYS.items():
            if k in doc:
                raise SpecError(f"{where}: {k}: an old key; the model spec names it {new!r}")
        unknown = sorted(set(doc) - set(_CORE))
        if unknown:
            raise SpecError(f"{where}: {unknown[0]} is not a field of the model spec (a "
                            f"parameter goes under 'params'), got {doc[unknown[0]]!r}")
        for k in _REQUIRED:
            if k not in doc:
                raise SpecError(f"{where}: manifest lacks {k!r}")
        inp = doc["input"]
        shape = inp.get("shape") if isinstance(inp, dict) else None
        if (not isinstance(shape, list) or len(shape) < 2
                or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 1
                           for d in shape[1:])):
            raise SpecError(f"{where}: input.shape must be [batch, size, ...] with whole-number "
                            f"sizes, got {shape if isinstance(inp, dict) else inp!r}")
        kw = {k: doc[k] for k in _CORE if k in doc and k not in ("format", "version", "input")}
        kw.update(n_inputs=_prod(shape[1:]), input_name=inp.get("name", "x"),
                  input_dims=list(shape[1:]) if len(shape) > 2 else None)
        spec = cls.__new__(cls)
        try:
            _init_no_check(spec, kw)
        except TypeError as exc:
            raise SpecError(f"{where}: {exc}") from None
        spec._typed(where)
        spec.check(where)
        return spec

    # -- helpers ---------------------------------------------------------------
    @property
    def n_pins(self) -> int:
        return int(self.profile["n_pins"])

    @property
    def family(self) -> str:
        """The :data:`device.pi.models.params.PARAMS` family of the model."""
        return family_of(self.kind, self.model)

    def pipeline_profile(self, where: str = ""):
        """The model's :class:`device.profile.PipelineProfile`, parsed from its text."""
        doc = tomllib.loads(self.profile["toml"])
        return parse_pipeline_profile(doc, source=where or f"{self.profile['name']}.toml")


_REQUIRED = ("kind", "task", "model", "T", "input", "metrics", "profile", "onnx", "sha256",
             "feature_spec")
#: keys of a version 2 manifest that are measured facts now
_V2_MEASURED = ("trained_on", "int8", "cost_per_decision")


def _from_version_2(doc: dict) -> dict:
    """A version 2 manifest in this version's shape: its top-level parameters under
    ``params`` (the keys its family declares; any other under ``training``), its
    measured facts under ``measured``, ``task`` and ``model`` defaulting to ``kind``."""
    out = {k: v for k, v in doc.items() if k in _CORE or k in LEGACY_KEYS}
    kind = doc.get("kind")
    out.setdefault("task", kind)
    out.setdefault("model", kind)
    fam = family_of(str(kind), str(out["model"]))
    names = set(field_names(fam))
    out["params"] = {k: v for k, v in doc.items() if k in names and k not in _CORE}
    out["measured"] = {k: doc[k] for k in _V2_MEASURED if k in doc}
    rest = {k: v for k, v in doc.items()
            if k not in _CORE and k not in LEGACY_KEYS and k not in names
            and k not in _V2_MEASURED}
    if rest:
        out["training"] = {**(doc.get("training") or {}), **rest} \
            if isinstance(doc.get("training", {}), dict) else doc.get("training")
    out["version"] = SPEC_VERSION
    return out


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
