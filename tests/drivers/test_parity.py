"""The same results on every OpenCL implementation installed here: Intel's CPU runtime and Mesa's
rusticl (privately, by tests/drivers/install.sh) against PoCL, the system's default.

A child process per (implementation, launch shape, run) renders every public path forward and
backward on the scenes (:func:`render_all`): rasterize with each sampler (image, alpha, feature
gradient), a pixel subset, the SH color kernel, render_volume_fused (image, alpha, depth) and
rasterization (image and gradients w.r.t. means, quats, scales, opacities and colors). Each
implementation runs twice with one fresh kernel cache: the first run builds from source, the
second loads pyopencl's cached binaries (which carry no argument info on Intel's runtime). Every
output must equal PoCL's within 1e-4 of its largest value (a float16 table's gradient, rounded to
float16, within 1e-3) in all but 0.1 % of its rows: rays whose transmittance meets a K sampler's
boundary, or whose Gaussian's alpha meets the 1/255 cut or whose T meets V-Render's stop, at float
rounding, decide differently under another compiler. rusticl (llvmpipe) ends loops after 65535
iterations, so it walks in windows; its compiler does not fuse multiply-adds as PoCL's and
Intel's do, so its projection differs from theirs in the last bits. The default suite renders the
procedural scene on Intel's runtime (CPU shapes, first and cached runs); everything else is the
slow suite's (`python -m pytest -m slow tests/drivers`): Intel's GPU shapes, rusticl (whose
compiler takes minutes), the real scenes, the dense room, rusticl's self-check, and the
kernel-against-twin tests on Intel's runtime. Skipped for implementations
not installed.

Run as a script (``python tests/drivers/test_parity.py OUT.npz SCENE...``) this file is the child.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from qr_cl.app.bench.parity import compare
from qr_cl.runtime.implementations import NAMES, environment, installed

#: The real scenes, rendered on each implementation in the slow suite (as is "dense", the
#: 300k-Gaussian room); the default suite renders the procedural "random" scene.
REAL_SCENES = ["fox", "donut"]
SHAPES = ["cpu", "gpu"]


# ---------------------------------------------------------------- the child

def child(out: str, scenes: list[str]) -> None:
    from qr_cl.app.bench.parity import render_scenes
    from qr_cl.runtime import runtime
    from qr_cl.runtime.device import implementation
    print(implementation(runtime().device), flush=True)
    np.savez(out, **render_scenes(scenes, Path(os.environ["QR_CL_DATA"])))


# ---------------------------------------------------------------- the parent

def run_child(implementation: str, shape: str, cache: Path, out: Path, scenes: list[str], data: Path,
              **env: str) -> subprocess.CompletedProcess:
    """The child on ``implementation`` with ``shape`` launches, its kernel caches in ``cache``."""
    environ = environment(implementation, QR_CL_LAUNCH=shape, XDG_CACHE_HOME=str(cache / "xdg"),
                          QR_CL_CACHE=str(cache / "qr-cl"), QR_CL_DATA=str(data), PYTHONWARNINGS="ignore",
                          **env)
    return subprocess.run([sys.executable, __file__, str(out), *scenes], env=environ, capture_output=True,
                          text=True, timeout=900)


@pytest.fixture(scope="module")
def reference(tmp_path_factory, data_dir):
    """PoCL's outputs per launch shape (computed on first use)."""
    shared = (data_dir / "wakufactory-fox" / "fox.ply").is_file()
    done = {}

    def get(shape: str, scenes: list[str]) -> dict:
        if (shape, tuple(scenes)) not in done:
            folder = tmp_path_factory.mktemp(f"pocl-{shape}")
            run = run_child("pocl", shape, folder, folder / "out.npz", scenes, data_dir)
            assert run.returncode == 0, run.stderr[-3000:]
            done[shape, tuple(scenes)] = dict(np.load(folder / "out.npz"))
        return done[shape, tuple(scenes)]
    get.shared, get.data = shared, data_dir
    return get


def needs(name: str) -> None:
    if name not in installed():
        pytest.skip(f"{name} is not installed (bash tests/drivers/install.sh {name})")


def check_equal_first_and_cached(name: str, shape: str, scenes: list[str], reference, folder: Path,
                                 runs: tuple[str, ...] = ("first", "cached")) -> None:
    want = reference(shape, scenes)
    for run_name in runs:
        run = run_child(name, shape, folder, folder / f"{run_name}.npz", scenes, reference.data)
        assert run.returncode == 0, f"{name} {shape} {run_name} run failed:\n{run.stderr[-3000:]}"
        bad = compare(dict(np.load(folder / f"{run_name}.npz")), want)
        assert not bad, f"{name}, {shape} shapes, {run_name} run differs from PoCL: {bad}"


@pytest.mark.parametrize("shape", ["cpu", pytest.param("gpu", marks=pytest.mark.slow)])
def test_intel_equals_pocl_first_and_cached(shape, reference, tmp_path):
    needs("intel")
    check_equal_first_and_cached("intel", shape, ["random"], reference, tmp_path)


@pytest.mark.slow
def test_rusticl_equals_pocl_walking_in_windows(reference, tmp_path):
    """On the procedural scene, GPU shapes, a first run: llvmpipe's compiler takes minutes (both
    shapes' first and cached runs on the real scenes are further down)."""
    needs("rusticl")
    check_equal_first_and_cached("rusticl", "gpu", ["random"], reference, tmp_path, runs=("first",))


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("shape", SHAPES)
def test_implementation_equals_pocl_on_the_real_scenes(name, shape, reference, tmp_path):
    needs(name)
    if not reference.shared:
        pytest.skip("the real scenes are not here")
    check_equal_first_and_cached(name, shape, REAL_SCENES, reference, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("shape", SHAPES)
def test_implementation_equals_pocl_on_the_dense_room(name, shape, reference, tmp_path):
    needs(name)
    check_equal_first_and_cached(name, shape, ["dense"], reference, tmp_path)


@pytest.mark.slow
def test_rusticl_passes_the_self_check_walking_in_windows():
    """Mesa 22.3's llvmpipe ends loops after 65535 iterations: measured by the loop probe, so its
    walks go in windows, and it passes the render check (it was refused before windows)."""
    needs("rusticl")
    devices = subprocess.run([sys.executable, "-m", "qr_cl.app.cli", "devices"], env=environment("rusticl"),
                             capture_output=True, text=True, timeout=600)
    assert devices.returncode == 0, devices.stdout + devices.stderr[-3000:]
    line = next(line for line in devices.stdout.splitlines() if "rusticl" in line)
    assert line.startswith("*") and "loops end after 65535 iterations (walks in windows)" in line, line
    assert "render check passed" in line, line


#: The kernel-against-twin test modules that also run on the other implementations (paths under
#: tests/), in two groups of about equal time that run at once: a child spends most of its time in
#: Intel's compiler, on one core.
KERNEL_TESTS = (["stages/test_blend.py", "stages/test_sh.py", "stages/test_vrender.py", "stages/test_transpose.py",
                 "stages/test_binning.py"],
                ["stages/test_select.py", "runtime/test_signatures.py", "stages/test_project.py",
                 "render/test_rasterization.py", "render/test_half_tables.py", "render/test_rasterize.py"])
#: Left out there: the real scenes through rasterize, which the parity tests above render on Intel's
#: runtime on both launch shapes (forward and backward, every sampler).
KERNEL_TESTS_LEFT_OUT = ["render/test_rasterize.py::test_real_scenes_match_reference"]


@pytest.mark.slow
def test_kernel_tests_pass_on_intel(tmp_path, data_dir):
    needs("intel")
    tests = Path(__file__).resolve().parents[1]
    children = []
    for i, group in enumerate(KERNEL_TESTS):
        env = environment("intel", XDG_CACHE_HOME=str(tmp_path / f"xdg{i}"), QR_CL_CACHE=str(tmp_path / f"qr-cl{i}"),
                          QR_CL_DATA=str(data_dir))
        command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                   *(f"--deselect=tests/{t}" for t in KERNEL_TESTS_LEFT_OUT), *(str(tests / t) for t in group)]
        children.append(subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                         text=True, cwd=tests.parent))
    try:
        outputs = [child.communicate(timeout=900)[0] for child in children]
    finally:
        for child in children:
            if child.poll() is None:
                child.kill()
                child.wait()
    failed = [out[-4000:] for child, out in zip(children, outputs) if child.returncode]
    assert not failed, "\n\n".join(failed)


if __name__ == "__main__":
    child(sys.argv[1], sys.argv[2:])
