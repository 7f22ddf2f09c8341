"""RGB and 512-D features from one selection: ``qr_cl.rasterization(..., extra_signals=F)`` against
two calls (the RGB render, then the features as colours), on a real capture, forward and forward +
backward (gradients w.r.t. the features and the Gaussians).

    python examples/one_pass_rgb_and_features.py [--ply ../shared/data/wakufactory-fox/fox.ply]

One call projects, bins and selects once per camera and blends the 3 + 512 channels in one pass;
two calls do all of it twice. Prints the median time of each over ``--rounds`` and their ratio.
"""
from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np
import torch

import qr_cl

DEFAULT_PLY = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "wakufactory-fox" / "fox.ply"


def median_seconds(call, rounds: int) -> float:
    """The median wall time of ``call()`` over ``rounds`` runs, after one warm-up run."""
    call()
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ply", type=Path, default=DEFAULT_PLY, help="a 3DGS capture (INRIA PLY)")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--channels", type=int, default=512, help="feature channels besides RGB")
    parser.add_argument("--sampler", default="quantile")
    parser.add_argument("-k", type=int, default=40)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    if not args.ply.is_file():
        parser.error(f"{args.ply}: no such file (pass --ply with a 3DGS PLY, e.g. the fox of ../shared/data)")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        g = qr_cl.load_ply(args.ply)
    cam = qr_cl.orbit_cameras(g.means, 4, args.width, args.width * 3 // 4)[1]
    viewmats, Ks = torch.from_numpy(cam.viewmat)[None], torch.from_numpy(np.asarray(cam.K, np.float32))[None]
    rgb = torch.from_numpy(g.rgb.astype(np.float32))
    features = torch.from_numpy(np.random.default_rng(0).normal(size=(len(g), args.channels)).astype(np.float32))
    options = dict(sampler=args.sampler, k=args.k, packed=False)

    def tensors(grad: bool) -> list[torch.Tensor]:
        return [torch.from_numpy(np.asarray(a, np.float32)).requires_grad_(grad)
                for a in (g.means, g.quats, g.scales, g.opacities)] + [rgb.clone().requires_grad_(grad),
                                                                      features.clone().requires_grad_(grad)]

    def one(grad: bool) -> None:
        x = tensors(grad)
        with torch.set_grad_enabled(grad):
            image, _, meta = qr_cl.rasterization(*x[:5], viewmats, Ks, cam.width, cam.height, extra_signals=x[5],
                                                 **options)
            if grad:
                (image.sum() + meta["render_extra_signals"].sum()).backward()

    def two(grad: bool) -> None:
        x = tensors(grad)
        with torch.set_grad_enabled(grad):
            image, _, _ = qr_cl.rasterization(*x[:5], viewmats, Ks, cam.width, cam.height, **options)
            signals, _, _ = qr_cl.rasterization(*x[:4], x[5], viewmats, Ks, cam.width, cam.height, **options)
            if grad:
                (image.sum() + signals.sum()).backward()

    print(f"{len(g)} Gaussians, {cam.width}x{cam.height} px, RGB + {args.channels} channels, "
          f"sampler={args.sampler} k={args.k}, median of {args.rounds}")
    for grad in (False, True):
        t_one, t_two = median_seconds(lambda: one(grad), args.rounds), median_seconds(lambda: two(grad), args.rounds)
        what = "forward + backward" if grad else "forward"
        print(f"{what:>18}: one call {t_one * 1e3:7.1f} ms, two calls {t_two * 1e3:7.1f} ms, "
              f"two / one = {t_two / t_one:.2f}")


if __name__ == "__main__":
    main()
