"""The object-mode voxel field's CPU training step and renders: forward and backward in numba.

The PyTorch path (:func:`.render.render_rays` + autograd) spends most of a step building index
tensors, gathering 8 corner rows per sample and scattering gradients back through generic
kernels; on 2 CPU cores that is ~1,000 rays/s at a 256^3 lattice. Here one ray is one loop:
march, interpolate, composite, then walk the same samples back with the closed-form gradient of
alpha compositing (as Plenoxels' CUDA kernel does), adding straight into the tables' gradient
buffers and marking the rows touched for the lazy Adam step. The math matches
:func:`.render.render_rays` sample for sample (same sample positions, trilinear weights,
softplus density, sigmoid SH colour, colour only where the weight exceeds ``weight_eps``, rays
cut once transmittance falls below it); ``tests/static/test_kernels.py`` checks values and
gradients against autograd.

Rays run in parallel chunks (``prange``). Two rays of different threads that touch the same
row at the same instant can lose one of the two gradient additions (no atomics on CPU arrays):
Hogwild-style, rare, and harmless for stochastic training.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import prange

from ..geometry.sh_numba import sh_basis_into
from .field import VoxelField

RAY_RUN = 32     # CPU training draws rays in runs of this many consecutive bank entries

_FM = {"nsz", "arcp", "contract", "afn", "reassoc"}
_CHUNK = RAY_RUN     # rays per parallel work item: one run of neighbouring pixels (scratch per chunk)


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def _softplus(x: float) -> float:
    return x + math.log1p(math.exp(-x)) if x > 0 else math.log1p(math.exp(x))


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def _sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x))


@numba.njit(cache=True, fastmath=_FM, nogil=True, parallel=True)
def render_rays_cpu(o: np.ndarray, d: np.ndarray, jitter: np.ndarray, bg: np.ndarray, target: np.ndarray,
                    ray_w: np.ndarray, index: np.ndarray, occ: np.ndarray, res: int, dens: np.ndarray, sh: np.ndarray,
                    gdens: np.ndarray, gsh: np.ndarray, touched_d: np.ndarray, touched_sh: np.ndarray,
                    act_shift: float, step: float, degree: int, active_degree: int, weight_eps: float,
                    grad_scale: float, backward: bool, nearest: bool, out: np.ndarray) -> None:
    """Render rays over their backgrounds; with ``backward``, also add
    ``grad_scale * d(sum of squared errors)/d(table)`` into the gradient buffers.

    ``o`` (B, 3) normalized ray origins (object at the origin, radius 1), ``d`` (B, 3) unit
    directions, ``jitter`` (B,) in [0, 1) (sample offset in steps), ``bg`` / ``target`` (B, 3)
    background colour and composited target (``target`` unused without ``backward``);
    ``ray_w`` (B,) each ray's weight in the squared error (1: plain L2; robust training
    lowers it for rays that keep disagreeing, :func:`.rays.robust_weights`).
    ``index`` (res^3,) int32 lattice -> row (-1: inactive, read as the sentinel row N),
    ``occ`` (res^3,) bool dilated occupancy. ``dens`` (N+1,), ``sh`` (N+1, 3*nb) float32
    tables; ``gdens``/``gsh`` their gradient buffers (added to), ``touched_d`` /
    ``touched_sh`` (N+1,) bool: rows given a gradient. ``step`` sample spacing in normalized
    units. ``degree``: the tables' SH degree; only the bands up to ``active_degree`` are read
    and given a gradient (progressive SH). ``nearest``: a sample reads its nearest lattice
    point alone (piecewise constant, as the baked tree renders) instead of the 8 trilinear
    corners. ``out`` (B, 5) receives the composited RGB, the opacity and the squared error
    summed over RGB.
    """
    B = o.shape[0]
    nb = (degree + 1) * (degree + 1)
    C = 3 * nb
    na = (min(active_degree, degree) + 1) ** 2     # coefficients in use per channel
    inv_cell = res / 2.0
    S_max = int(2.0 / step) + 3
    sentinel = dens.shape[0] - 1
    n_chunks = (B + _CHUNK - 1) // _CHUNK
    ncorner = 1 if nearest else 8           # corners read per sample (nearest: rows[:, 0] only)
    for ch in prange(n_chunks):
        rows = np.empty((S_max, 8), np.int32)
        wts = np.empty((S_max, 8), np.float32)
        a_s = np.empty(S_max, np.float32)       # sample opacity
        T_s = np.empty(S_max, np.float32)       # transmittance before the sample
        ds_s = np.empty(S_max, np.float32)      # d softplus / d raw
        rgb = np.zeros((S_max, 3), np.float32)
        coloured = np.zeros(S_max, np.bool_)
        shb = np.zeros(16)
        cf = np.empty(C, np.float32)            # interpolated SH coefficients of one sample
        gq = np.empty(C, np.float32)            # their gradient
        for r in range(ch * _CHUNK, min(B, (ch + 1) * _CHUNK)):
            ox, oy, oz = o[r, 0], o[r, 1], o[r, 2]
            dx, dy, dz = d[r, 0], d[r, 1], d[r, 2]
            b = ox * dx + oy * dy + oz * dz
            c = ox * ox + oy * oy + oz * oz - 1.0
            disc = b * b - c
            C0, C1, C2 = 0.0, 0.0, 0.0
            T = 1.0
            n = 0
            if disc > 0:
                s = math.sqrt(disc)
                t0 = max(-b - s, 0.0)
                t1 = max(-b + s, 0.0)
                sh_basis_into(dx, dy, dz, degree, shb)
                # Lattice coordinates (point i at i) move by (d * inv_cell) per unit of t.
                bx, by, bz = (ox + 1.0) * inv_cell - 0.5, (oy + 1.0) * inv_cell - 0.5, (oz + 1.0) * inv_cell - 0.5
                vx, vy, vz = dx * inv_cell, dy * inv_cell, dz * inv_cell
                k = 0
                while True:
                    t = t0 + (k + jitter[r]) * step
                    k += 1
                    if t >= t1:
                        break
                    ux, uy, uz = bx + t * vx, by + t * vy, bz + t * vz
                    # Occupancy at the nearest lattice point (as the PyTorch path rounds).
                    qx = min(max(int(ux + 0.5), 0), res - 1)     # int() truncates: fine, u > -0.5
                    qy = min(max(int(uy + 0.5), 0), res - 1)
                    qz = min(max(int(uz + 0.5), 0), res - 1)
                    if not occ[(qx * res + qy) * res + qz]:
                        continue
                    if nearest:
                        row = index[(qx * res + qy) * res + qz]
                        if row < 0:
                            row = sentinel
                        rows[n, 0] = row
                        wts[n, 0] = 1.0
                        raw = dens[row]
                    else:
                        ux = min(max(ux, 0.0), res - 1.0)
                        uy = min(max(uy, 0.0), res - 1.0)
                        uz = min(max(uz, 0.0), res - 1.0)
                        ix = min(int(ux), res - 2)
                        iy = min(int(uy), res - 2)
                        iz = min(int(uz), res - 2)
                        fx, fy, fz = ux - ix, uy - iy, uz - iz
                        raw = 0.0
                        for cc in range(8):
                            cx, cy, cz = (cc >> 2) & 1, (cc >> 1) & 1, cc & 1
                            row = index[((ix + cx) * res + iy + cy) * res + iz + cz]
                            if row < 0:
                                row = sentinel
                            w = ((fx if cx else 1.0 - fx) * (fy if cy else 1.0 - fy)
                                 * (fz if cz else 1.0 - fz))
                            rows[n, cc] = row
                            wts[n, cc] = w
                            raw += w * dens[row]
                    z = raw + act_shift
                    sig = _softplus(z)
                    a = 1.0 - math.exp(-sig * step)
                    wgt = T * a
                    a_s[n] = a
                    T_s[n] = T
                    ds_s[n] = _sigmoid(z)
                    coloured[n] = wgt > weight_eps
                    if coloured[n]:
                        cf[:] = 0.0
                        for cc in range(ncorner):
                            row = rows[n, cc]
                            w32 = wts[n, cc]
                            for c3 in range(3):
                                for q in range(c3 * nb, c3 * nb + na):
                                    cf[q] += w32 * sh[row, q]
                        for c3 in range(3):
                            v = 0.0
                            for q in range(na):
                                v += cf[c3 * nb + q] * shb[q]
                            rgb[n, c3] = _sigmoid(v)
                        C0 += wgt * rgb[n, 0]
                        C1 += wgt * rgb[n, 1]
                        C2 += wgt * rgb[n, 2]
                    T *= 1.0 - a
                    n += 1
                    if T < weight_eps:
                        break
            C0 += T * bg[r, 0]
            C1 += T * bg[r, 1]
            C2 += T * bg[r, 2]
            out[r, 0], out[r, 1], out[r, 2], out[r, 3] = C0, C1, C2, 1.0 - T
            if not backward:
                continue
            e0, e1, e2 = C0 - target[r, 0], C1 - target[r, 1], C2 - target[r, 2]
            out[r, 4] = e0 * e0 + e1 * e1 + e2 * e2
            gw = 2 * grad_scale * ray_w[r]
            g0, g1, g2 = gw * e0, gw * e1, gw * e2
            # Backward. With w_i = T_i a_i and R_i the colour behind sample i (background
            # included): dC/dsigma_i = step * (T_{i+1} c_i - R_i).
            A0, A1, A2 = 0.0, 0.0, 0.0
            for i in range(n):
                wgt = T_s[i] * a_s[i]
                c0 = rgb[i, 0] if coloured[i] else 0.0
                c1 = rgb[i, 1] if coloured[i] else 0.0
                c2 = rgb[i, 2] if coloured[i] else 0.0
                A0 += wgt * c0
                A1 += wgt * c1
                A2 += wgt * c2
                Tn = T_s[i] * (1.0 - a_s[i])
                gs = step * (g0 * (Tn * c0 - (C0 - A0)) + g1 * (Tn * c1 - (C1 - A1))
                             + g2 * (Tn * c2 - (C2 - A2)))
                graw = gs * ds_s[i]
                for cc in range(ncorner):
                    row = rows[i, cc]
                    if row == sentinel:     # inactive corner: reset every step, no gradient
                        continue
                    gdens[row] += wts[i, cc] * graw
                    touched_d[row] = True
                if coloured[i]:
                    h0 = g0 * wgt * c0 * (1.0 - c0)
                    h1 = g1 * wgt * c1 * (1.0 - c1)
                    h2 = g2 * wgt * c2 * (1.0 - c2)
                    for q in range(na):
                        gq[q] = h0 * shb[q]
                        gq[nb + q] = h1 * shb[q]
                        gq[2 * nb + q] = h2 * shb[q]
                    for cc in range(ncorner):
                        row = rows[i, cc]
                        if row == sentinel:
                            continue
                        touched_sh[row] = True
                        w32 = wts[i, cc]
                        for c3 in range(3):
                            for q in range(c3 * nb, c3 * nb + na):
                                gsh[row, q] += w32 * gq[q]


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def tv_grad(picks: np.ndarray, active: np.ndarray, index: np.ndarray, res: int, dens: np.ndarray,
            sh: np.ndarray, gdens: np.ndarray, gsh: np.ndarray, touched_d: np.ndarray,
            touched_sh: np.ndarray, w_dens: float, w_sh: float) -> tuple[float, float]:
    """Total variation over the rows ``picks`` (n,) and their +x, +y, +z neighbours (inactive
    ones not counted), as :func:`.train.tv_loss`: the mean squared difference of density
    and of SH coefficients. Adds ``w_dens`` / ``w_sh`` times their gradients; returns both means.
    ``active`` (N,) int64 lattice index of each row."""
    C = sh.shape[1]
    pairs = np.empty((picks.shape[0] * 3, 2), np.int64)
    m = 0
    rr = res * res
    for k in range(picks.shape[0]):
        a = picks[k]
        lin = active[a]
        ijk = (lin // rr, (lin // res) % res, lin % res)
        for axis in range(3):
            if ijk[axis] + 1 >= res:
                continue
            nb_row = index[lin + (rr if axis == 0 else (res if axis == 1 else 1))]
            if nb_row >= 0:
                pairs[m, 0] = a
                pairs[m, 1] = nb_row
                m += 1
    if m == 0:
        return 0.0, 0.0
    sd = 0.0
    ss = 0.0
    kd = 2.0 * w_dens / m
    ks = 2.0 * w_sh / (m * C)
    for p in range(m):
        a, b = pairs[p, 0], pairs[p, 1]
        diff = dens[a] - dens[b]
        sd += diff * diff
        gdens[a] += kd * diff
        gdens[b] -= kd * diff
        for q in range(C):
            diff = sh[a, q] - sh[b, q]
            ss += diff * diff
            gsh[a, q] += ks * diff
            gsh[b, q] -= ks * diff
        touched_d[a] = touched_d[b] = True
        touched_sh[a] = touched_sh[b] = True
    return sd / m, ss / (m * C)




def kernel_render(field: VoxelField, origins: torch.Tensor, dirs: torch.Tensor, bg: torch.Tensor,
                  target: torch.Tensor | None, jitter: torch.Tensor, ray_w: torch.Tensor | None = None) -> np.ndarray:
    """Run :func:`render_rays_cpu` on world rays: origins, unit directions (B, 3), backgrounds
    (B, 3), sample offsets ``jitter`` (B,) in [0, 1). With ``target`` (B, 3) it also adds the
    gradient of the mean squared error (each ray's term weighted by ``ray_w`` (B,), None: 1)
    into the field's buffers. Returns (B, 5): RGB over ``bg``, alpha, squared error."""
    if not field.cpu_kernel:
        raise ValueError("the CPU kernel covers object mode on the CPU only")
    o = ((origins - field.center) / field.radius).float().contiguous().numpy()
    B = o.shape[0]
    out = np.zeros((B, 5), np.float32)
    tgt = target if target is not None else bg
    w = np.ones(B, np.float32) if ray_w is None else ray_w.float().contiguous().numpy()
    render_rays_cpu(o, dirs.float().contiguous().numpy(), jitter.float().contiguous().numpy(),
                    bg.float().contiguous().numpy(), tgt.float().contiguous().numpy(), w,
                    field.index.numpy(), field.occupancy().numpy(), field.res,
                    field.density.data.numpy()[:, 0], field.sh.data.numpy(), field.density.grad.numpy()[:, 0],
                    field.sh.grad.numpy(), field.density.touched.numpy(), field.sh.touched.numpy(),
                    field.act_shift, field.step, field.cfg.sh_degree, field.sh_active, field.cfg.weight_eps,
                    1.0 / (3 * B), target is not None, field.nearest, out)
    return out


def photometric_step(field: VoxelField, origins: torch.Tensor, dirs: torch.Tensor, bg: torch.Tensor,
                     target: torch.Tensor, jitter: torch.Tensor,
                     ray_w: torch.Tensor | None = None) -> tuple[torch.Tensor, np.ndarray]:
    """The photometric loss of :func:`.render.render_rays` + MSE, without autograd: renders the
    rays (B, 3) world origins / unit directions over ``bg`` (B, 3), compares with ``target``
    (B, 3) and adds the gradient of the mean squared error (each ray's term weighted by
    ``ray_w`` (B,) when given) into the field's gradient buffers (as ``backward`` would).
    ``jitter`` (B,) in [0, 1) offsets the samples. Returns the unweighted MSE (0-d) and the
    rays as rendered (B, 4): RGB over ``bg``, alpha."""
    out = kernel_render(field, origins, dirs, bg, target, jitter, ray_w)
    return torch.tensor(float(out[:, 4].sum()) / (3 * out.shape[0])), out[:, :4]


def tv_step(field: VoxelField, n: int, gen: torch.Generator) -> tuple[float, float]:
    """:func:`.train.tv_loss` without autograd: adds ``tv_density`` / ``tv_sh`` times its
    gradient into the field's buffers; returns the two means."""
    if field.n_active == 0:
        return 0.0, 0.0
    pick = torch.randint(0, field.n_active, (min(n, field.n_active),), generator=gen)
    return tv_grad(pick.numpy(), field.active.numpy(), field.index.numpy(), field.res,
                   field.density.data.numpy()[:, 0], field.sh.data.numpy(), field.density.grad.numpy()[:, 0],
                   field.sh.grad.numpy(), field.density.touched.numpy(), field.sh.touched.numpy(),
                   field.cfg.tv_density, field.cfg.tv_sh)
