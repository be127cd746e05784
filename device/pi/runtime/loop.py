"""The leg runtime: camera + IMU in, surface decisions out over the UART.

``python -m device.pi run --camera v4l2:///dev/video0 --imu i2c://1/0x68 --serial
/dev/serial0`` (or ``sim://walk``, ``sim://walk``, ``loop://`` with no hardware). See
docs/runtime.md for the options, the config keys, the packets and the fault handling.

One loop, one thread for the work (a second thread only grabs frames, so a camera
that blocks or vanishes cannot stall the loop):

    frame -> MarkerStream -> fixed pin layout -> rolling windows -> models (ONNX
    Runtime, int8, one session each, one thread) or the paper's rules with the gait
    context -> decision -> SURFACE packet -> non-blocking writer

and around it, on every pass, with or without a frame: the MCU's GAIT / COMMAND
packets are read, the IMU summary and the HEARTBEAT go out at their rates, a change
of the fault state sends FAULT at once, the status file is rewritten and the
systemd watchdog is fed.
"""
from __future__ import annotations

import json
import math
import os
import queue
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from device.pi.runtime import protocol as _p
from device.pi.runtime.config import LegConfig

# -- fault bits (FAULT and SURFACE packets, docs/protocol.md). Bits 0-5 are the
#    pipeline's per-frame bits; the runtime raises these:
FAULT_CAMERA = _p.FAULT_CAMERA        # no frame within camera.stall_periods frame periods
FAULT_IMU = _p.FAULT_IMU              # the IMU read failed (stale / offline)
FAULT_MODEL = _p.FAULT_MODEL          # a model gave no usable output (uniform fallback)
FAULT_PINS_LOST = _p.FAULT_PINS_LOST  # more than half the reference pins lost this frame
FAULT_LINK = _p.FAULT_LINK            # bytes waiting and the port took none for stall_ms
#: (status file and JSON log only: a stalled port cannot carry it)

#: a live camera that delivered nothing for this long is closed and reopened
REOPEN_AFTER_S = 1.0

SURFACE_CLASSES = _p.SURFACE_CLASSES   # the SURFACE class ids: no-touch, hard, soft, slippery
EXIT_BAD_INPUT = 2


def all_fault_names(bits: int) -> list[str]:
    return _p.fault_names(bits)


class StartupError(Exception):
    """The runtime cannot start: a bad config, model, source or port (exit 2)."""


# ---------------------------------------------------------------------------
# Camera feed: a grab thread with reopen and backoff
# ---------------------------------------------------------------------------

class CameraFeed:
    """Frames from a camera factory on a grab thread.

    ``lossless`` (files and sim://): every frame is handed over in order (the grab
    thread waits for the loop). Otherwise (live cameras) only the newest frame is
    kept. A source that raises is closed and reopened with a backoff doubling from
    ``reopen_min_s`` to ``reopen_max_s``; the thread never gives up. ``read()``
    returning None ends a finite stream (``eof``)."""

    def __init__(self, factory, *, lossless: bool, reopen_min_s: float = 0.1,
                 reopen_max_s: float = 2.0, first=None, clock=time.monotonic):
        self.factory = factory
        self.lossless = lossless
        self.min_s, self.max_s = reopen_min_s, reopen_max_s
        self.clock = clock
        self._q: queue.Queue = queue.Queue(maxsize=1)
        self._stop = threading.Event()
        self._reopen = threading.Event()
        self._cam = first
        self.opens = 1 if first is not None else 0
        self.errors = 0
        self.last_error = ""
        self.eof = False
        self.opened_at = clock() if first is not None else None
        self._thread = threading.Thread(target=self._run, name="camera", daemon=True)

    def start(self):
        self._thread.start()
        return self

    def _put(self, item) -> None:
        if self.lossless:
            while not self._stop.is_set():
                try:
                    self._q.put(item, timeout=0.05)
                    return
                except queue.Full:
                    continue
        else:
            try:
                self._q.get_nowait()          # drop the older frame: newest only
            except queue.Empty:
                pass
            try:
                self._q.put_nowait(item)
            except queue.Full:
                pass

    def _run(self) -> None:
        backoff = self.min_s
        while not self._stop.is_set():
            if self._reopen.is_set():
                self._reopen.clear()
                self._close_cam()
            if self._cam is None:
                try:
                    self._cam = self.factory()
                    self.opens += 1
                    self.opened_at = self.clock()
                    backoff = self.min_s
                except Exception as exc:        # CameraError, OSError, driver errors
                    self.errors += 1
                    self.last_error = str(exc)
                    self._stop.wait(backoff)
                    backoff = min(self.max_s, max(backoff * 2, 1e-3))
                    continue
            try:
                fr = self._cam.read()
            except Exception as exc:            # unplugged: close, reopen with backoff
                self.errors += 1
                self.last_error = str(exc)
                self._close_cam()
                self._stop.wait(backoff)
                backoff = min(self.max_s, max(backoff * 2, 1e-3))
                continue
            if fr is None:
                self.eof = True
                self._put(None)
                return
            self._put((fr, self.clock()))

    def _close_cam(self) -> None:
        cam, self._cam = self._cam, None
        if cam is not None:
            try:
                cam.close()
            except Exception:
                pass

    def get(self, timeout: float):
        """(Frame, t_available) or None (no frame within ``timeout``), or the string
        "eof" at the end of a finite stream."""
        try:
            item = self._q.get(timeout=max(timeout, 0.0)) if timeout > 0 else self._q.get_nowait()
        except queue.Empty:
            return None
        return "eof" if item is None else item

    def reopen(self) -> None:
        """Ask for a reopen (e.g. a new frame rate); done on the grab thread before
        its next grab."""
        self._reopen.set()

    def stop(self) -> None:
        self._stop.set()
        try:
            self._q.get_nowait()
        except queue.Empty:
            pass
        self._thread.join(timeout=2.0)
        self._close_cam()


# ---------------------------------------------------------------------------
# Models
# ---------------------------------------------------------------------------

@dataclass
class Models:
    surface: object | None = None       # Classifier or RuleClassifier
    texture: object | None = None
    slip: object | None = None
    pressure: object | None = None
    localiser: object | None = None
    rule: object | None = None          # the rule classifier (always present)
    loaded: tuple = ()


def default_models_dir() -> Path:
    return Path(__file__).resolve().parents[3] / "models"


def _manifest_for(folder: Path, variant: str) -> Path:
    """The manifest to load: ``manifest.json`` (int8 when the model was quantised)
    or, for the float variant, ``manifest.float.json`` when there is one."""
    if variant == "float" and (folder / "manifest.float.json").is_file():
        return folder / "manifest.float.json"
    return folder / "manifest.json" if (folder / "manifest.json").is_file() else folder


def _load_classifier(folder: Path, kind: str, variant: str):
    from device.pi.models.classifier import Classifier
    return Classifier.load(_manifest_for(folder, variant), expect_kind=kind)


def load_models(models_dir: Path | str | None, variant: str, profile_n_pins: int,
                cfg: LegConfig) -> Models:
    """Every model present in ``models_dir`` (surface, texture, slip, pressure,
    localiser-*), loaded once. Raises ModelError naming the file for a bad one."""
    from device.pi.models.artefact import ModelError
    from device.pi.models.rules import RuleClassifier, SURFACE_CLASSES as RULE_CLASSES

    m = Models()
    loaded = []
    d = Path(models_dir) if models_dir is not None else default_models_dir()
    if models_dir is not None and not d.is_dir():
        raise ModelError(f"{d}: models folder not found")
    if d.is_dir():
        for kind in ("surface", "texture", "slip"):
            f = d / kind
            if (f / "manifest.json").is_file() or (f.is_dir() and any(f.iterdir())):
                setattr(m, kind, _load_classifier(f, kind, variant))
                loaded.append(kind)
        f = d / "pressure"
        if f.is_dir():
            from device.pi.models.regressor import Regressor
            m.pressure = Regressor.load(_manifest_for(f, variant))
            loaded.append("pressure")
        locs = sorted(p for p in d.glob("localiser*") if p.is_dir())
        if locs:
            from device.pi.vision.localiser import Localiser
            pick = next((p for p in locs if p.name == f"localiser-{cfg.models.profile}"),
                        locs[0])
            m.localiser = Localiser.load(pick)
            loaded.append(pick.name)
    dc = cfg.decision
    rule = {"contact_px": 1.0, "expected_mag_px": dc.nominal_load_n * dc.mag_px_per_n,
            "soft_ratio": 0.6,
            "expected_motion_px": dc.nominal_speed_mm_s * dc.motion_px_per_mm / cfg.camera.fps,
            "wet_ratio": 0.3}
    if isinstance(m.surface, RuleClassifier):
        m.rule = m.surface
    else:
        m.rule = RuleClassifier(rule, list(RULE_CLASSES), cfg.models.window_T, profile_n_pins)
    from device.pi.models.window import RollingWindow
    for name in ("surface", "texture", "slip", "pressure"):
        mod = getattr(m, name)
        if mod is None or isinstance(mod, RuleClassifier):
            continue
        man = mod.model.manifest
        T = int(man.get("T", getattr(mod, "T", 1)))
        layout = man.get("input_layout", "vectors")
        try:
            x = RollingWindow(T, profile_n_pins).encode(layout,
                                                        with_imu=bool(man.get("uses_imu")))
        except ValueError as exc:
            raise ModelError(f"{mod.model.path / 'manifest.json'}: {exc}") from None
        if x.size != mod.n_features:
            raise ModelError(f"{mod.model.path / 'manifest.json'}: the model takes "
                             f"{mod.n_features} inputs, but a {layout} window of T={T} over "
                             f"the {profile_n_pins}-pin layout gives {x.size}")
    m.loaded = tuple(loaded)
    return m


# ---------------------------------------------------------------------------
# The runtime
# ---------------------------------------------------------------------------

@dataclass
class Gait:
    """The MCU's latest gait context (t = clock time it arrived)."""
    stance: bool
    load_n: float
    vel_mm_s: float
    t: float


def _finite(x, default=0.0) -> float:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return default
    return x if math.isfinite(x) else default


class LegRuntime:
    """The loop. Build it with :func:`build_runtime` (sources from strings) or
    directly with stand-ins (tests): ``camera_factory()`` returns a camera source,
    ``imu`` has ``read()``, ``port`` is a pyserial-like port."""

    def __init__(self, cfg: LegConfig, camera_factory, imu, port, models: Models, *,
                 lossless: bool = True, fps: float | None = None, json_log=None,
                 status_path: str | None = None, max_frames: int | None = None,
                 first_camera=None, clock=time.monotonic, notify=None, camera_opts=None):
        from device.pi.runtime.link import LinkReader, LinkWriter
        from device.pi.vision.encoder import FrameEncoder
        from device.pi.models.window import RollingWindow
        from device.pi.runtime import protocol

        self.cfg = cfg
        self.camera_opts = camera_opts        # the live camera's open options (set rate)
        self.proto = protocol
        self.clock = clock
        self.fps = float(fps or cfg.camera.fps)
        self.models = models
        need_crop = any(getattr(c, "input_layout", "") == "frames"
                        for c in (models.surface, models.texture, models.slip) if c is not None)
        self.encoder = FrameEncoder(cfg.models.profile, crop_px=32 if need_crop else None,
                                    localiser=models.localiser)
        self.stream = self.encoder.stream
        self.n_pins = self.encoder.n_pins
        self._prev_v = np.zeros((self.n_pins, 2), np.float32)
        Ts = {models.rule.T}
        for c in (models.surface, models.texture, models.slip):
            if c is not None:
                Ts.add(c.T)
        if models.pressure is not None:
            Ts.add(models.pressure.T)
        self.windows = {T: RollingWindow(T, self.n_pins, self.stream.profile.grid_n)
                        for T in sorted(Ts)}
        self.imu = imu
        self._imu_out = np.zeros(6, np.float32)
        self._imu_sum = np.zeros(6, np.float64)
        self._imu_peak_g = 0.0
        self._imu_n = 0
        self.port = port
        self.writer = LinkWriter(port, stall_ms=cfg.serial.stall_ms, clock=clock)
        self.reader = LinkReader(port)
        self.feed = CameraFeed(camera_factory, lossless=lossless,
                               reopen_min_s=cfg.camera.reopen_min_s,
                               reopen_max_s=cfg.camera.reopen_max_s, first=first_camera,
                               clock=clock)
        self.json_log = json_log
        self.status_path = status_path
        self.max_frames = max_frames
        self.notify = notify
        # state
        self.seq = 0
        self.frames = 0
        self.faults = 0
        self._pins_lost = 0
        self.fault_changes = 0
        self.gait: Gait | None = None
        self.gait_packets = 0
        self.commands = 0
        self.rezeros = {"command": 0, "auto": 0}
        self._last_rezero = -1e9
        self._still = 0
        self._pipe_faults = 0
        self._imu_faults = 0
        self._model_fault = False
        self._t0 = clock()
        self._last_frame_t = None
        self._wait_since = self._t0
        self._next_hb = self._t0
        self._next_imu = self._t0
        self._next_status = self._t0
        self._next_fault_repeat = 1e18
        self.latencies_ms: list[float] = []
        self.cpu_ms: list[float] = []          # thread CPU time per frame
        self.fault_log: list[tuple[float, int]] = []   # (clock, bits) at each change
        self.stopped = False
        self._ready = False
        self._reopen_asked = False
        from device.pi.runtime.sdnotify import Watchdog
        self.watchdog = Watchdog()

    # -- packets ---------------------------------------------------------------
    def _t_ms(self) -> int:
        return int((self.clock() - self._t0) * 1000.0) & 0xFFFFFFFF

    def _next_seq(self) -> int:
        s = self.seq
        self.seq = (self.seq + 1) & 0xFFFF
        return s

    def _send(self, kind: str, msg) -> None:
        frame = msg.encode(self._next_seq(), self._t_ms())
        self.writer.send(kind, msg.msg_type, frame)

    # -- the loop --------------------------------------------------------------
    def start(self) -> None:
        self.feed.start()

    def run(self) -> int:
        self.start()
        self.run_t0 = self.clock()
        try:
            while not self.stopped:
                self.step()
        finally:
            self.run_s = self.clock() - self.run_t0
            self.close()
        return 0

    def step(self) -> None:
        """One pass: wait for a frame (at most until the next housekeeping deadline
        or one frame period), process it, then housekeeping."""
        now = self.clock()
        period = 1.0 / self.fps
        deadline = min(self._next_hb, self._next_imu, self._next_status,
                       self._next_fault_repeat, now + period)
        got = self.feed.get(max(0.0, deadline - now))
        if got == "eof":
            self.stopped = True
        elif got is not None:
            frame, t_avail = got
            t_avail = max(t_avail, self._wait_since)
            self._wait_since = self.clock()       # a frame came: the camera is not stalled
            self._frame(frame, t_avail)
            self._wait_since = self.clock()
        self._housekeeping()
        if self.max_frames is not None and self.frames >= self.max_frames:
            self.stopped = True

    def _camera_stalled(self, now: float) -> bool:
        stall_s = self.cfg.camera.stall_periods / self.fps
        since = self._wait_since
        if self._last_frame_t is None:
            # before the first frame: allow the camera time to open (sim scenes,
            # V4L2 negotiation), then the same rule
            opened = self.feed.opened_at
            since = max(since, (opened if opened is not None else self._t0 + 1.0))
            if opened is None and now - self._t0 > 1.0:
                return True
        return now - since > stall_s

    def _frame(self, frame, t_avail: float) -> None:
        c0 = time.thread_time()
        self.frames += 1
        self._last_frame_t = t_avail
        imu_vec, imu_bits = self.imu.read(self._imu_out)
        self._imu_faults = int(imu_bits)
        self._imu_acc(imu_vec)
        ef = self.encoder.encode(frame.image, frame.t_s)
        ff = ef.features
        self._pipe_faults = int(ff.faults) & 0xFF
        if self.stream.reference is not None and len(ff.lost):
            self._pins_lost = int(ff.lost.sum())
            if self._pins_lost * 2 > len(ff.lost):
                self._pipe_faults |= FAULT_PINS_LOST
        else:
            self._pins_lost = 0
        v = ef.vectors
        for w in self.windows.values():
            w.push(vectors=v, imu=imu_vec, grid=ff.grid, frame=ef.crop)
        # gait context
        exp_mag, exp_motion, gait = self._expected()
        # decisions
        m = self.models
        model_fault = False
        rwin = self.windows[m.rule.T]
        probs_rule = None
        if rwin.full:
            _, probs_rule = m.rule.predict(rwin.encode("vectors"), expected_mag_px=exp_mag,
                                           expected_motion_px=exp_motion)
        surface_probs = rule_probs = self._surface_probs(probs_rule)
        model_probs = None
        if m.surface is not None and m.surface is not m.rule:
            w = self.windows[m.surface.T]
            if w.full:
                _, p = m.surface.predict_window(w)
                surface_probs = model_probs = self._reorder(m.surface.classes, p)
                model_fault |= bool(m.surface.fault)
                wr = self.cfg.decision.gait_rule_weight
                if gait is not None and probs_rule is not None and wr > 0:
                    # the learned model cannot see the gait context; the rule can
                    surface_probs = (1.0 - wr) * model_probs + wr * rule_probs
        texture = None
        # a texture is only felt in contact: no texture inference in the air
        if m.texture is not None and ff.contact and self.windows[m.texture.T].full:
            tid, tp = m.texture.predict_window(self.windows[m.texture.T])
            texture = (m.texture.classes[tid], float(tp[tid]), tid)
            model_fault |= bool(m.texture.fault)
        meas = m.rule.last if rwin.full else {}
        slip_conf = 0.0
        if m.slip is not None and self.windows[m.slip.T].full:
            ctx = ({"expected_mag_px": exp_mag, "expected_motion_px": exp_motion}
                   if hasattr(m.slip, "rule") else {})       # a rule slip model: gait context
            sid, sp = m.slip.predict_window(self.windows[m.slip.T], **ctx)
            slip_conf = float(sp[list(m.slip.classes).index("slip")]) \
                if "slip" in m.slip.classes else float(sp[sid])
            model_fault |= bool(m.slip.fault)
        elif probs_rule is not None:
            slip_conf = float(probs_rule[list(m.rule.classes).index("slippery")]) \
                if "slippery" in m.rule.classes else 0.0
        pressure = None
        if m.pressure is not None and self.stream.reference is not None:
            pressure = m.pressure.predict_window(self.windows[m.pressure.T])
            model_fault |= pressure is not None and bool(m.pressure.fault)
        self._model_fault = model_fault
        class_id = int(np.argmax(surface_probs))
        contact = bool(ff.contact) and SURFACE_CLASSES[class_id] != "no-touch"
        slip = contact and slip_conf >= 0.5
        self._auto_rezero(v, ef.lost, contact, gait)
        faults = self._fault_bits()
        msg = self.proto_surface(class_id, surface_probs, contact, slip, slip_conf,
                                 ff.direction_deg, float(ff.magnitude), pressure,
                                 len(ff.pins), faults, texture[2] if texture else None)
        self._send("surface", msg)
        self._update_faults(faults)
        before = self.writer.packets_sent
        self.writer.pump()
        t_done = self.clock()
        self.cpu_ms.append((time.thread_time() - c0) * 1e3)
        lat = None
        if self.writer.packets_sent > before and self.writer.pending == 0:
            lat = (t_done - t_avail) * 1e3
            self.latencies_ms.append(lat)
        if self.json_log is None:
            return
        # the decision log line, built after the packet went out
        dec = {"frame": self.frames - 1, "index": int(frame.index),
               "t_s": round(float(frame.t_s), 6), "class": SURFACE_CLASSES[class_id],
               "class_id": class_id, "probs": [round(float(x), 4) for x in surface_probs],
               "contact": contact, "slip": slip, "slip_conf": round(slip_conf, 4),
               "texture": texture[0] if texture else None,
               "shear_dir_deg": round(ff.direction_deg, 2),
               "shear_mag_px": round(float(ff.magnitude), 3),
               "pressure": None if pressure is None else round(float(pressure), 4),
               "pins": int(len(ff.pins)), "faults": all_fault_names(faults),
               "expected_mag_px": round(exp_mag, 3) if exp_mag is not None else None,
               "expected_motion_px": round(exp_motion, 4) if exp_motion is not None else None,
               "gait": gait, "magnitude_px": round(float(meas.get("magnitude_px", 0.0)), 3),
               "motion_px": (None if meas.get("motion_px") is None
                             else round(float(meas["motion_px"]), 4)),
               "latency_ms": None if lat is None else round(lat, 4)}
        if model_probs is not None:
            dec["model_probs"] = [round(float(x), 4) for x in model_probs]
            dec["rule_probs"] = [round(float(x), 4) for x in rule_probs]
        self.json_log.write(json.dumps(dec) + "\n")

    @staticmethod
    def _reorder(classes, p) -> np.ndarray:
        out = np.zeros(len(SURFACE_CLASSES))
        for c, x in zip(classes, p):
            if c in SURFACE_CLASSES:
                out[SURFACE_CLASSES.index(c)] = x
        s = out.sum()
        return out / s if s > 0 else np.full(len(SURFACE_CLASSES), 1.0 / len(SURFACE_CLASSES))

    def _surface_probs(self, probs_rule) -> np.ndarray:
        if probs_rule is None:
            p = np.zeros(len(SURFACE_CLASSES))
            p[SURFACE_CLASSES.index("no-touch")] = 1.0
            return p
        return self._reorder(self.models.rule.classes, probs_rule)

    def _expected(self):
        """(expected_mag_px, expected_motion_px, gait dict | None) from a fresh GAIT
        context, or (None, None, None): the rule's nominal values."""
        g = self.gait
        dc = self.cfg.decision
        if g is None or (self.clock() - g.t) * 1e3 > dc.gait_timeout_ms:
            return None, None, None
        load = g.load_n if g.stance else 0.0
        mag = max(0.0, load) * dc.mag_px_per_n
        motion = abs(g.vel_mm_s) * dc.motion_px_per_mm / self.fps if g.stance else 0.0
        return mag, motion, {"stance": g.stance, "load_n": round(g.load_n, 3),
                             "vel_mm_s": round(g.vel_mm_s, 3)}

    def _auto_rezero(self, v, lost, contact: bool, gait) -> None:
        rz = self.cfg.rezero
        ok = ~lost
        step = (float(np.hypot(*(v[ok] - self._prev_v[ok]).T).mean()) if ok.any() else 0.0)
        self._prev_v[:] = v
        if not rz.auto or gait is None or gait["stance"] or contact \
                or self.stream.reference is None:
            self._still = 0
            return
        self._still = self._still + 1 if step < rz.still_px else 0
        if self._still >= rz.still_frames and \
                self.clock() - self._last_rezero >= rz.min_interval_s:
            self.rezero("auto")

    def rezero(self, why: str) -> None:
        self.stream.rezero()
        for w in self.windows.values():
            w.clear()
        self._still = 0
        self._last_rezero = self.clock()
        self.rezeros[why] = self.rezeros.get(why, 0) + 1

    def _fault_bits(self) -> int:
        now = self.clock()
        bits = self._pipe_faults
        if self._camera_stalled(now):
            bits |= FAULT_CAMERA
        if self._imu_faults:
            bits |= FAULT_IMU
        if self._model_fault:
            bits |= FAULT_MODEL
        if self.writer.stalled:
            bits |= FAULT_LINK
        return bits

    def _update_faults(self, bits: int) -> None:
        now = self.clock()
        if bits != self.faults:
            raised = bits & ~self.faults
            self.faults = bits
            self.fault_changes += 1
            self.fault_log.append((now, bits))
            self._send("fault", self.proto_fault(bits, raised))
            self._next_fault_repeat = now + self.cfg.serial.fault_repeat_s if bits else 1e18
        elif bits and now >= self._next_fault_repeat:
            self._send("fault", self.proto_fault(bits))
            self._next_fault_repeat = now + self.cfg.serial.fault_repeat_s

    def _imu_acc(self, vec) -> None:
        self._imu_sum += vec
        a = math.sqrt(float(vec[0]) ** 2 + float(vec[1]) ** 2 + float(vec[2]) ** 2)
        if a > self._imu_peak_g:
            self._imu_peak_g = a
        self._imu_n += 1

    def _housekeeping(self) -> None:
        now = self.clock()
        for msg in self.reader.poll():
            self._handle(msg)
        if self._last_frame_t is None or \
                now - self._last_frame_t > self.cfg.camera.stall_periods / self.fps:
            # no frames (camera stalled): keep the IMU read going at the summary rate;
            # otherwise the IMU is read once per frame, with the frame
            if now >= self._next_imu:
                vec, bits = self.imu.read(self._imu_out)
                self._imu_faults = int(bits)
                self._imu_acc(vec)
        if self._last_frame_t is not None and self._camera_stalled(now):
            self._pipe_faults = 0                 # no frame: the pipeline's bits are old
            # a live camera silent this long is reopened (once per stall; a grab that
            # is still blocked in the driver reopens when it returns)
            if (not self.feed.lossless and not self._reopen_asked
                    and now - self._wait_since > REOPEN_AFTER_S):
                self._reopen_asked = True
                self.feed.reopen()
        elif self._last_frame_t is not None:
            self._reopen_asked = False
        self._update_faults(self._fault_bits())
        if now >= self._next_imu:
            self._send_imu()
            self._next_imu = now + 1.0 / self.cfg.imu.summary_hz
        if now >= self._next_hb:
            self._send("heartbeat", self.proto_heartbeat())
            self._next_hb = now + 1.0 / self.cfg.serial.heartbeat_hz
        self.writer.pump()
        if now >= self._next_status:
            self.write_status()
            self._next_status = now + self.cfg.status.interval_s
        if not self._ready:
            self._ready = True
            self._notify("READY=1")
        self.watchdog.tick(now)

    def _notify(self, state: str) -> None:
        if self.notify is not None:
            self.notify(state)
            return
        from device.pi.runtime.sdnotify import notify
        notify(state)

    def _send_imu(self) -> None:
        n = max(self._imu_n, 1)
        mean = self._imu_sum / n
        msg = self.proto_imu(mean, self._imu_peak_g, self._imu_n,
                             self._fault_bits() if self._imu_faults else 0)
        self._imu_sum[:] = 0
        self._imu_peak_g = 0.0
        self._imu_n = 0
        self._send("imu", msg)

    def _handle(self, msg) -> None:
        p = self.proto
        if isinstance(msg, p.Gait):
            self.gait_packets += 1
            self.gait = gait_from_message(msg, self.clock())
        elif isinstance(msg, p.Command):
            self.commands += 1
            op = command_op(msg)
            if op == "rezero":
                self.rezero("command")
            elif op == "rate":
                fps = _finite(command_value(msg), 0.0)
                if 1.0 <= fps <= 1000.0:
                    self.fps = fps
                    if self.camera_opts is not None:      # a live camera: ask it for the rate
                        self.camera_opts["fps"] = fps
                        self.feed.reopen()
            elif op == "status":
                self._send("status", self.proto_heartbeat())
                self.write_status(force=True)

    # -- status ----------------------------------------------------------------
    def status(self) -> dict:
        w = self.writer
        return {"pid": os.getpid(), "t_unix": time.time(), "frames": self.frames,
                "packets_sent": w.packets_sent, "packets_dropped": w.packets_dropped,
                "faults": self.faults, "fault_names": all_fault_names(self.faults),
                "fault_changes": self.fault_changes, "camera_opens": self.feed.opens,
                "camera_errors": self.feed.errors, "gait_packets": self.gait_packets,
                "commands": self.commands, "rezeros": dict(self.rezeros),
                "models": list(self.models.loaded), "fps": self.fps}

    def write_status(self, force: bool = False) -> None:
        if not self.status_path:
            return
        path = Path(self.status_path)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            tmp.write_text(json.dumps(self.status()))
            os.replace(tmp, path)
        except OSError:
            pass

    def close(self) -> None:
        self._update_faults(self._fault_bits())   # before the feed stops on purpose
        self.feed.stop()
        for _ in range(3):
            self.writer.pump()
        self.write_status(force=True)
        self._notify("STOPPING=1")
        if self.json_log is not None:
            self.json_log.flush()

    # -- message builders (device.pi.runtime.protocol) ---------------------------------
    def proto_surface(self, class_id, probs, contact, slip, slip_conf, dir_deg, mag_px,
                      pressure, pins, faults, texture_id=None):
        return surface_message(self.proto, class_id, probs, contact, slip, slip_conf, dir_deg,
                               mag_px, pressure, pins, faults, texture_id)

    def proto_fault(self, bits: int, raised: int = 0):
        return fault_message(self.proto, bits, raised, self._pins_lost)

    def proto_heartbeat(self):
        return heartbeat_message(self.proto, self)

    def proto_imu(self, mean, peak_g, samples, faults):
        return imu_message(self.proto, mean, peak_g, samples, faults)


# ---------------------------------------------------------------------------
# The protocol's messages (field names of device.pi.runtime.protocol)
# ---------------------------------------------------------------------------

def _cpu_temp_c() -> int:
    try:
        with open("/sys/class/thermal/thermal_zone0/temp") as fh:
            return int(round(int(fh.read().strip()) / 1000.0))
    except (OSError, ValueError):
        return -128


def surface_message(p, class_id, probs, contact, slip, slip_conf, dir_deg, mag_px, pressure,
                    pins, faults, texture_id=None):
    return p.Surface(class_id=int(class_id), probs=tuple(float(x) for x in probs),
                     contact=bool(contact), slip=bool(slip), slip_conf=float(slip_conf),
                     shear_dir_deg=float(dir_deg), shear_px=float(mag_px),
                     load_n=0.0 if pressure is None else float(pressure), pins=int(pins),
                     faults=int(faults) & 0xFFFF,
                     texture_id=p.TEXTURE_NONE if texture_id is None else int(texture_id))


def fault_message(p, bits, raised=0, pins_lost=0):
    return p.Fault(faults=int(bits) & 0xFFFF, raised=int(raised) & 0xFFFF,
                   pins_lost=int(pins_lost))


def heartbeat_message(p, rt):
    return p.Heartbeat(uptime_s=int(rt.clock() - rt._t0), rate_fps=float(rt.fps),
                       frames_dropped=min(int(rt.writer.packets_dropped), 0xFFFF),
                       temp_c=_cpu_temp_c(), faults=int(rt.faults) & 0xFFFF)


def imu_message(p, mean, peak_g, samples, faults):
    return p.ImuSummary(acc_mg=tuple(float(x) * 1000.0 for x in mean[:3]),
                        gyro_dps=tuple(float(x) for x in mean[3:6]),
                        acc_peak_mg=float(peak_g) * 1000.0, samples=min(int(samples), 255),
                        faults=int(faults) & 0xFFFF)


def gait_from_message(msg, t: float) -> Gait:
    v = msg.vel_mm_s
    vel = math.hypot(_finite(v[0]), _finite(v[1])) if len(v) >= 2 else abs(_finite(v[0]))
    return Gait(stance=int(msg.phase) == 0, load_n=max(0.0, _finite(msg.load_n)),
                vel_mm_s=vel, t=t)


def command_op(msg) -> str:
    return {1: "rezero", 2: "rate", 3: "status"}.get(int(msg.command), "unknown")


def command_value(msg):
    return msg.arg


# ---------------------------------------------------------------------------
# Building from source strings
# ---------------------------------------------------------------------------

def build_runtime(camera: str, imu: str, serial: str, *, models_dir=None, config=None,
                  fps: float | None = None, json_log: str | None = None,
                  status: str | None = None, frames: int | None = None,
                  float_models: bool = False, port=None, notify=None) -> LegRuntime:
    """A runtime from the command line's strings; StartupError (exit 2) for a bad
    config, model, source or port."""
    from device.config import ConfigError
    from device.pi.models.artefact import ModelError
    from device.pi.sources.camera import CameraError, open_camera
    from device.pi.sources.imu import RetryingImuSource, open_imu
    from device.pi.sources.mpu6050 import IMUError, IMUUnavailable
    from device.pi.runtime.config import load_leg_config
    from device.pi.runtime.link import LinkError, open_port

    import sys

    import cv2
    cv2.setNumThreads(1)              # one thread for the work (ONNX Runtime: intra_op 1)
    sys.setswitchinterval(0.001)      # hand a grabbed frame to the loop without a 5 ms wait
    try:
        cfg = load_leg_config(config)
    except ConfigError as exc:
        raise StartupError(str(exc)) from None
    if fps is not None:
        if not (isinstance(fps, (int, float)) and math.isfinite(fps) and 1 <= fps <= 1000):
            raise StartupError(f"--fps must be a number 1..1000, got {fps!r}")
        cfg.camera.fps = float(fps)
    try:
        from device.profile import load_pipeline_profile
        load_pipeline_profile(cfg.models.profile)
    except Exception as exc:
        raise StartupError(f"{cfg.source or 'config'}: models.profile: {exc}") from None
    live = camera.lower().startswith("v4l2://")
    opts = {}
    if live:
        from urllib.parse import parse_qsl, urlsplit
        q = dict(parse_qsl(urlsplit(camera).query))
        c = cfg.camera
        for k, v in (("width", c.width), ("height", c.height), ("fps", c.fps),
                     ("fourcc", c.fourcc), ("buffersize", c.buffersize)):
            if k not in q:
                opts[k] = v

    def factory():
        return open_camera(camera, **opts)

    first = None
    opened = []                            # closed again if start-up fails later

    def fail(msg: str):
        for r in opened:
            try:
                r.close()
            except Exception:
                pass
        raise StartupError(msg)

    try:
        first = factory()
        opened.append(first)
    except CameraError as exc:
        if not live:
            raise StartupError(f"--camera {camera!r}: cannot open: {exc}") from None
        first = None                     # a live camera not there yet: fault + retries
    except ValueError as exc:
        raise StartupError(f"--camera: {exc}") from None
    if fps is None and first is not None and first.fps:
        cfg.camera.fps = float(first.fps)      # the rate the source actually runs at
    try:
        n_pins = _layout_pins(cfg.models.profile)
        models = load_models(models_dir, "float" if float_models else cfg.models.variant,
                             n_pins, cfg)
    except (ModelError, ValueError) as exc:
        fail(str(exc))
    try:
        imu_src = open_imu(imu)
        opened.append(imu_src)
    except IMUUnavailable as exc:
        # nothing answers yet: run with the IMU fault set and keep trying (a wrong
        # device or a bad option below still refuses to start)
        print(f"device.pi run: warning: --imu: {exc}; running with the IMU fault set, "
              f"retrying", file=sys.stderr)
        imu_src = RetryingImuSource(imu, exc)
        opened.append(imu_src)
    except (ValueError, IMUError) as exc:
        fail(f"--imu: {exc}")
    if port is None:
        try:
            port = open_port(serial, cfg.serial.baudrate)
            opened.append(port)
        except LinkError as exc:
            fail(str(exc))
    log = None
    if json_log:
        try:
            log = open(json_log, "w", buffering=1)     # line by line: greppable live
        except OSError as exc:
            fail(f"--json-log {json_log!r}: {exc}")
    return LegRuntime(cfg, factory, imu_src, port, models, lossless=not live, fps=cfg.camera.fps,
                      json_log=log, status_path=status, max_frames=frames, first_camera=first,
                      notify=notify, camera_opts=opts if live else None)


def _layout_pins(profile: str) -> int:
    from device.pi.vision.layout import layout_for_profile
    return int(len(layout_for_profile(profile)))
