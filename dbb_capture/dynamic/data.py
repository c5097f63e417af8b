"""The RSSM's data: a preprocess dataset's crops in memory, its sequence windows, training batches
and their augmentation."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from ..core.errors import DbbError
from ..core.images import resize_rgba
from ..core.fields import MISSING, entry, number, shown, type_name
from ..core.progress import progress
from ..crops.sequences import sequence_windows
from ..datasets.images import load_rgba
from ..datasets.entries import frame_split, up_vector
from ..datasets.transforms import find_dataset_file, load_dataset, missing_crops
from .anchor import ViewAtlas
from .rgba import premultiply


@dataclass
class SequenceData:
    """Frames of a crops.json dataset in memory, and the sequence windows over them."""

    source: Path
    rgba: np.ndarray               # (N, S, S, 4) uint8 straight RGBA
    views: np.ndarray              # (N, 3) float32 [azimuth_deg, elevation_deg, distance_m]
    splits: np.ndarray             # (N,) str
    times: np.ndarray              # (N,) seconds
    windows: list[tuple[int, str]]  # (start, split)
    length: int                    # frames per window (1 context + predicted)
    meta: dict = field(default_factory=dict)
    atlas: ViewAtlas | None = None  # the view anchor (with_anchor), and its render at each frame's view:
    anchor: np.ndarray | None = None  # (N, 4, S, S) uint8 premultiplied RGBA

    def starts(self, split: str) -> np.ndarray:
        return np.array([s for s, sp in self.windows if sp == split], dtype=np.int64)

    def horizon(self) -> int:
        """Open-loop steps a window trains (``length`` - 1): the stepper's temperature warm-up."""
        return self.length - 1

    def fixed_camera(self) -> bool:
        """Whether every frame has the same viewpoint (preprocess's fixed-camera mode)."""
        return bool(np.ptp(self.views[:, :2], 0).max() < 1e-3)

    def fps(self) -> float | None:
        """Frames per second (the median frame interval's), None for a single frame."""
        if len(self.times) < 2:
            return None
        return round(1.0 / float(np.median(np.diff(self.times))), 4)


def load_sequences(dataset: Path, size: int = 64) -> SequenceData:
    """Read ``crops.json`` (RGBA crops, per-frame ``viewpoint``, ``split``, ``time``; the window
    length ``sequence_length``, the windows ``sequences`` and the scene's ``up``, as preprocess
    writes them), every entry checked before a crop is decoded."""
    why = missing_crops(Path(dataset))
    if why is not None:
        raise DbbError(why)
    src = find_dataset_file(Path(dataset))
    if src.name != "crops.json":
        raise DbbError(f"{dataset}: the RSSM trains on a preprocess dataset (crops.json), found {src.name}")
    ds = load_dataset(src)
    meta, where, n = ds.extras, str(src), len(ds.frames)
    for i, fr in enumerate(ds.frames):
        if fr.viewpoint is None:
            raise DbbError(f"{where}: frames[{i}].viewpoint is missing ({{azimuth_deg, elevation_deg, distance_m}})")
        if fr.time is None:
            raise DbbError(f"{where}: frames[{i}].time is missing (seconds)")
    up_vector(entry(meta, "up", where), where)
    length = int(number(entry(meta, "sequence_length", where), "sequence_length", where, low=2, high=n,
                        integer=True, unit=" frames"))
    windows = _windows(entry(meta, "sequences", where), length, n, where)
    if not any(sp == "train" for _, sp in windows):
        raise DbbError(f"{where}: no training sequences of {length} consecutive frames")
    splits = np.array([fr.split for fr in ds.frames])
    imgs = np.empty((n, size, size, 4), np.uint8)
    with progress(transient=True) as prog:
        task = prog.add_task("load crops", total=n, info="")
        for i, fr in enumerate(ds.frames):
            imgs[i] = np.round(resize_rgba(load_rgba(fr), size) * 255).astype(np.uint8)
            prog.update(task, advance=1)
    views = np.array([[fr.viewpoint.azimuth_deg, fr.viewpoint.elevation_deg, fr.viewpoint.distance_m]
                      for fr in ds.frames], np.float32)
    return SequenceData(src, imgs, views, splits, np.array([fr.time for fr in ds.frames]), windows, length,
                        dict(meta))


def with_anchor(data: SequenceData, atlas: ViewAtlas | None) -> SequenceData:
    """``data`` with the view anchor ``atlas`` and its render at every frame's view (None: without)."""
    if atlas is None:
        return replace(data, atlas=None, anchor=None)
    views = torch.from_numpy(data.views)
    with torch.no_grad():
        a = torch.cat([atlas(views[i:i + 256]) for i in range(0, len(views), 256)])
    return replace(data, atlas=atlas, anchor=(a * 255).round().to(torch.uint8).numpy())


def _windows(value: object, length: int, n: int, where: str) -> list[tuple[int, str]]:
    """The ``sequences`` entry: windows ``{"start": frame, "split": train | test}`` of ``length``
    frames that lie within the ``n`` frames."""
    if not isinstance(value, list):
        raise DbbError(f"{where}: sequences must be a list of windows {{start, split}}, not {type_name(value)} "
                       f"({shown(value)})")
    windows = []
    for i, w in enumerate(value):
        at = f"sequences[{i}]"
        start = int(number(entry(w, "start", where, parent=at), f"{at}.start", where, low=0, high=n - length,
                           integer=True))
        windows.append((start, frame_split(w, where, at, default=MISSING)))
    return windows


def training_windows(data: SequenceData, horizon: int | None) -> tuple[np.ndarray, int]:
    """Starts and length (1 + ``horizon``) of windows cut from runs of consecutive training frames
    (no gap, no split change), for the latent-only steps (``TrainConfig.dynamics_horizon``); the
    horizon shrinks to what the training frames allow, and ``None`` keeps the dataset's windows."""
    if horizon is None or horizon + 1 == data.length:
        return data.starts("train"), data.length
    n_train = int((data.splits == "train").sum())
    for length in range(min(horizon + 1, n_train), data.length - 1, -1):
        # At least half as many windows as frames: a handful of long windows would be memorised.
        w = sequence_windows(data.times, data.splits, length)
        starts = np.array([s for s, sp in w if sp == "train"], dtype=np.int64)
        if len(starts) >= max(1, n_train // 2):
            return starts, length
    return data.starts("train"), data.length


def long_training_runs(data: SequenceData, steps: int, count: int) -> tuple[np.ndarray, int]:
    """``count`` evenly spread starts of runs of consecutive training frames, and their length: the
    longest (at most 1 + ``steps``, at least the dataset's window) at which ``count`` starts lie a
    window's length apart or more, so they see different views and moments (footage with gaps
    may have one long run, where ``count`` starts a frame apart would be one view); when no length
    has that many, the length with the most (the longest of those)."""
    best = (0, np.zeros(0, np.int64), 0)
    for length in range(min(steps + 1, len(data.times)), data.length - 1, -1):
        apart = []
        for s, sp in sequence_windows(data.times, data.splits, length):
            if sp == "train" and (not apart or s >= apart[-1] + data.length):
                apart.append(s)
        if len(apart) > best[0]:
            best = (len(apart), np.array(apart, np.int64), length)
        if len(apart) >= count:
            break
    _, starts, length = best
    if len(starts) > count:
        starts = starts[np.unique(np.linspace(0, len(starts) - 1, count).round().astype(int))]
    return starts, length


def batch(data: SequenceData, starts: np.ndarray, device: torch.device,
          length: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Premultiplied RGBA (B, L, 4, S, S) float and views (B, L, 3) of windows starting at ``starts``
    (L = ``length``, default the dataset's window length)."""
    idx = starts[:, None] + np.arange(length or data.length)[None]
    x = torch.from_numpy(data.rgba[idx]).to(device).permute(0, 1, 4, 2, 3).float() / 255.0
    return premultiply(x), torch.from_numpy(data.views[idx]).to(device)


def anchor_batch(data: SequenceData, starts: np.ndarray, device: torch.device,
                 length: int | None = None) -> torch.Tensor | None:
    """The view anchor's premultiplied RGBA (B, L, 4, S, S) float at the views of the windows
    starting at ``starts`` (as :func:`batch`); None without an anchor."""
    if data.anchor is None:
        return None
    idx = starts[:, None] + np.arange(length or data.length)[None]
    return torch.from_numpy(data.anchor[idx]).to(device).float() / 255.0


def first_frames(data: SequenceData, idx: np.ndarray) -> torch.Tensor:
    """Straight RGBA (B, 4, S, S) float of frames ``idx`` (B,): what a rollout starts from."""
    return torch.from_numpy(data.rgba[idx]).permute(0, 3, 1, 2).float() / 255.0


def augment(x: torch.Tensor, views: torch.Tensor, how: str, rng: np.random.Generator,
            anchor: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Training windows ``x`` (B, L, 4, S, S), ``views`` (B, L, 3), each changed with probability 1/2
    as ``how`` asks (``TrainConfig.augment``): "flip" mirrors the frames left-right and negates the
    azimuth (the mirrored toy seen from the mirrored side), "reverse" plays the window backwards.
    "shift" moves every window by a random whole-pixel offset of up to S/16 (:func:`shift_windows`).
    The view anchor's renders ``anchor`` (B, L, 4, S, S) change with their frames (a mirrored
    render, not the render at the negated azimuth: the mirrored toy's anchor).

    The toy is seen along one camera path, each viewpoint at one time: the model can learn which
    pose goes with which view and window instead of how the toy moves (2-5 dB better on training
    windows than on held-out ones without these; docs/decisions.md, augment); mirrored and reversed
    windows are motions it has not seen.
    """
    if anchor is not None:
        x, views, _ = augment(torch.cat([x, anchor], 2), views, how, rng)
        return x[:, :, :4], views, x[:, :, 4:]
    kinds = set(how.split(","))
    B = x.shape[0]
    if "flip" in kinds:
        f = torch.from_numpy(rng.random(B) < 0.5).to(x.device)
        x = torch.where(f[:, None, None, None, None], x.flip(-1), x)
        views = torch.where(f[:, None, None], views * views.new_tensor([-1.0, 1.0, 1.0]), views)
    if "reverse" in kinds:
        r = torch.from_numpy(rng.random(B) < 0.5).to(x.device)
        x = torch.where(r[:, None, None, None, None], x.flip(1), x)
        views = torch.where(r[:, None, None], views.flip(1), views)
    if "shift" in kinds:
        x = shift_windows(x, rng.integers(-(x.shape[-1] // 16), x.shape[-1] // 16 + 1, size=(B, 2)))
    return x, views, None


def shift_windows(x: torch.Tensor, offsets: np.ndarray) -> torch.Tensor:
    """Windows ``x`` (B, L, C, S, S) each moved by whole pixels ``offsets`` (B, 2) = (dx, dy), the
    same for every frame of a window (its motion is kept), edges repeated (DrQ's random shift).

    The crops put the toy at one place in the frame; a model that only ever sees it there can key
    its motion to pixel positions it will not meet at new viewpoints, where the crop sits a pixel
    or two off."""
    B, L, C, S, _ = x.shape
    k = int(np.abs(offsets).max()) if len(offsets) else 0
    if k == 0:
        return x
    pad = F.pad(x.reshape(B, L * C, S, S), (k, k, k, k), mode="replicate")
    out = [pad[b, :, k - dy:k - dy + S, k - dx:k - dx + S] for b, (dx, dy) in enumerate(offsets.tolist())]
    return torch.stack(out).reshape(B, L, C, S, S)
