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
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from ..geometry.sh_numba import sh_basis_into

BRICK_SHIFT = 3      # 8^3 leaves per brick (the leaf table's unit)
_FAR = 1e30          # 1 / direction component when that component is ~0
_MAX_HITS = 64       # colour lookups a ray defers before shading them (see trace_rays)

# No nnan/ninf: exits of axis-parallel rays are huge finite numbers and must compare right.
_FM = {"nsz", "arcp", "contract", "afn", "reassoc"}


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def _exp_neg(x: float) -> float:
    """exp(-x) for x >= 0; a degree-6 Taylor polynomial below 0.5 (error < 2e-6, several times
    cheaper than libm), where nearly every leaf's optical depth falls."""
    if x < 0.5:
        return 1.0 - x * (1.0 - x * (0.5 - x * (1 / 6 - x * (1 / 24 - x * (1 / 120 - x * (1 / 720))))))
    return math.exp(-x)


@intrinsic
def _half_bits(typingctx, u):
    """float32 value of IEEE float16 bits ``u`` (uint16): one hardware conversion (F16C)."""
    def codegen(context, builder, signature, args):
        return builder.fpext(builder.bitcast(args[0], ir.HalfType()), ir.FloatType())
    return types.float32(types.uint16), codegen


@intrinsic
def _prefetch(typingctx, arr, i):
    """Ask the memory system for the cache line of ``arr[i, 0]`` (2-D C-ordered array) ahead
    of its use; no effect on results."""
    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        zero = context.get_constant(types.intp, 0)
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1], zero], wraparound=False)
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        builder.call(fn, [builder.bitcast(ptr, i8p), ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()
    return types.void(arr, types.intp), codegen


@numba.njit(cache=True, nogil=True)
def _half(u: int) -> float:
    """The value of IEEE float16 bits ``u`` (a Python-callable view of :func:`_half_bits`)."""
    return _half_bits(np.uint16(u))


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def _sigmoid(v: float) -> float:
    """1 / (1 + exp(-v)) in float32 (libm's expf: a third of the float64 path's cost)."""
    return np.float32(1.0) / (np.float32(1.0) + math.exp(-v))


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def _colour(coef: np.ndarray, row: int, shb: np.ndarray, nb: int, sigmoid: bool) -> tuple[float, float, float]:
    """RGB of data row ``row`` (float16 bits) seen along the direction whose SH basis is
    ``shb`` (float32), all in float32."""
    v0 = np.float32(0.0)
    v1 = np.float32(0.0)
    v2 = np.float32(0.0)
    for k in range(nb):
        b = shb[k]
        v0 += _half_bits(coef[row, k]) * b
        v1 += _half_bits(coef[row, nb + k]) * b
        v2 += _half_bits(coef[row, 2 * nb + k]) * b
    if sigmoid:
        return _sigmoid(v0), _sigmoid(v1), _sigmoid(v2)
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


_UNQ = 1.0 / 16384      # cached colours are 16-bit fixed point over [0, 4)
FRAME_MAX = 65535       # frame stamps are 16 bits


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def _pack(v0: float, v1: float, v2: float, frame: int) -> int:
    """One colour cache entry: RGB as 16-bit fixed point (step 1/16384, 96 dB) and the frame
    stamp in the top 16 bits. One 8-byte store and load: threads share the cache without
    locks (a racing thread writes the same value, and never half of one)."""
    q0 = min(max(int(v0 * 16384.0 + 0.5), 0), 65535)
    q1 = min(max(int(v1 * 16384.0 + 0.5), 0), 65535)
    q2 = min(max(int(v2 * 16384.0 + 0.5), 0), 65535)
    return q0 | (q1 << 16) | (q2 << 32) | (frame << 48)


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def _shade(nh: int, hrow: np.ndarray, hcell: np.ndarray, hw: np.ndarray, coef: np.ndarray, nb: int, degree: int,
           sigmoid: bool, frame: int, cc: np.ndarray, shb: np.ndarray, px: float, py: float, pz: float,
           sx: float, sy: float, sz: float) -> tuple[float, float, float]:
    """Sum of ``hw[j]`` times the colour of data row ``hrow[j]`` over the ``nh`` deferred hits
    of one ray. With ``frame`` > 0 a leaf is coloured along the direction from the camera
    (lattice point ``p``) to the centre of its cell ``hcell[j]`` (packed 10 bits per axis), the
    lattice to world scale being ``s`` per axis, once per frame through the cache ``cc``
    (see :func:`_pack`). Otherwise ``shb`` already holds the ray's SH basis. Rows missing
    from the cache are prefetched together first, so their memory latencies overlap instead
    of adding up."""
    if frame > 0:
        for j in range(nh):
            if cc[hrow[j], 0] >> 48 != frame:
                _prefetch(coef, hrow[j])
    r = 0.0
    g = 0.0
    b = 0.0
    for j in range(nh):
        row = hrow[j]
        if frame > 0:
            e = cc[row, 0]
            if e >> 48 != frame:
                c = hcell[j]
                ex = ((c >> 20) + 0.5 - px) * sx
                ey = (((c >> 10) & 1023) + 0.5 - py) * sy
                ez = ((c & 1023) + 0.5 - pz) * sz
                en = 1.0 / max(math.sqrt(ex * ex + ey * ey + ez * ez), 1e-12)
                sh_basis_into(ex * en, ey * en, ez * en, degree, shb)
                v0, v1, v2 = _colour(coef, row, shb, nb, sigmoid)
                e = _pack(v0, v1, v2, frame)
                cc[row, 0] = e
            # Always the stored colour: a pixel must not depend on which ray or thread met
            # the leaf first.
            v0 = (e & 65535) * _UNQ
            v1 = ((e >> 16) & 65535) * _UNQ
            v2 = ((e >> 32) & 65535) * _UNQ
        else:
            v0, v1, v2 = _colour(coef, row, shb, nb, sigmoid)
        w = hw[j]
        r += w * v0
        g += w * v1
        b += w * v2
    return r, g, b


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def trace_rays(origins: np.ndarray, dirs: np.ndarray, rot: np.ndarray, inv: np.ndarray, offset: np.ndarray,
               L: int, lo: np.ndarray, hi: np.ndarray, skip: np.ndarray, bricks: np.ndarray, nbrk: int,
               leaf_row: np.ndarray, leaf_sigma: np.ndarray, coef: np.ndarray,
               degree: int, sigmoid: bool, t_min: float, w_eps: float, start: int, end: int,
               frame: int, cache: np.ndarray, pixel: np.ndarray, mode: int, bg: np.ndarray,
               out: np.ndarray, eager: bool, wmax: np.ndarray) -> None:
    """Colour of rays ``start`` to ``end`` into row ``pixel[r]`` of ``out`` (see :func:`_write`
    for ``mode`` and ``bg``). Releases the GIL: Python threads run disjoint ranges side by side.

    ``origins`` (1 or N, 3) world; ``dirs`` (N, 3) unit, turned to world by ``rot`` (3, 3);
    the tree maps world x to lattice ``(offset + x * inv) * L`` (L <= 1024). ``lo``/``hi`` (3,)
    bound the occupied leaves (lattice units). ``skip`` (nbrk^3,) uint8 is the chessboard
    distance, in bricks, of each 8^3-leaf brick to the nearest occupied one (0 occupied),
    ``bricks`` (nbrk^3,) int32 the brick of each 8^3-leaf brick (-1 empty);
    ``leaf_row`` (n_bricks * 512, 2) int32 holds per leaf (brick * 512 + x * 64 + y * 8 + z)
    its density (float32 bits, read
    through the float32 view ``leaf_sigma`` of the same memory; 0 = empty) and its data row,
    so one cache line serves both.
    ``coef`` (K, >= 3 * B) uint16 the float16 bits of each row's SH coefficients (rows
    padded to whole cache lines: one miss fetches a leaf's colour).
    Rays stop once transmittance < ``t_min``; colour is evaluated only where the sample
    weight exceeds ``w_eps``.
    ``frame`` in 1 .. :data:`FRAME_MAX` (only with one origin) turns on the leaf colour cache
    ``cache`` (K, 1) int64 of :func:`_pack` entries, valid where stamped ``frame``, which the
    threads share. ``eager`` also prefetches the SH rows of cached leaves as the walk
    meets them: worth it when most leaves are met by one ray only (leaves about a pixel wide).

    The walk only records which rows a ray needs and with what weight (prefetching their
    cache entries), then :func:`_shade` colours them: colour lookups are scattered over tens
    of MB, and a lookup made where the walk finds it stalls the walk for a memory latency.

    With a non-empty ``wmax`` (K,) float32 the rays only record, per data row, the largest
    weight any of them gave it (above ``w_eps``; what the bake's weight pruning keeps leaves
    by) and colour nothing; ``out`` then receives alpha only.
    """
    nb = (degree + 1) * (degree + 1)
    rsz = float(1 << BRICK_SHIFT)
    shb = np.zeros(16, np.float32)
    hrow = np.empty(_MAX_HITS, np.int64)
    hcell = np.empty(_MAX_HITS, np.int64)
    hw = np.empty(_MAX_HITS, np.float64)
    cc = cache
    record = wmax.shape[0] > 0
    wsx, wsy, wsz = 1.0 / (inv[0] * L), 1.0 / (inv[1] * L), 1.0 / (inv[2] * L)   # world per leaf
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
        stx, sty, stz = 2 * hx - 1, 2 * hy - 1, 2 * hz - 1
        # Clip to the occupied leaves' box.
        ax, bx = (lo[0] - px) * ix, (hi[0] - px) * ix
        ay, by = (lo[1] - py) * iy, (hi[1] - py) * iy
        az, bz = (lo[2] - pz) * iz, (hi[2] - pz) * iz
        t = max(0.0, max(min(ax, bx), max(min(ay, by), min(az, bz))))
        t_end = min(max(ax, bx), min(max(ay, by), max(az, bz)))
        if not t < t_end:
            _write(out, pixel[r], mode, bg, 0.0, 0.0, 0.0, 0.0)
            continue
        if frame == 0:
            sh_basis_into(wx, wy, wz, degree, shb)
        eps = 1e-4 / math.sqrt(dx * dx + dy * dy + dz * dz)   # a 1e-4 leaf nudge
        T = 1.0
        cr = 0.0
        cg = 0.0
        cb = 0.0
        nh = 0
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
            corner = ((kx << 20) | (ky << 10) | kz) << BRICK_SHIFT
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
                    if w > w_eps and record:
                        row = leaf_row[local, 1]
                        if w > wmax[row]:
                            wmax[row] = w
                    elif w > w_eps:
                        row = leaf_row[local, 1]
                        if frame > 0:
                            _prefetch(cc, row)
                        if frame == 0 or eager:
                            _prefetch(coef, row)
                        hrow[nh] = row
                        hcell[nh] = corner + ((lx << 20) | (ly << 10) | lz)
                        hw[nh] = w
                        nh += 1
                        w_sum += w
                        if nh == _MAX_HITS:
                            vr, vg, vb = _shade(nh, hrow, hcell, hw, coef, nb, degree, sigmoid, frame, cc, shb,
                                                px, py, pz, wsx, wsy, wsz)
                            cr += vr
                            cg += vg
                            cb += vb
                            nh = 0
                    T *= 1.0 - a
                    if T < t_min:
                        done = True
                        break
                t = max(tn, t)
                if t >= t_end:
                    break
                if mx <= my and mx <= mz:
                    lx += stx
                    mx += sx
                    if lx < 0 or lx > 7:
                        break
                elif my <= mz:
                    ly += sty
                    my += sy
                    if ly < 0 or ly > 7:
                        break
                else:
                    lz += stz
                    mz += sz
                    if lz < 0 or lz > 7:
                        break
        if nh:
            vr, vg, vb = _shade(nh, hrow, hcell, hw, coef, nb, degree, sigmoid, frame, cc, shb,
                                px, py, pz, wsx, wsy, wsz)
            cr += vr
            cg += vg
            cb += vb
        # The weight of skipped samples goes to the evaluated ones in proportion.
        scale = (1.0 - T) / w_sum if w_sum > 0 else 0.0
        _write(out, pixel[r], mode, bg, cr * scale, cg * scale, cb * scale, 1.0 - T)
