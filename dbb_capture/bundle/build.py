"""Billboard asset bundles: package a training run, render from a bundle, verify a bundle.

A bundle is a folder (or the same folder zipped, ``.dbb``) holding:

- ``manifest.json``: :class:`Manifest` (format ``"deep-billboard"``, version, kind, model and
  the inputs it expects, ``bundle_from_board``, object sphere and up in the board frame,
  billboard canvas size in metres, colour activation, previews, creation details, and
  ``files``: path, sha256 and bytes of every other file);
- ``manifest.sha256``: the sha256 of ``manifest.json`` (``sha256sum -c`` format), so a changed
  byte anywhere in the bundle is caught;
- ``model/``: static — ``plenoctree.npz`` (svox ``N3Tree`` npz, copied byte for byte from the
  run); dynamic — ``stepper.ts`` (TorchScript stepper), ``rssm.pt`` (weights and config) and
  ``first_frame.png`` (the straight RGBA context frame, with its viewpoint in the manifest);
- ``proxy.glb``: the physics proxy (:mod:`dbb_capture.bundle.proxy`) in bundle space;
- ``previews/``: ``turntable.gif``, ``sheet.png`` (straight RGBA, several elevations), and for
  dynamic bundles ``rollout.png``.

Cameras given to :func:`render_bundle` are in the board frame (the capture's world frame) by
default, or in bundle space (``space="bundle"``).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import shutil
import tempfile
import time
import zipfile
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from ..geometry.cameras import Intrinsics
from ..geometry.rays import camera_rays, pixel_grid
from ..geometry.transforms import invert_rigid, look_at
from ..geometry.conventions import opencv_from_opengl
from ..crops.camera import crop_camera
from ..geometry.viewpoint import up_from_cameras, viewpoint
from ..core.errors import DbbError
from ..core.outputs import atomic_dir, read_json, write_json
from ..core.progress import progress
from .proxy import bundle_from_board, dynamic_proxy, read_glb, static_proxy, write_glb
from ..core.device import pick_device
from ..core.images import to_u8

FORMAT = "deep-billboard"
VERSION = 1
MANIFEST = "manifest.json"
CHECKSUM = "manifest.sha256"
PREVIEW_PX = 160            # preview cell size: cheap enough for the 15-minute demo on 2 cores
TURNTABLE_FRAMES = 24
SHEET_ELEVATIONS = (0.0, 30.0, 60.0)
SHEET_AZIMUTHS = 6
PREVIEW_FILL = 0.9          # the object sphere's share of a preview's side
CHECK_PSNR_DB = 35.0        # verify: a fresh render must match the stored preview this closely
SEED = 0                    # dynamic previews: sampled rollouts are seeded, so verify can repeat them


# --------------------------------------------------------------------------- manifest
# What readers of each kind look up (besides the fields every manifest has).
_KIND_KEYS = {"static": (("model", "file"),),
              "dynamic": (("model", "file"), ("inputs", "frame_size"), ("inputs", "crop_fill"),
                          ("inputs", "first_frame"), ("inputs", "first_view"), ("previews", "rollout"))}

@dataclass(frozen=True)
class FileEntry:
    path: str                 # relative, forward slashes
    sha256: str
    bytes: int


@dataclass
class Manifest:
    """``manifest.json`` of a bundle."""

    kind: str                                  # "static" or "dynamic"
    model: dict                                # type, file(s), format details
    inputs: dict                               # what the model expects at run time
    proxy_mesh: dict                           # ProxyMesh.to_json
    bundle_from_board: list[list[float]]       # 4x4
    object: dict                               # {center, radius} board frame, metres
    up: list[float]                            # board frame
    canvas: dict                               # {size_m, note}
    colour_activation: str | None
    previews: dict
    created: dict
    files: list[FileEntry] = field(default_factory=list)
    format: str = FORMAT
    version: int = VERSION

    def to_json(self) -> dict:
        d = asdict(self)
        return {"format": d.pop("format"), "version": d.pop("version"), **d}

    @classmethod
    def from_json(cls, d: object, where: str = MANIFEST) -> Manifest:
        """Validate the schema; a foreign or broken manifest gives one clear :class:`DbbError`."""
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            got = d.get("format") if isinstance(d, dict) else type(d).__name__
            raise DbbError(f"{where} is not a deep-billboard manifest (format {got!r})")
        if not isinstance(d.get("version"), int) or d["version"] > VERSION:
            raise DbbError(f"{where}: bundle version {d.get('version')!r} is not supported (this tool reads <= {VERSION})")
        need = [f for f in ("kind", "model", "inputs", "proxy_mesh", "bundle_from_board", "object", "up",
                            "canvas", "previews", "created", "files") if f not in d]
        if need:
            raise DbbError(f"{where}: missing {', '.join(need)}")
        if d["kind"] not in ("static", "dynamic"):
            raise DbbError(f"{where}: kind must be static or dynamic, not {d['kind']!r}")
        need = _KIND_KEYS[d["kind"]] + (("object", "center"), ("object", "radius"), ("proxy_mesh", "file"),
                                        ("previews", "sheet"), ("previews", "cell_px"))
        lacking = [f"{a}.{b}" for a, b in need if not isinstance(d[a], dict) or b not in d[a]]
        if lacking:
            raise DbbError(f"{where}: missing {', '.join(lacking)}")
        try:
            T = np.asarray(d["bundle_from_board"], float)
        except (TypeError, ValueError):
            T = np.zeros(0)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise DbbError(f"{where}: bundle_from_board must be a 4x4 matrix")
        try:
            files = [FileEntry(str(e["path"]), str(e["sha256"]), int(e["bytes"])) for e in d["files"]]
        except (TypeError, KeyError, ValueError):
            raise DbbError(f"{where}: files must be [{{path, sha256, bytes}}]") from None
        return cls(d["kind"], d["model"], d["inputs"], d["proxy_mesh"], T.tolist(), d["object"], d["up"],
                   d["canvas"], d.get("colour_activation"), d["previews"], d["created"], files)

    @property
    def T(self) -> np.ndarray:
        return np.asarray(self.bundle_from_board, float)

    @property
    def center(self) -> np.ndarray:
        return np.asarray(self.object["center"], float)

    @property
    def radius(self) -> float:
        return float(self.object["radius"])


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def file_entries(root: Path) -> list[FileEntry]:
    """Every file under ``root`` but the manifest and its checksum, sorted by path."""
    out = []
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if p.is_file() and rel not in (MANIFEST, CHECKSUM):
            out.append(FileEntry(rel, sha256_of(p), p.stat().st_size))
    return out


def write_manifest(root: Path, m: Manifest) -> None:
    """Fill ``m.files`` from ``root``, write ``manifest.json`` and its checksum."""
    m.files = file_entries(root)
    write_json(root / MANIFEST, m.to_json())
    (root / CHECKSUM).write_text(f"{sha256_of(root / MANIFEST)}  {MANIFEST}\n")


# --------------------------------------------------------------------------- open a bundle
@dataclass
class Bundle:
    """An opened bundle: its folder (a zip is extracted to a scratch folder) and manifest."""

    root: Path
    source: Path
    manifest: Manifest

    def file(self, rel: str) -> Path:
        p = (self.root / rel).resolve()
        if not p.is_relative_to(self.root.resolve()):
            raise DbbError(f"{self.source}: file {rel!r} points outside the bundle")
        if not p.is_file():
            raise DbbError(f"{self.source}: {rel} is missing")
        return p


def _safe_extract(zf: zipfile.ZipFile, dest: Path, where: Path) -> None:
    for name in zf.namelist():
        if name.startswith("/") or ".." in Path(name).parts:
            raise DbbError(f"{where}: zip member {name!r} points outside the bundle")
    try:
        zf.extractall(dest)
    except (zipfile.BadZipFile, OSError, EOFError) as e:
        raise DbbError(f"{where} is a corrupt bundle zip: {e}") from None


@contextlib.contextmanager
def open_bundle(path: Path) -> Iterator[Bundle]:
    """Open a bundle folder or ``.dbb`` zip (extracted into a scratch folder while open)."""
    path = Path(path)
    if path.is_dir():
        yield Bundle(path, path, _read_manifest(path, path))
        return
    if not path.is_file():
        raise DbbError(f"bundle not found: {path}")
    if not zipfile.is_zipfile(path):
        raise DbbError(f"{path} is neither a bundle folder nor a .dbb zip")
    with tempfile.TemporaryDirectory(prefix="dbb-bundle-") as tmp:
        try:
            with zipfile.ZipFile(path) as zf:
                _safe_extract(zf, Path(tmp), path)
        except zipfile.BadZipFile as e:
            raise DbbError(f"{path} is a corrupt bundle zip: {e}") from None
        yield Bundle(Path(tmp), path, _read_manifest(Path(tmp), path))


def _read_manifest(root: Path, source: Path) -> Manifest:
    if not (root / MANIFEST).is_file():
        raise DbbError(f"{source} is not a deep-billboard bundle (no {MANIFEST} at its root)")
    try:
        d = json.loads((root / MANIFEST).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DbbError(f"{source}: {MANIFEST} is not valid JSON ({e})") from None
    return Manifest.from_json(d, f"{source}/{MANIFEST}")


# --------------------------------------------------------------------------- cameras
@dataclass(frozen=True)
class View:
    """A camera to render: output name, OpenCV camera-to-world in the board frame, intrinsics."""

    name: str
    c2w: np.ndarray
    intr: Intrinsics


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


def read_cameras(path: Path, T: np.ndarray | None = None) -> list[View]:
    """Cameras of a transforms-style file (top-level or per-frame intrinsics, OpenGL c2w).

    ``T`` (bundle_from_board): when given, the poses are in bundle space and are taken to the
    board frame. Missing intrinsics, poses or names: one clear :class:`DbbError`.
    """
    from ..datasets.transforms import _intrinsics

    path = Path(path)
    meta = read_json(path, "cameras file")
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise DbbError(f"{path}: no frames")
    top = None
    if any(k in meta for k in ("fl_x", "fl_y", "camera_angle_x")):
        top = _intrinsics(meta, None, None, str(path))
    board_from_bundle = invert_rigid(T) if T is not None else np.eye(4)
    views, names = [], set()
    for i, f in enumerate(meta["frames"]):
        where = f"{path} frame {i}"
        if not isinstance(f, dict) or "file_path" not in f or "transform_matrix" not in f:
            raise DbbError(f"{where}: needs file_path and transform_matrix")
        if any(k in f for k in ("fl_x", "fl_y", "camera_angle_x")) or top is None:
            if top is None and not any(k in f for k in ("fl_x", "fl_y", "camera_angle_x")):
                raise DbbError(f"{where}: missing intrinsics (fl_x, fl_y, cx, cy, w, h at the top level or per frame)")
            intr = _intrinsics(f, top, None, where)
        else:
            intr = top
        m = np.asarray(f["transform_matrix"], float)
        if m.shape == (3, 4):
            m = np.vstack([m, [0, 0, 0, 1]])
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise DbbError(f"{where}: transform_matrix must be 4x4 finite numbers")
        name = Path(str(f["file_path"])).stem + ".png"
        if name in names:
            raise DbbError(f"{where}: two frames would both be written as {name}")
        names.add(name)
        views.append(View(name, board_from_bundle @ opencv_from_opengl(m), intr))
    return views


class StaticRenderer:
    """Straight RGBA renders of a static bundle's PlenOctree."""

    def __init__(self, tree_path: Path):
        from ..octree.render import TreeRenderer
        from ..octree.tree import PlenOctree

        self.renderer = TreeRenderer(PlenOctree.load(tree_path), pick_device())

    def render(self, views: list[View], tick=None) -> list[np.ndarray]:
        out = []
        for v in views:
            out.append(to_u8(self.renderer.render(v.c2w, v.intr)))
            if tick:
                tick()
        return out


def load_stepper(path: Path):
    try:
        return torch.jit.load(str(path), map_location="cpu").eval()
    except (RuntimeError, OSError, ValueError) as e:
        raise DbbError(f"cannot load the TorchScript model {path}: {e}") from None


def read_rgba(path: Path) -> np.ndarray:
    """Straight RGBA uint8 (H, W, 4) of an image file (alpha 255 where it has none)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DbbError(f"cannot read image {path}")
    if img.dtype == np.uint16:
        img = (img // 257).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, 2)
    if img.shape[2] == 3:
        img = np.concatenate([img, np.full(img.shape[:2] + (1,), 255, np.uint8)], 2)
    return cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)


def _rgba_tensor(rgba_u8: np.ndarray, size: int) -> torch.Tensor:
    """(1, 4, S, S) float straight RGBA from uint8 (H, W, 4), resized on premultiplied colour."""
    from ..core.images import resize_rgba

    x = resize_rgba(rgba_u8.astype(np.float32) / 255.0, size)
    return torch.from_numpy(np.ascontiguousarray(x)).permute(2, 0, 1)[None].float()


class DynamicRenderer:
    """Rollouts of a dynamic bundle's TorchScript stepper, warped into each camera's image."""

    def __init__(self, b: Bundle):
        m = b.manifest
        self.stepper = load_stepper(b.file(m.model["file"]))
        self.size = int(m.inputs["frame_size"])
        self.fill = float(m.inputs["crop_fill"])
        self.center, self.radius, self.up = m.center, m.radius, np.asarray(m.up, float)
        self.first = read_rgba(b.file(m.inputs["first_frame"]))
        self.first_view = np.asarray(m.inputs["first_view"], np.float32)

    def view_of(self, v: View) -> np.ndarray:
        """[azimuth_deg, elevation_deg, distance_m] of a camera from the object centre."""
        p = viewpoint(v.c2w[:3, 3], self.center, self.up)
        return np.array([p.azimuth_deg, p.elevation_deg, p.distance_m], np.float32)

    @torch.no_grad()
    def frames(self, views: np.ndarray, first: np.ndarray | None = None,
               first_view: np.ndarray | None = None, seed: int = SEED) -> np.ndarray:
        """Model frames (T, S, S, 4) uint8 for viewpoints (T, 3), one step each after the context."""
        from ..dynamic.stepper import rollout

        torch.manual_seed(seed)
        ctx = _rgba_tensor(self.first if first is None else first, self.size)
        fv = self.first_view if first_view is None else np.asarray(first_view, np.float32)
        vs = torch.from_numpy(np.concatenate([fv[None], np.asarray(views, np.float32)]))[None]
        x = rollout(self.stepper, ctx, vs)[0]
        return to_u8(x.permute(0, 2, 3, 1).numpy())

    def warp(self, crop: np.ndarray, v: View) -> np.ndarray:
        """The model's crop (S, S, 4) uint8 placed into camera ``v``'s image (H, W, 4) uint8.

        The crop is the camera's own view rotated to face the object centre (a homography),
        so each image pixel's ray is turned into the crop camera and looked up there.
        """
        cam = crop_camera(v.c2w, v.intr, self.center, self.radius, self.up, self.size, self.fill)
        d = camera_rays(v.intr, pixel_grid(v.intr.width, v.intr.height)).reshape(-1, 3)
        d = d @ (cam.c2w[:3, :3].T @ v.c2w[:3, :3]).T
        z = d[:, 2]
        ok = z > 1e-6
        zs = np.where(ok, z, 1.0)
        mx = np.where(ok, cam.intr.fx * d[:, 0] / zs + cam.intr.cx, -1e4).astype(np.float32)
        my = np.where(ok, cam.intr.fy * d[:, 1] / zs + cam.intr.cy, -1e4).astype(np.float32)
        f = crop.astype(np.float32) / 255.0
        pm = np.concatenate([f[..., :3] * f[..., 3:], f[..., 3:]], -1)
        H, W = v.intr.height, v.intr.width
        out = cv2.remap(pm, mx.reshape(H, W), my.reshape(H, W), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        a = out[..., 3:]
        rgb = np.where(a > 1e-6, out[..., :3] / np.maximum(a, 1e-6), 0.0)
        return to_u8(np.concatenate([rgb.clip(0, 1), a], -1))


def render_bundle(bundle: Path, cameras: Path, out: Path, first_frame: Path | None = None,
                  space: str = "board", overwrite: bool = False) -> list[Path]:
    """Render one straight RGBA PNG per camera of ``cameras`` into ``out`` (written aside).

    A dynamic bundle steps once per camera, in the file's order, from ``first_frame`` (seen
    from the first camera) or from its stored first frame (seen from its stored viewpoint).
    """
    if space not in ("board", "bundle"):
        raise DbbError("--space must be board or bundle")
    with open_bundle(bundle) as b:
        m = b.manifest
        views = read_cameras(cameras, m.T if space == "bundle" else None)
        if first_frame is not None and m.kind == "static":
            raise DbbError("--first-frame applies to dynamic bundles only; this bundle is static")
        with atomic_dir(Path(out), overwrite or _empty_dir(out)) as tmp, progress() as prog:
            task = prog.add_task("render", total=len(views), info=m.kind)
            if m.kind == "static":
                imgs = StaticRenderer(b.file(m.model["file"])).render(views, lambda: prog.advance(task))
            else:
                r = DynamicRenderer(b)
                vv = np.stack([r.view_of(v) for v in views])
                first = read_rgba(first_frame) if first_frame is not None else None
                crops = r.frames(vv, first, vv[0] if first is not None else None)
                imgs = []
                for c, v in zip(crops, views, strict=True):
                    imgs.append(r.warp(c, v))
                    prog.advance(task)
            for img, v in zip(imgs, views, strict=True):
                if not cv2.imwrite(str(tmp / v.name), cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)):
                    raise DbbError(f"cannot write {tmp / v.name}")
    return [Path(out) / v.name for v in views]


def _empty_dir(p: Path) -> bool:
    """An empty folder someone made for the output is not a result to protect."""
    p = Path(p)
    return p.is_dir() and not any(p.iterdir())


# --------------------------------------------------------------------------- previews
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


def write_static_previews(folder: Path, tree_path: Path, T: np.ndarray, radius: float, az0: float,
                          prog) -> dict:
    plan = preview_plan(3.0 * radius, az0)
    r = StaticRenderer(tree_path)
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


# --------------------------------------------------------------------------- building
def _dataset_cameras(dataset: Path) -> tuple[list[float], np.ndarray]:
    """Up (3,) and camera poses (N, 4, 4, OpenCV, board frame) of a dataset, without its images.

    Up is the board normal on the cameras' side: the dataset's recorded "up", else from its poses.
    """
    from ..datasets.transforms import find_dataset_file

    src = find_dataset_file(dataset)
    meta = read_json(src, "dataset")
    try:
        c2w = np.stack([opencv_from_opengl(np.asarray(f["transform_matrix"], float)[:4])
                        for f in meta["frames"]])
    except (KeyError, TypeError, ValueError):
        raise DbbError(f"{src}: cannot read the camera poses to tell which way is up") from None
    if isinstance(meta.get("up"), list) and len(meta["up"]) == 3:
        return [float(v) for v in meta["up"]], c2w
    return [float(v) for v in up_from_cameras(c2w)], c2w


def mean_azimuth(c2w: np.ndarray, center: np.ndarray, up: np.ndarray) -> float:
    """Circular mean of the cameras' azimuths about ``up`` (degrees): the side best seen."""
    a = np.radians([viewpoint(T[:3, 3], center, up).azimuth_deg for T in c2w])
    return float(np.degrees(np.arctan2(np.sin(a).mean(), np.cos(a).mean()))) if len(a) else 0.0


def _run_dataset(meta: dict, run: Path, dataset: Path | None) -> Path:
    ds = Path(dataset) if dataset is not None else Path(meta.get("dataset", ""))
    if not ds.exists():
        raise DbbError(f"the dataset of {run} is gone ({ds}): pass --dataset to point at it")
    return ds


def _created(run: Path, meta: dict) -> dict:
    from importlib.metadata import PackageNotFoundError, version

    try:
        v = version("dbb-capture")
    except PackageNotFoundError:
        v = "unknown"
    return {"tool": "dbb-export bundle", "tool_version": v,
            "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "run": str(Path(run).resolve()), "run_format": meta.get("format"),
            "training_steps": meta.get("training", {}).get("steps"), "training_seconds": meta.get("training", {}).get("seconds")}


_RUN_KEYS = {"dynamic": (("stepper", "file"), ("stepper", "frame_size"), ("model", "file"))}


def _run_kind(run: Path) -> tuple[str, dict]:
    """"static" or "dynamic" and the run.json of a finished dbb-train run (one clear error if not)."""
    from ..static.run import RUN_FORMAT as TREE_FORMAT
    from ..static.run import load_run
    from ..dynamic.record import RUN_FORMAT as RSSM_FORMAT
    from ..dynamic.record import RunRecord

    if not Path(run).is_dir():
        raise DbbError(f"run folder not found: {run}")
    meta = read_json(Path(run) / "run.json", "run description (is this a finished training run?)")
    kinds = {TREE_FORMAT: "static", RSSM_FORMAT: "dynamic"}
    if not isinstance(meta, dict) or meta.get("format") not in kinds:
        raise DbbError(f"{run} is not a finished dbb-train run (run.json format "
                       f"{meta.get('format') if isinstance(meta, dict) else None!r})")
    kind = kinds[meta["format"]]
    if kind == "static":
        load_run(run)      # the typed record: refuses other versions and incomplete records
    else:
        RunRecord.read(run)
    for a, b in _RUN_KEYS.get(kind, ()):
        if not isinstance(meta.get(a), dict) or b not in meta[a]:
            raise DbbError(f"{run}/run.json lacks {a}.{b}: is it a finished training run?")
    return kind, meta


def _need(run: Path, *names: str) -> None:
    for n in names:
        if not (Path(run) / n).is_file():
            raise DbbError(f"{run} is not a finished training run: {n} is missing")


def build_static(run: Path, meta: dict, tmp: Path, dataset: Path | None, prog) -> Manifest:
    from ..static.run import load_run

    r = load_run(run)
    rec = r.record
    _need(run, rec.tree.file, r.density_grid_path.name)
    center, radius = np.asarray(rec.volume.center, float), float(rec.volume.radius)
    up, cams = _dataset_cameras(_run_dataset(meta, run, dataset))
    T = bundle_from_board(center, up)
    (tmp / "model").mkdir()
    shutil.copyfile(r.tree_path, tmp / "model" / "plenoctree.npz")
    task = prog.add_task("proxy mesh", total=1, info="marching cubes")
    proxy = static_proxy(r.density_grid_path, T)
    write_glb(tmp / "proxy.glb", proxy)
    prog.advance(task)
    previews = write_static_previews(tmp / "previews", tmp / "model" / "plenoctree.npz", T, radius,
                                     round(mean_azimuth(cams, center, np.asarray(up)), 1), prog)
    return Manifest(
        kind="static",
        model={"type": "plenoctree", "file": "model/plenoctree.npz", "format": "svox N3Tree npz",
               "data_format": rec.tree.data_format, "sh_degree": rec.tree.sh_degree,
               "depth_limit": rec.tree.depth_limit, "density_units": "per metre (board frame)",
               "frame": "board (tree: offset + board_point * invradius3 in [0, 1]^3)"},
        inputs={"camera": "a ray per pixel in the board frame (bundle-space rays: apply the inverse of "
                          "bundle_from_board first)", "output": "straight RGBA"},
        proxy_mesh=proxy.to_json("proxy.glb"), bundle_from_board=T.tolist(),
        object={"center": center.tolist(), "radius": radius}, up=list(up),
        canvas={"size_m": 2 * radius, "note": "a camera-facing square of this side, centred on the object, "
                                                 "holds the object sphere"},
        colour_activation=rec.tree.colour_activation, previews=previews, created=_created(run, meta))


def build_dynamic(run: Path, meta: dict, tmp: Path, dataset: Path | None, prog) -> Manifest:
    from ..datasets.transforms import find_dataset_file, load_dataset
    from ..datasets.images import load_rgba

    _need(run, meta["stepper"]["file"], meta["model"]["file"])
    ds_file = find_dataset_file(_run_dataset(meta, run, dataset))
    o = meta.get("object") or {}
    if "center" not in o or "radius" not in o:
        raise DbbError(f"{run}/run.json has no object sphere")
    center, radius = np.asarray(o["center"], float), float(o["radius"])
    up = meta.get("up") or _dataset_cameras(ds_file)[0]
    T = bundle_from_board(center, up)
    (tmp / "model").mkdir()
    shutil.copyfile(Path(run) / meta["stepper"]["file"], tmp / "model" / "stepper.ts")
    shutil.copyfile(Path(run) / meta["model"]["file"], tmp / "model" / "rssm.pt")
    size = int(meta["stepper"]["frame_size"])
    fill = float((meta.get("crop") or {}).get("fill") or 0.9)
    first = load_dataset(ds_file).frames[0]
    write_png(tmp / "model" / "first_frame.png", to_u8(load_rgba(first)))
    vp = viewpoint(first.c2w[:3, 3], center, np.asarray(up, float))
    task = prog.add_task("proxy mesh", total=1, info="visual hull")
    proxy = dynamic_proxy(ds_file, center, radius, T)
    write_glb(tmp / "proxy.glb", proxy)
    prog.advance(task)
    m = Manifest(
        kind="dynamic",
        model={"type": "rssm", "file": "model/stepper.ts", "format": "TorchScript",
               "weights": "model/rssm.pt", "api": meta["stepper"].get("api"),
               "temperature": meta["stepper"].get("temperature"), "fps": meta["stepper"].get("fps")},
        inputs={"first_frame": "model/first_frame.png", "first_view": [vp.azimuth_deg, vp.elevation_deg,
                                                                       vp.distance_m],
                "view": "[azimuth_deg, elevation_deg, distance_m] of the camera from the object centre: "
                        "elevation from the board plane toward up, azimuth right-handed about up from the "
                        "board's x axis (bundle space: about +Y from +X)",
                "frame_size": size, "crop_fill": fill, "output": "straight RGBA (B, 4, S, S) in 0..1 per step"},
        proxy_mesh=proxy.to_json("proxy.glb"), bundle_from_board=T.tolist(),
        object={"center": center.tolist(), "radius": radius}, up=[float(v) for v in up],
        canvas={"size_m": 2 * radius / fill, "note": "side of the camera-facing square the model's frame "
                                                      "covers at the object centre (far camera)"},
        colour_activation="sigmoid (decoder output, straight RGBA)", previews={}, created=_created(run, meta))
    b = Bundle(tmp, tmp, m)
    m.previews = write_dynamic_previews(tmp / "previews", DynamicRenderer(b), prog)
    return m


def make_bundle(run: Path, out: Path, zip_it: bool = False, dataset: Path | None = None,
                overwrite: bool = False) -> Manifest:
    """Package the finished training run ``run`` as a bundle at ``out`` (a ``.dbb`` zip if ``zip_it``).

    Nothing appears at ``out`` unless the whole bundle was written.
    """
    run, out = Path(run), Path(out)
    kind, meta = _run_kind(run)
    if out.exists() and not (overwrite or _empty_dir(out)):
        raise DbbError(f"{out} already exists (pass --overwrite to replace it)")
    build = build_static if kind == "static" else build_dynamic
    with progress() as prog:
        if not zip_it:
            with atomic_dir(out, overwrite=True) as tmp:
                m = build(run, meta, tmp, dataset, prog)
                write_manifest(tmp, m)
            return m
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix=f".{out.name}.partial-", dir=out.parent) as t:
            tmp = Path(t) / "bundle"
            tmp.mkdir()
            m = build(run, meta, tmp, dataset, prog)
            write_manifest(tmp, m)
            z = Path(t) / "bundle.dbb"
            with zipfile.ZipFile(z, "w", zipfile.ZIP_DEFLATED) as zf:
                for p in [tmp / MANIFEST, tmp / CHECKSUM] + [tmp / e.path for e in m.files]:
                    zf.write(p, p.relative_to(tmp).as_posix())
            if out.is_dir():
                shutil.rmtree(out)
            os.replace(z, out)
        return m


# --------------------------------------------------------------------------- verify
def verify_bundle(path: Path) -> list[str]:
    """Check a bundle: manifest checksum and schema, every file's size and sha256, no stray
    files, the model loads, the proxy mesh reads with its collision nodes, and a fresh render
    matches the stored preview. Returns what passed; raises :class:`DbbError` at the first failure."""
    from ..core.metrics import psnr_from_mse

    done = []
    with open_bundle(path) as b:
        m = b.manifest
        ck = (b.root / CHECKSUM)
        if not ck.is_file():
            raise DbbError(f"{path}: {CHECKSUM} is missing")
        want = ck.read_text().split()[0] if ck.read_text().split() else ""
        if sha256_of(b.root / MANIFEST) != want:
            raise DbbError(f"{path}: {MANIFEST} does not match {CHECKSUM} (the manifest was changed or damaged)")
        done.append(f"manifest: format {m.format} v{m.version}, kind {m.kind}, checksum ok")
        listed = {e.path for e in m.files}
        for e in m.files:
            p = b.file(e.path)
            if p.stat().st_size != e.bytes:
                raise DbbError(f"{path}: {e.path} is {p.stat().st_size} bytes, manifest says {e.bytes}")
            if sha256_of(p) != e.sha256:
                raise DbbError(f"{path}: {e.path} fails its sha256 check (changed or damaged)")
        present = {p.relative_to(b.root).as_posix() for p in b.root.rglob("*") if p.is_file()}
        stray = sorted(present - listed - {MANIFEST, CHECKSUM})
        if stray:
            raise DbbError(f"{path}: files not in the manifest: {', '.join(stray[:3])}")
        done.append(f"files: {len(m.files)} match their sha256 and size")
        meshes = read_glb(b.file(m.proxy_mesh["file"]))
        names = sorted(meshes)
        if not any(n.endswith("-colonly") for n in names) or not any(n.endswith("-convcolonly") for n in names):
            raise DbbError(f"{path}: proxy mesh lacks its -colonly / -convcolonly nodes (has {names})")
        done.append(f"proxy mesh: nodes {', '.join(names)}")
        pv = m.previews
        sheet = read_rgba(b.file(pv["sheet"]["file"]))
        cols, S = int(pv["sheet"]["columns"]), int(pv["cell_px"])
        if m.kind == "static":
            r = StaticRenderer(b.file(m.model["file"]))
            a, e, d = pv["sheet"]["views"][0]
            fresh = r.render([orbit_view("check", m.T, m.radius, a, e, d)])[0]
            stored = cell(sheet, 0, cols, S)
            what = "sheet view 0"
        else:
            r = DynamicRenderer(b)
            rows = pv["rollout"]["rows"]
            fresh = tile(list(r.frames(np.array(rows["still"]), seed=int(pv["rollout"]["seed"]))), 16)
            stored = read_rgba(b.file(pv["rollout"]["file"]))[:S]
            what = "rollout row 1"
        done.append(f"model: {m.model['file']} loads")
        if fresh.shape != stored.shape:
            raise DbbError(f"{path}: a fresh render of {what} is {fresh.shape}, the stored preview {stored.shape}")
        p = psnr_from_mse(float((((fresh.astype(np.float32) - stored.astype(np.float32)) / 255.0) ** 2).mean()))
        if p < CHECK_PSNR_DB:
            raise DbbError(f"{path}: a fresh render of {what} differs from the stored preview ({p:.1f} dB < "
                           f"{CHECK_PSNR_DB:.0f} dB)")
        done.append(f"render: {what} matches the stored preview ({p:.1f} dB)")
    return done
