"""The ChArUco calibration board tagloc prints and detects.

A chessboard whose white squares carry ArUco markers: the chessboard corners are located to a
fraction of a pixel, the markers name each corner, so a partly visible or steeply tilted board
still gives identified corners. Both the printed sheet (:mod:`tagloc.io.calibration_board`) and
the detector (:mod:`tagloc.vision.calibration`) build the board from one :class:`BoardSpec`, so
what is printed is what is looked for.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from tagloc.core.errors import InputError

#: ArUco dictionaries a board may use (name -> OpenCV constant).
DICTIONARIES = {
    "4x4_50": cv2.aruco.DICT_4X4_50,
    "5x5_100": cv2.aruco.DICT_5X5_100,
    "6x6_250": cv2.aruco.DICT_6X6_250,
}
_MARKER_BITS = {"4x4_50": 4, "5x5_100": 5, "6x6_250": 6}


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board.

    The default fits an A4 sheet in landscape with margins (220 x 160 mm), and its 14 mm markers
    are 7 cells of 2 mm (5x5 bits plus the one-cell black border), so at 10 px/mm every marker cell
    is a whole number of pixels and the sheet prints without resampling.

    Attributes:
        squares_x, squares_y: chessboard squares across and down (inner corners: one fewer each).
        square_m: side of one chessboard square, metres.
        marker_m: side of the ArUco marker inside a white square, metres (< ``square_m``).
        dictionary: key of :data:`DICTIONARIES`.
    """

    squares_x: int = 11
    squares_y: int = 8
    square_m: float = 0.020
    marker_m: float = 0.014
    dictionary: str = "5x5_100"

    def __post_init__(self) -> None:
        if self.dictionary not in DICTIONARIES:
            raise InputError(f"unknown ArUco dictionary {self.dictionary!r} (choose from {', '.join(DICTIONARIES)})")
        if self.squares_x < 3 or self.squares_y < 3:
            raise InputError(f"a ChArUco board needs at least 3x3 squares, not {self.squares_x}x{self.squares_y}")
        if not 0 < self.marker_m < self.square_m:
            raise InputError(
                f"marker side {self.marker_m} m must be positive and below the square side {self.square_m} m"
            )
        markers = self.squares_x * self.squares_y // 2
        limit = int(self.dictionary.split("_")[1])
        if markers > limit:
            raise InputError(
                f"{self.squares_x}x{self.squares_y} squares need {markers} markers, dictionary has {limit}"
            )

    @property
    def marker_bits(self) -> int:
        """Data bits along one side of a marker (its black border adds one cell each side)."""
        return _MARKER_BITS[self.dictionary]

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the chessboard, metres."""
        return self.squares_x * self.square_m, self.squares_y * self.square_m

    def describe(self) -> str:
        """One line naming the board, as printed on the sheet."""
        return (
            f"ChArUco {self.squares_x}x{self.squares_y} squares of {self.square_m * 1000:g} mm, "
            f"markers {self.marker_m * 1000:g} mm, dictionary {self.dictionary.upper()}"
        )


#: The board ``tagloc calibrate board`` prints by default.
DEFAULT_BOARD = BoardSpec()


def make_board(spec: BoardSpec = DEFAULT_BOARD) -> cv2.aruco.CharucoBoard:
    """The OpenCV board of ``spec``; object points in metres, board z = 0, origin at a corner."""
    dictionary = cv2.aruco.getPredefinedDictionary(DICTIONARIES[spec.dictionary])
    return cv2.aruco.CharucoBoard((spec.squares_x, spec.squares_y), spec.square_m, spec.marker_m, dictionary)


def board_image(spec: BoardSpec, px_per_mm: float) -> np.ndarray:
    """The board drawn at ``px_per_mm`` (uint8, (H, W)), no margin: pixel (0, 0) is the board's corner."""
    w_m, h_m = spec.size_m
    size = (round(w_m * 1000 * px_per_mm), round(h_m * 1000 * px_per_mm))
    return make_board(spec).generateImage(size, marginSize=0, borderBits=1)
