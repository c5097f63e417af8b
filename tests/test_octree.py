"""PlenOctree bake (svox N3Tree npz), load, and the RGBA renderer over the tree."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from dbb_capture.datasets.records import write_transforms
from dbb_capture.static.field import (
    Budget,
    FieldConfig,
    TrainState,
    build_ray_bank,
    frame_tensors,
    new_field,
    render_image,
    train,
)
from dbb_capture.core.metrics import psnr_from_mse
from dbb_capture.octree.render import PlenOctree, TreeRenderer, bake, build_tree, leaf_cells


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


def test_renderer_alpha_of_one_opaque_cube_is_exact():
    """A single leaf cell of density sigma: a ray straight through sees 1 - exp(-sigma * side)."""
    depth = 2                                               # 8^3 lattice over [-1, 1]^3: side 0.25
    sigma = 3.0
    data, child, pd = build_tree(np.array([[4, 4, 4]]), np.array([[2.0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, sigma]],
                                                                   np.float32), depth)
    inv = np.full(3, 0.5, np.float32)                       # radius 1, centre 0
    tree = PlenOctree(data.astype(np.float16), child, pd, inv, (0.5 - 0 * inv).astype(np.float32), depth, "SH4")
    r = TreeRenderer(tree)
    o = torch.tensor([[0.1, 0.1, -3.0], [0.6, 0.6, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    rgb, a = r.render_rays(o, d)
    assert a[0].item() == pytest.approx(1 - math.exp(-sigma * 0.25), abs=0.02)
    assert a[1].item() == 0.0
    # Colour: sigmoid(C0 * 2) for the red channel, sigmoid(0) for green and blue.
    want = torch.sigmoid(torch.tensor([0.28209479 * 2, 0.0, 0.0])) * a[0]
    assert torch.allclose(rgb[0], want, atol=1e-3)


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    from test_fields import synthetic_object_frames

    folder = tmp_path_factory.mktemp("octree")
    frames, vol = synthetic_object_frames(folder, n=12, size=24, seed=2)
    cfg = FieldConfig(res_start=16, res_max=32, batch_rays=512, upsample_at=(0.3,), tv_points=2048)
    torch.manual_seed(0)
    state = train(TrainState(new_field(cfg, vol, torch.device("cpu"))),
                  build_ray_bank(frames, 1, vol), Budget(steps=30))
    tree = bake(state.field)
    return frames, vol, state, tree, folder


def test_bake_save_load_round_trip_in_svox_format(baked):
    frames, vol, state, tree, folder = baked
    path = folder / "tree.npz"
    nbytes = tree.save(path)
    assert nbytes == path.stat().st_size
    z = np.load(path)
    for key in ("data", "child", "parent_depth", "n_internal", "n_free", "data_dim", "depth_limit",
                "geom_resize_fact", "invradius3", "offset", "data_format"):
        assert key in z.files, key
    assert z["data"].dtype == np.float16 and z["child"].dtype == np.int32
    assert z["data"].shape[1:] == (2, 2, 2, 28) and str(z["data_format"]) == "SH9"
    assert int(z["depth_limit"]) == 4                      # 32^3 lattice -> leaves at depth 4
    np.testing.assert_allclose(z["invradius3"], 0.5 / vol.radius, rtol=1e-6)
    np.testing.assert_allclose(z["offset"] + np.asarray(vol.center) * z["invradius3"], 0.5, atol=1e-5)
    assert str(z["dbb_colour_activation"]) == "sigmoid"
    back = PlenOctree.load(path)
    np.testing.assert_array_equal(back.data, tree.data)
    np.testing.assert_array_equal(back.child, tree.child)
    # Trimmed: no leaf with density outside the object sphere.
    cells, _ = leaf_cells(back)
    L = 1 << (back.depth_limit + 1)
    centres = (cells + 0.5) / L * 2 - 1
    assert len(cells) > 0 and (np.linalg.norm(centres, axis=1) <= 1 + 1e-6).all()


def test_tree_renders_like_the_field(baked):
    frames, vol, state, tree, _ = baked
    r = TreeRenderer(tree)
    f = frames[5]
    o, d, _ = frame_tensors(f, 1)
    field_img = render_image(state.field, torch.from_numpy(o), torch.from_numpy(d), (1.0, 1.0, 1.0))
    tree_img = r.render(f.c2w, f.intr, (1.0, 1.0, 1.0))
    assert psnr_from_mse(float(((field_img - tree_img) ** 2).mean())) > 28
    rgba = r.render(f.c2w, f.intr)
    assert rgba.shape == (24, 24, 4) and 0.05 < rgba[..., 3].mean() < 0.9


def test_cli_writes_a_self_describing_run_and_rejects_bad_input(baked, tmp_path):
    import json

    from dbb_capture.cli.train import main
    from dbb_capture.static.run import load_run

    frames, vol, *_ = baked
    write_transforms(tmp_path / "transforms.json", frames, vol)
    run = tmp_path / "run"
    args = ["plenoctree", str(tmp_path), "-o", str(run), "--steps", "8", "--res-max", "16", "--batch-rays", "256"]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    meta = json.loads((run / "run.json").read_text())
    assert meta["mode"] == "object" and meta["tree"]["colour_activation"] == "sigmoid"
    # A transforms dataset's alpha is the truth: no carving or robust training unless asked for.
    assert meta["field"]["carve_share"] == 0.0 and meta["field"]["robust_from"] == 1.0
    assert meta["object"]["radius"] == pytest.approx(vol.radius)
    loaded = load_run(run)
    assert loaded.tree().data_format == "SH9"
    for name in ("tree.npz", "density_grid.npz", "checkpoint.pt", "report/curve.png", "report/metrics.json"):
        assert (run / name).is_file(), name
    g = np.load(run / "density_grid.npz")
    assert g["sigma"].shape == (16, 16, 16)
    assert CliRunner().invoke(main, args).exit_code == 2                     # exists, no --overwrite
    res = CliRunner().invoke(main, args + ["--resume", "--steps", "10"])      # continue the same run
    assert res.exit_code == 0, res.output
    assert json.loads((run / "run.json").read_text())["training"]["steps"] == 10
    assert CliRunner().invoke(main, ["plenoctree", str(tmp_path / "nope"), "-o", str(tmp_path / "r2")]).exit_code == 2
    # Carving and robust training from the command line, recorded with the field's settings.
    more = ["--carve", "0.2", "--robust-from", "0.5"]
    res = CliRunner().invoke(main, args[:3] + [str(tmp_path / "r3")] + args[4:] + more)
    assert res.exit_code == 0, res.output
    field = json.loads((tmp_path / "r3" / "run.json").read_text())["field"]
    assert field["carve_share"] == 0.2 and field["robust_from"] == 0.5
    assert CliRunner().invoke(main, args[:3] + [str(tmp_path / "r4"), "--carve", "2"]).exit_code == 2


def _random_tree(seed: int = 0, depth: int = 3) -> PlenOctree:
    """A tree with random leaves at the finest depth plus shallower leaves (svox trees have
    them) holding density, SH degree 2."""
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
    inv = np.full(3, 0.25, np.float32)                       # radius 2, centre (0.3, -0.2, 0.1)
    offset = (0.5 - np.array([0.3, -0.2, 0.1]) * inv).astype(np.float32)
    return PlenOctree(data.astype(np.float16), child, pd, inv, offset, depth, "SH9")


def test_cpu_kernel_matches_a_dense_torch_reference():
    """The exact cell walk (numba) against the torch sampler at 1/16 leaf steps, for rays from
    outside and inside the tree, axis-parallel ones included, and shallow leaves."""
    tree = _random_tree()
    fast = TreeRenderer(tree)
    ref = TreeRenderer(tree, backend="torch", step=1 / 16, chunk_samples=256)
    assert fast.backend == "numba" and ref.backend == "torch"
    g = torch.Generator().manual_seed(1)
    far = torch.randn(3000, 3, generator=g)
    far = 6 * far / far.norm(dim=-1, keepdim=True)
    inner = torch.rand(1000, 3, generator=g) * 2 - 1
    o = torch.cat([far, inner, torch.tensor([[0.3, -0.2, -5.0], [-5.0, 0.1, 0.2]])])
    target = torch.randn(o.shape[0], 3, generator=g) * 0.6
    d = torch.cat([target[:-2] - o[:-2], torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])])
    d = d / d.norm(dim=-1, keepdim=True)
    rgb_f, a_f = fast.render_rays(o, d)
    rgb_r, a_r = ref.render_rays(o, d)
    assert float(a_f.mean()) > 0.2 and float(a_f[-2:].min()) > 0.5
    mse = float(torch.cat([rgb_f - rgb_r, (a_f - a_r)[:, None]], 1).pow(2).mean())
    assert psnr_from_mse(mse) > 40


def test_cpu_renderer_matches_the_torch_renderer_on_a_trained_tree(baked):
    frames, vol, state, tree, _ = baked
    f = frames[3]
    fast = TreeRenderer(tree).render(f.c2w, f.intr)
    ref = TreeRenderer(tree, backend="torch", step=1 / 8).render(f.c2w, f.intr)
    assert fast.shape == ref.shape == (24, 24, 4)
    assert psnr_from_mse(float(((fast[..., :3] * fast[..., 3:] - ref[..., :3] * ref[..., 3:]) ** 2).mean())) > 40
    assert psnr_from_mse(float(((fast[..., 3] - ref[..., 3]) ** 2).mean())) > 40


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


def test_colour_cache_does_not_leak_between_frames(baked):
    """Leaf colours are cached per frame: a frame after another camera's equals a fresh one."""
    frames, vol, state, tree, _ = baked
    r = TreeRenderer(tree)
    r.render(frames[0].c2w, frames[0].intr)
    again = r.render(frames[6].c2w, frames[6].intr)
    fresh = TreeRenderer(tree).render(frames[6].c2w, frames[6].intr)
    np.testing.assert_array_equal(again, fresh)


def test_threads_and_prefetch_mode_do_not_change_pixels(baked, monkeypatch):
    """Threads share one colour cache and the eager prefetch only reorders memory traffic:
    a frame is the same bit for bit with one thread or several, eager or not."""
    import dbb_capture.octree.render as octree
    from dbb_capture.geometry.cameras import scaled_intrinsics

    frames, vol, state, tree, _ = baked
    intr = scaled_intrinsics(frames[2].intr, 24 / 160)        # 160x160: several work items
    monkeypatch.setattr(octree, "_EAGER_PIXELS", 0.0)
    one = TreeRenderer(tree, threads=1).render(frames[2].c2w, intr)
    monkeypatch.setattr(octree, "_EAGER_PIXELS", 1e9)
    many = TreeRenderer(tree, threads=3).render(frames[2].c2w, intr)
    assert one.shape == (160, 160, 4) and float(one[..., 3].mean()) > 0.05
    np.testing.assert_array_equal(one, many)


_FORKED: dict = {}


def _render_in_child(c2w, intr):
    return _FORKED["renderer"].render(c2w, intr)


def test_renderer_works_in_a_forked_child_after_the_parent_rendered(baked):
    """The render threads do not survive fork; a child must not wait on its parent's pool."""
    import multiprocessing as mp

    from dbb_capture.geometry.cameras import scaled_intrinsics

    frames, vol, state, tree, _ = baked
    intr = scaled_intrinsics(frames[1].intr, 0.25)            # 96x96: more rays than one work item
    r = _FORKED["renderer"] = TreeRenderer(tree, threads=2)
    want = r.render(frames[1].c2w, intr)
    with mp.get_context("fork").Pool(1) as pool:
        got = pool.apply_async(_render_in_child, (frames[1].c2w, intr)).get(timeout=60)
    np.testing.assert_array_equal(got, want)


def _wall_tree() -> tuple[PlenOctree, dict[str, tuple[int, int, int]]]:
    """8^3 lattice over [-1, 1]^3 (leaf side 0.25): an opaque wall at z index 3 (x, y 2..5), a
    leaf behind it, a faint leaf in front of it (alpha 0.002) and a fainter-but-seen one
    (alpha 0.05); red SH1 colour everywhere."""
    side = 0.25
    wall = [(x, y, 3) for x in range(2, 6) for y in range(2, 6)]
    named = {"hidden": (4, 4, 5), "haze": (4, 4, 1), "faint": (3, 3, 1)}
    alphas = {"hidden": 0.9, "haze": 0.002, "faint": 0.05}
    cells = np.array(wall + list(named.values()))
    sig = [-math.log(1 - 0.99999) / side] * len(wall) + [-math.log(1 - alphas[k]) / side for k in named]
    vals = np.zeros((len(cells), 4), np.float32)
    vals[:, 0] = 2.0
    vals[:, 3] = sig
    data, child, pd = build_tree(cells, vals, 2)
    inv = np.full(3, 0.5, np.float32)
    return PlenOctree(data.astype(np.float16), child, pd, inv, np.full(3, 0.5, np.float32), 2, "SH1"), named


def test_weight_pruning_drops_hidden_and_faint_leaves_and_keeps_the_visible_ones():
    from dbb_capture.geometry.cameras import Intrinsics
    from dbb_capture.geometry.transforms import look_at
    from dbb_capture.octree.render import leaf_max_weights, prune_by_weight

    tree, named = _wall_tree()
    f = 16 / math.tan(math.radians(25))
    cams = [(look_at(np.array([dx, dy, -3.0]), np.zeros(3), np.array([0.0, -1.0, 0.0])),
             Intrinsics(32, 32, f, f, 15.5, 15.5)) for dx, dy in ((0.0, 0.0), (0.3, 0.0), (0.0, -0.3))]
    cells, rows, w = leaf_max_weights(tree, cams, 1e-4)
    got = {tuple(c): float(x) for c, x in zip(cells, w)}
    assert got[named["hidden"]] == 0.0                        # behind an opaque wall: never reached
    assert got[named["haze"]] == pytest.approx(0.002, rel=0.05)  # a ray straight through its middle
    assert got[named["faint"]] == pytest.approx(0.05, rel=0.05)
    assert got[(2, 2, 3)] > 0.9
    pruned = prune_by_weight(tree, cams, 0.01)
    kept = {tuple(c) for c in leaf_cells(pruned)[0]}
    assert kept == {c for c in got if c not in (named["hidden"], named["haze"])}
    # What the cameras see barely changes: at most the dropped haze's 0.002 of a pixel.
    a, b = TreeRenderer(tree), TreeRenderer(pruned)
    for c2w, intr in cams:
        assert np.abs(a.render(c2w, intr)[..., 3] - b.render(c2w, intr)[..., 3]).max() < 0.003
    assert prune_by_weight(tree, cams, 0.0) is tree


def test_bake_with_training_cameras_prunes_without_changing_the_views(baked):
    frames, vol, state, tree, _ = baked
    cams = [(f.c2w, f.intr) for f in frames]
    pruned = bake(state.field, cameras=cams, prune_weight=0.02)
    assert pruned.n_leaves_with_data() < tree.n_leaves_with_data()
    a, b = TreeRenderer(tree), TreeRenderer(pruned)
    for f in frames[:4]:
        diff = a.render(f.c2w, f.intr, (1.0, 1.0, 1.0)) - b.render(f.c2w, f.intr, (1.0, 1.0, 1.0))
        assert psnr_from_mse(float((diff ** 2).mean())) > 30


def test_a_tree_finer_than_the_lattice_skips_the_nearest_lookup_phase():
    from dbb_capture.static.run import for_tree_depth

    cfg = FieldConfig(res_max=128)
    assert for_tree_depth(cfg, 7).nearest_from == 1.0           # 256^3 leaves sample the trilinear field
    assert for_tree_depth(cfg, 6).nearest_from == cfg.nearest_from   # 128^3 leaves: the lattice's own cells
    assert for_tree_depth(cfg, None) == cfg
