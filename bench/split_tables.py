"""A feature table over the device's largest buffer: this checkout against another install, back to back.

The 300k-Gaussian dense room (:func:`qr_cl.app.scenes.procedural.dense_room`), a 512-D float32
table (614 MB, in torch's memory) and the device's largest buffer forced to a third of it
(``Runtime.max_buffer_bytes``), so that the table must be split while the image still fits one
buffer (hence 320x240: at 3M Gaussians and PoCL's 4 GiB a 640x480 image fits too). Per install,
in fresh processes: Q-Render K=40 through ``qr_cl.rasterize`` with the limit (``split``) and
without it (``whole``), the minimum over the calls, and the bytes a split call copies out of the
table (the padded host rows made by ``qr_cl.runtime.memory.device_rows``: where an install with
channel groups copies each group's columns, and row parts would copy a part they cannot read in
place)::

    python bench/split_tables.py --base PYTHON_OR_CHECKOUT --rounds 3     # --base: see bench/ab.py

Prints a table and the ratio of the base's split call to this checkout's. Timings are the
machine's of the moment; keep a report only with the machine named.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from ab import ab_arguments, ab_parse, ab_rounds, installs
from benchutil import timing

WIDTH, HEIGHT, CHANNELS, DENSE_N, K = 320, 240, 512, 300_000, 40


def make_scene(out: Path) -> None:
    """Write the dense room's Gaussians and camera to ``out`` (npz)."""
    from qr_cl.app.scenes.procedural import dense_room
    g, cam = dense_room(DENSE_N, width=WIDTH, height=HEIGHT)
    np.savez(out, means=g.means, quats=g.quats, scales=g.scales, opacities=g.opacities, viewmat=cam.viewmat, K=cam.K)


def measure_install(args) -> dict:
    """{"whole_s", "split_s", "copied_bytes", "table_bytes"} for the qr_cl this interpreter imports:
    the scene of ``args.inputs``, ``args.calls`` timed calls of each."""
    import torch

    import qr_cl
    from qr_cl.runtime import Runtime, memory
    torch.set_num_threads(1)
    a, calls = np.load(args.inputs), args.calls
    geo = [np.ascontiguousarray(a[k], np.float32) for k in ("means", "quats", "scales", "opacities")]
    table = torch.empty(len(geo[0]), CHANNELS).copy_(
        torch.from_numpy(np.random.default_rng(0).random((len(geo[0]), CHANNELS), dtype=np.float32)))
    table_bytes = table.numel() * table.element_size()

    def render():
        return qr_cl.rasterize(*geo, table, a["viewmat"], a["K"], WIDTH, HEIGHT, sampler="quantile", k=K)[0]

    copied = []
    padded = memory.host_empty                            # device_rows' copies of rows it cannot read in place

    def counting(shape, dtype=np.float32):
        out = padded(shape, dtype)
        copied.append(out.nbytes)
        return out
    result = {"table_bytes": table_bytes}
    for name in ("whole", "split"):
        if name == "split":
            Runtime.max_buffer_bytes = property(lambda self: table_bytes // 3)
        kept = [render()]                                 # warm-up; results stay alive as in a render loop

        def keep() -> None:
            kept[0] = render()
        result[f"{name}_s"] = min(timing.timed_calls(keep, calls)[0])
        memory.host_empty, copied[:] = counting, []
        keep()
        memory.host_empty = padded
        result[f"{name}_copied_bytes"] = sum(copied)
    return result


def main() -> None:
    ap = ab_arguments(__doc__.splitlines()[0], rounds=3, calls=3)
    args = ab_parse(ap, measure_install)
    if args is None:
        return
    with tempfile.TemporaryDirectory() as tmp:
        scene_file = Path(tmp) / "scene.npz"
        make_scene(scene_file)
        with installs(args.base) as runs_of:
            runs = ab_rounds(__file__, runs_of, args.rounds, args.calls, lambda run: (
                f"whole {run['whole_s'] * 1e3:.0f} ms, split {run['split_s'] * 1e3:.0f} ms, "
                f"copied {run['split_copied_bytes'] / 1e6:.0f} MB"), inputs=scene_file)
    best = {(label, key): min(r[key] for r in rs) for label, rs in runs.items() for key in ("whole_s", "split_s")}
    table_mb = runs["this"][0]["table_bytes"] / 1e6
    print(f"\nbase = {args.base}; dense room {DENSE_N // 1000}k, {WIDTH}x{HEIGHT}, C={CHANNELS} float32 "
          f"({table_mb:.0f} MB), Q-Render K={K}, largest buffer forced to a third of the table; "
          f"minimum ms over {args.rounds} runs x {args.calls} calls\n")
    print("| install | whole ms | split ms | split / whole | MB copied per split call |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for label in ("base", "this"):
        whole, split = best[label, "whole_s"] * 1e3, best[label, "split_s"] * 1e3
        print(f"| {label} | {whole:.0f} | {split:.0f} | {split / whole:.2f}x | "
              f"{runs[label][-1]['split_copied_bytes'] / 1e6:.0f} |")
    print(f"\nsplit call, base / this: {best['base', 'split_s'] / best['this', 'split_s']:.2f}x")


if __name__ == "__main__":
    main()
