"""An opaque shell tree seen from a camera, shared by the renderer tests."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dbb_capture.geometry.cameras import Intrinsics
from dbb_capture.geometry.transforms import look_at
from dbb_capture.octree.tree import PlenOctree, build_tree


@pytest.fixture(scope="session")
def shell():
    """A sphere of radius 0.6 around the origin (tree radius 1), two leaves thick at depth 4
    (32^3), alpha 0.95 per leaf, random SH9 colour and a haze of faint leaves inside; and a
    camera (OpenCV c2w, 24 px intrinsics) that sees all of it: what a baked object looks like."""
    depth, L = 4, 32
    g = (np.arange(L) + 0.5) / L * 2 - 1
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    dist = np.sqrt(x * x + y * y + z * z)
    rng = np.random.default_rng(2)
    shell_cells = np.argwhere(np.abs(dist - 0.6) < 2.0 / L)
    haze_cells = np.argwhere((dist < 0.4) & (rng.random(dist.shape) < 0.2))
    cells = np.concatenate([shell_cells, haze_cells])
    sigma = np.concatenate([np.full(len(shell_cells), -math.log(0.05) / (2.0 / L)),
                            np.full(len(haze_cells), -math.log(0.98) / (2.0 / L))])
    vals = np.concatenate([rng.normal(0, 0.5, (len(cells), 27)), sigma[:, None]], 1).astype(np.float32)
    data, child, pd = build_tree(cells, vals, depth)
    tree = PlenOctree(data.astype(np.float16), child, pd, np.full(3, 0.5, np.float32),
                      np.full(3, 0.5, np.float32), depth, "SH9")
    f = 12 / math.tan(math.radians(20))
    c2w = look_at(np.array([0.0, -2.4, -0.7]), np.zeros(3), np.array([0.0, 0.0, -1.0]))
    return tree, c2w, Intrinsics(24, 24, f, f, 11.5, 11.5)
