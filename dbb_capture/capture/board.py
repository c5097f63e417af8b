"""The ChArUco board: ``board.json`` <-> :class:`BoardSpec` <-> OpenCV ``CharucoBoard``.

The board frame is the capture's world frame, exactly as OpenCV defines it: origin at the
board's outer top-left corner, x along squares_x, y along squares_y, z = x cross y, board
plane z = 0, metres.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..core.errors import DbbError
from ..core.fields import entry, flag, number, text

MAX_SQUARE_M = 1.0      # a board square larger than this is a unit mistake (lengths are metres)
MAX_SQUARES = 200       # squares along a side: more than any ArUco dictionary has markers for


def aruco_dictionary_names() -> list[str]:
    """All predefined ArUco/AprilTag dictionary names OpenCV knows (``DICT_...``)."""
    import cv2

    return sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board as written in ``board.json`` (lengths in metres)."""

    squares_x: int
    squares_y: int
    square_length: float
    marker_length: float
    dictionary: str
    legacy_pattern: bool = False

    def __post_init__(self) -> None:
        if self.squares_x < 2 or self.squares_y < 2:
            raise DbbError(f"board: needs at least 2x2 squares, got {self.squares_x}x{self.squares_y}")
        # Each length is blamed for itself: a bad square_length is not the marker's fault.
        if not 0 < self.square_length <= MAX_SQUARE_M:
            raise DbbError(f"board: square_length ({self.square_length}) must be positive and at most "
                           f"{MAX_SQUARE_M:g} m (lengths are metres)")
        if not 0 < self.marker_length:
            raise DbbError(f"board: marker_length ({self.marker_length}) must be positive")
        if not self.marker_length < self.square_length:
            raise DbbError(f"board: marker_length ({self.marker_length}) must be smaller than "
                           f"square_length ({self.square_length})")
        if self.dictionary not in aruco_dictionary_names():
            raise DbbError(f"board: unknown dictionary {self.dictionary!r} "
                           f"(expected one of DICT_4X4_50 ... DICT_APRILTAG_36h11)")
        n_markers = (self.squares_x * self.squares_y) // 2
        if n_markers > self.cv_dictionary().bytesList.shape[0]:
            raise DbbError(f"board: {self.dictionary} has too few markers for a "
                           f"{self.squares_x}x{self.squares_y} board ({n_markers} needed)")

    # ---- files
    @classmethod
    def from_json(cls, d: dict, source: str = "board.json") -> "BoardSpec":
        """The board of ``board.json`` content ``d``; each entry checked on its own (type, range),
        so the message names the entry that is wrong."""
        def length(name: str) -> float:
            return number(entry(d, name, source), name, source, low=0, low_open=True,
                          high=MAX_SQUARE_M, unit=" m")

        sx, sy = (number(entry(d, n, source), n, source, low=2, high=MAX_SQUARES, integer=True)
                  for n in ("squares_x", "squares_y"))
        square, marker = length("square_length"), length("marker_length")
        if not marker < square:
            raise DbbError(f"{source}: marker_length {marker:g} m must be smaller than square_length {square:g} m")
        return cls(int(sx), int(sy), square, marker, text(entry(d, "dictionary", source), "dictionary", source),
                   flag(entry(d, "legacy_pattern", source, False), "legacy_pattern", source))

    @classmethod
    def load(cls, path: Path) -> "BoardSpec":
        from ..core.outputs import read_json

        d = read_json(path, "board file")
        if not isinstance(d, dict):
            raise DbbError(f"{path}: expected a JSON object describing the board")
        try:
            return cls.from_json(d, str(path))
        except DbbError as e:
            msg = str(e)
            raise type(e)(msg if msg.startswith(str(path)) else f"{path}: {msg.removeprefix('board: ')}") from None

    def to_json(self) -> dict:
        return asdict(self)

    # ---- geometry
    @property
    def size_m(self) -> tuple[float, float]:
        """Board extent (x, y) in metres."""
        return self.squares_x * self.square_length, self.squares_y * self.square_length

    @property
    def center(self) -> np.ndarray:
        """Board centre in the board frame (3,)."""
        w, h = self.size_m
        return np.array([w / 2, h / 2, 0.0])

    def chessboard_corners(self) -> np.ndarray:
        """Inner chessboard corners (N, 3) in the board frame, indexed by ChArUco id."""
        return np.asarray(self.cv_board().getChessboardCorners(), np.float64).reshape(-1, 3)

    # ---- OpenCV objects
    def cv_dictionary(self):
        import cv2

        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))

    def cv_board(self):
        import cv2

        board = cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_length,
                                       self.marker_length, self.cv_dictionary())
        board.setLegacyPattern(self.legacy_pattern)
        return board

    def render(self, px_per_square: int) -> np.ndarray:
        """Board image (H, W) uint8 with no margin: pixel edges coincide with the board edges."""
        w = self.squares_x * px_per_square
        h = self.squares_y * px_per_square
        return self.cv_board().generateImage((w, h), marginSize=0, borderBits=1)
