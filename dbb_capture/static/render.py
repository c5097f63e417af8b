"""Volume rendering of the voxel field in PyTorch: ray samplers, differentiable rays, images.

:func:`render_rays` is what the PyTorch training path backpropagates through (CUDA and scene
mode); the CPU's object mode trains and renders with the numba kernel (:mod:`.kernels`), which
matches it sample for sample. :func:`render_image` takes whichever the field runs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .field import VoxelField, contract, lattice_lin
from .kernels import kernel_render


def _sphere_hits(o: torch.Tensor, d: torch.Tensor, r: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit distances (B,) of rays with the sphere of radius ``r`` at the origin.

    Rays that miss get entry = exit = the distance of closest approach (clamped at 0).
    """
    b = (o * d).sum(-1)
    c = (o * o).sum(-1) - r * r
    disc = b * b - c
    s = disc.clamp_min(0).sqrt()
    t0 = (-b - s).clamp_min(0)
    t1 = (-b + s).clamp_min(0)
    miss = disc <= 0
    tc = (-b).clamp_min(0)
    return torch.where(miss, tc, t0), torch.where(miss, tc, t1)


def object_samples(field: VoxelField, o: torch.Tensor, d: torch.Tensor,
                   jitter: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sample distances (B, S), validity (B, S) and spacing (B, S) inside the unit sphere, for
    normalized origins and unit directions (B, 3), sample offsets ``jitter`` (B,) in steps."""
    t0, t1 = _sphere_hits(o, d, 1.0)
    step = field.step
    S = max(1, int(math.ceil(float((t1 - t0).max()) / step)))
    k = torch.arange(S, device=o.device, dtype=o.dtype)
    t = t0[:, None] + (k[None] + jitter[:, None]) * step
    valid = t < t1[:, None]
    return t, valid, torch.full_like(t, step)


def scene_samples(field: VoxelField, o: torch.Tensor, d: torch.Tensor, jitter: torch.Tensor,
                  far: float = 1e4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Samples for the contracted scene (as :func:`object_samples`): even inside the unit
    sphere, even in contracted radius outside it (before and after), so the lattice sees about
    one sample per half cell; spacing measured in lattice space."""
    step = field.step
    t0, t1 = _sphere_hits(o, d, 1.0)
    S_in = max(1, int(math.ceil(float((t1 - t0).max()) / step)))
    # Outside, offsets u from the sphere so that 2 - 1/(1+u) advances by one step each.
    s = (torch.arange(int(math.ceil(1 / step)), device=o.device, dtype=o.dtype)[None]
         + jitter[:, None]) * step
    u = 1 / (1 - s).clamp_min(1e-4) - 1
    k = torch.arange(S_in, device=o.device, dtype=o.dtype)
    t_in = t0[:, None] + (k[None] + jitter[:, None]) * step
    t_pre = (t0[:, None] - u.flip(-1))
    t_post = t1[:, None] + u
    t = torch.cat([t_pre, t_in, t_post], -1)
    valid = torch.cat([t_pre > 0, t_in < t1[:, None], t_post < far], -1)
    # Spacing measured in lattice space, where the density lives.
    x = contract(o[:, None] + t[..., None] * d[:, None])
    gap = (x[:, 1:] - x[:, :-1]).norm(dim=-1)
    delta = torch.cat([gap, gap[:, -1:]], -1)
    return t, valid, delta


@dataclass
class RayOutput:
    rgb: torch.Tensor        # (B, 3) composited on the given background
    alpha: torch.Tensor      # (B,) accumulated opacity = 1 - transmittance
    depth: torch.Tensor      # (B,) expected distance (world units), 0 where empty


def render_rays(field: VoxelField, origins: torch.Tensor, dirs: torch.Tensor,
                background: torch.Tensor | None = None, jitter: bool = False) -> RayOutput:
    """Volume-render world rays: origins (B, 3), unit directions (B, 3), background (B, 3) or None (black).

    Samples in empty lattice space are skipped; colour is evaluated only where a sample's
    weight exceeds ``weight_eps``. Differentiable with respect to the field.
    """
    dev = origins.device
    B = origins.shape[0]
    o = (origins - field.center) / field.radius
    j = torch.rand(B, device=dev) if jitter else torch.full((B,), 0.5, device=dev)
    sampler = object_samples if field.cfg.mode == "object" else scene_samples
    t, valid, delta = sampler(field, o, dirs, j)
    x = o[:, None] + t[..., None] * dirs[:, None]
    if field.cfg.mode == "scene":
        x = contract(x)
    u = field.to_lattice(x).round().long().clamp(0, field.res - 1)
    valid &= field.occupancy()[lattice_lin(u, field.res)]
    idx = valid.nonzero()
    bi, si = idx[:, 0], idx[:, 1]
    rows, w = field.corners(x[bi, si])
    if torch.is_grad_enabled():
        # Pass 1 without autograd: drop samples hidden behind opaque matter (a suffix of each
        # ray), so the differentiable pass only pays for what can still be seen.
        with torch.no_grad():
            raw = torch.bmm(w[:, None, :], field.density.data[rows])[:, 0, 0]
            tau0 = torch.zeros_like(t).index_put((bi, si), F.softplus(raw + field.act_shift) * delta[bi, si])
            seen = (torch.cumsum(tau0, -1) - tau0)[bi, si] < -math.log(field.cfg.weight_eps)
        bi, si, rows, w = bi[seen], si[seen], rows[seen], w[seen]
    sig = field.sigma_from(rows, w)
    tau = torch.zeros_like(t).index_put((bi, si), sig * delta[bi, si])
    # Transmittance before each sample: exp of minus the optical depth accumulated so far.
    T = torch.exp(-(torch.cumsum(tau, -1) - tau))
    wgt = (T * (1 - torch.exp(-tau)))[bi, si]
    keep = wgt > field.cfg.weight_eps
    rgb_s = field.rgb_from(rows[keep], w[keep], dirs[bi[keep]])
    rgb = torch.zeros(B, 3, device=dev).index_add(0, bi[keep], wgt[keep, None] * rgb_s)
    acc = torch.zeros(B, device=dev).index_add(0, bi, wgt)
    dep = torch.zeros(B, device=dev).index_add(0, bi, wgt * t[bi, si]) * field.radius
    if background is not None:
        rgb = rgb + (1 - acc)[:, None] * background
    return RayOutput(rgb, acc, dep)


@torch.no_grad()
def render_image(field: VoxelField, origins: torch.Tensor, dirs: torch.Tensor,
                 background: tuple[float, float, float] | None = None, chunk: int = 8192) -> np.ndarray:
    """Straight RGBA (H, W, 4) float32 of rays (H, W, 3) — or RGB on ``background`` if given."""
    H, W = origins.shape[:2]
    o = origins.reshape(-1, 3).to(field.device)
    d = dirs.reshape(-1, 3).to(field.device)
    out = []
    for s in range(0, o.shape[0], chunk):
        if field.cpu_kernel:
            n = o[s:s + chunk].shape[0]
            res = torch.from_numpy(kernel_render(field, o[s:s + chunk], d[s:s + chunk], torch.zeros(n, 3), None,
                                                 torch.full((n,), 0.5)))
            r = RayOutput(res[:, :3], res[:, 3], torch.zeros(n))
        else:
            r = render_rays(field, o[s:s + chunk], d[s:s + chunk])
        a = r.alpha.clamp(0, 1)
        if background is None:
            rgb = r.rgb / a.clamp_min(1e-6)[:, None]
            out.append(torch.cat([rgb.clamp(0, 1), a[:, None]], -1))
        else:
            bg = torch.tensor(background, device=o.device, dtype=torch.float32)
            out.append((r.rgb + (1 - a)[:, None] * bg).clamp(0, 1))
    return torch.cat(out).reshape(H, W, -1).cpu().numpy()
