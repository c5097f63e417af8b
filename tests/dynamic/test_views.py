"""Viewpoint encodings: the change of view, from encodings or from the angles' difference."""

from __future__ import annotations

import torch

from dbb_capture.dynamic.views import view_delta_encoding, view_encoding, view_octaves


def test_view_change_from_encodings_is_the_encoding_of_the_difference():
    torch.manual_seed(0)
    oct4 = view_octaves(4)
    assert torch.allclose(oct4 / oct4[0], torch.tensor([1.0, 2.0, 4.0, 8.0]))
    v1, v0 = torch.rand(5, 3) * 300 - 150, torch.rand(5, 3) * 300 - 150
    pe1, pe0 = view_encoding(v1, oct4), view_encoding(v0, oct4)
    assert pe1.shape == (5, 16) and view_encoding(torch.rand(2, 11, 3), oct4).shape == (2, 11, 16)
    assert torch.allclose(view_delta_encoding(pe1, pe0), view_encoding(v1 - v0, oct4), atol=1e-5)
    # Turning the context and the current view together tells the decoder nothing new; distance is not encoded.
    turn = torch.tensor([90.0, 0.0, 0.5])
    turned = view_delta_encoding(view_encoding(v1 + turn, oct4), view_encoding(v0 + turn, oct4))
    assert torch.allclose(turned, view_delta_encoding(pe1, pe0), atol=1e-5)
