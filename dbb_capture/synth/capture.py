"""Writing a synthetic capture folder (videos, board.json, object.json, ground truth), frames
rendered in worker processes; and reading its ground truth back."""

from __future__ import annotations

import os
import time as _time
from dataclasses import asdict, dataclass
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import torch

from ..core.errors import DbbError
from ..core.outputs import atomic_dir, write_json
from ..core.progress import progress
from ..geometry.cameras import Intrinsics
from ..geometry.conventions import opengl_from_opencv
from .objects import ObjectModel
from .path import camera_path
from .render import Renderer, sensor
from .scene import Scene, SynthConfig, make_scene


@dataclass(frozen=True)
class SynthResult:
    root: Path
    n_frames: int
    n_background_frames: int
    width: int
    height: int
    fps: float
    seconds_per_frame: float


class _VideoWriter:
    """H.264 (yuv420p, near-lossless CRF) through PyAV."""

    def __init__(self, path: Path, width: int, height: int, fps: float, crf: int = 16):
        import av

        self.container = av.open(str(path), mode="w")
        self.stream = self.container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        self.stream.width, self.stream.height = width, height
        self.stream.pix_fmt = "yuv420p"
        self.stream.options = {"crf": str(crf), "preset": "veryfast"}

    def write(self, rgb: np.ndarray) -> None:
        import av

        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        for packet in self.stream.encode(frame):
            self.container.mux(packet)

    def close(self) -> None:
        for packet in self.stream.encode():
            self.container.mux(packet)
        self.container.close()


# Per-process state of the render workers (set once by _init_worker).
_WORKER: dict = {}


def _init_worker(scene: Scene, intr: Intrinsics, samples: int, noise: float, seed: int) -> None:
    # One intra-op thread per process: two processes beat two threads spinning on one frame.
    torch.set_num_threads(1)
    _WORKER.update(scene=scene, empty=scene.without_object(), renderer=Renderer(intr, samples),
                   noise=noise, seed=seed)


def _render_job(job: tuple[str, int, np.ndarray, float]) -> tuple[np.ndarray, np.ndarray]:
    """One finished frame: (noisy RGB (H, W, 3) uint8, object coverage (H, W) uint8)."""
    which, i, c2w, t = job
    w = _WORKER
    img, cover = w["renderer"].render(w["scene"] if which == "video" else w["empty"], c2w, t)
    # Noise seeded per frame: the same capture whatever the number of processes.
    rng = np.random.default_rng([w["seed"], 3 if which == "video" else 4, i])
    return sensor(img, w["noise"], rng), np.round(cover * 255).astype(np.uint8)


class _FramePool:
    """Renders frames in order, in this process or in ``workers`` spawned processes."""

    def __init__(self, scene: Scene, intr: Intrinsics, cfg: SynthConfig, workers: int):
        self.args = (scene, intr, cfg.samples, cfg.noise, cfg.seed)
        self.workers = max(1, workers)
        self.pool = None

    def __enter__(self) -> "_FramePool":
        if self.workers > 1:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            self.pool = ProcessPoolExecutor(self.workers, mp_context=mp.get_context("spawn"),
                                            initializer=_init_worker, initargs=self.args)
        else:
            threads = torch.get_num_threads()
            _init_worker(*self.args)
            torch.set_num_threads(threads)  # in this process, keep the caller's threads
        return self

    def frames(self, which: str, poses: np.ndarray, times: np.ndarray):
        jobs = [(which, i, poses[i], float(times[i])) for i in range(len(poses))]
        if self.pool is None:
            return map(_render_job, jobs)
        return self.pool.map(_render_job, jobs, chunksize=2)

    def __exit__(self, *exc) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)


def _frames_json(poses: np.ndarray, times: np.ndarray) -> list[dict]:
    return [{"index": i, "time": round(float(t), 6),
             "transform_matrix": opengl_from_opencv(c2w).round(9).tolist()}
            for i, (c2w, t) in enumerate(zip(poses, times))]


def write_capture(cfg: SynthConfig, out: Path, overwrite: bool = False,
                  with_camera_json: bool = False) -> SynthResult:
    """Render a whole capture into ``out`` (written aside, renamed into place).

    Layout: ``video.mp4``, ``background.mp4``, ``board.json``, ``object.json`` (sphere and
    ``kind``), optional ``camera.json``, and ``ground_truth/{camera.json, cameras.json, object_model.json,
    masks/NNNNN.png}``. ``cameras.json`` holds per-frame OpenGL camera-to-world matrices in
    the board frame (as in ``transforms.json``) for the video and the clean plate.
    """
    if cfg.width % 2 or cfg.height % 2:
        raise DbbError(f"resolution {cfg.width}x{cfg.height}: width and height must be even (H.264)")
    rng = np.random.default_rng(cfg.seed)
    scene = make_scene(cfg, rng)
    intr = cfg.intrinsics()
    n = max(1, int(round(cfg.seconds * cfg.fps)))
    times = np.arange(n) / cfg.fps
    poses = camera_path(cfg, scene, times, np.random.default_rng([cfg.seed, 1]))
    nb = 0 if cfg.background_seconds is None else max(1, int(round(cfg.background_seconds * cfg.fps)))
    btimes = np.arange(nb) / cfg.fps
    bposes = (camera_path(cfg, scene, btimes, np.random.default_rng([cfg.seed, 2])) if nb
              else np.zeros((0, 4, 4)))
    center, radius = scene.obj_sphere
    t0 = _time.perf_counter()
    with atomic_dir(Path(out), overwrite=overwrite) as tmp:
        gt = tmp / "ground_truth"
        (gt / "masks").mkdir(parents=True)
        write_json(tmp / "board.json", cfg.board.to_json())
        write_json(tmp / "object.json", {"center": center.round(6).tolist(), "radius": round(radius, 6),
                                       "kind": cfg.kind})
        if with_camera_json:
            write_json(tmp / "camera.json", intr.to_json())
        write_json(gt / "camera.json", intr.to_json())
        write_json(gt / "object_model.json", scene.obj.to_json())
        write_json(gt / "cameras.json", {
            "note": "transform_matrix: camera-to-world, OpenGL camera axes, board frame, metres",
            "intrinsics": intr.to_json(), "fps": cfg.fps,
            "video": _frames_json(poses, times), "background": _frames_json(bposes, btimes)})
        write_json(gt / "synth_config.json", {**asdict(cfg), "board": cfg.board.to_json()})
        workers = cfg.workers or (min(2, os.cpu_count() or 1) if n + nb >= 40 else 1)
        with progress() as prog, _FramePool(scene, intr, cfg, workers) as pool:
            task = prog.add_task("render video", total=n, info="")
            vw = _VideoWriter(tmp / "video.mp4", cfg.width, cfg.height, cfg.fps, cfg.crf)
            for i, (rgb, mask) in enumerate(pool.frames("video", poses, times)):
                vw.write(rgb)
                cv2.imwrite(str(gt / "masks" / f"{i:05d}.png"), mask)
                prog.advance(task)
            vw.close()
            spf = (_time.perf_counter() - t0) / n
            if nb:
                task = prog.add_task("render clean plate", total=nb, info="")
                vw = _VideoWriter(tmp / "background.mp4", cfg.width, cfg.height, cfg.fps, cfg.crf)
                for rgb, _ in pool.frames("background", bposes, btimes):
                    vw.write(rgb)
                    prog.advance(task)
                vw.close()
    return SynthResult(Path(out), n, nb, cfg.width, cfg.height, cfg.fps, spf)


def load_ground_truth(capture: Path) -> tuple[Intrinsics, dict, ObjectModel]:
    """(intrinsics, cameras.json content, object model) of a synthetic capture."""
    from ..core.outputs import read_json

    gt = Path(capture) / "ground_truth"
    return (Intrinsics.load(gt / "camera.json"), read_json(gt / "cameras.json", "ground truth"),
            ObjectModel.from_json(read_json(gt / "object_model.json", "ground truth")))
