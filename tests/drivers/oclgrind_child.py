"""The child process of the oclgrind tests (test_oclgrind_reports.py, test_oclgrind_values.py),
and how they start it: under oclgrind, the OpenCL device simulator (issue 12: "Prove any OpenCL
driver").

A child sees only oclgrind (a private ``OCL_ICD_VENDORS`` folder, never registered system-wide),
picks it with ``QR_CL_DEVICE`` (oclgrind is not a CPU device, so qr-cl launches its GPU shapes:
padded work-groups, device sorts) and renders tiny scenes through every kernel. The checks of
Debian's oclgrind 21.10 (built on LLVM 14) do not all work together, hence two checking modes:

* ``races``: out-of-bounds accesses (always checked), data races (``OCLGRIND_DATA_RACES``) and
  API misuse (``OCLGRIND_CHECK_API``) on the usual optimized builds.
* ``uninitialized``: uses of uninitialized values (``OCLGRIND_UNINITIALIZED``) and API misuse,
  on unoptimized builds (``-cl-opt-disable``): on optimized code this checker stops with a fatal
  "Unsupported instruction: freeze" (in pyopencl's scan) and flags the poison lanes of vector
  stores that LLVM splits into scalar stores (project.cl's ``splats[i] = splat``). It ignores
  clEnqueueFillBuffer (pyopencl's ``zeros``), so the child fills buffers by host writes, and it
  misreads buffers whose memory was freed and handed out again, so the child keeps every device
  array alive.

pyopencl's scans and radix sort are interpreted slowly (thousands of work-items per call, minutes
under the race checker) and are not qr-cl's: the ``races`` run checks them once each on the
device (:func:`exercise_pyopencl`), then both runs do them on the host; every qr-cl kernel runs on
oclgrind. A third mode, ``project``, runs project.cl without checks (:func:`project_runs`).

Run as a script: ``python tests/drivers/oclgrind_child.py races|uninitialized [quick|full]``
(``quick``: :func:`quick_exercise`, the default suite's; ``full``, the default: :func:`exercise`
and, in the ``races`` run, pyopencl's kernels), or ``project OUT.npz``.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import NamedTuple

from tests.drivers.oclgrind_host_ops import record_scan_and_sort_specs, use_host_scan_sort

ICD_LIBRARIES = ("/usr/lib/oclgrind/liboclgrind-rt-icd.so",                 # Debian, Ubuntu
                 "/usr/lib/x86_64-linux-gnu/liboclgrind-rt-icd.so",
                 "/usr/lib64/oclgrind/liboclgrind-rt-icd.so",
                 "/usr/local/lib/liboclgrind-rt-icd.so")
REPO = Path(__file__).resolve().parents[2]
W, H = 24, 16
MODES = {
    "races": {"OCLGRIND_CHECK_API": "1", "OCLGRIND_DATA_RACES": "1"},
    "uninitialized": {"OCLGRIND_CHECK_API": "1", "OCLGRIND_UNINITIALIZED": "1",
                      "OCLGRIND_BUILD_OPTIONS": "-cl-opt-disable"},
}


def oclgrind_icd() -> str | None:
    return next((p for p in ICD_LIBRARIES if os.path.exists(p)), None)


# ---------------------------------------------------------------- the child (runs under oclgrind)

def tiny_scene(n: int = 36, seed: int = 0):
    """n random Gaussians in front of a camera at the origin (fx = fy = 20, 24x16 px) with edge
    cases (behind the camera, either side of the near plane, one covering the image), plus a dense
    stack of 40 faint wide Gaussians in front of pixel (5, 5): rays there blend more than 32
    Gaussians (vrender.cl's batch). Returns float32 means, quats, scales, opacities, SH [N,16,3]."""
    import numpy as np
    rng = np.random.default_rng(seed)
    means = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(1, 4, n)]
    scales = np.exp(rng.uniform(-3, -1, (n, 3)))
    opac = rng.uniform(0.1, 1, n)
    means[:3, 2] = -1.0                                      # behind the camera
    means[3:5] = [[0, 0, 0.0101], [0, 0, 0.0099]]            # either side of the near plane
    means[5], scales[5] = [0, 0, 3], [5, 5, 5]               # covers the image
    z = np.linspace(2.0, 3.0, 40)
    stack = np.c_[(5.5 - W / 2) / 20 * z, (5.5 - H / 2) / 20 * z, z]   # projects to (5.5, 5.5)
    means = np.r_[means, stack]
    scales = np.r_[scales, np.full((len(z), 3), 0.3)]
    opac = np.r_[opac, np.full(len(z), 0.08)]
    q = rng.normal(size=(len(means), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    sh = rng.normal(0, 0.5, (len(means), 16, 3))
    return tuple(np.ascontiguousarray(a, np.float32) for a in (means, q, scales, opac, sh))


def exercise() -> None:
    """Render the tiny scene through every public kernel path (one line per path on stdout)."""
    import numpy as np
    import torch

    import qr_cl
    from qr_cl.app.bench import roofline
    from qr_cl.runtime import runtime

    torch.set_num_threads(1)
    rt = runtime()
    print("device:", rt.device.name.strip(), "/", rt.device.platform.name.strip(), flush=True)
    means, quats, scales, opac, sh = tiny_scene()
    n = len(means)
    cam = qr_cl.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 20.0, 20.0, W, H)
    geo = (means, quats, scales, opac)
    rng = np.random.default_rng(1)
    feats = rng.normal(size=(n, 5)).astype(np.float32)       # 5 channels: padded rows
    bg = np.array([0.1, -0.2, 0.3, 0.4, 0.5], np.float32)
    pixels = np.array([[0, 0], [5, 5], [23, 15], [12, 8], [5, 5], [17, 3]], np.int32)

    densest = 0
    for sampler in ("volume", "quantile", "topk"):
        for px in (None, pixels):
            for background in (None, bg):
                f = torch.from_numpy(feats).requires_grad_(True)
                img, alpha, meta = qr_cl.rasterize(*geo, f, cam.viewmat, cam.K, W, H, sampler=sampler,
                                                   k=4, background=background, pixels=px)
                img.sum().backward()
                assert f.grad is not None and bool(torch.isfinite(f.grad).all())
                if sampler == "volume":
                    densest = max(densest, int(meta["selection"].host()["count"].max()))
                print(f"rasterize {sampler} pixels={px is not None} background={background is not None}"
                      " forward+backward: ok", flush=True)
    assert densest > 32, f"the dense stack must give a ray more than 32 Gaussians, got {densest}"

    viewmats, Ks = torch.from_numpy(cam.viewmat)[None], torch.from_numpy(cam.K)[None]
    for sampler, packed in (("volume", False), ("quantile", True)):   # gradients w.r.t. the Gaussians, camera
        inputs = [torch.from_numpy(a).requires_grad_(True) for a in (*geo, feats, bg)]
        views = viewmats.clone().requires_grad_(True)
        img, alpha, meta = qr_cl.rasterization(*inputs[:5], views, Ks, W, H, backgrounds=inputs[5][None],
                                               sampler=sampler, k=4, packed=packed, absgrad=True)
        meta["means2d"].retain_grad()
        (img.sum() + (alpha.sum() if sampler == "volume" else 0)).backward()
        grads = [t.grad for t in inputs] + [views.grad, meta["means2d"].grad, meta["means2d"].absgrad]
        assert all(bool(torch.isfinite(g).all()) for g in grads)
        print(f"rasterization {sampler} packed={packed} backward w.r.t. the Gaussians, viewmats, means2d "
              "(absgrad): ok", flush=True)

    for background in (None, bg):
        img, alpha, meta = qr_cl.render_volume_fused(*geo, feats, cam.viewmat, cam.K, W, H,
                                                     background=background)
        ref, ref_alpha, _ = qr_cl.rasterize(*geo, feats, cam.viewmat, cam.K, W, H, sampler="volume",
                                            background=background)
        assert np.abs(img.numpy() - ref.numpy()).max() < 1e-4, "fused V-Render != volume selection"
        assert np.abs(alpha.numpy() - ref_alpha.numpy()).max() < 1e-5
        print(f"render_volume_fused background={background is not None}: ok "
              f"(densest ray {densest} Gaussians)", flush=True)
    half = torch.from_numpy(feats).half()                     # a float16 table: the HALF_ROWS builds
    for sampler in ("volume", "quantile"):
        inputs = [torch.from_numpy(a).requires_grad_(True) for a in geo] + [half.clone().requires_grad_(True)]
        img, _, _ = qr_cl.rasterization(*inputs, viewmats, Ks, W, H, sampler=sampler, k=4)
        img.sum().backward()
        assert all(bool(torch.isfinite(t.grad.float()).all()) for t in inputs)
    qr_cl.render_volume_fused(*geo, half, cam.viewmat, cam.K, W, H)
    print("float16 tables: rasterization volume and quantile forward+backward, render_volume_fused: ok",
          flush=True)
    wide = rng.normal(size=(n, 544)).astype(np.float32)      # two channel chunks of 17 vectors
    qr_cl.render_volume_fused(*geo, wide, cam.viewmat, cam.K, W, H)
    qr_cl.rasterize(*geo, wide, cam.viewmat, cam.K, W, H, sampler="quantile", k=4)
    print("render_volume_fused and rasterize, 544 channels: ok", flush=True)
    row_parts_exercise(rt, geo, cam, feats, wide, bg, pixels)

    for degree in (1, 3):                      # the color stage and its backward (sh_backward)
        coeffs = torch.from_numpy(sh).requires_grad_(True)
        qr_cl.rasterize(*geo, coeffs, cam.viewmat, cam.K, W, H, sh_degree=degree)[0].sum().backward()
        assert bool(torch.isfinite(coeffs.grad).all())
        qr_cl.render_volume_fused(*geo, sh, cam.viewmat, cam.K, W, H, sh_degree=degree)
        print(f"RGB from SH degree {degree}, forward and backward: ok", flush=True)

    walks_exercise(rt, geo, cam, feats, pixels)
    gpu_shaped, rt.gpu_shaped = rt.gpu_shaped, False   # CPU shapes: each K sampler with the blend fused in
    for sampler in ("quantile", "topk", "stratified"):
        for px, background in ((None, None), (pixels, bg)):
            for table in (feats, half):
                qr_cl.rasterize(*geo, table, cam.viewmat, cam.K, W, H, sampler=sampler, k=4,
                                background=background, pixels=px)
            print(f"rasterize {sampler} CPU shapes (selection with the blend) pixels={px is not None}: ok",
                  flush=True)
    rt.gpu_shaped = gpu_shaped

    roofline.FMA_ITERS = 16                    # fma_peak's loop length (passed as -DITERS)
    roofline.fma_rate(rt, work_items=16, rounds=1)
    roofline.stream_bandwidth(rt, mib=1, rounds=1)
    print("roofline fma_peak, triad: ok", flush=True)
    rt.queue.finish()


def quick_exercise() -> None:
    """The default suite's share of :func:`exercise`: every kernel file on one path each, both walks
    (the tile walk in windows), forward and backward; the slow suite runs the whole exercise."""
    import numpy as np
    import torch

    import qr_cl
    from qr_cl.runtime import runtime

    torch.set_num_threads(1)
    rt = runtime()
    print("device:", rt.device.name.strip(), "/", rt.device.platform.name.strip(), flush=True)
    means, quats, scales, opac, sh = tiny_scene()
    cam = qr_cl.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 20.0, 20.0, W, H)
    geo = (means, quats, scales, opac)
    feats = np.random.default_rng(1).normal(size=(len(means), 5)).astype(np.float32)
    bg = np.array([0.1, -0.2, 0.3, 0.4, 0.5], np.float32)
    pixels = np.array([[0, 0], [5, 5], [23, 15], [12, 8], [5, 5], [17, 3]], np.int32)
    for sampler in ("volume", "quantile", "topk", "stratified"):       # GPU shapes: tile walks, select -> blend
        f = torch.from_numpy(feats).requires_grad_(True)
        img, _, _ = qr_cl.rasterize(*geo, f, cam.viewmat, cam.K, W, H, sampler=sampler, k=4, background=bg,
                                    pixels=pixels if sampler in ("topk", "stratified") else None)
        img.sum().backward()
        assert bool(torch.isfinite(f.grad).all())
        print(f"rasterize {sampler} forward+backward: ok", flush=True)
    inputs = [torch.from_numpy(a).requires_grad_(True) for a in (*geo, feats)]
    img, alpha, meta = qr_cl.rasterization(*inputs, torch.from_numpy(cam.viewmat)[None], torch.from_numpy(cam.K)[None],
                                           W, H, packed=False, absgrad=True)
    (img.sum() + alpha.sum()).backward()
    assert all(bool(torch.isfinite(t.grad).all()) for t in inputs)
    qr_cl.render_volume_fused(*geo, feats, cam.viewmat, cam.K, W, H, background=bg)
    coeffs = torch.from_numpy(sh).requires_grad_(True)
    qr_cl.rasterize(*geo, coeffs, cam.viewmat, cam.K, W, H, sh_degree=3)[0].sum().backward()
    print("rasterization backward w.r.t. the Gaussians (absgrad), render_volume_fused, SH degree 3: ok", flush=True)
    gpu_shaped = rt.gpu_shaped
    rt.gpu_shaped, rt.loop_limit = True, WINDOWS_LIMITS[True]             # the tile walk in windows
    f = torch.from_numpy(feats).requires_grad_(True)
    qr_cl.rasterize(*geo, f, cam.viewmat, cam.K, W, H, sampler="quantile", k=4)[0].sum().backward()
    qr_cl.render_volume_fused(*geo, feats, cam.viewmat, cam.K, W, H)
    rt.gpu_shaped, rt.loop_limit = False, None                           # the block walk, blend fused in
    f = torch.from_numpy(feats).requires_grad_(True)
    qr_cl.rasterize(*geo, f, cam.viewmat, cam.K, W, H, sampler="quantile", k=4, background=bg)[0].sum().backward()
    qr_cl.render_volume_fused(*geo, feats, cam.viewmat, cam.K, W, H)
    rt.gpu_shaped = gpu_shaped
    print("tile walk in windows, block walk with the blend fused in, forward+backward: ok", flush=True)
    rt.queue.finish()


#: The loop limits under which walks_exercise walks in windows, for the block walk (CPU shapes) and
#: the tile walk (GPU shapes), whose loop iterations per list position differ: every walk over the
#: tiny scene's lists (up to 76 Gaussians) then takes two to five windows.
WINDOWS_LIMITS = {False: 2048, True: 256}


def walks_exercise(rt, geo, cam, feats, pixels) -> None:
    """Both walks of every sampler: the block walk (CPU shapes) and the tile walk (GPU shapes), in
    one launch (the samplers exercise() leaves to one shape) and in windows (WINDOWS_LIMITS),
    forward and backward, and the fused V-Render."""
    import torch

    import qr_cl
    gpu_shaped = rt.gpu_shaped
    runs = [(False, None, ("volume", "stratified")), (True, None, ("stratified",))]
    runs += [(shape, limit, ("volume", "quantile", "topk", "stratified")) for shape, limit in WINDOWS_LIMITS.items()]
    for rt.gpu_shaped, rt.loop_limit, samplers in runs:
        start = time.perf_counter()
        for sampler in samplers:
            f = torch.from_numpy(feats).requires_grad_(True)
            img, _, _ = qr_cl.rasterize(*geo, f, cam.viewmat, cam.K, W, H, sampler=sampler, k=4,
                                        pixels=pixels if sampler == "topk" else None)
            img.sum().backward()
            assert bool(torch.isfinite(f.grad).all())
        if rt.loop_limit:
            qr_cl.render_volume_fused(*geo, feats, cam.viewmat, cam.K, W, H)
        print(f"{'tile' if rt.gpu_shaped else 'block'} walks, loop limit {rt.loop_limit}: {', '.join(samplers)}"
              f"{' and the fused V-Render' if rt.loop_limit else ''} forward+backward: ok "
              f"({time.perf_counter() - start:.0f} s)", flush=True)
    rt.gpu_shaped, rt.loop_limit = gpu_shaped, None


def row_parts_exercise(rt, geo, cam, feats, wide, bg, pixels) -> None:
    """Tables in row parts (the kernels' row0 / n_rows / accumulate): the fused V-Render of two
    parts of ``feats`` added (against the whole table's), and
    renders with gradients of a table over a buffer limit of a third of it (three parts; the rays
    within it), on GPU and CPU shapes."""
    import numpy as np
    import torch

    import qr_cl
    from qr_cl.render import rasterize_plan
    from qr_cl.runtime import Runtime, channel_layout, host_empty, row_parts, to_device
    from qr_cl.stages import render_fused

    n, cut = len(feats), len(feats) // 3
    plan = rasterize_plan(*geo, cam.viewmat, cam.K, W, H)
    cstride = channel_layout(feats.shape[1], rt.gpu_shaped)[2]
    rows = np.zeros((n, cstride), np.float32)
    rows[:, :feats.shape[1]] = feats
    whole = render_fused(plan, to_device(rt, rows), feats.shape[1], bg)[0].copy()
    out = host_empty((H, W, cstride))
    for i, (r0, r1) in enumerate(((0, cut), (cut, n))):
        image = render_fused(plan, to_device(rt, rows[r0:r1]), feats.shape[1], None if i else bg, out=out, row0=r0,
                             accumulate=i > 0)[0]
    assert np.abs(image - whole).max() < 1e-4, "fused V-Render in row parts != the whole table's"
    limit, Runtime.max_buffer_bytes = Runtime.max_buffer_bytes, property(lambda self: wide.strides[0] * -(-n // 3))
    assert len(row_parts(rt, n, channel_layout(wide.shape[1])[2])) == 3
    gpu_shaped = rt.gpu_shaped
    for rt.gpu_shaped, sampler in ((gpu_shaped, "volume"), (gpu_shaped, "quantile"), (False, "quantile")):
        inputs = [torch.from_numpy(a).requires_grad_(True) for a in (*geo, wide)]
        img, alpha, _ = qr_cl.rasterize(*inputs, cam.viewmat, cam.K, W, H, sampler=sampler, k=4, pixels=pixels,
                                        background=np.linspace(-1, 1, wide.shape[1]))
        (img.sum() + alpha.sum()).backward()
        assert all(bool(torch.isfinite(t.grad).all()) for t in inputs)
    Runtime.max_buffer_bytes, rt.gpu_shaped = limit, gpu_shaped
    print("tables in row parts: render_volume_fused, rasterize volume and quantile (GPU and CPU shapes) "
          "forward+backward: ok", flush=True)


def exercise_pyopencl() -> None:
    """pyopencl's kernels that qr-cl uses, once each on the device (the ``races`` run): the
    exclusive "a+b" scan (binning, volume offsets, transposes), an inclusive "max(a, b)" scan
    (the GPU-shaped transpose) and the radix sort of binning, checked against numpy."""
    import numpy as np
    import pyopencl.array as cla
    from pyopencl.scan import InclusiveScanKernel

    from qr_cl.runtime import exclusive_scan, runtime
    from qr_cl.stages import radix_sorter

    rt = runtime()
    q = rt.queue
    rng = np.random.default_rng(2)
    x = rng.integers(0, 9, 2000).astype(np.int32)
    got = exclusive_scan(rt, cla.to_device(q, x), cla.empty(q, len(x), np.int32)).get()
    assert np.array_equal(got, np.cumsum(x) - x)
    y = cla.to_device(q, x)
    InclusiveScanKernel(rt.context, np.int32, "max(a, b)", "0")(y)
    assert np.array_equal(y.get(), np.maximum.accumulate(x))
    tiles, depths = rng.integers(0, 8, 1000), rng.integers(0, 2 ** 32, 1000)
    keys = (tiles.astype(np.uint64) << np.uint64(32)) | depths.astype(np.uint64)
    values = np.arange(1000, dtype=np.int32)
    (sk, sv), _ = radix_sorter(rt.context)(cla.to_device(q, keys), cla.to_device(q, values), key_bits=35)
    order = np.argsort(keys, kind="stable")
    assert np.array_equal(sk.get(), keys[order]) and np.array_equal(sv.get(), values[order])
    print("pyopencl exclusive scan, max scan, radix sort on the device: ok", flush=True)


PROJECT_RUNS = 3


def project_runs(path: str) -> None:
    """project.cl on the self-check scene (160 Gaussians, 40x24 px: tile rectangles of two tile
    rows, so tile_spans' lanes past the first count), :data:`PROJECT_RUNS` times on the same
    device arrays; the outputs of every run saved to ``path`` (npz) for the parent to check."""
    import numpy as np

    from qr_cl.render import selfcheck
    from qr_cl.runtime import runtime, to_device
    from qr_cl.stages.project import project

    rt = runtime()
    print("device:", rt.device.name.strip(), "/", rt.device.platform.name.strip(), flush=True)
    geometry, _, _, cam = selfcheck._scene()
    arrays = [to_device(rt, a) for a in geometry]
    runs = {}
    for run in range(PROJECT_RUNS):
        out = project(rt, *arrays, cam.viewmat, cam.K, selfcheck.WIDTH, selfcheck.HEIGHT, 0.01, 1e10)
        runs.update({f"{name}{run}": a.get() for name, a in zip(out._fields, out)})
    np.savez(path, **runs)


class Child(NamedTuple):
    """A child started by :func:`start_child`: its process, start time and folder (output files there)."""
    proc: subprocess.Popen
    start: float
    folder: Path


def start_child(mode: str, folder: Path, args: tuple[str, ...] = ()) -> Child:
    """The child in ``mode`` started under oclgrind in ``folder``, not waited for; its stdout and
    stderr go to files there (no pipe to fill while another child is waited for)."""
    vendors = folder / "vendors"
    vendors.mkdir()
    (vendors / "oclgrind.icd").write_text(oclgrind_icd() + "\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OCLGRIND_", "PYOPENCL_CTX"))}
    env.update(MODES.get(mode, {}), OCL_ICD_VENDORS=str(vendors), QR_CL_DEVICE="oclgrind:0",
               OCLGRIND_MAX_ERRORS="1000000",
               PYOPENCL_NO_CACHE="1",     # binaries cached by another run ignore BUILD_OPTIONS
               OMP_NUM_THREADS="1",
               # no self-check: its loop probe (64 x 2^20 iterations) took two of the child's three
               # minutes simulated, and its render check runs kernels that exercise() runs anyway
               QR_CL_SELF_CHECK="off",
               QR_CL_LOOP_LIMIT="none",  # oclgrind runs loops whole; its loop probe takes a minute there
               PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    with open(folder / "stdout.txt", "w") as out, open(folder / "stderr.txt", "w") as err:
        proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), mode, *args], cwd=folder, env=env,
                                stdout=out, stderr=err)
    return Child(proc, time.perf_counter(), folder)


def finish_child(child: Child, timeout: float = 600) -> tuple[subprocess.CompletedProcess, float]:
    """Wait for a :func:`start_child` child: (its finished process with its output, seconds since its start)."""
    try:
        child.proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        child.proc.kill()
        raise
    out, err = ((child.folder / name).read_text() for name in ("stdout.txt", "stderr.txt"))
    return (subprocess.CompletedProcess(child.proc.args, child.proc.returncode, out, err),
            time.perf_counter() - child.start)



if __name__ == "__main__":
    if sys.argv[1] == "project":
        project_runs(sys.argv[2])
        sys.exit()
    mode, scope = sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else "full"
    record_scan_and_sort_specs()
    if mode == "races" and scope == "full":
        exercise_pyopencl()
    use_host_scan_sort(uninitialized=mode == "uninitialized")
    quick_exercise() if scope == "quick" else exercise()
