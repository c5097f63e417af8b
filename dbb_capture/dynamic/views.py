"""How the model is told where the viewer is: positional encodings of viewpoints and of their changes.

A viewpoint is (..., 3) [azimuth_deg, elevation_deg, distance_m] of the camera from the object
centre (crops.json ``viewpoint``); distance is not encoded (the crops are distance-normalized,
thesis 6.1.1). Only the decoder and the posterior read these: the transition never does.
"""

from __future__ import annotations

import math

import torch


def view_octaves(freqs: int) -> torch.Tensor:
    """Radians per degree at octaves 1, 2, 4, ... (freqs,) float32: the frequencies of :func:`view_encoding`."""
    return (math.pi / 180.0) * 2.0 ** torch.arange(freqs, dtype=torch.float32)


def view_encoding(view: torch.Tensor, octaves: torch.Tensor) -> torch.Tensor:
    """Viewpoints (..., 3) -> (..., 4 * F): sin, then cos, of the azimuth at the F ``octaves``
    (:func:`view_octaves`), then the same of the elevation. The encoding of a difference of
    viewpoints is that of the change of view."""
    a = view[..., :2, None] * octaves.to(view.dtype)                # (..., 2, F)
    return torch.cat([torch.sin(a), torch.cos(a)], -1).flatten(-2)


def view_delta_encoding(pe: torch.Tensor, ref_pe: torch.Tensor) -> torch.Tensor:
    """The change of view from ``ref_pe`` to ``pe``, both :func:`view_encoding` rows (N, 4F), by the
    angle-difference identities (sin(a - b) = sin a cos b - cos a sin b, ...): the same function as
    the encoding of the difference of viewpoints, from encodings at hand (training encodes every
    frame's view once; the stepper, one view a step, encodes the difference). The change since the
    context frame is what the warp needs; an MLP can form these products of its inputs only approximately.
    """
    freqs = pe.shape[-1] // 4
    s1, c1 = pe.view(-1, 2, 2, freqs).unbind(2)
    s0, c0 = ref_pe.view(-1, 2, 2, freqs).unbind(2)
    return torch.stack([s1 * c0 - c1 * s0, c1 * c0 + s1 * s0], 2).flatten(1)
