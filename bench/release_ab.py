"""This checkout against another install of qr-cl (e.g. an earlier release in its own venv), back to back.

The renderer's headline figures, on the real fox (50k Gaussians; with ``--data``) and the
300k-Gaussian dense room (``qr_cl.app.scenes.procedural.dense_room``), 640x480, each public call timed
from its arguments to the image (plan included):

* ``walk``: the fused V-Render of 3 channels (the tile walk, almost no blending);
* ``fused``: the fused V-Render of 512 channels;
* ``q40`` / ``q10``: Q-Render (``rasterize(..., sampler="quantile", k=K)``) of 512 channels;
* ``train``: 4 renders of 2048 random rays (Q-Render K=40, 512-D features that require grad) and
  the backward of their sum of squares;
* minor page faults (``ru_minflt``) of a warm ``q40`` call.

The scenes and cameras are made once by this checkout and handed to both installs as arrays, so
both render the same Gaussians. Only public names are used (``qr_cl.rasterize``, and
``qr_cl.render_volume_fused`` or, in releases before it, ``sampler="volume_fused"``)::

    python bench/release_ab.py --base <old-checkout> --data DATA --rounds 2
    python bench/release_ab.py --base <venv of an earlier release>/bin/python --data DATA

(``--base``: see bench/ab.py.)
Each round runs the base, then this checkout, in fresh processes; the table gives the minimum
over rounds and calls of each, the speed-up, and each build's fused V-Render over its Q-Render.
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from ab import ab_arguments, ab_parse, ab_rounds, installs
from benchutil import fox_and_dense_room, timing

WIDTH, HEIGHT, CHANNELS, DENSE_N = 640, 480, 512, 300_000
VIEWS, RAYS = 4, 2048
PATHS = ("walk", "fused", "q40", "q10", "train")


def make_scenes(data: Path | None, out: Path) -> list[str]:
    """Write the scenes' Gaussians and cameras to ``out`` (npz, keys ``<scene>/<array>``); their names."""
    scenes = fox_and_dense_room(data, WIDTH, HEIGHT, DENSE_N)
    arrays = {}
    for name, (g, cam) in scenes.items():
        for key in ("means", "quats", "scales", "opacities"):
            arrays[f"{name}/{key}"] = np.ascontiguousarray(getattr(g, key), np.float32)
        arrays[f"{name}/viewmat"] = np.asarray(cam.viewmat, np.float32)
        arrays[f"{name}/K"] = np.asarray(cam.K, np.float32)
    np.savez(out, **arrays)
    return list(scenes)


def measure_install(args) -> dict:
    """{scene: {path: {"min_s", "faults"}}} for the qr_cl this interpreter imports: the scenes of
    ``args.inputs``, ``args.calls`` timed calls of each path."""
    import torch
    import qr_cl
    torch.set_num_threads(1)
    fused = getattr(qr_cl, "render_volume_fused", None) or (
        lambda *a: qr_cl.rasterize(*a, sampler="volume_fused"))
    arrays, calls = np.load(args.inputs), args.calls
    names = sorted({k.split("/")[0] for k in arrays.files})
    rng = np.random.default_rng(0)
    results = {}
    for name in names:
        geo = [arrays[f"{name}/{k}"] for k in ("means", "quats", "scales", "opacities")]
        cam = (arrays[f"{name}/viewmat"], arrays[f"{name}/K"], WIDTH, HEIGHT)
        # in torch's own memory (rows on 64-byte lines), as GS-Net's features are
        feats = torch.empty(len(geo[0]), CHANNELS).copy_(
            torch.from_numpy(rng.random((len(geo[0]), CHANNELS), dtype=np.float32)))
        leaf = feats.clone().requires_grad_(True)
        pixels = [rng.integers(0, (WIDTH, HEIGHT), (RAYS, 2)) for _ in range(VIEWS)]

        def train():
            leaf.grad = None
            images = [qr_cl.rasterize(*geo, leaf, *cam, sampler="quantile", k=40, pixels=p)[0] for p in pixels]
            torch.cat(images).square().sum().backward()

        calls_of = {"walk": lambda: fused(*geo, feats[:, :3].contiguous(), *cam),
                    "fused": lambda: fused(*geo, feats, *cam),
                    "q40": lambda: qr_cl.rasterize(*geo, feats, *cam, sampler="quantile", k=40),
                    "q10": lambda: qr_cl.rasterize(*geo, feats, *cam, sampler="quantile", k=10),
                    "train": train}
        results[name] = {}
        for path in PATHS:
            call, kept, cpu = calls_of[path], [], []
            kept.append(call())                  # warm-up; results stay alive as in a render loop

            def keep(call=call, kept=kept, cpu=cpu) -> None:
                start = time.process_time()
                kept[0] = call()
                cpu.append(time.process_time() - start)
            times, faults = timing.timed_calls(keep, calls)
            results[name][path] = {"min_s": min(times), "cpu_s": min(cpu), "faults": min(faults)}
    return results


def table(base: list[dict], this: list[dict], base_name: str) -> str:
    """Markdown: minima over the runs of both installs (wall and CPU time: the process's, PoCL's
    threads included, which other processes on the machine inflate less than the wall time),
    speed-ups and fused / Q-Render ratios."""
    lines = [f"base = {base_name}; ms are minima over {len(this)} runs of each install", "",
             "| scene | path | base ms | this ms | base / this | base CPU ms | this CPU ms | base / this (CPU) |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    best = {}
    for label, runs in (("base", base), ("this", this)):
        for scene in runs[0]:
            for path in PATHS:
                best[label, scene, path] = min(r[scene][path]["min_s"] for r in runs) * 1e3
                best[label, scene, path, "cpu"] = min(r[scene][path].get("cpu_s", float("nan")) for r in runs) * 1e3
                best[label, scene, "faults"] = min(r[scene]["q40"]["faults"] for r in runs)
    scenes = list(this[0])
    for scene in scenes:
        for path in PATHS:
            b, t = best["base", scene, path], best["this", scene, path]
            bc, tc = best["base", scene, path, "cpu"], best["this", scene, path, "cpu"]
            lines.append(f"| {scene} | {path} | {b:.1f} | {t:.1f} | {b / t:.2f}x | {bc:.1f} | {tc:.1f} | {bc / tc:.2f}x |")
    lines += ["", "| scene | install | fused / q40 | fused / q10 | page faults per warm q40 |",
              "| --- | --- | ---: | ---: | ---: |"]
    for scene in scenes:
        for label in ("base", "this"):
            fused = best[label, scene, "fused"]
            lines.append(f"| {scene} | {label} | {fused / best[label, scene, 'q40']:.2f}x | "
                         f"{fused / best[label, scene, 'q10']:.2f}x | {best[label, scene, 'faults']} |")
    return "\n".join(lines)


def main() -> None:
    ap = ab_arguments(__doc__.splitlines()[0], rounds=2, calls=2)
    ap.add_argument("--data", type=Path, help="folder with wakufactory-fox/fox.ply (else the dense room alone)")
    args = ab_parse(ap, measure_install)
    if args is None:
        return
    with tempfile.TemporaryDirectory() as tmp:
        scenes_file = Path(tmp) / "scenes.npz"
        print("scenes:", ", ".join(make_scenes(args.data, scenes_file)), flush=True)
        with installs(args.base) as runs_of:
            runs = ab_rounds(__file__, runs_of, args.rounds, args.calls, lambda run: "; ".join(
                f"{s} " + " ".join(f"{p} {v['min_s'] * 1e3:.0f}" for p, v in paths.items()) for s, paths in run.items()),
                inputs=scenes_file)
    print()
    print(table(runs["base"], runs["this"], args.base))


if __name__ == "__main__":
    main()
