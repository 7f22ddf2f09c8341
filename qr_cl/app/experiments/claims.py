"""The paper's numbers and claims, judged on a reproduction's runs over seeds (and the look-ups of
those results the report shares).

Every training run of a plan is repeated with ``plan.seeds`` seeds; a quantity is its mean and
standard deviation over them (:class:`Stat`). A seed gives every run the same network
initialisation, rays and scene order, so two runs of one seed differ by their renderer (or
training rooms) alone: a claim "a >= b + margin" is judged on the paired differences a_s - b_s
over the seeds (:func:`difference`; a quantity without seeds, Dr.Splat's registration, is
subtracted from every seed). It is **reproduced** when the difference's band (mean +- std) lies
wholly above the margin, **not reproduced** when wholly below, **undecided** when the margin
falls inside it, and **not measured** when a run it needs is missing. So the seeds resolve a
difference only where it is farther from the margin than its own standard deviation: every claim
states that resolution (:func:`resolution`), which an undecided claim lacks.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from .plan import NOISE_K

#: The paper's numbers (ScanNet, MinkUNet; Fig. 4 and the noise table), mIoU in %.
PAPER = {"volume": 49.02, "topk": {5: 37.84, 10: 40.22, 20: 43.59, 40: 45.70, 50: 44.93},
         "quantile": {5: 49.98, 10: 50.75, 20: 50.65, 40: 50.85, 50: 50.28},
         "noise": {0.0: 50.75, 0.25: 50.13, 0.5: 50.18, 1.0: 47.13, 2.0: 38.13, 4.0: 16.12}}

VERDICTS = ("reproduced", "not reproduced", "undecided", "not measured")


@dataclass(frozen=True)
class Stat:
    """Mean and (sample) standard deviation of a quantity over ``n`` seeds (std 0 for one seed,
    which prints as its value alone)."""

    mean: float
    std: float
    n: int

    @classmethod
    def of(cls, values) -> Stat:
        values = [float(v) for v in values]
        mean = sum(values) / len(values)
        var = sum((v - mean) ** 2 for v in values) / (len(values) - 1) if len(values) > 1 else 0.0
        return cls(mean, math.sqrt(var), len(values))

    def __str__(self) -> str:
        return f"{self.mean:.1f}" if self.n == 1 else f"{self.mean:.1f} ± {self.std:.1f}"


def runs_of(results: dict, sampler: str, k: int = 0, noise: float = 0.0) -> list[dict]:
    """The runs of one renderer, K and noise scale, one per seed."""
    return [r for r in results["runs"] if r["sampler"] == sampler and r["k"] == k and r["noise"] == noise]


def metric(results: dict, sampler: str, k: int = 0, noise: float = 0.0, key: str = "miou19") -> Stat | None:
    """``key`` of the runs of (``sampler``, ``k``, ``noise``) over their seeds; None without runs."""
    runs = runs_of(results, sampler, k, noise)
    return Stat.of(r[key] for r in runs) if runs else None


def clean_renderers(results: dict) -> list[tuple[str, int, str]]:
    """(sampler, k, label) of each distinct run without opacity noise, in the plan's order."""
    seen = {}
    for r in results["runs"]:
        if not r["noise"]:
            seen.setdefault((r["sampler"], r["k"]), r["label"])
    return [(*key, label) for key, label in seen.items()]


def stat_cell(stat: Stat | None) -> str:
    """A table cell of ``stat`` ("mean ± std"), "-" when missing or NaN."""
    return "-" if stat is None or math.isnan(stat.mean) else str(stat)


def render_ms(results: dict, sampler: str, k: int = 0) -> float | None:
    row = next((t for t in results["render_ms"] if t["sampler"] == sampler and t["k"] == k), None)
    return None if row is None else row["ms"]


def cosine_to_volume(results: dict, sampler: str, k: int = 0) -> float | None:
    row = next((a for a in results["agreement"] if a["sampler"] == sampler and a["k"] == k), None)
    return None if row is None else row["cosine"]


def entry_seed(entry: dict) -> int | None:
    """The training seed of a result entry (``train_seed``, else the run's ``seed`` offset; None
    for an entry without one)."""
    return entry.get("train_seed", entry.get("seed"))


def difference(a: list[dict] | None, b: list[dict] | None, key: str = "miou19") -> Stat | None:
    """``key`` of the entries ``a`` minus those of ``b``, paired by training seed over the seeds
    both have; a side with one entry (no seeds: Dr.Splat's registration) is subtracted from, or
    from, every entry of the other. None when a side is missing or no seed pairs."""
    if not a or not b:
        return None
    va, vb = {entry_seed(e): e[key] for e in a}, {entry_seed(e): e[key] for e in b}
    if len(vb) == 1 and len(va) > 1:
        diffs = [x - next(iter(vb.values())) for x in va.values()]
    elif len(va) == 1 and len(vb) > 1:
        diffs = [next(iter(va.values())) - y for y in vb.values()]
    else:
        diffs = [va[seed] - vb[seed] for seed in va if seed in vb]
    return Stat.of(diffs) if diffs else None


def exceeds(d: Stat | None, margin: float = 0.0) -> str:
    """The verdict on "a >= b + margin" from the paired difference ``d`` = a - b (module docstring)."""
    if d is None:
        return "not measured"
    if d.mean - d.std > margin:
        return "reproduced"
    if d.mean + d.std < margin:
        return "not reproduced"
    return "undecided"


def negated(d: Stat | None) -> Stat | None:
    """b - a from a - b."""
    return None if d is None else Stat(-d.mean, d.std, d.n)


def resolution(*ds: Stat | None) -> str:
    """How far from its margin a claim's difference must lie for its seeds to decide it: the
    largest standard deviation of its paired differences ``ds`` ("-" when one is missing)."""
    if not ds or any(d is None for d in ds):
        return "-"
    return f"±{max(d.std for d in ds):.1f} points"


def delta(d: Stat | None) -> str:
    """The paired difference as the reports print it."""
    return "-" if d is None else f"Δ {d.mean:+.1f} ± {d.std:.1f}"


def combined(verdicts: list[str]) -> str:
    """All parts reproduced: reproduced; any not reproduced: not reproduced; any part not
    measured (or none at all): not measured; else undecided."""
    if not verdicts or "not measured" in verdicts:
        return "not measured"
    if "not reproduced" in verdicts:
        return "not reproduced"
    return "reproduced" if all(v == "reproduced" for v in verdicts) else "undecided"


def paper_claims(results: dict, tolerance: float = 1.0) -> list[dict]:
    """The paper's renderer claims judged on ``results`` (held-out mIoU19 in points, over seeds):
    each {"claim", "measured", "verdict", "resolution"} with a verdict of :data:`VERDICTS`. ``tolerance``: the points
    a difference may have and still count as "on par"/"robust"."""
    claims = []
    v = metric(results, "volume")
    qks = sorted({r["k"] for r in results["runs"] if r["sampler"] == "quantile" and r["k"] >= 10 and not r["noise"]})
    qs = {k: (metric(results, "quantile", k), difference(runs_of(results, "quantile", k), runs_of(results, "volume")))
          for k in qks}
    claims.append({"claim": f"Q-Render >= V-Render - {tolerance:g} at K >= 10",
                   "measured": "; ".join(f"K={k}: {q} vs {v} ({delta(d)})" for k, (q, d) in qs.items())
                   if v and qs else "-",
                   "verdict": combined([exceeds(d, -tolerance) for _, d in qs.values()]) if v else "not measured",
                   "resolution": resolution(*(d for _, d in qs.values()))})
    t5, q5 = metric(results, "topk", 5), metric(results, "quantile", 5)
    d5 = difference(runs_of(results, "quantile", 5), runs_of(results, "topk", 5))
    claims.append({"claim": "top-K at K=5 at least 3 points below Q-Render at K=5",
                   "measured": f"top-K {t5} vs Q-Render {q5} ({delta(d5)})" if t5 and q5 else "-",
                   "verdict": exceeds(d5, 3.0), "resolution": resolution(d5)})
    depth = results.get("depth_rooms")
    if depth:
        k, sub = depth["ray_depth"]["k"], {"runs": depth["runs"]}
        td, qd = metric(sub, "topk", k), metric(sub, "quantile", k)
        dd = difference(runs_of(sub, "quantile", k), runs_of(sub, "topk", k))
        claims.append({"claim": f"top-K at K={k} at least 3 points below Q-Render at K={k} on rooms with the depth "
                                "structure where top-K fails (thick semi-transparent shells)",
                       "measured": f"top-K {td} vs Q-Render {qd} ({delta(dd)})" if td and qd else "-",
                       "verdict": exceeds(dd, 3.0), "resolution": resolution(dd)})
    clean = metric(results, "quantile", NOISE_K)
    scales = sorted({r["noise"] for r in results["runs"] if 0 < r["noise"] <= 0.5})
    mild = {s: (metric(results, "quantile", NOISE_K, s),
                difference(runs_of(results, "quantile", NOISE_K, s), runs_of(results, "quantile", NOISE_K)))
            for s in scales}
    claims.append({"claim": f"robust to opacity noise up to 0.5 (within {tolerance:g} point)",
                   "measured": "; ".join(f"noise {s:g}: {m} vs clean {clean} ({delta(d)})" for s, (m, d) in mild.items())
                   if clean and mild else "-",
                   "verdict": combined([exceeds(d, -tolerance) for _, d in mild.values()]) if clean else
                   "not measured", "resolution": resolution(*(d for _, d in mild.values()))})
    strat = metric(results, "stratified", NOISE_K)
    ds = difference(runs_of(results, "stratified", NOISE_K), runs_of(results, "quantile", NOISE_K))
    t_s, t_q = render_ms(results, "stratified", NOISE_K), render_ms(results, "quantile", NOISE_K)
    name = f"Stratified-K on par (within {tolerance:g} point) at about half Q-Render's speed (K=40)"
    if strat and clean and t_s and t_q:
        ratio = t_s / t_q
        speed = "reproduced" if 1.5 <= ratio <= 2.5 else "not reproduced"
        claims.append({"claim": name, "measured": f"{strat} vs {clean} ({delta(ds)}), {ratio:.2f}x Q-Render's time",
                       "verdict": combined([exceeds(ds, -tolerance), exceeds(negated(ds), -tolerance), speed]),
                       "resolution": resolution(ds)})
    else:
        claims.append({"claim": name, "measured": "-", "verdict": "not measured", "resolution": "-"})
    rgb = [r for r in results.get("rgb", []) if r["k"] >= 20]
    claims.append({"claim": "slight RGB PSNR drop of Q-Render (>= 30 dB from V-Render at K >= 20)",
                   "measured": "; ".join(f"{r['scene']} K={r['k']}: raw {r['psnr_raw']:.1f} dB, x V alpha "
                                         f"{r['psnr_alpha']:.1f} dB" for r in rgb) or "-",
                   "verdict": ("reproduced" if all(r["psnr_alpha"] >= 30 for r in rgb) else "not reproduced")
                   if rgb else "not measured", "resolution": "one deterministic render"})
    return claims
