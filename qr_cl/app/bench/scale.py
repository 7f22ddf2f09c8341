"""``qr-cl bench scale``: how each stage's cost grows with the number of Gaussians N.

The dense indoor room of :func:`qr_cl.app.scenes.procedural.dense_room` (layered semi-transparent
walls and floaters) at N = 300k, 1M and 3M, one 640x480 camera, 512-D features (float32, or
float16 with ``table_dtype``) and Q-Render K=40. Per N: projection, binning+sort, selection,
blend forward and the feature backward (:class:`qr_cl.app.bench.sweep.Sweep`'s stage timings),
the public call end to end, the process's peak resident memory above its level before the scene
was made (PoCL's buffers are host memory, so the device's arrays count too), the feature table's
own size, and the peak of one public call above the level before it (the table resident): what
a render costs beyond its table.

The cost model it checks: projection and the tile sort are O(N) (every Gaussian is projected,
each visible one keyed once per tile it touches); the selection walk is O(pixels x entries per
tile list), which grows with N only through the depth complexity of the lists; blend forward and
backward are O(pixels x K x C), bounded by K whatever N is; the feature table itself is
O(N x C) memory.
"""
from __future__ import annotations

import json
from pathlib import Path

import torch
from tqdm import tqdm

from ...render import checked_runtime
from ...runtime import channel_layout
from ..images import plt
from ..renderers import SamplerRenderer
from ..scenes.views import dense_view
from ..timing import PeakMemory
from . import roofline
from .sweep import Sweep

SCALES = (300_000, 1_000_000, 3_000_000)
STAGES = ("projection", "binning+sort", "selection", "blend-forward", "blend-backward", "end-to-end")


def run_scale(out: Path, scales=SCALES, k: int = 40, channels: int = 512, size: tuple[int, int] = (640, 480),
              rounds: int = 2, table_dtype: str = "float32") -> dict:
    """Measure every N of ``scales`` (module docstring) with feature tables of ``table_dtype``
    ("float32" or "float16"); write scale.json, scale.md and scale.png into ``out`` and return
    the report {"rows", "memory", "k", "channels", "size", "table_dtype"}."""
    dtype = {"float32": torch.float32, "float16": torch.float16}[table_dtype]
    itemsize = torch.finfo(dtype).bits // 8
    out.mkdir(parents=True, exist_ok=True)
    rt = checked_runtime()
    sweep = Sweep(rounds, {"bandwidth_bytes_s": roofline.stream_bandwidth(rt, 64), "fma_flops": roofline.fma_rate(rt)})
    memory = []
    for n in tqdm(scales, desc="scale", unit="scene"):
        with PeakMemory() as peak:
            scene = dense_view(n, *size)
            sweep.plan(scene)
            sweep.sampler(scene, "quantile", k, stage_channels(rt, n, channels), dtype)
            call = sweep.end_to_end(scene, SamplerRenderer("quantile", k), channels, dtype)
        memory.append({"n_gaussians": len(scene.gaussians), "peak_bytes": peak.above_base,
                       "table_bytes": len(scene.gaussians) * channels * itemsize,
                       "call_peak_bytes": call["call_peak_bytes"]})
        del scene
    rows = [r for r in sweep.rows if r["stage"] in STAGES]
    report = {"k": k, "channels": channels, "size": list(size), "rows": rows, "memory": memory,
              "table_dtype": table_dtype, "max_buffer_bytes": rt.max_buffer_bytes}
    (out / "scale.json").write_text(json.dumps(report, indent=1))
    (out / "scale.md").write_text(scale_markdown(report))
    plot_scale(report, out / "scale.png")
    return report


def stage_channels(rt, n: int, channels: int) -> int:
    """The channels of the blend stages' rows at ``n`` Gaussians: ``channels``, halved until an
    [n, C] float32 table fits one device buffer: the backward's dF rows are float32 whatever the
    table's dtype (the public call takes a larger table in row parts itself; the stage rows time
    one buffer's table)."""
    while channels > 16 and n * channel_layout(channels)[2] * 4 > rt.max_buffer_bytes:
        channels //= 2
    return channels


def _ms(rows: list[dict], n: int, stage: str) -> float | None:
    row = next((r for r in rows if r["n_gaussians"] == n and r["stage"] == stage), None)
    return None if row is None else 1e3 * row["min_s"]


def blend_channels(report: dict) -> dict[int, int]:
    """N -> the channels the blend rows of ``report`` timed at N (:func:`stage_channels`)."""
    return {m["n_gaussians"]: next((r["channels"] for r in report["rows"] if r["n_gaussians"] == m["n_gaussians"]
                                    and r["stage"] == "blend-forward"), report["channels"]) for m in report["memory"]}


def scale_markdown(report: dict) -> str:
    """The scale table: ms per stage and peak memory against N, and each against the smallest N."""
    ns = [m["n_gaussians"] for m in report["memory"]]
    blend_c = blend_channels(report)
    w, h = report["size"]
    dtype = report.get("table_dtype", "float32")
    lines = [f"# Cost against the number of Gaussians (dense room, {w}x{h}, Q-Render K={report['k']}, "
             f"C={report['channels']} {dtype})", "",
             "Minimum wall ms over the rounds after a warm-up; x: against the smallest N. Peak memory: resident "
             "memory above the level before the scene was made (scene, plan, selection, feature table, image, "
             "and the stage rows' own table and dF); one call over its table: the "
             "peak of a first public call above the level before it, the table resident and the memory pools "
             "emptied. " +
             (f"The device's largest buffer: {report['max_buffer_bytes'] / 2**30:.1f} GiB (PoCL sizes it from the "
              "memory free when it starts). " if "max_buffer_bytes" in report else "") +
             "The blend rows time the largest table that fits one device buffer: C = " +
             ", ".join(f"{blend_c[n]} at N={n:,}" for n in ns) + "; end-to-end is the public call with all "
             f"{report['channels']} channels (a table over one buffer taken in row parts).", "",
             "| stage | " + " | ".join(f"N={n:,}" for n in ns) + " | " + " | ".join(f"x at {n:,}" for n in ns[1:]) + " |",
             "| --- |" + " ---: |" * (2 * len(ns) - 1)]
    for stage in STAGES:
        ms = [_ms(report["rows"], n, stage) for n in ns]
        if all(v is None for v in ms):
            continue
        cells = [f"{v:.1f}" if v is not None else "-" for v in ms]
        ratios = [f"{v / ms[0]:.2f}" if v and ms[0] else "-" for v in ms[1:]]
        lines.append(f"| {stage} | " + " | ".join(cells + ratios) + " |")
    mem = report["memory"]
    lines.append("| peak memory, GB | " + " | ".join(f"{m['peak_bytes'] / 1e9:.2f}" for m in mem) + " | " +
                 " | ".join(f"{m['peak_bytes'] / max(mem[0]['peak_bytes'], 1):.2f}" for m in mem[1:]) + " |")
    lines.append("| feature table, GB | " + " | ".join(f"{m['table_bytes'] / 1e9:.2f}" for m in mem) + " | " +
                 " | ".join(f"{m['table_bytes'] / mem[0]['table_bytes']:.2f}" for m in mem[1:]) + " |")
    if all("call_peak_bytes" in m for m in mem):
        first = mem[0]["call_peak_bytes"]
        lines.append("| one call over its table, GB | " + " | ".join(f"{m['call_peak_bytes'] / 1e9:.2f}" for m in mem)
                     + " | " + " | ".join(f"{m['call_peak_bytes'] / first:.2f}" if first > 0 else "-"
                                          for m in mem[1:]) + " |")
    return "\n".join(lines) + "\n"


def stage_label(report: dict, stage: str) -> str:
    """The plot's label of ``stage``: its name, with the channels where its rows time fewer than
    the report's (the blend rows of a table that fits one buffer, :func:`stage_channels`)."""
    fewer = {n: c for n, c in blend_channels(report).items() if c != report["channels"]}
    if not fewer or not stage.startswith("blend"):
        return stage
    return f"{stage} (" + ", ".join(f"C={c} at N={n:,}" for n, c in fewer.items()) + ")"


def plot_scale(report: dict, path: Path) -> None:
    """ms per stage against N, log-log, with the O(N) slope for reference; blend rows that time
    fewer channels at some N (a table that fits one buffer) say so in their label."""
    ns = [m["n_gaussians"] for m in report["memory"]]
    fig, ax = plt.subplots(figsize=(9, 4.5))
    for stage in STAGES:
        pts = [(n, _ms(report["rows"], n, stage)) for n in ns]
        pts = [p for p in pts if p[1] is not None]
        if pts:
            ax.plot(*zip(*pts), "o-", label=stage_label(report, stage))
    first = _ms(report["rows"], ns[0], "projection")
    if first:
        ax.plot(ns, [first * n / ns[0] for n in ns], ":", color="gray", label="O(N) from projection")
    ax.set(xscale="log", yscale="log", xlabel="Gaussians N", ylabel="ms (min over rounds)",
           title=f"dense room {report['size'][0]}x{report['size'][1]}, Q-Render K={report['k']}, "
                 f"C={report['channels']} {report.get('table_dtype', 'float32')}")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1))      # beside the lines, never on them
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
