"""The voxel radiance field: SH basis, contraction, training on a synthetic object, checkpoints."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from dbb_capture.capture.board import BoardSpec
from dbb_capture.geometry.cameras import Intrinsics
from dbb_capture.geometry.transforms import look_at
from dbb_capture.geometry.conventions import opengl_from_opencv
from dbb_capture.datasets.records import Frame, ObjectVolume
from dbb_capture.static.field import (
    Budget,
    FieldConfig,
    TrainState,
    build_ray_bank,
    contract,
    frame_tensors,
    lattice_for_views,
    new_field,
    render_image,
    stage_resolutions,
    train,
)
from dbb_capture.core.metrics import psnr_from_mse
from dbb_capture.geometry.sh import sh_basis


def synthetic_object_frames(folder, n=24, size=32, seed=0):
    """RGBA renders of the synthetic toy from known poses around it (every 8th held out)."""
    import cv2

    from dbb_capture.synth.scene import make_object, render_object_rgba

    model = make_object("static", BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100"), np.random.default_rng(seed))
    c, r = model.bounding_sphere(np.array([0.0]))
    f = size * 1.2
    intr = Intrinsics(size, size, f, f, (size - 1) / 2, (size - 1) / 2)
    dist = 1.1 * r / math.sin(math.atan(0.5 / 1.2))
    rng = np.random.default_rng(seed + 1)
    frames = []
    for i in range(n):
        az, el = 2 * math.pi * i / n + rng.uniform(0, 0.2), rng.uniform(0.15, 1.2)
        eye = c + dist * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), -math.sin(el)])
        c2w = look_at(eye, c, np.array([0, 0, -1.0]))
        p = folder / f"{i:03d}.png"
        cv2.imwrite(str(p), cv2.cvtColor(render_object_rgba(model, intr, c2w, 0.0, samples=2), cv2.COLOR_RGBA2BGRA))
        frames.append(Frame(f"{i:03d}", p, c2w, intr, "test" if i % 8 == 3 else "train"))
    return frames, ObjectVolume(tuple(float(v) for v in c), float(r) * 1.05)


TINY = FieldConfig(res_start=16, res_max=32, batch_rays=512, upsample_at=(0.3,), tv_points=2048)


def _band2(cfg: FieldConfig) -> torch.Tensor:
    """(3 * n_basis,) bool: the SH table's degree-2 columns (each channel's coefficients 4..8)."""
    return (torch.arange(3 * cfg.n_basis) % cfg.n_basis) >= 4


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    folder = tmp_path_factory.mktemp("synth_object")
    frames, vol = synthetic_object_frames(folder, n=16, size=24)
    bank = build_ray_bank([f for f in frames if f.split == "train"], 1, vol)
    torch.manual_seed(0)
    state = TrainState(new_field(TINY, vol, torch.device("cpu")))
    state = train(state, bank, Budget(steps=50), checkpoint=folder / "ckpt.pt")
    return frames, vol, state, folder


def _view_psnr(field, frame, bg):
    o, d, rgba = frame_tensors(frame, 1)
    img = render_image(field, torch.from_numpy(o), torch.from_numpy(d), bg)
    gt = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:]) * np.asarray(bg, np.float32)
    return psnr_from_mse(float(((img - gt) ** 2).mean())), img, rgba


def test_sh_basis_is_orthonormal():
    d = torch.nn.functional.normalize(torch.randn(200_000, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    Y = sh_basis(3, d.double())
    gram = 4 * math.pi * (Y.T @ Y) / d.shape[0]
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=0.03)
    assert sh_basis(0, d[:1]).item() == pytest.approx(0.28209479177387814)


def test_contraction_is_identity_inside_and_bounded():
    x = torch.tensor([[0.3, -0.2, 0.5], [3.0, 0.0, 0.0], [0.0, -1e6, 0.0]])
    y = contract(x)
    assert torch.allclose(y[0], x[0])
    assert y[1, 0].item() == pytest.approx(2 - 1 / 3)
    assert y[2].norm().item() == pytest.approx(2.0, abs=1e-5)


def test_training_learns_the_object_and_its_transparency(trained):
    frames, vol, state, _ = trained
    first, last = state.history[0]["psnr"], state.history[-1]["psnr"]
    assert last > first + 8 and last > 24, (first, last)
    assert state.field.res == 32                               # coarse to fine happened
    for f in [f for f in frames if f.split == "test"]:
        for bg in ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)):
            p, _, _ = _view_psnr(state.field, f, bg)
            assert p > 21, (f.name, bg, p)                     # novel views, both backgrounds
    # True transparency: where the truth is empty the field must be empty too (no haze).
    o, d, rgba = frame_tensors(frames[3], 1)
    img = render_image(state.field, torch.from_numpy(o), torch.from_numpy(d), None)
    empty = rgba[..., 3] < 0.01
    assert img[..., 3][empty].mean() < 0.05


def test_checkpoint_resume_continues(trained, tmp_path):
    frames, vol, state, folder = trained
    loaded = TrainState.load(folder / "ckpt.pt", torch.device("cpu"))
    assert loaded.step == state.step and loaded.field.n_active == state.field.n_active
    f = frames[3]
    a = _view_psnr(state.field, f, (1.0, 1.0, 1.0))[1]
    b = _view_psnr(loaded.field, f, (1.0, 1.0, 1.0))[1]
    np.testing.assert_allclose(a, b, atol=1e-6)
    bank = build_ray_bank(frames[:4], 1, vol)
    more = train(loaded, bank, Budget(steps=state.step + 3))
    assert more.step == state.step + 3


def test_higher_sh_bands_join_at_sh_full_from(tmp_path):
    """Progressive SH: before ``sh_full_from`` only bands 0 and 1 train (band 2 stays exactly
    zero); from there on band 2 trains too."""
    from dataclasses import replace

    frames, vol = synthetic_object_frames(tmp_path, n=8, size=16)
    bank = build_ray_bank(frames, 1, vol)
    band2 = _band2(TINY)
    for full_from, moved in [(1.0, False), (0.5, True)]:
        cfg = replace(TINY, sh_full_from=full_from, upsample_at=())
        state = train(TrainState(new_field(cfg, vol, torch.device("cpu"))), bank, Budget(steps=12))
        sh = state.field.sh.data[:-1]
        assert float(sh[:, ~band2].abs().max()) > 0
        assert (float(sh[:, band2].abs().max()) > 0) == moved, full_from


def test_final_steps_fine_tune_what_the_tree_renders(trained):
    """From ``nearest_from`` on, samples read the nearest lattice point (the tree's piecewise
    constant leaves), so the baked tree renders what the field learned; a trilinear field's
    tree does not (26 dB between field and tree on this toy when trained without the phase)."""
    from dbb_capture.octree.render import TreeRenderer, bake

    frames, _, state, folder = trained
    assert state.field.nearest
    assert TrainState.load(folder / "ckpt.pt", torch.device("cpu")).field.nearest
    rend = TreeRenderer(bake(state.field), torch.device("cpu"))
    f = frames[3]
    _, img_field, _ = _view_psnr(state.field, f, (1.0, 1.0, 1.0))
    img_tree = rend.render(f.c2w, f.intr, (1.0, 1.0, 1.0))
    assert psnr_from_mse(float(((img_field - img_tree) ** 2).mean())) > 31


def test_scene_mode_fits_an_opaque_rgb_view(tmp_path):
    frames, vol = synthetic_object_frames(tmp_path, n=6, size=16)
    cfg = FieldConfig(mode="scene", res_start=16, res_max=16, batch_rays=256, tv_points=512)
    bank = build_ray_bank(frames, 1, vol, mode="scene")
    bank.rgba[:, :3] = bank.rgba[:, :3] * bank.rgba[:, 3:] + (1 - bank.rgba[:, 3:]) * torch.tensor([0.2, 0.5, 0.8])
    bank.rgba[:, 3] = 1                                          # a scene: every pixel opaque
    state = train(TrainState(new_field(cfg, vol, torch.device("cpu"))), bank, Budget(steps=40))
    assert state.history[-1]["psnr"] > state.history[0]["psnr"] + 5


@pytest.mark.parametrize("nearest,sh_active", [(False, 2), (True, 2), (False, 1)])
def test_cpu_kernel_matches_autograd(nearest, sh_active):
    """The numba training step renders the same colours and adds the same gradients as
    render_rays + MSE + autograd, on a random field with inactive points and degree-2 SH,
    interpolating trilinearly or (the tree fine-tuning phase) reading the nearest point, and
    with the opacity prior; with the degree-2 band not yet in use (progressive SH), it neither
    colours nor gets a gradient."""
    from dbb_capture.static.field import (VoxelField, cpu_photometric_step, cpu_tv_step, opacity_prior, render_rays,
                                    tv_loss)

    torch.manual_seed(3)
    cfg = FieldConfig(res_start=12, res_max=12, sh_degree=2)
    res = 12
    active = torch.randperm(res ** 3)[: int(0.7 * res ** 3)].sort().values
    n = active.numel()
    vol = ObjectVolume((0.1, -0.2, 0.3), 0.5)
    field = VoxelField(cfg, vol, res, torch.device("cpu"), active,
                       torch.randn(n, 1) * 2 + 3, torch.randn(n, 3 * cfg.n_basis))
    field.nearest = nearest
    field.sh_active = sh_active
    B = 64
    d = torch.nn.functional.normalize(torch.randn(B, 3), dim=-1)
    o = torch.tensor(vol.center) - 1.2 * d + 0.3 * torch.randn(B, 3) * 0.5
    bg = torch.rand(B, 3)
    target = torch.rand(B, 3)

    beta = 0.05 if nearest else 0.0       # the opacity prior, checked in one of the two runs
    # Per-ray weights (robust training), checked in the other run.
    ray_w = None if nearest else torch.rand(B)
    out = render_rays(field, o, d, bg, jitter=False)
    se = ((out.rgb - target) ** 2).mean(-1)
    ref = se.mean()
    ((se * ray_w).mean() if ray_w is not None else ref + beta * opacity_prior(out.alpha)).backward()
    g_dens, g_sh = field.density.grad.clone(), field.sh.grad.clone()
    field.density.grad.zero_()
    field.sh.grad.zero_()

    import numba

    threads = numba.get_num_threads()
    numba.set_num_threads(1)    # exact comparison: no concurrent additions into one row
    try:
        mse, rendered = cpu_photometric_step(field, o, d, bg, target, torch.full((B,), 0.5), beta, ray_w)
    finally:
        numba.set_num_threads(threads)
    assert float(mse) == pytest.approx(float(ref.detach()), rel=1e-4)
    assert np.allclose(rendered[:, :3], out.rgb.detach().numpy(), atol=1e-5)
    assert np.allclose(rendered[:, 3], out.alpha.detach().numpy(), atol=1e-5)
    # The sentinel row (inactive points) is reset every step: the kernel gives it no gradient.
    assert torch.allclose(field.density.grad[:-1], g_dens[:-1], atol=1e-9, rtol=1e-4)
    assert torch.allclose(field.sh.grad[:-1], g_sh[:-1], atol=1e-9, rtol=1e-4)
    assert float(g_dens.abs().sum()) > 0 and float(g_sh.abs().sum()) > 0
    assert torch.equal(field.density.touched[:-1], g_dens[:-1, 0] != 0)
    band2 = _band2(cfg)
    assert (float(field.sh.grad[:, band2].abs().sum()) == 0) == (sh_active < 2)

    # Total variation: the same means and gradients as tv_loss + autograd.
    field.density.grad.zero_()
    field.sh.grad.zero_()
    tvd, tvs = tv_loss(field, 300, torch.Generator().manual_seed(5))
    (cfg.tv_density * tvd + cfg.tv_sh * tvs).backward()
    g_dens, g_sh = field.density.grad.clone(), field.sh.grad.clone()
    field.density.grad.zero_()
    field.sh.grad.zero_()
    d2, s2 = cpu_tv_step(field, 300, torch.Generator().manual_seed(5))
    assert d2 == pytest.approx(float(tvd.detach()), rel=1e-4) and s2 == pytest.approx(float(tvs.detach()), rel=1e-4)
    assert torch.allclose(field.density.grad, g_dens, atol=1e-12, rtol=1e-4)
    assert torch.allclose(field.sh.grad, g_sh, atol=1e-12, rtol=1e-4)

    # Rendering without gradients (render_image's CPU path) agrees with the PyTorch renderer.
    with torch.no_grad():
        ref_img = render_rays(field, o, d, bg)
    img = render_image(field, o[:, None], d[:, None], None)
    a = ref_img.alpha.clamp(0, 1)
    straight = (ref_img.rgb - (1 - a)[:, None] * bg) / a.clamp_min(1e-6)[:, None]
    assert np.allclose(img[:, 0, 3], a.numpy(), atol=1e-5)
    assert np.allclose(img[:, 0, :3], straight.clamp(0, 1).numpy(), atol=1e-4)


def _room(size: int, rng: np.random.Generator) -> np.ndarray:
    """A smooth room behind one view (size, size, 3) uint8: two random colours blended across it."""
    c0, c1 = rng.uniform(20, 235, 3), rng.uniform(20, 235, 3)
    t = np.linspace(0, 1, size)[None, :, None] * np.ones((size, 1, 1))
    return np.round(c0 * (1 - t) + c1 * t).astype(np.uint8)


def test_observed_pixels_over_the_predicted_room_correct_a_bad_matte(tmp_path):
    """Crops that keep the observed pixels and the predicted room (preprocess writes both): the
    field renders over each ray's room and is compared with what the camera saw, so a matte that
    cut holes into the object (alpha 0 on a third of it in each view) does not make the object
    see-through; trained on the matte alone it does."""
    import cv2

    from dbb_capture.datasets.records import load_dataset
    from dbb_capture.static.field import ray_targets

    frames, vol = synthetic_object_frames(tmp_path, n=24, size=24)
    rng = np.random.default_rng(3)
    truth = {}
    for f in frames:
        rgba = cv2.cvtColor(cv2.imread(str(f.image_path), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA)
        truth[f.name] = rgba[..., 3].astype(np.float32) / 255
        room = _room(24, rng)
        a = rgba[..., 3:].astype(np.float32) / 255
        seen = np.round(rgba[..., :3] * a + room * (1 - a)).astype(np.uint8)
        bad = rgba.copy()
        bad[..., 3] = np.where(rng.random((24, 24)) < 0.33, 0, rgba[..., 3])     # holes in the matte
        cv2.imwrite(str(tmp_path / f"{f.name}.png"), cv2.cvtColor(bad, cv2.COLOR_RGBA2BGRA))
        cv2.imwrite(str(tmp_path / f"seen_{f.name}.png"), cv2.cvtColor(seen, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(tmp_path / f"room_{f.name}.png"), cv2.cvtColor(room, cv2.COLOR_RGB2BGR))
    doc = {"camera_model": "OPENCV", "object": {"center": list(vol.center), "radius": vol.radius}, "frames": [
        {"file_path": f"{f.name}.png", "observed_path": f"seen_{f.name}.png", "background_path": f"room_{f.name}.png",
         "transform_matrix": opengl_from_opencv(f.c2w).tolist(), "split": f.split, **f.intr.nerfstudio_fields()}
        for f in frames]}
    (tmp_path / "crops.json").write_text(json.dumps(doc))
    ds = load_dataset(tmp_path)
    assert all(f.observed_path is not None and f.background_path is not None for f in ds.frames)
    bank = build_ray_bank(ds.split("train"), 1, vol)
    assert bank.observed is not None and bank.observed.shape == bank.room.shape == (bank.n, 3)

    def see_through(cfg: FieldConfig) -> float:
        """Mean transparency over the object's core on the held-out views."""
        torch.manual_seed(0)
        st = train(TrainState(new_field(cfg, vol, torch.device("cpu"))), bank, Budget(steps=150))
        out = []
        for f in ds.split("test"):
            o, d, _ = frame_tensors(f, 1)
            a = render_image(st.field, torch.from_numpy(o), torch.from_numpy(d), None)[..., 3]
            out.append(1 - a[truth[f.name] > 0.99].mean())
        return float(np.mean(out))

    matte_only = see_through(TINY)
    observed = see_through(replace(TINY, observed_loss=True))
    assert matte_only > 0.1 and observed < 0.5 * matte_only, (matte_only, observed)
    # Rays where the matte says "room" pick their target: the observed pixel over the room where
    # colour decides, the matte (over a random colour) where it cannot, with probability
    # matte_prior; NaN or a matte that sees any object (alpha >= matte_opaque): the matte.
    rgba = torch.tensor([[0.9, 0.1, 0.1, 0.0]] * 3 + [[0.9, 0.1, 0.1, 0.6]])
    bg = torch.full((4, 3), 0.5)
    seen = torch.tensor([[0.9, 0.1, 0.1], [0.3, 0.3, 0.3], [float("nan")] * 3, [0.9, 0.1, 0.1]])
    room = torch.tensor([[0.2, 0.2, 0.2], [0.3, 0.3, 0.3], [0.2, 0.2, 0.2], [0.2, 0.2, 0.2]])
    matte = rgba[:, :3] * rgba[:, 3:] + (1 - rgba[:, 3:]) * bg
    gen = torch.Generator().manual_seed(0)
    picks = [ray_targets(rgba, bg, seen, room, replace(TINY, observed_loss=True, matte_prior=1.0), gen)
             for _ in range(20)]
    assert all(torch.equal(b[0], room[0]) and torch.equal(t[0], seen[0]) for b, t in picks)   # colour decides
    assert all(torch.equal(t[1], matte[1]) for _, t in picks)           # no colour difference, prior 1: matte
    assert all(torch.equal(b[2:], bg[2:]) and torch.equal(t[2:], matte[2:]) for b, t in picks)
    b, t = ray_targets(rgba, bg, seen, room, TINY, gen)
    assert torch.equal(b, bg) and torch.equal(t, matte)


def test_robust_training_lets_the_views_outvote_a_false_object(tmp_path):
    """Each training view's matte adds a false object (a dark 5x5 patch where the view sees
    only room, at a different place in every view): plain L2 learns it as haze that other
    views see (alpha over the room of held-out views 2-6 times that of clean mattes); with
    robust training the views that see through those places outvote each false patch and
    much of that haze goes. Where the patches land moves the figures a lot (one placement
    keeps 17-75 % of the haze, and one placement's figure moved from pass to fail between
    two machines' float paths), so the bar is on four placements pooled: 36-42 % kept in
    three draws, the bar 65 %.
    The IRLS weights themselves: 1 for unseen rays, falling with the ray's running error."""
    import cv2

    from dbb_capture.static.field import robust_weights

    frames, vol = synthetic_object_frames(tmp_path, n=24, size=24)
    truth = {f.name: cv2.imread(str(f.image_path), cv2.IMREAD_UNCHANGED) for f in frames}

    def with_false_patches(rng: np.random.Generator, tag: str) -> list[Frame]:
        """The frames with a dark 5x5 patch over room pixels of every training view."""
        out = []
        for f in frames:
            bad = truth[f.name].copy()      # BGRA
            if f.split == "train":
                empty = np.argwhere(bad[..., 3] == 0)
                for _ in range(100):
                    y, x = empty[rng.integers(len(empty))]
                    if 4 <= y < 19 and 4 <= x < 19 and (bad[y - 2:y + 3, x - 2:x + 3, 3] == 0).all():
                        break
                bad[y - 2:y + 3, x - 2:x + 3] = (30, 30, 30, 255)
            p = tmp_path / f"bad{tag}_{f.name}.png"
            cv2.imwrite(str(p), bad)
            out.append(replace(f, image_path=p))
        return out

    def room_alpha(cfg: FieldConfig, views: list[Frame]) -> float:
        """Mean alpha over the room (truth alpha < 0.01) of the held-out views."""
        bank = build_ray_bank([f for f in views if f.split == "train"], 1, vol)
        torch.manual_seed(0)
        st = train(TrainState(new_field(cfg, vol, torch.device("cpu"))), bank, Budget(steps=800))
        if cfg.robust_from is not None and cfg.robust_from < 1:
            assert bank.error is not None and not bank.error.isnan().all()
        out = []
        for f in frames:
            if f.split == "test":
                o, d, _ = frame_tensors(f, 1)
                a = render_image(st.field, torch.from_numpy(o), torch.from_numpy(d), None)[..., 3]
                out.append(a[truth[f.name][..., 3] < 3].mean())
        return float(np.mean(out))

    import numba

    threads = numba.get_num_threads()
    numba.set_num_threads(1)    # repeatable: no concurrent additions into one row (Hogwild)
    try:
        clean = room_alpha(TINY, frames)
        rng = np.random.default_rng(3)
        placements = [with_false_patches(rng, str(k)) for k in range(4)]
        l2 = np.array([room_alpha(TINY, v) for v in placements])
        robust = np.array([room_alpha(replace(TINY, robust_from=0.5), v) for v in placements])
    finally:
        numba.set_num_threads(threads)
    assert l2.mean() > 1.6 * clean, (clean, l2)
    assert robust.sum() < 0.65 * l2.sum(), (clean, l2, robust)
    w = robust_weights(torch.tensor([float("nan"), 0.0, 0.01, 1.0]), 0.1)
    assert torch.allclose(w, torch.tensor([1.0, 1.0, 0.5, 1 / 101]))


def test_carving_keeps_the_object_and_clears_what_the_views_see_through(tmp_path):
    """Space carving from the views' alpha: no lattice point inside the true object is carved
    (the footprint and a pixel of slack keep the outline), most of the sphere around it is;
    a point that fewer than ``min_views`` views (or less than ``share`` of those that see it)
    see as empty stays; carving a field drops exactly those points."""
    from dbb_capture.static.field import VoxelField, carve_mask
    from dbb_capture.synth.scene import make_object

    frames, vol = synthetic_object_frames(tmp_path, n=24, size=32)
    bank = build_ray_bank([f for f in frames if f.split == "train"], 1, vol)
    assert bank.views is not None and len(bank.views.alphas) == 21
    res = 32
    cfg = replace(TINY, res_start=res, res_max=res)
    field = VoxelField(cfg, vol, res, torch.device("cpu"))
    pts = field.lattice_points(field.active).numpy().astype(np.float64) * vol.radius + np.asarray(vol.center)
    model = make_object("static", BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100"), np.random.default_rng(0))
    inside = np.zeros(len(pts), bool)
    for c, R, e in model.posed(0.0):
        inside |= np.linalg.norm((pts - c) @ R / np.asarray(e.radii), axis=1) <= 1
    in_sphere = np.linalg.norm(pts - np.asarray(vol.center), axis=1) < vol.radius
    cut = carve_mask(bank.views, pts, field.cell * vol.radius, 0.2)
    assert inside.sum() > 100 and not cut[inside].any()
    assert cut[in_sphere & ~inside].mean() > 0.5
    assert not carve_mask(bank.views, pts, field.cell * vol.radius, 0.2, min_views=len(bank.views.alphas) + 1).any()
    carved = field.carved(bank.views, 0.2)
    assert carved.n_active == int((~cut).sum())
    assert torch.equal(carved.active, field.active[torch.from_numpy(~cut)])


def test_matte_treatments_follow_the_dataset_kind_unless_set():
    """Preprocess crops get carving, robust training and the observed loss; datasets whose alpha
    is the truth do not; a value given explicitly (even "off") is kept."""
    crops = FieldConfig().for_dataset("crops")
    assert (crops.carve_share, crops.robust_from, crops.observed_loss) == (0.1, 0.5, True)
    for kind in ("blender", "transforms"):
        other = FieldConfig().for_dataset(kind)
        assert (other.carve_share, other.robust_from, other.observed_loss) == (0.0, 1.0, False)
    kept = FieldConfig(carve_share=0.0, robust_from=1.0, observed_loss=False).for_dataset("crops")
    assert (kept.carve_share, kept.robust_from, kept.observed_loss) == (0.0, 1.0, False)


def test_lattice_follows_the_pixels_across_the_object():
    """One cell per pixel: a sphere of radius 1 seen from 4 units by a 100 px focal length spans
    2 * 100 * tan(asin(1/4)) = 51.6 px -> 64^3; nearer or sharper views raise it, to 512 at most;
    scene mode (lattice over twice the sphere) doubles it; --downscale shrinks it."""
    vol = ObjectVolume((0.0, 0.0, 0.0), 1.0)
    cam = lambda dist: look_at(np.array([0.0, -dist, 0.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    intr = lambda f: Intrinsics(128, 128, f, f, 64.0, 64.0)
    assert lattice_for_views([(cam(4.0), intr(100.0))], vol, "object") == 64
    assert lattice_for_views([(cam(4.0), intr(100.0)), (cam(2.0), intr(100.0))], vol, "object") == 128
    assert lattice_for_views([(cam(4.0), intr(100.0))], vol, "scene") == 128
    assert lattice_for_views([(cam(4.0), intr(100.0))], vol, "object", downscale=2.0) == 32
    assert lattice_for_views([(cam(1.5), intr(2000.0))], vol, "object") == 512
    assert lattice_for_views([(cam(40.0), intr(100.0))], vol, "object", start=16) == 16


def test_coarse_to_fine_reaches_the_finest_lattice():
    """The default schedule has a stage start for every doubling from 32^3 up to 512^3."""
    cfg = FieldConfig(res_max=512)
    assert stage_resolutions(cfg) == [32, 64, 128, 256, 512]
    assert len(cfg.upsample_at) >= len(stage_resolutions(cfg)) - 1
    assert stage_resolutions(replace(cfg, res_max=96)) == [32, 64, 96]
