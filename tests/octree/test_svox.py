"""svox (PlenOctrees' own library) against ours: ``N3Tree.load`` reads the trees we write, its
point queries return our lookup's values bit for bit, and its volume renderer draws the frames
our renderer draws (issue 39). svox runs its pure-PyTorch paths here (no CUDA extension)."""

from __future__ import annotations

import inspect
import textwrap
import warnings
from dataclasses import replace

import numpy as np
import pytest
import torch

from dbb_capture.core.metrics import psnr
from dbb_capture.geometry.cameras import scaled_intrinsics
from dbb_capture.geometry.conventions import opengl_from_opencv
from dbb_capture.octree.render import TorchTreeRenderer, TreeRenderer

from .trees import random_tree

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)       # "CUDA extension could not be loaded": expected
    svox = pytest.importorskip("svox", exc_type=ImportError,
                               reason="svox is not importable (scripts/setup.sh installs svox==0.2.32)")

# svox's PyTorch paths warn on every call that they are slow, and torch.meshgrid (in svox's
# persp_rays) that it wants an indexing argument.
pytestmark = [pytest.mark.filterwarnings("ignore::UserWarning:svox"),
              pytest.mark.filterwarnings("ignore:torch.meshgrid:UserWarning")]

# svox 0.2.32's CPU path of VolumeRenderer.forward ends by adding the background as
# (B, 3) += (B,): a RuntimeError for any batch but 1 or 3 rays.
_CRASH = "out_rgb += light_intensity * self.background_brightness"


@pytest.fixture
def svox_renderer(monkeypatch):
    """``svox.VolumeRenderer`` with its CPU path recompiled from svox's own source with that one
    line broadcast right (``light_intensity[:, None]``), so all else is svox's code; torch on one
    thread while it runs (its loop of small ops loses to thread hand-offs on 2 busy cores)."""
    import svox.renderer

    src = textwrap.dedent(inspect.getsource(svox.VolumeRenderer.forward))
    if _CRASH in src:                                   # a later svox may have fixed it
        ns = dict(vars(svox.renderer))
        fixed = src.replace(_CRASH, "out_rgb += light_intensity[:, None] * self.background_brightness")
        exec(compile(fixed, svox.renderer.__file__, "exec"), ns)  # noqa: S102 - svox's source, one line fixed
        monkeypatch.setattr(svox.VolumeRenderer, "forward", ns["forward"])
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield svox.VolumeRenderer
    torch.set_num_threads(threads)


def test_svox_loads_our_tree_and_its_queries_equal_our_lookup_exactly(tmp_path):
    """``PlenOctree.save`` writes the bake's ``tree.npz`` (a bundle copies it byte for byte);
    svox loads every array of it unchanged, and at 4096 random points of the tree's cube
    (off-centre, radius 2, shallow leaves too) its query returns, bit for bit, the leaf values
    the renderers' lookup finds (all 28 channels: random SH9 colour and density per leaf)."""
    tree = random_tree(seed=3)
    tree.save(tmp_path / "tree.npz")
    st = svox.N3Tree.load(tmp_path / "tree.npz")
    assert (st.N, st.depth_limit, str(st.data_format), st.n_internal) == (2, 3, "SH9", tree.n_nodes)
    for theirs, ours in ((st.data, tree.data), (st.child, tree.child), (st.parent_depth, tree.parent_depth),
                         (st.invradius, tree.invradius), (st.offset, tree.offset)):
        np.testing.assert_array_equal(theirs.detach().numpy(), ours)

    rng = np.random.default_rng(0)
    x = torch.from_numpy(tree.center + tree.radius * rng.uniform(-1, 1, (4096, 3))).float()
    with torch.no_grad():
        theirs, leaf = st(x, cuda=False, want_node_ids=True)   # leaf: node * 8 + slot
    lookup = TorchTreeRenderer(tree, torch.device("cpu"))
    row = lookup._leaf((lookup.offset + x * lookup.inv) * lookup.L)   # the renderers' world -> lattice
    hit = row >= 0
    shallow = tree.parent_depth[leaf[hit].numpy() // 8, 1] < tree.depth_limit
    assert hit.sum() > 1000 and shallow.any() and not shallow.all()
    assert torch.equal(theirs[hit], lookup.data[row[hit]])
    assert not theirs[~hit].any()              # where we find no density, svox's leaf is empty (zeros)


def test_svox_renderer_draws_our_frames(shell, svox_renderer, tmp_path):
    """svox's VolumeRenderer against ours (the numba walk ``dbb-export render`` uses) on a 64x64
    view of the shell, >= 40 dB each (measured 56 dB colour, 53 dB alpha).

    Compositing: svox returns ``sum w_i sigmoid(SH . c_i) + T * background_brightness``, colour
    premultiplied by opacity over a uniform grey; ours with ``background=(b, b, b)`` is the same.
    Brightness 0 gives premultiplied RGB, 1 RGB over white, and ``1 - (white - black)`` alpha.
    Both take density per world unit (svox scales its tree-unit lengths by 1 / invradius) and
    svox's SH basis of the direction: per ray for svox, toward each leaf's centre for ours,
    which (with our stop at transmittance 0.01) is the remaining difference. Trees whose SH
    coefficients are laid out basis-major, or whose basis has one sign flipped, fall far below
    (22 dB, 33 dB): the comparison sees layout and basis."""
    tree, c2w, intr = shell
    W = 64
    # svox's persp_rays: pixel (i, j) looks along ((i - W/2) / fx, -(j - H/2) / fy, -1) in OpenGL
    # camera axes: OpenCV's with the principal point at (W/2, H/2) in pixel-centre coordinates.
    cam = replace(scaled_intrinsics(intr, intr.width / W), cx=W / 2, cy=W / 2)
    tree.save(tmp_path / "tree.npz")
    st = svox.N3Tree.load(tmp_path / "tree.npz")
    gl = torch.from_numpy(opengl_from_opencv(c2w)).float()

    def theirs(brightness: float) -> np.ndarray:
        # svox lengthens each voxel crossing by step_size (tree units; default 1e-3, 3% of a
        # leaf here); ours integrates exact lengths. Every ray of this view enters the cube,
        # which svox's CPU path assumes.
        vr = svox_renderer(st, step_size=1e-5, background_brightness=brightness)
        with torch.no_grad():
            return vr.render_persp(gl, W, W, cam.fx, cam.fy, cuda=False).reshape(W, W, 3).numpy()

    black, white = theirs(0.0), theirs(1.0)

    def scores(t) -> tuple[float, float, float]:
        r = TreeRenderer(t)
        b, w = r.render(c2w, cam, (0.0, 0.0, 0.0)), r.render(c2w, cam, (1.0, 1.0, 1.0))
        return psnr(b, black), psnr(w, white), psnr(1 - (w - b), 1 - (white - black))

    assert 0.2 < float((1 - (white - black)).mean()) < 0.8
    assert min(scores(tree)) >= 40
    sh = tree.data[..., :-1].reshape(tree.data.shape[:-1] + (3, 9))
    basis_major = np.concatenate([sh.swapaxes(-1, -2).reshape(sh.shape[:-2] + (27,)), tree.data[..., -1:]], -1)
    flipped = tree.data.copy()
    flipped[..., 2:27:9] *= -1                             # the z basis function's sign, every channel
    for data in (basis_major, flipped):
        assert max(scores(replace(tree, data=data))[:2]) < 40
