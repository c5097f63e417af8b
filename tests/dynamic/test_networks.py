"""The encoder's keypoints, the accumulated warp, the decoder's start, PhaseUp and the oscillator cell."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
from torch.nn import functional as F

from dbb_capture.core.metrics import psnr
from dbb_capture.dynamic.model import Rssm
from dbb_capture.dynamic.networks import (
    OscCell,
    PhaseUp,
    SpatialSoftmax,
    accumulated_warp,
    fast_decoder,
    identity_grid,
    keypoint_maps,
)
from dbb_capture.dynamic.rgba import premultiply

from .conftest import SMALL, scaled


def test_accumulated_warp_moves_parts_far_and_resamples_the_image_once():
    S = 32
    base = identity_grid(1, S)
    assert torch.allclose(accumulated_warp(base, torch.zeros(1, 2, S, S), base), base, atol=1e-6)
    # A bright square moved right by four steps of half a pixel: the composed coordinates
    # resample the context frame once, 2 px over; four resamplings of the image smear it.
    img = torch.zeros(1, 4, S, S)
    img[:, :, 12:18, 8:14] = 1.0
    half = torch.zeros(1, 2, S, S)
    half[:, 0] = -0.5 * 2.0 / S                         # backward flow: from half a pixel to the left
    grid, resampled = base, img
    for _ in range(4):
        grid = accumulated_warp(grid, half, base)
        resampled = F.grid_sample(resampled, base + half.permute(0, 2, 3, 1), align_corners=False)
    shifted = torch.roll(img, 2, -1)
    assert torch.allclose(F.grid_sample(img, grid, align_corners=False), shifted, atol=1e-4)
    assert (resampled - shifted).abs().max() > 0.2
    # Far travel: 40 steps of 1 px take the square 40 px from where a single flow could reach.
    one = torch.zeros(1, 2, 64, 64)
    one[:, 0] = -2.0 / 64
    b64, big = identity_grid(1, 64), torch.zeros(1, 4, 64, 64)
    big[:, :, 30:34, 2:6] = 1.0
    g = b64
    for _ in range(40):
        g = accumulated_warp(g, one, b64)
    out = F.grid_sample(big, g, align_corners=False)
    assert torch.allclose(out[:, :, 30:34, 42:46], torch.ones(1, 4, 4, 4), atol=1e-4) and out[..., :40].abs().max() < 1e-4
    # A leak shrinks the displacement toward the context layout each step; still parts stay put.
    held = accumulated_warp(g, torch.zeros(1, 2, 64, 64), b64, leak=0.25)
    assert torch.allclose(held - b64, 0.75 * (g - b64), atol=1e-5)
    assert torch.equal(accumulated_warp(b64, torch.zeros(1, 2, 64, 64), b64, leak=0.25), b64)


def test_decoder_starts_as_the_context_frame_and_steps_from_its_own_warp():
    torch.manual_seed(6)
    m = Rssm(SMALL).eval()
    dec = m.decoder
    ctx_pm = premultiply(torch.rand(2, 4, 32, 32))
    ctx = m.encoder.context(ctx_pm)
    feat = torch.randn(2, dec.fc[0].in_features)
    ident = dec.grid.expand(2, -1, -1, -1)
    with torch.no_grad():
        frame, grid = dec(feat, ctx, ctx_pm, ident)
        # Untrained: zero flow (the warp stays the identity, up to the leak of nothing) and ~95 % the context frame.
        assert torch.allclose(grid, ident, atol=1e-6) and psnr(frame.numpy(), ctx_pm.numpy()) > 25
        dec.ups[-1].bias[4] = 100.0                        # warp share 1: the context frame exactly
        assert torch.allclose(dec(feat, ctx, ctx_pm, ident)[0], ctx_pm, atol=1e-4)
        # A constant step flow: each step moves the warp on by it (composed, then shrunk by the leak).
        dec.ups[-1].bias[5] = 0.5                          # tanh(0.5) * 0.25 half-widths = 1.85 px per step
        g = ident
        for _ in range(3):
            g = dec(feat, ctx, ctx_pm, g)[1]
        step, keep = math.tanh(0.5) * 0.25, 1.0 - SMALL.warp_leak
        inside = slice(0, 20)                              # columns whose source is still in the frame
        expected = identity_grid(1, 32)[..., inside, 0] + step * (keep + keep ** 2 + keep ** 3)
        assert torch.allclose(g[..., inside, 0], expected, atol=1e-4)


def test_stepper_upsamples_with_phase_convolutions_exactly():
    torch.manual_seed(0)
    for c_in, c_out in ((12, 5), (40, 8)):          # below and above the channels-last width
        up = torch.nn.ConvTranspose2d(c_in, c_out, 4, 2, 1)
        x = torch.randn(2, c_in, 7, 9)
        with torch.no_grad():
            assert torch.allclose(PhaseUp(up)(x), up(x), atol=1e-5)
    with pytest.raises(ValueError):
        PhaseUp(torch.nn.ConvTranspose2d(4, 4, 3, 2, 1))
    m = Rssm(SMALL).eval()
    fast = fast_decoder(m.decoder)
    assert all(isinstance(u, PhaseUp) for u in fast.ups)
    assert all(isinstance(u, torch.nn.ConvTranspose2d) for u in m.decoder.ups)     # training untouched
    pm = torch.rand(3, 4, 32, 32)
    feat = torch.randn(3, m.decoder.fc[0].in_features)
    ident = m.decoder.grid.expand(3, -1, -1, -1)
    with torch.no_grad():
        ctx = m.encoder.context(pm)
        assert torch.allclose(fast(feat, ctx, pm, ident)[0], m.decoder(feat, ctx, pm, ident)[0], atol=1e-5)


def test_keypoints_follow_a_small_part_the_flattened_embedding_hardly_sees():
    """A 2x2-px spot on a plain 32x32 frame: the keypoints move with it by a large fraction of the
    frame, the flattened conv embedding by orders of magnitude less."""
    torch.manual_seed(0)
    cfg = replace(SMALL, keypoints=8)
    m = Rssm(cfg).eval()
    frames = torch.full((6, 4, 32, 32), 0.6)
    frames[:, 3] = 1.0
    for i in range(6):                       # the spot travels left to right along a row
        frames[i, :3, 15:17, 3 + 5 * i:5 + 5 * i] = torch.tensor([0.9, 0.1, 0.1])[:, None, None]
    with torch.no_grad():
        e = m.encoder(frames)
    assert e.shape == (6, cfg.embed + 2 * cfg.keypoints)
    emb_spread = e[:, :cfg.embed].std(0).mean()
    kp_spread = e[:, cfg.embed:].std(0).mean()
    assert kp_spread > 0.05 and kp_spread > 100 * emb_spread
    # A keypoint that picks the spot's channel lands on it: x grows with the spot's column.
    sm = SpatialSoftmax(1, 1, 16)
    with torch.no_grad():
        sm.conv.weight.fill_(1.0)
        sm.conv.bias.zero_()
        sm.log_beta.fill_(math.log(50.0))
        f = torch.zeros(1, 1, 16, 16)
        f[0, 0, 4, 12] = 1.0
        kx, ky = sm(f)[0]
    assert abs(kx.item() - (12.5 / 8 - 1)) < 1e-3 and abs(ky.item() - (4.5 / 8 - 1)) < 1e-3
    assert not any("keypoints" in k for k in Rssm(SMALL).state_dict())


def test_keypoint_maps_peak_at_the_keypoint_at_every_scale():
    kp = torch.tensor([[-0.45, 0.3, 0.7, -0.1]])                 # K = 2: x = (-0.45, 0.3), y = (0.7, -0.1)
    for r in (4, 8, 32):
        maps = keypoint_maps(kp, r, 0.08)
        assert maps.shape == (1, 2, r, r) and float(maps.max()) <= 1.0
        for k, (x, y) in enumerate([(-0.45, 0.7), (0.3, -0.1)]):
            row, col = divmod(int(maps[0, k].argmax()), r)
            assert (row, col) == (int((y + 1) / 2 * r), int((x + 1) / 2 * r))
    # At least half a cell wide: a point between coarse pixel centres still reaches them.
    assert float(keypoint_maps(torch.tensor([[0.0, 0.0]]), 4, 0.01).max()) > 0.3     # exp(-1): not ~0


def test_keypoint_maps_decoder_draws_from_the_states_keypoints():
    m = Rssm(replace(scaled(keypoints=1.0), keypoints=4, keypoint_maps=True)).eval()
    assert m.kp_head is m.decoder.kp_net          # one head: trained on the keypoints, drawn where it says
    torch.manual_seed(0)
    ctx_pm = premultiply(torch.rand(1, 4, 32, 32))
    ctx = m.encoder.context(ctx_pm)
    assert [c.shape[1] for c in ctx] == [c.shape[1] + 4 for c in m.encoder.features(ctx_pm)]
    feat = torch.randn(1, m.decoder.fc[0].in_features)
    ident = m.decoder.grid.expand(1, -1, -1, -1)
    with torch.no_grad():
        m.decoder.ups[-1].weight[:, 5:7] = 0.01 * torch.randn_like(m.decoder.ups[-1].weight[:, 5:7])
    out = m.decoder(feat, ctx, ctx_pm, ident)[0]
    out.square().sum().backward()                 # the pixels pull on the keypoints' head
    assert float(m.decoder.kp_net[-1].weight.grad.abs().sum()) > 0
    with torch.no_grad():
        m.decoder.kp_net[-1].bias.add_(0.5)       # the state's keypoints elsewhere: another frame
        assert not torch.allclose(m.decoder(feat, ctx, ctx_pm, ident)[0], out, atol=1e-5)


def test_oscillator_modes_ring_after_the_input_stops():
    cell = OscCell(64, 16, 4)
    # One kick, then no input: the modes keep turning (a GRU's state settles to a fixed point).
    with torch.no_grad():
        h = cell(torch.randn(1, 64), torch.zeros(1, 24))
        modes = []
        for _ in range(60):
            h = cell(torch.zeros(1, 64), h)
            modes.append(h[0, 16:].clone())
        modes = torch.stack(modes)
    keep = cell.kept().detach()
    amp = torch.sqrt(modes[:, :4] ** 2 + modes[:, 4:] ** 2)
    assert torch.allclose(amp[-1], amp[0] * keep ** 59, rtol=1e-4)            # damped only by keep
    assert (modes[1:] - modes[:-1]).abs().sum(1).min() > 1e-3 * modes.abs().sum(1).max()   # still turning
    # A floor on the kept length holds whatever the trained rate says.
    floored = OscCell(64, 16, 4, keep_min=0.999)
    with torch.no_grad():
        floored.nu.fill_(5.0)                                  # exp(-exp(5)): nothing kept
        h = floored(torch.zeros(1, 64), torch.cat([torch.zeros(1, 16), torch.ones(1, 8)], 1))
    assert torch.allclose(torch.sqrt(h[0, 16:20] ** 2 + h[0, 20:] ** 2), torch.full((4,), 0.999 * 2 ** 0.5))
    assert isinstance(Rssm(replace(SMALL, deter=24, osc=4)).gru, OscCell)


def test_the_oscillator_bound_holds_past_the_range_and_changes_nothing_within_it():
    torch.manual_seed(0)
    cell = OscCell(8, 6, 3, keep_min=0.999).eval()
    with torch.no_grad():
        cell.drive.weight.mul_(50.0)
    # A loop with gain above 1 (the modes drive themselves, as prior -> z -> drive can): unbounded it grows.
    feed = torch.randn(8, 6) * 4.0
    def ring(c, steps=200):
        h = torch.zeros(1, 12)
        h[:, 6] = 0.1
        with torch.no_grad():
            for _ in range(steps):
                h = c(torch.tanh(h[:, 6:]) @ feed.T + h[:, 6:] @ feed.T, h)
        return h
    wild = cell.amplitude(ring(cell))
    assert not bool(torch.isfinite(wild).all()) or float(wild.max()) > 1e6
    cell.amp_limit.fill_(2.0)
    amp = cell.amplitude(ring(cell))
    assert bool(torch.isfinite(amp).all()) and float(amp.max()) <= 3.0 + 1e-5 and float(amp.max()) > 2.0
    # Below the limit the cell is the unbounded one, exactly; training mode never bounds.
    x, h = 0.01 * torch.randn(4, 8), torch.cat([torch.randn(4, 6), 0.5 * torch.randn(4, 6).clamp(-1, 1)], 1)
    free = OscCell(8, 6, 3, keep_min=0.999).eval()
    free.load_state_dict(cell.state_dict())
    assert "amp_limit" not in cell.state_dict()                   # a run-time fit, not a weight
    with torch.no_grad():
        assert float(cell.amplitude(free(x, h)).max()) < 2.0       # stays within the limit
        assert free.amp_limit.eq(0).all() and torch.equal(cell(x, h), free(x, h))
        big = h.clone()
        big[:, 6:] *= 40.0
        assert not torch.equal(cell(x, big), free(x, big))
        assert torch.equal(cell.train()(x, big), free(x, big))
