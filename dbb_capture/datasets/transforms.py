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

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..core.errors import InputError
from ..core.fields import entry, text
from ..core.outputs import read_json, write_json
from ..geometry.cameras import Intrinsics
from ..geometry.conventions import corner_from_centre_px, opengl_from_opencv
from .entries import (
    FOCAL_KEYS,
    INTRINSIC_KEYS,
    camera_to_world,
    frame_list,
    frame_split,
    intrinsics,
    object_volume,
    optional_path,
    optional_time,
    source_frame,
    touches_border,
    up_vector,
    version,
    viewpoint,
)
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

    Every entry is checked where it is read (:mod:`.entries`): one :class:`InputError` line
    naming the file, the entry and what it must be, before any image is decoded beyond the first.
    """
    src = find_dataset_file(Path(path))
    where = str(src)
    meta = read_json(src, "dataset")
    raw = frame_list(meta, where)
    root = src.parent
    _check_version(meta, where)
    kind = "crops" if src.name == "crops.json" else (
        "blender" if "fl_x" not in meta and "camera_angle_x" in meta else "transforms")
    top = None
    if any(k in meta for k in FOCAL_KEYS):
        size = None
        if "w" not in meta and "h" not in meta:      # Blender files: the size is the images'
            first = text(entry(raw[0], "file_path", where, parent="frames[0]"), "frames[0].file_path", where)
            size = _image_size(_resolve_image(root, first, f"{where}: frames[0].file_path"))
        top = intrinsics(meta, None, size, where)
    if "up" in meta:
        up_vector(meta["up"], where)
    frames = [_frame(f, f"frames[{i}]", root, top, where) for i, f in enumerate(raw)]
    rgba = (kind in ("crops", "blender") or any(fr.mask_path is not None for fr in frames)
            or _has_alpha(frames[0].image_path))
    volume = _read_volume(meta, root, where)
    return PosedDataset(src, kind, frames, rgba, volume,
                        {k: v for k, v in meta.items() if k not in ("frames",)})


def _check_version(meta: dict, where: str) -> None:
    """A crops.json must be of :data:`DATASET_VERSION` (another principal point convention before)."""
    v = version(meta, where)
    if "crop_size" not in meta and v is None:
        return
    if v is None or v < DATASET_VERSION:
        raise InputError(f"{where} was written by an older version of dbb-capture preprocess "
                         "(another principal point convention): preprocess the capture again")
    if v > DATASET_VERSION:
        raise InputError(f"{where}: dbb_dataset_version {v} is newer than this dbb-capture reads "
                         f"({DATASET_VERSION}): update dbb-capture")


def _frame(f: dict, at: str, root: Path, top: Intrinsics | None, where: str) -> Frame:
    """One ``frames[]`` entry ``f`` (named ``at``) of a dataset in folder ``root``."""
    file_path = text(entry(f, "file_path", where, parent=at), f"{at}.file_path", where)
    c2w = camera_to_world(entry(f, "transform_matrix", where, parent=at), f"{at}.transform_matrix", where)
    img = _resolve_image(root, file_path, f"{where}: {at}.file_path")
    if top is None or any(k in f for k in INTRINSIC_KEYS):
        size = None if "w" in f or "h" in f or top is not None else _image_size(img)
        intr = intrinsics(f, top, size, where, f"{at}.")
    else:
        intr = top
    mask = optional_path(f, "mask_path", where, at)
    seen, room = (optional_path(f, k, where, at) for k in ("observed_path", "background_path"))
    both = seen is not None and room is not None
    return Frame(Path(file_path).stem, img, c2w, intr, frame_split(f, where, at),
                 _resolve_image(root, mask, f"{where}: {at}.mask_path") if mask else None,
                 optional_time(f, where, at),
                 _resolve_image(root, seen, f"{where}: {at}.observed_path") if both else None,
                 _resolve_image(root, room, f"{where}: {at}.background_path") if both else None,
                 source_frame(f, where, at), viewpoint(f, where, at), touches_border(f, where, at))


def load_cameras(path: Path) -> list[Frame]:
    """The cameras of a transforms-style cameras file (top-level or per-frame intrinsics, OpenGL
    camera-to-world): frames named after the basename of their ``file_path``, whose images need
    not exist (``image_path`` is the path as written). One clear :class:`InputError` otherwise."""
    path = Path(path)
    where = str(path)
    meta = read_json(path, "cameras file")
    raw = frame_list(meta, where)
    top = intrinsics(meta, None, None, where) if any(k in meta for k in FOCAL_KEYS) else None
    frames = []
    for i, f in enumerate(raw):
        at = f"frames[{i}]"
        file_path = text(entry(f, "file_path", where, parent=at), f"{at}.file_path", where)
        c2w = camera_to_world(entry(f, "transform_matrix", where, parent=at), f"{at}.transform_matrix", where)
        if top is None and not any(k in f for k in FOCAL_KEYS):
            raise InputError(f"{where}: {at} has no intrinsics (fl_x, fl_y, cx, cy, w, h at the top level or per frame)")
        intr = intrinsics(f, top, None, where, f"{at}.") if top is None or any(k in f for k in INTRINSIC_KEYS) else top
        frames.append(Frame(Path(file_path).stem, Path(file_path), c2w, intr, time=optional_time(f, where, at)))
    return frames


def load_poses(path: Path) -> tuple[np.ndarray, dict]:
    """The camera poses of a dataset folder or file without reading its images or intrinsics:
    OpenCV camera-to-world (N, 4, 4) of its frames, and its top-level keys (``up``, ``object`` ...)."""
    src = find_dataset_file(Path(path))
    meta = read_json(src, "dataset")
    raw = frame_list(meta, str(src))
    c2w = np.stack([camera_to_world(entry(f, "transform_matrix", str(src), parent=f"frames[{i}]"),
                                    f"frames[{i}].transform_matrix", str(src)) for i, f in enumerate(raw)])
    return c2w, {k: v for k, v in meta.items() if k != "frames"}


def _read_volume(meta: dict, root: Path, where: str) -> ObjectVolume | None:
    """Object sphere from the dataset json (``object``) or an ``object.json`` beside it."""
    obj = entry(meta, "object", where, None)
    if obj is not None:
        return object_volume(obj, where)
    if (root / "object.json").is_file():
        return object_volume(read_json(root / "object.json", "object file"), str(root / "object.json"), "")
    return None


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
