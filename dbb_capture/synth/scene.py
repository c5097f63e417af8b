"""Synthetic captures with ground truth: a ChArUco board on a table in a textured room, a toy
object beside it, seen by a smooth handheld-like camera.

Everything is analytic ray casting, vectorized in PyTorch (2x2 or more stratified samples per
pixel): axis-aligned room box, table top and board on the plane z = 0, and the object as a set
of ellipsoids grouped into rigid parts. Parts of a dynamic object rotate about pivots:
arms swing periodically, the head wanders along a quasi-periodic (never repeating) path.

World frame = board frame (OpenCV ChArUco convention): the board lies face up on the table
in the plane z = 0, so "up" (toward the cameras) is -z and the table is at z >= 0 below.

The object's model (``ground_truth/object_model.json``) can be rendered alone as straight
RGBA for any camera and time with :func:`render_object_rgba`: that is the ground truth used
to score novel views.
"""

from __future__ import annotations

import math
import os
import time as _time
from dataclasses import asdict, dataclass, field
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import torch

from ..capture.board import BoardSpec
from ..geometry.cameras import Intrinsics
from ..geometry.rays import camera_rays, pixel_grid
from ..geometry.transforms import look_at
from ..geometry.conventions import opengl_from_opencv
from ..core.errors import DbbError
from ..core.outputs import atomic_dir, write_json
from ..core.progress import progress

UP = np.array([0.0, 0.0, -1.0])  # board normal on the cameras' side (board face up on a table)


# --------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class SynthConfig:
    """What to render. Lengths in metres, angles in degrees, times in seconds."""

    kind: str = "static"                     # "static" | "dynamic"
    seconds: float = 10.0
    fps: float = 10.0
    width: int = 640
    height: int = 480
    hfov_deg: float = 62.0
    seed: int = 0
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    board: BoardSpec = field(default_factory=lambda: BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100"))
    samples: int = 2                         # per pixel along each axis
    noise: float = 0.01                      # read-noise std, fraction of full scale
    background_seconds: float | None = 10.0  # clean plate length; None: no clean plate
    azimuth_range_deg: tuple[float, float] = (-60.0, 60.0)
    elevation_range_deg: tuple[float, float] = (10.0, 75.0)
    distance_range_m: tuple[float, float] = (0.5, 0.85)
    roll_deg: float = 4.0
    crf: int = 18                            # H.264 quality (lower: better, larger)
    workers: int = 0                         # render processes (0: 2 on multi-core machines for long captures)

    def intrinsics(self) -> Intrinsics:
        f = 0.5 * self.width / math.tan(math.radians(self.hfov_deg) / 2)
        return Intrinsics(self.width, self.height, f, f, (self.width - 1) / 2 + 0.37,
                          (self.height - 1) / 2 - 0.61, tuple(float(v) for v in self.dist))


# --------------------------------------------------------------------------- object model
@dataclass(frozen=True)
class Ellipsoid:
    """An ellipsoid of a rigid part, axis-aligned at rest; centre and radii in metres."""

    part: str
    center: tuple[float, float, float]
    radii: tuple[float, float, float]
    color: tuple[float, float, float]        # albedo, linear 0..1
    stripes: float = 0.0                     # stripe frequency along local z (0: plain)


@dataclass(frozen=True)
class Motion:
    """Rotation of a part about ``pivot`` around ``axis``: angle(t) = sum a_i sin(2 pi t / T_i + p_i)."""

    part: str
    pivot: tuple[float, float, float]
    axis: tuple[float, float, float]
    amplitudes_deg: tuple[float, ...]
    periods_s: tuple[float, ...]
    phases: tuple[float, ...]

    def angle_rad(self, t: float) -> float:
        return math.radians(sum(a * math.sin(2 * math.pi * t / T + p) for a, T, p in
                                zip(self.amplitudes_deg, self.periods_s, self.phases)))


@dataclass(frozen=True)
class ObjectModel:
    """The object: ellipsoids in rigid parts, and the motions of the parts that move."""

    ellipsoids: tuple[Ellipsoid, ...]
    motions: tuple[Motion, ...] = ()

    def posed(self, t: float) -> list[tuple[np.ndarray, np.ndarray, Ellipsoid]]:
        """World pose of every ellipsoid at time t: [(centre (3,), rotation (3, 3), ellipsoid)]."""
        rot = {m.part: (np.asarray(m.pivot), _axis_angle(np.asarray(m.axis), m.angle_rad(t)))
               for m in self.motions}
        out = []
        for e in self.ellipsoids:
            c = np.asarray(e.center, float)
            R = np.eye(3)
            if e.part in rot:
                pivot, R = rot[e.part]
                c = pivot + R @ (c - pivot)
            out.append((c, R, e))
        return out

    def bounding_sphere(self, times: np.ndarray) -> tuple[np.ndarray, float]:
        """A sphere (centre (3,), radius) holding the object at all ``times``."""
        pts = []
        for t in times:
            for c, R, e in self.posed(float(t)):
                # Corners of the ellipsoid's oriented bounding box hold it.
                corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
                pts.append(c + (corners * np.asarray(e.radii)) @ R.T)
        pts = np.concatenate(pts)
        center = 0.5 * (pts.min(0) + pts.max(0))
        return center, float(np.linalg.norm(pts - center, axis=1).max())

    def to_json(self) -> dict:
        return {"ellipsoids": [asdict(e) for e in self.ellipsoids],
                "motions": [asdict(m) for m in self.motions]}

    @classmethod
    def from_json(cls, d: dict) -> "ObjectModel":
        def tup(v):
            return tuple(tup(x) for x in v) if isinstance(v, list) else v

        return cls(tuple(Ellipsoid(**{k: tup(v) for k, v in e.items()}) for e in d["ellipsoids"]),
                   tuple(Motion(**{k: tup(v) for k, v in m.items()}) for m in d["motions"]))


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    R, _ = cv2.Rodrigues(axis * angle)
    return R


def make_object(kind: str, board: BoardSpec, rng: np.random.Generator) -> ObjectModel:
    """A toy (body, head with ears and nose, arms, feet) standing on the table beside the board.

    Its front faces -y, toward the middle of the camera path. ``dynamic``: the arms swing
    periodically, the head turns and nods along a quasi-periodic path.
    """
    w, h = board.size_m
    s = float(rng.uniform(0.9, 1.1))
    base = np.array([w + 0.07 * s + 0.03, h / 2, 0.0])

    def hsv(hue: float, sat: float, val: float) -> tuple[float, float, float]:
        px = np.uint8([[[int(hue * 179) % 180, int(sat * 255), int(val * 255)]]])
        r, g, b = cv2.cvtColor(px, cv2.COLOR_HSV2RGB)[0, 0] / 255.0
        return (float(r), float(g), float(b))

    hue = float(rng.uniform(0, 1))
    body_c, head_c = hsv(hue, 0.65, 0.85), hsv(hue + 0.08, 0.45, 0.95)
    limb_c, acc_c = hsv(hue + 0.5, 0.7, 0.8), hsv(hue + 0.25, 0.8, 0.6)

    def at(x: float, y: float, z: float) -> tuple[float, float, float]:
        p = base + s * np.array([x, y, z])
        return (float(p[0]), float(p[1]), float(p[2]))

    def rr(*r: float) -> tuple[float, float, float]:
        return tuple(float(s * v) for v in r)  # type: ignore[return-value]

    E = Ellipsoid
    ells = [
        E("body", at(0, 0, -0.062), rr(0.046, 0.039, 0.056), body_c, stripes=7.0),
        E("body", at(-0.022, -0.008, -0.008), rr(0.019, 0.026, 0.008), acc_c),   # feet
        E("body", at(0.022, -0.008, -0.008), rr(0.019, 0.026, 0.008), acc_c),
        E("head", at(0, 0, -0.142), rr(0.036, 0.034, 0.034), head_c, stripes=5.0),
        E("head", at(-0.026, 0.004, -0.172), rr(0.012, 0.006, 0.013), acc_c),    # ears
        E("head", at(0.026, 0.004, -0.172), rr(0.012, 0.006, 0.013), acc_c),
        E("head", at(0, -0.034, -0.138), rr(0.011, 0.010, 0.009), limb_c),        # nose
        E("arm_l", at(-0.058, 0, -0.074), rr(0.012, 0.012, 0.033), limb_c, stripes=4.0),
        E("arm_r", at(0.058, 0, -0.074), rr(0.012, 0.012, 0.033), limb_c, stripes=4.0),
    ]
    motions: list[Motion] = []
    if kind == "dynamic":
        ph = rng.uniform(0, 2 * math.pi, size=6)
        swing_T = float(rng.uniform(1.4, 1.9))
        motions = [
            # Periodic: arms swing in opposition about the shoulders.
            Motion("arm_l", at(-0.054, 0, -0.1), (1.0, 0.0, 0.0), (40.0,), (swing_T,), (ph[0],)),
            Motion("arm_r", at(0.054, 0, -0.1), (1.0, 0.0, 0.0), (40.0,), (swing_T,), (ph[0] + math.pi,)),
            # Non-periodic: the head turns about the up axis with incommensurate periods.
            Motion("head", at(0, 0, -0.11), tuple(UP), (28.0, 14.0, 9.0),
                   (3.1, 3.1 * math.sqrt(2), 3.1 * math.pi), (ph[1], ph[2], ph[3])),
        ]
    elif kind != "static":
        raise DbbError(f"unknown object kind {kind!r} (expected static or dynamic)")
    return ObjectModel(tuple(ells), tuple(motions))


# --------------------------------------------------------------------------- scene
@dataclass
class Scene:
    """Everything the renderer needs that does not change from frame to frame."""

    board: BoardSpec
    obj: ObjectModel | None
    obj_sphere: tuple[np.ndarray, float]
    textures: dict[str, torch.Tensor]        # name -> (1, 3, H, W) float
    board_tex: torch.Tensor                  # (1, 1, H, W) float 0..1
    room_min: np.ndarray = field(default_factory=lambda: np.array([-2.2, -2.6, -2.4]))
    room_max: np.ndarray = field(default_factory=lambda: np.array([2.8, 2.4, 0.76]))
    table_min: np.ndarray = field(default_factory=lambda: np.array([-0.45, -0.45]))
    table_max: np.ndarray = field(default_factory=lambda: np.array([0.95, 0.75]))
    light: np.ndarray = field(default_factory=lambda: np.array([0.35, -0.6, -1.6]))

    def without_object(self) -> "Scene":
        return Scene(self.board, None, self.obj_sphere, self.textures, self.board_tex,
                     self.room_min, self.room_max, self.table_min, self.table_max, self.light)


def _noise_texture(rng: np.random.Generator, size: int, octaves: int = 5) -> np.ndarray:
    """Smooth value noise (size, size) in 0..1, tileable, from summed upsampled random grids."""
    out = np.zeros((size, size), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        n = 4 * 2 ** o
        g = rng.random((n, n)).astype(np.float32)
        g = np.tile(g, (3, 3))  # tile so the cubic resize wraps around seamlessly
        big = cv2.resize(g, (3 * size, 3 * size), interpolation=cv2.INTER_CUBIC)[size:2 * size, size:2 * size]
        out += amp * big
        total += amp
        amp *= 0.55
    out /= total
    return np.clip((out - out.min()) / (np.ptp(out) + 1e-6), 0, 1)


def make_textures(rng: np.random.Generator, size: int = 512) -> dict[str, torch.Tensor]:
    """Table (wood), floor (tiles), walls (patterned paper), ceiling: (1, 3, size, size) each."""
    u = np.linspace(0, 1, size, endpoint=False, dtype=np.float32)
    uu, vv = np.meshgrid(u, u)

    def rgb(base, img):
        return np.clip(np.asarray(base, np.float32)[None, None, :] * img[..., None], 0, 1)

    n1, n2, n3 = (_noise_texture(rng, size) for _ in range(3))
    wood = 0.75 + 0.25 * np.sin(2 * np.pi * (vv * 9 + 1.5 * n1))
    table = rgb(rng.uniform([0.55, 0.35, 0.2], [0.7, 0.5, 0.3]), wood * (0.85 + 0.3 * n2))
    tiles = ((np.floor(uu * 4) + np.floor(vv * 4)) % 2) * 0.25 + 0.6
    grout = ((np.abs((uu * 4) % 1 - 0.5) > 0.47) | (np.abs((vv * 4) % 1 - 0.5) > 0.47))
    floor = rgb(rng.uniform([0.5, 0.5, 0.5], [0.8, 0.75, 0.7]), np.where(grout, 0.3, tiles * (0.8 + 0.4 * n3)))
    motif = 0.8 + 0.2 * np.sin(2 * np.pi * 6 * uu) * np.sin(2 * np.pi * 6 * vv)
    wall = rgb(rng.uniform([0.6, 0.6, 0.55], [0.9, 0.85, 0.8]), motif * (0.75 + 0.4 * n1.T))
    ceiling = rgb([0.9, 0.9, 0.88], 0.85 + 0.15 * n2.T)
    return {k: torch.from_numpy(v).permute(2, 0, 1)[None].contiguous()
            for k, v in dict(table=table, floor=floor, wall=wall, ceiling=ceiling).items()}


def make_scene(cfg: SynthConfig, rng: np.random.Generator) -> Scene:
    obj = make_object(cfg.kind, cfg.board, rng)
    times = np.linspace(0, max(cfg.seconds, 60.0), 600) if obj.motions else np.zeros(1)
    sphere = obj.bounding_sphere(times)
    board_img = cfg.board.render(px_per_square=160).astype(np.float32) / 255.0
    # Printed paper is not pure black and white.
    board_img = 0.08 + 0.84 * board_img
    return Scene(cfg.board, obj, (sphere[0], sphere[1] * 1.03), make_textures(rng),
                 torch.from_numpy(board_img)[None, None])


# --------------------------------------------------------------------------- renderer
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


# --------------------------------------------------------------------------- camera path
def _smooth_signal(rng: np.random.Generator, t: np.ndarray, seconds: float,
                   n: int = 4, fast: float = 1.0) -> np.ndarray:
    """A smooth random signal in [-1, 1]: a few sinusoids, slowest about one cycle per capture."""
    base = 1.0 / max(seconds, 1.0)
    out = np.zeros_like(t)
    total = 0.0
    for i in range(n):
        f = base * fast * (1 + i * 1.7) * rng.uniform(0.8, 1.25)
        a = 1.0 / (1 + i) ** 1.3
        out += a * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
        total += a
    return out / total


def camera_path(cfg: SynthConfig, scene: Scene, times: np.ndarray, rng: np.random.Generator):
    """OpenCV camera-to-world poses (N, 4, 4) of a handheld camera circling the object.

    Azimuth about the up axis (0 = in front of the object, on the board's -y side), elevation
    above the table and distance from the object centre follow slow random sinusoids; a few
    degrees of roll and millimetre jitter make it handheld.
    """
    T = cfg.seconds
    c_obj = scene.obj_sphere[0]
    target0 = c_obj + 0.4 * (scene.board.center - c_obj)
    a_lo, a_hi = cfg.azimuth_range_deg
    e_lo, e_hi = cfg.elevation_range_deg
    d_lo, d_hi = cfg.distance_range_m
    def sweep(cycles: float) -> np.ndarray:
        # Eased triangle wave in [-1, 1] from a random phase: every capture visits the whole range.
        tri = 4 * np.abs(((times / max(T, 1e-6)) * cycles + rng.uniform(0, 1)) % 1.0 - 0.5) - 1
        return np.sin(tri * np.pi / 2)

    az = np.radians(a_lo + (a_hi - a_lo) * 0.5 * (1 + 0.85 * sweep(1.0) + 0.15 * _smooth_signal(rng, times, T, 3, 3)))
    # Elevation biased upward: grazing views (where the board is unreadable) stay brief.
    e01 = np.clip(0.5 * (1 + 0.93 * sweep(1.4) + 0.07 * _smooth_signal(rng, times, T, 3, 2)), 0, 1)
    el = np.radians(e_lo + (e_hi - e_lo) * e01 ** 0.5)
    dist = d_lo + (d_hi - d_lo) * 0.5 * (1 + _smooth_signal(rng, times, T, 3, 1.3))
    roll = np.radians(cfg.roll_deg) * _smooth_signal(rng, times, T, 3, 4.0)
    jitter = 0.002 * np.stack([_smooth_signal(rng, times, 0.7, 3) for _ in range(3)], -1)
    look_jit = 0.012 * np.stack([_smooth_signal(rng, times, T, 2, 3) for _ in range(3)], -1)
    fwd, side = np.array([0.0, -1.0, 0.0]), np.array([1.0, 0.0, 0.0])
    poses = []
    for i in range(len(times)):
        dirn = np.cos(el[i]) * (np.cos(az[i]) * fwd + np.sin(az[i]) * side) + np.sin(el[i]) * UP
        eye = c_obj + dist[i] * dirn + jitter[i]
        c2w = look_at(eye, target0 + look_jit[i], UP)
        Rz, _ = cv2.Rodrigues(np.array([0.0, 0.0, roll[i]]))
        c2w[:3, :3] = c2w[:3, :3] @ Rz
        poses.append(c2w)
    return np.stack(poses)


# --------------------------------------------------------------------------- writing
@dataclass(frozen=True)
class SynthResult:
    root: Path
    n_frames: int
    n_background_frames: int
    width: int
    height: int
    fps: float
    seconds_per_frame: float


class _VideoWriter:
    """H.264 (yuv420p, near-lossless CRF) through PyAV."""

    def __init__(self, path: Path, width: int, height: int, fps: float, crf: int = 16):
        import av

        self.container = av.open(str(path), mode="w")
        self.stream = self.container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        self.stream.width, self.stream.height = width, height
        self.stream.pix_fmt = "yuv420p"
        self.stream.options = {"crf": str(crf), "preset": "veryfast"}

    def write(self, rgb: np.ndarray) -> None:
        import av

        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        for packet in self.stream.encode(frame):
            self.container.mux(packet)

    def close(self) -> None:
        for packet in self.stream.encode():
            self.container.mux(packet)
        self.container.close()


# Per-process state of the render workers (set once by _init_worker).
_WORKER: dict = {}


def _init_worker(scene: Scene, intr: Intrinsics, samples: int, noise: float, seed: int) -> None:
    # One intra-op thread per process: two processes beat two threads spinning on one frame.
    torch.set_num_threads(1)
    _WORKER.update(scene=scene, empty=scene.without_object(), renderer=Renderer(intr, samples),
                   noise=noise, seed=seed)


def _render_job(job: tuple[str, int, np.ndarray, float]) -> tuple[np.ndarray, np.ndarray]:
    """One finished frame: (noisy RGB (H, W, 3) uint8, object coverage (H, W) uint8)."""
    which, i, c2w, t = job
    w = _WORKER
    img, cover = w["renderer"].render(w["scene"] if which == "video" else w["empty"], c2w, t)
    # Noise seeded per frame: the same capture whatever the number of processes.
    rng = np.random.default_rng([w["seed"], 3 if which == "video" else 4, i])
    return sensor(img, w["noise"], rng), np.round(cover * 255).astype(np.uint8)


class _FramePool:
    """Renders frames in order, in this process or in ``workers`` spawned processes."""

    def __init__(self, scene: Scene, intr: Intrinsics, cfg: SynthConfig, workers: int):
        self.args = (scene, intr, cfg.samples, cfg.noise, cfg.seed)
        self.workers = max(1, workers)
        self.pool = None

    def __enter__(self) -> "_FramePool":
        if self.workers > 1:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            self.pool = ProcessPoolExecutor(self.workers, mp_context=mp.get_context("spawn"),
                                            initializer=_init_worker, initargs=self.args)
        else:
            threads = torch.get_num_threads()
            _init_worker(*self.args)
            torch.set_num_threads(threads)  # in this process, keep the caller's threads
        return self

    def frames(self, which: str, poses: np.ndarray, times: np.ndarray):
        jobs = [(which, i, poses[i], float(times[i])) for i in range(len(poses))]
        if self.pool is None:
            return map(_render_job, jobs)
        return self.pool.map(_render_job, jobs, chunksize=2)

    def __exit__(self, *exc) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)


def _frames_json(poses: np.ndarray, times: np.ndarray) -> list[dict]:
    return [{"index": i, "time": round(float(t), 6),
             "transform_matrix": opengl_from_opencv(c2w).round(9).tolist()}
            for i, (c2w, t) in enumerate(zip(poses, times))]


def write_capture(cfg: SynthConfig, out: Path, overwrite: bool = False,
                  with_camera_json: bool = False) -> SynthResult:
    """Render a whole capture into ``out`` (written aside, renamed into place).

    Layout: ``video.mp4``, ``background.mp4``, ``board.json``, ``object.json``, optional
    ``camera.json``, and ``ground_truth/{camera.json, cameras.json, object_model.json,
    masks/NNNNN.png}``. ``cameras.json`` holds per-frame OpenGL camera-to-world matrices in
    the board frame (as in ``transforms.json``) for the video and the clean plate.
    """
    if cfg.width % 2 or cfg.height % 2:
        raise DbbError(f"resolution {cfg.width}x{cfg.height}: width and height must be even (H.264)")
    rng = np.random.default_rng(cfg.seed)
    scene = make_scene(cfg, rng)
    intr = cfg.intrinsics()
    n = max(1, int(round(cfg.seconds * cfg.fps)))
    times = np.arange(n) / cfg.fps
    poses = camera_path(cfg, scene, times, np.random.default_rng([cfg.seed, 1]))
    nb = 0 if cfg.background_seconds is None else max(1, int(round(cfg.background_seconds * cfg.fps)))
    btimes = np.arange(nb) / cfg.fps
    bposes = (camera_path(cfg, scene, btimes, np.random.default_rng([cfg.seed, 2])) if nb
              else np.zeros((0, 4, 4)))
    center, radius = scene.obj_sphere
    t0 = _time.perf_counter()
    with atomic_dir(Path(out), overwrite=overwrite) as tmp:
        gt = tmp / "ground_truth"
        (gt / "masks").mkdir(parents=True)
        write_json(tmp / "board.json", cfg.board.to_json())
        write_json(tmp / "object.json", {"center": center.round(6).tolist(), "radius": round(radius, 6)})
        if with_camera_json:
            write_json(tmp / "camera.json", intr.to_json())
        write_json(gt / "camera.json", intr.to_json())
        write_json(gt / "object_model.json", scene.obj.to_json())
        write_json(gt / "cameras.json", {
            "note": "transform_matrix: camera-to-world, OpenGL camera axes, board frame, metres",
            "intrinsics": intr.to_json(), "fps": cfg.fps,
            "video": _frames_json(poses, times), "background": _frames_json(bposes, btimes)})
        write_json(gt / "synth_config.json", {**asdict(cfg), "board": cfg.board.to_json()})
        workers = cfg.workers or (min(2, os.cpu_count() or 1) if n + nb >= 40 else 1)
        with progress() as prog, _FramePool(scene, intr, cfg, workers) as pool:
            task = prog.add_task("render video", total=n, info="")
            vw = _VideoWriter(tmp / "video.mp4", cfg.width, cfg.height, cfg.fps, cfg.crf)
            for i, (rgb, mask) in enumerate(pool.frames("video", poses, times)):
                vw.write(rgb)
                cv2.imwrite(str(gt / "masks" / f"{i:05d}.png"), mask)
                prog.advance(task)
            vw.close()
            spf = (_time.perf_counter() - t0) / n
            if nb:
                task = prog.add_task("render clean plate", total=nb, info="")
                vw = _VideoWriter(tmp / "background.mp4", cfg.width, cfg.height, cfg.fps, cfg.crf)
                for rgb, _ in pool.frames("background", bposes, btimes):
                    vw.write(rgb)
                    prog.advance(task)
                vw.close()
    return SynthResult(Path(out), n, nb, cfg.width, cfg.height, cfg.fps, spf)


def load_ground_truth(capture: Path) -> tuple[Intrinsics, dict, ObjectModel]:
    """(intrinsics, cameras.json content, object model) of a synthetic capture."""
    from ..core.outputs import read_json

    gt = Path(capture) / "ground_truth"
    return (Intrinsics.load(gt / "camera.json"), read_json(gt / "cameras.json", "ground truth"),
            ObjectModel.from_json(read_json(gt / "object_model.json", "ground truth")))
