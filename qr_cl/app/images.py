"""Pictures: renders as PNGs (RGB, depth with a colour map, alpha in grey) and plots."""
from __future__ import annotations

import os

import matplotlib
import numpy as np

matplotlib.use("Agg")   # files only: never open a window (before pyplot is imported)
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib import colormaps  # noqa: E402
from matplotlib.image import imsave  # noqa: E402


def save_rgb(path: str | os.PathLike, image: np.ndarray) -> None:
    """image [H,W,3] in [0,1] (clipped) -> 8-bit PNG."""
    imsave(path, np.clip(np.asarray(image, np.float32), 0, 1))


def save_alpha(path: str | os.PathLike, alpha: np.ndarray) -> None:
    """alpha [H,W,1] or [H,W] in [0,1] -> grey PNG."""
    a = np.clip(np.asarray(alpha, np.float32).reshape(alpha.shape[0], alpha.shape[1]), 0, 1)
    imsave(path, a, cmap="gray", vmin=0, vmax=1)


def save_depth(path: str | os.PathLike, depth: np.ndarray, alpha: np.ndarray) -> None:
    """Expected depth [H,W,1] -> turbo-coloured PNG (near = red), black where alpha < 0.5;
    the colour range spans the 1st..99th percentile of the covered pixels."""
    d = np.asarray(depth, np.float32)[..., 0]
    covered = np.asarray(alpha, np.float32)[..., 0] >= 0.5
    rgb = np.zeros(d.shape + (3,), np.float32)
    if covered.any():
        lo, hi = np.percentile(d[covered], [1, 99])
        t = np.clip((d - lo) / max(hi - lo, 1e-12), 0, 1)
        rgb[covered] = colormaps["turbo"](1 - t[covered])[:, :3]
    imsave(path, rgb)


def plot_transmittance_profiles(profiles: dict[str, tuple[np.ndarray, np.ndarray]], path: str,
                                title: str = "") -> None:
    """Step plot of T against depth for each sampler of ``profiles`` (name -> (depths, T) from
    :func:`qr_cl.app.experiments.transmittance.transmittance_profile`), saved to ``path`` (any matplotlib format)."""
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for name, (depths, t) in profiles.items():
        if len(depths):
            ax.step(np.concatenate([[depths[0]], depths]), t, where="post", marker=".", label=name)
    ax.set_xlabel("depth (camera z)")
    ax.set_ylabel("transmittance T")
    ax.set_ylim(-0.02, 1.02)
    ax.legend()
    if title:
        ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def save_image_grid(path: str | os.PathLike, rows: list[list[np.ndarray]], titles: list[str]) -> None:
    """A titled grid of pictures saved to ``path``: one row per entry of ``rows``, one column per
    title. RGB images [H,W,3] are clipped to [0, 1]; label maps [H,W] (integers, -1 = none, left
    white) are drawn with a 10-colour map."""
    fig, axes = plt.subplots(len(rows), len(titles), figsize=(3 * len(titles), 2.4 * len(rows)), squeeze=False)
    for r, images in enumerate(rows):
        for c, image in enumerate(images):
            if image.ndim == 2:
                axes[r, c].imshow(np.ma.masked_less(image, 0), cmap="tab10", vmin=0, vmax=9)
            else:
                axes[r, c].imshow(np.clip(image, 0, 1))
            axes[r, c].axis("off")
            if r == 0:
                axes[r, c].set_title(titles[c], fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
