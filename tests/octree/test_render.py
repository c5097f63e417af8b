"""The tree renderers: exact alpha, the numba walk against the torch sampler, caches and threads."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dbb_capture.core.errors import DbbError
from dbb_capture.core.metrics import psnr_from_mse
from dbb_capture.geometry.cameras import scaled_intrinsics
from dbb_capture.octree.render import NumbaTreeRenderer, TorchTreeRenderer, TreeRenderer
from dbb_capture.octree.tree import PlenOctree, build_tree

from .trees import random_tree


def test_renderer_alpha_of_one_opaque_cube_is_exact():
    """A single leaf cell of density sigma: a ray straight through sees 1 - exp(-sigma * side)."""
    depth = 2                                               # 8^3 lattice over [-1, 1]^3: side 0.25
    sigma = 3.0
    data, child, pd = build_tree(np.array([[4, 4, 4]]), np.array([[2.0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, sigma]],
                                                                   np.float32), depth)
    inv = np.full(3, 0.5, np.float32)                       # radius 1, centre 0
    tree = PlenOctree(data.astype(np.float16), child, pd, inv, (0.5 - 0 * inv).astype(np.float32), depth, "SH4")
    o = torch.tensor([[0.1, 0.1, -3.0], [0.6, 0.6, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    for backend in ("numba", "torch"):
        rgb, a = TreeRenderer(tree, backend=backend).render_rays(o, d)
        assert a[0].item() == pytest.approx(1 - math.exp(-sigma * 0.25), abs=0.02), backend
        assert a[1].item() == 0.0
        # Colour: sigmoid(C0 * 2) for the red channel, sigmoid(0) for green and blue.
        want = torch.sigmoid(torch.tensor([0.28209479 * 2, 0.0, 0.0])) * a[0]
        assert torch.allclose(rgb[0], want, atol=1e-3), backend


def test_backend_follows_the_device_and_bad_choices_are_refused():
    tree = random_tree()
    r = TreeRenderer(tree)
    assert r.backend == "numba" and isinstance(r.impl, NumbaTreeRenderer)
    t = TreeRenderer(tree, backend="torch")
    assert t.backend == "torch" and isinstance(t.impl, TorchTreeRenderer)
    with pytest.raises(DbbError):
        TreeRenderer(tree, backend="vulkan")
    with pytest.raises(DbbError):
        TreeRenderer(tree, device="meta", backend="numba")
    odd = PlenOctree(tree.data, tree.child, tree.parent_depth, tree.invradius, tree.offset, tree.depth_limit,
                     tree.data_format, "tanh")
    with pytest.raises(DbbError):
        TreeRenderer(odd)


def test_numba_walk_matches_a_dense_torch_reference():
    """The exact cell walk (numba) against the torch sampler at 1/16 leaf steps, for rays from
    outside and inside the tree, axis-parallel ones included, and shallow leaves."""
    tree = random_tree()
    fast = TreeRenderer(tree)
    ref = TreeRenderer(tree, backend="torch", step=1 / 16, chunk_samples=256)
    g = torch.Generator().manual_seed(1)
    far = torch.randn(3000, 3, generator=g)
    far = 6 * far / far.norm(dim=-1, keepdim=True)
    inner = torch.rand(1000, 3, generator=g) * 2 - 1
    o = torch.cat([far, inner, torch.tensor([[0.3, -0.2, -5.0], [-5.0, 0.1, 0.2]])])
    target = torch.randn(o.shape[0], 3, generator=g) * 0.6
    d = torch.cat([target[:-2] - o[:-2], torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])])
    d = d / d.norm(dim=-1, keepdim=True)
    rgb_f, a_f = fast.render_rays(o, d)
    rgb_r, a_r = ref.render_rays(o, d)
    assert float(a_f.mean()) > 0.2 and float(a_f[-2:].min()) > 0.5
    mse = float(torch.cat([rgb_f - rgb_r, (a_f - a_r)[:, None]], 1).pow(2).mean())
    assert psnr_from_mse(mse) > 40


def test_camera_renders_of_both_backends_agree(shell):
    """Straight RGBA frames: the numba walk (leaf colours toward each leaf's centre, skipped
    weight shared out) against the torch sampler at 1/8 leaf steps; composited frames too."""
    tree, c2w, intr = shell
    fast = TreeRenderer(tree).render(c2w, intr)
    ref = TreeRenderer(tree, backend="torch", step=1 / 8).render(c2w, intr)
    assert fast.shape == ref.shape == (24, 24, 4) and 0.1 < float(fast[..., 3].mean()) < 0.9
    assert psnr_from_mse(float(((fast[..., :3] * fast[..., 3:] - ref[..., :3] * ref[..., 3:]) ** 2).mean())) > 40
    assert psnr_from_mse(float(((fast[..., 3] - ref[..., 3]) ** 2).mean())) > 40
    for backend in ("numba", "torch"):
        r = TreeRenderer(tree, backend=backend)
        rgba, white = r.render(c2w, intr), r.render(c2w, intr, (1.0, 1.0, 1.0))
        np.testing.assert_allclose(white, rgba[..., :3] * rgba[..., 3:] + 1 - rgba[..., 3:], atol=2e-3)


def test_colour_cache_does_not_leak_between_frames(shell):
    """Leaf colours are cached per frame: a frame after another camera's equals a fresh one."""
    tree, c2w, intr = shell
    other = c2w.copy()
    other[:3, 3] *= 1.3
    r = TreeRenderer(tree)
    r.render(other, intr)
    again = r.render(c2w, intr)
    fresh = TreeRenderer(tree).render(c2w, intr)
    np.testing.assert_array_equal(again, fresh)


def test_threads_and_prefetch_mode_do_not_change_pixels(shell, monkeypatch):
    """Threads share one colour cache and the eager prefetch only reorders memory traffic:
    a frame is the same bit for bit with one thread or several, eager or not."""
    import dbb_capture.octree.render as octree_render

    tree, c2w, intr = shell
    big = scaled_intrinsics(intr, 24 / 160)                  # 160x160: several work items
    monkeypatch.setattr(octree_render, "_EAGER_PIXELS", 0.0)
    one = TreeRenderer(tree, threads=1).render(c2w, big)
    monkeypatch.setattr(octree_render, "_EAGER_PIXELS", 1e9)
    many = TreeRenderer(tree, threads=3).render(c2w, big)
    assert one.shape == (160, 160, 4) and float(one[..., 3].mean()) > 0.05
    np.testing.assert_array_equal(one, many)


_FORKED: dict = {}


def _render_in_child(c2w, intr):
    return _FORKED["renderer"].render(c2w, intr)


def test_renderer_works_in_a_forked_child_after_the_parent_rendered(shell):
    """The render threads do not survive fork; a child must not wait on its parent's pool."""
    import multiprocessing as mp

    tree, c2w, intr = shell
    big = scaled_intrinsics(intr, 0.25)                       # 96x96: more rays than one work item
    r = _FORKED["renderer"] = TreeRenderer(tree, threads=2)
    want = r.render(c2w, big)
    with mp.get_context("fork").Pool(1) as pool:
        got = pool.apply_async(_render_in_child, (c2w, big)).get(timeout=60)
    np.testing.assert_array_equal(got, want)


def test_max_weights_record_each_leafs_largest_weight(shell):
    """With weights recorded nothing is coloured: each leaf's largest weight over the camera's
    rays, in the order of the renderer's cells; the nearest side of the shell reaches 0.95 and
    more (rays cross its leaves obliquely)."""
    tree, c2w, intr = shell
    r = NumbaTreeRenderer(tree, t_min=1e-4, w_min=1e-4)
    w = r.max_weights(c2w, scaled_intrinsics(intr, 0.25))
    assert w.shape == (len(r.cells),) == (len(r.rows),) and w.dtype == np.float32
    assert 0.9 < float(w.max()) <= 1.0
    assert (w == 0).mean() > 0.3                              # the far side and the inside are hidden
