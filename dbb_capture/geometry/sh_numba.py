"""The SH basis of :mod:`.sh` for numba kernels (one direction at a time, into a buffer)."""

from __future__ import annotations

import numba
import numpy as np

from .sh import C0, C1, C2, C3

# numba's fast-math flags of the kernels that call it (no NaN/inf assumption: empty space is inf).
_FM = {"nsz", "arcp", "contract", "afn", "reassoc"}


@numba.njit(cache=True, fastmath=_FM, nogil=True)
def sh_basis_into(dx: float, dy: float, dz: float, degree: int, out: np.ndarray) -> None:
    """Real SH basis at a unit direction into ``out`` ((degree+1)^2,), svox's convention."""
    out[0] = C0
    if degree >= 1:
        out[1] = -C1 * dy
        out[2] = C1 * dz
        out[3] = -C1 * dx
    if degree >= 2:
        xx, yy, zz = dx * dx, dy * dy, dz * dz
        out[4] = C2[0] * dx * dy
        out[5] = C2[1] * dy * dz
        out[6] = C2[2] * (2 * zz - xx - yy)
        out[7] = C2[3] * dx * dz
        out[8] = C2[4] * (xx - yy)
        if degree >= 3:
            out[9] = C3[0] * dy * (3 * xx - yy)
            out[10] = C3[1] * dx * dy * dz
            out[11] = C3[2] * dy * (4 * zz - xx - yy)
            out[12] = C3[3] * dz * (2 * zz - 3 * xx - 3 * yy)
            out[13] = C3[4] * dx * (4 * zz - xx - yy)
            out[14] = C3[5] * dz * (xx - yy)
            out[15] = C3[6] * dx * (xx - 3 * yy)
