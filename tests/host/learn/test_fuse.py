"""host/learn/fuse.py: the per-frame models as one ONNX graph, built from the
artefacts of a models folder; each member's output is its own model's, bit for bit."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from device.pi.models.artefact import ModelError, ort_session, read_spec, sha256_file
from host.learn.fuse import fuse_models, main
from tests import REPO_ROOT

TASKS = ("surface", "texture", "slip", "pressure")


@pytest.fixture(scope="module")
def shipped(tmp_path_factory):
    """A copy of the shipped per-frame models (int8 + float; pressure at opset 13,
    the classifiers at 17)."""
    d = tmp_path_factory.mktemp("models")
    for t in TASKS:
        if not (REPO_ROOT / "models" / t / "manifest.json").is_file():
            pytest.skip(f"no shipped models/{t}")
        shutil.copytree(REPO_ROOT / "models" / t, d / t)
    return d


def test_the_fused_graph_gives_each_members_output_bit_for_bit(shipped):
    import onnx

    built = fuse_models(shipped)
    assert set(built) == {"int8", "float"}
    rng = np.random.default_rng(3)
    for variant, manifest in built.items():
        spec, _ = read_spec(manifest)
        assert spec.kind == "fused" and spec.profile["name"] == "roboskin"
        rows = spec.params.members
        assert [r["task"] for r in rows] == list(TASKS)
        fused = ort_session(str(manifest.parent / spec.onnx))
        assert sha256_file(manifest.parent / spec.onnx) == spec.sha256[spec.onnx]
        assert [o.name for o in fused.get_outputs()] == [r["output"] for r in rows]
        # surface and slip read the same window features: one input, computed once
        # by the leg (features version 2: no feature node is left to share)
        assert [r["input"] for r in rows] == ["surface/x", "texture/x", "surface/x",
                                              "pressure/x"]
        assert [i.name for i in fused.get_inputs()] == ["surface/x", "texture/x", "pressure/x"]
        nodes = [n.op_type for n in onnx.load(str(manifest.parent / spec.onnx)).graph.node]
        per_member = sum(len(onnx.load(str(shipped / r["task"] / r["onnx"])).graph.node)
                         for r in rows)
        assert len(nodes) <= per_member - 12         # no label branch (4 nodes x 3)
        for trial in range(3):
            feeds, want = {}, {}
            for r in rows:
                mdoc = json.loads((shipped / r["manifest"]).read_text())
                assert r["onnx"] == mdoc["onnx"] and r["sha256"] == mdoc["sha256"][r["onnx"]]
                assert mdoc["variant"] == ("int8" if variant == "int8" else "float")
                if r["input"] not in feeds:     # surface and slip read one input
                    feeds[r["input"]] = (np.round(rng.normal(0, 3, (1, r["n_inputs"])) * 4)
                                         / 4).astype(np.float32)
                x = feeds[r["input"]]
                one = ort_session(str(shipped / r["task"] / r["onnx"]))
                want[r["task"]] = one.run([r["output"].split("/", 1)[1]], {"x": x})[0]
            got = fused.run([r["output"] for r in rows], feeds)
            for r, g in zip(rows, got):
                np.testing.assert_array_equal(g, want[r["task"]], err_msg=r["task"])


def test_the_graphs_hold_only_the_nodes_read_and_the_one_without_texture_is_the_same(shipped):
    """Issue #25: no label branch in the fused graph (ONNX Runtime runs every node,
    read or not), and the graph without texture (for frames out of contact) has no
    texture node and gives the other members' outputs bit for bit."""
    import onnx

    built = fuse_models(shipped)
    rng = np.random.default_rng(4)
    for variant, manifest in built.items():
        spec, _ = read_spec(manifest)
        full = onnx.load(str(manifest.parent / spec.onnx))
        assert not {"ArgMax", "ArrayFeatureExtractor"} & {n.op_type for n in full.graph.node}
        assert not any(o.endswith("/label") for n in full.graph.node for o in n.output)
        (sub,) = spec.params.subsets
        assert sub["tasks"] == ["surface", "slip", "pressure"]
        path = manifest.parent / sub["onnx"]
        assert sha256_file(path) == spec.sha256[sub["onnx"]]
        cut = onnx.load(str(path))
        assert not any(n.name.startswith("texture/") for n in cut.graph.node)
        assert {n.name for n in cut.graph.node} < {n.name for n in full.graph.node}
        a, b = ort_session(str(manifest.parent / spec.onnx)), ort_session(str(path))
        rows = {r["task"]: r for r in spec.params.members}
        outs = [rows[t]["output"] for t in sub["tasks"]]
        assert [o.name for o in b.get_outputs()] == outs
        for trial in range(3):
            feeds = {r["input"]: (np.round(rng.normal(0, 3, (1, r["n_inputs"])) * 4) / 4
                                  ).astype(np.float32) for r in rows.values()}   # one each
            want = a.run(outs, feeds)
            got = b.run(outs, {k: v for k, v in feeds.items() if not k.startswith("texture/")})
            for o, g, w in zip(outs, got, want):
                np.testing.assert_array_equal(g, w, err_msg=f"{variant} {o}")


def test_a_rebuild_follows_the_members_and_fewer_than_two_give_no_graph(shipped, tmp_path):
    d = tmp_path / "models"
    for t in ("surface", "pressure"):
        shutil.copytree(shipped / t, d / t)
    (d / "fused").mkdir()
    (d / "fused" / "stale.onnx").write_bytes(b"old")
    built = fuse_models(d)
    assert not (d / "fused" / "stale.onnx").exists()
    rows = read_spec(built["int8"])[0].params.members
    assert [r["task"] for r in rows] == ["surface", "pressure"]
    assert read_spec(built["int8"])[0].params.subsets == []     # no texture member
    assert sorted(p.name for p in (d / "fused").iterdir()) == [
        "fused.float.onnx", "fused.onnx", "manifest.float.json", "manifest.json"]
    shutil.rmtree(d / "pressure")
    assert fuse_models(d) == {} and not (d / "fused").exists()


def test_the_command_builds_it_and_a_broken_member_is_one_line(shipped, tmp_path, capsys):
    d = tmp_path / "models"
    for t in ("surface", "slip"):
        shutil.copytree(shipped / t, d / t)
    assert main([str(d)]) == 0
    assert (d / "fused" / "manifest.json").is_file()
    assert "manifest.json" in capsys.readouterr().out
    (d / "slip" / "model.int8.onnx").write_bytes(b"not onnx")
    assert main([str(d)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("host.learn.fuse: error: ") and "slip" in err
    assert main([]) == 2
    with pytest.raises(ModelError):
        fuse_models(d)


def test_a_fused_copy_links_the_models_and_leaves_their_folder_alone(shipped, tmp_path):
    from device.pi.runtime.config import LegConfig
    from device.pi.runtime.load import load_models
    from host.learn.fuse import fused_copy

    before = sorted(p.name for p in shipped.iterdir())
    d = fused_copy(shipped, tmp_path)
    assert sorted(p.name for p in shipped.iterdir()) == before
    assert all((d / t).is_symlink() for t in TASKS) and (d / "fused" / "manifest.json").is_file()
    m = load_models(d, "int8", 133, LegConfig())
    assert m.fused is not None and m.fused.tasks == TASKS


def test_repeated_nodes_are_computed_once_and_control_flow_is_left_alone():
    """_shared_nodes drops a node that repeats an earlier one (constants compared by
    value, not by name) and reads its output instead; a node giving a graph output
    stays; a graph holding a subgraph is not touched."""
    from onnx import helper, numpy_helper

    from host.learn.fuse import _shared_nodes

    c1 = numpy_helper.from_array(np.array([2.0], np.float32), "a/c")
    c2 = numpy_helper.from_array(np.array([2.0], np.float32), "b/c")
    c3 = numpy_helper.from_array(np.array([3.0], np.float32), "b/d")
    nodes = [helper.make_node("Mul", ["x", "a/c"], ["a/m"]),
             helper.make_node("Mul", ["x", "b/c"], ["b/m"]),            # = a/m
             helper.make_node("Mul", ["x", "b/d"], ["b/n"]),            # another constant
             helper.make_node("Relu", ["b/m"], ["b/r"]),
             helper.make_node("Relu", ["a/m"], ["a/out"])]              # a graph output
    kept = _shared_nodes(nodes, [c1, c2, c3], {"a/out", "b/r"})
    assert [n.output[0] for n in kept] == ["a/m", "b/n", "b/r", "a/out"]
    assert list(kept[2].input) == ["a/m"]
    body = helper.make_graph([], "body", [], [])
    loop = [helper.make_node("If", ["x"], ["y"], then_branch=body, else_branch=body)]
    again = [helper.make_node("Mul", ["x", "a/c"], ["a/m"]),
             helper.make_node("Mul", ["x", "b/c"], ["b/m"])] + loop
    assert len(_shared_nodes(again, [c1, c2], set())) == 3
