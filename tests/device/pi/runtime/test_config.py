"""device/leg.toml and device/pi/runtime/config.py: defaults, and one clear error
naming the key for every bad value."""
from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from device.config import ConfigError
from device.pi.runtime.config import (DEFAULT_CONFIG, LegConfig, load_leg_config,
                                  parse_leg_config)


def test_shipped_leg_toml_spells_out_the_defaults():
    cfg = load_leg_config()
    assert DEFAULT_CONFIG.name == "leg.toml" and cfg.source == "leg.toml"
    assert cfg.to_dict() == LegConfig().to_dict()          # the file and the code agree
    assert cfg.camera.fourcc in ("MJPG", "YUYV") and cfg.camera.buffersize == 1


def test_empty_file_takes_defaults_and_values_are_read(tmp_path):
    assert parse_leg_config({}).to_dict() == LegConfig().to_dict()
    p = tmp_path / "leg.toml"
    p.write_text('[camera]\nfps = 90\nfourcc = "YUYV"\n[rezero]\nauto = false\n'
                 '[decision]\nmag_px_per_n = 1.5\n')
    cfg = load_leg_config(p)
    assert (cfg.camera.fps, cfg.camera.fourcc, cfg.rezero.auto,
            cfg.decision.mag_px_per_n) == (90.0, "YUYV", False, 1.5)
    assert cfg.models.localiser is False                   # the localiser is off by default
    assert parse_leg_config({"models": {"localiser": True}}).models.localiser is True
    # the tracker's coarse search runs beside the loop on a leg unless set inline
    assert cfg.rezero.reacquire == "background"
    assert parse_leg_config({"rezero": {"reacquire": "inline"}}).rezero.reacquire == "inline"


@pytest.mark.parametrize("text, key, value", [
    ("[camera]\nfps = 0\n", "camera.fps", "0"),
    ('[camera]\nfourcc = "H264"\n', "camera.fourcc", "H264"),
    ("[camera]\nwidth = 640.5\n", "camera.width", "640.5"),
    ("[camera]\nreopen_min_s = 3.0\nreopen_max_s = 1.0\n", "camera.reopen_max_s", "1.0"),
    ("[serial]\nbaudrate = \"fast\"\n", "serial.baudrate", "fast"),
    ('[models]\nvariant = "int4"\n', "models.variant", "int4"),
    ("[decision]\nmag_px_per_n = 0\n", "decision.mag_px_per_n", "0"),
    ("[rezero]\nauto = 1\n", "rezero.auto", "1"),
    ('[rezero]\nreacquire = "later"\n', "rezero.reacquire", "later"),
    ('[models]\nlocaliser = "yes"\n', "models.localiser", "yes"),
    ("[status]\ninterval_s = 5\n", "status.interval_s", "5"),
    ("[mcap]\nimage_every = 0\n", "mcap.image_every", "0"),
    ("[mcap]\nimage_width = 4\n", "mcap.image_width", "4"),
    ("[mcap]\njpeg_quality = 101\n", "mcap.jpeg_quality", "101"),
    ("[mcap]\nchunk_kb = 0\n", "mcap.chunk_kb", "0"),
    ("[camera]\nfsp = 120\n", "camera.fsp", "120"),           # a typo is not ignored
    ("[cameras]\nfps = 120\n", "cameras", "fps"),
    ("camera = 3\n", "camera", "3"),
])
def test_bad_value_names_the_key_and_value(tmp_path, text, key, value):
    p = tmp_path / "leg.toml"
    p.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_leg_config(p)
    msg = str(e.value)
    assert msg.startswith("leg.toml: ") and key in msg and value in msg


def test_broken_toml_and_missing_file_are_clear(tmp_path):
    p = tmp_path / "leg.toml"
    p.write_text("[camera\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_leg_config(p)
    with pytest.raises(ConfigError, match="file not found"):
        load_leg_config(tmp_path / "none.toml")


@settings(max_examples=80, deadline=None)
@given(section=st.sampled_from(["camera", "imu", "serial", "models", "decision", "rezero",
                                "status", "mcap"]),
       value=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(),
                       st.text(max_size=5), st.booleans()))
def test_any_value_is_accepted_or_refused_with_its_key(section, value):
    """Every key of every section: a value is either taken (and is then finite and in
    range) or refused with a ConfigError naming section.key; nothing else escapes."""
    for key in getattr(LegConfig(), section).__dataclass_fields__:
        try:
            cfg = parse_leg_config({section: {key: value}})
        except ConfigError as e:
            assert f"{section}.{key}" in str(e)
            continue
        got = getattr(getattr(cfg, section), key)
        if isinstance(got, float):
            assert got == got and abs(got) < float("inf")
