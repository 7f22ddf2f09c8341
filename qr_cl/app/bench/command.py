"""``qr-cl bench``: per-stage kernel sweeps, baselines, roofline, complexity fit; JSON + markdown + plots.

Its subcommands: ``sweep`` (the report), ``compare A.json B.json`` (time ratios of two reports),
``scale [N ...]`` (cost and memory against the number of Gaussians) and ``implementations`` (the
sweep on every OpenCL implementation installed, side by side).

Every number is a wall time measured in this run with the OpenCL queue finished inside the timed
call, after a warm-up call; ratios compare timings from the same run. The sweep is a list of jobs
(:mod:`qr_cl.app.bench.jobs`) run by :class:`qr_cl.app.bench.sweep.Sweep`; the report format
(:data:`qr_cl.app.bench.report.REPORT_VERSION`) is stable so that two reports, e.g. from two
devices, can be compared with ``qr-cl bench compare A.json B.json``.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
from pathlib import Path

from tqdm import tqdm

from ...render import checked_runtime
from ..arguments import positive_int
from ..timing import Stopwatch
from . import roofline
from .complexity import complexity_fits, complexity_jobs
from .implementations import run_all
from .jobs import sweep_jobs, sweep_sizes
from .plots import write_plots
from .report import REPORT_VERSION, compare, report_meta, summary_markdown
from .scale import SCALES, run_scale
from .sweep import Sweep


def run_sweep(mode: str, out: Path, data: Path | None = None) -> dict:
    """Run the sweep of ``mode`` (sizes: :func:`qr_cl.app.bench.jobs.sweep_sizes`) on the real
    scenes of ``data`` (when given and the mode uses them) and synthetic ones, and the complexity
    sweep; write report.json, summary.md and plots into ``out``; return the report."""
    sizes = sweep_sizes(mode)
    rt = checked_runtime()
    out.mkdir(parents=True, exist_ok=True)
    jobs, layered = sweep_jobs(mode, sizes, data), complexity_jobs(sizes)
    limits = {"bandwidth_bytes_s": roofline.stream_bandwidth(rt, 64 if mode != "full" else 256),
              "fma_flops": roofline.fma_rate(rt)}
    sweep = Sweep(sizes["rounds"], limits)
    results = []
    for job in tqdm(jobs + layered, desc="qr-cl bench", unit="job"):
        results.append(sweep.run(job))
    report = {"version": REPORT_VERSION, "meta": report_meta(rt, mode), "limits": limits,
              "gsplat": "installed" if importlib.util.find_spec("gsplat") else "not installed",
              "results": sweep.rows, "complexity": complexity_fits(sizes, list(zip(layered, results[len(jobs):])))}
    tmp = out / "report.json.tmp"
    tmp.write_text(json.dumps(report, indent=1))
    os.replace(tmp, out / "report.json")
    (out / "summary.md").write_text(summary_markdown(report))
    write_plots(report, out)
    return report


def _mode_options(parser: argparse.ArgumentParser) -> None:
    """The sweep's size (``--quick``, ``--smoke``; the full sweep without either) and ``--data``."""
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="the small sweep (under 3 minutes on 2 cores)")
    size.add_argument("--smoke", action="store_true", help="a seconds-long run on tiny inputs (tests)")
    parser.add_argument("--data", default=os.environ.get("QR_CL_DATA"),
                        help="folder with the real scenes (wakufactory-fox/fox.ply, v3dg-donut/"
                             "donut_fused.ply; default $QR_CL_DATA): timed beside the synthetic ones")


def _device_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", help="OpenCL device (as QR_CL_DEVICE: cpu, gpu, <platform>:<index>)")


def _out_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="qr-cl-bench", help="report folder (default ./qr-cl-bench)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl bench`` and its subcommands."""
    sub = parser.add_subparsers(dest="bench", required=True, metavar="{sweep,compare,scale,implementations}")
    sweep = sub.add_parser("sweep", help="the per-stage sweep: report.json, summary.md and plots")
    _mode_options(sweep)
    _device_option(sweep)
    _out_option(sweep)
    comparison = sub.add_parser("compare", help="print B/A time ratios of two sweep reports")
    comparison.add_argument("reports", nargs=2, metavar=("A.json", "B.json"))
    scale = sub.add_parser("scale", help="per-stage time and peak memory against the number of Gaussians")
    scale.add_argument("n", type=positive_int, nargs="*", metavar="N",
                       help="numbers of Gaussians (dense room, 640x480, Q-Render K=40, C=512; "
                            f"default {' '.join(map(str, SCALES))})")
    scale.add_argument("--table-dtype", choices=("float32", "float16"), default="float32",
                       help="the feature tables' dtype (default float32)")
    _device_option(scale)
    _out_option(scale)
    implementations = sub.add_parser(
        "implementations", help="the sweep on PoCL and on every implementation tests/drivers/install.sh "
                                "installed, one after the other: implementations.md side by side")
    _mode_options(implementations)
    _out_option(implementations)


def run(args: argparse.Namespace) -> int:
    """``qr-cl bench SUBCOMMAND``: measure and write a report, or compare two reports."""
    if args.bench == "compare":
        print(compare(*args.reports))
        return 0
    if getattr(args, "device", None):
        os.environ["QR_CL_DEVICE"] = args.device
    out = Path(args.out)
    watch = Stopwatch()
    if args.bench == "scale":
        run_scale(out, tuple(args.n) or SCALES, table_dtype=args.table_dtype)
        print((out / "scale.md").read_text())
        print(f"finished in {watch.seconds:.0f} s. Report: {out.resolve()} (scale.json, scale.md, scale.png)")
        return 0
    if args.data and not Path(args.data).is_dir():
        raise FileNotFoundError(2, "no such folder (--data)", args.data)
    mode = "smoke" if args.smoke else "quick" if args.quick else "full"
    data = Path(args.data) if args.data else None
    if args.bench == "implementations":
        print(run_all(mode, out, data))
        print(f"finished in {watch.seconds:.0f} s. Report: {(out / 'implementations.md').resolve()}")
        return 0
    run_sweep(mode, out, data)
    print((out / "summary.md").read_text())
    print(f"bench finished in {watch.seconds:.0f} s. Report: {out.resolve()} "
          "(report.json, summary.md, time_vs_k.png, time_vs_c.png, roofline.png, complexity.png)")
    return 0
