"""Rendering the field: the kernel's images against the PyTorch renderer, samplers, backgrounds."""

from __future__ import annotations

import numpy as np
import torch

from dbb_capture.datasets.records import ObjectVolume
from dbb_capture.static.field import FieldConfig, VoxelField
from dbb_capture.static.render import (
    object_samples,
    render_image,
    render_rays,
    scene_samples,
)


def _field(mode: str = "object") -> VoxelField:
    g = torch.Generator().manual_seed(4)
    res = 16
    cfg = FieldConfig(mode=mode, res_start=res, res_max=res, sh_degree=1)
    active = torch.randperm(res ** 3, generator=g)[: res ** 3 // 2].sort().values
    return VoxelField(cfg, ObjectVolume((0.1, -0.2, 0.3), 0.5), res, torch.device("cpu"), active,
                      torch.randn(active.numel(), 1, generator=g) + 6,
                      torch.randn(active.numel(), 12, generator=g))


def _rays(field: VoxelField, B: int = 96) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(5)
    d = torch.nn.functional.normalize(torch.randn(B, 3, generator=g), dim=-1)
    return torch.tensor(field.volume.center) - 1.2 * d + 0.1 * torch.randn(B, 3, generator=g), d


def test_images_of_the_kernel_and_of_the_pytorch_renderer_agree():
    """render_image on the CPU in object mode runs the numba kernel: straight RGBA equal to
    render_rays' colour over black, unpremultiplied; on a background, the composite."""
    field = _field()
    assert field.cpu_kernel
    o, d = _rays(field)
    with torch.no_grad():
        ref = render_rays(field, o, d)
    a = ref.alpha.clamp(0, 1)
    img = render_image(field, o[:, None], d[:, None], None)
    assert img.shape == (96, 1, 4)
    assert np.allclose(img[:, 0, 3], a.numpy(), atol=1e-5)
    seen = (a > 0.05).numpy()
    assert seen.sum() > 20
    want = (ref.rgb / a.clamp_min(1e-6)[:, None]).clamp(0, 1).numpy()
    assert np.allclose(img[seen, 0, :3], want[seen], atol=1e-4)
    on = render_image(field, o[:, None], d[:, None], (0.2, 0.4, 0.6))[:, 0]
    want = (ref.rgb + (1 - a)[:, None] * torch.tensor([0.2, 0.4, 0.6])).clamp(0, 1)
    assert np.allclose(on, want.numpy(), atol=1e-5)
    assert (ref.depth[a > 0.5] > 0).all()


def test_samplers_cover_the_sphere_and_the_contracted_scene():
    field = _field("scene")
    o = torch.tensor([[0.0, 0.0, -3.0], [0.0, 5.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    t, valid, delta = object_samples(field, o, d, torch.zeros(2))
    assert float(t[0, valid[0]].min()) == 2.0 and float(t[0, valid[0]].max()) < 4.0
    assert not valid[1].any()                                  # misses the unit sphere
    assert torch.allclose(delta, torch.full_like(delta, field.step))
    t, valid, delta = scene_samples(field, o, d, torch.full((2,), 0.5))
    assert valid[1].sum() > 0 and float(t[1, valid[1]].max()) > 10     # far outside, contracted
    assert (delta[valid] > 0).all()
    out = render_rays(field, o * field.radius + field.center, d)   # scene mode: the PyTorch path
    assert out.rgb.shape == (2, 3) and ((out.alpha >= 0) & (out.alpha <= 1 + 1e-6)).all()
