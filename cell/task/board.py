"""The ChArUco calibration board (task `calibration.board`, `cell calibrate hand-eye`): its
squares, markers, ArUco dictionary and pose in the cell, as OpenCV's cv2.aruco.CharucoBoard.

The board frame is OpenCV's: origin at the printed image's top-left corner, x along its columns
(squares_x squares), y down its rows (squares_y), z into the board, so a board lying face up has
z pointing down. The task gives the pose of the board's centre in that orientation:
T_cell_board = T_cell_centre @ translate(-width / 2, -height / 2, 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from cell.core import geometry

# the predefined ArUco dictionaries: name -> markers in it (cv2.aruco.DICT_* by the same name)
DICTIONARIES = {f"DICT_{bits}X{bits}_{n}": n for bits in (4, 5, 6, 7) for n in (50, 100, 250, 1000)}
DICTIONARIES["DICT_ARUCO_ORIGINAL"] = 1024


@dataclass(frozen=True)
class Board:
    squares: tuple[int, int]        # (squares_x, squares_y)
    square_m: float                 # a chessboard square's side
    marker_m: float                 # an ArUco marker's side, inside a white square
    dictionary: str                 # a DICTIONARIES name
    T_cell_centre: np.ndarray       # the board's centre in the cell, board-frame axes

    @property
    def size_m(self) -> np.ndarray:
        """(width along x, height along y) of the squares [m]."""
        return self.square_m * np.array(self.squares, float)

    @property
    def T_cell_board(self) -> np.ndarray:
        """The board frame (OpenCV's origin, top-left corner) in the cell."""
        return self.T_cell_centre @ geometry.transform(translation=(*(-self.size_m / 2), 0.0))

    @property
    def markers(self) -> int:
        """Markers on the board: one in every other square."""
        return self.squares[0] * self.squares[1] // 2

    def charuco(self) -> Any:
        """The cv2.aruco.CharucoBoard (OpenCV's default pattern: no setLegacyPattern)."""
        import cv2
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(tuple(self.squares), self.square_m, self.marker_m, dictionary)

    def image(self, px_per_square: int) -> np.ndarray:
        """The printed board (squares_y * px, squares_x * px) uint8, 255 white: each square exactly
        px_per_square pixels, no margin, so pixel (i, j) covers board x in [j, j + 1) * square /
        px_per_square, y likewise."""
        width, height = (n * px_per_square for n in self.squares)
        return self.charuco().generateImage((width, height), marginSize=0, borderBits=1)
