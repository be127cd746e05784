"""host/data/dataset.py: reading the index goes through device.jsondoc."""
from __future__ import annotations

import pytest

from host.data import dataset


def test_a_dataset_index_that_is_not_a_table_is_a_dataset_error(tmp_path):
    (tmp_path / "dataset.json").write_text("[]")         # was an AttributeError
    with pytest.raises(dataset.DatasetError, match="not a tacfoot dataset index"):
        dataset.read_index(tmp_path)
