"""The run-time stepper: the trained model one frame at a time, TorchScript-exportable (``stepper.ts``).

Frames in and out are straight RGBA (B, 4, S, S) in [0, 1]; views (B, 3) [azimuth_deg,
elevation_deg, distance_m] (crops.json ``viewpoint``). A model with a view anchor carries its
atlas (:class:`dbb_capture.dynamic.anchor.ViewAtlas`) inside, so ``stepper.ts`` needs nothing else. The stochastic state is sampled, not
replaced by its mean (the mean settles within ~30 steps). A temperature above 1 makes up for
the prior's motion fading past the horizon it was trained on; within that horizon (``warmup``
steps) the temperature rises from the prior as trained (1, or the temperature if lower) to it,
so the first steps, which the training's open loop covered, are not made noisier than trained.
"""

from __future__ import annotations

from typing import List, Optional

import torch

from ..core.errors import DbbError
from .anchor import ViewAtlas, no_atlas
from .model import LatentStep, Rssm, decoder_input, sample
from .networks import fast_decoder, image_pyramid
from .rgba import premultiply, straight


class Stepper(LatentStep):
    """Run-time API, TorchScript-exportable; the model's own latent step (:class:`LatentStep`) and
    decoder (its upsampling as :class:`dbb_capture.dynamic.networks.PhaseUp`: the same function, faster).

    ``start(rgba, view) -> (h, z)``: the state after seeing the first frame. The stepper keeps that
    frame (and its encoder maps) as the context of the following steps, so one stepper runs one
    rollout (batch) at a time.
    ``step(h, z, view) -> (h, z, rgba)``: advance one frame (the transition ignores ``view``),
    sample the stochastic state (``temperature`` scales its std; 0 gives the mean; see
    :meth:`step_temperature` for the first ``warmup`` steps) and decode the next frame as seen
    from ``view``.
    ``observe(h, z, rgba, view) -> (h, z)`` and ``decode(h, z, view) -> rgba``: filtering instead of
    forecasting, and the frame of any state.
    """

    def __init__(self, model: Rssm, temperature: float = 1.0, atlas: ViewAtlas | None = None, warmup: int = 0):
        super().__init__()
        if model.cfg.anchor and atlas is None:
            raise DbbError("this RSSM reads a view anchor: the stepper needs its atlas (the run's model.pt)")
        self.use_anchor = bool(model.cfg.anchor)
        self.atlas = atlas if self.use_anchor else no_atlas(model.cfg.size)
        self.levels = len(model.decoder.ups)
        self.ctx_anchor = []                # the context view's anchor pyramid, set by start()
        self.encoder = model.encoder
        self.decoder = fast_decoder(model.decoder)
        self.z_in = model.z_in
        self.gru = model.gru
        self.prior = model.prior
        self.post = model.post
        self.min_std = float(model.cfg.min_std)
        self.deter = int(model.cfg.deter)
        self.temperature = float(temperature)
        self.warmup = int(warmup)           # steps of the temperature's rise (the trained horizon)
        self.t = 0                          # steps since start()
        self.ctx = []                       # the context frame's encoder maps, set by start()
        self.ctx_pm = torch.zeros(0)        # its premultiplied pixels
        self.warp = torch.zeros(0)          # the last frame's warp, set by start(), step()
        self.ctx_view = torch.zeros(0)      # the context's and the last frame's viewpoints (N, 3)
        self.prev_view = torch.zeros(0)
        self.register_buffer("octaves", model.octaves.clone(), persistent=False)

    @torch.jit.export
    def start(self, rgba: torch.Tensor, view: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        pm = premultiply(rgba)
        emb = self.encoder(pm)
        self.ctx = self.encoder.context(pm)
        self.ctx_pm = pm
        self.ctx_view = view
        self.prev_view = view
        if self.use_anchor:
            self.ctx_anchor = image_pyramid(self.atlas(view), self.levels)
        self.warp = self.decoder.grid.expand(rgba.shape[0], -1, -1, -1).to(rgba.dtype)
        h = torch.zeros(rgba.shape[0], self.deter, dtype=rgba.dtype, device=rgba.device)
        self.t = 0
        mean, std = self.post_stats(h, emb, self.encode_view(view))
        return h, sample(mean, std, self.step_temperature())

    def _decode(self, h: torch.Tensor, z: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
        """Straight RGBA (B, 4, S, S) of state (h, z) seen from ``view``; moves the accumulated warp on.
        The view's changes are encoded from the angles' differences (one encoding for both)."""
        n = view.shape[0]
        d = self.encode_view(torch.cat([view - self.ctx_view, view - self.prev_view]))
        anchor: Optional[torch.Tensor] = None
        ctx_anchor: Optional[List[torch.Tensor]] = None
        if self.use_anchor:
            anchor, ctx_anchor = self.atlas(view), self.ctx_anchor
        pm, self.warp = self.decoder(decoder_input(h, z, d[:n], d[n:]), self.ctx, self.ctx_pm, self.warp,
                                     None, anchor, ctx_anchor)
        self.prev_view = view
        return straight(pm)

    @torch.jit.export
    def step_temperature(self) -> float:
        """The temperature of step ``t`` since start() (0: the context's posterior): from
        min(1, temperature) at 0 linearly to ``temperature`` at step ``warmup``, then flat."""
        first = min(1.0, self.temperature)
        if self.t >= self.warmup:
            return self.temperature
        return first + (self.temperature - first) * float(self.t) / float(self.warmup)

    @torch.jit.export
    def step(self, h: torch.Tensor, z: torch.Tensor, view: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        self.t += 1
        h = self.transition(h, z)
        mean, std = self.prior_stats(h)
        z = sample(mean, std, self.step_temperature())
        return h, z, self._decode(h, z, view)

    @torch.jit.export
    def observe(self, h: torch.Tensor, z: torch.Tensor, rgba: torch.Tensor, view: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Filtering instead of forecasting: the next state after seeing frame ``rgba`` (straight
        RGBA (B, 4, S, S)) from ``view``, z the posterior's mean. Nothing is decoded; the steps
        that follow count from this frame (the warm-up starts again)."""
        self.t = 0
        h = self.transition(h, z)
        mean, _std = self.post_stats(h, self.encoder(premultiply(rgba)), self.encode_view(view))
        return h, mean

    @torch.jit.export
    def decode(self, h: torch.Tensor, z: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
        """The frame of a state (e.g. from :meth:`observe`) seen from ``view`` (see :meth:`step`)."""
        return self._decode(h, z, view)

    def forward(self, h: torch.Tensor, z: torch.Tensor, view: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return self.step(h, z, view)


def script_stepper(model: Rssm, temperature: float = 1.0, atlas: ViewAtlas | None = None,
                   warmup: int = 0) -> torch.jit.ScriptModule:
    """The TorchScript stepper of ``model`` with its view anchor ``atlas`` (on CPU, eval mode)."""
    st = Stepper(model, temperature, atlas, warmup).cpu().eval()
    st.ctx = torch.jit.Attribute([], List[torch.Tensor])     # TorchScript cannot type an empty list
    st.ctx_anchor = torch.jit.Attribute([], List[torch.Tensor])
    return torch.jit.script(st)


@torch.no_grad()
def rollout(stepper, first: torch.Tensor, views: torch.Tensor) -> torch.Tensor:
    """Open-loop frames from ``first`` (B, 4, S, S) straight RGBA; ``views`` (B, T+1, 3) incl. frame 0.

    ``stepper``: a :class:`Stepper` (eager or TorchScript). Returns straight RGBA (B, T, 4, S, S)
    for frames 1..T.
    """
    h, z = stepper.start(first, views[:, 0])
    out = []
    for t in range(1, views.shape[1]):
        h, z, x = stepper.step(h, z, views[:, t])
        out.append(x)
    return torch.stack(out, 1)
