"""bench/train_scale.py: the report of its measurements, and (slow) a run on tiny rooms."""
from __future__ import annotations

import json

import pytest

import train_scale


def run(wall: float, cpu: float, warnings: list[str]) -> dict:
    return {"wall_s": wall, "cpu_s": cpu, "peak_gb": 1.0, "warnings": warnings, "touched": 0.5,
            "load_before": 1.0, "load_after": 1.5}


def test_report_has_a_row_and_a_growth_row_per_size():
    sizes = [{"gaussians": n, "voxels": v, "touched_gaussians": n / 2, "s_per_step": t, "peak_gb": p,
              "cores_busy": 1.0, "runs": [run(1, 1, []), run(2, 2, ["view_selections_mb=1 is full"])]}
             for n, v, t, p in ((1000, 10, 0.5, 1.0), (4000, 20, 1.0, 3.0))]
    results = {"command": "python bench/train_scale.py", "cpu": "CPU", "cores": 2, "memory_gb": 24, "extra": [], "room": {"width": 64, "height": 48, "views": 2},
               "short": 1, "long": 3, "rounds": 1, "sizes": sizes}
    text = train_scale.report(results)
    assert "| 4,000 | 20 | 2,000 | 1.00 | 3.00 | 1.00 |" in text
    assert "| 4,000 | 4.00x | 2.00x | 4.00x | 2.00x | 3.00x |" in text
    assert "- 1,000: view_selections_mb=1 is full" in text
    assert train_scale.per_step(run(10, 0, []), run(30, 0, []), 10) == 2.0


@pytest.mark.slow
def test_tiny_rooms_are_measured(tmp_path, monkeypatch):
    monkeypatch.setattr("sys.argv", ["train_scale.py", "--out", str(tmp_path / "r"), "--sizes", "3000", "6000",
                                     "--width", "80", "--height", "60", "--views", "4", "--short", "1",
                                     "--long", "2", "--cache", str(tmp_path / "cache"), "--view-selections-mb", "1"])
    train_scale.main()
    results = json.loads((tmp_path / "r" / "results.json").read_text())
    assert [row["gaussians"] for row in results["sizes"]] == [3000, 6000]
    assert all(row["peak_gb"] > 0.1 and row["voxels"] > 0 for row in results["sizes"])
    assert "view_selections_mb=1 is full" in (tmp_path / "r" / "report.md").read_text()
