"""Numpy twin of binning.cl + sort (:mod:`qr_cl.stages.binning`): per-tile depth-sorted lists."""
from __future__ import annotations

import numpy as np

from ..runtime import TILE
from .project import tile_grid


def bin_and_sort(proj: dict, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-tile depth-sorted Gaussian ids (binning.cl + sort). Returns (ranges [tiles,2], ids [M])."""
    tiles_x, tiles_y = tile_grid(width, height)
    n_tiles = tiles_x * tiles_y
    tile_ids, gauss_ids = [], []
    for i in np.flatnonzero(proj["radii"] > 0):
        x0, y0, x1, y1 = proj["rects"][i]
        tys, txs = np.mgrid[y0:y1, x0:x1]
        tile_ids.append((tys * tiles_x + txs).ravel())
        gauss_ids.append(np.full(tys.size, i))
    tile_ids = np.concatenate(tile_ids) if tile_ids else np.zeros(0, np.int64)
    gauss_ids = np.concatenate(gauss_ids) if gauss_ids else np.zeros(0, np.int64)
    depth32 = proj["depths"].astype(np.float32)[gauss_ids]   # the kernel sorts float32 depths
    order = np.lexsort((gauss_ids, depth32, tile_ids))
    tile_ids, ids = tile_ids[order], gauss_ids[order]
    starts = np.searchsorted(tile_ids, np.arange(n_tiles), "left")
    ends = np.searchsorted(tile_ids, np.arange(n_tiles), "right")
    return np.stack([starts, ends], 1), ids


def tile_pixels(tile: int, width: int, height: int) -> np.ndarray:
    """Pixel coordinates [P,2] (x, y) of one tile, clipped to the image."""
    tiles_x = tile_grid(width, height)[0]
    ys, xs = np.mgrid[0:TILE, 0:TILE]
    xs, ys = xs.ravel() + (tile % tiles_x) * TILE, ys.ravel() + (tile // tiles_x) * TILE
    keep = (xs < width) & (ys < height)
    return np.stack([xs[keep], ys[keep]], 1)
