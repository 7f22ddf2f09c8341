"""torchrun data-parallel training: 2 gloo ranks end with the weights of 1 rank accumulating the same scenes."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from qr_cl.app.process import torch_threads
from qr_cl.app.training.config import TrainConfig
from qr_cl.app.training.trainer import Trainer, train
from tests.synthetic_helpers import tiny_scene

REPO = Path(__file__).resolve().parents[2]


def test_two_ranks_match_gradient_accumulation(tmp_path):
    scenes = [str(tiny_scene(tmp_path / "cache", seed=s)) for s in (1, 2)]
    opts = ["--steps", "3", "--batch-scenes", "2", "--views", "2", "--rays", "128", "--net", "tiny",
            "--grid-size", "0.2", "--lr", "0.01", "-k", "8"]
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nnodes", "1", "--nproc_per_node", "2",
           "-m", "qr_cl.app.training.command", *scenes, "--out", str(tmp_path / "ddp"), *opts]
    proc = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    ddp = torch.load(tmp_path / "ddp" / "checkpoint.pt", weights_only=False)

    cfg = TrainConfig(scenes=scenes, out=str(tmp_path / "one"), steps=3, batch_scenes=2, views=2, rays=128,
                      net="tiny", grid_size=0.2, lr=0.01, k=8)
    with torch_threads(1):
        single = train(cfg, progress=False)
    assert ddp["step"] == 3
    np.testing.assert_allclose(ddp["history"], single.history, rtol=1e-5)
    params = dict(single.net.named_parameters())
    for name, value in ddp["model"].items():
        if name in params:
            torch.testing.assert_close(value, params[name].detach(), rtol=1e-5, atol=1e-6, msg=name)
    start = Trainer(cfg).net.state_dict()
    moved = max(float((ddp["model"][n] - start[n]).abs().max()) for n in params)
    assert moved > 1e-3  # the comparison is not between untrained nets
