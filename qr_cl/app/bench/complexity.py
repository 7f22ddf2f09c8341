"""The complexity sweep: select + blend time against the depth complexity N (C fixed) and against C
(N fixed) on layered scenes, and per sampler the fitted exponents of t ~ N^a and t ~ C^b and the
marginal cost of a channel (slope of t against C at N fixed), which the paper's complexities
predict to grow with N for V-Render and with K for top-K and Q-Render."""
from __future__ import annotations

import numpy as np

from ...runtime import SAMPLERS
from ..renderers import FUSED_NAME
from ..scenes.views import layered_view
from .jobs import Job

WIDTH, HEIGHT = 128, 96     # px of the layered scenes
K = 10                      # of the K samplers
C_FIXED = 64                # channels of the sweep over N


def n_fixed(sizes: dict) -> int:
    """The depth complexity of the sweep over C: the second largest of ``sizes["layers"]``."""
    return sizes["layers"][-2]


def complexity_jobs(sizes: dict) -> list[Job]:
    """Per (N, C) of the sweep, a layered scene of N Gaussians per ray: its plan, the fused
    V-Render and every sampler's selection and blend of C channels."""
    jobs = []
    pairs = [(n, C_FIXED) for n in sizes["layers"]] + [(n_fixed(sizes), c) for c in sizes["layer_cs"]]
    for depth, channels in pairs:
        scene = layered_view(depth, WIDTH, HEIGHT)
        jobs += [Job("plan", scene), Job("fused", scene, (channels,))]
        jobs += [Job("sampler", scene, (sampler, K, channels)) for sampler in SAMPLERS]
    return jobs


def complexity_fits(sizes: dict, done: list[tuple[Job, object]]) -> dict:
    """The report's complexity section from the :func:`complexity_jobs` of ``sizes`` and what each
    returned (``done``, in order): the points (renderer, N, C, seconds of select + blend, or of
    the fused V-Render) and the fits per renderer."""
    points = []
    for job, result in done:
        depth = len(job.scene.gaussians)
        if job.stage == "fused":
            points.append((FUSED_NAME, depth, job.args[0], result["min_s"]))
        elif job.stage == "sampler":
            selection, forward = result
            points.append((job.args[0], depth, job.args[2], selection["min_s"] + forward["min_s"]))
    fits = {}
    for sampler in (FUSED_NAME, *SAMPLERS):
        by_n = [(n, t) for s, n, c, t in points if s == sampler and c == C_FIXED]
        by_c = [(c, t) for s, n, c, t in points if s == sampler and n == n_fixed(sizes)]
        fits[sampler] = {"exponent_N": float(np.polyfit(*np.log(np.array(by_n)).T, 1)[0]),
                         "exponent_C": float(np.polyfit(*np.log(np.array(by_c)).T, 1)[0]),
                         "ms_per_channel": 1e3 * float(np.polyfit(*np.array(by_c).T, 1)[0])}
    return {"width": WIDTH, "height": HEIGHT, "k": K, "C_fixed": C_FIXED, "N_fixed": n_fixed(sizes),
            "points": [{"sampler": s, "N": n, "C": c, "seconds": t} for s, n, c, t in points],
            "fits": fits}
