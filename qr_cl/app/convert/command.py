"""``qr-cl convert SRC DST``: a scene from one format to another. SRC is an INRIA 3DGS ``.ply``, an
antimatter15 ``.splat``, a SceneSplat folder or a scene folder; DST a ``.ply`` or a SceneSplat
folder (any other name). Values are kept within float32 rounding (docs/scenesplat.md); a
SceneSplat folder's labels, normals, language features and frames stay where they are (a PLY has
no place for them) and are named."""
from __future__ import annotations

import argparse
from pathlib import Path

from ...scene import SCENESPLAT_FILES, is_scenesplat, load_scene, save_ply, save_scenesplat


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl convert``."""
    parser.add_argument("src", help="a .ply, a .splat, a SceneSplat folder (coord.npy, ...) or a scene folder")
    parser.add_argument("dst", help="a .ply file, or a folder to write as SceneSplat's .npy files")
    parser.add_argument("--force", action="store_true", help="replace DST when it exists")


def run(args: argparse.Namespace) -> int:
    """Read SRC, write DST; print what was written and what a PLY cannot carry."""
    src, dst = Path(args.src), Path(args.dst)
    if not src.exists():
        raise FileNotFoundError(2, "no such scene file or folder", str(src))
    if dst.exists() and not args.force and (dst.is_file() or any(dst.iterdir())):
        raise SystemExit(f"qr-cl convert: {dst} exists (--force replaces it)")
    gaussians = load_scene(src)
    if dst.suffix.lower() == ".ply":
        save_ply(dst, gaussians)
        if is_scenesplat(src):
            left = sorted(p.stem for p in src.glob("*.npy") if p.stem not in SCENESPLAT_FILES + ("sh",))
            left += [p.name for p in src.glob("*.json")]
            if left:
                print(f"not in the PLY (kept in {src}): {', '.join(left)}")
    else:
        save_scenesplat(dst, gaussians)
    print(f"wrote {len(gaussians)} Gaussians (SH degree {gaussians.sh_degree}) to {dst}")
    return 0
