"""The transpose (transpose.cl) of a selection: its entries grouped by Gaussian, the backward's input."""
from __future__ import annotations

import numpy as np
import pytest

from qr_cl.render import rasterize_plan
from qr_cl.stages import select, transpose


@pytest.fixture(scope="module")
def plan(random_scene):
    return rasterize_plan(*random_scene)


def test_transpose_groups_entries_by_gaussian(plan):
    sel = select(plan, "quantile", 6)
    cursor, t_ray, t_w, t_entry, chunks, _ = transpose(sel)
    ends = cursor.get()[chunks - 1::chunks]
    h = sel.host()
    counts = np.bincount(h["ids"][h["ids"] >= 0], minlength=sel.n_gaussians)
    np.testing.assert_array_equal(np.diff(ends, prepend=0), counts)
    rays = t_ray.get()[:ends[-1]]
    for g in np.flatnonzero(counts)[:50]:     # ordered by ray within a Gaussian
        seg = rays[(ends[g - 1] if g else 0):ends[g]]
        assert (np.diff(seg) >= 0).all()
    entry = t_entry.get()[:ends[-1]]                  # each transposed entry's selection index
    owner = np.repeat(np.arange(sel.n_gaussians), counts)
    np.testing.assert_array_equal(sel.ids.get()[entry], owner)
    np.testing.assert_array_equal(sel.weights.get()[entry], t_w.get()[:ends[-1]])
    np.testing.assert_array_equal(entry // 6, rays)   # quantile rows of K = 6 slots
