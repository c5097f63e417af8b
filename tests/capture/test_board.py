"""board.json: round trip and clear errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dbb_capture.capture.board import BoardSpec
from dbb_capture.core.errors import DbbError


def test_board_json_round_trip(tmp_path):
    spec = BoardSpec(7, 5, 0.04, 0.03, "DICT_5X5_100")
    p = tmp_path / "board.json"
    p.write_text(json.dumps(spec.to_json()))
    assert BoardSpec.load(p) == spec
    assert spec.chessboard_corners().shape == (6 * 4, 3)
    assert np.allclose(spec.chessboard_corners()[0], [0.04, 0.04, 0])
    assert spec.render(20).shape == (100, 140)


@pytest.mark.parametrize("d, words", [
    ({"squares_x": 7, "squares_y": 5, "square_length": 0.04, "marker_length": 0.03,
      "dictionary": "DICT_NOPE"}, "unknown dictionary"),
    ({"squares_x": 7, "squares_y": 5, "square_length": 0.04, "marker_length": 0.05,
      "dictionary": "DICT_4X4_50"}, "smaller than"),
    ({"squares_x": 7, "square_length": 0.04, "marker_length": 0.03,
      "dictionary": "DICT_4X4_50"}, "squares_y"),
    ({"squares_x": 20, "squares_y": 20, "square_length": 0.04, "marker_length": 0.03,
      "dictionary": "DICT_4X4_50"}, "too few markers"),
])
def test_bad_board_json_says_why(tmp_path, d, words):
    p = tmp_path / "board.json"
    p.write_text(json.dumps(d))
    with pytest.raises(DbbError, match=words):
        BoardSpec.load(p)


def test_board_json_not_json(tmp_path):
    p = tmp_path / "board.json"
    p.write_text("{squares_x: 7")
    with pytest.raises(DbbError, match="not valid JSON"):
        BoardSpec.load(p)
