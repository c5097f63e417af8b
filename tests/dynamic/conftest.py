"""A small RSSM config, a synthetic crops.json dataset (made once) and a model whose frames move."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from dbb_capture.dynamic.anchor import AtlasGrid, ViewAtlas
from dbb_capture.dynamic.config import RssmConfig
from dbb_capture.dynamic.data import load_sequences
from dbb_capture.dynamic.model import Rssm
from dbb_capture.synth.crops import synthetic_crops

# One thread: the CI machine has 2 cores and other tests run beside these.
torch.set_num_threads(1)

# The defaults at 32 px with small networks, without the view anchor (ANCHORED has it; its tests
# give it an atlas, :func:`random_atlas`).
SMALL = replace(RssmConfig(), size=32, deter=16, stoch=16, hidden=64, embed=64, enc_depth=8, dec_depth=8,
                anchor=False)
ANCHORED = replace(SMALL, anchor=True)


def random_atlas(size: int = 32, seed: int = 0) -> ViewAtlas:
    """A view atlas of random renders on a 30-degree grid from 0 to 60 degrees elevation."""
    g = torch.Generator().manual_seed(seed)
    return ViewAtlas(torch.randint(0, 256, (3, 12, 4, size, size), generator=g, dtype=torch.uint8),
                     AtlasGrid(30.0, 12, 0.0, 3, 0.7))


def scaled(cfg: RssmConfig = SMALL, **scales: float) -> RssmConfig:
    """``cfg`` with some ``loss_scales`` changed."""
    return replace(cfg, loss_scales={**cfg.loss_scales, **scales})


def moving_model(seed: int = 4, cfg: RssmConfig = SMALL) -> Rssm:
    """An eval-mode model with perturbed weights: its frames move (an untrained one copies the context)."""
    torch.manual_seed(seed)
    m = Rssm(cfg).eval()
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return m


def batch_of(b: int = 2, t1: int = 11, size: int = 32, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Random premultiplied-range frames (b, t1, 4, S, S) and views (b, t1, 3)."""
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, t1, 4, size, size, generator=g), torch.rand(b, t1, 3, generator=g) * 40


@pytest.fixture(scope="session")
def crops(tmp_path_factory):
    """A 3-second 32x32 crops.json of the synthetic dynamic toy (10 fps), with still-view truth."""
    return synthetic_crops(tmp_path_factory.mktemp("rssm") / "ds", seconds=3.0, fps=10, size=32,
                           still_steps=12, samples=1)


@pytest.fixture(scope="session")
def data(crops):
    return load_sequences(crops.root, 32)
