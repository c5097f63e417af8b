"""The numba walk's scalar helpers: float16 decoding and the float32 sigmoid."""

from __future__ import annotations

import numpy as np


def test_float16_decoding_is_exact():
    from dbb_capture.octree.kernels import _half

    bits = np.arange(1 << 16, dtype=np.uint16)
    want = bits.view(np.float16).astype(np.float64)
    finite = np.isfinite(want)
    got = np.array([_half(int(u)) for u in bits[finite][::7]])
    np.testing.assert_array_equal(got, want[finite][::7])


def test_fast_sigmoid_matches_numpy():
    from dbb_capture.octree.kernels import _sigmoid

    v = np.linspace(-120, 120, 4001)
    got = np.array([_sigmoid(x) for x in v])
    want = 1 / (1 + np.exp(-v))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)       # float32 colours
