"""Numpy twin of binning.cl + sort (:mod:`qr_cl.stages.binning`): per-tile depth-sorted lists."""
from __future__ import annotations

import numpy as np

from ..runtime import TILE
from .project import tile_grid
from .project_ref import tile_spans


def bin_and_sort(proj: dict, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-tile depth-sorted Gaussian ids (binning.cl + sort), each Gaussian in the tiles of its
    :func:`~qr_cl.stages.project_ref.tile_spans`. Returns (ranges [tiles,2], ids [M])."""
    tiles_x, tiles_y = tile_grid(width, height)
    n_tiles = tiles_x * tiles_y
    tile_ids, gauss_ids = [], []
    for i in np.flatnonzero(proj["radii"][:, 0] > 0):
        spans = tile_spans(proj["means2d"][i], proj["conics"][i], proj["opacities"][i], proj["rects"][i], tiles_x)
        tiles = np.concatenate([ty * tiles_x + np.arange(x0, x1) for ty, x0, x1 in spans])
        tile_ids.append(tiles)
        gauss_ids.append(np.full(tiles.size, i))
    tile_ids = np.concatenate(tile_ids) if tile_ids else np.zeros(0, np.int64)
    gauss_ids = np.concatenate(gauss_ids) if gauss_ids else np.zeros(0, np.int64)
    depth32 = proj["depths"].astype(np.float32)[gauss_ids]   # the kernel sorts float32 depths
    order = np.lexsort((gauss_ids, depth32, tile_ids))
    tile_ids, ids = tile_ids[order], gauss_ids[order]
    starts = np.searchsorted(tile_ids, np.arange(n_tiles), "left")
    ends = np.searchsorted(tile_ids, np.arange(n_tiles), "right")
    return np.where((ends > starts)[:, None], np.stack([starts, ends], 1), 0), ids   # empty: (0, 0)


def tile_pixels(tile: int, width: int, height: int) -> np.ndarray:
    """Pixel coordinates [P,2] (x, y) of one tile, clipped to the image."""
    tiles_x = tile_grid(width, height)[0]
    ys, xs = np.mgrid[0:TILE, 0:TILE]
    xs, ys = xs.ravel() + (tile % tiles_x) * TILE, ys.ravel() + (tile // tiles_x) * TILE
    keep = (xs < width) & (ys < height)
    return np.stack([xs[keep], ys[keep]], 1)
