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
        if not 0 < self.marker_length < self.square_length:
            raise DbbError(
                f"board: marker_length ({self.marker_length}) must be positive and smaller than "
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
        try:
            return cls(int(d["squares_x"]), int(d["squares_y"]), float(d["square_length"]),
                       float(d["marker_length"]), str(d["dictionary"]),
                       bool(d.get("legacy_pattern", False)))
        except (KeyError, TypeError, ValueError) as e:
            raise DbbError(f"{source}: missing or invalid board field ({e})") from None

    @classmethod
    def load(cls, path: Path) -> "BoardSpec":
        from ..core.outputs import read_json

        d = read_json(path, "board file")
        if not isinstance(d, dict):
            raise DbbError(f"{path}: expected a JSON object describing the board")
        return cls.from_json(d, str(path))

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
