"""device/pi/sources/options.py: source-string option checkers and parse_options."""

from __future__ import annotations

import pytest

from device.pi.sources.options import (opt_bool, opt_choice, opt_float, opt_int, opt_int_in, opt_positive,
                                       parse_options)


def test_checkers_accept_query_text_and_python_values():
    assert opt_int("n", "-3") == -3 and opt_int("n", 7) == 7
    assert opt_int_in("addr", "0x68", 0, 0x7F) == 0x68 and opt_int_in("addr", "12", 0, 20) == 12
    assert opt_float("x", "2.5") == 2.5
    assert opt_positive("fps", "30") == 30.0
    assert opt_bool("loop", "off") is False and opt_bool("loop", "YES") is True and opt_bool("loop", 1) is True
    assert opt_choice("accel_g", "8", (2, 4, 8, 16)) == 2


@pytest.mark.parametrize("check,value,match", [
    (lambda v: opt_int("n", v), True, r"n must be an int, got True"),
    (lambda v: opt_int("n", v), "1.5", r"n must be an int, got '1.5'"),
    (lambda v: opt_int_in("addr", v, 0, 0x7F), 0x80, r"addr must be in \[0, 127\], got 128"),
    (lambda v: opt_int_in("addr", v, 0, 0x7F), "zz", r"addr must be an int in \[0, 127\], got 'zz'"),
    (lambda v: opt_float("x", v), "nan", r"x must be finite, got 'nan'"),
    (lambda v: opt_float("x", v), False, r"x must be a number, got False"),
    (lambda v: opt_positive("fps", v), 0, r"fps must be > 0, got 0"),
    (lambda v: opt_bool("loop", v), "maybe", r"loop must be a bool, got 'maybe'"),
    (lambda v: opt_choice("accel_g", v, (2, 4)), 3, r"accel_g must be one of \[2, 4\], got 3"),
])
def test_bad_values_name_the_option_and_the_value(check, value, match):
    with pytest.raises(ValueError, match=match):
        check(value)


def test_parse_options_merges_keywords_over_the_query_and_names_the_source():
    spec = {"fps": opt_positive, "loop": opt_bool}
    assert parse_options("camera", "file://a.avi", {"fps": "10", "loop": "1"}, {"fps": 20}, spec) == \
        {"fps": 20.0, "loop": True}
    with pytest.raises(ValueError, match=r"unknown option 'gain' for IMU source 'sim://walk'; known: \['fps', 'loop'\]"):
        parse_options("IMU", "sim://walk", {"gain": "2"}, {}, spec)
    with pytest.raises(ValueError, match=r"fps must be > 0, got '-1' \(camera source 'x'\)"):
        parse_options("camera", "x", {"fps": "-1"}, {}, spec)
