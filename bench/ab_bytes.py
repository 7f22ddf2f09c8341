"""Bytes of the renderer's outputs and gradients, for checking that a change leaves them unchanged.

Renders a seeded procedural scene through every public path (rasterize with each sampler, whole
image and a pixel subset, with gradients w.r.t. features and Gaussians; a cached selection
rendered and back-propagated twice; rasterization with SH, RGB+ED and absgrad; the fused
V-Render; a training step's gathered, concatenated and compacted selection with its transpose
made ahead; registration's weight sums of a view's top contributors) under each install and
compares every array's bytes and the kernels launched (name, work-items, build defines, in
order: the same launches do the same work); exit status 1 when any differs::

    python bench/ab_bytes.py --base PYTHON_OR_CHECKOUT
"""
from __future__ import annotations

import argparse
import inspect
import sys
import tempfile
from pathlib import Path

import numpy as np

from ab import add_base_option, installs


def recorded_launches() -> list[str]:
    """Records every kernel launch from now on ("name size defines"), in the returned list."""
    from qr_cl.runtime import Runtime
    launched, launch = [], Runtime.launch

    def record(self, name, global_size, defines=None, local_size=None, **args):
        launched.append(f"{name} {global_size} {sorted((defines or {}).items())}")
        return launch(self, name, global_size, defines, local_size, **args)
    Runtime.launch = record
    return launched


def outputs() -> dict[str, np.ndarray]:
    """Every output and gradient of the renders above, by name, and the kernels launched."""
    import torch

    import qr_cl
    from qr_cl.app.registration.contributors import top_contributors
    from qr_cl.app.registration.register import mask_weight_sums
    from qr_cl.app.scenes.procedural import procedural_scene
    from qr_cl.render import SelectionCache, blend, rasterize_plan
    from qr_cl.scene import orbit_cameras
    try:                                           # the selection operations' home in the install
        from qr_cl.render import compact_selections, concat_selections, gather_rays, prepare_backward
        from qr_cl.render import select_rays as select
    except ImportError:                            # before render/rays.py: stages and training
        from qr_cl.app.training.selections import compact_selections, concat_selections, gather_rays
        from qr_cl.stages import prepare_backward, select
    out = {}
    launched = recorded_launches()
    g = procedural_scene(3000)
    W, H = 96, 64
    cam = orbit_cameras(g.means, 8, W, H)[1]
    rng = np.random.default_rng(0)
    feats = rng.standard_normal((len(g), 19)).astype(np.float32)
    pixels = rng.integers(0, [W, H], (500, 2))
    geo = [np.asarray(a, np.float32) for a in (g.means, g.quats, g.scales, g.opacities)]
    for sampler, k in (("volume", 0), ("quantile", 8), ("topk", 6), ("stratified", 7)):
        for px in (None, pixels):
            params = [torch.from_numpy(a.copy()).requires_grad_(True) for a in geo + [feats]]
            img, alpha, _ = qr_cl.rasterize(*params, cam.viewmat, cam.K, W, H, sampler=sampler, k=max(k, 1),
                                            pixels=px, background=np.ones(19, np.float32))
            (img * torch.linspace(-1, 1, img.numel()).reshape(img.shape)).sum().backward()
            tag = f"{sampler}-{px is None}"
            out[tag + "-img"] = img.detach().numpy()
            out[tag + "-alpha"] = alpha.detach().numpy()
            for i, p in enumerate(params):
                out[f"{tag}-g{i}"] = p.grad.numpy()
    # cached renders, twice, with backward
    cache = SelectionCache(1 << 30)
    for rep in range(2):
        f = torch.from_numpy(feats.copy()).requires_grad_(True)
        img, _, _ = qr_cl.rasterize(*geo, f, cam.viewmat, cam.K, W, H, sampler="quantile", k=8, cache=cache)
        (img ** 2).sum().backward()
        out[f"cached{rep}-img"], out[f"cached{rep}-grad"] = img.detach().numpy(), f.grad.numpy()
    # gsplat call with SH and absgrad
    sh = rng.standard_normal((len(g), 16, 3)).astype(np.float32) * 0.3
    params = [torch.from_numpy(a.copy()).requires_grad_(True) for a in geo + [sh]]
    colors, _, meta = qr_cl.rasterization(*params, torch.from_numpy(cam.viewmat)[None], torch.from_numpy(cam.K)[None],
                                          W, H, sh_degree=3, render_mode="RGB+ED", absgrad=True, sampler="topk", k=5)
    meta["means2d"].retain_grad()
    (colors * torch.linspace(0, 1, colors.numel()).reshape(colors.shape)).sum().backward()
    out["gs-colors"] = colors.detach().numpy()
    for i, p in enumerate(params):
        out[f"gs-g{i}"] = p.grad.numpy()
    out["gs-absgrad"] = meta["means2d"].absgrad.numpy()
    img, _, meta = qr_cl.render_volume_fused(*geo, feats, cam.viewmat, cam.K, W, H)
    out["fused-img"], out["fused-depth"] = img.numpy(), np.asarray(meta["depth"])
    # training selections: gather, concat, compact, blend + backward with the transpose made ahead
    plan = rasterize_plan(*geo, cam.viewmat, cam.K, W, H)
    whole = select(plan, "quantile", 8)
    parts = [gather_rays(whole, rng.integers(0, W * H, 300)) for _ in range(2)]
    rows, (compact,) = compact_selections([concat_selections(parts)])
    index = prepare_backward(compact)            # None where an install's selections kept their own
    table = torch.from_numpy(feats[rows].copy()).requires_grad_(True)
    name = next(n for n in ("backward_index", "views") if n in inspect.signature(blend).parameters) \
        if index is not None else None         # the parameter's name in the install (views before)
    r = blend(compact, table) if index is None else blend(compact, table, **{name: index})
    (r * torch.linspace(-1, 1, r.numel()).reshape(r.shape)).sum().backward()
    out["train-img"], out["train-grad"] = r.detach().numpy(), table.grad.numpy()
    # registration: per picked Gaussian, its weight sums per mask (the transpose of a blend)
    ids, weights = top_contributors(plan, pixels, 5)
    masks = rng.integers(-1, 6, (len(pixels), 3))
    out["register-rows"], out["register-sums"] = mask_weight_sums(plan, pixels, ids, weights, masks, 6)
    out["launches"] = np.array(launched)
    return out


def differing(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> list[str]:
    """Names of the arrays only one side has, or whose dtype or bytes differ."""
    return sorted(set(a) ^ set(b)) + [k for k in sorted(set(a) & set(b))
                                      if a[k].dtype != b[k].dtype or a[k].tobytes() != b[k].tobytes()]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_base_option(ap, required=True)
    ap.add_argument("--worker", help=argparse.SUPPRESS)      # the npz file to write: render, save
    args = ap.parse_args()
    if args.worker:
        np.savez(args.worker, **outputs())
        return
    with installs(args.base) as runs_of, tempfile.TemporaryDirectory(prefix="qr-cl-ab-") as tmp:
        arrays = {}
        for install in runs_of:
            out = Path(tmp) / f"{install.label}.npz"
            proc = install.run([str(Path(__file__).resolve()), "--base", args.base, "--worker", str(out)],
                               capture_output=True, text=True, cwd=tmp)
            if proc.returncode:
                sys.exit(f"{install.label} run failed:\n{proc.stderr[-3000:]}")
            with np.load(out) as f:
                arrays[install.label] = {k: f[k] for k in f.files}
    bad = differing(arrays["base"], arrays["this"])
    print(f"{len(arrays['base'])} and {len(arrays['this'])} arrays ({len(arrays['this']['launches'])} kernel "
          f"launches); differing: {bad or 'none'}")
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
