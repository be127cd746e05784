"""One ONNX graph for the per-frame models: built on the host from the signed
artefacts of a models folder, run by the leg once per frame.

The leg runs surface, texture, slip and pressure on every frame. Four ONNX Runtime
sessions cost more in the loop than their sum alone (each session's caches are
cold after the marker pipeline), so :func:`fuse_models` puts them side by side in
one graph: each model's nodes, initialisers, input and output renamed with its
task as prefix (``surface/x`` -> ``surface/probabilities``), no edge between them.
Members that read the same window encoding (surface and slip: T frames of vectors
with the IMU) share one input, and a node that repeats another (the same features
computed from it) is computed once. Only the output the runtime reads is kept (a
classifier's probabilities, the regressor's value), and only the nodes it needs, so
the label branch is not in the graph (ONNX Runtime runs every node of a graph, read
or not).

The fused graph is written as a model folder, ``MODELS/fused``, beside the
artefacts it was built from::

    fused/fused.onnx           the members' default files (int8 where quantised), fused
    fused/<manifest>           a model spec (kind "fused") naming the file and its
                               SHA-256, and in ``members`` each member's task,
                               manifest, ONNX file and that file's SHA-256
    fused/fused.float.onnx     the same for the float variant (when the members
    fused/manifest.float.json  have float files other than their default)
    fused/fused.notexture.onnx the same graph without the texture member (and
                               fused.float.notexture.onnx), listed in the manifest's
                               ``subsets`` and ``sha256``: the leg runs it on the
                               frames with no texture due (out of contact)

so ``host deploy`` signs it with the others and ``models-set.json`` covers it. The
individual artefacts stay the unit of training and signing: the leg loads them
as before, and uses the fused graph only when every member it records is a model
it loaded, file hash for file hash (:mod:`device.pi.models.fused`).

``python -m host.learn.fuse MODELS`` (re)builds it (``make models`` does, for the
shipped ones); ``host deploy`` builds it into each release from the models it
ships, and ``host bench runtime`` runs a linked copy of the models with it
(:func:`fused_copy`).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from device.pi.models.artefact import ModelError, checked_model_file, sha256_file
from device.pi.models.manifest import FLOAT_MANIFEST, MANIFEST, manifest_for, read_spec
from device.pi.models.fused import FUSED_DIR, FUSED_KIND, FUSED_TASKS
from device.pi.models.spec import ModelSpec, check_same_profiles
from host.data.dataset import atomic_write

__all__ = ["fuse_models", "fused_graph", "fused_copy", "FuseError"]

#: (ONNX file, manifest) of each pick in the fused folder, as
#: :func:`device.pi.models.manifest.manifest_for` picks the members' manifests
FUSED_FILES = {"int8": ("fused.onnx", MANIFEST),
               "float": ("fused.float.onnx", FLOAT_MANIFEST)}


#: the member the leg runs on some frames only (a texture is decided in contact):
#: the fused folder also holds the graph without it, for the frames it is not due
SKIPPED_TASK = "texture"


class FuseError(ModelError):
    """The models cannot be fused; the message names the file."""


def _members(models_dir: Path, variant: str) -> list[dict]:
    """The ONNX models of ``models_dir`` the leg runs per frame, as loaded for
    ``variant``: task, manifest path, spec and ONNX file."""
    out = []
    for task in FUSED_TASKS:
        folder = models_dir / task
        if not folder.is_dir():
            continue
        mf = manifest_for(folder, variant)
        if mf.is_dir():
            continue                              # no manifest: the leg refuses it anyway
        spec, _ = read_spec(mf)
        if spec.model == "rule" or spec.onnx is None:
            continue                              # a rule has no graph
        onnx = checked_model_file(folder, spec.onnx, spec.sha256, mf)   # its hash
        out.append({"task": task, "manifest": mf, "spec": spec, "onnx": onnx})
    return out


def _output_name(graph, spec, task: str) -> str:
    """The output the runtime reads: a classifier's manifest ``output`` (default
    probabilities, else the last), the regressor's first."""
    names = [o.name for o in graph.output]
    if task == "pressure":
        return names[0]
    want = spec.output
    return want if want in names else names[-1]


def fused_graph(members: list[dict]):
    """(onnx.ModelProto, member records) of ``members`` (task, spec, onnx path) side
    by side: names prefixed with ``task/``, only the read output kept, the opsets
    raised to the highest among them (onnx.version_converter)."""
    import onnx
    from onnx import compose, helper, version_converter

    protos = []
    for m in members:
        try:
            protos.append(onnx.load(str(m["onnx"])))
        except Exception as exc:       # protobuf's own errors
            raise FuseError(f"{m['onnx']}: not an ONNX model ({exc})") from None
    opsets: dict[str, int] = {}
    for p in protos:
        for o in p.opset_import:
            opsets[o.domain] = max(opsets.get(o.domain, 0), o.version)
    nodes, inits, inputs, outputs, vinfo, recs = [], [], [], [], [], []
    ir = max(p.ir_version for p in protos)
    first_of: dict[tuple, str] = {}             # window encoding -> the input that reads it
    for m, p in zip(members, protos):
        have = {o.domain: o.version for o in p.opset_import}
        if have.get("", opsets.get("", 0)) != opsets.get("", 0):
            try:
                p = version_converter.convert_version(p, opsets[""])
            except Exception as exc:       # the converter's own errors
                raise FuseError(f"{m['onnx']}: cannot raise its opset to {opsets['']} to fuse "
                                f"it ({exc})") from None
        keep = _output_name(p.graph, m["spec"], m["task"])
        prefix = f"{m['task']}/"
        p = compose.add_prefix(p, prefix)
        g = p.graph
        if len(g.input) != 1:
            raise FuseError(f"{m['onnx']}: has {len(g.input)} inputs; a member reads one window")
        name = g.input[0].name
        enc = _encoding(m)
        if enc is not None and enc in first_of:
            # the same window, encoded the same way, as an earlier member: read its input
            for n in g.node:
                n.input[:] = [first_of[enc] if i == name else i for i in n.input]
            name = first_of[enc]
        else:
            inputs += list(g.input)
            if enc is not None:
                first_of[enc] = name
        nodes += list(g.node)
        inits += list(g.initializer)
        outputs += [o for o in g.output if o.name == prefix + keep]
        vinfo += list(g.value_info)
        recs.append({"task": m["task"], "input": name, "output": prefix + keep})
    nodes = _shared_nodes(nodes, inits, {o.name for o in outputs})
    model = _graph_for(nodes, inputs, outputs, inits, vinfo,
                       [helper.make_opsetid(d, v) for d, v in sorted(opsets.items())], ir)
    return onnx.shape_inference.infer_shapes(model), recs


def _encoding(member: dict) -> tuple | None:
    """What a classifier member reads (T, input layout, IMU or not, input shape, and
    the window features the leg computes for it, when its graph reads them): members
    that read the same share one input of the fused graph, as the leg gives them the
    same window encoding (or the same features, computed once). None for the
    regressor (its input is clipped to its own training range)."""
    spec = member["spec"]
    if member["task"] == "pressure":
        return None
    return (spec.T, spec.input_layout, spec.uses_imu,
            json.dumps([None, *(spec.input_dims or [spec.n_inputs])]),
            json.dumps(spec.features, sort_keys=True))


def _shared_nodes(nodes, inits, outputs: set) -> list:
    """``nodes`` with each node that repeats an earlier one (the same operator and
    attributes on the same inputs, constants compared by value) left out and its
    outputs read from the earlier node's: members that compute the same features
    from one input compute them once, value for value. A node that gives a graph
    output (``outputs``) is kept. A graph with control flow (a node holding a
    subgraph, which may read any outer name) is left as it is."""
    import hashlib

    import onnx

    if any(a.type in (onnx.AttributeProto.GRAPH, onnx.AttributeProto.GRAPHS)
           for n in nodes for a in n.attribute):
        return list(nodes)
    consts = {}
    for t in inits:
        c = onnx.TensorProto()
        c.CopyFrom(t)
        c.name = ""
        consts[t.name] = ("const", hashlib.sha256(c.SerializeToString()).hexdigest())
    same: dict[str, str] = {}                   # a left-out output -> the earlier one
    seen: dict[tuple, object] = {}
    keep = []
    for n in nodes:
        n.input[:] = [same.get(i, i) for i in n.input]
        key = (n.domain, n.op_type, tuple(a.SerializeToString() for a in n.attribute),
               tuple(consts.get(i, i) for i in n.input))
        first = seen.get(key)
        if first is not None and not outputs.intersection(n.output) \
                and len(first.output) == len(n.output):
            same.update(zip(n.output, first.output))
            continue
        seen.setdefault(key, n)
        keep.append(n)
    return keep


def _graph_for(nodes, inputs, outputs, inits, vinfo, opsets, ir: int):
    """A checked model of the nodes that ``outputs`` need (walked back from them),
    and of the inputs, initialisers and value infos those nodes read: a node whose
    outputs nothing reads (a classifier's label branch) is not in it, as ONNX
    Runtime would run it on every call."""
    import onnx
    from onnx import helper

    need = {o.name for o in outputs}
    keep = []
    for n in reversed(list(nodes)):
        if any(o in need for o in n.output):
            keep.append(n)
            need.update(i for i in n.input if i)
    graph = helper.make_graph(keep[::-1], "tacfoot-fused",
                              [i for i in inputs if i.name in need], list(outputs),
                              initializer=[i for i in inits if i.name in need],
                              value_info=[v for v in vinfo if v.name in need])
    model = helper.make_model(graph, opset_imports=opsets,
                              producer_name="tacfoot host.learn.fuse")
    model.ir_version = ir
    onnx.checker.check_model(model)
    return model


def subset_graph(model, tasks):
    """The fused ``model`` cut down to the members ``tasks``: the same nodes, so
    each output is the full graph's, value for value."""
    g = model.graph
    prefixes = tuple(f"{t}/" for t in tasks)
    return _graph_for(g.node, g.input, [o for o in g.output if o.name.startswith(prefixes)],
                      g.initializer, g.value_info, list(model.opset_import), model.ir_version)


def _trained_on(specs: list) -> dict:
    """The members' training data as one record: their data kind (real+simulated
    when they differ) and their recordings."""
    kinds = {s.measured.trained_on.get("data", "unknown") for s in specs}
    data = kinds.pop() if len(kinds) == 1 else (
        "real+simulated" if kinds <= {"real", "simulated", "real+simulated"} else "unknown")
    recs, seen = [], set()
    for s in specs:
        for r in s.measured.trained_on.get("recordings", []):
            if r.get("path") not in seen:
                seen.add(r.get("path"))
                recs.append(r)
    return {"data": data, "recordings": recs,
            "split": "fused from the member models (see members; each has its own)"}


def _spec(models_dir: Path, members: list[dict], recs: list[dict], onnx_name: str,
          sha: str, size: int, subsets: list[dict], subset_sha: dict) -> ModelSpec:
    specs = {str(m["manifest"]): m["spec"] for m in members}
    profile = check_same_profiles({w: s.profile for w, s in specs.items()})
    n = sum(s.n_inputs for s in specs.values())
    rows = []
    for m, r in zip(members, recs):
        rows.append({**r, "manifest": str(m["manifest"].relative_to(models_dir)),
                     "onnx": m["spec"].onnx, "sha256": sha256_file(m["onnx"]),
                     "n_inputs": specs[str(m["manifest"])].n_inputs,
                     "T": specs[str(m["manifest"])].T})
    return ModelSpec(kind=FUSED_KIND, task=FUSED_KIND, model="fused", classes=[],
                     T=max(s.T for s in specs.values()), input_layout="vectors", n_inputs=n,
                     profile={k: profile[k] for k in ("name", "n_pins", "sha256", "toml")},
                     input_name=recs[0]["input"], output=recs[0]["output"],
                     output_kind="fused",
                     measured={"trained_on": _trained_on(list(specs.values()))},
                     onnx=onnx_name, sha256={onnx_name: sha, **subset_sha}, size_bytes=size,
                     variant="int8" if any(m["spec"].variant == "int8" for m in members)
                     else "float", params={"members": rows, "subsets": subsets})


def fuse_models(models_dir: Path | str) -> dict:
    """Build ``models_dir/fused`` from the per-frame models of ``models_dir`` (see
    the module doc); a stale one is replaced, and removed when fewer than two
    models have a graph. Returns {variant: manifest path}. FuseError naming the
    file when a member cannot be fused."""
    import shutil

    d = Path(models_dir)
    out = d / FUSED_DIR
    built: dict[str, Path] = {}
    seen: dict[tuple, str] = {}
    plans = {}
    for variant in ("int8", "float"):
        members = _members(d, variant)
        if len(members) < 2:
            continue
        key = tuple(str(m["onnx"]) for m in members)
        if key in seen:
            continue                            # the float pick is the default's files
        seen[key] = variant
        plans[variant] = members
    if out.exists():
        shutil.rmtree(out)                      # stale: rebuilt from the members as they are
    from device.pi.models.manifest import write_spec

    for variant, members in plans.items():
        model, recs = fused_graph(members)
        out.mkdir(parents=True, exist_ok=True)
        data = model.SerializeToString()
        name, manifest = FUSED_FILES[variant]
        atomic_write(out / name, lambda fh: fh.write(data))
        subsets, subset_sha = [], {}
        tasks = [r["task"] for r in recs]
        if SKIPPED_TASK in tasks and len(tasks) > 1:
            rest = [t for t in tasks if t != SKIPPED_TASK]
            sub = subset_graph(model, rest).SerializeToString()
            sname = name.replace(".onnx", f".no{SKIPPED_TASK}.onnx")
            atomic_write(out / sname, lambda fh: fh.write(sub))
            subsets.append({"tasks": rest, "onnx": sname})
            subset_sha[sname] = sha256_file(out / sname)
        spec = _spec(d, members, recs, name, sha256_file(out / name), len(data), subsets,
                     subset_sha)
        built[variant] = write_spec(out, spec, manifest)
    return built


def fused_copy(models_dir: Path | str, out: Path | str) -> Path:
    """``out/models``: links to every model folder of ``models_dir`` and a fused
    graph built from them, so the leg runs them as a deploy ships them, without
    writing into ``models_dir`` (``host bench runtime``)."""
    src, dst = Path(models_dir).resolve(), Path(out) / "models"
    dst.mkdir(parents=True)
    for f in sorted(src.iterdir()):
        if f.is_dir() and f.name != FUSED_DIR and not f.name.startswith("."):
            (dst / f.name).symlink_to(f, target_is_directory=True)
    fuse_models(dst)
    return dst


def main(argv=None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 1:
        print("usage: python -m host.learn.fuse MODELS_FOLDER", file=sys.stderr)
        return 2
    try:
        built = fuse_models(args[0])
    except (ModelError, OSError) as exc:
        print(f"host.learn.fuse: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({v: str(p) for v, p in built.items()}))
    return 0


if __name__ == "__main__":                      # pragma: no cover
    raise SystemExit(main())
