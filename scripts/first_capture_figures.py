"""Pictures of docs/first-capture.md, made from the toolkit's own board and synthetic renders.

    .venv/bin/python scripts/first_capture_figures.py [--bundle BUNDLE] [--out docs/figures/first-capture]

- ``board.png``: the default 7x5 ChArUco board (DICT_5X5_100) as it should be printed;
- ``good_frames.jpg``: four frames along a synthetic handheld path (board and object in view,
  different heights and sides), ``clean_plate.jpg``: the same room without the object;
- ``bad_frames.jpg``: what to avoid (board cut off, object cut off, motion blur, too far);
- ``camera_path.png``: the path seen from above and from the side;
- ``bundle_sheet.jpg`` and ``bundle_proxy.jpg`` (with ``--bundle``): a bundle's preview sheet
  and its proxy mesh over the sheet's first view.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import cv2
import numpy as np


def _label(img: np.ndarray, text: str) -> np.ndarray:
    out = img.copy()
    cv2.rectangle(out, (0, 0), (out.shape[1], 22), (255, 255, 255), -1)
    cv2.putText(out, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return out


def _row(imgs: list[np.ndarray], gap: int = 6) -> np.ndarray:
    h = imgs[0].shape[0]
    sep = np.full((h, gap, 3), 255, np.uint8)
    parts = []
    for i, im in enumerate(imgs):
        parts += [im] + ([sep] if i < len(imgs) - 1 else [])
    return np.concatenate(parts, 1)


def _u8(rgb: np.ndarray) -> np.ndarray:
    return np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8)


def figures(out: Path, bundle: Path | None) -> list[Path]:
    from dbb_capture.geometry.transforms import look_at
    from dbb_capture.synth.objects import UP
    from dbb_capture.synth.path import camera_path
    from dbb_capture.synth.render import Renderer
    from dbb_capture.synth.scene import SynthConfig, make_scene

    out.mkdir(parents=True, exist_ok=True)
    made = []
    cfg = SynthConfig(kind="static", seconds=12.0, fps=10, width=320, height=240, seed=5)
    board = cfg.board
    cv2.imwrite(str(out / "board.png"), cv2.copyMakeBorder(board.render(120), 40, 40, 40, 40,
                                                           cv2.BORDER_CONSTANT, value=255))
    made.append(out / "board.png")
    rng = np.random.default_rng(cfg.seed)
    scene = make_scene(cfg, rng)
    times = np.arange(round(cfg.seconds * cfg.fps)) / cfg.fps
    poses = camera_path(cfg, scene, times, rng)
    intr = cfg.intrinsics()
    r = Renderer(intr, samples=1)
    picks = np.linspace(0, len(times) - 1, 4).round().astype(int)
    good = [_label(cv2.cvtColor(_u8(r.render(scene, poses[i], float(times[i]))[0]), cv2.COLOR_RGB2BGR),
                   f"t = {times[i]:.1f} s") for i in picks]
    cv2.imwrite(str(out / "good_frames.jpg"), _row(good))
    plate = cv2.cvtColor(_u8(r.render(scene.without_object(), poses[picks[1]], 0.0)[0]), cv2.COLOR_RGB2BGR)
    cv2.imwrite(str(out / "clean_plate.jpg"), _label(plate, "clean plate: same room, object removed"))
    made += [out / "good_frames.jpg", out / "clean_plate.jpg"]
    # What to avoid: aim past the board, come too close to the object, shake, stand too far.
    c_obj, rad = scene.obj_sphere
    eye0 = poses[picks[1]][:3, 3]
    away = c_obj + (eye0 - c_obj) * 0.55
    bad_poses = {
        "board out of view": look_at(eye0, c_obj + np.array([0.35, -0.25, 0.0]), UP),
        "object cut off": look_at(away, c_obj + np.array([0.0, 0.0, -0.04]), UP),
        "too far": look_at(c_obj + (eye0 - c_obj) * 2.4, c_obj, UP),
    }
    bad = [_label(cv2.cvtColor(_u8(r.render(scene, c2w, 0.0)[0]), cv2.COLOR_RGB2BGR), k)
           for k, c2w in bad_poses.items()]
    blur = cv2.blur(cv2.cvtColor(_u8(r.render(scene, poses[picks[2]], 0.0)[0]), cv2.COLOR_RGB2BGR), (15, 1))
    bad.insert(2, _label(blur, "motion blur"))
    cv2.imwrite(str(out / "bad_frames.jpg"), _row(bad))
    made.append(out / "bad_frames.jpg")
    made.append(_path_plot(out / "camera_path.png", poses, c_obj, rad, board))
    if bundle is not None:
        made += _bundle_figures(out, bundle)
    return made


def _path_plot(path: Path, poses: np.ndarray, c_obj: np.ndarray, rad: float, board) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    eyes = poses[:, :3, 3]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
    w, h = board.size_m
    ax[0].add_patch(plt.Rectangle((0, 0), w, h, fill=False, lw=1.5, label="board"))
    ax[0].add_patch(plt.Circle(c_obj[:2], rad, color="tab:green", alpha=0.5, label="object"))
    ax[0].plot(eyes[:, 0], eyes[:, 1], ".-", ms=2, lw=0.6, label="camera")
    ax[0].set_aspect("equal")
    ax[0].set_title("from above (board x, y in metres)")
    ax[0].legend(loc="upper left", fontsize=7)
    dist = np.linalg.norm(eyes[:, :2] - c_obj[:2], axis=1)
    ax[1].plot(dist, -eyes[:, 2], ".", ms=2)
    ax[1].plot([0], [-c_obj[2]], "o", color="tab:green")
    ax[1].set_xlabel("horizontal distance to the object (m)")
    ax[1].set_ylabel("height above the board (m)")
    ax[1].set_title("from the side: 10-75 degrees of elevation")
    ax[1].set_aspect("equal")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _bundle_figures(out: Path, bundle: Path) -> list[Path]:
    """The bundle's preview sheet over a checkerboard, and its proxy mesh drawn over view 0."""
    from dbb_capture.bundle import build as B
    from dbb_capture.bundle.proxy import read_glb, transform_points

    with B.open_bundle(bundle) as b:
        m = b.manifest
        sheet = B.read_rgba(b.file(m.previews["sheet"]["file"]))
        cv2.imwrite(str(out / "bundle_sheet.jpg"), cv2.cvtColor(B.over_checker(sheet), cv2.COLOR_RGB2BGR))
        S, cols = int(m.previews["cell_px"]), int(m.previews["sheet"]["columns"])
        a, e, d = m.previews["sheet"]["views"][0]
        view = B.orbit_view("v", m.T, m.radius, a, e, d)
        cell = B.over_checker(B.cell(sheet, 0, cols, S))
        col = read_glb(b.file(m.proxy_mesh["file"]))["proxy-colonly"]
        v_board = transform_points(np.linalg.inv(m.T), np.asarray(col.vertices))
        from dbb_capture.geometry.cameras import project_points

        uv = project_points(v_board, view.c2w, view.intr)
        img = cv2.resize(cv2.cvtColor(cell, cv2.COLOR_RGB2BGR), (3 * S, 3 * S), interpolation=cv2.INTER_NEAREST)
        for f in np.asarray(col.faces)[:: max(1, math.ceil(len(col.faces) / 1500))]:
            pts = np.round((uv[f] + 0.5) * 3 - 0.5).astype(np.int32)
            cv2.polylines(img, [pts], True, (40, 40, 200), 1, cv2.LINE_AA)
        left = cv2.resize(cv2.cvtColor(cell, cv2.COLOR_RGB2BGR), (3 * S, 3 * S), interpolation=cv2.INTER_LINEAR)
        cv2.imwrite(str(out / "bundle_proxy.jpg"), _row([_label(left, "billboard render"),
                                                         _label(img, f"proxy mesh ({len(col.faces)} triangles)")]))
    return [out / "bundle_sheet.jpg", out / "bundle_proxy.jpg"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs/figures/first-capture")
    ap.add_argument("--bundle", type=Path, default=None, help="a static bundle whose previews to show")
    a = ap.parse_args(argv)
    for p in figures(a.out, a.bundle):
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
