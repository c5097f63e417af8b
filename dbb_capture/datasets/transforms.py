"""The one reader and writer of transforms-style files.

Reads the three dataset flavours training accepts:

- nerfstudio / instant-ngp ``transforms.json`` (top-level or per-frame intrinsics, OpenCV
  distortion keys, absolute or relative ``file_path``, optional ``mask_path``);
- Blender / NeRF-synthetic ``transforms_train.json`` (``camera_angle_x`` only, RGBA images,
  ``file_path`` often without extension);
- the project's ``crops.json`` (per-frame crop intrinsics, RGBA crops, ``split``, ``viewpoint``).

and writes ``transforms.json`` and ``crops.json`` (:func:`write_transforms`). Files hold the
conventions of nerfstudio and instant-ngp, converted here by :mod:`..geometry.conventions`:
OpenGL camera-to-world poses, and principal points with the pixel origin at the image's corner
(``cx = w / 2`` for a centred camera); every :class:`Frame` holds OpenCV's (camera-to-world,
pixel centres at integers). A Blender file's principal point is the image centre. Written files
say ``applied_transform`` (the identity: poses are in the board frame as they are), so nerfstudio
does not insert an axis swap of its own.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..core.errors import InputError
from ..core.outputs import read_json, write_json
from ..geometry.cameras import Intrinsics
from ..geometry.conventions import (
    centre_from_corner_px,
    corner_from_centre_px,
    opencv_from_opengl,
    opengl_from_opencv,
)
from ..geometry.viewpoint import Viewpoint
from .records import Frame, ObjectVolume, PosedDataset

DATASET_FILES = ("crops.json", "transforms.json", "transforms_train.json")
DATASET_VERSION = 2      # crops.json: 2 = principal points with the corner origin (the contract's)
APPLIED_TRANSFORM = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]


_IMAGE_EXTS = ("", ".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")


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


def missing_crops(path: Path) -> str | None:
    """Why the folder ``path``, a preprocess output (``preprocess.json``) without ``crops.json``,
    has no object crops (one line naming the stages it ran and how to make them); None for any
    other path (a folder with crops, a json file, a nerfstudio or Blender dataset)."""
    path = Path(path)
    record = path / "preprocess.json"
    if not path.is_dir() or (path / "crops.json").is_file() or not record.is_file():
        return None
    meta = read_json(record, "preprocess record")
    ran = meta.get("stages_run") if isinstance(meta, dict) else None
    stages = ", ".join(map(str, ran)) if isinstance(ran, list) and ran else "unknown stages"
    return (f"{path} has no object crops (crops.json): preprocess ran only {stages}; run "
            f"`dbb-capture preprocess` without --stop-after to make them")


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
    # The file's principal point has the corner origin; a fallback (an Intrinsics) is OpenCV's
    # already, and without either the image centre is (w - 1) / 2 in OpenCV's pixels.
    cx = centre_from_corner_px(d["cx"]) if "cx" in d else float(base.get("cx", (w - 1) / 2))
    cy = centre_from_corner_px(d["cy"]) if "cy" in d else float(base.get("cy", (h - 1) / 2))
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
    if "crop_size" in meta and meta.get("dbb_dataset_version") != DATASET_VERSION:
        raise InputError(f"{src} was written by an older version of dbb-capture preprocess "
                         "(another principal point convention): preprocess the capture again")
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
        m = _camera_to_world(f, where)
        mask = _resolve_image(root, str(f["mask_path"]), where) if f.get("mask_path") else None
        split = str(f.get("split", "train"))
        if split not in ("train", "test"):
            raise InputError(f"{where}: split must be train or test, not {split!r}")
        seen = room = None
        if f.get("observed_path") and f.get("background_path"):
            seen = _resolve_image(root, str(f["observed_path"]), where)
            room = _resolve_image(root, str(f["background_path"]), where)
        frames.append(Frame(Path(f["file_path"]).stem, img, m, intr, split, mask,
                            float(f["time"]) if f.get("time") is not None else None, seen, room,
                            int(f["source_frame"]) if f.get("source_frame") is not None else None,
                            _viewpoint(f.get("viewpoint"), where),
                            bool(f["touches_border"]) if f.get("touches_border") is not None else None))
    rgba = (kind in ("crops", "blender") or any(fr.mask_path is not None for fr in frames)
            or _has_alpha(frames[0].image_path))
    volume = _read_volume(meta, root)
    return PosedDataset(src, kind, frames, rgba, volume,
                        {k: v for k, v in meta.items() if k not in ("frames",)})


def load_cameras(path: Path) -> list[Frame]:
    """The cameras of a transforms-style cameras file (top-level or per-frame intrinsics, OpenGL
    camera-to-world): frames named after the basename of their ``file_path``, whose images need
    not exist (``image_path`` is the path as written). One clear :class:`InputError` otherwise."""
    path = Path(path)
    meta = read_json(path, "cameras file")
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise InputError(f"{path}: no frames")
    focal = ("fl_x", "fl_y", "camera_angle_x")
    top = _intrinsics(meta, None, None, str(path)) if any(k in meta for k in focal) else None
    frames = []
    for i, f in enumerate(meta["frames"]):
        where = f"{path} frame {i}"
        if not isinstance(f, dict) or "file_path" not in f or "transform_matrix" not in f:
            raise InputError(f"{where}: needs file_path and transform_matrix")
        if top is None and not any(k in f for k in focal):
            raise InputError(f"{where}: missing intrinsics (fl_x, fl_y, cx, cy, w, h at the top level or per frame)")
        intr = _intrinsics(f, top, None, where) if top is None or any(k in f for k in focal) else top
        frames.append(Frame(Path(str(f["file_path"])).stem, Path(str(f["file_path"])), _camera_to_world(f, where), intr,
                            time=float(f["time"]) if isinstance(f.get("time"), (int, float)) else None))
    return frames


def load_poses(path: Path) -> tuple[np.ndarray, dict]:
    """The camera poses of a dataset folder or file without reading its images or intrinsics:
    OpenCV camera-to-world (N, 4, 4) of its frames, and its top-level keys (``up``, ``object`` ...)."""
    src = find_dataset_file(Path(path))
    meta = read_json(src, "dataset")
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise InputError(f"{src}: no frames")
    c2w = np.stack([_camera_to_world(f if isinstance(f, dict) else {}, f"{src} frame {i}")
                    for i, f in enumerate(meta["frames"])])
    return c2w, {k: v for k, v in meta.items() if k != "frames"}


def _camera_to_world(f: dict, where: str) -> np.ndarray:
    """A frame's OpenCV camera-to-world (4, 4) from its OpenGL ``transform_matrix`` (4x4 or 3x4)."""
    try:
        m = np.asarray(f["transform_matrix"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        m = np.zeros(0)
    if m.shape == (3, 4):
        m = np.vstack([m, [0, 0, 0, 1]])
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise InputError(f"{where}: transform_matrix must be 4x4 finite numbers")
    return opencv_from_opengl(m)


def _viewpoint(vp, where: str) -> Viewpoint | None:
    """A frame's ``viewpoint`` entry (crops.json), or None where it has none."""
    if vp is None:
        return None
    try:
        return Viewpoint(float(vp["azimuth_deg"]), float(vp["elevation_deg"]), float(vp["distance_m"]))
    except (TypeError, KeyError, ValueError):
        raise InputError(f"{where}: viewpoint needs azimuth_deg, elevation_deg, distance_m") from None


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


def intrinsics_fields(intr: Intrinsics) -> dict:
    """The intrinsics keys of a nerfstudio ``transforms.json`` (OPENCV camera model) for ``intr``."""
    k1, k2, p1, p2, k3 = (float(v) for v in intr.dist_array)
    return {"camera_model": "OPENCV", "fl_x": intr.fx, "fl_y": intr.fy, "cx": corner_from_centre_px(intr.cx),
            "cy": corner_from_centre_px(intr.cy), "w": intr.width, "h": intr.height,
            "k1": k1, "k2": k2, "k3": k3, "p1": p1, "p2": p2}


def relative_path(path: Path | None, root: Path) -> str | None:
    """``path`` relative to the folder ``root`` where it lies inside it, else absolute."""
    if path is None:
        return None
    try:
        return str(Path(path).resolve().relative_to(root.resolve()))
    except ValueError:
        return str(Path(path).resolve())


def frame_json(f: Frame, root: Path, own_camera: bool, with_split: bool) -> dict:
    """One ``frames[]`` entry: paths relative to ``root``, OpenGL camera-to-world, and with
    ``own_camera`` the frame's own pinhole (``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``);
    ``split`` only ``with_split`` (readers take a frame without one for training)."""
    d: dict = {"file_path": relative_path(f.image_path, root),
               "transform_matrix": opengl_from_opencv(f.c2w).round(9).tolist()}
    if own_camera:
        i = f.intr
        d.update({"fl_x": i.fx, "fl_y": i.fy, "cx": corner_from_centre_px(i.cx), "cy": corner_from_centre_px(i.cy),
                  "w": i.width, "h": i.height})
    if f.source_frame is not None:
        d["source_frame"] = f.source_frame
    if f.time is not None:
        d["time"] = round(float(f.time), 6)
    if f.viewpoint is not None:
        d["viewpoint"] = f.viewpoint.to_json()
    if with_split:
        d["split"] = f.split
    if f.touches_border is not None:
        d["touches_border"] = f.touches_border
    if f.mask_path is not None:
        d["mask_path"] = relative_path(f.mask_path, root)
    if f.observed_path is not None and f.background_path is not None:
        d["observed_path"] = relative_path(f.observed_path, root)
        d["background_path"] = relative_path(f.background_path, root)
    return d


def write_transforms(path: Path, frames: Sequence[Frame], volume: ObjectVolume | None = None,
                     extra: dict | None = None, own_cameras: bool | None = None) -> None:
    """Write ``frames`` as a nerfstudio-schema file (``transforms.json``, ``crops.json``, a
    cameras file): one camera for all at the top level when they share it, else each frame's
    own pinhole (and the shared size and distortion at the top level; ``own_cameras`` True: always
    the frame's own, as crops.json has it); the object's ``volume``
    as ``object`` and ``extra`` keys join the top level before ``frames``. Image paths are
    relative to the file's folder where possible."""
    path = Path(path)
    shared = not own_cameras and all(f.intr == frames[0].intr for f in frames)
    top = intrinsics_fields(frames[0].intr) if frames else {"camera_model": "OPENCV"}
    if not shared:
        top = {k: v for k, v in top.items() if k not in ("fl_x", "fl_y", "cx", "cy")}
        if any((f.intr.width, f.intr.height) != (frames[0].intr.width, frames[0].intr.height) for f in frames):
            top = {k: v for k, v in top.items() if k not in ("w", "h")}
    with_split = any(f.split != "train" for f in frames)
    top["applied_transform"] = APPLIED_TRANSFORM
    if volume is not None:
        top["object"] = {"center": [float(c) for c in volume.center], "radius": float(volume.radius)}
    write_json(path, {**top, **(extra or {}),
                      "frames": [frame_json(f, path.parent, not shared, with_split) for f in frames]})


def write_crops(path: Path, frames: Sequence[Frame], center: np.ndarray, radius: float, up: np.ndarray,
                crop_size: int, crop_fill: float, sequence_length: int, sequences: Sequence[tuple[int, str]],
                extra: dict | None = None) -> None:
    """Write a ``crops.json``: :func:`write_transforms` of the crop frames (each its own camera)
    with the object's sphere (board frame, metres), the scene's ``up`` (3,), the crop size and
    fill, and the sequence windows ``sequences`` ([(start frame, split)] of ``sequence_length``
    frames: 1 context + N predicted)."""
    write_transforms(path, frames, extra={
        "dbb_dataset_version": DATASET_VERSION,
        "object": {"center": [round(float(v), 6) for v in center], "radius": round(float(radius), 6)},
        "up": [float(v) for v in up], "crop_size": crop_size, "crop_fill": crop_fill,
        "sequence_length": sequence_length, "sequences": [{"start": s, "split": sp} for s, sp in sequences],
        **(extra or {})}, own_cameras=True)
