"""Rendering a bundle: the cameras of a transforms-style file, the static and dynamic renderers.

Cameras given to :func:`render_bundle` are in the board frame (the capture's world frame) by
default, or in bundle space (``space="bundle"``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from ..core.device import pick_device
from ..core.errors import DbbError
from ..core.images import to_u8
from ..core.outputs import atomic_dir, empty_dir
from ..core.progress import progress
from ..crops.camera import crop_camera
from ..datasets.transforms import load_cameras
from ..geometry.cameras import Intrinsics
from ..geometry.rays import camera_rays, pixel_grid
from ..geometry.transforms import invert_rigid
from ..geometry.viewpoint import viewpoint
from .manifest import Bundle, open_bundle

SEED = 0                    # dynamic previews: sampled rollouts are seeded, so verify can repeat them


@dataclass(frozen=True)
class View:
    """A camera to render: output name, OpenCV camera-to-world in the board frame, intrinsics."""

    name: str
    c2w: np.ndarray
    intr: Intrinsics


def read_cameras(path: Path, T: np.ndarray | None = None) -> list[View]:
    """Cameras of a transforms-style file (:func:`~..datasets.transforms.load_cameras`), each
    rendered to the basename of its ``file_path`` as a PNG. ``T`` (bundle_from_board): when
    given, the poses are in bundle space and are taken to the board frame."""
    board_from_bundle = invert_rigid(T) if T is not None else np.eye(4)
    views, names = [], set()
    for i, f in enumerate(load_cameras(path)):
        name = f.name + ".png"
        if name in names:
            raise DbbError(f"{path} frame {i}: two frames would both be written as {name}")
        names.add(name)
        views.append(View(name, board_from_bundle @ f.c2w, f.intr))
    return views


class StaticRenderer:
    """Straight RGBA renders of a static bundle's PlenOctree."""

    def __init__(self, tree):
        """``tree``: the bundle's ``plenoctree.npz`` path, or a :class:`~..octree.tree.PlenOctree`
        already read from it."""
        from ..octree.render import TreeRenderer
        from ..octree.tree import PlenOctree

        self.renderer = TreeRenderer(tree if isinstance(tree, PlenOctree) else PlenOctree.load(tree), pick_device())

    def render(self, views: list[View], tick=None) -> list[np.ndarray]:
        out = []
        for v in views:
            out.append(to_u8(self.renderer.render(v.c2w, v.intr)))
            if tick:
                tick()
        return out


def load_stepper(path: Path):
    try:
        return torch.jit.load(str(path), map_location="cpu").eval()
    except (RuntimeError, OSError, ValueError) as e:
        raise DbbError(f"cannot load the TorchScript model {path}: {e}") from None


def read_rgba(path: Path) -> np.ndarray:
    """Straight RGBA uint8 (H, W, 4) of an image file (alpha 255 where it has none)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DbbError(f"cannot read image {path}")
    if img.dtype == np.uint16:
        img = (img // 257).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, 2)
    if img.shape[2] == 3:
        img = np.concatenate([img, np.full(img.shape[:2] + (1,), 255, np.uint8)], 2)
    return cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)


def rgba_tensor(rgba_u8: np.ndarray, size: int) -> torch.Tensor:
    """(1, 4, S, S) float straight RGBA from uint8 (H, W, 4), resized on premultiplied colour."""
    from ..core.images import resize_rgba

    x = resize_rgba(rgba_u8.astype(np.float32) / 255.0, size)
    return torch.from_numpy(np.ascontiguousarray(x)).permute(2, 0, 1)[None].float()


class DynamicRenderer:
    """Rollouts of a dynamic bundle's TorchScript stepper, warped into each camera's image."""

    def __init__(self, b: Bundle):
        m = b.manifest
        self.stepper = load_stepper(b.file(m.model["file"]))
        self.size = int(m.inputs["frame_size"])
        self.fill = float(m.inputs["crop_fill"])
        self.center, self.radius, self.up = m.center, m.radius, np.asarray(m.up, float)
        self.first = read_rgba(b.file(m.inputs["first_frame"]))
        self.first_view = np.asarray(m.inputs["first_view"], np.float32)

    def view_of(self, v: View) -> np.ndarray:
        """[azimuth_deg, elevation_deg, distance_m] of a camera from the object centre."""
        p = viewpoint(v.c2w[:3, 3], self.center, self.up)
        return np.array([p.azimuth_deg, p.elevation_deg, p.distance_m], np.float32)

    @torch.no_grad()
    def frames(self, views: np.ndarray, first: np.ndarray | None = None,
               first_view: np.ndarray | None = None, seed: int = SEED) -> np.ndarray:
        """Model frames (T, S, S, 4) uint8 for viewpoints (T, 3), one step each after the context."""
        from ..dynamic.stepper import rollout

        torch.manual_seed(seed)
        ctx = rgba_tensor(self.first if first is None else first, self.size)
        fv = self.first_view if first_view is None else np.asarray(first_view, np.float32)
        vs = torch.from_numpy(np.concatenate([fv[None], np.asarray(views, np.float32)]))[None]
        x = rollout(self.stepper, ctx, vs)[0]
        return to_u8(x.permute(0, 2, 3, 1).numpy())

    def warp(self, crop: np.ndarray, v: View) -> np.ndarray:
        """The model's crop (S, S, 4) uint8 placed into camera ``v``'s image (H, W, 4) uint8.

        The crop is the camera's own view rotated to face the object centre (a homography),
        so each image pixel's ray is turned into the crop camera and looked up there.
        """
        cam = crop_camera(v.c2w, v.intr, self.center, self.radius, self.up, self.size, self.fill)
        d = camera_rays(v.intr, pixel_grid(v.intr.width, v.intr.height)).reshape(-1, 3)
        d = d @ (cam.c2w[:3, :3].T @ v.c2w[:3, :3]).T
        z = d[:, 2]
        ok = z > 1e-6
        zs = np.where(ok, z, 1.0)
        mx = np.where(ok, cam.intr.fx * d[:, 0] / zs + cam.intr.cx, -1e4).astype(np.float32)
        my = np.where(ok, cam.intr.fy * d[:, 1] / zs + cam.intr.cy, -1e4).astype(np.float32)
        f = crop.astype(np.float32) / 255.0
        pm = np.concatenate([f[..., :3] * f[..., 3:], f[..., 3:]], -1)
        H, W = v.intr.height, v.intr.width
        out = cv2.remap(pm, mx.reshape(H, W), my.reshape(H, W), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        a = out[..., 3:]
        rgb = np.where(a > 1e-6, out[..., :3] / np.maximum(a, 1e-6), 0.0)
        return to_u8(np.concatenate([rgb.clip(0, 1), a], -1))


def render_bundle(bundle: Path, cameras: Path, out: Path, first_frame: Path | None = None,
                  space: str = "board", overwrite: bool = False) -> list[Path]:
    """Render one straight RGBA PNG per camera of ``cameras`` into ``out`` (written aside).

    A dynamic bundle steps once per camera, in the file's order, from ``first_frame`` (seen
    from the first camera) or from its stored first frame (seen from its stored viewpoint).
    """
    if space not in ("board", "bundle"):
        raise DbbError("{=space} must be board or bundle")
    with open_bundle(bundle) as b:
        m = b.manifest
        views = read_cameras(cameras, m.T if space == "bundle" else None)
        if first_frame is not None and m.kind == "static":
            raise DbbError("{=first_frame} applies to dynamic bundles only; this bundle is static")
        # The model is read (and checked) before the output folder is made.
        r = StaticRenderer(b.file(m.model["file"])) if m.kind == "static" else DynamicRenderer(b)
        with atomic_dir(Path(out), overwrite or empty_dir(out)) as tmp, progress() as prog:
            task = prog.add_task("render", total=len(views), info=m.kind)
            if isinstance(r, StaticRenderer):
                imgs = r.render(views, lambda: prog.advance(task))
            else:
                vv = np.stack([r.view_of(v) for v in views])
                first = read_rgba(first_frame) if first_frame is not None else None
                crops = r.frames(vv, first, vv[0] if first is not None else None)
                imgs = []
                for c, v in zip(crops, views, strict=True):
                    imgs.append(r.warp(c, v))
                    prog.advance(task)
            for img, v in zip(imgs, views, strict=True):
                if not cv2.imwrite(str(tmp / v.name), cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)):
                    raise DbbError(f"cannot write {tmp / v.name}")
    return [Path(out) / v.name for v in views]
