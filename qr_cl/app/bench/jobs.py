"""The sweep as a list of jobs, built before any runs (so its progress counts them): the sizes of
each mode (:func:`sweep_sizes`) and the jobs of the per-stage sweep (:func:`sweep_jobs`); the
complexity sweep's are in :mod:`qr_cl.app.bench.complexity`."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ...runtime import SAMPLERS
from ..renderers import FusedVolumeRenderer, SamplerRenderer
from ..scenes.views import SceneView, dense_view, procedural_view, real_views


@dataclass(frozen=True)
class Job:
    """One measurement of the sweep: the :class:`~qr_cl.app.bench.sweep.Sweep` method ``stage``
    called with ``scene`` and ``args``. A "plan" job times the scene's projection and binning and
    makes the plan that the scene's jobs after it use."""

    stage: str
    scene: SceneView
    args: tuple = ()


def sweep_sizes(mode: str) -> dict:
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


def _k_sweep(scene: SceneView, sizes: dict) -> list[Job]:
    """Every sampler's selection and blend over the K values at the K sweep's C (volume: once)."""
    return [Job("sampler", scene, (sampler, k, sizes["k_sweep_c"])) for sampler in SAMPLERS
            for k in (sizes["ks"] if sampler != "volume" else sizes["ks"][:1])]


def _main_scene_jobs(scene: SceneView, sizes: dict) -> list[Job]:
    """The jobs of a scene at the main resolution: time against K and C, the baselines, the
    public calls end to end, the training path and the gradients."""
    c, k = sizes["k_sweep_c"], sizes["c_sweep_k"]
    jobs = [Job("plan", scene)] + _k_sweep(scene, sizes)
    for channels in sizes["cs"]:
        jobs.append(Job("fused", scene, (channels,)))
        for sampler in SAMPLERS:
            if channels != c:
                jobs.append(Job("sampler", scene, (sampler, k, channels)))
            jobs.append(Job("end_to_end", scene, (SamplerRenderer(sampler, k), channels)))
    jobs += [Job("looped_rgb", scene, (c, sizes["looped_rounds"])),
             Job("torch_baselines", scene, (k, c, sizes["numpy_rounds"])),
             Job("end_to_end", scene, (FusedVolumeRenderer(), c))]
    jobs += [Job("end_to_end", scene, (SamplerRenderer("quantile", kk), c)) for kk in sizes["ks"] if kk != k]
    jobs.append(Job("training_path", scene, (k, c)))
    return jobs + [Job("gradients", scene, (sampler, sizes["ks"][0])) for sampler in ("volume", "quantile")]


def _scene_jobs(scene: SceneView, sizes: dict) -> list[Job]:
    """The jobs of another scene: its plan, the fused V-Render and every sampler at the K sweep's C."""
    c = sizes["k_sweep_c"]
    return [Job("plan", scene), Job("fused", scene, (c,))] + [
        Job("sampler", scene, (sampler, sizes["c_sweep_k"], c)) for sampler in SAMPLERS]


def _dense_jobs(scene: SceneView, sizes: dict) -> list[Job]:
    """The dense room's jobs (depth complexity): the fused V-Render at 3 and C channels, every
    sampler over K, Q-Render and Stratified-K end to end over K, and the training path."""
    c = sizes["k_sweep_c"]
    jobs = [Job("plan", scene)] + [Job("fused", scene, (channels,)) for channels in (3, c)] + _k_sweep(scene, sizes)
    for k in sizes["ks"]:
        jobs += [Job("end_to_end", scene, (SamplerRenderer("quantile", k), c)),
                 Job("end_to_end", scene, (SamplerRenderer("stratified", k), c))]
    return jobs + [Job("end_to_end", scene, (FusedVolumeRenderer(), c)),
                   Job("training_path", scene, (sizes["c_sweep_k"], c))]


def sweep_jobs(mode: str, sizes: dict, data: Path | None) -> list[Job]:
    """The per-stage sweep of ``mode`` with ``sizes`` (:func:`sweep_sizes`), in the order it runs:
    the real scenes of ``data`` (when the mode uses them; else the procedural scene) at each
    resolution (one scene per resolution unless the mode is "full"), the dense room, and the
    procedural scene at each size."""
    main_res = sizes["resolutions"][0]
    jobs = []
    for res in sizes["resolutions"]:
        scenes = (real_views(data, *res) if sizes["real"] else []) or [
            procedural_view(50_000 if sizes["real"] else 2_000, *res)]
        for scene in scenes if mode == "full" else scenes[:1]:
            jobs += _main_scene_jobs(scene, sizes) if res == main_res else _scene_jobs(scene, sizes)
    jobs += _dense_jobs(dense_view(sizes["dense"], *main_res), sizes)
    for n in sizes["synthetic"]:
        jobs += _scene_jobs(procedural_view(n, *main_res), sizes)
    return jobs
