"""The MCU's framing layer (device/micropython/tflink.py) on REAL MicroPython (the
WebAssembly port under Node) and on CPython: 30k fuzzed streams per interpreter (100k
with TACFOOT_FUZZ_STREAMS=100000)
(no exception, no corrupt frame accepted, resynchronised within one frame), and the
same frames accepted as the Pi's decoder (device/pi/protocol.py)."""
from __future__ import annotations

import json
import os

from hypothesis import given, settings
from hypothesis import strategies as st

from device.pi import protocol as P
from tests.mpyrun import MPY_LIB, cpython_path, requires_mpy, run_cpython, run_mpy

# make test fuzzes 30 000 streams on each interpreter; the figure in docs/protocol.md
# (100 000, no corrupt frame accepted) is TACFOOT_FUZZ_STREAMS=100000
FUZZ_STREAMS = int(os.environ.get("TACFOOT_FUZZ_STREAMS", "30000"))


FUZZ = r"""
import json, mpy_args
import tflink

N = int(mpy_args.ARGV[1])
seed = int(mpy_args.ARGV[2])

# xorshift32: the same streams on MicroPython and CPython
_s = [seed & 0xFFFFFFFF or 1]
def rnd(n):
    x = _s[0]
    x ^= (x << 13) & 0xFFFFFFFF
    x ^= x >> 17
    x ^= (x << 5) & 0xFFFFFFFF
    _s[0] = x
    return x % n

enc = tflink.Encoder()
# pools of random bytes; streams take slices at random offsets (cheap on MicroPython)
POOL = 4096
noise = bytearray(POOL + 64)          # zeros frequent: line noise
nonzero = bytearray(POOL + 64)        # no zeros: garbage that hides the next delimiter
for j in range(POOL + 64):
    noise[j] = 0 if rnd(8) == 0 else rnd(256)
    nonzero[j] = rnd(255) + 1
frames = []          # the good frames of the current stream: (type, seq, t_ms, payload)
got = []

def on_frame(d):
    got.append((d.msg_type, d.seq, d.t_ms, bytes(d.payload)))

dec = tflink.Decoder(64, on_frame)
try:                   # CPython: the Pi's decoder must agree frame for frame
    from device.pi.protocol import FrameDecoder
    pi = FrameDecoder(64)
except ImportError:    # MicroPython
    pi = None

def good():
    n = rnd(13)
    o = rnd(POOL)
    pay = noise[o:o + n]
    t = rnd(0x40) + 1
    x = rnd(0x40000000)
    s = x & 0xFFFF
    ms = x * 4 + rnd(4)
    frames.append((t, s, ms, bytes(pay)))
    return bytearray(enc.frame(t, s, ms, pay, n))

stats = {"streams": 0, "bytes": 0, "accepted": 0, "corrupt_accepted": 0,
         "missed_resync": 0, "exceptions": 0, "kinds": [0, 0, 0, 0]}
for i in range(N):
    kind = rnd(4)
    stats["kinds"][kind] += 1
    del frames[:]
    del got[:]
    must = None
    if kind == 0:          # garbage with no delimiter, then A, B: B must decode
        o = rnd(POOL)
        g = nonzero[o:o + rnd(16) + 1]
        a = good()
        b = good()
        stream = g + a + b
        must = frames[1]
    elif kind == 1:        # A with 1-3 flipped bits (not its delimiter), then B: B must decode
        a = good()
        for j in range(rnd(3) + 1):
            k = rnd(len(a) - 1)
            a[k] ^= 1 << rnd(8)
        stream = a + good()
        must = frames[1]
    elif kind == 2:        # A with a byte dropped, inserted or a slice repeated, then B
        a = good()
        k = rnd(len(a) - 1)
        op = rnd(3)
        if op == 0:
            a = a[:k] + a[k + 1:]
        elif op == 1:
            a = a[:k] + bytearray([rnd(256)]) + a[k:]
        else:
            a = a[:k] + a[rnd(len(a)):]
        stream = a + good()
        must = frames[1]
    else:                  # line noise (zeros frequent), then a delimiter, then A
        o = rnd(POOL)
        g = noise[o:o + rnd(32) + 1]
        stream = g + bytearray(1) + good()
        must = frames[0]
    stats["streams"] += 1
    stats["bytes"] += len(stream)
    try:
        # two uneven reads, as a UART delivers them
        cut = rnd(len(stream) + 1)
        dec.feed(stream[:cut], cut)
        rest = stream[cut:]
        dec.feed(rest, len(rest))
    except Exception as e:
        stats["exceptions"] += 1
        dec.reset()
        continue
    if pi is not None:
        pf = [(f.msg_type, f.seq, f.t_ms, f.payload) for f in pi.feed(stream)]
        if pf != got:
            stats["pi_disagrees"] = stats.get("pi_disagrees", 0) + 1
    for f in got:
        stats["accepted"] += 1
        if f not in frames:
            stats["corrupt_accepted"] += 1
    if must not in got:
        stats["missed_resync"] += 1
for k in ("frames_ok", "crc_errors", "too_long", "malformed", "newer_version"):
    stats[k] = getattr(dec, k)
if pi is not None:
    stats["pi_counters"] = dict((k, getattr(pi, k)) for k in (
        "frames_ok", "crc_errors", "too_long", "malformed", "newer_version"))
print(json.dumps(stats))
"""


def _check_fuzz(stats: dict, n: int):
    assert stats["streams"] == n
    assert stats["exceptions"] == 0
    assert stats["corrupt_accepted"] == 0, stats
    assert stats["missed_resync"] == 0, stats
    # every kind ran, and the decoder saw (and counted) each kind of damage
    assert min(stats["kinds"]) > n // 5
    assert stats["crc_errors"] > n // 20 and stats["malformed"] > n // 20
    assert stats["accepted"] >= n


@requires_mpy
def test_fuzz_streams_on_micropython():
    res = run_mpy(FUZZ, libs=[MPY_LIB], args=[FUZZ_STREAMS, 12345], timeout=120)
    assert res.returncode == 0, res.stderr[-3000:]
    _check_fuzz(json.loads(res.stdout), FUZZ_STREAMS)


def test_fuzz_streams_on_cpython_same_streams():
    """The same streams as on MicroPython (same PRNG and seed)."""
    stats = json.loads(run_cpython(FUZZ, [FUZZ_STREAMS, 12345]))
    _check_fuzz(stats, FUZZ_STREAMS)
    # the Pi's decoder (device/pi/protocol.py) saw the same streams: same frames
    # accepted, same damage counted
    assert stats.get("pi_disagrees", 0) == 0
    assert stats["pi_counters"] == {k: stats[k] for k in stats["pi_counters"]}


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=80), max_size=6), st.integers(0, 3))
def test_mcu_decoder_and_pi_decoder_accept_the_same_frames(chunks, n_good):
    cpython_path()
    import tflink
    good = [P.Surface(i % 4).encode(i, i) for i in range(n_good)]
    stream = b"".join(c + g for c, g in zip(chunks, good + [b""] * len(chunks)))
    got = []
    d = tflink.Decoder(64, lambda d: got.append((d.msg_type, d.seq, d.t_ms,
                                                 bytes(d.payload))))
    d.feed(stream, len(stream))
    pi = P.FrameDecoder()
    assert got == [(f.msg_type, f.seq, f.t_ms, f.payload) for f in pi.feed(stream)]
    for k in ("crc_errors", "too_long", "malformed", "newer_version", "frames_ok"):
        assert getattr(d, k) == getattr(pi, k), k

