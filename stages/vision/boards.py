"""Calibration boards: parsing a board spec, detecting it in an image, drawing it.

Board specs (the ``--board`` option)::

    chessboard:COLSxROWS:SQUARE_M                 COLS×ROWS *inner* corners, square side in metres
    charuco:SXxSY:SQUARE_M:MARKER_M:DICT          SX×SY squares, ArUco dictionary name (DICT_6X6_250)

The board frame (used by ``calib/board_poses.json``, see stages/steps/calibrate.py):

- chessboard: origin at the first inner corner OpenCV reports, x along a row of
  COLS corners, y along the ROWS direction, z = 0 on the board (z points into the
  board for a right-handed frame).  Inner corner (i, j) sits at (i·s, j·s, 0);
  the printed board spans x ∈ [−s, COLS·s], y ∈ [−s, ROWS·s].
- charuco: OpenCV's CharucoBoard frame: origin at the outer corner of the board,
  corner id k at ``board.getChessboardCorners()[k]`` = ((k mod (SX−1) + 1)·s,
  (k div (SX−1) + 1)·s, 0); the board spans [0, SX·s] × [0, SY·s].

Known board poses (``CAPTURE/calib/board_poses.json``, written by ``rsl synth``, read by
``rsl calibrate``; build it with :func:`board_poses_json`)::

    {"board": "chessboard:9x6:0.025",
     "poses": {"VIEW": [tx, ty, tz, qw, qx, qy, qz], ...}}

Each pose maps the board frame above into the world, p_world = R(q) p_board + t (the
same pose convention as controls.json); VIEW is the image stem in calib/CAM/VIEW.png.
An optional ``"origin": "center"`` says the poses are of the *centred* board frame instead
(corner (i, j) at ((i − (COLS−1)/2)·s, (j − (ROWS−1)/2)·s, 0), as stages/synth_views.py
builds it); the default ``"origin": "first_corner"`` is the frame above.
When the file exists, the calibrated cameras are expressed in that world.

A chessboard with an even × odd corner grid looks the same after a half turn, so its
detected corner order can flip between views; use ChArUco for multi-camera rigs where
the board is seen from very different directions.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import cv2
import numpy as np

from stages.errors import RslError

_CHESS_RE = re.compile(r"^chessboard:(\d+)x(\d+):([0-9.eE+-]+)$")
_CHARUCO_RE = re.compile(r"^charuco:(\d+)x(\d+):([0-9.eE+-]+):([0-9.eE+-]+):(DICT_\w+)$")


@dataclass(frozen=True)
class Board:
    """A planar calibration target."""

    kind: str  # "chessboard" | "charuco"
    cols: int  # chessboard: inner corners per row; charuco: squares along x
    rows: int  # chessboard: inner corners per column; charuco: squares along y
    square_m: float
    marker_m: float = 0.0  # charuco only
    dictionary: str = ""  # charuco only

    @property
    def spec(self) -> str:
        if self.kind == "chessboard":
            return f"chessboard:{self.cols}x{self.rows}:{self.square_m:g}"
        return f"charuco:{self.cols}x{self.rows}:{self.square_m:g}:{self.marker_m:g}:{self.dictionary}"

    @property
    def object_points(self) -> np.ndarray:
        """All corners in the board frame, (N, 3) metres; row k is corner id k."""
        if self.kind == "chessboard":
            j, i = np.mgrid[0:self.rows, 0:self.cols]
            return np.stack([i.ravel() * self.square_m, j.ravel() * self.square_m,
                             np.zeros(i.size)], axis=1).astype(np.float64)
        return np.asarray(self._cv_board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1) of the printed board in the board frame, metres."""
        s = self.square_m
        if self.kind == "chessboard":
            return (-s, -s, self.cols * s, self.rows * s)
        return (0.0, 0.0, self.cols * s, self.rows * s)

    def _cv_board(self):
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, d)


def parse_board(spec: str) -> Board:
    """Parse a board spec (module doc); a malformed one raises RslError naming the spec."""
    s = spec.strip()
    m = _CHESS_RE.match(s)
    if m:
        cols, rows, sq = int(m[1]), int(m[2]), float(m[3])
        if cols < 2 or rows < 2 or sq <= 0:
            raise RslError(f"--board '{spec}': a chessboard needs at least 2x2 inner corners and a positive "
                           "square size in metres.")
        return Board("chessboard", cols, rows, sq)
    m = _CHARUCO_RE.match(s)
    if m:
        cols, rows, sq, mk, dic = int(m[1]), int(m[2]), float(m[3]), float(m[4]), m[5]
        if not hasattr(cv2.aruco, dic):
            raise RslError(f"--board '{spec}': unknown ArUco dictionary '{dic}' (e.g. DICT_6X6_250).")
        if cols < 3 or rows < 3 or sq <= 0 or not 0 < mk < sq:
            raise RslError(f"--board '{spec}': a ChArUco board needs at least 3x3 squares and "
                           "0 < marker size < square size (metres).")
        return Board("charuco", cols, rows, sq, mk, dic)
    raise RslError(f"--board '{spec}': expected chessboard:COLSxROWS:SQUARE_M or "
                   "charuco:SXxSY:SQUARE_M:MARKER_M:DICT (e.g. chessboard:9x6:0.025).")


@dataclass
class Detection:
    """Corners of a board found in one image."""

    ids: np.ndarray  # (k,) corner ids into Board.object_points
    image_points: np.ndarray  # (k, 2) pixels, sub-pixel refined


def to_gray(image: np.ndarray) -> np.ndarray:
    """RGB or gray uint8 -> gray uint8 (H, W)."""
    img = np.asarray(image)
    if img.ndim == 3:
        return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    return img


def detect(board: Board, image: np.ndarray, min_corners: int = 6, subpix_window: int | None = None
           ) -> Detection | None:
    """Find the board's corners in an RGB or gray image (None when not found).

    Chessboard: ``findChessboardCorners`` (adaptive threshold, normalise) and ``cornerSubPix``
    with half-window ``subpix_window`` (None: 11 as OpenCV's calibration sample, smaller when
    squares are under 25 px, where a window reaching the next corners biases the estimate);
    all corners are required.
    ChArUco: ``CharucoDetector.detectBoard``; at least ``min_corners`` corners.
    """
    gray = to_gray(image)
    if board.kind == "chessboard":
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        ok, corners = cv2.findChessboardCorners(gray, (board.cols, board.rows), flags=flags)
        if not ok or corners is None:
            return None
        corners = np.ascontiguousarray(corners.reshape(-1, 1, 2).astype(np.float32))
        grid = corners.reshape(board.rows, board.cols, 2)
        spacing = min(np.linalg.norm(np.diff(grid, axis=0), axis=2).min(),
                      np.linalg.norm(np.diff(grid, axis=1), axis=2).min())
        win = int(max(2, min(11, np.floor(0.45 * spacing)))) if subpix_window is None else int(subpix_window)
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01)
        corners = cv2.cornerSubPix(gray, corners, (win, win), (-1, -1), crit)
        return Detection(np.arange(board.cols * board.rows), corners.reshape(-1, 2).astype(np.float64))
    det = cv2.aruco.CharucoDetector(board._cv_board())
    cc, ci, _, _ = det.detectBoard(gray)
    if ci is None or len(ci) < max(min_corners, 4):
        return None
    ids = np.asarray(ci, dtype=np.int64).ravel()
    pts = np.asarray(cc, dtype=np.float64).reshape(-1, 2)
    obj = board.object_points[ids]
    # Collinear corners give no homography: need a spread in both board directions.
    if np.linalg.matrix_rank(obj[:, :2] - obj[:, :2].mean(0), tol=1e-9) < 2:
        return None
    return Detection(ids, pts)


def board_texture(board: Board, px_per_square: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A printable image of the board (gray uint8, with a one-square white margin) and the 3×3
    matrix A mapping texture pixel centres (u, v, 1) (OpenCV: integer = centre) to board (x, y, 1)."""
    s = board.square_m
    p = int(px_per_square)
    if board.kind == "chessboard":
        nx, ny = board.cols + 1, board.rows + 1  # squares
        img = np.full(((ny + 2) * p, (nx + 2) * p), 255, np.uint8)
        for j in range(ny):
            for i in range(nx):
                if (i + j) % 2 == 0:
                    img[(j + 1) * p:(j + 2) * p, (i + 1) * p:(i + 2) * p] = 0
        # pixel centre (u, v) -> board: x = ((u + ½) / p − 2) s; the first inner corner is the
        # edge between pixels 2p − 1 and 2p
        A = np.array([[s / p, 0, s / (2 * p) - 2 * s], [0, s / p, s / (2 * p) - 2 * s], [0, 0, 1.0]])
        return img, A
    img = None
    for k in (1, 2, 3, 4):  # OpenCV 5.0 rejects some exact sizes (a rounding bug); render larger and shrink
        try:
            img = board._cv_board().generateImage((board.cols * p * k, board.rows * p * k), marginSize=0,
                                                  borderBits=1)
            break
        except cv2.error:
            continue
    if img is None:
        raise RslError(f"cannot draw board {board.spec} at {p} px per square.")
    img = cv2.resize(img, (board.cols * p, board.rows * p), interpolation=cv2.INTER_AREA)
    img = cv2.copyMakeBorder(img, p, p, p, p, cv2.BORDER_CONSTANT, value=255)
    A = np.array([[s / p, 0, s / (2 * p) - s], [0, s / p, s / (2 * p) - s], [0, 0, 1.0]])
    return np.asarray(img, np.uint8), A


def render_board(board: Board, K: np.ndarray, R: np.ndarray, t: np.ndarray, size: tuple[int, int],
                 background: np.ndarray | int = 128, px_per_square: int = 64, supersample: int = 3
                 ) -> np.ndarray:
    """Pinhole picture (gray uint8 (H, W), no distortion) of the board at pose board→camera (R, t):
    homography H = K [r1 r2 t] A from texture pixels to image pixels, drawn ``supersample``
    times larger (x_big = s·x + (s−1)/2) and area-averaged down, against aliasing."""
    w, h = size
    ss = int(supersample)
    tex, A = board_texture(board, px_per_square)
    S = np.array([[ss, 0, (ss - 1) / 2], [0, ss, (ss - 1) / 2], [0, 0, 1.0]])
    H = S @ np.asarray(K) @ np.column_stack([R[:, 0], R[:, 1], np.reshape(t, 3)]) @ A
    big = (w * ss, h * ss)
    warped = cv2.warpPerspective(tex, H, big, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                 borderValue=0).astype(np.float64)
    cover = cv2.warpPerspective(np.full(tex.shape, 255, np.uint8), H, big, flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=0).astype(np.float64) / 255
    if ss > 1:
        warped = cv2.resize(warped * cover, (w, h), interpolation=cv2.INTER_AREA)
        cover = cv2.resize(cover, (w, h), interpolation=cv2.INTER_AREA)
    else:
        warped = warped * cover
    bg = np.broadcast_to(np.asarray(background, dtype=np.float64), (h, w))
    return np.clip(np.round(warped + (1 - cover) * bg), 0, 255).astype(np.uint8)


def center_offset(board: Board) -> np.ndarray:
    """Board-frame position (3,) of the centre of the corner grid (the centred frame's origin)."""
    p = board.object_points
    return 0.5 * (p.min(0) + p.max(0))


def board_poses_json(board: Board, poses: dict[str, np.ndarray], origin: str = "first_corner") -> dict:
    """The JSON object of calib/board_poses.json: view name -> pose [tx,ty,tz,qw,qx,qy,qz]
    of the board in the world (p_world = R(q) p_board + t)."""
    out = {}
    for name, pose in poses.items():
        pose = np.asarray(pose, dtype=np.float64).ravel()
        if pose.shape != (7,):
            raise ValueError(f"pose of view {name!r} should be [tx,ty,tz,qw,qx,qy,qz]")
        out[str(name)] = [float(v) for v in pose]
    return {"board": board.spec, "origin": origin, "poses": out}
