"""Proxy meshes for physics (thesis 4.4): a closed collision mesh and its convex hull, in bundle space.

Bundle space is object-centred, metres, glTF axes: +Y is "up" (the board normal on the
cameras' side), +X the board's x axis made orthogonal to up, +Z = X x Y. ``bundle_from_board``
(4, 4) maps board-frame points into it.

- Static objects: marching cubes (scikit-image) on the run's density grid, thresholded at half
  the object's typical interior density; only the largest connected part is kept, cavities are
  filled, the surface is closed (the grid is padded) and decimated with open3d to at most
  ``max_triangles``; if decimation opens the surface, a coarser grid is meshed instead.
- Dynamic objects: the visual hull carved from the posed RGBA crop mattes of the dataset
  (a voxel stays when it projects inside the matte in most views that see it), or a sphere of
  the mattes' mean area where carving cannot work (too few views, too narrow a spread of
  views, nothing left); :attr:`ProxyMesh.method` and ``note`` say which and why.

Both go into one ``.glb``: nodes ``<name>-colonly`` (the mesh) and ``<name>-convcolonly`` (its
convex hull), the suffixes Godot reads as collision shapes.
"""

from __future__ import annotations

import io
import math
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import DbbError

MAX_TRIANGLES = 5000


@dataclass(frozen=True)
class SupportPlane:
    """The plane an object stands on (the board plane z = 0), board frame: ``point`` (3,) metres
    and unit ``normal`` (3,), the board's up (the side the cameras were)."""

    point: np.ndarray
    normal: np.ndarray

    @classmethod
    def board(cls, up: np.ndarray) -> SupportPlane:
        n = np.asarray(up, float)
        return cls(np.zeros(3), n / np.linalg.norm(n))

    def height(self, p_board: np.ndarray) -> np.ndarray:
        """Signed height (...,) in metres of board points (..., 3) above the plane."""
        return (np.asarray(p_board, float) - self.point) @ self.normal

    def in_bundle(self, T: np.ndarray) -> dict:
        """The plane in bundle space (``T`` = bundle_from_board): the point of the plane nearest
        the object centre (the bundle origin) and the normal, for the manifest."""
        foot = transform_points(T, self.point)
        n = T[:3, :3] @ self.normal
        return {"point": [round(float(v), 6) + 0.0 for v in n * float(foot @ n)],     # + 0.0: no -0.0
                "normal": [round(float(v), 6) + 0.0 for v in n],
                "note": "the board plane (the table the object stands on): bundle space, metres; "
                        "the proxy mesh is cut by it"}


@dataclass
class ProxyMesh:
    """A closed triangle mesh and its convex hull in bundle space (metres, +Y up)."""

    vertices: np.ndarray         # (V, 3) float64
    faces: np.ndarray            # (F, 3) int64, counter-clockwise seen from outside
    hull_vertices: np.ndarray    # (Vh, 3) float64
    hull_faces: np.ndarray       # (Fh, 3) int64
    method: str                  # "marching cubes", "visual hull" or "sphere"
    note: str                    # how it was made (threshold, views) or why a sphere
    base_m: float | None = None  # lowest vertex above the support plane (0: rests on it; None: no plane)

    @property
    def watertight(self) -> bool:
        return _trimesh(self.vertices, self.faces).is_watertight

    def to_json(self, file: str) -> dict:
        return {"file": file, "method": self.method, "note": self.note, "triangles": len(self.faces),
                "hull_triangles": len(self.hull_faces), "watertight": bool(self.watertight),
                "volume_m3": float(abs(_trimesh(self.vertices, self.faces).volume)),
                "base_above_support_m": None if self.base_m is None else round(self.base_m, 6),
                "space": "bundle (object-centred, metres, +Y up)"}


# --------------------------------------------------------------------------- bundle space
def bundle_from_board(center: np.ndarray, up: np.ndarray) -> np.ndarray:
    """4x4 taking board-frame points to bundle space (origin ``center`` (3,), +Y along ``up`` (3,)).

    X is the board's x axis made orthogonal to up (the y axis if x is parallel to up), Z = X x Y.
    """
    y = np.asarray(up, float) / np.linalg.norm(up)
    ref = np.array([1.0, 0.0, 0.0]) if abs(y[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - (ref @ y) * y
    x /= np.linalg.norm(x)
    z = np.cross(x, y)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z])            # rows: bundle axes in board coordinates
    T[:3, 3] = -T[:3, :3] @ np.asarray(center, float)
    return T


def transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply a 4x4 ``T`` to points (..., 3)."""
    return np.asarray(p, float) @ T[:3, :3].T + T[:3, 3]


# --------------------------------------------------------------------------- voxels -> mesh
def _trimesh(v: np.ndarray, f: np.ndarray):
    import trimesh

    return trimesh.Trimesh(np.asarray(v, float), np.asarray(f, np.int64), process=False)


def clean_occupancy(mask: np.ndarray) -> np.ndarray:
    """Largest 6-connected part of a boolean grid (G, G, G), its cavities filled."""
    from scipy import ndimage

    lab, n = ndimage.label(mask)
    if n == 0:
        return mask.copy()
    sizes = np.bincount(lab.ravel())[1:]
    keep = lab == (1 + int(np.argmax(sizes)))
    return ndimage.binary_fill_holes(keep)


def _decimate(v: np.ndarray, f: np.ndarray, max_triangles: int) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f.astype(np.int32)))
    m = m.simplify_quadric_decimation(target_number_of_triangles=int(max_triangles))
    m.remove_degenerate_triangles()
    m.remove_unreferenced_vertices()
    return np.asarray(m.vertices, float), np.asarray(m.triangles, np.int64)


def _heights(plane: SupportPlane, lo: np.ndarray, cell: np.ndarray, shape: tuple, first: float) -> np.ndarray:
    """Height above ``plane`` (metres) of the samples of a grid whose sample i along axis k sits
    at ``lo[k] + cell[k] * (i + first)``: (shape)."""
    ax = [(lo[k] + cell[k] * (np.arange(shape[k]) + first) - plane.point[k]) * plane.normal[k] for k in range(3)]
    return ax[0][:, None, None] + ax[1][None, :, None] + ax[2][None, None, :]


def occupancy_mesh(mask: np.ndarray, bbox_min: np.ndarray, bbox_max: np.ndarray,
                   max_triangles: int = MAX_TRIANGLES,
                   support: SupportPlane | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Closed surface (V, 3) board-frame metres, faces (F, 3) of a cleaned occupancy grid.

    ``mask`` (G, G, G) bool indexed [x, y, z] at cell centres of the box [bbox_min, bbox_max].
    The grid is padded so the surface closes at the box; after decimation to ``max_triangles``
    the mesh must still be watertight, else the grid is halved and meshed again. With a
    ``support`` plane, what lies under it is cut away and the cut closed by a flat base on it.
    """
    from scipy import ndimage
    from skimage.measure import marching_cubes

    lo, hi = np.asarray(bbox_min, float), np.asarray(bbox_max, float)
    cell0 = (hi - lo) / np.asarray(np.shape(mask), float)
    mask = np.asarray(mask, bool)
    if support is not None:
        # Keep one layer of cells under the plane: the level set below places the base on it.
        mask = mask & (_heights(support, lo, cell0, mask.shape, 0.5) > -cell0.max())
    mask = clean_occupancy(mask)
    if not mask.any():
        raise DbbError("nothing occupied to mesh" + ("" if support is None else " above the board plane"))
    # Mesh only the occupied box (plus a margin): the object rarely fills its cube.
    idx = np.argwhere(mask)
    a = np.maximum(idx.min(0) - 2, 0)
    b = np.minimum(idx.max(0) + 3, mask.shape)
    mask = mask[a[0]:b[0], a[1]:b[1], a[2]:b[2]]
    lo, hi = lo + a * cell0, lo + b * cell0
    grid = mask.astype(np.float32)
    for _ in range(4):
        G = np.asarray(grid.shape, float)
        cell = (hi - lo) / G
        # A light blur turns the voxel staircase into a smooth level set at the same boundary.
        vol = np.pad(ndimage.gaussian_filter(grid, 0.6), 2)
        if support is not None:
            # Intersect with the half-space above the plane: a field linear in the height, at the
            # level on the plane and gentle (under the blurred grid's interior there), so marching
            # cubes' linear interpolation puts the base on the plane.
            ramp = 0.5 + _heights(support, lo, cell, vol.shape, 0.5 - 2) / (2 * cell.min())
            vol = np.minimum(vol, ramp.astype(vol.dtype))
        v, f, _, _ = marching_cubes(vol, 0.5, spacing=tuple(cell))
        v = v + lo + cell * (0.5 - 2)
        f = f[:, ::-1]                     # skimage winds inward for a solid above the level
        if len(f) > max_triangles:
            v, f = _decimate(v, f, max_triangles)
        if support is not None:            # what decimation moved under the plane goes back onto it
            h = support.height(v)
            v = v - np.minimum(h, 0.0)[:, None] * support.normal
        tm = _trimesh(v, f)
        if tm.is_watertight and len(f) <= max_triangles:
            if tm.volume < 0:
                f = f[:, ::-1]
            return v, f
        grid = ndimage.zoom(grid, 0.5, order=1)
    raise DbbError("could not make a watertight proxy mesh within the triangle budget")


def convex_hull(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Convex hull of points (N, 3): vertices (Vh, 3), outward faces (Fh, 3)."""
    h = _trimesh(v, np.zeros((0, 3), np.int64)).convex_hull
    return np.asarray(h.vertices, float), np.asarray(h.faces, np.int64)


def _finish(v_board: np.ndarray, f: np.ndarray, T: np.ndarray, method: str, note: str,
            support: SupportPlane | None = None) -> ProxyMesh:
    base = None
    if support is not None:
        base = max(float(support.height(v_board).min()), 0.0)
        note += ("; cut at the board plane, its base resting on it" if base < 1e-4 else
                 f"; {base * 1000:.0f} mm above the board plane (nothing to cut)")
    v = transform_points(T, v_board)
    hv, hf = convex_hull(v)
    return ProxyMesh(v, f, hv, hf, method, note, base)


# --------------------------------------------------------------------------- static: density grid
def density_level(sigma: np.ndarray) -> float:
    """Surface threshold of a density grid: half the object's typical interior density.

    Interior = cells above Otsu's threshold of log density (over cells with any density);
    its median is robust to the few very dense cells a field grows at edges.
    """
    from skimage.filters import threshold_otsu

    pos = sigma[sigma > 1e-3 * float(sigma.max())] if sigma.max() > 0 else sigma[:0]
    if pos.size < 8:
        raise DbbError("the density grid is empty: the run learned no object")
    t = math.exp(threshold_otsu(np.log(pos.astype(np.float64))))
    return 0.5 * float(np.median(pos[pos > t]))


def static_proxy(density_grid: Path, T: np.ndarray, max_triangles: int = MAX_TRIANGLES,
                 support: SupportPlane | None = None) -> ProxyMesh:
    """Proxy of a static run from its ``density_grid.npz`` (sigma[x, y, z], bbox_min, bbox_max),
    cut by the ``support`` plane if given."""
    try:
        g = np.load(Path(density_grid))
        sigma = g["sigma"].astype(np.float32)
        lo, hi = g["bbox_min"].astype(float), g["bbox_max"].astype(float)
    except (OSError, KeyError, ValueError) as e:
        raise DbbError(f"cannot read the density grid {density_grid}: {e}") from None
    level = density_level(sigma)
    v, f = occupancy_mesh(sigma > level, lo, hi, max_triangles, support)
    return _finish(v, f, T, "marching cubes",
                   f"density grid {sigma.shape[0]}^3 at {level:.4g} per metre (half the interior median); "
                   "largest part, cavities filled, decimated with open3d", support)


# --------------------------------------------------------------------------- dynamic: visual hull
def sphere_proxy(radius: float, T: np.ndarray, center: np.ndarray, note: str,
                 support: SupportPlane | None = None) -> ProxyMesh:
    """An icosphere of ``radius`` metres at the object centre (in bundle space: the origin); with
    a ``support`` plane under the centre, its part below the plane is pressed flat onto it (the
    sphere is convex: the flattened cap is the cut's base, closed as it was)."""
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=3, radius=float(radius))
    v_board = transform_points(np.linalg.inv(T), np.asarray(s.vertices))
    if support is not None and support.height(np.asarray(center, float)) > 0:
        v_board = v_board - np.minimum(support.height(v_board), 0.0)[:, None] * support.normal
    return _finish(v_board, np.asarray(s.faces, np.int64), T, "sphere", note, support)


def _view_spread_deg(dirs: np.ndarray) -> float:
    """Largest angle (degrees) between unit view directions (N, 3)."""
    c = np.clip(dirs @ dirs.T, -1, 1)
    return float(np.degrees(np.arccos(c.min())))


def _project(P: np.ndarray, c2w: np.ndarray, intr) -> np.ndarray:
    """Pixels (N, 2) of board points (N, 3): plain pinhole maths for undistorted crop cameras
    (cv2.projectPoints is ~10x slower on a voxel grid), the lens model otherwise."""
    from ..geometry.cameras import project_points
    from ..geometry.transforms import invert_rigid

    if intr.distorted:
        return project_points(P, c2w, intr)
    w2c = invert_rigid(c2w)
    q = P @ w2c[:3, :3].T + w2c[:3, 3]
    z = np.where(q[:, 2] > 1e-9, q[:, 2], np.nan)      # behind the camera: NaN, never inside
    return np.stack([intr.fx * q[:, 0] / z + intr.cx, intr.fy * q[:, 1] / z + intr.cy], -1)


def dynamic_proxy(crops_json: Path, center: np.ndarray, radius: float, T: np.ndarray, res: int = 64,
                  agree: float = 0.9, max_views: int = 80, min_spread_deg: float = 30.0,
                  max_triangles: int = MAX_TRIANGLES, support: SupportPlane | None = None) -> ProxyMesh:
    """Visual hull of a crops.json dataset's mattes over the object sphere, else a sphere; either
    cut by the ``support`` plane if given.

    A voxel of the ``res``^3 grid over the sphere's cube stays when its centre falls inside the
    matte (alpha > 0.5) in at least ``agree`` of the views that see it; a moving object thus
    keeps what it occupies most of the time. (Views from above cannot carve under the object:
    the hull reaches down to the sphere, and the support plane cuts it at the table.)
    """
    from ..datasets.images import load_rgba
    from ..datasets.transforms import load_dataset

    center = np.asarray(center, float)
    try:
        ds = load_dataset(Path(crops_json))
    except DbbError as e:
        return sphere_proxy(radius, T, center, f"sphere of the object radius: dataset unreadable ({e})", support)
    frames = ds.frames[:: max(1, math.ceil(len(ds.frames) / max_views))]
    ax = center[None] + ((np.arange(res) + 0.5) / res * 2 - 1)[:, None] * radius
    P = np.stack(np.meshgrid(ax[:, 0], ax[:, 1], ax[:, 2], indexing="ij"), -1).reshape(-1, 3)
    inside = np.linalg.norm(P - center, axis=1) <= radius
    Pin = P[inside]                     # only voxels inside the object sphere can be kept
    votes = np.zeros(len(Pin), np.int32)
    seen = np.zeros(len(Pin), np.int32)
    areas, dirs = [], []
    for fr in frames:
        alpha = load_rgba(fr)[..., 3]
        h, w = alpha.shape
        areas.append(float((alpha > 0.5).sum()) / (fr.intr.fx * fr.intr.fy))   # steradians-ish
        eye = fr.c2w[:3, 3]
        dirs.append((eye - center) / np.linalg.norm(eye - center))
        uv = np.round(np.nan_to_num(_project(Pin, fr.c2w, fr.intr), nan=-1.0)).astype(np.int64)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        seen += ok
        votes[ok] += alpha[uv[ok, 1], uv[ok, 0]] > 0.5
    # Sphere of the mattes' mean solid angle, seen from the mean distance.
    dist = float(np.mean([np.linalg.norm(fr.c2w[:3, 3] - center) for fr in frames]))
    r_eq = min(radius, dist * math.sin(math.sqrt(max(np.mean(areas), 0.0) / math.pi))) if areas else radius
    spread = _view_spread_deg(np.array(dirs)) if dirs else 0.0
    why = None
    if len(frames) < 3:
        why = f"only {len(frames)} views"
    elif spread < min_spread_deg:
        why = f"views span only {spread:.0f} degrees (need {min_spread_deg:.0f})"
    keep = np.zeros(len(P), bool)
    keep[inside] = (seen >= 3) & (votes >= agree * np.maximum(seen, 1))
    if why is None and keep.sum() < 8:
        why = "carving left nothing"
    if why is None:
        try:
            v, f = occupancy_mesh(keep.reshape(res, res, res), center - radius, center + radius, max_triangles,
                                  support)
        except DbbError as e:
            why = str(e)
        else:
            return _finish(v, f, T, "visual hull",
                           f"carved from {len(frames)} crop mattes over {spread:.0f} degrees of views, "
                           f"{res}^3 voxels, kept where inside in >= {agree:.0%} of views", support)
    return sphere_proxy(max(r_eq, 1e-3), T, center, f"sphere of the mattes' mean area: visual hull failed ({why})",
                        support)


# --------------------------------------------------------------------------- glTF
def write_glb(path: Path, proxy: ProxyMesh, name: str = "proxy") -> None:
    """One ``.glb`` with nodes ``<name>-colonly`` (mesh) and ``<name>-convcolonly`` (convex hull)."""
    import trimesh

    from ..core.outputs import write_bytes_atomic

    scene = trimesh.Scene()
    scene.add_geometry(_trimesh(proxy.vertices, proxy.faces), node_name=f"{name}-colonly",
                       geom_name=f"{name}-colonly")
    scene.add_geometry(_trimesh(proxy.hull_vertices, proxy.hull_faces), node_name=f"{name}-convcolonly",
                       geom_name=f"{name}-convcolonly")
    write_bytes_atomic(Path(path), with_buffer_targets(scene.export(file_type="glb")))


def with_buffer_targets(glb: bytes) -> bytes:
    """A binary glTF with each buffer view's ``target`` set: ELEMENT_ARRAY_BUFFER for the ones
    meshes read indices from, ARRAY_BUFFER for vertex attributes (what trimesh leaves out, and
    what the Khronos validator hints at: engines use it to choose GPU buffers)."""
    import json

    magic, version, _ = struct.unpack_from("<4sII", glb, 0)
    n, kind = struct.unpack_from("<I4s", glb, 12)
    if magic != b"glTF" or kind != b"JSON":
        raise ValueError("not a binary glTF with a JSON chunk first")
    doc = json.loads(glb[20:20 + n])
    rest = glb[20 + n:]
    views = doc.get("bufferViews", [])
    for mesh in doc.get("meshes", []):
        for prim in mesh.get("primitives", []):
            if "indices" in prim:
                views[doc["accessors"][prim["indices"]]["bufferView"]]["target"] = 34963
            for acc in prim.get("attributes", {}).values():
                views[doc["accessors"][acc]["bufferView"]]["target"] = 34962
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)                    # chunks are 4-byte aligned, JSON padded with spaces
    out = struct.pack("<I4s", len(text), b"JSON") + text + rest
    return struct.pack("<4sII", b"glTF", version, 12 + len(out)) + out


_GLB_MAGIC, _JSON_CHUNK, _BIN_CHUNK = b"glTF", b"JSON", b"BIN\x00"


def check_glb_layout(data: bytes, path: Path) -> None:
    """Refuse a ``.glb`` whose 12-byte header or chunk lengths disagree with its bytes (the
    glTF 2.0 binary layout: magic, version 2, total length, then a JSON chunk and an optional
    BIN chunk): trimesh reads past such damage, a viewer may not."""
    if len(data) < 20 or data[:4] != _GLB_MAGIC:
        raise DbbError(f"the proxy mesh {path} is not a binary glTF (.glb) file")
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2 or length != len(data):
        raise DbbError(f"the proxy mesh {path} is damaged: its header says glTF {version}, {length} bytes "
                       f"(the file has {len(data)})")
    at, kinds = 12, []
    while at < len(data):
        if at + 8 > len(data):
            raise DbbError(f"the proxy mesh {path} is damaged: a chunk header is cut short")
        n, kind = struct.unpack_from("<I4s", data, at)
        if at + 8 + n > len(data) or n % 4:
            raise DbbError(f"the proxy mesh {path} is damaged: a chunk of {n} bytes does not fit the file")
        kinds.append(kind)
        at += 8 + n
    if kinds[:1] != [_JSON_CHUNK] or any(k != _BIN_CHUNK for k in kinds[1:2]):
        raise DbbError(f"the proxy mesh {path} is damaged: its chunks are {[k.decode('latin-1') for k in kinds]}")


def read_glb(path: Path) -> dict:
    """Meshes of a ``.glb`` by node name: {name: trimesh.Trimesh} (in the file's space)."""
    import trimesh

    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise DbbError(f"cannot read the proxy mesh {path}: {e.strerror or e}") from None
    check_glb_layout(data, path)
    try:
        scene = trimesh.load(io.BytesIO(data), file_type="glb", force="scene", process=False)
        out = {}
        for node in scene.graph.nodes_geometry:
            T, geom = scene.graph[node]
            out[node] = scene.geometry[geom].copy().apply_transform(T)
    except Exception as e:  # noqa: BLE001 - trimesh raises many kinds on a corrupt file
        raise DbbError(f"cannot read the proxy mesh {path}: {' '.join(str(e).split())[:120]}") from None
    bad = sorted(n for n, m in out.items() if not np.isfinite(np.asarray(m.vertices)).all())
    if bad:
        raise DbbError(f"the proxy mesh {path} is damaged: node {bad[0]} has non-finite vertices")
    return out
