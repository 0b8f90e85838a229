"""`rsl calibrate --sfm`: pycolmap on real photos (slow), and putting SfM in metres (fast)."""
from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest

from stages.artefacts import CamerasArtefact
from stages.steps.calibrate import CalibrateConfig, run
from stages.vision.boards import parse_board, render_board
from stages.vision.geometry import compose, mean_rotation, rotation_angle_deg, rotvec_to_matrix
from stages.vision.sfm import SfmResult, scale_by_board, scale_by_distance
from test_calibrate_board import _synthetic_rig, make_capture


@pytest.mark.slow
def test_sfm_on_opensfm_berlin(shared_data, tmp_path):
    """Three real photos of one phone: every image registers; rotations agree with OpenSfM's
    reference reconstruction within 3° after aligning the two worlds by rotation; the known
    distance fixes the scale."""
    src = shared_data / "opensfm_berlin"
    names = ["p01", "p02", "p03"]
    cap = make_capture(tmp_path / "cap", names)
    for n in names:
        d = cap / "frames" / n
        d.mkdir(parents=True)
        shutil.copy(src / "images" / f"{n[1:]}.jpg", d / "000000.jpg")
    ref = json.loads((src / "reconstruction_example.json").read_text())[0]["shots"]
    R_ref = {n: rotvec_to_matrix(ref[f"{n[1:]}.jpg"]["rotation"]) for n in names}
    c_ref = {n: -R_ref[n].T @ np.asarray(ref[f"{n[1:]}.jpg"]["translation"]) for n in names}
    d01 = float(np.linalg.norm(c_ref["p01"] - c_ref["p02"]))
    config = CalibrateConfig(cap, tmp_path / "ws", sfm=True, known_distance=f"p01:p02:{d01}",
                             sfm_single_camera=True, sfm_max_image_size=1000, sfm_threads=1)
    cams = CamerasArtefact.load(run(config))
    again = CamerasArtefact.load(run(dataclasses.replace(config, workspace=tmp_path / "ws2")))
    # one thread: a repeatable run (with two, thread scheduling changed the matches and the focal by 3–21 %)
    assert [c.K[0, 0] for c in again.cameras] == pytest.approx([c.K[0, 0] for c in cams.cameras], rel=1e-9)
    assert cams.method == "sfm"
    got = {c.name: c for c in cams.cameras}
    assert set(got) == set(names)
    Rw = mean_rotation([R_ref[n].T @ got[n].R for n in names])  # our world -> reference world
    for n in names:
        assert rotation_angle_deg(got[n].R @ Rw.T @ R_ref[n].T) < 3.0
    assert np.linalg.norm(got["p01"].center - got["p02"].center) == pytest.approx(d01, rel=1e-6)
    # the reference focal length (OpenSfM's own estimate from these photos: 0.8697 × 3264 px). Three
    # photos constrain the focal weakly: COLMAP's self-calibration landed 3–10.3 % from it over repeated
    # two-thread runs, once 20.6 % under load (thread scheduling changes the matches), and the repeatable
    # one-thread run lands at 19.6 %: the bound is 25 % (the rotations, the scale and the reprojection are the
    # pipeline's checks; the focal is what three photos give COLMAP)
    assert abs(got["p01"].K[0, 0] / (0.8696658 * 3264) - 1) < 0.25
    assert got["p01"].rms_px < 2.0


def test_scale_by_board_and_distance():
    """SfM cameras known up to a similarity (scale 0.37, rotated, shifted): the board's corner
    spacing brings back metres."""
    board = parse_board("chessboard:8x5:0.03")
    K, cams, poses = _synthetic_rig()
    s_true = 0.37
    Q = rotvec_to_matrix([0.3, -0.2, 0.5])
    q = np.array([0.4, -1.0, 2.0])
    # world' = s Q world + q  ⇒  camera pose (R Qᵀ, s t − R Qᵀ q)
    rec = SfmResult({}, {}, np.zeros((0, 3)), 0.1)
    images = {}
    Rb, tb = poses[0]
    for i, (Kc, R, t) in enumerate(cams):
        name = f"c{i}/frame0"
        rec.poses[name] = (R @ Q.T, s_true * t - R @ Q.T @ q)
        rec.intrinsics[name] = (Kc, np.zeros(5))
        P = compose((R, t), (Rb, tb))
        images[name] = render_board(board, Kc, P[0], P[1], (640, 480), background=90)
    assert scale_by_board(rec, board, images) == pytest.approx(1 / s_true, rel=2e-3)
    c0, c1 = (-R.T @ t for (_, R, t) in cams[:2])
    assert scale_by_distance(rec, "c0/frame0", "c1/frame0", float(np.linalg.norm(c0 - c1))) == \
        pytest.approx(1 / s_true, rel=1e-9)


def test_sfm_threads_below_one_is_one_sentence(tmp_path):
    """--sfm-threads 0 is refused before any work, in one sentence naming the option."""
    from stages.errors import RslError

    cap = make_capture(tmp_path / "cap", ["c0", "c1"])
    with pytest.raises(RslError, match="--sfm-threads should be at least 1, found 0"):
        run(CalibrateConfig(cap, tmp_path / "ws", sfm=True, sfm_threads=0))
