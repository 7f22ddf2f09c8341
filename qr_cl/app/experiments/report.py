"""The reproduction's report: report.md (tables, the paper's claims checked against the numbers),
results.json and the figures."""
from __future__ import annotations

import json
import math
from pathlib import Path

from ..renderers import FUSED_NAME
from .claims import PAPER, clean_renderers, cosine_to_volume, metric, render_ms, runs_of, stat_cell
from .figures import plot_miou_vs_time
from .plan import NOISE_K
from .ray_depth import ray_depth_section
from .scene_statistics import plot_scene_statistics
from .table2 import table2_section


def _fmt(value: float | None, digits: int = 1) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"


def _paper_miou(sampler: str, k: int) -> float | None:
    """The paper's Fig. 4 mIoU of a renderer (None where the paper has none)."""
    entry = PAPER.get(sampler)
    return entry.get(k) if isinstance(entry, dict) else entry


def segmentation_section(results: dict) -> list[str]:
    """The main run's per-class IoU table, confusion matrix and pictures."""
    seg = results.get("segmentation")
    if not seg:
        return []
    models = seg["models"]
    bar = (f"every class above {seg['min_share']:.0%} of the labelled Gaussians has an IoU above "
           f"{seg['min_iou']:g} for {seg['label']}" if not seg["below_bar"] else
           f"the classes above {seg['min_share']:.0%} of the labelled Gaussians at or under an IoU of "
           f"{seg['min_iou']:g} for {seg['label']}: {', '.join(seg['below_bar'])}")
    lines = ["## Per class (held-out room)", "",
             "IoU in % per class over the labelled Gaussians (support: their number and share), for the models of "
             f"Table 2 (first seed; accuracy: the first model's); the confusion matrix shows where {seg['label']}'s "
             f"Gaussians went (rows normalised). The bar: {bar}.", "",
             "| class | " + " | ".join(models) + " | accuracy | support |", "| --- |" + " ---: |" * (len(models) + 2)]
    lines += [f"| {c['class']} | " + " | ".join(f"{c['models'][m]:.1f}" for m in models) +
              f" | {c['acc']:.1f} | {c['support']} ({c['share']:.1%}) |" for c in seg["per_class"]]
    lines += ["", "Pictures, from above the room: RGB | PCA of the Q-Render feature image | predicted classes | "
              "ground truth (labelled Gaussians only) | cosine of the feature image to one class's text feature "
              "(stretched, turbo colours: red high); then the predictions of the models side by side.", ""]
    return lines + [f"![{Path(f).stem}]({f})" for f in seg["files"]] + [""]


def _features_sentence(results: dict) -> str:
    """What the rooms' simulated CLIP features are, with the measured mask accuracy."""
    acc = list(results.get("mask_accuracy19", {}).values())
    if results.get("features", "clip") == "orthogonal":
        return ("The \"CLIP\" features are simulated from random, nearly orthogonal class prototypes "
                "(qr_cl/app/scenes/room_features.py).")
    return ("The \"CLIP\" features are simulated around the real CLIP ViT-B/32 text embeddings of the class names "
            "(qr_cl/app/scenes/room_features.py): a mask's feature names its own class among the 19 for "
            f"{100 * min(acc):.0f}-{100 * max(acc):.0f} % of the masks of these rooms (CLIP on object crops: about "
            "60-75 %)." if acc else "")


def report_markdown(results: dict) -> str:
    """The report of ``results`` (as :func:`qr_cl.app.experiments.command.run_reproduction` returns and
    results.json holds)."""
    plan = results["plan"]
    lines = [f"# qr-cl reproduce ({results['mode']})", "",
             f"GS-Net (small sparse UNet) trained on {len(results['scenes']['train'])} synthetic \"3dgs\" rooms "
             f"({plan['room']}) for {plan['steps']} steps of {plan['views']} views x {plan['rays']} rays through each "
             f"renderer (the same budget), evaluated on the held-out room {results['scenes']['held_out']} (ground "
             "truth: the generator's per-Gaussian labels, opacity >= 0.1). " + _features_sentence(results) +
             f" Every run is repeated with {plan['seeds']} seeds (network initialisation and rays): tables give the "
             "mean ± standard deviation over them, and a claim counts as reproduced or not only when the bands do "
             f"not overlap (else undecided). Device: {results['device']}. Whole run: {results['wall_s'] / 60:.1f} "
             "min.", ""]
    lines += table2_section(results)
    lines += ["## Scenes against real captures", "",
             "Entries: the Gaussians V-Render blends per ray (alpha >= 1/255 until T < 1e-4), over the rays that hit "
             "anything; 90 % weight: the fewest Gaussians holding 90 % of a ray's weight (mean over sampled hit rays), "
             "how many Gaussians really shape a ray's colour or feature.", "",
             "| scene | kind | Gaussians | views | size | mean opacity | entries per hit pixel: mean | "
             "median | p90 | Gaussians holding 90 % weight | pixels hit |", "| --- " * 11 + "|"]
    for s in results["statistics"]:
        lines.append(f"| {s['scene']} | {s['kind']} | {s['n_gaussians']} | {s['views']} | {s['size']} | "
                     f"{s['opacity_mean']:.2f} | {s['entries_mean']:.1f} | {s['entries_median']:.0f} | "
                     f"{s['entries_p90']:.0f} | {s['holding_90']:.1f} | {s['coverage']:.0%} |")
    lines += ["", "![opacity histograms and entries per pixel](scene_statistics.png)", "",
              "## Renderers (held-out room; Fig. 4)", "",
              "Rendering time: whole images of 512-D features per view at "
              f"{plan['timing_size'][0]}x{plan['timing_size'][1]} on the held-out room "
              f"(min of {plan['timing_rounds']} rounds over {plan['timing_views']} views); training time of the run; "
              "cos to V: mean cosine similarity of the renderer's feature image to V-Render's (first view, pixels with "
              "V-Render alpha >= 0.5, features of the V-Render run's GS-Net).", "",
              "| renderer | mIoU19 | mAcc19 | mIoU15 | mIoU10 | paper mIoU19 | render ms | cos to V | train s | "
              "final loss |",
              "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for sampler, k, label in clean_renderers(results):
        runs = runs_of(results, sampler, k)
        lines.append(f"| {label} | " + " | ".join(stat_cell(metric(results, sampler, k, key=m))
                                                 for m in ("miou19", "macc19", "miou15", "miou10")) +
                     f" | {_fmt(_paper_miou(sampler, k), 2)} | {_fmt(render_ms(results, sampler, k))} | "
                     f"{_fmt(cosine_to_volume(results, sampler, k), 4)} | "
                     f"{sum(r['train_s'] for r in runs) / len(runs):.0f} | "
                     f"{sum(r['final_loss'] for r in runs) / len(runs):.3f} |")
    lines += [f"| fused V-Render kernel (no selection) | | | | | | {_fmt(render_ms(results, FUSED_NAME))} | | | |", "",
              "![mIoU vs rendering time](miou_vs_time.png)", ""]
    lines += segmentation_section(results)
    lines += ["## Opacity noise (Q-Render K=40)", "",
              "| noise scale | mIoU19 | mAcc19 | paper mIoU19 |", "| ---: | ---: | ---: | ---: |"]
    scales = sorted({r["noise"] for r in results["runs"] if r["sampler"] == "quantile" and r["k"] == NOISE_K})
    lines += [f"| {s:g} | {stat_cell(metric(results, 'quantile', NOISE_K, s))} | "
              f"{stat_cell(metric(results, 'quantile', NOISE_K, s, 'macc19'))} | {_fmt(PAPER['noise'].get(s), 2)} |"
              for s in scales]
    prof = results["profiles"]
    lines += ["", f"## Transmittance profiles (Fig. 3), K={prof['k']}", "",
              f"Over {prof['rays']} random hit rays of the held-out room's first view (V-Render blends "
              f"{prof['entries_mean']:.1f} Gaussians per ray there), at the depths of V-Render's entries: the mean "
              "|T_sampler - T_V-Render| (T of a K sampler: its un-normalized transmittance among the selected "
              "Gaussians, as plotted) and the mean gap between the normalized cumulative weights (1 - T) / (1 - T_end) "
              "(where along the ray the rendered feature takes its weight; 0 = V-Render's depth weighting).", "",
              "| sampler | mean T gap | mean weight-CDF gap |", "| --- | ---: | ---: |"]
    lines += [f"| {name} | {t_gap:.3f} | {cdf_gap:.3f} |" for name, (t_gap, cdf_gap) in prof["gap"].items()]
    lines += [""] + [f"![transmittance]({f})" for f in prof["files"]] + [""]
    lines += ray_depth_section(results)
    lines += ["", "## RGB fidelity (from SH colours)", "",
              "PSNR against V-Render (black background, values clipped to [0, 1]) of the raw normalized Q-Render "
              "image, of Q-Render's colour times V-Render's alpha, and of Q-Render's colour times its own alpha (the "
              "alpha `rasterize(sampler=\"quantile\")` returns: 1 - T where its walk stopped), and for comparison "
              "top-K's colour times V-Render's alpha. Pictures: V-Render | raw Q-Render | Q-Render x V-Render alpha | "
              "4x |V - raw Q| (largest K).", "",
              "| scene | views | size | K | raw Q-Render dB | Q-Render x V alpha dB | Q-Render x own alpha dB | "
              "top-K x V alpha dB |", "| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: |"]
    lines += [f"| {r['scene']} | {r['views']} | {r['size']} | {r['k']} | {_fmt(r['psnr_raw'])} | "
              f"{_fmt(r['psnr_alpha'])} | {_fmt(r['psnr_own_alpha'])} | {_fmt(r.get('psnr_topk_alpha'))} |"
              for r in results["rgb"]]
    lines += [""] + [f"![rgb {s}](rgb_{s}.png)" for s in dict.fromkeys(r["scene"] for r in results["rgb"])]
    lines += ["", "## The paper's claims", "",
              "Reproduced or not only where the seeds' bands do not overlap; \"seeds resolve\": the smallest "
              "difference (past the claim's margin) the bands decide, which an undecided claim's difference lacks.", "",
              "| claim | measured | verdict | seeds resolve |", "| --- | --- | --- | --- |"]
    lines += [f"| {c['claim']} | {c['measured']} | {c['verdict']} | {c.get('resolution', '-')} |"
              for c in results["claims"]]
    return "\n".join(lines) + "\n"


def write_report(out: Path, results: dict) -> list[Path]:
    """results.json, report.md, miou_vs_time.png and scene_statistics.png into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    files = [out / "results.json", out / "report.md", out / "miou_vs_time.png", out / "scene_statistics.png"]
    files[0].write_text(json.dumps(results, indent=1, default=str))
    files[1].write_text(report_markdown(results))
    plot_miou_vs_time(results, files[2])
    plot_scene_statistics(results["statistics"], files[3])
    return files
