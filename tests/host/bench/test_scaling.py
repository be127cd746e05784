"""host/bench/scaling.py: the per-frame cost against the pin count, and its fits."""
from __future__ import annotations

import math

import numpy as np


def test_fit_growth_recovers_a_line_and_a_power_law():
    from host.bench.scaling import fit_growth

    pins = [133, 331, 700, 1400]
    lin = fit_growth(pins, [0.2 + 0.003 * n for n in pins])
    assert lin["ok"]
    assert math.isclose(lin["slope_ms_per_pin"], 0.003, rel_tol=1e-9)
    assert math.isclose(lin["intercept_ms"], 0.2, rel_tol=1e-9)
    quad = fit_growth(pins, [1e-6 * n * n for n in pins])
    assert math.isclose(quad["exponent"], 2.0, rel_tol=1e-9)
    # one pin count, or a time that is not positive: no fit, NaN and not ok
    for bad in (fit_growth([133, 133], [1.0, 2.0]), fit_growth([133, 331], [1.0, 0.0]),
                fit_growth([133], [1.0])):
        assert not bad["ok"] and math.isnan(bad["exponent"])


def test_hex_points_are_a_lattice_of_the_requested_size():
    from host.bench.scaling import hex_points

    for n in (1, 7, 133, 700):
        p = hex_points(n, pitch_px=10.0)
        assert p.shape == (n, 2) and np.isfinite(p).all()
        if n > 1:
            d = np.hypot(*(p[:, None] - p[None]).transpose(2, 0, 1))
            np.fill_diagonal(d, np.inf)
            assert np.allclose(d.min(axis=1), 10.0)   # every point at one pitch from another
        assert (p >= 0).all()                         # shifted into positive pixels


def test_time_matching_reports_cpu_times_and_the_local_exponent():
    from host.bench.scaling import time_matching

    res = time_matching((50, 100), frames=8)
    assert sorted(res["sizes"]) == [50, 100]
    for e in res["sizes"].values():
        assert e["match"]["n"] == 8 and e["match"]["median_ms"] > 0
        assert e["tracker_update"]["median_ms"] > 0
        assert 0.9 <= e["matched_fraction"] <= 1.0    # small motion: nearly all matched
    assert math.isfinite(res["match_exponent_50_100"])
    assert res["match_fit"]["ok"]
    # the coarse re-acquisition after a jump of 1.2 pitch: timed, and it finds the pins
    for e in res["sizes"].values():
        assert e["reacquire"]["n"] == 3 and e["reacquire"]["median_ms"] > 0
        assert e["reacquire_right"] >= 0.9
    assert res["reacquire_fit"]["ok"] and math.isfinite(res["reacquire_exponent_50_100"])
    assert "reacquire" not in time_matching((50,), frames=3, reacquire_repeats=0)["sizes"][50]


def test_bench_scaling_on_simulated_layouts_finds_more_pins_on_denser_ones(capsys,
                                                                          monkeypatch):
    """``host bench scaling --json`` without --data: simulated hex layouts only; the
    denser layout gives more detected pins, every time is finite, the fits are made."""
    import json

    from host.bench import scaling
    from host.cli import main

    orig = scaling.bench_scaling

    def small(data, flat_profile, frames, repeats, progress):
        return orig(data, flat_profile, frames=6, repeats=1, sim_rings=(4, 6),
                    match_sizes=(40, 80), progress=progress)

    monkeypatch.setattr(scaling, "bench_scaling", small)
    assert main(["bench", "scaling", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    src = res["sources"]
    assert sorted(src) == ["sim hex 127", "sim hex 61"]
    assert src["sim hex 61"]["pins"] >= 50 and src["sim hex 127"]["pins"] >= 110
    assert src["sim hex 127"]["reference_pins"] >= 110      # the reference was set
    for e in src.values():
        assert e["frames"] == 6 and 0 < e["cpu"]["median_ms"] <= e["cpu"]["p99_ms"]
    assert res["fit_sim"]["ok"] and res["matching"]["match_fit"]["ok"]
    assert res["blas_threads"] == 1 and res["threads"] == 1
    assert "text" not in res and scaling.format_scaling(res).count("sim hex") == 2


def test_bench_scaling_refuses_a_missing_data_folder_or_flat_profile(tmp_path, capsys):
    from host.cli import main

    assert main(["bench", "scaling", "--data", str(tmp_path / "gone")]) == 2
    assert "--data" in capsys.readouterr().err
    assert main(["bench", "scaling", "--data", str(tmp_path), "--flat-profile",
                 str(tmp_path / "flat.toml")]) == 2
    assert "--flat-profile" in capsys.readouterr().err
