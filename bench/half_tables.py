"""float16 against float32 feature tables, timed back to back in one process.

On the 300k-Gaussian dense room (:func:`qr_cl.app.scenes.procedural.dense_room`) and, with
``--data``, the real fox, 640x480, 512-D features, Q-Render K=40 and K=10, each path timed for a
float32 table and for its float16 rounding, alternating within every round:

* ``blend``: ``qr_cl.rasterize`` with a warm :class:`qr_cl.render.SelectionCache` (the selection
  is reused, so the call is the blend of the table: what the half rows change);
* ``render``: the uncached call (plan, selection with the blend fused in);
* ``backward``: the feature gradient of the cached call alone (``torch.autograd.grad``; a float16
  table's gradient is summed in float32 and returned as float16).

Also the image's largest error against the float32 table's, relative to its largest value, and
the tables' sizes. Writes ``half.json`` and ``half.md`` into ``--out``::

    python bench/half_tables.py --data ../shared/data --rounds 5 --out bench/reports/half-tables-<machine>
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from benchutil import fox_and_dense_room

WIDTH, HEIGHT, CHANNELS, DENSE_N = 640, 480, 512, 300_000
PATHS = ("blend", "render", "backward")
DTYPES = {"float32": torch.float32, "float16": torch.float16}


def measure(g, cam, k: int, rounds: int) -> dict:
    """Minimum seconds per (path, dtype) over ``rounds`` alternating rounds, and the error."""
    import qr_cl
    from qr_cl.render import SelectionCache
    geometry = (g.means, g.quats, g.scales, g.opacities)
    table = torch.from_numpy(np.random.default_rng(0).normal(size=(len(g.means), CHANNELS)).astype(np.float32))
    table /= table.norm(dim=1, keepdim=True)                      # unit rows, as GS-Net's output
    tables = {"float32": table, "float16": table.half()}
    caches = {name: SelectionCache(2 << 30) for name in DTYPES}

    d_image = torch.ones(HEIGHT, WIDTH, CHANNELS)                  # made once: not part of any timing

    def call(name: str, cache=None, grad: bool = False):
        f = tables[name].requires_grad_(grad)
        image, _, _ = qr_cl.rasterize(*geometry, f, cam.viewmat, cam.K, WIDTH, HEIGHT, sampler="quantile", k=k,
                                      cache=cache)
        return image

    def backward_seconds(name: str) -> float:
        image = call(name, caches[name], grad=True)
        start = time.perf_counter()
        torch.autograd.grad(image, tables[name], d_image)
        return time.perf_counter() - start

    def timed(fn) -> float:
        start = time.perf_counter()
        fn()
        return time.perf_counter() - start

    images = {name: call(name, caches[name]) for name in DTYPES}          # warm-up, and the caches
    scale = float(images["float32"].abs().max())
    error = float((images["float16"] - images["float32"]).abs().max()) / scale
    best = {(path, name): float("inf") for path in PATHS for name in DTYPES}
    for _ in range(rounds):
        for name in DTYPES:
            best["blend", name] = min(best["blend", name], timed(lambda: call(name, caches[name])))
            best["render", name] = min(best["render", name], timed(lambda: call(name)))
            best["backward", name] = min(best["backward", name], backward_seconds(name))
    return {"k": k, "error": error, "ms": {f"{p}/{n}": 1e3 * s for (p, n), s in best.items()},
            "table_bytes": {name: t.numel() * t.element_size() for name, t in tables.items()}}


def markdown(rows: list[dict]) -> str:
    lines = [f"# float16 against float32 feature tables ({WIDTH}x{HEIGHT}, C={CHANNELS}, Q-Render)", "",
             "Minimum wall ms over alternating rounds in one process. blend: the call with a warm selection "
             "cache; render: the uncached call; backward: the feature gradient of the cached call alone. error: the float16 table's image against the float32 one's, largest absolute "
             "difference over the largest value.", "",
             "| scene | K | path | float32 ms | float16 ms | float32 / float16 |", "| --- | ---: | --- | ---: | ---: | ---: |"]
    for r in rows:
        for p in PATHS:
            f32, f16 = r["ms"][f"{p}/float32"], r["ms"][f"{p}/float16"]
            lines.append(f"| {r['scene']} | {r['k']} | {p} | {f32:.1f} | {f16:.1f} | {f32 / f16:.2f} |")
    lines += ["", "| scene | table float32 MB | table float16 MB | image error (K=40) |", "| --- | ---: | ---: | ---: |"]
    for r in rows:
        if r["k"] == max(x["k"] for x in rows):
            b = r["table_bytes"]
            lines.append(f"| {r['scene']} | {b['float32'] / 1e6:.0f} | {b['float16'] / 1e6:.0f} | {r['error']:.1e} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="../shared/data (adds the fox)")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    from qr_cl.app.process import cap_kernel_threads
    cap_kernel_threads()
    rows = []
    for name, (g, cam) in fox_and_dense_room(args.data, WIDTH, HEIGHT, DENSE_N).items():
        for k in (40, 10):
            rows.append({"scene": name, **measure(g, cam, k, args.rounds)})
            print(name, k, {key: round(v, 1) for key, v in rows[-1]["ms"].items()}, flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "half.json").write_text(json.dumps(rows, indent=1))
    (args.out / "half.md").write_text(markdown(rows))
    print(markdown(rows))


if __name__ == "__main__":
    main()
