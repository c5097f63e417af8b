"""The RSSM's view anchor: a PlenOctree fitted to the dynamic capture's own crops (the object's mean
shape and colour; what moves comes out soft), baked into a viewpoint atlas of its renders that the
decoder reads at the view it draws.

Along one handheld path each view is seen at one moment only, so an RSSM alone learns "this view
looks like this moment". The field is one 3D object for every moment, so its render at a view it
never saw is still the object from there; the RSSM then has to supply only what changes in time.

The atlas holds premultiplied RGBA renders on an azimuth x elevation grid at the footage's median
distance (the crops are distance-normalized, so distance changes the crop little). Looking a view up
blends the four nearest renders (bilinear in the angles, azimuth wrapping round, elevation held at
the grid's ends): the same images in training and at run time, a few microseconds a frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from ..core.progress import progress
from ..crops.camera import facing_camera
from ..geometry.viewpoint import Viewpoint, eye_at
from ..octree.render import TreeRenderer
from ..octree.tree import PlenOctree

ATLAS_MAX_BYTES = 48 * 2 ** 20      # the atlas's step grows with the frame size to stay under this
ELEVATION_MARGIN_DEG = 10.0         # the grid reaches this far beyond the footage's elevations
ELEVATION_LIMIT_DEG = 85.0          # a crop camera straight above the object has no up


@dataclass(frozen=True)
class AtlasGrid:
    """The atlas's views: ``n_az`` azimuths from 0 deg every ``step_deg`` (all the way round) by
    ``n_el`` elevations from ``el0_deg``, at ``distance_m`` from the object centre."""

    step_deg: float
    n_az: int
    el0_deg: float
    n_el: int
    distance_m: float

    def views(self) -> np.ndarray:
        """(n_el, n_az, 3) float [azimuth_deg, elevation_deg, distance_m], elevation rows first."""
        az = np.arange(self.n_az) * self.step_deg
        el = self.el0_deg + np.arange(self.n_el) * self.step_deg
        a, e = np.meshgrid(az, el)
        return np.stack([a, e, np.full_like(a, self.distance_m)], -1)

    def to_json(self) -> dict:
        return {"step_deg": self.step_deg, "azimuths": self.n_az, "elevation0_deg": self.el0_deg,
                "elevations": self.n_el, "distance_m": round(self.distance_m, 4)}


def atlas_grid(views: np.ndarray, size: int, max_bytes: int = ATLAS_MAX_BYTES) -> AtlasGrid:
    """The grid for footage seen from ``views`` (N, 3) at frames of ``size`` px: 5 deg steps, coarser
    (10, 15, ...) while the atlas (uint8 RGBA) would pass ``max_bytes``; elevations spanning the
    footage's and :data:`ELEVATION_MARGIN_DEG` beyond (the top row at the top of that span), every
    row within +-:data:`ELEVATION_LIMIT_DEG` (a crop camera straight above the object has no up)."""
    lo = max(float(views[:, 1].min()) - ELEVATION_MARGIN_DEG, -ELEVATION_LIMIT_DEG)
    hi = min(float(views[:, 1].max()) + ELEVATION_MARGIN_DEG, ELEVATION_LIMIT_DEG)
    step = 5.0
    while True:
        n_az, n_el = int(round(360.0 / step)), int(math.ceil((hi - lo) / step - 1e-9)) + 1
        if n_az * n_el * 4 * size * size <= max_bytes or step >= 45.0:
            break
        step += 5.0
    el0 = hi - (n_el - 1) * step            # at or up to one step below lo
    if el0 < -ELEVATION_LIMIT_DEG:          # both ends at the limits: a row fewer, the top short of hi
        el0, n_el = -ELEVATION_LIMIT_DEG, n_el - 1
    return AtlasGrid(step, n_az, el0, n_el, float(np.median(views[:, 2])))


def render_atlas(tree: PlenOctree, grid: AtlasGrid, center: np.ndarray, radius: float, up: np.ndarray,
                 size: int, fill: float, supersample: int = 2, quiet: bool = False) -> np.ndarray:
    """The tree's renders through the crop camera (:func:`dbb_capture.crops.camera.facing_camera`) of
    each of the grid's views: premultiplied RGBA (n_el, n_az, 4, S, S) uint8. Rendered at
    ``supersample`` times the size and averaged down, as the crops are resized from larger ones."""
    renderer = TreeRenderer(tree)
    views = grid.views().reshape(-1, 3)
    out = np.empty((len(views), 4, size, size), np.uint8)
    with progress(transient=True, disable=quiet) as prog:
        task = prog.add_task("anchor atlas", total=len(views), info="")
        for i, v in enumerate(views):
            eye = eye_at(Viewpoint(*map(float, v)), center, up)
            c2w, intr = facing_camera(eye, center, radius, up, size * supersample, fill)
            rgba = torch.from_numpy(renderer.render(c2w, intr)).permute(2, 0, 1)[None]
            pm = torch.cat([rgba[:, :3] * rgba[:, 3:], rgba[:, 3:]], 1)
            pm = F.avg_pool2d(pm, supersample) if supersample > 1 else pm
            out[i] = (pm[0].clamp(0, 1) * 255).round().to(torch.uint8).numpy()
            prog.update(task, advance=1)
    return out.reshape(grid.n_el, grid.n_az, 4, size, size)


class ViewAtlas(nn.Module):
    """Viewpoints (N, 3) -> the anchor's premultiplied RGBA (N, 4, S, S) float in [0, 1], bilinear
    in azimuth (wrapping) and elevation (held at the ends) over the atlas's renders. TorchScript-able."""

    def __init__(self, images: torch.Tensor, grid: AtlasGrid):
        super().__init__()
        self.register_buffer("images", images.contiguous())          # (n_el, n_az, 4, S, S) uint8
        self.step = float(grid.step_deg)
        self.el0 = float(grid.el0_deg)
        self.n_az = int(grid.n_az)
        self.n_el = int(grid.n_el)
        self.distance = float(grid.distance_m)

    def forward(self, views: torch.Tensor) -> torch.Tensor:
        u = torch.remainder(views[:, 0], 360.0) / self.step
        v = ((views[:, 1] - self.el0) / self.step).clamp(0.0, float(self.n_el - 1))
        a0, e0 = u.floor(), v.floor()
        fu, fv = (u - a0)[:, None, None, None], (v - e0)[:, None, None, None]
        a0l, e0l = a0.long() % self.n_az, e0.long()
        a1l, e1l = (a0l + 1) % self.n_az, (e0l + 1).clamp(max=self.n_el - 1)
        im = self.images
        top = torch.lerp(im[e0l, a0l].to(views.dtype), im[e0l, a1l].to(views.dtype), fu)
        bottom = torch.lerp(im[e1l, a0l].to(views.dtype), im[e1l, a1l].to(views.dtype), fu)
        return torch.lerp(top, bottom, fv) * (1.0 / 255.0)

    def state(self) -> dict:
        """What :meth:`from_state` rebuilds it from (model.pt's ``anchor`` entry)."""
        grid = AtlasGrid(self.step, self.n_az, self.el0, self.n_el, self.distance)
        return {"images": self.images.cpu(), "grid": grid.to_json()}

    @classmethod
    def from_state(cls, d: dict) -> ViewAtlas:
        g = d["grid"]
        return cls(d["images"], AtlasGrid(float(g["step_deg"]), int(g["azimuths"]), float(g["elevation0_deg"]),
                                          int(g["elevations"]), float(g["distance_m"])))


def build_atlas(tree_file: Path, views: np.ndarray, meta: dict, size: int, quiet: bool = False) -> ViewAtlas:
    """The atlas of the PlenOctree ``tree_file`` for a crops.json dataset whose frames were seen from
    ``views`` (N, 3); ``meta`` its top-level entries (``object`` centre and radius, ``up``,
    ``crop_fill``) place the crop cameras as preprocess placed them."""
    grid = atlas_grid(views, size)
    obj = meta["object"]
    images = render_atlas(PlenOctree.load(Path(tree_file)), grid, np.asarray(obj["center"], float),
                          float(obj["radius"]), np.asarray(meta["up"], float), size, float(meta["crop_fill"]),
                          quiet=quiet)
    return ViewAtlas(torch.from_numpy(images), grid)


def no_atlas(size: int) -> ViewAtlas:
    """A stand-in for a model without an anchor (a TorchScript stepper needs a module there)."""
    return ViewAtlas(torch.zeros(1, 1, 4, size, size, dtype=torch.uint8), AtlasGrid(360.0, 1, 0.0, 1, 1.0))

