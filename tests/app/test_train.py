"""Training: the loss falls on a tiny scene; --resume continues exactly; the loss itself; the free-feature fit."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from qr_cl.app.scenes.folders import load_scene_folder
from qr_cl.app.training.free_features import fit_free_features
from qr_cl.app.training.config import TrainConfig
from qr_cl.app.training.loss import contrastive_loss
from qr_cl.app.training.rays import sample_rays
from qr_cl.app.training.trainer import train


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def scene(tiny_room):
    return tiny_room


def _cfg(scene, out, **kw) -> TrainConfig:
    base = dict(scenes=[str(scene)], out=str(out), steps=12, views=2, rays=256, net="tiny", lr=1e-2,
                grid_size=0.2, checkpoint_every=100, plateau_interval=4)
    base.update(kw)
    return TrainConfig(**base)


def test_contrastive_loss_matches_formula():
    rng = np.random.default_rng(0)
    r, m = torch.tensor(rng.standard_normal((5, 8))), torch.tensor(rng.standard_normal((3, 8)))
    m = m / m.norm(dim=1, keepdim=True)
    t = torch.tensor([0, 2, 1, 1, 0])
    sim = (r / r.norm(dim=1, keepdim=True)) @ m.T / 0.5
    expected = -(sim[range(5), t] - torch.logsumexp(sim, 1)).mean()
    assert torch.allclose(contrastive_loss(r, t, m, 0.5), expected)
    perfect = contrastive_loss(m[t] * 3, t, m, 0.05)
    assert perfect < contrastive_loss(m[(t + 1) % 3], t, m, 0.05)


def test_rays_fall_inside_masks(scene):
    frame = load_scene_folder(scene).frames[0]
    pixels, rows = sample_rays(frame, 500, np.random.default_rng(0))
    assert (rows >= 0).all() and (frame.masks[pixels[:, 1], pixels[:, 0]] == rows).all()


@pytest.mark.parametrize("sampler", ["quantile", "volume"])
def test_tiny_training_loss_falls(scene, tmp_path, sampler):
    trainer = train(_cfg(scene, tmp_path, sampler=sampler, k=8), progress=False)
    loss = trainer.history
    assert len(loss) == 12 and np.isfinite(loss).all()
    assert np.mean(loss[-3:]) < 0.85 * np.mean(loss[:3]), loss
    ckpt = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert ckpt["step"] == 12 and {"model", "optimizer", "scheduler"} <= set(ckpt)


def test_resume_continues_exactly(scene, tmp_path):
    straight = train(_cfg(scene, tmp_path / "a", steps=6), progress=False)
    train(_cfg(scene, tmp_path / "b", steps=3), progress=False)
    resumed = train(_cfg(scene, tmp_path / "b", steps=6), resume=True, progress=False)
    assert resumed.history == straight.history
    for (name, a), b in zip(straight.net.state_dict().items(), resumed.net.state_dict().values()):
        assert torch.equal(a, b), name
    assert resumed.opt.state_dict()["state"][0]["step"] == straight.opt.state_dict()["state"][0]["step"]
    with pytest.raises(ValueError, match="different settings: lr"):
        train(_cfg(scene, tmp_path / "b", steps=7, lr=0.5), resume=True, progress=False)


def test_free_features_fit_one_scene(scene):
    data = load_scene_folder(scene)
    cfg = _cfg(scene, "-", steps=15, rays=256)
    feats = fit_free_features(data, cfg, progress=False)
    assert feats.shape == (len(data.gaussians), data.feature_dim)
    assert np.allclose(np.linalg.norm(feats, axis=1), 1, atol=1e-5)
    # The fitted features now render close to the masks' features on a training view.
    from qr_cl.app.training.rays import scene_loss
    untrained = torch.nn.functional.normalize(torch.randn(feats.shape, generator=torch.Generator().manual_seed(9)), dim=1)
    rng = lambda: np.random.default_rng(123)
    assert scene_loss(data, torch.from_numpy(feats), cfg, rng())[0] < 0.7 * scene_loss(data, untrained, cfg, rng())[0]


def test_the_training_thread_runs_no_kernel_while_the_next_rays_are_made(scene, tmp_path, monkeypatch):
    """The next step's rays are made on a background thread from when the step's blend backward
    is done; the training thread then launches nothing until it has them (kernel objects and
    the memory pool are not shared between threads at once)."""
    import threading
    import time

    from qr_cl.app.training import trainer as trainer_module
    from qr_cl.runtime import Runtime

    launches, making = [], []
    launch, make_rays = Runtime.launch, trainer_module.Trainer.make_rays

    def logged_launch(self, name, *args, **kwargs):
        launches.append((threading.current_thread() is threading.main_thread(), time.perf_counter(), name))
        return launch(self, name, *args, **kwargs)

    def timed_make_rays(self, *args):
        start = time.perf_counter()
        try:
            return make_rays(self, *args)
        finally:
            if threading.current_thread() is not threading.main_thread():
                making.append((start, time.perf_counter()))

    monkeypatch.setattr(Runtime, "launch", logged_launch)
    monkeypatch.setattr(trainer_module.Trainer, "make_rays", timed_make_rays)
    train(_cfg(scene, tmp_path, steps=5, k=8), progress=False)
    assert len(making) == 4                     # steps 2..5 made ahead
    overlapping = [name for main, t, name in launches if main and any(a < t < b for a, b in making)]
    assert not overlapping, overlapping
