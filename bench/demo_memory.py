"""The resident memory of ``qr-cl demo`` over its run, for this checkout or another install and this one.

Each install runs the demo in a fresh process (its scenes come from the shared cache, built once
by whichever runs first), its resident memory (``VmRSS``) sampled every ``--every`` seconds,
and its peak read from the kernel when it ends (``wait4``'s ``ru_maxrss``, which no sample can
miss). Writes ``demo_memory.md`` (wall time and peak per install) and ``demo_memory.png`` (memory
against time) into ``--out``::

    python bench/demo_memory.py --base PYTHON_OR_CHECKOUT --out REPORT_FOLDER   # --base: bench/ab.py

Options this script does not know are passed to ``qr-cl demo`` (e.g. ``--steps 60``).
"""
from __future__ import annotations

import argparse
import os
import subprocess
import tempfile
import time
from pathlib import Path

from ab import Install, add_base_option, installs
from benchutil import arguments, print_table
from qr_cl.app.images import plt  # pyplot on the file-only Agg backend


def resident_mb(pid: int) -> float | None:
    """Resident memory of process ``pid`` in MB, None once it is gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    return int(status.split("VmRSS:")[1].split()[0]) / 1024 if "VmRSS:" in status else None


def run_demo(install: Install, every: float, extra: list[str]) -> tuple[float, float, list[tuple[float, float]]]:
    """(wall s, peak MB, [(s, MB)] samples) of ``qr-cl demo`` in ``install``; the peak is the
    kernel's for that process (``wait4``), not the samples' largest."""
    with tempfile.TemporaryDirectory() as out, open(Path(out) / "stderr.txt", "w+") as stderr:
        start = time.perf_counter()
        proc = install.popen(["-m", "qr_cl.app.cli", "demo", "--out", out, *extra],
                             stdout=subprocess.DEVNULL, stderr=stderr, cwd=out)
        samples = []
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            mb = resident_mb(proc.pid)
            if mb is not None:
                samples.append((time.perf_counter() - start, mb))
            time.sleep(every)
        wall = time.perf_counter() - start
        proc.returncode = os.waitstatus_to_exitcode(status)
        if proc.returncode:
            stderr.seek(0)
            raise SystemExit(f"{install.label}: qr-cl demo failed (rc {proc.returncode}):\n{stderr.read()[-4000:]}")
    return wall, usage.ru_maxrss / 1024, samples


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_base_option(parser, required=False)
    parser.add_argument("--every", type=arguments.positive_float, default=1.0,
                        help="seconds between samples (default 1)")
    parser.add_argument("--out", type=Path, required=True, help="folder for demo_memory.md and demo_memory.png")
    args, extra = parser.parse_known_args()
    args.out.mkdir(parents=True, exist_ok=True)
    lines = [f"`qr-cl demo {' '.join(extra)}`, resident memory sampled every {args.every:g} s, "
             f"{os.cpu_count()} CPUs", "", "| install | wall s | peak GB |", "| --- | ---: | ---: |"]
    fig, ax = plt.subplots(figsize=(7, 4))
    with installs(args.base) as runs_of:
        for install in runs_of:
            wall, peak, samples = run_demo(install, args.every, extra)
            label = install.label
            print(f"{label}: {wall:.0f} s, peak {peak / 1024:.2f} GB", flush=True)
            lines.append(f"| {label} | {wall:.0f} | {peak / 1024:.2f} |")
            ax.plot([t for t, _ in samples], [mb / 1024 for _, mb in samples],
                    label=f"{label} (peak {peak / 1024:.2f} GB)")
    ax.set(xlabel="s", ylabel="resident GB", title="qr-cl demo: resident memory")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(args.out / "demo_memory.png", dpi=110)
    plt.close(fig)
    print_table("\n".join(lines), args.out / "demo_memory.md")


if __name__ == "__main__":
    main()
