"""The leg runtime: camera + IMU in, surface decisions out over the UART.

``python -m device.pi run --camera v4l2:///dev/video0 --imu i2c://1/0x68 --serial
/dev/serial0`` (or ``sim://walk`` for the camera and the IMU and ``loop://`` for the port, with no
hardware). See
docs/runtime.md for the options, the config keys, the packets and the fault handling.

One loop, one thread for the work (a second thread only grabs frames, so a camera
that blocks or vanishes cannot stall the loop):

    frame -> MarkerStream -> fixed pin layout -> rolling windows -> models (ONNX
    Runtime, int8, one thread: the fused graph of every model, one call per frame, or
    one session each) or the paper's rules with the gait context -> decision ->
    SURFACE packet -> non-blocking writer

and around it, on every pass, with or without a frame: the MCU's GAIT / COMMAND
packets are read, the IMU summary and the HEARTBEAT go out at their rates, a change
of the fault state sends FAULT at once, the status file is rewritten and the
systemd watchdog is fed.
"""
from __future__ import annotations

import logging
import math
import os
import time
from collections import deque

import numpy as np

from device.checks import FPS_MAX_HZ, FPS_MIN_HZ
from device.pi.faults import (FAULT_BAD_FRAME, FAULT_CAMERA, FAULT_FRAME, FAULT_IMU, FAULT_LINK,
                              FAULT_MODEL, FAULT_PINS_LOST, PIPELINE_FAULTS, fault_names)
from device.pi.models.window import RollingWindow, WindowTail
from device.pi import protocol as P
from device.pi.runtime import sdnotify
from device.pi.runtime.config import LegConfig
from device.pi.runtime.decisions import (GaitContext, decide, expected_context, finite_float,
                                         gait_from_message)
from device.pi.runtime.feed import CameraFeed
from device.pi.runtime.gcpolicy import WARMUP_FRAMES, GcPolicy
from device.pi.runtime.link import LinkReader, LinkWriter
from device.pi.runtime.load import Models
from device.pi.runtime.messages import (command_op, fault_message, heartbeat_message,
                                        imu_message, surface_message)
from device.pi.runtime.stats import BoundedStats
from device.pi.runtime.status import JsonLog, write_status_file
from device.pi.vision import native
from device.pi.vision.encoder import FrameEncoder
from device.errors import TacfootError

_log = logging.getLogger(__name__)

#: a live camera that delivered nothing for this long is closed and reopened
REOPEN_AFTER_S = 1.0
#: side of the binary crop the ``frames`` input layout reads, px
CROP_PX = 32
EXIT_BAD_INPUT = 2
#: fault-state changes the runtime remembers (the newest)
FAULT_LOG = 256
#: a COMMAND request-status rewrites the status file at most this often (and at most
#: once a pass); the requests of one pass share one HEARTBEAT answer. A write costs
#: 0.3-0.5 ms (more on an SD card); the MCU's surface_link asks at most this often too
STATUS_ANSWER_GAP_S = 0.05


class StartupError(TacfootError):
    """The runtime cannot start: a bad config, model, source or port (exit 2)."""


# ---------------------------------------------------------------------------
# The runtime
# ---------------------------------------------------------------------------

class LegRuntime:
    """The loop. Build it with :func:`build_runtime` (sources from strings) or
    directly with stand-ins (tests): ``camera_factory()`` returns a camera source,
    ``imu`` has ``read()``, ``port`` is a pyserial-like port."""

    def __init__(self, cfg: LegConfig, camera_factory, imu, port, models: Models, *,
                 lossless: bool = True, fps: float | None = None, json_log=None,
                 status_path: str | None = None, max_frames: int | None = None,
                 first_camera=None, clock=time.monotonic, notify=None, camera_opts=None,
                 gc_warmup_frames: int | None = WARMUP_FRAMES):
        self.cfg = cfg
        self.camera_opts = camera_opts        # the live camera's open options (set rate)
        self.clock = clock
        self.fps = float(fps or cfg.camera.fps)
        self.models = models
        need_crop = any(getattr(c, "input_layout", "") == "frames"
                        for c in (models.surface, models.texture, models.slip) if c is not None)
        self.encoder = FrameEncoder(models.profile_source or cfg.models.profile,
                                    crop_px=CROP_PX if need_crop else None,
                                    localiser=models.localiser, reacquire=cfg.rezero.reacquire)
        self.stream = self.encoder.stream
        self.n_pins = self.encoder.n_pins
        self._prev_v = np.zeros((self.n_pins, 2), np.float32)
        Ts = {models.rule.T}
        for c in (models.surface, models.texture, models.slip):
            if c is not None:
                Ts.add(c.T)
        if models.pressure is not None:
            Ts.add(models.pressure.T)
        # one window of the longest T, pushed once per frame; shorter T read its tail
        self._window = RollingWindow(max(Ts), self.n_pins, self.stream.profile.grid_n)
        self.windows = {T: self._window if T == self._window.T else WindowTail(self._window, T)
                        for T in sorted(Ts)}
        self.imu = imu
        self._imu_out = np.zeros(6, np.float32)
        self._imu_sum = np.zeros(6, np.float64)
        self._imu_peak_g = 0.0
        self._imu_n = 0
        self.port = port
        self.writer = LinkWriter(port, stall_ms=cfg.serial.stall_ms, clock=clock)
        self.reader = LinkReader(port, clock=clock)
        self.feed = CameraFeed(camera_factory, lossless=lossless,
                               reopen_min_s=cfg.camera.reopen_min_s,
                               reopen_max_s=cfg.camera.reopen_max_s, first=first_camera,
                               clock=clock)
        self.json_log = None if json_log is None else JsonLog(json_log)
        self.mcap = None          # an McapLog (device/pi/runtime/mcaplog.py), set by --mcap
        self.status_path = status_path
        self.max_frames = max_frames
        self.notify = notify
        # state
        self.seq = 0
        self.frames = 0
        self.faults = 0
        self._pins_lost = 0
        self.fault_changes = 0
        self.gait: GaitContext | None = None
        self.gait_packets = 0
        self.commands = 0
        self.rates_refused = 0          # rate COMMANDs outside --fps's bound, ignored
        self.gait_refused = 0           # GAITs with a phase not 0/1 or flagged non-finite
        self.gait_clamped = 0           # GAITs flagged clamped, used as sent
        self.status_requests = 0        # COMMAND request-status received
        self.status_requests_coalesced = 0   # answered with an earlier one of their pass
        self._status_asked = False
        self._status_t = -1e18          # when the status file was last written
        self.rezeros = {"command": 0, "auto": 0}
        self._last_rezero = -1e9
        self._still = 0
        self._pipe_faults = 0
        self._skipped_seen = 0
        self._last_index = -1             # the index of the last frame processed
        self._imu_faults = 0
        self._model_fault = False
        self._t0 = clock()
        self._last_frame_t = None
        self._wait_since = self._t0
        self._next_hb = self._t0
        self._next_imu = self._t0
        self._next_status = self._t0
        self._next_fault_repeat = 1e18
        # bounded, however long the run: see device/pi/runtime/stats.py
        self.latency_ms = BoundedStats()
        self.cpu_ms = BoundedStats()           # thread CPU time per frame
        self.fault_log: deque[tuple[float, int]] = deque(maxlen=FAULT_LOG)  # (clock, bits)
        self.stopped = False
        self._ready = False
        self._status_warned = False
        self._reopen_asked = False
        self.watchdog = sdnotify.Watchdog()
        # a full collection before the loop, the survivors frozen after the warm-up
        self.gc = GcPolicy(gc_warmup_frames)

    # -- packets ---------------------------------------------------------------
    def _t_ms(self) -> int:
        return int((self.clock() - self._t0) * 1000.0) & 0xFFFFFFFF

    def _next_seq(self) -> int:
        s = self.seq
        self.seq = (self.seq + 1) & 0xFFFF
        return s

    def _send(self, kind: str, msg) -> None:
        seq, t_ms = self._next_seq(), self._t_ms()
        self.writer.send(kind, msg.msg_type, msg.encode(seq, t_ms))
        if self.mcap is not None:
            self.mcap.packet("out", msg, self.clock(), seq, t_ms)

    # -- the loop --------------------------------------------------------------
    def start(self) -> None:
        self.gc.start()
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
        self.gc.frame_done(self.frames)
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
        gap = int(frame.index) - self._last_index          # > 1: frames were dropped
        self._last_index = int(frame.index)
        ef = self.encoder.encode(frame.image, frame.t_s, gap)   # the tracker bounds it
        ff = ef.features
        self._pipe_faults = int(ff.faults) & PIPELINE_FAULTS
        if self.feed.skipped != self._skipped_seen:   # a bad file frame was skipped before it
            self._skipped_seen = self.feed.skipped
            self._pipe_faults |= FAULT_BAD_FRAME
        if self.stream.reference is not None and len(ff.lost):
            self._pins_lost = int(ff.lost.sum())
            if self._pins_lost * 2 > len(ff.lost):
                self._pipe_faults |= FAULT_PINS_LOST
        else:
            self._pins_lost = 0
        v = ef.vectors
        frame_ok = not ff.faults & FAULT_FRAME     # an implausible frame never enters a window
        if frame_ok:
            self._window.push(vectors=v, imu=imu_vec, grid=ff.grid, frame=ef.crop)
        exp_mag, exp_motion, gait = expected_context(self.gait, self.clock(),
                                                     self.cfg.decision, self.fps)
        d = decide(self.models, self.windows, contact_seen=bool(ff.contact),
                   referenced=self.stream.reference is not None, expected_mag_px=exp_mag,
                   expected_motion_px=exp_motion, gait=gait,
                   gait_rule_weight=self.cfg.decision.gait_rule_weight, frame_ok=frame_ok)
        self._model_fault = d.model_fault
        contact, texture = d.contact, d.texture
        self._auto_rezero(v, ef.lost, contact or not frame_ok, gait)   # garbage is not "still"
        faults = self._fault_bits()
        msg = surface_message(d.class_id, d.probs, contact, d.slip, d.slip_conf,
                              ff.direction_deg, float(ff.magnitude), d.pressure,
                              len(ff.pins), faults, texture[2] if texture else None)
        self._send("surface", msg)
        self._update_faults(faults)
        before = self.writer.packets_sent
        self.writer.pump()
        t_done = self.clock()
        self.cpu_ms.add((time.thread_time() - c0) * 1e3)
        lat = None
        if self.writer.packets_sent > before and self.writer.pending == 0:
            lat = (t_done - t_avail) * 1e3
            self.latency_ms.add(lat)
        if self.json_log is None and self.mcap is None:
            return
        # the decision log line, built after the packet went out
        meas = d.measures
        dec = {"frame": self.frames - 1, "index": int(frame.index),
               "t_s": round(float(frame.t_s), 6), "class": P.SURFACE_CLASSES[d.class_id],
               "class_id": d.class_id, "probs": [round(float(x), 4) for x in d.probs],
               "contact": contact, "pipeline_contact": bool(ff.contact),
               "slip": d.slip, "slip_conf": round(d.slip_conf, 4),
               "texture": texture[0] if texture else None,
               "shear_dir_deg": round(ff.direction_deg, 2),
               "shear_mag_px": round(float(ff.magnitude), 3),
               "pressure": None if d.pressure is None else round(float(d.pressure), 4),
               "pins": int(len(ff.pins)), "faults": fault_names(faults),
               "expected_mag_px": round(exp_mag, 3) if exp_mag is not None else None,
               "expected_motion_px": round(exp_motion, 4) if exp_motion is not None else None,
               "gait": gait, "magnitude_px": round(float(meas.get("magnitude_px", 0.0)), 3),
               "motion_px": (None if meas.get("motion_px") is None
                             else round(float(meas["motion_px"]), 4)),
               "latency_ms": None if lat is None else round(lat, 4)}
        if d.model_probs is not None:
            dec["model_probs"] = [round(float(x), 4) for x in d.model_probs]
            dec["rule_probs"] = [round(float(x), 4) for x in d.rule_probs]
        if self.json_log is not None:
            self.json_log.write(dec)
        if self.mcap is not None:      # after the packet: its cost is off the latency
            self.mcap.frame(dec, d, frame, ef, imu_vec, faults, t_avail, t_done,
                            self.stream.reference)

    def _auto_rezero(self, v, lost, contact: bool, gait) -> None:
        rz = self.cfg.rezero
        if not rz.auto or gait is None or gait["stance"] or contact \
                or self.stream.reference is None:
            self._prev_v[:] = v
            self._still = 0
            return
        ok = ~lost          # the step is only measured when it can lead to a re-zero
        step = (float(np.hypot(*(v[ok] - self._prev_v[ok]).T).mean()) if ok.any() else 0.0)
        self._prev_v[:] = v
        self._still = self._still + 1 if step < rz.still_px else 0
        if self._still >= rz.still_frames and \
                self.clock() - self._last_rezero >= rz.min_interval_s:
            self.rezero("auto")

    def rezero(self, why: str) -> None:
        self.stream.rezero()
        self._window.clear()
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
            self._send("fault", fault_message(bits, raised, self._pins_lost))
            self._next_fault_repeat = now + self.cfg.serial.fault_repeat_s if bits else 1e18
        elif bits and now >= self._next_fault_repeat:
            self._send("fault", fault_message(bits, 0, self._pins_lost))
            self._next_fault_repeat = now + self.cfg.serial.fault_repeat_s

    def _imu_acc(self, vec) -> None:
        self._imu_sum += vec
        a = math.sqrt(float(vec[0]) ** 2 + float(vec[1]) ** 2 + float(vec[2]) ** 2)
        if a > self._imu_peak_g:
            self._imu_peak_g = a
        self._imu_n += 1

    def _housekeeping(self) -> None:
        now = self.clock()
        for msg, t_sent in self.reader.poll_timed():
            self._handle(msg, t_sent)
        if self._status_asked:            # this pass's requests: one answer, and the
            self._status_asked = False    # file at most every STATUS_ANSWER_GAP_S
            self._send("status", self._heartbeat())
            self._next_status = min(self._next_status,
                                    max(now, self._status_t + STATUS_ANSWER_GAP_S))
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
            self._send("heartbeat", self._heartbeat())
            self._next_hb = now + 1.0 / self.cfg.serial.heartbeat_hz
        self.writer.pump()
        if now >= self._next_status:
            self.write_status()
            self._status_t = now
            self._next_status = now + self.cfg.status.interval_s
        if not self._ready:
            self._ready = True
            self._notify("READY=1")
        self.watchdog.tick(now)

    def _notify(self, state: str) -> None:
        if self.notify is not None:
            self.notify(state)
            return
        sdnotify.notify(state)

    def _send_imu(self) -> None:
        n = max(self._imu_n, 1)
        mean = self._imu_sum / n
        msg = imu_message(mean, self._imu_peak_g, self._imu_n,
                          self._fault_bits() if self._imu_faults else 0)
        self._imu_sum[:] = 0
        self._imu_peak_g = 0.0
        self._imu_n = 0
        self._send("imu", msg)

    def _handle(self, msg, t_sent: float) -> None:
        if self.mcap is not None:
            self.mcap.packet("in", msg, self.clock())
        if isinstance(msg, P.Gait):
            self.gait_packets += 1
            # a phase that is neither stance nor swing, or a value the MCU sent as 0
            # for NaN/inf, is no context: refused (the last one ages out); clamped
            # values are at their field's end, on the right side: used, counted
            if msg.phase not in (P.PHASE_STANCE, P.PHASE_SWING) or \
                    msg.flags & P.GAIT_FLAG_NONFINITE:
                self.gait_refused += 1
                return
            if msg.flags & P.GAIT_FLAG_CLAMPED:
                self.gait_clamped += 1
            self.gait = gait_from_message(msg, t_sent)
        elif isinstance(msg, P.Command):
            self.commands += 1
            op = command_op(msg)
            if op == "rezero":
                self.rezero("command")
            elif op == "rate":
                fps = finite_float(msg.arg, 0.0)
                if FPS_MIN_HZ <= fps <= FPS_MAX_HZ:          # --fps's bound, as on the MCU
                    self.fps = fps
                    if self.camera_opts is not None:      # a live camera: ask it for the rate
                        self.camera_opts["fps"] = fps
                        self.feed.reopen()
                else:
                    self.rates_refused += 1
            elif op == "status":              # answered once per pass (_housekeeping)
                self.status_requests += 1
                self.status_requests_coalesced += self._status_asked
                self._status_asked = True

    # -- status ----------------------------------------------------------------
    def status(self) -> dict:
        w = self.writer
        return {"pid": os.getpid(), "t_unix": time.time(), "frames": self.frames,
                "packets_sent": w.packets_sent, "packets_dropped": w.packets_dropped,
                "faults": self.faults, "fault_names": fault_names(self.faults),
                "fault_changes": self.fault_changes, "camera_opens": self.feed.opens,
                "camera_errors": self.feed.errors, "frames_skipped": self.feed.skipped,
                "frames_dropped_behind": self.feed.dropped,
                "gait_packets": self.gait_packets, "gait_refused": self.gait_refused,
                "gait_clamped": self.gait_clamped,
                "commands": self.commands, "rates_refused": self.rates_refused,
                "status_requests": self.status_requests,
                "status_requests_coalesced": self.status_requests_coalesced,
                "link_messages_dropped": self.reader.messages_dropped,
                "rezeros": dict(self.rezeros),
                "models": list(self.models.loaded), "fps": self.fps,
                "profile": {"name": self.stream.profile.name,
                            "source": str(self.models.profile_source or self.cfg.models.profile),
                            "pins": int(self.n_pins)},
                "rules_only": not self.models.loaded,
                "models_fused": self.models.fused is not None,
                "tracker": self._tracker_status(),
                "layout_alignment": self._layout_status(),
                "gc": self.gc.status(), "packets_pending": w.pending, "faults_coalesced": w.faults_coalesced,
                "link_write_errors": w.write_errors, "json_log_lines_lost":
                    0 if self.json_log is None else self.json_log.lines_lost,
                **({} if self.mcap is None else self.mcap.status())}

    def _layout_status(self) -> dict | None:
        """How the current reference lined up with the profile's pin layout (shift,
        scale, rotation, residual, matched pins; :class:`LayoutAlignment`), or None
        before the first reference."""
        a = self.encoder.mapper.alignment
        return None if a is None else a.summary()

    def _tracker_status(self) -> dict:
        t = self.stream.tracker
        return {"matcher": "compiled" if native.active() else "numpy",
                "matcher_reason": native.status(), "reacquire": t.reacquire,
                "reacquisitions": t.reacquisitions, "reacquire_errors": t.reacquire_errors}

    def write_status(self) -> None:
        """Rewrite the status file now (the loop calls it every status interval,
        :meth:`close` once more at the end); a refusal is said once, then retried."""
        if not self.status_path:
            return
        ok = write_status_file(self.status_path, self.status())
        if not ok and not self._status_warned:     # once: the file system refused
            self._status_warned = True
            _log.warning("device.pi run: warning: --status %s: cannot write the status "
                         "file; retrying", self.status_path)
        elif ok:
            self._status_warned = False

    def close(self) -> None:
        self._update_faults(self._fault_bits())   # before the feed stops on purpose
        self.feed.stop()
        for _ in range(3):
            self.writer.pump()
        if self.mcap is not None:     # first: the status then counts what it lost
            self.mcap.close()
        self.write_status()
        self._notify("STOPPING=1")
        if self.json_log is not None:
            self.json_log.flush()
        self.gc.close()

    def _heartbeat(self) -> P.Heartbeat:
        return heartbeat_message(self.clock() - self._t0, self.fps,
                                 self.writer.packets_dropped, self.faults)
