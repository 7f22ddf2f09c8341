"""The feature backward against the forward on the dense room, for one install or two back to back.

The 300k-Gaussian dense room (:func:`qr_cl.app.scenes.procedural.dense_room`), 640x480, 512-D
float32 features, Q-Render K=40 and K=10, at the stage level: forward = the selection kernel
plus the blend (``select`` then ``blend_forward``), backward = the feature gradient of the whole
image (``blend_backward``: the deterministic scatter on CPU shapes). The issue's target is
backward <= 1.5x forward. With ``--base PYTHON_OR_CHECKOUT`` (see bench/ab.py) the same
measurement runs first under another install (e.g. the previous release), each run in a fresh
process::

    python bench/backward_ratio.py --base <old-checkout> --rounds 3

Prints one table: minimum ms over rounds of each part and the ratio backward / forward.
"""
from __future__ import annotations

import time

from ab import ab_arguments, ab_parse, ab_rounds, installs

WIDTH, HEIGHT, CHANNELS, DENSE_N = 640, 480, 512, 300_000
KS = (40, 10)


def measure_install(args) -> dict:
    """{K: {part: [s...]}} of ``args.calls`` timed calls, in this process (the install it imports)."""
    import numpy as np
    import pyopencl.array as cla

    from qr_cl.app.process import cap_kernel_threads
    cap_kernel_threads()
    from qr_cl.app.scenes.procedural import dense_room
    from qr_cl.render import checked_runtime, rasterize_plan
    from qr_cl.runtime import channel_layout, padded_rows, to_device
    from qr_cl.stages import blend_backward, blend_forward, select

    rt = checked_runtime()
    g, cam = dense_room(DENSE_N, width=WIDTH, height=HEIGHT)
    plan = rasterize_plan(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, WIDTH, HEIGHT)
    cstride = channel_layout(CHANNELS)[2]
    rng = np.random.default_rng(0)
    feats = to_device(rt, padded_rows(rng.random((len(g.means), CHANNELS), dtype=np.float32), cstride))
    dimage = to_device(rt, padded_rows(rng.random((WIDTH * HEIGHT, CHANNELS), dtype=np.float32), cstride))
    image = cla.empty(rt.queue, (WIDTH * HEIGHT, cstride), np.float32)

    def timed(fn) -> float:
        start = time.perf_counter()
        fn()
        rt.queue.finish()
        return time.perf_counter() - start
    out = {}
    for k in KS:
        parts = {"select": [], "blend": [], "backward": []}
        for call in range(args.calls + 1):                       # the first call warms up
            holder = {}
            t_sel = timed(lambda: holder.setdefault("sel", select(plan, "quantile", k)))
            sel = holder["sel"]
            t_blend = timed(lambda: blend_forward(sel, feats, CHANNELS, out=image))
            t_back = timed(lambda: blend_backward(sel, dimage, CHANNELS))
            if call:
                for name, t in zip(parts, (t_sel, t_blend, t_back)):
                    parts[name].append(t)
        out[k] = parts
    return out


def main() -> None:
    args = ab_parse(ab_arguments(__doc__.splitlines()[0], rounds=3, calls=3, base_required=False,
                                 calls_help="timed calls per run and K"), measure_install)
    if args is None:
        return
    with installs(args.base) as runs_of:
        runs = ab_rounds(__file__, runs_of, args.rounds, args.calls, lambda run: ", ".join(
            f"K={k} backward {min(parts['backward']) * 1e3:.0f} ms" for k, parts in run.items()))
    best = {(name, int(k), part): min(min(run[k][part]) for run in label_runs)      # JSON keys: str(K)
            for name, label_runs in runs.items() for k in label_runs[0] for part in label_runs[0][k]}
    print("| build | K | select ms | blend ms | forward ms | backward ms | backward / forward |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for name in runs:
        for k in KS:
            sel, blend, back = (1e3 * best[name, k, p] for p in ("select", "blend", "backward"))
            print(f"| {name} | {k} | {sel:.1f} | {blend:.1f} | {sel + blend:.1f} | {back:.1f} | {back / (sel + blend):.2f} |")


if __name__ == "__main__":
    main()
