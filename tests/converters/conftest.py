"""Fixtures shared by the converter tests."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest


@pytest.fixture
def tree_copy(tree: Path, tmp_path: Path) -> Path:
    """A writable copy, at tmp_path/src, of the requesting module's `tree` fixture (a generated
    source tree that its tests share read-only), for a test that breaks or edits a file in it."""
    return Path(shutil.copytree(tree, tmp_path / "src"))
