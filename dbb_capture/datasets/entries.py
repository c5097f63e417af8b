"""Typed reads of the entries of a transforms-style file (``transforms.json``, ``crops.json``, a
cameras file), each checked on its own so a message names the file, the entry and what it must be
(``…/transforms.json: frames[3].fl_x -1 px must be at least 1.2 px``).

Ranges are wide (no real camera or scene is refused) and exist so that a damaged or hand-edited
value is refused where the file is read, not met later as an overflow, an empty render or a
training run that sees nothing.
"""

from __future__ import annotations

import math
import numpy as np

from ..core.errors import InputError
from ..core.fields import entry, flag, matrix, number, numbers, shown, text, type_name
from ..geometry.cameras import MAX_SIDE_PX, Intrinsics
from ..geometry.conventions import centre_from_corner_px, opencv_from_opengl
from ..geometry.viewpoint import Viewpoint
from .records import ObjectVolume

# Focal lengths in units of the image's longer side: fields of view from about 170 degrees down
# to 0.06 degrees (a crop of a small object seen from afar is a long lens).
FOCAL_SIDES = (0.05, 1000.0)
PRINCIPAL_SPAN = 100.0       # principal point within this many image sides or focal lengths of the image
DISTORTION_LIMIT = 1000.0    # |k1, k2, k3, p1, p2|: beyond this no lens model is meant
WORLD_LIMIT = 1e6            # coordinates and distances in world units (metres for captures)
MAX_TIME_S = 1e6             # frame times: seconds from the footage's start (11 days)
ROTATION_TOLERANCE = 0.01    # |R^T R - I|: poses are rigid; files rounded to a few digits still pass
CAMERA_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")
FOCAL_KEYS = ("fl_x", "fl_y", "camera_angle_x")
INTRINSIC_KEYS = (*FOCAL_KEYS, "camera_angle_y", "w", "h", "cx", "cy", "camera_model", *DISTORTION_KEYS)


def frame_list(meta: object, where: str) -> list[dict]:
    """The ``frames`` of document ``meta``: a non-empty list of JSON objects."""
    frames = entry(meta, "frames", where)
    if not isinstance(frames, list) or not frames:
        got = "an empty list" if isinstance(frames, list) else f"{type_name(frames)} ({shown(frames)})"
        raise InputError(f"{where}: frames must be a non-empty list of frames, not {got}")
    for i, f in enumerate(frames):
        if not isinstance(f, dict):
            raise InputError(f"{where}: frames[{i}] must be a JSON object, not {type_name(f)} ({shown(f)})")
    return frames


def intrinsics(d: dict, fallback: Intrinsics | None, size: tuple[int, int] | None, where: str,
               at: str = "") -> Intrinsics:
    """Intrinsics from the nerfstudio keys of ``d`` (``at`` names it: ``frames[3].``) over
    ``fallback``; ``size`` = (w, h) of the image, used where ``d`` gives neither side."""
    base = fallback.to_json() if fallback is not None else {}
    given = "w" in d or "h" in d
    w = _side(d, "w", base.get("width", None if given or size is None else size[0]), where, at)
    h = _side(d, "h", base.get("height", None if given or size is None else size[1]), where, at)
    lo, hi = FOCAL_SIDES[0] * max(w, h), FOCAL_SIDES[1] * max(w, h)
    fx = _focal(d, "fl_x", "camera_angle_x", w, (lo, hi), where, at)
    if fx is None:
        if "fx" not in base:
            raise InputError(f"{where}: {at}fl_x is missing (the focal length in pixels; or camera_angle_x)")
        fx = float(base["fx"])
    fy = _focal(d, "fl_y", "camera_angle_y", h, (lo, hi), where, at)
    if fy is None:
        # A camera given its own fl_x alone has square pixels; else the shared camera's.
        fy = fx if ("fl_x" in d or "camera_angle_x" in d or "fy" not in base) else float(base["fy"])
    span = PRINCIPAL_SPAN * max(w, h, fx, fy)
    # The file's principal point has the corner origin; a fallback (an Intrinsics) is OpenCV's
    # already, and without either the image centre is (w - 1) / 2 in OpenCV's pixels.
    cx, cy = (centre_from_corner_px(number(d[k], at + k, where, low=-span, high=span, unit=" px")) if k in d
              else float(base.get(k, (n - 1) / 2)) for k, n in (("cx", w), ("cy", h)))
    model = text(d["camera_model"], at + "camera_model", where) if "camera_model" in d else "OPENCV"
    if model not in CAMERA_MODELS:
        raise InputError(f"{where}: {at}camera_model {model!r} is not supported (use OPENCV)")
    old = list(base.get("dist", [0.0] * 5))
    dist = tuple(number(d[k], at + k, where, low=-DISTORTION_LIMIT, high=DISTORTION_LIMIT) if k in d
                 else float(old[i]) for i, k in enumerate(DISTORTION_KEYS))
    return Intrinsics(w, h, fx, fy, cx, cy, dist)


def _side(d: dict, key: str, default: int | None, where: str, at: str) -> int:
    """Image width (``w``) or height (``h``) in whole pixels; ``default`` where ``d`` has none."""
    if key in d:
        return int(number(d[key], at + key, where, low=1, high=MAX_SIDE_PX, integer=True, unit=" px"))
    if default is None:
        side = "width" if key == "w" else "height"
        raise InputError(f"{where}: {at}{key} is missing (the image {side} in pixels)")
    return int(default)


def _focal(d: dict, key: str, angle: str, side: int, bounds: tuple[float, float], where: str,
           at: str) -> float | None:
    """Focal length in pixels from ``key`` or from the field of view ``angle`` (radians) over
    ``side`` pixels; None where ``d`` has neither."""
    if key in d:
        return number(d[key], at + key, where, low=bounds[0], high=bounds[1], unit=" px")
    if angle not in d:
        return None
    a = number(d[angle], at + angle, where, low=0, low_open=True, high=math.pi, unit=" rad")
    f = 0.5 * side / math.tan(0.5 * a) if a < math.pi else 0.0
    return number(f, f"the focal length {at}{angle} gives", where, low=bounds[0], high=bounds[1], unit=" px")


def camera_to_world(value: object, name: str, where: str) -> np.ndarray:
    """OpenCV camera-to-world (4, 4) from an OpenGL ``transform_matrix`` (4x4 or 3x4): a rotation
    and a translation within :data:`WORLD_LIMIT`."""
    m = np.asarray(matrix(value, name, where, ((4, 4), (3, 4))), np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
        raise InputError(f"{where}: {name} must end with the row [0, 0, 0, 1], not {shown(m[3].tolist())}")
    R = m[:3, :3]
    off = float(np.abs(R.T @ R - np.eye(3)).max())
    if not off <= ROTATION_TOLERANCE or np.linalg.det(R) <= 0:
        raise InputError(f"{where}: {name} must be a camera pose: its 3x3 part a rotation (orthonormal, "
                         f"determinant 1), not one off by {off:.2g}" + ("" if off > ROTATION_TOLERANCE
                                                                         else " with a mirror"))
    if np.abs(m[:3, 3]).max() > WORLD_LIMIT:
        raise InputError(f"{where}: {name} puts the camera at {shown(m[:3, 3].tolist())}, "
                         f"more than {WORLD_LIMIT:g} from the origin")
    return opencv_from_opengl(m)


def optional_time(f: dict, where: str, at: str) -> float | None:
    """A frame's ``time`` in seconds from the footage's start, None where absent (or null)."""
    t = entry(f, "time", where, None, parent=at)
    return None if t is None else number(t, f"{at}.time", where, low=0, high=MAX_TIME_S, unit=" s")


def optional_path(f: dict, key: str, where: str, at: str) -> str | None:
    """A frame's optional path entry ``key`` (``mask_path`` ...), None where absent, null or empty."""
    p = entry(f, key, where, None, parent=at)
    return text(p, f"{at}.{key}", where) or None if p is not None else None


def frame_split(f: dict, where: str, at: str, default: object = "train") -> str:
    """The ``split`` of entry ``f`` (named ``at``: a frame, a window): train or test (``default``
    where absent)."""
    split = text(entry(f, "split", where, default, parent=at), f"{at}.split", where)
    if split not in ("train", "test"):
        raise InputError(f"{where}: {at}.split must be train or test, not {split!r}")
    return split


def source_frame(f: dict, where: str, at: str) -> int | None:
    """A crop's ``source_frame`` (index of the footage frame it was cut from), None where absent."""
    v = entry(f, "source_frame", where, None, parent=at)
    return None if v is None else int(number(v, f"{at}.source_frame", where, low=0, high=1e9, integer=True))


def touches_border(f: dict, where: str, at: str) -> bool | None:
    """A crop's ``touches_border`` flag, None where absent."""
    v = entry(f, "touches_border", where, None, parent=at)
    return None if v is None else flag(v, f"{at}.touches_border", where)


def viewpoint(f: dict, where: str, at: str) -> Viewpoint | None:
    """A crop's ``viewpoint`` (degrees, metres from the object centre), None where absent."""
    vp = entry(f, "viewpoint", where, None, parent=at)
    if vp is None:
        return None
    name = f"{at}.viewpoint"
    az, el, dist = (entry(vp, k, where, parent=name) for k in ("azimuth_deg", "elevation_deg", "distance_m"))
    return Viewpoint(number(az, f"{name}.azimuth_deg", where, low=-360, high=360, unit=" deg"),
                     number(el, f"{name}.elevation_deg", where, low=-90, high=90, unit=" deg"),
                     number(dist, f"{name}.distance_m", where, low=0, low_open=True, high=WORLD_LIMIT, unit=" m"))


def object_volume(obj: object, where: str, at: str = "object") -> ObjectVolume:
    """The object's sphere ``{"center": [x, y, z], "radius": r}`` (world units) named ``at``."""
    pre = f"{at}." if at else ""
    c = point(entry(obj, "center", where, parent=at), f"{pre}center", where)
    r = number(entry(obj, "radius", where, parent=at), f"{pre}radius", where, low=0, low_open=True,
               high=WORLD_LIMIT)
    return ObjectVolume(tuple(c), r)  # type: ignore[arg-type]


def point(value: object, name: str, where: str) -> list[float]:
    """Three coordinates within :data:`WORLD_LIMIT` of the origin."""
    p = numbers(value, name, where, (3,), " [x, y, z]")
    if max(abs(v) for v in p) > WORLD_LIMIT:
        raise InputError(f"{where}: {name} {shown(p)} lies more than {WORLD_LIMIT:g} from the origin")
    return p


def up_vector(value: object, where: str, name: str = "up") -> np.ndarray:
    """The scene's ``up`` (3,): a direction, returned of unit length."""
    v = np.asarray(numbers(value, name, where, (3,), " [x, y, z]"), np.float64)
    n = float(np.linalg.norm(v))
    if not 1e-9 < n < math.inf:
        raise InputError(f"{where}: {name} {shown(v.tolist())} must be a direction (not zero)")
    return v / n


def version(meta: dict, where: str) -> int | None:
    """``dbb_dataset_version`` of a crops.json (a whole number), None where absent."""
    if "dbb_dataset_version" not in meta:
        return None
    return int(number(meta["dbb_dataset_version"], "dbb_dataset_version", where, low=1, integer=True))
