"""Writers of the pose stage's own files: a COLMAP sparse model (pycolmap) and the pose report
(JSON and a PNG of the camera path around the board). ``transforms.json`` is written by
:func:`..datasets.transforms.write_transforms`.

Poses come in as OpenCV camera-to-world (board frame, metres); COLMAP's pixel convention
(top-left pixel centre at (0.5, 0.5)) comes from :mod:`..geometry.conventions`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..capture.board import BoardSpec
from ..datasets.records import Frame
from ..datasets.transforms import relative_path
from ..geometry.cameras import Intrinsics
from ..geometry.conventions import colmap_from_opencv_px
from ..geometry.transforms import invert_rigid
from .run import PoseRun


def write_colmap(folder: Path, intr: Intrinsics, frames: Sequence[Frame], root: Path) -> None:
    """A COLMAP sparse model (cameras, rigs, frames, images; no points) in ``folder``, image names
    relative to the dataset folder ``root``.

    Camera model OPENCV (PINHOLE when undistorted); principal point shifted by +0.5 px.
    """
    import pycolmap

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rec = pycolmap.Reconstruction()
    cx, cy = colmap_from_opencv_px(intr.cx), colmap_from_opencv_px(intr.cy)
    if intr.distorted:
        k1, k2, p1, p2, _ = (float(v) for v in intr.dist_array)
        cam = pycolmap.Camera(model="OPENCV", width=intr.width, height=intr.height,
                              params=[intr.fx, intr.fy, cx, cy, k1, k2, p1, p2], camera_id=1)
    else:
        cam = pycolmap.Camera(model="PINHOLE", width=intr.width, height=intr.height,
                              params=[intr.fx, intr.fy, cx, cy], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    for i, f in enumerate(frames, start=1):
        w2c = invert_rigid(f.c2w)
        image = pycolmap.Image(name=relative_path(f.image_path, root), camera_id=1, image_id=i)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c[:3, :4]))
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


def plot_camera_path(run: PoseRun, board: BoardSpec, path: Path) -> None:
    """PNG: the board outline, the posed camera centres coloured by time and their viewing
    directions, seen from above and from the side."""
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
        sc = ax.scatter(C[:, a], C[:, b], c=t, cmap="viridis", s=12)
        ax.quiver(C[:, a], C[:, b], D[:, a] * scale, D[:, b] * scale, angles="xy",
                  scale_units="xy", scale=1, width=0.002, color="gray")
        ax.set_title(title)
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
