"""Test configuration shared by tests/ and bench/: where the real scenes are.

``$QR_CL_DATA``, else ``../shared/data`` beside this checkout. They exist in the project's CI and
on its developers' machines, not in a user's clone: tests that need them skip cleanly.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest

DATA = Path(os.environ.get("QR_CL_DATA", Path(__file__).resolve().parent.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The folder of the real scenes (it may not exist)."""
    return DATA


@pytest.fixture(scope="session")
def shared_data(data_dir) -> Path:
    """The folder with the real scenes; tests that use it skip when it is missing."""
    if not (data_dir / "wakufactory-fox" / "fox.ply").is_file():
        pytest.skip(f"real scenes not found in {data_dir} (set QR_CL_DATA)")
    return data_dir
