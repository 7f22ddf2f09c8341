"""The ``qr-cl`` command line: the parser and the errors that end a command in one line. Every
command (:data:`DELEGATED`) lives in its package's ``command.py``, a module with
``add_arguments(parser)`` and ``run(args)``.
"""
from __future__ import annotations

import argparse
import importlib
import sys
import warnings

from ..runtime import BufferLimitError, HostMemoryError, NoDeviceError
from ..scene import SceneFormatError
from .arguments import OneLineParser
from .training.network import CheckpointError


#: Each command: (the package under qr_cl.app whose command.py implements it, its help line).
DELEGATED = {"devices": ("devices", "list OpenCL devices and mark the one qr-cl uses"),
             "render": ("rendering", "render a 3DGS scene (.ply, .splat or a SceneSplat folder) to PNGs"),
             "demo": ("demo", "the embedded default job (see README)"),
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


def build_parser() -> argparse.ArgumentParser:
    """The parser of every command."""
    parser = OneLineParser(prog="qr-cl", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    for name, (package, text) in DELEGATED.items():
        _command(package).add_arguments(sub.add_parser(name, help=text))
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``qr-cl`` console script."""
    args = build_parser().parse_args(argv)
    commands = {name: _command(package).run for name, (package, _) in DELEGATED.items()}
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
