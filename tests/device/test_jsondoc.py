"""device/jsondoc.py: the one reader of tacfoot's versioned JSON documents (a model's
manifest, a dataset's index)."""
from __future__ import annotations

import json

import pytest

from device.jsondoc import read_json_doc


class DocError(ValueError):
    pass


def read(path):
    return read_json_doc(path, "doc.json", "tacfoot-thing", 2, "thing", "index", DocError)


def test_a_folder_or_the_file_itself(tmp_path):
    (tmp_path / "doc.json").write_text(json.dumps({"format": "tacfoot-thing", "version": 2}))
    assert read(tmp_path) == read(tmp_path / "doc.json") == (
        {"format": "tacfoot-thing", "version": 2}, tmp_path / "doc.json")


@pytest.mark.parametrize("text, why", [
    (None, r"doc\.json: not a tacfoot thing: index not found"),
    ("{broken", r"doc\.json: corrupt index"),
    (b"\xff\xfe", r"doc\.json: corrupt index"),
    ("[1, 2]", r"not a tacfoot thing index \(format \[1, 2\]"),
    ('{"format": "other"}', r"not a tacfoot thing index \(format 'other', expected"),
    ('{"format": "tacfoot-thing", "version": 3}', r"index version 3 is newer than this "
                                                  r"tacfoot reads \(2\)"),
    ('{"format": "tacfoot-thing", "version": "x"}', r"index version must be a whole number "
                                                    r">= 0, got 'x'"),
    ('{"format": "tacfoot-thing", "version": 1.5}', r"version must be a whole number"),
    ('{"format": "tacfoot-thing", "version": true}', r"version must be a whole number"),
    ("DIR", r"doc\.json: cannot read the index"),
])
def test_every_bad_document_is_the_callers_error_naming_the_file(tmp_path, text, why):
    if text == "DIR":
        (tmp_path / "doc.json").mkdir()
        (tmp_path / "doc.json" / "doc.json").mkdir()
    elif isinstance(text, bytes):
        (tmp_path / "doc.json").write_bytes(text)
    elif text is not None:
        (tmp_path / "doc.json").write_text(text)
    with pytest.raises(DocError, match=why):
        read(tmp_path)

