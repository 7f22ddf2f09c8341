"""Helpers shared by the benchmarks (imported by name: bench/ is on sys.path under pytest)."""
from __future__ import annotations

import importlib.util
from pathlib import Path


def run(benchmark, fn, full: bool, rounds: int = 5):
    """Time ``fn`` (which must finish its OpenCL queue) with warm-up in full mode, once in smoke."""
    return benchmark.pedantic(fn, rounds=rounds if full else 1, iterations=1,
                              warmup_rounds=1 if full else 0)


def _checkout_timing():
    """qr_cl/app/timing.py of this checkout, loaded from its file (it needs the standard library
    only): scripts that measure another install of qr-cl time both with the same helper."""
    spec = importlib.util.spec_from_file_location(
        "qr_cl_checkout_timing", Path(__file__).resolve().parents[1] / "qr_cl" / "app" / "timing.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


timing = _checkout_timing()


def fox_and_dense_room(data: Path | None, width: int, height: int, dense_n: int) -> dict:
    """{name: (Gaussians, Camera)} of this checkout's qr_cl: the real fox (where ``data`` holds
    it; its second orbit camera) and the procedural dense room of ``dense_n`` Gaussians, both
    width x height."""
    import warnings

    import qr_cl
    from qr_cl.app.scenes.procedural import dense_room
    scenes = {}
    fox = None if data is None else data / "wakufactory-fox" / "fox.ply"
    if fox is not None and fox.is_file():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            g = qr_cl.load_ply(fox)
        scenes["fox"] = (g, qr_cl.orbit_cameras(g.means, 8, width, height)[1])
    scenes[f"dense-room-{dense_n // 1000}k"] = dense_room(dense_n, width=width, height=height)
    return scenes
