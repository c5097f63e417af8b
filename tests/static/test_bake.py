"""Baking a trained field into a PlenOctree, and weight pruning the tree."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dbb_capture.core.errors import DbbError
from dbb_capture.core.metrics import psnr_from_mse
from dbb_capture.geometry.cameras import Intrinsics
from dbb_capture.geometry.transforms import look_at
from dbb_capture.octree.render import TreeRenderer
from dbb_capture.octree.tree import PlenOctree, build_tree, leaf_cells
from dbb_capture.static.bake import (
    bake,
    default_depth,
    leaf_max_weights,
    prune_by_weight,
)
from dbb_capture.static.rays import frame_tensors
from dbb_capture.static.render import render_image


def test_bake_copies_the_field_into_a_trimmed_svox_tree(trained, tmp_path):
    _, vol, state, _ = trained
    tree = bake(state.field)
    assert default_depth(state.field) == tree.depth_limit == 4       # 32^3 lattice -> leaves at depth 4
    assert tree.data.shape[1:] == (2, 2, 2, 28) and tree.data_format == "SH9"
    np.testing.assert_allclose(tree.invradius, 0.5 / vol.radius, rtol=1e-6)
    np.testing.assert_allclose(tree.center, vol.center, atol=1e-5)
    assert tree.save(tmp_path / "tree.npz") > 0
    back = PlenOctree.load(tmp_path / "tree.npz")
    np.testing.assert_array_equal(back.data, tree.data)
    # Trimmed: no leaf with density outside the object sphere.
    cells, _ = leaf_cells(back)
    centres = (cells + 0.5) / 32 * 2 - 1
    assert len(cells) > 0 and (np.linalg.norm(centres, axis=1) <= 1 + 1e-6).all()
    assert bake(state.field, depth=5).depth_limit == 5
    with pytest.raises(DbbError):
        bake(state.field, depth=9)


def test_tree_renders_like_the_field(trained):
    frames, _, state, _ = trained
    r = TreeRenderer(bake(state.field))
    f = frames[5]
    o, d, _ = frame_tensors(f, 1)
    field_img = render_image(state.field, torch.from_numpy(o), torch.from_numpy(d), (1.0, 1.0, 1.0))
    assert psnr_from_mse(float(((field_img - r.render(f.c2w, f.intr, (1.0, 1.0, 1.0))) ** 2).mean())) > 28
    rgba = r.render(f.c2w, f.intr)
    assert rgba.shape == (24, 24, 4) and 0.05 < rgba[..., 3].mean() < 0.9


def _wall_tree() -> tuple[PlenOctree, dict[str, tuple[int, int, int]]]:
    """8^3 lattice over [-1, 1]^3 (leaf side 0.25): an opaque wall at z index 3 (x, y 2..5), a
    leaf behind it, a faint leaf in front of it (alpha 0.002) and a fainter-but-seen one
    (alpha 0.05); red SH1 colour everywhere."""
    side = 0.25
    wall = [(x, y, 3) for x in range(2, 6) for y in range(2, 6)]
    named = {"hidden": (4, 4, 5), "haze": (4, 4, 1), "faint": (3, 3, 1)}
    alphas = {"hidden": 0.9, "haze": 0.002, "faint": 0.05}
    cells = np.array(wall + list(named.values()))
    sig = [-math.log(1 - 0.99999) / side] * len(wall) + [-math.log(1 - alphas[k]) / side for k in named]
    vals = np.zeros((len(cells), 4), np.float32)
    vals[:, 0] = 2.0
    vals[:, 3] = sig
    data, child, pd = build_tree(cells, vals, 2)
    inv = np.full(3, 0.5, np.float32)
    return PlenOctree(data.astype(np.float16), child, pd, inv, np.full(3, 0.5, np.float32), 2, "SH1"), named


def test_weight_pruning_drops_hidden_and_faint_leaves_and_keeps_the_visible_ones():
    tree, named = _wall_tree()
    f = 16 / math.tan(math.radians(25))
    cams = [(look_at(np.array([dx, dy, -3.0]), np.zeros(3), np.array([0.0, -1.0, 0.0])),
             Intrinsics(32, 32, f, f, 15.5, 15.5)) for dx, dy in ((0.0, 0.0), (0.3, 0.0), (0.0, -0.3))]
    cells, _, w = leaf_max_weights(tree, cams, 1e-4)
    got = {tuple(c): float(x) for c, x in zip(cells, w)}
    assert got[named["hidden"]] == 0.0                        # behind an opaque wall: never reached
    assert got[named["haze"]] == pytest.approx(0.002, rel=0.05)  # a ray straight through its middle
    assert got[named["faint"]] == pytest.approx(0.05, rel=0.05)
    assert got[(2, 2, 3)] > 0.9
    pruned = prune_by_weight(tree, cams, 0.01)
    kept = {tuple(c) for c in leaf_cells(pruned)[0]}
    assert kept == {c for c in got if c not in (named["hidden"], named["haze"])}
    # What the cameras see barely changes: at most the dropped haze's 0.002 of a pixel.
    a, b = TreeRenderer(tree), TreeRenderer(pruned)
    for c2w, intr in cams:
        assert np.abs(a.render(c2w, intr)[..., 3] - b.render(c2w, intr)[..., 3]).max() < 0.003
    assert prune_by_weight(tree, cams, 0.0) is tree


def test_bake_with_training_cameras_prunes_without_changing_the_views(trained):
    frames, _, state, _ = trained
    tree = bake(state.field)
    pruned = bake(state.field, cameras=[(f.c2w, f.intr) for f in frames], prune_weight=0.02)
    assert pruned.n_leaves_with_data() < tree.n_leaves_with_data()
    a, b = TreeRenderer(tree), TreeRenderer(pruned)
    for f in frames[:4]:
        diff = a.render(f.c2w, f.intr, (1.0, 1.0, 1.0)) - b.render(f.c2w, f.intr, (1.0, 1.0, 1.0))
        assert psnr_from_mse(float((diff ** 2).mean())) > 30
