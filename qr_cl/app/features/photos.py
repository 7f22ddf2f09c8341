"""The scene's photos: ``DIR/<img_name>`` for every camera of the scene (``cameras.json``, or the file
name of each frame's ``file_path`` in transforms), with any common
image extension, read as RGB uint8 and checked against the camera's size."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from ...scene import Camera
from .errors import FeaturesError

#: Extensions looked for (any case) when ``img_name`` has none or names no file.
EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
#: Relative aspect-ratio difference tolerated between an image and its camera.
ASPECT_TOLERANCE = 0.01


def find_images(folder: str | Path, cameras: list[Camera]) -> list[Path]:
    """The image of each camera (same order); FeaturesError naming the first camera without one
    and how many lack one."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FeaturesError(f"{folder}: no such image folder (--images)")
    by_name = {p.name.lower(): p for p in folder.iterdir() if p.is_file()}
    found, missing = [], []
    for cam in cameras:
        name = Path(cam.name)
        keys = [name.name.lower()] + [(name.stem + ext).lower() for ext in EXTENSIONS] \
            + [(name.name + ext).lower() for ext in EXTENSIONS]
        hit = next((by_name[k] for k in keys if k in by_name), None)
        (found if hit else missing).append(hit or cam.name)
    if missing:
        more = f" (and {len(missing) - 1} more cameras)" if len(missing) > 1 else ""
        raise FeaturesError(f"{folder / str(missing[0])}: no image for camera {missing[0]!r}{more}; looked for "
                            f"{missing[0]} with the extensions {', '.join(EXTENSIONS)}")
    return found


def read_image(path: Path, camera: Camera) -> np.ndarray:
    """[H, W, 3] uint8 RGB of the image at ``path``; FeaturesError naming it when it is unreadable
    or its aspect ratio differs from the camera's (another size of the same aspect is fine: the
    masks are made at the image's size)."""
    try:
        with Image.open(path) as im:
            rgb = np.asarray(im.convert("RGB"))
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise FeaturesError(f"{path}: not a readable image ({exc})") from None
    h, w = rgb.shape[:2]
    want = camera.width / camera.height
    if abs(w / h - want) > ASPECT_TOLERANCE * want:
        raise FeaturesError(f"{path}: image is {w}x{h} (WxH) but its camera says {camera.width}x{camera.height} "
                            f"for {camera.name!r}, a different aspect ratio")
    return rgb
