"""SH colors (sh.cl) and their backward against the float64 twin (qr_cl.stages.sh_ref)."""
import numpy as np
import pytest
import torch

from qr_cl.runtime import runtime, to_device
from qr_cl.stages import sh_colors, sh_ref
from qr_cl.stages.sh import sh_backward
from tests.twins import hostile_scene


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_colors_match_reference(degree):
    g = hostile_scene(n=300, seed=degree, degree=degree)
    campos = np.array([0.3, -0.2, -1.0])
    rt = runtime()
    rgb = sh_colors(rt, to_device(rt, g.means), g.sh, campos).get()
    np.testing.assert_allclose(rgb[:, :3], sh_ref.sh_to_rgb(g.means, g.sh, campos), atol=1e-5)
    assert (rgb[:, 3] == 0).all()


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_backward_matches_the_twins_autograd(degree):
    """sh_backward (sh.cl) against autograd of the float64 twin: d coefficients and d means,
    including Gaussians whose color is clamped at 0 (no gradient through the clamp)."""
    g = hostile_scene(n=300, seed=degree, degree=degree)
    g.sh[::10] -= 3.0                                            # some colors clamped at 0
    campos = np.array([0.3, -0.2, -1.0], np.float32)
    rt = runtime()
    means = to_device(rt, g.means)
    colors = sh_colors(rt, means, g.sh, campos)
    d_rgb = np.random.default_rng(degree).normal(size=(len(g.means), 3)).astype(np.float32)
    d_sh, d_means = sh_backward(rt, means, g.sh, campos, colors, d_rgb)
    m, c = (torch.tensor(a, dtype=torch.float64, requires_grad=True) for a in (g.means, g.sh))
    rgb = sh_ref.sh_to_rgb(m, c, torch.tensor(campos, dtype=torch.float64))
    assert (rgb == 0).any()
    (rgb * torch.from_numpy(d_rgb).double()).sum().backward()
    want_means = m.grad.numpy() if m.grad is not None else np.zeros_like(d_means)
    np.testing.assert_allclose(d_sh, c.grad.numpy(), atol=1e-5 * float(c.grad.abs().max()))
    np.testing.assert_allclose(d_means, want_means, atol=1e-5 * max(float(np.abs(want_means).max()), 1e-3))
