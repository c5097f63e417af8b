"""Parameter tables updated row by row: what the voxel fields of the room and of the object train.

Autograd's own paths are slow for a table of millions of rows of which a step touches a few:
a dense gradient clears the whole table every step and a sparse one sorts millions of indices
to coalesce them. :class:`RowTable` instead adds the backward pass into one persistent buffer,
marks the rows it touched and updates only those with a lazy Adam step (numba on the CPU).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import prange

_FM = {"nsz", "arcp", "contract", "afn", "reassoc"}


class RowTable:
    """A parameter table (N, C) whose gradient is gathered row-wise and updated by lazy Adam.

    Autograd's own paths are slow here: a dense gradient clears the whole table every step and
    a sparse one sorts millions of indices to coalesce them. Instead the backward pass adds into
    one persistent buffer and marks the rows it touched; :meth:`adam_step` updates only those.
    """

    def __init__(self, values: torch.Tensor):
        self.data = values.contiguous()
        self.grad = torch.zeros_like(self.data)
        self.touched = torch.zeros(self.data.shape[0], dtype=torch.bool, device=self.data.device)
        self.m = torch.zeros_like(self.data)
        self.v = torch.zeros_like(self.data)
        self.t = 0
        # A leaf that requires grad, so autograd calls our backward; it never gets a gradient.
        self.handle = torch.zeros((), device=self.data.device, requires_grad=True)

    def gather(self, rows: torch.Tensor) -> torch.Tensor:
        """``data[rows]`` (..., C), differentiable into :attr:`grad`."""
        return _Gather.apply(self.handle, rows, self)

    def adam_step(self, lr: float, b1: float = 0.9, b2: float = 0.99, eps: float = 1e-8) -> None:
        """One Adam step on the touched rows; their gradient is cleared."""
        if self.data.device.type == "cpu":
            self.t += 1
            step = lr * math.sqrt(1 - b2 ** self.t) / (1 - b1 ** self.t)
            adam_rows(self.data.numpy(), self.grad.numpy(), self.m.numpy(), self.v.numpy(),
                      self.touched.numpy(), step, b1, b2, eps)
            return
        idx = self.touched.nonzero()[:, 0]
        if idx.numel() == 0:
            return
        self.t += 1
        g = self.grad[idx]
        m = self.m[idx].mul_(b1).add_(g, alpha=1 - b1)
        v = self.v[idx].mul_(b2).addcmul_(g, g, value=1 - b2)
        self.m[idx] = m
        self.v[idx] = v
        step = lr * math.sqrt(1 - b2 ** self.t) / (1 - b1 ** self.t)
        self.data[idx] -= step * m / (v.sqrt() + eps)
        self.grad[idx] = 0
        self.touched[idx] = False


class _Gather(torch.autograd.Function):
    @staticmethod
    def forward(ctx, handle, rows, table):  # noqa: D102 - autograd API
        ctx.save_for_backward(rows)
        ctx.table = table
        return table.data[rows]

    @staticmethod
    def backward(ctx, g):  # noqa: D102 - autograd API
        (rows,) = ctx.saved_tensors
        t = ctx.table
        flat = rows.reshape(-1)
        t.grad.index_add_(0, flat, g.reshape(flat.numel(), t.data.shape[1]))
        t.touched[flat] = True
        return None, None, None


@numba.njit(cache=True, fastmath=_FM, nogil=True, parallel=True)
def adam_rows(data: np.ndarray, grad: np.ndarray, m: np.ndarray, v: np.ndarray, touched: np.ndarray,
              step_size: float, b1: float, b2: float, eps: float) -> None:
    """Adam on the rows marked in ``touched`` (N,) of ``data`` (N, C); clears their gradient
    and mark. ``step_size`` already holds the bias corrections (lr * sqrt(1-b2^t) / (1-b1^t))."""
    idx = np.nonzero(touched)[0]
    C = data.shape[1]
    for k in prange(idx.shape[0]):
        r = idx[k]
        for c in range(C):
            g = grad[r, c]
            mm = b1 * m[r, c] + (1 - b1) * g
            vv = b2 * v[r, c] + (1 - b2) * g * g
            m[r, c] = mm
            v[r, c] = vv
            data[r, c] -= step_size * mm / (math.sqrt(vv) + eps)
            grad[r, c] = 0.0
        touched[r] = False
