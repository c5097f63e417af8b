"""The numba training kernel and TV against render_rays / tv_loss with autograd."""

from __future__ import annotations

import numba
import numpy as np
import pytest
import torch

from dbb_capture.datasets.records import ObjectVolume
from dbb_capture.static.field import FieldConfig, VoxelField
from dbb_capture.static.kernels import photometric_step, tv_step
from dbb_capture.static.render import render_rays
from dbb_capture.static.train import tv_loss

from .synthetic import band2


def _random_field(nearest: bool, sh_active: int) -> VoxelField:
    """A 12^3 field with 70 % of its points active, dense random density and degree-2 SH."""
    torch.manual_seed(3)
    cfg = FieldConfig(res_start=12, res_max=12, sh_degree=2)
    res = 12
    active = torch.randperm(res ** 3)[: int(0.7 * res ** 3)].sort().values
    n = active.numel()
    field = VoxelField(cfg, ObjectVolume((0.1, -0.2, 0.3), 0.5), res, torch.device("cpu"), active,
                       torch.randn(n, 1) * 2 + 3, torch.randn(n, 3 * cfg.n_basis))
    field.nearest = nearest
    field.sh_active = sh_active
    return field


def _one_thread(fn, *args):
    """``fn(*args)`` on one numba thread: no concurrent additions into one row, exact sums."""
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        return fn(*args)
    finally:
        numba.set_num_threads(threads)


@pytest.mark.parametrize("nearest,sh_active,weighted", [(False, 2, True), (True, 2, False), (False, 1, False)])
def test_photometric_step_matches_autograd(nearest, sh_active, weighted):
    """The numba step renders the same colours and adds the same gradients as render_rays +
    MSE + autograd, on a field with inactive points, interpolating trilinearly or (the tree
    fine-tuning phase) reading the nearest point, with per-ray weights (robust training); with
    the degree-2 band not yet in use (progressive SH), it neither colours nor gets a gradient."""
    field = _random_field(nearest, sh_active)
    vol = field.volume
    B = 64
    d = torch.nn.functional.normalize(torch.randn(B, 3), dim=-1)
    o = torch.tensor(vol.center) - 1.2 * d + 0.3 * torch.randn(B, 3) * 0.5
    bg, target = torch.rand(B, 3), torch.rand(B, 3)
    ray_w = torch.rand(B) if weighted else None
    out = render_rays(field, o, d, bg, jitter=False)
    se = ((out.rgb - target) ** 2).mean(-1)
    ref = se.mean()
    ((se * ray_w).mean() if weighted else ref).backward()
    g_dens, g_sh = field.density.grad.clone(), field.sh.grad.clone()
    field.density.grad.zero_()
    field.sh.grad.zero_()
    mse, rendered = _one_thread(photometric_step, field, o, d, bg, target, torch.full((B,), 0.5), ray_w)
    assert float(mse) == pytest.approx(float(ref.detach()), rel=1e-4)
    assert np.allclose(rendered[:, :3], out.rgb.detach().numpy(), atol=1e-5)
    assert np.allclose(rendered[:, 3], out.alpha.detach().numpy(), atol=1e-5)
    # The sentinel row (inactive points) is reset every step: the kernel gives it no gradient.
    assert torch.allclose(field.density.grad[:-1], g_dens[:-1], atol=1e-9, rtol=1e-4)
    assert torch.allclose(field.sh.grad[:-1], g_sh[:-1], atol=1e-9, rtol=1e-4)
    assert float(g_dens.abs().sum()) > 0 and float(g_sh.abs().sum()) > 0
    assert torch.equal(field.density.touched[:-1], g_dens[:-1, 0] != 0)
    assert (float(field.sh.grad[:, band2(field.cfg)].abs().sum()) == 0) == (sh_active < 2)


def test_tv_step_matches_autograd():
    """Total variation: the same means and gradients as tv_loss + autograd."""
    field = _random_field(False, 2)
    cfg = field.cfg
    tvd, tvs = tv_loss(field, 300, torch.Generator().manual_seed(5))
    (cfg.tv_density * tvd + cfg.tv_sh * tvs).backward()
    g_dens, g_sh = field.density.grad.clone(), field.sh.grad.clone()
    field.density.grad.zero_()
    field.sh.grad.zero_()
    d2, s2 = tv_step(field, 300, torch.Generator().manual_seed(5))
    assert d2 == pytest.approx(float(tvd.detach()), rel=1e-4) and s2 == pytest.approx(float(tvs.detach()), rel=1e-4)
    assert torch.allclose(field.density.grad, g_dens, atol=1e-12, rtol=1e-4)
    assert torch.allclose(field.sh.grad, g_sh, atol=1e-12, rtol=1e-4)
