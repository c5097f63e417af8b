"""The training losses: unscaled terms weighted by loss_scales, what is decoded, and each term."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from dbb_capture.dynamic.config import LOSS_SCALES
from dbb_capture.dynamic.losses import (
    OPEN_LOOP_FROM,
    energy_match,
    keypoint_error,
    keypoint_spread,
    latent_loss,
    loss_terms,
    motion_weights,
    sequence_loss,
    sharpness_match,
    state_keypoints,
    weighted,
    with_predicted_change,
)
from dbb_capture.dynamic.model import Rssm, States
from dbb_capture.dynamic.rgba import premultiply

from .conftest import SMALL, batch_of, scaled


def test_terms_are_unscaled_and_weighted_by_loss_scales():
    x, v = batch_of()
    torch.manual_seed(0)
    m = Rssm(SMALL)
    torch.manual_seed(1)
    terms, info = loss_terms(m, x, v)
    assert set(terms) == {"rec", "kl", "overshoot", "first_step"} and set(info) == {"kl_dyn", "kl_rep"}
    assert all(t.ndim == 0 and math.isfinite(t.item()) for t in terms.values())
    assert weighted(terms, LOSS_SCALES).item() == pytest.approx(sum(t.item() for t in terms.values()), rel=1e-6)
    doubled = weighted(terms, {**LOSS_SCALES, "first_step": 3.0, "rec": 0.5}).item()
    assert doubled == pytest.approx(sum(t.item() for t in terms.values()) + 2 * terms["first_step"].item()
                                    - 0.5 * terms["rec"].item(), rel=1e-6)
    torch.manual_seed(1)
    loss, parts = sequence_loss(m, x, v)
    assert set(parts) == {"loss", "rec", "first_step", "kl_dyn", "kl_rep", "overshoot"}
    assert parts["loss"] == pytest.approx(sum(t.item() for t in terms.values()), rel=1e-6)
    # A term whose scale is 0 is not computed; sharp, energy and keypoints are off by default.
    torch.manual_seed(1)
    assert set(loss_terms(Rssm(scaled(first_step=0.0)), x, v)[0]) == {"rec", "kl", "overshoot"}
    terms = loss_terms(Rssm(scaled(energy=1.0, sharp=2.0)), x, v)[0]
    assert set(terms) == {"rec", "kl", "overshoot", "sharp", "energy"}      # the first step is the open loop's
    loss.backward()
    assert m.prior[-1].weight.grad.abs().sum() > 0 and m.post[-1].weight.grad.abs().sum() > 0


def test_the_open_loop_is_decoded_only_when_a_term_scores_it(monkeypatch):
    """Frames follow one another: filtering frame 1, frames 2..10 from its warp, the prior's first
    step from the identity warp and (for energy or sharp) the open loop 2..10 from frame 1's warp."""
    x, v = batch_of(3)
    for cfg, shapes in ((SMALL, [(3, 1), (3, 9), (3, 1)]), (scaled(energy=1.0), [(3, 1), (3, 9), (3, 1), (3, 9)])):
        torch.manual_seed(9)
        m = Rssm(cfg)
        calls = []
        real = m.decode_chain

        def spy(h, z, pe, prev_pe, ctx, ctx_pm, ctx_pe, grid, *rest):
            calls.append((h.shape[0], h.shape[1], grid.clone()))
            return real(h, z, pe, prev_pe, ctx, ctx_pm, ctx_pe, grid, *rest)

        monkeypatch.setattr(m, "decode_chain", spy)
        loss, _ = sequence_loss(m, x, v)
        assert [(n, t) for n, t, _ in calls] == shapes
        ident = m.decoder.grid.expand(3, -1, -1, -1)
        assert torch.equal(calls[0][2], ident) and torch.equal(calls[2][2], ident)
        if len(calls) == 4:
            assert torch.equal(calls[3][2], calls[1][2])     # the open loop goes on from frame 1's warp
        loss.backward()
        assert m.decoder.ups[-1].weight.grad[:, 5:7].abs().sum() > 0       # the step flow learns
    assert OPEN_LOOP_FROM == 1


def test_the_first_step_decodes_frame_1_from_a_prior_sample(monkeypatch):
    x, v = batch_of()
    m = Rssm(SMALL)
    priors = []
    real_prior = m.prior_stats
    monkeypatch.setattr(m, "prior_stats", lambda h: priors.append(h) or real_prior(h))
    sequence_loss(m, x, v)
    # 11 filtering steps, 9 open-loop steps, then the prior at h_1 of the filtering pass.
    assert len(priors) == 11 + 9 + 1 and torch.equal(priors[20], priors[1])


def test_motion_weights_count_the_truths_and_the_predictions_change():
    w = motion_weights(torch.stack([torch.zeros(4, 8, 8), torch.zeros(4, 8, 8), torch.ones(4, 8, 8)])[None], 10.0)
    assert w.shape == (1, 3, 1, 8, 8)
    assert torch.equal(w[0, :2], torch.ones(2, 1, 8, 8)) and torch.equal(w[0, 2], torch.full((1, 8, 8), 11.0))
    x = torch.zeros(1, 3, 4, 8, 8)
    x[:, 2, :, 2:4, 2:4] = 1.0                               # the truth changes in one corner at frame 2
    w = motion_weights(x, 10.0)[:, 1:].flatten(0, 1)         # weights of frames 1 and 2
    pred = torch.zeros(2, 4, 8, 8)
    pred[:, :, 5:7, 5:7] = 1.0                               # the prediction changes elsewhere
    both = with_predicted_change(w, pred, x[:, :2].flatten(0, 1), 10.0)
    assert torch.all(both[:, :, 5:7, 5:7] == 11.0) and torch.all(both[1, :, 2:4, 2:4] == 11.0)
    assert both[:, :, 0, 0].eq(1.0).all() and torch.all(both >= w)
    assert with_predicted_change(None, pred, pred, 10.0) is None
    # The same model with and without the weights: changing pixels count more.
    x, v = batch_of()
    torch.manual_seed(0)
    m = Rssm(replace(SMALL, motion_weight=0.0))
    mw = Rssm(SMALL)
    mw.load_state_dict(m.state_dict())
    torch.manual_seed(1)
    plain = sequence_loss(m, x, v)[1]["rec"]
    torch.manual_seed(1)
    assert sequence_loss(mw, x, v)[1]["rec"] > 2 * plain


def test_energy_match_asks_the_open_loop_to_move_as_much_as_the_truth():
    torch.manual_seed(0)
    moving = torch.rand(3, 6, 4, 8, 8)
    still = moving[:, :1].expand(-1, 6, -1, -1, -1)
    assert energy_match(moving, moving).item() == pytest.approx(0.0, abs=1e-9)
    pred = (still + 0.01 * torch.randn_like(still)).requires_grad_()
    e = energy_match(pred, moving)
    assert e.item() > 1.0
    e.backward()                                              # descending the term moves the frames apart
    nxt = (pred - 0.01 * pred.grad / pred.grad.abs().max()).detach()
    d = lambda f: (f[:, 1:] - f[:, :-1]).abs().mean().item()
    assert d(nxt) > d(pred.detach())


def test_sharpness_match_costs_a_faded_part_not_a_moved_one():
    # A 4x4 ball on a flat wall: drawn 10 px away it is sharp (no cost here, though squared error
    # counts it twice); the mean of the places it may be (a fade) costs.
    wall = torch.full((1, 4, 32, 32), 0.5)

    def ball(x0):
        f = wall.clone()
        f[:, 0, 14:18, x0:x0 + 4] = 1.0
        return f

    truth = ball(4)
    assert sharpness_match(ball(14), truth).item() == pytest.approx(0.0, abs=1e-9)
    fade = torch.cat([ball(x0) for x0 in range(4, 24, 2)]).mean(0, keepdim=True)
    assert sharpness_match(fade, truth).item() > 0.5
    assert ((fade - truth) ** 2).sum() < ((ball(14) - truth) ** 2).sum()   # squared error prefers the fade
    pred = fade.clone().requires_grad_()
    sharpness_match(pred, truth).backward()                  # descending it sharpens a faded frame
    assert sharpness_match((pred - 0.05 * pred.grad).detach(), truth) < sharpness_match(fade, truth)
    x, v = batch_of()
    loss, parts = sequence_loss(Rssm(scaled(sharp=2.0)), x, v)
    assert parts["sharp"] > 0 and torch.isfinite(loss)
    loss.backward()


def test_keypoint_loss_makes_the_state_say_where_the_spot_is():
    """loss_scales.keypoints: the state (h, z) is trained to give its frame's keypoints, the posterior's at
    each filtering step and the prior samples' along the open loop; a frozen keypoint layer (and
    the conv it reads) takes no gradient, and a few steps on spot sequences bring that error down."""
    torch.manual_seed(0)
    cfg = replace(scaled(keypoints=10.0), keypoints=4, keypoints_frozen=True)
    m = Rssm(cfg)
    x = torch.full((4, 11, 4, 32, 32), 0.6)
    x[:, :, 3] = 1.0
    for b in range(4):                       # a spot that travels, from a different column per sequence
        for t in range(11):
            c = (3 * b + 2 * t) % 28
            x[b, t, :3, 14:18, c:c + 4] = torch.tensor([0.9, 0.1, 0.1])[:, None, None]
    x = premultiply(x)
    v = torch.zeros(4, 11, 3)
    loss, parts = sequence_loss(m, x, v)
    loss.backward()
    assert parts["keypoints"] > 0
    assert all(p.grad is None for p in m.encoder.keypoints.parameters())
    assert all(p.grad is None for p in m.encoder.convs[0].parameters())
    for part in (m.kp_head, m.post, m.prior, m.gru):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in part.parameters())
    opt = torch.optim.Adam([p for p in m.parameters() if p.requires_grad], 3e-3)
    for _ in range(100):
        opt.zero_grad()
        loss, parts = sequence_loss(m, x, v)
        loss.backward()
        opt.step()
    # Below what a state that knows nothing scores (the targets' variance, filtering + open loop).
    with torch.no_grad():
        kp = m.encoder(x.flatten(0, 1))[:, cfg.embed:]
    assert parts["keypoints"] < 0.5 * 2 * kp.var(0).sum().item()
    assert "kp_head" not in "".join(Rssm(replace(SMALL, keypoints=4)).state_dict())


def _states(n: int) -> States:
    return States([torch.randn(2, 16, requires_grad=True) for _ in range(n)],
                  [torch.randn(2, 16, requires_grad=True) for _ in range(n)])


def test_keypoint_error_reads_the_filtering_and_the_open_loop_states():
    cfg = replace(scaled(keypoints=1.0), keypoints=4)
    m = Rssm(cfg)
    f, ol = _states(11), _states(9)
    keypoint_error(m, torch.randn(2, 11, cfg.embed + 8), f, ol, 1).backward()
    assert all(t.grad is not None for t in f.h + f.z + ol.h + ol.z)


def test_keypoint_horizon_scores_the_open_loops_first_steps_alone():
    cfg = replace(scaled(keypoints=1.0), keypoints=4, keypoint_horizon=3)
    m = Rssm(cfg)
    f, ol = _states(11), _states(9)
    keypoint_error(m, torch.randn(2, 11, cfg.embed + 8), f, ol, 1).backward()
    assert all(t.grad is not None for t in ol.h[:3] + ol.z[:3])
    assert all(t.grad is None for t in ol.h[3:] + ol.z[3:])


def test_keypoint_spread_asks_the_open_loop_to_range_as_far_as_the_frames():
    cfg = replace(scaled(keypoints=1.0, keypoint_spread=1.0), keypoints=4)
    m = Rssm(cfg)
    torch.manual_seed(0)
    emb = torch.randn(2, 11, cfg.embed + 8)
    ol = _states(9)
    with torch.no_grad():
        reading = state_keypoints(m, ol)
    # Frames whose keypoints range as the open loop's reading does (whatever the order) score ~0,
    # frames that range ten times as far score (log 10)^2 per coordinate.
    same = emb.clone()
    same[:, 2:, cfg.embed:] = reading.flip(1) + 0.3
    assert keypoint_spread(m, same, ol, 1, eps=1e-6).item() == pytest.approx(0.0, abs=1e-6)
    far = same.clone()
    far[:, 2:, cfg.embed:] = reading * 10.0
    assert keypoint_spread(m, far, ol, 1, eps=1e-6).item() == pytest.approx(8 * math.log(10.0) ** 2, rel=1e-3)
    keypoint_spread(m, far, ol, 1).backward()
    assert all(t.grad is not None for t in ol.h + ol.z)


def test_keypoint_spread_is_a_term_of_both_losses_when_scaled():
    x, views = batch_of(seed=2)
    for spread in (0.0, 1.0):
        m = Rssm(replace(scaled(keypoints=1.0, keypoint_spread=spread), keypoints=4))
        assert ("keypoint_spread" in loss_terms(m, x, views)[0]) == (spread > 0)
        assert ("keypoint_spread" in latent_loss(m, x, views)[1]) == (spread > 0)


def test_keypoint_teacher_decodes_training_frames_from_their_own_keypoints():
    x, views = batch_of(seed=3)
    base = replace(scaled(keypoints=1.0, energy=1.0), keypoints=4, keypoint_maps=True)

    def parts(teacher: bool, shift: float) -> dict:
        torch.manual_seed(1)
        m = Rssm(replace(base, keypoint_teacher=teacher))
        with torch.no_grad():
            m.decoder.kp_net[-1].bias.add_(shift)     # the state's keypoints elsewhere
        torch.manual_seed(3)
        return sequence_loss(m, x, views)[1]

    for teacher in (False, True):
        a, b = parts(teacher, 0.0), parts(teacher, 0.5)
        assert b["keypoints"] != pytest.approx(a["keypoints"])             # the head is still trained
        moved = [k for k in ("rec", "energy") if b[k] != pytest.approx(a[k], rel=1e-6)]
        # Teacher: no pixel term reads the state's keypoints; without it every one does.
        assert moved == ([] if teacher else ["rec", "energy"])


def test_latent_loss_trains_the_transition_and_prior_alone():
    x, v = batch_of()
    m = Rssm(replace(scaled(keypoints=1.0), keypoints=4))
    loss, parts = latent_loss(m, x, v)
    loss.backward()
    assert set(parts) == {"kl_dyn", "overshoot", "keypoints"} and math.isfinite(loss.item())
    trained = {n.split(".")[0] for n, p in m.named_parameters() if p.grad is not None and p.grad.abs().sum() > 0}
    assert trained == {"z_in", "gru", "prior", "kp_head"}
