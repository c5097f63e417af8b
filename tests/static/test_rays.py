"""Training rays: the bank, observed pixels over the predicted room, robust weights, carving."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
from conftest import synthetic_object_frames

from dbb_capture.static.rays import (
    build_ray_bank,
    carve_mask,
    ray_targets,
    robust_weights,
)

from .synthetic import BOARD, TINY, crops_with_room


def test_bank_keeps_the_rays_that_see_the_sphere_and_the_observed_pixels(tmp_path):
    ds, vol, _ = crops_with_room(tmp_path)
    assert all(f.observed_path is not None and f.background_path is not None for f in ds.frames)
    train = ds.split("train")
    bank = build_ray_bank(train, 1, vol)
    assert 0 < bank.n < len(train) * 24 * 24                    # rays past the sphere dropped
    assert bank.observed is not None and bank.observed.shape == bank.room.shape == (bank.n, 3)
    assert torch.allclose(bank.dirs.norm(dim=-1), torch.ones(bank.n), atol=1e-5)
    assert bank.views is not None and len(bank.views.alphas) == len(train)
    plain = build_ray_bank(train, 1, vol, observed=False)
    assert plain.observed is None and plain.n == bank.n
    scene = build_ray_bank(train, 1, vol, mode="scene")
    assert scene.n == len(train) * 24 * 24 and scene.views is None and scene.observed is None
    bank.record_errors(torch.arange(4), torch.zeros(4, 3), torch.zeros(4), torch.zeros(4, 3))
    assert not bank.error[:4].isnan().any() and bank.error[4:].isnan().all()


def test_targets_pick_the_observed_pixel_where_colour_decides():
    """Rays where the matte says "room" pick their target: the observed pixel over the room where
    colour decides, the matte (over a random colour) where it cannot, with probability
    matte_prior; NaN or a matte that sees any object (alpha >= matte_opaque): the matte."""
    rgba = torch.tensor([[0.9, 0.1, 0.1, 0.0]] * 3 + [[0.9, 0.1, 0.1, 0.6]])
    bg = torch.full((4, 3), 0.5)
    seen = torch.tensor([[0.9, 0.1, 0.1], [0.3, 0.3, 0.3], [float("nan")] * 3, [0.9, 0.1, 0.1]])
    room = torch.tensor([[0.2, 0.2, 0.2], [0.3, 0.3, 0.3], [0.2, 0.2, 0.2], [0.2, 0.2, 0.2]])
    matte = rgba[:, :3] * rgba[:, 3:] + (1 - rgba[:, 3:]) * bg
    gen = torch.Generator().manual_seed(0)
    picks = [ray_targets(rgba, bg, seen, room, replace(TINY, observed_loss=True, matte_prior=1.0), gen)
             for _ in range(20)]
    assert all(torch.equal(b[0], room[0]) and torch.equal(t[0], seen[0]) for b, t in picks)   # colour decides
    assert all(torch.equal(t[1], matte[1]) for _, t in picks)           # no colour difference, prior 1: matte
    assert all(torch.equal(b[2:], bg[2:]) and torch.equal(t[2:], matte[2:]) for b, t in picks)
    b, t = ray_targets(rgba, bg, seen, room, TINY, gen)
    assert torch.equal(b, bg) and torch.equal(t, matte)


def test_robust_weights_fall_with_the_running_error():
    """The IRLS weights: 1 for unseen rays, falling with the ray's running error."""
    w = robust_weights(torch.tensor([float("nan"), 0.0, 0.01, 1.0]), 0.1)
    assert torch.allclose(w, torch.tensor([1.0, 1.0, 0.5, 1 / 101]))


def test_carving_keeps_the_object_and_clears_what_the_views_see_through(tmp_path):
    """Space carving from the views' alpha: no lattice point inside the true object is carved
    (the footprint and a pixel of slack keep the outline), most of the sphere around it is;
    a point that fewer than ``min_views`` views (or less than ``share`` of those that see it)
    see as empty stays."""
    from dbb_capture.synth.objects import make_object

    frames, vol = synthetic_object_frames(tmp_path, n=24, size=32)
    bank = build_ray_bank([f for f in frames if f.split == "train"], 1, vol)
    assert bank.views is not None and len(bank.views.alphas) == 21
    res = 32
    ax = (np.arange(res) + 0.5) / res * 2 - 1
    x = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    pts = x * vol.radius + np.asarray(vol.center)
    cell = 2 * vol.radius / res
    model = make_object("static", BOARD, np.random.default_rng(0))
    inside = np.zeros(len(pts), bool)
    for c, R, e in model.posed(0.0):
        inside |= np.linalg.norm((pts - c) @ R / np.asarray(e.radii), axis=1) <= 1
    in_sphere = np.linalg.norm(pts - np.asarray(vol.center), axis=1) < vol.radius
    cut = carve_mask(bank.views, pts, cell, 0.2)
    assert inside.sum() > 100 and not cut[inside].any()
    assert cut[in_sphere & ~inside].mean() > 0.5
    assert not carve_mask(bank.views, pts, cell, 0.2, min_views=len(bank.views.alphas) + 1).any()
    assert carve_mask(bank.views, pts, cell, 0.2).sum() >= carve_mask(bank.views, pts, cell, 0.9).sum()
