"""Shared bench fixtures. Full sizes run with ``--benchmark-only`` (or QR_CL_BENCH_FULL=1);
otherwise every benchmark runs once on tiny inputs as a smoke test of the code path."""
from __future__ import annotations

import os
import warnings

import pytest


@pytest.fixture(scope="session")
def bench_full(request) -> bool:
    """True for real measurements, False for the smoke mode of the default test run."""
    if os.environ.get("QR_CL_BENCH_FULL") == "1":
        return True
    return bool(request.config.getoption("benchmark_only", False))


@pytest.fixture(scope="session")
def fox_or_procedural(bench_full, data_dir):
    """(Gaussians, width, height): the real fox at 640x480 in full mode, else a tiny procedural
    scene at 64x48 (also when ../shared/data is missing)."""
    import qr_cl
    from qr_cl.app.scenes.procedural import procedural_scene
    fox = data_dir / "wakufactory-fox" / "fox.ply"
    if bench_full and fox.is_file():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return qr_cl.load_ply(fox), 640, 480
    return procedural_scene(2000), 64, 48
