"""The bench report: the summary in markdown (headline ratios, the renderer end to end, gradients,
per stage, complexity fits) and the comparison of two reports. The report format
(:data:`REPORT_VERSION`) is stable so that two reports, e.g. from two devices, can be compared
with ``qr-cl bench compare A.json B.json``."""
from __future__ import annotations

import datetime
import json
import platform
from pathlib import Path

from ...runtime import SAMPLERS, Runtime
from ..renderers import FUSED_NAME

REPORT_VERSION = 1


def report_meta(rt: Runtime, mode: str) -> dict:
    """The device, driver, host, Python, mode and date of a report."""
    dev = rt.device
    return {"device": dev.name.strip(), "platform": dev.platform.name.strip(),
            "driver": dev.driver_version, "compute_units": dev.max_compute_units,
            "host": platform.node(), "python": platform.python_version(), "mode": mode,
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}


def find_row(rows: list[dict], **match) -> dict | None:
    """The first of ``rows`` whose fields equal every value of ``match`` (None if none does)."""
    return next((r for r in rows if all(r.get(k) == v for k, v in match.items())), None)


def _ms(row: dict | None) -> str:
    return "-" if row is None else f"{row['min_s'] * 1e3:.1f}"


def _fault_count(row: dict | None) -> str:
    return "-" if row is None or "faults_per_call" not in row else f"{row['faults_per_call']:.0f}"


def _faults(row: dict) -> str:
    return "" if "faults_per_call" not in row else f" ({row['faults_per_call']:.0f} page faults per warm call)"


def _renderer_table(rows: list[dict]) -> list[str]:
    """Markdown lines of the renderer's headline figures per scene with end-to-end rows: the walk
    (fused V-Render at C=3), Q-Render end to end against the fused V-Render of the same run, end
    to end over select + blend, the blend against the roofline and the bare gather-blend, backward
    over forward, and the training path (:meth:`qr_cl.app.bench.sweep.Sweep.training_path`)."""
    scenes = {(r["scene"], r["width"], r["height"]) for r in rows if r["stage"] == "end-to-end"
              and r["sampler"] == "quantile"}
    if not scenes:
        return []
    lines = ["## The renderer end to end", "", "| scene | WxH | walk: fused C=3 | Q-Render K | C | Q end to end | "
             "fused V-Render end to end | fused / Q | Q end to end / (select + blend) | Q blend fwd / roofline | "
             "Q blend fwd / bare gather | Q blend bwd / fwd | page faults per warm Q render | "
             "training path: 4 x 2048 rays, fwd + bwd |", "| --- " * 14 + "|"]
    for name, width, height in sorted(scenes):
        sc = dict(scene=name, width=width, height=height)
        walk = find_row(rows, stage="fused", channels=3, **sc)
        for q in (r for r in rows if r["stage"] == "end-to-end" and r["sampler"] == "quantile"
                  and all(r[key] == v for key, v in sc.items())):
            c, k = q["channels"], q["k"]
            fused = find_row(rows, stage="end-to-end", sampler=FUSED_NAME, channels=c, **sc)
            sel = find_row(rows, stage="selection", sampler="quantile", k=k, **sc)
            fwd = find_row(rows, stage="blend-forward", sampler="quantile", k=k, channels=c, **sc)
            bwd = find_row(rows, stage="blend-backward", sampler="quantile", k=k, channels=c, **sc)
            if not (fused and sel and fwd and bwd):
                continue
            train = find_row(rows, stage="training-path", k=k, channels=c, **sc)
            lines.append(f"| {name} | {width}x{height} | {_ms(walk)} | {k} | {c} | {_ms(q)} | {_ms(fused)} | "
                         f"{fused['min_s'] / q['min_s']:.2f}x | {q['min_s'] / (sel['min_s'] + fwd['min_s']):.2f} | "
                         f"{fwd['fraction_of_roofline']:.0%} | {fwd['fraction_of_bare_gather']:.0%} | "
                         f"{bwd['min_s'] / fwd['min_s']:.2f} | {_fault_count(q)} | {_ms(train)} |")
    return lines + [""]


def _gradient_table(rows: list[dict]) -> list[str]:
    """Markdown lines: qr_cl.rasterization forward vs forward + backward w.r.t. the Gaussians."""
    both = [r for r in rows if r["stage"] == "rasterization-forward-backward"]
    if not both:
        return []
    lines = ["## Gradients w.r.t. the Gaussians (qr_cl.rasterization, RGB from SH)", "",
             "| scene | WxH | sampler | K | forward | forward + backward | ratio |", "| --- " * 7 + "|"]
    for r in both:
        fwd = find_row(rows, stage="rasterization-forward", scene=r["scene"], sampler=r["sampler"], k=r["k"])
        lines.append(f"| {r['scene']} | {r['width']}x{r['height']} | {r['sampler']} | {r['k'] or '-'} | "
                     f"{_ms(fwd)} | {_ms(r)} | {r['over_forward']:.2f}x |")
    return lines + [""]


def summary_markdown(report: dict) -> str:
    """The markdown summary: headline ratios, the per-stage table, limits and complexity fits."""
    rows, meta, lim = report["results"], report["meta"], report["limits"]
    lines = [f"# qr-cl bench ({meta['mode']})", "",
             f"Device: {meta['device']} ({meta['platform']}, driver {meta['driver']}), {meta['date']}.",
             f"Limits measured here: streaming bandwidth {lim['bandwidth_bytes_s'] / 1e9:.1f} GB/s, "
             f"FMA rate {lim['fma_flops'] / 1e9:.0f} GFLOP/s. gsplat: {report['gsplat']}.",
             "Times are minima over the rounds (ms); ratios are against timings of the same run.", ""]
    head = next((r for r in rows if r["stage"] == "end-to-end" and r["sampler"] == "quantile"
                 and (r["k"], r["channels"]) in ((40, 512), (10, 16))), None)
    if head:
        sc = dict(scene=head["scene"], width=head["width"], height=head["height"])
        k, c = head["k"], head["channels"]
        q_sel = find_row(rows, stage="selection", sampler="quantile", k=k, **sc)
        q_fwd = find_row(rows, stage="blend-forward", sampler="quantile", k=k, channels=c, **sc)
        q = q_sel["min_s"] + q_fwd["min_s"]
        fused = find_row(rows, stage="fused", channels=c, **sc)
        baselines = [(f"fused V-Render (C={c})", fused),
                     (f"looped 3-channel V-Render x ceil({c}/3)", find_row(rows, stage="looped-3ch", channels=c, **sc)),
                     ("torch embedding_bag blend (same selection)",
                      find_row(rows, sampler="torch-embedding_bag", **sc)),
                     ("numpy blend (same selection)", find_row(rows, sampler="numpy", **sc))]
        lines += [f"## Q-Render (K={k}, C={c}) on {head['scene']} at {head['width']}x{head['height']}", "",
                  f"Q-Render selection + blend: {q * 1e3:.1f} ms (selection {_ms(q_sel)}, blend {_ms(q_fwd)}); "
                  f"end to end (projection to image): {_ms(head)} ms{_faults(head)}. Blend at "
                  f"{q_fwd['fraction_of_roofline']:.0%} of the roofline and "
                  f"{q_fwd['fraction_of_bare_gather']:.0%} of the bare coherent gather-blend.", "",
                  "| baseline | ms | baseline / Q-Render |", "| --- | --- | --- |"]
        for name, row in baselines:
            if row:
                cmp_t = q_fwd["min_s"] if row["stage"] == "blend-forward" else q
                lines.append(f"| {name} | {_ms(row)} | {row['min_s'] / cmp_t:.2f}x |")
        lines += ["", "(blend-only baselines are compared with Q-Render's blend; the others with "
                  "Q-Render's selection + blend)", ""]
    lines += _renderer_table(rows)
    lines += _gradient_table(rows)
    lines += ["## Per stage", "", "| scene | WxH | sampler | K | C | selection | blend fwd | blend bwd | "
              "fused | end-to-end | end-to-end page faults | blend fwd / roofline | mean entries | peak host MB |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        if r["stage"] != "blend-forward" or r["sampler"] not in SAMPLERS:
            continue
        sc = dict(scene=r["scene"], width=r["width"], height=r["height"])
        sel = find_row(rows, stage="selection", sampler=r["sampler"], k=r["k"], **sc)
        bwd = find_row(rows, stage="blend-backward", sampler=r["sampler"], k=r["k"], channels=r["channels"], **sc)
        fused = find_row(rows, stage="fused", channels=r["channels"], **sc)
        e2e = find_row(rows, stage="end-to-end", sampler=r["sampler"], channels=r["channels"],
                    k=r["k"] if r["sampler"] != "volume" else 0, **sc)
        peak = max(x.get("peak_host_bytes", 0) for x in (r, bwd or r)) / 2 ** 20
        lines.append(f"| {r['scene']} | {r['width']}x{r['height']} | {r['sampler']} | {r['k'] or '-'} | "
                     f"{r['channels']} | {_ms(sel)} | {_ms(r)} | {_ms(bwd)} | {_ms(fused)} | {_ms(e2e)} | "
                     f"{_fault_count(e2e)} | "
                     f"{r['fraction_of_roofline']:.0%} | {r['mean_entries']:.1f} | {peak:.0f} |")
    comp = report["complexity"]
    lines += ["", f"## Complexity (layered scenes, {comp['width']}x{comp['height']}, K={comp['k']})", "",
              f"Fitted exponents of select+blend time: t ~ N^a at C={comp['C_fixed']}, "
              f"t ~ C^b at N={comp['N_fixed']} (paper: V-Render O(NC), top-K O(N log K + KC), "
              "Q-Render O(N + KC)). The walk over the N Gaussians of a ray is O(N) for every sampler; "
              "what differs is the cost of a channel (slope of t vs C): proportional to N for "
              "V-Render, to K for top-K and Q-Render.", "",
              "| sampler | a (N) | b (C) | ms per channel | per channel / Q-Render's |",
              "| --- | --- | --- | --- | --- |"]
    q_slope = comp["fits"]["quantile"]["ms_per_channel"]
    lines += [f"| {s} | {f['exponent_N']:.2f} | {f['exponent_C']:.2f} | {f['ms_per_channel']:.4f} | "
              f"{f['ms_per_channel'] / q_slope:.1f} |" for s, f in comp["fits"].items()]
    for name in ("projection", "binning+sort"):
        for r in rows:
            if r["stage"] == name and r["scene"] in ("fox", "donut") or r["stage"] == name and "synthetic" in r["scene"]:
                lines.append(f"\n{name} {r['scene']} {r['width']}x{r['height']} ({r['n_gaussians']} Gaussians): "
                             f"{_ms(r)} ms")
    return "\n".join(lines) + "\n"


def compare(path_a: str, path_b: str) -> str:
    """Markdown table of B / A time ratios for the rows two reports share."""
    a, b = (json.loads(Path(p).read_text()) for p in (path_a, path_b))
    for p, r in ((path_a, a), (path_b, b)):
        if r.get("version") != REPORT_VERSION:
            raise ValueError(f"{p}: report version {r.get('version')}, expected {REPORT_VERSION}")
    key = lambda r: (r["scene"], r["width"], r["height"], r["stage"], r["sampler"], r["k"], r["channels"])  # noqa: E731
    rows_a = {key(r): r for r in a["results"]}
    lines = [f"A: {a['meta']['device']} ({path_a})", f"B: {b['meta']['device']} ({path_b})", "",
             "| scene | WxH | stage | sampler | K | C | A ms | B ms | B / A |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in b["results"]:
        if key(r) in rows_a:
            ra = rows_a[key(r)]
            lines.append(f"| {r['scene']} | {r['width']}x{r['height']} | {r['stage']} | {r['sampler']} | "
                         f"{r['k'] or '-'} | {r['channels'] or '-'} | {ra['min_s'] * 1e3:.2f} | "
                         f"{r['min_s'] * 1e3:.2f} | {r['min_s'] / ra['min_s']:.2f} |")
    return "\n".join(lines) + "\n"
