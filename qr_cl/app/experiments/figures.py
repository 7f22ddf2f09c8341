"""The report's figures: held-out mIoU against rendering time (the paper's Fig. 4a)."""
from __future__ import annotations

from pathlib import Path

from ..images import plt
from .claims import metric, render_ms
from .plan import LABELS


def plot_miou_vs_time(results: dict, path: Path) -> None:
    """Fig. 4a: held-out mIoU19 (mean over seeds, bars: standard deviation) against rendering time
    (ms per view) of every clean renderer."""
    fig, ax = plt.subplots(figsize=(6, 4))
    for sampler, style in (("topk", "s-"), ("quantile", "o-"), ("stratified", "^-"), ("volume", "D")):
        ks = sorted({r["k"] for r in results["runs"] if r["sampler"] == sampler and not r["noise"]})
        pts = [(k, render_ms(results, sampler, k), metric(results, sampler, k)) for k in ks]
        pts = [p for p in pts if p[1] is not None]
        if pts:
            ax.errorbar([p[1] for p in pts], [p[2].mean for p in pts], yerr=[p[2].std for p in pts], fmt=style,
                        capsize=3, label=LABELS[sampler])
            for k, t, m in pts:
                if k:
                    ax.annotate(f"K={k}", (t, m.mean), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set(xlabel="rendering time per view (ms, 512-D features)", ylabel="held-out mIoU19 (%)",
           title="mIoU vs rendering time (Fig. 4a)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
