"""``python -m device.pi run``: the leg runtime (docs/runtime.md).

Exit status: 0 when it stops (end of a finite source, ``--frames`` reached, SIGTERM
or Ctrl-C); 2 when it refuses to start (bad config, model, source or port), with
one line on stderr naming what is wrong (every :class:`device.errors.TacfootError`
is caught in :func:`main`, and only there; any other exception is a defect and shows
its traceback); 3 when, after SIGTERM or Ctrl-C, the loop
had not finished within :data:`STOP_GRACE_S` and the process was ended without its
clean-up (a guard: SIGTERM always ends the process within a second).

Messages go through :mod:`logging` to one stderr handler (:mod:`device.logs`):
``-q`` leaves errors only, ``-v`` adds debug notes; ``--json`` output on stdout is
untouched.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import os
import signal
import sys
import threading
import time


from device import logs
from device.errors import InputError, TacfootError, one_line
from device.pi.runtime.loop import EXIT_BAD_INPUT
from device.pi.runtime.start import build_runtime
from device.pi.vision import native

#: after a stop signal, the loop has this long to finish before the process ends anyway
STOP_GRACE_S = 0.8
#: after a stop signal, the MCAP writer has this long to write what is queued; what
#: it has not written by then (a stalled disk) is counted lost (mcap_messages_lost)
MCAP_STOP_WAIT_S = 0.5
EXIT_FORCED = 3

log = logging.getLogger("device.pi.run")     # not __name__: run as __main__


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m device.pi",
                                description="tacfoot leg module (Raspberry Pi)")
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="the leg runtime: camera + IMU -> surface packets on the UART")
    r.add_argument("--camera", required=True,
                   help="v4l2:///dev/video0, sim://SCENE, a video file or image folder")
    r.add_argument("--imu", required=True, help="i2c://1/0x68, file://imu.npy, sim://SCENE "
                                                "or none")
    r.add_argument("--serial", required=True,
                   help="pyserial port or URL: /dev/serial0, loop://, socket://HOST:PORT")
    r.add_argument("--models", help="models folder (default: the package's models/)")
    r.add_argument("--rules-only", action="store_true",
                   help="run on the surface rules alone, loading no model (without it, "
                        "a models folder with no model refuses to start)")
    r.add_argument("--config", help="leg config TOML (default: device/leg.toml)")
    r.add_argument("--fps", type=float, help="camera frame rate (overrides camera.fps)")
    r.add_argument("--float", dest="float_models", action="store_true",
                   help="load the float ONNX models instead of int8")
    r.add_argument("--json-log", help="write one JSON line per decision to FILE")
    r.add_argument("--status", help="rewrite FILE atomically with a JSON health summary")
    r.add_argument("--mcap", help="write an MCAP log to FILE for Foxglove (docs/viewing.md; "
                                  "needs pip install .[viz])")
    r.add_argument("--mcap-max-mb", type=float, default=256.0,
                   help="start the next MCAP file (FILE-0001.mcap, ...) at this size, "
                        "MB, 1 to 1048576 (default 256)")
    r.add_argument("--foxglove", metavar="[HOST:]PORT",
                   help="serve the same channels live to Foxglove over WebSocket "
                        "(default host 127.0.0.1; 0.0.0.0:8765 for the network; "
                        "needs pip install .[viz])")
    r.add_argument("--foxglove-max-clients", type=int, metavar="N",
                   help="live viewers served at once; more are refused (default 8)")
    r.add_argument("--frames", type=int, help="stop after N frames (tests, benchmarks)")
    r.add_argument("--json", action="store_true",
                   help="print a JSON summary on stdout when the runtime stops")
    logs.add_arguments(p)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    with logs.configured(args.verbose, args.quiet):
        try:
            return _run(args)
        except TacfootError as exc:     # bad config, model, source or port: one line
            log.error("device.pi run: error: %s", one_line(exc))
            return EXIT_BAD_INPUT


def _run(args) -> int:
    if args.frames is not None and args.frames < 1:
        raise InputError(f"--frames must be >= 1, got {args.frames}")
    if args.mcap or args.foxglove:
        err = _check_mcap(args)
        if err:
            raise InputError(err)
    refused = native.refused()          # a library is there but was not loaded: say why
    if refused:
        log.warning("device.pi run: warning: the tracker's compiled kernel is not loaded: %s; "
                    "the tracker runs on numpy (%s)", refused, native.rebuild_hint())
    rt = build_runtime(args.camera, args.imu, args.serial, models_dir=args.models,
                       config=args.config, fps=args.fps, json_log=args.json_log,
                       status=args.status, frames=args.frames,
                       float_models=args.float_models, rules_only=args.rules_only)
    log.debug("device.pi run: camera %s, IMU %s, serial %s, models %s",
              args.camera, args.imu, args.serial,
              "none (--rules-only)" if args.rules_only else (args.models or "the package's"))

    if args.mcap or args.foxglove:
        rt.mcap = _open_log(args, rt)
        if args.foxglove:
            log.info("device.pi run: Foxglove live view on ws://%s:%s", rt.mcap.host,
                     rt.mcap.port)
    guard: list[threading.Timer] = []

    def stop(signum, frame):
        rt.stopped = True
        log = getattr(rt, "mcap", None)
        if log is not None and log.close_by is None:     # within the grace
            log.close_by = time.monotonic() + MCAP_STOP_WAIT_S
        if not guard:                 # the loop should end at its next pass; if not, end
            guard.append(threading.Timer(STOP_GRACE_S, _force_exit, (signum,)))
            guard[0].daemon = True
            guard[0].start()

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    try:
        rc = rt.run()
    finally:
        if guard:
            guard[0].cancel()
    st = rt.status()
    st["latency_ms_p50"] = _pct(rt.latency_ms, 50)
    st["latency_ms_p99"] = _pct(rt.latency_ms, 99)
    st["latency_samples"] = rt.latency_ms.count
    st["cpu_ms_per_frame_p50"] = _pct(rt.cpu_ms, 50)
    st["cpu_ms_per_frame_p99"] = _pct(rt.cpu_ms, 99)
    run_s = getattr(rt, "run_s", 0.0)
    st["run_s"] = round(run_s, 4)
    st["throughput_fps"] = round(st["frames"] / run_s, 2) if run_s > 0 else None
    st["rss_mb_peak"] = _rss_mb()
    if args.json:
        print(json.dumps(st))
    else:
        prof = st["profile"]
        log.info("device.pi run: %s frames, %s packets sent, %s dropped, faults now %s; "
                 "profile %s (%s, %s pins)", st["frames"], st["packets_sent"],
                 st["packets_dropped"], st["fault_names"] or "none", prof["name"],
                 prof["source"], prof["pins"])
    return rc


def _open_log(args, rt):
    """The MCAP log and live view: written by a child process (``[mcap] writer``,
    device/pi/runtime/mcapproc.py), or by a thread of this one."""
    from device.pi.runtime.liveview import LiveView, parse_hostport
    from device.pi.runtime.mcaplog import McapLog, run_metadata
    addr = parse_hostport(args.foxglove) if args.foxglove else None
    kw = dict(max_mb=args.mcap_max_mb, clock=rt.clock, keep_existing=True,
              metadata=run_metadata(rt), records="device")
    if rt.cfg.mcap.writer == "process":
        from device.pi.runtime.mcapproc import McapProcess
        return McapProcess(args.mcap, rt.cfg.mcap, foxglove=addr,
                           max_clients=args.foxglove_max_clients, **kw)
    live = None if addr is None else LiveView(*addr, max_clients=args.foxglove_max_clients)
    return McapLog(args.mcap, rt.cfg.mcap, live=live, background=True, **kw)


def _check_mcap(args) -> str | None:
    """Why ``--mcap`` or ``--foxglove`` cannot work (checked before the sources open),
    or None."""
    from device.pi.runtime.liveview import parse_hostport
    from device.pi.runtime.mcaplog import INSTALL_HINT, MAX_MB_MAX, MAX_MB_MIN
    mb = args.mcap_max_mb
    if not (math.isfinite(mb) and MAX_MB_MIN <= mb <= MAX_MB_MAX):
        return (f"--mcap-max-mb must be a number of MB from {MAX_MB_MIN:g} to "
                f"{MAX_MB_MAX:.0f}, got {mb:g}")
    n = args.foxglove_max_clients
    if n is not None and not 1 <= n <= 1000:
        return f"--foxglove-max-clients must be 1..1000, got {n}"
    if args.foxglove:
        try:
            parse_hostport(args.foxglove)
            import foxglove  # noqa: F401
        except ValueError as exc:
            return str(exc)
        except ImportError:
            return f"--foxglove: {INSTALL_HINT.replace('MCAP logging', 'the live view')}"
    if not args.mcap:
        return None
    try:
        import mcap  # noqa: F401
    except ImportError:
        return f"--mcap: {INSTALL_HINT}"
    d = os.path.dirname(os.path.abspath(args.mcap))
    if os.path.isdir(args.mcap):
        return f"--mcap {args.mcap!r} is a folder; give a file, e.g. " \
               f"{os.path.join(args.mcap, 'run.mcap')}"
    if not os.path.isdir(d):
        return f"--mcap {args.mcap!r}: the folder {d} does not exist"
    return None


def _force_exit(signum: int) -> None:
    try:
        os.write(2, (f"device.pi run: error: still running {STOP_GRACE_S} s after "
                     f"{signal.Signals(signum).name}; ending without clean-up\n").encode())
    finally:
        os._exit(EXIT_FORCED)


def _rss_mb() -> float | None:
    """Peak resident set of this process, MB: VmHWM (per address space, so a parent's
    size does not leak in through fork + exec, as it does into ru_maxrss)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return round(int(line.split()[1]) / 1024.0, 1)
    except (OSError, ValueError):
        pass
    try:
        import resource
        return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)
    except (ImportError, OSError):
        return None


def _pct(stats, q):
    v = stats.percentile(q)
    return None if v is None else round(v, 4)


if __name__ == "__main__":
    sys.exit(main())
