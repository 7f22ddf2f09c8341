"""Densification against none: the fit of ``fit_and_train_gsnet.py`` run twice on a real capture,
with and without its gsplat-style :class:`Densifier` (driven by ``meta["means2d"].grad`` of
``qr_cl.rasterization``), from the same Gaussians for the same number of steps; prints the PSNR
over every view of each fit, its Gaussian count and time.

    python examples/densification_vs_none.py [--ply ../shared/data/wakufactory-fox/fox.ply] [--steps 300]
"""
from __future__ import annotations

import argparse
import time
import warnings

import torch

import qr_cl
from fit_and_train_gsnet import DEFAULT_PLY, fit, target_images


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ply", default=str(DEFAULT_PLY), help="a 3DGS capture (INRIA PLY)")
    parser.add_argument("--gaussians", type=int, default=3000, help="Gaussians at the start")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--width", type=int, default=128)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        capture = qr_cl.load_ply(args.ply)
    cameras = qr_cl.orbit_cameras(capture.means, args.views, args.width, args.width * 3 // 4)
    targets = target_images(capture, cameras)
    for densify in (False, True):
        start = time.perf_counter()
        _, fitted, _, densifier = fit(capture, cameras, targets, args.gaussians, args.steps, args.seed, densify)
        seconds = time.perf_counter() - start
        psnr = float(-10 * torch.log10(((target_images(fitted, cameras) - targets) ** 2).mean()))
        grown = "" if densifier is None else f" (refinements: {densifier.history})"
        print(f"{'densified' if densify else 'not densified'}: PSNR over {len(cameras)} views {psnr:.2f} dB, "
              f"{args.gaussians} -> {len(fitted)} Gaussians, {seconds:.0f} s{grown}")


if __name__ == "__main__":
    main()
