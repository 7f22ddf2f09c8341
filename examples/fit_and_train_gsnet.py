"""Fit 3D Gaussians to a real capture, then train GS-Net features on the fit: all on a CPU, no CUDA.

    python examples/fit_and_train_gsnet.py [--ply ../shared/data/wakufactory-fox/fox.ply] [--out fit-and-train]

1. Target images: the capture (a 3DGS PLY) rendered with qr-cl's V-Render from orbit views.
2. Fit: a few thousand Gaussians (a random subset of the capture's centres, grey, isotropic) are
   optimised with Adam through ``qr_cl.rasterization`` (gsplat's interface; gradients w.r.t.
   means, quats, scales, opacities and colours) against the target images, densified as gsplat's
   DefaultStrategy does (:class:`Densifier`: the screen-space gradients ``meta["means2d"].grad``
   accumulated per Gaussian; the small ones of large gradient cloned, the large ones split, the
   transparent ones pruned; ``--no-densify`` turns it off).
3. Semantics: the capture's Gaussians are clustered by colour (k-means) into "parts"; per view a
   mask map of the dominant part is rendered from the capture, and every mask gets a simulated
   512-D "CLIP" feature (its part's random prototype plus noise), written in LangSplat's layout
   beside the fitted Gaussians.
4. GS-Net is trained on the fitted Gaussians through Q-Render (``qr_cl.app.training.command``), and its
   per-Gaussian features are scored by the part each Gaussian's feature is closest to, rendered
   into every view and compared with the capture's part masks (pixel accuracy), beside the
   accuracy of always answering the largest part.

Writes fit.png (targets | fit before | fit after), parts.png (masks | GS-Net's parts), the scene
folder ``<out>/scene`` and the training run ``<out>/run``.
"""
from __future__ import annotations

import argparse
import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

import qr_cl
from qr_cl.app.images import save_image_grid
from qr_cl.app.scenes.folders import load_scene_folder
from qr_cl.app.training.config import TrainConfig
from qr_cl.app.training.network import network_features
from qr_cl.app.training.trainer import train
from qr_cl.scene.gaussians import quat_to_rotmat

DEFAULT_PLY = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "wakufactory-fox" / "fox.ply"
FEATURE_DIM = 512


def target_images(capture: qr_cl.Gaussians, cameras: list) -> torch.Tensor:
    """[V,H,W,3] RGB of the capture from each camera (V-Render, SH colours)."""
    images = [qr_cl.render_volume_fused(capture.means, capture.quats, capture.scales, capture.opacities,
                                        capture.sh, c.viewmat, c.K, c.width, c.height,
                                        sh_degree=capture.sh_degree)[0] for c in cameras]
    return torch.stack(images)


def gaussians(params: dict[str, torch.Tensor]) -> qr_cl.Gaussians:
    """The Gaussians of the fit's parameters (unit quaternions, activated scales, opacities)."""
    with torch.no_grad():
        quats = params["quats"] / params["quats"].norm(dim=1, keepdim=True)
        return qr_cl.Gaussians.from_rgb(params["means"].numpy().copy(), quats.numpy(),
                                        params["log_scales"].exp().numpy(),
                                        torch.sigmoid(params["logit_opacities"]).numpy(),
                                        params["colours"].clamp(0, 1).numpy())


@dataclass
class Densifier:
    """Growing and pruning in the manner of gsplat's DefaultStrategy, driven by the 2-D means'
    gradients that ``qr_cl.rasterization`` leaves in ``meta["means2d"].grad`` (packed meta).

    After each backward the norm of each visible Gaussian's screen-space gradient (in NDC units,
    scaled by the number of cameras, as gsplat) is added up with a count. Every ``every`` steps
    from ``start`` to ``stop``, Gaussians whose mean gradient exceeds ``grad2d`` grow: cloned
    where their largest scale is below ``scale3d`` of the scene's extent, else split in two
    (positions drawn from the Gaussian, scales / 1.6); then those with opacity below ``opacity``
    are pruned. New rows start with zero Adam moments. ``history`` records (step, cloned, split,
    pruned, N) per refinement.
    """

    extent: float
    grad2d: float = 5e-5
    scale3d: float = 0.03
    opacity: float = 0.05
    start: int = 50
    stop: int = 250
    every: int = 25
    seed: int = 0
    history: list = field(default_factory=list)

    def __post_init__(self) -> None:
        self.grad_sum: torch.Tensor | None = None
        self.count: torch.Tensor | None = None
        self.rng = torch.Generator().manual_seed(self.seed)

    def before_backward(self, meta: dict) -> None:
        """Keep the gradient of rasterization's meta["means2d"] (a non-leaf tensor)."""
        meta["means2d"].retain_grad()

    def after_backward(self, step: int, meta: dict, params: dict[str, torch.Tensor],
                       opt: torch.optim.Optimizer) -> None:
        """Add this step's screen-space gradients (packed meta) and refine when it is time;
        ``params`` (name -> [N, ...] leaf) and ``opt`` (one param group per parameter) are
        replaced in place."""
        n = len(params["means"])
        if self.grad_sum is None or len(self.grad_sum) != n:
            self.grad_sum, self.count = torch.zeros(n), torch.zeros(n)
        grad = meta["means2d"].grad.clone()
        grad[:, 0] *= meta["width"] / 2 * meta["n_cameras"]
        grad[:, 1] *= meta["height"] / 2 * meta["n_cameras"]
        self.grad_sum.index_add_(0, meta["gaussian_ids"], grad.norm(dim=-1))
        self.count.index_add_(0, meta["gaussian_ids"], torch.ones(len(grad)))
        if self.start <= step < self.stop and step % self.every == 0 and step > 0:
            self.refine(step, params, opt)

    @torch.no_grad()
    def refine(self, step: int, params: dict[str, torch.Tensor], opt: torch.optim.Optimizer) -> None:
        """Clone, split, then prune (see the class), and restart the gradient statistics."""
        grow = self.grad_sum / self.count.clamp_min(1) > self.grad2d
        large = params["log_scales"].exp().max(1).values > self.scale3d * self.extent
        clone, split = grow & ~large, grow & large
        rows = {key: p.detach() for key, p in params.items()}
        scales = rows["log_scales"][split].exp()
        quats = rows["quats"][split] / rows["quats"][split].norm(dim=1, keepdim=True)
        offsets = torch.einsum("nij,nj,bnj->bni", quat_to_rotmat(quats), scales,
                               torch.randn(2, len(scales), 3, generator=self.rng))
        added = {key: torch.cat([x[clone], x[split].repeat(2, *[1] * (x.ndim - 1))]) for key, x in rows.items()}
        n_clone = int(clone.sum())
        added["means"][n_clone:] += offsets.reshape(-1, 3)
        added["log_scales"][n_clone:] -= float(np.log(1.6))
        keep = ~split
        self._rebuild(params, opt, lambda x, new: torch.cat([x[keep], new]), added)
        pruned = torch.sigmoid(params["logit_opacities"].detach()) < self.opacity
        self._rebuild(params, opt, lambda x, new: x[~pruned], None)
        self.history.append((step, int(clone.sum()), int(split.sum()), int(pruned.sum()), len(params["means"])))
        self.grad_sum, self.count = None, None

    @staticmethod
    def _rebuild(params: dict[str, torch.Tensor], opt: torch.optim.Optimizer, rows, added: dict | None) -> None:
        """Replace every parameter by rows(old, new rows) and its Adam moments alike (new rows 0)."""
        for group in opt.param_groups:
            old = group["params"][0]
            key = next(k for k, p in params.items() if p is old)
            new_rows = None if added is None else added[key]
            param = rows(old.detach(), new_rows).requires_grad_(True)
            state = opt.state.pop(old, {})
            for moment in ("exp_avg", "exp_avg_sq"):
                if moment in state:
                    state[moment] = rows(state[moment], None if new_rows is None else torch.zeros_like(new_rows))
            group["params"][0], params[key] = param, param
            opt.state[param] = state


def fit(capture: qr_cl.Gaussians, cameras: list, targets: torch.Tensor, n: int, steps: int,
        seed: int, densify: bool = True) -> tuple[qr_cl.Gaussians, qr_cl.Gaussians, list[float], Densifier | None]:
    """``n`` Gaussians fitted to ``targets`` by Adam through qr_cl.rasterization (two views per
    step), densified by a :class:`Densifier` (refining until 5/6 of the steps) when ``densify``;
    returns them before and after the fit, the PSNR (dB) of every step and the densifier."""
    rng = np.random.default_rng(seed)
    start = capture.means[rng.choice(len(capture), n, replace=False)]
    extent = np.percentile(capture.means, 98, 0) - np.percentile(capture.means, 2, 0)
    params = {"means": torch.tensor(start, requires_grad=True),
              "quats": torch.tensor(np.tile([1.0, 0, 0, 0], (n, 1)), dtype=torch.float32, requires_grad=True),
              "log_scales": torch.full((n, 3), float(np.log(extent.mean() / n ** (1 / 3))), requires_grad=True),
              "logit_opacities": torch.zeros(n, requires_grad=True),
              "colours": torch.full((n, 3), 0.5, requires_grad=True)}
    rates = {"means": 2e-3 * float(extent.mean()), "quats": 1e-2, "log_scales": 1e-2, "logit_opacities": 5e-2,
             "colours": 2e-2}
    opt = torch.optim.Adam([{"params": [p], "lr": rates[k]} for k, p in params.items()])
    densifier = Densifier(float(extent.mean()), stop=steps * 5 // 6, seed=seed) if densify else None
    viewmats = torch.from_numpy(np.stack([c.viewmat for c in cameras]))
    Ks = torch.from_numpy(np.stack([c.K for c in cameras]).astype(np.float32))
    w, h = cameras[0].width, cameras[0].height
    initial = gaussians(params)
    psnr = []
    bar = tqdm(range(steps), desc="fit", unit="step")
    for step in bar:
        views = rng.choice(len(cameras), 2, replace=False)
        image, _, meta = qr_cl.rasterization(params["means"], params["quats"], params["log_scales"].exp(),
                                             torch.sigmoid(params["logit_opacities"]), params["colours"],
                                             viewmats[views], Ks[views], w, h)
        loss = ((image - targets[views]) ** 2).mean()
        opt.zero_grad()
        if densifier:
            densifier.before_backward(meta)
        loss.backward()
        if densifier:
            densifier.after_backward(step, meta, params, opt)
        opt.step()
        psnr.append(float(-10 * torch.log10(loss.detach())))
        bar.set_postfix(psnr=f"{psnr[-1]:.1f} dB", gaussians=len(params["means"]))
    return initial, gaussians(params), psnr, densifier


def colour_parts(capture: qr_cl.Gaussians, parts: int, seed: int) -> np.ndarray:
    """A part id [N] per Gaussian of the capture: k-means of its base colours (SH DC term)."""
    colours = capture.sh[:, 0].astype(np.float64)
    rng = np.random.default_rng(seed)
    centres = colours[rng.choice(len(colours), parts, replace=False)]
    for _ in range(30):
        ids = np.argmin(((colours[:, None] - centres[None]) ** 2).sum(-1), 1)
        centres = np.stack([colours[ids == p].mean(0) if (ids == p).any() else centres[p] for p in range(parts)])
    return ids


def part_maps(gaussians: qr_cl.Gaussians, part: np.ndarray, parts: int, cameras: list) -> list[np.ndarray]:
    """Per camera an [H,W] int32 map of the dominant part (-1 where the coverage is below 0.5)."""
    onehot = np.eye(parts, dtype=np.float32)[part]
    maps = []
    for c in cameras:
        image, _, _ = qr_cl.rasterize(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                                      onehot, c.viewmat, c.K, c.width, c.height)
        image = image.numpy()
        maps.append(np.where(image.max(-1) >= 0.5, image.argmax(-1), -1).astype(np.int32))
    return maps


def write_scene_folder(folder: Path, fitted: qr_cl.Gaussians, cameras: list, maps: list[np.ndarray],
                       prototypes: np.ndarray, seed: int) -> None:
    """The fitted Gaussians with the capture's part masks in qr-cl's scene-folder layout (see the
    README): point_cloud.ply, cameras.json, language_features/<view>_s.npy and _f.npy (one level,
    a simulated feature per mask) and classes.json (a part's "text" feature is its prototype)."""
    rng = np.random.default_rng(seed)
    lang = folder / "language_features"
    lang.mkdir(parents=True, exist_ok=True)
    qr_cl.save_ply(folder / "point_cloud.ply", fitted)
    entries = []
    for i, (cam, part) in enumerate(zip(cameras, maps)):
        name = f"view{i:02d}"
        present = np.unique(part[part >= 0])
        row = np.full(len(prototypes), -1, np.int32)
        row[present] = np.arange(len(present))
        noisy = prototypes[present] + 0.5 * rng.standard_normal((len(present), FEATURE_DIM)) / np.sqrt(FEATURE_DIM)
        np.save(lang / f"{name}_s.npy", np.where(part >= 0, row[np.maximum(part, 0)], -1)[None])
        np.save(lang / f"{name}_f.npy", (noisy / np.linalg.norm(noisy, axis=1, keepdims=True)).astype(np.float32))
        entries.append({"id": i, "img_name": name, "width": cam.width, "height": cam.height,
                        "position": cam.position.tolist(), "rotation": cam.viewmat[:3, :3].T.tolist(),
                        "fx": cam.fx, "fy": cam.fy})
    (folder / "cameras.json").write_text(json.dumps(entries))
    classes = [{"id": p, "name": f"part {p}", "text_feature": prototypes[p].tolist()} for p in range(len(prototypes))]
    (folder / "classes.json").write_text(json.dumps({"feature_dim": FEATURE_DIM, "classes": classes}))


def part_accuracy(folder: Path, checkpoint: Path, maps: list[np.ndarray], prototypes: np.ndarray
                  ) -> tuple[float, float, list[np.ndarray]]:
    """(pixel accuracy of GS-Net's parts against the masks, accuracy of the largest part, the
    predicted part maps): each fitted Gaussian takes the part whose prototype its GS-Net
    feature is closest to, and the parts are rendered into every view."""
    scene = load_scene_folder(folder)
    part = np.argmax(network_features(checkpoint, scene) @ prototypes.T, 1)
    predicted = part_maps(scene.gaussians, part, len(prototypes), [f.camera for f in scene.frames])
    masked = np.concatenate([m[m >= 0] for m in maps])
    hits = sum(int((p[m >= 0] == m[m >= 0]).sum()) for p, m in zip(predicted, maps))
    return hits / len(masked), np.bincount(masked).max() / len(masked), predicted


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ply", type=Path, default=DEFAULT_PLY, help="a 3DGS capture (INRIA PLY)")
    parser.add_argument("--out", type=Path, default=Path("fit-and-train"))
    parser.add_argument("--gaussians", type=int, default=3000, help="Gaussians to fit")
    parser.add_argument("--fit-steps", type=int, default=300)
    parser.add_argument("--no-densify", action="store_true", help="fit without growing and pruning")
    parser.add_argument("--train-steps", type=int, default=100)
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--width", type=int, default=128)
    parser.add_argument("--parts", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if not args.ply.is_file():
        parser.error(f"{args.ply}: no such file (pass --ply with a 3DGS PLY, e.g. the fox of ../shared/data)")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        capture = qr_cl.load_ply(args.ply)
    cameras = qr_cl.orbit_cameras(capture.means, args.views, args.width, args.width * 3 // 4)
    args.out.mkdir(parents=True, exist_ok=True)

    targets = target_images(capture, cameras)
    initial, fitted, psnr, densifier = fit(capture, cameras, targets, args.gaussians, args.fit_steps, args.seed,
                                           densify=not args.no_densify)
    before, after = target_images(initial, cameras), target_images(fitted, cameras)
    before_psnr, after_psnr = (float(-10 * torch.log10(((x - targets) ** 2).mean())) for x in (before, after))
    print(f"fit: {len(fitted)} Gaussians, PSNR over all {len(cameras)} views {before_psnr:.1f} dB before -> "
          f"{after_psnr:.1f} dB after {args.fit_steps} steps")

    part = colour_parts(capture, args.parts, args.seed)
    maps = part_maps(capture, part, args.parts, cameras)
    prototypes = np.random.default_rng(args.seed + 1).standard_normal((args.parts, FEATURE_DIM))
    prototypes /= np.linalg.norm(prototypes, axis=1, keepdims=True)
    write_scene_folder(args.out / "scene", fitted, cameras, maps, prototypes, args.seed)
    cfg = TrainConfig(scenes=[str(args.out / "scene")], out=str(args.out / "run"), steps=args.train_steps,
                      views=2, rays=512, sampler="quantile", k=10, grid_size=float(np.ptp(fitted.means, 0).max()) / 40,
                      checkpoint_every=args.train_steps)
    train(cfg)
    accuracy, largest, predicted = part_accuracy(args.out / "scene", args.out / "run" / "checkpoint.pt", maps,
                                                 prototypes)
    print(f"GS-Net on the fitted Gaussians: part pixel accuracy {accuracy:.1%} (largest part alone: {largest:.1%})")

    shown = range(0, len(cameras), max(1, len(cameras) // 3))
    save_image_grid(args.out / "fit.png", [[x[v].numpy() for x in (targets, before, after)] for v in shown],
               ["capture (target)", f"{len(fitted)} Gaussians before", f"after {args.fit_steps} steps"])
    save_image_grid(args.out / "parts.png", [[maps[v], predicted[v]] for v in shown],
               ["capture's parts (masks)", "GS-Net on the fit"])
    print(f"wrote {args.out / 'fit.png'}, {args.out / 'parts.png'}")


if __name__ == "__main__":
    main()
