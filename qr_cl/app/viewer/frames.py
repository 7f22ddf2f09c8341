"""Frames of the web viewer: a camera pose, a render mode, a query, a sampler and K in, an 8-bit
RGB image rendered by qr-cl out.

Modes: ``rgb`` (the SH colours through the fused V-Render), and, when the scene has features,
``pca`` (each Gaussian coloured by the 3 principal components of the features, fixed for the
session so colours stay put while moving), ``classes`` (each Gaussian coloured by its predicted
class of the scene's classes.json, the prediction of ``qr-cl eval``) and ``relevancy`` (a query's
per-Gaussian score as a heatmap over the grey RGB, as ``qr-cl query`` draws it). The feature modes
render per-Gaussian colours or scores through the chosen sampler and K.
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, replace

import numpy as np
import torch
from matplotlib import colormaps

from ...runtime import DEFAULTS, SAMPLERS
from ...scene import Camera, look_at
from ..evaluation.metrics import UNLABELLED
from ..evaluation.scoring import predict
from ..evaluation.visuals import UNLABELLED_RGB
from ..query.pictures import heat_colours, overlay, render_rgb, render_values
from ..query.relevancy import score, score_range
from ..query.scene import QueryScene
from ..query.text import QueryError, TextLookup, normalise

MODES = ("rgb", "pca", "classes", "relevancy")
#: Largest frame side the viewer renders, px.
MAX_SIDE = 4096
#: Largest K the viewer renders (a selection holds K entries per pixel).
MAX_K = 512


@dataclass(frozen=True)
class FrameRequest:
    """One frame: camera ``eye``, ``target`` and ``up`` (world, 3 floats each), vertical field of
    view ``fov_y`` (degrees), size in px, ``mode`` (:data:`MODES`), ``query`` text (relevancy),
    ``sampler`` and ``k`` of the feature modes."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float]
    fov_y: float
    width: int
    height: int
    mode: str = "rgb"
    query: str = ""
    sampler: str = DEFAULTS.sampler
    k: int = DEFAULTS.k

    def camera(self) -> Camera:
        """The pinhole camera of this request (square pixels, centred principal point)."""
        f = 0.5 * self.height / math.tan(math.radians(self.fov_y) / 2)
        return look_at(self.eye, self.target, self.up, f, f, self.width, self.height)

    def check(self) -> None:
        """QueryError naming the first field out of range."""
        values = [*self.eye, *self.target, *self.up, self.fov_y]
        if not all(math.isfinite(v) for v in values):
            raise QueryError("camera values must be finite numbers")
        if not 1 <= self.fov_y <= 170:
            raise QueryError(f"fov_y={self.fov_y}: choose 1..170 degrees")
        if not (8 <= self.width <= MAX_SIDE and 8 <= self.height <= MAX_SIDE):
            raise QueryError(f"frame size {self.width}x{self.height}: each side 8..{MAX_SIDE} px")
        if self.mode not in MODES:
            raise QueryError(f"mode={self.mode!r}: choose one of {MODES}")
        if self.sampler not in SAMPLERS:
            raise QueryError(f"sampler={self.sampler!r}: choose one of {SAMPLERS}")
        if not 1 <= self.k <= MAX_K:
            raise QueryError(f"k={self.k}: choose 1..{MAX_K}")
        forward = np.subtract(self.target, self.eye)
        if np.linalg.norm(np.cross(forward, self.up)) <= 1e-9 * max(np.linalg.norm(forward), 1e-30):
            raise QueryError("the camera looks along its up vector (or eye = target)")


def pca_colours(features: np.ndarray) -> np.ndarray:
    """[N,3] colours in [0,1]: the 3 principal components of ``features`` [N,C], each stretched
    over its 1st..99th percentile."""
    flat = torch.from_numpy(np.asarray(features, np.float64))
    centred = flat - flat.mean(0)
    sample = centred[:: max(1, len(flat) // 8192)]
    _, vecs = torch.linalg.eigh(sample.T @ sample)
    proj = (centred @ vecs.flip(1)[:, :3]).numpy()
    lo, hi = np.percentile(proj, 1, axis=0), np.percentile(proj, 99, axis=0)
    return np.clip((proj - lo) / np.maximum(hi - lo, 1e-12), 0, 1).astype(np.float32)


def class_palette(ids) -> dict[int, np.ndarray]:
    """A colour [3] per class id, in sorted id order: tab20's (as ``qr-cl eval``'s pictures), then
    tab20b's and tab20c's, so up to 60 classes get distinct colours."""
    colours = [colormaps[name](i)[:3] for name in ("tab20", "tab20b", "tab20c") for i in range(20)]
    return {c: np.asarray(colours[i % len(colours)], np.float32) for i, c in enumerate(sorted(int(c) for c in ids))}


def to_hex(colour: np.ndarray) -> str:
    """#rrggbb of an RGB colour [3] in [0,1]."""
    return "#" + "".join(f"{int(round(float(x) * 255)):02x}" for x in colour)


class FrameRenderer:
    """Renders :class:`FrameRequest` s of ``scene`` with per-Gaussian ``features`` [N,C] (or None:
    RGB only); ``lookup`` resolves query texts (None: no relevancy). One render at a time (a
    lock), so server threads may call :meth:`render` together."""

    def __init__(self, scene: QueryScene, features: np.ndarray | None = None, lookup: TextLookup | None = None,
                 method: str = "relevancy"):
        self.scene, self.features, self.lookup, self.method = scene, features, lookup, method
        self._lock = threading.Lock()
        self._scores: dict[str, tuple[np.ndarray, float, float]] = {}
        g = scene.gaussians
        self.rgb = np.ascontiguousarray(g.rgb, np.float32)
        self.pca = pca_colours(features) if features is not None else None
        self.legend: list[dict] = []
        self.class_colours = None
        if features is not None and scene.classes is not None:
            pred = predict(features, scene.classes)
            palette = class_palette(scene.classes.ids)
            palette[UNLABELLED] = UNLABELLED_RGB
            self.class_colours = np.stack([palette[int(c)] for c in pred])
            names = {**dict(zip(scene.classes.ids.tolist(), scene.classes.names)), UNLABELLED: "no feature"}
            ids, counts = np.unique(pred, return_counts=True)
            self.legend = [{"name": names[int(c)], "colour": to_hex(palette[int(c)]), "gaussians": int(n)}
                           for c, n in sorted(zip(ids, counts), key=lambda p: -p[1])]

    def modes(self) -> list[str]:
        """The modes this scene can show."""
        have = {"rgb": True, "pca": self.pca is not None, "classes": self.class_colours is not None,
                "relevancy": self.features is not None and self.lookup is not None}
        return [m for m in MODES if have[m]]

    def warm_up(self, request: FrameRequest) -> None:
        """Render ``request`` once in every mode but relevancy (whose query is not known yet), so
        that the kernels are built before the page's first frame."""
        for mode in self.modes():
            if mode != "relevancy":
                self.render(replace(request, mode=mode))

    def scores(self, text: str) -> tuple[np.ndarray, float, float]:
        """(per-Gaussian score [N] of ``text``, the colour map's low and high), cached per text;
        UnknownQueryError for text the lookup does not know."""
        key = normalise(text)
        if key not in self._scores:
            values = score(self.features, self.lookup, self.lookup(text), self.method)
            self._scores[key] = (values, *score_range(values))
        return self._scores[key]

    def render(self, request: FrameRequest) -> tuple[np.ndarray, float]:
        """(image [H,W,3] uint8, render time in ms) of ``request``; QueryError for a request
        this scene cannot render (a mode it lacks, an unknown query, a value out of range)."""
        request.check()
        if request.mode not in self.modes():
            raise QueryError(f"mode {request.mode!r} needs per-Gaussian features (--checkpoint or --features)"
                             + (" and a classes.json" if request.mode == "classes" else ""))
        with self._lock:
            start = time.perf_counter()
            image = self._image(request)
            seconds = time.perf_counter() - start
        return (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8), 1000 * seconds

    def _image(self, request: FrameRequest) -> np.ndarray:
        g, cam = self.scene.gaussians, request.camera()
        if request.mode == "rgb":
            return render_rgb(g, cam)[0]
        if request.mode == "relevancy":
            values, lo, hi = self.scores(request.query)
            table = np.concatenate([self.rgb, values[:, None]], 1)
        else:
            table = self.pca if request.mode == "pca" else self.class_colours
        image, alpha = render_values(g, table, cam, request.sampler, request.k)
        if request.sampler == "volume":               # V-Render's weights sum to alpha: undo for the average
            image = image / np.maximum(alpha, 1e-6)[..., None]
        if request.mode == "relevancy":
            return overlay(image[..., :3], heat_colours(image[..., 3], lo, hi), alpha)
        return image * alpha[..., None]
