"""Writers of the pose stage's own files: the board's corners as a sparse point cloud (a PLY, and
the points of a COLMAP sparse model written with pycolmap), and the pose report (JSON and a PNG
of the camera path around the board). ``transforms.json`` is written by
:func:`..datasets.transforms.write_transforms`.

The point cloud is true by construction: the ChArUco corners lie exactly where the board says
in the board frame, and every posed frame observed the ones its pose was solved from. Gaussian
splatting and COLMAP readers (nerfstudio's splatfacto, its ``ColmapDataParser``) start from it.

Poses come in as OpenCV camera-to-world (board frame, metres); COLMAP's pixel convention
(top-left pixel centre at (0.5, 0.5)) comes from :mod:`..geometry.conventions`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..capture.board import BoardSpec
from ..datasets.records import Frame
from ..datasets.transforms import relative_path
from ..geometry.cameras import Intrinsics
from ..geometry.conventions import corner_from_centre_px
from ..geometry.transforms import invert_rigid
from .run import PoseRun


@dataclass(frozen=True)
class Sighting:
    """The board corners one posed frame saw: ChArUco ``ids`` (N,), their pixels ``xy`` (N, 2) in
    the undistorted frame (OpenCV's pixel centres) and the colours there ``rgb`` (N, 3) uint8."""

    ids: np.ndarray
    xy: np.ndarray
    rgb: np.ndarray


@dataclass(frozen=True)
class BoardPoints:
    """The board's corners the posed frames saw: ``ids`` (P,), ``xyz`` (P, 3) board frame (metres),
    ``rgb`` (P, 3) uint8 (the mean colour seen), and per point its ``track``: (frame position, xy
    (2,) undistorted OpenCV pixels) in every frame that saw it."""

    ids: np.ndarray
    xyz: np.ndarray
    rgb: np.ndarray
    tracks: list[list[tuple[int, np.ndarray]]]


def corner_pixels(run: PoseRun, intr: Intrinsics) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per posed frame index: the ChArUco ids its pose used (the inliers) and where they are in the
    undistorted frame, (N,) and (N, 2) OpenCV pixels; ``intr`` is the footage's camera (distortion
    included), undistorted to the same K."""
    import cv2

    dets = {d.index: d for d in run.detections}
    out = {}
    for p in run.posed:
        d = dets.get(p.index)
        if d is None or d.n_corners == 0:
            continue
        keep = np.ones(d.n_corners, bool) if p.inliers is None else np.asarray(p.inliers, bool)
        pts = np.asarray(d.corners, np.float64)[keep].reshape(-1, 1, 2)
        xy = cv2.undistortPoints(pts, intr.K, intr.dist_array, None, intr.K).reshape(-1, 2) if intr.distorted \
            else pts.reshape(-1, 2)
        out[p.index] = (np.asarray(d.ids)[keep], xy)
    return out


def sample_colours(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Colours (N, 3) uint8 of RGB ``image`` (H, W, 3) at pixels ``xy`` (N, 2) (nearest pixel)."""
    h, w = image.shape[:2]
    u = np.clip(np.round(xy[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.round(xy[:, 1]).astype(int), 0, h - 1)
    return image[v, u, :3].astype(np.uint8)


def board_points(board: BoardSpec, sightings: Sequence[Sighting | None]) -> BoardPoints:
    """The corners seen in ``sightings`` (one per frame, in frame order; None: a frame that saw none)."""
    corners = board.chessboard_corners()
    tracks: dict[int, list[tuple[int, np.ndarray]]] = {}
    colours: dict[int, list[np.ndarray]] = {}
    for k, s in enumerate(sightings):
        if s is None:
            continue
        for cid, xy, rgb in zip(s.ids.tolist(), s.xy, s.rgb):
            tracks.setdefault(int(cid), []).append((k, xy))
            colours.setdefault(int(cid), []).append(rgb)
    ids = np.array(sorted(tracks), np.int64)
    rgb = np.array([np.round(np.mean(colours[i], 0)) for i in ids], np.uint8).reshape(-1, 3)
    return BoardPoints(ids, corners[ids].reshape(-1, 3), rgb, [tracks[i] for i in ids])


def write_ply(path: Path, points: BoardPoints) -> None:
    """An ASCII PLY of the points: ``x y z`` (metres, board frame) and ``red green blue`` (uchar)."""
    from ..core.outputs import write_bytes_atomic

    head = ["ply", "format ascii 1.0", f"element vertex {len(points.ids)}", "property float x", "property float y",
            "property float z", "property uchar red", "property uchar green", "property uchar blue", "end_header"]
    rows = [f"{x:.9g} {y:.9g} {z:.9g} {r} {g} {b}" for (x, y, z), (r, g, b) in zip(points.xyz, points.rgb.tolist())]
    write_bytes_atomic(Path(path), ("\n".join(head + rows) + "\n").encode())


def write_colmap(folder: Path, intr: Intrinsics, frames: Sequence[Frame], images: Path,
                 points: BoardPoints | None = None) -> None:
    """A COLMAP sparse model (cameras, rigs, frames, images and, given ``points``, the board's
    corners with their tracks) in ``folder``; image names relative to the image folder ``images``
    (COLMAP's image path), so readers that join the two find the files.

    Camera model OPENCV (PINHOLE when undistorted); pixels with COLMAP's corner origin.
    """
    import pycolmap

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rec = pycolmap.Reconstruction()
    cx, cy = corner_from_centre_px(intr.cx), corner_from_centre_px(intr.cy)
    if intr.distorted:
        k1, k2, p1, p2, _ = (float(v) for v in intr.dist_array)
        cam = pycolmap.Camera(model="OPENCV", width=intr.width, height=intr.height,
                              params=[intr.fx, intr.fy, cx, cy, k1, k2, p1, p2], camera_id=1)
    else:
        cam = pycolmap.Camera(model="PINHOLE", width=intr.width, height=intr.height,
                              params=[intr.fx, intr.fy, cx, cy], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    seen: dict[int, list[tuple[int, np.ndarray]]] = {}       # frame position -> (point, xy) in track order
    for p, track in enumerate(points.tracks if points is not None else []):
        for k, xy in track:
            seen.setdefault(k, []).append((p, xy))
    where: dict[tuple[int, int], int] = {}                    # (point, frame position) -> its Point2D index
    for k, f in enumerate(frames):
        w2c = invert_rigid(f.c2w)
        image = pycolmap.Image(name=relative_path(f.image_path, images), camera_id=1, image_id=k + 1)
        obs = seen.get(k, [])
        image.points2D = pycolmap.Point2DList(
            [pycolmap.Point2D(np.array([corner_from_centre_px(x), corner_from_centre_px(y)])) for _, (x, y) in obs])
        where.update({(p, k): j for j, (p, _) in enumerate(obs)})
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c[:3, :4]))
    if points is not None:
        for p, (xyz, rgb, track) in enumerate(zip(points.xyz, points.rgb, points.tracks)):
            rec.add_point3D(np.asarray(xyz, np.float64),
                            pycolmap.Track([pycolmap.TrackElement(k + 1, where[(p, k)]) for k, _ in track]),
                            np.asarray(rgb, np.uint8))
    rec.write(str(folder))


def pose_report(run: PoseRun, board: BoardSpec) -> dict:
    """Per-frame status, corner count, sharpness (variance of the Laplacian) and reprojection
    RMS (px), with totals by status."""
    counts: dict[str, int] = {}
    frames = []
    sharp = {d.index: d.sharpness for d in run.detections}
    for p in run.frames:
        counts[p.status] = counts.get(p.status, 0) + 1
        row = {"name": p.name, "index": p.index, "time": round(p.time, 6), "status": p.status,
               "corners": p.n_corners, "sharpness": round(float(sharp.get(p.index, float("nan"))), 2)}
        if p.c2w is not None:
            row["reprojection_px"] = round(float(p.reproj_px), 4)
            row["ambiguity"] = round(float(p.ambiguity), 4)
            row["distance_m"] = round(float(np.linalg.norm(p.c2w[:3, 3] - board.center)), 5)
        frames.append(row)
    errs = np.array([p.reproj_px for p in run.posed if p.status == "posed"])
    report = {"intrinsics": run.intrinsics.to_json(), "intrinsics_source": run.intrinsics_source,
              "frames_in_footage": run.frames_in_footage, "frames_sampled": len(run.frames),
              "frames_posed": len(run.posed), "by_status": counts,
              "reprojection_px": {"median": round(float(np.median(errs)), 4),
                                  "p95": round(float(np.percentile(errs, 95)), 4),
                                  "max": round(float(errs.max()), 4)} if len(errs) else None,
              "frames": frames}
    if run.calibration is not None:
        report["calibration"] = run.calibration.to_json()
    if run.refined_rms is not None:
        report["joint_refinement_rms_px"] = round(run.refined_rms, 4)
    return report


def plot_camera_path(run: PoseRun, board: BoardSpec, path: Path,
                     sphere: tuple[np.ndarray, float] | None = None, sphere_label: str = "object sphere") -> None:
    """PNG: the board outline, the posed camera centres coloured by time and their viewing
    directions, and the object ``sphere`` (centre (3,), radius, board frame, metres) if known,
    seen from above and from the side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    posed = run.posed
    C = np.array([p.c2w[:3, 3] for p in posed]).reshape(-1, 3)
    D = np.array([p.c2w[:3, 2] for p in posed]).reshape(-1, 3)
    t = np.array([p.time for p in posed])
    bw, bh = board.size_m
    outline = np.array([[0, 0], [bw, 0], [bw, bh], [0, bh], [0, 0]])
    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    scale = 0.2 * max(np.ptp(C, axis=0).max() if len(C) else 1.0, bw)
    for ax, (a, b), title in ((axes[0], (0, 1), "top view (x, y)"), (axes[1], (0, 2), "side view (x, z)")):
        if b == 1:
            ax.plot(outline[:, 0], outline[:, 1], "k-", lw=2, label="board")
        else:
            ax.plot([0, bw], [0, 0], "k-", lw=3, label="board")
        if sphere is not None:                     # a sphere looks like a circle from any side
            ax.add_patch(plt.Circle((sphere[0][a], sphere[0][b]), sphere[1], color="tab:red", alpha=0.35,
                                    label=sphere_label))
        sc = ax.scatter(C[:, a], C[:, b], c=t, cmap="viridis", s=12, label="camera centres")
        ax.quiver(C[:, a], C[:, b], D[:, a] * scale, D[:, b] * scale, angles="xy",
                  scale_units="xy", scale=1, width=0.002, color="gray")
        ax.set_title(title)
        ax.legend(loc="best", fontsize=8)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)" if b == 1 else "z (m)")
        if b == 2:
            ax.invert_yaxis()  # the cameras are at z < 0: show them above the board
    fig.colorbar(sc, ax=axes, label="time (s)")
    n_all = len(run.frames)
    fig.suptitle(f"{len(posed)} of {n_all} frames posed, board frame (metres)")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
