"""``host bench runtime`` (host/bench/runtime.py): the leg runtime end to end on
simulated hardware, as JSON."""
from __future__ import annotations

import json

from host.cli import main


def test_host_bench_runtime_json(capsys):
    assert main(["bench", "runtime", "--frames", "40", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["frames"] == 40 and res["latency_samples"] >= 35
    assert 0 < res["latency_ms_p50"] <= res["latency_ms_p99"] < 1000
    assert res["throughput_fps"] > 10 and 30 < res["rss_mb_peak"] < 2000
    assert res["rss_mb_peak_with_simulator"] > res["rss_mb_peak"]   # the sim is not free
    assert res["surface_packet_bytes"] <= 32 and res["meets"]["surface_packet_bytes"]
    assert res["meets"]["latency_ms_p99"] == (res["latency_ms_p99"] <= 2.0)

