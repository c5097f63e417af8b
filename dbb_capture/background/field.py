"""Background prediction: a radiance field of the room around the object (thesis 6.1.3).

The matte only needs the room where it shows *behind or around the object*, in crop windows
whose rays all pass within a few object radii of the object centre. There, what lies behind
the object is mostly the surface it stands on. So the field is layered along "up" (the board
normal, from the data): ``K`` planes parallel to the board plane (one of them the board plane
itself) over a square around the object, each an RGBA texture (colour and opacity), and an
opaque sphere far past every camera for the rest of the room. A ray's colour is the
front-to-back alpha composite of its crossings with the planes, then the sphere. It is a
layered radiance field (as multi-plane images are): trained by volume rendering from posed
views, parallax-correct, and every ray needs only ~K+1 samples found in closed form, which is
what makes it train in minutes and render crop windows in milliseconds on a CPU. The table
and the board lie exactly on a layer, so they come out sharp from every side. The far sphere
is a depth panorama (each texel at the distance a sweep over spheres finds the views agree):
the room's walls are not at one radius, and a wall placed at the wrong one is smeared by the
parallax between the views.

Training data are "background crops": each clean-plate frame cut through the crop camera it
would have had, so the field is trained in the geometry it is rendered in. Training starts
from a plane sweep (each texel: the mean colour of its point across views, opaque where the
views agree). Without a clean plate the object video is used with every pixel whose ray
passes through the object's sphere left out; parallax shows other views what lies behind it;
after the first mattes it is trained again on the rays they call room (:func:`refine_on_room`),
which see the table through the sphere wherever the object is not.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..geometry.cameras import Intrinsics, project_points
from ..crops.camera import CropCamera, crop_camera, cut_crop
from ..core.errors import DbbError
from ..core.row_table import RowTable
from ..geometry.rays import pixel_rays


@dataclass(frozen=True)
class BackgroundConfig:
    """The field's shape and its training. Lengths are multiples of the object radius ``R``."""

    layers: int = 16
    layer_px: int = 384             # texels along each side of a layer
    env_width: int = 1024           # azimuth texels of the far sphere (height: half of it)
    env_depths: int = 24            # radii the far sphere's depth sweep tries per texel (0: one sphere)
    top: float = 1.5                # highest layer: this many R above the object centre
    r_out_factor: float = 2.0       # far sphere: this many times the farthest camera distance
    train_size: int = 64            # side of the training crops (pixels); preprocess sizes them to
                                    # the matte's pixels, never below this (:func:`training_size`)
    train_fill: float = 0.6         # the sphere fills less of a training crop: a margin around it
    minutes: float = 2.0
    steps: int | None = None        # stop after this many steps (tests), else the time budget
    batch_rays: int = 8192
    lr: float = 0.05
    tv_weight: float = 1e-4
    sphere_margin: float = 1.08     # without a clean plate: rays within this many R are left out
    refine_share: float = 0.5       # without a clean plate: then trained again on what the first mattes call
                                    # room, for this share of the budget (minutes or steps; 0: not)
    refine_grow_px: int = 2         # ... keeping this far from anything they call object
    max_frames: int = 400
    video_room: bool = True         # with a clean plate: also learn from the object video's rays that
                                    # pass the object's sphere (beyond sphere_margin R; the plate's
                                    # path need not cover the video's viewpoints)
    seed: int = 0

    def validate(self) -> None:
        if self.layers < 3 or self.layer_px < 16 or self.minutes <= 0 and not self.steps:
            raise DbbError("background field: need >= 3 layers, >= 16 texels and a positive budget")


# --------------------------------------------------------------------------- geometry
def _bilinear_rows(x: torch.Tensor, y: torch.Tensor, h: int, w: int, base: torch.Tensor,
                   wrap_x: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Table rows (P, 4) of the 4 texels around continuous texel coordinates ``x``, ``y`` (P,)
    (texel centres at integers) and the blend weights ``fx``, ``fy`` (P, 1)."""
    y = y.clamp(0, h - 1)
    if not wrap_x:
        x = x.clamp(0, w - 1)
    x0 = torch.floor(x) if wrap_x else torch.floor(x).clamp(max=w - 2)
    y0 = torch.floor(y).clamp(max=h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    xi0 = x0.long() % w if wrap_x else x0.long()
    xi1 = (xi0 + 1) % w if wrap_x else xi0 + 1
    b = base + y0.long() * w
    return torch.stack([b + xi0, b + xi1, b + w + xi0, b + w + xi1], 1), fx, fy


class LayerField:
    """Layers along ``up`` plus a far sphere, as one texel table (rows of RGB and opacity logits).

    ``center`` (3,) object centre, board frame (m); ``basis`` (3, 3) rows x_ref, y_ref, up;
    ``heights`` (K,) layer heights above the board plane (m, along up), increasing; layers cover
    ``|u|, |v| <= half`` around the centre with ``S x S`` texels; the sphere has radius
    ``r_out`` and ``He x We`` equirectangular texels (azimuth wraps); with ``env_depth`` (He, We)
    each of its texels lies at its own distance from the centre (a depth panorama: the room's
    walls, not a sphere, so a wall point seen from far apart views lands on one texel).
    """

    def __init__(self, layers: torch.Tensor, env: torch.Tensor, center: torch.Tensor, basis: torch.Tensor,
                 heights: torch.Tensor, half: float, r_out: float, guess: torch.Tensor | None = None,
                 env_depth: np.ndarray | None = None):
        """``layers`` (K, S, S, 4), ``env`` (He, We, 4) logits; ``guess`` (G, G) float, 1 where the
        board plane's texel is a guess (no view saw it past the object), over the layers' square;
        ``env_depth`` (He, We) float32 metres or None (every texel at ``r_out``)."""
        self.guess = guess
        self.env_depth = None if env_depth is None else np.ascontiguousarray(env_depth, np.float32)
        # Where the fixed-point iteration of :func:`env_coords` starts (the panorama's median distance).
        self.env_start = float(r_out) if env_depth is None else float(np.median(self.env_depth))
        self.k, self.s = layers.shape[0], layers.shape[1]
        self.he, self.we = env.shape[0], env.shape[1]
        self.table = RowTable(torch.cat([layers.reshape(-1, 4), env.reshape(-1, 4)]))
        self.center, self.basis, self.heights = center, basis, heights
        self.half, self.r_out = float(half), float(r_out)

    @property
    def device(self) -> torch.device:
        return self.table.data.device

    @property
    def n_layer_rows(self) -> int:
        return self.k * self.s * self.s

    @property
    def layers(self) -> torch.Tensor:
        return self.table.data[:self.n_layer_rows].view(self.k, self.s, self.s, 4)

    @property
    def env(self) -> torch.Tensor:
        return self.table.data[self.n_layer_rows:].view(self.he, self.we, 4)

    def _blend(self, rows, fx, fy) -> torch.Tensor:
        v = self.table.gather(rows)                                          # (P, 4 texels, 4)
        return (v[:, 0] * (1 - fx) + v[:, 1] * fx) * (1 - fy) + (v[:, 2] * (1 - fx) + v[:, 3] * fx) * fy

    def composite(self, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        """Colour (N, 3) in 0..1 along rays ``origins``, ``dirs`` (N, 3) (board frame, dirs unit)."""
        n = origins.shape[0]
        oc = origins - self.center
        ou, du = oc @ self.basis.T, dirs @ self.basis.T                     # in (x_ref, y_ref, up)
        h0 = float(self.center @ self.basis[2])                             # centre height above the board
        e = torch.where(du[:, 2].abs() < 1e-9, torch.full_like(du[:, 2], 1e-9), du[:, 2])
        t = (self.heights[None] - h0 - ou[:, 2:3]) / e[:, None]            # (N, K)
        pu = ou[:, None, 0] + t * du[:, None, 0]
        pv = ou[:, None, 1] + t * du[:, None, 1]
        valid = (t > 0) & (pu.abs() <= self.half) & (pv.abs() <= self.half)
        t = torch.where(valid, t, torch.full_like(t, float("inf")))
        t, order = torch.sort(t, 1)
        valid = torch.gather(valid, 1, order)
        pu, pv = torch.gather(pu, 1, order), torch.gather(pv, 1, order)
        ri, ci = valid.nonzero(as_tuple=True)
        layer = order[ri, ci]
        s = self.s
        rows, fx, fy = _bilinear_rows((pu[ri, ci] / self.half + 1) * 0.5 * s - 0.5,
                                      (pv[ri, ci] / self.half + 1) * 0.5 * s - 0.5, s, s, layer * s * s, False)
        raw = self._blend(rows, fx, fy)
        alpha = torch.zeros(t.shape, device=t.device, dtype=origins.dtype).index_put((ri, ci), torch.sigmoid(raw[:, 3]))
        trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha + 1e-7], 1), 1)
        w = (alpha * trans[:, :-1])[ri, ci]
        rgb = torch.zeros(n, 3, device=t.device, dtype=origins.dtype).index_add(0, ri, torch.sigmoid(raw[:, :3]) * w[:, None])
        # The far sphere (the camera is inside it) takes what is left.
        ex, ey = env_coords(ou.detach().cpu().numpy(), du.detach().cpu().numpy(), self.env_start, self.he, self.we,
                            self.env_depth)
        x, y = (torch.from_numpy(v).to(ou) for v in (ex, ey))
        rows, fx, fy = _bilinear_rows(x, y, self.he, self.we, torch.full_like(x, self.n_layer_rows, dtype=torch.long), True)
        env = torch.sigmoid(self._blend(rows, fx, fy)[:, :3])
        return rgb + trans[:, -1:] * env

    def baked(self) -> tuple[np.ndarray, np.ndarray]:
        """Texture logits as arrays for rendering: layers (K, S, S, 4) and far sphere (He, We + 1, 3)
        float32 (the sphere's first column repeated at the end, so sampling wraps around)."""
        if getattr(self, "_baked", None) is None or self._baked[2] != self.table.t:
            lay = self.layers.cpu().numpy()
            env = self.env[..., :3].cpu().numpy()
            self._baked = (np.ascontiguousarray(lay), np.ascontiguousarray(np.concatenate([env, env[:, :1]], 1)),
                           self.table.t)
        return self._baked[0], self._baked[1]

    def render(self, cam: CropCamera) -> np.ndarray:
        """The predicted room (H, W, 3) uint8 seen by a pinhole crop camera.

        The image :meth:`composite` gives, computed the fast way: each layer is resampled with
        one ``cv2.remap`` at its crossing points, then the layers are composited in depth order.
        """
        import cv2

        lay, env = self.baked()
        h, w = cam.intr.height, cam.intr.width
        o, d = _flat_rays(cam)
        basis = self.basis.cpu().numpy().astype(np.float64)
        c = self.center.cpu().numpy().astype(np.float64)
        ou, du = (o - c) @ basis.T, d @ basis.T
        e = np.where(np.abs(du[:, 2]) < 1e-9, 1e-9, du[:, 2])
        heights = self.heights.cpu().numpy().astype(np.float64) - c @ basis[2]
        t = (heights[:, None] - ou[None, :, 2]) / e[None]                           # (K, P)
        pu, pv = ou[None, :, 0] + t * du[None, :, 0], ou[None, :, 1] + t * du[None, :, 1]
        valid = (t > 0) & (np.abs(pu) <= self.half) & (np.abs(pv) <= self.half)
        mx = ((pu / self.half + 1) * 0.5 * self.s - 0.5).astype(np.float32)
        my = ((pv / self.half + 1) * 0.5 * self.s - 0.5).astype(np.float32)
        samples = np.stack([cv2.remap(lay[k], mx[k].reshape(h, w), my[k].reshape(h, w), cv2.INTER_LINEAR,
                                      borderMode=cv2.BORDER_REPLICATE).reshape(-1, 4)
                            for k in range(self.k)])                                # (K, P, 4)
        samples = 1.0 / (1.0 + np.exp(-samples))        # interpolate logits, then activate (as in training)
        samples[..., 3] *= valid
        order = np.argsort(np.where(valid, t, np.inf), axis=0)
        samples = np.take_along_axis(samples, order[..., None], 0)
        alpha = samples[..., 3]
        trans = np.cumprod(np.concatenate([np.ones((1, alpha.shape[1]), np.float32), 1 - alpha + 1e-7]), 0)
        rgb = (samples[..., :3] * (alpha * trans[:-1])[..., None]).sum(0)
        ex, ey = env_coords(ou, du, self.env_start, self.he, self.we, self.env_depth)
        ex %= self.we
        far = cv2.remap(env, ex.astype(np.float32).reshape(h, w), ey.astype(np.float32).reshape(h, w),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3)
        rgb = rgb + trans[-1][:, None] / (1.0 + np.exp(-far))
        return np.round(np.clip(rgb, 0, 1) * 255).reshape(h, w, 3).astype(np.uint8)

    def resized(self, layer_px: int) -> LayerField:
        """The same field with ``layer_px`` texels per layer side (a fresh optimiser state)."""
        lay = F.interpolate(self.layers.permute(0, 3, 1, 2), size=(layer_px, layer_px), mode="bilinear",
                            align_corners=False).permute(0, 2, 3, 1)
        return LayerField(lay, self.env.clone(), self.center, self.basis, self.heights, self.half, self.r_out,
                          self.guess, self.env_depth)

    def local_rays(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World rays ``o``, ``d`` (N, 3) -> origins relative to the centre and directions in the
        field's basis (x_ref, y_ref, up), float64 (N, 3) each."""
        basis = self.basis.cpu().numpy().astype(np.float64)
        c = self.center.cpu().numpy().astype(np.float64)
        return (np.asarray(o, np.float64) - c) @ basis.T, np.asarray(d, np.float64) @ basis.T

    def board_hits(self, ou: np.ndarray, du: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where local rays (:meth:`local_rays`) meet the board plane: ray parameter t and the
        layers' coordinates u, v (N,) (metres from the centre; t <= 0: the ray leaves the plane)."""
        c = self.center.cpu().numpy().astype(np.float64)
        e = np.where(np.abs(du[:, 2]) < 1e-9, 1e-9, du[:, 2])
        t = (-(c @ self.basis.cpu().numpy().astype(np.float64)[2]) - ou[:, 2]) / e
        return t, ou[:, 0] + t * du[:, 0], ou[:, 1] + t * du[:, 1]

    def guessed(self, cam: CropCamera) -> np.ndarray:
        """Pixels (H, W) bool of a crop camera whose ray meets the board plane where its colour is
        a guess (continued from around the object, never seen): there a prediction error is no
        evidence of the object."""
        import cv2

        h, w = cam.intr.height, cam.intr.width
        if self.guess is None:
            return np.zeros((h, w), bool)
        t, pu, pv = self.board_hits(*self.local_rays(*_flat_rays(cam)))
        g = self.guess.shape[0]
        mx = ((pu / self.half + 1) * 0.5 * g - 0.5).astype(np.float32).reshape(h, w)
        my = ((pv / self.half + 1) * 0.5 * g - 0.5).astype(np.float32).reshape(h, w)
        hit = cv2.remap(self.guess.cpu().numpy().astype(np.float32), mx, my, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return (hit > 0.5) & (t > 0).reshape(h, w)

    def state(self) -> dict:
        st = {"layers": self.layers.half().cpu(), "env": self.env.half().cpu(), "center": self.center.cpu(),
              "basis": self.basis.cpu(), "heights": self.heights.cpu(), "half": self.half, "r_out": self.r_out}
        if self.guess is not None:
            st["guess"] = self.guess.to(torch.uint8).cpu()
        if self.env_depth is not None:
            st["env_depth"] = torch.from_numpy(self.env_depth)
        return st

    @classmethod
    def from_state(cls, st: dict, device: torch.device | str = "cpu") -> LayerField:
        return cls(st["layers"].float().to(device), st["env"].float().to(device), st["center"].float().to(device),
                   st["basis"].float().to(device), st["heights"].float().to(device), st["half"], st["r_out"],
                   st["guess"].float() if st.get("guess") is not None else None,
                   st["env_depth"].numpy() if st.get("env_depth") is not None else None)


def _sphere_exit(ou: np.ndarray, du: np.ndarray, r: np.ndarray | float) -> np.ndarray:
    """Unit directions (N, 3) from the centre to where rays ``ou``, ``du`` (N, 3) (origins
    relative to the centre, unit directions) leave a centred sphere of radius ``r`` ((N,) or scalar)."""
    b = (ou * du).sum(-1)
    tf = -b + np.sqrt(np.clip(b * b - (ou * ou).sum(-1) + np.asarray(r, np.float64) ** 2, 0, None))
    q = ou + tf[:, None] * du
    return q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)


def _equirect(q: np.ndarray, he: int, we: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel coordinates x (azimuth, unwrapped), y (N,) of unit directions ``q`` (N, 3) (texel centres at integers)."""
    x = (np.arctan2(q[:, 1], q[:, 0]) / (2 * np.pi) + 0.5) * we - 0.5
    y = (0.5 - np.arcsin(np.clip(q[:, 2], -1, 1)) / np.pi) * he - 0.5
    return x, y


def _sample_wrapped(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples (N,) of a panorama ``img`` (He, We) at texel coordinates ``x`` (wraps), ``y``."""
    he, we = img.shape
    y = np.clip(y, 0, he - 1)
    x0, y0 = np.floor(x), np.minimum(np.floor(y), he - 2)
    fx, fy = x - x0, y - y0
    xi0 = x0.astype(np.int64) % we
    xi1, yi0 = (xi0 + 1) % we, y0.astype(np.int64)
    return ((img[yi0, xi0] * (1 - fx) + img[yi0, xi1] * fx) * (1 - fy)
            + (img[yi0 + 1, xi0] * (1 - fx) + img[yi0 + 1, xi1] * fx) * fy)


def env_coords(ou: np.ndarray, du: np.ndarray, r_out: float, he: int, we: int,
               depth: np.ndarray | None = None, iters: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Far-sphere texel coordinates x (unwrapped), y (N,) float32 where rays ``ou``, ``du`` (N, 3)
    (origins relative to the centre, unit directions; field basis) meet the room.

    Without ``depth`` the room is the sphere of radius ``r_out``; with ``depth`` (He, We) metres it
    is the depth panorama, met by fixed-point iteration from the sphere of radius ``r_out`` (hit
    the sphere at the depth found where the previous hit pointed; the map is smooth, so a few
    steps settle).
    """
    ou, du = np.asarray(ou, np.float64), np.asarray(du, np.float64)
    x, y = _equirect(_sphere_exit(ou, du, r_out), he, we)
    for _ in range(iters if depth is not None else 0):
        x, y = _equirect(_sphere_exit(ou, du, _sample_wrapped(depth, x, y)), he, we)
    return x.astype(np.float32), y.astype(np.float32)


def env_depth_sweep(fld: LayerField, bank: RayBank, n_depths: int = 24, min_rays: int = 4,
                    max_rays: int = 400_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth panorama of the room beyond the layers, by a sweep over spheres (thesis-style plane sweep).

    The training rays that do not meet the board plane inside the layers' square see the room's
    walls; for each of ``n_depths`` radii (uniform in inverse depth, from just outside the
    farthest camera to 25 times that) they land on the panorama's texels (half resolution), and
    a texel takes the radius at which the colours landing on it agree best (a wall point seen
    from far apart views lands on one texel only at its true distance). The choice is
    median-filtered; texels no ray reaches take the median radius.
    Returns depth (He, We) float32 metres, the mean colour (He, We, 3) float32 0..1 of the rays
    landing on each texel at that depth and how many did (He, We) int.
    """
    from scipy.ndimage import median_filter

    he, we = fld.he, fld.we
    rng = np.random.default_rng(seed)
    pick = rng.choice(bank.n, min(bank.n, max_rays), replace=False) if bank.n > max_rays else np.arange(bank.n)
    ou, du = fld.local_rays(bank.origins.numpy()[pick], bank.dirs.numpy()[pick])
    col = bank.rgb.numpy()[pick].astype(np.float64)
    t, pu, pv = fld.board_hits(ou, du)
    beyond = ~((t > 0) & (np.abs(pu) <= fld.half) & (np.abs(pv) <= fld.half))
    ou, du, col = ou[beyond], du[beyond], col[beyond]
    far = float(np.linalg.norm(ou, axis=1).max()) if len(ou) else fld.r_out / 2
    radii = 1.0 / np.linspace(1.0 / (1.05 * far), 1.0 / (25 * far), max(n_depths, 1))
    gh, gw = max(2, he // 2), max(4, we // 2)
    cost = np.full((len(radii), gh * gw), np.inf)
    for k, r in enumerate(radii):
        x, y = _equirect(_sphere_exit(ou, du, r), gh, gw)
        idx = np.clip(np.round(y), 0, gh - 1).astype(np.int64) * gw + np.round(x).astype(np.int64) % gw
        cnt = np.bincount(idx, minlength=gh * gw)
        s1 = np.stack([np.bincount(idx, col[:, j], gh * gw) for j in range(3)], 1)
        s2 = np.bincount(idx, (col ** 2).sum(1), gh * gw)
        var = s2 / np.maximum(cnt, 1) - (s1 ** 2).sum(1) / np.maximum(cnt, 1) ** 2
        cost[k] = np.where(cnt >= min_rays, var, np.inf)
    seen = np.isfinite(cost).any(0)
    best = np.where(seen, cost.argmin(0), -1).reshape(gh, gw)
    fill = int(np.median(best[best >= 0])) if (best >= 0).any() else len(radii) // 2
    best = median_filter(np.where(best >= 0, best, fill), size=5, mode="wrap")
    inv = np.interp(best, np.arange(len(radii)), 1.0 / radii)
    import cv2

    depth = (1.0 / cv2.resize(inv.astype(np.float32), (we, he), interpolation=cv2.INTER_LINEAR)).astype(np.float32)
    x, y = env_coords(ou, du, float(np.median(depth)), he, we, depth)
    idx = np.clip(np.round(y), 0, he - 1).astype(np.int64) * we + np.round(x).astype(np.int64) % we
    cnt = np.bincount(idx, minlength=he * we)
    mean = np.stack([np.bincount(idx, col[:, j], he * we) for j in range(3)], 1) / np.maximum(cnt, 1)[:, None]
    return depth, mean.reshape(he, we, 3).astype(np.float32), cnt.reshape(he, we)


def field_basis(up: np.ndarray, c2ws: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Rows x_ref, y_ref, up (3, 3): x_ref is horizontal and 90 deg from the cameras' mean
    direction, so the far sphere's azimuth seam (+-180 deg) lies away from both the side the
    cameras stand on and the side behind the object."""
    up = np.asarray(up, float) / np.linalg.norm(up)
    v = (np.asarray(c2ws)[:, :3, 3] - center).mean(0)
    v = v - (v @ up) * up
    if np.linalg.norm(v) < 1e-9:
        v = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    v /= np.linalg.norm(v)
    x_ref = np.cross(v, up)
    return np.stack([x_ref, np.cross(up, x_ref), up])


def new_field(cfg: BackgroundConfig, center: np.ndarray, radius: float, up: np.ndarray, c2ws: np.ndarray,
              bank: RayBank, layer_px: int, device: torch.device | str = "cpu") -> LayerField:
    """A transparent field (opaque grey far sphere) sized to the cameras and the training rays.

    Layers: from one spacing below the board plane to ``top * R`` above the centre; their square
    reaches as far as the training rays meet the board plane (99th percentile).
    """
    basis = field_basis(up, c2ws, center)
    far = float(np.linalg.norm(np.asarray(c2ws)[:, :3, 3] - center, axis=1).max())
    r_out = max(cfg.r_out_factor * far, 4 * radius)
    h_top = float(center @ basis[2]) + cfg.top * radius
    step = h_top / (cfg.layers - 2)
    heights = np.arange(-1, cfg.layers - 1) * step
    o, d = bank.origins.numpy().astype(np.float64), bank.dirs.numpy().astype(np.float64)
    e = d @ basis[2]
    t = -(o @ basis[2]) / np.where(np.abs(e) < 1e-9, 1e-9, e)
    hit = (o + t[:, None] * d - center)[t > 0]
    reach = np.percentile(np.abs(hit @ basis[:2].T), 99) if len(hit) else 4 * radius
    half = float(np.clip(reach * 1.05, 2 * radius, 0.5 * r_out))
    lay = torch.zeros(cfg.layers, layer_px, layer_px, 4)
    lay[..., 3] = -4.0
    env = torch.zeros(max(4, cfg.env_width // 2), cfg.env_width, 4)
    env[..., :3] = torch.logit(bank.rgb.mean(0).clamp(0.02, 0.98))
    f32 = {"dtype": torch.float32, "device": device}
    return LayerField(lay.to(device), env.to(device), torch.tensor(center, **f32), torch.tensor(basis, **f32),
                      torch.tensor(heights, **f32), half, r_out)


# --------------------------------------------------------------------------- training data
def training_size(cfg: BackgroundConfig, matte_px: int, crop_fill: float, window_px: float) -> int:
    """Side (pixels) of the training crops for crops matted at ``matte_px`` pixels with the object
    sphere filling ``crop_fill`` of them, whose windows span ``window_px`` source pixels (median).

    The field learns the room at the size of a matte pixel, so the board's pattern right behind
    the object comes out as sharp as the matte compares it; never finer than the footage (one
    training pixel per source pixel) nor coarser than ``cfg.train_size``. At 64 px the 640x480
    capture's 256 px mattes met a room blurred over 3-4 of their pixels: 128 px crops'
    background near the outline 24-25 dB in frames where the board shows behind the object,
    28-32 dB at 160 px; crops against the truth +0.9 dB on white (docs/benchmarks.md, issue 4).
    """
    want = matte_px * cfg.train_fill / crop_fill
    footage = window_px * crop_fill / cfg.train_fill      # the training window in source pixels
    return int(round(max(cfg.train_size, min(want, footage))))


@dataclass(frozen=True)
class TrainingView:
    """A source frame to learn from: RGB (H, W, 3) uint8, its (possibly distorted) camera, OpenCV c2w."""

    image: np.ndarray
    intr: Intrinsics
    c2w: np.ndarray


def view_rays(view: TrainingView, center: np.ndarray, radius: float, up: np.ndarray, size: int, fill: float,
              drop_sphere: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One frame's training rays: its crop window cut at ``size`` pixels (pure function).

    Returns origins, dirs (M, 3) float32 and colours (M, 3) float32 in 0..1; pixels outside the
    frame are left out, and with ``drop_sphere`` (a radius factor) so is every pixel whose ray
    passes within ``drop_sphere * radius`` of the centre (the object is in this frame).
    """
    cam = crop_camera(view.c2w, view.intr, center, radius, up, size, fill)
    rgb, touched = cut_crop(view.image, cam, view.intr, view.c2w)
    keep = np.ones(rgb.shape[0] * rgb.shape[1], bool)
    if touched:  # only then can pixels lie outside the frame
        mask, _ = cut_crop(np.full(view.image.shape[:2], 255, np.uint8), cam, view.intr, view.c2w)
        keep = mask.reshape(-1) == 255
    o, d = _flat_rays(cam)
    if drop_sphere is not None:
        oc = center - o
        along = (oc * d).sum(1)
        miss2 = (oc * oc).sum(1) - along ** 2
        keep &= miss2 > (drop_sphere * radius) ** 2
    cols = rgb.reshape(-1, 3)[keep].astype(np.float32) / 255.0
    return o[keep].astype(np.float32), d[keep].astype(np.float32), cols


@dataclass
class RayBank:
    origins: torch.Tensor
    dirs: torch.Tensor
    rgb: torch.Tensor

    @property
    def n(self) -> int:
        return int(self.rgb.shape[0])


def build_bank(views: Iterable[TrainingView], center: np.ndarray, radius: float, up: np.ndarray,
               cfg: BackgroundConfig, drop_sphere: bool,
               tick: Callable[[], None] | None = None, allow_empty: bool = False) -> RayBank:
    parts = []
    for v in views:
        parts.append(view_rays(v, center, radius, up, cfg.train_size, cfg.train_fill,
                               cfg.sphere_margin if drop_sphere else None))
        if tick:
            tick()
    if not parts:
        if allow_empty:
            return RayBank(torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0, 3))
        raise DbbError("no posed frames to learn the background from")
    o, d, c = (torch.from_numpy(np.concatenate(x)) for x in zip(*parts))
    return RayBank(o, d, c)


def with_env_depth(fld: LayerField, bank: RayBank, n_depths: int) -> LayerField:
    """``fld`` with its far sphere made a depth panorama (:func:`env_depth_sweep`), each texel
    starting at the mean colour of the rays that land on it."""
    depth, mean, cnt = env_depth_sweep(fld, bank, n_depths)
    env = fld.env.clone()
    seen = torch.from_numpy(cnt > 0)
    start = torch.logit(torch.from_numpy(mean).clamp(0.01, 0.99)).to(env)
    env[..., :3] = torch.where(seen[..., None].to(env.device), start, env[..., :3])
    return LayerField(fld.layers, env, fld.center, fld.basis, fld.heights, fld.half, fld.r_out, fld.guess, depth)


# --------------------------------------------------------------------------- photo-consistency start
def photo_init(fld: LayerField, views: list[TrainingView], exclude_radius: float | None = None,
               max_views: int = 24, sharpness: float = 0.04) -> LayerField:
    """Plane sweep: every layer texel takes the mean colour of its point seen in up to
    ``max_views`` views, and an opacity that is high where those colours agree (a surface) and
    low where they do not (empty space). Training then starts near the answer.

    ``exclude_radius``: a view whose ray to the point passes this close to the object centre
    does not count (the object stands there in the object video).
    """
    import cv2

    pick = np.unique(np.linspace(0, len(views) - 1, min(max_views, len(views))).round().astype(int))
    s = fld.s
    g = (np.arange(s) + 0.5) / s * 2 * fld.half - fld.half
    vv, uu = np.meshgrid(g, g, indexing="ij")
    basis = fld.basis.cpu().numpy().astype(np.float64)
    center = fld.center.cpu().numpy().astype(np.float64)
    h0 = center @ basis[2]
    layers = fld.layers.clone()
    guess = None
    for li, hgt in enumerate(fld.heights.cpu().numpy().astype(np.float64)):
        pts = center + uu.reshape(-1, 1) * basis[0] + vv.reshape(-1, 1) * basis[1] + (hgt - h0) * basis[2]
        s1, s2, cnt = np.zeros((len(pts), 3)), np.zeros((len(pts), 3)), np.zeros(len(pts))
        for vi in pick:
            v = views[vi]
            eye = v.c2w[:3, 3]
            ok = (pts - eye) @ v.c2w[:3, 2] > 1e-3
            if exclude_radius is not None:
                d = pts - eye
                d /= np.linalg.norm(d, axis=1, keepdims=True)
                oc = center - eye
                along = d @ oc
                ok &= ~((along > 0) & ((oc @ oc) - along ** 2 < exclude_radius ** 2))
            uv = np.clip(project_points(pts, v.c2w, v.intr), -1e6, 1e6).astype(np.float32)  # behind: far off
            hh, ww = v.image.shape[:2]
            ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= ww - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= hh - 1)
            col = cv2.remap(v.image, uv[:, 0].reshape(s, s), uv[:, 1].reshape(s, s), cv2.INTER_LINEAR)
            col = col.reshape(-1, 3).astype(np.float64) / 255.0
            s1[ok] += col[ok]
            s2[ok] += col[ok] ** 2
            cnt[ok] += 1
        seen = cnt >= 2
        mean = np.clip(s1 / np.maximum(cnt, 1)[:, None], 0.01, 0.99)
        var = (s2 / np.maximum(cnt, 1)[:, None] - mean ** 2).sum(1).clip(0)
        # Unseen texels start transparent: where the object stands (no clean plate), nothing is
        # known, and a grey haze there would tint every ray through the object's disc.
        alpha = np.clip(np.where(seen, 0.9 * np.exp(-var / sharpness ** 2), 0.001), 0.001, 0.99)
        if abs(hgt) < 1e-9:
            # The board plane: the board is an opaque plane there, and so most likely is what it
            # lies on. Its fine high-contrast texture would fail the agreement test under
            # sub-pixel pose noise, so it starts opaque wherever seen, and where the object
            # hides it from every view the surface around is continued into the gap.
            alpha = np.where(seen, 0.95, alpha)
            hole = ~seen.reshape(s, s)
            if hole.any() and seen.any():
                img = np.round(mean.reshape(s, s, 3) * 255).astype(np.uint8)
                filled = cv2.inpaint(img, hole.astype(np.uint8), 5, cv2.INPAINT_TELEA).reshape(-1, 3)
                mean = np.where(seen[:, None], mean, np.clip(filled / 255.0, 0.01, 0.99))
                near = cv2.dilate(seen.reshape(s, s).astype(np.uint8), np.ones((3, 3), np.uint8),
                                  iterations=max(1, s // 8)).reshape(-1).astype(bool)
                alpha = np.where(near, 0.95, alpha)   # only the gap under the object, not the whole square
                # Remembered: the matte cannot trust the prediction where the plane is a guess.
                guess = torch.from_numpy((near & ~seen).reshape(s, s).astype(np.float32))
                seen = near
        t = layers[li].view(-1, 4)
        t[:, :3] = torch.from_numpy(np.where(seen[:, None], np.log(mean / (1 - mean)), 0.0)).float()
        t[:, 3] = torch.from_numpy(np.log(alpha / (1 - alpha))).float()
    return LayerField(layers, fld.env.clone(), fld.center, fld.basis, fld.heights, fld.half, fld.r_out,
                      guess if exclude_radius is not None else None, fld.env_depth)


# --------------------------------------------------------------------------- training
@dataclass
class TrainLog:
    steps: int = 0
    seconds: float = 0.0
    psnr: float = float("nan")
    history: list[dict] = field(default_factory=list)


def _tv(fld: LayerField, n: int, gen: torch.Generator) -> torch.Tensor:
    """Total variation over random layer texel neighbourhoods (smooths texels few rays see)."""
    s = fld.s
    r = torch.randint(0, fld.n_layer_rows, (n,), generator=gen)
    right = torch.where(r % s < s - 1, r + 1, r)
    down = torch.where((r // s) % s < s - 1, r + s, r)
    v = fld.table.gather(torch.stack([r, right, down], 1))
    return ((v[:, 0] - v[:, 1]) ** 2).mean() + ((v[:, 0] - v[:, 2]) ** 2).mean()


def train_field(fld: LayerField, bank: RayBank, cfg: BackgroundConfig,
                on_step: Callable[[TrainLog, float], None] | None = None,
                coarse: bool = True) -> tuple[LayerField, TrainLog]:
    """Fit ``fld`` to the bank's rays (MSE), coarse to fine: half, then full layer size
    (``coarse`` False: full size throughout, to refine a trained field)."""
    if bank.n < 1000:
        raise DbbError(f"only {bank.n} rays to learn the background from: too little of the room is seen")
    gen = torch.Generator().manual_seed(cfg.seed)
    dev = fld.device
    levels = [max(16, fld.s // 2), fld.s]
    level = 0 if coarse else 1
    fld = fld.resized(levels[level])
    log = TrainLog()
    t0 = time.monotonic()
    while True:
        seconds = time.monotonic() - t0
        frac = (log.steps / cfg.steps) if cfg.steps else seconds / (cfg.minutes * 60)
        if frac >= 1.0:
            break
        if frac >= 0.4 and level == 0:
            level = 1
            fld = fld.resized(levels[1])
        idx = torch.randint(0, bank.n, (cfg.batch_rays,), generator=gen)
        pred = fld.composite(bank.origins[idx].to(dev), bank.dirs[idx].to(dev))
        mse = F.mse_loss(pred, bank.rgb[idx].to(dev))
        loss = mse + cfg.tv_weight * _tv(fld, 16384, gen) if cfg.tv_weight > 0 else mse
        loss.backward()
        fld.table.adam_step(cfg.lr)
        log.steps += 1
        p = -10 * math.log10(max(float(mse.detach()), 1e-10))
        log.psnr = p if math.isnan(log.psnr) else 0.9 * log.psnr + 0.1 * p
        if log.steps % 25 == 0:
            log.history.append({"step": log.steps, "seconds": round(time.monotonic() - t0, 2),
                                "psnr": round(log.psnr, 3)})
        if on_step:
            on_step(log, min(frac, 1.0))
    log.seconds = time.monotonic() - t0
    if level == 0:  # a budget that ended early still delivers a full-size field
        fld = fld.resized(levels[1])
    return fld, log


# --------------------------------------------------------------------------- the model
@dataclass
class BackgroundModel:
    """A trained background field and how it was made."""

    field: LayerField
    mode: str                  # "clean plate" or "object video"
    frames: int
    rays: int
    log: TrainLog
    cfg: BackgroundConfig
    refine: TrainLog | None = None   # the second training on the rays the first mattes call room

    def render(self, cam: CropCamera) -> np.ndarray:
        """Predicted background (H, W, 3) uint8 in a crop camera (never the full frame)."""
        return self.field.render(cam)

    def guessed(self, cam: CropCamera) -> np.ndarray:
        """Pixels (H, W) bool of a crop camera where the prediction is a guess (see LayerField.guessed)."""
        return self.field.guessed(cam)

    def save(self, path: Path) -> None:
        torch.save({"field": self.field.state(), "mode": self.mode, "frames": self.frames, "rays": self.rays,
                    "cfg": asdict(self.cfg), "steps": self.log.steps, "psnr": self.log.psnr,
                    "refine": asdict(self.refine) if self.refine is not None else None}, path)

    @classmethod
    def load(cls, path: Path, device: torch.device | str = "cpu") -> BackgroundModel:
        try:
            st = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as e:  # noqa: BLE001 - any unreadable file is the same user error
            raise DbbError(f"cannot read the background model {path}: {e}") from None
        log = TrainLog(steps=st["steps"], psnr=st["psnr"])
        known = set(BackgroundConfig.__dataclass_fields__)
        ref = TrainLog(**st["refine"]) if st.get("refine") else None
        return cls(LayerField.from_state(st["field"], device), st["mode"], st["frames"], st["rays"], log,
                   BackgroundConfig(**{k: v for k, v in st["cfg"].items() if k in known}), ref)


def parallax_coverage(c2ws: np.ndarray, center: np.ndarray, radius: float, up: np.ndarray,
                      min_views: int = 2, max_views: int = 60) -> float:
    """How much of what the object hides can other views see: median over views of the fraction.

    For a view, the board-plane points hidden behind the object's sphere (its disc, a grid of
    rays) but outside the sphere itself are what the matte needs predicted there; a point counts
    as seen when at least ``min_views`` other views reach it with a ray that misses the sphere.
    Points under the object (inside the sphere) are left out: nothing ever sees them.
    """
    c2ws = np.asarray(c2ws)
    if len(c2ws) > max_views:
        c2ws = c2ws[np.linspace(0, len(c2ws) - 1, max_views).round().astype(int)]
    eyes = c2ws[:, :3, 3]
    g = np.linspace(-1, 1, 9)
    gx, gy = np.meshgrid(g, g)
    disc = np.stack([gx.ravel(), gy.ravel()], 1)
    disc = disc[(disc ** 2).sum(1) <= 1]
    fractions = []
    for i, e in enumerate(eyes):
        v = center - e
        D = float(np.linalg.norm(v))
        if D <= radius:
            continue
        z = v / D
        x = np.cross(z, up)
        if np.linalg.norm(x) < 1e-9:
            x = np.cross(z, [1.0, 0.0, 0.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        tan_a = radius / np.sqrt(D * D - radius * radius)
        d = z + tan_a * (disc[:, :1] * x + disc[:, 1:] * y)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        du = d @ up
        ok = du < -1e-9                                  # rays going down toward the plane
        t = -(e @ up) / np.where(ok, du, -1.0)
        pts = e + t[:, None] * d
        ok &= np.linalg.norm(pts - center, axis=1) > radius
        if not ok.any():
            continue
        pts = pts[ok]
        others = np.delete(eyes, i, 0)
        seg = pts[None] - others[:, None]                # (V, P, 3) from each other eye to each point
        L = np.linalg.norm(seg, axis=2)
        u = seg / L[..., None]
        oc = center - others
        along = np.einsum("vpk,vk->vp", u, oc)
        miss = ((oc * oc).sum(1)[:, None] - along ** 2 > radius ** 2) | (along < 0) | (along > L)
        fractions.append(float((miss.sum(0) >= min_views).mean()))
    return float(np.median(fractions)) if fractions else 0.0


def train_background(views: Iterable[TrainingView], n_views: int, center: np.ndarray, radius: float,
                     up: np.ndarray, clean_plate: bool, cfg: BackgroundConfig = BackgroundConfig(),
                     device: torch.device | str = "cpu",
                     on_step: Callable[[TrainLog, float], None] | None = None,
                     tick: Callable[[], None] | None = None,
                     room_views: Iterable[TrainingView] = ()) -> BackgroundModel:
    """Train the background field from ``n_views`` posed views of the clean plate (``clean_plate``)
    or of the object video (rays through the object's sphere are then left out).

    ``room_views``: with a clean plate, views of the object video too, whose rays that pass the
    object's sphere (beyond ``sphere_margin * radius``) join the plate's. A plate filmed along
    another path leaves the room behind the object unseen from some of the video's viewpoints
    (seed-41 capture: video frames 31-41 degrees from every plate view, the room near the object's
    outline predicted at 25 dB against 30-44 elsewhere, the matte cut the object's top); the
    video itself sees the room around the object from exactly there.

    ``views`` is consumed once, as a stream: only each view's training crop and a few whole
    frames for the plane sweep are kept, so long 4K footage does not fill the memory.
    """
    keep = set(np.linspace(0, max(n_views - 1, 0), min(24, max(n_views, 1))).round().astype(int).tolist())
    init_views: list[TrainingView] = []
    c2ws = []

    def stream():
        for i, v in enumerate(views):
            c2ws.append(v.c2w)
            if i in keep:
                init_views.append(v)
            yield v

    bank = build_bank(stream(), center, radius, up, cfg, drop_sphere=not clean_plate, tick=tick)
    if clean_plate:
        extra = build_bank(room_views, center, radius, up, cfg, drop_sphere=True, tick=tick, allow_empty=True)
        if extra.n:
            bank = RayBank(*(torch.cat([a, b]) for a, b in ((bank.origins, extra.origins), (bank.dirs, extra.dirs),
                                                            (bank.rgb, extra.rgb))))
    exclude = None if clean_plate else cfg.sphere_margin * radius
    fld = new_field(cfg, center, radius, up, np.stack(c2ws), bank, cfg.layer_px // 2, device)
    if cfg.env_depths > 0:
        fld = with_env_depth(fld, bank, cfg.env_depths)
    fld = photo_init(fld, init_views, exclude).resized(cfg.layer_px)
    fld, log = train_field(fld, bank, cfg, on_step)
    return BackgroundModel(fld, "clean plate" if clean_plate else "object video", len(c2ws), bank.n, log, cfg)


# --------------------------------------------------------------------------- without a plate: train again
def room_rays(cam: CropCamera, observed: np.ndarray, alpha: np.ndarray, inside: np.ndarray | None,
              grow_px: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A matted crop's room rays (pure function): origins, dirs (M, 3) float32 and colours (M, 3)
    float32 0..1 of the pixels of ``observed`` (S, S, 3) uint8 that ``alpha`` (S, S) uint8 calls
    room, at least ``grow_px`` pixels from anything it calls object, inside the frame (``inside``
    (S, S) uint8, 255 inside, or None)."""
    import cv2

    k = 2 * grow_px + 1
    room = cv2.dilate((alpha > 0).astype(np.uint8), np.ones((k, k), np.uint8)) == 0
    if inside is not None:
        room &= inside == 255
    keep = room.reshape(-1)
    o, d = _flat_rays(cam)
    return (o[keep].astype(np.float32), d[keep].astype(np.float32),
            observed.reshape(-1, 3)[keep].astype(np.float32) / 255.0)


def refine_on_room(model: BackgroundModel, rays: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]],
                   on_step: Callable[[TrainLog, float], None] | None = None) -> BackgroundModel:
    """Without a clean plate: the field trained again (full size, ``refine_share`` of its budget) on the room
    rays of the first mattes (:func:`room_rays`), which pass through the object's sphere wherever
    the object is not: the table right behind and under a moving object, which the first
    training had to leave out, gets its own texture, and stops being a guess where at least
    two of those rays reach the board plane."""
    parts = list(rays)
    if not parts:
        return model
    o, d, c = (torch.from_numpy(np.concatenate(x)) for x in zip(*parts))
    bank = RayBank(o, d, c)
    if bank.n < 1000:
        return model
    cfg = model.cfg
    fld = model.field
    if fld.guess is not None:
        t, pu, pv = fld.board_hits(*fld.local_rays(o.numpy(), d.numpy()))
        g = fld.guess.shape[0]
        gx = np.floor(pu / fld.half * 0.5 * g + 0.5 * g).astype(np.int64)
        gy = np.floor(pv / fld.half * 0.5 * g + 0.5 * g).astype(np.int64)
        ok = (t > 0) & (gx >= 0) & (gx < g) & (gy >= 0) & (gy < g)
        hits = np.bincount(gy[ok] * g + gx[ok], minlength=g * g).reshape(g, g)
        guess = fld.guess * torch.from_numpy(hits < 2).to(fld.guess)
        fld = LayerField(fld.layers, fld.env, fld.center, fld.basis, fld.heights, fld.half, fld.r_out, guess,
                         fld.env_depth)
    budget = replace(cfg, minutes=cfg.refine_share * cfg.minutes,
                     steps=max(1, round(cfg.refine_share * cfg.steps)) if cfg.steps else None)
    fld, log = train_field(fld, bank, budget, on_step, coarse=False)
    return BackgroundModel(fld, model.mode, model.frames, model.rays, model.log, model.cfg, log)


def _flat_rays(cam) -> tuple[np.ndarray, np.ndarray]:
    """Origins and unit directions (H*W, 3) float64 in the board frame of a crop camera ``cam``."""
    o, d = pixel_rays(cam.intr, cam.c2w, np.float64)
    return o.reshape(-1, 3), d.reshape(-1, 3)
