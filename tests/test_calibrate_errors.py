"""Bad input to `rsl calibrate` ends with one clear sentence and a non-zero exit (real CLI)."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from stages.artefacts import Camera, CamerasArtefact
from stages.steps.calibrate import CalibrateConfig, run
from stages.capture import write_cameras_json, write_image
from test_calibrate_board import make_capture


@pytest.fixture
def chess_capture(shared_data, tmp_path):
    src = shared_data / "opencv_samples_chessboard"
    cap = make_capture(tmp_path / "cap", ["left", "right"])
    for side in ("left", "right"):
        d = cap / "calib" / side
        d.mkdir(parents=True)
        for v in ("01", "03", "04", "05"):
            # the right camera's views carry other names: no view is shared
            shutil.copy(src / f"{side}{v}.jpg", d / (f"{v}.jpg" if side == "left" else f"r{v}.jpg"))
    return cap


def test_no_board_found(chess_capture, tmp_path, rsl):
    p = rsl("calibrate", chess_capture, "-w", tmp_path / "ws", "--board", "chessboard:7x5:0.025")
    assert p.returncode != 0
    assert "no chessboard:7x5:0.025 board found in any of the 4 views" in p.stderr
    assert "calib/left" in p.stderr
    assert not (tmp_path / "ws" / "cameras.h5").exists()


def test_camera_without_shared_view(chess_capture, tmp_path, rsl):
    p = rsl("calibrate", chess_capture, "-w", tmp_path / "ws", "--board", "chessboard:9x6:0.025")
    assert p.returncode != 0
    assert "no calibration view shows the board to two cameras at once" in p.stderr
    # with one shared view, the other camera links
    shutil.copy(chess_capture / "calib" / "right" / "r01.jpg", chess_capture / "calib" / "right" / "01.jpg")
    run(CalibrateConfig(chess_capture, tmp_path / "ws", board="chessboard:9x6:0.025"))
    assert CamerasArtefact.load(tmp_path / "ws" / "cameras.h5").method == "chessboard"


def test_mismatched_frame_counts(tmp_path, rsl):
    cap = make_capture(tmp_path / "cap", ["a", "b"])
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    write_cameras_json(cap / "cameras.json", [Camera(n, K, np.zeros(5), np.eye(3), np.array([0, 0, 1.0]), 64, 48)
                                              for n in ("a", "b")])
    for cam, n in (("a", 2), ("b", 3)):
        for i in range(n):
            write_image(cap / "frames" / cam / f"{i:06d}.png", np.zeros((48, 64, 3), np.uint8))
    p = rsl("calibrate", cap, "-w", tmp_path / "ws")
    assert p.returncode != 0
    assert "cameras hold unequal frame counts (a: 2, b: 3)" in p.stderr
