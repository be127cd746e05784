"""Decisions (device/pi/runtime/decisions.py): the gait context from GAIT, the
expected load and motion it gives, learned-model probabilities as SURFACE class ids,
one decision from rule windows, and the runtime's decisions under a GAIT context
(soft against hard, slippery, nominal values, the learned model blended with the
rule)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from device.pi.models.window import RollingWindow
from device.pi import protocol as P
from device.pi.runtime.config import DecisionConfig, LegConfig
from device.pi.runtime.decisions import (SLIP_THRESHOLD, GaitContext, decide, expected_context,
                                         finite_float, gait_from_message, no_touch_probs,
                                         surface_probs_of_model, unknown_class_wins)
from device.pi.runtime.load import load_models
from device.pi.runtime.loop import LegRuntime
from tests.device.pi.runtime.standins import (FPS, NullImu, RecordingPort, SimCamera,
                                              make_runtime, run_for)

N_PINS = 133


def test_gait_message_gives_stance_load_and_horizontal_speed():
    g = gait_from_message(P.Gait(P.PHASE_STANCE, 12.5, (3.0, 4.0, 99.0)), t=7.0)
    assert (g.stance, g.load_n, g.vel_mm_s, g.t) == (True, 12.5, 5.0, 7.0)
    swing = gait_from_message(P.Gait(P.PHASE_SWING, 1.0, (0.0, 0.0, 0.0)), t=0.0)
    assert swing.stance is False


def test_bad_gait_numbers_become_finite():
    msg = P.Gait(P.PHASE_STANCE, 0.0, (0.0, 0.0, 0.0))
    msg.load_n, msg.vel_mm_s = float("nan"), (float("inf"), -2.0)
    g = gait_from_message(msg, 0.0)
    assert g.load_n == 0.0 and g.vel_mm_s == 2.0
    assert finite_float("x", 3.0) == 3.0 and finite_float(float("-inf")) == 0.0


def test_expected_context_from_fresh_gait_and_none_when_stale():
    dc = DecisionConfig()
    g = GaitContext(stance=True, load_n=10.0, vel_mm_s=20.0, t=1.0)
    mag, motion, info = expected_context(g, 1.1, dc, fps=100.0)
    assert mag == pytest.approx(10.0 * dc.mag_px_per_n)
    assert motion == pytest.approx(20.0 * dc.motion_px_per_mm / 100.0)
    assert info == {"stance": True, "load_n": 10.0, "vel_mm_s": 20.0, "age_ms": 100.0}
    assert expected_context(g, 1.0 + dc.gait_timeout_ms / 1e3 + 0.01, dc, 100.0) == \
        (None, None, None)
    assert expected_context(None, 0.0, dc, 100.0) == (None, None, None)
    swing = GaitContext(stance=False, load_n=10.0, vel_mm_s=20.0, t=1.0)
    assert expected_context(swing, 1.0, dc, 100.0)[:2] == (0.0, 0.0)


def test_model_probabilities_land_on_the_surface_class_ids():
    p = surface_probs_of_model(["hard", "no-touch", "slippery", "soft"], [0.1, 0.2, 0.3, 0.4])
    assert p.tolist() == pytest.approx([0.2, 0.1, 0.4, 0.3])      # no-touch, hard, soft, slippery
    only = surface_probs_of_model(["soft", "lego"], [0.5, 0.5])
    assert only.tolist() == pytest.approx([0.0, 0.0, 1.0, 0.0])
    assert surface_probs_of_model(["lego"], [1.0]).tolist() == pytest.approx([0.25] * 4)
    assert no_touch_probs().tolist() == [1.0, 0.0, 0.0, 0.0]


def _windows(models, vectors_px):
    Ts = {models.rule.T}
    ws = {T: RollingWindow(T, N_PINS) for T in Ts}
    for v in vectors_px:
        for w in ws.values():
            w.push(vectors=v, imu=np.zeros(6, np.float32))
    return ws


def test_decide_before_the_window_is_full_is_no_touch(tmp_path):
    m = load_models(tmp_path, "int8", N_PINS, LegConfig())
    d = decide(m, _windows(m, []), contact_seen=True, referenced=True, expected_mag_px=None,
               expected_motion_px=None, gait=None, gait_rule_weight=0.5)
    assert d.class_id == P.SURFACE_CLASSES.index("no-touch") and not d.contact
    assert d.slip_conf == 0.0 and d.pressure is None and d.measures == {}


def test_decide_with_the_rule_hard_soft_and_slippery(tmp_path):
    m = load_models(tmp_path, "int8", N_PINS, LegConfig())
    press = np.full((N_PINS, 2), 2.0, np.float32)                # |v| = 2.83 px, no motion
    ws = _windows(m, [press] * m.rule.T)
    kw = dict(contact_seen=True, referenced=True, gait=None, gait_rule_weight=0.5)
    hard = decide(m, ws, expected_mag_px=1.0, expected_motion_px=0.0, **kw)
    soft = decide(m, ws, expected_mag_px=100.0, expected_motion_px=0.0, **kw)
    wet = decide(m, ws, expected_mag_px=1.0, expected_motion_px=5.0, **kw)
    names = P.SURFACE_CLASSES
    assert (names[hard.class_id], names[soft.class_id], names[wet.class_id]) == \
        ("hard", "soft", "slippery")
    assert hard.contact and not hard.slip
    assert wet.slip and wet.slip_conf >= SLIP_THRESHOLD
    assert math.isclose(float(hard.probs.sum()), 1.0)
    assert hard.measures["magnitude_px"] == pytest.approx(math.hypot(2.0, 2.0), rel=1e-5)
    airborne = decide(m, ws, expected_mag_px=1.0, expected_motion_px=5.0,
                      **{**kw, "contact_seen": False})
    assert not airborne.contact and not airborne.slip


def _decisions(tmp_path, gait, frames=70, scene="press-hard"):
    log = tmp_path / f"log{id(gait)}.jsonl"
    fh = open(log, "w")
    rt, cam, port = make_runtime(tmp_path, cam=SimCamera(scene), json_log=fh)

    def hook(rt):
        if gait is not None:
            port.send(gait)
    run_for(rt, frames=frames, hook=hook)
    fh.close()
    return [json.loads(x) for x in log.read_text().splitlines()], rt


def test_expected_load_from_gait_decides_soft_vs_hard(tmp_path):
    light, _ = _decisions(tmp_path, P.Gait(P.PHASE_STANCE, 1.0, (0.0, 0.0, 0.0)))
    heavy, rt = _decisions(tmp_path, P.Gait(P.PHASE_STANCE, 200.0, (0.0, 0.0, 0.0)))
    assert rt.gait_packets > 0
    k = rt.cfg.decision.mag_px_per_n
    assert light[-1]["expected_mag_px"] == pytest.approx(1.0 * k, abs=1e-3)
    assert heavy[-1]["expected_mag_px"] == pytest.approx(200.0 * k, abs=1e-3)
    touch = [i for i, d in enumerate(light) if d["contact"]]
    assert touch, "press-hard never touched"
    # the same frames: what the robot believes it applies changes the call
    assert light[touch[-1]]["class"] == "hard"
    assert heavy[touch[-1]]["class"] == "soft"


def test_expected_motion_not_seen_is_slippery(tmp_path):
    still, _ = _decisions(tmp_path, P.Gait(P.PHASE_STANCE, 1.0, (0.0, 0.0, 0.0)))
    moving, _ = _decisions(tmp_path, P.Gait(P.PHASE_STANCE, 1.0, (400.0, 0.0, 0.0)))
    last = [d for d in moving if d["contact"]][-1]
    assert last["expected_motion_px"] > 1.0 and last["class"] == "slippery" and last["slip"]
    assert [d for d in still if d["contact"]][-1]["class"] != "slippery"


def test_without_gait_nominal_values_are_used(tmp_path):
    ds, rt = _decisions(tmp_path, None, frames=20)
    assert all(d["gait"] is None and d["expected_mag_px"] is None for d in ds)


def test_learned_surface_model_is_blended_with_the_gait_aware_rule(model_dir, tmp_path):
    def decisions(gait, weight):
        cfg = LegConfig()
        cfg.decision.gait_rule_weight = weight
        log = tmp_path / f"b{weight}{gait is None}.jsonl"
        fh = open(log, "w")
        models = load_models(model_dir, "int8", 133, cfg)
        port = RecordingPort()
        rt = LegRuntime(cfg, SimCamera().factory, NullImu(), port, models, fps=FPS,
                        json_log=fh, notify=lambda s: None)
        run_for(rt, frames=40, hook=(lambda rt: port.send(gait)) if gait else None)
        fh.close()
        return [json.loads(x) for x in log.read_text().splitlines() if '"model_probs"' in x]

    g = P.Gait(P.PHASE_STANCE, 8.0, (2.5, 0.0, 0.0))
    blended = decisions(g, 0.5)
    assert blended
    for d in blended:
        want = 0.5 * np.array(d["model_probs"]) + 0.5 * np.array(d["rule_probs"])
        assert np.allclose(d["probs"], want, atol=2e-4)
    for d in decisions(None, 0.5) + decisions(g, 0.0):        # no GAIT, or weight 0
        assert d["probs"] == d["model_probs"]



def test_a_surface_class_the_link_has_no_id_for_is_a_model_fault(tmp_path, synthetic_windows):
    """A surface model trained with a class outside SURFACE_CLASSES (a typo such as
    ``lava``): when that class wins, the decision says model_fault rather than
    quietly taking the best of the other classes."""
    from host.learn.train import train_model
    ws = synthetic_windows(n_pins=N_PINS, classes=("hard", "lava"))
    train_model("surface", "fnn", ws, out_dir=tmp_path / "models" / "surface", progress=False,
                hidden=(8, 4), epochs=60)
    m = load_models(tmp_path / "models", "float", N_PINS, LegConfig())
    assert list(m.surface.classes) == ["hard", "lava"]

    def decision(level_px):
        w = {T: RollingWindow(T, N_PINS) for T in {m.rule.T, m.surface.T}}
        for _ in range(max(w)):
            for x in w.values():
                x.push(vectors=np.full((N_PINS, 2), level_px, np.float32),
                       imu=np.zeros(6, np.float32))
        return decide(m, w, contact_seen=True, referenced=True, expected_mag_px=None,
                      expected_motion_px=None, gait=None, gait_rule_weight=0.0)

    hard, lava = decision(0.0), decision(2.0)         # synthetic: class k sits at 2k px
    assert not hard.model_fault and P.SURFACE_CLASSES[hard.class_id] == "hard"
    assert lava.model_fault
    assert unknown_class_wins(["hard", "lava"], [0.2, 0.8])
    assert not unknown_class_wins(["hard", "lava"], [0.8, 0.2])


def test_a_frame_fault_holds_no_touch_without_running_a_model(tmp_path):
    """A garbage frame's decision is no-touch, whatever the windows and the pipeline's
    contact say: no contact, slip, texture or pressure."""
    m = load_models(tmp_path, "int8", N_PINS, LegConfig())
    ws = _windows(m, [np.full((N_PINS, 2), 3.0, np.float32)] * 40)
    kw = dict(contact_seen=True, referenced=True, expected_mag_px=1.0, expected_motion_px=5.0,
              gait=None, gait_rule_weight=0.5)
    live = decide(m, ws, **kw)
    assert live.contact and live.class_id != P.SURFACE_CLASSES.index("no-touch")
    d = decide(m, ws, frame_ok=False, **kw)
    assert d.class_id == P.SURFACE_CLASSES.index("no-touch") and d.probs[d.class_id] == 1.0
    assert not d.contact and not d.slip and d.slip_conf == 0.0
    assert d.texture is None and d.pressure is None and not d.model_fault
    assert d.measures == {} and d.model_probs is None


RULE_T = LegConfig().models.window_T


class _Stub:
    """A stand-in learned model: fixed probabilities (or a fixed pressure value), a
    fault flag, and the context it was called with."""

    def __init__(self, T, classes=(), probs=(), fault=False, value=None):
        self.T, self.classes, self.fault, self.value = T, list(classes), fault, value
        self.probs = np.asarray(probs, np.float64)
        self.calls: list = []

    def predict_window(self, window, **context):
        self.calls.append(context)
        if self.value is not None or not self.classes:
            return self.value
        return int(np.argmax(self.probs)), self.probs


def _pressed(tmp_path, **models):
    """The default models (rule only) with ``models`` put in, and full windows of a
    hard press the rule calls hard (contact)."""
    from dataclasses import replace
    m = replace(load_models(tmp_path, "int8", N_PINS, LegConfig()), **models)
    return m, _windows(m, [np.full((N_PINS, 2), 2.0, np.float32)] * m.rule.T)


_KW = dict(referenced=True, expected_mag_px=1.0, expected_motion_px=0.0, gait=None,
           gait_rule_weight=0.5)


@pytest.mark.parametrize("name", ["texture", "slip", "pressure"])
def test_a_fault_of_the_texture_slip_or_pressure_model_reaches_the_decision(tmp_path, name):
    """Each model's fault flag sets the decision's model_fault; a model without a
    fault leaves it clear."""
    def model(fault):
        return {"texture": _Stub(RULE_T, ["smooth", "lego"], [0.3, 0.7], fault),
                "slip": _Stub(RULE_T, ["no-slip", "slip"], [0.8, 0.2], fault),
                "pressure": _Stub(RULE_T, fault=fault, value=12.5)}[name]
    for fault in (False, True):
        m, ws = _pressed(tmp_path, **{name: model(fault)})
        d = decide(m, ws, contact_seen=True, **_KW)
        assert d.model_fault is fault, (name, fault)
        assert d.contact and P.SURFACE_CLASSES[d.class_id] == "hard"


def test_texture_and_pressure_values_and_when_they_are_left_out(tmp_path):
    """The texture is (name, confidence, id) of the texture model's best class, in
    contact only; pressure is the pressure model's value once a reference frame is
    set, None (and no model run, no stale fault) before."""
    tex, prs = _Stub(RULE_T, ["smooth", "lego"], [0.3, 0.7]), _Stub(RULE_T, value=12.5)
    m, ws = _pressed(tmp_path, texture=tex, pressure=prs)
    d = decide(m, ws, contact_seen=True, **_KW)
    assert d.texture == ("lego", pytest.approx(0.7), 1) and d.pressure == 12.5
    assert decide(m, ws, contact_seen=False, **_KW).texture is None
    prs.fault = True
    no_ref = decide(m, ws, contact_seen=True, **{**_KW, "referenced": False})
    assert no_ref.pressure is None and not no_ref.model_fault and len(prs.calls) == 2
    # a pressure model whose window is not yet full returns None: no pressure, no fault
    m2, ws2 = _pressed(tmp_path, pressure=_Stub(RULE_T, fault=True, value=None))
    d2 = decide(m2, ws2, contact_seen=True, **_KW)
    assert d2.pressure is None and not d2.model_fault


def test_slip_confidence_is_the_slip_class_and_the_flag_starts_at_the_threshold(tmp_path):
    """A slip model's confidence is its ``slip`` class (not its best class); the flag
    is set in contact from SLIP_THRESHOLD on (a confidence equal to it slips); a model
    without a ``slip`` class gives its best class's confidence."""
    def slip(probs, classes=("no-slip", "slip")):
        m, ws = _pressed(tmp_path, slip=_Stub(RULE_T, classes, probs))
        return decide(m, ws, contact_seen=True, **_KW)
    low = slip([0.7, 0.3])
    assert low.slip_conf == pytest.approx(0.3) and not low.slip
    at = slip([1.0 - SLIP_THRESHOLD, SLIP_THRESHOLD])
    assert at.slip_conf == SLIP_THRESHOLD and at.slip
    below = slip([1.0 - np.nextafter(SLIP_THRESHOLD, 0.0), np.nextafter(SLIP_THRESHOLD, 0.0)])
    assert not below.slip
    assert slip([0.35, 0.65], classes=("dry", "wet")).slip_conf == pytest.approx(0.65)
    m, ws = _pressed(tmp_path, slip=_Stub(RULE_T, ["no-slip", "slip"], [0.0, 1.0]))
    assert not decide(m, ws, contact_seen=False, **_KW).slip


def test_a_rule_slip_model_sees_the_gait_context_and_a_learned_one_does_not(tmp_path):
    """A rule slip model is given the expected load and motion (motion the pins do
    not show is slip); a learned slip model is called without them."""
    from device.pi.models.rules import RuleClassifier
    m0, _ = _pressed(tmp_path)
    rule_slip = RuleClassifier(m0.rule.rule, ["no-slip", "slip"], m0.rule.T, N_PINS, task="slip")
    m, ws = _pressed(tmp_path, slip=rule_slip)
    still = decide(m, ws, contact_seen=True, **_KW)
    moving = decide(m, ws, contact_seen=True, **{**_KW, "expected_motion_px": 5.0})
    assert still.slip_conf < 0.1 and moving.slip_conf > 0.9 and moving.slip
    learned = _Stub(RULE_T, ["no-slip", "slip"], [0.8, 0.2])
    m, ws = _pressed(tmp_path, slip=learned)
    decide(m, ws, contact_seen=True, **{**_KW, "expected_motion_px": 5.0})
    assert learned.calls == [{}]



def decide_both(one, fused, ws, v, imu, kw, frame):
    """Push one frame into each model set's windows (``ws[id(models)]``), decide with
    both, check the decisions are equal field for field; returns the first."""
    got = []
    for m in (one, fused):
        ws[id(m)][3].push(vectors=v, imu=imu)
        got.append(decide(m, ws[id(m)], **kw))
    assert_same_decision(*got, frame)
    return got[0]


def assert_same_decision(a, b, frame) -> None:
    """Two decisions equal field for field (the probabilities element for element)."""
    for f in ("class_id", "contact", "slip", "slip_conf", "texture", "pressure",
              "model_fault", "measures"):
        assert getattr(a, f) == getattr(b, f), (frame, f)
    for f in ("probs", "rule_probs", "model_probs"):
        x, y = getattr(a, f), getattr(b, f)
        assert (x is None) == (y is None), (frame, f)
        if x is not None:
            np.testing.assert_array_equal(x, y)

def test_the_fused_graph_decides_exactly_as_one_session_per_model(model_dir, tmp_path):
    """Issue #25: with the fused graph (one model call per frame) every decision is
    the one the individual sessions give, field for field, frame by frame; with
    contact, without, with and without a reference and a gait context."""
    import shutil

    from host.learn.fuse import fuse_models

    fused_dir = tmp_path / "fused-models"
    for t in ("surface", "pressure"):
        shutil.copytree(model_dir / t, fused_dir / t)
    fuse_models(fused_dir)
    one = load_models(model_dir, "int8", N_PINS, LegConfig())
    fused = load_models(fused_dir, "int8", N_PINS, LegConfig())
    assert one.fused is None and fused.fused is not None
    ws = {}
    for m in (one, fused):
        w = RollingWindow(3, N_PINS)
        ws[id(m)] = {3: w}
    rng = np.random.default_rng(5)
    n = 0
    for i in range(40):
        v = rng.normal(0, 1 + i % 5, (N_PINS, 2)).astype(np.float32)
        imu = rng.normal(0, 1, 6).astype(np.float32)
        kw = dict(contact_seen=i % 3 != 0, referenced=i % 7 != 3,
                  expected_mag_px=None if i % 2 else 2.0,
                  expected_motion_px=None if i % 2 else 0.5,
                  gait=None if i % 2 else {"stance": True}, gait_rule_weight=0.5)
        a = decide_both(one, fused, ws, v, imu, kw, i)
        n += a.model_probs is not None and a.pressure is not None
    assert n > 20                        # both models decided on most frames


def test_the_fused_graph_with_texture_decides_as_one_session_per_model_in_and_out_of_contact(
        model_dir, tmp_path):
    """Issue #25: with a texture member, frames in contact run the whole fused graph
    and frames out of contact the graph without texture; surface and slip read one
    input. Every decision is still one session per model's, field for field."""
    import shutil

    from host.learn.fuse import fuse_models

    one_dir, fused_dir = tmp_path / "one", tmp_path / "fused"
    for d in (one_dir, fused_dir):
        for t in ("surface", "pressure"):
            shutil.copytree(model_dir / t, d / t)
        for t in ("texture", "slip"):        # the surface fnn serving as texture and slip
            shutil.copytree(model_dir / "surface", d / t)
            for mf in (d / t).glob("manifest*.json"):
                doc = json.loads(mf.read_text())
                doc["kind"] = doc["task"] = t
                if t == "slip":
                    doc["classes"] = ["a", "slip", "b", "c"]
                mf.write_text(json.dumps(doc))
    fuse_models(fused_dir)
    one = load_models(one_dir, "int8", N_PINS, LegConfig())
    fused = load_models(fused_dir, "int8", N_PINS, LegConfig())
    assert one.fused is None and fused.fused is not None
    assert fused.fused.shared_inputs == {"texture": "surface", "slip": "surface"}
    ws = {id(m): {3: RollingWindow(3, N_PINS)} for m in (one, fused)}
    rng = np.random.default_rng(8)
    seen = set()
    for i in range(30):
        v = rng.normal(0, 1 + i % 4, (N_PINS, 2)).astype(np.float32)
        imu = rng.normal(0, 1, 6).astype(np.float32)
        kw = dict(contact_seen=i % 3 != 0, referenced=True, expected_mag_px=None,
                  expected_motion_px=None, gait=None, gait_rule_weight=0.5)
        a = decide_both(one, fused, ws, v, imu, kw, i)
        if a.model_probs is not None:
            seen.add(a.texture is not None)
    assert seen == {True, False}            # frames with texture and frames without
    # both graphs ran: the whole one in contact, the one without texture out of it
    runs = fused.fused.graph_runs
    assert set(runs) == {("surface", "texture", "slip", "pressure"), ("surface", "slip", "pressure")}, runs
    assert all(n > 0 for n in runs.values())


def test_the_log_names_both_contacts_and_the_decision_needs_the_pipelines(tmp_path):
    """`contact` (the decision's) is never set without `pipeline_contact` (the marker
    pipeline's), and a texture is only ever logged on a pipeline contact (issue 33)."""
    recs, _ = _decisions(tmp_path, None, frames=60, scene="press-hard")
    assert all(isinstance(r["pipeline_contact"], bool) for r in recs)
    assert any(r["pipeline_contact"] for r in recs)
    assert all(r["pipeline_contact"] for r in recs if r["contact"])
    assert all(r["pipeline_contact"] for r in recs if r["texture"] is not None)

