"""The values of project.cl under oclgrind, the OpenCL device simulator (test_oclgrind_reports.py
reads only its reports): project.cl run three times (no checks, seconds) in the child
(tests/drivers/oclgrind_child.py ``project``) must give the float64 twin's projection each time.
Skipped when oclgrind's ICD library is not installed (Debian/Ubuntu: ``apt-get install
oclgrind``).
"""
from __future__ import annotations

import pytest

from tests.drivers.oclgrind_child import PROJECT_RUNS, finish_child, oclgrind_icd, start_child


def test_projection_under_oclgrind_is_the_twins(tmp_path):
    """The values of project.cl under oclgrind (the reports test reads only its reports): every
    run of the child's ``project_runs`` equal to the first, and the tile rectangles, radii, tiles touched and
    stored row spans equal to the float64 twin's, splats close to it. Caught integer max/min with
    a scalar bound on a lanei in tile_spans (spans.h): oclgrind reads that bound's lanes 1.. out
    of its own memory, so the tiles touched changed from run to run and some Gaussians were culled."""
    import numpy as np

    from qr_cl.render import selfcheck
    from qr_cl.runtime import FOOTPRINT_RECT, FOOTPRINT_SPANS, SPLAT
    from qr_cl.stages import project_ref
    from qr_cl.stages.project import tile_grid

    if oclgrind_icd() is None:
        pytest.skip("oclgrind is not installed (apt-get install oclgrind)")
    out = tmp_path / "project.npz"
    proc, seconds = finish_child(start_child("project", tmp_path, args=(str(out),)), timeout=300)
    assert proc.returncode == 0, f"child failed (rc {proc.returncode}):\n{proc.stdout}\n{proc.stderr[-8000:]}"
    assert "device: Oclgrind" in proc.stdout, proc.stdout
    got = np.load(out)
    for run in range(1, PROJECT_RUNS):
        for name in ("splats", "radii", "footprints", "tiles_touched", "depth_keys"):
            assert np.array_equal(got[f"{name}{run}"], got[f"{name}0"]), f"run {run}: {name} differ from run 0"

    geometry, _, _, cam = selfcheck._scene()
    w, h = selfcheck.WIDTH, selfcheck.HEIGHT
    twin = project_ref.project(*geometry, cam.viewmat, cam.K, w, h)
    splats, footprints = got["splats0"], got["footprints0"]
    np.testing.assert_array_equal(got["radii0"], twin["radii"])
    np.testing.assert_array_equal(footprints[:, FOOTPRINT_RECT], twin["rects"])
    np.testing.assert_array_equal(got["tiles_touched0"], twin["tiles_touched"])
    vis = twin["radii"][:, 0] > 0
    assert vis.sum() > 100, "the scene should keep most Gaussians"
    np.testing.assert_allclose(splats[vis, SPLAT.mean], twin["means2d"][vis], rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(splats[vis, SPLAT.conic], twin["conics"][vis], rtol=1e-4, atol=1e-4)
    spans = footprints[:, FOOTPRINT_SPANS].copy().view(np.uint16).astype(np.int64)   # (x0 - rect x0) | (x1 - rect x0) << 8
    tiles_x, _ = tile_grid(w, h)
    for i in np.flatnonzero(vis):
        rect = twin["rects"][i]
        want = project_ref.tile_spans(twin["means2d"][i], twin["conics"][i], twin["opacities"][i], rect, tiles_x)
        rows = spans[i, :rect[3] - rect[1]]
        n_got = (rows >> 8) - (rows & 0xff)
        assert np.array_equal(n_got, np.maximum(want[:, 2] - want[:, 1], 0)), f"Gaussian {i}: row spans"
    print(f"child ran {seconds:.1f} s; {int(vis.sum())} Gaussians, {int(twin['tiles_touched'].sum())} tiles")
