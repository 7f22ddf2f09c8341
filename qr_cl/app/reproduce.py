"""``qr-cl reproduce``: the paper's controlled experiments on 3DGS-like synthetic rooms, one command.

1. Scenes: seeded "3dgs"-style rooms (:mod:`qr_cl.app.synthetic`: thick semi-transparent shells,
   anisotropic Gaussians, floaters; cached), compared with the real captures of ``--data`` (the
   fox, the donut), the demo's flat rooms and the dense indoor room of :mod:`qr_cl.app.procedural`
   by their opacity histograms and V-Render entries per pixel (Gaussians blended per ray).
2. GS-Net trained on the training rooms with the same budget through every renderer of the plan
   (V-Render, top-K and Q-Render over K, Stratified-K), and through Q-Render K=40 on rooms whose
   opacity logits carry Gaussian noise, and Q-Render K=40 again with the next seed (the run-to-run
   spread); held-out mIoU/mAcc (19/15/10 classes), over all labelled Gaussians and over those the
   room's views reach. The per-scene baseline (free features fitted on the held-out room itself,
   the same budget) is scored the same way (Table 1: GS-Net against per-scene optimization).
3. The rendering time of every renderer on the held-out room (512-D features, whole images).
4. The transmittance profiles along sample rays (Fig. 3) and their mean gap to V-Render's, and
   each renderer's feature image compared with V-Render's (cosine similarity).
5. RGB fidelity: PSNR of Q-Render against V-Render from SH colours: the raw normalized
   Q-Render image, Q-Render's colour times V-Render's alpha and times its own alpha (and top-K's
   colour times V-Render's alpha), with pictures.
6. ``report.md`` (tables, the paper's claims checked against the numbers), ``results.json`` and
   the plots, in ``--out``.

Plans (:data:`PLANS`): "full" (15 minutes measured on 2 cores), "quick"
(``--quick``, 5 minutes: fewer K values, noise levels and steps, 2 training rooms) and "smoke"
(``--smoke``, seconds on tiny rooms: checks the wiring, its numbers mean nothing).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import time
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..render import rasterize, rasterize_plan, render_volume_fused
from ..runtime import runtime
from ..scene import Camera, Gaussians, load_ply, orbit_cameras, save_ply
from ..stages.select import select, transmittance_profile
from .baseline import fit_free_features
from .benchmark import dense_scene, real_scenes
from .data import SceneData, load_scene_folder
from .evaluate import evaluate_features, ground_truth, network_features, reached_gaussians
from .images import plot_transmittance_profiles, plt, save_image_grid
from .metrics import SUBSETS
from .model import cap_kernel_threads, keep_freed_memory, torch_threads
from .synthetic import SyntheticConfig, build_folder, synthetic_scene
from .timing import measure
from .train import TrainConfig, train

OPACITY_BINS = 20                     # opacity histogram bins over [0, 1]
NOISE_K = 40                          # the noise table's Q-Render K (paper: "Sensitivity under Gaussian Perturbation")
PROFILE_RAYS = 256                    # rays whose transmittance profiles are compared with V-Render's
PLOTTED_PROFILES = 3                  # of which this many are plotted (Fig. 3)
CONCENTRATION_RAYS = 2048             # hit rays per view whose weight concentration is measured

#: The paper's numbers (ScanNet, MinkUNet; Fig. 4 and the noise table), mIoU in %.
PAPER = {"volume": 49.02, "topk": {5: 37.84, 10: 40.22, 20: 43.59, 40: 45.70, 50: 44.93},
         "quantile": {5: 49.98, 10: 50.75, 20: 50.65, 40: 50.85, 50: 50.28},
         "noise": {0.0: 50.75, 0.25: 50.13, 0.5: 50.18, 1.0: 47.13, 2.0: 38.13, 4.0: 16.12}}
LABELS = {"volume": "V-Render", "quantile": "Q-Render", "topk": "top-K", "stratified": "Stratified-K"}


@dataclass
class Plan:
    """The budget of one reproduction: rooms (``room``: SyntheticConfig overrides of the "3dgs"
    style), training (same ``steps``, ``views`` and ``rays`` for every renderer), the K values and
    noise scales, the sizes of the timing, profile and RGB measurements (pixels), and the flat
    room compared with them (``flat_room``: overrides of the default flat room, the demo's)."""

    train_rooms: int
    steps: int
    ks: tuple[int, ...]
    stratified_ks: tuple[int, ...]
    noise: tuple[float, ...]
    room: dict = field(default_factory=dict)
    views: int = 4
    rays: int = 2048
    timing_views: int = 2
    timing_size: tuple[int, int] = (640, 480)
    timing_rounds: int = 3
    rgb_ks: tuple[int, ...] = (10, 20, 40)
    rgb_views: int = 4
    rgb_size: tuple[int, int] = (640, 480)
    profile_k: int = 10
    stats_views: int = 4
    dense_gaussians: int = 300_000
    flat_room: dict = field(default_factory=dict)


PLANS = {
    "full": Plan(train_rooms=4, steps=300, ks=(5, 10, 20, 40, 50), stratified_ks=(10, 40),
                 noise=(0.0, 0.25, 0.5, 1.0, 2.0, 4.0), room={"n_gaussians": 60_000}),
    "quick": Plan(train_rooms=2, steps=150, ks=(5, 10, 40), stratified_ks=(40,), noise=(0.0, 0.5, 2.0),
                  room={"n_gaussians": 60_000}, timing_views=1, timing_size=(320, 240), timing_rounds=2,
                  rgb_views=2, rgb_size=(320, 240), stats_views=2),
    "smoke": Plan(train_rooms=1, steps=2, ks=(5,), stratified_ks=(5,), noise=(0.0, 1.0),
                  room={"n_gaussians": 5000, "layers": 2.0, "n_objects": 3, "n_wall_objects": 1, "n_views": 4,
                        "width": 80, "height": 60, "dim": 32, "points_per_gaussian": 8},
                  views=2, rays=256, timing_views=1, timing_size=(64, 48), timing_rounds=1, rgb_ks=(10,),
                  rgb_views=1, rgb_size=(64, 48), stats_views=1, dense_gaussians=5000,
                  flat_room={"n_gaussians": 3000, "n_views": 1, "width": 64, "height": 48, "dim": 32}),
}


@dataclass(frozen=True)
class Renderer:
    """One feature renderer of the comparison: sampler name and K (0 for V-Render), the
    opacity-noise scale of the rooms it trains on, and the offset of its training seed (a
    repeated run measures the run-to-run spread)."""

    sampler: str
    k: int = 0
    noise: float = 0.0
    seed: int = 0

    @property
    def label(self) -> str:
        name = LABELS[self.sampler] + (f" K={self.k}" if self.k else "")
        return name + (f", opacity noise {self.noise:g}" if self.noise else "") + (
            f", seed +{self.seed}" if self.seed else "")


def renderers(plan: Plan) -> list[Renderer]:
    """Every training run of ``plan``: V-Render, top-K and Q-Render at each K, Stratified-K,
    Q-Render K=40 at each noise scale (noise 0 is the clean Q-Render K=40 run, added if the K
    values lack 40), and Q-Render K=40 again with the next seed (the run-to-run spread)."""
    runs = [Renderer("volume")]
    runs += [Renderer(s, k) for s in ("topk", "quantile") for k in plan.ks]
    runs += [Renderer("stratified", k) for k in plan.stratified_ks]
    runs += [Renderer("quantile", NOISE_K, s) for s in plan.noise if s or NOISE_K not in plan.ks]
    return runs + [Renderer("quantile", NOISE_K, seed=1)]


# ----------------------------------------------------------------------------------------------
# scenes and their statistics
# ----------------------------------------------------------------------------------------------

def splat_rooms(plan: Plan, seed: int, cache: Path | None) -> tuple[list[Path], Path]:
    """The folders of the plan's "3dgs" training rooms (seeds ``seed`` ...) and its held-out room
    (seed ``seed`` + 1000), generated on first use."""
    cfgs = [SyntheticConfig(seed=s, style="3dgs", **plan.room)
            for s in list(range(seed, seed + plan.train_rooms)) + [seed + 1000]]
    paths = [synthetic_scene(c, cache) for c in tqdm(cfgs, desc="rooms", unit="room")]
    return paths[:-1], paths[-1]


def perturb_opacities(gaussians: Gaussians, scale: float, rng: np.random.Generator) -> Gaussians:
    """``gaussians`` with N(0, ``scale``) noise added to their opacity logits before the sigmoid
    (the paper's perturbation study); opacities are clipped to [1e-6, 1 - 1e-6] before the logit."""
    p = np.clip(np.asarray(gaussians.opacities, np.float64), 1e-6, 1 - 1e-6)
    logit = np.log(p / (1 - p)) + rng.normal(0.0, scale, len(p))
    return dataclasses.replace(gaussians, opacities=(1 / (1 + np.exp(-logit))).astype(np.float32))


def noisy_scene(path: Path, scale: float, seed: int) -> Path:
    """A copy of the scene folder ``path`` (beside it, made once) whose point_cloud.ply has opacity
    noise ``scale`` (:func:`perturb_opacities`, seeded by ``seed`` and the scene's name); the
    other files are symbolic links to the originals."""
    path = Path(path)

    def write(folder: Path) -> None:
        rng = np.random.default_rng([seed, zlib.crc32(path.name.encode()), int(round(scale * 1000))])
        for entry in path.iterdir():
            if entry.name != "point_cloud.ply":
                (folder / entry.name).symlink_to(entry.resolve())
        save_ply(folder / "point_cloud.ply", perturb_opacities(load_ply(path / "point_cloud.ply"), scale, rng))
    return build_folder(path.parent / f"{path.name}-opacity-noise-{scale:g}-{seed}", "point_cloud.ply", write)


def volume_selection(gaussians: Gaussians, camera: Camera, pixels: np.ndarray | None = None):
    """V-Render's Selection of ``camera``'s whole image, or of the rays ``pixels`` [P,2] (x, y)."""
    g = gaussians
    plan = rasterize_plan(g.means, g.quats, g.scales, g.opacities, camera.viewmat, camera.K,
                          camera.width, camera.height)
    return select(plan, "volume", 1, pixels)


def entries_per_ray(gaussians: Gaussians, camera: Camera) -> np.ndarray:
    """V-Render's entries (Gaussians blended) of every ray of ``camera``'s image: [H*W] int."""
    sel = volume_selection(gaussians, camera)
    return sel.count.get()[:sel.n_rays]


def weight_concentration(weights: np.ndarray, share: float = 0.9) -> np.ndarray:
    """Per ray of ``weights`` [P,L] (V-Render weights, 0 padded) the fewest Gaussians whose
    weights hold ``share`` of the ray's total weight: [P] int (0 for a ray without weight)."""
    ordered = -np.sort(-weights, axis=1)
    cum = np.cumsum(ordered, axis=1)
    total = cum[:, -1:] if cum.shape[1] else np.zeros((len(weights), 1))
    return np.where(total[:, 0] > 0, (cum < share * total).sum(1) + 1, 0)


def scene_statistics(name: str, kind: str, gaussians: Gaussians, cameras: list[Camera],
                     rng: np.random.Generator) -> dict:
    """Opacity histogram (:data:`OPACITY_BINS` fractions over [0, 1]), V-Render entries per pixel
    over the rays of ``cameras`` that hit anything (mean, median, 90th percentile), and the mean
    number of Gaussians holding 90 % of a ray's weight (:func:`weight_concentration`) over up to
    :data:`CONCENTRATION_RAYS` random hit rays per camera."""
    hist, _ = np.histogram(gaussians.opacities, OPACITY_BINS, (0.0, 1.0))
    counts, holding = [], []
    for cam in cameras:
        c = entries_per_ray(gaussians, cam)
        hit = np.flatnonzero(c > 0)
        rays = np.sort(rng.choice(hit, min(CONCENTRATION_RAYS, len(hit)), replace=False))
        if len(rays):
            pixels = np.stack([rays % cam.width, rays // cam.width], 1).astype(np.int32)
            holding.append(weight_concentration(volume_selection(gaussians, cam, pixels).host()["weights"]))
        counts.append(c)
    counts = np.concatenate(counts)
    hit = counts[counts > 0]
    holding = np.concatenate(holding) if holding else np.zeros(0)
    return {"scene": name, "kind": kind, "n_gaussians": len(gaussians), "views": len(cameras),
            "size": f"{cameras[0].width}x{cameras[0].height}",
            "opacity_hist": (hist / max(len(gaussians), 1)).tolist(),
            "opacity_mean": float(np.mean(gaussians.opacities)),
            "entries_mean": float(hit.mean()) if hit.size else 0.0,
            "entries_median": float(np.median(hit)) if hit.size else 0.0,
            "entries_p90": float(np.percentile(hit, 90)) if hit.size else 0.0,
            "holding_90": float(holding.mean()) if holding.size else 0.0,
            "coverage": float((counts > 0).mean())}


def real_captures(data: Path | None, views: int, size: tuple[int, int]) -> list[tuple[str, Gaussians, list[Camera]]]:
    """(name, Gaussians, ``views`` orbit cameras of ``size`` px) of the real scenes found in ``data``."""
    return [(s.name, s.gaussians, orbit_cameras(s.gaussians.means, views, *size)) for s in real_scenes(data, *size)]


def compare_scenes(plan: Plan, held: SceneData, flat: SceneData, data: Path | None, seed: int) -> list[dict]:
    """:func:`scene_statistics` of the held-out "3dgs" room, a flat demo room, the real captures of
    ``data`` (orbit views at the plan's RGB size) and the dense indoor room (the >= 50 entries target)."""
    n, rng = plan.stats_views, np.random.default_rng(seed)
    scenes = [(held.name, "synthetic 3dgs room", held.gaussians, [f.camera for f in held.frames[:n]]),
              (flat.name, "synthetic flat room (demo)", flat.gaussians, [f.camera for f in flat.frames[:n]])]
    scenes += [(name, "real capture", g, cams) for name, g, cams in real_captures(data, n, plan.rgb_size)]
    dense = dense_scene(plan.dense_gaussians, *plan.rgb_size)
    scenes.append((dense.name, "dense indoor target (procedural)", dense.gaussians, [dense.camera]))
    return [scene_statistics(*scene, rng) for scene in tqdm(scenes, desc="scene statistics", unit="scene")]


# ----------------------------------------------------------------------------------------------
# training, evaluation, timing
# ----------------------------------------------------------------------------------------------

def metric_summary(metrics: dict, suffix: str = "") -> dict:
    """{"miou19", "macc19", ...} (names + ``suffix``) in % from
    :func:`qr_cl.app.evaluate.evaluate_features`' result."""
    return {f"{name}{s}{suffix}": 100 * metrics[s][name] for s in metrics for name in ("miou", "macc")}


def held_out_scores(held: SceneData, features: np.ndarray, gt: np.ndarray, reached: np.ndarray) -> dict:
    """mIoU/mAcc (19/15/10 classes) of per-Gaussian ``features`` [N,C] of the held-out room over
    all labelled Gaussians, and mIoU19/mAcc19 over those the room's views reach (``reached`` [N]
    bool; keys ``miou19_reached``, ``macc19_reached``)."""
    scores = metric_summary(evaluate_features(held, features, gt, tuple(SUBSETS)))
    return {**scores, **metric_summary(evaluate_features(held, features, np.where(reached, gt, -1), (19,)),
                                       "_reached")}


def train_and_evaluate(plan: Plan, run: Renderer, train_paths: list[Path], held: SceneData, gt: np.ndarray,
                       reached: np.ndarray, out: Path, seed: int) -> dict:
    """Train GS-Net through ``run``'s renderer with the plan's budget (on rooms with ``run.noise``
    opacity noise) and evaluate it on the held-out room (features predicted from the room with
    the same noise, scored against the clean room's ground truth; :func:`held_out_scores`)."""
    scenes = [noisy_scene(p, run.noise, seed) if run.noise else p for p in train_paths]
    name = f"{run.sampler}{run.k}" + (f"-noise{run.noise:g}" if run.noise else "") + (
        f"-seed{seed + run.seed}" if run.seed else "")
    cfg = TrainConfig(scenes=[str(p) for p in scenes], out=str(out / "runs" / name), steps=plan.steps,
                      views=plan.views, rays=plan.rays, sampler=run.sampler, k=run.k or NOISE_K,
                      seed=seed + run.seed, checkpoint_every=plan.steps)
    start = time.perf_counter()
    state = train(cfg).state()
    seconds = time.perf_counter() - start
    scene = load_scene_folder(noisy_scene(held.root, run.noise, seed)) if run.noise else held
    return {**asdict(run), "label": run.label, "steps": plan.steps, "train_s": seconds,
            "final_loss": state["history"][-1], "checkpoint": str(Path(cfg.out) / "checkpoint.pt"),
            **held_out_scores(held, network_features(state, scene), gt, reached)}


def baseline_scores(plan: Plan, held: SceneData, gt: np.ndarray, reached: np.ndarray, out: Path, seed: int) -> dict:
    """The per-scene baseline (:func:`qr_cl.app.baseline.fit_free_features`: free features fitted
    on the held-out room itself) with GS-Net's budget through Q-Render K=40, scored like the runs."""
    cfg = TrainConfig(scenes=[str(held.root)], out=str(out / "runs" / "baseline"), steps=plan.steps,
                      views=plan.views, rays=plan.rays, sampler="quantile", k=NOISE_K, seed=seed)
    start = time.perf_counter()
    features = fit_free_features(held, cfg)
    return {"label": f"per-scene baseline, Q-Render K={NOISE_K}", "steps": plan.steps,
            "train_s": time.perf_counter() - start, **held_out_scores(held, features, gt, reached)}


def render_times(plan: Plan, scene: SceneData, features: np.ndarray, runs: list[Renderer]) -> list[dict]:
    """Wall time (min over ``plan.timing_rounds`` after a warm-up, ms) of rendering ``features``
    [N,C] over the first ``plan.timing_views`` views of ``scene`` at ``plan.timing_size``, per
    renderer of ``runs`` (``rasterize``, whole images) and for the fused V-Render kernel."""
    g = scene.gaussians
    cams = [f.camera.resized(*plan.timing_size) for f in scene.frames[:plan.timing_views]]
    args = (g.means, g.quats, g.scales, g.opacities, features)

    def call(sampler: str, k: int):
        def render() -> None:
            for c in cams:
                if sampler == "volume_fused":
                    render_volume_fused(*args, c.viewmat, c.K, c.width, c.height)
                else:
                    rasterize(*args, c.viewmat, c.K, c.width, c.height, sampler=sampler, k=k or 1)
        return render

    rows = []
    timed = [(r.sampler, r.k) for r in runs] + [("volume_fused", 0)]
    for sampler, k in tqdm(timed, desc="render times", unit="renderer"):
        t = measure(call(sampler, k), plan.timing_rounds)
        rows.append({"sampler": sampler, "k": k, "ms": 1e3 * t["min_s"] / len(cams),
                     "median_ms": 1e3 * t["median_s"] / len(cams)})
    return rows


def feature_agreement(plan: Plan, scene: SceneData, features: np.ndarray, runs: list[Renderer]) -> list[dict]:
    """Mean cosine similarity between each renderer's feature image of ``features`` [N,C] and
    V-Render's, over the pixels of ``scene``'s first view (at ``plan.timing_size``) where
    V-Render's alpha is >= 0.5: how differently the renderers supervise the same network."""
    g, cam = scene.gaussians, scene.frames[0].camera.resized(*plan.timing_size)
    args = (g.means, g.quats, g.scales, g.opacities, features, cam.viewmat, cam.K, cam.width, cam.height)
    ref, alpha, _ = rasterize(*args, sampler="volume")
    covered = alpha.numpy()[..., 0] >= 0.5
    ref = ref.numpy()[covered]
    rows = []
    for run in runs:
        img = rasterize(*args, sampler=run.sampler, k=run.k or 1)[0].numpy()[covered]
        cos = np.sum(img * ref, 1) / np.maximum(np.linalg.norm(img, axis=1) * np.linalg.norm(ref, axis=1), 1e-12)
        rows.append({"sampler": run.sampler, "k": run.k, "cosine": float(cos.mean()) if cos.size else float("nan")})
    return rows


# ----------------------------------------------------------------------------------------------
# transmittance profiles (Fig. 3)
# ----------------------------------------------------------------------------------------------

def step_value(depths: np.ndarray, t: np.ndarray, at: np.ndarray) -> np.ndarray:
    """A transmittance profile (depths [n] ascending, T [n+1]) evaluated at depths ``at`` [m]:
    T after every Gaussian at depth <= ``at``."""
    return t[np.searchsorted(depths, at, side="right")]


def weight_cdf(t: np.ndarray) -> np.ndarray:
    """The normalized cumulative weight (1 - T) / (1 - T_last) [n+1] of a transmittance profile's
    T [n+1]: where along the ray the rendered feature takes its weight (all zeros if T never drops)."""
    mass = 1.0 - t[-1]
    return (1.0 - t) / mass if mass > 0 else np.zeros_like(t)


def profile_gaps(volume: tuple[np.ndarray, np.ndarray], other: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    """Two distances of a sampler's profile ``other`` from V-Render's ``volume`` (each (depths [n]
    ascending, T [n+1])), evaluated at the depths of V-Render's entries: mean |T_other - T_volume|,
    and mean |CDF_other - CDF_volume| of their normalized cumulative weights (:func:`weight_cdf`).
    (0, 0) for a ray V-Render does not hit."""
    depths, t = volume
    if not len(depths):
        return 0.0, 0.0
    t_other = step_value(*other, depths)
    cdf_other = step_value(other[0], weight_cdf(other[1]), depths)
    return float(np.mean(np.abs(t_other - t[1:]))), float(np.mean(np.abs(cdf_other - weight_cdf(t)[1:])))


def profile_rays(scene: SceneData, view: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` pixels [n,2] (x, y) drawn among those of ``scene``'s frame ``view`` that V-Render hits."""
    cam = scene.frames[view].camera
    counts = entries_per_ray(scene.gaussians, cam)
    hit = np.flatnonzero(counts > 0)
    pick = np.sort(rng.choice(hit, min(n, len(hit)), replace=False))
    return np.stack([pick % cam.width, pick // cam.width], 1).astype(np.int32)


def transmittance_study(plan: Plan, scene: SceneData, out: Path, seed: int) -> dict:
    """Transmittance profiles of :data:`PROFILE_RAYS` rays of the held-out room's first view for
    V-Render, Q-Render, top-K and Stratified-K at K = ``plan.profile_k``: the mean gaps of each to
    V-Render's profile (:func:`profile_gaps`: transmittance, normalized weight) and the plots of
    three rays (few, median and many entries), written to ``out``."""
    g, cam = scene.gaussians, scene.frames[0].camera
    pixels = profile_rays(scene, 0, PROFILE_RAYS, np.random.default_rng(seed))
    ones = np.ones((len(g), 1), np.float32)
    profiles = {}
    for sampler in ("volume", "quantile", "topk", "stratified"):
        _, _, meta = rasterize(g.means, g.quats, g.scales, g.opacities, ones, cam.viewmat, cam.K, cam.width,
                               cam.height, sampler=sampler, k=plan.profile_k, pixels=pixels)
        name = LABELS[sampler] + ("" if sampler == "volume" else f" K={plan.profile_k}")
        profiles[name] = [transmittance_profile(meta["selection"], r) for r in range(len(pixels))]
    volume = profiles[LABELS["volume"]]
    gaps = {name: np.mean([profile_gaps(v, p) for v, p in zip(volume, rays)], axis=0).tolist()
            for name, rays in profiles.items() if name != LABELS["volume"]}
    entries = np.array([len(v[0]) for v in volume])
    order = np.argsort(entries, kind="stable")
    chosen = [int(order[int(q * (len(order) - 1))]) for q in np.linspace(0.1, 0.95, PLOTTED_PROFILES)]
    files = []
    for r in chosen:
        path = out / f"transmittance_ray{r:03d}.png"
        x, y = pixels[r]
        plot_transmittance_profiles({name: rays[r] for name, rays in profiles.items()}, str(path),
                                    f"pixel ({x}, {y}): {entries[r]} V-Render entries")
        files.append(path.name)
    return {"k": plan.profile_k, "rays": len(pixels), "gap": gaps, "entries_mean": float(entries.mean()),
            "files": files}


# ----------------------------------------------------------------------------------------------
# RGB fidelity
# ----------------------------------------------------------------------------------------------

def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two images with values clipped to [0, 1] (peak 1)."""
    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(1 / mse)


def rgb_renders(g: Gaussians, cam: Camera, ks: tuple[int, ...]) -> dict:
    """V-Render's RGB [H,W,3] and alpha [H,W,1] from SH, and per K the normalized RGB [H,W,3] and
    own alpha [H,W,1] (1 - T where the walk stopped) of Q-Render ("quantile") and top-K ("topk")."""
    args = (g.means, g.quats, g.scales, g.opacities, g.sh, cam.viewmat, cam.K, cam.width, cam.height)
    rgb, alpha, _ = rasterize(*args, sampler="volume", sh_degree=g.sh_degree)
    renders = {"volume": rgb.numpy(), "alpha": alpha.numpy()}
    for sampler in ("quantile", "topk"):
        renders[sampler] = {}
        for k in ks:
            k_rgb, k_alpha, _ = rasterize(*args, sampler=sampler, k=k, sh_degree=g.sh_degree)
            renders[sampler][k] = (k_rgb.numpy(), k_alpha.numpy())
    return renders


def rgb_fidelity(name: str, g: Gaussians, cams: list[Camera], ks: tuple[int, ...], out: Path) -> list[dict]:
    """PSNR (mean over ``cams``) against V-Render at each K of Q-Render's raw normalized image, of
    its colour times V-Render's alpha and times its own alpha, and of top-K's colour times
    V-Render's alpha; writes rgb_<name>.png of the first view (V-Render | raw Q-Render |
    Q-Render x V alpha | 4 |V - raw Q|, at the largest K)."""
    renders = [rgb_renders(g, c, ks) for c in cams]

    def mean_psnr(sampler: str, k: int, composite) -> float:
        return float(np.mean([psnr(composite(*r[sampler][k], r["alpha"]), r["volume"]) for r in renders]))
    rows = [{"scene": name, "k": k, "views": len(cams), "size": f"{cams[0].width}x{cams[0].height}",
             "psnr_raw": mean_psnr("quantile", k, lambda q, own, v_alpha: q),
             "psnr_alpha": mean_psnr("quantile", k, lambda q, own, v_alpha: q * v_alpha),
             "psnr_own_alpha": mean_psnr("quantile", k, lambda q, own, v_alpha: q * own),
             "psnr_topk_alpha": mean_psnr("topk", k, lambda q, own, v_alpha: q * v_alpha)} for k in ks]
    first, k = renders[0], max(ks)
    q = first["quantile"][k][0]
    panels = [first["volume"], q, q * first["alpha"], 4 * np.abs(np.clip(q, 0, 1) - np.clip(first["volume"], 0, 1))]
    save_image_grid(out / f"rgb_{name}.png", [panels], ["V-Render", f"Q-Render K={k} (raw, normalized)",
                                                        f"Q-Render K={k} x V-Render alpha", "4 |V - raw Q|"])
    return rows


def rgb_study(plan: Plan, held: SceneData, data: Path | None, out: Path) -> list[dict]:
    """:func:`rgb_fidelity` on the held-out room's first views (resized to the plan's RGB size) and
    on orbit views of the real captures of ``data`` (none when absent)."""
    scenes = [(held.name, held.gaussians, [f.camera.resized(*plan.rgb_size) for f in held.frames[:plan.rgb_views]])]
    scenes += real_captures(data, plan.rgb_views, plan.rgb_size)
    rows = []
    for name, g, cams in tqdm(scenes, desc="RGB fidelity", unit="scene"):
        rows += rgb_fidelity(name, g, cams, plan.rgb_ks, out)
    return rows


# ----------------------------------------------------------------------------------------------
# the paper's claims, plots and the report
# ----------------------------------------------------------------------------------------------

def _first_seed(results: dict) -> list[dict]:
    """The runs of ``results`` trained with the command's seed (not the repeated one)."""
    return [r for r in results["runs"] if not r.get("seed", 0)]


def _run(results: dict, sampler: str, k: int = 0, noise: float = 0.0, seed: int = 0) -> dict | None:
    return next((r for r in results["runs"] if r["sampler"] == sampler and r["k"] == k and r["noise"] == noise
                 and r.get("seed", 0) == seed), None)


def _time(results: dict, sampler: str, k: int = 0) -> float | None:
    row = next((t for t in results["render_ms"] if t["sampler"] == sampler and t["k"] == k), None)
    return None if row is None else row["ms"]


def _cosine(results: dict, sampler: str, k: int = 0) -> float | None:
    row = next((a for a in results["agreement"] if a["sampler"] == sampler and a["k"] == k), None)
    return None if row is None else row["cosine"]


def paper_claims(results: dict, tolerance: float = 1.0) -> list[dict]:
    """The paper's claims checked on ``results`` (held-out mIoU19 in points): each
    {"claim", "measured", "holds": True/False, or None when the runs it needs are missing}.
    ``tolerance``: the points a difference may have and still count as "on par"/"robust"."""
    claims = []
    v = _run(results, "volume")
    qs = [r for r in _first_seed(results) if r["sampler"] == "quantile" and r["k"] >= 10 and not r["noise"]]
    claims.append({"claim": "Q-Render >= V-Render - 1 at K >= 10",
                   "measured": (", ".join(f"K={q['k']}: {q['miou19'] - v['miou19']:+.1f}" for q in qs)
                                if v and qs else "-"),
                   "holds": all(q["miou19"] >= v["miou19"] - 1 for q in qs) if v and qs else None})
    t5, q5 = _run(results, "topk", 5), _run(results, "quantile", 5)
    claims.append({"claim": "top-K at K=5 at least 3 points below Q-Render at K=5",
                   "measured": f"top-K - Q-Render = {t5['miou19'] - q5['miou19']:+.1f}" if t5 and q5 else "-",
                   "holds": t5["miou19"] <= q5["miou19"] - 3 if t5 and q5 else None})
    clean = _run(results, "quantile", NOISE_K)
    mild = [r for r in _first_seed(results) if 0 < r["noise"] <= 0.5]
    claims.append({"claim": f"robust to opacity noise up to 0.5 (within {tolerance:g} point)",
                   "measured": ", ".join(f"noise {r['noise']:g}: {r['miou19'] - clean['miou19']:+.1f}" for r in mild)
                   if clean and mild else "-",
                   "holds": all(r["miou19"] >= clean["miou19"] - tolerance for r in mild) if clean and mild else None})
    strat = _run(results, "stratified", NOISE_K)
    t_s, t_q = _time(results, "stratified", NOISE_K), _time(results, "quantile", NOISE_K)
    if strat and clean and t_s and t_q:
        ratio = t_s / t_q
        claims.append({"claim": f"Stratified-K on par (within {tolerance:g} point) at about half Q-Render's speed "
                                "(K=40)",
                       "measured": f"{strat['miou19'] - clean['miou19']:+.1f} points, {ratio:.2f}x Q-Render's time",
                       "holds": abs(strat["miou19"] - clean["miou19"]) <= tolerance and 1.5 <= ratio <= 2.5})
    else:
        claims.append({"claim": "Stratified-K on par at about half Q-Render's speed (K=40)", "measured": "-",
                       "holds": None})
    base = results.get("baseline")
    if base and clean:
        ratios = {part: clean[f"miou19{part}"] / max(base[f"miou19{part}"], 1e-9) for part in ("", "_reached")}
        claims.append({"claim": "GS-Net on a held-out room at least matches a per-scene model fitted on it (Table 1: "
                                "50.75 vs 22.60); bar here: >= 0.8x the baseline's mIoU19, all labelled Gaussians",
                       "measured": f"all labelled: {clean['miou19']:.1f} vs {base['miou19']:.1f} ({ratios['']:.2f}x); "
                                   f"reached only: {clean['miou19_reached']:.1f} vs {base['miou19_reached']:.1f} "
                                   f"({ratios['_reached']:.2f}x)",
                       "holds": ratios[""] >= 0.8})
    else:
        claims.append({"claim": "GS-Net >= 0.8x the per-scene baseline on the held-out room", "measured": "-",
                       "holds": None})
    rgb = results.get("rgb", [])
    claims.append({"claim": "slight RGB PSNR drop of Q-Render (>= 30 dB from V-Render at K >= 20)",
                   "measured": "; ".join(f"{r['scene']} K={r['k']}: raw {r['psnr_raw']:.1f} dB, x V alpha "
                                         f"{r['psnr_alpha']:.1f} dB" for r in rgb if r["k"] >= 20) or "-",
                   "holds": (all(r["psnr_alpha"] >= 30 for r in rgb if r["k"] >= 20) if any(r["k"] >= 20 for r in rgb)
                             else None)})
    return claims


def plot_miou_vs_time(results: dict, path: Path) -> None:
    """Fig. 4a: held-out mIoU19 against rendering time (ms per view) of every clean run."""
    fig, ax = plt.subplots(figsize=(6, 4))
    for sampler, style in (("topk", "s-"), ("quantile", "o-"), ("stratified", "^-"), ("volume", "D")):
        pts = sorted((r["k"], _time(results, sampler, r["k"]), r["miou19"]) for r in _first_seed(results)
                     if r["sampler"] == sampler and not r["noise"])
        pts = [p for p in pts if p[1] is not None]
        if pts:
            ax.plot([p[1] for p in pts], [p[2] for p in pts], style, label=LABELS[sampler])
            for k, t, m in pts:
                if k:
                    ax.annotate(f"K={k}", (t, m), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set(xlabel="rendering time per view (ms, 512-D features)", ylabel="held-out mIoU19 (%)",
           title="mIoU vs rendering time (Fig. 4a)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_scene_statistics(stats: list[dict], path: Path) -> None:
    """Opacity histograms (left) and mean V-Render entries per pixel (right) of the compared scenes."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    centres = (np.arange(OPACITY_BINS) + 0.5) / OPACITY_BINS
    for s in stats:
        axes[0].plot(centres, s["opacity_hist"], "o-", ms=3, label=f"{s['scene']} ({s['kind']})")
    axes[0].set(xlabel="opacity", ylabel="fraction of Gaussians", title="opacity histograms")
    axes[0].legend(fontsize=6)
    axes[1].barh([s["scene"] for s in stats], [s["entries_mean"] for s in stats])
    axes[1].axvline(50, color="gray", linestyle="--", label="dense indoor target: 50")
    axes[1].set(xlabel="V-Render entries per hit pixel (mean)")
    axes[1].tick_params(axis="y", labelsize=7)
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _fmt(value: float | None, digits: int = 1) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"


def _verdict(holds: bool | None) -> str:
    return {True: "reproduced", False: "not reproduced", None: "not measured"}[holds]


def _paper_miou(run: dict) -> float | None:
    """The paper's Fig. 4 mIoU of a clean run's renderer (None where the paper has none)."""
    entry = PAPER.get(run["sampler"])
    return entry.get(run["k"]) if isinstance(entry, dict) else entry


def _spread(results: dict) -> str:
    """A sentence on the run-to-run spread: Q-Render K=40 trained with two seeds."""
    first, again = _run(results, "quantile", NOISE_K), _run(results, "quantile", NOISE_K, seed=1)
    if not (first and again):
        return "One seed per run; the run-to-run spread was not measured."
    return (f"One seed per run; Q-Render K=40 trained again with the next seed scored mIoU19 {again['miou19']:.1f} "
            f"against {first['miou19']:.1f} ({again['miou19'] - first['miou19']:+.1f} points): differences of that "
            "size between renderers are within run-to-run noise.")


def baseline_section(results: dict) -> list[str]:
    """The report's lines comparing GS-Net with the per-scene baseline on the held-out room."""
    base, reached = results.get("baseline"), results.get("reached")
    if not base:
        return []
    lines = ["## GS-Net against a per-scene model (held-out room; Table 1)", "",
             f"The per-scene baseline fits free per-Gaussian features on the held-out room itself (qr_cl/app/"
             f"baseline.py) with GS-Net's budget through Q-Render K={NOISE_K}; GS-Net never saw the room. \"all\": "
             "every labelled Gaussian; \"reached\": the labelled Gaussians that some pixel's Q-Render "
             f"K={NOISE_K} selection in the room's views holds ({reached['gaussians']} of {reached['labelled']}), "
             "the only ones the baseline's rays can train: the others keep their random initial features.", "",
             "| model | mIoU19 all | mAcc19 all | mIoU19 reached | mAcc19 reached | train s |",
             "| --- | ---: | ---: | ---: | ---: | ---: |"]
    rows = [base] + [r for r in (_run(results, "quantile", NOISE_K), _run(results, "volume")) if r]
    lines += [f"| {'GS-Net, ' if r is not base else ''}{r['label']} | {_fmt(r['miou19'])} | {_fmt(r['macc19'])} | "
              f"{_fmt(r['miou19_reached'])} | {_fmt(r['macc19_reached'])} | {r['train_s']:.0f} |" for r in rows]
    return lines + [""]


def report_markdown(results: dict) -> str:
    """The report of ``results`` (as :func:`run_reproduction` returns and results.json holds)."""
    plan = results["plan"]
    lines = [f"# qr-cl reproduce ({results['mode']})", "",
             f"GS-Net (small sparse UNet) trained on {len(results['scenes']['train'])} synthetic \"3dgs\" rooms "
             f"({plan['room']}) for {plan['steps']} steps of {plan['views']} views x {plan['rays']} rays through each "
             f"renderer (the same budget), evaluated on the held-out room {results['scenes']['held_out']} (ground "
             "truth: the generator's per-Gaussian labels, opacity >= 0.1). The \"CLIP\" features are simulated "
             f"(qr_cl/app/synthetic.py). {_spread(results)} Device: {results['device']}. Whole run: "
             f"{results['wall_s'] / 60:.1f} min.", "",
             "## Scenes against real captures", "",
             "Entries: the Gaussians V-Render blends per ray (alpha >= 1/255 until T < 1e-4), over the rays that hit "
             "anything; 90 % weight: the fewest Gaussians holding 90 % of a ray's weight (mean over sampled hit rays), "
             "how many Gaussians really shape a ray's colour or feature.", "",
             "| scene | kind | Gaussians | views | size | mean opacity | entries per hit pixel: mean | "
             "median | p90 | Gaussians holding 90 % weight | pixels hit |", "| --- " * 11 + "|"]
    for s in results["statistics"]:
        lines.append(f"| {s['scene']} | {s['kind']} | {s['n_gaussians']} | {s['views']} | {s['size']} | "
                     f"{s['opacity_mean']:.2f} | {s['entries_mean']:.1f} | {s['entries_median']:.0f} | "
                     f"{s['entries_p90']:.0f} | {s['holding_90']:.1f} | {s['coverage']:.0%} |")
    lines += ["", "![opacity histograms and entries per pixel](scene_statistics.png)", "",
              "## Renderers (held-out room; Fig. 4)", "",
              "Rendering time: whole images of 512-D features per view at "
              f"{plan['timing_size'][0]}x{plan['timing_size'][1]} on the held-out room "
              f"(min of {plan['timing_rounds']} rounds over {plan['timing_views']} views); training time of the run; "
              "cos to V: mean cosine similarity of the renderer's feature image to V-Render's (first view, pixels with "
              "V-Render alpha >= 0.5, features of the V-Render run's GS-Net).", "",
              "| renderer | mIoU19 | mAcc19 | mIoU15 | mIoU10 | paper mIoU19 | render ms | cos to V | train s | "
              "final loss |",
              "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in (r for r in results["runs"] if not r["noise"]):
        lines.append(f"| {r['label']} | {_fmt(r['miou19'])} | {_fmt(r['macc19'])} | {_fmt(r['miou15'])} | "
                     f"{_fmt(r['miou10'])} | {_fmt(_paper_miou(r), 2)} | "
                     f"{_fmt(_time(results, r['sampler'], r['k']))} | "
                     f"{_fmt(_cosine(results, r['sampler'], r['k']), 4)} | "
                     f"{r['train_s']:.0f} | {r['final_loss']:.3f} |")
    lines += [f"| fused V-Render kernel (no selection) | | | | | | {_fmt(_time(results, 'volume_fused'))} | | | |", "",
              "![mIoU vs rendering time](miou_vs_time.png)", ""]
    lines += baseline_section(results)
    lines += ["## Opacity noise (Q-Render K=40)", "",
              "| noise scale | mIoU19 | mAcc19 | paper mIoU19 |", "| ---: | ---: | ---: | ---: |"]
    for r in sorted((r for r in _first_seed(results) if r["sampler"] == "quantile" and r["k"] == NOISE_K),
                    key=lambda r: r["noise"]):
        lines.append(f"| {r['noise']:g} | {_fmt(r['miou19'])} | {_fmt(r['macc19'])} | "
                     f"{_fmt(PAPER['noise'].get(r['noise']), 2)} |")
    prof = results["profiles"]
    lines += ["", f"## Transmittance profiles (Fig. 3), K={prof['k']}", "",
              f"Over {prof['rays']} random hit rays of the held-out room's first view (V-Render blends "
              f"{prof['entries_mean']:.1f} Gaussians per ray there), at the depths of V-Render's entries: the mean "
              "|T_sampler - T_V-Render| (T of a K sampler: its un-normalized transmittance among the selected "
              "Gaussians, as plotted) and the mean gap between the normalized cumulative weights (1 - T) / (1 - T_end) "
              "(where along the ray the rendered feature takes its weight; 0 = V-Render's depth weighting).", "",
              "| sampler | mean T gap | mean weight-CDF gap |", "| --- | ---: | ---: |"]
    lines += [f"| {name} | {t_gap:.3f} | {cdf_gap:.3f} |" for name, (t_gap, cdf_gap) in prof["gap"].items()]
    lines += [""] + [f"![transmittance]({f})" for f in prof["files"]]
    lines += ["", "## RGB fidelity (from SH colours)", "",
              "PSNR against V-Render (black background, values clipped to [0, 1]) of the raw normalized Q-Render "
              "image, of Q-Render's colour times V-Render's alpha, and of Q-Render's colour times its own alpha (the "
              "alpha `rasterize(sampler=\"quantile\")` returns: 1 - T where its walk stopped), and for comparison "
              "top-K's colour times V-Render's alpha. Pictures: V-Render | raw Q-Render | Q-Render x V-Render alpha | "
              "4x |V - raw Q| (largest K).", "",
              "| scene | views | size | K | raw Q-Render dB | Q-Render x V alpha dB | Q-Render x own alpha dB | "
              "top-K x V alpha dB |", "| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: |"]
    lines += [f"| {r['scene']} | {r['views']} | {r['size']} | {r['k']} | {_fmt(r['psnr_raw'])} | "
              f"{_fmt(r['psnr_alpha'])} | {_fmt(r['psnr_own_alpha'])} | {_fmt(r.get('psnr_topk_alpha'))} |"
              for r in results["rgb"]]
    lines += [""] + [f"![rgb {s}](rgb_{s}.png)" for s in dict.fromkeys(r["scene"] for r in results["rgb"])]
    lines += ["", "## The paper's claims", "", "| claim | measured | verdict |", "| --- | --- | --- |"]
    lines += [f"| {c['claim']} | {c['measured']} | {_verdict(c['holds'])} |" for c in results["claims"]]
    return "\n".join(lines) + "\n"


def write_report(out: Path, results: dict) -> list[Path]:
    """results.json, report.md, miou_vs_time.png and scene_statistics.png into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    files = [out / "results.json", out / "report.md", out / "miou_vs_time.png", out / "scene_statistics.png"]
    files[0].write_text(json.dumps(results, indent=1, default=str))
    files[1].write_text(report_markdown(results))
    plot_miou_vs_time(results, files[2])
    plot_scene_statistics(results["statistics"], files[3])
    return files


# ----------------------------------------------------------------------------------------------
# the command
# ----------------------------------------------------------------------------------------------

def run_reproduction(plan: Plan, mode: str, out: Path, cache: Path | None, data: Path | None, seed: int) -> dict:
    """Run every experiment of ``plan`` (module docstring), write the report into ``out`` and
    return the results."""
    start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    train_paths, held_path = splat_rooms(plan, seed, cache)
    held = load_scene_folder(held_path)
    gt, _ = ground_truth(held)
    flat = load_scene_folder(synthetic_scene(SyntheticConfig(seed=seed + 1000, **plan.flat_room), cache))
    statistics = compare_scenes(plan, held, flat, data, seed)
    reached = reached_gaussians(held, "quantile", NOISE_K)
    runs = renderers(plan)
    rows = []
    with torch_threads(1):
        for run in tqdm(runs, desc="renderers", unit="run"):
            rows.append(train_and_evaluate(plan, run, train_paths, held, gt, reached, out, seed))
        baseline = baseline_scores(plan, held, gt, reached, out, seed)
        features = network_features(Path(rows[0]["checkpoint"]), held)      # timed renders: V-Render's GS-Net
    timed = [r for r in runs if not r.noise]
    results = {"mode": mode, "plan": asdict(plan), "seed": seed, "device": runtime().device.name.strip(),
               "scenes": {"train": [p.name for p in train_paths], "held_out": held.name},
               "statistics": statistics, "runs": rows, "baseline": baseline,
               "reached": {"gaussians": int((reached & (gt >= 0)).sum()), "labelled": int((gt >= 0).sum())},
               "render_ms": render_times(plan, held, features, timed),
               "agreement": feature_agreement(plan, held, features, timed),
               "profiles": transmittance_study(plan, held, out, seed),
               "rgb": rgb_study(plan, held, data, out)}
    results["claims"] = paper_claims(results)
    results["wall_s"] = time.perf_counter() - start
    write_report(out, results)
    return results


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl reproduce``."""
    parser.add_argument("--quick", action="store_true",
                        help="the quick plan (about 5 minutes on 2 cores): top-K/Q-Render K in {5, 10, 40}, "
                             "noise {0, 0.5, 2}, 150 steps, 2 training rooms")
    parser.add_argument("--smoke", action="store_true", help="seconds on tiny rooms (tests; numbers mean nothing)")
    parser.add_argument("--out", default="qr-cl-reproduce", help="report folder (default ./qr-cl-reproduce)")
    parser.add_argument("--cache", help="scene cache (default $QR_CL_CACHE/scenes or ~/.cache/qr-cl/scenes)")
    parser.add_argument("--data", default=os.environ.get("QR_CL_DATA"),
                        help="folder with the real scenes (wakufactory-fox/fox.ply, v3dg-donut/donut_fused.ply; "
                             "default $QR_CL_DATA): compared with the synthetic rooms and used for RGB fidelity")
    parser.add_argument("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> int:
    """``qr-cl reproduce``: run the plan and print the report's path and claims."""
    cap_kernel_threads()                      # before the first render (scene generation)
    keep_freed_memory()
    mode = "smoke" if args.smoke else "quick" if args.quick else "full"
    out = Path(args.out)
    results = run_reproduction(PLANS[mode], mode, out, Path(args.cache) if args.cache else None,
                               Path(args.data) if args.data else None, args.seed)
    for c in results["claims"]:
        print(f"{_verdict(c['holds']):>15}: {c['claim']} ({c['measured']})")
    print(f"reproduce ({mode}) finished in {results['wall_s']:.0f} s. Report: {(out / 'report.md').resolve()}")
    return 0
