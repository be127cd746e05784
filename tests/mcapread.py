"""An MCAP file read back with the ``mcap`` package's own reader, for the tests of
the commands that write one (``--mcap``)."""
from __future__ import annotations

import json


def read_mcap(path) -> tuple[dict, dict]:
    """(topic -> schema name, topic -> [(log_time ns, decoded JSON)] in file order).
    The summary is read too, so a file without its footer fails here."""
    from mcap.reader import make_reader
    with open(path, "rb") as fh:
        r = make_reader(fh)
        summary = r.get_summary()
        schemas = {s.id: s.name for s in summary.schemas.values()}
        chans = {c.topic: schemas[c.schema_id] for c in summary.channels.values()}
        msgs: dict[str, list] = {}
        for _, ch, m in r.iter_messages(log_time_order=False):
            msgs.setdefault(ch.topic, []).append((m.log_time, json.loads(m.data)))
    return chans, msgs


def sim_run_command(tmp_path, *extra, frames=20, config=None) -> list[str]:
    """``python -m device.pi run`` on ``sim://walk`` (camera and IMU) over ``loop://``
    with ``--json``, ``frames`` frames (none: until the scene ends), a leg config
    written from ``config`` (TOML text) when given, then ``extra``."""
    import sys
    cmd = [sys.executable, "-m", "device.pi", "run", "--camera", "sim://walk", "--imu",
           "sim://walk", "--serial", "loop://", "--json"]
    if frames:
        cmd += ["--frames", str(frames)]
    if config:
        cfg = tmp_path / "leg.toml"
        cfg.write_text(config)
        cmd += ["--config", str(cfg)]
    return cmd + [str(x) for x in extra]


def kill_when_logged(tmp_path, f, size: int, writer: str = "process") -> None:
    """Run the runtime on ``sim://walk`` in real time with ``--mcap f`` (4 kB chunks,
    every frame an image, ``writer``) until ``f`` holds ``size`` bytes, then SIGKILL it."""
    import signal
    import subprocess
    import time
    cmd = sim_run_command(tmp_path, "--mcap", f, frames=None,
                          config=f"[mcap]\nchunk_kb = 4\nimage_every = 1\n"
                                 f"writer = \"{writer}\"\n")
    cmd[cmd.index("sim://walk")] = "sim://walk?realtime=1"
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        t_end = time.monotonic() + 60
        while time.monotonic() < t_end and (not f.exists() or f.stat().st_size < size):
            assert proc.poll() is None, "the runtime ended before it was killed"
            time.sleep(0.02)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)


def frame_args(k=0, t_s=0.01, reference=None) -> tuple:
    """``McapLog.frame``'s arguments for frame ``k``: two pins (the second lost), a
    64x48 image, a 3x3 grid, no contact, and ``reference`` pins (or None)."""
    from types import SimpleNamespace

    import numpy as np
    ff = SimpleNamespace(pins=np.array([[10.0, 20.0], [30.0, 40.0]]),
                         vectors=np.array([[1.0, 0.0], [0.0, 2.0]], np.float32),
                         lost=np.array([False, True]), grid=np.zeros((3, 3)), contact=False)
    dec = {"frame": k, "t_s": t_s, "probs": [0.2, 0.8], "texture": None, "pins": 2,
           "latency_ms": 1.0}
    frame = SimpleNamespace(t_s=t_s, image=np.zeros((48, 64), np.uint8))
    return (dec, SimpleNamespace(texture=None), frame, SimpleNamespace(features=ff),
            np.zeros(6), 0, 1.0, 1.002, reference)
