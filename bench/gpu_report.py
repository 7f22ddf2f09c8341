"""The phases of the GPU report (``bench/gpu_report.sh``), one per call, each in its own process:

    python bench/gpu_report.py PHASE OUT WORK [--tiny] [--data DIR] [--reference FILE]

``devices``  ``qr-cl devices`` (its self-check included) and the chosen device's limits.
``parity``   every public path on the scenes (:mod:`qr_cl.app.bench.parity`) against PoCL's
             results made beforehand (``--reference``, carried in; compared when present), and the
             render check against the float64 twins.
``twins``    the kernel-against-twin test modules (pytest) on the device.
``sweep``    timings at 640x480, C = 512, K = 10 and 40, V-Render and the fused V-Render, on the fox,
             the donut and the dense 300k room (``--tiny``: a 3000-Gaussian scene at 160x120).
``gsplat``   gsplat's ``rasterization`` of the same scenes and features, channel_chunk 32 and 512
             (when gsplat and a CUDA device are there).
``report``   ``OUT/report.json`` and ``OUT/report.md`` from the phases' results.

Each phase writes ``WORK/<phase>.json`` (its results, or why it did not run); the report reads
them all. ``make-reference`` (run here, on PoCL) writes the parity reference of the scenes (a fixed sample of
each output's rows, :func:`qr_cl.app.bench.parity.sample_rows`).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: The kernel-against-twin test modules the twins phase runs (those the parity tests run on Intel's
#: runtime, tests/drivers/test_parity.py KERNEL_TESTS), and the tiny run's subset.
TWIN_TESTS = ["stages/test_select.py", "stages/test_blend.py", "stages/test_vrender.py", "stages/test_transpose.py",
              "stages/test_binning.py", "stages/test_sh.py", "stages/test_project.py", "stages/test_gpu_shapes.py",
              "render/test_rasterization.py", "render/test_half_tables.py", "render/test_rasterize.py"]
TINY_TWIN_TESTS = ["stages/test_vrender.py"]
#: The sweep: image size, channels, the K of the K samplers; the tiny run's.
FULL_SIZES = {"width": 640, "height": 480, "channels": 512, "ks": (10, 40), "rounds": 5}
TINY_SIZES = {"width": 160, "height": 120, "channels": 16, "ks": (4, 10), "rounds": 2}
#: gsplat's channel chunks: its default and the whole 512-D row at once.
GSPLAT_CHUNKS = (32, 512)


def write(work: Path, phase: str, result: dict) -> None:
    """``WORK/<phase>.json``, written whole (a phase killed midway leaves none)."""
    tmp = work / f"{phase}.json.tmp"
    tmp.write_text(json.dumps(result, indent=1, default=str))
    os.replace(tmp, work / f"{phase}.json")


def device_info() -> dict:
    """The device qr-cl renders on and the limits that shape its launches."""
    from qr_cl.render import checked_runtime
    from qr_cl.runtime import implementation
    rt = checked_runtime()
    d = rt.device
    return {"device": implementation(d), "name": d.name.strip(), "kind": "GPU" if rt.gpu_shaped else "CPU",
            "gpu_shaped": rt.gpu_shaped, "compute_units": d.max_compute_units,
            "global_mem_mib": d.global_mem_size >> 20, "local_mem_bytes": d.local_mem_size,
            "max_alloc_mib": d.max_mem_alloc_size >> 20, "group_limit": rt.group_limit,
            "group_rays": rt.group_rays, "blend_group": rt.blend_group, "loop_limit": rt.loop_limit}


def phase_devices(args) -> dict:
    run = subprocess.run([sys.executable, "-m", "qr_cl.app.cli", "devices"], capture_output=True, text=True,
                         timeout=600)
    return {"returncode": run.returncode, "text": run.stdout + run.stderr[-3000:], **device_info()}


def phase_parity(args) -> dict:
    from qr_cl.app.bench.parity import FLIPPED_ROWS, differences, render_scenes, sample_rows
    from qr_cl.render import render_check
    import numpy as np
    scenes = ["random"] if args.tiny else ["random", "fox", "donut", "dense"]
    if not args.tiny and args.data is None:
        scenes = ["random", "dense"]
    start = time.perf_counter()
    got = render_scenes(scenes, args.data)
    result = {"scenes": scenes, "seconds": time.perf_counter() - start, "twin_check": render_check() or "passed"}
    if args.reference is None or not args.reference.is_file():
        result["reference"] = "none carried: outputs not compared with PoCL's"
        return result
    want = dict(np.load(args.reference))
    want = {k: v for k, v in want.items() if k.split(":")[0] in scenes}
    rows = {}
    for key, (err, off, n) in differences(sample_rows(got), want).items():
        rows[key] = {"max_error": err, "rows_off": off, "rows": n, "agrees": off <= int(FLIPPED_ROWS * n)}
    result.update(reference=str(args.reference.name), outputs=rows,
                  agree=sum(r["agrees"] for r in rows.values()), compared=len(rows))
    return result


def phase_twins(args) -> dict:
    tests = TINY_TWIN_TESTS if args.tiny else TWIN_TESTS
    junit = args.work / "twins.xml"
    # --import-mode=append: the installed qr-cl, not the source tree on sys.path first
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--import-mode=append",
                          f"--junitxml={junit}",
                          *(str(REPO / "tests" / t) for t in tests)], cwd=REPO, capture_output=True, text=True,
                         env={**os.environ, **({"QR_CL_DATA": str(args.data)} if args.data else {})})
    tail = (run.stdout + run.stderr).strip().splitlines()
    result = {"modules": tests, "returncode": run.returncode, "summary": tail[-1] if tail else "",
              "failed": [line for line in tail if line.startswith(("FAILED", "ERROR"))][:40]}
    if junit.is_file():
        import xml.etree.ElementTree as ET
        suite = ET.parse(junit).getroot()
        suite = suite if suite.tag == "testsuite" else suite.find("testsuite")
        result.update({k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")})
    return result


def sweep_scenes(args, sizes: dict) -> list:
    """The sweep's scenes at the sweep's size."""
    from qr_cl.app.scenes.views import dense_view, procedural_view, real_views
    w, h = sizes["width"], sizes["height"]
    if args.tiny:
        return [procedural_view(3000, w, h)]
    return real_views(args.data, w, h) + [dense_view(300_000, w, h)]


def phase_sweep(args) -> dict:
    from qr_cl.app.bench.sweep import Sweep
    from qr_cl.app.renderers import FusedVolumeRenderer, SamplerRenderer
    sizes = TINY_SIZES if args.tiny else FULL_SIZES
    sweep = Sweep(sizes["rounds"], {"bandwidth_bytes_s": float("nan"), "fma_flops": float("nan")})
    c = sizes["channels"]
    for scene in sweep_scenes(args, sizes):
        print(f"sweep: {scene.name}", flush=True)
        sweep.plan(scene)
        sweep.fused(scene, c)
        for k in sizes["ks"]:
            sweep.sampler(scene, "quantile", k, c)
        sweep.sampler(scene, "volume", 0, c)
        for renderer in (SamplerRenderer("quantile", max(sizes["ks"])), FusedVolumeRenderer()):
            sweep.end_to_end(scene, renderer, c)
    keep = ("scene", "n_gaussians", "width", "height", "stage", "sampler", "k", "channels", "min_s", "median_s",
            "mean_entries")
    return {"sizes": sizes, "rows": [{k: r[k] for k in keep if k in r} for r in sweep.rows]}


def phase_gsplat(args) -> dict:
    import importlib.util
    import torch
    if importlib.util.find_spec("gsplat") is None:
        return {"not_run": "gsplat is not installed here"}
    if not torch.cuda.is_available():
        return {"not_run": "no CUDA device for gsplat"}
    from gsplat import rasterization
    from qr_cl.app.timing import measure
    sizes = TINY_SIZES if args.tiny else FULL_SIZES
    c, rows = sizes["channels"], []
    for scene in sweep_scenes(args, sizes):
        g, cam = scene.gaussians, scene.camera
        dev = torch.device("cuda")
        t = [torch.as_tensor(a, device=dev) for a in (g.means, g.quats, g.scales, g.opacities)]
        feats = torch.rand(len(g.means), c, device=dev, generator=torch.Generator(dev).manual_seed(0))
        views = torch.as_tensor(cam.viewmat, device=dev)[None], torch.as_tensor(cam.K, device=dev, dtype=torch.float32)[None]
        for chunk in GSPLAT_CHUNKS:
            def call():
                rasterization(*t, feats, *views, cam.width, cam.height, channel_chunk=chunk)
                torch.cuda.synchronize()
            timing = measure(call, sizes["rounds"])
            rows.append({"scene": scene.name, "n_gaussians": len(g.means), "width": cam.width, "height": cam.height,
                         "stage": "gsplat-rasterization", "channel_chunk": chunk, "channels": c,
                         "min_s": timing["min_s"], "median_s": timing["median_s"]})
    import gsplat
    return {"gsplat": gsplat.__version__, "torch": torch.__version__, "cuda_device": torch.cuda.get_device_name(),
            "rows": rows}


def phase_make_reference(args) -> dict:
    """PoCL's parity outputs of the scenes, saved to ``--reference`` (run here, before the trip)."""
    import numpy as np
    from qr_cl.app.bench.parity import render_scenes, sample_rows
    scenes = ["random"] if args.tiny else ["random", "fox", "donut", "dense"] if args.data else ["random", "dense"]
    np.savez_compressed(args.reference, **sample_rows(render_scenes(scenes, args.data)))
    return {"scenes": scenes, "reference": str(args.reference)}


# ---------------------------------------------------------------------------------------- report

def _load(work: Path, phase: str) -> dict:
    path = work / f"{phase}.json"
    return json.loads(path.read_text()) if path.is_file() else {"not_run": "did not finish (see its log)"}


def _ms(seconds: float) -> str:
    return f"{seconds * 1e3:.2f}"


def report_markdown(report: dict) -> str:
    """The report's tables: the device, its self-check, parity, the twin tests, and the timings
    side by side with gsplat's."""
    d, m = report["devices"], report["meta"]
    lines = [f"# qr-cl GPU report: {d.get('name', '?')}", "",
             f"- Command: `{m['command']}` ({m['date']}, {m['seconds']:.0f} s), {m['machine']}",
             f"- Device: {d.get('device', d.get('not_run', '?'))}; {d.get('kind', '?')} shapes, "
             f"{d.get('compute_units', '?')} compute units, work-groups up to {d.get('group_limit', '?')} "
             f"(tile walk {d.get('group_rays', '?')} rays, blends {d.get('blend_group', '?')}), loop limit "
             f"{d.get('loop_limit') or 'none'}",
             f"- Python {m['python']}, torch {m['torch']}, pyopencl {m['pyopencl']}", "",
             "## qr-cl devices", "", "```", d.get("text", d.get("not_run", "")).strip(), "```", ""]
    p = report["parity"]
    lines += ["## Every public path", ""]
    if "not_run" in p:
        lines.append(f"Not run: {p['not_run']}")
    else:
        lines.append(f"- Render check against the float64 twins: {p['twin_check']}")
        if "outputs" in p:
            lines.append(f"- Against PoCL's results ({p['reference']}), scenes {', '.join(p['scenes'])}: "
                         f"{p['agree']} of {p['compared']} outputs agree")
            off = {k: v for k, v in p["outputs"].items() if not v["agrees"]}
            lines += [f"  - {k}: error {v['max_error']:.2e} in {v['rows_off']} of {v['rows']} rows"
                      for k, v in sorted(off.items())]
        else:
            lines.append(f"- {p['reference']}")
    t = report["twins"]
    lines += ["", "## Kernel-against-twin tests", ""]
    lines.append(f"Not run: {t['not_run']}" if "not_run" in t else
                 f"{t.get('tests', '?')} tests, {t.get('failures', '?')} failed, {t.get('errors', '?')} errors, "
                 f"{t.get('skipped', '?')} skipped ({t['summary']})")
    lines += [f"- {f}" for f in t.get("failed", [])]
    s, gs = report["sweep"], report["gsplat"]
    lines += ["", "## Timings", ""]
    if "not_run" in s:
        lines.append(f"Not run: {s['not_run']}")
    else:
        lines += ["Minimum of the rounds, ms (the OpenCL queue finished inside each timed call).", "",
                  "| scene | N | WxH | stage | sampler | K | C | min ms | median ms |",
                  "| --- | ---: | --- | --- | --- | ---: | ---: | ---: | ---: |"]
        lines += [f"| {r['scene']} | {r['n_gaussians']} | {r['width']}x{r['height']} | {r['stage']} | {r['sampler']} | "
                  f"{r['k'] or '-'} | {r['channels'] or '-'} | {_ms(r['min_s'])} | {_ms(r['median_s'])} |"
                  for r in s["rows"]]
    lines += ["", "## gsplat side by side", ""]
    if "not_run" in gs:
        lines.append(f"Not run: {gs['not_run']}")
    else:
        ours = {(r["scene"], r["sampler"], r["k"]): r["min_s"] for r in s.get("rows", []) if r["stage"] == "end-to-end"}
        lines += [f"gsplat {gs['gsplat']} on {gs['cuda_device']} (torch {gs['torch']}); qr-cl's public calls take "
                  "CPU tensors (the copies included), gsplat's CUDA tensors.", "",
                  "| scene | C | gsplat chunk | gsplat ms | qr-cl Q-Render K=40 ms | qr-cl fused V-Render ms |",
                  "| --- | ---: | ---: | ---: | ---: | ---: |"]
        for r in gs["rows"]:
            q = ours.get((r["scene"], "quantile", max(s["sizes"]["ks"])))
            v = ours.get((r["scene"], "volume_fused", 0))
            lines.append(f"| {r['scene']} | {r['channels']} | {r['channel_chunk']} | {_ms(r['min_s'])} | "
                         f"{_ms(q) if q else '-'} | {_ms(v) if v else '-'} |")
    return "\n".join(lines) + "\n"


def phase_report(args) -> dict:
    import numpy as np
    import pyopencl
    import torch
    meta = {"command": args.command or "bench/gpu_report.sh", "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "seconds": args.seconds, "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores",
            "python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__,
            "pyopencl": pyopencl.VERSION_TEXT, "tiny": args.tiny}
    report = {"meta": meta, **{p: _load(args.work, p) for p in ("devices", "parity", "twins", "sweep", "gsplat")}}
    (args.out / "report.json").write_text(json.dumps(report, indent=1, default=str))
    (args.out / "report.md").write_text(report_markdown(report))
    return {"written": [str(args.out / "report.json"), str(args.out / "report.md")]}


PHASES = {"devices": phase_devices, "parity": phase_parity, "twins": phase_twins, "sweep": phase_sweep,
          "gsplat": phase_gsplat, "report": phase_report, "make-reference": phase_make_reference}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("phase", choices=sorted(PHASES))
    parser.add_argument("out", type=Path)
    parser.add_argument("work", type=Path)
    parser.add_argument("--tiny", action="store_true", help="tiny scenes and sizes (the test's run)")
    parser.add_argument("--data", type=Path, default=None, help="the real scenes' folder (as ../shared/data)")
    parser.add_argument("--reference", type=Path, default=None, help="PoCL's parity outputs (.npz)")
    parser.add_argument("--command", default="", help="the command line, for the report")
    parser.add_argument("--seconds", type=float, default=0.0, help="the run's wall time so far, for the report")
    args = parser.parse_args()
    if args.data is not None and not (args.data / "wakufactory-fox" / "fox.ply").is_file():
        args.data = None
    args.work.mkdir(parents=True, exist_ok=True)
    result = PHASES[args.phase](args)
    if args.phase not in ("report", "make-reference"):
        write(args.work, args.phase, result)
    print(json.dumps(result, default=str)[:2000])


if __name__ == "__main__":
    main()
