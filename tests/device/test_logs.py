"""The one log handler of the entry points, and -v/-q (issue 32)."""
from __future__ import annotations

import argparse
import logging

from device import logs


def _say(name: str = "device.pi.runtime.loop") -> None:
    log = logging.getLogger(name)
    log.debug("a debug note")
    log.info("a progress note")
    log.warning("a warning")
    log.error("an error")


def test_quiet_shows_errors_only_default_adds_info_verbose_adds_debug(capsys):
    for (v, q), want in {(0, 1): ["an error"],
                         (0, 0): ["a progress note", "a warning", "an error"],
                         (1, 0): ["a debug note", "a progress note", "a warning",
                                  "an error"]}.items():
        with logs.configured(v, q):
            _say()
            _say("host.cli.bench")
        out, err = capsys.readouterr()
        assert out == ""                                # stdout stays the JSON's
        assert err.splitlines() == want * 2             # plain lines, no prefix


def test_the_handler_is_gone_after_the_entry_point():
    before = [(logging.getLogger(n).level, list(logging.getLogger(n).handlers))
              for n in logs.ROOTS]
    with logs.configured(1, 0):
        assert logging.getLogger("host").handlers
    assert [(logging.getLogger(n).level, list(logging.getLogger(n).handlers))
            for n in logs.ROOTS] == before


def test_verbose_and_quiet_work_before_and_after_the_sub_command():
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="command")
    sub.add_parser("run")
    logs.add_arguments(p)
    assert vars(p.parse_args(["run"])) == {"command": "run", "verbose": 0, "quiet": 0}
    assert p.parse_args(["-q", "run"]).quiet == 1
    assert p.parse_args(["run", "-v"]).verbose == 1
