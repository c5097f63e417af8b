"""The RSSM's networks: the encoder (with spatial-softmax keypoints), the decoder that redraws the
context frame through an accumulated warp, its fast run-time upsampling (:class:`PhaseUp`) and the
oscillator cell that may stand beside the GRU (:class:`OscCell`).

Frames are premultiplied RGBA (B, 4, S, S) in [0, 1]; grids are ``grid_sample`` coordinates
(align_corners=False) in [-1, 1], (x, y) last.
"""

from __future__ import annotations

import copy
import math
from typing import List, Optional

import torch
from torch import nn
from torch.nn import functional as F

from .config import RssmConfig


# --------------------------------------------------------------------------- warps and maps
def identity_grid(n: int, size: int, device: torch.device | None = None) -> torch.Tensor:
    """Pixel-centre sampling grid of ``grid_sample`` (align_corners=False), (n, S, S, 2) as (x, y) in [-1, 1]."""
    lin = (torch.arange(size, dtype=torch.float32, device=device) * 2.0 + 1.0) / size - 1.0
    gy, gx = torch.meshgrid(lin, lin, indexing="ij")
    return torch.stack([gx, gy], -1)[None].expand(n, -1, -1, -1).contiguous()


def accumulated_warp(grid: torch.Tensor, flow: torch.Tensor, base: torch.Tensor, leak: float = 0.0) -> torch.Tensor:
    """Where each pixel of the next frame comes from in the context frame, (N, S, S, 2) grid_sample
    coordinates: ``grid`` the same for the current frame, ``flow`` (N, 2, S, S) the step's motion
    as a backward flow (the next frame's pixel p was at p + flow(p) in the current one), ``base``
    the identity grid (1, S, S, 2) (:func:`identity_grid`).

    The composition grid(p + flow(p)) resamples the smooth coordinate field, never the image, so
    a part that travels far over many steps stays as sharp as one resampling of the context frame,
    and a still part (flow 0) keeps its coordinates exactly. ``leak`` > 0 then shrinks the
    displacement from ``base`` by that fraction: a step's error no longer persists for ever
    (errors stay within about error / leak), and a part must be held where it is by the flow.
    """
    b = base.to(flow.dtype)
    g = F.grid_sample(grid.permute(0, 3, 1, 2), b + flow.permute(0, 2, 3, 1), mode="bilinear",
                      padding_mode="border", align_corners=False).permute(0, 2, 3, 1)
    return g if leak == 0.0 else torch.lerp(g, b, leak)


def warp_maps(maps: List[torch.Tensor], grid: torch.Tensor) -> List[torch.Tensor]:
    """The context frame's encoder maps moved to where their content is now: each map (N, C, r, r)
    resampled through ``grid`` (N, S, S, 2) averaged down to r x r (the identity grid leaves them as they are).
    ``maps`` coarsest first (:meth:`Encoder.features`); the averages are taken finest first, each
    from the last (2x2 means: the same as averaging S x S down to r, at a fraction of the cost)."""
    g = grid.permute(0, 3, 1, 2)
    out: List[torch.Tensor] = []
    for m in maps[::-1]:
        r = m.shape[-1]
        while g.shape[-1] > r:                 # sizes are powers of two (RssmConfig.validate)
            g = F.avg_pool2d(g, 2)
        out.append(F.grid_sample(m, g.permute(0, 2, 3, 1), mode="bilinear", padding_mode="border",
                                 align_corners=False))
    return out[::-1]


def image_pyramid(x: torch.Tensor, levels: int) -> List[torch.Tensor]:
    """``x`` (N, C, S, S) averaged down by 2 ``levels`` times, coarsest first: [S / 2^levels, ..., S / 2]."""
    out: List[torch.Tensor] = []
    for _ in range(levels):
        x = F.avg_pool2d(x, 2)
        out.insert(0, x)
    return out


def keypoint_maps(kp: torch.Tensor, r: int, std: float) -> torch.Tensor:
    """Keypoints (N, 2K) as :class:`SpatialSoftmax` gives them (K x, then K y, in [-1, 1]) ->
    Gaussian maps (N, K, r, r) at the pixel centres of an r x r grid, peak 1; the std is at
    least half a cell (2 / r frame units a cell), so a coarse map still sees the point."""
    k = kp.shape[1] // 2
    s = max(std, 1.0 / r)
    c = (torch.arange(r, dtype=kp.dtype, device=kp.device) + 0.5) * (2.0 / r) - 1.0
    gx = torch.exp(-0.5 * ((c - kp[:, :k, None]) / s) ** 2)             # (N, K, r)
    gy = torch.exp(-0.5 * ((c - kp[:, k:, None]) / s) ** 2)
    return gy[:, :, :, None] * gx[:, :, None, :]


# --------------------------------------------------------------------------- encoder
def _enc_channels(cfg: RssmConfig) -> list[int]:
    """Channels after each encoder conv, at resolutions S/2, S/4, ..., 4."""
    n = int(math.log2(cfg.size // 4))
    return [min(cfg.enc_depth * 2 ** i, 256) for i in range(n)]


def _dec_channels(cfg: RssmConfig) -> list[int]:
    """Channels at resolutions 4, 8, ..., size/2 (the last conv makes the decoder's outputs)."""
    n = int(math.log2(cfg.size // 4))
    return [max(8, min(128, cfg.dec_depth * 32 // (4 * 2 ** i))) for i in range(n)]


class SpatialSoftmax(nn.Module):
    """Feature map (B, C, H, W) -> keypoints (B, 2K): the expected (x, y) in [-1, 1] of each of K
    softmax distributions over the map (Finn et al. 2016, deep spatial autoencoders).

    Each channel of a 1x1 conv is standardised over the map before the softmax, so a small
    part unlike its surroundings dominates whatever its size; the sharpness is learned (one per
    keypoint, starting at 5: a 5-px ball on a plain wall then moves its keypoints by ~0.1-0.6).
    """

    def __init__(self, channels: int, k: int, size: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, k, 1)
        self.log_beta = nn.Parameter(torch.full((k,), math.log(5.0)))
        c = (torch.arange(size, dtype=torch.float32) + 0.5) * (2.0 / size) - 1.0     # pixel centres
        self.register_buffer("coords", c, persistent=False)

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        logits = self.conv(f).flatten(2)
        logits = (logits - logits.mean(-1, keepdim=True)) / (logits.std(-1, keepdim=True) + 1e-5)
        p = torch.softmax(logits * self.log_beta.exp()[:, None], -1).view(f.shape[0], -1, f.shape[2], f.shape[3])
        return torch.cat([(p.sum(2) * self.coords).sum(-1), (p.sum(3) * self.coords).sum(-1)], 1)


class Encoder(nn.Module):
    """Premultiplied RGBA (B, 4, S, S) in [0, 1] -> embedding (B, embed + 2 * keypoints); also its
    feature maps, which the decoder reads of the context frame."""

    def __init__(self, cfg: RssmConfig):
        super().__init__()
        layers: list[nn.Module] = []
        c_in = 4
        for c in _enc_channels(cfg):
            layers += [nn.Conv2d(c_in, c, 4, 2, 1), nn.SiLU()]
            c_in = c
        self.convs = nn.Sequential(*layers)
        self.out = nn.Linear(c_in * 16, cfg.embed)
        # Keypoints over the first (finest) feature map.
        self.keypoints = (SpatialSoftmax(_enc_channels(cfg)[0], cfg.keypoints, cfg.size // 2)
                          if cfg.keypoints > 0 else None)
        self.maps = bool(cfg.keypoint_maps)
        self.map_std = float(cfg.keypoint_map_std)

    def freeze_keypoints(self) -> None:
        """Keep the keypoint layer and the first conv, whose (finest) map it reads, at their
        initial weights: learned, the softmax spreads and the features drift until the keypoints
        no longer follow a small part."""
        if self.keypoints is not None:
            self.keypoints.requires_grad_(False)
            self.convs[0].requires_grad_(False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        maps = self.features(x)                  # coarsest first: the last is the finest
        kp = x.new_zeros(x.shape[0], 0) if self.keypoints is None else self.keypoints(maps[-1])
        return torch.cat([F.silu(self.out(maps[0].flatten(1))), kp], 1)

    def features(self, x: torch.Tensor) -> List[torch.Tensor]:
        """Feature maps after each conv, coarsest first: [(B, C, 4, 4), (B, C', 8, 8), ..., (B, c, S/2, S/2)]."""
        maps: List[torch.Tensor] = []
        x = x - 0.5
        i = 0
        for layer in self.convs:
            x = layer(x)
            if i % 2 == 1:
                maps.insert(0, x)
            i += 1
        return maps

    def context(self, x: torch.Tensor) -> List[torch.Tensor]:
        """What the decoder reads of a context frame (B, 4, S, S): :meth:`features`, with
        ``keypoint_maps`` each joined by the Gaussian maps of the frame's keypoints."""
        maps = self.features(x)
        if not self.maps or self.keypoints is None:
            return maps
        kp = self.keypoints(maps[-1])
        return [torch.cat([m, keypoint_maps(kp, m.shape[-1], self.map_std)], 1) for m in maps]


# --------------------------------------------------------------------------- decoder
class Decoder(nn.Module):
    """One step of the frame sequence: features (N, deter + stoch + 8 * view_freqs: the state and the
    encodings of the view's change since the context frame and since the last frame, see
    :func:`dbb_capture.dynamic.model.decoder_input`) and the current warp -> the next premultiplied
    RGBA frame (N, 4, S, S) and its warp.

    The context frame's encoder maps join each resolution (U-Net style), moved along the warp so
    far (:func:`warp_maps`), so the decoder sees where things are now. The last layer gives
    generated RGBA, the warp's share (a mask) and one step's flow; the flow is composed with the
    warp so far (:func:`accumulated_warp`), so parts may travel anywhere in the frame over many
    steps while the frame stays one resampling of the context frame, blended with generated content
    where the context frame cannot show the view. It starts as the context frame exactly (zero
    flow, ~95 % warp share). With ``keypoint_maps`` each layer also reads Gaussian maps of the
    keypoints that ``kp_net`` reads from the state (h, z), the first deter + stoch features.

    With ``anchor`` each layer also reads the view anchor's renders (:mod:`dbb_capture.dynamic.anchor`)
    at the drawn view and at the context frame's, averaged down to its size: how the object's mean
    shape looks from here and how it moved since the context frame. The generated content is then
    itself a blend of the network's colours and the anchor's render at the drawn view (its own share).
    """

    def __init__(self, cfg: RssmConfig):
        super().__init__()
        ch = _dec_channels(cfg)
        self.c0 = ch[0]
        self.max_step_flow = float(cfg.max_step_flow)
        self.warp_leak = float(cfg.warp_leak)
        n_pe = 2 * 4 * cfg.view_freqs            # the view's change since the context frame, since the last frame
        self.fc = nn.Sequential(nn.Linear(cfg.deter + cfg.stoch + n_pe, cfg.hidden), nn.SiLU(),
                                nn.Linear(cfg.hidden, ch[0] * 16))
        enc = _enc_channels(cfg)[::-1]           # the context maps at 4, 8, ..., S/2
        self.n_state = cfg.deter + cfg.stoch
        self.map_std = float(cfg.keypoint_map_std)
        self.kp_net = (nn.Sequential(nn.Linear(self.n_state, cfg.hidden), nn.SiLU(),
                                     nn.Linear(cfg.hidden, 2 * cfg.keypoints)) if cfg.keypoint_maps else None)
        if cfg.keypoint_maps:                    # the state's keypoints, and the context's in its maps
            enc = [c + 2 * cfg.keypoints for c in enc]
        self.anchor = bool(cfg.anchor)
        if self.anchor:                          # the anchor at the drawn view and at the context's
            enc = [c + 8 for c in enc]
        # Outputs: RGBA, the warp's share (a logit), the step's flow x, y, then the anchor's share.
        self.ups = nn.ModuleList([nn.ConvTranspose2d(c_in + c_skip, c_out, 4, 2, 1)
                                  for c_in, c_skip, c_out in zip(ch, enc, ch[1:] + [8 if self.anchor else 7])])
        # Pixel-centre sampling grid of grid_sample (align_corners=False), (1, S, S, 2) as (x, y).
        self.register_buffer("grid", identity_grid(1, cfg.size), persistent=False)
        with torch.no_grad():                    # start as the context frame, unwarped
            last = self.ups[-1]
            last.weight[:, 4:].mul_(0.1)
            last.bias[4:] = 0.0
            last.bias[4] = 3.0                   # ~95 % warp share
            last.weight[:, 5:7] = 0.0            # zero flow: the first steps are the context frame exactly
            if self.anchor:
                last.bias[7] = 0.0               # the generated half the anchor's render

    def state_keypoints(self, feat: torch.Tensor) -> torch.Tensor:
        """``keypoint_maps``: the keypoints (N, 2K) the state (feat's first deter + stoch) puts the parts at."""
        if self.kp_net is None:
            return feat.new_zeros(feat.shape[0], 0)
        return self.kp_net(feat[:, :self.n_state])

    def heads(self, feat: torch.Tensor, ctx: List[torch.Tensor], kp: torch.Tensor,
              anchors: List[torch.Tensor]) -> torch.Tensor:
        """The last layer's output (N, 7 or 8, S, S) before compositing: RGBA and warp-share logits,
        the flow's, the anchor share's; ``ctx`` the context maps as the decoder sees them now, ``kp``
        the keypoints to draw from, ``anchors`` the anchor's maps at each layer (or none)."""
        x = F.silu(self.fc(feat).view(-1, self.c0, 4, 4))
        n = len(self.ups)
        i = 0
        for up in self.ups:
            x = torch.cat([x, ctx[i]], 1)
            if self.anchor:
                x = torch.cat([x, anchors[i]], 1)
            if self.kp_net is not None:
                x = torch.cat([x, keypoint_maps(kp, x.shape[-1], self.map_std)], 1)
            x = up(x)
            if i < n - 1:
                x = F.silu(x)
            i += 1
        return x

    def anchor_maps(self, anchor: torch.Tensor, ctx_anchor: List[torch.Tensor]) -> List[torch.Tensor]:
        """The anchor's maps at each layer's input (4, 8, ..., S/2): its render at the drawn view
        ``anchor`` (N, 4, S, S) averaged down, beside ``ctx_anchor`` (the same of the context frame's
        view, :func:`image_pyramid` of it with as many levels as layers)."""
        here = image_pyramid(anchor, len(self.ups))
        return [torch.cat([a, c], 1) for a, c in zip(here, ctx_anchor)]

    def forward(self, feat: torch.Tensor, ctx: List[torch.Tensor], ctx_pm: torch.Tensor,
                grid: torch.Tensor, kp: Optional[torch.Tensor] = None, anchor: Optional[torch.Tensor] = None,
                ctx_anchor: Optional[List[torch.Tensor]] = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The next frame (N, 4, S, S) premultiplied and its warp (N, S, S, 2), from the current
        frame's warp ``grid`` (the identity grid before the first step), the context frame's maps
        ``ctx`` (:meth:`Encoder.context`, one row per frame) and pixels ``ctx_pm``; ``kp`` (N, 2K)
        the keypoints to draw from (``keypoint_teacher`` in training), by default the state's.
        With ``anchor``: its render at the drawn view (N, 4, S, S) premultiplied and ``ctx_anchor``
        the context view's pyramid (:meth:`anchor_maps`)."""
        if kp is None:
            kp = self.state_keypoints(feat)
        anchors: List[torch.Tensor] = []
        if anchor is not None and ctx_anchor is not None:
            anchors = self.anchor_maps(anchor, ctx_anchor)
        x = self.heads(feat, warp_maps(ctx, grid), kp, anchors)
        s = torch.sigmoid(x[:, :5])                               # RGBA and the warp's share
        gen = torch.cat([s[:, :3] * s[:, 3:4], s[:, 3:4]], 1)
        if anchor is not None:
            gen = torch.lerp(gen, anchor, torch.sigmoid(x[:, 7:8]))
        flow = torch.tanh(x[:, 5:7]) * self.max_step_flow
        grid = accumulated_warp(grid, flow, self.grid, self.warp_leak)
        warped = F.grid_sample(ctx_pm, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        return torch.lerp(gen, warped, s[:, 4:5]), grid


class PhaseUp(nn.Module):
    """A ``ConvTranspose2d(c_in, c_out, 4, stride=2, padding=1)`` as one 2x2 convolution to
    4 x c_out channels, one per output phase, interleaved into the doubled grid: the same
    function with the same multiply-adds as the transposed convolution, which has no fast CPU
    kernel (measured on 1 core at 64x64: 505 us for the four layers against 743 for 3x3 subpixel
    convolutions and 902 for the transposed ones). The stepper decodes with these; training keeps
    the transposed convolutions (same weights, same results)."""

    def __init__(self, up: nn.ConvTranspose2d):
        super().__init__()
        if up.kernel_size != (4, 4) or up.stride != (2, 2) or up.padding != (1, 1) or up.groups != 1:
            raise ValueError("PhaseUp converts ConvTranspose2d(k=4, s=2, p=1) only")
        w = up.weight.detach()                                   # (c_in, c_out, 4, 4)
        c_in, c_out = w.shape[:2]
        k = w.new_zeros(c_out, 2, 2, c_in, 2, 2)                 # (c_out, row phase, col phase, c_in, 2, 2)
        # Output row 2m + a: a = 0 takes input rows m - 1 (tap 3) and m (tap 1); a = 1 takes rows
        # m (tap 2) and m + 1 (tap 0). The 2x2 convolution over the input padded by 1 sees rows
        # q - 1 and q at its output row q, so phase a reads its output at q = m + a.
        taps = ((3, 1), (2, 0))
        for a in (0, 1):
            for b in (0, 1):
                for j in (0, 1):
                    for i in (0, 1):
                        k[:, a, b, :, j, i] = w[:, :, taps[a][j], taps[b][i]].t()
        # Channels-last convolutions are faster from 32 input channels (1 core: 1.3-1.8x), slower below.
        self.channels_last = c_in >= 32
        fmt = torch.channels_last if self.channels_last else torch.contiguous_format
        self.weight = nn.Parameter(k.reshape(4 * c_out, c_in, 2, 2).contiguous(memory_format=fmt), requires_grad=False)
        bias = up.bias.detach() if up.bias is not None else w.new_zeros(c_out)
        self.bias = nn.Parameter(bias.repeat_interleave(4), requires_grad=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        y = F.conv2d(x, self.weight, self.bias, padding=1)       # (N, 4C, H + 1, W + 1), either layout
        n, c, h, w = y.shape[0], y.shape[1] // 4, y.shape[2] - 1, y.shape[3] - 1
        sn, sc, sh, sw = y.stride(0), y.stride(1), y.stride(2), y.stride(3)
        # Phase (a, b) at (m, n) is y[:, 4c + 2a + b, m + a, n + b]: a linear offset in (a, b, m, n)
        # in any layout, so one strided view gathers all four phases.
        s = y.as_strided([n, c, 2, 2, h, w], [sn, 4 * sc, 2 * sc + sh, sc + sw, sh, sw])
        return s.permute(0, 1, 4, 2, 5, 3).reshape(n, c, 2 * h, 2 * w)


def fast_decoder(dec: Decoder) -> Decoder:
    """A copy of ``dec`` for the run-time stepper, its upsampling layers recast as :class:`PhaseUp`."""
    fast = copy.deepcopy(dec)
    fast.ups = nn.ModuleList([PhaseUp(u) for u in fast.ups])
    return fast


# --------------------------------------------------------------------------- recurrent cell
class OscCell(nn.Module):
    """A GRU cell beside ``n`` damped rotations, one recurrent state (B, units + 2n): [gru, re, im].

    Each mode k turns by ``theta_k`` radians a step and keeps ``exp(-exp(nu_k))`` of its length;
    the input drives the modes, the GRU reads them. Initialised near the unit circle (keeps
    0.97-0.999 a step) with periods of 6-120 steps, so a mode rings long after the trained horizon.
    ``keep_min`` floors the kept length. Same call as ``nn.GRUCell``: ``cell(x, h) -> h``.

    The modes are linear and the input is read from the state (prior -> z -> drive), so a loop
    with gain above 1 can grow without end past the trained horizon (a swing run's open loop
    reached inf by step 100). ``amp_limit`` (n,), fitted after training to each mode's largest
    length over the training footage (:func:`dbb_capture.dynamic.evaluate.fit_amp_limit`),
    bounds the lengths outside training: below it nothing changes, above it a length saturates
    softly at 1.5x. All zeros (models fitted before it, and in training mode): unbounded."""

    def __init__(self, input_size: int, units: int, n: int, keep_min: float = 0.0):
        super().__init__()
        self.n = n
        self.keep_min = keep_min
        self.units = units
        self.cell = nn.GRUCell(input_size + 2 * n, units)
        self.drive = nn.Linear(input_size, 2 * n, bias=False)   # rings about 0
        g = torch.Generator().manual_seed(0)
        keep = 0.97 + 0.029 * torch.rand(n, generator=g)
        self.nu = nn.Parameter(torch.log(-torch.log(keep)))
        self.theta = nn.Parameter(2 * math.pi / torch.exp(torch.empty(n).uniform_(math.log(6.0), math.log(120.0), generator=g)))
        with torch.no_grad():
            self.drive.weight.mul_(0.1)
        # A run-time fit, not a weight: model.pt keeps it beside the state dict (the stepper has it).
        self.register_buffer("amp_limit", torch.zeros(n), persistent=False)

    def amplitude(self, h: torch.Tensor) -> torch.Tensor:
        """Each mode's length (B, n) in state ``h`` (B, units + 2n)."""
        re, im = h[:, self.units:self.units + self.n], h[:, self.units + self.n:]
        return torch.sqrt(re * re + im * im)

    def kept(self) -> torch.Tensor:
        """The share of each mode's length kept a step (n,)."""
        return torch.exp(-torch.exp(self.nu)).clamp(min=self.keep_min)

    def forward(self, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        g, re, im = h[:, :self.units], h[:, self.units:self.units + self.n], h[:, self.units + self.n:]
        keep = self.kept()
        c, s = keep * torch.cos(self.theta), keep * torch.sin(self.theta)
        d_re, d_im = self.drive(x).chunk(2, -1)
        re, im = c * re - s * im + d_re, s * re + c * im + d_im
        if not self.training and bool((self.amp_limit > 0).any()):
            a = torch.sqrt(re * re + im * im).clamp(min=1e-12)
            lim = self.amp_limit.clamp(min=1e-12)
            w = 0.5 * lim
            bounded = torch.minimum(a, lim) + w * torch.tanh((a - lim).clamp(min=0.0) / w)
            scale = torch.where(self.amp_limit > 0, bounded / a, torch.ones_like(a))
            re, im = re * scale, im * scale
        g = self.cell(torch.cat([x, re, im], -1), g)
        return torch.cat([g, re, im], -1)
