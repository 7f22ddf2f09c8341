"""``qr-cl reproduce``: the "3dgs" room generator, the opacity noise, the profile and PSNR measures,
the paper's claims, the report writer and the command's wiring (a smoke run on tiny rooms)."""
from __future__ import annotations

import filecmp
import json
import math

import numpy as np
import pytest

from qr_cl.app.cli import DELEGATED, build_parser, main
from qr_cl.app.experiments.claims import Stat, combined, difference, exceeds, paper_claims, resolution
from qr_cl.app.experiments.plan import PLANS, TrainingRun, plan_runs
from qr_cl.app.experiments.report import report_markdown, write_report
from qr_cl.app.experiments.rgb import psnr
from qr_cl.app.experiments.rooms import noisy_scene, perturb_opacities
from qr_cl.app.experiments.ray_depth import cdf_gap, depth_spread, leading_class, pick_positions, pick_statistics
from qr_cl.app.experiments.scene_statistics import entries_per_ray, weight_concentration
from qr_cl.app.experiments.table2 import PAPER_RATIO, ratio_of, ratio_verdict, table2_claims
from qr_cl.app.experiments.transmittance import profile_gaps
from qr_cl.app.scenes.folders import load_scene_folder
from qr_cl.app.scenes.room_config import SyntheticConfig
from qr_cl.app.scenes.synthetic import room_folder
from tests.synthetic_helpers import tiny_config

# orthogonal prototypes: at 32 channels a mask's nearest text feature is its own class's
SPLAT_ROOM = dict(style="3dgs", n_gaussians=5000, layers=2.0, n_objects=3, n_wall_objects=1, n_views=3, width=80,
                  height=60, dim=32, features="orthogonal")


@pytest.fixture(scope="module")
def splat_room(tmp_path_factory):
    return room_folder(SyntheticConfig(seed=5, **SPLAT_ROOM), tmp_path_factory.mktemp("splat"))


def _mean_entries(path) -> float:
    scene = load_scene_folder(path)
    counts = np.concatenate([entries_per_ray(scene.gaussians, f.camera) for f in scene.frames])
    return float(counts[counts > 0].mean())


def test_splat_rays_cross_many_gaussians_unlike_flat_rooms(splat_room, tmp_path):
    flat_room = {k: v for k, v in SPLAT_ROOM.items() if k not in ("style", "layers")}
    flat = room_folder(SyntheticConfig(seed=5, **flat_room), tmp_path)
    splat, opaque = _mean_entries(splat_room), _mean_entries(flat)
    assert splat >= 50
    assert splat > 1.5 * opaque


def test_splat_gaussians_are_semi_transparent_anisotropic_with_floaters(splat_room):
    scene = load_scene_folder(splat_room)
    g, labels = scene.gaussians, scene.gaussian_labels
    surface = g.opacities[labels >= 0]
    assert 0.3 < np.mean((surface > 0.1) & (surface < 0.9)) < 0.9      # many semi-transparent ...
    assert np.mean(surface < 0.1) > 0.05 and np.mean(surface > 0.9) > 0.05   # ... and faint and opaque ones
    s = np.sort(g.scales, axis=1)
    assert np.median(s[:, 2] / s[:, 0]) > 2.5
    floaters = labels == -1
    assert 0.005 < floaters.mean() < 0.05
    assert g.opacities[floaters].mean() < 0.3 * surface.mean()
    assert not (splat_room / "labels" / "points.ply").exists()          # ground truth: per-Gaussian labels


def test_splat_masks_come_from_object_ids(splat_room):
    scene = load_scene_folder(splat_room)
    present = set(np.unique(scene.gaussian_labels[scene.gaussian_labels >= 0]).tolist())
    hits = total = 0
    for frame in scene.frames:
        assert (frame.masks >= 0).mean() > 0.5
        best = scene.classes.ids[(frame.features @ scene.classes.text_features.T).argmax(1)]
        hits += sum(int(b) in present for b in best)
        total += len(best)
    assert total >= 2 * len(scene.frames) and hits >= 0.8 * total


def test_splat_room_is_seeded_and_cached(splat_room, tmp_path):
    again = room_folder(SyntheticConfig(seed=5, **SPLAT_ROOM), tmp_path)
    assert again.name.startswith("splat-room-5-")
    for rel in ("point_cloud.ply", "cameras.json", "labels/gaussian_labels.npy", "language_features/frame_001_s.npy"):
        assert filecmp.cmp(splat_room / rel, again / rel, shallow=False), rel
    mtime = (again / "point_cloud.ply").stat().st_mtime_ns
    assert room_folder(SyntheticConfig(seed=5, **SPLAT_ROOM), tmp_path) == again
    assert (again / "point_cloud.ply").stat().st_mtime_ns == mtime
    other = room_folder(SyntheticConfig(seed=6, **SPLAT_ROOM), tmp_path)
    assert not filecmp.cmp(splat_room / "point_cloud.ply", other / "point_cloud.ply", shallow=False)


def test_cache_keys_hold_only_the_fields_a_room_reads():
    # a flat room's key ignores the "3dgs" style's fields; each feature model's ignores the other's
    flat = SyntheticConfig(seed=0, n_gaussians=24000)
    assert SyntheticConfig(seed=0, n_gaussians=24000, layers=7.0).key() == flat.key()
    assert SyntheticConfig(seed=0, n_gaussians=24000, mask_noise=0.9).key() == flat.key()
    assert SyntheticConfig(seed=0, n_gaussians=24000, clip_noise=3.0).key() != flat.key()
    assert SyntheticConfig(seed=0, style="3dgs").key() != SyntheticConfig(seed=0, style="3dgs", layers=7.0).key()
    with pytest.raises(ValueError, match="style"):
        SyntheticConfig(style="mesh")
    assert tiny_config().folder_name.startswith("room-0-")


def test_opacity_noise_acts_on_logits(tiny_room):
    g = load_scene_folder(tiny_room).gaussians
    same = perturb_opacities(g, 0.0, np.random.default_rng(0))
    assert np.allclose(same.opacities, g.opacities, atol=1e-6)
    noisy = perturb_opacities(g, 2.0, np.random.default_rng(0))
    p, q = (np.clip(x.astype(np.float64), 1e-6, 1 - 1e-6) for x in (g.opacities, noisy.opacities))
    delta = np.log(q / (1 - q)) - np.log(p / (1 - p))
    assert abs(delta.std() - 2.0) < 0.15 and abs(delta.mean()) < 0.1
    assert np.array_equal(noisy.means, g.means) and noisy.opacities.dtype == np.float32
    again = perturb_opacities(g, 2.0, np.random.default_rng(0))
    assert np.array_equal(again.opacities, noisy.opacities)


def test_noisy_scene_is_a_cached_copy_with_noisy_opacities(tiny_room):
    noisy = noisy_scene(tiny_room, 1.0, 0)
    assert noisy != tiny_room and (noisy / "cameras.json").is_symlink()
    assert not (noisy / "point_cloud.ply").is_symlink()
    clean, perturbed = load_scene_folder(tiny_room), load_scene_folder(noisy)
    assert np.array_equal(clean.gaussians.means, perturbed.gaussians.means)
    assert not np.allclose(clean.gaussians.opacities, perturbed.gaussians.opacities, atol=0.01)
    assert len(perturbed.frames) == len(clean.frames)
    mtime = (noisy / "point_cloud.ply").stat().st_mtime_ns
    assert noisy_scene(tiny_room, 1.0, 0) == noisy and (noisy / "point_cloud.ply").stat().st_mtime_ns == mtime
    assert noisy_scene(tiny_room, 1.0, 1) != noisy


def test_profile_gaps():
    depths, t = np.array([1.0, 2.0, 3.0]), np.array([1.0, 0.5, 0.25, 0.125])
    assert profile_gaps((depths, t), (depths, t)) == (0.0, 0.0)
    # one Gaussian at depth 2 taking T from 1 to 0.5: at depths 1, 2, 3 its T is 1, 0.5, 0.5 against
    # V-Render's 0.5, 0.25, 0.125; its normalized weight is all at depth 2, V-Render's CDF is
    # (4/7, 6/7, 1) there
    t_gap, cdf_gap = profile_gaps((depths, t), (np.array([2.0]), np.array([1.0, 0.5])))
    assert t_gap == pytest.approx((0.5 + 0.25 + 0.375) / 3)
    assert cdf_gap == pytest.approx((4 / 7 + 1 / 7 + 0) / 3)
    assert profile_gaps((np.zeros(0), np.ones(1)), (depths, t)) == (0.0, 0.0)


def test_weight_concentration():
    w = np.array([[0.5, 0.3, 0.1, 0.05, 0.05], [0.2, 0.2, 0.2, 0.2, 0.2], [0.0, 0.0, 0.0, 0.0, 0.0],
                  [0.05, 0.9, 0.0, 0.0, 0.0]])
    assert weight_concentration(w).tolist() == [3, 5, 0, 1]
    assert weight_concentration(w, 0.5).tolist() == [1, 3, 0, 1]


def test_psnr():
    a = np.zeros((4, 4, 3))
    assert psnr(a, a) == math.inf
    assert psnr(a + 0.1, a) == pytest.approx(20.0)
    assert psnr(a + 2.0, a) == pytest.approx(0.0)        # clipped to [0, 1]


def test_renderers_of_the_plans():
    full = plan_runs(PLANS["full"])
    keys = [(r.label, r.seed) for r in full]
    assert len(set(keys)) == len(keys)
    assert {r.seed for r in full} == {0, 1, 2} and PLANS["quick"].seeds >= 3
    for seed in range(3):
        assert TrainingRun("volume", seed=seed) in full and TrainingRun("stratified", 40, seed=seed) in full
        for k in (5, 10, 20, 40, 50):
            assert TrainingRun("topk", k, seed=seed) in full and TrainingRun("quantile", k, seed=seed) in full
    assert {r.noise for r in full} == {0.0, 0.25, 0.5, 1.0, 2.0, 4.0}
    assert all(r.sampler == "quantile" and r.k == 40 for r in full if r.noise)
    assert len(full) == 3 * len({r.label for r in full})
    assert len(plan_runs(PLANS["quick"])) < len(full)
    quick = {(r.sampler, r.k) for r in plan_runs(PLANS["quick"])}
    assert ("topk", 5) in quick and ("topk", 40) not in quick and ("quantile", 40) in quick


def test_stat_and_verdicts():
    s = Stat.of([40.0, 42.0, 44.0])
    assert (s.mean, s.std, s.n) == (42.0, 2.0, 3) and str(s) == "42.0 ± 2.0" and str(Stat.of([5.0])) == "5.0"
    assert Stat.of([5.0]).std == 0.0
    assert exceeds(Stat(5, 1, 3), 3.0) == "reproduced"                 # 4 > 3
    assert exceeds(Stat(5, 3, 3), 3.0) == "undecided"                  # 3 lies in [2, 8]
    assert exceeds(Stat(1, 1, 3), 3.0) == "not reproduced"
    assert exceeds(Stat(-1.5, 0.2, 3), -2.0) == "reproduced"           # margin: a >= b - 2
    assert exceeds(None) == "not measured"
    assert combined(["reproduced", "reproduced"]) == "reproduced"
    assert combined(["reproduced", "undecided"]) == "undecided"
    assert combined(["undecided", "not reproduced"]) == "not reproduced"
    assert combined([]) == "not measured"


def test_differences_pair_the_seeds():
    a = [{"seed": s, "miou19": v} for s, v in enumerate((10.0, 20.0, 30.0))]
    b = [{"seed": s, "miou19": v} for s, v in enumerate((9.0, 19.0, 29.0))]
    d = difference(a, b)
    assert (d.mean, d.std, d.n) == (1.0, 0.0, 3)                      # the seeds' shared swing cancels
    assert exceeds(d, 0.5) == "reproduced" and exceeds(Stat.of([10.0, 20.0, 30.0]), 19.0) == "undecided"
    one = [{"miou19": 12.0}]                                           # no seed: Dr.Splat's registration
    assert difference(a, one) == Stat.of([-2.0, 8.0, 18.0]) and difference(one, a) == Stat.of([2.0, -8.0, -18.0])
    assert difference(a, [{"train_seed": 7, "miou19": 1.0}, {"train_seed": 8, "miou19": 2.0}]) is None
    assert difference(a, []) is None and difference(None, a) is None
    assert [r["seed"] for r in a] == [0, 1, 2]
    assert resolution(Stat(1, 0.3, 3), None) == "-" and resolution(Stat(1, 0.3, 3), Stat(2, 1.5, 3)) == "±1.5 points"


def _results(q5: float = 30.0, t5: float = 25.0, noise_half: float = 40.5, strat_ms: float = 20.0,
             drsplat: float = 18.0, overfit: float = 52.0, spread: float = 0.2, anti: bool = False) -> dict:
    """Results of runs over three seeds, each run's mIoU19 its value -spread, 0, +spread (standard
    deviation ``spread``); with ``anti`` V-Render's and top-K's seeds swing the other way, so their
    paired differences to the others spread by twice ``spread``."""
    def run(sampler, k, miou, noise=0.0):
        sign = -1 if anti and sampler in ("volume", "topk") else 1
        return [{"sampler": sampler, "k": k, "noise": noise, "seed": seed,
                 "label": TrainingRun(sampler, k, noise, seed).label, "steps": 10, "train_s": 1.0,
                 "final_loss": 0.5, "miou19": miou + sign * d, "macc19": miou + d + 5, "miou15": miou + 1, "macc15": 0.0,
                 "miou10": miou + 2, "macc10": 0.0, "miou19_reached": miou + 3, "macc19_reached": miou + 4}
                for seed, d in enumerate((-spread, 0.0, spread))]
    runs = [*run("volume", 0, 40.0), *run("topk", 5, t5), *run("quantile", 5, q5), *run("quantile", 40, 40.5),
            *run("stratified", 40, 40.2), *run("quantile", 40, noise_half, 0.5), *run("quantile", 40, 12.0, 4.0)]
    times = [{"sampler": s, "k": k, "ms": ms, "median_ms": ms} for s, k, ms in
             (("volume", 0, 30.0), ("topk", 5, 8.0), ("quantile", 5, 6.0), ("quantile", 40, 10.0),
              ("stratified", 40, strat_ms), ("volume_fused", 0, 25.0))]
    stats = [{"scene": name, "kind": "k", "n_gaussians": 10, "views": 1, "size": "8x6", "opacity_hist": [0.05] * 20,
              "opacity_mean": 0.5, "entries_mean": e, "entries_median": e, "entries_p90": e, "holding_90": 3.0,
              "coverage": 1.0}
             for name, e in (("room", 80.0), ("fox", 21.0))]
    def scores(value, d=0.0):
        return {"miou19": value + d, "macc19": 60.0, "miou15": value, "macc15": 61.0, "miou10": value, "macc10": 62.0,
                "miou19_reached": 48.0, "macc19_reached": 65.0}
    free = [{"label": "free features", "steps": 10, "train_s": 2.0, "train_seed": seed, **scores(5.0, d)}
            for seed, d in enumerate((-spread, 0.0, spread))]
    over = [{"label": "GS-Net overfit", "steps": 10, "train_s": 2.0, "train_seed": seed, **scores(overfit, d)}
            for seed, d in enumerate((-spread, 0.0, spread))]
    reg = [{"label": "Dr.Splat", "k": 40, "gaussians": 9, "reached": 6, "views": 2, "rays": 30, "entries": 300,
            "seconds": 1.5, "labelled_unreached": 2, "labelled": 8, **scores(drsplat)}]
    return {"mode": "test", "plan": {"room": {}, "steps": 10, "views": 1, "rays": 8, "timing_size": [8, 6],
                                     "timing_rounds": 1, "timing_views": 1, "seeds": 3},
            "seed": 0, "features": "clip", "mask_accuracy19": {"a": 0.68, "b": 0.72}, "device": "cpu",
            "wall_s": 60.0, "scenes": {"train": ["a"], "held_out": "b"},
            "statistics": stats, "runs": runs, "render_ms": times, "free_features": free, "overfit": over,
            "drsplat": reg,
            "reached": {"gaussians": 7, "labelled": 9},
            "segmentation": {"label": "GS-Net Q-Render K=40, seed 0", "files": ["confusion.png"],
                             "models": ["GS-Net", "Dr.Splat"], "min_share": 0.01, "min_iou": 10.0, "below_bar": [],
                             "per_class": [{"class": "desk", "iou": 12.5, "acc": 30.0, "support": 40, "share": 0.4,
                                            "models": {"GS-Net": 12.5, "Dr.Splat": 7.25}}]},
            "ray_depths": [{"scene": name, "kind": kind, "k": 5, "rays": 64, "entries_mean": 50.0, "spread_median": sp,
                            "spread_rays": 0.5, "topk_front": 0.4, "topk_behind": 0.1, "topk_gap": 0.05,
                            "topk_mismatch": mm, "quantile_front": 0.45, "quantile_behind": 0.12, "quantile_gap": 0.07,
                            "quantile_mismatch": mm}
                           for name, kind, sp, mm in (("b", "synthetic 3dgs room", 0.2, 0.04),
                                                      ("fox", "real capture", 0.01, None))],
            "profiles": {"k": 10, "rays": 4, "entries_mean": 80.0, "gap": {"Q-Render K=10": [0.1, 0.05]},
                         "files": ["transmittance_ray000.png"]},
            "rgb": [{"scene": "fox", "k": 20, "views": 1, "size": "8x6", "psnr_raw": 21.5, "psnr_alpha": 47.4,
                     "psnr_own_alpha": 45.0}],
            "agreement": [{"sampler": "topk", "k": 5, "cosine": 0.9876}]}


def _verdicts(results: dict) -> list[str]:
    return [c["verdict"] for c in paper_claims(results)]


def test_claims_follow_the_numbers_over_seeds():
    assert _verdicts(_results()) == ["reproduced"] * 5
    assert _verdicts(_results(q5=30.0, t5=28.0, noise_half=38.0, strat_ms=10.5)) == [
        "reproduced", "not reproduced", "not reproduced", "not reproduced", "reproduced"]
    # the seeds swing together: paired, the same means are decided even with wide spreads ...
    assert _verdicts(_results(q5=30.0, t5=26.0, spread=2.0))[:2] == ["reproduced", "reproduced"]
    # ... and not when V-Render's and top-K's seeds swing the other way
    wide = paper_claims(_results(q5=30.0, t5=26.0, spread=2.0, anti=True))
    assert [c["verdict"] for c in wide[:2]] == ["undecided", "undecided"]
    assert wide[1]["resolution"] == "±4.0 points" and "Δ +4.0 ± 4.0" in wide[1]["measured"]
    bad = _results()
    bad["rgb"][0]["psnr_alpha"] = 25.0
    for r in bad["runs"]:
        if r["sampler"] == "quantile" and r["k"] == 40 and not r["noise"]:
            r["miou19"] -= 2.5                             # Q-Render K=40 two points under V-Render
    assert _verdicts(bad)[0] == "not reproduced" and _verdicts(bad)[4] == "not reproduced"
    missing = _results()
    missing["runs"] = [r for r in missing["runs"] if r["sampler"] != "topk"]
    missing["rgb"] = []
    claims = _verdicts(missing)
    assert claims[1] == claims[4] == "not measured"
    depth = _results()
    depth["depth_rooms"] = {"ray_depth": {"k": 5}, "runs": [r for r in depth["runs"] if r["k"] == 5]}
    assert [c["verdict"] for c in paper_claims(depth)][2] == "reproduced"   # 30 vs 25 on those rooms too


def test_table2_claims():
    # GS-Net generalised is Q-Render K=40's 40.5 ± 0.2
    verdicts = [c["verdict"] for c in table2_claims(_results(drsplat=18.0, overfit=52.0))]
    assert verdicts == ["reproduced", "reproduced", "reproduced"]              # 40.5 / 18 = 2.25
    verdicts = [c["verdict"] for c in table2_claims(_results(drsplat=41.0, overfit=40.4))]
    assert verdicts == ["not reproduced", "not reproduced", "not reproduced"]   # paired: -0.1 ± 0.0
    verdicts = [c["verdict"] for c in table2_claims(_results(drsplat=40.4, overfit=40.6))]
    assert verdicts[:2] == ["undecided", "reproduced"]                          # 40.5 ± 0.2 - 40.4
    assert [c["verdict"] for c in table2_claims(_results(drsplat=12.0))][2] == "not reproduced"   # 3.4
    none = _results()
    del none["overfit"], none["drsplat"]
    assert [c["verdict"] for c in table2_claims(none)] == ["not measured"] * 3
    assert abs(PAPER_RATIO - 50.75 / 23.21) < 1e-12
    r = ratio_of(Stat(40.0, 2.0, 3), Stat(20.0, 0.0, 1))
    assert (r.mean, r.std) == (2.0, 0.1)
    assert ratio_verdict(Stat(2.2, 0.7, 3)) == "undecided" and ratio_verdict(None) == "not measured"


def test_ray_depth_measures():
    walk = np.array([[10, 11, 12, 13], [20, 21, -1, -1]])
    assert pick_positions(walk, np.array([[12, 10], [21, -1]])).tolist() == [[2, 0], [1, -1]]
    assert pick_positions(walk, np.array([[99, -1], [-1, -1]])).tolist() == [[-1, -1], [-1, -1]]
    w = np.array([[0.4, 0.3, 0.2, 0.1], [0.5, 0.5, 0.0, 0.0]])
    cdf = np.cumsum(w, 1)
    front, behind = pick_statistics(cdf, w, np.array([[0, 2], [-1, -1]]))
    assert front[0] == pytest.approx((0.0 + 0.7) / 2) and behind[0] == pytest.approx(0.1) and np.isnan(front[1])
    count = np.array([4, 2])
    picked = np.array([[0.5, 0.0, 0.5, 0.0], [0.5, 0.5, 0.0, 0.0]])
    gaps = cdf_gap(cdf, picked, count)
    assert gaps[0] == pytest.approx((0.1 + 0.2 + 0.1 + 0.0) / 4) and gaps[1] == 0.0
    labels = np.array([[1, 2, 2, -1], [3, 3, -1, -1]])
    assert leading_class(w, labels).tolist() == [2, 3]
    depths = np.array([[1.0, 2.0, 3.0, 4.0], [2.0, 2.0, 0.0, 0.0]])
    assert depth_spread(cdf, depths, count).tolist() == pytest.approx([(4.0 - 1.0) / 2.0, 0.0])


def test_report_writer(tmp_path):
    results = _results()
    results["claims"] = paper_claims(results)
    files = write_report(tmp_path, results)
    assert all(f.is_file() and f.stat().st_size > 0 for f in files)
    text = (tmp_path / "report.md").read_text()
    assert text == report_markdown(json.loads((tmp_path / "results.json").read_text()))
    assert "| top-K K=5 | 25.0 ± 0.2 | 30.0 ± 0.2 | 26.0 ± 0.0 | 27.0 ± 0.0 | 37.84 | 8.0 | 0.9876 |" in text
    assert "| Q-Render K=5 | 30.0 ± 0.2 | 35.0 ± 0.2 | 31.0 ± 0.0 | 32.0 ± 0.0 | 49.98 | 6.0 | - |" in text
    assert "| 0.5 | 40.5 ± 0.2 | 45.5 ± 0.2 | 50.18 |" in text
    assert "| fox | 1 | 8x6 | 20 | 21.5 | 47.4 | 45.0 |" in text
    assert "| Q-Render K=10 | 0.100 | 0.050 |" in text
    assert text.count("| reproduced |") == 8
    assert "(7 of 9; the only" in text and "repeated with 3 seeds" in text and "68-72 % of the masks" in text
    assert "| Dr.Splat registration | 18.0 | 60.0 | 18.0 | 61.0 | 18.0 | 62.0 |" in text
    assert "| *paper* | *23.21* | *35.42* | *25.33* | *34.64* | *36.71* | *53.29* |" in text
    assert "| GS-Net generalised | 40.5 ± 0.2 | 45.5 ± 0.2 | 41.5 ± 0.0 | 0.0 ± 0.0 | 42.5 ± 0.0 | 0.0 ± 0.0 |" in text
    assert "| GS-Net overfit | 52.0 ± 0.2 |" in text and "| *paper* | *62.83* | - |" in text
    assert "2 of the 8 labelled ones" in text and "seeds resolve" in text
    assert "| desk | 12.5 | 7.2 | 30.0 | 40 (40.0%) |" in text and "![confusion](confusion.png)" in text
    assert "every class above 1% of the labelled Gaussians has an IoU above 10" in text
    assert "| b | synthetic 3dgs room | 50 | 20.0% | 50% | 0.40 | 10% | 0.050 | 4.0% |" in text
    assert "| fox | real capture |" in text and "the room does not have that structure" in text
    assert "fox (real capture): it does not" in text


def test_cli_registers_reproduce():
    assert DELEGATED["reproduce"][0] == "experiments"
    args = build_parser().parse_args(["reproduce", "--quick", "--out", "x"])
    assert args.quick and not args.smoke and args.out == "x"


def test_smoke_run_writes_the_report(tmp_path, data_dir, capsys):
    out = tmp_path / "out"
    data = ["--data", str(data_dir)] if data_dir.is_dir() else []        # a user's clone has no shared data
    assert main(["reproduce", "--smoke", "--out", str(out), "--cache", str(tmp_path / "cache")] + data) == 0
    results = json.loads((out / "results.json").read_text())
    assert {r["label"] for r in results["runs"]} == {r.label for r in plan_runs(PLANS["smoke"])}
    assert {t["sampler"] for t in results["render_ms"]} == {"volume", "topk", "quantile", "stratified", "volume_fused"}
    assert 0 < results["reached"]["gaussians"] <= results["reached"]["labelled"]
    seeds = PLANS["smoke"].seeds
    assert len(results["free_features"]) == len(results["overfit"]) == seeds == len({r["seed"] for r in results["runs"]})
    assert {"miou19", "miou19_reached"} <= set(results["free_features"][0]) and "miou19_reached" in results["runs"][0]
    assert {"miou19", "macc10"} <= set(results["overfit"][0]) and len(results["drsplat"]) == 1
    assert 0 < results["drsplat"][0]["reached"] <= results["drsplat"][0]["gaussians"]
    assert len(results["claims"]) == 9 and all("resolution" in c for c in results["claims"])
    depth = results["depth_rooms"]
    assert len(depth["runs"]) == 2 * seeds and {r["sampler"] for r in depth["runs"]} == {"topk", "quantile"}
    assert depth["ray_depth"]["k"] == PLANS["smoke"].depth_k and (out / "runs" / "depth-rooms-topk5-seed0").is_dir()
    assert results["ray_depths"][0]["kind"] == "synthetic 3dgs room"
    assert set(results["segmentation"]["models"]) == {"GS-Net generalised", "GS-Net overfit", "Dr.Splat registration",
                                                     "free features"}
    assert {c["verdict"] for c in results["claims"]} <= {"reproduced", "not reproduced", "undecided", "not measured"}
    assert results["segmentation"]["per_class"] and 0 <= min(results["mask_accuracy19"].values()) <= 1
    real = (data_dir / "wakufactory-fox" / "fox.ply").is_file()
    assert ("fox" in {s["scene"] for s in results["statistics"]}) == real
    assert ("fox" in {r["scene"] for r in results["rgb"]}) == real
    assert all(r["psnr_alpha"] > r["psnr_raw"] - 1e-6 or r["scene"] != "fox" for r in results["rgb"])
    assert {"psnr_raw", "psnr_alpha", "psnr_own_alpha", "psnr_topk_alpha"} <= set(results["rgb"][0])
    for name in (["report.md", "miou_vs_time.png", "scene_statistics.png"] + results["profiles"]["files"]
                 + results["segmentation"]["files"]):
        assert (out / name).is_file(), name
    printed = capsys.readouterr().out
    assert "Report:" in printed and "| GS-Net overfit |" in printed and "seeds resolve" in printed
