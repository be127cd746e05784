"""The per-frame models as one ONNX Runtime call: the fused graph ``MODELS/fused``
that ``host.learn.fuse`` builds from the individual artefacts.

The leg loads and checks every model as before; :func:`load_fused` then loads the
fused graph for the same variant and uses it only when its members are exactly the
ONNX models the leg loaded (each member's task and the SHA-256 of the ONNX file it
was built from, against the file the loaded model's manifest names), and when each
member's input and output have the sizes the loaded model has. Anything else (no
fused folder, a member retrained or swapped since the fuse, a bad fused artefact)
leaves the individual sessions in charge, with one line saying why.

:meth:`FusedModels.run` is then the frame's one model call: each member that is to
decide this frame gets its input written the way its own ``predict_window`` writes
it (a classifier's window encoding as it is, or the window features its graph reads,
computed for every such member in one call, :mod:`device.pi.models.winfeat`; the
regressor's input cleaned and clipped),
the graph runs once over I/O-bound buffers, and each member's output goes through
its own post-processing (probabilities cleaned, the regressor's fallback and fault
flag). The results are those of the members' ``predict_window``, value for value.
Two classifiers that read the same window encoding share one input of the graph,
written once (the loaded models must read it the same way, else the graph is not
used). A frame whose members are all in one of the manifest's ``subsets`` (the graph
without texture, for frames out of contact) runs that smaller graph instead.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from device.pi.models.artefact import (ModelError, checked_model_file, load_model, model_file,
                                       ort_session)
from device.pi.models.manifest import MANIFEST, manifest_for
from device.pi.models.signature import SignatureError
from device.pi.models.winfeat import WindowFeatures

#: the fused graph's folder inside the models folder, and its manifest's kind
FUSED_DIR = "fused"
FUSED_KIND = "fused"
#: the per-frame tasks a fused graph may hold, in its order
FUSED_TASKS = ("surface", "texture", "slip", "pressure")


class MultiBoundRun:
    """One session run over fixed input buffers ``inputs`` ({name: array}): the
    first call runs it the plain way, then inputs and outputs are bound (ONNX
    Runtime I/O binding) to the buffers and to preallocated outputs shaped as the
    first call's, so later calls copy nothing. Returns {output name: array} (the
    bound buffers: read them before the next call)."""

    def __init__(self, session, inputs: dict, outputs: list[str]):
        self.session = session
        self.inputs = inputs
        self.outputs = list(outputs)
        self._binding = None
        self._out: dict = {}

    def __call__(self) -> dict:
        if self._binding:
            self.session.run_with_iobinding(self._binding)
            return self._out
        got = self.session.run(self.outputs, self.inputs)
        res = {n: np.asarray(a) for n, a in zip(self.outputs, got)}
        if self._binding is None:
            self._bind(res)
        return res

    def _bind(self, first: dict) -> None:
        try:
            b = self.session.io_binding()
            for name, x in self.inputs.items():
                b.bind_cpu_input(name, x)
            for name in self.outputs:
                o = np.empty(first[name].shape, first[name].dtype)
                b.bind_output(name, "cpu", 0, o.dtype, list(o.shape), o.ctypes.data)
                self._out[name] = o
        except Exception:              # a session without I/O binding
            self._binding = False
            return
        self._binding = b


class FusedModels:
    """The loaded fused graph and its members ({task: Classifier or Regressor}), with
    ``subsets`` ([(tasks, session)]: the same graph cut down to those members, for
    the frames that need no other)."""

    def __init__(self, model, members: dict, rows: list[dict], subsets=()):
        self.model = model
        self.members = members
        self.tasks = tuple(r["task"] for r in rows)
        self._in = {}
        self._out_name = {}
        bufs: dict = {}
        #: {task: the earlier member whose input it reads} (the same window encoding)
        self._reads = {}
        for r in rows:
            mod = members[r["task"]]
            if r["input"] in bufs:
                self._reads[r["task"]] = bufs[r["input"]][0]
            else:
                bufs[r["input"]] = (r["task"], np.zeros(mod._x.shape, np.float32))
            self._in[r["task"]] = bufs[r["input"]][1]
            self._out_name[r["task"]] = r["output"]
        by_task = {r["task"]: r for r in rows}
        # the members whose graph reads window features (features version 2): one
        # call computes them all for a frame, each into its input buffer
        specs, outs = [], []
        self._feat_index = {}
        for t in self.tasks:
            spec = getattr(members[t], "features", None)
            if spec is not None and t not in self._reads:
                self._feat_index[t] = len(specs)
                specs.append(spec)
                outs.append(self._in[t])
        self._features = WindowFeatures(specs, outs) if specs else None

        def runner(session, tasks):
            names = {i.name for i in session.get_inputs()}
            return MultiBoundRun(session, {by_task[t]["input"]: self._in[t] for t in tasks
                                           if by_task[t]["input"] in names},
                                 [by_task[t]["output"] for t in tasks])
        self._runner = runner(model.session, self.tasks)
        # (tasks, members in order, runner), fewest tasks first: a frame runs the first
        # that covers it
        self._subsets = []
        for t, sess in sorted(subsets, key=lambda ts: len(ts[0])):
            members = tuple(x for x in self.tasks if x in t)
            self._subsets.append((frozenset(t), members, runner(sess, list(members))))
        self._bad_input = dict.fromkeys(self.tasks, False)
        #: how many frames ran each graph: {members of the graph run: count}
        self.graph_runs: dict[tuple, int] = {}

    @property
    def shared_inputs(self) -> dict:
        """{task: the earlier member whose graph input it reads} (the same window
        encoding, written once a frame)."""
        return dict(self._reads)

    def _runner_for(self, tasks) -> MultiBoundRun:
        for have, members, run in self._subsets:
            if have.issuperset(tasks):
                self.graph_runs[members] = self.graph_runs.get(members, 0) + 1
                return run
        self.graph_runs[self.tasks] = self.graph_runs.get(self.tasks, 0) + 1
        return self._runner

    def run(self, windows: dict) -> dict:
        """{task: the result its model's ``predict_window`` gives} for the members
        in ``windows`` ({task: full window of the member's T}), from one run of the
        graph (the smallest of its subsets that holds them). Members not asked for
        keep their last input; their outputs are not read."""
        which, feat_windows = [], []
        for task, w in windows.items():
            mod = self.members[task]
            first = self._reads.get(task)
            if first is not None and first in windows:
                if windows[first] is not w:
                    raise ModelError(f"{self.model.path}: {task} and {first} read one input "
                                     f"of the fused graph; give them the same window")
                continue                   # its input is written: the same window
            if task == "pressure":
                self._bad_input[task] = mod.prepare_window(w, self._in[task])
            elif task in self._feat_index:
                if w.T != mod.T:
                    raise ModelError(f"{mod.onnx_path}: the model sees T={mod.T} frames, the "
                                     f"window holds {w.T}")
                which.append(self._feat_index[task])
                feat_windows.append(w)
            else:
                mod.fill_window(w, self._in[task])
        if which:
            self._features.compute(feat_windows, which)
        try:
            outs = self._runner_for(windows)()
        except Exception as exc:      # onnxruntime's own exception types
            raise ModelError(f"{self.model.path}: ONNX Runtime failed: {exc}") from None
        res = {}
        for task in windows:
            mod = self.members[task]
            o = outs[self._out_name[task]]
            if task == "pressure":
                res[task] = mod.finish(o, self._bad_input[task])
            else:
                p = mod.probabilities_from_output(o)
                res[task] = (int(p.argmax()), p)
        return res


def _reads_same(a, b) -> bool:
    """Whether two loaded classifiers take the same window encoding (the same T,
    layout, IMU or not and input size), so one input of the fused graph serves both
    (never a regressor: its input is clipped to its own range)."""
    key = ("T", "input_layout", "uses_imu", "n_features")
    def feats(m):
        f = getattr(m, "features", None)
        return None if f is None else f.key()
    return all(hasattr(m, "fill_window") and all(hasattr(m, k) for k in key) for m in (a, b)) \
        and all(getattr(a, k) == getattr(b, k) for k in key) and feats(a) == feats(b)


def _onnx_sha(mod) -> str | None:
    spec = mod.model.spec
    return spec.sha256.get(spec.onnx)


def _subsets(model, mf: Path, want: dict) -> list:
    """[(tasks, session)] of the manifest's ``subsets``: each a list of member
    ``tasks`` and the ``onnx`` file of the graph cut down to them (its SHA-256 in the
    manifest's ``sha256``, each member's input and output as in ``want``, {task:
    member row}). ModelError naming the manifest or the file for a bad one."""
    rows = model.spec.params.subsets          # FusedParams, typed by the one parse
    out = []
    for r in rows:
        have = r.get("tasks") if isinstance(r, dict) else None
        if not isinstance(have, list) or not have or not set(have) < set(want):
            raise ModelError(f"{mf}: a subset's tasks must be some of the members "
                             f"{sorted(want)}, got {have!r}")
        path = checked_model_file(model.path, r.get("onnx"), model.spec.sha256, mf)
        try:
            sess = ort_session(str(path))
        except Exception as exc:      # onnxruntime's own exception types
            raise ModelError(f"{path}: ONNX Runtime cannot load it ({exc})") from None
        names = {i.name for i in sess.get_inputs()} | {o.name for o in sess.get_outputs()}
        for t in have:
            if want[t].get("input") not in names or want[t].get("output") not in names:
                raise ModelError(f"{path}: lacks its member {t}'s input or output")
        out.append((tuple(have), sess))
    return out


def load_fused(models_dir: Path | str, variant: str, loaded: dict, check=None):
    """(FusedModels or None, why not): the fused graph of ``models_dir`` for
    ``variant`` when its members are exactly ``loaded`` ({task: loaded Classifier
    or Regressor}, rules left out). ``check(manifest)`` (the signature check) runs
    before the graph is loaded."""
    folder = Path(models_dir) / FUSED_DIR
    if not folder.is_dir():
        return None, f"no {FUSED_DIR}/ graph in {models_dir}"
    mf = manifest_for(folder, variant)
    if mf.is_dir():
        return None, f"{folder}: no {MANIFEST}"
    try:
        if check is not None:
            check(mf)
        model = load_model(mf, expect_kind=FUSED_KIND)
        rows = model.spec.params.members      # FusedParams: a list of tables
        want = {r.get("task"): r for r in rows}
        if set(want) != set(loaded) or len(want) != len(rows):
            return None, (f"{mf}: built from {sorted(t for t in want if t)}, the leg loaded "
                          f"{sorted(loaded)}; rebuild it (python -m host.learn.fuse)")
        names_in = {i.name: i for i in model.session.get_inputs()}
        names_out = {o.name for o in model.session.get_outputs()}
        for task, r in want.items():
            mod = loaded[task]
            if r.get("sha256") != _onnx_sha(mod) or r.get("onnx") != mod.model.spec.onnx:
                return None, (f"{mf}: its {task} member is not the loaded "
                              f"{model_file(mod.model.path, mod.model.spec.onnx)} "
                              f"(another file or hash); rebuild it (python -m host.learn.fuse)")
            inp = names_in.get(r.get("input"))
            dims = [d for d in (inp.shape[1:] if inp is not None else []) if isinstance(d, int)]
            if inp is None or r.get("output") not in names_out or \
                    int(np.prod(dims or [0])) != mod._x.size:
                return None, f"{mf}: its {task} member's input or output is not the model's"
        for task, r in want.items():
            other = [t for t, o in want.items() if t != task and o.get("input") == r.get("input")]
            if other and not all(_reads_same(loaded[task], loaded[t]) for t in other):
                return None, (f"{mf}: its {task} member shares the input of {other}, which the "
                              f"loaded models do not read the same way; rebuild it "
                              f"(python -m host.learn.fuse)")
        subsets = _subsets(model, mf, want)
        return FusedModels(model, loaded, [want[t] for t in FUSED_TASKS if t in want],
                           subsets), ""
    except SignatureError:
        raise                          # a fused graph signed by no one is refused, not skipped
    except (ModelError, ValueError, KeyError, TypeError) as exc:
        return None, f"{exc}"
