"""tacfoot's tests. The tree mirrors the code: tests/device/... and tests/host/..."""
from pathlib import Path

#: the repository root, wherever a test module sits in the tree
REPO_ROOT = Path(__file__).resolve().parent.parent
