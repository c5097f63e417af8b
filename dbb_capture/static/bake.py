"""Baking: a trained voxel field becomes a :class:`~..octree.tree.PlenOctree`, then weight-pruned.

The field's SH coefficients and density go to leaves at the tree's lattice over the object's
cube as they are (same basis and activation), density converted to world units.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..core.errors import DbbError
from ..geometry.cameras import Intrinsics, scaled_intrinsics
from ..octree.render import NumbaTreeRenderer
from ..octree.tree import SH_FORMATS, PlenOctree, build_tree
from .field import VoxelField

PRUNE_WEIGHT = 0.005  # bake's default weight-pruning threshold (see prune_by_weight)


def default_depth(field: VoxelField) -> int:
    """Tree depth whose leaf lattice matches the field's (capped at 8, i.e. 512^3)."""
    return int(min(8, max(1, round(math.log2(field.res)) - 1)))


@torch.no_grad()
def bake(field: VoxelField, depth: int | None = None, alpha_min: float = 0.03, max_cut: float = 0.3,
         chunk: int = 1 << 18, cameras: Sequence[tuple[np.ndarray, Intrinsics]] | None = None,
         prune_weight: float = PRUNE_WEIGHT) -> PlenOctree:
    """Bake the field's inner object volume into a :class:`PlenOctree` of ``depth`` (1-8;
    None: :func:`default_depth`).

    Leaves sit at the 2^(depth+1) lattice over the object's cube; cells whose centre lies
    outside the object sphere are trimmed, so are cells whose density is haze: opacity
    across 1/256 of the object's diameter (a cell's side at depth 7) under ``alpha_min``,
    but never more than the ``max_cut`` faintest of the cells with any opacity (1e-3 over
    the cell). Fixing the length keeps the cut the same at every depth. The fields fit the
    mattes' fringe with faint cells just outside the outline, which rays cross (render time);
    past ~0.04 the cut reaches the outline's own cells (docs/decisions.md, ``alpha_min``).
    Density and SH coefficients are read at each cell's centre (an average over the cell
    smears the field's thin surfaces: docs/decisions.md, density at the leaf centre).
    With ``cameras`` (the training views: (c2w, intrinsics) pairs) the tree is then
    weight-pruned (:func:`prune_by_weight` at ``prune_weight``, a depth-7 leaf's weight, halved
    per level deeper; 0 turns it off).
    """
    depth = default_depth(field) if depth is None else int(depth)
    if not 1 <= depth <= 8:
        raise DbbError("octree depth must be 1..8")
    L = 1 << (depth + 1)
    # Candidate cells: near active field points, inside the unit sphere.
    occ = field.occupancy().float().view(1, 1, *(field.res,) * 3)
    if field.cfg.mode == "scene":
        # Lattice spans [-2, 2]: keep the inner [-1, 1] cube, where contraction is the identity.
        a, b = field.res // 4, 3 * field.res // 4
        occ = occ[..., a:b, a:b, a:b]
    cand = F.interpolate(occ, size=(L,) * 3, mode="nearest").view(-1) > 0
    lin = cand.nonzero()[:, 0]
    ijk = torch.stack([lin // (L * L), (lin // L) % L, lin % L], -1)
    size = 2.0 / L                                           # cell side, normalized units
    centres = (ijk.float() + 0.5) * size - 1.0
    inside = centres.norm(dim=-1) <= 1.0
    ijk, centres = ijk[inside], centres[inside]
    sig = torch.cat([field.query(centres[i:i + chunk])[0] for i in range(0, centres.shape[0], chunk)])
    ok = (1 - torch.exp(-sig * size)) >= 1e-3               # no visible opacity in the cell at all
    cut = -math.log1p(-alpha_min) / (2.0 / 256)               # haze, normalized units (radius 1)
    if bool(ok.any()):
        # A field that is faint all over (early in training) is not haze: cut at most max_cut.
        cut = min(cut, float(torch.quantile(sig[ok][:1 << 24], max_cut)))
    keep = (ok & (sig >= cut)).nonzero()[:, 0]
    keep_cells, keep_vals = [], []
    for i in range(0, keep.numel(), chunk):
        k = keep[i:i + chunk]
        _, coef = field.raw_at(centres[k])
        keep_cells.append(ijk[k].cpu())
        keep_vals.append(torch.cat([coef, (sig[k] / field.radius)[:, None]], -1).cpu())
    C = 3 * field.cfg.n_basis + 1
    cells = torch.cat(keep_cells).numpy() if keep_cells else np.zeros((0, 3), np.int64)
    vals = torch.cat(keep_vals).numpy() if keep_vals else np.zeros((0, C), np.float32)
    data, child, pd = build_tree(cells, vals, depth)
    inv = np.full(3, 0.5 / field.radius, np.float32)
    offset = (0.5 - np.asarray(field.volume.center) * inv).astype(np.float32)
    fmt = SH_FORMATS[field.cfg.n_basis]
    tree = PlenOctree(np.clip(data, -65000, 65000).astype(np.float16), child, pd, inv, offset, depth, fmt)
    if cameras is not None:
        # A ray crosses half as much of a leaf one level deeper, so a faint or thin part gives
        # each of its leaves half the weight: a fixed threshold cut visible detail at depth 8
        # (docs/decisions.md, ``--prune-weight``).
        tree = prune_by_weight(tree, cameras, prune_weight * min(1.0, 2.0 ** (7 - depth)))
    return tree


def leaf_max_weights(tree: PlenOctree, cameras: Sequence[tuple[np.ndarray, Intrinsics]], floor: float,
                     leaf_px: float = 2.0, threads: int | None = None, max_pixels: int = 1 << 22
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The largest rendering weight (transmittance times alpha) each leaf with density gets
    from any ray of ``cameras`` ((c2w (4, 4) OpenCV camera-to-world, intrinsics) pairs).

    Each camera is rendered at the size where a finest leaf at the tree's centre is
    ``leaf_px`` pixels wide (whatever its own resolution; at most ``max_pixels``), so every
    leaf in view is crossed by several rays and a leaf's largest weight is that of a ray
    through its middle. Weights up to ``floor`` are not recorded (0) and rays stop once
    their transmittance is under ``floor``: no later leaf can reach it.

    Returns the leaves' fine-lattice cells (K, 3) int64, their data rows (K,) int64 and
    their largest weights (K,) float32.
    """
    r = NumbaTreeRenderer(tree, t_min=floor, w_min=floor, threads=threads)
    best = np.zeros(max(1, len(r.cells)), np.float32)
    for c2w, intr in cameras:
        c2w = np.asarray(c2w, np.float64)
        down = max(r.leaf_pixels(c2w, intr) / leaf_px, math.sqrt(intr.width * intr.height / max_pixels))
        np.maximum(best, r.max_weights(c2w, scaled_intrinsics(intr, down)), out=best)
    return r.cells, r.rows, best[:len(r.cells)]


def prune_by_weight(tree: PlenOctree, cameras: Sequence[tuple[np.ndarray, Intrinsics]], threshold: float,
                    leaf_px: float = 2.0, threads: int | None = None) -> PlenOctree:
    """``tree`` without the leaves that no ray of ``cameras`` gives a weight of ``threshold``
    (PlenOctrees' weight pruning): leaves hidden behind opaque ones and haze that the views
    see through. Rays then meet fewer leaves and more bricks empty out, so renders are
    faster; what the cameras see barely changes (each dropped leaf took under ``threshold``
    of a pixel). Leaves are rebuilt at the finest depth; ``threshold`` <= 0 keeps them all.
    """
    if threshold <= 0:
        return tree
    cells, rows, w = leaf_max_weights(tree, cameras, threshold / 2, leaf_px, threads)
    keep = w >= threshold
    vals = tree.data.reshape(-1, tree.data_dim)[rows[keep]].astype(np.float32)
    data, child, pd = build_tree(cells[keep], vals, tree.depth_limit)
    return PlenOctree(data.astype(np.float16), child, pd, tree.invradius.copy(), tree.offset.copy(),
                      tree.depth_limit, tree.data_format, tree.colour_activation)
