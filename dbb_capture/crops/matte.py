"""Alpha mattes from an observation and a predicted background (thesis 6.1.3).

Pure functions over arrays, one crop at a time: the background model renders what the room
looks like behind the object in a crop camera; the matte is where the observation differs.

    d      = robust colour distance(observed, predicted)  (min over 1-px shifts of the prediction,
             so a slightly blurred or misaligned prediction does not light up edges)
    alpha  = soft threshold of d (thresholds from the noise level measured outside the object,
             raised per pixel for predicted colours the room around the object shows predicted
             worse) restricted to the projected bounding sphere, raised by its edge-aware (guided,
             the observed crop as guide) smoothing where d shows any difference; where the
             prediction is sound, also the decisions of a sharper distance (a misregistration
             explains only part of a 1-px shift's change, so an object colour that a textured
             room shows within a pixel is not explained away),
    then     morphology (an opening cuts specks and thin misregistration lines apart, small
             pieces are dropped, the object's thin parts grow back from what is kept, holes
             are filled), fractional alpha at the edges from the
             compositing equation, and colour decontamination so edge pixels carry the
             object's colour, not the room's.

Where the prediction is only a guess (without a clean plate, the table right behind the object
that no view saw past it), a difference from it is no evidence of the object: there a pixel
stays object only if the object's colours explain it better than the room's (colour
histograms of this crop: the room from where the decision is sure, the object from the
decided pixels whose colour the room does not show).

A second pass over the whole capture (:class:`CaptureMatte`, learnt from the first mattes) adds
what one crop cannot know: the capture's usual noise level (a crop whose room is partly
predicted badly measures too much noise and loses weak object parts) and the object's colours
from every view (a part coloured like the table, seen only against the guessed table in this
crop, is seen against sound room elsewhere). A temporal median of neighbouring frames' alphas
then removes flicker (the crop follows the object, so its parts stay at nearly the same crop
pixels from frame to frame).
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
    min_blob: float = 0.1          # pieces under this fraction of the largest are dropped (specks; parts stay joined)
    edge_px: int = 1               # width of the band where alpha is fractional
    edge_ramp: tuple[float, float] = (0.0, 1.0)  # the band's alpha mapped linearly from (lo, hi) to (0, 1)
    edge_gain: float = 1.25        # the compositing alpha of a shaded rim runs low (F from inside is brighter): x this
    rim_min_off: float = 0.3       # shaded-rim alpha where the room lies off the object's shading line by this share of |F - B| (inf: off)
    guided_px: int = 3             # edge-aware smoothing of the soft alpha before the decision (0: off)
    guided_eps: float = 1e-3
    colour_bins: int = 32          # per channel, of the room/object colour histograms (8 levels a bin)
    colour_ratio: float = 3.0      # where the prediction is a guess: room if its colours explain a pixel this much better
    sharp_shift: float = 0.25      # share of the prediction's 1-px variation a misregistration may explain (1: off)
    sharp_room_max: float = 0.02   # the sharper distance is used if it adds at most this share of false room core
    guess_margin_px: int = 8       # the sharper distance keeps this far from a guessed prediction
    sharp_min_detail: float = 0.8  # ... and needs a field that keeps this share of the room's 1-px detail
    room_levels: int = 8           # per channel, predicted colours whose room error is measured apart (0: off)
    room_min_px: int = 20          # room pixels a predicted colour needs for its own noise level
    # Matte at 2x where the crop window has this many source px per crop px (crops.matte_scale).
    supersample_between: tuple[float, float] = (1.0, 6.0)
    # At 2x: how many source pixels resampling spreads the outline over, and the band's ramp
    # (crops.matte_config_at).
    supersampled_spread: float = 2.0
    supersampled_ramp: tuple[float, float] = (0.25, 0.75)


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


def local_variation(image: np.ndarray, shift_px: int = 1) -> np.ndarray:
    """Largest colour change (H, W) float32 (0..1 RGB scale) of an RGB image (H, W, 3) uint8 over
    shifts by up to ``shift_px`` pixels: how much a misregistration that small can change it."""
    h, w = image.shape[:2]
    pad = cv2.copyMakeBorder(image.astype(np.float32) / 255.0, shift_px, shift_px, shift_px, shift_px,
                             cv2.BORDER_REPLICATE).transpose(2, 0, 1)     # channels first: sums of 3 planes
    f = pad[:, shift_px:shift_px + h, shift_px:shift_px + w]
    out = np.zeros((h, w), np.float32)
    for dy in range(-shift_px, shift_px + 1):
        for dx in range(-shift_px, shift_px + 1):
            e = f - pad[:, shift_px + dy:shift_px + dy + h, shift_px + dx:shift_px + dx + w]
            np.maximum(out, e[0] * e[0] + e[1] * e[1] + e[2] * e[2], out=out)
    return np.sqrt(out)


def sharp_distance(observed: np.ndarray, predicted: np.ndarray, shifted: np.ndarray,
                   share: float, shift_px: int = 1) -> np.ndarray:
    """A colour distance (H, W) float32 between the robust one and the plain one.

    ``shifted``: :func:`colour_distance` (the minimum over shifts). The minimum over shifts also
    explains away an object colour close to a textured room's (any of 9 room pixels may match
    it); here a misregistration may explain only ``share`` of the prediction's own 1-px change
    (:func:`local_variation`): max(shifted, plain - share * variation). ``share`` 1 gives
    ``shifted`` back (triangle inequality), 0 the plain distance.
    """
    plain = colour_distance(observed, predicted, 0)
    return np.maximum(shifted, plain - share * local_variation(predicted, shift_px))


def _soft_alpha(d: np.ndarray, t0: float | np.ndarray, t1: float | np.ndarray, disc: np.ndarray,
                observed: np.ndarray, cfg: MatteConfig) -> np.ndarray:
    """Soft threshold of the distance ``d`` (H, W) inside ``disc`` (thresholds scalars or per
    pixel), raised by its edge-aware smoothing."""
    alpha = np.clip((d - t0) / (t1 - t0), 0, 1) * disc
    if cfg.guided_px > 0:
        # Edge-aware: alpha spreads within regions the image shows as one surface and stops at
        # its edges, so object areas coloured like the room take the decision of their surroundings.
        guide = observed.astype(np.float32) / 255.0
        # Only raised, and only where the colour differs at all (half the low threshold, 1.5
        # noise sigmas): boundaries stay where the evidence puts them; weak parts inside the
        # object (a dark limb on a dark table, a stripe of the table's colour) fill in.
        g = cv2.ximgproc.guidedFilter(guide, alpha.astype(np.float32), cfg.guided_px, cfg.guided_eps) * disc
        alpha = np.where(d > 0.5 * t0, np.maximum(alpha, g), alpha)
    return alpha


def _room_core(d: np.ndarray, t0: float | np.ndarray, t1: float | np.ndarray, room: np.ndarray,
               observed: np.ndarray, cfg: MatteConfig) -> float:
    """Share of the ``room`` pixels (H, W) bool that the decision would call object (after the
    opening that cuts specks): how often a distance sees an object where none can be."""
    core = _soft_alpha(d, t0, t1, np.ones_like(room), observed, cfg) > 0.5
    core = cv2.morphologyEx(core.astype(np.uint8), cv2.MORPH_OPEN, np.ones((2, 2), np.uint8)).astype(bool)
    return float((core & room).sum()) / max(int(room.sum()), 1)


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


def rim_alpha(I: np.ndarray, B: np.ndarray, F: np.ndarray, min_off: float) -> tuple[np.ndarray, np.ndarray]:
    """Coverage (N,) of mixed pixels by a shaded-rim compositing model, and where it holds (N,) bool.

    ``I``, ``B``, ``F`` (N, 3) float: observed colour, predicted room, the object's colour from
    inside. A rim is the object's colour scaled by its shading (darker or brighter than F), so
    I = (1 - a) B + s F with an unknown scale s: a least-squares fit of the two coefficients;
    the coverage is 1 minus the room's. It needs a room colour off the object's shading line
    (the line from black through F) by at least ``min_off`` |F - B| (on or near that line shading
    and coverage cannot be told apart, and the fit's noise grows as |F - B| over that distance;
    0.3 keeps it within about 3 times the plain equation's), a non-negative object part and a fit
    within 30% of |F - B| (plus 10 levels).
    """
    bb, ff, bf = (B * B).sum(-1), (F * F).sum(-1), (B * F).sum(-1)
    det = bb * ff - bf * bf
    ib, i_f = (I * B).sum(-1), (I * F).sum(-1)
    room = (ib * ff - i_f * bf) / np.maximum(det, 1e-6)
    obj = (i_f * bb - ib * bf) / np.maximum(det, 1e-6)
    resid = np.linalg.norm(I - room[:, None] * B - obj[:, None] * F, axis=1)
    fb = np.linalg.norm(F - B, axis=1)
    off = np.sqrt(np.maximum(det, 0) / np.maximum(ff, 1e-6))       # |B minus its projection on F|
    holds = (det > 0) & (off >= min_off * fb) & (obj >= -0.05) & (resid < 0.3 * fb + 10.0)
    return np.clip(1.0 - room, 0, 1), holds


def _edge_alpha(observed: np.ndarray, predicted: np.ndarray, core: np.ndarray, edge_px: int,
                gain: float = 1.0, rim_min_off: float = np.inf,
                ramp: tuple[float, float] = (0.0, 1.0)) -> np.ndarray:
    """Fractional alpha (H, W) float32 in a band around ``core`` by the compositing equation.

    With the object's colour F taken from the nearest surely-inside pixel and the background
    B predicted, observed I = a F + (1 - a) B gives a = (I - B).(F - B) / |F - B|^2, times
    ``gain``: a shaded object's rim is darker than the pixels inside that give F, so it reads
    as part room (against the true coverage the plain equation runs 0.03-0.1 low on fractional
    pixels of the synthetic captures; 1.25 leaves -0.01 to +0.04). Where the room's colour lies
    off the object's shading line (``rim_min_off``, :func:`rim_alpha`), the shaded rim is
    modelled instead: the rim's shading then costs nothing. ``ramp`` (lo, hi) steepens the
    band's alpha, lo and below to 0, hi and above to 1 (:func:`~.object.matte_config_at`).
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
    # Where object and room look alike the equation says nothing, and off the line from B to F
    # the pixel is no mix of the two (F is wrong there: a darker rim, another part): keep the
    # hard decision.
    resid = np.linalg.norm(I - B - a[:, None] * fb, axis=1)
    mixed = (denom > 30.0 ** 2) & (resid < 0.3 * np.sqrt(denom))
    a = np.where(mixed, np.clip(gain * a, 0, 1), core[band].astype(np.float32))
    if np.isfinite(rim_min_off):
        rim, holds = rim_alpha(I, B, F, rim_min_off)
        a = np.where(holds, rim, a)
    lo, hi = ramp
    alpha[band] = np.clip((a - lo) / (hi - lo), 0, 1)
    return alpha


def colour_counts(pixels: np.ndarray, bins: int) -> np.ndarray:
    """Colour histogram counts (bins, bins, bins) float64 of RGB pixels (N, 3) uint8."""
    q = pixels.astype(np.int32) * bins // 256
    flat = (q[:, 0] * bins + q[:, 1]) * bins + q[:, 2]
    return np.bincount(flat, minlength=bins ** 3).astype(np.float64).reshape((bins,) * 3)


def normalized_histogram(counts: np.ndarray) -> np.ndarray:
    """Smoothed, normalized colour histogram (bins,)*3 float64 from counts of the same shape."""
    from scipy.ndimage import gaussian_filter

    h = gaussian_filter(counts, 1.0, mode="constant")   # colours next to seen ones are likely too
    return h / max(h.sum(), 1e-12)


def colour_histogram(pixels: np.ndarray, bins: int) -> np.ndarray:
    """Normalized, smoothed colour histogram (bins, bins, bins) float64 of RGB pixels (N, 3) uint8."""
    return normalized_histogram(colour_counts(pixels, bins))


def room_by_colour(observed: np.ndarray, candidates: np.ndarray, room: np.ndarray, core: np.ndarray,
                   bins: int = 32, ratio: float = 3.0, object_hist: np.ndarray | None = None) -> np.ndarray:
    """Pixels of ``candidates`` (H, W) bool whose colour the room explains ``ratio`` times better
    than the object does.

    ``room``, ``core`` (H, W) bool: pixels surely room and pixels decided object. The object's
    colours come from the core pixels outside ``candidates`` (decided where the evidence is
    sound) and those whose colour is rare in the room (the 5% least likely room colour or
    rarer), so room wrongly in the core does not teach the object model. ``object_hist``
    (bins,)*3: the object's colours over the whole capture (:func:`normalized_histogram`); a
    colour counts as the object's if either model says so.
    Returns (H, W) bool (all False when either side has too few pixels to judge).
    """
    none = np.zeros(candidates.shape, bool)
    if core.sum() < 20 or room.sum() < 50 or not candidates.any():
        return none
    q = observed.astype(np.int32) * bins // 256
    pr = colour_histogram(observed[room], bins)[q[..., 0], q[..., 1], q[..., 2]]
    seed = (core & ~candidates) | (core & (pr < np.percentile(pr[room], 5)))
    if seed.sum() < 10:
        return none
    po = colour_histogram(observed[seed], bins)[q[..., 0], q[..., 1], q[..., 2]]
    if object_hist is not None and object_hist.shape == (bins,) * 3:
        po = np.maximum(po, object_hist[q[..., 0], q[..., 1], q[..., 2]])
    return candidates & (pr > ratio * po)


def _noise(d: np.ndarray, disc: np.ndarray) -> float:
    """Noise level of the colour distance (0..1 RGB scale) from where no object can be.

    Robust to a room part the prediction gets wrong (a far wall seen edge-on): the lower
    quartile, scaled to the median it has on clean crops. Without enough room outside the disc
    (a fixed window), the whole crop stands in: the room is most of it.
    """
    outside = ~disc
    ring = d[outside] if outside.sum() > 50 else d
    return 1.6 * float(np.percentile(ring, 25)) / 0.6745


def noise_map(d: np.ndarray, predicted: np.ndarray, room: np.ndarray, noise: float,
              levels: int = 8, min_px: int = 20, margin: float = 1.0) -> np.ndarray:
    """Noise level per pixel (H, W) float32 of the colour distance ``d`` (H, W): ``noise``, raised
    where the prediction shows a colour that the room around the sphere (``room`` (H, W) bool)
    shows predicted worse than the rest of it (a far wall the field renders as a smooth grey).

    How well a field predicts the room depends on what it predicts (its depth, its texture), so
    the room pixels are grouped by predicted colour (``levels`` per channel); a group of at least
    ``min_px`` pixels whose median distance is over ``margin`` times the room's raises ``noise``
    by that ratio for every pixel predicted in that colour.
    """
    out = np.full(d.shape, noise, np.float32)
    if levels <= 0 or room.sum() < 50:
        return out
    q = predicted.astype(np.int32) * levels // 256
    group = (q[..., 0] * levels + q[..., 1]) * levels + q[..., 2]
    g, dr = group[room], d[room]
    typical = max(float(np.median(dr)), 1e-6)
    order = np.argsort(g, kind="stable")
    g, dr = g[order], dr[order]
    ids, start, count = np.unique(g, return_index=True, return_counts=True)
    big = count >= min_px
    for v, a, n in zip(ids[big], start[big], count[big]):
        ratio = float(np.median(dr[a:a + n])) / typical
        if ratio > margin:
            out[group == v] = noise * ratio
    return out


def noise_level(observed: np.ndarray, predicted: np.ndarray, disc: np.ndarray,
                cfg: MatteConfig = MatteConfig()) -> float:
    """The noise level :func:`matte` measures in one crop (observed, predicted (H, W, 3) uint8)."""
    return _noise(colour_distance(observed, predicted, cfg.shift_px), disc)


@dataclass(frozen=True)
class CaptureMatte:
    """What the first mattes of a capture teach the second pass.

    ``noise``: the capture's median crop noise level (a crop may measure more, never uses more);
    ``object_hist`` (bins,)*3 or None: the object's colours over the capture, from pixels decided
    object where the prediction is sound (:func:`sure_object_counts`, summed, normalized);
    ``sharp``: whether the sharper colour distance may be used (:func:`sharp_distance`; off when
    in the capture's median crop the prediction keeps too little of the room's 1-px detail: a
    field that renders the room blurred, where a misregistration explains more than it allows).
    """

    noise: float
    object_hist: np.ndarray | None = None
    sharp: bool = True


def sure_object_counts(rgba: np.ndarray, guessed: np.ndarray | None, bins: int = 32) -> np.ndarray:
    """Colour counts (bins,)*3 float64 of a matte's sure object pixels: opaque, not at its edge,
    not where the prediction was a guess. ``rgba`` (H, W, 4) uint8 from :func:`matte`."""
    solid = cv2.erode((rgba[..., 3] == 255).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    if guessed is not None:
        solid &= ~guessed
    return colour_counts(rgba[..., :3][solid], bins)


def capture_matte(noises: list[float], counts: np.ndarray | None, details: list[float] | None = None,
                  min_detail: float = MatteConfig.sharp_min_detail) -> CaptureMatte:
    """The capture's statistics from per-crop noise levels, summed object colour counts and the
    per-crop share of the room's detail the prediction keeps (:func:`room_detail`; nan: not
    measured): the sharper distance is allowed if its median is at least ``min_detail``."""
    hist = normalized_histogram(counts) if counts is not None and counts.sum() >= 50 else None
    kept = np.asarray(details if details is not None else [], float)
    kept = kept[np.isfinite(kept)]
    return CaptureMatte(float(np.median(noises)), hist, not (len(kept) and float(np.median(kept)) < min_detail))


def room_detail(observed: np.ndarray, predicted: np.ndarray, room: np.ndarray) -> float:
    """Share of the observed room's 1-px detail (:func:`local_variation`, mean over ``room``
    (H, W) bool) that the prediction shows: ~0.85-0.9 for a well trained field (the sensor's
    noise is detail the prediction lacks), less for a blurred one; nan with too little room."""
    if room.sum() < 50:
        return float("nan")
    seen = float(local_variation(observed)[room].mean())
    return float(local_variation(predicted)[room].mean()) / max(seen, 1e-6)


def matte(observed: np.ndarray, predicted: np.ndarray, disc: np.ndarray,
          cfg: MatteConfig = MatteConfig(), guessed: np.ndarray | None = None,
          capture: CaptureMatte | None = None) -> np.ndarray:
    """:func:`matte_and_noise` without the measurements."""
    return matte_and_noise(observed, predicted, disc, cfg, guessed, capture)[0]


def matte_and_noise(observed: np.ndarray, predicted: np.ndarray, disc: np.ndarray,
                    cfg: MatteConfig = MatteConfig(), guessed: np.ndarray | None = None,
                    capture: CaptureMatte | None = None) -> tuple[np.ndarray, float, float]:
    """Straight RGBA (H, W, 4) uint8 of the object from ``observed`` (H, W, 3) uint8 and the
    predicted background ``predicted`` (H, W, 3) uint8, inside ``disc`` (H, W) bool.

    ``guessed`` (H, W) bool: pixels where the prediction is a guess (colour decides there).
    ``capture``: the second pass's statistics of the whole capture (noise cap, object colours).
    Also returns what the second pass's statistics are made of: the noise level this crop
    measures (:func:`noise_level`; before any cap) and the share of the room's detail around the
    sphere that the prediction keeps (:func:`room_detail`).
    """
    d = colour_distance(observed, predicted, cfg.shift_px)
    outside = ~disc
    sound_room = outside & ~guessed if guessed is not None else outside
    noise = measured = _noise(d, disc)
    if capture is not None:
        noise = min(noise, capture.noise)
    # Thresholds per pixel: where the room around the sphere shows that the field predicts this
    # colour worse (a far wall, the table's edge), a larger difference is needed.
    levels = noise_map(d, predicted, sound_room, noise, cfg.room_levels, cfg.room_min_px)
    t0 = np.maximum(cfg.min_threshold, cfg.low_sigmas * levels)
    t1 = np.maximum(t0 * 1.5, cfg.high_sigmas * levels)
    core = _soft_alpha(d, t0, t1, disc, observed, cfg) > 0.5
    # (the second pass does not need it again)
    detail = room_detail(observed, predicted, sound_room) if capture is None else float("nan")
    if cfg.sharp_shift < 1 and (capture is None or capture.sharp):
        # An object part coloured like a textured room (a pale head on a wood table) is lost to
        # the minimum over shifts; the sharper distance keeps it where the prediction is sound:
        # away from a guessed prediction, in a capture whose field keeps the room's detail, and
        # only in crops where it finds no more object in the room around the sphere than the
        # robust distance does (a field that renders the room's texture off by more than a pixel
        # would light it up).
        ds = sharp_distance(observed, predicted, d, cfg.sharp_shift, cfg.shift_px)
        sound = np.ones_like(disc)
        if guessed is not None and guessed.any():
            k = 2 * cfg.guess_margin_px + 1
            sound = ~cv2.dilate(guessed.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
            ds = np.where(sound, ds, d)
        room = outside & sound
        if room.sum() > 50 and (_room_core(ds, t0, t1, room, observed, cfg)
                                - _room_core(d, t0, t1, room, observed, cfg)) <= cfg.sharp_room_max:
            core |= _soft_alpha(ds, t0, t1, disc, observed, cfg) > 0.5
            d = ds
    if guessed is not None and guessed.any():
        sure_room = (outside | (d <= t0)) & ~guessed
        core &= ~room_by_colour(observed, core & guessed, sure_room, core, cfg.colour_bins, cfg.colour_ratio,
                                capture.object_hist if capture is not None else None)
    if core.any():
        # Specks and the thin lines a misregistered pattern leaves are cut apart by an opening and
        # dropped; the thin parts of the object that the opening removed grow back from the
        # pieces kept (within the decided pixels, a few pixels from them).
        opened = cv2.morphologyEx(core.astype(np.uint8), cv2.MORPH_OPEN, np.ones((2, 2), np.uint8))
        kept = _keep_large(opened.astype(bool), cfg.min_blob).astype(np.uint8)
        for _ in range(3):
            kept = cv2.dilate(kept, np.ones((3, 3), np.uint8)) & core
        core = _fill_holes(kept.astype(bool))
    alpha = _edge_alpha(observed, predicted, core, cfg.edge_px, cfg.edge_gain, cfg.rim_min_off, cfg.edge_ramp) * disc
    alpha[alpha < 0.02] = 0
    return straight_rgba(observed, predicted, alpha), measured, detail


def straight_rgba(observed: np.ndarray, predicted: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Straight RGBA (H, W, 4) uint8 from alpha (H, W) float 0..1: the object's colour decontaminated.

    observed = a F + (1 - a) B, so F = (observed - (1 - a) B) / a at the edges.
    """
    o = observed.astype(np.float32)
    b = predicted.astype(np.float32)
    a = alpha.astype(np.float32)[..., None]
    fg = np.where(a > 0.15, (o - (1 - a) * b) / np.maximum(a, 1e-3), o)
    rgba = np.concatenate([np.clip(fg, 0, 255), a * 255], -1)
    return np.round(rgba).astype(np.uint8)


def temporal_median(alphas: list[np.ndarray]) -> np.ndarray:
    """Per-pixel median (H, W) uint8 of the alphas (H, W) uint8 of consecutive crops (2 or 3;
    with 2 the median is their mean). A part missed or added in one frame only is outvoted; the
    crop follows the object, so its parts move little between neighbouring frames."""
    return np.median(np.stack(alphas), 0).round().astype(np.uint8)

