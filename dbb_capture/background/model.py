"""A trained background model: the field, how it was trained, and its files."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..core.errors import DbbError
from ..crops.camera import CropCamera
from .config import BackgroundConfig
from .field import LayerField


@dataclass
class TrainLog:
    steps: int = 0
    seconds: float = 0.0
    psnr: float = float("nan")
    history: list[dict] = field(default_factory=list)


@dataclass
class BackgroundModel:
    """A trained background field and how it was made."""

    field: LayerField
    mode: str                  # "clean plate" or "object video"
    frames: int
    rays: int
    log: TrainLog
    cfg: BackgroundConfig
    refine: TrainLog | None = None   # the second training on the rays the first mattes call room

    def render(self, cam: CropCamera) -> np.ndarray:
        """Predicted background (H, W, 3) uint8 in a crop camera (never the full frame)."""
        return self.field.render(cam)

    def guessed(self, cam: CropCamera) -> np.ndarray:
        """Pixels (H, W) bool of a crop camera where the prediction is a guess (see LayerField.guessed)."""
        return self.field.guessed(cam)

    def save(self, path: Path) -> None:
        torch.save({"field": self.field.state(), "mode": self.mode, "frames": self.frames, "rays": self.rays,
                    "cfg": asdict(self.cfg), "steps": self.log.steps, "psnr": self.log.psnr,
                    "refine": asdict(self.refine) if self.refine is not None else None}, path)

    @classmethod
    def load(cls, path: Path, device: torch.device | str = "cpu") -> BackgroundModel:
        try:
            st = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as e:  # noqa: BLE001 - any unreadable file is the same user error
            raise DbbError(f"cannot read the background model {path}: {e}") from None
        log = TrainLog(steps=st["steps"], psnr=st["psnr"])
        known = set(BackgroundConfig.__dataclass_fields__)
        ref = TrainLog(**st["refine"]) if st.get("refine") else None
        return cls(LayerField.from_state(st["field"], device), st["mode"], st["frames"], st["rays"], log,
                   BackgroundConfig(**{k: v for k, v in st["cfg"].items() if k in known}), ref)
