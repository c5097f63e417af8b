"""PlenOctrees: bake a field into svox's ``N3Tree`` ``.npz``, load it back, render it as RGBA.

The file is exactly what ``svox.N3Tree.save`` writes (``N3Tree.load`` reads it):
``data`` float16 (capacity, 2, 2, 2, data_dim), ``child`` int32 (capacity, 2, 2, 2) holding
the *relative* offset of the child node (0 = leaf), ``parent_depth`` int32 (capacity, 2)
(packed parent cell ``node * 8 + slot`` and node depth; root depth 0), ``n_internal``,
``n_free``, ``data_dim``, ``depth_limit``, ``geom_resize_fact``, ``invradius3``
(``0.5 / radius`` per axis), ``offset`` (``0.5 - center * invradius``), ``data_format``
(``"SH9"`` for SH degree 2, ``"SH16"`` for degree 3). A node at depth k splits its cube in
2x2x2 cells, so leaves at depth ``depth_limit`` make a 2^(depth_limit+1) lattice (depth 8: 512).

Leaf channels are ``[R basis.., G basis.., B basis.., sigma]``; ``sigma`` is density per
world unit (metres for captures); colour is ``sigmoid(SH . coeffs)`` as svox does it. We
add ``dbb_colour_activation`` (``"sigmoid"``) and ``dbb_density_units`` keys; svox ignores them.
"""

from __future__ import annotations

import io
import itertools
import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..geometry.cameras import Intrinsics
from ..core.errors import DbbError
from ..geometry.sh import COLOUR_ACTIVATION, sh_basis
from ..static.field import VoxelField
from ..core.outputs import write_bytes_atomic

_FORMATS = {1: "SH1", 4: "SH4", 9: "SH9", 16: "SH16"}


@dataclass
class PlenOctree:
    """An N3Tree (branching 2) as flat arrays, exactly the svox fields."""

    data: np.ndarray          # (n, 2, 2, 2, data_dim) float16
    child: np.ndarray         # (n, 2, 2, 2) int32, relative index of the child node, 0 = leaf
    parent_depth: np.ndarray  # (n, 2) int32
    invradius: np.ndarray     # (3,) float32: world -> tree scale per axis
    offset: np.ndarray        # (3,) float32: tree = offset + world * invradius, in [0, 1]^3
    depth_limit: int
    data_format: str          # "SH9" ...
    colour_activation: str = COLOUR_ACTIVATION

    @property
    def n_nodes(self) -> int:
        return int(self.child.shape[0])

    @property
    def data_dim(self) -> int:
        return int(self.data.shape[-1])

    @property
    def sh_degree(self) -> int:
        return int(round(math.sqrt((self.data_dim - 1) // 3))) - 1

    @property
    def center(self) -> np.ndarray:
        """World centre of the tree's cube (3,)."""
        return (0.5 - self.offset) / self.invradius

    @property
    def radius(self) -> np.ndarray:
        """Half side of the tree's cube per axis (3,)."""
        return 0.5 / self.invradius

    def n_leaves_with_data(self) -> int:
        return int(((self.child == 0) & (self.data[..., -1] > 0)).sum())

    # ---- persistence ----------------------------------------------------------------------
    def save(self, path: Path, compress: bool = True) -> int:
        """Write the svox ``.npz`` atomically; returns its size in bytes."""
        buf = io.BytesIO()
        arrays = {
            "data_dim": np.int64(self.data_dim), "child": self.child.astype(np.int32),
            "parent_depth": self.parent_depth.astype(np.int32),
            "n_internal": np.int64(self.n_nodes), "n_free": np.int64(0),
            "invradius3": self.invradius.astype(np.float32), "offset": self.offset.astype(np.float32),
            "depth_limit": np.int64(self.depth_limit), "geom_resize_fact": np.float64(1.0),
            "data": self.data.astype(np.float16), "data_format": np.array(self.data_format),
            "dbb_colour_activation": np.array(self.colour_activation),
            "dbb_density_units": np.array("per world unit"),
        }
        (np.savez_compressed if compress else np.savez)(buf, **arrays)
        write_bytes_atomic(Path(path), buf.getvalue())
        return len(buf.getvalue())

    @classmethod
    def load(cls, path: Path) -> "PlenOctree":
        """Read a svox ``.npz`` (ours or svox's). Trees without a recorded activation are
        svox's own, whose colour activation is sigmoid."""
        try:
            z = np.load(Path(path))
        except (OSError, ValueError) as e:
            raise DbbError(f"cannot read PlenOctree {path}: {e}") from None
        need = {"data", "child", "parent_depth", "offset", "depth_limit"}
        if not need <= set(z.files) or not ({"invradius3", "invradius"} & set(z.files)):
            raise DbbError(f"{path} is not a svox N3Tree npz (missing {sorted(need - set(z.files))})")
        child = z["child"]
        if child.ndim != 4 or child.shape[1:] != (2, 2, 2):
            raise DbbError(f"{path}: only branching factor 2 trees are supported")
        n = int(z["n_internal"]) if "n_internal" in z.files else child.shape[0]
        inv = z["invradius3"] if "invradius3" in z.files else np.full(3, float(z["invradius"]))
        fmt = str(z["data_format"]) if "data_format" in z.files else "RGBA"
        act = str(z["dbb_colour_activation"]) if "dbb_colour_activation" in z.files else "sigmoid"
        if not fmt.startswith("SH"):
            raise DbbError(f"{path}: data_format {fmt} is not supported (need SH1/SH4/SH9/SH16)")
        return cls(z["data"][:n], child[:n], z["parent_depth"][:n], np.asarray(inv, np.float32).reshape(3),
                   np.asarray(z["offset"], np.float32).reshape(3), int(z["depth_limit"]), fmt, act)


# ---- baking -----------------------------------------------------------------------------------

def build_tree(cells: np.ndarray, values: np.ndarray, depth: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """N3Tree arrays holding ``values`` (K, C) at leaf cells ``cells`` (K, 3) of the
    2^(depth+1) lattice; everything else is an empty leaf (zeros).

    Returns (data (n, 2, 2, 2, C) float32, child (n, 2, 2, 2) int32 relative, parent_depth (n, 2)).
    Nodes are numbered breadth first, each depth sorted by position.
    """
    cells = np.asarray(cells, np.int64)
    C = values.shape[1]
    keys_by_depth = []          # sorted unique node keys per depth
    for k in range(depth + 1):
        q = cells >> (depth + 1 - k)          # node coordinates at depth k (2^k per axis)
        keys_by_depth.append(np.unique((q[:, 0] << (2 * k)) | (q[:, 1] << k) | q[:, 2])
                             if len(cells) else np.zeros(0, np.int64))
    keys_by_depth[0] = np.zeros(1, np.int64)  # the root exists even for an empty tree
    starts = np.cumsum([0] + [len(k) for k in keys_by_depth])
    n = int(starts[-1])
    data = np.zeros((n, 2, 2, 2, C), np.float32)
    child = np.zeros((n, 2, 2, 2), np.int32)
    parent_depth = np.zeros((n, 2), np.int32)
    for k in range(1, depth + 1):
        keys = keys_by_depth[k]
        q = np.stack([keys >> (2 * k), (keys >> k) & ((1 << k) - 1), keys & ((1 << k) - 1)], -1)
        pq = q >> 1
        km1 = k - 1
        pkeys = (pq[:, 0] << (2 * km1)) | (pq[:, 1] << km1) | pq[:, 2]
        pidx = starts[km1] + np.searchsorted(keys_by_depth[km1], pkeys)
        idx = starts[k] + np.arange(len(keys))
        s = q & 1
        child[pidx, s[:, 0], s[:, 1], s[:, 2]] = (idx - pidx).astype(np.int32)
        parent_depth[idx, 0] = pidx * 8 + s[:, 0] * 4 + s[:, 1] * 2 + s[:, 2]
        parent_depth[idx, 1] = k
    if len(cells):
        q = cells >> 1
        keys = (q[:, 0] << (2 * depth)) | (q[:, 1] << depth) | q[:, 2]
        nidx = starts[depth] + np.searchsorted(keys_by_depth[depth], keys)
        s = cells & 1
        data[nidx, s[:, 0], s[:, 1], s[:, 2]] = values
    return data, child, parent_depth


def default_depth(field: VoxelField) -> int:
    """Tree depth whose leaf lattice matches the field's (capped at 8, i.e. 512^3)."""
    return int(min(8, max(1, round(math.log2(field.res)) - 1)))


PRUNE_WEIGHT = 0.005  # bake's default weight-pruning threshold (see prune_by_weight)


@torch.no_grad()
def bake(field: VoxelField, depth: int | None = None, alpha_min: float = 0.03, max_cut: float = 0.3,
         supersample: int = 1, chunk: int = 1 << 18,
         cameras: Sequence[tuple[np.ndarray, Intrinsics]] | None = None,
         prune_weight: float = PRUNE_WEIGHT) -> PlenOctree:
    """Bake the field's inner object volume into a :class:`PlenOctree`.

    Leaves sit at the 2^(depth+1) lattice over the object's cube; cells whose centre lies
    outside the object sphere are trimmed, so are cells whose density is haze: opacity
    across 1/256 of the object's diameter (a cell's side at depth 7) under ``alpha_min``,
    but never more than the ``max_cut`` faintest of the cells with any opacity (1e-3 over
    the cell). Fixing the length keeps the cut the same at every depth. On lego and the
    synthetic object a 0.02 cut dropped 21-27% of the leaves (rays cross them, so they cost
    render time) and held-out PSNR rose 0.06-0.56 dB (docs/benchmarks.md). The fields fit the
    mattes' fringe with faint cells just outside the outline: re-baking the same runs at 0.03
    gained +0.2-0.3 dB on white on two 640x480 captures and +0.01 on lego; past ~0.04 the cut
    reaches the outline's own cells (0.1: -3.5 dB).
    Density is averaged over ``supersample``^3 points per cell (default 1: the centre; on a
    20-minute lego run the centre gave 28.18 dB held out against 27.92 for the 2^3 average,
    which smears the field's thin surfaces); SH coefficients are taken at the centre.
    With ``cameras`` (the training views: (c2w, intrinsics) pairs) the tree is then
    weight-pruned (:func:`prune_by_weight` at ``prune_weight``; 0 turns it off).
    """
    depth = default_depth(field) if depth is None else int(depth)
    if not 1 <= depth <= 8:
        raise DbbError("octree depth must be 1..8")
    L = 1 << (depth + 1)
    dev = field.device
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
    s = supersample
    offs = ((torch.stack(torch.meshgrid(*(torch.arange(s),) * 3, indexing="ij"), -1).view(-1, 3).float()
             + 0.5) / s - 0.5).to(dev) * size
    sig = torch.cat([field.query((centres[i:i + chunk, None, :] + offs[None]).view(-1, 3))[0]
                     .view(-1, offs.shape[0]).mean(-1) for i in range(0, centres.shape[0], chunk)])
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
    r = field.radius
    inv = np.full(3, 0.5 / r, np.float32)
    offset = (0.5 - np.asarray(field.volume.center) * inv).astype(np.float32)
    fmt = _FORMATS[field.cfg.n_basis]
    tree = PlenOctree(np.clip(data, -65000, 65000).astype(np.float16), child, pd, inv, offset, depth, fmt)
    if cameras is not None:
        tree = prune_by_weight(tree, cameras, prune_weight)
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
    from ..geometry.cameras import scaled_intrinsics

    r = TreeRenderer(tree, t_min=floor, w_min=floor, threads=threads, backend="numba")
    cells, rows = r._np["cells"], r._np["rows"]
    best = np.zeros(max(1, len(cells)), np.float32)
    for c2w, intr in cameras:
        c2w = np.asarray(c2w, np.float64)
        down = max(r._leaf_pixels(c2w, intr) / leaf_px, math.sqrt(intr.width * intr.height / max_pixels))
        dirs, pixel = r._camera_dirs(scaled_intrinsics(intr, down))
        ws: list[np.ndarray] = []
        r._trace_np(c2w[None, :3, 3], dirs, c2w[:3, :3], pixel, wmax=ws)
        np.maximum(best, np.max(ws, axis=0), out=best)
    return cells, rows, best[:len(cells)]


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


# ---- rendering --------------------------------------------------------------------------------

BRICK = 8   # leaves per brick side in the renderer's two-level lookup
_RAY_CHUNK = 4096   # rays per work item of the CPU renderer's threads (64 8x8 tiles)
_EAGER_PIXELS = 2.0  # leaves narrower than this many pixels: most are met by one ray only
_POOL: ThreadPoolExecutor | None = None
_NO_WEIGHTS = np.zeros(0, np.float32)   # trace_rays' "colour, do not record weights"


def _pool(threads: int) -> ThreadPoolExecutor:
    """The process's render threads (grown on demand, never shrunk)."""
    global _POOL
    if _POOL is None or _POOL._max_workers < threads:
        _POOL = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="dbb-octree")
    return _POOL


def _cores() -> int:
    """CPU cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _forget_pool() -> None:
    """A forked child has none of its parent's threads: it must start its own pool."""
    global _POOL
    _POOL = None


os.register_at_fork(after_in_child=_forget_pool)


def leaf_cells(tree: PlenOctree) -> tuple[np.ndarray, np.ndarray]:
    """Cells of the finest lattice (2^(depth_limit+1) per axis) covered by leaves that hold
    density, and the data row (node * 8 + slot) each one reads: (K, 3) int64, (K,) int64.

    Shallower leaves are expanded over the fine cells they cover.
    """
    n = tree.n_nodes
    D = tree.depth_limit
    depth = tree.parent_depth[:, 1].astype(np.int64)
    corner = np.zeros((n, 3), np.int64)              # node position at its own depth
    for k in range(1, int(depth.max(initial=0)) + 1):
        ids = np.nonzero(depth == k)[0]
        par = tree.parent_depth[ids, 0].astype(np.int64)
        pnode, slot = par // 8, par % 8
        bits = np.stack([(slot >> 2) & 1, (slot >> 1) & 1, slot & 1], -1)
        corner[ids] = 2 * corner[pnode] + bits
    is_leaf = (tree.child == 0) & (tree.data[..., -1].astype(np.float32) > 0)
    node, sx, sy, sz = np.nonzero(is_leaf)
    s = np.stack([sx, sy, sz], -1)
    rows = node * 8 + sx * 4 + sy * 2 + sz
    kd = depth[node]
    cells, rws = [], []
    for k in np.unique(kd):
        m = kd == k
        c = (2 * corner[node[m]] + s[m]) << (D - k)  # first fine cell covered
        span = 1 << (D - k)
        if span == 1:
            cells.append(c)
            rws.append(rows[m])
            continue
        g = np.stack(np.meshgrid(*(np.arange(span),) * 3, indexing="ij"), -1).reshape(-1, 3)
        cells.append((c[:, None, :] + g[None]).reshape(-1, 3))
        rws.append(np.repeat(rows[m], len(g)))
    if not cells:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    return np.concatenate(cells), np.concatenate(rws)


class TreeRenderer:
    """RGBA ray casting through a :class:`PlenOctree`, on the CPU or with PyTorch on any device.

    The tree's dense leaves are indexed through two levels (a brick grid of 8^3-leaf bricks,
    then the brick), which answers "which leaf holds this point" in two lookups.

    ``backend="numba"`` (the default on the CPU, :mod:`.octree_cpu`) walks every ray exactly
    cell by cell, integrates each leaf over the length the ray spends in it, skips empty
    8^3-leaf bricks (whole empty cubes of them at once) and stops a ray once its
    transmittance is under ``t_min``; ``threads`` threads (default: the usable cores) share
    the rays.
    ``backend="torch"`` (the default on CUDA) is vectorized PyTorch: a coarse pass finds, per
    ray, the stretch that crosses occupied bricks; the fine pass samples it every ``step``
    leaves in chunks of ``chunk_samples``, composites front to back
    (``alpha = 1 - exp(-sigma * step)``) and drops rays under ``t_min`` after each chunk.

    The numba walk evaluates SH colour only for leaves whose weight (transmittance times
    alpha) reaches ``w_min``; the skipped weight is shared out over the evaluated colours,
    so alpha stays exact. Defaults ``w_min`` 5e-3 and ``t_min`` 1e-2: lego frames are 50 dB
    from rendering every leaf to transmittance 1e-4 (1e-3 / 1e-3: 64 dB) and held-out PSNR
    moves 0.03 dB, while a 800^2 frame costs ~15% less (docs/benchmarks.md).
    For a camera, each leaf is coloured once per frame (see :meth:`_trace_np`).
    """

    def __init__(self, tree: PlenOctree, device: torch.device | str = "cpu", t_min: float = 1e-2,
                 chunk_samples: int = 48, backend: str = "auto", step: float = 0.5, w_min: float = 5e-3,
                 threads: int | None = None):
        if tree.colour_activation not in ("sigmoid", "relu_shift"):
            raise DbbError(f"unknown colour activation {tree.colour_activation!r}")
        self.tree = tree
        self.device = torch.device(device)
        if backend == "auto":
            backend = "numba" if self.device.type == "cpu" else "torch"
        if backend not in ("numba", "torch") or (backend == "numba" and self.device.type != "cpu"):
            raise DbbError(f"renderer backend {backend!r} is not available on {self.device}")
        self.backend = backend
        self.t_min = t_min
        self._w_eps = w_min
        self.threads = int(threads) if threads else _cores()
        self._lock = threading.Lock()
        self.K = chunk_samples
        self.step = float(step)
        self.L = 1 << (tree.depth_limit + 1)
        self.degree = tree.sh_degree
        self.n_basis = (self.degree + 1) ** 2
        cells, rows = leaf_cells(tree)
        nb = max(1, self.L // BRICK)
        bc = cells // BRICK
        bkey = (bc[:, 0] * nb + bc[:, 1]) * nb + bc[:, 2]
        ub, binv = np.unique(bkey, return_inverse=True)
        grid = np.full(nb ** 3, -1, np.int32)
        grid[ub] = np.arange(len(ub), dtype=np.int32)
        self.nb = nb
        self._grid = grid
        self._cam_cache: tuple = (None, None)
        self._colour_cache: np.ndarray | None = None   # packed leaf RGB + frame stamp, shared
        self._frame = 0
        if backend == "numba":
            self._np = self._cpu_tables(cells, rows, ub, binv)
            self.inv = tree.invradius.astype(np.float64)
            self.offset = tree.offset.astype(np.float64)
            return
        uniq, inv = np.unique(rows, return_inverse=True)
        table = np.full((max(1, len(ub)), BRICK ** 3), -1, np.int32)
        lc = cells % BRICK
        table[binv, (lc[:, 0] * BRICK + lc[:, 1]) * BRICK + lc[:, 2]] = inv.astype(np.int32)
        self.data = torch.from_numpy(tree.data.reshape(-1, tree.data_dim)[uniq].astype(np.float32)).to(self.device)
        self.bricks = torch.from_numpy(grid).to(self.device)
        self.table = torch.from_numpy(table.reshape(-1)).to(self.device)
        self.inv = torch.from_numpy(tree.invradius.astype(np.float32)).to(self.device)
        self.offset = torch.from_numpy(tree.offset.astype(np.float32)).to(self.device)

    def _cpu_tables(self, cells: np.ndarray, rows: np.ndarray, ub: np.ndarray, binv: np.ndarray) -> dict:
        """Arrays of the numba kernel (see :func:`.octree_cpu.trace_rays`) for fine cells (K, 3)
        reading data ``rows`` (K,) and lying in bricks ``binv`` (K,) of the ``ub`` occupied ones.

        Colour rows are stored brick by brick, so the leaves a ray bundle meets share cache
        lines; each leaf's density and row share 8 bytes of a dense per-brick table (0 = empty).
        """
        from scipy.ndimage import distance_transform_cdt

        g = self.tree.data.reshape(-1, self.tree.data_dim)
        empty = (self._grid < 0).reshape((self.nb,) * 3)
        skip = np.full(empty.shape, 255, np.uint8)
        if not empty.all():
            skip[...] = np.minimum(distance_transform_cdt(empty, metric="chessboard"), 255)
        lc = cells % BRICK
        slot = binv.astype(np.int64) * BRICK ** 3 + (lc[:, 0] * BRICK + lc[:, 1]) * BRICK + lc[:, 2]
        order = np.argsort(slot, kind="stable")
        n_slots = max(1, len(ub)) * BRICK ** 3
        leaf = np.zeros((n_slots, 2), np.int32)               # [sigma (float32 bits), row]
        leaf[:, 1] = -1
        leaf[slot[order], 1] = np.arange(len(order), dtype=np.int32)
        leaf.view(np.float32)[slot, 0] = g[rows, -1].astype(np.float32)
        # float16 bits as stored, each row padded to whole 64-byte lines and line aligned.
        width = -(-(g.shape[1] - 1) // 32) * 32
        k = max(1, len(rows))
        buf = np.zeros(k * width + 32, np.uint16)
        start = (-buf.ctypes.data % 64) // 2
        coef = buf[start:start + k * width].reshape(k, width)
        if len(rows):
            coef[:, :g.shape[1] - 1] = g[rows[order], :-1].astype(np.float16).view(np.uint16)
        return {"cells": cells[order], "rows": rows[order], "L": self.L, "lo": (cells.min(0) if len(cells) else np.zeros(3)).astype(np.float64),
                "hi": (cells.max(0) + 1 if len(cells) else np.zeros(3)).astype(np.float64),
                "skip": skip.reshape(-1), "bricks": self._grid, "nbrk": self.nb, "leaf": leaf,
                "leaf_sigma": leaf.view(np.float32), "coef": coef, "degree": self.degree,
                "sigmoid": self.tree.colour_activation == "sigmoid"}

    def _trace_np(self, origins: np.ndarray, dirs: np.ndarray, rot: np.ndarray, pixel: np.ndarray | None = None,
                  background: tuple[float, float, float] | None | str = "premultiplied",
                  eager: bool = False, wmax: list[np.ndarray] | None = None) -> np.ndarray:
        """Colours (N, 4 or 3) float32 of rays with the numba kernel; ``dirs`` (N, 3) unit
        directions turned to world by ``rot`` (3, 3), ``origins`` (1 or N, 3) world; ray ``r``
        lands in row ``pixel[r]`` (default ``r``). ``background``: ``"premultiplied"``
        (premultiplied RGBA), ``None`` (straight RGBA) or an RGB to composite on. With one
        origin (a camera), leaf colours are cached per frame; ``eager`` prefetches every met
        leaf's SH row (see :func:`.octree_cpu.trace_rays`), which changes only the speed.
        With ``wmax`` (a list) nothing is coloured: each thread appends the largest weight
        its rays gave each leaf, (K,) float32 in the order of ``self._np["cells"]``.

        Ranges of ``_RAY_CHUNK`` rays go to ``self.threads`` threads, each pulling the next
        range when it is done, so a thread that the OS pauses does not hold the frame up.
        """
        from .kernels import FRAME_MAX, trace_rays

        n = dirs.shape[0]
        mode = 0 if isinstance(background, str) else (1 if background is None else 2)
        bg = np.asarray(background if mode == 2 else (0.0, 0.0, 0.0), np.float64)
        out = np.empty((n, 3 if mode == 2 else 4), np.float32)
        pixel = np.arange(n) if pixel is None else pixel
        g = self._np
        workers = max(1, min(self.threads, -(-n // _RAY_CHUNK)))
        frame = 0
        cache = np.zeros((1, 1), np.int64)
        if origins.shape[0] == 1 and wmax is None:
            if self._colour_cache is None:
                self._colour_cache = np.zeros((g["coef"].shape[0], 1), np.int64)
                self._frame = 0
            if self._frame >= FRAME_MAX:                 # stamps are 16 bits
                self._colour_cache[:] = 0
                self._frame = 0
            self._frame += 1
            frame = self._frame
            cache = self._colour_cache
        args = (np.ascontiguousarray(origins, np.float64), np.ascontiguousarray(dirs, np.float32),
                np.ascontiguousarray(rot, np.float64), self.inv, self.offset, g["L"], g["lo"], g["hi"],
                g["skip"], g["bricks"], g["nbrk"], g["leaf"], g["leaf_sigma"], g["coef"],
                g["degree"], g["sigmoid"], float(self.t_min), self._w_eps)
        starts = itertools.count(0, _RAY_CHUNK)

        def work() -> None:
            # One weight array per thread: racing max updates could lose the larger value.
            w = _NO_WEIGHTS if wmax is None else np.zeros(g["coef"].shape[0], np.float32)
            for s in starts:                 # next() on a count is atomic under the GIL
                if s >= n:
                    break
                trace_rays(*args, s, min(n, s + _RAY_CHUNK), frame, cache, pixel, mode, bg, out, eager, w)
            if wmax is not None:
                wmax.append(w)

        with self._lock:                     # the colour cache is per renderer
            if workers == 1:
                work()
            else:
                for f in [_pool(self.threads).submit(work) for _ in range(workers)]:
                    f.result()
        return out

    def _leaf_pixels(self, c2w: np.ndarray, intr) -> float:
        """Width in pixels of a finest leaf at the tree's centre seen from camera ``c2w``."""
        centre = (0.5 - self.offset) / self.inv
        dist = max(float(np.linalg.norm(c2w[:3, 3] - centre)), 1e-9)
        return float(min(intr.fx, intr.fy) / (self.inv.max() * self.L) / dist)

    def _camera_dirs(self, intr) -> tuple[np.ndarray, np.ndarray]:
        """Unit camera-frame ray directions (H*W, 3) float32 of ``intr`` in 8x8-pixel tile
        order, and each one's pixel (row-major index), cached per intrinsics (undistorting
        every pixel is the dearest part of a small frame). Neighbouring rays meet the same
        leaves, so tiles keep the leaf data they read in cache."""
        from ..geometry.rays import camera_rays, pixel_grid

        if self._cam_cache[0] != intr:
            H, W, s = intr.height, intr.width, 8
            d = camera_rays(intr, pixel_grid(W, H)).reshape(-1, 3)
            idx = np.full((-(-H // s) * s, -(-W // s) * s), -1, np.int64)
            idx[:H, :W] = np.arange(H * W).reshape(H, W)
            order = idx.reshape(idx.shape[0] // s, s, idx.shape[1] // s, s).transpose(0, 2, 1, 3).reshape(-1)
            order = order[order >= 0]
            self._cam_cache = (intr, (np.ascontiguousarray(d[order], np.float32), order))
        return self._cam_cache[1]

    def colour(self, coef: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """RGB (M, 3) from SH coefficients (M, 3*B) seen along world directions (M, 3)."""
        v = torch.bmm(coef.view(-1, 3, self.n_basis), sh_basis(self.degree, d)[:, :, None])[..., 0]
        if self.tree.colour_activation == "sigmoid":
            return torch.sigmoid(v)
        return (v + 0.5).clamp_min(0)      # Plenoxels' relu(x + 0.5)

    def _leaf(self, p: torch.Tensor) -> torch.Tensor:
        """Data row (...,) of lattice points (..., 3) (leaf units), -1 where empty or outside."""
        L, nb = self.L, self.nb
        c = p.floor().int()
        inside = ((c >= 0) & (c < L)).all(-1)
        c = c.clamp(0, L - 1)
        b = c >> 3                                   # BRICK == 8: shifts and masks, not division
        brick = self.bricks[(b[..., 0] * nb + b[..., 1]) * nb + b[..., 2]]
        lc = c & 7
        local = (lc[..., 0] << 6) | (lc[..., 1] << 3) | lc[..., 2]
        row = self.table[(brick.clamp_min(0).long() << 9) | local]
        return torch.where(inside & (brick >= 0), row, torch.full_like(row, -1)).long()

    @torch.no_grad()
    def render_rays(self, origins: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Premultiplied RGB (B, 3) and alpha (B,) of world rays (B, 3) with unit directions."""
        if self.backend == "numba":
            o = origins.detach().cpu().numpy() if torch.is_tensor(origins) else np.asarray(origins)
            d = dirs.detach().cpu().numpy() if torch.is_tensor(dirs) else np.asarray(dirs)
            out = self._trace_np(o.reshape(-1, 3), d.reshape(-1, 3), np.eye(3))
            return torch.from_numpy(out[:, :3]), torch.from_numpy(out[:, 3])
        return self._render_rays_torch(origins, dirs)

    def _render_rays_torch(self, origins: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        dev = self.device
        L = float(self.L)
        dw = dirs.to(dev).float()
        P = (self.offset + origins.to(dev).float() * self.inv) * L        # lattice units
        Dv = dw * self.inv * L                                            # per world unit of t
        B = P.shape[0]
        rgb = torch.zeros(B, 3, device=dev)
        trans = torch.ones(B, device=dev)
        inv_d = 1 / torch.where(Dv.abs() < 1e-9, torch.full_like(Dv, 1e-9), Dv)
        ta, tb = -P * inv_d, (L - P) * inv_d
        t0 = torch.minimum(ta, tb).amax(-1).clamp_min(0)
        t1 = torch.maximum(ta, tb).amin(-1)
        speed = Dv.norm(dim=-1)                                           # lattice units per t
        # Coarse pass: where along each ray are occupied bricks?
        ids = (t1 > t0).nonzero()[:, 0]
        if ids.numel() == 0:
            return rgb, 1 - trans
        dtc = (BRICK / 3) / speed[ids]
        nc = int(math.ceil(float(((t1[ids] - t0[ids]) / dtc).max()))) + 1
        k = torch.arange(nc, device=dev, dtype=torch.float32)
        tc = t0[ids, None] + k[None] * dtc[:, None]
        pc = P[ids, None] + tc[..., None] * Dv[ids, None]
        b = pc.floor().int().clamp(0, self.L - 1) >> 3
        occ = (self.bricks[(b[..., 0] * self.nb + b[..., 1]) * self.nb + b[..., 2]] >= 0) & (tc <= t1[ids, None])
        anyo = occ.any(-1)
        first = torch.where(occ, k[None], torch.full_like(tc, nc)).amin(-1)
        last = torch.where(occ, k[None], torch.full_like(tc, -1)).amax(-1)
        ids, dtc, first, last = ids[anyo], dtc[anyo], first[anyo], last[anyo]
        t = (t0[ids] + (first - 1.5) * dtc).clamp_min(t0[ids])
        t_end = torch.minimum(t0[ids] + (last + 1.5) * dtc, t1[ids])
        # Fine pass: chunks of K samples half a leaf apart, front to back.
        K = self.K
        kk = torch.arange(K, device=dev, dtype=torch.float32)[None] + 0.5
        while ids.numel():
            step = self.step / speed[ids]                                       # world units
            ts = t[:, None] + kk * step[:, None]
            p = P[ids, None] + ts[..., None] * Dv[ids, None]
            row = self._leaf(p)
            row = torch.where(ts < t_end[:, None], row, torch.full_like(row, -1))
            hit = row >= 0
            if bool(hit.any()):
                hr = hit.nonzero()
                ri, si = hr[:, 0], hr[:, 1]
                val = self.data[row[ri, si]]
                tau = torch.zeros_like(ts).index_put((ri, si), val[:, -1].clamp_min(0) * step[ri])
                csum = torch.cumsum(tau, -1)
                Tin = trans[ids, None] * torch.exp(-(csum - tau))
                w = (Tin * (1 - torch.exp(-tau)))[ri, si]
                big = w > 1e-4
                if bool(big.any()):
                    ri2 = ri[big]
                    c = self.colour(val[big, :-1], dw[ids[ri2]])
                    rgb.index_add_(0, ids[ri2], w[big, None] * c)
                trans[ids] = trans[ids] * torch.exp(-csum[:, -1])
            t = t + K * step
            live = (t < t_end) & (trans[ids] > self.t_min)
            ids, t, t_end = ids[live], t[live], t_end[live]
        return rgb, 1 - trans

    @torch.no_grad()
    def render(self, c2w: np.ndarray, intr, background: tuple[float, float, float] | None = None,
               chunk: int = 1 << 16) -> np.ndarray:
        """Straight RGBA (H, W, 4) float32 — or RGB (H, W, 3) on ``background`` — of one camera.

        ``c2w`` is OpenCV camera-to-world (4, 4); ``intr`` an :class:`~.cameras.Intrinsics`.
        """
        if self.backend == "numba":
            c2w = np.asarray(c2w, np.float64)
            dirs, pixel = self._camera_dirs(intr)
            out = self._trace_np(c2w[None, :3, 3], dirs, c2w[:3, :3], pixel,
                                 None if background is None else tuple(float(v) for v in background),
                                 self._leaf_pixels(c2w, intr) < _EAGER_PIXELS)
            return out.reshape(intr.height, intr.width, -1)
        from ..geometry.rays import pixel_rays

        o, d = pixel_rays(intr, c2w)
        H, W = o.shape[:2]
        o = torch.from_numpy(o.reshape(-1, 3))
        d = torch.from_numpy(d.reshape(-1, 3))
        outs = []
        for s in range(0, o.shape[0], chunk):
            rgb, a = self.render_rays(o[s:s + chunk], d[s:s + chunk])
            if background is None:
                outs.append(torch.cat([(rgb / a.clamp_min(1e-6)[:, None]).clamp(0, 1), a[:, None]], -1))
            else:
                bg = torch.tensor(background, dtype=torch.float32, device=rgb.device)
                outs.append((rgb + (1 - a)[:, None] * bg).clamp(0, 1))
        return torch.cat(outs).reshape(H, W, -1).cpu().numpy()
