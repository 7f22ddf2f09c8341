"""Every public path's outputs on a scene, to compare OpenCL implementations (the parity tests
and the GPU report): the same renders, written as float32 arrays by name, and the rule by which
two such sets agree.

:func:`render_all` renders rasterize with each sampler (image, alpha, feature gradient), a float16
table, a pixel subset, the SH colour kernel, render_volume_fused (image, alpha, depth) and
rasterization (image and gradients w.r.t. means, quats, scales, opacities and colours).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

#: The renders' image size (px), channels and K.
WIDTH, HEIGHT, CHANNELS, K = 160, 120, 64, 10
#: The scenes :func:`load_scene` knows: "random" (procedural), "fox" and "donut" (the real scenes
#: of a data folder) and "dense" (the procedural 300k-Gaussian room).
SCENES = ("random", "fox", "donut", "dense")
#: An output agrees when it is within RTOL of its largest value (HALF_RTOL for a float16 table's
#: gradient, rounded to float16: one float16 rounding apart where the float32 sums differ in their
#: last bit) in all but FLIPPED_ROWS of its rows (pixels, or Gaussians of a gradient): rays at a
#: threshold by float rounding (a K sampler's boundary, the 1/255 alpha cut, V-Render's stop) decide
#: differently under another compiler.
RTOL, HALF_RTOL, FLIPPED_ROWS = 1e-4, 1e-3, 1e-3


def load_scene(name: str, data: Path | None):
    """(Gaussians, Camera at WIDTH x HEIGHT) of scene ``name`` (:data:`SCENES`); the real ones from
    the folder ``data`` (as ../shared/data holds them)."""
    import qr_cl
    from ..scenes.procedural import dense_room, procedural_scene
    from ...scene import load_layout_instance
    if name == "random":
        g = procedural_scene(3000, seed=2)
        return g, qr_cl.orbit_cameras(g.means, 1, WIDTH, HEIGHT)[0]
    if name == "dense":
        g, cam = dense_room()
        return g, cam.resized(WIDTH, HEIGHT)
    if data is None:
        raise ValueError(f"scene {name!r} needs a data folder")
    if name == "fox":
        g = qr_cl.load_ply(data / "wakufactory-fox" / "fox.ply")
        return g, qr_cl.orbit_cameras(g.means, 1, WIDTH, HEIGHT, up_axis=1)[0]
    if name == "donut":
        layout = data / "v3dg-donut" / "_SingleDonut.json"
        g = qr_cl.load_ply(data / "v3dg-donut" / "donut_fused.ply").transformed(*load_layout_instance(layout))
        return g, qr_cl.load_cameras(layout)[0].resized(WIDTH, HEIGHT)
    raise ValueError(f"unknown scene {name!r}: use one of {SCENES}")


def render_all(g, cam) -> dict[str, np.ndarray]:
    """Every public path's outputs for one scene and camera (float32 arrays by name)."""
    import torch

    import qr_cl
    rng = np.random.default_rng(0)
    n = len(g.means)
    feats = rng.normal(size=(n, CHANNELS)).astype(np.float32)
    weights = torch.from_numpy(rng.normal(size=(HEIGHT, WIDTH, CHANNELS)).astype(np.float32))
    geometry = (g.means, g.quats, g.scales, g.opacities)
    view = (cam.viewmat, cam.K, WIDTH, HEIGHT)
    out = {}
    for sampler in ("volume", "quantile", "topk", "stratified"):
        f = torch.from_numpy(feats).requires_grad_(True)
        img, alpha, _ = qr_cl.rasterize(*geometry, f, *view, sampler=sampler, k=K)
        (img * weights).sum().backward()
        out.update({f"{sampler}/image": img.detach().numpy(), f"{sampler}/alpha": alpha.numpy(),
                    f"{sampler}/dfeatures": f.grad.numpy()})
    f = torch.from_numpy(feats).half().requires_grad_(True)                      # a float16 table
    img, _, _ = qr_cl.rasterize(*geometry, f, *view, sampler="quantile", k=K)
    (img * weights).sum().backward()
    out.update({"half/image": img.detach().numpy(), "half/dfeatures": f.grad.float().numpy()})
    pixels = np.stack([rng.integers(0, WIDTH, 700), rng.integers(0, HEIGHT, 700)], 1)
    f = torch.from_numpy(feats).requires_grad_(True)
    img, _, _ = qr_cl.rasterize(*geometry, f, *view, sampler="quantile", k=K, pixels=pixels)
    (img * weights[pixels[:, 1], pixels[:, 0]]).sum().backward()
    out.update({"pixels/image": img.detach().numpy(), "pixels/dfeatures": f.grad.numpy()})
    img, _, _ = qr_cl.rasterize(*geometry, g.sh, *view, sh_degree=g.sh_degree)
    out["sh/image"] = img.numpy()
    img, alpha, meta = qr_cl.render_volume_fused(*geometry, feats, *view)
    out.update({"fused/image": img.numpy(), "fused/alpha": alpha.numpy(), "fused/depth": meta["depth"]})
    colours = torch.from_numpy(rng.uniform(0, 1, (n, 3)).astype(np.float32))
    for sampler in ("volume", "quantile"):
        params = [torch.from_numpy(np.asarray(a, np.float32)).requires_grad_(True)
                  for a in (*geometry, colours)]
        img, _, _ = qr_cl.rasterization(*params, torch.from_numpy(cam.viewmat[None]).float(),
                                        torch.from_numpy(cam.K[None]).float(), WIDTH, HEIGHT, sampler=sampler, k=K)
        (img[0] * weights[..., :3]).sum().backward()
        out[f"rasterization-{sampler}/image"] = img.detach().numpy()
        for name, p in zip(("means", "quats", "scales", "opacities", "colors"), params):
            out[f"rasterization-{sampler}/d{name}"] = p.grad.numpy()
    return out


def render_scenes(scenes: list[str], data: Path | None) -> dict[str, np.ndarray]:
    """:func:`render_all` of each scene, keyed ``"<scene>:<output>"``."""
    results = {}
    for name in scenes:
        g, cam = load_scene(name, data)
        results.update({f"{name}:{k}": v for k, v in render_all(g, cam).items()})
    return results


#: Rows a carried reference keeps of each output: a fixed sample (the same rows of the outputs
#: compared with it), so that PoCL's results of the four scenes travel in a few MB.
REFERENCE_ROWS = 1024


def sample_rows(outputs: dict[str, np.ndarray], rows: int = REFERENCE_ROWS) -> dict[str, np.ndarray]:
    """Each output as its rows [R, last dim] (:func:`differences`' rows), the outputs of more than
    ``rows`` rows cut to a fixed sample of ``rows`` of them (seeded by the row count)."""
    out = {}
    for key, a in outputs.items():
        flat = a.reshape(-1, a.shape[-1]) if a.ndim > 1 else a.reshape(-1, 1)
        if len(flat) > rows:
            flat = flat[np.sort(np.random.default_rng(len(flat)).choice(len(flat), rows, replace=False))]
        out[key] = np.ascontiguousarray(flat)
    return out


def differences(got: dict, want: dict) -> dict[str, tuple[float, int, int]]:
    """Per output of ``want``: (largest error over want's largest value, rows off by more than the
    tolerance, rows); outputs missing from ``got`` count as wholly off."""
    out = {}
    for key, ref in want.items():
        rows = ref.reshape(-1, ref.shape[-1]) if ref.ndim > 1 else ref.reshape(-1, 1)
        if key not in got or got[key].shape != ref.shape:
            out[key] = (float("inf"), len(rows), len(rows))
            continue
        scale = max(float(np.abs(ref).max(initial=0)), 1e-30)
        err = np.abs(got[key] - ref)
        off = (err > (HALF_RTOL if "half/" in key else RTOL) * scale).reshape(len(rows), -1).any(1)
        out[key] = (float(err.max(initial=0)) / scale, int(off.sum()), len(rows))
    return out


def compare(got: dict, want: dict) -> list[str]:
    """The outputs of ``got`` that do not agree with ``want``'s (see :data:`FLIPPED_ROWS`), as
    lines "key: error in rows of rows"."""
    return [f"{key}: {err:.2e} in {off} of {rows} rows" for key, (err, off, rows) in sorted(differences(got, want).items())
            if off > int(FLIPPED_ROWS * rows)]
