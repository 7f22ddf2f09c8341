"""GS-Net trained through a feature renderer with the contrastive loss (paper App. D).

Each step draws ``batch_scenes`` scenes (seeded by the step, identical on every rank); for each
scene ``views`` random views are drawn, ``rays`` pixels per view inside masks are selected with
the chosen sampler, and the rays are rendered from GS-Net's features of the Gaussians those
selections use: the UNet runs on every voxel, and the blend reads, per used Gaussian, its
de-voxelized UNet feature scaled by the inverse norm of its head output
(:meth:`~qr_cl.backbone.GSNet.head_inputs`, D + 1 channels). A blend is linear, so the head
applied to these rendered rays gives the rays of the unit features; the loss
(:func:`qr_cl.app.training.loss.contrastive_loss`) scores them through the head's matrix without
forming them (:func:`~qr_cl.app.training.loss.head_cosine_logits`): no [U, feature_dim] table and
no [rays, feature_dim] rays. Adam; ReduceLROnPlateau (factor 0.1) on the mean loss of every
``plateau_interval`` steps.

Where the time goes (demo rooms): the selections are geometry, so each view's
whole-image selection is made once and a step's rays are gathered from it (up to
``view_selections_mb`` of them are kept; then views are selected ray by ray each step), and the
next step's rays are made on a background thread while this step back-propagates through the
network.
Torch runs one intra-op thread (the CLI's ``--torch-threads``): its OpenMP workers spin-wait at
barriers, and beside other busy processes two of them made a step many times slower than one.
The sparse convolutions, most of a step, run as row blocks on :func:`conv_thread_count` threads
(every core the process may use; results do not depend on the count, see
:mod:`qr_cl.backbone.conv`), and PoCL runs the kernels on the same cores
(:func:`qr_cl.app.process.cap_kernel_threads`). The training thread waits while it renders. The
next step's rays are started once the step's last blend backward is done, so their kernels run
beside the network's backward (torch only), never beside the training thread's own kernels:
OpenCL kernel objects (ours and pyopencl's) must not be set up from two threads at once, and the
two threads never run OpenCL work at the same time.

Scale-out: ``torchrun --nproc_per_node N -m qr_cl.app.training.command ...`` runs data-parallel over the
scenes of a step (gloo on CPU): rank r takes slots r, r+N, ...; gradients are summed with
all_reduce, so N ranks end with the weights of one rank accumulating the same scenes. Every
process creates its own OpenCL context (torchrun spawns fresh interpreters; never fork after
OpenCL init). BatchNorm running statistics stay per rank; rank 0's are checkpointed.

Checkpoints (``<out>/checkpoint.pt``) hold model, optimizer, scheduler and the step, written to
a temporary file and renamed; ``--resume`` continues exactly (all randomness derives from the
seed and the step).
"""
from __future__ import annotations

import json
import os
import signal
import sys
import warnings
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, replace
from functools import partial
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from tqdm import tqdm

from qr_cl.backbone.conv import conv_threads
from ...render import SelectionCache, prepare_backward
from ..process import process_cores
from ..scenes.folders import SceneDataError, load_scene_folder
from ..timing import Stopwatch
from .config import TrainConfig
from .network import build_net, load_checkpoint
from .rays import StepRays, rays_loss, step_rays


def step_slots(cfg: TrainConfig, step: int, n_scenes: int) -> list[int]:
    """Scene indices of the ``batch_scenes`` slots of ``step`` (the same on every rank)."""
    rng = np.random.default_rng([cfg.seed, step, 7])
    return rng.choice(n_scenes, cfg.batch_scenes, replace=cfg.batch_scenes > n_scenes).tolist()


def conv_thread_count() -> int:
    """Threads for GS-Net's sparse convolutions: the cores this process may use
    (:func:`~qr_cl.app.process.process_cores`) over torch's intra-op threads, at least 1, so that
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
        frameless = [s.root for s in self.scenes if not s.frames]
        if frameless:
            raise SceneDataError(f"{frameless[0]}: no frames to train on (cameras in cameras.json or "
                                 "transforms_train.json, and language_features/ from qr-cl features)")
        dims = {s.feature_dim for s in self.scenes}
        if len(dims) != 1:
            raise ValueError(f"the scenes' language features disagree in dimension: "
                             f"{ {s.name: s.feature_dim for s in self.scenes} }")
        cfg.feature_dim = dims.pop()
        torch.manual_seed(cfg.seed)
        self.net = build_net(cfg.net, cfg.feature_dim, cfg.grid_size)
        self.batches: dict[int, object] = {}
        self.selections = SelectionCache(cfg.view_selections_mb << 20) if cfg.view_selections_mb > 0 else None
        self.touched: list[float] = []     # U / N of each slot this process trained (not checkpointed)
        self._ahead: dict[tuple[int, int], Future] = {}
        self._said_full = False
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
        rng = np.random.default_rng([self.cfg.seed, step, slot])
        rays = step_rays(self.scenes[scene], self.cfg, rng, self.selections)
        return replace(rays, backward_index=prepare_backward(rays.selection))

    def prefetch(self, step: int) -> None:
        """Start making the rays of ``step`` on a background thread (one slot at a time). Call it
        only when the training thread runs no more OpenCL work until it takes the result (see
        :meth:`train_step`): the two threads must never run kernels at the same time."""
        if self._worker is None:
            self._worker = ThreadPoolExecutor(1, thread_name_prefix="qr-cl-rays")
        for slot, scene in self.my_slots(step):
            self._ahead[(step, slot)] = self._worker.submit(self.make_rays, step, slot, scene)

    def _prefetch_after_blend(self, step: int, grad: torch.Tensor) -> None:
        """A gradient hook on the table (called once the blend backward made its gradient, which it
        leaves unchanged): :meth:`prefetch` the rays of ``step``."""
        self.prefetch(step)

    def close(self) -> None:
        """Wait for and drop the rays made ahead, and stop their thread."""
        if self._worker is not None:
            self._worker.shutdown(wait=True)
            self._worker = None
        self._ahead.clear()

    def train_step(self) -> tuple[float, int]:
        """One optimizer step over this step's scenes; returns (global loss, rays on this rank).

        The next step's rays are made on a background thread, started by a hook on the last
        slot's table gradient, i.e. when its blend backward is done and only torch work (the rest
        of the network's backward, the optimizer) is left (unless this is the last step of
        ``cfg.steps``); the step waits for them before it returns and frees its own device arrays
        (the memory pool is not shared between threads at once either)."""
        cfg = self.cfg
        self.net.train()
        self.opt.zero_grad(set_to_none=False)
        mine = self.my_slots(self.step)
        made = [self._ahead.pop((self.step, slot)).result() if (self.step, slot) in self._ahead
                else self.make_rays(self.step, slot, scene) for slot, scene in mine]
        self._say_if_full()
        total, rays = torch.zeros(()), 0
        for i, ((slot, scene), step) in enumerate(zip(mine, made)):
            table = self.net.head_inputs(self.batch(scene), torch.from_numpy(step.rows))
            if i == len(mine) - 1 and self.step + 1 < cfg.steps:
                table.register_hook(partial(self._prefetch_after_blend, self.step + 1))
            loss = rays_loss(step, table, cfg.temperature, self.net.head_matrix())
            (loss / cfg.batch_scenes).backward()
            total += loss.detach() / cfg.batch_scenes
            rays += step.n_rays
            self.touched.append(step.touched)
        if self.world > 1:
            for p in self.net.parameters():
                dist.all_reduce(p.grad)
            dist.all_reduce(total)
        self.opt.step()
        for future in self._ahead.values():     # done before this step's device arrays are freed
            future.result()
        self.step += 1
        value = float(total)
        self.history.append(value)
        self.window.append(value)
        if len(self.window) == cfg.plateau_interval:
            self.sched.step(float(np.mean(self.window)))
            self.window = []
        return value, rays

    def _say_if_full(self) -> None:
        """Warn, once, when the whole-view selections reached ``view_selections_mb`` and a view's
        were not kept: its rays are then selected afresh every step (the same results, slower)."""
        if self._said_full or self.selections is None or not self.selections.refused:
            return
        self._said_full = True
        views = sum(len(s.frames) for s in self.scenes)
        warnings.warn(f"view_selections_mb={self.cfg.view_selections_mb} is full: {len(self.selections)} of the "
                      f"{views} views' whole-image selections are kept ({self.selections.nbytes / 2**20:.0f} MiB); the "
                      "others' rays are selected afresh every step (the same results, slower; "
                      "--view-selections-mb raises the bound)", stacklevel=3)

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
        trainer.load(load_checkpoint(path))
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler) if rank == 0 else None
    bar = tqdm(total=cfg.steps, initial=trainer.step, desc=f"train {cfg.sampler}", unit="step",
               disable=not progress or rank != 0)
    try:
        with conv_threads(conv_thread_count()):
            while trainer.step < cfg.steps:
                iteration = Stopwatch()
                loss, rays = trainer.train_step()
                if trainer.step % cfg.checkpoint_every == 0 or trainer.step == cfg.steps:
                    trainer.save()
                seconds = iteration.seconds   # rays of all ranks over the whole iteration, checkpoint included
                bar.update(1)
                bar.set_postfix(loss=f"{loss:.3f}", rays_s=f"{rays * world / seconds:.0f}",
                                touched=f"{trainer.touched[-1]:.0%}")
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
