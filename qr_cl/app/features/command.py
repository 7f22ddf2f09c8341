"""``qr-cl features``: LangSplat's language features for every frame of a scene's cameras (its
cameras.json, or a SceneSplat folder's transforms_train.json: :func:`qr_cl.scene.scene_camera_file`).

Reads ``DIR/<img_name>`` per camera (``<file_path>``'s file name for transforms), makes SAM's automatic masks at LangSplat's four levels,
encodes each mask's crop with CLIP's image encoder and writes ``SCENE/language_features/<img>_s.npy``
and ``<img>_f.npy`` (:mod:`.frames`), frame by frame and atomically, so an interrupted run goes on
where it stopped (:mod:`.store`). ``--workers N`` runs frames in N processes (:mod:`.workers`);
``--shard I/N`` does one of N disjoint parts of the frames, for runs that split a scene without
talking to each other (:mod:`.shards`). ``--classes`` also writes ``SCENE/classes.json`` with the
same CLIP's text features (:mod:`.classes`). Models are built in plain torch from the weights files
(:mod:`.clip_model`, :mod:`.sam_model`); nothing is downloaded.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import asdict
from pathlib import Path

from ..arguments import nonnegative_int, positive_int
from ..process import keep_freed_memory, process_cores
from .errors import FeaturesError
from .shards import Shard, shard_spec

#: What the command needs beyond the core install (the ``features`` extra).
EXTRA_MODULES = ("scipy", "regex")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl features``."""
    parser.add_argument("scene", help="scene folder with cameras.json or transforms_train.json (language_features/ "
                                      "is written there)")
    parser.add_argument("--images", required=True, help="folder of the photos: <img_name> of each camera, any "
                                                        "common image extension")
    parser.add_argument("--clip-weights", required=True, help="OpenCLIP (.bin/.safetensors) or OpenAI (.pt) CLIP "
                                                              "ViT weights file, e.g. ViT-B-16 laion2b_s34b_b88k")
    parser.add_argument("--sam-weights", required=True, help="SAM checkpoint sam_vit_{b,l,h}_*.pth, or MobileSAM's "
                                                            "mobile_sam.pt (the fast profile)")
    parser.add_argument("--clip-model", help="OpenCLIP name of the CLIP weights (e.g. ViT-B-16, ViT-B-32-quickgelu); "
                                             "checked against the file, which gives it by default")
    parser.add_argument("--clip-vocab", help="CLIP's bpe_simple_vocab_16e6.txt.gz for --classes (default: beside "
                                             "the CLIP weights or from an installed open_clip)")
    parser.add_argument("--classes", help="class names, comma-separated or a file: writes SCENE/classes.json")
    parser.add_argument("--device", default="cpu", help="torch device (default cpu; e.g. cuda, cuda:1, mps, xpu)")
    parser.add_argument("--threads", type=positive_int, help="torch CPU threads in all, shared by the workers "
                                                             "(default: this process's cores)")
    parser.add_argument("--workers", type=positive_int, default=1, help="worker processes, each loading the models "
                                                                        "and doing whole frames (default 1: in this "
                                                                        "process)")
    parser.add_argument("--shard", type=shard_spec, default=Shard(), metavar="I/N",
                        help="do only the frames at positions p (0-based, the cameras' order) with p %% N == I-1, "
                             "e.g. 2/8 in an array job; N such runs write every frame once (default 1/1)")
    parser.add_argument("--batch", type=positive_int, default=32, help="mask crops per CLIP batch (default 32)")
    parser.add_argument("--points-per-side", type=positive_int, default=32, help="SAM point grid per side (LangSplat: 32)")
    parser.add_argument("--crop-layers", type=nonnegative_int, default=1, help="SAM crop layers (LangSplat: 1, i.e. 1+4 crops; "
                                                                                 "0: the fast setting, one embedding a frame)")
    parser.add_argument("--overwrite", action="store_true", help="redo frames already written")


def run(args: argparse.Namespace) -> int:
    """Write the features (module docstring); bad input: one line, exit status 2."""
    try:
        return _run(args)
    except FeaturesError as exc:
        print(f"qr-cl: error: {exc}", file=sys.stderr)
        return 2


def _device(name: str):
    import torch

    try:
        device = torch.device(name)
        torch.empty(1, device=device)
    except (RuntimeError, AssertionError) as exc:
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise FeaturesError(f"--device {name}: not usable here ({reason})") from None
    return device


def _check_extra() -> None:
    import importlib.util

    absent = [m for m in EXTRA_MODULES if importlib.util.find_spec(m) is None]
    if absent:
        raise FeaturesError(f"qr-cl features needs {', '.join(absent)}: pip install -e \".[features]\"")


def _classes(args, clip, scene: Path) -> None:
    from .classes import class_features, encoder_record, read_class_names, write_classes
    from .tokenizer import ClipTokenizer, find_vocabulary

    names = read_class_names(args.classes)
    try:
        tokenizer, missing = ClipTokenizer(find_vocabulary(args.clip_vocab, args.clip_weights)), None
    except FeaturesError as exc:
        if args.clip_vocab is not None:
            raise
        tokenizer, missing = None, exc
    rows, sources = class_features(clip, tokenizer, names, missing)
    write_classes(scene / "classes.json", names, rows, sources, encoder_record(clip, Path(args.clip_weights)))
    print(f"{scene / 'classes.json'}: {len(names)} classes ({clip.arch.name} text features)")


def _in_process(sam, clip, work, settings, batch: int, folder: Path):
    """(stem, masks) of each frame of ``work`` as it is written, in this process."""
    from . import store
    from .frames import frame_features
    from .photos import read_image

    for cam, path, stem in work:
        result = frame_features(sam, clip, read_image(path, cam), settings, batch)
        store.write_frame(folder, stem, result.ids, result.features)
        yield stem, sum(result.counts)


def _in_workers(args, work, settings, folder: Path, threads: int):
    """(stem, masks) of each frame of ``work`` as a worker writes it (:mod:`.workers`)."""
    from .workers import WorkerPool, WorkerSetup, worker_threads

    workers = min(args.workers, len(work))
    setup = WorkerSetup(str(args.clip_weights), args.clip_model, str(args.sam_weights), args.device,
                        worker_threads(threads, workers), settings, args.batch, folder)
    with WorkerPool(setup, workers) as pool:
        yield from pool.frames(work)


def _run(args: argparse.Namespace) -> int:
    _check_extra()
    import torch
    from tqdm import tqdm

    from ...scene import load_cameras, scene_camera_file
    from .clip_model import load_clip
    from .masks import MaskSettings
    from .photos import find_images
    from .sam_model import load_sam
    from .store import check_record, check_record_kept, remove_stale_temporaries
    from .weights import file_sha256

    scene = Path(args.scene)
    cameras = load_cameras(scene_camera_file(scene))
    images = find_images(args.images, cameras)
    device = _device(args.device)
    threads = args.threads or process_cores()
    torch.set_num_threads(threads)
    keep_freed_memory()                       # the decoder's temporaries: reused, not faulted in per batch
    clip = load_clip(args.clip_weights, args.clip_model).to(device)
    if args.classes:
        _classes(args, clip, scene)
    sam = load_sam(args.sam_weights).to(device)
    settings = MaskSettings(points_per_side=args.points_per_side, crop_layers=args.crop_layers)
    record = {"clip": {"model": clip.arch.name, "weights": Path(args.clip_weights).name,
                       "sha256": file_sha256(args.clip_weights)},
              "sam": {"model": sam.arch.name, "weights": Path(args.sam_weights).name,
                      "sha256": file_sha256(args.sam_weights)},
              "masks": asdict(settings)}
    names = f"SAM {sam.arch.name}, CLIP {clip.arch.name}"
    folder = scene / "language_features"
    stems = [Path(c.name).stem for c in cameras]
    shard = args.shard
    mine = shard.select(list(zip(cameras, images, stems)))
    folder.mkdir(parents=True, exist_ok=True)
    removed = remove_stale_temporaries(folder, [stem for _, _, stem in mine])
    if removed:
        print(f"{folder}: removed {removed} temporary files of an interrupted run")
    todo = set(check_record(folder, record, [stem for _, _, stem in mine], args.overwrite, stems))
    if len(todo) < len(mine):
        print(f"{folder}: {len(mine) - len(todo)} of {len(mine)} frames already written; going on")
    work = [frame for frame in mine if frame[2] in todo]
    if args.workers > 1 and work:
        del sam, clip                                  # each worker loads its own
        if device.type == "cuda":
            torch.cuda.empty_cache()
        frames = _in_workers(args, work, settings, folder, threads)
    else:
        frames = _in_process(sam, clip, work, settings, args.batch, folder)
    masks = 0
    try:
        for _, count in tqdm(frames, total=len(work), desc="features", unit="frame"):
            masks += count
            check_record_kept(folder, record)
    finally:
        frames.close()                                 # stops the workers, whatever stopped the loop
    part = "" if shard.whole else f"shard {shard}: {len(mine)} of {len(stems)} frames; "
    print(f"{folder}: {len(work)} frames written ({part}{masks} masks; {names}, {device})")
    return 0
