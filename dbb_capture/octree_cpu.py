"""CPU ray casting through a PlenOctree's leaf lattice: exact cell traversal in numba.

The tree is piecewise constant, so a ray is integrated exactly cell by cell: each leaf it
crosses over a length ``s`` (world units) contributes ``alpha = 1 - exp(-sigma * s)``.
Empty space is skipped brick by brick (8^3 leaves, the unit the leaf table is indexed by),
and many bricks at once: each empty brick knows its chessboard distance to the nearest
occupied one, so a ray leaves the whole empty cube around it in one step. Every step recomputes
the cell from a point nudged just past the current ``t``, so the walk never drifts off the
lattice through rounding. The kernel releases the GIL; the caller runs ray ranges on
Python threads that pull work as they free up (dynamic balance on a shared machine).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .fields import _C0, _C1, _C2, _C3

BRICK_SHIFT = 3      # 8^3 leaves per brick (the leaf table's unit)
_FAR = 1e30          # 1 / direction component when that component is ~0

# No nnan/ninf: exits of axis-parallel rays are huge finite numbers and must compare right.
_FM = {"nsz", "arcp", "contract", "afn", "reassoc"}


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def _sh_basis(dx: float, dy: float, dz: float, degree: int, out: np.ndarray) -> None:
    """Real SH basis at a unit direction into ``out`` ((degree+1)^2,), svox's convention."""
    out[0] = _C0
    if degree >= 1:
        out[1] = -_C1 * dy
        out[2] = _C1 * dz
        out[3] = -_C1 * dx
    if degree >= 2:
        xx, yy, zz = dx * dx, dy * dy, dz * dz
        out[4] = _C2[0] * dx * dy
        out[5] = _C2[1] * dy * dz
        out[6] = _C2[2] * (2 * zz - xx - yy)
        out[7] = _C2[3] * dx * dz
        out[8] = _C2[4] * (xx - yy)
        if degree >= 3:
            out[9] = _C3[0] * dy * (3 * xx - yy)
            out[10] = _C3[1] * dx * dy * dz
            out[11] = _C3[2] * dy * (4 * zz - xx - yy)
            out[12] = _C3[3] * dz * (2 * zz - 3 * xx - 3 * yy)
            out[13] = _C3[4] * dx * (4 * zz - xx - yy)
            out[14] = _C3[5] * dz * (xx - yy)
            out[15] = _C3[6] * dx * (xx - 3 * yy)


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def _exp_neg(x: float) -> float:
    """exp(-x) for x >= 0; a degree-6 Taylor polynomial below 0.5 (error < 2e-6, several times
    cheaper than libm), where nearly every leaf's optical depth falls."""
    if x < 0.5:
        return 1.0 - x * (1.0 - x * (0.5 - x * (1 / 6 - x * (1 / 24 - x * (1 / 120 - x * (1 / 720))))))
    return math.exp(-x)


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def _half(u: int, p2: np.ndarray) -> float:
    """The value of IEEE float16 bits ``u`` (finite); ``p2`` is :data:`HALF_SCALE`."""
    e = (u >> 10) & 31
    v = ((u & 1023) + (1024 if e > 0 else 0)) * p2[e]
    return -v if u & 32768 else v


HALF_SCALE = np.array([2.0 ** -24] + [2.0 ** (e - 25) for e in range(1, 32)])


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def _colour(coef: np.ndarray, row: int, shb: np.ndarray, nb: int, sigmoid: bool,
            p2: np.ndarray) -> tuple[float, float, float]:
    """RGB of data row ``row`` (float16 bits) seen along the direction whose SH basis is ``shb``."""
    v0 = 0.0
    v1 = 0.0
    v2 = 0.0
    for k in range(nb):
        v0 += _half(coef[row, k], p2) * shb[k]
        v1 += _half(coef[row, nb + k], p2) * shb[k]
        v2 += _half(coef[row, 2 * nb + k], p2) * shb[k]
    if sigmoid:
        return 1.0 / (1.0 + math.exp(-v0)), 1.0 / (1.0 + math.exp(-v1)), 1.0 / (1.0 + math.exp(-v2))
    return max(v0 + 0.5, 0.0), max(v1 + 0.5, 0.0), max(v2 + 0.5, 0.0)   # Plenoxels' relu(x + 0.5)


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def _write(out: np.ndarray, p: int, mode: int, bg: np.ndarray, r: float, g: float, b: float, a: float) -> None:
    """Store premultiplied ``r, g, b`` and alpha ``a`` in ``out[p]`` as mode 0: premultiplied
    RGBA; 1: straight RGBA (colour clipped to [0, 1]); 2: RGB over background ``bg`` (3,)."""
    if mode == 0:
        out[p, 0], out[p, 1], out[p, 2], out[p, 3] = r, g, b, a
    elif mode == 1:
        k = 1.0 / max(a, 1e-6)
        out[p, 0] = min(max(r * k, 0.0), 1.0)
        out[p, 1] = min(max(g * k, 0.0), 1.0)
        out[p, 2] = min(max(b * k, 0.0), 1.0)
        out[p, 3] = a
    else:
        out[p, 0] = min(max(r + (1.0 - a) * bg[0], 0.0), 1.0)
        out[p, 1] = min(max(g + (1.0 - a) * bg[1], 0.0), 1.0)
        out[p, 2] = min(max(b + (1.0 - a) * bg[2], 0.0), 1.0)


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def _span_exit(ax: int, ay: int, az: int, bx: int, by: int, bz: int, size: float, px: float, py: float,
               pz: float, hx: int, hy: int, hz: int, ix: float, iy: float, iz: float) -> float:
    """Ray parameter where the ray P + t D leaves box ``a * size .. b * size``."""
    tx = ((bx if hx else ax) * size - px) * ix
    ty = ((by if hy else ay) * size - py) * iy
    tz = ((bz if hz else az) * size - pz) * iz
    return min(tx, min(ty, tz))


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def _box_exit(cx: int, cy: int, cz: int, size: float, px: float, py: float, pz: float,
              hx: int, hy: int, hz: int, ix: float, iy: float, iz: float) -> float:
    """Ray parameter where the ray P + t D leaves box ``c * size .. (c + 1) * size``;
    ``h`` is 1 on axes the ray travels up, ``i`` is 1 / D."""
    tx = ((cx + hx) * size - px) * ix
    ty = ((cy + hy) * size - py) * iy
    tz = ((cz + hz) * size - pz) * iz
    return min(tx, min(ty, tz))


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def trace_rays(origins: np.ndarray, dirs: np.ndarray, rot: np.ndarray, inv: np.ndarray, offset: np.ndarray,
               L: int, lo: np.ndarray, hi: np.ndarray, skip: np.ndarray, bricks: np.ndarray, nbrk: int,
               leaf_row: np.ndarray, leaf_sigma: np.ndarray, coef: np.ndarray, p2: np.ndarray,
               degree: int, sigmoid: bool, t_min: float, w_eps: float, start: int, end: int, slot: int,
               frame: int, cache: np.ndarray, pixel: np.ndarray, mode: int, bg: np.ndarray,
               out: np.ndarray) -> None:
    """Colour of rays ``start`` to ``end`` into row ``pixel[r]`` of ``out`` (see :func:`_write`
    for ``mode`` and ``bg``). Releases the GIL: Python threads run disjoint ranges side by side.

    ``origins`` (1 or N, 3) world; ``dirs`` (N, 3) unit, turned to world by ``rot`` (3, 3);
    the tree maps world x to lattice ``(offset + x * inv) * L``. ``lo``/``hi`` (3,) bound the
    occupied leaves (lattice units). ``skip`` (nbrk^3,) uint8 is the chessboard distance, in
    bricks, of each 8^3-leaf brick to the nearest occupied one (0 occupied), ``bricks``
    (nbrk^3,) int32 the brick of each 8^3-leaf brick (-1 empty);
    ``leaf_row`` (n_bricks * 512, 2) int32 holds per leaf its density (float32 bits, read
    through the float32 view ``leaf_sigma`` of the same memory; 0 = empty) and its data row,
    so one cache line serves both.
    ``coef`` (K, >= 3 * B) uint16 the float16 bits of each row's SH coefficients (rows
    padded to whole cache lines: one miss fetches a leaf's colour), ``p2`` :data:`HALF_SCALE`.
    Rays stop once transmittance < ``t_min``; colour is evaluated only where the sample
    weight exceeds ``w_eps``.
    ``frame`` > 0 (only with one origin, below 2^24) turns on the leaf colour cache
    ``cache[slot]`` (K, 4) float32: RGB, valid where the 4th value equals ``frame``; each
    thread owns a slot.
    """
    nb = (degree + 1) * (degree + 1)
    rsz = float(1 << BRICK_SHIFT)
    shb = np.zeros(16)
    for r in range(start, end):
        oi = r if origins.shape[0] > 1 else 0
        wx = rot[0, 0] * dirs[r, 0] + rot[0, 1] * dirs[r, 1] + rot[0, 2] * dirs[r, 2]
        wy = rot[1, 0] * dirs[r, 0] + rot[1, 1] * dirs[r, 1] + rot[1, 2] * dirs[r, 2]
        wz = rot[2, 0] * dirs[r, 0] + rot[2, 1] * dirs[r, 1] + rot[2, 2] * dirs[r, 2]
        px = (offset[0] + origins[oi, 0] * inv[0]) * L
        py = (offset[1] + origins[oi, 1] * inv[1]) * L
        pz = (offset[2] + origins[oi, 2] * inv[2]) * L
        dx, dy, dz = wx * inv[0] * L, wy * inv[1] * L, wz * inv[2] * L
        ix = 1.0 / dx if abs(dx) > 1e-12 else _FAR
        iy = 1.0 / dy if abs(dy) > 1e-12 else _FAR
        iz = 1.0 / dz if abs(dz) > 1e-12 else _FAR
        hx, hy, hz = int(dx >= 0), int(dy >= 0), int(dz >= 0)
        sx, sy, sz = abs(ix), abs(iy), abs(iz)       # t per leaf along each axis
        # Clip to the occupied leaves' box.
        ax, bx = (lo[0] - px) * ix, (hi[0] - px) * ix
        ay, by = (lo[1] - py) * iy, (hi[1] - py) * iy
        az, bz = (lo[2] - pz) * iz, (hi[2] - pz) * iz
        t = max(0.0, max(min(ax, bx), max(min(ay, by), min(az, bz))))
        t_end = min(max(ax, bx), min(max(ay, by), max(az, bz)))
        if not t < t_end:
            _write(out, pixel[r], mode, bg, 0.0, 0.0, 0.0, 0.0)
            continue
        eps = 1e-4 / math.sqrt(dx * dx + dy * dy + dz * dz)   # a 1e-4 leaf nudge
        T = 1.0
        cr = 0.0
        cg = 0.0
        cb = 0.0
        basis_ready = False
        w_sum = 0.0
        done = False
        while t < t_end and not done:
            tt = t + eps
            cx = min(max(int(math.floor(px + tt * dx)), 0), L - 1)
            cy = min(max(int(math.floor(py + tt * dy)), 0), L - 1)
            cz = min(max(int(math.floor(pz + tt * dz)), 0), L - 1)
            kx, ky, kz = cx >> BRICK_SHIFT, cy >> BRICK_SHIFT, cz >> BRICK_SHIFT
            kb = (kx * nbrk + ky) * nbrk + kz
            brick = bricks[kb]
            if brick < 0:
                # Every brick within chessboard distance skip - 1 is empty: leave that cube.
                e = skip[kb] - 1
                t = max(_span_exit(kx - e, ky - e, kz - e, kx + e + 1, ky + e + 1, kz + e + 1, rsz,
                                   px, py, pz, hx, hy, hz, ix, iy, iz), tt)
                continue
            # Occupied brick: walk its leaves incrementally (Amanatides-Woo).
            base = brick << 9
            lx, ly, lz = cx & 7, cy & 7, cz & 7
            mx = ((cx + hx) - px) * ix
            my = ((cy + hy) - py) * iy
            mz = ((cz + hz) - pz) * iz
            while True:
                tn = min(mx, min(my, mz))
                local = base | (lx << 6) | (ly << 3) | lz
                sg = leaf_sigma[local, 0]
                if sg > 0:
                    a = 1.0 - _exp_neg(sg * (min(tn, t_end) - t))
                    w = T * a
                    if w > w_eps:
                        row = leaf_row[local, 1]
                        if frame > 0:
                            # One camera centre: colour a leaf once per frame, along
                            # the direction to its centre (within a leaf's angle of
                            # every ray through it), and reuse it for later rays.
                            if cache[slot, row, 3] == frame:
                                v0, v1, v2 = cache[slot, row, 0], cache[slot, row, 1], cache[slot, row, 2]
                            else:
                                ex = ((kx << 3) + lx + 0.5 - px) / (inv[0] * L)
                                ey = ((ky << 3) + ly + 0.5 - py) / (inv[1] * L)
                                ez = ((kz << 3) + lz + 0.5 - pz) / (inv[2] * L)
                                en = 1.0 / max(math.sqrt(ex * ex + ey * ey + ez * ez), 1e-12)
                                _sh_basis(ex * en, ey * en, ez * en, degree, shb)
                                v0, v1, v2 = _colour(coef, row, shb, nb, sigmoid, p2)
                                cache[slot, row, 0] = v0
                                cache[slot, row, 1] = v1
                                cache[slot, row, 2] = v2
                                cache[slot, row, 3] = frame
                                # Use the stored (float32) colour, as later hits will: a pixel
                                # must not depend on which thread met the leaf first.
                                v0, v1, v2 = cache[slot, row, 0], cache[slot, row, 1], cache[slot, row, 2]
                        else:
                            if not basis_ready:
                                _sh_basis(wx, wy, wz, degree, shb)
                                basis_ready = True
                            v0, v1, v2 = _colour(coef, row, shb, nb, sigmoid, p2)
                        cr += w * v0
                        cg += w * v1
                        cb += w * v2
                        w_sum += w
                    T *= 1.0 - a
                    if T < t_min:
                        done = True
                        break
                t = max(tn, t)
                if t >= t_end:
                    break
                if mx <= my and mx <= mz:
                    lx += 2 * hx - 1
                    mx += sx
                    if lx < 0 or lx > 7:
                        break
                elif my <= mz:
                    ly += 2 * hy - 1
                    my += sy
                    if ly < 0 or ly > 7:
                        break
                else:
                    lz += 2 * hz - 1
                    mz += sz
                    if lz < 0 or lz > 7:
                        break
        # The weight of skipped samples goes to the evaluated ones in proportion.
        scale = (1.0 - T) / w_sum if w_sum > 0 else 0.0
        _write(out, pixel[r], mode, bg, cr * scale, cg * scale, cb * scale, 1.0 - T)
