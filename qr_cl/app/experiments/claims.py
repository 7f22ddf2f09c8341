"""The paper's numbers and claims, judged on a reproduction's runs over seeds (and the look-ups of
those results the report shares).

Every training run of a plan is repeated with ``plan.seeds`` seeds; a quantity is its mean and
standard deviation over them (:class:`Stat`). A claim "a >= b + margin" is **reproduced** when
a's band (mean +- std) lies wholly above b + margin's band, **not reproduced** when wholly below,
and **undecided** when the bands overlap; **not measured** when a run it needs is missing. So the
seeds decide a difference a - b (past the claim's margin) only when it exceeds the sum of the two
standard deviations: every claim states that resolution (:func:`resolution`), which an undecided
claim lacks.
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


def at_least(a: Stat | None, b: Stat | None, margin: float = 0.0) -> str:
    """The verdict on "a >= b + margin" (module docstring)."""
    if a is None or b is None:
        return "not measured"
    if a.mean - a.std > b.mean + margin + b.std:
        return "reproduced"
    if a.mean + a.std < b.mean + margin - b.std:
        return "not reproduced"
    return "undecided"


def resolution(*pairs: tuple[Stat | None, Stat | None]) -> str:
    """The smallest difference between the two quantities of each pair (a, b) that their bands
    decide, the largest over the pairs: std(a) + std(b) points ("-" when one is missing)."""
    if not pairs or any(a is None or b is None for a, b in pairs):
        return "-"
    return f"> {max(a.std + b.std for a, b in pairs):.1f} points"


def combined(verdicts: list[str]) -> str:
    """All parts reproduced: reproduced; any not reproduced: not reproduced; any part not
    measured (or none at all): not measured; else undecided."""
    if not verdicts or "not measured" in verdicts:
        return "not measured"
    if "not reproduced" in verdicts:
        return "not reproduced"
    return "reproduced" if all(v == "reproduced" for v in verdicts) else "undecided"


def _diff(a: Stat, b: Stat) -> str:
    return f"{a.mean - b.mean:+.1f}"


def paper_claims(results: dict, tolerance: float = 1.0) -> list[dict]:
    """The paper's renderer claims judged on ``results`` (held-out mIoU19 in points, over seeds):
    each {"claim", "measured", "verdict", "resolution"} with a verdict of :data:`VERDICTS`. ``tolerance``: the points
    a difference may have and still count as "on par"/"robust"."""
    claims = []
    v = metric(results, "volume")
    qks = sorted({r["k"] for r in results["runs"] if r["sampler"] == "quantile" and r["k"] >= 10 and not r["noise"]})
    qs = {k: metric(results, "quantile", k) for k in qks}
    claims.append({"claim": f"Q-Render >= V-Render - {tolerance:g} at K >= 10",
                   "measured": "; ".join(f"K={k}: {q} vs {v}" for k, q in qs.items()) if v and qs else "-",
                   "verdict": combined([at_least(q, v, -tolerance) for q in qs.values()]) if v else "not measured",
                   "resolution": resolution(*((q, v) for q in qs.values()))})
    t5, q5 = metric(results, "topk", 5), metric(results, "quantile", 5)
    claims.append({"claim": "top-K at K=5 at least 3 points below Q-Render at K=5",
                   "measured": f"top-K {t5} vs Q-Render {q5} ({_diff(t5, q5)})" if t5 and q5 else "-",
                   "verdict": at_least(q5, t5, 3.0), "resolution": resolution((q5, t5))})
    depth = results.get("depth_rooms")
    if depth:
        k, sub = depth["ray_depth"]["k"], {"runs": depth["runs"]}
        td, qd = metric(sub, "topk", k), metric(sub, "quantile", k)
        claims.append({"claim": f"top-K at K={k} at least 3 points below Q-Render at K={k} on rooms with the depth "
                                "structure where top-K fails (thick semi-transparent shells)",
                       "measured": f"top-K {td} vs Q-Render {qd} ({_diff(td, qd)})" if td and qd else "-",
                       "verdict": at_least(qd, td, 3.0), "resolution": resolution((qd, td))})
    clean = metric(results, "quantile", NOISE_K)
    scales = sorted({r["noise"] for r in results["runs"] if 0 < r["noise"] <= 0.5})
    mild = {s: metric(results, "quantile", NOISE_K, s) for s in scales}
    claims.append({"claim": f"robust to opacity noise up to 0.5 (within {tolerance:g} point)",
                   "measured": "; ".join(f"noise {s:g}: {m} vs clean {clean}" for s, m in mild.items())
                   if clean and mild else "-",
                   "verdict": combined([at_least(m, clean, -tolerance) for m in mild.values()]) if clean else
                   "not measured", "resolution": resolution(*((m, clean) for m in mild.values()))})
    strat = metric(results, "stratified", NOISE_K)
    t_s, t_q = render_ms(results, "stratified", NOISE_K), render_ms(results, "quantile", NOISE_K)
    name = f"Stratified-K on par (within {tolerance:g} point) at about half Q-Render's speed (K=40)"
    if strat and clean and t_s and t_q:
        ratio = t_s / t_q
        speed = "reproduced" if 1.5 <= ratio <= 2.5 else "not reproduced"
        claims.append({"claim": name, "measured": f"{strat} vs {clean} ({_diff(strat, clean)}), {ratio:.2f}x "
                                                  "Q-Render's time",
                       "verdict": combined([at_least(strat, clean, -tolerance), at_least(clean, strat, -tolerance),
                                            speed]), "resolution": resolution((strat, clean))})
    else:
        claims.append({"claim": name, "measured": "-", "verdict": "not measured", "resolution": "-"})
    rgb = [r for r in results.get("rgb", []) if r["k"] >= 20]
    claims.append({"claim": "slight RGB PSNR drop of Q-Render (>= 30 dB from V-Render at K >= 20)",
                   "measured": "; ".join(f"{r['scene']} K={r['k']}: raw {r['psnr_raw']:.1f} dB, x V alpha "
                                         f"{r['psnr_alpha']:.1f} dB" for r in rgb) or "-",
                   "verdict": ("reproduced" if all(r["psnr_alpha"] >= 30 for r in rgb) else "not reproduced")
                   if rgb else "not measured", "resolution": "one deterministic render"})
    return claims
