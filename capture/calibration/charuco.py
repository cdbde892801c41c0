"""The one adapter between mifacerf and OpenCV's ChArUco API (``cv2.aruco``, contrib).

OpenCV changed this API repeatedly (4.6: even-row boards; 4.7: ``CharucoDetector``
and ``calibrateCameraCharuco`` gone from the Python bindings; ``setLegacyPattern``
for boards printed before 4.6). Everything ChArUco goes through here; calibration
itself uses ``cv2.calibrateCamera`` on matched object/image points, which exists in
every version.

Board frame (OpenCV's): origin at the board's top-left corner as printed, +x along
the rows (right), +y down the columns, +z into the board (away from a viewer facing
the print); metres. Chessboard (inner) corner ``i`` sits at
``((i % (nx-1) + 1) * square, (i // (nx-1) + 1) * square, 0)``.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from ...errors import MifacerfError


class CharucoError(MifacerfError, RuntimeError):
    """The ChArUco board or its detection failed (the message says which and why)."""


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board: ``squares_x`` x ``squares_y`` squares of ``square`` metres with ArUco
    markers of ``marker`` metres from ``dictionary``; ``legacy`` for boards made by OpenCV < 4.6
    with an even number of rows."""

    squares_x: int = 7
    squares_y: int = 5
    square: float = 0.03
    marker: float = 0.022
    dictionary: str = "DICT_4X4_50"
    legacy: bool = False

    def __post_init__(self):
        if self.squares_x < 2 or self.squares_y < 2:
            raise ValueError("a ChArUco board needs at least 2 x 2 squares")
        if not 0 < self.marker < self.square:
            raise ValueError(f"marker size {self.marker} must be positive and smaller than the square {self.square}")

    @property
    def size(self) -> tuple[float, float]:
        """(width, height) of the board in metres."""
        return self.squares_x * self.square, self.squares_y * self.square

    @property
    def n_corners(self) -> int:
        return (self.squares_x - 1) * (self.squares_y - 1)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "BoardSpec":
        return cls(**d)

    # -------------------------------------------------------------- OpenCV
    def cv_board(self):
        cv2 = _aruco()
        try:
            dict_id = getattr(cv2.aruco, self.dictionary)
        except AttributeError:
            raise CharucoError(f"unknown ArUco dictionary {self.dictionary!r}") from None
        dictionary = cv2.aruco.getPredefinedDictionary(dict_id)
        board = cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square, self.marker, dictionary)
        if self.legacy and hasattr(board, "setLegacyPattern"):
            board.setLegacyPattern(True)
        return board

    def image(self, px_per_square: int = 100) -> np.ndarray:
        """The printable board, uint8 (H, W), exactly ``squares * px_per_square`` pixels, no margin."""
        w, h = self.squares_x * px_per_square, self.squares_y * px_per_square
        return self.cv_board().generateImage((w, h), marginSize=0, borderBits=1)

    def corners(self) -> np.ndarray:
        """Object points of every chessboard corner (n_corners, 3), board frame, metres."""
        return np.asarray(self.cv_board().getChessboardCorners(), np.float64).reshape(-1, 3)


@dataclass
class Detection:
    """Corners found in one image: ``ids`` (N,), pixel positions ``image_points`` (N, 2),
    board-frame ``object_points`` (N, 3)."""

    ids: np.ndarray
    image_points: np.ndarray
    object_points: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


def _aruco():
    import cv2

    if not hasattr(cv2, "aruco") or not hasattr(cv2.aruco, "CharucoBoard"):
        raise CharucoError("OpenCV without the aruco contrib module: pip install opencv-contrib-python-headless")
    return cv2


def to_gray8(image: np.ndarray) -> np.ndarray:
    """Any image (H, W[, C]) as uint8 grey for detection (float data is taken as linear 0..1 and
    sRGB-encoded; the min..max range is stretched when it is very dark)."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., :3].mean(axis=2) if img.dtype != np.uint8 else img[..., :3].mean(axis=2).astype(np.uint8)
    if img.dtype == np.uint8:
        return img
    g = np.nan_to_num(img.astype(np.float64))
    hi = np.percentile(g, 99.5)
    if hi > 0:
        g = g / hi
    g = np.clip(g, 0, 1)
    g = np.where(g <= 0.0031308, 12.92 * g, 1.055 * g ** (1 / 2.4) - 0.055)
    return (g * 255 + 0.5).astype(np.uint8)


def detect(board: BoardSpec, image: np.ndarray, min_corners: int = 6) -> Detection | None:
    """ChArUco corners in ``image``; None when fewer than ``min_corners`` are found."""
    cv2 = _aruco()
    gray = to_gray8(image)
    cvb = board.cv_board()
    if hasattr(cv2.aruco, "CharucoDetector"):  # OpenCV >= 4.7
        params = cv2.aruco.CharucoParameters()
        if hasattr(params, "minMarkers"):
            params.minMarkers = 1
        dparams = cv2.aruco.DetectorParameters()
        dparams.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        det = cv2.aruco.CharucoDetector(cvb, params, dparams)
        ch_corners, ch_ids, _, _ = det.detectBoard(gray)
    else:  # OpenCV 4.6 and older
        corners, ids, _ = cv2.aruco.detectMarkers(gray, cvb.dictionary)
        if ids is None or len(ids) == 0:
            return None
        _, ch_corners, ch_ids = cv2.aruco.interpolateCornersCharuco(corners, ids, gray, cvb)
    if ch_ids is None or len(ch_ids) < min_corners:
        return None
    ids = np.asarray(ch_ids, np.int64).reshape(-1)
    rows, cols = ids // (board.squares_x - 1), ids % (board.squares_x - 1)
    if len(np.unique(rows)) < 2 or len(np.unique(cols)) < 2:
        return None  # corners on one line: no homography, useless for calibration
    img_pts = np.asarray(ch_corners, np.float64).reshape(-1, 2)
    obj_pts = board.corners()[ids]
    return Detection(ids, img_pts, obj_pts)
