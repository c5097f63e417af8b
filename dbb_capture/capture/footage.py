"""Footage ingest: every input kind is a converter with one interface.

A :class:`FootageSource` knows its frames' times without decoding them (``info``) and reads
any increasing subset of them (``read``), so workers can split a video into segments. Frames
come out as RGB arrays (uint8, or uint16 for RAW) with their time in seconds; the pose stage
asks for grey uint8 directly where the codec can give it cheaply.

Kinds: video files (PyAV; display rotation honoured), image folders (jpg/png), RAW folders
(rawpy: linear, camera white balance, no auto-brightening, 16 bit, no EXIF flip) and Record3D
``.r3d`` exports (jpg frames, intrinsics and ARKit poses).
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np

from ..core.errors import DbbError, InputError
from ..geometry.cameras import Intrinsics

VIDEO_EXTS = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
IMAGE_EXTS = (".jpg", ".jpeg", ".png")
RAW_EXTS = (".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf", ".orf", ".rw2", ".pef", ".srw")
DEFAULT_IMAGE_FPS = 10.0  # time step given to image folders, which carry no clock
# A video with fewer of the frames its container announces than this share is refused: a copy
# cut short (an upload that stopped) would give poses of a part of the capture without saying so.
MIN_DECODED_SHARE = 0.5


@dataclass(frozen=True)
class FootageFrame:
    """One decoded frame: ``image`` (H, W, 3) RGB uint8/uint16 or (H, W) grey; ``time`` in seconds."""

    index: int          # position in the source (0-based)
    time: float
    image: np.ndarray
    name: str           # stable name for output files, e.g. "00012"


@dataclass(frozen=True)
class FootageInfo:
    """What a source holds, known before decoding pixels. ``times`` (N,) seconds, increasing."""

    kind: str           # "video" | "images" | "raw" | "r3d"
    path: Path
    width: int          # as displayed (after rotation)
    height: int
    fps: float          # nominal rate (images: the assumed one)
    times: np.ndarray
    announced: int | None = None   # frames the container's index announces (videos), None: unknown

    @property
    def n_frames(self) -> int:
        return int(len(self.times))


class FootageSource:
    """Base converter: ``info`` and ``read(indices, gray)``; subclasses add their own extras."""

    kind = "?"
    single_thread = False  # set in worker processes: one decoding thread each, no oversubscription

    def __init__(self, path: Path):
        self.path = Path(path)
        self._info: FootageInfo | None = None

    @property
    def info(self) -> FootageInfo:
        if self._info is None:
            self._info = self._probe()
        return self._info

    def _probe(self) -> FootageInfo:
        raise NotImplementedError

    def read(self, indices: Sequence[int], gray: bool = False) -> Iterator[FootageFrame]:
        """Frames at increasing source ``indices`` (grey uint8 (H, W) when ``gray``)."""
        raise NotImplementedError

    def intrinsics(self) -> Intrinsics | None:
        """Intrinsics the footage carries itself (Record3D), else None."""
        return None


# --------------------------------------------------------------------------- video
def _rotate(img: np.ndarray, rotation_deg: float) -> np.ndarray:
    """Apply a display-matrix rotation (degrees counter-clockwise, as PyAV reports it)."""
    k = int(round(rotation_deg / 90.0)) % 4
    return np.ascontiguousarray(np.rot90(img, k)) if k else img


_PLANAR_YUV = ("yuv420p", "yuvj420p", "yuv422p", "yuvj422p", "yuv444p", "yuvj444p", "nv12", "gray")


def _luma(frame) -> np.ndarray:
    """Grey uint8 (H, W) of a decoded frame: its Y plane as is when it has one (no colour
    conversion; video range 16-235 is fine for finding a board), else converted."""
    if frame.format.name in _PLANAR_YUV:
        plane = frame.planes[0]
        return np.frombuffer(plane, np.uint8).reshape(-1, plane.line_size)[:frame.height, :frame.width].copy()
    return frame.to_ndarray(format="gray")


class VideoSource(FootageSource):
    """A video file decoded with PyAV (threaded decoding, display rotation applied)."""

    kind = "video"

    def _open(self):
        import av

        try:
            container = av.open(str(self.path), metadata_errors="replace")
            stream = container.streams.video[0]
        except (av.error.FFmpegError, IndexError, OSError) as e:
            raise InputError(f"cannot read video {self.path}: {_why(e)}") from None
        stream.thread_type = "NONE" if self.single_thread else "AUTO"
        return container, stream

    def _probe(self) -> FootageInfo:
        import av

        container, stream = self._open()
        try:
            # Packet timestamps give every frame's time without decoding a pixel.
            pts = sorted(p.pts for p in _packets(container, stream) if p.pts is not None and p.size)
            announced = int(stream.frames or 0) or None
            container.seek(0)
            first = next(_decoded(container, stream), None)
            # Read everything from the stream before closing: PyAV objects of a closed
            # container point at freed memory (a segmentation fault, not an exception).
            tb = float(stream.time_base)
            rate = float(stream.average_rate or stream.guessed_rate or 0)
            if first is not None:
                rotation, w, h = float(first.rotation or 0), first.width, first.height
        except av.error.FFmpegError as e:
            raise InputError(f"cannot read video {self.path}: {_why(e)}") from None
        finally:
            container.close()
        if first is None or not pts:
            raise InputError(f"video {self.path} holds no decodable frames")
        if announced and len(pts) < MIN_DECODED_SHARE * announced:
            raise InputError(f"video {self.path} is cut short: its container announces {announced} frames but the "
                             f"file holds {len(pts)} ({100 * len(pts) / announced:.0f} %, at least "
                             f"{100 * MIN_DECODED_SHARE:.0f} % needed): a truncated copy? copy the file again")
        times = (np.asarray(pts, np.float64) - pts[0]) * tb
        self._pts0 = pts[0]
        self._rotation = rotation
        if int(round(self._rotation / 90.0)) % 2:
            w, h = h, w
        fps = rate or (
            (len(times) - 1) / times[-1] if len(times) > 1 and times[-1] > 0 else 30.0)
        return FootageInfo(self.kind, self.path, w, h, fps, times, announced)

    def read(self, indices: Sequence[int], gray: bool = False) -> Iterator[FootageFrame]:
        import av

        info = self.info
        want = sorted(set(int(i) for i in indices))
        if not want:
            return
        container, stream = self._open()
        tb = float(stream.time_base)
        try:
            start_pts = int(round(info.times[want[0]] / tb)) + self._pts0
            if want[0] > 0:
                container.seek(start_pts, stream=stream, backward=True, any_frame=False)
            j = 0
            for frame in _decoded(container, stream):
                if frame.pts is None:
                    continue
                # Match decoded frames to indices by timestamp (robust to seeking to a keyframe).
                t = (frame.pts - self._pts0) * tb
                k = int(np.searchsorted(info.times, t - 1e-6))
                while j < len(want) and want[j] < k:
                    j += 1  # a frame the decoder did not return; skip it
                if j >= len(want):
                    break
                if want[j] != k:
                    continue
                img = _luma(frame) if gray else frame.to_ndarray(format="rgb24")
                yield FootageFrame(k, float(info.times[k]), _rotate(img, self._rotation), f"{k:05d}")
                j += 1
                if j >= len(want):
                    break
        except av.error.FFmpegError as e:
            raise InputError(f"cannot decode video {self.path}: {_why(e)}") from None
        finally:
            container.close()


def _why(e: Exception) -> str:
    """FFmpeg's words for an error, without its number and the file name the message repeats."""
    return str(getattr(e, "strerror", None) or e)


def frames_decoded(info: FootageInfo, sampled: int, got: int) -> int:
    """How many of the footage's frames decode, from ``got`` decoded of ``sampled`` asked for;
    an :class:`InputError` where a video decodes to fewer than :data:`MIN_DECODED_SHARE` of the
    frames its container announces (before any pose is solved from the few that did)."""
    n = info.n_frames if got >= sampled else int(info.n_frames * got / max(sampled, 1))
    if info.announced and n < MIN_DECODED_SHARE * info.announced:
        raise InputError(f"video {info.path}: only {n} of the {info.announced} frames its container announces "
                         f"could be decoded ({100 * n / info.announced:.0f} %, at least "
                         f"{100 * MIN_DECODED_SHARE:.0f} % needed): the file is cut short or damaged; copy it again")
    return n


def _packets(container, stream) -> Iterator:
    """The stream's packets up to the first the container cannot read (a file cut short ends
    there instead of failing: the frames before it are good)."""
    import av

    packets = container.demux(stream)
    while True:
        try:
            yield next(packets)
        except (StopIteration, av.error.FFmpegError):
            return


def _decoded(container, stream) -> Iterator:
    """Decoded frames of the stream; a packet the decoder refuses (damaged, or cut off at the
    end of the file) loses its frame and decoding goes on, so a caller counts what it got."""
    import av

    for packet in _packets(container, stream):
        try:
            frames = packet.decode()
        except av.error.FFmpegError:
            continue
        yield from frames


# --------------------------------------------------------------------------- image folders
class _FileListSource(FootageSource):
    """Frames that are files in a folder, sorted by name, one ``DEFAULT_IMAGE_FPS`` step apart."""

    exts: tuple[str, ...] = ()

    def __init__(self, path: Path, fps: float = DEFAULT_IMAGE_FPS):
        super().__init__(path)
        self.fps = fps
        if not self.path.is_dir():
            raise InputError(f"footage folder not found: {self.path}")
        self.files = sorted(p for p in self.path.iterdir() if p.suffix.lower() in self.exts)
        if not self.files:
            raise InputError(f"{self.path} holds no {'/'.join(self.exts)} files")

    def _probe(self) -> FootageInfo:
        first = self._load(self.files[0])
        h, w = first.shape[:2]
        times = np.arange(len(self.files)) / self.fps
        return FootageInfo(self.kind, self.path, w, h, self.fps, times)

    def _load(self, path: Path) -> np.ndarray:
        raise NotImplementedError

    def read(self, indices: Sequence[int], gray: bool = False) -> Iterator[FootageFrame]:
        info = self.info
        for i in sorted(set(int(i) for i in indices)):
            img = self._load(self.files[i])
            if img.shape[:2] != (info.height, info.width):
                raise InputError(f"{self.files[i]}: size {img.shape[1]}x{img.shape[0]} differs from "
                                 f"the first frame's {info.width}x{info.height}")
            if gray:
                img = to_gray8(img)
            yield FootageFrame(i, float(info.times[i]), img, self.files[i].stem)


class ImageFolderSource(_FileListSource):
    kind = "images"
    exts = IMAGE_EXTS

    def _load(self, path: Path) -> np.ndarray:
        return read_rgb8(path)


def read_rgb8(path: Path) -> np.ndarray:
    """An image file as RGB uint8 (H, W, 3), turned by its EXIF orientation as viewers do (16-bit
    images keep their high byte). Read with Pillow, which says what is wrong with a damaged file
    in its exception, where libpng and libjpeg under OpenCV print it on stderr."""
    from PIL import Image, ImageOps

    try:
        with Image.open(path) as im:
            im = ImageOps.exif_transpose(im)
            if im.mode.startswith("I"):          # 16/32-bit grey
                grey = (np.asarray(im, np.uint32) >> (8 if im.mode.startswith("I;16") else 24)).astype(np.uint8)
                return np.repeat(grey[..., None], 3, 2)
            return np.asarray(im.convert("RGB"))
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as e:
        raise InputError(f"cannot read image {path}: {e}") from None


def decode_raw(path: Path) -> np.ndarray:
    """RAW file -> linear, camera-white-balanced, unrotated RGB uint16 (H, W, 3)."""
    import rawpy

    try:
        with rawpy.imread(str(path)) as raw:
            return raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16,
                                   use_camera_wb=True, user_flip=0)
    except (rawpy.LibRawError, OSError) as e:
        hint = (" (Apple ProRAW from iOS 18 uses JPEG-XL compression, which the LibRaw in rawpy "
                "cannot decode: export as JPEG/HEIC-free DNG or use the video)")
        raise InputError(f"cannot decode RAW {path}: {type(e).__name__}{hint if path.suffix.lower() == '.dng' else ''}") from None


class RawFolderSource(_FileListSource):
    kind = "raw"
    exts = RAW_EXTS

    def _load(self, path: Path) -> np.ndarray:
        return decode_raw(path)


# --------------------------------------------------------------------------- Record3D
class R3dSource(FootageSource):
    """A Record3D ``.r3d`` export: a zip of ``metadata`` (JSON) and ``rgbd/{i}.jpg``."""

    kind = "r3d"

    def __init__(self, path: Path):
        super().__init__(path)
        try:
            with zipfile.ZipFile(self.path) as z:
                self.meta = json.loads(z.read("metadata"))
                names = {n for n in z.namelist() if n.startswith("rgbd/") and n.endswith(".jpg")}
        except (OSError, zipfile.BadZipFile, KeyError, json.JSONDecodeError) as e:
            raise InputError(f"cannot read Record3D export {self.path}: {e}") from None
        self.jpgs = sorted(names, key=lambda n: int(Path(n).stem))
        if not self.jpgs:
            raise InputError(f"{self.path} holds no rgbd/*.jpg frames")

    def _probe(self) -> FootageInfo:
        fps = float(self.meta.get("fps", 30))
        first = self._decode(self.jpgs[0])
        h, w = first.shape[:2]
        return FootageInfo(self.kind, self.path, w, h, fps, np.arange(len(self.jpgs)) / fps)

    def _decode(self, name: str, z: zipfile.ZipFile | None = None) -> np.ndarray:
        data = (z.read(name) if z is not None else zipfile.ZipFile(self.path).read(name))
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise InputError(f"{self.path}: cannot decode {name}")
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def read(self, indices: Sequence[int], gray: bool = False) -> Iterator[FootageFrame]:
        info = self.info
        with zipfile.ZipFile(self.path) as z:
            for i in sorted(set(int(i) for i in indices)):
                img = self._decode(self.jpgs[i], z)
                yield FootageFrame(i, float(info.times[i]), to_gray8(img) if gray else img, f"{i:05d}")

    def intrinsics(self) -> Intrinsics:
        """The export's K (9 values, column-major), scaled from the depth/meta size to the jpgs."""
        K = np.asarray(self.meta["K"], np.float64).reshape(3, 3).T
        w0, h0 = int(self.meta.get("w", self.info.width)), int(self.meta.get("h", self.info.height))
        sx, sy = self.info.width / w0, self.info.height / h0
        return Intrinsics(self.info.width, self.info.height, K[0, 0] * sx, K[1, 1] * sy,
                          (K[0, 2] + 0.5) * sx - 0.5, (K[1, 2] + 0.5) * sy - 0.5)

    def arkit_c2w_opencv(self) -> np.ndarray:
        """ARKit camera-to-world poses (N, 4, 4) in OpenCV camera axes (ARKit's world, not the board's)."""
        from scipy.spatial.transform import Rotation

        poses = np.asarray(self.meta.get("poses", []), np.float64).reshape(-1, 7)
        out = np.tile(np.eye(4), (len(poses), 1, 1))
        out[:, :3, :3] = Rotation.from_quat(poses[:, :4]).as_matrix()
        out[:, :3, 3] = poses[:, 4:]
        return out @ np.diag([1.0, -1.0, -1.0, 1.0])


# --------------------------------------------------------------------------- dispatch
def open_footage(path: Path) -> FootageSource:
    """The converter for ``path``: a video file, an image/RAW folder, an ``.r3d``, or a capture folder."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"footage not found: {path}")
    if path.is_file():
        suf = path.suffix.lower()
        if suf == ".r3d":
            return R3dSource(path)
        if suf in VIDEO_EXTS:
            return VideoSource(path)
        raise InputError(f"{path}: not a video ({', '.join(VIDEO_EXTS)}) or Record3D .r3d file")
    exts = {p.suffix.lower() for p in path.iterdir() if p.is_file()}
    if exts & set(IMAGE_EXTS) and not (path / "board.json").exists():
        return ImageFolderSource(path)
    if exts & set(RAW_EXTS):
        return RawFolderSource(path)
    return capture_footage(path)


def capture_footage(capture: Path) -> FootageSource:
    """The object footage of a capture folder: video.mp4/.mov, frames/, raw/ or one .r3d."""
    capture = Path(capture)
    for name in ("video.mp4", "video.mov"):
        if (capture / name).is_file():
            return VideoSource(capture / name)
    if (capture / "frames").is_dir():
        return ImageFolderSource(capture / "frames")
    if (capture / "raw").is_dir():
        return RawFolderSource(capture / "raw")
    r3d = sorted(capture.glob("*.r3d"))
    if r3d:
        return R3dSource(r3d[0])
    videos = sorted(p for p in capture.iterdir() if p.suffix.lower() in VIDEO_EXTS
                    and not p.stem.startswith("background")) if capture.is_dir() else []
    if videos:
        return VideoSource(videos[0])
    raise InputError(f"{capture}: no footage found (expected video.mp4/video.mov, frames/, raw/ or a .r3d)")


def prefetched(frames: Iterator[FootageFrame], depth: int = 4) -> Iterator[FootageFrame]:
    """Decode ahead in a thread (PyAV and OpenCV release the GIL), so decoding the next frames
    overlaps work on this one; exceptions of the decoder are raised here, in order."""
    import queue
    import threading

    q: queue.Queue = queue.Queue(maxsize=depth)
    done = object()
    stop = threading.Event()

    def run() -> None:
        try:
            for f in frames:
                while not stop.is_set():
                    try:
                        q.put(f, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            q.put(done)
        except BaseException as e:  # handed to the consumer
            q.put(e)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    try:
        while True:
            item = q.get()
            if item is done:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()


# --------------------------------------------------------------------------- sampling & sharpness
def sample_indices(times: np.ndarray, fps: float | None) -> np.ndarray:
    """Indices (M,) of frames kept when resampling frame ``times`` (N,) seconds to ``fps``.

    Keeps the first frame at or after each tick k / fps; ``None`` keeps every frame.
    """
    times = np.asarray(times, np.float64)
    if fps is None or len(times) == 0:
        return np.arange(len(times))
    if fps <= 0:
        raise DbbError(f"{{=fps}} must be positive, got {fps}")
    ticks = np.arange(0.0, times[-1] + 1e-9, 1.0 / fps)
    idx = np.searchsorted(times, ticks - 1e-6)
    return np.unique(idx[idx < len(times)])


def to_gray8(img: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) RGB uint8/uint16 -> (H, W) uint8 grey (16 bit: scaled by its 99.5th percentile)."""
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    if img.dtype == np.uint8:
        return img
    # Linear RAW is dark; stretch so the board's white is near the top of the 8-bit range.
    hi = max(float(np.percentile(img[::8, ::8], 99.5)), 1.0)
    return np.clip(img.astype(np.float32) * (235.0 / hi), 0, 255).astype(np.uint8)


def sharpness(gray: np.ndarray, max_side: int = 640) -> float:
    """Variance of the Laplacian of a grey image (H, W), reduced to ``max_side``: higher is sharper.

    Only compared between neighbouring frames of one footage, so the reduction (for speed)
    changes nothing that matters; motion blur of a few pixels still shows at that size.
    """
    k = -(-max(gray.shape) // max_side)  # integer factor: OpenCV's fast INTER_AREA path
    if k > 1:
        gray = cv2.resize(gray, None, fx=1 / k, fy=1 / k, interpolation=cv2.INTER_AREA)
    _, std = cv2.meanStdDev(cv2.Laplacian(gray, cv2.CV_16S))
    return float(std[0, 0] ** 2)


def blurry_mask(scores: np.ndarray, ratio: float = 0.4, window: int = 9) -> np.ndarray:
    """Frames (N,) whose sharpness is below ``ratio`` x the running median of ``window`` neighbours.

    Relative to neighbours, not absolute: sharpness depends on the scene and the resolution.
    """
    s = np.asarray(scores, np.float64)
    if len(s) < 3 or ratio <= 0:
        return np.zeros(len(s), bool)
    half = window // 2
    med = np.array([np.median(s[max(0, i - half): i + half + 1]) for i in range(len(s))])
    return s < ratio * med
