"""host/bench/memcheck.py: an error with a frame in the C core is the core's, one
whose stack never enters it is not; leak records and the summary are not errors."""
from __future__ import annotations

from host.bench.memcheck import classify, errors, main

LOG = """==7== Memcheck, a memory error detector
==7== Invalid read of size 4
==7==    at 0x4A1: tf_detect (detect.c:212)
==7==    by 0x4B2: ffi_call_unix64 (in /usr/lib/x86_64-linux-gnu/libffi.so.8.1.2)
==7==  Address 0x5 is 0 bytes after a block of size 16 alloc'd
==7== 
==7== Conditional jump or move depends on uninitialised value(s)
==7==    at 0x4C3: Py_DECREF (object.h:537)
==7==    by 0x4D4: list_dealloc (listobject.c:357)
==7== 
==7== Use of uninitialised value of size 8
==7==    at 0x4E5: ??? (in /tmp/x/_match-0123abcdef01.so)
==7== 
==7== HEAP SUMMARY:
==7==    definitely lost: 10 bytes in 1 blocks
==7== ERROR SUMMARY: 3 errors from 3 contexts (suppressed: 0 from 0)
"""


def test_errors_in_the_core_are_told_from_the_interpreters():
    assert len(errors(LOG)) == 3
    res = classify(LOG)
    assert res["contexts"] == 3 and res["in_core"] == 2
    assert "detect.c:212" in res["core_errors"][0]
    assert res["elsewhere_by_first_frame"] == [("Py_DECREF (object.h:537)", 1)]
    assert res["error_summary"] == "ERROR SUMMARY: 3 errors from 3 contexts"


def test_a_log_without_errors_has_none_in_the_core():
    assert classify("==7== ERROR SUMMARY: 0 errors from 0 contexts\n")["in_core"] == 0


def test_bad_frames_are_refused_with_one_line(capsys):
    assert main(["--clip", "x.avi", "--frames", "0"]) == 2
    assert "--frames must be >= 1, got 0" in capsys.readouterr().err
