"""``qr-cl demo``: the embedded default job (for now a procedural scene rendered to PNGs)."""
from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl demo``."""
    parser.add_argument("--out", default="qr-cl-demo", help="output folder (default ./qr-cl-demo)")
    parser.add_argument("--gaussians", type=int, default=20000, help="scene size (default 20000)")
    parser.add_argument("--views", type=int, default=8, help="orbit views (default 8)")
    parser.add_argument("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> int:
    """Generate the procedural scene, save it as PLY and render orbit views to PNGs."""
    from .camera import orbit_cameras
    from .cli import render_views
    from .procedural import procedural_scene
    from .scene import save_ply
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = procedural_scene(args.gaussians, seed=args.seed)
    save_ply(out / "procedural.ply", scene)
    cameras = orbit_cameras(scene.means, args.views, 640, 480, elevation_deg=30)
    seconds = render_views(scene, cameras, out, None, prefix="view_")
    print(f"demo: {len(scene)} procedural Gaussians (SH degree {scene.sh_degree}) rendered from "
          f"{len(cameras)} orbit views in {seconds:.1f} s.\nReport: {out.resolve()} "
          "(view_*_rgb.png, *_depth.png, *_alpha.png, procedural.ply)")
    return 0
