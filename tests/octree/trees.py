"""A random tree to order (random leaves, some of them shallow)."""

from __future__ import annotations

import numpy as np

from dbb_capture.octree.tree import PlenOctree, build_tree


def random_tree(seed: int = 0, depth: int = 3) -> PlenOctree:
    """A tree with random leaves at the finest depth plus shallower leaves (svox trees have
    them) holding density, SH degree 2; its cube has radius 2 around (0.3, -0.2, 0.1)."""
    rng = np.random.default_rng(seed)
    L = 1 << (depth + 1)
    cells = np.unique(rng.integers(L // 4, 3 * L // 4, (L ** 3 // 20, 3)), axis=0)
    vals = np.concatenate([rng.normal(0, 1, (len(cells), 27)), rng.uniform(0.5, 12, (len(cells), 1))], 1)
    data, child, pd = build_tree(cells, vals.astype(np.float32), depth)
    shallow = (child == 0) & (pd[:, 1] < depth)[:, None, None, None]
    node, sx, sy, sz = np.nonzero(shallow)
    pick = rng.random(len(node)) < 0.3
    data[node[pick], sx[pick], sy[pick], sz[pick]] = np.concatenate(
        [rng.normal(0, 1, (int(pick.sum()), 27)), rng.uniform(0.05, 0.5, (int(pick.sum()), 1))], 1)
    inv = np.full(3, 0.25, np.float32)
    offset = (0.5 - np.array([0.3, -0.2, 0.1]) * inv).astype(np.float32)
    return PlenOctree(data.astype(np.float16), child, pd, inv, offset, depth, "SH9")
