"""ChArUco detection: board corners in every frame of the footage, in full-resolution pixels.

Fast detection (:class:`BoardDetector`): markers are found on a reduced image, inside the
board's region from the previous frame when there is one, and the ChArUco corners are then
refined at full resolution. :func:`detect_footage` splits the footage into contiguous
segments decoded and detected in ``spawn`` worker processes (rawpy's OpenMP threads
deadlock under ``fork``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import cv2
import numpy as np

from ..capture.board import BoardSpec
from ..capture.footage import FootageSource, prefetched, sharpness, to_gray8
from ..core.errors import DbbError
from ..core.parallel import map_spawned, report, split
from .corners import corner_margins_px, refine_saddles, refine_xjunctions


@dataclass(frozen=True)
class Detection:
    """Board corners found in one frame. ``ids`` (N,) ChArUco ids, ``corners`` (N, 2) full-res px."""

    index: int
    time: float
    name: str
    ids: np.ndarray
    corners: np.ndarray
    n_markers: int
    sharpness: float

    @property
    def n_corners(self) -> int:
        return int(len(self.ids))


@dataclass(frozen=True)
class DetectorConfig:
    """Fast-path knobs. ``max_side``: long side (px) of the image markers are searched in."""

    max_side: int = 960
    track: bool = True
    refine: bool = True       # re-refine corners at full resolution (cornerSubPix)
    win_frac: float = 0.5     # refinement half-window, as a fraction of the square's white margin
    win_max: int = 6
    px_per_bit: float = 3.5   # reduce no further than this many px per marker bit (25th pct. marker)
    one_threshold: bool = True  # once marker size is known, one adaptive-threshold window, not 3
    saddle: bool = True       # final corners: saddle points of the image (:func:`refine_saddles`)
    saddle_frac: float = 0.8  # saddle-fit half-window, as a fraction of the square's white margin
    saddle_max: int = 8
    saddle_blur: float = 1.0  # Gaussian sigma (px) applied to the fitted patch
    xjunction_below: float = 6.0  # re-fit corners as X-junctions where white margins are under this (px)
    upsample_below: float = 2.0  # markers missed and the found ones under this many px per bit:
    upsample: tuple[float, ...] = (2.0, 3.0)  # ... search the board's region enlarged by these


_SCALES = (1.0, 2.0 / 3.0, 0.5, 1.0 / 3.0, 0.25)  # cheap resize factors


def _quantize_scale(scale: float, up: bool) -> float:
    """The nearest cheap resize factor at or above (``up``) or at or below ``scale``."""
    if up:
        return min(s for s in _SCALES if s >= scale - 1e-9) if scale <= 1 else 1.0
    return max([s for s in _SCALES if s <= scale + 1e-9] or [_SCALES[-1]])


class BoardDetector:
    """Stateful per-stream detector: remembers the board's region to search the next frame."""

    def __init__(self, board: BoardSpec, cfg: DetectorConfig = DetectorConfig()):
        self.board = board
        self.cfg = cfg
        self._cv_board = board.cv_board()
        self._det = cv2.aruco.CharucoDetector(self._cv_board)
        self._dets_by_window: dict[int, object] = {}
        self._window: int | None = None  # adaptive-threshold window for the next frame (px)
        self._roi: tuple[int, int, int, int] | None = None   # x0, y0, x1, y1 in full-res px
        self._last_n = 0
        self._scale_hint: float | None = None  # scale that keeps the last frame's markers readable

    def reset(self) -> None:
        self._roi, self._last_n, self._scale_hint, self._window = None, 0, None, None

    def _detector(self, window: int | None):
        """OpenCV's detector; with ``window``, thresholding at that one window size only
        (OpenCV's default tries 3, 13 and 23 px, which triples the marker search)."""
        if window is None or not self.cfg.one_threshold:
            return self._det
        if window not in self._dets_by_window:
            p = cv2.aruco.DetectorParameters()
            p.adaptiveThreshWinSizeMin = p.adaptiveThreshWinSizeMax = window
            self._dets_by_window[window] = cv2.aruco.CharucoDetector(
                self._cv_board, cv2.aruco.CharucoParameters(), p)
        return self._dets_by_window[window]

    def _detect_in(self, gray: np.ndarray, roi: tuple[int, int, int, int] | None, scale: float,
                   window: int | None = None):
        """detectBoard on ``gray`` cropped to ``roi`` and resized by ``scale``; results in full-res px."""
        x0, y0 = (roi[0], roi[1]) if roi else (0, 0)
        sub = gray[roi[1]:roi[3], roi[0]:roi[2]] if roi else gray
        # INTER_AREA is fast at 1/k (integer k); 2/3 goes through bilinear, which aliases a
        # little, harmless for finding markers (corners are refined at full resolution).
        integer = abs(1.0 / scale - round(1.0 / scale)) < 1e-6
        interp = cv2.INTER_CUBIC if scale > 1.0 else cv2.INTER_AREA if integer else cv2.INTER_LINEAR
        small = sub if scale == 1.0 else cv2.resize(sub, None, fx=scale, fy=scale, interpolation=interp)
        cc, ci, mc, mi = self._detector(window).detectBoard(small)
        n_markers = 0 if mi is None else int(len(np.ravel(mi)))
        if cc is None or ci is None or len(np.ravel(ci)) == 0:
            return None, None, n_markers, mc
        off = np.array([x0, y0], np.float64)
        # Pixel centres sit at integers in both images: full = (small + 0.5) / s - 0.5.
        corners = (np.asarray(cc, np.float64).reshape(-1, 2) + 0.5) / scale - 0.5 + off
        mcs = [(np.asarray(m, np.float64).reshape(-1, 2) + 0.5) / scale - 0.5 + off for m in mc]
        return np.asarray(ci).reshape(-1).astype(np.int32), corners, n_markers, mcs

    def detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """Board corners in a grey frame (H, W) uint8: (ids (N,), corners (N, 2) px, markers found).

        Tries, in order until one finds about as many corners as the previous frame: the
        tracked region, the whole reduced image, the whole image at full resolution.
        """
        H, W = gray.shape
        scale = _quantize_scale(min(1.0, self.cfg.max_side / max(H, W)), up=False)
        if self._scale_hint is not None:
            scale = _quantize_scale(self._scale_hint, up=True)
        # The cheap guess first (tracked region, one threshold window), then OpenCV's defaults.
        attempts = ([(self._roi, scale, self._window)] if self.cfg.track and self._roi is not None else [])
        attempts += [(None, scale, None)] + ([(None, 1.0, None)] if scale < 1.0 else [])
        best, used_scale = (None, None, 0, None), 1.0
        for roi, s, win in attempts:
            got = self._detect_in(gray, roi, s, win)
            if got[0] is not None and (best[0] is None or len(got[0]) > len(best[0])):
                best, used_scale = got, s
            elif best[0] is None:
                best = (None, None, max(best[2], got[2]), None)
            if best[0] is not None and len(best[0]) >= 0.8 * self._last_n:
                break
        roi = self._roi if best[3] is None else _region(best[1], best[3], (W, H))
        small = roi is not None and self._small_markers(best[2], best[3])
        if small:
            for s in self.cfg.upsample:
                if (roi[2] - roi[0]) * (roi[3] - roi[1]) * s * s > max(H * W, 1280 * 960):
                    break   # a board this large is not imaged too small; bounds the cost
                got = self._detect_in(gray, roi, s)
                if got[0] is not None and (best[0] is None or len(got[0]) > len(best[0])):
                    best, used_scale = got, s
        ids, corners, n_markers, mcs = best
        if ids is None:
            self.reset()
            return np.zeros(0, np.int32), np.zeros((0, 2)), n_markers
        if self.cfg.refine and used_scale < 1.0:
            # detectBoard refined them in the reduced image; sharpen them at full resolution.
            corners = self._refine(gray, corners, mcs, used_scale)
        if self.cfg.saddle and len(ids) >= 4:
            margins = corner_margins_px(self.board, ids, corners)
            half = np.clip(np.floor(self.cfg.saddle_frac * margins), 2, self.cfg.saddle_max).astype(np.int64)
            corners, _ = refine_saddles(gray, corners, half, self.cfg.saddle_blur)
            if small or np.median(margins) < self.cfg.xjunction_below:
                # Narrow white margins (low resolution, far or grazing views) leave the saddle
                # window 2-4 px (corners 0.03 px off at 640x480, up to 1.8 px at grazing
                # views); the X-junction fit reads the squares' edges instead (0.015 px). In
                # the enlarged search's frames a corner it cannot fit is dropped, not guessed.
                fit, fitted = refine_xjunctions(gray, self.board, ids, corners)
                ids, corners = (ids[fitted], fit[fitted]) if small else (ids, fit)
                if not len(ids):
                    self.reset()
                    return np.zeros(0, np.int32), np.zeros((0, 2)), n_markers
        self._last_n = len(ids)
        # Next frame: the smallest scale that keeps ``px_per_bit`` on all but the smallest
        # quarter of the markers, and a threshold window of ~0.4 marker side at that scale.
        sides = [np.linalg.norm(np.diff(np.vstack([m, m[:1]]), axis=0), axis=1).min() for m in mcs]
        self._scale_hint = self._window = None
        if sides:
            bits = self._cv_board.getDictionary().markerSize + 2
            side = max(float(np.percentile(sides, 25)), 1.0)
            self._scale_hint = float(np.clip(self.cfg.px_per_bit * bits / side, 0.25, 1.0))
            s = _quantize_scale(self._scale_hint, up=True)
            self._window = int(np.clip(0.4 * np.median(sides) * s, 5, 23)) | 1
        self._roi = _region(corners, mcs, (W, H))
        return ids, corners, n_markers

    def _small_markers(self, n_markers: int, marker_corners) -> bool:
        """Were markers missed because they are imaged too small to read (far or grazing
        views: a few px per bit)? Then an enlarged image finds them (bilinear/bicubic
        interpolation lets the adaptive threshold and the bit sampling resolve them)."""
        if not self.cfg.upsample or n_markers >= len(self._cv_board.getIds()):
            return False
        if not marker_corners:
            return True    # none read at all, in the region where the board last was
        bits = self._cv_board.getDictionary().markerSize + 2
        sides = [np.linalg.norm(np.diff(np.vstack([m, m[:1]]), axis=0), axis=1).min() for m in marker_corners]
        return float(np.median(sides)) / bits < self.cfg.upsample_below

    def _refine(self, gray: np.ndarray, corners: np.ndarray, marker_corners, scale: float) -> np.ndarray:
        """cornerSubPix at full resolution, with a window that stays inside the white margin
        between the saddle point and the nearest marker edge."""
        side = np.median([np.linalg.norm(np.diff(np.vstack([m, m[:1]]), axis=0), axis=1).mean()
                          for m in marker_corners]) if marker_corners else 0.0
        margin_px = side * (self.board.square_length - self.board.marker_length) / (2 * self.board.marker_length)
        half = int(np.clip(math.floor(self.cfg.win_frac * margin_px), 2, self.cfg.win_max))
        pts = corners.astype(np.float32).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.005)
        refined = cv2.cornerSubPix(gray, pts.copy(), (half, half), (-1, -1), crit).reshape(-1, 2)
        # A corner that wanders farther than the reduced image's pixel was pulled off by clutter.
        moved = np.linalg.norm(refined - corners, axis=1)
        max_move = max(1.5, 1.0 / scale)
        return np.where((moved < max_move)[:, None], refined.astype(np.float64), corners)


def _region(corners: np.ndarray, marker_corners, size: tuple[int, int]) -> tuple[int, int, int, int]:
    """The board's region (x0, y0, x1, y1) px around found corners (N, 2) and marker corners, padded."""
    pts = np.concatenate([corners.reshape(-1, 2)] + [np.reshape(m, (-1, 2)) for m in marker_corners or []])
    lo, hi = pts.min(0), pts.max(0)
    pad = 0.25 * (hi - lo) + 24
    return (int(max(0, lo[0] - pad[0])), int(max(0, lo[1] - pad[1])),
            int(min(size[0], hi[0] + pad[0] + 1)), int(min(size[1], hi[1] + pad[1] + 1)))


def detect_frames(frames, board: BoardSpec, cfg: DetectorConfig = DetectorConfig(),
                  tick: Callable[[], None] | None = None) -> list[Detection]:
    """Detect the board in an iterable of :class:`~..capture.footage.FootageFrame` (grey or RGB), in order (tracking)."""
    det = BoardDetector(board, cfg)
    out = []
    for f in frames:
        gray = to_gray8(f.image)
        ids, corners, n_markers = det.detect(gray)
        out.append(Detection(f.index, f.time, f.name, ids, corners, n_markers, sharpness(gray)))
        if tick is not None:
            tick()
    return out


@dataclass(frozen=True)
class _Segment:
    source: FootageSource
    indices: tuple[int, ...]
    board: BoardSpec
    cfg: DetectorConfig


def _detect_segment(seg: _Segment) -> list[Detection]:
    """Worker: decode and detect one contiguous segment (runs in a spawned process)."""
    seg.source.single_thread = True
    return detect_frames(prefetched(seg.source.read(seg.indices, gray=True)), seg.board, seg.cfg, report)


def detect_footage(source: FootageSource, indices: Sequence[int], board: BoardSpec,
                   cfg: DetectorConfig = DetectorConfig(), workers: int = 1,
                   tick: Callable[[int], None] | None = None) -> list[Detection]:
    """Detect the board in frames ``indices`` of ``source``; ``workers`` > 1 splits the footage
    into that many contiguous segments, each decoded and detected in its own spawned process
    (one decoding thread each). In one process, PyAV's decoding threads run ahead of detection."""
    indices = list(indices)
    # A spawned worker costs about a second to start: only worth it on longer footage.
    workers = max(1, min(workers, len(indices) // 60 or 1))
    if workers == 1:
        return detect_frames(prefetched(source.read(indices, gray=True)), board, cfg,
                             (lambda: tick(1)) if tick else None)
    segments = [_Segment(source, c, board, cfg) for c in split(indices, workers)]
    results = map_spawned(_detect_segment, segments, workers, tick)
    return [d for r in results for d in r]


# The smallest dictionary of each family: larger ones of a family begin with the same markers,
# and boards number their markers from 0, so these name the family quickly.
# (APRILTAG_36h10, slow to decode and rarely printed, is not probed.)
_PROBE_DICTIONARIES = ("DICT_4X4_50", "DICT_5X5_50", "DICT_6X6_50", "DICT_7X7_50",
                       "DICT_ARUCO_ORIGINAL", "DICT_ARUCO_MIP_36h12", "DICT_APRILTAG_16h5",
                       "DICT_APRILTAG_25h9", "DICT_APRILTAG_36h11")


def _family(name: str) -> str:
    parts = name.split("_")
    return "_".join(parts[:2]) if parts[2:] and parts[-1].isdigit() else name


def diagnose_no_board(frames: Sequence[np.ndarray], board: BoardSpec) -> str:
    """Why no board was found in grey ``frames``: which dictionary's markers they show instead."""
    params = cv2.aruco.DetectorParameters()
    small = [g if max(g.shape) <= 960 else cv2.resize(g, None, fx=960 / max(g.shape), fy=960 / max(g.shape),
                                                      interpolation=cv2.INTER_AREA) for g in frames]
    own = board.dictionary
    names = [own] + [n for n in _PROBE_DICTIONARIES if _family(n) != _family(own)]
    counts: dict[str, int] = {}
    for name in names:
        det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)), params)
        counts[name] = sum(len(ids) for ids in (det.detectMarkers(g)[1] for g in small) if ids is not None)
    best = max(names[1:], key=lambda n: counts[n], default=own)
    if counts[own] > 0 and counts[best] <= counts[own]:
        return (f"{own} markers were found but no corners of a {board.squares_x}x"
                f"{board.squares_y} board: check squares_x, squares_y and legacy_pattern in board.json")
    if counts.get(best, 0) > 0:
        sized = f"{_family(best)}_* (e.g. {best})" if _family(best) != best else best
        return (f"the board's dictionary does not match: board.json says {own} but the frames "
                f"show {sized} markers ({counts[best]} found)")
    return "no ArUco markers of any dictionary were found (is the board in view and in focus?)"


def detect_sampled(source: FootageSource, board: BoardSpec, fps: float | None = None,
                   det_cfg: DetectorConfig = DetectorConfig(), workers: int = 1,
                   tick: Callable[[int], None] | None = None,
                   total: Callable[[int], None] | None = None) -> list[Detection]:
    """Detections in the frames of ``source`` resampled to ``fps``.

    Raises :class:`DbbError` when no frame shows the board, naming the dictionary seen instead.
    """
    from ..capture.footage import sample_indices

    idx = sample_indices(source.info.times, fps)
    if total:
        total(len(idx))
    dets = detect_footage(source, idx, board, det_cfg, workers, tick)
    if not any(d.n_corners for d in dets):
        probe = [f.image for f in source.read(idx[np.linspace(0, len(idx) - 1, min(3, len(idx))).astype(int)],
                                              gray=True)]
        raise DbbError(f"no ChArUco board found in any of {len(dets)} frames of {source.info.path}: "
                       + diagnose_no_board(probe, board))
    return dets
