"""Dr.Splat's registration against one GS-Net training step: wall time and peak resident memory on
the demo's held-out room and on the 300k-Gaussian dense room.

Each measurement runs in a fresh process; its peak is the kernel's (``wait4``'s ``ru_maxrss``):

- load: the scene folder loaded and one view planned (what every other row starts from);
- registration: ``qr_cl.app.registration.register`` over all the room's views, then over its
  first two only (streaming: the peak must not grow with the views);
- training: GS-Net with the demo's settings (small UNet, 10 cm voxels, Q-Render K=40, 4 views x
  2048 rays per step) for ``--steps`` steps; a step's time is the median of the steps after the
  first (which builds the voxels, kernel maps and view selections).

The dense room (``qr_cl.app.scenes.procedural.dense_room``, 640x480) has no masks: it is written
once as a scene folder with ``DENSE_VIEWS`` cameras turned about its own and, per view, a grid of
mask blocks with seeded random unit 512-D features (the registration's cost depends on the pixels
and Gaussians, not on what the masks say)::

    python bench/registration_cost.py --out bench/reports/registration-epyc-2cores/registration_cost.md
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchutil import print_table, timing

DENSE_N, WIDTH, HEIGHT, DENSE_VIEWS, CHANNELS = 300_000, 640, 480, 8, 512
MASK_GRID = (8, 6)                  # mask blocks across and down each dense-room view
YAW_STEP = 0.12                     # radians between the dense room's views


def dense_scene_folder(cache: Path) -> Path:
    """The dense room as a scene folder under ``cache`` (written once)."""
    from qr_cl.app.scenes.procedural import dense_room
    from qr_cl.app.scenes.synthetic import build_folder, camera_entry
    from qr_cl.scene import Camera, save_ply

    def write(folder: Path) -> None:
        g, cam = dense_room(DENSE_N, width=WIDTH, height=HEIGHT)
        save_ply(folder / "point_cloud.ply", g)
        cams = []
        for i in range(DENSE_VIEWS):
            a = YAW_STEP * (i - DENSE_VIEWS // 2)
            turn = np.eye(4)
            turn[[0, 0, 2, 2], [0, 2, 0, 2]] = np.cos(a), np.sin(a), -np.sin(a), np.cos(a)
            cams.append(Camera(turn @ cam.viewmat, cam.fx, cam.fy, cam.cx, cam.cy, WIDTH, HEIGHT, f"view_{i:02d}"))
        (folder / "cameras.json").write_text(json.dumps([camera_entry(i, c) for i, c in enumerate(cams)]))
        lang = folder / "language_features"
        lang.mkdir()
        gx, gy = MASK_GRID
        ys, xs = np.mgrid[:HEIGHT, :WIDTH]
        masks = (ys * gy // HEIGHT) * gx + xs * gx // WIDTH
        rng = np.random.default_rng(0)
        for c in cams:
            features = rng.standard_normal((gx * gy, CHANNELS)).astype(np.float32)
            np.save(lang / f"{c.name}_s.npy", masks[None].astype(np.int32))
            np.save(lang / f"{c.name}_f.npy", features / np.linalg.norm(features, axis=1, keepdims=True))
    return build_folder(cache / f"dense-room-{DENSE_N // 1000}k-masks", "cameras.json", write)


def child(mode: str, scene: str, count: int) -> dict:
    """One measurement in this process (see the module docstring); returns its numbers."""
    from qr_cl.app.process import cap_kernel_threads, torch_threads
    cap_kernel_threads()
    from qr_cl.app.registration.register import register, scene_views
    from qr_cl.app.training.rays import camera_plan
    from qr_cl.app.scenes.folders import load_scene_folder
    data = load_scene_folder(scene)
    camera_plan(data.gaussians, data.frames[0].camera)
    if mode == "load":
        return {"gaussians": len(data.gaussians), "views": len(data.frames)}
    if mode == "register":
        views = list(scene_views([data]))[:count]
        result = register(data.gaussians, iter(views), progress=False)
        return {**result.summary(), "sum_mb": result.features.nbytes / 2 ** 20}
    from qr_cl.app.training.config import TrainConfig
    from qr_cl.app.training.trainer import Trainer, conv_thread_count
    from qr_cl.backbone.conv import conv_threads
    with tempfile.TemporaryDirectory() as out, torch_threads(1), conv_threads(conv_thread_count()):
        trainer = Trainer(TrainConfig(scenes=[scene], out=out, steps=count))
        seconds = []
        for _ in range(count):
            watch = timing.Stopwatch()
            trainer.train_step()
            seconds.append(watch.seconds)
        trainer.close()
    return {"step_s": seconds}


def measure(mode: str, scene: Path, count: int = 0) -> tuple[dict, float]:
    """(the child's numbers, its peak resident MB) of one measurement in a fresh process."""
    proc = subprocess.Popen([sys.executable, __file__, "--child", mode, str(scene), str(count)],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    stdout = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    if os.waitstatus_to_exitcode(status):
        raise SystemExit(f"{mode} on {scene} failed (rc {os.waitstatus_to_exitcode(status)})")
    return json.loads(stdout.strip().splitlines()[-1]), usage.ru_maxrss / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, help="write the table to this Markdown file")
    parser.add_argument("--steps", type=int, default=6, help="GS-Net steps per room (default 6)")
    parser.add_argument("--cache", type=Path, help="scene cache (default the rooms' own)")
    parser.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        mode, scene, count = args.child
        print(json.dumps(child(mode, scene, int(count))))
        return
    from qr_cl.app.scenes.room_config import SyntheticConfig
    from qr_cl.app.scenes.synthetic import default_cache, room_folder
    cache = args.cache or default_cache()
    rooms = {"demo held-out room": room_folder(SyntheticConfig(seed=1000, n_gaussians=60000, style="3dgs"), cache),
             f"dense room {DENSE_N // 1000}k": dense_scene_folder(cache)}
    lines = [f"Registration (K=40, level 0) against GS-Net training steps (demo settings), {os.cpu_count()} CPUs; "
             "peaks are each fresh process's resident maximum (`bench/registration_cost.py`).", "",
             "| room | Gaussians | views | load peak GB | registration s | registration peak GB | "
             "peak, 2 views GB | [N, C] sum GB | GS-Net step s (median) | training peak GB | registration / step |",
             "| --- |" + " ---: |" * 10]
    for name, scene in rooms.items():
        loaded, load_peak = measure("load", scene)
        reg, reg_peak = measure("register", scene, loaded["views"])
        _, two_peak = measure("register", scene, 2)
        steps, train_peak = measure("train", scene, args.steps)
        step = float(np.median(steps["step_s"][1:]))
        print(f"{name}: registration {reg['seconds']:.1f} s, step {step:.2f} s", flush=True)
        lines.append(f"| {name} | {loaded['gaussians']} | {loaded['views']} | {load_peak / 1024:.2f} | "
                     f"{reg['seconds']:.1f} | {reg_peak / 1024:.2f} | {two_peak / 1024:.2f} | "
                     f"{reg['sum_mb'] / 1024:.2f} | {step:.2f} | {train_peak / 1024:.2f} | {reg['seconds'] / step:.1f} |")
    print_table("\n".join(lines), args.out)


if __name__ == "__main__":
    main()
