"""``qr-cl render``: RGB, depth and alpha PNGs of a scene (``.ply``, ``.splat``, a SceneSplat or
scene folder) from orbit cameras or a camera file, through the fused V-Render."""
from __future__ import annotations

import argparse
from pathlib import Path

from tqdm import tqdm

from ...render import render_volume_fused
from ...runtime import DEFAULTS
from ...scene import Camera, Gaussians, load_cameras, load_layout_instance, load_scene, orbit_cameras
from ..arguments import AXES, nonnegative_int, positive_int
from ..timing import Stopwatch


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl render``."""
    parser.add_argument("scene", help="INRIA 3DGS .ply, antimatter15 .splat, SceneSplat folder or scene folder")
    views = parser.add_mutually_exclusive_group()
    views.add_argument("--cameras", help="3DGS cameras.json, V3DG layout or NeRF/nerfstudio transforms(_train).json")
    views.add_argument("--orbit", type=positive_int, default=8, help="number of orbit cameras (default 8)")
    parser.add_argument("--width", type=positive_int, help=f"image width in px (orbit default {DEFAULTS.width}; rescales --cameras)")
    parser.add_argument("--height", type=positive_int, help=f"image height in px (orbit default {DEFAULTS.height})")
    parser.add_argument("--up-axis", type=int, choices=AXES, default=2, help="world up axis for orbits (2 = z, 1 = y)")
    parser.add_argument("--sh-degree", type=nonnegative_int, help="use at most this SH degree (default: the file's)")
    parser.add_argument("--out", required=True, help="output folder")


def render_views(gaussians: Gaussians, cameras: list[Camera], out: Path, sh_degree: int | None,
                 prefix: str = "") -> float:
    """Render ``<prefix><i>_rgb.png``, ``_depth.png`` and ``_alpha.png`` of every camera into
    ``out`` (SH up to ``sh_degree``, all of the scene's when None); returns seconds spent."""
    from ..images import save_alpha, save_depth, save_rgb   # matplotlib: only when rendering (the parser imports every command)

    out.mkdir(parents=True, exist_ok=True)
    degree = gaussians.sh_degree if sh_degree is None else min(sh_degree, gaussians.sh_degree)
    watch = Stopwatch()
    for i, cam in enumerate(tqdm(cameras, desc="render", unit="view")):
        image, alpha, meta = render_volume_fused(gaussians.means, gaussians.quats, gaussians.scales,
                                                 gaussians.opacities, gaussians.sh, cam.viewmat, cam.K,
                                                 cam.width, cam.height, sh_degree=degree)
        name = f"{prefix}{i:03d}"
        save_rgb(out / f"{name}_rgb.png", image.numpy())
        save_depth(out / f"{name}_depth.png", meta["depth"], alpha.numpy())
        save_alpha(out / f"{name}_alpha.png", alpha.numpy())
    return watch.seconds


def run(args: argparse.Namespace) -> int:
    """Render every camera of ``--cameras`` (or ``--orbit`` cameras) of the scene into ``--out``."""
    gaussians = load_scene(args.scene)
    if args.cameras:
        cameras = load_cameras(args.cameras)
        instance = load_layout_instance(args.cameras)
        if instance is not None:
            print(f"{args.cameras}: placing the scene by the layout's instance transform "
                  f"(scale {instance[0]:.4g})")
            gaussians = gaussians.transformed(*instance)
        if args.width:
            cameras = [c.resized(args.width, args.height or round(c.height * args.width / c.width))
                       for c in cameras]
    else:
        cameras = orbit_cameras(gaussians.means, args.orbit, args.width or DEFAULTS.width, args.height or DEFAULTS.height,
                                up_axis=args.up_axis)
    seconds = render_views(gaussians, cameras, Path(args.out), args.sh_degree)
    print(f"rendered {len(cameras)} views of {len(gaussians)} Gaussians in {seconds:.1f} s -> {args.out}")
    return 0
