"""The RSSM's training losses: terms returned unscaled, weighted by ``RssmConfig.loss_scales``.

- *A prior that never learns slow motion*: the run-time rollout uses the prior only, so the prior
  is trained the way it runs: every batch also rolls the prior open loop from the filtering state of
  frame 1 (sampled states), with latent overshooting (KL from the stopped-gradient filtering posterior
  to the open-loop prior) and the run-time first step's frame scored on its own.
- *Free nats and KL balancing done right*: the dynamics term KL(sg(q) || p), which trains the prior,
  is never clamped (a clamp removes its gradient exactly when the per-step KL is small, i.e. for slow
  motion); free nats apply to the batch-mean representation term KL(q || sg(p)) only, as
  max(KL, free nats). Balance 0.8 / 0.2 (Dreamer).
- Pixel losses are squared errors on premultiplied RGBA (Gaussian, unit variance), summed over
  pixels, averaged over frames, each pixel weighted up where the truth or the prediction changes.
"""

from __future__ import annotations

import torch

from ..core.errors import DbbError
from .config import LOSS_SCALES
from .model import Rssm, States, sample
from .networks import image_pyramid

# The training open loop starts from the filtering state of frame 1, after the posterior has seen
# frames 0 and 1. From frame 0 (the run-time start exactly) one frame cannot tell which way a swing
# goes, so a sampled rollout scored against one direction is least wrong as a still, averaged frame:
# the model learned to stop (docs/decisions.md, open_loop_from). From frame 1 the direction is in z_1;
# the run time samples z_1 from the prior, which the dynamics KL trains to cover those posteriors.
OPEN_LOOP_FROM = 1


# --------------------------------------------------------------------------- terms
def kl_divergence(m1: torch.Tensor, s1: torch.Tensor, m2: torch.Tensor, s2: torch.Tensor) -> torch.Tensor:
    """KL(N(m1, s1) || N(m2, s2)) summed over the last axis (nats)."""
    return (torch.log(s2 / s1) + (s1 ** 2 + (m1 - m2) ** 2) / (2 * s2 ** 2) - 0.5).sum(-1)


def reconstruction(pred_pm: torch.Tensor, target_pm: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Squared error (N, 4, S, S) of premultiplied frames, each pixel's times ``weight`` (N, 1, S, S),
    summed over pixels, mean over frames."""
    err = (pred_pm - target_pm) ** 2
    return (err if weight is None else err * weight).flatten(1).sum(1).mean()


def motion_weights(x: torch.Tensor, scale: float) -> torch.Tensor:
    """Per-pixel loss weights (B, T, 1, S, S) of premultiplied frames ``x`` (B, T, 4, S, S), T >= 2.

    1 + ``scale`` * (largest channel change from the previous frame; frame 0 uses frame 1's): the
    moving parts of a toy are a small fraction of the crop, and a plain per-pixel error is
    minimised well enough by a still frame.
    """
    d = (x[:, 1:] - x[:, :-1]).abs().amax(2, keepdim=True)
    return 1.0 + scale * torch.cat([d[:, :1], d], 1)


def with_predicted_change(w: torch.Tensor | None, pred: torch.Tensor, prev: torch.Tensor,
                          scale: float) -> torch.Tensor | None:
    """The loss weights ``w`` (N, 1, S, S) of predicted frames ``pred`` (N, 4, S, S), raised to
    1 + ``scale`` * the prediction's largest channel change from the true previous frame ``prev``
    (N, 4, S, S) where that is more (no gradient through the weight).

    Weights from the truth's change alone pull a prediction toward change: a part drawn moving
    where the truth stays would cost no more than elsewhere, one left still where the truth moves
    up to 1 + scale times as much.
    """
    if w is None:
        return w
    return torch.maximum(w, 1.0 + scale * (pred.detach() - prev).abs().amax(1, keepdim=True))


def energy_match(pred: torch.Tensor, truth: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    """Squared log ratio of motion energies (mean |frame change|) of each sequence, mean over the batch.

    ``pred``, ``truth``: premultiplied (B, T, 4, S, S), T >= 2 consecutive frames. A sampled
    open loop scored by squared error alone is free to move more or less than the truth (the
    error of a wrong motion is about that of none); this term asks it to move as much.
    """
    e_p = (pred[:, 1:] - pred[:, :-1]).abs().flatten(1).mean(1)
    e_t = (truth[:, 1:] - truth[:, :-1]).abs().flatten(1).mean(1)
    return ((torch.log(e_p + eps) - torch.log(e_t + eps)) ** 2).mean()


def sharpness_match(pred: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Squared distance between the distributions of the pixel-to-pixel differences (horizontal and
    vertical, per channel) of each frame, summed over them, mean over frames: ``pred``, ``truth``
    (N, C, S, S), each frame's differences sorted and compared rank by rank (the 1-D Wasserstein-2
    distance, times their count).

    Blind to where things are: an edge drawn in the wrong place costs nothing here, an edge left
    out, faded or smeared does. Squared error alone is least for the mean of the places a part may
    be, so a small moving part whose place is uncertain (a pendulum's ball, a toy's arm) is drawn
    faded or smeared; with this term beside it a sharp part in one place may cost less. (On the
    pendulum footage a frame with the ball 5-6 frames away scores 0.03-0.12 here, the mean of 13
    frames 0.25-0.45; a global value histogram told them apart less well, exposure flicker moves it.)
    """
    def diffs(x: torch.Tensor) -> torch.Tensor:
        dv, dh = x[..., 1:, :] - x[..., :-1, :], x[..., :, 1:] - x[..., :, :-1]
        return torch.cat([dv.flatten(2), dh.flatten(2)], 2)

    return ((diffs(pred).sort(-1).values - diffs(truth).sort(-1).values) ** 2).flatten(1).sum(1).mean()


def state_keypoints(model: Rssm, states: States) -> torch.Tensor:
    """``kp_head``'s reading (B, T, 2K) of a pass's states (T of (B, .)), in [-1, 1] frame units."""
    return model.kp_head(torch.cat([torch.stack(states.h, 1), torch.stack(states.z, 1)], -1))


def keypoint_error(model: Rssm, emb: torch.Tensor, filtering: States, open_loop: States, k: int) -> torch.Tensor:
    """The frames' keypoints (``emb`` (B, T+1, embed + 2K), detached) against ``kp_head``'s reading of
    the filtering states (T+1 of (B, .)) and of the open loop's from frame ``k`` (T - k of (B, .); its
    first ``cfg.keypoint_horizon`` steps), squared distances summed over keypoints, mean over frames: a
    target the warp's vanishing gradient cannot hide, so the state carries where a small part is."""
    kp = emb[:, :, model.cfg.embed:].detach()
    err = ((state_keypoints(model, filtering) - kp) ** 2).sum(-1).mean()
    if not open_loop.h:
        return err
    n = model.cfg.keypoint_horizon or len(open_loop.h)
    ko = state_keypoints(model, States(h=open_loop.h[:n], z=open_loop.z[:n]))
    return err + ((ko - kp[:, k + 1:k + 1 + n]) ** 2).sum(-1).mean()


def keypoint_spread(model: Rssm, emb: torch.Tensor, open_loop: States, k: int, eps: float = 0.01) -> torch.Tensor:
    """Squared log ratio of how far each keypoint ranges over the open loop from frame ``k`` (its std
    over time, per sequence and coordinate, of ``kp_head``'s reading of T - k >= 2 states) and over the
    frames' own (``emb`` (B, T+1, embed + 2K), detached), summed over coordinates, mean over the batch.

    Blind to phase: past the steps whose keypoints are scored one by one (``keypoint_horizon``) a
    swing may be anywhere on its arc, and this asks only that it range as far as the truth's does.
    On the pendulum a prior trained without it settled to a point (keypoints ranging 0.3-1.1 px where
    the frames' range 9 px); 400 latent-only steps of it on that prior gave 6-9 px, and the decoded
    ball's travel (bench motion) was 2.5 px instead of 1.0 (docs/decisions.md, keypoint_spread).
    """
    kp = emb[:, k + 1:, model.cfg.embed:].detach()
    ko = state_keypoints(model, open_loop)
    return ((torch.log(ko.std(1) + eps) - torch.log(kp.std(1) + eps)) ** 2).sum(-1).mean()


def _dynamics_kl(f: States) -> torch.Tensor:
    """KL(sg(q) || p) of a filtering pass, batch mean per step, mean over steps: it trains the prior."""
    return torch.stack([kl_divergence(qm.detach(), qs.detach(), pm, ps).mean()
                        for qm, qs, pm, ps in zip(f.post_mean, f.post_std, f.prior_mean, f.prior_std)]).mean()


def _kl_terms(model: Rssm, f: States) -> tuple[torch.Tensor, dict[str, float]]:
    """The balanced KL of a filtering pass and its parts: the dynamics term (trains the prior, never
    clamped) and the representation term (trains the posterior, free nats on its batch mean)."""
    cfg = model.cfg
    dyn = _dynamics_kl(f)
    rep = torch.stack([kl_divergence(qm, qs, pm.detach(), ps.detach()).mean()
                       for qm, qs, pm, ps in zip(f.post_mean, f.post_std, f.prior_mean, f.prior_std)])
    floored = torch.clamp(rep, min=cfg.free_nats).mean()
    kl = cfg.kl_balance * dyn + (1 - cfg.kl_balance) * floored
    return kl, {"kl_dyn": dyn.item(), "kl_rep": rep.mean().item()}


def _overshoot(f: States, open_loop: States, k: int) -> torch.Tensor:
    """Latent overshooting: the filtering posteriors of frames k+1..T (detached) against the open
    loop's priors from frame ``k``, mean over steps."""
    return torch.stack([kl_divergence(f.post_mean[t].detach(), f.post_std[t].detach(), pm, ps).mean()
                        for t, pm, ps in zip(range(k + 1, len(f.h)), open_loop.prior_mean, open_loop.prior_std)]).mean()


def _keypoint_terms(terms: dict[str, torch.Tensor], model: Rssm, emb: torch.Tensor, f: States,
                    ol: States, k: int) -> None:
    """Add the keypoint terms (with ``kp_head``) of a pass to ``terms``: :func:`keypoint_error` and,
    with its scale and an open loop of 2 or more steps, :func:`keypoint_spread`."""
    if model.kp_head is None:
        return
    terms["keypoints"] = keypoint_error(model, emb, f, ol, k)
    if model.cfg.scale("keypoint_spread") > 0 and len(ol.h) > 1:
        terms["keypoint_spread"] = keypoint_spread(model, emb, ol, k)


# --------------------------------------------------------------------------- the two losses
class _Batch:
    """A batch's frames as the decoder reads them: the context (frame 0's maps, pixels, view) and
    the views' encodings; :meth:`chain` decodes consecutive frames of every sequence."""

    def __init__(self, model: Rssm, x: torch.Tensor, views: torch.Tensor, anchor: torch.Tensor | None):
        self.model, self.x = model, x
        self.pe = model.encode_view(views)
        self.emb = model.encoder(x.flatten(0, 1)).view(x.shape[0], x.shape[1], -1)
        self.ctx = model.encoder.context(x[:, 0])
        if model.cfg.anchor and anchor is None:
            raise DbbError("this RSSM reads a view anchor: the batch must carry its renders")
        self.anchor = anchor if model.cfg.anchor else None
        self.ctx_anchor = (None if self.anchor is None else
                           image_pyramid(self.anchor[:, 0], len(model.decoder.ups)))
        self.w = motion_weights(x, model.cfg.motion_weight) if model.cfg.motion_weight > 0 else None

    def identity(self) -> torch.Tensor:
        """The warp before the first step (B, S, S, 2): the context frame as it is."""
        return self.model.decoder.grid.expand(self.x.shape[0], -1, -1, -1)

    def chain(self, h: torch.Tensor, z: torch.Tensor, t0: int, t1: int, grid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Frames t0..t1-1 (B, t1 - t0, 4, S, S) decoded in order from states ``h``, ``z`` (B, t1 - t0, .),
        starting from the warp ``grid`` of frame t0 - 1; and the last frame's warp."""
        cfg = self.model.cfg
        kp = self.emb[:, t0:t1, cfg.embed:].detach() if cfg.keypoint_teacher else None
        return self.model.decode_chain(h, z, self.pe[:, t0:t1], self.pe[:, t0 - 1], self.ctx, self.x[:, 0],
                                       self.pe[:, 0], grid, kp,
                                       None if self.anchor is None else self.anchor[:, t0:t1], self.ctx_anchor)

    def rec(self, pred: torch.Tensor, t0: int, t1: int) -> torch.Tensor:
        """:func:`reconstruction` of ``pred`` (B * (t1 - t0), 4, S, S): frames t0..t1-1 of every sequence."""
        x = self.x
        w = None if self.w is None else self.w[:, t0:t1].flatten(0, 1)
        w = with_predicted_change(w, pred, x[:, t0 - 1:t1 - 1].flatten(0, 1), self.model.cfg.motion_weight)
        return reconstruction(pred, x[:, t0:t1].flatten(0, 1), w)


def loss_terms(model: Rssm, x: torch.Tensor, views: torch.Tensor,
               anchor: torch.Tensor | None = None) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
    """The unscaled training terms of a batch of sequences (names of ``RssmConfig.loss_scales``; a term
    whose scale is 0 is left out) and the KL's parts.

    ``x``: premultiplied RGBA (B, T+1, 4, S, S) in [0, 1], frame 0 the context; ``views``: (B, T+1, 3)
    [azimuth_deg, elevation_deg, distance_m]; ``anchor`` (B, T+1, 4, S, S) premultiplied, the view
    anchor's render at each frame's view (``cfg.anchor``). Frames follow one another (each step's warp builds on
    the last): the filtering frames 1..T are decoded in order from the identity warp (frame 0 is the
    context itself), the open loop goes on from the filtering warp of frame k, as its states do.
    """
    cfg = model.cfg
    b = _Batch(model, x, views, anchor)
    T1 = x.shape[1]
    f = model.observe(b.emb, b.pe)
    kl, info = _kl_terms(model, f)
    k = min(OPEN_LOOP_FROM, T1 - 2)
    H, Z = torch.stack(f.h, 1), torch.stack(f.z, 1)
    filtered, g_k = x[:, :0], b.identity()
    if k >= 1:
        filtered, g_k = b.chain(H[:, 1:k + 1], Z[:, 1:k + 1], 1, k + 1, g_k)
    rest, _ = b.chain(H[:, k + 1:], Z[:, k + 1:], k + 1, T1, g_k)
    terms = {"rec": b.rec(torch.cat([filtered, rest], 1).flatten(0, 1), 1, T1), "kl": kl}
    ol = model.imagine(f.h[k], f.z[k], T1 - k - 1)
    terms["overshoot"] = _overshoot(f, ol, k)
    # The open loop's frames are decoded only for a term that scores them (energy, sharp); without
    # one the prior learns from the KL and overshooting, at about half a step's cost.
    decode_open_loop = cfg.scale("energy") > 0 or cfg.scale("sharp") > 0
    first = None
    if k >= 1 and (decode_open_loop or cfg.scale("first_step") > 0):
        # The run-time step 1 exactly: z_1 sampled from the prior at h_1, decoded from the identity
        # warp (the open loop from frame k >= 1 never decodes it; untrained, it drew a random motion
        # and lost ~3 dB to copying). Scored on its own; with the open loop decoded it is that loop's
        # first frame instead, which the sharpness match scores (the energy match starts after it).
        pm1, ps1 = model.prior_stats(f.h[1])
        first, _ = b.chain(f.h[1][:, None], sample(pm1, ps1)[:, None], 1, 2, b.identity())
        if not decode_open_loop:
            terms["first_step"] = b.rec(first.flatten(0, 1), 1, 2)
    if decode_open_loop:
        frames, _ = b.chain(torch.stack(ol.h, 1), torch.stack(ol.z, 1), k + 1, T1, g_k)
        t = torch.arange(k + 1, T1, device=x.device)
        n0 = 0 if first is None else 1
        if first is not None:
            frames, t = torch.cat([first, frames], 1), torch.cat([t.new_ones(1), t])
        if cfg.scale("sharp") > 0:
            terms["sharp"] = sharpness_match(frames.flatten(0, 1), x[:, t].flatten(0, 1))
    _keypoint_terms(terms, model, b.emb, f, ol, k)
    if decode_open_loop and cfg.scale("energy") > 0 and T1 - k - 1 > 1:
        terms["energy"] = energy_match(frames[:, n0:], x[:, k + 1:])
    return terms, info


def weighted(terms: dict[str, torch.Tensor], scales: dict[str, float]) -> torch.Tensor:
    """The training loss: each term times its scale, summed in the order of :data:`LOSS_SCALES`."""
    total = None
    for name in LOSS_SCALES:
        if name in terms:
            part = float(scales[name]) * terms[name]
            total = part if total is None else total + part
    return total


def sequence_loss(model: Rssm, x: torch.Tensor, views: torch.Tensor,
                  anchor: torch.Tensor | None = None) -> tuple[torch.Tensor, dict]:
    """Training loss of a batch of sequences (:func:`loss_terms`, weighted by ``loss_scales``) and its
    parts for the history: the terms (the KL as its two parts ``kl_dyn``, ``kl_rep``) and ``loss``."""
    terms, info = loss_terms(model, x, views, anchor)
    loss = weighted(terms, model.cfg.loss_scales)
    parts = {"rec": terms["rec"].item(), **info,
             **{k: v.item() for k, v in terms.items() if k not in ("rec", "kl")}, "loss": loss.item()}
    return loss, parts


def latent_loss(model: Rssm, x: torch.Tensor, views: torch.Tensor,
                anchor: torch.Tensor | None = None) -> tuple[torch.Tensor, dict]:
    """The prior's share of :func:`sequence_loss` alone, with the encoder and posterior held fixed
    and nothing decoded (``TrainConfig.dynamics_steps``): the dynamics KL along the filtering
    states (as ``kl``, times ``kl_balance``), latent overshooting along the open loop and (with
    ``loss_scales.keypoints``) the keypoints read from both. Same arguments as :func:`sequence_loss`
    (nothing is decoded, so ``anchor`` is not read); a fraction of its cost."""
    cfg = model.cfg
    B, T1 = x.shape[:2]
    pe = model.encode_view(views)
    with torch.no_grad():
        emb = model.encoder(x.flatten(0, 1)).view(B, T1, -1)
    f = model.observe(emb, pe, train_posterior=False)
    dyn = _dynamics_kl(f)
    k = min(OPEN_LOOP_FROM, T1 - 2)
    ol = model.imagine(f.h[k], f.z[k], T1 - k - 1)
    terms = {"kl": cfg.kl_balance * dyn, "overshoot": _overshoot(f, ol, k)}
    _keypoint_terms(terms, model, emb, f, ol, k)
    parts = {"kl_dyn": dyn.item(), "overshoot": terms["overshoot"].item(),
             **{n: terms[n].item() for n in ("keypoints", "keypoint_spread") if n in terms}}
    return weighted(terms, cfg.loss_scales), parts
