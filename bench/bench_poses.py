"""Pose accuracy over varied synthetic captures, and pose speed at 1920x1440.

Accuracy (``accuracy``): renders synthetic captures (boards, dictionaries, lens distortion,
resolutions vary), runs the pose stage with the true intrinsics and with intrinsics
self-calibrated from the footage, and compares every posed frame with the ground truth:
frames posed, rotation error (median, 95th percentile, degrees), translation error per
metre of camera-to-board-centre distance (mm/m).

Speed (``speed``): a 1920x1440 synthetic capture is re-encoded as a longer video (played
forth and back, a keyframe a second, as phones write) and posed end to end, decode
included, three ways: plain full-resolution ``detectBoard`` in one process; the fast path
(reduced image, tracked region, full-resolution corner refinement) in one process; the
fast path over 2 spawned processes. Prints Markdown rows for docs/results.md.

    .venv/bin/python bench/bench_poses.py accuracy --work out/bench/poses
    .venv/bin/python bench/bench_poses.py speed --work out/bench/poses
    .venv/bin/python bench/bench_poses.py calibration --work out/bench/poses
    # further captures with the same settings, other seeds:
    .venv/bin/python bench/bench_poses.py accuracy --work out/bench/poses \
        --cases 4,4,4,0,1 --seeds 60,61,62,63,64
    .venv/bin/python bench/bench_poses.py accuracy --work out/bench/poses \
        --cases 2,3 --seeds 65,66
    .venv/bin/python bench/bench_poses.py accuracy --work out/bench/poses-10s \
        --seconds 10 --cases 4,0 --seeds 40,41
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import time
from fractions import Fraction
from pathlib import Path

import numpy as np

from dbb_capture.capture.board import BoardSpec
from dbb_capture.capture.footage import VideoSource, open_footage
from dbb_capture.geometry.conventions import opencv_from_opengl
from dbb_capture.poses.detect import DetectorConfig
from dbb_capture.poses.run import estimate_poses
from dbb_capture.poses.solve import PoseConfig

# dbb_capture.synth.scene (and torch with it) is imported inside the functions that render: spawned
# pose workers re-import this main module, and torch would cost each of them seconds to load.

# name, board, distortion, resolution
CASES = [
    ("7x5 5X5_100, no distortion, 960x720", BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100"),
     (0.0,) * 5, (960, 720)),
    ("5x7 6X6_250 (0.04/0.02), barrel k1=-0.2, 960x720", BoardSpec(5, 7, 0.04, 0.02, "DICT_6X6_250"),
     (-0.2, 0.08, 0.0005, -0.0005, 0.0), (960, 720)),
    ("9x6 4X4_50, pincushion k1=+0.1, 1280x960", BoardSpec(9, 6, 0.035, 0.026, "DICT_4X4_50"),
     (0.1, -0.05, 0.0, 0.0, 0.0), (1280, 960)),
    ("6x8 APRILTAG_36h11 legacy, barrel, 1280x720", BoardSpec(6, 8, 0.045, 0.034, "DICT_APRILTAG_36h11", True),
     (-0.12, 0.03, 0.0, 0.0, 0.0), (1280, 720)),
    ("7x5 5X5_100, barrel k1=-0.15, 640x480", BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100"),
     (-0.15, 0.05, 0.0, 0.0, 0.0), (640, 480)),
]


def errors(run, cams: dict, board: BoardSpec) -> dict:
    """Pose errors of a run against ground-truth ``cameras.json`` content."""
    gt = [opencv_from_opengl(np.array(f["transform_matrix"])) for f in cams["video"]]
    rot, trans = [], []
    for p in run.posed:
        g = gt[p.index]
        R = p.c2w[:3, :3].T @ g[:3, :3]
        rot.append(math.degrees(math.acos(float(np.clip((np.trace(R) - 1) / 2, -1, 1)))))
        dist = np.linalg.norm(g[:3, 3] - board.center)
        trans.append(1000 * np.linalg.norm(p.c2w[:3, 3] - g[:3, 3]) / dist)
    rot, trans = np.array(rot), np.array(trans)
    return {"frames": len(run.frames), "posed": len(rot),
            "rot_med": float(np.median(rot)), "rot_p95": float(np.percentile(rot, 95)),
            "trans_med": float(np.median(trans)), "trans_p95": float(np.percentile(trans, 95))}


def board_in_view(cams: dict, board: BoardSpec, intr) -> np.ndarray:
    """Per frame: are all the board's corners inside the image (N,) bool."""
    from dbb_capture.geometry.cameras import project_points

    obj = board.chessboard_corners()
    out = []
    for f in cams["video"]:
        uv = project_points(obj, opencv_from_opengl(np.array(f["transform_matrix"])), intr)
        out.append(bool(((uv >= 0) & (uv <= [intr.width - 1, intr.height - 1])).all()))
    return np.array(out)


def accuracy(work: Path, seconds: float, fps: float, cases: list[int] | None = None,
             seeds: list[int] | None = None, refine: bool = True, path_window: int | None = None) -> None:
    """``cases``: indices into CASES (repeats allowed), ``seeds``: one per case (default 10 + k,
    the table's captures; other seeds render further captures with the same settings);
    ``refine``: also self-calibrated with ``--refine``; ``path_window``: the poses' fusion with the
    camera path (``PoseConfig.path_window``; 0: off; None: the default)."""
    from dbb_capture.synth.capture import load_ground_truth, write_capture
    from dbb_capture.synth.scene import SynthConfig

    rows = []
    cases = list(range(len(CASES))) if cases is None else cases
    seeds = [10 + k for k in cases] if seeds is None else seeds
    for k, seed in zip(cases, seeds):
        name, board, dist, (w, h) = CASES[k]
        cap = work / (f"acc{k}" if seed == 10 + k else f"acc{k}_s{seed}")
        if seed != 10 + k:
            name = f"{name}, seed {seed}"
        if not (cap / "video.mp4").exists():
            write_capture(SynthConfig(kind="static", seconds=seconds, fps=fps, width=w, height=h,
                                      board=board, dist=dist, background_seconds=None, seed=seed),
                          cap, overwrite=True)
        intr, cams, _ = load_ground_truth(cap)
        src = open_footage(cap)
        gates = PoseConfig() if path_window is None else PoseConfig(path_window=path_window)
        known_run = estimate_poses(src, board, intr, pose_cfg=gates)
        known = errors(known_run, cams, board)
        selfcal = {}
        for r in (False, True) if refine else (False,):   # preprocess's default, and with --refine
            run = estimate_poses(src, board, None, refine=r, pose_cfg=gates)
            selfcal[r] = {**errors(run, cams, board), "fx_err_pct": 100 * (run.intrinsics.fx / intr.fx - 1)}
        selfcal.setdefault(True, None)
        in_view = board_in_view(cams, board, intr)
        posed_ids = {p.index for p in known_run.posed}
        posed_in_view = np.mean([i in posed_ids for i in np.flatnonzero(in_view)]) if in_view.any() else float("nan")
        rows.append((name, known, selfcal, posed_in_view, int(in_view.sum())))
        print(json.dumps({"case": name, "known": known, "selfcal": selfcal[False], "selfcal_refined": selfcal[True],
                          "posed_of_full_board_views": posed_in_view}), flush=True)
    print("\n| capture | frames posed (all / full board in view) | rot median / p95 (deg) | "
          "trans median / p95 (mm/m) | self-calibrated: fx err, rot median / p95, trans median "
          "| same with `--refine` |")
    print("|---|---|---|---|---|---|")
    for name, kn, sc, piv, n_in in rows:
        print(f"| {name} | {kn['posed']}/{kn['frames']} ({100 * kn['posed'] / kn['frames']:.0f}%) / "
              f"{100 * piv:.0f}% of {n_in} | {kn['rot_med']:.3f} / {kn['rot_p95']:.3f} | "
              f"{kn['trans_med']:.2f} / {kn['trans_p95']:.2f} | "
              + " | ".join("-" if e is None else
                           f"{e['fx_err_pct']:+.3f}%, {e['rot_med']:.3f} / {e['rot_p95']:.3f}, {e['trans_med']:.2f}"
                           for e in (sc[False], sc[True])) + " |")


def pingpong_video(src_capture: Path, out: Path, repeats: int, fps: int = 30) -> list[int]:
    """Re-encode the capture's frames forth and back ``repeats`` times, a keyframe each second;
    returns the source frame index of every output frame."""
    import av

    frames = [f.image for f in VideoSource(src_capture / "video.mp4").read(range(10_000))]
    order = []
    for r in range(repeats):
        order += list(range(len(frames))) if r % 2 == 0 else list(range(len(frames) - 1, -1, -1))
    with av.open(str(out), "w") as c:
        s = c.add_stream("libx264", rate=Fraction(fps))
        s.width, s.height, s.pix_fmt = frames[0].shape[1], frames[0].shape[0], "yuv420p"
        s.options = {"crf": "18", "g": str(fps), "preset": "veryfast"}
        for i in order:
            for p in s.encode(av.VideoFrame.from_ndarray(frames[i], format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return order


def _cpu_seconds() -> float:
    """CPU time of this process and of its finished children (worker processes), seconds."""
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def speed(work: Path, seconds: float, repeats: int) -> None:
    import cv2

    from dbb_capture.synth.capture import load_ground_truth, write_capture
    from dbb_capture.synth.scene import SynthConfig

    cap = work / "speed1920"
    board = BoardSpec(7, 5, 0.05, 0.0375, "DICT_5X5_100")
    if not (cap / "video.mp4").exists():
        write_capture(SynthConfig(kind="static", seconds=seconds, fps=10, width=1920, height=1440,
                                  board=board, background_seconds=None, seed=0), cap, overwrite=True)
    intr, cams, _ = load_ground_truth(cap)
    video = work / "speed1920_pingpong.mp4"
    order_file = work / "speed1920_order.json"
    if not video.exists():
        order_file.write_text(json.dumps(pingpong_video(cap, video, repeats)))
    order = json.loads(order_file.read_text())
    gt = {"video": [cams["video"][i] for i in order]}

    # detectBoard alone on one full-resolution frame (the figure the issue quotes).
    src = VideoSource(video)
    gray = next(src.read([5], gray=True)).image
    det = cv2.aruco.CharucoDetector(board.cv_board())
    det.detectBoard(gray)
    t0 = time.perf_counter()
    for _ in range(10):
        det.detectBoard(gray)
    detect_ms = (time.perf_counter() - t0) / 10 * 1000

    plain = DetectorConfig(max_side=100_000, track=False, refine=False, saddle=False)
    fast = DetectorConfig()
    rows = []
    for label, cfg, workers in (("plain detectBoard, full resolution, 1 process", plain, 1),
                                ("fast path, 1 process", fast, 1),
                                ("fast path, 2 processes (spawn)", fast, 2)):
        src = VideoSource(video)
        src.info  # the demux pass is part of opening a file, done once: not timed
        load0 = os.getloadavg()[0]
        t0, c0 = time.perf_counter(), _cpu_seconds()
        run = estimate_poses(src, board, intr, workers=workers, det_cfg=cfg)
        dt, cpu = time.perf_counter() - t0, _cpu_seconds() - c0
        e = errors(run, gt, board)
        cpu_ms = 1000 * cpu / len(order)
        rows.append((label, len(order) / dt, cpu_ms, e, max(load0, os.getloadavg()[0])))
        print(json.dumps({"mode": label, "fps": len(order) / dt, "seconds": dt, "cpu_ms_per_frame": cpu_ms,
                          "load": os.getloadavg(), **e}), flush=True)
    print(f"\ndetectBoard alone on one 1920x1440 frame: {detect_ms:.1f} ms ({1000 / detect_ms:.1f} frames/s)\n")
    print("| 1920x1440, decode + detect + pose | frames/s (wall) | CPU ms/frame | machine load | posed | "
          "rot median / p95 (deg) | trans median / p95 (mm/m) |")
    print("|---|---|---|---|---|---|---|")
    for label, fps, cpu_ms, e, load in rows:
        print(f"| {label} | {fps:.1f} | {cpu_ms:.1f} | {load:.1f} | {e['posed']}/{e['frames']} | "
              f"{e['rot_med']:.3f} / {e['rot_p95']:.3f} | {e['trans_med']:.2f} / {e['trans_p95']:.2f} |")


def calibration(work: Path) -> None:
    """`dbb-capture calibrate` on the accuracy captures (rendered by ``accuracy``): OpenCV's
    calibration (the default) against ``--precise``, errors against the true intrinsics."""
    from dbb_capture.poses.calibrate import calibrate_footage
    from dbb_capture.synth.capture import load_ground_truth

    print("| capture | default: fx / fy err, cx / cy err (px), RMS px | `--precise`: same |")
    print("|---|---|---|")
    for k, (name, board, _, _) in enumerate(CASES):
        intr, _, _ = load_ground_truth(work / f"acc{k}")
        cells = []
        for precise in (False, True):
            c = calibrate_footage(open_footage(work / f"acc{k}"), board, precise=precise)
            i = c.intrinsics
            cells.append(f"{100 * (i.fx / intr.fx - 1):+.2f}% / {100 * (i.fy / intr.fy - 1):+.2f}%, "
                         f"{i.cx - intr.cx:+.2f} / {i.cy - intr.cy:+.2f}, {c.rms:.3f}")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["accuracy", "speed", "calibration"])
    ap.add_argument("--work", type=Path, default=Path("out/bench/poses"),
                    help="Folder for the rendered captures (reused when present).")
    ap.add_argument("--seconds", type=float, default=4.8, help="Length of each synthetic capture.")
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=4, help="speed: forth-and-back passes.")
    ap.add_argument("--cases", help="accuracy: comma-separated indices into CASES (default all).")
    ap.add_argument("--seeds", help="accuracy: one synth seed per case (default 10 + index).")
    ap.add_argument("--no-refine", action="store_true", help="accuracy: skip the runs with --refine.")
    ap.add_argument("--path-window", type=int, default=None,
                    help="accuracy: posed neighbours each side in the fusion with the camera path (0: off; default: the pose stage's)")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    if a.what == "accuracy":
        ints = lambda v: None if v is None else [int(x) for x in v.split(",")]   # noqa: E731
        accuracy(a.work, a.seconds, a.fps, ints(a.cases), ints(a.seeds), not a.no_refine, a.path_window)
    elif a.what == "calibration":
        calibration(a.work)
    else:
        speed(a.work, a.seconds, a.repeats)


if __name__ == "__main__":
    main()
