"""Analytic ray casting of a synthetic scene, vectorized in PyTorch, with adaptive supersampling
at edges; the object alone as straight RGBA for any camera and time (:func:`render_object_rgba`:
the ground truth novel views are scored against)."""

from __future__ import annotations

import math

import numpy as np
import torch

from ..capture.board import BoardSpec
from ..geometry.cameras import Intrinsics
from ..geometry.rays import camera_rays, pixel_grid
from .objects import ObjectModel
from .scene import Scene


def _sample(tex: torch.Tensor, u: torch.Tensor, v: torch.Tensor, wrap: bool = True,
            mode: str = "bilinear") -> torch.Tensor:
    """Texture lookup; u, v (M,) in texture periods (wrapped) or 0..1 (clamped) -> (M, C)."""
    if wrap:
        u, v = torch.remainder(u, 1.0), torch.remainder(v, 1.0)
    grid = torch.stack([u * 2 - 1, v * 2 - 1], -1)[None, None]  # (1, 1, M, 2)
    out = torch.nn.functional.grid_sample(tex, grid, mode=mode, padding_mode="border",
                                          align_corners=False)
    return out[0, :, 0].T


def _shade(albedo, normal, points, eye, light, specular: float = 0.0):
    """Lambert + ambient under one point light, optional Blinn-Phong highlight.

    albedo, normal, points: (3, M) channel-first (1-D component arithmetic is several times
    faster in torch than reductions over a trailing axis of 3); eye, light (3,). Returns (3, M).
    """
    Lx, Ly, Lz = light[0] - points[0], light[1] - points[1], light[2] - points[2]
    dist2 = Lx * Lx + Ly * Ly + Lz * Lz
    inv = dist2.rsqrt()
    ndl = ((normal[0] * Lx + normal[1] * Ly + normal[2] * Lz) * inv).clamp_(min=0)
    fall = (2.6 / dist2.clamp(min=0.25)).clamp_(max=1.4)  # point-light falloff, ~1 near the table
    col = albedo * (0.38 + 0.62 * ndl * fall)
    if specular > 0:
        Vx, Vy, Vz = eye[0] - points[0], eye[1] - points[1], eye[2] - points[2]
        vinv = (Vx * Vx + Vy * Vy + Vz * Vz).rsqrt()
        Hx, Hy, Hz = Lx * inv + Vx * vinv, Ly * inv + Vy * vinv, Lz * inv + Vz * vinv
        hinv = (Hx * Hx + Hy * Hy + Hz * Hz).rsqrt()
        ndh = ((normal[0] * Hx + normal[1] * Hy + normal[2] * Hz) * hinv).clamp_(min=0)
        col = col + specular * ndh ** 40
    return col


_ONES3 = torch.ones(3)


def _intersect_object(obj: ObjectModel, t_obj: float, o: torch.Tensor, d: torch.Tensor):
    """Nearest ellipsoid hit for rays from ``o`` (3,) along ``d`` (M, 3).

    Returns (t (M,) with inf where missed, normal (M, 3), albedo (M, 3), index of the
    ellipsoid hit (M,) uint8).
    """
    M = d.shape[0]
    best_t = torch.full((M,), float("inf"))
    which = torch.zeros(M, dtype=torch.uint8)
    normal = torch.zeros((M, 3))
    albedo = torch.zeros((M, 3))
    for j, (c, R, e) in enumerate(obj.posed(t_obj)):
        # Only the rays through the ellipsoid's bounding sphere: each part covers a small
        # share of the object's rays.
        co = torch.from_numpy(c).float() - o
        along = d @ co
        rb = max(e.radii)
        sel = ((float(co @ co) - along * along < rb * rb) & (along > -rb)).nonzero().squeeze(1)
        if len(sel) == 0:
            continue
        Rt = torch.from_numpy(R).float()
        inv_r = 1.0 / torch.tensor(e.radii, dtype=torch.float32)
        oc = (-co @ Rt) * inv_r                                        # (3,) in the unit sphere frame
        dl = (d[sel] @ Rt) * inv_r                                     # (S, 3)
        # Matrix-vector products: much faster in torch than reductions over a trailing axis of 3.
        a = (dl * dl) @ _ONES3
        b = 2 * (dl @ oc)
        cc = float((oc * oc).sum() - 1.0)
        disc = b * b - 4 * a * cc
        t = (-b - disc.clamp(min=0).sqrt()) / (2 * a)
        closer = (disc > 0) & (t > 0) & (t < best_t[sel])
        if not bool(closer.any()):
            continue
        idx, t, dl = sel[closer], t[closer], dl[closer]
        q = oc[None] + t[:, None] * dl                                 # unit-sphere coordinates
        n = (q * inv_r) @ Rt.T
        best_t[idx] = t
        normal[idx] = n / n.norm(dim=-1, keepdim=True)
        col = torch.tensor(e.color, dtype=torch.float32)[None].expand(len(idx), 3)
        if e.stripes > 0:
            # Stripes and a seam in the part's own frame make its rotation visible.
            stripe = 0.78 + 0.22 * torch.tanh(4 * torch.sin(math.pi * e.stripes * q[:, 2:3]))
            seam = 1 - 0.35 * torch.exp(-((q[:, 0:1] * 6) ** 2)) * (q[:, 1:2] < 0)
            col = col * stripe * seam
        albedo[idx] = col
        which[idx] = j
    return best_t, normal, albedo, which


def render_rays(scene: Scene, c2w: np.ndarray, rays_cam: torch.Tensor, t_obj: float,
                object_only: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cast rays (3, M) given in the OpenCV camera frame from camera ``c2w`` (4, 4) at time ``t_obj``.

    Returns (colour (3, M) in 0..1, object coverage (M,) 0/1, surface id (M,) uint8: which
    room face, the table, the board or which ellipsoid each ray hit; see ``_SURF_*``). With
    ``object_only`` the colour is black wherever the object is not hit.
    """
    R = torch.from_numpy(c2w[:3, :3]).float()
    o = torch.from_numpy(c2w[:3, 3]).float()
    d = R @ rays_cam
    M = d.shape[1]
    light = torch.from_numpy(scene.light).float()
    color, surf = torch.zeros((3, M)), torch.zeros(M, dtype=torch.uint8)
    obj_hit = torch.zeros(M)
    if scene.obj is not None:
        # Only rays that pass through the bounding sphere (of the object posed at t) can hit it.
        c, r = scene.obj.bounding_sphere(np.array([t_obj]))
        oc = torch.from_numpy(c).float() - o
        along = oc[0] * d[0] + oc[1] * d[1] + oc[2] * d[2]
        perp2 = (oc * oc).sum() - along * along
        cand = ((perp2 < r * r) & (along > -r)).nonzero().squeeze(1)
        if len(cand):
            t, n, alb, which = _intersect_object(scene.obj, t_obj, o, d[:, cand].T)
            got = torch.isfinite(t)
            idx = cand[got]
            if len(idx):
                p = o[None] + t[got, None] * d[:, idx].T
                color[:, idx] = _shade(alb[got].T, n[got].T, p.T, o, light, specular=0.25)
                obj_hit[idx] = 1.0
                surf[idx] = which[got] + _SURF_OBJECT
    if not object_only:
        # The room only behind the rays that missed the object (most refined samples hit it).
        miss = (obj_hit == 0).nonzero().squeeze(1) if bool(obj_hit.any()) else None
        if miss is None:
            color, surf = _render_background(scene, o, d, light)
        elif len(miss):
            color[:, miss], surf[miss] = _render_background(scene, o, d[:, miss], light)
    return color, obj_hit, surf


# Surface ids (uint8): which face a ray hit. Neighbouring pixels that see different surfaces
# straddle an edge, so the adaptive renderer supersamples them.
_SURF_TABLE, _SURF_BOARD, _SURF_FLOOR, _SURF_CEILING, _SURF_WALL_X, _SURF_WALL_Y = 1, 2, 3, 4, 5, 7


_SURF_OBJECT = 16  # + index of the ellipsoid


def _render_background(scene: Scene, o: torch.Tensor, d: torch.Tensor,
                       light: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Room, table and board as seen along rays ``d`` (3, M) from ``o`` (3,).

    Returns (colour (3, M), surface id (M,) uint8).
    """
    M = d.shape[1]
    ox, oy, oz = (float(v) for v in o)
    dx, dy, dz = d[0], d[1], d[2]
    lo, hi = scene.room_min, scene.room_max

    def exit_t(dc, oc, lo_c, hi_c):
        # Distance to the room wall this ray leaves through along one axis.
        return torch.where(dc > 0, hi_c - oc, lo_c - oc) / torch.where(dc.abs() < 1e-9, 1e-9, dc)

    tx, ty, tz = exit_t(dx, ox, lo[0], hi[0]), exit_t(dy, oy, lo[1], hi[1]), exit_t(dz, oz, lo[2], hi[2])
    t_room = torch.minimum(torch.minimum(tx, ty), tz)
    # Table top (and the board printed on it) on the plane z = 0, hit from above (d_z > 0).
    t_tab = -oz / dz.clamp(min=1e-9)
    px_t, py_t = ox + t_tab * dx, oy + t_tab * dy
    (x0, y0), (x1, y1) = scene.table_min, scene.table_max
    on_table = (dz > 0) & (t_tab < t_room) & (px_t >= x0) & (px_t <= x1) & (py_t >= y0) & (py_t <= y1)
    t = torch.where(on_table, t_tab, t_room)
    p = torch.stack([ox + t * dx, oy + t * dy, oz + t * dz])
    # Normals face the camera: -sign(d) along the exit axis; the table faces up (-z).
    wall_x = ~on_table & (tx <= ty) & (tx <= tz)
    wall_y = ~on_table & ~wall_x & (ty <= tz)
    flat = ~on_table & ~wall_x & ~wall_y          # floor or ceiling
    n = torch.zeros((3, M))
    n[0] = torch.where(wall_x, -torch.sign(dx), 0.0)
    n[1] = torch.where(wall_y, -torch.sign(dy), 0.0)
    n[2] = torch.where(flat, -torch.sign(dz), torch.where(on_table, -1.0, 0.0))

    albedo = torch.empty((3, M))
    surf = torch.empty(M, dtype=torch.uint8)
    bw, bh = scene.board.size_m
    on_board = on_table & (p[0] >= 0) & (p[0] <= bw) & (p[1] >= 0) & (p[1] <= bh)
    for mask, name, (a, b), scale, sid in (
            (on_table & ~on_board, "table", (0, 1), (0.6, 0.6), _SURF_TABLE),
            (flat & (dz > 0), "floor", (0, 1), (1.2, 1.2), _SURF_FLOOR),
            (flat & (dz <= 0), "ceiling", (0, 1), (2.0, 2.0), _SURF_CEILING),
            (wall_x, "wall", (1, 2), (1.0, 1.0), _SURF_WALL_X),
            (wall_y, "wall", (0, 2), (1.0, 1.0), _SURF_WALL_Y),
            (on_board, "board", (0, 1), (bw, bh), _SURF_BOARD)):
        k = mask.nonzero().squeeze(1)
        if len(k) == 0:
            continue
        # Opposite walls get ids one apart (the sign of the ray's direction picks the wall).
        surf[k] = sid + (d[a ^ b ^ 3, k] > 0).to(torch.uint8) if name == "wall" else sid
        # Bilinear everywhere: the board's edges must be exact to the sub-pixel (poses are scored
        # on them), and the room's texels (about a pixel wide) must not make steps between
        # pixels, which the adaptive renderer would take for edges to supersample.
        albedo[:, k] = _sample(scene.board_tex if name == "board" else scene.textures[name],
                               p[a, k] / scale[0], p[b, k] / scale[1], wrap=name != "board").T
    return _shade(albedo, n, p, o, light), surf


def _edge_pixels(col: torch.Tensor, surf: torch.Tensor, contrast: float) -> torch.Tensor:
    """Pixels whose centre sample may differ from their average: (H, W) bool.

    col (3, H, W) colour of the centre samples, surf (H, W) surface ids. A pixel is marked
    when an 8-connected neighbour sees another surface (an edge of the board, the table, a
    wall or the object runs between the centres: both pixels are marked), or when the colour
    is not linear across it: a second difference of R + G + B along a row, a column or a
    diagonal above ``contrast`` (a texture edge or a stripe; on a linear gradient the centre
    is the box average). Any straight edge crossing a pixel separates its centre from one of
    its 8 neighbours' centres, so every pixel an edge crosses is marked.
    """
    H, W = surf.shape
    flag = torch.zeros((H, W), dtype=torch.bool)
    lo, hi, al = slice(None, -2), slice(2, None), slice(None)
    a, b = slice(None, -1), slice(1, None)
    for pa, pb in (((al, a), (al, b)), ((a, al), (b, al)), ((a, a), (b, b)), ((a, b), (b, a))):
        diff = surf[pa] != surf[pb]
        flag[pa] |= diff
        flag[pb] |= diff
    # The channels' sum stands for the colour: albedos are scaled by texture, stripe and light
    # factors alike, so the channels' second differences share a sign within a surface.
    lum = col.sum(0)
    two_mid = 2 * lum[1:-1, 1:-1]
    inner = flag[1:-1, 1:-1]
    c = slice(1, -1)
    for pa, pb in (((c, lo), (c, hi)), ((lo, c), (hi, c)), ((lo, lo), (hi, hi)), ((lo, hi), (hi, lo))):
        inner |= (lum[pa] + lum[pb]).sub_(two_mid).abs_() > contrast
    return flag


class Renderer:
    """Renders frames of one camera (fixed intrinsics, s x s stratified samples per pixel).

    Adaptive (the default for s > 1): a first ray through every pixel's centre, then the full
    s x s samples only where :func:`_edge_pixels` finds an edge or a texture step (typically
    5-15 % of the pixels at 640x480). There the pixel is the box-filtered average of its
    samples, exactly as brute force; elsewhere the image is smooth at the pixel scale and the
    centre sample is the average to within about ``contrast`` (R + G + B, 0..3).
    ``adaptive=False``: every pixel s x s.
    """

    def __init__(self, intr: Intrinsics, samples: int = 2, adaptive: bool = True, contrast: float = 0.06):
        self.intr = intr
        self.s = samples
        self.adaptive = adaptive and samples > 1
        self.contrast = contrast
        self.refined = 1.0  # fraction of the pixels supersampled in the last frame
        W, H, s = intr.width, intr.height, samples
        # Sample rays pixel by pixel, (H*W, s*s, 3): the s*s rays of one pixel are adjacent.
        grid = pixel_grid(W, H, s).reshape(H, s, W, s, 2).transpose(0, 2, 1, 3, 4)
        self.sub_rays = torch.from_numpy(camera_rays(intr, grid).reshape(H * W, s * s, 3)).float()
        self.centre_rays = None
        if self.adaptive:
            centres = camera_rays(intr, pixel_grid(W, H, 1)).reshape(-1, 3)
            self.centre_rays = torch.from_numpy(centres.T.copy()).float()  # (3, H*W)

    def _samples(self, scene: Scene, c2w: np.ndarray, t: float, pixels: torch.Tensor | None = None,
                 object_only: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Colour (3, P, s*s) and coverage (P, s*s) of the samples of ``pixels`` (all if None)."""
        rays = self.sub_rays if pixels is None else self.sub_rays[pixels]
        col, hit, _ = render_rays(scene, c2w, rays.reshape(-1, 3).T, t, object_only)
        n = self.s * self.s
        return col.view(3, -1, n), hit.view(-1, n)

    def _image(self, values: torch.Tensor) -> np.ndarray:
        """(C, H*W) -> (H, W, C) array."""
        return values.view(-1, self.intr.height, self.intr.width).permute(1, 2, 0).contiguous().numpy()

    def render(self, scene: Scene, c2w: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free frame (H, W, 3) float RGB 0..1 and object coverage (H, W) 0..1."""
        if not self.adaptive:
            col, hit = self._samples(scene, c2w, t)
            return self._image(col.mean(-1)), self._image(hit.mean(-1)[None])[..., 0]
        W, H = self.intr.width, self.intr.height
        col, hit, surf = render_rays(scene, c2w, self.centre_rays, t)
        k = _edge_pixels(col.view(3, H, W), surf.view(H, W), self.contrast).view(-1).nonzero().squeeze(1)
        self.refined = len(k) / (H * W)
        if len(k):
            scol, shit = self._samples(scene, c2w, t, k)
            col[:, k] = scol.mean(-1)
            hit[k] = shit.mean(-1)
        return self._image(col), self._image(hit[None])[..., 0]

    def render_object(self, scene: Scene, c2w: np.ndarray, t: float) -> np.ndarray:
        """The object alone as straight RGBA (H, W, 4) float 0..1 (every pixel s x s: ground truth)."""
        col, hit = self._samples(scene, c2w, t, object_only=True)
        premul = self._image((col * hit[None]).mean(-1))
        alpha = self._image(hit.mean(-1)[None])
        rgb = np.where(alpha > 0, premul / np.maximum(alpha, 1e-6), 0)
        return np.concatenate([rgb, alpha], -1)


def sensor(img: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
    """Sensor-like noise (read noise plus signal-dependent shot noise), quantized to uint8 RGB."""
    if noise > 0:
        std = noise * np.sqrt(0.35 + 1.5 * img)
        img = img + std * rng.standard_normal(img.shape, dtype=np.float32)
    return np.clip(np.round(img * 255), 0, 255).astype(np.uint8)


def render_object_rgba(model: ObjectModel, intr: Intrinsics, c2w_opencv: np.ndarray, t: float,
                       samples: int = 3) -> np.ndarray:
    """Ground truth: the object alone at time ``t`` as straight RGBA uint8 (H, W, 4).

    ``c2w_opencv`` is the board-from-camera pose (4, 4) in the OpenCV camera convention.
    """
    sphere = model.bounding_sphere(np.array([t]))
    scene = Scene(BoardSpec(2, 2, 0.02, 0.01, "DICT_4X4_50"), model, sphere, {}, torch.zeros(1, 1, 1, 1))
    rgba = Renderer(intr, samples).render_object(scene, np.asarray(c2w_opencv, float), t)
    return np.clip(np.round(rgba * 255), 0, 255).astype(np.uint8)
