"""Where tensors live: CUDA when present, else the CPU."""

from __future__ import annotations


def pick_device():
    """``torch.device("cuda")`` when a CUDA device is available, else ``torch.device("cpu")``."""
    import torch

    return torch.device("cuda" if torch.cuda.is_available() else "cpu")
