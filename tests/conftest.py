"""Shared fixtures: the real scenes of ../shared/data (skipped cleanly when absent)."""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("QR_CL_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The folder with the real scenes; tests that use it skip when it is missing."""
    if not (DATA / "wakufactory-fox" / "fox.ply").is_file():
        pytest.skip(f"real scenes not found in {DATA} (set QR_CL_DATA)")
    return DATA


def _load(path: Path):
    import qr_cl
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return qr_cl.load_ply(path)


@pytest.fixture(scope="session")
def fox(shared_data):
    """The fox scene (50k Gaussians, SH degree 0, no cameras)."""
    return _load(shared_data / "wakufactory-fox" / "fox.ply")


@pytest.fixture(scope="session")
def donut(shared_data):
    """(Gaussians, cameras) of the donut scene, placed by its V3DG layout instance."""
    import qr_cl
    from qr_cl.camera import load_layout_instance
    layout = shared_data / "v3dg-donut" / "_SingleDonut.json"
    scale, quat, translation = load_layout_instance(layout)
    g = _load(shared_data / "v3dg-donut" / "donut_fused.ply").transformed(scale, quat, translation)
    return g, qr_cl.load_cameras(layout)
