"""Measure OpenCL kernels against the numpy reference on the real scenes (max abs errors, times).

    python examples/kernel_vs_reference.py [--data ../shared/data]

Prints, per scene: projection errors (means2d px, conics, depths), radius mismatches, the image
error of the fused V-Render against the reference blend of the same tile lists and against the
all-reference pipeline, for RGB and 512-D features; and the time of one OpenCL render next to the
numpy reference's time, measured in this run.
"""
import argparse
import warnings
from pathlib import Path

import numpy as np

import qr_cl
from qr_cl.app.timing import timed
from qr_cl.scene import load_layout_instance
from qr_cl.stages import sh_ref, vrender_ref


def scenes(data: Path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fox = qr_cl.load_ply(data / "wakufactory-fox" / "fox.ply")
        layout = data / "v3dg-donut" / "_SingleDonut.json"
        donut = qr_cl.load_ply(data / "v3dg-donut" / "donut_fused.ply").transformed(*load_layout_instance(layout))
    yield "fox (orbit 640x480)", fox, qr_cl.orbit_cameras(fox.means, 8, 640, 480)[1]
    yield "donut (own camera, 640x360)", donut, qr_cl.load_cameras(layout)[0].resized(640, 360)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    data = Path(parser.parse_args().data)
    rng = np.random.default_rng(0)
    for name, g, cam in scenes(data):
        args = (g.means, g.quats, g.scales, g.opacities)
        view = (cam.viewmat, cam.K, cam.width, cam.height)
        qr_cl.rasterize(*args, g.rgb, *view)  # warm-up: kernel builds
        for label, feats in (("rgb", None), ("512-D", rng.random((len(g), 512), dtype=np.float32))):
            if feats is None:
                (img, alpha, meta), t_cl = timed(lambda: qr_cl.rasterize(*args, g.sh, *view, sh_degree=0))
                feats = sh_ref.sh_to_rgb(g.means, g.sh, cam.position)
            else:
                (img, alpha, meta), t_cl = timed(lambda: qr_cl.rasterize(*args, feats, *view))
            (full, full_alpha, _, proj), t_ref = timed(lambda: vrender_ref.render(*args, feats, *view))
            same_lists, *_ = vrender_ref.vrender(meta, meta["tile_ranges"], meta["flatten_ids"], feats,
                                         cam.width, cam.height)
            img = img.numpy()
            vis = (proj["radii"][:, 0] > 0) & (meta["radii"][:, 0] > 0)
            print(f"{name} {label}: OpenCL {t_cl * 1e3:.0f} ms, numpy reference {t_ref * 1e3:.0f} ms "
                  f"(x{t_ref / t_cl:.1f})")
            print(f"  projection max abs err: means2d {np.abs(meta['means2d'] - proj['means2d'])[vis].max():.2e} px, "
                  f"conics {np.abs(meta['conics'] - proj['conics'])[vis].max():.2e}, "
                  f"depths {np.abs(meta['depths'] - proj['depths'])[vis].max():.2e}; "
                  f"radius mismatches {(meta['radii'] != proj['radii']).any(1).sum()} of {len(g)}")
            diff = np.abs(img - full).max(-1)
            print(f"  image max abs err: vs reference blend of the same tile lists "
                  f"{np.abs(img - same_lists).max():.2e}; vs all-reference pipeline {diff.max():.2e} "
                  f"({(diff > 1e-4).sum()} of {diff.size} pixels > 1e-4); alpha {np.abs(alpha.numpy() - full_alpha).max():.2e}")


if __name__ == "__main__":
    main()
