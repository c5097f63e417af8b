"""Alpha mattes from an observation and a predicted background (thesis 6.1.3).

Pure functions over arrays, one crop at a time: the background model renders what the room
looks like behind the object in a crop camera; the matte is where the observation differs.

    d      = robust colour distance(observed, predicted)  (min over 1-px shifts of the prediction,
             so a slightly blurred or misaligned prediction does not light up edges)
    alpha  = soft threshold of d (thresholds from the noise level measured outside the object)
             restricted to the projected bounding sphere, raised by its edge-aware (guided,
             the observed crop as guide) smoothing where d shows any difference,
    then     morphology (drop specks, fill holes), fractional alpha at the edges from the
             compositing equation, and colour decontamination so edge pixels carry the
             object's colour, not the room's.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class MatteConfig:
    """Thresholds in units of the measured noise level; areas as fractions of the disc."""

    low_sigmas: float = 3.0        # below: background
    high_sigmas: float = 6.0       # above: object
    min_threshold: float = 0.035   # colour distance floor (0..1 RGB scale)
    shift_px: int = 1              # robustness to misregistration of the prediction
    disc_margin: float = 1.04      # the sphere's disc, slightly enlarged
    min_blob: float = 0.01         # components smaller than this fraction of the largest are dropped
    edge_px: int = 1               # width of the band where alpha is fractional
    guided_px: int = 3             # edge-aware smoothing of the soft alpha before the decision (0: off)
    guided_eps: float = 1e-3


def sphere_disc(size: int, fill: float, margin: float = 1.0) -> np.ndarray:
    """Mask (size, size) bool of the bounding sphere's projection in a crop (centred circle)."""
    c = (size - 1) / 2
    yy, xx = np.mgrid[0:size, 0:size]
    return (xx - c) ** 2 + (yy - c) ** 2 <= (fill * size / 2 * margin) ** 2


def colour_distance(observed: np.ndarray, predicted: np.ndarray, shift_px: int = 1) -> np.ndarray:
    """Per-pixel distance (H, W) float32 between RGB images (H, W, 3) uint8, 0..~1.7.

    The minimum over shifts of the prediction by up to ``shift_px`` pixels: a thin edge in the
    room that the prediction places one pixel off does not count as object.
    """
    o = observed.astype(np.float32) / 255.0
    p = predicted.astype(np.float32) / 255.0
    best = np.full(o.shape[:2], np.inf, np.float32)
    pad = cv2.copyMakeBorder(p, shift_px, shift_px, shift_px, shift_px, cv2.BORDER_REPLICATE)
    h, w = o.shape[:2]
    for dy in range(-shift_px, shift_px + 1):
        for dx in range(-shift_px, shift_px + 1):
            q = pad[shift_px + dy:shift_px + dy + h, shift_px + dx:shift_px + dx + w]
            np.minimum(best, np.sqrt(((o - q) ** 2).sum(-1)), out=best)
    return best


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """Fill regions not connected to the border (an object's colour can match the room)."""
    h, w = mask.shape
    flood = np.zeros((h + 2, w + 2), np.uint8)
    flood[1:-1, 1:-1] = mask
    ff = flood.copy()
    cv2.floodFill(ff, np.zeros((h + 4, w + 4), np.uint8), (0, 0), 1)
    holes = ff[1:-1, 1:-1] == 0
    return mask | holes


def _keep_large(mask: np.ndarray, min_blob: float) -> np.ndarray:
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 2:
        return mask
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = np.flatnonzero(areas >= min_blob * areas.max()) + 1
    return np.isin(lab, keep)


def _edge_alpha(observed: np.ndarray, predicted: np.ndarray, core: np.ndarray, edge_px: int) -> np.ndarray:
    """Fractional alpha (H, W) float32 in a band around ``core`` by the compositing equation.

    With the object's colour F taken from the nearest surely-inside pixel and the background
    B predicted, observed I = a F + (1 - a) B gives a = (I - B).(F - B) / |F - B|^2.
    """
    from scipy.ndimage import distance_transform_edt

    k = np.ones((3, 3), np.uint8)
    inside = cv2.erode(core.astype(np.uint8), k, iterations=edge_px).astype(bool)
    band = cv2.dilate(core.astype(np.uint8), k, iterations=edge_px).astype(bool) & ~inside
    alpha = inside.astype(np.float32)
    if not inside.any() or not band.any():
        return core.astype(np.float32)
    _, (iy, ix) = distance_transform_edt(~inside, return_indices=True)
    obs = observed.astype(np.float32)
    # The object's colour near each edge pixel: a local mean over surely-inside pixels (less noise).
    w = cv2.blur(inside.astype(np.float32), (3, 3))
    local = cv2.blur(obs * inside[..., None], (3, 3)) / np.maximum(w, 1e-6)[..., None]
    I = obs[band]
    B = predicted.astype(np.float32)[band]
    F = local[iy[band], ix[band]]
    fb = F - B
    denom = (fb * fb).sum(-1)
    a = ((I - B) * fb).sum(-1) / np.maximum(denom, 1e-6)
    # Where object and room look alike the equation says nothing: keep the hard decision.
    a = np.where(denom > 30.0 ** 2, np.clip(a, 0, 1), core[band].astype(np.float32))
    alpha[band] = a
    return alpha


def matte(observed: np.ndarray, predicted: np.ndarray, disc: np.ndarray,
          cfg: MatteConfig = MatteConfig()) -> np.ndarray:
    """Straight RGBA (H, W, 4) uint8 of the object from ``observed`` (H, W, 3) uint8 and the
    predicted background ``predicted`` (H, W, 3) uint8, inside ``disc`` (H, W) bool."""
    d = colour_distance(observed, predicted, cfg.shift_px)
    outside = ~disc
    # Noise level from where no object can be (robust: median absolute distance).
    # Without enough room outside the disc (a fixed window), the whole crop's median stands in:
    # the room is most of it.
    noise = float(np.median(d[outside] if outside.sum() > 50 else d)) / 0.6745
    t0 = max(cfg.min_threshold, cfg.low_sigmas * noise)
    t1 = max(t0 * 1.5, cfg.high_sigmas * noise)
    alpha = np.clip((d - t0) / (t1 - t0), 0, 1) * disc
    if cfg.guided_px > 0:
        # Edge-aware: alpha spreads within regions the image shows as one surface and stops at
        # its edges, so object areas coloured like the room take the decision of their surroundings.
        guide = observed.astype(np.float32) / 255.0
        # Only raised, and only where the colour differs at all: boundaries stay where the
        # evidence puts them; weak parts inside the object (a dark limb on a dark table) fill in.
        g = cv2.ximgproc.guidedFilter(guide, alpha.astype(np.float32), cfg.guided_px, cfg.guided_eps) * disc
        alpha = np.where(d > t0, np.maximum(alpha, g), alpha)
    core = alpha > 0.5
    core = cv2.morphologyEx(core.astype(np.uint8), cv2.MORPH_OPEN, np.ones((2, 2), np.uint8)).astype(bool)
    if core.any():
        core = _fill_holes(_keep_large(core, cfg.min_blob))
    alpha = _edge_alpha(observed, predicted, core, cfg.edge_px) * disc
    alpha[alpha < 0.02] = 0
    # Decontaminate: observed = a F + (1 - a) B, so F = (observed - (1 - a) B) / a at the edges.
    o = observed.astype(np.float32)
    b = predicted.astype(np.float32)
    a = alpha[..., None]
    fg = np.where(a > 0.15, (o - (1 - a) * b) / np.maximum(a, 1e-3), o)
    rgba = np.concatenate([np.clip(fg, 0, 255), alpha[..., None] * 255], -1)
    return np.round(rgba).astype(np.uint8)
