"""Real spherical harmonics in svox's convention (basis order and signs), and the colour model.

A radiance field's colour along a unit direction ``d`` is ``sigmoid(sum_b c_b Y_b(d))`` per RGB
channel, as svox's PlenOctrees have it (:data:`COLOUR_ACTIVATION`), so a trained field bakes into
a tree by a straight copy. The numba twin of :func:`sh_basis` is :mod:`.sh_numba`.
"""

from __future__ import annotations

import torch

COLOUR_ACTIVATION = "sigmoid"   # what the SH sum goes through; recorded in every baked tree
C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
       0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
       -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_basis(degree: int, d: torch.Tensor) -> torch.Tensor:
    """Real SH basis (..., (degree+1)^2) at unit directions ``d`` (..., 3), svox's convention."""
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z,
                C2[4] * (xx - yy)]
    if degree >= 3:
        out += [C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
                C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy),
                C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy)]
    if degree > 3:
        raise ValueError("SH degree above 3 is not supported")
    return torch.stack(out, -1)
