"""``qr-cl bench``: per-stage kernel sweeps, baselines, roofline, complexity fit; JSON + markdown + plots.

Every number is a wall time measured in this run with the OpenCL queue finished inside the timed
call, after a warm-up call; ratios compare timings from the same run. The report format
(``REPORT_VERSION``) is stable so that two reports, e.g. from two devices, can be compared with
``qr-cl bench --compare A.json B.json``.
"""
from __future__ import annotations

import argparse
import datetime
import importlib.util
import json
import math
import os
import platform
import resource
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyopencl.array as cla
from matplotlib.ticker import NullFormatter
import torch
from tqdm import tqdm

from ..render import rasterization, rasterize, render_volume_fused
from ..render.selfcheck import checked_runtime
from ..runtime import SAMPLERS, channel_layout, padded_rows, to_device
from ..scene import Gaussians, load_ply, look_at, orbit_cameras
from ..stages import RasterPlan, bin_and_sort, blend_backward, blend_forward, project, render_fused, select
from . import roofline
from .images import plt  # pyplot on the file-only Agg backend
from .procedural import dense_room, procedural_scene
from .bench_implementations import run_all
from .timing import measure

REPORT_VERSION = 1


# ----------------------------------------------------------------------------------------------
# scenes
# ----------------------------------------------------------------------------------------------

@dataclass
class BenchScene:
    """A named scene with one camera."""

    name: str
    gaussians: object
    camera: object


def real_scenes(data: Path | None, width: int, height: int) -> list[BenchScene]:
    """The real scenes of the folder ``data`` (the fox and the donut, as in the project's shared
    data) with an orbit camera; [] if ``data`` is None or holds neither."""
    found = []
    for name, rel in (("fox", "wakufactory-fox/fox.ply"), ("donut", "v3dg-donut/donut_fused.ply")):
        if data is not None and (data / rel).is_file():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                g = load_ply(data / rel)
            found.append(BenchScene(name, g, orbit_cameras(g.means, 8, width, height)[1]))
    return found


def synthetic_scene(n: int, width: int, height: int) -> BenchScene:
    """The procedural scene with ``n`` Gaussians and an orbit camera."""
    g = procedural_scene(n)
    return BenchScene(f"synthetic-{n // 1000}k", g, orbit_cameras(g.means, 8, width, height)[1])


def dense_scene(n: int, width: int, height: int) -> BenchScene:
    """:func:`qr_cl.app.procedural.dense_room` with ``n`` Gaussians and its camera."""
    g, cam = dense_room(n, width=width, height=height)
    return BenchScene(f"dense-room-{n // 1000}k", g, cam)


def layered_scene(depth: int, width: int, height: int) -> BenchScene:
    """``depth`` screen-filling Gaussians stacked along the view axis, each with alpha 5/depth,
    so every ray meets exactly ``depth`` Gaussians (the complexity sweep's N)."""
    z = np.linspace(2.0, 3.0, depth)
    g = Gaussians(np.c_[np.zeros((depth, 2)), z].astype(np.float32),
                  np.tile([1.0, 0, 0, 0], (depth, 1)).astype(np.float32),
                  np.full((depth, 3), 50.0, np.float32),
                  np.full(depth, min(0.5, 5.0 / depth), np.float32), np.zeros((depth, 1, 3), np.float32))
    cam = look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], width, width, width, height)
    return BenchScene(f"layers-{depth}", g, cam)


# ----------------------------------------------------------------------------------------------
# the sweep
# ----------------------------------------------------------------------------------------------

class Sweep:
    """Runs configurations on one device and collects result rows."""

    def __init__(self, rounds: int, progress) -> None:
        self.rt = checked_runtime()
        self.rounds = rounds
        self.rows: list[dict] = []
        self.progress = progress
        self._bare: dict = {}
        self._out_buffers: dict = {}

    def _finish(self) -> None:
        self.rt.queue.finish()

    def _row(self, scene: BenchScene, stage: str, sampler: str, k: int, channels: int,
             timing: dict, **extra) -> dict:
        cam = scene.camera
        row = {"scene": scene.name, "n_gaussians": len(scene.gaussians), "width": cam.width,
               "height": cam.height, "stage": stage, "sampler": sampler, "k": k,
               "channels": channels, **timing, **extra}
        self.rows.append(row)
        self.progress.update(1)
        return row

    def _host_out(self, shape: tuple) -> np.ndarray:
        if shape not in self._out_buffers:
            self._out_buffers = {shape: np.zeros(shape, np.float32)}
        return self._out_buffers[shape]

    def plan(self, scene: BenchScene):
        """Time projection and binning+sort; return the RasterPlan."""
        g, cam = scene.gaussians, scene.camera
        dev = [to_device(self.rt, a) for a in (g.means, g.quats, g.scales, g.opacities)]
        args = (cam.viewmat, cam.K, cam.width, cam.height, 0.01, 1e10)

        def do_project():
            out = project(self.rt, *dev, *args)
            self._finish()
            return out
        self._row(scene, "projection", "-", 0, 0, measure(do_project, self.rounds))
        proj = do_project()

        def bin_sort():
            out = bin_and_sort(self.rt, proj, cam.width, cam.height)
            self._finish()
            return out
        self._row(scene, "binning+sort", "-", 0, 0, measure(bin_sort, self.rounds))
        return RasterPlan(self.rt, cam.width, cam.height, proj.splats, proj.radii, *bin_sort())

    def fused(self, scene: BenchScene, plan, channels: int) -> dict:
        """Time the fused V-Render of ``channels`` random features."""
        cstride = channel_layout(channels)[2]
        feats = to_device(self.rt, padded_rows(np.random.default_rng(0).random(
            (len(scene.gaussians), channels), dtype=np.float32), cstride))
        out = self._host_out((plan.height, plan.width, cstride))
        timing = measure(lambda: render_fused(plan, feats, channels, out=out), self.rounds)
        device_bytes = plan.splats.nbytes + plan.ids.nbytes + feats.nbytes + out.nbytes
        return self._row(scene, "fused", "volume_fused", 0, channels, timing, device_bytes=device_bytes)

    def looped_rgb(self, scene: BenchScene, plan, channels: int, rounds: int) -> dict:
        """The paper's 512-dagger baseline: the fused 3-channel V-Render looped ceil(C/3) times."""
        loops = math.ceil(channels / 3)
        feats = to_device(self.rt, padded_rows(np.random.default_rng(0).random(
            (len(scene.gaussians), 3), dtype=np.float32), 4))
        out = self._host_out((plan.height, plan.width, 4))

        def run():
            for _ in range(loops):
                render_fused(plan, feats, 3, out=out)
        return self._row(scene, "looped-3ch", "volume_fused", 0, channels,
                         measure(run, rounds, warmup=0), loops=loops)

    def sampler(self, scene: BenchScene, plan, sampler: str, k: int, channels: int) -> dict:
        """Time selection, blend forward and blend backward for one sampler; return the blend row."""

        kk = k if sampler != "volume" else 0

        def do_select():
            s = select(plan, sampler, kk or 1)
            self._finish()
            return s
        self._row(scene, "selection", sampler, kk, 0, measure(do_select, self.rounds))
        sel = do_select()
        cstride = channel_layout(channels)[2]
        feats = to_device(self.rt, padded_rows(np.random.default_rng(0).random(
            (len(scene.gaussians), channels), dtype=np.float32), cstride))
        image = cla.empty(self.rt.queue, (sel.n_rays, cstride), np.float32)

        def forward():
            blend_forward(sel, feats, channels, out=image)
            self._finish()
        count = sel.count.get()[:sel.n_rays]
        hit = count[count > 0]
        mean_k = float(hit.mean()) if hit.size else 0.0
        timing = measure(forward, self.rounds)
        device_bytes = plan.splats.nbytes + plan.ids.nbytes + sel.nbytes + feats.nbytes + image.nbytes
        fwd = self._row(scene, "blend-forward", sampler, kk, channels, timing, mean_entries=mean_k,
                        device_bytes=device_bytes, **self._roofline_fields(hit.size, mean_k, channels,
                                                                           timing["min_s"], sel.n_rays))

        def backward():
            blend_backward(sel, image, channels)
            self._finish()
        timing = measure(backward, self.rounds)
        self._row(scene, "blend-backward", sampler, kk, channels, timing, mean_entries=mean_k,
                  device_bytes=device_bytes + feats.nbytes,
                  **self._roofline_fields(hit.size, mean_k, channels, timing["min_s"], sel.n_rays))
        return fwd

    def end_to_end(self, scene: BenchScene, sampler: str, k: int, channels: int) -> dict:
        """Time the public call (projection to image) for one sampler: ``rasterize``, or
        ``render_volume_fused`` for sampler "volume_fused"; and count the minor page faults of a
        warm call (``faults_per_call``, 0 when nothing is freshly allocated)."""
        g, cam = scene.gaussians, scene.camera
        feats = random_features(len(g), channels)
        args = (g.means, g.quats, g.scales, g.opacities, feats, cam.viewmat, cam.K, cam.width, cam.height)
        if sampler == "volume_fused":
            call = lambda: render_volume_fused(*args)  # noqa: E731
        else:
            call = lambda: rasterize(*args, sampler=sampler, k=k)  # noqa: E731
        timing = measure(call, self.rounds)
        return self._row(scene, "end-to-end", sampler, k if sampler in ("quantile", "topk") else 0,
                         channels, timing, faults_per_call=warm_page_faults(call))

    def training_path(self, scene: BenchScene, k: int, channels: int, views: int = 4, rays: int = 2048) -> dict:
        """Time the renderer's part of a training step: ``views`` Q-Render K renders of ``rays``
        random pixels each (``rasterize`` with ``pixels``, the scene's camera) of [N, channels]
        features, forward and backward w.r.t. the features (loss: the images' sum of squares)."""
        g, cam = scene.gaussians, scene.camera
        feats = random_features(len(g), channels).requires_grad_(True)
        rng = np.random.default_rng(1)

        def call():
            feats.grad = None
            images = [rasterize(g.means, g.quats, g.scales, g.opacities, feats, cam.viewmat, cam.K, cam.width,
                                cam.height, sampler="quantile", k=k,
                                pixels=rng.integers(0, (cam.width, cam.height), (rays, 2)))[0]
                      for _ in range(views)]
            torch.cat(images).square().sum().backward()
        timing = measure(call, self.rounds)
        return self._row(scene, "training-path", "quantile", k, channels, timing, views=views, rays=rays,
                         faults_per_call=warm_page_faults(call))

    def gradients(self, scene: BenchScene, sampler: str, k: int) -> dict:
        """Time :func:`qr_cl.rasterization` of RGB (from the scene's SH) forward alone and forward +
        backward w.r.t. means, quats, scales, opacities and SH (loss: the image sum); the second
        row carries ``over_forward``, the ratio of the two."""
        g, cam = scene.gaussians, scene.camera
        views = torch.from_numpy(cam.viewmat)[None], torch.from_numpy(np.asarray(cam.K, np.float32))[None]

        def call(backward: bool) -> None:
            inputs = [torch.tensor(a, requires_grad=backward) for a in (g.means, g.quats, g.scales, g.opacities, g.sh)]
            with torch.set_grad_enabled(backward):
                image, _, _ = rasterization(*inputs, *views, cam.width, cam.height, sh_degree=g.sh_degree,
                                            sampler=sampler, k=k)
                if backward:
                    image.sum().backward()
        k = k if sampler != "volume" else 0
        fwd = self._row(scene, "rasterization-forward", sampler, k, 3, measure(lambda: call(False), self.rounds))
        both = measure(lambda: call(True), self.rounds)
        return self._row(scene, "rasterization-forward-backward", sampler, k, 3, both,
                         over_forward=both["min_s"] / fwd["min_s"])

    def torch_baselines(self, scene: BenchScene, plan, k: int, channels: int, numpy_rounds: int) -> None:
        """The same blend (Q-Render's selection) with torch embedding_bag and with numpy."""

        sel = select(plan, "quantile", k).host()
        ids, w = sel["ids"], sel["weights"]
        feats = torch.from_numpy(np.random.default_rng(0).random((len(scene.gaussians), channels),
                                                                 dtype=np.float32))
        flat_ids = torch.from_numpy(np.where(ids >= 0, ids, 0).astype(np.int64).ravel())
        flat_w = torch.from_numpy(w.ravel())
        offsets = torch.arange(0, flat_ids.numel(), max(ids.shape[1], 1))[:len(ids)]

        def embedding_bag():
            return torch.nn.functional.embedding_bag(flat_ids, feats, offsets, mode="sum",
                                                     per_sample_weights=flat_w)
        self._row(scene, "blend-forward", "torch-embedding_bag", k, channels,
                  measure(embedding_bag, self.rounds))
        f = feats.numpy()

        def numpy_blend():
            out = np.empty((len(ids), channels), np.float32)
            for start in range(0, len(ids), 4096):
                sl = slice(start, start + 4096)
                out[sl] = np.einsum("pk,pkc->pc", w[sl], f[np.where(ids[sl] >= 0, ids[sl], 0)])
            return out
        self._row(scene, "blend-forward", "numpy", k, channels, measure(numpy_blend, numpy_rounds, 0))

    def _roofline_fields(self, rays: int, mean_k: float, channels: int, seconds: float,
                         rows: int) -> dict:
        """Fractions of this device's limits for a blend of ``rows`` output rows whose ``rays``
        non-empty rays hold ``mean_k`` entries on average: against the bare coherent gather-blend
        of the non-empty rays, and against the analytic roofline max(flops / FMA rate, minimal
        bytes / bandwidth), the minimal bytes being every output row written once plus the
        entries' ids and weights read once."""
        if rays == 0:
            return {"bare_gather_s": 0.0, "fraction_of_bare_gather": 0.0, "fraction_of_roofline": 0.0}
        k = max(1, round(mean_k))
        key = (rays, k, channels)
        if key not in self._bare:
            self._bare[key] = roofline.bare_gather_blend(self.rt, rays, k, channels)
        flops = 2.0 * rays * mean_k * channels
        min_bytes = rows * channels * 4 + rays * mean_k * 8
        limit = max(flops / self.limits["fma_flops"], min_bytes / self.limits["bandwidth_bytes_s"])
        return {"bare_gather_s": self._bare[key], "fraction_of_bare_gather": self._bare[key] / seconds,
                "fraction_of_roofline": limit / seconds}


def random_features(n: int, channels: int) -> torch.Tensor:
    """Random features [n, channels] in [0, 1) for the public calls, in torch's own memory as
    GS-Net's outputs are: its rows start on 64-byte lines (large numpy arrays start 16 bytes past
    one, which makes the blend's row loads straddle lines: the dense room's Q-Render K=40 end to
    end 675 against 596 ms, README). The device-buffer stages are timed from aligned rows too."""
    rows = torch.from_numpy(np.random.default_rng(0).random((n, channels), dtype=np.float32))
    return torch.empty(n, channels).copy_(rows)


def warm_page_faults(call, calls: int = 2) -> float:
    """Minor page faults (``ru_minflt``) per call of ``call()`` after a warm-up call: what fresh
    allocations cost a warm call (glibc maps allocations above 32 MB freshly each time)."""
    call()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(calls):
        call()
    return (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / calls


# ----------------------------------------------------------------------------------------------
# plans (quick and full) and the report
# ----------------------------------------------------------------------------------------------

def _config(mode: str) -> dict:
    """Sweep sizes for mode "smoke" (seconds; the default test run), "quick" (< 3 min) or "full"."""
    if mode == "smoke":
        return {"resolutions": [(64, 48), (32, 24)], "ks": [10], "cs": [3, 16], "k_sweep_c": 16,
                "c_sweep_k": 10, "synthetic": [1000], "dense": 5000, "layers": [8, 16, 32], "layer_cs": [4, 16],
                "rounds": 1,
                "looped_rounds": 1, "numpy_rounds": 1, "real": False}
    if mode == "quick":
        return {"resolutions": [(640, 480)], "ks": [10, 40], "cs": [3, 64, 512], "k_sweep_c": 512,
                "c_sweep_k": 40, "synthetic": [], "dense": 300_000, "layers": [32, 128, 512],
                "layer_cs": [16, 64, 256],
                "rounds": 3, "looped_rounds": 1, "numpy_rounds": 1, "real": True}
    return {"resolutions": [(640, 480), (1280, 960)], "ks": [5, 10, 20, 40, 50],
            "cs": [3, 6, 16, 64, 512, 1024], "k_sweep_c": 512, "c_sweep_k": 40,
            "synthetic": [10_000, 100_000, 1_000_000], "dense": 300_000, "layers": [16, 64, 256, 1000],
            "layer_cs": [16, 64, 256, 1024], "rounds": 5, "looped_rounds": 2, "numpy_rounds": 1,
            "real": True}


def run_sweep(mode: str, out: Path, data: Path | None = None) -> dict:
    """Run the sweep of ``mode`` (see :func:`_config`) on the real scenes of ``data`` (when given
    and the mode uses them) and synthetic ones, write report.json, summary.md and plots into
    ``out``; return the report."""

    cfg = _config(mode)
    quick = mode != "full"
    rt = checked_runtime()
    out.mkdir(parents=True, exist_ok=True)
    scenes_by_res = {res: (real_scenes(data, *res) if cfg["real"] else [])
                     or [synthetic_scene(50_000 if cfg["real"] else 2_000, *res)] for res in cfg["resolutions"]}
    main_res = cfg["resolutions"][0]
    n_jobs = 0
    for res, scenes in scenes_by_res.items():
        per_scene = (2 + len(cfg["ks"]) + 3 * len(cfg["ks"]) * 3 + len(cfg["cs"]) * (1 + 3 * 3 + 3)
                     if res == main_res else 2 + 4 * 3 + 4)
        n_jobs += per_scene * (1 if quick else len(scenes))
    n_jobs += len(cfg["synthetic"]) * 8 + (len(cfg["layers"]) + len(cfg["layer_cs"])) * 4 * 2 + 6
    n_jobs += 2 + 2 + 3 * len(SAMPLERS) * len(cfg["ks"]) + 2 * len(cfg["ks"]) + 2 + 4
    with tqdm(total=n_jobs, desc="qr-cl bench", unit="run") as bar:
        sweep = Sweep(cfg["rounds"], bar)
        sweep.limits = {"bandwidth_bytes_s": roofline.stream_bandwidth(rt, 64 if quick else 256),
                        "fma_flops": roofline.fma_rate(rt)}
        for res, scenes in scenes_by_res.items():
            for scene in scenes[:1] if quick else scenes:
                plan = sweep.plan(scene)
                if res == main_res:
                    for sampler in SAMPLERS:          # time vs K at C = k_sweep_c
                        for k in cfg["ks"] if sampler != "volume" else cfg["ks"][:1]:
                            sweep.sampler(scene, plan, sampler, k, cfg["k_sweep_c"])
                    for c in cfg["cs"]:                  # time vs C at K = c_sweep_k
                        sweep.fused(scene, plan, c)
                        for sampler in SAMPLERS:
                            if c != cfg["k_sweep_c"]:
                                sweep.sampler(scene, plan, sampler, cfg["c_sweep_k"], c)
                            sweep.end_to_end(scene, sampler, cfg["c_sweep_k"], c)
                    c = cfg["k_sweep_c"]
                    sweep.looped_rgb(scene, plan, c, cfg["looped_rounds"])
                    sweep.torch_baselines(scene, plan, cfg["c_sweep_k"], c, cfg["numpy_rounds"])
                    sweep.end_to_end(scene, "volume_fused", 0, c)
                    for k in cfg["ks"]:
                        if k != cfg["c_sweep_k"]:
                            sweep.end_to_end(scene, "quantile", k, c)
                    sweep.training_path(scene, cfg["c_sweep_k"], c)
                    for sampler in ("volume", "quantile"):
                        sweep.gradients(scene, sampler, cfg["ks"][0])
                else:
                    sweep.fused(scene, plan, cfg["k_sweep_c"])
                    for sampler in SAMPLERS:
                        sweep.sampler(scene, plan, sampler, cfg["c_sweep_k"], cfg["k_sweep_c"])
        scene = dense_scene(cfg["dense"], *main_res)     # depth complexity: a dense room
        plan = sweep.plan(scene)
        for c in (3, cfg["k_sweep_c"]):
            sweep.fused(scene, plan, c)
        for sampler in SAMPLERS:
            for k in cfg["ks"] if sampler != "volume" else cfg["ks"][:1]:
                sweep.sampler(scene, plan, sampler, k, cfg["k_sweep_c"])
        for k in cfg["ks"]:
            sweep.end_to_end(scene, "quantile", k, cfg["k_sweep_c"])
            sweep.end_to_end(scene, "stratified", k, cfg["k_sweep_c"])
        sweep.end_to_end(scene, "volume_fused", 0, cfg["k_sweep_c"])
        sweep.training_path(scene, cfg["c_sweep_k"], cfg["k_sweep_c"])
        for n in cfg["synthetic"]:                       # scene size
            scene = synthetic_scene(n, *main_res)
            plan = sweep.plan(scene)
            sweep.fused(scene, plan, cfg["k_sweep_c"])
            for sampler in SAMPLERS:
                sweep.sampler(scene, plan, sampler, cfg["c_sweep_k"], cfg["k_sweep_c"])
        complexity = complexity_sweep(sweep, cfg)
    report = {"version": REPORT_VERSION, "meta": _meta(rt, mode), "limits": sweep.limits,
              "gsplat": "installed" if importlib.util.find_spec("gsplat") else "not installed",
              "results": sweep.rows, "complexity": complexity}
    tmp = out / "report.json.tmp"
    tmp.write_text(json.dumps(report, indent=1))
    os.replace(tmp, out / "report.json")
    (out / "summary.md").write_text(summary_markdown(report))
    write_plots(report, out)
    return report


def complexity_sweep(sweep: Sweep, cfg: dict) -> dict:
    """Select+blend time vs depth complexity N (C fixed) and vs C (N fixed) on layered scenes;
    per sampler the fitted exponents of t ~ N^a and t ~ C^b, and the marginal cost of a channel
    (slope of t vs C at N fixed), which the paper's complexities predict to grow with N for
    V-Render and with K for top-K and Q-Render."""
    width, height = 128, 96
    c_fixed, n_fixed = 64, cfg["layers"][-2]
    points = []
    for depth, channels in [(n, c_fixed) for n in cfg["layers"]] + [(n_fixed, c) for c in cfg["layer_cs"]]:
        scene = layered_scene(depth, width, height)
        plan = sweep.plan(scene)
        points.append(("volume_fused", depth, channels, sweep.fused(scene, plan, channels)["min_s"]))
        for sampler in SAMPLERS:
            fwd = sweep.sampler(scene, plan, sampler, 10, channels)
            sel = next(r for r in sweep.rows[::-1] if r["stage"] == "selection" and r["scene"] == scene.name
                       and r["sampler"] == sampler)
            points.append((sampler, depth, channels, sel["min_s"] + fwd["min_s"]))
    fits = {}
    for sampler in ("volume_fused", *SAMPLERS):
        by_n = [(n, t) for s, n, c, t in points if s == sampler and c == c_fixed]
        by_c = [(c, t) for s, n, c, t in points if s == sampler and n == n_fixed]
        fits[sampler] = {"exponent_N": float(np.polyfit(*np.log(np.array(by_n)).T, 1)[0]),
                         "exponent_C": float(np.polyfit(*np.log(np.array(by_c)).T, 1)[0]),
                         "ms_per_channel": 1e3 * float(np.polyfit(*np.array(by_c).T, 1)[0])}
    return {"width": width, "height": height, "k": 10, "C_fixed": c_fixed, "N_fixed": n_fixed,
            "points": [{"sampler": s, "N": n, "C": c, "seconds": t} for s, n, c, t in points],
            "fits": fits}


def _meta(rt, mode: str) -> dict:
    dev = rt.device
    return {"device": dev.name.strip(), "platform": dev.platform.name.strip(),
            "driver": dev.driver_version, "compute_units": dev.max_compute_units,
            "host": platform.node(), "python": platform.python_version(), "mode": mode,
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}


def _find(rows: list[dict], **match) -> dict | None:
    return next((r for r in rows if all(r.get(k) == v for k, v in match.items())), None)


def _ms(row: dict | None) -> str:
    return "-" if row is None else f"{row['min_s'] * 1e3:.1f}"


def _fault_count(row: dict | None) -> str:
    return "-" if row is None or "faults_per_call" not in row else f"{row['faults_per_call']:.0f}"


def _faults(row: dict) -> str:
    return "" if "faults_per_call" not in row else f" ({row['faults_per_call']:.0f} page faults per warm call)"


def _renderer_table(rows: list[dict]) -> list[str]:
    """Markdown lines of the renderer's headline figures per scene with end-to-end rows: the walk
    (fused V-Render at C=3), Q-Render end to end against the fused V-Render of the same run, end
    to end over select + blend, the blend against the roofline and the bare gather-blend, backward
    over forward, and the training path (:meth:`Sweep.training_path`)."""
    scenes = {(r["scene"], r["width"], r["height"]) for r in rows if r["stage"] == "end-to-end"
              and r["sampler"] == "quantile"}
    if not scenes:
        return []
    lines = ["## The renderer end to end", "", "| scene | WxH | walk: fused C=3 | Q-Render K | C | Q end to end | "
             "fused V-Render end to end | fused / Q | Q end to end / (select + blend) | Q blend fwd / roofline | "
             "Q blend fwd / bare gather | Q blend bwd / fwd | page faults per warm Q render | "
             "training path: 4 x 2048 rays, fwd + bwd |", "| --- " * 14 + "|"]
    for name, width, height in sorted(scenes):
        sc = dict(scene=name, width=width, height=height)
        walk = _find(rows, stage="fused", channels=3, **sc)
        for q in (r for r in rows if r["stage"] == "end-to-end" and r["sampler"] == "quantile"
                  and all(r[key] == v for key, v in sc.items())):
            c, k = q["channels"], q["k"]
            fused = _find(rows, stage="end-to-end", sampler="volume_fused", channels=c, **sc)
            sel = _find(rows, stage="selection", sampler="quantile", k=k, **sc)
            fwd = _find(rows, stage="blend-forward", sampler="quantile", k=k, channels=c, **sc)
            bwd = _find(rows, stage="blend-backward", sampler="quantile", k=k, channels=c, **sc)
            if not (fused and sel and fwd and bwd):
                continue
            train = _find(rows, stage="training-path", k=k, channels=c, **sc)
            lines.append(f"| {name} | {width}x{height} | {_ms(walk)} | {k} | {c} | {_ms(q)} | {_ms(fused)} | "
                         f"{fused['min_s'] / q['min_s']:.2f}x | {q['min_s'] / (sel['min_s'] + fwd['min_s']):.2f} | "
                         f"{fwd['fraction_of_roofline']:.0%} | {fwd['fraction_of_bare_gather']:.0%} | "
                         f"{bwd['min_s'] / fwd['min_s']:.2f} | {_fault_count(q)} | {_ms(train)} |")
    return lines + [""]


def _gradient_table(rows: list[dict]) -> list[str]:
    """Markdown lines: qr_cl.rasterization forward vs forward + backward w.r.t. the Gaussians."""
    both = [r for r in rows if r["stage"] == "rasterization-forward-backward"]
    if not both:
        return []
    lines = ["## Gradients w.r.t. the Gaussians (qr_cl.rasterization, RGB from SH)", "",
             "| scene | WxH | sampler | K | forward | forward + backward | ratio |", "| --- " * 7 + "|"]
    for r in both:
        fwd = _find(rows, stage="rasterization-forward", scene=r["scene"], sampler=r["sampler"], k=r["k"])
        lines.append(f"| {r['scene']} | {r['width']}x{r['height']} | {r['sampler']} | {r['k'] or '-'} | "
                     f"{_ms(fwd)} | {_ms(r)} | {r['over_forward']:.2f}x |")
    return lines + [""]


def summary_markdown(report: dict) -> str:
    """The markdown summary: headline ratios, the per-stage table, limits and complexity fits."""
    rows, meta, lim = report["results"], report["meta"], report["limits"]
    lines = [f"# qr-cl bench ({meta['mode']})", "",
             f"Device: {meta['device']} ({meta['platform']}, driver {meta['driver']}), {meta['date']}.",
             f"Limits measured here: streaming bandwidth {lim['bandwidth_bytes_s'] / 1e9:.1f} GB/s, "
             f"FMA rate {lim['fma_flops'] / 1e9:.0f} GFLOP/s. gsplat: {report['gsplat']}.",
             "Times are minima over the rounds (ms); ratios are against timings of the same run.", ""]
    head = next((r for r in rows if r["stage"] == "end-to-end" and r["sampler"] == "quantile"
                 and (r["k"], r["channels"]) in ((40, 512), (10, 16))), None)
    if head:
        sc = dict(scene=head["scene"], width=head["width"], height=head["height"])
        k, c = head["k"], head["channels"]
        q_sel = _find(rows, stage="selection", sampler="quantile", k=k, **sc)
        q_fwd = _find(rows, stage="blend-forward", sampler="quantile", k=k, channels=c, **sc)
        q = q_sel["min_s"] + q_fwd["min_s"]
        fused = _find(rows, stage="fused", channels=c, **sc)
        baselines = [(f"fused V-Render (C={c})", fused),
                     (f"looped 3-channel V-Render x ceil({c}/3)", _find(rows, stage="looped-3ch", channels=c, **sc)),
                     ("torch embedding_bag blend (same selection)", _find(rows, sampler="torch-embedding_bag", **sc)),
                     ("numpy blend (same selection)", _find(rows, sampler="numpy", **sc))]
        lines += [f"## Q-Render (K={k}, C={c}) on {head['scene']} at {head['width']}x{head['height']}", "",
                  f"Q-Render selection + blend: {q * 1e3:.1f} ms (selection {_ms(q_sel)}, blend {_ms(q_fwd)}); "
                  f"end to end (projection to image): {_ms(head)} ms{_faults(head)}. Blend at "
                  f"{q_fwd['fraction_of_roofline']:.0%} of the roofline and "
                  f"{q_fwd['fraction_of_bare_gather']:.0%} of the bare coherent gather-blend.", "",
                  "| baseline | ms | baseline / Q-Render |", "| --- | --- | --- |"]
        for name, row in baselines:
            if row:
                cmp_t = q_fwd["min_s"] if row["stage"] == "blend-forward" else q
                lines.append(f"| {name} | {_ms(row)} | {row['min_s'] / cmp_t:.2f}x |")
        lines += ["", "(blend-only baselines are compared with Q-Render's blend; the others with "
                  "Q-Render's selection + blend)", ""]
    lines += _renderer_table(rows)
    lines += _gradient_table(rows)
    lines += ["## Per stage", "", "| scene | WxH | sampler | K | C | selection | blend fwd | blend bwd | "
              "fused | end-to-end | end-to-end page faults | blend fwd / roofline | mean entries | peak host MB |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        if r["stage"] != "blend-forward" or r["sampler"] not in SAMPLERS:
            continue
        sc = dict(scene=r["scene"], width=r["width"], height=r["height"])
        sel = _find(rows, stage="selection", sampler=r["sampler"], k=r["k"], **sc)
        bwd = _find(rows, stage="blend-backward", sampler=r["sampler"], k=r["k"], channels=r["channels"], **sc)
        fused = _find(rows, stage="fused", channels=r["channels"], **sc)
        e2e = _find(rows, stage="end-to-end", sampler=r["sampler"], channels=r["channels"],
                    k=r["k"] if r["sampler"] != "volume" else 0, **sc)
        peak = max(x.get("peak_host_bytes", 0) for x in (r, bwd or r)) / 2 ** 20
        lines.append(f"| {r['scene']} | {r['width']}x{r['height']} | {r['sampler']} | {r['k'] or '-'} | "
                     f"{r['channels']} | {_ms(sel)} | {_ms(r)} | {_ms(bwd)} | {_ms(fused)} | {_ms(e2e)} | "
                     f"{_fault_count(e2e)} | "
                     f"{r['fraction_of_roofline']:.0%} | {r['mean_entries']:.1f} | {peak:.0f} |")
    comp = report["complexity"]
    lines += ["", f"## Complexity (layered scenes, {comp['width']}x{comp['height']}, K={comp['k']})", "",
              f"Fitted exponents of select+blend time: t ~ N^a at C={comp['C_fixed']}, "
              f"t ~ C^b at N={comp['N_fixed']} (paper: V-Render O(NC), top-K O(N log K + KC), "
              "Q-Render O(N + KC)). The walk over the N Gaussians of a ray is O(N) for every sampler; "
              "what differs is the cost of a channel (slope of t vs C): proportional to N for "
              "V-Render, to K for top-K and Q-Render.", "",
              "| sampler | a (N) | b (C) | ms per channel | per channel / Q-Render's |",
              "| --- | --- | --- | --- | --- |"]
    q_slope = comp["fits"]["quantile"]["ms_per_channel"]
    lines += [f"| {s} | {f['exponent_N']:.2f} | {f['exponent_C']:.2f} | {f['ms_per_channel']:.4f} | "
              f"{f['ms_per_channel'] / q_slope:.1f} |" for s, f in comp["fits"].items()]
    for name in ("projection", "binning+sort"):
        for r in rows:
            if r["stage"] == name and r["scene"] in ("fox", "donut") or r["stage"] == name and "synthetic" in r["scene"]:
                lines.append(f"\n{name} {r['scene']} {r['width']}x{r['height']} ({r['n_gaussians']} Gaussians): "
                             f"{_ms(r)} ms")
    return "\n".join(lines) + "\n"


def write_plots(report: dict, out: Path) -> None:
    """time_vs_k.png, time_vs_c.png, roofline.png and complexity.png into ``out``."""
    rows = report["results"]
    blend = [r for r in rows if r["stage"] == "blend-forward" and r["sampler"] in SAMPLERS]
    if not blend:
        return
    sc = dict(scene=blend[0]["scene"], width=blend[0]["width"], height=blend[0]["height"])
    c_main = max(r["channels"] for r in blend)
    fig, ax = plt.subplots(figsize=(6, 4))
    for sampler in (s for s in SAMPLERS if s != "volume"):
        pts = sorted((r["k"], r["min_s"] + _find(rows, stage="selection", sampler=sampler, k=r["k"], **sc)["min_s"])
                     for r in blend if r["sampler"] == sampler and r["channels"] == c_main and r["scene"] == sc["scene"]
                     and r["width"] == sc["width"])
        if pts:
            ax.plot(*zip(*[(k, t * 1e3) for k, t in pts]), "o-", label=f"{sampler} (select + blend)")
    for name, row in (("volume (select + blend)", _find(rows, stage="blend-forward", sampler="volume", channels=c_main, **sc)),
                      ("fused V-Render", _find(rows, stage="fused", channels=c_main, **sc))):
        if row:
            t = row["min_s"] + (_find(rows, stage="selection", sampler="volume", **sc)["min_s"] if "select" in name else 0)
            ax.axhline(t * 1e3, linestyle="--", color="gray" if "fused" in name else "black", label=name)
    ax.set(xlabel="K", ylabel="ms", title=f"{sc['scene']} {sc['width']}x{sc['height']}, C={c_main}")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(out / "time_vs_k.png", dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    ks = sorted({r["k"] for r in blend if r["sampler"] == "quantile"})
    k_c = 40 if 40 in ks else ks[-1]
    for sampler in SAMPLERS:
        pts = sorted((r["channels"], r["min_s"]) for r in blend if r["sampler"] == sampler and
                     r["k"] == (k_c if sampler != "volume" else 0) and r["scene"] == sc["scene"] and r["width"] == sc["width"])
        if pts:
            ax.plot(*zip(*[(c, t * 1e3) for c, t in pts]), "o-", label=f"{sampler} blend")
    fused = sorted((r["channels"], r["min_s"] * 1e3) for r in rows if r["stage"] == "fused" and r["scene"] == sc["scene"]
                   and r["width"] == sc["width"])
    if fused:
        ax.plot(*zip(*fused), "s--", color="gray", label="fused V-Render")
    ax.set(xscale="log", yscale="log", xlabel="C (channels)", ylabel="ms",
           title=f"{sc['scene']} {sc['width']}x{sc['height']}, K={k_c}")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "time_vs_c.png", dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 4))
    sel_rows = [r for r in blend if r["scene"] == sc["scene"] and r["width"] == sc["width"]]
    labels = [f"{r['sampler'][:5]} K{r['k']} C{r['channels']}" for r in sel_rows]
    ax.barh(labels, [r["fraction_of_roofline"] for r in sel_rows], label="of analytic roofline")
    ax.barh(labels, [r["fraction_of_bare_gather"] for r in sel_rows], alpha=0.5, label="of bare gather-blend")
    ax.set(xlabel="fraction of the limit (1 = at the limit)", title="blend forward")
    ax.tick_params(axis="y", labelsize=7)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "roofline.png", dpi=110)
    plt.close(fig)

    comp = report["complexity"]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.8))
    for sampler in comp["fits"]:
        pts = [p for p in comp["points"] if p["sampler"] == sampler]
        by_n = sorted((p["N"], p["seconds"] * 1e3) for p in pts if p["C"] == comp["C_fixed"])
        by_c = sorted((p["C"], p["seconds"] * 1e3) for p in pts if p["N"] == comp["N_fixed"])
        fit = comp["fits"][sampler]
        axes[0].plot(*zip(*by_n), "o-", label=f"{sampler} (N^{fit['exponent_N']:.2f})")
        axes[1].plot(*zip(*by_c), "o-", label=f"{sampler} (C^{fit['exponent_C']:.2f})")
    axes[0].set(xscale="log", yscale="log", xlabel="Gaussians per ray N", ylabel="ms",
                title=f"C={comp['C_fixed']}")
    axes[1].set(xscale="log", yscale="log", xlabel="C", title=f"N={comp['N_fixed']}")
    for a in axes:
        a.legend(fontsize=7)
        a.xaxis.set_minor_formatter(NullFormatter())
        a.yaxis.set_minor_formatter(NullFormatter())
    fig.tight_layout()
    fig.savefig(out / "complexity.png", dpi=110)
    plt.close(fig)


def compare(path_a: str, path_b: str) -> str:
    """Markdown table of B / A time ratios for the rows two reports share."""
    a, b = (json.loads(Path(p).read_text()) for p in (path_a, path_b))
    for p, r in ((path_a, a), (path_b, b)):
        if r.get("version") != REPORT_VERSION:
            raise ValueError(f"{p}: report version {r.get('version')}, expected {REPORT_VERSION}")
    key = lambda r: (r["scene"], r["width"], r["height"], r["stage"], r["sampler"], r["k"], r["channels"])  # noqa: E731
    rows_a = {key(r): r for r in a["results"]}
    lines = [f"A: {a['meta']['device']} ({path_a})", f"B: {b['meta']['device']} ({path_b})", "",
             "| scene | WxH | stage | sampler | K | C | A ms | B ms | B / A |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in b["results"]:
        if key(r) in rows_a:
            ra = rows_a[key(r)]
            lines.append(f"| {r['scene']} | {r['width']}x{r['height']} | {r['stage']} | {r['sampler']} | "
                         f"{r['k'] or '-'} | {r['channels'] or '-'} | {ra['min_s'] * 1e3:.2f} | "
                         f"{r['min_s'] * 1e3:.2f} | {r['min_s'] / ra['min_s']:.2f} |")
    return "\n".join(lines) + "\n"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl bench``."""
    parser.add_argument("--device", help="OpenCL device (as QR_CL_DEVICE: cpu, gpu, <platform>:<index>)")
    parser.add_argument("--quick", action="store_true", help="the small sweep (under 3 minutes on 2 cores)")
    parser.add_argument("--smoke", action="store_true", help="a seconds-long run on tiny inputs (tests)")
    parser.add_argument("--out", default="qr-cl-bench", help="report folder (default ./qr-cl-bench)")
    parser.add_argument("--data", default=os.environ.get("QR_CL_DATA"),
                        help="folder with the real scenes (wakufactory-fox/fox.ply, v3dg-donut/"
                             "donut_fused.ply; default $QR_CL_DATA): timed beside the synthetic ones")
    parser.add_argument("--compare", nargs=2, metavar=("A.json", "B.json"),
                        help="print B/A time ratios of two reports instead of measuring")
    parser.add_argument("--implementations", action="store_true",
                        help="run the sweep on PoCL and on every implementation tests/drivers/install.sh "
                             "installed, one after the other, and write implementations.md side by side")


def run(args: argparse.Namespace) -> int:
    """``qr-cl bench``: measure and write the report, or compare two reports."""
    if args.compare:
        print(compare(*args.compare))
        return 0
    if args.device:
        os.environ["QR_CL_DEVICE"] = args.device
    out = Path(args.out)
    start = time.perf_counter()
    mode = "smoke" if args.smoke else "quick" if args.quick else "full"
    if args.implementations:
        print(run_all(mode, out, Path(args.data) if args.data else None))
        print(f"finished in {time.perf_counter() - start:.0f} s. Report: {(out / 'implementations.md').resolve()}")
        return 0
    run_sweep(mode, out, Path(args.data) if args.data else None)
    print((out / "summary.md").read_text())
    print(f"bench finished in {time.perf_counter() - start:.0f} s. Report: {out.resolve()} "
          "(report.json, summary.md, time_vs_k.png, time_vs_c.png, roofline.png, complexity.png)")
    return 0
