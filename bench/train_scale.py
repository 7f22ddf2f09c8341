"""Seconds per step and peak memory of ``qr-cl train`` against the number of Gaussians.

For each size N (default 80k, 300k and 1M, the size of a SceneSplat-7K ScanNet scene) the
synthetic "3dgs" room of N Gaussians (``SyntheticConfig(n_gaussians=N)``, 640x480 frames, 24
views by default: the same room, cameras and masks at every size, only denser; built once into
the scene cache, ``--cache``) is trained with ``qr-cl train`` at its default settings, each run in
a fresh process. A step's cost is the difference of a long and a short run (``--long`` and
``--short`` steps), so start-up (imports, scene loading, kernel builds, the first whole-view
selections) cancels: s/step = (wall_long - wall_short) / (long - short). The peak is the long
run's peak resident memory as the kernel counts it (``wait4``'s ``ru_maxrss``). Warnings a run
prints (a bound it met, e.g. ``view_selections_mb``) are reported with it::

    python bench/train_scale.py --out bench/reports/train-scale-<machine>

Writes ``report.md`` (the table, the machine, its load average before and after each run) and
``results.json`` into ``--out``. Options this script does not know are passed to ``qr-cl train``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchutil import arguments

#: Sizes measured by default (Gaussians).
SIZES = (80_000, 300_000, 1_000_000)

#: What a training step does, and which of it grows with N (docs/design.md, "Training").
GROWTH = """What grows with N, in a room of fixed size, frames, views and rays: the UNet runs on every
voxel, and the voxels follow the room's occupied volume, not N; the blend and the loss take the
step's views x rays x K entries, fixed; de-voxelization and the head's norms take the U Gaussians
the rays touch, which grow with N but slower (the rays and their K entries are fixed); a view whose
whole-image selection is not kept (`view_selections_mb`) is projected and binned afresh each step,
O(N) per such view. In memory: the scene (44 bytes per Gaussian in float32, plus its SH), the voxel
index (24 bytes per Gaussian), the plans of the views being selected; the whole-view selections
kept are bounded by `view_selections_mb` (a view's is frame pixels x K entries whatever N, plus its
plan), and no [N, 512] table is made (the blend reads the head's D + 1 inputs)."""


def cpu_name() -> str:
    """The CPU's model name (/proc/cpuinfo), else platform's guess."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def room(n: int, width: int, height: int, views: int, cache: Path | None) -> tuple[Path, int]:
    """(folder, voxels at the default grid) of the synthetic "3dgs" room of ``n`` Gaussians,
    built on first use."""
    from qr_cl.app.process import cap_kernel_threads
    from qr_cl.app.scenes.room_config import SyntheticConfig
    from qr_cl.app.scenes.synthetic import room_folder
    from qr_cl.app.training.config import TrainConfig
    from qr_cl.backbone import VoxelConfig, voxelize
    from qr_cl.scene import load_ply
    cap_kernel_threads()
    folder = room_folder(SyntheticConfig(seed=0, n_gaussians=n, style="3dgs", width=width, height=height,
                                         n_views=views), cache)
    grid = TrainConfig(scenes=["-"], out="-").grid_size
    voxels = voxelize(load_ply(folder / "point_cloud.ply"), VoxelConfig(grid_size=grid)).coords.shape[0]
    return folder, voxels


def run_train(folder: Path, steps: int, extra: list[str]) -> dict:
    """One fresh ``qr-cl train folder --steps steps`` process: wall s, CPU s, peak resident GB
    (``wait4``), its warnings, the mean fraction of the Gaussians a step touched, and the
    1-minute load average before and after; SystemExit with its stderr if it fails."""
    with tempfile.TemporaryDirectory() as out, open(Path(out) / "stderr.txt", "w+") as stderr:
        load_before = os.getloadavg()[0]
        start = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "qr_cl.app.cli", "train", str(folder), "--out", out,
                                 "--steps", str(steps), "--checkpoint-every", "100000", *extra],
                                stdout=subprocess.DEVNULL, stderr=stderr, cwd=out)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - start
        stderr.seek(0)
        text = stderr.read()
        if os.waitstatus_to_exitcode(status):
            raise SystemExit(f"qr-cl train {folder} --steps {steps} failed:\n{text[-4000:]}")
        touched = json.loads((Path(out) / "train_log.json").read_text())["touched"]
    return {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime, "peak_gb": usage.ru_maxrss * 1024 / 1e9,
            "warnings": sorted({line.split("warning: ", 1)[1] for line in text.replace("\r", "\n").splitlines()
                                if "warning: " in line}),
            "touched": statistics.mean(touched), "load_before": load_before, "load_after": os.getloadavg()[0]}


def per_step(short: dict, long: dict, steps: int) -> float:
    """Seconds per step: the difference of a long and a short run over their ``steps`` difference."""
    return (long["wall_s"] - short["wall_s"]) / steps


def report(results: dict) -> str:
    """The Markdown report of :func:`main`'s results."""
    cfg = results["room"]
    lines = [f"# `qr-cl train` against the number of Gaussians", "",
             f"Machine: {results['cpu']}, {results['cores']} cores, {results['memory_gb']:.0f} GB. Room: the "
             f"synthetic \"3dgs\" room (seed 0), {cfg['width']}x{cfg['height']}, {cfg['views']} views, only its "
             f"number of Gaussians changed. `qr-cl train` at its defaults{''.join(' ' + a for a in results['extra'])}; "
             f"s/step from "
             f"runs of {results['short']} and {results['long']} steps ({results['rounds']} round(s), the median), "
             "peak: the long run's peak resident memory (`wait4`'s ru_maxrss), each run a fresh process. The "
             "load average counts the runs' own threads too.", "", f"Command: `{results['command']}`", "",
             "| Gaussians | voxels | Gaussians a step touches (U) | s/step | peak GB | cores busy "
             "| load average (1 min) before / after |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for row in results["sizes"]:
        load = ", ".join(f"{r['load_before']:.2f} / {r['load_after']:.2f}" for r in row["runs"])
        lines.append(f"| {row['gaussians']:,} | {row['voxels']:,} | {row['touched_gaussians']:,.0f} "
                     f"| {row['s_per_step']:.2f} | {row['peak_gb']:.2f} | {row['cores_busy']:.2f} | {load} |")
    first = results["sizes"][0]
    lines += ["", f"Growth from {first['gaussians']:,} Gaussians (each quantity over its value there):", "",
              "| Gaussians | N | voxels | U | s/step | peak |", "| --- | --- | --- | --- | --- | --- |"]
    for row in results["sizes"]:
        lines.append(f"| {row['gaussians']:,} | " + " | ".join(
            f"{row[k] / first[k]:.2f}x" for k in ("gaussians", "voxels", "touched_gaussians", "s_per_step", "peak_gb"))
            + " |")
    lines += ["", GROWTH]
    bounds = sorted({w for row in results["sizes"] for r in row["runs"] for w in r["warnings"]})
    lines += ["", "Warnings the runs printed (bounds they met):", ""] + \
        ([f"- {row['gaussians']:,}: {w}" for row in results["sizes"]
          for w in sorted({w for r in row["runs"] for w in r["warnings"]})] if bounds else ["- none"])
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="report folder (report.md, results.json)")
    parser.add_argument("--sizes", type=arguments.positive_int, nargs="+", default=list(SIZES),
                        help="numbers of Gaussians (default 80000 300000 1000000)")
    parser.add_argument("--width", type=arguments.positive_int, default=640, help="frame width (default 640)")
    parser.add_argument("--height", type=arguments.positive_int, default=480, help="frame height (default 480)")
    parser.add_argument("--views", type=arguments.positive_int, default=24, help="views of the room (default 24)")
    parser.add_argument("--cache", type=Path, help="scene cache (default $QR_CL_CACHE/scenes or ~/.cache/qr-cl/scenes)")
    parser.add_argument("--short", type=arguments.positive_int, default=5, help="steps of the short run (default 5)")
    parser.add_argument("--long", type=arguments.positive_int, default=25, help="steps of the long run (default 25)")
    parser.add_argument("--rounds", type=arguments.positive_int, default=1, help="rounds (default 1)")
    args, extra = parser.parse_known_args()
    if args.long <= args.short:
        parser.error(f"--long ({args.long}) must exceed --short ({args.short})")
    memory = int(Path("/proc/meminfo").read_text().split("MemTotal:")[1].split()[0]) * 1024
    results = {"command": " ".join(["python", "bench/train_scale.py", *sys.argv[1:]]), "cpu": cpu_name(),
               "cores": os.cpu_count(), "memory_gb": memory / 1e9, "extra": extra,
               "room": {"width": args.width, "height": args.height, "views": args.views},
               "short": args.short, "long": args.long, "rounds": args.rounds, "sizes": []}
    for n in args.sizes:
        folder, voxels = room(n, args.width, args.height, args.views, args.cache)
        runs, steps = [], []
        for r in range(args.rounds):
            short, long = run_train(folder, args.short, extra), run_train(folder, args.long, extra)
            runs += [short, long]
            steps.append(per_step(short, long, args.long - args.short))
            print(f"{n} Gaussians, round {r + 1}: {steps[-1]:.2f} s/step, peak {long['peak_gb']:.2f} GB", flush=True)
        longs = runs[1::2]
        cpu = statistics.median((b["cpu_s"] - a["cpu_s"]) / (b["wall_s"] - a["wall_s"]) for a, b in zip(runs[::2], longs))
        results["sizes"].append({"gaussians": n, "folder": folder.name, "voxels": voxels, "s_per_step": statistics.median(steps),
                                 "s_per_step_rounds": steps, "peak_gb": max(r["peak_gb"] for r in longs),
                                 "touched_gaussians": n * statistics.median(r["touched"] for r in longs),
                                 "cores_busy": cpu, "runs": runs})
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    text = report(results)
    (args.out / "report.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
