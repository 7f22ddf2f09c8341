"""The reproduction's report: report.md (tables, the paper's claims checked against the numbers),
results.json and the figures."""
from __future__ import annotations

import json
import math
from pathlib import Path

from ..renderers import FUSED_NAME
from .claims import PAPER, cosine_to_volume, find_run, first_seed_runs, render_ms, verdict
from .figures import plot_miou_vs_time
from .plan import NOISE_K
from .scene_statistics import plot_scene_statistics


def _fmt(value: float | None, digits: int = 1) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"


def _paper_miou(run: dict) -> float | None:
    """The paper's Fig. 4 mIoU of a clean run's renderer (None where the paper has none)."""
    entry = PAPER.get(run["sampler"])
    return entry.get(run["k"]) if isinstance(entry, dict) else entry


def _spread(results: dict) -> str:
    """A sentence on the run-to-run spread: Q-Render K=40 trained with two seeds."""
    first, again = find_run(results, "quantile", NOISE_K), find_run(results, "quantile", NOISE_K, seed=1)
    if not (first and again):
        return "One seed per run; the run-to-run spread was not measured."
    return (f"One seed per run; Q-Render K=40 trained again with the next seed scored mIoU19 {again['miou19']:.1f} "
            f"against {first['miou19']:.1f} ({again['miou19'] - first['miou19']:+.1f} points): differences of that "
            "size between renderers are within run-to-run noise.")


def baseline_section(results: dict) -> list[str]:
    """The report's lines comparing GS-Net with the per-scene baseline on the held-out room."""
    base, reached = results.get("baseline"), results.get("reached")
    if not base:
        return []
    lines = ["## GS-Net against a per-scene model (held-out room; Table 1)", "",
             "The per-scene baseline fits free per-Gaussian features on the held-out room itself "
             f"(qr_cl/app/training/baseline.py) with GS-Net's budget through Q-Render K={NOISE_K}; GS-Net never saw "
             "the room. \"all\": every labelled Gaussian; \"reached\": the labelled Gaussians that some pixel's "
             f"Q-Render K={NOISE_K} selection in the room's views holds ({reached['gaussians']} of "
             f"{reached['labelled']}), the only ones the baseline's rays can train: the others keep their random "
             "initial features.", "",
             "| model | mIoU19 all | mAcc19 all | mIoU19 reached | mAcc19 reached | train s |",
             "| --- | ---: | ---: | ---: | ---: | ---: |"]
    rows = [base] + [r for r in (find_run(results, "quantile", NOISE_K), find_run(results, "volume")) if r]
    lines += [f"| {'GS-Net, ' if r is not base else ''}{r['label']} | {_fmt(r['miou19'])} | {_fmt(r['macc19'])} | "
              f"{_fmt(r['miou19_reached'])} | {_fmt(r['macc19_reached'])} | {r['train_s']:.0f} |" for r in rows]
    return lines + [""]


def report_markdown(results: dict) -> str:
    """The report of ``results`` (as :func:`qr_cl.app.reproduce.run_reproduction` returns and
    results.json holds)."""
    plan = results["plan"]
    lines = [f"# qr-cl reproduce ({results['mode']})", "",
             f"GS-Net (small sparse UNet) trained on {len(results['scenes']['train'])} synthetic \"3dgs\" rooms "
             f"({plan['room']}) for {plan['steps']} steps of {plan['views']} views x {plan['rays']} rays through each "
             f"renderer (the same budget), evaluated on the held-out room {results['scenes']['held_out']} (ground "
             "truth: the generator's per-Gaussian labels, opacity >= 0.1). The \"CLIP\" features are simulated "
             f"(qr_cl/app/scenes/synthetic.py). {_spread(results)} Device: {results['device']}. Whole run: "
             f"{results['wall_s'] / 60:.1f} min.", "",
             "## Scenes against real captures", "",
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
    for r in (r for r in results["runs"] if not r["noise"]):
        lines.append(f"| {r['label']} | {_fmt(r['miou19'])} | {_fmt(r['macc19'])} | {_fmt(r['miou15'])} | "
                     f"{_fmt(r['miou10'])} | {_fmt(_paper_miou(r), 2)} | "
                     f"{_fmt(render_ms(results, r['sampler'], r['k']))} | "
                     f"{_fmt(cosine_to_volume(results, r['sampler'], r['k']), 4)} | "
                     f"{r['train_s']:.0f} | {r['final_loss']:.3f} |")
    lines += [f"| fused V-Render kernel (no selection) | | | | | | {_fmt(render_ms(results, FUSED_NAME))} | | | |", "",
              "![mIoU vs rendering time](miou_vs_time.png)", ""]
    lines += baseline_section(results)
    lines += ["## Opacity noise (Q-Render K=40)", "",
              "| noise scale | mIoU19 | mAcc19 | paper mIoU19 |", "| ---: | ---: | ---: | ---: |"]
    for r in sorted((r for r in first_seed_runs(results) if r["sampler"] == "quantile" and r["k"] == NOISE_K),
                    key=lambda r: r["noise"]):
        lines.append(f"| {r['noise']:g} | {_fmt(r['miou19'])} | {_fmt(r['macc19'])} | "
                     f"{_fmt(PAPER['noise'].get(r['noise']), 2)} |")
    prof = results["profiles"]
    lines += ["", f"## Transmittance profiles (Fig. 3), K={prof['k']}", "",
              f"Over {prof['rays']} random hit rays of the held-out room's first view (V-Render blends "
              f"{prof['entries_mean']:.1f} Gaussians per ray there), at the depths of V-Render's entries: the mean "
              "|T_sampler - T_V-Render| (T of a K sampler: its un-normalized transmittance among the selected "
              "Gaussians, as plotted) and the mean gap between the normalized cumulative weights (1 - T) / (1 - T_end) "
              "(where along the ray the rendered feature takes its weight; 0 = V-Render's depth weighting).", "",
              "| sampler | mean T gap | mean weight-CDF gap |", "| --- | ---: | ---: |"]
    lines += [f"| {name} | {t_gap:.3f} | {cdf_gap:.3f} |" for name, (t_gap, cdf_gap) in prof["gap"].items()]
    lines += [""] + [f"![transmittance]({f})" for f in prof["files"]]
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
    lines += ["", "## The paper's claims", "", "| claim | measured | verdict |", "| --- | --- | --- |"]
    lines += [f"| {c['claim']} | {c['measured']} | {verdict(c['holds'])} |" for c in results["claims"]]
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
