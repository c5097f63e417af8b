"""Training rays of the static field: the ray bank, each ray's target, its robust weight, carving.

Every training pixel becomes a world ray with its straight RGBA (and, for preprocess crops, the
observed colour and the room predicted behind it); :func:`ray_targets` decides what each drawn
ray is compared with, :func:`robust_weights` how much it counts, and :func:`carve_mask` which
lattice points the views' alpha clears.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..core.errors import DbbError
from ..datasets.images import load_rgb, load_rgba
from ..datasets.records import Frame, ObjectVolume
from ..geometry.cameras import Intrinsics, project_points, scaled_intrinsics
from ..geometry.rays import pixel_rays
from ..geometry.transforms import invert_rigid
from .field import FieldConfig


@dataclass
class Silhouettes:
    """The training views' alpha (each (h, w) uint8, 255 = opaque) and cameras (OpenCV c2w (4, 4),
    intrinsics at the alpha's size): what :func:`carve_mask` asks which points the views see empty."""

    alphas: list[np.ndarray]
    cameras: list[tuple[np.ndarray, Intrinsics]]


@dataclass
class RayBank:
    """Every training pixel as a ray: origins, unit directions (N, 3) world; straight RGBA (N, 4);
    for preprocess crops also the observed RGB and the predicted room's RGB (N, 3), else None;
    for robust training each ray's running squared error (N,) (NaN until first rendered)."""

    origins: torch.Tensor
    dirs: torch.Tensor
    rgba: torch.Tensor
    observed: torch.Tensor | None = None
    room: torch.Tensor | None = None
    error: torch.Tensor | None = None
    views: Silhouettes | None = None

    @property
    def n(self) -> int:
        return int(self.origins.shape[0])

    def record_errors(self, pick: torch.Tensor, rgb: torch.Tensor, alpha: torch.Tensor, bg: torch.Tensor,
                      keep: float = 0.5) -> None:
        """Fold the rays ``pick`` (B,) as just rendered into their running error (:attr:`error`):
        ``rgb`` (B, 3) composited over ``bg`` (B, 3), ``alpha`` (B,). The error is the squared
        premultiplied-colour difference (summed over RGB) plus the squared alpha difference to
        the ray's straight RGBA target, so the random background does not enter it; it replaces
        ``1 - keep`` of the previous value."""
        if self.error is None:
            self.error = torch.full((self.n,), float("nan"))
        t = self.rgba[pick]
        pm = rgb - (1 - alpha[:, None]) * bg
        e = ((pm - t[:, :3] * t[:, 3:]) ** 2).sum(-1) + (alpha - t[:, 3]) ** 2
        old = self.error[pick]
        self.error[pick] = torch.where(old.isnan(), e, keep * old + (1 - keep) * e)


def frame_tensors(frame: Frame, downscale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(origins, dirs, rgba) of one frame at 1/downscale size, each (h, w, C) float32."""
    rgba = load_rgba(frame, downscale)
    o, d = pixel_rays(scaled_intrinsics(frame.intr, downscale), frame.c2w)
    return o, d, rgba


def build_ray_bank(frames: list[Frame], downscale: float, volume: ObjectVolume | None = None,
                   mode: str = "object", observed: bool = True) -> RayBank:
    """All pixels of ``frames``; in object mode, rays that miss the object sphere are dropped
    (they only ever see the background, which the random-background loss already covers), and
    the views' alpha is kept for carving (:attr:`RayBank.views`). With ``observed``, frames that
    name their observed crop and predicted room (preprocess crops) add them to the bank
    (:attr:`.field.FieldConfig.observed_loss` uses them)."""
    # Frames without them (a crop past the frame's border) get NaN rows: the matte alone.
    has_room = [f.observed_path is not None and f.background_path is not None for f in frames]
    with_room = observed and mode == "object" and any(has_room)
    os_, ds, cs, seen, rooms, alphas = [], [], [], [], [], []
    for f, known in zip(frames, has_room):
        o, d, c = frame_tensors(f, downscale)
        alphas.append(np.round(c[..., 3] * 255).astype(np.uint8))
        o, d, c = o.reshape(-1, 3), d.reshape(-1, 3), c.reshape(-1, 4)
        hit = np.ones(len(o), bool)
        if mode == "object" and volume is not None:
            oc = o - np.asarray(volume.center, np.float32)
            b = (oc * d).sum(-1)
            hit = b * b - ((oc * oc).sum(-1) - volume.radius ** 2) > 0
        os_.append(o[hit])
        ds.append(d[hit])
        cs.append(c[hit])
        if with_room:
            unknown = np.full((int(hit.sum()), 3), np.nan, np.float32)
            seen.append(load_rgb(f.observed_path, f.intr, downscale).reshape(-1, 3)[hit] if known else unknown)
            rooms.append(load_rgb(f.background_path, f.intr, downscale).reshape(-1, 3)[hit] if known else unknown)
    if not os_ or sum(len(o) for o in os_) == 0:
        raise DbbError("no training rays: no frame sees the object volume")

    def cat(xs: list[np.ndarray]) -> torch.Tensor | None:
        return torch.from_numpy(np.concatenate(xs)) if xs else None

    views = None
    if mode == "object":
        views = Silhouettes(alphas, [(f.c2w, scaled_intrinsics(f.intr, downscale)) for f in frames])
    return RayBank(cat(os_), cat(ds), cat(cs), cat(seen), cat(rooms), views=views)


def ray_targets(rgba: torch.Tensor, bg: torch.Tensor, observed: torch.Tensor | None, room: torch.Tensor | None,
                cfg: FieldConfig, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Background and target colour (B, 3) of each training ray.

    ``rgba`` (B, 4) straight RGBA (a matte's alpha for crops), ``bg`` (B, 3) random colours:
    the target is ``rgba`` composited over ``bg``. With ``observed`` / ``room`` (B, 3) (see
    :attr:`.field.FieldConfig.observed_loss`), a ray instead renders over the predicted room and
    is compared with the observed pixel, except with probability ``matte_prior * (1 - diff /
    decisive_diff)`` (clipped at 0), ``diff`` the largest RGB difference observed - room: where
    colour cannot tell object from room, the matte decides; so it does where its alpha is at least
    ``matte_opaque``. Rays with NaN ``observed`` take the matte.
    """
    target = rgba[:, :3] * rgba[:, 3:] + (1 - rgba[:, 3:]) * bg
    if observed is None or room is None or not cfg.observed_loss:
        return bg, target
    diff = (observed - room).abs().amax(-1)
    p_matte = cfg.matte_prior * (1 - diff / max(cfg.decisive_diff, 1e-6)).clamp(0, 1)
    p_matte = torch.where(rgba[:, 3] >= cfg.matte_opaque, torch.ones_like(p_matte), p_matte)
    use_seen = (torch.rand(diff.shape[0], generator=gen) >= p_matte.cpu()).to(rgba.device) & diff.isfinite()
    use_seen = use_seen[:, None]
    return torch.where(use_seen, room, bg), torch.where(use_seen, observed, target)


def robust_weights(error: torch.Tensor, scale: float) -> torch.Tensor:
    """IRLS weights (B,) of the Cauchy loss for rays with running squared errors ``error`` (B,):
    ``1 / (1 + error / scale^2)``; rays not yet rendered (NaN) weigh 1."""
    w = 1.0 / (1.0 + error / (scale * scale))
    return torch.where(error.isnan(), torch.ones_like(w), w)


def carve_mask(views: Silhouettes, points: np.ndarray, cell: float, share: float, min_views: int = 3,
               empty_alpha: float = 0.1) -> np.ndarray:
    """Which world points (M, 3) the views carve away: (M,) bool, True where at least ``share``
    of the views that see the point (it projects inside the image, in front of the camera), and
    at least ``min_views`` of them, find alpha below ``empty_alpha`` everywhere within one pixel
    plus half the point's footprint (a cube of side ``cell`` world units) of where it projects.
    So a point is only carved where views clearly see through it: pose and resampling errors of
    a pixel, and holes that fewer views than ``share`` have, keep it."""
    import cv2

    seen = np.zeros(len(points), np.int32)
    empty = np.zeros(len(points), np.int32)
    for a, (c2w, intr) in zip(views.alphas, views.cameras):
        w2c = invert_rigid(c2w)
        z = points @ w2c[:3, :3].T[:, 2] + w2c[2, 3]
        front = z > 1e-6
        if not front.any():
            continue
        # Dilate by the footprint of a cell at the view's median depth (plus one pixel).
        r = 1 + int(math.ceil(0.5 * cell * 0.5 * (intr.fx + intr.fy) / float(np.median(z[front]))))
        wide = cv2.dilate(a, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
        uv = project_points(points[front], c2w, intr)
        iu, iv = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
        inside = (iu >= 0) & (iu < a.shape[1]) & (iv >= 0) & (iv < a.shape[0])
        idx = np.nonzero(front)[0][inside]
        seen[idx] += 1
        empty[idx] += wide[iv[inside], iu[inside]] < 255 * empty_alpha
    return (empty >= min_views) & (empty >= share * seen)
