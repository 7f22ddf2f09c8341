"""Shared fixtures: the real scenes (``shared_data`` in the root conftest.py; skipped cleanly when
absent), a random scene, a tiny synthetic room and one torch thread."""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

import qr_cl
from qr_cl.app.process import torch_threads
from qr_cl.scene import load_layout_instance
from tests.synthetic_helpers import tiny_scene


def _load(path: Path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return qr_cl.load_ply(path)


@pytest.fixture(scope="session")
def fox(shared_data):
    """The fox scene (50k Gaussians, SH degree 0, no cameras)."""
    return _load(shared_data / "wakufactory-fox" / "fox.ply")


@pytest.fixture(scope="session")
def donut(shared_data):
    """(Gaussians, cameras) of the donut scene, placed by its V3DG layout instance."""
    layout = shared_data / "v3dg-donut" / "_SingleDonut.json"
    scale, quat, translation = load_layout_instance(layout)
    g = _load(shared_data / "v3dg-donut" / "donut_fused.ply").transformed(scale, quat, translation)
    return g, qr_cl.load_cameras(layout)


def make_random_scene(n: int = 400, seed: int = 0, width: int = 70, height: int = 50):
    """(means, quats, scales, opacities, viewmat, K, width, height) of ``n`` random Gaussians in
    front of an identity camera; they cover the left ~3/4 of the image, so the right edge is empty."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(2.0, 6.0, n)
    means = np.stack([rng.uniform(-0.9, 0.45, n) * z, rng.uniform(-0.6, 0.6, n) * z, z], 1)
    quats = rng.standard_normal((n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    scales = np.exp(rng.uniform(np.log(0.02), np.log(0.4), (n, 3)))
    opacities = np.clip(rng.uniform(0.05, 1.2, n), 0, 1)
    f = 0.9 * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], np.float32)
    return (means.astype(np.float32), quats.astype(np.float32), scales.astype(np.float32),
            opacities.astype(np.float32), np.eye(4, dtype=np.float32), K, width, height)


@pytest.fixture(scope="session")
def random_scene():
    """A random scene of 400 Gaussians at 70x50 px (see make_random_scene)."""
    return make_random_scene()


@pytest.fixture(scope="module")
def one_torch_thread():
    """Run a module's tests with one torch thread (training's setting)."""
    with torch_threads(1):
        yield


@pytest.fixture(scope="session")
def tiny_room(tmp_path_factory):
    """The folder of a tiny synthetic training room (seed 1; see synthetic_helpers.tiny_config)."""
    return tiny_scene(tmp_path_factory.mktemp("rooms"), seed=1)
