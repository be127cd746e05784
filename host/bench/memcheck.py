"""``make memcheck``: valgrind's memcheck over the leg runtime on a real clip, and
whether any error it reports is in the compiled frame core (``match.c``,
``detect.c``: the ``_match-*.so`` library of :mod:`device.pi.vision.native`).

    python -m host.bench.memcheck --clip REAL_DATA/roboskin/concrete.avi \
        --imu REAL_DATA/roboskin/concrete_gyro.npy --frames 100

1. builds the library with ``-g`` (``TACFOOT_NATIVE_CFLAGS=-g``) into a temporary
   folder (``TACFOOT_NATIVE_DIR``), so valgrind names its files and lines;
2. runs ``valgrind --tool=memcheck`` over this module's ``--child``: the runtime
   (:func:`~device.pi.runtime.start.build_runtime`, the shipped models, ``loop://``)
   for ``--frames`` frames of the clip, with ``PYTHONMALLOC=malloc`` (no pymalloc
   noise) and valgrind's python3 suppressions where the system has them; the child
   then prints whether detection and matching ran compiled (a run in which the core
   fell back to numpy proves nothing, and fails);
3. reads valgrind's log: each error with one frame in ``match.c``, ``detect.c`` or
   ``_match-*.so`` is the core's; the others (CPython, numpy, OpenCV, ONNX Runtime)
   are counted by where their first frame is, not judged.

Exit 0 when the core ran compiled and no error is in it, 1 otherwise; 2 without
valgrind. About 4 minutes for 100 frames on a 2-core x86-64 machine.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from collections import Counter

CORE = re.compile(r"\b(match\.c|detect\.c):\d+|_match-[0-9a-f]+\.so")
SUPPRESSIONS = ("/usr/lib/valgrind/python3.supp", "/usr/lib/x86_64-linux-gnu/valgrind/python3.supp")
_ERR_START = re.compile(r"^==\d+== (Invalid |Conditional |Use of uninit|Syscall param|Source and "
                        r"destination overlap|Mismatched free|Argument |Jump to)")


def errors(log: str) -> list[list[str]]:
    """The error records of a memcheck log: each the lines from its headline to the
    blank line that ends it (leak records are not errors here)."""
    out: list[list[str]] = []
    cur: list[str] | None = None
    for line in log.splitlines():
        body = re.sub(r"^==\d+== ?", "", line)
        if _ERR_START.match(line):
            cur = [body]
            out.append(cur)
        elif cur is not None:
            if not body.strip():
                cur = None
            else:
                cur.append(body)
    return out


def where(record: list[str]) -> str:
    """Where an error happened: its first stack frame's function, or object."""
    for line in record[1:]:
        m = re.search(r"(?:at|by) 0x[0-9A-F]+: (.*)", line)
        if m:
            return m.group(1)
    return "?"


def classify(log: str) -> dict:
    recs = errors(log)
    core = [r for r in recs if any(CORE.search(ln) for ln in r[1:])]
    summary = re.search(r"ERROR SUMMARY: (\d+) errors from (\d+) contexts", log)
    return {"contexts": len(recs), "in_core": len(core),
            "core_errors": ["\n".join(r) for r in core][:10],
            "error_summary": summary.group(0) if summary else None,
            "elsewhere_by_first_frame": Counter(where(r) for r in recs
                                                if r not in core).most_common(8)}


def child(clip: str, imu: str, frames: int) -> int:
    """The runtime on the clip, then one JSON line: did the core run compiled."""
    from device.pi.runtime.start import build_runtime
    rt = build_runtime(f"file://{clip}", f"file://{imu}" if imu else "none", "loop://",
                       frames=frames)
    rt.run()
    det = rt.stream.detector
    print(json.dumps({"frames": rt.frames, "tracker": rt.status()["tracker"],
                      "detect_compiled": det is not None and not det.compiled_why,
                      "detect_why": None if det is None else det.compiled_why}))
    return 0


def run(clip: str, imu: str | None, frames: int, keep_log: str | None = None) -> dict:
    tool = shutil.which("valgrind")
    if tool is None:
        raise FileNotFoundError("valgrind not found (Debian: apt-get install valgrind)")
    with tempfile.TemporaryDirectory(prefix="tacfoot-memcheck-") as tmp:
        env = dict(os.environ, TACFOOT_NATIVE_CFLAGS="-g", TACFOOT_NATIVE_DIR=tmp,
                   PYTHONMALLOC="malloc", OMP_NUM_THREADS="1")
        subprocess.run([sys.executable, "-m", "device.pi.vision.native", "build"], env=env,
                       check=True, capture_output=True, text=True)
        log = keep_log or os.path.join(tmp, "memcheck.log")
        cmd = [tool, "--tool=memcheck", "--error-limit=no", "--num-callers=40",
               f"--log-file={log}"]
        cmd += [f"--suppressions={s}" for s in SUPPRESSIONS if os.path.exists(s)]
        cmd += [sys.executable, "-m", "host.bench.memcheck", "--child", "--clip", clip,
                "--frames", str(frames)] + (["--imu", imu] if imu else [])
        r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=3600)
        text = open(log, encoding="utf-8", errors="replace").read()
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    ran = json.loads(lines[-1]) if lines else {}
    res = {"command": " ".join(cmd), "returncode": r.returncode, "run": ran, **classify(text)}
    res["core_ran_compiled"] = bool(ran.get("detect_compiled")) and \
        ran.get("tracker", {}).get("matcher") == "compiled"
    res["ok"] = r.returncode == 0 and res["core_ran_compiled"] and res["in_core"] == 0
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m host.bench.memcheck", description=__doc__.split("\n")[0])
    ap.add_argument("--clip", required=True, help="a real clip (file path)")
    ap.add_argument("--imu", help="its IMU rows (.npy)")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--log", help="keep valgrind's log here")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.frames < 1:
        print(f"memcheck: error: --frames must be >= 1, got {a.frames}", file=sys.stderr)
        return 2
    if a.child:
        return child(a.clip, a.imu, a.frames)
    try:
        res = run(a.clip, a.imu, a.frames, a.log)
    except FileNotFoundError as exc:
        print(f"memcheck: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(res, indent=1))
    print(f"memcheck: {res['run'].get('frames')} frames, core compiled: "
          f"{res['core_ran_compiled']}; {res['error_summary']}; errors in the core "
          f"(match.c, detect.c): {res['in_core']} -> {'ok' if res['ok'] else 'FAILED'}",
          file=sys.stderr)
    return 0 if res["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
