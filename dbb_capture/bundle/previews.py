"""A bundle's previews: a turntable, a sheet of views at several elevations, a rollout strip."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from ..core.errors import DbbError
from ..core.images import to_u8
from ..crops.camera import crop_camera
from ..geometry.cameras import Intrinsics
from ..geometry.transforms import invert_rigid, look_at
from .render import SEED, DynamicRenderer, StaticRenderer, View

PREVIEW_PX = 160            # preview cell size: cheap enough for the 15-minute demo on 2 cores


TURNTABLE_FRAMES = 24


SHEET_ELEVATIONS = (0.0, 30.0, 60.0)


SHEET_AZIMUTHS = 6


PREVIEW_FILL = 0.9          # the object sphere's share of a preview's side


def orbit_view(name: str, T: np.ndarray, radius: float, az_deg: float, el_deg: float, dist: float,
               size: int = PREVIEW_PX) -> View:
    """A preview camera on a sphere around the object, looking at its centre, up kept up.

    Azimuth is right-handed about +Y (bundle space) from +X, like :class:`~.crops.Viewpoint`;
    the intrinsics make the object sphere fill :data:`PREVIEW_FILL` of the square image.
    """
    a, e = math.radians(az_deg), math.radians(el_deg)
    eye_b = dist * np.array([math.cos(e) * math.cos(a), math.sin(e), -math.cos(e) * math.sin(a)])
    board_from_bundle = invert_rigid(T)
    eye = board_from_bundle[:3, :3] @ eye_b + board_from_bundle[:3, 3]
    center, up = board_from_bundle[:3, 3], board_from_bundle[:3, 1]
    cam = crop_camera(look_at(eye, center, up), Intrinsics(size, size, 1.0, 1.0, 0.0, 0.0), center, radius,
                      up, size, PREVIEW_FILL)
    return View(name, cam.c2w, cam.intr)


def _checker(h: int, w: int, cell: int = 8) -> np.ndarray:
    yy, xx = np.mgrid[:h, :w]
    return np.where(((yy // cell) + (xx // cell)) % 2 == 0, 0.6, 0.8)[..., None]


def over_checker(rgba: np.ndarray) -> np.ndarray:
    """RGB uint8 of straight RGBA uint8 (H, W, 4) over a grey checkerboard."""
    f = rgba.astype(np.float32) / 255.0
    bg = _checker(*rgba.shape[:2])
    return to_u8(f[..., :3] * f[..., 3:] + (1 - f[..., 3:]) * bg)


def write_gif(path: Path, frames: list[np.ndarray], fps: float = 12.0) -> None:
    from PIL import Image

    ims = [Image.fromarray(over_checker(f)) for f in frames]
    ims[0].save(path, save_all=True, append_images=ims[1:], duration=int(1000 / fps), loop=0)


def tile(cells: list[np.ndarray], cols: int) -> np.ndarray:
    """Straight RGBA cells (S, S, 4) in a grid of ``cols`` columns (transparent gaps of 0)."""
    S = cells[0].shape[0]
    rows = math.ceil(len(cells) / cols)
    out = np.zeros((rows * S, cols * S, 4), np.uint8)
    for i, c in enumerate(cells):
        r, k = divmod(i, cols)
        out[r * S:(r + 1) * S, k * S:(k + 1) * S] = c
    return out


def cell(sheet: np.ndarray, i: int, cols: int, S: int) -> np.ndarray:
    r, k = divmod(i, cols)
    return sheet[r * S:(r + 1) * S, k * S:(k + 1) * S]


def write_png(path: Path, rgba: np.ndarray) -> None:
    if not cv2.imwrite(str(path), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA)):
        raise DbbError(f"cannot write {path}")


def preview_plan(dist: float, az0: float = 0.0) -> dict:
    """Viewpoints of the previews: turntable at 20 degrees, sheet rows at SHEET_ELEVATIONS;
    both start at azimuth ``az0`` (the side the capture saw best)."""
    tt = [[az0 + 360.0 * i / TURNTABLE_FRAMES, 20.0, dist] for i in range(TURNTABLE_FRAMES)]
    sheet = [[az0 + 360.0 * k / SHEET_AZIMUTHS, e, dist] for e in SHEET_ELEVATIONS for k in range(SHEET_AZIMUTHS)]
    return {"turntable": tt, "sheet": sheet}


def _views(plan: list[list[float]], T: np.ndarray, radius: float) -> list[View]:
    return [orbit_view(f"{i:03d}", T, radius, a, e, d) for i, (a, e, d) in enumerate(plan)]


def write_static_previews(folder: Path, tree, T: np.ndarray, radius: float, az0: float,
                          prog) -> dict:
    """``tree``: the bundle's PlenOctree (a path or the tree read from it)."""
    plan = preview_plan(3.0 * radius, az0)
    r = StaticRenderer(tree)
    task = prog.add_task("previews", total=len(plan["turntable"]) + len(plan["sheet"]), info="static")
    tick = lambda: prog.advance(task)
    turntable = r.render(_views(plan["turntable"], T, radius), tick)
    sheet = r.render(_views(plan["sheet"], T, radius), tick)
    folder.mkdir(parents=True, exist_ok=True)
    write_gif(folder / "turntable.gif", turntable)
    write_png(folder / "sheet.png", tile(sheet, SHEET_AZIMUTHS))
    return _preview_json(plan, "straight RGBA renders of the tree")


def _preview_json(plan: dict, what: str) -> dict:
    return {"cell_px": PREVIEW_PX, "fill": PREVIEW_FILL, "space": "views as [azimuth_deg, elevation_deg, "
            "distance_m] about bundle +Y from +X, looking at the object centre",
            "turntable": {"file": "previews/turntable.gif", "views": plan["turntable"],
                          "note": "over a grey checkerboard (GIF has no partial alpha)"},
            "sheet": {"file": "previews/sheet.png", "columns": SHEET_AZIMUTHS, "views": plan["sheet"],
                      "note": what}}


def write_dynamic_previews(folder: Path, r: DynamicRenderer, prog) -> dict:
    """Turntable, elevation sheet (one step from the context at each view) and a rollout strip."""
    a0, e0, d0 = (float(x) for x in r.first_view)
    plan = preview_plan(d0, a0)
    plan["turntable"] = [[a0 + a, e0, d0] for a, _, _ in plan["turntable"]]
    task = prog.add_task("previews", total=3, info="dynamic")
    turntable = list(r.frames(np.array(plan["turntable"])))
    prog.advance(task)
    # Each sheet cell starts from the context again: the object's first step seen from that view.
    sheet = [r.frames(np.array([v]))[0] for v in plan["sheet"]]
    prog.advance(task)
    still = [[a0, e0, d0]] * 16
    sweep = [[a0 - 45 + 90 * i / 15, e0, d0] for i in range(16)]
    strip = np.concatenate([r.frames(np.array(still)), r.frames(np.array(sweep))])
    prog.advance(task)
    folder.mkdir(parents=True, exist_ok=True)
    S = r.size
    write_gif(folder / "turntable.gif", [cv2.resize(f, (PREVIEW_PX, PREVIEW_PX), interpolation=cv2.INTER_LINEAR)
                                         for f in turntable])
    write_png(folder / "sheet.png", tile(sheet, SHEET_AZIMUTHS))
    write_png(folder / "rollout.png", tile(list(strip), 16))
    out = _preview_json(plan, "one model step from the first frame at each view")
    out["cell_px"] = S
    out["rollout"] = {"file": "previews/rollout.png", "columns": 16, "seed": SEED,
                      "rows": {"still": still, "sweep": sweep},
                      "note": "row 1: 16 steps at the first frame's viewpoint; row 2: azimuth sweeping 90 degrees"}
    out["seed"] = SEED
    return out
