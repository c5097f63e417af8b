"""Training the room's field: initialization from the photos, the depth of the far room, the
optimization, and training again on the first mattes' room."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import replace

import numpy as np
import torch
import torch.nn.functional as F

from ..core.errors import DbbError
from ..geometry.cameras import project_points
from .config import BackgroundConfig
from .field import LayerField, field_basis
from .model import BackgroundModel, TrainLog
from .panorama import env_coords, equirect, sphere_exit
from .rays import RayBank, TrainingView, build_bank


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
        x, y = equirect(sphere_exit(ou, du, r), gh, gw)
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


def with_env_depth(fld: LayerField, bank: RayBank, n_depths: int) -> LayerField:
    """``fld`` with its far sphere made a depth panorama (:func:`env_depth_sweep`), each texel
    starting at the mean colour of the rays that land on it."""
    depth, mean, cnt = env_depth_sweep(fld, bank, n_depths)
    env = fld.env.clone()
    seen = torch.from_numpy(cnt > 0)
    start = torch.logit(torch.from_numpy(mean).clamp(0.01, 0.99)).to(env)
    env[..., :3] = torch.where(seen[..., None].to(env.device), start, env[..., :3])
    return LayerField(fld.layers, env, fld.center, fld.basis, fld.heights, fld.half, fld.r_out, fld.guess, depth)


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
