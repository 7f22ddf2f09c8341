"""The report's figures: held-out mIoU against rendering time (the paper's Fig. 4a)."""
from __future__ import annotations

from pathlib import Path

from ..images import plt
from .claims import first_seed_runs, render_ms
from .plan import LABELS


def plot_miou_vs_time(results: dict, path: Path) -> None:
    """Fig. 4a: held-out mIoU19 against rendering time (ms per view) of every clean run."""
    fig, ax = plt.subplots(figsize=(6, 4))
    for sampler, style in (("topk", "s-"), ("quantile", "o-"), ("stratified", "^-"), ("volume", "D")):
        pts = sorted((r["k"], render_ms(results, sampler, r["k"]), r["miou19"]) for r in first_seed_runs(results)
                     if r["sampler"] == sampler and not r["noise"])
        pts = [p for p in pts if p[1] is not None]
        if pts:
            ax.plot([p[1] for p in pts], [p[2] for p in pts], style, label=LABELS[sampler])
            for k, t, m in pts:
                if k:
                    ax.annotate(f"K={k}", (t, m), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set(xlabel="rendering time per view (ms, 512-D features)", ylabel="held-out mIoU19 (%)",
           title="mIoU vs rendering time (Fig. 4a)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
