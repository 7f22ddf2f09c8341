"""Study: where along a ray top-K's and Q-Render's K picks lie, and how the ray's weight spreads in
depth, on the rooms and on real captures: why top-K at small K does or does not fall behind.

Per sampled hit ray, from V-Render's walk (entries in depth order, weights w_i = alpha_i T_i
normalized to sum 1, their cumulative c_i after entry i) and each sampler's K picks with its own
normalized weights:

- **pick depth**: the weight in front of each pick, c_(i-1), averaged over the picks (0: the
  ray's first weight; 1: its last);
- **unseen behind**: 1 - c at the deepest pick, the share of the ray's weight behind every pick,
  which the rendered feature never sees;
- **weight-CDF gap**: the mean over the walk's entries of |C_sampler - c|, C_sampler the
  cumulative of the sampler's weights at its picks' places: how differently it spreads the ray's
  weight along the depth (0: as V-Render);
- **class mismatch** (scenes with per-Gaussian labels): the share of rays whose class with the
  most weight among the picks differs from V-Render's, i.e. whose rendered feature leans towards
  another object than the ray's own;
- **depth spread**: the depth between c = 10 % and c = 90 %, over the depth at c = 50 %: how
  far the weight is spread behind the first surface (0 for an opaque surface); and the share of
  rays whose spread exceeds :data:`SPREAD_RAY`.
"""
from __future__ import annotations

import numpy as np
from tqdm import tqdm

from ...render import rasterize_plan, select_rays
from ...runtime import SPLAT, SPLAT_FLOATS
from ...scene import Camera, Gaussians
from ..scenes.folders import SceneData
from ..scenes.views import dense_view
from .claims import Stat
from .plan import Plan
from .scene_statistics import real_captures

#: The kinds of scene the study compares.
ROOM, REAL, DENSE = "synthetic 3dgs room", "real capture", "dense indoor target (procedural)"
DEPTH_ROOM = "synthetic room, thick semi-transparent shells"

DEPTH_RAYS = 2048                     # hit rays sampled per scene (over its cameras)
SPREAD_RAY = 0.05                     # a ray's relative depth spread above which its weight is "spread"
UNSEEN_MARGIN = 0.02                  # top-K's unseen share above Q-Render's by more: its picks lie in front


def pick_positions(walk_ids: np.ndarray, picks: np.ndarray) -> np.ndarray:
    """Positions [P,K] in each ray's walk ``walk_ids`` [P,L] (-1 padded) of its ``picks`` [P,K]
    (Gaussian ids, -1 padded); -1 for an empty slot or a pick not in the walk."""
    match = (walk_ids[:, :, None] == picks[:, None, :]) & (picks[:, None, :] >= 0)
    return np.where(match.any(1), match.argmax(1), -1)


def placed(weights: np.ndarray, positions: np.ndarray, length: int) -> np.ndarray:
    """The pick ``weights`` [P,K] at their ``positions`` [P,K] (-1: none) of walks of ``length``
    entries: [P, length], zero elsewhere."""
    out = np.zeros((len(weights), length))
    rows, slots = np.nonzero(positions >= 0)
    out[rows, positions[rows, slots]] = weights[rows, slots]
    return out


def cdf_gap(cdf: np.ndarray, picked: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Per ray: the mean over its ``count`` [P] walk entries of |cumsum(``picked``) - ``cdf``|
    ([P,L] each: a sampler's weights in place, V-Render's cumulative weights)."""
    valid = np.arange(cdf.shape[1])[None] < count[:, None]
    return (np.abs(np.cumsum(picked, 1) - cdf) * valid).sum(1) / np.maximum(count, 1)


def leading_class(weights: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Per ray the label (of ``labels`` [P,L], -1 included as a class) holding the most of
    ``weights`` [P,L]."""
    classes, index = np.unique(labels, return_inverse=True)
    shares = np.zeros((len(weights), len(classes)))
    np.add.at(shares, (np.repeat(np.arange(len(weights)), weights.shape[1]), index.ravel()), weights.ravel())
    return classes[shares.argmax(1)]


def pick_statistics(cdf: np.ndarray, weights: np.ndarray, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per ray (cumulative weights ``cdf`` [P,L] normalized to end at 1, ``weights`` [P,L] the
    normalized weights, pick ``positions`` [P,K], -1 empty): the mean weight in front of its picks
    and the weight behind its deepest pick; NaN for a ray without picks."""
    valid = positions >= 0
    at = np.maximum(positions, 0)
    front = np.take_along_axis(cdf - weights, at, 1)
    mean_front = np.where(valid.any(1), (front * valid).sum(1) / np.maximum(valid.sum(1), 1), np.nan)
    deepest = np.where(valid, positions, -1).max(1)
    behind = np.where(deepest >= 0, 1 - np.take_along_axis(cdf, np.maximum(deepest, 0)[:, None], 1)[:, 0], np.nan)
    return mean_front, behind


def depth_spread(cdf: np.ndarray, depths: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Per ray: (depth at c = 0.9 - depth at c = 0.1) / depth at c = 0.5, the c-quantiles being the
    first entries whose cumulative weight ``cdf`` [P,L] reaches them (``depths`` [P,L] camera z)."""
    rows = np.arange(len(cdf))
    masked = np.where(np.arange(cdf.shape[1])[None] < count[:, None], cdf, 2.0)
    at = {q: np.minimum((masked < q).sum(1), count - 1) for q in (0.1, 0.5, 0.9)}
    mid = depths[rows, at[0.5]]
    return (depths[rows, at[0.9]] - depths[rows, at[0.1]]) / np.maximum(mid, 1e-9)


def ray_depth_statistics(name: str, kind: str, gaussians: Gaussians, cameras: list[Camera], k: int,
                         rng: np.random.Generator, labels: np.ndarray | None = None) -> dict:
    """The module docstring's measures over up to :data:`DEPTH_RAYS` random hit rays of
    ``cameras`` for top-K and Q-Render at ``k`` (class mismatch with per-Gaussian ``labels`` [N]
    only): means over the rays, and the V-Render entries."""
    g = gaussians
    host = [np.ascontiguousarray(np.asarray(a), np.float32) for a in (g.means, g.quats, g.scales, g.opacities)]
    per = {s: {"front": [], "behind": [], "gap": [], "mismatch": []} for s in ("topk", "quantile")}
    spreads, entries = [], []
    for cam in cameras:
        plan = rasterize_plan(*host, cam.viewmat, cam.K, cam.width, cam.height)
        hit = np.flatnonzero(select_rays(plan, "volume", 1).count.get()[:cam.width * cam.height] > 0)
        rays = np.sort(rng.choice(hit, min(DEPTH_RAYS // len(cameras), len(hit)), replace=False))
        if not len(rays):
            continue
        pixels = np.stack([rays % cam.width, rays // cam.width], 1).astype(np.int32)
        walk = select_rays(plan, "volume", 1, pixels).host()
        w = walk["weights"].astype(np.float64)
        w /= np.maximum(w.sum(1, keepdims=True), 1e-30)
        cdf = np.cumsum(w, 1)
        depths = plan.splats.get().reshape(-1, SPLAT_FLOATS)[np.maximum(walk["ids"], 0), SPLAT.depth]
        ray_labels = None if labels is None else np.where(walk["ids"] >= 0, labels[np.maximum(walk["ids"], 0)], -1)
        for sampler, stats in per.items():
            picks = select_rays(plan, sampler, k, pixels).host()
            pos = pick_positions(walk["ids"], picks["ids"])
            front, behind = pick_statistics(cdf, w, pos)
            weights = placed(picks["weights"].astype(np.float64), pos, w.shape[1])
            stats["front"].append(front)
            stats["behind"].append(behind)
            stats["gap"].append(cdf_gap(cdf, weights, walk["count"]))
            if ray_labels is not None:
                stats["mismatch"].append(leading_class(weights, ray_labels) != leading_class(w, ray_labels))
        spreads.append(depth_spread(cdf, depths, walk["count"]))
        entries.append(walk["count"])
    spread = np.concatenate(spreads)
    row = {"scene": name, "kind": kind, "k": k, "rays": len(spread), "entries_mean": float(np.concatenate(entries).mean()),
           "spread_median": float(np.median(spread)), "spread_rays": float((spread > SPREAD_RAY).mean())}
    for sampler, stats in per.items():
        for measure, values in stats.items():
            row[f"{sampler}_{measure}"] = float(np.nanmean(np.concatenate(values))) if values else None
    return row


def ray_depth_study(plan: Plan, held: SceneData, data, seed: int, k: int = 5) -> list[dict]:
    """:func:`ray_depth_statistics` at ``k`` on the held-out room's first views, on the real
    captures of ``data`` (orbit views at the plan's RGB size; none when absent) and on the dense
    procedural room (many faint layers per surface: weights decaying through depth)."""
    rng = np.random.default_rng(seed)
    scenes = [(held.name, ROOM, held.gaussians, [f.camera for f in held.frames[:plan.stats_views]],
               held.gaussian_labels)]
    scenes += [(name, REAL, g, cams, None) for name, g, cams in real_captures(data, plan.stats_views, plan.rgb_size)]
    dense = dense_view(plan.dense_gaussians, *plan.rgb_size)
    scenes.append((dense.name, DENSE, dense.gaussians, [dense.camera], None))
    return [ray_depth_statistics(name, kind, g, cams, k, rng, labels)
            for name, kind, g, cams, labels in tqdm(scenes, desc="ray depths", unit="scene")]


def depth_judgement(rows: list[dict]) -> str:
    """What the measures say about the rooms against the real captures (the rooms' rows have
    kind "synthetic 3dgs room"): whether their weight spreads over depth at all as the captures'
    do, and whether top-K's picks represent a ray's weight worse than Q-Render's there."""
    rooms = [r for r in rows if r["kind"] == ROOM]
    real = [r for r in rows if r["kind"] == REAL]
    if not rooms:
        return ""
    room = rooms[0]

    def front_loaded(r: dict) -> bool:
        """Top-K's K largest weights leave more of the ray's weight behind them unseen than
        Q-Render's picks do (by over :data:`UNSEEN_MARGIN`)."""
        return r["topk_behind"] > r["quantile_behind"] + UNSEEN_MARGIN
    text = [f"On the room, top-K K={room['k']} leaves {room['topk_behind']:.0%} of a ray's weight behind its deepest pick "
            f"(Q-Render: {room['quantile_behind']:.0%}) and spreads the weight along the ray with a CDF gap of "
            f"{room['topk_gap']:.3f} (Q-Render: {room['quantile_gap']:.3f}); its picks lean to another class than the "
            f"ray's weight on {room['topk_mismatch']:.1%} of the rays (Q-Render: {room['quantile_mismatch']:.1%})."]
    if real:
        spread = max(r["spread_median"] for r in real)
        text.append(f"The room's weight spreads over {room['spread_median']:.1%} of the depth (median ray) against "
                    f"{spread:.1%} at most on the real captures here ({', '.join(r['scene'] for r in real)}), so the "
                    "room " + ("does not lack" if room["spread_median"] >= spread else "lacks") +
                    " weight spread in depth as these captures have it.")
    text.append("Top-K fails in the paper where a ray's K largest weights all lie in front of weight it never sees "
                f"(its unseen share more than {UNSEEN_MARGIN:.0%} above Q-Render's): " +
                ("the room has that structure." if front_loaded(room) else
                 "the room does not have that structure: its K largest weights span the ray as well as the quantile "
                 "picks do, so nothing in its rays makes top-K at small K fall behind."))
    for r in rows:
        if r["kind"] != ROOM:
            text.append(f"{r['scene']} ({r['kind']}): " + ("it has it" if front_loaded(r) else "it does not") +
                        f" (top-K leaves {r['topk_behind']:.0%} unseen, Q-Render {r['quantile_behind']:.0%}).")
    return " ".join(text)


def ray_depth_section(results: dict) -> list[str]:
    """The report's lines of the ray-depth study (none when the results have none)."""
    depth = results.get("depth_rooms")
    rows = (results.get("ray_depths") or []) + ([{**depth["ray_depth"], "kind": DEPTH_ROOM}] if depth else [])
    if not rows:
        return []
    k = rows[0]["k"]
    lines = [f"## Where top-K's and Q-Render's picks lie (K={k}; why top-K does or does not fall behind)", "",
             f"Over {rows[0]['rays']} random hit rays per scene: spread, the depth between 10 % and 90 % of V-Render's "
             "weight over the depth at 50 % (median ray) and the share of rays above "
             f"{SPREAD_RAY:.0%}; front, the ray's weight in front of a pick (mean over picks); behind, the weight behind "
             "the deepest pick (never seen); CDF gap, the mean gap between the sampler's and V-Render's cumulative "
             "weights along the ray; mismatch, the rays whose picks' leading class differs from the ray's "
             "(qr_cl/app/experiments/ray_depth.py).", "",
             "| scene | kind | entries | spread | rays spread | top-K front | behind | CDF gap | mismatch | "
             "Q-Render front | behind | CDF gap | mismatch |", "| --- | --- |" + " ---: |" * 11]

    def cell(v, fmt):
        return "-" if v is None else format(v, fmt)
    for r in rows:
        lines.append(f"| {r['scene']} | {r['kind']} | {r['entries_mean']:.0f} | {r['spread_median']:.1%} | "
                     f"{r['spread_rays']:.0%} | " + " | ".join(
                         f"{cell(r[f'{s}_front'], '.2f')} | {cell(r[f'{s}_behind'], '.0%')} | {cell(r[f'{s}_gap'], '.3f')} "
                         f"| {cell(r[f'{s}_mismatch'], '.1%')}" for s in ("topk", "quantile")) + " |")
    lines += ["", depth_judgement(rows), ""]
    if depth:
        lines += depth_room_lines(depth)
    return lines


def depth_room_lines(depth: dict) -> list[str]:
    """The lines of the top-K / Q-Render comparison on the rooms with the depth structure."""
    k = depth["ray_depth"]["k"]
    lines = [f"Rooms with the structure ({DEPTH_ROOM}: SyntheticConfig {depth['room']}; "
             f"{len(depth['scenes']['train'])} training rooms, held-out {depth['scenes']['held_out']}; the plan's budget "
             f"and seeds, qr_cl/app/experiments/depth_rooms.py). Held-out mIoU19, mean ± std over the seeds:", "",
             "| renderer | mIoU19 | mAcc19 | train s |", "| --- | ---: | ---: | ---: |"]
    for sampler, name in (("topk", "top-K"), ("quantile", "Q-Render")):
        runs = [r for r in depth["runs"] if r["sampler"] == sampler]
        if runs:
            stats = [Stat.of(r[key] for r in runs) for key in ("miou19", "macc19")]
            lines.append(f"| {name} K={k} | {stats[0]} | {stats[1]} | {sum(r['train_s'] for r in runs) / len(runs):.0f} |")
    return lines + [""]
