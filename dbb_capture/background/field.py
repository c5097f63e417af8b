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

import numpy as np
import torch
import torch.nn.functional as F

from ..core.row_table import RowTable
from ..crops.camera import CropCamera
from ..geometry.rays import pixel_rays
from .panorama import env_coords


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
        o, d = flat_rays(cam)
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
        t, pu, pv = self.board_hits(*self.local_rays(*flat_rays(cam)))
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


def flat_rays(cam) -> tuple[np.ndarray, np.ndarray]:
    """Origins and unit directions (H*W, 3) float64 in the board frame of a crop camera ``cam``."""
    o, d = pixel_rays(cam.intr, cam.c2w, np.float64)
    return o.reshape(-1, 3), d.reshape(-1, 3)
