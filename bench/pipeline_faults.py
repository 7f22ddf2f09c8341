"""Page faults and wall time of the public render and training calls, cold and warm.

Counts first: minor page faults (``ru_minflt`` of ``getrusage``) per call, which are what a fresh
large allocation costs on every call (glibc hands allocations above 32 MB to mmap, so each one is
faulted in again), then wall times. Scene: the procedural 50k-Gaussian scene, 640x480, orbit view 1.

* render: whole-image Q-Render (``sampler="quantile"``, K=40) of 512-D features, 1 cold + N warm.
* train: 4 views x 2048 random pixels (``pixels=``), forward and backward w.r.t. the [N, 512]
  features (``requires_grad``), gradients set to None between steps; 1 cold + N warm steps.

Runs against whichever ``qr_cl`` the interpreter imports (this checkout, or an older installed
release: only ``qr_cl.rasterize``, ``qr_cl.orbit_cameras`` and the procedural scene are used)::

    python bench/pipeline_faults.py                       # both paths, this checkout
    perf stat -e page-faults,task-clock python bench/pipeline_faults.py --what render --calls 5
    python bench/pipeline_faults.py --base PYTHON_OR_CHECKOUT --rounds 3

``--base`` (see bench/ab.py) runs the measurement under the other install and this checkout
alternately, ``--rounds`` times each (back to back), and prints the per-warm-call minima of both
and their ratio.
"""
from __future__ import annotations

import statistics

from ab import ab_arguments, ab_parse, ab_rounds, installs
from benchutil import timing

WIDTH, HEIGHT, N_GAUSSIANS, CHANNELS, K = 640, 480, 50_000, 512, 40
VIEWS, PIXELS = 4, 2048


def scene():
    import numpy as np

    import qr_cl
    try:
        from qr_cl.app.scenes.procedural import procedural_scene
    except ImportError:
        try:
            from qr_cl.app.procedural import procedural_scene
        except ImportError:                      # releases before the layered package
            from qr_cl.procedural import procedural_scene
    g = procedural_scene(N_GAUSSIANS)
    cams = qr_cl.orbit_cameras(g.means, 8, WIDTH, HEIGHT)
    geo = tuple(np.ascontiguousarray(a, np.float32) for a in (g.means, g.quats, g.scales, g.opacities))
    return qr_cl, geo, cams


def cold_and_warm(call, warm: int) -> dict:
    """Cold call, then ``warm`` calls: wall seconds and minor page faults of each."""
    times, faults = timing.timed_calls(call, 1 + warm)
    w_t, w_f = times[1:] or times, faults[1:] or faults
    return {"cold_s": times[0], "cold_faults": faults[0], "warm_min_s": min(w_t),
            "warm_median_s": statistics.median(w_t), "warm_faults_per_call": statistics.mean(w_f),
            "warm_faults": w_f, "warm_s": w_t}


def run(what: str, warm: int) -> dict:
    import numpy as np
    import torch
    torch.set_num_threads(1)
    qr_cl, geo, cams = scene()
    rng = np.random.default_rng(0)
    feats = torch.from_numpy(rng.standard_normal((len(geo[0]), CHANNELS), dtype=np.float32))
    out = {}
    if what in ("render", "both"):
        cam = cams[1]
        state = {}

        def render():
            # the previous result stays alive during the call, as in `for ...: img = render()`
            state["img"] = qr_cl.rasterize(*geo, feats, cam.viewmat, cam.K, WIDTH, HEIGHT,
                                           sampler="quantile", k=K)[0]
        out["render"] = cold_and_warm(render, warm)
        assert tuple(state["img"].shape) == (HEIGHT, WIDTH, CHANNELS)
    if what in ("train", "both"):
        leaf = feats.clone().requires_grad_(True)
        pix = [np.c_[rng.integers(0, WIDTH, PIXELS), rng.integers(0, HEIGHT, PIXELS)] for _ in range(VIEWS)]
        targets = [torch.from_numpy(rng.standard_normal((PIXELS, CHANNELS), dtype=np.float32))
                   for _ in range(VIEWS)]

        def step():
            leaf.grad = None
            loss = 0
            for cam, p, t in zip(cams[:VIEWS], pix, targets):
                img = qr_cl.rasterize(*geo, leaf, cam.viewmat, cam.K, WIDTH, HEIGHT,
                                      sampler="quantile", k=K, pixels=p)[0]
                loss = loss + (img * t).sum()
            loss.backward()
            assert leaf.grad is not None and leaf.grad.shape == leaf.shape
        out["train"] = cold_and_warm(step, warm)
    return out


def measure_install(args) -> dict:
    """:func:`run` of ``args.what`` with ``args.calls`` warm calls (the worker of an A/B run)."""
    return run(args.what, args.calls)


def compare(args) -> None:
    """Alternate runs of the ``--base`` install and this checkout; print minima and ratios."""
    with installs(args.base) as runs_of:
        results = ab_rounds(__file__, runs_of, args.rounds, args.calls, lambda run: ", ".join(
            f"{k} {v['warm_min_s'] * 1e3:.0f} ms {v['warm_faults_per_call']:.0f} faults" for k, v in run.items()),
            worker_args=("--what", args.what))
    print(f"\nper warm call, min over {args.rounds} rounds x {args.calls} warm calls (base = {args.base}):")
    print("| path | base ms | this ms | this / base | base faults | this faults |")
    print("| --- | --- | --- | --- | --- | --- |")
    for path in results["this"][0]:
        b = min(x[path]["warm_min_s"] for x in results["base"])
        t = min(x[path]["warm_min_s"] for x in results["this"])
        bf = min(x[path]["warm_faults_per_call"] for x in results["base"])
        tf = min(x[path]["warm_faults_per_call"] for x in results["this"])
        print(f"| {path} | {b * 1e3:.1f} | {t * 1e3:.1f} | {t / b:.2f} | {bf:.0f} | {tf:.0f} |")


def main() -> None:
    ap = ab_arguments(__doc__.splitlines()[0], rounds=3, calls=4, base_required=False,
                      calls_help="warm calls after the cold one")
    ap.add_argument("--what", choices=["render", "train", "both"], default="both")
    args = ab_parse(ap, measure_install)
    if args is None:
        return
    if args.base:
        compare(args)
        return
    for path, r in run(args.what, args.calls).items():
        print(f"{path}: cold {r['cold_s'] * 1e3:.0f} ms / {r['cold_faults']} faults; warm min "
              f"{r['warm_min_s'] * 1e3:.0f} ms, median {r['warm_median_s'] * 1e3:.0f} ms, "
              f"{r['warm_faults_per_call']:.0f} faults per call {r['warm_faults']}")


if __name__ == "__main__":
    main()
