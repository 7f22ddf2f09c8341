"""The ``qr-cl bench`` driver in its smoke mode: report, summary, plots and comparison."""
import json

import pytest

from qr_cl.app.bench.report import REPORT_VERSION
from qr_cl.app.cli import main
from qr_cl.runtime import SAMPLERS


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    assert main(["bench", "sweep", "--smoke", "--out", str(out)]) == 0
    return out


def test_report_has_every_stage_and_baseline(report_dir):
    report = json.loads((report_dir / "report.json").read_text())
    assert report["version"] == REPORT_VERSION and report["meta"]["mode"] == "smoke"
    stages = {(r["stage"], r["sampler"]) for r in report["results"]}
    for sampler in ("volume", "quantile", "topk"):
        for stage in ("selection", "blend-forward", "blend-backward", "end-to-end"):
            assert (stage, sampler) in stages
    for expected in [("projection", "-"), ("binning+sort", "-"), ("fused", "volume_fused"),
                     ("looped-3ch", "volume_fused"), ("blend-forward", "torch-embedding_bag"),
                     ("blend-forward", "numpy"), ("rasterization-forward", "volume"),
                     ("rasterization-forward-backward", "quantile"), ("training-path", "quantile")]:
        assert expected in stages
    train = [r for r in report["results"] if r["stage"] == "training-path"]
    assert {r["scene"] for r in train} == {"synthetic-2k", "dense-room-5k"}
    assert all(r["views"] == 4 and r["rays"] == 2048 for r in train)
    grads = [r for r in report["results"] if r["stage"] == "rasterization-forward-backward"]
    assert len(grads) == 2 and all(r["over_forward"] > 0 for r in grads)
    sizes = {(r["scene"], r["width"]) for r in report["results"]}
    assert {("synthetic-2k", 64), ("synthetic-2k", 32), ("synthetic-1k", 64)} <= sizes
    for row in report["results"]:
        assert 0 < row["min_s"] <= row["median_s"] and row["rounds"] >= 1 and row["spread_s"] >= 0
    assert report["limits"]["bandwidth_bytes_s"] > 1e8 and report["limits"]["fma_flops"] > 1e8
    fits = report["complexity"]["fits"]
    assert set(fits) == {"volume_fused", *SAMPLERS}
    points = report["complexity"]["points"]
    assert {p["N"] for p in points} == {8, 16, 32} and {p["C"] for p in points} == {4, 16, 64}


def test_summary_and_plots(report_dir):
    text = (report_dir / "summary.md").read_text()
    assert "## Q-Render (K=10, C=16)" in text and "looped 3-channel" in text and "embedding_bag" in text
    assert "## Complexity" in text and "## Gradients w.r.t. the Gaussians" in text
    assert "training path: 4 x 2048 rays" in text and "## The renderer end to end" in text
    for name in ("time_vs_k.png", "time_vs_c.png", "roofline.png", "complexity.png"):
        assert (report_dir / name).stat().st_size > 5000


def test_compare_two_reports(report_dir, capsys):
    path = str(report_dir / "report.json")
    assert main(["bench", "compare", path, path]) == 0
    table = capsys.readouterr().out
    assert "| 1.00 |" in table and "B / A" in table


def test_implementations_side_by_side_lists_shared_rows_and_refusals():
    from qr_cl.app.bench.implementations import side_by_side
    meta = dict(device="D", platform="P", driver="1", compute_units=2, mode="smoke", date="today")
    row = dict(scene="s", width=8, height=6, stage="selection", sampler="quantile", k=10, channels=0)
    a = {"meta": meta, "results": [{**row, "min_s": 0.002}, {**row, "stage": "fused", "min_s": 0.1}]}
    b = {"meta": {**meta, "device": "E"}, "results": [{**row, "min_s": 0.003}]}
    text = side_by_side({"pocl": a, "intel": b}, {"rusticl": "loop limit"})
    assert "**rusticl**: not run: loop limit" in text and "| pocl | intel |" in text
    assert "| s | 8x6 | selection | quantile | 10 | - | 2.00 | 3.00 (1.50x) |" in text
    assert "fused" not in text.split("| --- |")[-1]          # not shared: not in the table


@pytest.mark.slow
def test_scale_sweep_measures_every_stage_and_memory_against_n(tmp_path, capsys):
    from qr_cl.app.bench.scale import STAGES, run_scale
    report = run_scale(tmp_path, scales=(2000, 8000), channels=16, size=(64, 48), rounds=1)
    ns = [m["n_gaussians"] for m in report["memory"]]
    assert ns[0] < ns[1]
    for n in ns:
        assert {r["stage"] for r in report["rows"] if r["n_gaussians"] == n} == set(STAGES)
    assert all(m["peak_bytes"] > 0 and m["table_bytes"] == m["n_gaussians"] * 16 * 4 for m in report["memory"])
    table = (tmp_path / "scale.md").read_text()
    assert "| blend-backward |" in table and "| peak memory, GB |" in table and f"N={ns[1]:,}" in table
    assert "| one call over its table, GB |" in table
    assert (tmp_path / "scale.png").stat().st_size > 0
    assert main(["bench", "scale", "2000", "--table-dtype", "float16", "--out", str(tmp_path / "cli")]) == 0
    assert "scale.md" in capsys.readouterr().out
    half = json.loads((tmp_path / "cli" / "scale.json").read_text())
    assert half["table_dtype"] == "float16" and half["memory"][0]["table_bytes"] == half["memory"][0]["n_gaussians"] * 1024
    assert {r.get("table_dtype") for r in half["rows"] if r["stage"] in ("blend-forward", "end-to-end")} == {"float16"}


def test_scale_report_names_the_channels_of_blend_rows_that_time_fewer():
    """At 4 GiB a 3M x 512 float32 table does not fit one buffer, so the blend rows time C=256
    there: the table and the plot's blend labels say so."""
    from qr_cl.app.bench import scale
    rows = [{"n_gaussians": n, "stage": "blend-forward", "channels": c, "min_s": 0.1} for n, c in ((10, 512), (30, 256))]
    report = {"k": 40, "channels": 512, "size": [64, 48], "rows": rows,
              "memory": [{"n_gaussians": n, "peak_bytes": 1, "table_bytes": 1} for n in (10, 30)]}
    assert scale.blend_channels(report) == {10: 512, 30: 256}
    assert "C = 512 at N=10, 256 at N=30" in scale.scale_markdown(report)
    assert [scale.stage_label(report, s) for s in ("blend-forward", "blend-backward", "selection")] == [
        "blend-forward (C=256 at N=30)", "blend-backward (C=256 at N=30)", "selection"]
