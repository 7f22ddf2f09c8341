"""``qr-cl train``: GS-Net trained through a feature renderer with the contrastive loss (paper App. D).

Each step draws ``batch_scenes`` scenes (seeded by the step, identical on every rank); for each
scene ``views`` random views are drawn, ``rays`` pixels per view inside masks are selected with
the chosen sampler, GS-Net predicts the features of the Gaussians those selections use (the
UNet runs on every voxel; de-voxelization, head and normalization only for those rows) and the
rays rendered from them are scored by :func:`qr_cl.app.loss.contrastive_loss`. Adam;
ReduceLROnPlateau (factor 0.1) on the mean loss of every ``plateau_interval`` steps.

Where the time goes (demo rooms, 2 cores): the selections are geometry, so each view's
whole-image selection is made once and a step's rays are gathered from it (up to
``view_selections_mb`` of them are kept; then views are selected ray by ray each step), and the
next step's rays are made on a background thread while this step renders and back-propagates.
Torch runs one intra-op thread (the CLI's ``--torch-threads``): its OpenMP workers spin-wait at
barriers, and beside other busy processes two of them made a step 3.6-16x slower than one. The
sparse convolutions and GS-Net's head, most of a step, run as row blocks on
:func:`conv_thread_count` threads (both cores; results do not depend on the count, see
:mod:`qr_cl.backbone.conv`), and PoCL runs the kernels on both cores
(:func:`qr_cl.app.model.cap_kernel_threads`). They take turns: the training thread waits while it
renders, and the next step's rays are started after the network's forward (its convolutions),
beside the blend, so that a convolution thread and a PoCL worker are seldom both asked for one
core.

Scale-out: ``torchrun --nproc_per_node N -m qr_cl.train ...`` runs data-parallel over the
scenes of a step (gloo on CPU): rank r takes slots r, r+N, ...; gradients are summed with
all_reduce, so N ranks end with the weights of one rank accumulating the same scenes. Every
process creates its own OpenCL context (torchrun spawns fresh interpreters; never fork after
OpenCL init). BatchNorm running statistics stay per rank; rank 0's are checkpointed.

Checkpoints (``<out>/checkpoint.pt``) hold model, optimizer, scheduler and the step, written to
a temporary file and renamed; ``--resume`` continues exactly (all randomness derives from the
seed and the step).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from tqdm import tqdm

from ..backbone.conv import conv_threads
from ..runtime import SAMPLERS
from ..stages import prepare_backward
from .data import load_scene_folder
from .loss import StepRays, ViewSelections, rays_loss, step_rays
from .model import NETS, build_net, cap_kernel_threads, keep_freed_memory, process_cores, torch_threads

@dataclass
class TrainConfig:
    """Training options (lengths in scene units, counts per step)."""

    scenes: list[str]
    out: str
    steps: int = 200
    batch_scenes: int = 1
    views: int = 4
    rays: int = 2048
    sampler: str = "quantile"
    k: int = 40
    lr: float = 1e-2                    # chosen by experiment on the 3dgs rooms (README, "Choosing GS-Net's settings")
    temperature: float = 0.1
    grid_size: float = 0.1
    net: str = "small"
    seed: int = 0
    checkpoint_every: int = 50
    plateau_interval: int = 25
    patience: int = 2
    level: int = 0
    view_selections_mb: int = 1024      # whole-view selections kept (MiB; results do not depend on it)
    feature_dim: int = field(default=0)

    def __post_init__(self) -> None:
        if self.sampler not in SAMPLERS:
            raise ValueError(f"sampler={self.sampler!r}: choose one of {SAMPLERS}")
        if self.net not in NETS:
            raise ValueError(f"net={self.net!r}: choose one of {sorted(NETS)}")
        if not self.scenes:
            raise ValueError("no training scenes given")


def step_slots(cfg: TrainConfig, step: int, n_scenes: int) -> list[int]:
    """Scene indices of the ``batch_scenes`` slots of ``step`` (the same on every rank)."""
    rng = np.random.default_rng([cfg.seed, step, 7])
    return rng.choice(n_scenes, cfg.batch_scenes, replace=cfg.batch_scenes > n_scenes).tolist()


def conv_thread_count() -> int:
    """Threads for GS-Net's sparse convolutions: the cores this process may use
    (:func:`~qr_cl.app.model.process_cores`) over torch's intra-op threads, at least 1, so that
    convolution threads times torch threads never exceed the cores. PoCL's workers idle while the
    convolutions run (they take turns with the kernels: see the module docstring)."""
    return max(1, process_cores() // torch.get_num_threads())


def save_atomic(obj, path: Path) -> None:
    """torch.save to ``path`` via a temporary file and os.replace (never a half-written file)."""
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    torch.save(obj, tmp)
    os.replace(tmp, path)


class Trainer:
    """GS-Net, its optimizer and scheduler, the scenes, and the training loop of one rank."""

    def __init__(self, cfg: TrainConfig, rank: int = 0, world: int = 1):
        if cfg.batch_scenes % world:
            raise ValueError(f"batch_scenes={cfg.batch_scenes} must be a multiple of the {world} ranks")
        self.cfg, self.rank, self.world = cfg, rank, world
        self.scenes = [load_scene_folder(s, cfg.level) for s in cfg.scenes]
        dims = {s.feature_dim for s in self.scenes}
        if len(dims) != 1:
            raise ValueError(f"the scenes' language features disagree in dimension: "
                             f"{ {s.name: s.feature_dim for s in self.scenes} }")
        cfg.feature_dim = dims.pop()
        torch.manual_seed(cfg.seed)
        self.net = build_net(cfg.net, cfg.feature_dim, cfg.grid_size)
        self.batches: dict[int, object] = {}
        self.views = ViewSelections(cfg.view_selections_mb << 20)
        self.touched: list[float] = []     # U / N of each slot this process trained (not checkpointed)
        self._ahead: dict[tuple[int, int], Future] = {}
        self._worker: ThreadPoolExecutor | None = None
        self.opt = torch.optim.Adam(self.net.parameters(), lr=cfg.lr, fused=True)
        self.sched = torch.optim.lr_scheduler.ReduceLROnPlateau(self.opt, factor=0.1, patience=cfg.patience)
        self.step = 0
        self.window: list[float] = []
        self.history: list[float] = []

    def batch(self, i: int):
        """The voxelized scene ``i`` (built once; its kernel maps are cached on it)."""
        if i not in self.batches:
            self.batches[i] = self.net.prepare([self.scenes[i].gaussians])
        return self.batches[i]

    def my_slots(self, step: int) -> list[tuple[int, int]]:
        """(slot, scene index) of the slots of ``step`` that this rank trains."""
        slots = step_slots(self.cfg, step, len(self.scenes))
        return [(slot, slots[slot]) for slot in range(self.rank, len(slots), self.world)]

    def make_rays(self, step: int, slot: int, scene: int) -> StepRays:
        """The rays of ``slot`` of ``step`` (scene index ``scene``), selected and re-indexed, with
        what the blend backward needs of them made too (:func:`prepare_backward`): geometry only,
        so it can run while the network of the previous step does."""
        rays = step_rays(self.scenes[scene], self.cfg, np.random.default_rng([self.cfg.seed, step, slot]), self.views)
        prepare_backward(rays.selection)
        return rays

    def prefetch(self, step: int) -> None:
        """Start making the rays of ``step`` on a background thread (one at a time, so the OpenCL
        work of the selections never runs beside itself; the training thread meanwhile runs
        torch and only the blend kernels, so the two never share a kernel object)."""
        if self._worker is None:
            self._worker = ThreadPoolExecutor(1, thread_name_prefix="qr-cl-rays")
        for slot, scene in self.my_slots(step):
            self._ahead[(step, slot)] = self._worker.submit(self.make_rays, step, slot, scene)

    def close(self) -> None:
        """Wait for and drop the rays made ahead, and stop their thread."""
        if self._worker is not None:
            self._worker.shutdown(wait=True)
            self._worker = None
        self._ahead.clear()

    def train_step(self) -> tuple[float, int]:
        """One optimizer step over this step's scenes; returns (global loss, rays on this rank).

        The next step's rays are made on a background thread, started after the first slot's
        network forward (unless this is the last step of ``cfg.steps``)."""
        cfg = self.cfg
        self.net.train()
        self.opt.zero_grad(set_to_none=False)
        mine = self.my_slots(self.step)
        made = [self._ahead.pop((self.step, slot)).result() if (self.step, slot) in self._ahead
                else self.make_rays(self.step, slot, scene) for slot, scene in mine]
        total, rays = torch.zeros(()), 0
        for i, ((slot, scene), step) in enumerate(zip(mine, made)):
            table = self.net(self.batch(scene), torch.from_numpy(step.rows))
            if i == 0 and self.step + 1 < cfg.steps:
                self.prefetch(self.step + 1)
            loss = rays_loss(step, table, cfg.temperature)
            (loss / cfg.batch_scenes).backward()
            total += loss.detach() / cfg.batch_scenes
            rays += step.n_rays
            self.touched.append(step.touched)
        if self.world > 1:
            for p in self.net.parameters():
                dist.all_reduce(p.grad)
            dist.all_reduce(total)
        self.opt.step()
        self.step += 1
        value = float(total)
        self.history.append(value)
        self.window.append(value)
        if len(self.window) == cfg.plateau_interval:
            self.sched.step(float(np.mean(self.window)))
            self.window = []
        return value, rays

    def state(self) -> dict:
        """Everything a resume needs."""
        return {"model": self.net.state_dict(), "optimizer": self.opt.state_dict(),
                "scheduler": self.sched.state_dict(), "step": self.step, "window": self.window,
                "history": self.history, "config": asdict(self.cfg)}

    def load(self, ckpt: dict) -> None:
        """Continue from a checkpoint of the same configuration (steps may differ)."""
        saved = dict(ckpt["config"])
        mine = asdict(self.cfg)
        free = ("steps", "out", "checkpoint_every", "view_selections_mb")   # do not change the results
        diff = [k for k in mine if k not in free and saved.get(k) != mine[k]]
        if diff:
            raise ValueError("--resume: the checkpoint was trained with different settings: " +
                             ", ".join(f"{k}={saved.get(k)!r} (now {mine[k]!r})" for k in diff))
        self.net.load_state_dict(ckpt["model"])
        self.opt.load_state_dict(ckpt["optimizer"])
        self.sched.load_state_dict(ckpt["scheduler"])
        self.step, self.window, self.history = ckpt["step"], list(ckpt["window"]), list(ckpt["history"])

    def save(self) -> Path:
        """Write ``<out>/checkpoint.pt`` atomically (rank 0 only) and return its path."""
        path = Path(self.cfg.out) / "checkpoint.pt"
        if self.rank == 0:
            path.parent.mkdir(parents=True, exist_ok=True)
            save_atomic(self.state(), path)
        return path


def train(cfg: TrainConfig, resume: bool = False, rank: int = 0, world: int = 1, progress: bool = True) -> Trainer:
    """Run (or continue, with ``resume``) training to ``cfg.steps`` steps; returns the trainer.

    A checkpoint is written every ``cfg.checkpoint_every`` steps and at the end; Ctrl-C (or
    SIGTERM) writes one for the last finished step before stopping.
    """
    trainer = Trainer(cfg, rank, world)
    path = Path(cfg.out) / "checkpoint.pt"
    if resume and path.is_file():
        trainer.load(torch.load(path, weights_only=False))
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler) if rank == 0 else None
    bar = tqdm(total=cfg.steps, initial=trainer.step, desc=f"train {cfg.sampler}", unit="step",
               disable=not progress or rank != 0)
    try:
        with conv_threads(conv_thread_count()):
            last = time.perf_counter()
            while trainer.step < cfg.steps:
                loss, rays = trainer.train_step()
                if trainer.step % cfg.checkpoint_every == 0 or trainer.step == cfg.steps:
                    trainer.save()
                now = time.perf_counter()     # rays of all ranks over the whole iteration, checkpoint included
                bar.update(1)
                bar.set_postfix(loss=f"{loss:.3f}", rays_s=f"{rays * world / (now - last):.0f}",
                                touched=f"{trainer.touched[-1]:.0%}")
                last = now
    except KeyboardInterrupt:
        trainer.save()
        bar.close()
        print(f"interrupted at step {trainer.step}; checkpoint {path} (continue with --resume)", file=sys.stderr)
        raise
    finally:
        trainer.close()
        bar.close()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    if rank == 0:
        Path(cfg.out).mkdir(parents=True, exist_ok=True)
        log = {"loss": trainer.history, "touched": trainer.touched, "config": asdict(cfg)}
        Path(cfg.out, "train_log.json").write_text(json.dumps(log))
    return trainer


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl train`` / ``python -m qr_cl.train``."""
    d = TrainConfig(scenes=["-"], out="-")
    parser.add_argument("scenes", nargs="+", help="scene folders (point_cloud.ply, cameras.json, language_features/)")
    parser.add_argument("--out", required=True, help="output folder (checkpoint.pt, train_log.json)")
    parser.add_argument("--steps", type=int, default=d.steps, help=f"optimizer steps (default {d.steps})")
    parser.add_argument("--batch-scenes", type=int, default=d.batch_scenes,
                        help="scenes per step, split over ranks (default 1)")
    parser.add_argument("--views", type=int, default=d.views, help="views per scene per step (default 4)")
    parser.add_argument("--rays", type=int, default=d.rays, help="rays per view (default 2048)")
    parser.add_argument("--sampler", choices=SAMPLERS, default=d.sampler, help="feature renderer (default quantile)")
    parser.add_argument("-k", type=int, default=d.k, help="K of quantile/topk (default 40)")
    parser.add_argument("--lr", type=float, default=d.lr, help="Adam learning rate (default 1e-2)")
    parser.add_argument("--temperature", type=float, default=d.temperature, help="loss temperature (default 0.1)")
    parser.add_argument("--grid-size", type=float, default=d.grid_size, help="voxel size, scene units (default 0.1)")
    parser.add_argument("--net", choices=sorted(NETS), default=d.net, help="UNet preset (default small)")
    parser.add_argument("--seed", type=int, default=d.seed)
    parser.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every, help="steps (default 50)")
    parser.add_argument("--plateau-interval", type=int, default=d.plateau_interval,
                        help="steps per ReduceLROnPlateau observation (default 25)")
    parser.add_argument("--level", type=int, default=d.level, help="LangSplat mask level (default 0)")
    parser.add_argument("--view-selections-mb", type=int, default=d.view_selections_mb,
                        help="MiB of whole-view selections kept for gathering rays (default 1024; 0 selects "
                             "each step's rays afresh; same results either way)")
    parser.add_argument("--resume", action="store_true", help="continue from <out>/checkpoint.pt")
    parser.add_argument("--torch-threads", type=int, default=1, help="torch intra-op threads (default 1)")


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
        # asking for the GIL, the rank aborted ("terminate called without an active exception":
        # about 1 run in 10 of tests/test_distributed.py; a barrier before the exit left 1 in 20).
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m qr_cl.train`` (e.g. under torchrun)."""
    parser = argparse.ArgumentParser(prog="python -m qr_cl.train", description=__doc__.split("\n")[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
