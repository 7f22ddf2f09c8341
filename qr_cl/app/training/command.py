"""``qr-cl train``: GS-Net trained through a feature renderer with the contrastive loss (paper App. D).

The command, also run as ``python -m qr_cl.app.training.command`` (e.g. under torchrun): one process, or one
rank of a torchrun job when ``WORLD_SIZE`` > 1. The training itself: :mod:`qr_cl.app.training.trainer`.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import torch.distributed as dist

from ...runtime import SAMPLERS
from ..arguments import OneLineParser, nonnegative_int, positive_float, positive_int
from ..process import cap_kernel_threads, keep_freed_memory, torch_threads
from .config import TrainConfig
from .network import NETS
from .trainer import train


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl train`` / ``python -m qr_cl.app.training.command``."""
    d = TrainConfig(scenes=["-"], out="-")
    parser.add_argument("scenes", nargs="+", help="scene folders (point_cloud.ply, cameras.json, language_features/)")
    parser.add_argument("--out", required=True, help="output folder (checkpoint.pt, train_log.json)")
    parser.add_argument("--steps", type=positive_int, default=d.steps, help=f"optimizer steps (default {d.steps})")
    parser.add_argument("--batch-scenes", type=positive_int, default=d.batch_scenes,
                        help="scenes per step, split over ranks (default 1)")
    parser.add_argument("--views", type=positive_int, default=d.views, help="views per scene per step (default 4)")
    parser.add_argument("--rays", type=positive_int, default=d.rays, help="rays per view (default 2048)")
    parser.add_argument("--sampler", choices=SAMPLERS, default=d.sampler, help="feature renderer (default quantile)")
    parser.add_argument("-k", type=positive_int, default=d.k, help=f"K of quantile/topk (default {d.k})")
    parser.add_argument("--lr", type=positive_float, default=d.lr, help="Adam learning rate (default 1e-2)")
    parser.add_argument("--temperature", type=positive_float, default=d.temperature, help="loss temperature (default 0.1)")
    parser.add_argument("--grid-size", type=positive_float, default=d.grid_size, help="voxel size, scene units (default 0.1)")
    parser.add_argument("--net", choices=sorted(NETS), default=d.net, help="UNet preset (default small)")
    parser.add_argument("--seed", type=nonnegative_int, default=d.seed)
    parser.add_argument("--checkpoint-every", type=positive_int, default=d.checkpoint_every, help="steps (default 50)")
    parser.add_argument("--plateau-interval", type=positive_int, default=d.plateau_interval,
                        help="steps per ReduceLROnPlateau observation (default 25)")
    parser.add_argument("--level", type=nonnegative_int, default=d.level, help="LangSplat mask level (default 0)")
    parser.add_argument("--view-selections-mb", type=nonnegative_int, default=d.view_selections_mb,
                        help="MiB of whole-view selections kept for gathering rays (default 1024; 0 selects "
                             "each step's rays afresh; same results either way)")
    parser.add_argument("--resume", action="store_true", help="continue from <out>/checkpoint.pt")
    parser.add_argument("--torch-threads", type=positive_int, default=1, help="torch intra-op threads (default 1)")


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """A TrainConfig from parsed ``add_arguments`` options."""
    return TrainConfig(scenes=[str(Path(s).resolve()) for s in args.scenes], out=args.out, steps=args.steps,
                       batch_scenes=args.batch_scenes, views=args.views, rays=args.rays, sampler=args.sampler,
                       k=args.k, lr=args.lr, temperature=args.temperature, grid_size=args.grid_size, net=args.net,
                       seed=args.seed, checkpoint_every=args.checkpoint_every,
                       plateau_interval=args.plateau_interval, level=args.level,
                       view_selections_mb=args.view_selections_mb)


def run(args: argparse.Namespace) -> int:
    """Train (one process, or one rank of a torchrun job when WORLD_SIZE > 1)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    if world > 1:
        dist.init_process_group("gloo")
    cap_kernel_threads()
    keep_freed_memory()
    try:
        with torch_threads(args.torch_threads):
            trainer = train(config_from_args(args), args.resume, rank, world)
    except KeyboardInterrupt:
        return 130
    except ValueError as exc:
        print(f"qr-cl train: error: {exc}", file=sys.stderr)
        return 2
    finally:
        if world > 1:
            dist.destroy_process_group()
    if rank == 0:
        print(f"trained {trainer.step} steps, final loss {trainer.history[-1]:.4f}; "
              f"checkpoint {Path(args.out) / 'checkpoint.pt'}")
    if world > 1:
        # A rank of a torchrun job ends here, without Python's finalization: gloo's worker threads
        # destroy a finished all_reduce's work, and with it the last references to the gradients,
        # after the caller's wait returns; when that ran into finalization, which ends threads
        # asking for the GIL, the rank aborted now and then ("terminate called without an active
        # exception" in tests/app/test_train_distributed.py; a barrier before the exit only made it rarer).
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m qr_cl.app.training.command`` (e.g. under torchrun)."""
    parser = OneLineParser(prog="python -m qr_cl.app.training.command", description=__doc__.split("\n")[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
