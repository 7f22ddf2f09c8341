"""The constants of the 3DGS conventions and of qr-cl, defined once.

The kernels see the same values: every program is built with ``-D NAME=value`` for each entry of
:data:`KERNEL_CONSTANTS` (see :mod:`qr_cl.runtime.context`), so no kernel header defines them.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

TILE = 16                          # tiles are TILE x TILE pixels
ALPHA_MIN = np.float32(1) / np.float32(255)   # Gaussians with a smaller alpha are skipped
ALPHA_MAX = np.float32(0.99)       # alpha is clamped here
T_MIN = np.float32(1e-4)           # V-Render stops before T would drop to this
#: Tile spans (tile_spans in kernels/spans.h): a Gaussian is binned to the tiles of each tile row that
#: its blend ellipse sigma <= sigma_max reaches, the ellipse widened against float rounding: sigma_max
#: + SPAN_SLACK, times 1 + SPAN_ROUNDING * eps32 * (the conic's condition a c / det); the x-extent by
#: SPAN_MARGIN_PX + SPAN_MARGIN_REL * its half-width. Conics with det <= SPAN_DET_MIN or a condition
#: above SPAN_COND_MAX (needles, or not positive definite in float32) keep their whole tile rectangle.
SPAN_SLACK = 2e-3
SPAN_ROUNDING = 64.0
SPAN_MARGIN_PX = 1.0
SPAN_MARGIN_REL = 1e-3
SPAN_DET_MIN = 1e-30
SPAN_COND_MAX = 1e5
MAX_CHANNELS = 2048                # feature channels a render supports (1..MAX_CHANNELS)
#: Images of at least this many bytes are written with non-temporal stores (VSTREAM in
#: kernels/rows.h); smaller ones, e.g. a training step's rays, are read right after and stay cached.
STREAM_MIN_BYTES = 64 << 20

#: The window end of a walk launched whole (walk windows, kernels/common.h): past any list.
WALK_ALL = 2**31 - 1

#: Samplers of the selection stage (``qr_cl.stages.select``): which Gaussians a ray blends.
SAMPLERS = ("volume", "quantile", "topk", "stratified")


class Defaults(NamedTuple):
    """The defaults every command and the Python API read (docs/design.md, "Defaults"), defined
    here once."""

    sampler: str = "quantile"        # features render through Q-Render (the paper's GS-Net setting)
    k: int = 40                      # its K, and top-K's / Stratified-K's
    rasterize_sampler: str = "volume"  # rasterize / gsplat's rasterization: every Gaussian, as 3DGS
    width: int = 640                 # px of a picture from orbit cameras
    height: int = 480


#: The defaults (see :class:`Defaults`).
DEFAULTS = Defaults()


class SplatLayout(NamedTuple):
    """Where the fields of a Gaussian's splat lie in its float8 (slot numbers): the splat
    project.cl writes and every walk reads, and its gradient (``d_splats``, the same slots: d mean,
    d conic, d opacity, d depth) except that blend.cl's splat_backward sums absgrad, gsplat's
    per-Gaussian sums of |d mean2d x|, |d mean2d y|, into the slots of depth and sigma_max.

    Python indexes a splat array [..., 8] with the fields (``splats[..., SPLAT.mean]``); the
    kernels get them as swizzles by :meth:`defines` (``s.SPLAT_OPACITY`` is slot 5 of splat ``s``).
    """

    mean: slice = slice(0, 2)        # mean2d (x, y), px
    conic: slice = slice(2, 5)       # conic (a, b, c) = the inverse 2D covariance [[a, b], [b, c]]
    opacity: int = 5
    depth: int = 6                   # camera z
    sigma_max: int = 7               # ln(opacity / ALPHA_MIN): beyond this exponent alpha is skipped
    absgrad: slice = slice(6, 8)     # of a gradient only: sum |d mean2d x|, sum |d mean2d y|

    def defines(self) -> dict[str, str]:
        """``SPLAT_<FIELD>`` -> the OpenCL C swizzle of its slots (``s01``), and for the fields of
        several slots each slot alone: ``SPLAT_MEAN_X``, ``_Y``; ``SPLAT_CONIC_A``, ``_B``, ``_C``;
        ``SPLAT_ABSGRAD_X``, ``_Y``."""
        parts = {"mean": "XY", "conic": "ABC", "absgrad": "XY"}
        out = {}
        for name, where in self._asdict().items():
            slots = range(SPLAT_FLOATS)[where] if isinstance(where, slice) else [where]
            out[f"SPLAT_{name.upper()}"] = "s" + "".join(f"{k:x}" for k in slots)
            for part, k in zip(parts.get(name, ""), slots):
                out[f"SPLAT_{name.upper()}_{part}"] = f"s{k:x}"
        return out


#: Floats of a splat (an OpenCL float8).
SPLAT_FLOATS = 8
#: The splat's layout (see :class:`SplatLayout`).
SPLAT = SplatLayout()


class WalkStateLayout(NamedTuple):
    """Where a selection's walk waits between walk windows (kernels/select.h): a slot of the ray's
    float8 in ``state_f`` for each float field, of its int4 in ``state_i`` for each of
    :attr:`INTS`. Every field has a slot of its own whatever the sampler (a walk keeps some of
    them), so T and T^Q lie in the same slots for Q-Render and Stratified-K.

    The kernels get them as swizzles by :meth:`defines` (``state_f[p].WALK_TQ`` is slot 1)."""

    t: int = 0                       # T, the transmittance of the walk
    tq: int = 1                      # T^Q, among the selected Gaussians (quantile, stratified)
    mu: int = 2                      # Stratified-K's boundaries: the normal's mean,
    sigma: int = 3                   # its deviation
    t_end: int = 4                   # and the T where the first walk ended
    sum: int = 5                     # Stratified-K's first walk: the sum of T after each Gaussian,
    sum_sq: int = 6                  # of T^2
    used: int = 7                    # and their count
    k: int = 0                       # int: the next boundary (quantile, stratified)
    n: int = 1                       # int: the entries written (top-K's heap size; V-Render's fill: next slot)
    done: int = 2                    # int: -1 once the ray stopped, else 0

    INTS = ("k", "n", "done")

    def defines(self) -> dict[str, str]:
        """``WALK_<FIELD>`` -> the OpenCL C swizzle of its slot (``s1``)."""
        return {f"WALK_{name.upper()}": f"s{slot:x}" for name, slot in self._asdict().items()}


#: Floats (an OpenCL float8) and ints (an int4) of a ray's walk state.
WALK_STATE_FLOATS = 8
WALK_STATE_INTS = 4
#: The walk state's layout (see :class:`WalkStateLayout`).
WALK_STATE = WalkStateLayout()

class VolumeStateLayout(NamedTuple):
    """Where the fused V-Render's walk waits between walk windows (kernels/vrender.cl): a slot of
    the ray's float4 for each field. The kernels get them as swizzles by :meth:`defines`
    (``st.VSTATE_DEPTH_SUM`` is slot 1)."""

    t: int = 0                       # T, the transmittance of the walk
    depth_sum: int = 1               # the sum of w_i z_i so far (the expected depth's numerator)
    done: int = 2                    # 1 once the ray stopped, else 0

    def defines(self) -> dict[str, str]:
        """``VSTATE_<FIELD>`` -> the OpenCL C swizzle of its slot (``s1``)."""
        return {f"VSTATE_{name.upper()}": f"s{slot:x}" for name, slot in self._asdict().items()}


#: Floats (an OpenCL float4) of a ray's fused V-Render walk state.
VOLUME_STATE_FLOATS = 4
#: The fused V-Render's walk state layout (see :class:`VolumeStateLayout`).
VOLUME_STATE = VolumeStateLayout()

#: A Gaussian's footprint (project.cl writes it, the binning passes read it): 16 int32 (an OpenCL
#: int16, 64 bytes) holding its tile rectangle [x0, y0, x1, y1) and, from int FOOTPRINT_SPANS.start
#: on, the tiles [x0, x1) of up to SPAN_ROWS of its tile rows as ushorts (x0 - rect x0) |
#: (x1 - rect x0) << 8 (kernels/spans.h: FOR_TILE_SPANS).
FOOTPRINT_INTS = 16
FOOTPRINT_RECT = slice(0, 4)
FOOTPRINT_SPANS = slice(4, FOOTPRINT_INTS)
SPAN_ROWS = 2 * (FOOTPRINT_SPANS.stop - FOOTPRINT_SPANS.start)

#: Real spherical-harmonic basis constants (original 3DGS computeColorFromSH), degrees 0..3.
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def _float_literal(x: float) -> str:
    """OpenCL C float literal of float32(x) (9 significant digits round-trip a float32)."""
    text = f"{np.float32(x):.9g}"
    text += "f" if any(ch in text for ch in ".e") else ".f"        # 64 -> 64.f, not the int 64f
    return f"({text})" if text.startswith("-") else text


def _kernel_constants() -> dict[str, str]:
    out = {"TILE": str(TILE), "WALK_ALL": str(WALK_ALL), "ALPHA_MIN": _float_literal(ALPHA_MIN),
           "ALPHA_MAX": _float_literal(ALPHA_MAX), "T_MIN": _float_literal(T_MIN),
           "SPAN_SLACK": _float_literal(SPAN_SLACK), "SPAN_ROUNDING": _float_literal(SPAN_ROUNDING),
           "SPAN_MARGIN_PX": _float_literal(SPAN_MARGIN_PX), "SPAN_MARGIN_REL": _float_literal(SPAN_MARGIN_REL),
           "SPAN_DET_MIN": _float_literal(SPAN_DET_MIN), "SPAN_COND_MAX": _float_literal(SPAN_COND_MAX),
           "SH_C0": _float_literal(SH_C0), "SH_C1": _float_literal(SH_C1)}
    for name, values in (("SH_C2", SH_C2), ("SH_C3", SH_C3)):
        out.update({f"{name}_{i}": _float_literal(v) for i, v in enumerate(values)})
    out.update(SPLAT.defines())
    out.update(WALK_STATE.defines())
    out.update(VOLUME_STATE.defines())
    out.update({"FOOTPRINT_RECT": str(FOOTPRINT_RECT.start), "FOOTPRINT_SPANS": str(FOOTPRINT_SPANS.start),
                "SPAN_ROWS": str(SPAN_ROWS)})
    return out


#: ``-D`` definitions every kernel program is built with (name -> OpenCL C literal).
KERNEL_CONSTANTS: dict[str, str] = _kernel_constants()
