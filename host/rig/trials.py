"""``host rig``: unattended trials on the data-collection rig (docs/rig.md).

    host rig check TRIALS.toml                       validate a trial file
    host rig run TRIALS.toml --rig /dev/ttyACM0|sim:// --camera v4l2:///dev/video0|sim://
                 --out DATASET [--resume]

A trial file is validated completely before anything moves. Each trial is one
repetition of one action variant on one base plate (a press at one depth, a drag
in one direction at one load and speed). While a trial runs, the camera records
and the rig streams its position, load and IMU; rig times are put on the host
clock with the NTP-style offset estimated at the start of each trial. Every
trial is written atomically in the dataset format (docs/datasets.md), so a crash
or unplug loses at most the trial in progress, and ``--resume`` runs only the
trials not yet in the dataset.
"""
from __future__ import annotations

import json
import logging
import sys
import threading
import time
from pathlib import Path

import numpy as np

from device.checks import serial_url
from device.config import ConfigError
from device.sim.scene import SURFACE_LABELS, TEXTURE_LABELS
from host.rig.plan import DIRECTIONS, Plan, RigLimits, Trial, Variant
from host.extras import need
from device.errors import TacfootError

RUN_STATE = "rig_run.json"


class RigSetupError(TacfootError, ValueError):
    """The rig or the camera cannot be opened or does not answer: nothing ran."""


CONTACT_FLOOR_N = 0.5          # as the simulator's ground truth (docs/datasets.md)
TOUCH_N = 0.05                 # the firmware's touch threshold (50 mN)
STREAM_PERIOD_MS = 5


# -- cameras ----------------------------------------------------------------------------------
class CameraRecorder:
    """Records a live camera (any ``open_camera`` source) on a thread between
    start() and stop(); frames are converted to grey."""

    def __init__(self, url: str):
        from device.pi.sources.camera import open_camera
        self.url = url
        self.cam = open_camera(url)
        self.width, self.height = self.cam.width, self.cam.height
        self.fps = self.cam.fps or 30.0
        self._frames: list = []
        self._stop = threading.Event()
        self._thread = None
        self.error: BaseException | None = None

    def start(self) -> None:
        self._frames = []
        self.error = None
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, daemon=True, name="camera")
        self._thread.start()

    def _loop(self) -> None:
        import cv2
        while not self._stop.is_set():
            try:
                fr = self.cam.read()
            except Exception as exc:       # CameraError: unplugged
                self.error = exc
                return
            if fr is None:
                return
            img = fr.image
            if img.ndim == 3:
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            # a live camera stamps frames with time.monotonic() at the grab; files and
            # folders carry stream time, so they are stamped on arrival instead
            live = self.url.startswith("v4l2://") and fr.t_s is not None
            self._frames.append((fr.t_s if live else time.monotonic(), img.copy()))

    def stop(self):
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self.error is not None:
            raise RuntimeError(f"camera {self.url}: {self.error}")
        if not self._frames:
            return np.zeros((0, self.height, self.width), np.uint8), np.zeros(0)
        return (np.stack([f for _, f in self._frames]),
                np.array([t for t, _ in self._frames], float))

    def close(self) -> None:
        self._stop.set()
        self.cam.close()


# -- the connection -----------------------------------------------------------------------------
class Connection:
    """The rig link: opens ``--rig`` (a pyserial URL/path or ``sim://``), and
    reopens it after an unplug."""

    def __init__(self, url: str, seed: int = 0):
        self.url = url
        self.sim = None
        if url.startswith("sim://"):
            from host.rig.sim import SimRig
            self.sim = SimRig(url, seed=seed)
        self.client = None
        self.open()

    def open(self):
        import serial
        from host.rig.link import RigClient
        if self.sim is not None:
            port = serial.Serial(self.sim.port, 115200, timeout=0.02)
        else:
            port = serial.serial_for_url(serial_url(self.url), 115200, timeout=0.02)
        self.client = RigClient(port)
        return self.client

    def reconnect(self, timeout_s: float = 20.0) -> None:
        """Close, wait for the device to come back, reopen and check it answers."""
        from host.rig.link import RigError
        self.client.close()
        end = time.monotonic() + timeout_s
        last = None
        while time.monotonic() < end:
            try:
                if self.sim is not None:
                    self.sim.reconnect()
                self.open()
                self.client.sync_clock(n=3)
                return
            except (RigError, OSError) as exc:
                last = exc
                if self.client is not None:
                    self.client.close()
                time.sleep(0.5)
        raise ConnectionError(f"rig {self.url} did not come back within {timeout_s:g} s: {last}")

    def close(self) -> None:
        if self.client is not None:
            for quiet in (self.client.stop, lambda: self.client.stream(0)):
                try:
                    quiet()                   # Ctrl-C mid-trial: stop the axes now
                except Exception:
                    pass
            self.client.close()
        if self.sim is not None:
            self.sim.close()


# -- keys ---------------------------------------------------------------------------------------
class Keys:
    """p: pause/resume between trials, q: stop after this trial (on a TTY only)."""

    def __init__(self, enabled: bool):
        self.paused = threading.Event()
        self.quit = threading.Event()
        self._old = None
        if not enabled or not sys.stdin.isatty():
            return
        import termios
        import tty
        fd = sys.stdin.fileno()
        self._old = termios.tcgetattr(fd)
        tty.setcbreak(fd)
        threading.Thread(target=self._loop, daemon=True, name="keys").start()

    def _loop(self) -> None:
        import select
        while not self.quit.is_set():
            r, _, _ = select.select([sys.stdin], [], [], 0.2)
            if not r:
                continue
            ch = sys.stdin.read(1).lower()
            if ch == "p":
                if self.paused.is_set():
                    self.paused.clear()
                else:
                    self.paused.set()
                print("\n[paused: p to resume, q to stop]" if self.paused.is_set()
                      else "\n[resumed]", file=sys.stderr)
            elif ch == "q":
                self.quit.set()
                print("\n[stopping after this trial]", file=sys.stderr)

    def restore(self) -> None:
        if self._old is not None:
            import termios
            termios.tcsetattr(sys.stdin.fileno(), termios.TCSADRAIN, self._old)
            self._old = None


# -- recording one trial ------------------------------------------------------------------------
def record_trial(client, camera, trial: Trial, lim: RigLimits) -> tuple:
    """Run one trial; return (frames, truth, info). Raises RigError/LinkLost."""
    v = trial.variant
    client.samples = []                    # keep only this trial's samples in memory
    client.pongs = client.pongs[-50:]
    sync = client.sync_clock(n=8, gap_s=0.005)
    client.move_to(lim.surface_mm - lim.approach_mm, 0.0)
    s0 = len(client.samples)
    camera.start()
    t_start = time.monotonic()
    try:
        time.sleep(0.05)
        if v.action == "press":
            client.press_depth(v.depth_mm, v.press_speed_mm_s)
            time.sleep(v.hold_s)
        else:
            client.press_load(v.load_n, v.press_speed_mm_s)
            sign = DIRECTIONS[v.direction]
            if sign:
                client.drag(sign * v.distance_mm, v.speed_mm_s,
                            timeout=v.distance_mm / v.speed_mm_s + 5.0)
            time.sleep(v.hold_s)
        client.lift(lim.approach_mm)
        time.sleep(0.05)
    finally:
        frames, t_frames = camera.stop()
    samples = client.samples[s0:]
    if sign_drag(v):
        client.drag(-DIRECTIONS[v.direction] * v.distance_mm, lim.max_speed_mm_s / 2,
                    timeout=v.distance_mm / (lim.max_speed_mm_s / 2) + 5.0)   # back to centre
    if len(frames) < 2:
        raise RuntimeError(f"camera gave {len(frames)} frames")
    if len(samples) < 2:
        raise RuntimeError("the rig streamed no samples")
    truth = align(samples, t_frames, sync["offset_ms"], trial, lim)
    fps = (len(t_frames) - 1) / max(t_frames[-1] - t_frames[0], 1e-9)
    info = {"trial_id": trial.id, "plate": trial.plate.name, "variant": v.key,
            "scene": f"rig:{v.key}", "seed": trial.rep, "fps": round(float(fps), 3),
            "width": int(frames.shape[2]), "height": int(frames.shape[1]),
            "clock_offset_ms": round(sync["offset_ms"], 3), "clock_rtt_ms": round(sync["rtt_ms"], 3),
            "clock_spread_ms": round(sync["spread_ms"], 3), "samples": len(samples),
            "t_start_host_s": t_start}
    return frames, truth, info


def recover(client, lim: RigLimits) -> None:
    """After a failed trial: lift, and drag x back to the centre."""
    client.lift(lim.approach_mm)
    x = client.read().x_mm
    if abs(x) > 0.05:
        v = lim.max_speed_mm_s / 2
        client.drag(-x, v, timeout=abs(x) / v + 5.0)


def sign_drag(v: Variant) -> bool:
    return v.action == "drag" and DIRECTIONS.get(v.direction, 0) != 0


def align(samples, t_frames: np.ndarray, offset_ms: float, trial: Trial, lim: RigLimits) -> dict:
    """Per-frame truth from the rig's samples, on the host clock."""
    t_s = np.array([(s.t_rig_ms - offset_ms) / 1000.0 for s in samples])
    order = np.argsort(t_s, kind="stable")
    t_s = t_s[order]
    # samples closer than 1 us in time are one sample (np.interp's slope between
    # them would overflow): keep the last of each such run
    keep = np.append(np.diff(t_s) > 1e-6, True)
    order, t_s = order[keep], t_s[keep]
    z = np.array([samples[i].z_mm for i in order])
    x = np.array([samples[i].x_mm for i in order])
    load = np.array([samples[i].load_n for i in order])
    imu = np.array([samples[i].imu for i in order], float).reshape(-1, 6)
    tf = np.asarray(t_frames, float)
    zf = np.interp(tf, t_s, z)
    xf = np.interp(tf, t_s, x)
    lf = np.maximum(np.interp(tf, t_s, load), 0.0)
    imuf = np.column_stack([np.interp(tf, t_s, imu[:, k]) for k in range(6)])
    touched = np.flatnonzero(load >= TOUCH_N)
    z_touch = z[touched[0]] if touched.size else lim.surface_mm
    depth_cmd = zf - z_touch
    contact = lf >= CONTACT_FLOOR_N
    vx = np.zeros_like(xf)
    if len(tf) > 1:                        # x speed, mm/s (repeated frame times: 0)
        dt = np.diff(tf)
        v = np.where(dt > 1e-6, np.diff(xf) / np.maximum(dt, 1e-6), 0.0)
        vx[1:] = v
        vx[0] = v[0]
    slip = contact & (np.abs(vx) > 0.5)       # the rig drags the skin over the plate
    s_code = SURFACE_LABELS.index(trial.plate.surface)
    t_code = TEXTURE_LABELS.index(trial.plate.texture)
    return {
        "t_s": tf - tf[0], "t_host_s": tf, "load_n": lf, "depth_cmd_mm": depth_cmd,
        "depth_mm": np.maximum(depth_cmd, 0.0), "rig_z_mm": zf, "rig_x_mm": xf,
        "contact": contact, "touch": lf >= TOUCH_N, "slip": slip,
        "surface": np.where(contact, s_code, 0).astype(np.int8),
        "texture": np.where(contact, t_code, 0).astype(np.int8),
        "imu": imuf,
        "rig_samples": np.column_stack([t_s, z, x, load, imu]).astype(np.float64),
    }


# -- the run ------------------------------------------------------------------------------------
def _read_state(out: Path) -> dict:
    p = out / RUN_STATE
    if p.exists():
        try:
            return json.loads(p.read_text())
        except json.JSONDecodeError:
            return {}
    return {}


def _release(writer, out: Path, created: bool) -> None:
    """Release the dataset folder's writer lock; a folder this run created and left
    empty is removed."""
    writer.close()
    if created and writer.n_trials == 0:
        try:
            out.rmdir()
        except OSError:
            pass


def run(plan: Plan, rig_url: str, camera_url: str, out: Path | str, resume: bool = False,
        profile: str = "roboskin", progress: bool = True, keys: bool = True, yes: bool = False,
        seed: int = 0, reconnect_s: float = 20.0, log=None) -> dict:
    """Run the plan; return the summary (see docs/rig.md)."""
    from host.data.dataset import DatasetWriter, atomic_write_text, is_dataset, read_index
    from host.rig.link import LinkLost, RigError

    out = Path(out)
    log = log or logging.getLogger(__name__).info
    done_ids: set = set()
    if is_dataset(out):
        idx = read_index(out)
        done_ids = {e.get("trial_id") for e in idx["trials"]}
        mine = [t for t in plan.trials if t.id in done_ids]
        if idx["trials"] and not resume:
            raise ConfigError(f"--out {out}: already holds {len(idx['trials'])} trials "
                              f"({len(mine)} of this plan); add --resume to continue the run, "
                              f"or choose another folder")
    todo = [t for t in plan.trials if t.id not in done_ids]
    state = _read_state(out)
    state.update({"trials_file": plan.source, "plan": plan.name, "rig": rig_url,
                  "camera": camera_url})
    # failures of earlier runs stay listed until their trial is done
    prior = {k: v for k, v in (state.get("failed") or {}).items() if k not in done_ids}
    failed: dict = {}
    summary = {"trials_file": plan.source, "out": str(out), "planned": len(plan.trials),
               "done_before": len(plan.trials) - len(todo), "done": 0, "failed": [],
               "stopped_early": False, "reconnects": 0, "clock": None}
    t_run = time.monotonic()
    # the folder's writer lock first: a second run into it stops here (exit 2)
    created = not out.exists()
    writer = DatasetWriter(out, meta={"surface_labels": list(SURFACE_LABELS),
                                      "texture_labels": list(TEXTURE_LABELS)}, source="rig")
    try:
        conn = Connection(rig_url, seed=seed)
    except (OSError, ValueError) as exc:           # serial.SerialException is an OSError
        _release(writer, out, created)
        raise RigSetupError(f"--rig {rig_url}: cannot open: {exc}") from None
    camera = None
    kc = Keys(keys and progress)
    bar = None
    try:
        if camera_url.startswith("sim://"):
            from host.rig.sim import SimRigCamera, current
            if current() is None:
                raise ConfigError("--camera sim:// films the simulated rig: use it with "
                                  "--rig sim://")
            q = camera_url[len("sim://"):].lstrip("?")
            fps = float(dict(x.split("=", 1) for x in q.split("&") if "=" in x).get("fps", 60))
            camera = SimRigCamera(current(), fps=fps, seed=seed)
        else:
            try:
                camera = CameraRecorder(camera_url)
            except (OSError, ValueError) as exc:
                raise RigSetupError(f"--camera {camera_url}: cannot open: {exc}") from None
        if conn.sim is not None and not conn.sim.surface_given:
            conn.sim.carriage.surface_mm = plan.limits.surface_mm
        c = conn.client
        try:
            first_sync = c.sync_clock(n=20)
            c.stream(STREAM_PERIOD_MS)
            c.home()
        except RigError as exc:
            raise RigSetupError(f"--rig {rig_url}: {exc}") from None
        summary["clock"] = {"offset_ms": round(first_sync["offset_ms"], 3),
                            "rtt_ms": round(first_sync["rtt_ms"], 3),
                            "spread_ms": round(first_sync["spread_ms"], 3)}
        log(f"rig clock offset {first_sync['offset_ms']:+.2f} ms (rig - host), round trip "
            f"{first_sync['rtt_ms']:.2f} ms")
        tqdm = need("tqdm").tqdm
        bar = tqdm(total=len(todo), desc=plan.name, unit="trial", file=sys.stderr,
                   disable=not progress or None, smoothing=0.1)
        plate = None
        offsets = []
        for trial in todo:
            if kc.quit.is_set():
                summary["stopped_early"] = True
                break
            while kc.paused.is_set() and not kc.quit.is_set():
                time.sleep(0.1)
            if trial.plate.name != plate:
                plate = trial.plate.name
                if conn.sim is not None:
                    conn.sim.carriage.set_plate(trial.plate.sim)
                elif not yes and sys.stdin.isatty():
                    input(f"\nput the {plate!r} plate on the load cell, then press Enter ")
                else:
                    log(f"plate {plate!r} (on a real rig: swap it now)")
            try:
                frames, truth, info = record_trial(conn.client, camera, trial, plan.limits)
                offsets.append(info["clock_offset_ms"])
                info.update({"profile": profile, "n_pins": None, "effects": [],
                             "scene_file": plan.source, "rig": rig_url})
                if profile:
                    try:
                        from device.profile import load_profile
                        info["n_pins"] = load_profile(profile).n_pins
                    except ConfigError:
                        pass
                writer.add_trial(frames, truth, info)
                failed.pop(trial.id, None)
                prior.pop(trial.id, None)
                summary["done"] += 1
            except (LinkLost, ConnectionError) as exc:
                failed[trial.id] = f"link lost: {exc}"
                log(f"{trial.id}: link lost ({exc}); reconnecting")
                try:
                    conn.reconnect(reconnect_s)
                    summary["reconnects"] += 1
                    conn.client.stop()        # in case a command outlived the drop
                    conn.client.stream(STREAM_PERIOD_MS)
                    conn.client.home()
                    recover(conn.client, plan.limits)
                except (ConnectionError, RigError) as exc2:
                    failed[trial.id] += f"; reconnect failed: {exc2}"
                    summary["stopped_early"] = True
                    break
            except (RigError, RuntimeError) as exc:
                failed[trial.id] = str(exc)
                log(f"{trial.id}: failed: {exc}")
                try:
                    recover(conn.client, plan.limits)
                except RigError as exc2:
                    log(f"{trial.id}: could not lift and re-centre: {exc2}")
            finally:
                state["failed"] = {**prior, **failed}
                atomic_write_text(out / RUN_STATE, json.dumps(state, indent=1))
                bar.update(1)
        if offsets:
            summary["clock"]["drift_ms"] = round(max(offsets) - min(offsets), 3)
        if conn.sim is not None:
            summary["sim"] = {"firmware_link_lost_stops": conn.sim.firmware.link_lost,
                              "firmware_t_ms": conn.sim.firmware.t_ms}
    finally:
        kc.restore()
        if bar is not None:
            bar.close()
        if camera is not None:
            camera.close()
        conn.close()
        _release(writer, out, created)
    summary["failed"] = [{"trial": k, "reason": v} for k, v in failed.items()]
    summary["remaining"] = len(plan.trials) - summary["done_before"] - summary["done"]
    summary["elapsed_s"] = round(time.monotonic() - t_run, 2)
    return summary


def summary_text(s: dict) -> str:
    lines = [f"{s['trials_file']}: {s['done']} trial(s) done this run, {s['done_before']} before, "
             f"{len(s['failed'])} failed, {s['remaining']} of {s['planned']} remaining "
             f"({s['elapsed_s']:.1f} s) -> {s['out']}"]
    if s.get("clock"):
        c = s["clock"]
        lines.append(f"clock offset rig - host {c['offset_ms']:+.2f} ms, round trip "
                     f"{c['rtt_ms']:.2f} ms" + (f", drift over the run {c['drift_ms']:.2f} ms"
                                                if "drift_ms" in c else ""))
    for f in s["failed"]:
        lines.append(f"  failed {f['trial']}: {f['reason']}")
    if s["stopped_early"]:
        lines.append("stopped early; run again with --resume to finish")
    elif s["remaining"] or s["failed"]:
        lines.append("run again with --resume to retry the failed trials")
    return "\n".join(lines)

