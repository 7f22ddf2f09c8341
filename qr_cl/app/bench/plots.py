"""The bench report's plots: time against K and against C, fractions of the roofline, complexity."""
from __future__ import annotations

from pathlib import Path

from matplotlib.ticker import NullFormatter

from ...runtime import SAMPLERS
from ..images import plt  # pyplot on the file-only Agg backend
from .report import find_row


def write_plots(report: dict, out: Path) -> None:
    """time_vs_k.png, time_vs_c.png, roofline.png and complexity.png into ``out``."""
    rows = report["results"]
    blend = [r for r in rows if r["stage"] == "blend-forward" and r["sampler"] in SAMPLERS]
    if not blend:
        return
    sc = dict(scene=blend[0]["scene"], width=blend[0]["width"], height=blend[0]["height"])
    c_main = max(r["channels"] for r in blend)
    fig, ax = plt.subplots(figsize=(6, 4))
    for sampler in (s for s in SAMPLERS if s != "volume"):
        pts = sorted((r["k"], r["min_s"] + find_row(rows, stage="selection", sampler=sampler, k=r["k"], **sc)["min_s"])
                     for r in blend if r["sampler"] == sampler and r["channels"] == c_main and r["scene"] == sc["scene"]
                     and r["width"] == sc["width"])
        if pts:
            ax.plot(*zip(*[(k, t * 1e3) for k, t in pts]), "o-", label=f"{sampler} (select + blend)")
    for name, row in (("volume (select + blend)", find_row(rows, stage="blend-forward", sampler="volume", channels=c_main, **sc)),
                      ("fused V-Render", find_row(rows, stage="fused", channels=c_main, **sc))):
        if row:
            t = row["min_s"] + (find_row(rows, stage="selection", sampler="volume", **sc)["min_s"] if "select" in name else 0)
            ax.axhline(t * 1e3, linestyle="--", color="gray" if "fused" in name else "black", label=name)
    ax.set(xlabel="K", ylabel="ms", title=f"{sc['scene']} {sc['width']}x{sc['height']}, C={c_main}")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(out / "time_vs_k.png", dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    ks = sorted({r["k"] for r in blend if r["sampler"] == "quantile"})
    k_c = 40 if 40 in ks else ks[-1]
    for sampler in SAMPLERS:
        pts = sorted((r["channels"], r["min_s"]) for r in blend if r["sampler"] == sampler and
                     r["k"] == (k_c if sampler != "volume" else 0) and r["scene"] == sc["scene"] and r["width"] == sc["width"])
        if pts:
            ax.plot(*zip(*[(c, t * 1e3) for c, t in pts]), "o-", label=f"{sampler} blend")
    fused = sorted((r["channels"], r["min_s"] * 1e3) for r in rows if r["stage"] == "fused" and r["scene"] == sc["scene"]
                   and r["width"] == sc["width"])
    if fused:
        ax.plot(*zip(*fused), "s--", color="gray", label="fused V-Render")
    ax.set(xscale="log", yscale="log", xlabel="C (channels)", ylabel="ms",
           title=f"{sc['scene']} {sc['width']}x{sc['height']}, K={k_c}")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "time_vs_c.png", dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 4))
    sel_rows = [r for r in blend if r["scene"] == sc["scene"] and r["width"] == sc["width"]]
    labels = [f"{r['sampler'][:5]} K{r['k']} C{r['channels']}" for r in sel_rows]
    ax.barh(labels, [r["fraction_of_roofline"] for r in sel_rows], label="of analytic roofline")
    ax.barh(labels, [r["fraction_of_bare_gather"] for r in sel_rows], alpha=0.5, label="of bare gather-blend")
    ax.set(xlabel="fraction of the limit (1 = at the limit)", title="blend forward")
    ax.tick_params(axis="y", labelsize=7)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "roofline.png", dpi=110)
    plt.close(fig)

    comp = report["complexity"]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.8))
    for sampler in comp["fits"]:
        pts = [p for p in comp["points"] if p["sampler"] == sampler]
        by_n = sorted((p["N"], p["seconds"] * 1e3) for p in pts if p["C"] == comp["C_fixed"])
        by_c = sorted((p["C"], p["seconds"] * 1e3) for p in pts if p["N"] == comp["N_fixed"])
        fit = comp["fits"][sampler]
        axes[0].plot(*zip(*by_n), "o-", label=f"{sampler} (N^{fit['exponent_N']:.2f})")
        axes[1].plot(*zip(*by_c), "o-", label=f"{sampler} (C^{fit['exponent_C']:.2f})")
    axes[0].set(xscale="log", yscale="log", xlabel="Gaussians per ray N", ylabel="ms",
                title=f"C={comp['C_fixed']}")
    axes[1].set(xscale="log", yscale="log", xlabel="C", title=f"N={comp['N_fixed']}")
    for a in axes:
        a.legend(fontsize=7)
        a.xaxis.set_minor_formatter(NullFormatter())
        a.yaxis.set_minor_formatter(NullFormatter())
    fig.tight_layout()
    fig.savefig(out / "complexity.png", dpi=110)
    plt.close(fig)
