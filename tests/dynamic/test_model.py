"""The model: a transition without viewpoint, the filtering and open loops, the decoded chain."""

from __future__ import annotations

from dataclasses import replace

import torch

from dbb_capture.dynamic.model import Rssm, gaussian, sample

from .conftest import SMALL, batch_of, scaled


def test_the_transition_has_no_room_for_a_viewpoint():
    m = Rssm(SMALL)
    assert m.z_in[0].in_features == SMALL.stoch and m.gru.input_size == SMALL.hidden
    assert m.prior[0].in_features == SMALL.deter
    assert m.post[0].in_features == SMALL.deter + SMALL.embed + 4 * SMALL.view_freqs     # the posterior reads the view


def test_filtering_and_open_loop_states():
    x, v = batch_of()
    m = Rssm(SMALL)
    emb, pe = m.encoder(x.flatten(0, 1)).view(2, 11, -1), m.encode_view(v)
    f = m.observe(emb, pe)
    assert len(f.h) == len(f.z) == len(f.post_mean) == len(f.prior_std) == 11
    assert torch.equal(f.h[0], torch.zeros(2, SMALL.deter))            # the first posterior reads frame 0 alone
    assert f.post_mean[3].requires_grad
    held = m.observe(emb.detach(), pe, train_posterior=False)
    assert not held.post_mean[3].requires_grad and held.h[3].requires_grad   # the transition still learns
    ol = m.imagine(f.h[1], f.z[1], 9)
    assert len(ol.h) == 9 and not ol.post_mean and ol.z[0].shape == (2, SMALL.stoch)
    # Sampled, not the mean: N(mean, (temperature std)^2); temperature 0 gives the mean.
    mean, std = gaussian(torch.zeros(4096, 2 * SMALL.stoch), 0.1)
    assert torch.allclose(std, torch.full_like(std, 0.1 + torch.log(torch.tensor(2.0)).item()))
    assert torch.equal(sample(mean, std, 0.0), mean)
    assert abs(sample(mean, std, 2.0).std().item() / (2 * std[0, 0].item()) - 1) < 0.02


def test_decode_chain_goes_on_from_the_warp_it_is_given():
    torch.manual_seed(0)
    m = Rssm(SMALL).eval()
    x, v = batch_of()
    pe, ctx = m.encode_view(v), m.encoder.context(x[:, 0])
    h, z = torch.randn(2, 4, 16), torch.randn(2, 4, 16)
    ident = m.decoder.grid.expand(2, -1, -1, -1)
    with torch.no_grad():
        frames, grid = m.decode_chain(h, z, pe[:, 1:5], pe[:, 0], ctx, x[:, 0], pe[:, 0], ident)
        first, g2 = m.decode_chain(h[:, :2], z[:, :2], pe[:, 1:3], pe[:, 0], ctx, x[:, 0], pe[:, 0], ident)
        rest, g4 = m.decode_chain(h[:, 2:], z[:, 2:], pe[:, 3:5], pe[:, 2], ctx, x[:, 0], pe[:, 0], g2)
    assert frames.shape == (2, 4, 4, 32, 32)
    assert torch.allclose(torch.cat([first, rest], 1), frames) and torch.allclose(g4, grid)


def test_keypoint_heads():
    assert Rssm(SMALL).kp_head is None
    assert Rssm(replace(scaled(keypoints=1.0), keypoints=4)).kp_head is not None
    m = Rssm(replace(scaled(keypoints=1.0), keypoints=4, keypoint_maps=True))
    assert m.kp_head is m.decoder.kp_net
    frozen = Rssm(replace(SMALL, keypoints=4, keypoints_frozen=True))
    assert not any(p.requires_grad for p in frozen.encoder.keypoints.parameters())
    assert not any(p.requires_grad for p in frozen.encoder.convs[0].parameters())   # the features it reads
    assert all(p.requires_grad for p in frozen.encoder.convs[1].parameters())
