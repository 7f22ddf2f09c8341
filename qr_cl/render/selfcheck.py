"""The render check a device passes before qr-cl renders on it, and the accessor of the runtime
that passed it (:func:`checked_runtime`), which the public calls render on: a tiny scene through every
sampler (forward and feature backward), a table read in row parts (as one larger than the device's
largest buffer is) and a float16 table through Q-Render, and the fused V-Render, against the
float64 twins.

It catches drivers that build and run the kernels but compute something else (the loop probe of
:func:`qr_cl.runtime.trial_run` catches loops ended early). A device that fails is refused with
:class:`DeviceCheckError` naming the implementation, its version and what differed. A pass is
remembered per device, driver and kernel source in ``$QR_CL_CACHE/checks`` (default
``~/.cache/qr-cl/checks``), so later processes skip it. ``QR_CL_SELF_CHECK=off`` skips it.

The check renders through the engine the public calls adapt (:func:`qr_cl.render.engine.render_view`
and :func:`qr_cl.render.engine.fused_volume`, on the runtime it checks), so this module sits above
the engine and below the public calls (:mod:`qr_cl.render.rasterize`, :mod:`qr_cl.render.gsplat_compat`).
"""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from ..runtime import (KERNEL_CONSTANTS, SAMPLERS, NoDeviceError, Runtime, implementation, kernel_files, kernel_source,
                       runtime, self_check_enabled)
from ..scene import look_at
from ..stages import blend_ref, check_pixels, check_sampler, select_ref, vrender_ref
from .autograd import View
from .engine import feature_tensor, fused_volume, gaussian_tensors, render_view
from .rays import image_pixels
from .meta import RenderMeta

#: The check scene: Gaussians, image size (px), channels, K of the K samplers.
N_GAUSSIANS, WIDTH, HEIGHT, CHANNELS, K = 160, 40, 24, 24, 5
#: The table rendered with the device's buffers capped to a third of it (three row parts, ray
#: sets of 54 rays): its channels, and every how many pixels a ray is drawn.
WIDE_CHANNELS, PIXEL_STEP = 256, 7
#: A pixel differs when its largest channel error exceeds this fraction of the image's largest
#: value; a few may (rays whose transmittance meets a boundary at float rounding), no more.
PIXEL_RTOL, DIFFERING_PIXELS = 1e-3, 0.02

_PASSED: set[int] = set()


class DeviceCheckError(NoDeviceError):
    """A device built and ran qr-cl's kernels but rendered something else than the twins."""


def _scene():
    """A seeded scene of overlapping Gaussians in front of a camera at the origin (tile lists of
    tens of entries, rays that blend more than K), features and an image gradient."""
    rng = np.random.default_rng(7)
    z = rng.uniform(2, 5, N_GAUSSIANS)
    means = np.c_[rng.uniform(-0.7, 0.7, N_GAUSSIANS) * z, rng.uniform(-0.45, 0.45, N_GAUSSIANS) * z, z]
    quats = rng.normal(size=(N_GAUSSIANS, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    scales = np.exp(rng.uniform(np.log(0.05), np.log(0.5), (N_GAUSSIANS, 3)))
    opacities = rng.uniform(0.1, 0.9, N_GAUSSIANS)
    features = rng.normal(size=(N_GAUSSIANS, CHANNELS))
    grad = rng.normal(size=(HEIGHT * WIDTH, CHANNELS))
    cam = look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 30.0, 30.0, WIDTH, HEIGHT)
    f32 = lambda a: np.ascontiguousarray(a, np.float32)
    return (f32(means), f32(quats), f32(scales), f32(opacities)), f32(features), f32(grad), cam


def _differing(got: np.ndarray, want: np.ndarray) -> float:
    """The fraction of pixels (rows) of got whose largest error exceeds PIXEL_RTOL of want's scale."""
    scale = max(float(np.abs(want).max()), 1e-6)
    return float(np.mean(np.abs(got - want).max(axis=1) > PIXEL_RTOL * scale))


def _camera(cam) -> tuple[np.ndarray, np.ndarray]:
    """The check camera's viewmat [4,4] and K [3,3] as float32 arrays, as the public calls take them."""
    return np.ascontiguousarray(cam.viewmat, np.float32), np.ascontiguousarray(cam.K, np.float32)


def _render(rt: Runtime, geometry, features, cam, sampler: str, pixels: np.ndarray | None = None):
    """``qr_cl.rasterize``'s render of the check scene on ``rt`` (the engine under it, the same
    argument checks): image [P,C] (P = the pixels, or H*W) and its meta."""
    viewmat, intrinsics = _camera(cam)
    rays = None if pixels is None else check_pixels(pixels, WIDTH, HEIGHT)
    view = View(viewmat, intrinsics, WIDTH, HEIGHT, sampler=sampler, k=check_sampler(sampler, K), pixels=rays)
    out = render_view(*gaussian_tensors(*geometry), feature_tensor(features, N_GAUSSIANS), None, view, rt=rt)
    return out.image, RenderMeta(out.plan)


def _sampler_failures(rt: Runtime, label: str, geometry, features: np.ndarray, grad: np.ndarray, cam, sampler: str,
                      pixels: np.ndarray | None = None) -> list[str]:
    """Render ``features`` [N, C] with ``sampler`` at ``pixels`` (None: the whole image) on ``rt``
    forward and the feature gradient of sum(image * grad) backward; what of the two differs from
    the twins."""
    f = torch.from_numpy(features).requires_grad_(True)
    image, meta = _render(rt, geometry, f, cam, sampler, pixels)
    image = image.reshape(-1, features.shape[1])
    (image * torch.from_numpy(grad)).sum().backward()
    rays = image_pixels(WIDTH, HEIGHT) if pixels is None else pixels
    twin = select_ref.select(meta, meta["tile_ranges"], meta["flatten_ids"], rays, WIDTH, sampler, K)
    want = blend_ref.blend(twin["ids"], twin["weights"], features)
    want_grad = np.zeros(features.shape)
    valid = twin["ids"] >= 0
    np.add.at(want_grad, twin["ids"][valid], twin["weights"][valid][:, None] * grad[np.nonzero(valid)[0]])
    failures = []
    for what, got, ref in (("image", image.detach().numpy(), want), ("feature gradient", f.grad.numpy(), want_grad)):
        share = _differing(got, ref)
        if share > DIFFERING_PIXELS:
            failures.append(f"{label} {what}: {share:.0%} of its rows differ from the float64 twin")
    return failures


def render_check(rt: Runtime | None = None) -> list[str]:
    """Render the check scene on ``rt`` (default: the process's runtime); returns what differed
    from the twins (empty when the device passed)."""
    rt = rt or runtime()
    geometry, features, grad, cam = _scene()
    pixels = image_pixels(WIDTH, HEIGHT)
    failures = []
    for sampler in SAMPLERS:
        failures += _sampler_failures(rt, sampler, geometry, features, grad, cam, sampler)
    rng = np.random.default_rng(8)                                   # a table read in row parts
    wide = rng.normal(size=(N_GAUSSIANS, WIDE_CHANNELS)).astype(np.float32)
    some = pixels[::PIXEL_STEP]
    with rt.capped_buffers(wide.strides[0] * -(-N_GAUSSIANS // 3)):
        failures += _sampler_failures(rt, f"quantile, a table in row parts ({WIDE_CHANNELS} channels),", geometry,
                                      wide, rng.normal(size=(len(some), WIDE_CHANNELS)).astype(np.float32), cam,
                                      "quantile", some)
    half = features.astype(np.float16)                               # read as half (vload_half)
    image, meta = _render(rt, geometry, half, cam, "quantile")
    twin = select_ref.select(meta, meta["tile_ranges"], meta["flatten_ids"], pixels, WIDTH, "quantile", K)
    want = blend_ref.blend(twin["ids"], twin["weights"], half.astype(np.float64))
    share = _differing(image.numpy().reshape(-1, CHANNELS), want)
    if share > DIFFERING_PIXELS:
        failures.append(f"quantile image of a float16 table: {share:.0%} of its rows differ from the float64 twin")
    image, _, plan, _ = fused_volume(rt, *gaussian_tensors(*geometry), feature_tensor(features, N_GAUSSIANS), None,
                                     *_camera(cam), WIDTH, HEIGHT)
    meta = RenderMeta(plan)
    want = vrender_ref.vrender(meta, meta["tile_ranges"], meta["flatten_ids"], features, WIDTH, HEIGHT)[0]
    share = _differing(image.numpy().reshape(-1, CHANNELS), want.reshape(-1, CHANNELS))
    if share > DIFFERING_PIXELS:
        failures.append(f"fused V-Render image: {share:.0%} of its pixels differ from the float64 twin")
    return failures


def _record(rt: Runtime) -> Path:
    """Where a pass of ``rt``'s device is remembered: keyed by the implementation, the launch
    shapes, every kernel source and build constant, and this check's own source (a pass of an
    earlier check, which rendered less, is not taken for one of this)."""
    key = hashlib.sha256()
    for part in (implementation(rt.device), str(rt.gpu_shaped), str(rt.accumulator_floats), str(rt.loop_limit),
                 str(rt.group_limit),
                 json.dumps(KERNEL_CONSTANTS, sort_keys=True), Path(__file__).read_text(),
                 *(kernel_source(f) for f in sorted(set(kernel_files().values())))):
        key.update(part.encode())
    root = Path(os.environ.get("QR_CL_CACHE", Path.home() / ".cache" / "qr-cl")) / "checks"
    return root / f"{key.hexdigest()[:32]}.json"


def checked_runtime() -> Runtime:
    """The process-wide Runtime, its device having passed :func:`render_check` (once per process,
    or remembered from an earlier one). Raises DeviceCheckError when it fails."""
    rt = runtime()
    if id(rt) in _PASSED or not self_check_enabled():
        return rt
    record = _record(rt)
    if not record.is_file():
        with torch.enable_grad():          # it may be first reached under no_grad or in a Function's forward
            failures = render_check(rt)
        if failures:
            raise DeviceCheckError(f"{implementation(rt.device)} failed qr-cl's render check, so qr-cl refuses "
                                   "it (QR_CL_DEVICE chooses another device):\n  " + "\n  ".join(failures))
        record.parent.mkdir(parents=True, exist_ok=True)
        record.write_text(json.dumps({"device": implementation(rt.device), "passed": True}))
    _PASSED.add(id(rt))
    return rt


def check_in_child(platform_index: int, device_index: int) -> str:
    """The render check of device ``device_index`` of platform ``platform_index`` in a child
    process (each process renders on one device): "render check passed" or what failed."""
    env = {**os.environ, "PYOPENCL_CTX": f"{platform_index}:{device_index}"}
    env.pop("QR_CL_DEVICE", None)
    run = subprocess.run([sys.executable, "-c", "from qr_cl.render.selfcheck import report; report()"], env=env,
                         capture_output=True, text=True, timeout=600)
    lines = run.stdout.strip().splitlines()
    return lines[-1] if lines else f"render check died ({run.returncode}): {run.stderr.strip()[-300:]}"


def report() -> None:
    """Print the verdict of :func:`checked_runtime` on this process's device in one line."""
    try:
        checked_runtime()
    except NoDeviceError as exc:
        print("render check failed: " + " ".join(str(exc).split("\n")[1:]).strip())
    else:
        print("render check passed")
