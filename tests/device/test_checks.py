"""device/checks.py: the argument checks the Pi code, the simulator and the host share."""
from __future__ import annotations

import math

import numpy as np
import pytest

from device.checks import (bounds_text, finite_number, frame_rate, positive_number, serial_url,
                           whole_number)


def test_whole_numbers_in_range_come_back_as_int():
    assert whole_number("k", np.int64(3), 1) == 3 and type(whole_number("k", 3, 1)) is int
    assert whole_number("reg", 0xFF, 0, 0xFF) == 255 and whole_number("n", -5) == -5


@pytest.mark.parametrize("value, lo, hi, why", [
    (0, 1, None, r"k must be a whole number >= 1, got k=0"),
    (256, 0, 255, r"k must be a whole number in \[0, 255\], got k=256"),
    (1.0, 0, None, r"k must be a whole number >= 0, got k=1\.0"),
    (True, 0, None, r"got k=True"),
    ("3", None, 9, r"k must be a whole number <= 9, got k='3'"),
])
def test_whole_number_names_the_argument_and_the_value(value, lo, hi, why):
    with pytest.raises(ValueError, match=why):
        whole_number("k", value, lo, hi)


def test_finite_numbers_and_their_bounds():
    assert finite_number("x", np.float32(0.5), 0, 1) == 0.5
    assert finite_number("x", 1, 0, 1) == 1.0                     # closed by default
    assert positive_number("x", 1e-9) == 1e-9
    for bad, why in ((0.0, r"x must be a finite number > 0, got x=0\.0"),
                     (math.nan, r"> 0, got x=nan"), (math.inf, r"got x=inf"),
                     ("1.5", r"x must be a number, got x='1\.5'"), (False, r"x must be a number")):
        with pytest.raises(ValueError, match=why):
            positive_number("x", bad)
    with pytest.raises(ValueError, match=r"x must be a finite number in \[0, 1\), got x=1"):
        finite_number("x", 1, 0, 1, hi_open=True)


def test_a_callers_error_class_is_raised():
    class DataError(ValueError):
        pass

    with pytest.raises(DataError, match="window must be a whole number >= 1"):
        whole_number("window", 0, 1, error=DataError)
    with pytest.raises(DataError, match="alpha must be a finite number >= 0"):
        finite_number("alpha", -1.0, 0, error=DataError)


@pytest.mark.parametrize("url", ["/dev/serial0", "loop://", "socket://localhost:7777",
                                 "rfc2217://10.0.0.2:2217", "spy:///dev/ttyUSB0", "COM3"])
def test_serial_urls_that_name_a_port_pass(url):
    assert serial_url(url) == url


@pytest.mark.parametrize("url, why", [
    ("socket://notahost", r"'socket://notahost': a socket:// URL needs a host and a port "
                          r"1-65535, e.g. socket://localhost:7777"),
    ("socket://notahost:99999", r"needs a host and a port 1-65535"),
    ("socket://:7777", r"needs a host and a port"),
    ("SOCKET://h:x", r"a socket:// URL needs"),
    ("rfc2217://host", r"a rfc2217:// URL needs"),
    ("", r"serial port must be a device path or a pyserial URL, got ''"),
    (None, r"got None"),
])
def test_a_serial_url_without_what_it_needs_is_refused(url, why):
    with pytest.raises(ValueError, match=why):
        serial_url(url)


def test_bounds_are_worded_as_the_messages_word_them():
    assert bounds_text(1, None) == " >= 1" and bounds_text(None, 9) == " <= 9"
    assert bounds_text(0, 1, lo_open=True) == " in (0, 1]" and bounds_text(None, None) == ""


def test_frame_rates_are_held_to_what_a_camera_runs_at():
    assert frame_rate("fps", 120) == 120.0 and frame_rate("fps", 1) == 1.0
    for bad in (0.5, 1e9, float("nan"), 0):
        with pytest.raises(ValueError, match=rf"fps must be a finite number in \[1\.0, 1000\.0\], got fps={bad!r}"):
            frame_rate("fps", bad)
