"""Camera import/export: rsl cameras.json, COLMAP text/binary (checked against pycolmap), transforms.json."""
from __future__ import annotations

import json

import numpy as np
import pytest

from stages.artefacts import Camera, CamerasArtefact
from stages.steps.calibrate import CalibrateConfig, run
from stages.capture import write_cameras_json
from stages.errors import RslError
from stages.progress import SilentReporter
from stages.vision.colmap_io import cameras_from_transforms, cameras_to_transforms, read_colmap, write_colmap
from stages.vision.geometry import project, rotvec_to_matrix
from test_calibrate_board import make_capture


def _cams() -> list[Camera]:
    return [
        Camera("a", np.array([[500, 0, 320.5], [0, 510, 240.25], [0, 0, 1.0]]),
               np.array([0.1, -0.2, 0.001, 0.002, 0.0]), rotvec_to_matrix([0.1, 0.2, 0.3]),
               np.array([0.1, 0.2, 1.0]), 640, 480),
        Camera("b", np.array([[400, 0, 300], [0, 400, 200], [0, 0, 1.0]]),
               np.array([0.1, -0.2, 0.001, 0.002, 0.05]), rotvec_to_matrix([-0.1, 0.2, 2.9]),
               np.array([-0.1, 0.2, 1.5]), 600, 400),
    ]


def _same(a: Camera, b: Camera, tol: float = 1e-9) -> None:
    assert a.name == b.name and (a.width, a.height) == (b.width, b.height)
    for k in ("K", "dist", "R", "t"):
        assert np.allclose(getattr(a, k), getattr(b, k), atol=tol), k


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_round_trip_and_pycolmap(tmp_path, binary):
    import pycolmap

    cams = _cams()
    write_colmap(cams, tmp_path / "ours", binary=binary)
    back = read_colmap(tmp_path / "ours", ["a", "b"])
    for a, b in zip(cams, back):
        _same(a, b)
    # pycolmap reads what we wrote; what pycolmap writes, we read.
    rec = pycolmap.Reconstruction(str(tmp_path / "ours"))
    assert rec.num_images() == 2
    for im in rec.images.values():
        c = {x.name: x for x in cams}[im.name.split(".")[0]]
        pose = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        assert np.allclose(pose.rotation.matrix(), c.R, atol=1e-9)
        assert np.allclose(pose.translation, c.t, atol=1e-9)
    out = tmp_path / "theirs"
    out.mkdir()
    (rec.write_binary if binary else rec.write_text)(str(out))
    for a, b in zip(cams, read_colmap(out, ["a", "b"])):
        _same(a, b)


def test_transforms_round_trip_projects_the_same(tmp_path):
    cams = _cams()
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps(cameras_to_transforms(cams)))
    back = cameras_from_transforms(path, ["a", "b"])
    pts = np.random.default_rng(0).normal(size=(20, 3)) * 0.2
    for a, b in zip(cams, back):
        _same(a, b)
        assert np.allclose(project(pts, a.K, a.dist, a.R, a.t)[0], project(pts, b.K, b.dist, b.R, b.t)[0])
    with pytest.raises(RslError, match="no frame for camera"):
        cameras_from_transforms(path, ["a", "zz"])


def test_stage_imports(tmp_path):
    cams = _cams()
    cap = make_capture(tmp_path / "cap", ["b", "a"])
    write_cameras_json(cap / "cameras.json", cams)
    rep = SilentReporter()
    # no option: CAPTURE/cameras.json is imported, in capture.toml's camera order
    out = run(CalibrateConfig(cap, tmp_path / "ws"), rep)
    art = CamerasArtefact.load(out)
    assert art.method == "json" and [c.name for c in art.cameras] == ["b", "a"]
    _same(art.by_name("a"), cams[0])
    assert "2 camera(s) by json" in rep.messages[-1]
    write_colmap(cams, tmp_path / "model" / "sparse" / "0", binary=True)
    art = CamerasArtefact.load(run(CalibrateConfig(cap, tmp_path / "ws", from_colmap=str(tmp_path / "model"))))
    assert art.method == "colmap"
    _same(art.by_name("b"), cams[1])
    (tmp_path / "t.json").write_text(json.dumps(cameras_to_transforms(cams)))
    art = CamerasArtefact.load(run(CalibrateConfig(cap, tmp_path / "ws", from_transforms=str(tmp_path / "t.json"))))
    assert art.method == "transforms"
    _same(art.by_name("a"), cams[0], tol=1e-9)
    with pytest.raises(RslError, match="no image for camera"):
        run(CalibrateConfig(make_capture(tmp_path / "cap2", ["a", "c"]), tmp_path / "ws2",
                            from_colmap=str(tmp_path / "model")))
    with pytest.raises(RslError, match="give --board"):
        run(CalibrateConfig(make_capture(tmp_path / "cap3", ["a"]), tmp_path / "ws3"))


def test_board_from_capture_toml(shared_data, tmp_path):
    """Without options or cameras.json, capture.toml [calibration] board names the board."""
    import shutil

    cap = make_capture(tmp_path / "cap", ["left"])
    with open(cap / "capture.toml", "a") as f:
        f.write('[calibration]\nboard = "chessboard:9x6:0.025"\n')
    d = cap / "calib" / "left"
    d.mkdir(parents=True)
    for v in ("01", "03", "04", "05", "06"):
        shutil.copy(shared_data / "opencv_samples_chessboard" / f"left{v}.jpg", d / f"{v}.jpg")
    art = CamerasArtefact.load(run(CalibrateConfig(cap, tmp_path / "ws")))
    assert art.method == "chessboard" and art.cameras[0].rms_px < 0.5
