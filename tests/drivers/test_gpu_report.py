"""bench/gpu_report.sh in its bare mode here (``--implementation``): a fresh venv holding torch
2.13.0 (this machine's disk file) and the carried wheels (downloaded for this Python by
``--prepare``; skipped without a network), the OpenCL implementation through a private ICD
folder, the tiny scenes. It must write the report a GPU run writes, within the 8 files a GPU
machine sends back, with every phase that needs no CUDA done and passing."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from qr_cl.runtime.implementations import installed

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "bench" / "gpu_report.sh"
FILES = {"report.md", "report.json", "setup.log", "devices.log", "parity.log", "sweep.log", "gsplat.log", "twins.log"}
#: What the report names as the device, per implementation.
PLATFORMS = {"pocl": "Portable Computing Language", "intel": "Intel(R) OpenCL"}


@pytest.fixture(scope="module")
def carry(tmp_path_factory) -> Path:
    """The carry folder of a tiny run: this Python's wheels and PoCL's results on the small scene."""
    folder = tmp_path_factory.mktemp("carry")
    run = subprocess.run(["bash", str(SCRIPT), "--prepare", "--tiny", "--carry", str(folder), "--python-version",
                          f"{sys.version_info[0]}.{sys.version_info[1]}"], capture_output=True, text=True, timeout=900)
    if run.returncode != 0 and "pip download" in run.stderr + run.stdout or not any(folder.glob("wheels/*/*.whl")):
        pytest.skip(f"the wheels could not be downloaded: {(run.stderr or run.stdout).strip()[-300:]}")
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-3000:]
    return folder


@pytest.mark.parametrize("name", ["pocl", pytest.param("intel", marks=pytest.mark.slow)])
def test_the_gpu_report_runs_bare_here(name, carry, tmp_path):
    if name != "pocl" and name not in installed():
        pytest.skip(f"{name} is not installed (bash tests/drivers/install.sh {name})")
    out = tmp_path / "out"
    run = subprocess.run(["bash", str(SCRIPT), str(out), "--implementation", name, "--tiny", "--carry", str(carry)],
                         cwd=REPO, capture_output=True, text=True, timeout=1500)
    logs = "\n".join(f"== {p.name}\n{p.read_text()[-3000:]}" for p in sorted(out.glob("*.log")))
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:] + logs
    assert {p.name for p in out.iterdir()} == FILES, logs
    report = json.loads((out / "report.json").read_text())
    assert report["meta"]["torch"].startswith("2.13.0") and report["meta"]["tiny"]
    devices = report["devices"]
    assert PLATFORMS[name] in devices["device"] and devices["returncode"] == 0, devices
    assert "render check passed" in devices["text"], devices["text"]
    parity = report["parity"]
    assert parity["twin_check"] == "passed" and parity["scenes"] == ["random"], parity
    assert parity["compared"] > 20 and parity["agree"] == parity["compared"], parity
    twins = report["twins"]
    assert twins["tests"] > 0 and twins["failures"] == twins["errors"] == 0, twins
    stages = {(r["stage"], r["sampler"], r["k"]) for r in report["sweep"]["rows"]}
    assert {("fused", "volume_fused", 0), ("selection", "quantile", 10), ("blend-forward", "volume", 0),
            ("end-to-end", "quantile", 10)} <= stages, stages
    assert "not_run" in report["gsplat"], report["gsplat"]       # no CUDA here
    text = (out / "report.md").read_text()
    for heading in ("# qr-cl GPU report", "## qr-cl devices", "## Every public path", "## Kernel-against-twin tests",
                    "## Timings", "## gsplat side by side"):
        assert heading in text, text
