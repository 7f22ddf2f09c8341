"""``qr-cl bench implementations``: the same sweep on every OpenCL implementation installed
here, one after the other (PoCL, the system's default, and those tests/drivers/install.sh put
under ``$QR_CL_DRIVERS``), and their times side by side. Information for users, not a target: each
implementation runs the kernels its own compiler built, on the same machine."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from ...runtime.implementations import environment, installed

#: The stages the side-by-side table shows (every row of these stages that all reports share).
STAGES = ("projection", "binning+sort", "selection", "blend-forward", "blend-backward", "end-to-end", "fused",
          "training-path", "rasterization-forward-backward")


def _key(row: dict) -> tuple:
    return (row["scene"], row["width"], row["height"], row["stage"], row["sampler"], row["k"], row["channels"])


def run_all(mode: str, out: Path, data: Path | None) -> str:
    """Run ``qr-cl bench sweep`` in ``mode`` ("smoke", "quick" or "full") in a child per implementation
    (reports in ``out/<name>``), write ``out/implementations.md`` and return its text. An
    implementation that qr-cl refuses (or that fails) is listed with the reason."""
    names = ["pocl", *installed()]
    reports, failures = {}, {}
    for name in names:
        folder = out / name
        cmd = [sys.executable, "-m", "qr_cl.app.cli", "bench", "sweep", "--out", str(folder)]
        cmd += {"smoke": ["--smoke"], "quick": ["--quick"], "full": []}[mode] + (["--data", str(data)] if data else [])
        print(f"bench on {name} ...", flush=True)
        run = subprocess.run(cmd, env=environment(name), capture_output=True, text=True)
        report = folder / "report.json"
        if run.returncode == 0 and report.is_file():
            reports[name] = json.loads(report.read_text())
        else:
            failures[name] = ((run.stderr or run.stdout).strip().splitlines() or [f"exit {run.returncode}"])[-1]
    text = side_by_side(reports, failures)
    out.mkdir(parents=True, exist_ok=True)
    (out / "implementations.md").write_text(text)
    return text


def side_by_side(reports: dict[str, dict], failures: dict[str, str]) -> str:
    """Markdown: each implementation's device, then the shared rows of :data:`STAGES` in ms, and
    each time over PoCL's (the first report)."""
    lines = ["# qr-cl bench on every OpenCL implementation installed here", ""]
    for name, report in reports.items():
        m = report["meta"]
        lines.append(f"- **{name}**: {m['device']} ({m['platform']}, driver {m['driver']}), "
                     f"{m['compute_units']} compute units, {m['mode']} sweep, {m['date']}")
    lines += [f"- **{name}**: not run: {reason}" for name, reason in failures.items()]
    if not reports:
        return "\n".join(lines) + "\n"
    names = list(reports)
    rows = [{_key(r): r for r in rep["results"] if r["stage"] in STAGES} for rep in reports.values()]
    shared = [k for k in rows[0] if all(k in r for r in rows[1:])]
    lines += ["", "Minimum times (ms) of the same rows; in brackets the time over the first column's.", "",
              "| scene | WxH | stage | sampler | K | C | " + " | ".join(names) + " |",
              "| --- | --- | --- | --- | --- | --- | " + " | ".join("---:" for _ in names) + " |"]
    for key in shared:
        scene, w, h, stage, sampler, k, c = key
        base = rows[0][key]["min_s"]
        cells = [f"{r[key]['min_s'] * 1e3:.2f}" + ("" if i == 0 else f" ({r[key]['min_s'] / base:.2f}x)")
                 for i, r in enumerate(rows)]
        lines.append(f"| {scene} | {w}x{h} | {stage} | {sampler} | {k or '-'} | {c or '-'} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
