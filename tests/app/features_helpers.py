"""Tiny random-weight models saved as their publishers' files, and scenes of a few frames, for the
``qr-cl features`` tests."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from qr_cl.app import cli

from qr_cl.app.features.clip_model import ClipArchitecture
from qr_cl.app.features.random_models import random_clip, random_sam, save_weights, write_vocabulary
from qr_cl.app.features.sam_model import SamArchitecture
from qr_cl.scene import Camera

#: A tiny CLIP (image tower width 64, 2 blocks, 16 px patches at 64 px; text tower width 64).
TINY_SAM = SamArchitecture(64, 2, 2, (1,))
CLASS_WORDS = ["wall", "floor", "chair", "fox", "object"]
#: Fast mask settings for tests: 2x2 points, no crops.
FAST = ["--points-per-side", "2", "--crop-layers", "0"]


def tiny_clip_arch(vocab: int) -> ClipArchitecture:
    """The tests' CLIP with a text tower of ``vocab`` tokens."""
    return ClipArchitecture(64, 2, 16, 64, 256, 32, 64, 1, 16, vocab, 256, False)


def write_models(folder: Path, clip_name: str = "open_clip_model.safetensors") -> dict[str, Path]:
    """Tiny CLIP (``clip_name``, a BPE vocabulary beside it) and SAM (``sam_vit_tiny.pth``) weights
    files in ``folder``; returns their paths by option."""
    folder.mkdir(parents=True, exist_ok=True)
    vocab = write_vocabulary(folder / "bpe_simple_vocab_16e6.txt.gz", [f"a {w}" for w in CLASS_WORDS])
    clip = save_weights(random_clip(tiny_clip_arch(vocab), seed=1), folder / clip_name)
    sam = save_weights(random_sam(TINY_SAM, seed=2), folder / "sam_vit_tiny.pth")
    return {"clip": clip, "sam": sam}


def camera_entry(i: int, cam: Camera) -> dict:
    """A 3DGS cameras.json entry of ``cam`` (camera-to-world rotation columns and position)."""
    return {"id": i, "img_name": cam.name, "width": cam.width, "height": cam.height,
            "position": cam.position.tolist(), "rotation": cam.viewmat[:3, :3].T.astype(float).tolist(),
            "fx": cam.fx, "fy": cam.fy}


def write_cameras(path: Path, cameras: list[Camera]) -> None:
    path.write_text(json.dumps([camera_entry(i, c) for i, c in enumerate(cameras)]))


def drawn_scene(folder: Path, frames: int = 3, width: int = 64, height: int = 48) -> tuple[Path, Path]:
    """(scene folder with cameras.json, image folder with ``view_<i>.png``): discs and boxes on a
    gradient, a few frames; no 3DGS scene needed."""
    scene, images = folder / "scene", folder / "images"
    scene.mkdir(parents=True)
    images.mkdir()
    cams = []
    yy, xx = np.mgrid[:height, :width]
    for i in range(frames):
        img = np.stack([xx * 4 % 256, yy * 5 % 256, np.full_like(xx, 40 * i)], -1).astype(np.uint8)
        disc = (xx - 20 - 6 * i) ** 2 + (yy - 24) ** 2 < 120
        img[disc] = (230, 40, 40)
        img[8:20, 40:58] = (20, 200, 60)
        Image.fromarray(img).save(images / f"view_{i}.png")
        cams.append(Camera(np.eye(4, dtype=np.float32), 50.0, 50.0, width / 2, height / 2, width, height, f"view_{i}"))
    write_cameras(scene / "cameras.json", cams)
    return scene, images


def run_features(scene: Path, images: Path, models: dict[str, Path], *extra: str) -> int:
    """``qr-cl features`` on ``scene`` with the tiny ``models``, one thread, the fast mask settings."""
    return cli.main(["features", str(scene), "--images", str(images), "--clip-weights", str(models["clip"]),
                     "--sam-weights", str(models["sam"]), "--threads", "1", *FAST, *extra])


def assert_matches_predictor(predictor_class, reference, ours, image: np.ndarray, points: np.ndarray) -> None:
    """``ours`` (a loaded :class:`~qr_cl.app.features.sam_model.Sam`) embeds ``image`` and predicts
    the multimask logits and IoU of ``points`` as the official ``predictor_class`` of ``reference``."""
    predictor = predictor_class(reference)
    predictor.set_image(image)
    coords = torch.as_tensor(predictor.transform.apply_coords(points, image.shape[:2]), dtype=torch.float32)
    logits, iou, _ = predictor.predict_torch(coords[:, None], torch.ones(len(points), 1), multimask_output=True,
                                             return_logits=True)
    view = ours.embed(image)
    torch.testing.assert_close(view.embedding, predictor.features, atol=1e-4, rtol=1e-4)
    got_logits, got_iou = view.predict(points)
    torch.testing.assert_close(got_iou, iou, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(got_logits, logits, atol=1e-3, rtol=1e-3)
