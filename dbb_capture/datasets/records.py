"""Posed image datasets as typed records, and the rays of their pixels.

Reads the three dataset flavours training accepts:

- nerfstudio / instant-ngp ``transforms.json`` (top-level or per-frame intrinsics, OpenCV
  distortion keys, absolute or relative ``file_path``, optional ``mask_path``);
- Blender / NeRF-synthetic ``transforms_train.json`` (``camera_angle_x`` only, RGBA images,
  ``file_path`` often without extension);
- the project's ``crops.json`` (per-frame crop intrinsics, RGBA crops, ``split``).

Poses in the files are OpenGL camera-to-world; every :class:`Frame` holds the OpenCV
camera-to-world (converted once, by :func:`dbb_capture.geometry.cameras.opencv_from_opengl`).
Principal points in the files are read in the project's pixel convention (centre of the
top-left pixel at (0, 0)), the same convention :meth:`Intrinsics.nerfstudio_fields` writes;
for Blender files the principal point is the image centre, ``((w - 1) / 2, (h - 1) / 2)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..geometry.cameras import Intrinsics
from ..geometry.conventions import opencv_from_opengl
from ..core.errors import InputError
from ..core.outputs import read_json
from ..geometry.cameras import scaled_intrinsics

DATASET_FILES = ("crops.json", "transforms.json", "transforms_train.json")
_IMAGE_EXTS = ("", ".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")


@dataclass(frozen=True)
class Frame:
    """One posed image: where its pixels are, how they were seen and from where."""

    name: str                     # file stem, used to name renders and to pick held-out views
    image_path: Path
    c2w: np.ndarray               # (4, 4) board/world-from-camera, OpenCV camera axes
    intr: Intrinsics
    split: str = "train"          # "train" or "test"
    mask_path: Path | None = None
    time: float | None = None
    # Preprocess crops only: the observed crop and the room predicted behind it (RGB images the
    # matte was cut from), so training can composite over the predicted room (:mod:`.fields`).
    observed_path: Path | None = None
    background_path: Path | None = None


@dataclass(frozen=True)
class ObjectVolume:
    """The sphere that holds the object, in world units (metres for captures)."""

    center: tuple[float, float, float]
    radius: float
    estimated: bool = False       # True when guessed from the cameras, not read from a file

    def to_json(self) -> dict:
        return {"center": [float(c) for c in self.center], "radius": float(self.radius),
                "estimated": self.estimated}


@dataclass(frozen=True)
class PosedDataset:
    """Frames of one dataset file, plus the object volume when the dataset states it."""

    source: Path                  # the json file read
    kind: str                     # "crops", "transforms" or "blender"
    frames: list[Frame]
    rgba: bool                    # images carry an alpha channel (or a mask) to supervise
    volume: ObjectVolume | None = None
    extras: dict = field(default_factory=dict)

    def split(self, name: str) -> list[Frame]:
        return [f for f in self.frames if f.split == name]


def find_dataset_file(path: Path) -> Path:
    """The dataset json inside folder ``path`` (crops.json first), or ``path`` itself if a file."""
    path = Path(path)
    if path.is_file():
        return path
    if not path.is_dir():
        raise InputError(f"dataset not found: {path}")
    for name in DATASET_FILES:
        if (path / name).is_file():
            return path / name
    raise InputError(f"{path} holds none of {', '.join(DATASET_FILES)}")


def _intrinsics(d: dict, fallback: Intrinsics | None, size: tuple[int, int] | None,
                where: str) -> Intrinsics:
    """Intrinsics from nerfstudio keys in ``d`` over ``fallback``; ``size`` = (w, h) if known."""
    base = fallback.to_json() if fallback is not None else {}
    w = d.get("w", base.get("width", size[0] if size else None))
    h = d.get("h", base.get("height", size[1] if size else None))
    if w is None or h is None:
        raise InputError(f"{where}: image size (w, h) missing")
    w, h = int(w), int(h)
    fx = d.get("fl_x", base.get("fx"))
    fy = d.get("fl_y", base.get("fy"))
    if fx is None and "camera_angle_x" in d:
        fx = 0.5 * w / math.tan(0.5 * float(d["camera_angle_x"]))
    if fy is None and "camera_angle_y" in d:
        fy = 0.5 * h / math.tan(0.5 * float(d["camera_angle_y"]))
    if fx is None and fy is None:
        raise InputError(f"{where}: no focal length (fl_x/fl_y or camera_angle_x)")
    fx = float(fx if fx is not None else fy)
    fy = float(fy if fy is not None else fx)
    cx = float(d.get("cx", base.get("cx", (w - 1) / 2)))
    cy = float(d.get("cy", base.get("cy", (h - 1) / 2)))
    model = d.get("camera_model", "OPENCV")
    if model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        raise InputError(f"{where}: camera_model {model!r} is not supported (use OPENCV)")
    old = list(base.get("dist", [0.0] * 5))
    dist = tuple(float(d.get(k, old[i])) for i, k in enumerate(("k1", "k2", "p1", "p2", "k3")))
    return Intrinsics(w, h, fx, fy, cx, cy, dist)


def _resolve_image(root: Path, file_path: str, where: str) -> Path:
    p = Path(file_path)
    if not p.is_absolute():
        p = root / p
    for ext in _IMAGE_EXTS:
        q = p.with_name(p.name + ext) if ext else p
        if q.is_file():
            return q
    raise InputError(f"{where}: image not found: {p}")


def _image_size(path: Path) -> tuple[int, int]:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"cannot read image {path}")
    return img.shape[1], img.shape[0]


def _has_alpha(path: Path) -> bool:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return img is not None and img.ndim == 3 and img.shape[2] == 4


def load_dataset(path: Path) -> PosedDataset:
    """Read a dataset folder or json file into a :class:`PosedDataset`.

    Raises :class:`InputError` with one clear line on any missing key, image or bad matrix.
    """
    src = find_dataset_file(Path(path))
    meta = read_json(src, "dataset")
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise InputError(f"{src}: no frames")
    root = src.parent
    kind = "crops" if src.name == "crops.json" else (
        "blender" if "fl_x" not in meta and "camera_angle_x" in meta else "transforms")
    top = None
    if any(k in meta for k in ("fl_x", "fl_y", "camera_angle_x")):
        size = None
        if "w" not in meta or "h" not in meta:
            first = meta["frames"][0]
            size = _image_size(_resolve_image(root, str(first.get("file_path", "")), str(src)))
        top = _intrinsics(meta, None, size, str(src))
    frames = []
    for i, f in enumerate(meta["frames"]):
        where = f"{src} frame {i}"
        if "file_path" not in f or "transform_matrix" not in f:
            raise InputError(f"{where}: needs file_path and transform_matrix")
        img = _resolve_image(root, str(f["file_path"]), where)
        if any(k in f for k in ("fl_x", "fl_y", "camera_angle_x", "w", "h")) or top is None:
            size = None if ("w" in f and "h" in f) or top is not None else _image_size(img)
            intr = _intrinsics(f, top, size, where)
        else:
            intr = top
        m = np.asarray(f["transform_matrix"], dtype=np.float64)
        if m.shape == (3, 4):
            m = np.vstack([m, [0, 0, 0, 1]])
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise InputError(f"{where}: transform_matrix must be 4x4 finite numbers")
        mask = _resolve_image(root, str(f["mask_path"]), where) if f.get("mask_path") else None
        split = str(f.get("split", "train"))
        if split not in ("train", "test"):
            raise InputError(f"{where}: split must be train or test, not {split!r}")
        seen = room = None
        if f.get("observed_path") and f.get("background_path"):
            seen = _resolve_image(root, str(f["observed_path"]), where)
            room = _resolve_image(root, str(f["background_path"]), where)
        frames.append(Frame(Path(f["file_path"]).stem, img, opencv_from_opengl(m), intr, split, mask,
                            float(f["time"]) if f.get("time") is not None else None, seen, room))
    rgba = (kind in ("crops", "blender") or any(fr.mask_path is not None for fr in frames)
            or _has_alpha(frames[0].image_path))
    volume = _read_volume(meta, root)
    return PosedDataset(src, kind, frames, rgba, volume,
                        {k: v for k, v in meta.items() if k not in ("frames",)})


def _read_volume(meta: dict, root: Path) -> ObjectVolume | None:
    """Object sphere from the dataset json (``object``) or an ``object.json`` beside it."""
    obj = meta.get("object")
    if obj is None and (root / "object.json").is_file():
        obj = read_json(root / "object.json", "object file")
    if obj is None:
        return None
    try:
        c = tuple(float(v) for v in obj["center"])
        r = float(obj["radius"])
    except (KeyError, TypeError, ValueError):
        raise InputError(f"object volume in {root} needs center [x, y, z] and radius") from None
    if len(c) != 3 or not r > 0:
        raise InputError(f"object volume in {root}: center needs 3 values and radius > 0")
    return ObjectVolume(c, r)  # type: ignore[arg-type]


def estimate_volume(frames: list[Frame], margin: float = 1.1) -> ObjectVolume:
    """Guess the object sphere from the cameras alone.

    Centre: the point nearest (least squares) to all optical axes. Radius: what the
    view's half field of view holds at the nearest camera, times ``margin``: an object
    seen whole in every view fits in every view's cone.
    """
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for f in frames:
        o, d = f.c2w[:3, 3], f.c2w[:3, 2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ o
    try:
        c = np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        raise InputError("cannot estimate the object centre: the cameras' axes are parallel") from None
    dist = min(float(np.linalg.norm(f.c2w[:3, 3] - c)) for f in frames)
    # The wider half-angle of each view: tightly framed objects (NeRF-synthetic) stay whole.
    half = min(max(math.atan2(f.intr.width / 2, f.intr.fx), math.atan2(f.intr.height / 2, f.intr.fy))
               for f in frames)
    r = margin * dist * math.sin(half)
    return ObjectVolume(tuple(float(v) for v in c), r, estimated=True)  # type: ignore[arg-type]


def load_rgba(frame: Frame, downscale: float = 1.0) -> np.ndarray:
    """Straight RGBA float32 (h, w, 4) in [0, 1] at 1/``downscale`` size.

    Images without alpha get alpha 1 unless the frame has a mask (black = transparent).
    Resizing averages premultiplied colour so edges keep their true colour.
    """
    import cv2

    img = _read_image(frame.image_path, cv2.IMREAD_UNCHANGED, frame.intr)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    img = img.astype(np.float32) / scale
    rgb = img[..., 2::-1] if img.shape[2] >= 3 else img
    alpha = img[..., 3:4] if img.shape[2] == 4 else np.ones_like(img[..., :1])
    if frame.mask_path is not None:
        m = cv2.imread(str(frame.mask_path), cv2.IMREAD_GRAYSCALE)
        if m is None or m.shape != img.shape[:2]:
            raise InputError(f"mask {frame.mask_path} is unreadable or not the image's size")
        alpha = alpha * (m[..., None].astype(np.float32) / 255.0)
    rgba = _area_downscale(np.concatenate([rgb * alpha, alpha], axis=-1), frame.intr, downscale)
    a = rgba[..., 3:4]
    rgb = np.where(a > 1e-6, rgba[..., :3] / np.maximum(a, 1e-6), 0.0)
    return np.ascontiguousarray(np.concatenate([np.clip(rgb, 0, 1), a], -1), dtype=np.float32)


def load_rgb(path: Path, intr: Intrinsics, downscale: float = 1.0) -> np.ndarray:
    """An RGB image float32 (h, w, 3) in [0, 1] of a frame with intrinsics ``intr``, at
    1/``downscale`` size (area-averaged), e.g. a crop's observed pixels or predicted room."""
    import cv2

    rgb = _read_image(path, cv2.IMREAD_COLOR, intr)[..., ::-1].astype(np.float32) / 255.0
    return np.ascontiguousarray(_area_downscale(rgb, intr, downscale), dtype=np.float32)


def _read_image(path: Path, flags: int, intr: Intrinsics) -> np.ndarray:
    """``cv2.imread`` of a frame's image, which must be ``intr``'s size (clear errors otherwise)."""
    import cv2

    img = cv2.imread(str(path), flags)
    if img is None:
        raise InputError(f"cannot read image {path}")
    if (img.shape[1], img.shape[0]) != (intr.width, intr.height):
        raise InputError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, dataset says {intr.width}x{intr.height}")
    return img


def _area_downscale(img: np.ndarray, intr: Intrinsics, downscale: float) -> np.ndarray:
    """``img`` (h, w, C) float32 of a frame with intrinsics ``intr`` at 1/``downscale`` size (area average)."""
    if downscale == 1:
        return img
    import cv2

    target = scaled_intrinsics(intr, downscale)
    return cv2.resize(img, (target.width, target.height), interpolation=cv2.INTER_AREA)


def holdout_every(frames: list[Frame], n: int) -> list[Frame]:
    """Mark every ``n``-th frame (0, n, 2n, ...) as ``test``; the rest ``train``."""
    if n <= 0:
        return frames
    return [replace(f, split="test" if i % n == 0 else "train") for i, f in enumerate(frames)]


def holdout_named(frames: list[Frame], names: set[str]) -> list[Frame]:
    """Mark frames whose name (file stem) is in ``names`` as ``test``; the rest ``train``."""
    return [replace(f, split="test" if f.name in names else "train") for f in frames]


def write_transforms(path: Path, frames: list[Frame], volume: ObjectVolume | None = None) -> None:
    """Write ``frames`` as a nerfstudio ``transforms.json`` (per-frame intrinsics, OpenGL
    camera-to-world, ``split``), image paths relative to the file where possible."""
    from ..geometry.conventions import opengl_from_opencv
    from ..core.outputs import write_json

    path = Path(path)
    out = []
    for f in frames:
        try:
            rel = str(Path(f.image_path).resolve().relative_to(path.parent.resolve()))
        except ValueError:
            rel = str(Path(f.image_path).resolve())
        d = {"file_path": rel, "transform_matrix": opengl_from_opencv(f.c2w).tolist(), "split": f.split,
             **{k: v for k, v in f.intr.nerfstudio_fields().items()}}
        if f.time is not None:
            d["time"] = f.time
        out.append(d)
    meta: dict = {"camera_model": "OPENCV", "frames": out}
    if volume is not None:
        meta["object"] = {"center": list(volume.center), "radius": volume.radius}
    write_json(path, meta)
