"""The typed parameters of each model kind, and the one table that names them.

A manifest's ``params`` table holds what a loader reads beyond the model spec's
common fields (:mod:`device.pi.models.spec`): a regressor's training mean and
input clip, a rule's thresholds, the localiser's layout, the fused graph's
members. Each family of models has one dataclass here, registered in
:data:`PARAMS`; :func:`family_of` says which family a spec's ``kind`` and ``model``
belong to. :func:`parse_params` builds the family's dataclass from the table and
refuses an unknown, missing or mistyped field with one line naming the file, the
field and the value. What a run measured (cost, the int8 and identity verdicts,
the training data) is not a parameter: it is the spec's ``measured`` record.
"""
from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field

from device.errors import InputError

__all__ = ["Params", "ClassifierParams", "RuleParams", "RegressorParams", "LocaliserParams",
           "FusedParams", "PARAMS", "family_of", "parse_params", "params_for"]


#: what a classifier's output holds, and the window layouts it reads
OUTPUT_KINDS = ("probabilities", "logits")
CLASSIFIER_LAYOUTS = ("vectors", "grids", "frames")


class _Bad(InputError):
    """A parameter out of its type; the spec names the file."""


@dataclass
class Params:
    """The parameters of one model family (subclasses declare them)."""

    def to_doc(self) -> dict:
        """The ``params`` table (plain JSON values)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def check_spec(self, spec, where: str) -> None:
        """The family's own rules on the spec's common fields (none by default)."""

    def check(self, where: str) -> None:
        """The spec's error (a ValueError naming ``where``, the field and the
        value) for a field out of its declared type."""
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not _fits(v, hints[f.name]):
                raise _Bad(f"{where}: params.{f.name} must be {_say(hints[f.name])}, got {v!r}")


def _fits(v, typ) -> bool:
    if isinstance(typ, types.UnionType) or typing.get_origin(typ) is typing.Union:
        return any(_fits(v, t) for t in typing.get_args(typ))
    if typ is type(None):
        return v is None
    if typ is bool:
        return isinstance(v, bool)
    if typ is int:
        return isinstance(v, int) and not isinstance(v, bool)
    if typ is float:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    origin = typing.get_origin(typ) or typ
    if origin is list:
        args = typing.get_args(typ)
        return isinstance(v, list) and (not args or all(_fits(x, args[0]) for x in v))
    return isinstance(v, origin)


def _say(typ) -> str:
    if isinstance(typ, types.UnionType) or typing.get_origin(typ) is typing.Union:
        return " or ".join(_say(t) for t in typing.get_args(typ))
    if typ is type(None):
        return "null"
    names = {bool: "true or false", int: "a whole number", float: "a finite number",
             str: "a string", dict: "a table", list: "a list"}
    origin = typing.get_origin(typ) or typ
    if origin is list and typing.get_args(typ):
        return f"a list of {_say(typing.get_args(typ)[0]).removeprefix('a ')}s"
    return names.get(origin, getattr(origin, "__name__", str(origin)))


@dataclass
class ClassifierParams(Params):
    """A learned classifier (fnn, gbt, logreg, cnn, ...): the pins its training
    left out and whether it reads the texture roughness neighbours (both also in
    the ``features`` record the runtime computes), and the output's meaning."""
    ignored_pins: list[int] = field(default_factory=list)
    roughness: bool = False
    output_doc: str | None = None

    def check_spec(self, spec, where: str) -> None:
        """At least 2 distinct class names, a window layout and an output kind a
        classifier reads."""
        c = spec.classes
        if len(c) < 2 or not all(c):
            raise _Bad(f"{where}: classes must list at least 2 class names, got {c!r}")
        twice = sorted({x for x in c if c.count(x) > 1})
        if twice:
            raise _Bad(f"{where}: classes names {twice} more than once; each output of the "
                       f"model is one class, got {c!r}")
        if spec.input_layout not in CLASSIFIER_LAYOUTS:
            raise _Bad(f"{where}: input_layout must be one of {list(CLASSIFIER_LAYOUTS)}, got "
                       f"{spec.input_layout!r}")
        if spec.output_kind not in OUTPUT_KINDS:
            raise _Bad(f"{where}: output_kind must be one of {list(OUTPUT_KINDS)}, got "
                       f"{spec.output_kind!r}")


@dataclass
class RuleParams(Params):
    """The rule baseline (:mod:`device.pi.models.rules`): its thresholds and their
    checksum, and the pins of the window it reads."""
    n_pins: int
    rule: dict
    rule_sha256: str




@dataclass
class RegressorParams(Params):
    """The pressure regressor: the training targets' mean (the value given for a
    non-finite output) and range, and the input range the runtime clips to
    (``[lo, hi]``, each one value per input; null: no clip)."""
    target_mean: float
    target_range: list[float] | None = None
    input_clip: list[list[float]] | None = None
    n_pins: int | None = None
    untracked_pins: str | None = None

    def check_spec(self, spec, where: str) -> None:
        """``input_clip``, when given, is two rows of one value per model input."""
        c = self.input_clip
        if c is not None and (len(c) != 2 or any(len(r) != spec.n_inputs for r in c)):
            raise _Bad(f"{where}: params.input_clip must be [lo, hi] of {spec.n_inputs} values "
                       f"each, got {[len(r) for r in c]} values")


@dataclass
class LocaliserParams(Params):
    """The pin localiser (:mod:`device.pi.models.localiser`): the crop it reads,
    the mean pin layout it predicts around and the plausibility ranges of its input."""
    n_pins: int
    size: int
    crop_factor: float
    mean_layout_norm: list[list[float]]
    fill_range: list[float] = field(default_factory=lambda: [0.0, 1.0])
    fill_grid: int = 0
    fill_cells_range: list[list[float]] = field(default_factory=lambda: [[0.0], [1.0]])
    max_dev_norm: float | None = None
    weights_dtype: str = "float32"
    vision_params: dict = field(default_factory=dict)
    output_doc: str | None = None


@dataclass
class FusedParams(Params):
    """The fused graph (:mod:`device.pi.models.fused`): one row per member model
    (task, file, hash, input, output) and the graphs cut down to some members."""
    members: list[dict]
    subsets: list[dict] = field(default_factory=list)


#: the one table of model families and their parameters
PARAMS: dict[str, type[Params]] = {
    "classifier": ClassifierParams,
    "rule": RuleParams,
    "regressor": RegressorParams,
    "localiser": LocaliserParams,
    "fused": FusedParams,
}
#: the family of a spec's ``kind`` (a rule ``model`` is the rule family whatever
#: its task); any other kind is a classifier
_KIND_FAMILY = {"pressure": "regressor", "localiser": "localiser", "fused": "fused"}


def family_of(kind: str, model: str) -> str:
    """The :data:`PARAMS` family of a spec's ``kind`` and ``model``."""
    if model == "rule":
        return "rule"
    return _KIND_FAMILY.get(kind, "classifier")


def field_names(family: str) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(PARAMS[family]))


def parse_params(doc, kind: str, model: str, where: str) -> Params:
    """The family's parameters from a manifest's ``params`` table; a ValueError
    naming ``where``, the field and the value for an unknown, missing or mistyped
    one."""
    cls = PARAMS[family_of(kind, model)]
    if not isinstance(doc, dict):
        raise _Bad(f"{where}: params must be a table, got {doc!r}")
    names = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(doc) - set(names))
    if unknown:
        raise _Bad(f"{where}: params.{unknown[0]} is not a parameter of a "
                   f"{family_of(kind, model)} model (it takes {sorted(names)}), got "
                   f"{doc[unknown[0]]!r}")
    for n, f in names.items():
        if n not in doc and f.default is dataclasses.MISSING \
                and f.default_factory is dataclasses.MISSING:
            raise _Bad(f"{where}: params.{n} is required for a {family_of(kind, model)} "
                       f"model, got nothing")
    p = cls(**doc)
    p.check(where)
    return p


def params_for(kind: str, model: str, values: dict, where: str = "params") -> Params:
    """The family's parameters from ``values`` (a writer's keyword values), checked."""
    return parse_params(dict(values), kind, model, where)
