"""The RSSM (PlaNet family, thesis chapter 6): a deterministic GRU state ``h`` and a Gaussian
stochastic state ``z``, a posterior that reads each frame, and a prior that forecasts it.

- The transition ``h_t = GRU(h_{t-1}, z_{t-1})``, ``z_t ~ p(z_t | h_t)`` never sees the viewpoint;
  only the posterior and the decoder ``x_t = dec(h_t, z_t, view change)`` do, so the object's own
  motion cannot stall or repeat because of where the camera is (structural, tested).
- :class:`LatentStep` holds the pieces of one step (transition, the two Gaussians, sampling, the view
  encoding) that the training loops here (:meth:`Rssm.observe`: filtering; :meth:`Rssm.imagine`: the
  open loop) and the run-time :class:`dbb_capture.dynamic.stepper.Stepper` share.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional, Tuple

import torch
from torch import nn
from torch.nn import functional as F

from .config import RssmConfig
from .networks import Decoder, Encoder, OscCell
from .views import view_delta_encoding, view_encoding, view_octaves


def gaussian(stats: torch.Tensor, min_std: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """A network's output (..., 2D) -> Gaussian mean and std (..., D): std = softplus(x) + min_std (PlaNet)."""
    mean, raw = stats.chunk(2, -1)
    return mean, F.softplus(raw) + min_std


def sample(mean: torch.Tensor, std: torch.Tensor, temperature: float = 1.0) -> torch.Tensor:
    """A sample of N(mean, (temperature x std)^2); temperature 0 gives the mean (the noise is drawn anyway)."""
    return mean + temperature * std * torch.randn_like(std)


def decoder_input(h: torch.Tensor, z: torch.Tensor, since_context: torch.Tensor,
                  since_last: torch.Tensor) -> torch.Tensor:
    """The decoder's features (N, deter + stoch + 8F): the state and the encodings of the view's
    change since the context frame (what the warp as a whole must follow) and since the last
    frame (what this step's flow must follow)."""
    return torch.cat([h, z, since_context, since_last], -1)


class LatentStep(nn.Module):
    """One latent step's pieces, shared by :class:`Rssm` and the run-time stepper (which takes the
    model's modules: ``z_in``, ``gru``, ``prior``, ``post``, and ``min_std``, ``octaves``)."""

    def transition(self, h: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Next deterministic state (B, deter) from (B, deter), (B, stoch); no viewpoint."""
        return self.gru(self.z_in(z), h)

    def prior_stats(self, h: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """The prior p(z_t | h_t): mean and std (B, stoch)."""
        return gaussian(self.prior(h), self.min_std)

    def post_stats(self, h: torch.Tensor, emb: torch.Tensor, pe: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """The posterior q(z_t | h_t, frame t, view t): mean and std (B, stoch)."""
        return gaussian(self.post(torch.cat([h, emb, pe], -1)), self.min_std)

    def encode_view(self, view: torch.Tensor) -> torch.Tensor:
        """Viewpoints (..., 3) -> (..., 4 * view_freqs) (:func:`dbb_capture.dynamic.views.view_encoding`)."""
        return view_encoding(view, self.octaves)


@dataclass
class States:
    """The states of a pass over a window, one (B, .) entry per frame: filtering (:meth:`Rssm.observe`)
    or the open loop (:meth:`Rssm.imagine`, no posterior entries)."""

    h: list[torch.Tensor] = field(default_factory=list)
    z: list[torch.Tensor] = field(default_factory=list)        # posterior samples
    post_mean: list[torch.Tensor] = field(default_factory=list)
    post_std: list[torch.Tensor] = field(default_factory=list)
    prior_mean: list[torch.Tensor] = field(default_factory=list)
    prior_std: list[torch.Tensor] = field(default_factory=list)


class Rssm(LatentStep):
    """The model: encoder, decoder, transition (``z_in``, ``gru``), ``prior``, ``post`` and, with
    ``loss_scales.keypoints`` > 0, ``kp_head`` (a state's keypoints; the decoder's own with ``keypoint_maps``)."""

    def __init__(self, cfg: RssmConfig):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        self.min_std = float(cfg.min_std)
        self.encoder = Encoder(cfg)
        self.decoder = Decoder(cfg)
        self.z_in = nn.Sequential(nn.Linear(cfg.stoch, cfg.hidden), nn.SiLU())
        self.gru = (OscCell(cfg.hidden, cfg.deter - 2 * cfg.osc, cfg.osc, cfg.osc_keep_min) if cfg.osc
                    else nn.GRUCell(cfg.hidden, cfg.deter))
        self.prior = nn.Sequential(nn.Linear(cfg.deter, cfg.hidden), nn.SiLU(), nn.Linear(cfg.hidden, 2 * cfg.stoch))
        self.post = nn.Sequential(nn.Linear(cfg.deter + cfg.embed + 2 * cfg.keypoints + 4 * cfg.view_freqs, cfg.hidden),
                                  nn.SiLU(), nn.Linear(cfg.hidden, 2 * cfg.stoch))
        # Training only: the keypoints of a state's frame. With keypoint_maps it is the decoder's own
        # (one head: the maps are drawn where it says).
        self.kp_head = (self.decoder.kp_net if cfg.keypoint_maps else
                        nn.Sequential(nn.Linear(cfg.deter + cfg.stoch, cfg.hidden), nn.SiLU(),
                                      nn.Linear(cfg.hidden, 2 * cfg.keypoints)) if cfg.scale("keypoints") > 0 else None)
        if cfg.keypoints_frozen:
            self.encoder.freeze_keypoints()
        self.register_buffer("octaves", view_octaves(cfg.view_freqs), persistent=False)

    def observe(self, emb: torch.Tensor, pe: torch.Tensor, train_posterior: bool = True) -> States:
        """States: the posterior at every frame. ``emb`` (B, T+1, E) the frames' embeddings, ``pe``
        (B, T+1, 4F) their views' encodings; each z_t sampled from the posterior. ``train_posterior``
        False holds the posterior fixed (no gradient reaches it); the transition and prior still learn."""
        B, T1 = emb.shape[:2]
        out = States()
        h = emb.new_zeros(B, self.cfg.deter)
        z: Optional[torch.Tensor] = None
        grad = torch.is_grad_enabled() and train_posterior
        for t in range(T1):
            if z is not None:
                h = self.transition(h, z)
            pm, ps = self.prior_stats(h)
            with torch.set_grad_enabled(grad):
                qm, qs = self.post_stats(h, emb[:, t], pe[:, t])
            z = sample(qm, qs)
            for store, v in ((out.h, h), (out.z, z), (out.post_mean, qm), (out.post_std, qs),
                             (out.prior_mean, pm), (out.prior_std, ps)):
                store.append(v)
        return out

    def imagine(self, h: torch.Tensor, z: torch.Tensor, steps: int) -> States:
        """The open loop from state (``h``, ``z``) (B, .): ``steps`` transitions, each z sampled from
        the prior, as at run time (no posterior entries)."""
        out = States()
        for _ in range(steps):
            h = self.transition(h, z)
            pm, ps = self.prior_stats(h)
            z = sample(pm, ps)
            for store, v in ((out.h, h), (out.z, z), (out.prior_mean, pm), (out.prior_std, ps)):
                store.append(v)
        return out

    def decode_chain(self, h: torch.Tensor, z: torch.Tensor, pe: torch.Tensor, prev_pe: torch.Tensor,
                     ctx: List[torch.Tensor], ctx_pm: torch.Tensor, ctx_pe: torch.Tensor,
                     grid: torch.Tensor, kp: torch.Tensor | None = None, anchor: torch.Tensor | None = None,
                     ctx_anchor: List[torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Consecutive frames of each row, one step after another. ``h``, ``z`` (N, T, .), ``pe``
        (N, T, 4F) their views, ``prev_pe`` (N, 4F) the view of the frame before the first, ``grid``
        (N, S, S, 2) its warp; ``ctx``/``ctx_pm``/``ctx_pe`` the context frame's maps, pixels and view,
        one row per row; ``kp`` (N, T, 2K) the keypoints to draw each frame from (None: the states');
        ``anchor`` (N, T, 4, S, S) the view anchor at each frame's view and ``ctx_anchor`` the context
        view's pyramid (``cfg.anchor``, :meth:`dbb_capture.dynamic.networks.Decoder.anchor_maps`).
        Returns premultiplied RGBA (N, T, 4, S, S) and the last frame's warp."""
        out = []
        for t in range(h.shape[1]):
            feat = decoder_input(h[:, t], z[:, t], view_delta_encoding(pe[:, t], ctx_pe),
                                 view_delta_encoding(pe[:, t], prev_pe))
            x, grid = self.decoder(feat, ctx, ctx_pm, grid, None if kp is None else kp[:, t],
                                   None if anchor is None else anchor[:, t], ctx_anchor)
            out.append(x)
            prev_pe = pe[:, t]
        return torch.stack(out, 1), grid
