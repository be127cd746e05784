"""Fixtures shared across the test tree."""
from __future__ import annotations

import pytest

from tests import REPO_ROOT
from tests.windows import synthetic


@pytest.fixture
def repo_root():
    """The repository root."""
    return REPO_ROOT


@pytest.fixture
def synthetic_windows():
    """A factory of easy-to-learn synthetic windows (tests/windows.py)."""
    return synthetic
