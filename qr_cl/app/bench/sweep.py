"""The sweep's measurements (:class:`Sweep`): per stage of the pipeline (projection, binning, each
sampler's selection, blend forward and backward, the fused V-Render), the public calls end to
end, the training path, gradients w.r.t. the Gaussians and torch / numpy baselines; one row each.

Every number is a wall time measured with the OpenCL queue finished inside the timed call,
after a warm-up call (:func:`qr_cl.app.timing.measure`).
"""
from __future__ import annotations

import math

import numpy as np
import pyopencl.array as cla
import torch

from ...render import checked_runtime, rasterization, rasterize
from ...runtime import channel_layout, host_pool, padded_rows, shared_array, to_device, trim_device_pool
from ...stages import RasterPlan, bin_and_sort, blend_backward, blend_forward, project, render_fused, select
from ..renderers import FUSED_NAME, FeatureRenderer
from ..scenes.views import SceneView
from ..timing import PeakMemory, measure, warm_page_faults
from . import roofline
from .jobs import Job


class Sweep:
    """Runs the sweep's jobs on one device and collects their result rows.

    ``limits``: the device's streaming bandwidth (``bandwidth_bytes_s``, bytes/s) and FMA rate
    (``fma_flops``, flop/s) that the blend rows are compared with."""

    def __init__(self, rounds: int, limits: dict[str, float]) -> None:
        self.rt = checked_runtime()
        self.rounds = rounds
        self.limits = limits
        self.rows: list[dict] = []
        self._bare: dict = {}
        self._out_buffers: dict = {}
        self._planned: tuple[SceneView, RasterPlan] | None = None

    def run(self, job: Job):
        """Run ``job`` (its stage's method on its scene); returns what the method returns."""
        return getattr(self, job.stage)(job.scene, *job.args)

    def _plan_of(self, scene: SceneView) -> RasterPlan:
        """The plan that the latest "plan" job made, which must be of ``scene``."""
        if self._planned is None or self._planned[0] is not scene:
            raise RuntimeError(f"no plan of {scene.name}: a 'plan' job must come before its scene's stages")
        return self._planned[1]

    def _finish(self) -> None:
        self.rt.queue.finish()

    def _row(self, scene: SceneView, stage: str, sampler: str, k: int, channels: int,
             timing: dict, **extra) -> dict:
        cam = scene.camera
        row = {"scene": scene.name, "n_gaussians": len(scene.gaussians), "width": cam.width,
               "height": cam.height, "stage": stage, "sampler": sampler, "k": k,
               "channels": channels, **timing, **extra}
        self.rows.append(row)
        return row

    def _host_out(self, shape: tuple) -> np.ndarray:
        if shape not in self._out_buffers:
            self._out_buffers = {shape: np.zeros(shape, np.float32)}
        return self._out_buffers[shape]

    def plan(self, scene: SceneView) -> RasterPlan:
        """Time projection and binning+sort; return the RasterPlan (which the scene's next jobs use)."""
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
        ranges, ids, n_keys = bin_sort()
        plan = RasterPlan(runtime=self.rt, width=cam.width, height=cam.height, splats=proj.splats, radii=proj.radii,
                          ranges=ranges, ids=ids, n_keys=n_keys)
        self._planned = (scene, plan)
        return plan

    def fused(self, scene: SceneView, channels: int) -> dict:
        """Time the fused V-Render of ``channels`` random features."""
        plan = self._plan_of(scene)
        cstride = channel_layout(channels)[2]
        feats = to_device(self.rt, padded_rows(np.random.default_rng(0).random(
            (len(scene.gaussians), channels), dtype=np.float32), cstride))
        out = self._host_out((plan.height, plan.width, cstride))
        timing = measure(lambda: render_fused(plan, feats, channels, out=out), self.rounds)
        device_bytes = plan.splats.nbytes + plan.ids.nbytes + feats.nbytes + out.nbytes
        return self._row(scene, "fused", FUSED_NAME, 0, channels, timing, device_bytes=device_bytes)

    def looped_rgb(self, scene: SceneView, channels: int, rounds: int) -> dict:
        """The paper's 512-dagger baseline: the fused 3-channel V-Render looped ceil(C/3) times."""
        plan = self._plan_of(scene)
        loops = math.ceil(channels / 3)
        feats = to_device(self.rt, padded_rows(np.random.default_rng(0).random(
            (len(scene.gaussians), 3), dtype=np.float32), 4))
        out = self._host_out((plan.height, plan.width, 4))

        def run():
            for _ in range(loops):
                render_fused(plan, feats, 3, out=out)
        return self._row(scene, "looped-3ch", FUSED_NAME, 0, channels,
                         measure(run, rounds, warmup=0), loops=loops)

    def sampler(self, scene: SceneView, sampler: str, k: int, channels: int,
                dtype: torch.dtype = torch.float32) -> tuple[dict, dict]:
        """Time selection, blend forward and blend backward for one sampler, the blend reading a
        table of ``dtype`` (float32 or float16); return the selection and blend forward rows."""
        plan = self._plan_of(scene)
        kk = k if sampler != "volume" else 0

        def do_select():
            s = select(plan, sampler, kk or 1)
            self._finish()
            return s
        selection = self._row(scene, "selection", sampler, kk, 0, measure(do_select, self.rounds))
        sel = do_select()
        cstride = channel_layout(channels)[2]
        table = random_features(len(scene.gaussians), channels, dtype).numpy()
        if channels < cstride:
            table = np.pad(table, ((0, 0), (0, cstride - channels)))
        with shared_array(self.rt, table, "r") as feats:      # the table's own memory on CPU devices
            return selection, self._blend_rows(scene, sel, kk, channels, feats)

    def _blend_rows(self, scene: SceneView, sel, k: int, channels: int, feats: cla.Array) -> dict:
        """Time blend forward and backward of ``sel`` with the device rows ``feats``; the forward row."""
        plan, cstride = sel.plan, feats.shape[1]
        image = cla.empty(self.rt.queue, (sel.n_rays, cstride), np.float32)

        def forward():
            blend_forward(sel, feats, channels, out=image)
            self._finish()
        count = sel.count.get()[:sel.n_rays]
        hit = count[count > 0]
        mean_k = float(hit.mean()) if hit.size else 0.0
        timing = measure(forward, self.rounds)
        device_bytes = plan.splats.nbytes + plan.ids.nbytes + sel.nbytes + feats.nbytes + image.nbytes
        fwd = self._row(scene, "blend-forward", sel.sampler, k, channels, timing, mean_entries=mean_k,
                        table_dtype=str(feats.dtype), device_bytes=device_bytes,
                        **self._roofline_fields(hit.size, mean_k, channels, timing["min_s"], sel.n_rays))

        def backward():
            blend_backward(sel, image, channels)
            self._finish()
        timing = measure(backward, self.rounds)
        self._row(scene, "blend-backward", sel.sampler, k, channels, timing, mean_entries=mean_k,
                  device_bytes=device_bytes + 4 * sel.n_gaussians * cstride,      # dF: float32 rows
                  **self._roofline_fields(hit.size, mean_k, channels, timing["min_s"], sel.n_rays))
        return fwd

    def end_to_end(self, scene: SceneView, renderer: FeatureRenderer, channels: int,
                   dtype: torch.dtype = torch.float32) -> dict:
        """Time the public call (projection to image) of one renderer (``rasterize`` through a
        sampler, or ``render_volume_fused``) of a ``dtype`` table, count the minor page faults of a
        warm call (``faults_per_call``, 0 when nothing is freshly allocated) and measure the peak
        resident memory of a first call above the level before it, the table resident and the
        memory pools emptied (``call_peak_bytes``: what a render costs beyond its table)."""
        g, cam = scene.gaussians, scene.camera
        feats = random_features(len(g), channels, dtype)
        args = (g.means, g.quats, g.scales, g.opacities, feats, cam.viewmat, cam.K, cam.width, cam.height)

        def call():
            return renderer(*args)
        trim_device_pool(self.rt, 0)
        host_pool().clear()
        with PeakMemory() as peak:
            call()
        timing = measure(call, self.rounds)
        k = renderer.k if renderer.name in ("quantile", "topk") else 0
        return self._row(scene, "end-to-end", renderer.name, k, channels, timing,
                         faults_per_call=warm_page_faults(call), call_peak_bytes=peak.above_base,
                         table_dtype=str(dtype).removeprefix("torch."))

    def training_path(self, scene: SceneView, k: int, channels: int, views: int = 4, rays: int = 2048) -> dict:
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

    def gradients(self, scene: SceneView, sampler: str, k: int) -> dict:
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

    def torch_baselines(self, scene: SceneView, k: int, channels: int, numpy_rounds: int) -> None:
        """The same blend (Q-Render's selection) with torch embedding_bag and with numpy."""
        sel = select(self._plan_of(scene), "quantile", k).host()
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


#: Rows of random features drawn at a time (no float32 temporary of a whole large table).
RANDOM_ROWS = 1 << 16


def random_features(n: int, channels: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Random features [n, channels] in [0, 1) of ``dtype`` (float32's values rounded) for the
    public calls, in torch's own memory as GS-Net's outputs are: its rows start on 64-byte lines
    (large numpy arrays start 16 bytes past one, which makes the blend's row loads straddle lines
    and measured slower end to end). The device-buffer stages are timed from aligned rows too."""
    rng = np.random.default_rng(0)
    out = torch.empty(n, channels, dtype=dtype)
    for start in range(0, n, RANDOM_ROWS):
        rows = min(RANDOM_ROWS, n - start)
        out[start:start + rows] = torch.from_numpy(rng.random((rows, channels), dtype=np.float32))
    return out
