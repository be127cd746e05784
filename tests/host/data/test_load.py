"""host/data/load.py: one entry point for every data spec; missing specs and bad arguments are named."""
from __future__ import annotations

import pytest

from host.data.load import load_spec
from host.data.windows import DataError

def test_missing_files_are_named(tmp_path, write_csv):
    m = write_csv(tmp_path / "m.csv", ["path,label", "nowhere/clip.avi,hard"])
    with pytest.raises(DataError, match=r"row 1.*column path: no such file.*nowhere/clip\.avi"):
        load_spec(str(m), "surface", 2)
    m = write_csv(tmp_path / "m2.csv", ["path,label,imu", "sim://no-touch,hard,gone.npy"])
    with pytest.raises(DataError, match=r"column imu: no such file.*gone\.npy"):
        load_spec(str(m), "surface", 2)
    with pytest.raises(DataError, match=r"no such data spec.*absent_dir"):
        load_spec(str(tmp_path / "absent_dir"), "surface", 2)
    with pytest.raises(DataError, match=r"no such manifest.*absent\.csv"):
        load_spec(str(tmp_path / "absent.csv"), "surface", 2)


def test_bad_arguments_are_named(tmp_path):
    with pytest.raises(DataError, match="task must be one of.*'colour'"):
        load_spec(str(tmp_path), "colour", 2)
    with pytest.raises(DataError, match="window must be.*window=0"):
        load_spec(str(tmp_path), "surface", 0)
    with pytest.raises(DataError, match="stride must be.*stride=0"):
        load_spec(str(tmp_path), "surface", 2, stride=0)
    with pytest.raises(DataError, match="data spec must be a path"):
        load_spec("  ", "surface", 2)
