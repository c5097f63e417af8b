"""PlenOctrees as svox's ``N3Tree`` ``.npz``: the record, save and load, and its leaf lattice.

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
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import DbbError
from ..core.outputs import write_bytes_atomic
from ..core.zips import read_npz
from ..geometry.sh import COLOUR_ACTIVATION

SH_FORMATS = {1: "SH1", 4: "SH4", 9: "SH9", 16: "SH16"}   # data_format by SH coefficients per channel
COLOUR_ACTIVATIONS = ("sigmoid", "relu_shift")            # what the renderers apply to the SH sum
MAX_DEPTH = 10      # a 2048^3 leaf lattice: the renderer's brick grid of deeper trees outgrows memory


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
    def load(cls, path: Path) -> PlenOctree:
        """Read a svox ``.npz`` (ours or svox's), every array checked once (names, dtypes, shapes,
        child offsets, finite values) so a damaged file is one clear :class:`DbbError` naming the
        array instead of a crash or a wrong render later. Trees without a recorded activation
        are svox's own, whose colour activation is sigmoid."""
        return _checked_tree(read_npz(Path(path), "PlenOctree"), Path(path))


def _scalar(a: dict[str, np.ndarray], key: str, path: Path, low: int, high: int) -> int:
    """Integer scalar array ``a[key]`` in [``low``, ``high``]."""
    v = a[key]
    if v.shape != () or not np.issubdtype(v.dtype, np.integer) or not low <= int(v) <= high:
        raise DbbError(f"{path}: {key} must be a whole number in {low}..{high}, not {_shown(v)}")
    return int(v)


def _shown(v: np.ndarray) -> str:
    """An array as a few words: its value when small, else its dtype and shape."""
    if v.size <= 3 and v.dtype.kind in "iufUSb":
        return str(v.tolist())
    return f"{v.dtype} array of shape {v.shape}"


def _vector3(a: dict[str, np.ndarray], key: str, path: Path, positive: bool = False) -> np.ndarray:
    """Three finite (``positive``: and > 0) floats ``a[key]`` (a scalar is taken for all three)."""
    v = a[key]
    ok = v.dtype.kind in "iuf" and v.size in (1, 3)
    f = np.broadcast_to(v.astype(np.float64).reshape(-1), (3,)) if ok else np.zeros(3)
    if not ok or not np.isfinite(f).all() or (positive and not (f > 0).all()):
        rule = "positive " if positive else ""
        raise DbbError(f"{path}: {key} must be 3 finite {rule}numbers, not {_shown(v)}")
    return f.astype(np.float32)


def _checked_tree(a: dict[str, np.ndarray], path: Path) -> PlenOctree:
    """The tree of svox arrays ``a`` read from ``path``, refused (naming the array) unless the
    arrays agree with each other: a renderer walking a bad child offset reads out of bounds."""
    lacking = sorted({"data", "child", "parent_depth", "offset", "depth_limit"} - set(a))
    if lacking or not ({"invradius3", "invradius"} & set(a)):
        raise DbbError(f"{path} is not a svox N3Tree npz (missing {', '.join(lacking or ['invradius3'])})")
    child, data, pd = a["child"], a["data"], a["parent_depth"]
    if not np.issubdtype(child.dtype, np.integer) or child.ndim != 4 or child.shape[1:] != (2, 2, 2) \
            or len(child) == 0:
        raise DbbError(f"{path}: child must be an integer array (nodes, 2, 2, 2) (branching 2), not {_shown(child)}")
    cap = len(child)
    if data.dtype.kind != "f" or data.ndim != 5 or data.shape[1:4] != (2, 2, 2) or len(data) < cap:
        raise DbbError(f"{path}: data must be a float array ({cap} nodes, 2, 2, 2, channels), not {_shown(data)}")
    if not np.issubdtype(pd.dtype, np.integer) or pd.shape != (len(pd), 2) or len(pd) < cap:
        raise DbbError(f"{path}: parent_depth must be an integer array ({cap} nodes, 2), not {_shown(pd)}")
    n = _scalar(a, "n_internal", path, 1, cap) if "n_internal" in a else cap
    depth_limit = _scalar(a, "depth_limit", path, 0, MAX_DEPTH)
    fmt = str(a["data_format"]) if "data_format" in a else "RGBA"
    basis = next((k for k, v in SH_FORMATS.items() if v == fmt), None)
    if basis is None:
        raise DbbError(f"{path}: data_format {fmt[:20]} is not supported (need {'/'.join(SH_FORMATS.values())})")
    if data.shape[-1] != 3 * basis + 1:
        raise DbbError(f"{path}: data has {data.shape[-1]} channels, data_format {fmt} needs {3 * basis + 1}")
    act = str(a["dbb_colour_activation"]) if "dbb_colour_activation" in a else "sigmoid"
    if act not in COLOUR_ACTIVATIONS:
        raise DbbError(f"{path}: dbb_colour_activation {act[:20]} is not one of {', '.join(COLOUR_ACTIVATIONS)}")
    child, data, pd = child[:n], data[:n], pd[:n]
    # Children come after their parent (svox allocates them so): no offset may point back or out.
    node = np.arange(n).reshape(n, 1, 1, 1)
    if ((child < 0) | (node + child.astype(np.int64) >= n)).any():
        raise DbbError(f"{path}: child holds offsets outside the tree's {n} nodes")
    depth = pd[:, 1]
    if depth[0] != 0 or ((depth[1:] < 1) | (depth[1:] > depth_limit)).any():
        raise DbbError(f"{path}: parent_depth holds depths outside 0..depth_limit {depth_limit}")
    if ((pd[1:, 0] < 0) | (pd[1:, 0] >= 8 * n)).any():
        raise DbbError(f"{path}: parent_depth holds parent cells outside the tree's {n} nodes")
    if not np.isfinite(data).all():
        raise DbbError(f"{path}: data holds NaN or infinite values")
    inv = _vector3(a, "invradius3" if "invradius3" in a else "invradius", path, positive=True)
    offset = _vector3(a, "offset", path)
    return PlenOctree(data, child, pd, inv, offset, depth_limit, fmt, act)


def build_tree(cells: np.ndarray, values: np.ndarray, depth: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """N3Tree arrays holding ``values`` (K, C) at leaf cells ``cells`` (K, 3) of the
    2^(depth+1) lattice; everything else is an empty leaf (zeros). The inverse of
    :func:`leaf_cells` for trees whose leaves all sit at ``depth``.

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
