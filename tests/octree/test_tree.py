"""The PlenOctree record: svox's N3Tree layout, its npz file, and the leaf lattice."""

from __future__ import annotations

import numpy as np
import pytest

from dbb_capture.core.errors import DbbError
from dbb_capture.octree.tree import PlenOctree, build_tree, leaf_cells

from .trees import random_tree


def _descend(child, cell, depth):
    """Reference point location: the data row of fine-lattice ``cell`` by walking the tree."""
    node = 0
    for k in range(depth + 1):
        s = [(c >> (depth - k)) & 1 for c in cell]
        rel = child[node, s[0], s[1], s[2]]
        if rel == 0:
            return node, tuple(s)
        node += rel
    raise AssertionError("deeper than depth_limit")


def test_build_tree_structure_matches_svox_layout():
    rng = np.random.default_rng(0)
    depth = 3
    cells = np.unique(rng.integers(0, 16, (40, 3)), axis=0)
    vals = rng.normal(size=(len(cells), 5)).astype(np.float32)
    data, child, pd = build_tree(cells, vals, depth)
    n = child.shape[0]
    assert data.shape == (n, 2, 2, 2, 5) and child.dtype == np.int32 and pd.shape == (n, 2)
    assert (child >= 0).all()                              # relative, forward
    for c, v in zip(cells, vals):
        node, s = _descend(child, c, depth)
        np.testing.assert_array_equal(data[node][s], v)
        assert pd[node, 1] == depth
    # Every non-root node's packed parent cell points back at it.
    for i in range(1, n):
        p, slot = divmod(int(pd[i, 0]), 8)
        assert p + child[p, slot >> 2, (slot >> 1) & 1, slot & 1] == i
    got, rows = leaf_cells(PlenOctree(data.astype(np.float16), child, pd, np.ones(3, np.float32),
                                      np.zeros(3, np.float32), depth, "SH1"))
    pos = vals[:, -1] > 0
    assert {tuple(c) for c in got} == {tuple(c) for c in cells[pos]}
    assert len(got) == len(rows)


def test_leaf_cells_expand_shallow_leaves_over_the_cells_they_cover():
    tree = random_tree(depth=3)
    cells, rows = leaf_cells(tree)
    for c, r in zip(cells[::7], rows[::7]):
        node, s = _descend(tree.child, c, tree.depth_limit)
        assert r == node * 8 + s[0] * 4 + s[1] * 2 + s[2]
    assert len({tuple(c) for c in cells}) == len(cells)        # each fine cell once
    shallow = tree.parent_depth[rows // 8, 1] < tree.depth_limit
    assert shallow.any() and (~shallow).any()


def test_save_load_round_trip_in_svox_format(tmp_path):
    tree = random_tree(seed=1)
    path = tmp_path / "tree.npz"
    nbytes = tree.save(path)
    assert nbytes == path.stat().st_size
    z = np.load(path)
    for key in ("data", "child", "parent_depth", "n_internal", "n_free", "data_dim", "depth_limit",
                "geom_resize_fact", "invradius3", "offset", "data_format"):
        assert key in z.files, key
    assert z["data"].dtype == np.float16 and z["child"].dtype == np.int32
    assert str(z["data_format"]) == "SH9" and str(z["dbb_colour_activation"]) == "sigmoid"
    back = PlenOctree.load(path)
    for k in ("data", "child", "parent_depth", "invradius", "offset"):
        np.testing.assert_array_equal(getattr(back, k), getattr(tree, k))
    assert (back.depth_limit, back.data_format, back.sh_degree) == (3, "SH9", 2)
    np.testing.assert_allclose(back.center, [0.3, -0.2, 0.1], atol=1e-6)
    np.testing.assert_allclose(back.radius, 2.0)
    assert back.n_leaves_with_data() == tree.n_leaves_with_data() > 0


def test_load_rejects_what_is_not_a_tree(tmp_path):
    np.savez(tmp_path / "other.npz", data=np.zeros(3))
    (tmp_path / "text.npz").write_text("not a zip")
    for name in ("other.npz", "text.npz", "missing.npz"):
        with pytest.raises(DbbError):
            PlenOctree.load(tmp_path / name)


def test_load_refuses_arrays_that_disagree_naming_the_array(tmp_path):
    tree = random_tree(seed=2)
    tree.save(tmp_path / "ok.npz")
    with np.load(tmp_path / "ok.npz") as z:
        good = {k: z[k] for k in z.files}
    bad = {"child": {"child": good["child"] + 10 ** 6}, "data": {"data": np.full_like(good["data"], np.nan)},
           "invradius3": {"invradius3": np.zeros(3, np.float32)}, "depth_limit": {"depth_limit": np.int64(-1)},
           "data_format": {"data_format": np.array("SH5")}, "n_internal": {"n_internal": np.int64(10 ** 9)}}
    for name, change in bad.items():
        np.savez(tmp_path / f"{name}.npz", **(good | change))
        with pytest.raises(DbbError, match=name):
            PlenOctree.load(tmp_path / f"{name}.npz")
    (tmp_path / "empty.npz").write_bytes(b"")
    with pytest.raises(DbbError, match="empty"):
        PlenOctree.load(tmp_path / "empty.npz")
