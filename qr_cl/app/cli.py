"""The ``qr-cl`` command line: devices and render here; every other command in its package's command.py.

The delegated commands (:data:`DELEGATED`): demo, bench, train, eval, reproduce, register, query,
view, features and convert, each a module with ``add_arguments(parser)`` and ``run(args)``.
"""
from __future__ import annotations

import argparse
import importlib
import sys
import warnings
from pathlib import Path

from tqdm import tqdm

from ..render import check_in_child, render_volume_fused
from ..runtime import (BufferLimitError, HostMemoryError, NoDeviceError, choose_device, implementation, list_devices,
                       loop_limit, self_check_enabled, trial_run)
from ..scene import SceneFormatError, load_cameras, load_layout_instance, load_scene, orbit_cameras
from .arguments import AXES, OneLineParser, nonnegative_int, positive_int
from .training.network import CheckpointError
from .timing import Stopwatch


# Sub-commands implemented in their packages' command.py, each with add_arguments(parser) and run(args).
DELEGATED = {"demo": ("demo", "the embedded default job (see README)"),
             "bench": ("bench", "kernel benchmarks: sweep, compare, scale, implementations"),
             "train": ("training", "train GS-Net through a feature renderer on scene folders"),
             "eval": ("evaluation", "open-vocabulary 3D segmentation: mIoU/mAcc tables, images, PLYs"),
             "reproduce": ("experiments", "the paper's controlled experiments on 3DGS-like rooms: report and plots"),
             "register": ("registration", "Dr.Splat's training-free registration of mask features onto Gaussians"),
             "query": ("query", "where is some text in a scene: relevancy per Gaussian, heatmaps, PLYs"),
             "view": ("viewer", "a web viewer on localhost rendering the scene on the CPU"),
             "features": ("features", "LangSplat mask features of a scene's photos (SAM + CLIP, any torch device)"),
             "convert": ("convert", "a scene from one format to another: PLY, .splat, SceneSplat folders")}


def _command(package: str):
    """The command module of ``qr_cl.app.<package>``."""
    return importlib.import_module(f"qr_cl.app.{package}.command")


def _cmd_devices(args: argparse.Namespace) -> int:
    """Every device with its implementation and the self-check's verdict (trial kernels and loop
    probe here, the render check in a child process per device); * marks the one qr-cl uses."""
    devices = list_devices()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            chosen = choose_device().int_ptr
        except NoDeviceError:
            chosen = None
    for pi, di, platform, dev in devices:
        status = trial_run(dev)
        if status is None:
            limit = loop_limit(dev)
            status = ("trial kernels ok, " + (f"loops end after {limit} iterations (walks in windows), "
                                              if limit else "")
                      + (check_in_child(pi, di) if self_check_enabled() else "self-check off (QR_CL_SELF_CHECK)"))
        print(f"{'*' if dev.int_ptr == chosen else ' '} [{pi}:{di}] {implementation(dev)}  "
              f"({'GPU' if dev.type & 4 else 'CPU' if dev.type & 2 else 'other'}, "
              f"{dev.max_compute_units} compute units, {dev.global_mem_size >> 20} MiB) - {status}")
    print("* = the device qr-cl uses (QR_CL_DEVICE=cpu|gpu|<platform substring>:<index> chooses another)"
          if chosen is not None else "no device passed the self-check: qr-cl refuses to render here")
    return 0 if chosen is not None else 2


def render_views(gaussians, cameras, out: Path, sh_degree: int | None, prefix: str = "") -> float:
    """Render RGB, depth and alpha PNGs of every camera into ``out``; returns seconds spent."""
    from .images import save_alpha, save_depth, save_rgb   # matplotlib: not imported by the other commands

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


def _cmd_render(args: argparse.Namespace) -> int:
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
        cameras = orbit_cameras(gaussians.means, args.orbit, args.width or 640, args.height or 480,
                                up_axis=args.up_axis)
    seconds = render_views(gaussians, cameras, Path(args.out), args.sh_degree)
    print(f"rendered {len(cameras)} views of {len(gaussians)} Gaussians in {seconds:.1f} s -> {args.out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="qr-cl", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("devices", help="list OpenCL devices and mark the one qr-cl uses")
    r = sub.add_parser("render", help="render a 3DGS scene (.ply, .splat or a SceneSplat folder) to PNGs")
    r.add_argument("scene", help="INRIA 3DGS .ply, antimatter15 .splat, SceneSplat folder or scene folder")
    views = r.add_mutually_exclusive_group()
    views.add_argument("--cameras", help="3DGS cameras.json, V3DG layout or NeRF/nerfstudio transforms(_train).json")
    views.add_argument("--orbit", type=positive_int, default=8, help="number of orbit cameras (default 8)")
    r.add_argument("--width", type=positive_int, help="image width in px (orbit default 640; rescales --cameras)")
    r.add_argument("--height", type=positive_int, help="image height in px (orbit default 480)")
    r.add_argument("--up-axis", type=int, choices=AXES, default=2, help="world up axis for orbits (2 = z, 1 = y)")
    r.add_argument("--sh-degree", type=nonnegative_int, help="use at most this SH degree (default: the file's)")
    r.add_argument("--out", required=True, help="output folder")
    for name, (package, text) in DELEGATED.items():
        _command(package).add_arguments(sub.add_parser(name, help=text))
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``qr-cl`` console script."""
    args = build_parser().parse_args(argv)
    commands = {"devices": _cmd_devices, "render": _cmd_render}
    commands.update({name: _command(package).run for name, (package, _) in DELEGATED.items()})
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.formatwarning = lambda msg, cat, *a, **k: f"warning: {msg}\n"
        try:
            return commands[args.command](args)
        except (SceneFormatError, NoDeviceError, CheckpointError, BufferLimitError, HostMemoryError) as exc:
            print(f"qr-cl: error: {exc}", file=sys.stderr)
            return 2
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError) as exc:
            print(f"qr-cl: error: {exc.filename or ''}: {exc.strerror or exc}" if exc.filename
                  else f"qr-cl: error: {exc}", file=sys.stderr)
            return 2


if __name__ == "__main__":
    sys.exit(main())
