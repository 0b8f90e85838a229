"""Capture folders: capture.toml, controls.json, poses and tracks, frames, markers, truth, cameras.json."""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from stages.artefacts import Camera
from stages.capture import (CaptureError, Controls, Track, apply_pose, load_capture, load_controls, matrix_to_quat,
                            parse_controls, quat_to_matrix, read_cameras_json, read_markers, read_truth,
                            select_handles, slerp, write_cameras_json, write_image, write_markers, write_truth)

TOML = """[capture]
name = "t"
fps = 25.0
cameras = ["a", "b"]
[object]
mesh = "object.mesh"
density = 900.0
[material]
model = "yeoh"
young = 2.0e5
poisson = 0.4
[regions.stiff]
young = 7.0e5
"""


@pytest.fixture
def capture(tmp_path: Path, sample_data: Path) -> Path:
    root = tmp_path / "cap"
    root.mkdir()
    shutil.copy(sample_data / "bar" / "object.mesh", root / "object.mesh")
    (root / "capture.toml").write_text(TOML)
    return root


# --------------------------------------------------------------------------- capture.toml
def test_sample_captures_load(sample_data: Path) -> None:
    for name in ("bar", "dino"):
        cap = load_capture(sample_data / name)
        assert cap.name == name and cap.fps == 30.0 and cap.dt == pytest.approx(1 / 30)
        assert cap.mesh_path.is_file() and cap.density == 1070.0
        np.testing.assert_allclose(cap.gravity, [0, 0, -9.81])
        ctl = cap.controls()
        assert ctl.n_frames == 41


def test_capture_fields(capture: Path) -> None:
    cap = load_capture(capture)
    assert (cap.name, cap.fps, cap.camera_names, cap.density) == ("t", 25.0, ["a", "b"], 900.0)
    m = cap.material
    assert (m.model, m.young, m.poisson) == ("yeoh", 2.0e5, 0.4)
    assert m.young_range == (2.0e4, 2.0e6)  # default: a decade either side
    assert m.region_young("stiff") == 7.0e5 and m.region_young("body") == 2.0e5
    assert m.region_poisson("stiff") == 0.4
    assert cap.controls().handles == []  # no controls.json: no controls


@pytest.mark.parametrize("text, message", [
    ("[capture\nfps=1", "not valid TOML"),
    ("[object]\ndensity = 1.0\n", "'object.mesh' is missing"),
    ("[object]\nmesh = 'object.mesh'\n[material]\nmodel = 'hooke'\n", "'material.model' should be one of"),
    ("[object]\nmesh = 'object.mesh'\n[material]\npoisson = 0.5\n", r"'material.poisson' should lie in \[0, 0.5\)"),
    ("[object]\nmesh = 'object.mesh'\ndensity = -3\n", "'object.density' should be positive"),
    ("[object]\nmesh = 'object.mesh'\ndensity = 'heavy'\n", "'object.density' should be a finite number"),
    ("[capture]\ngravity = [0, 1]\n[object]\nmesh = 'object.mesh'\n", "'capture.gravity' should be a list of 3"),
    ("[capture]\ncameras = 'a'\n[object]\nmesh = 'object.mesh'\n", "'capture.cameras' should be a list"),
    ("[object]\nmesh = 'object.fbx'\n", "unsupported type '.fbx'"),
    ("[object]\nmesh = 'nothing.obj'\n", "nothing.obj: mesh file named by capture.toml 'object.mesh' not found"),
    ("[object]\nmesh = 'object.mesh'\n[material]\nyoung_range = [5.0, 1.0]\n", "'material.young_range' should be"),
])
def test_capture_toml_errors(capture: Path, text: str, message: str) -> None:
    (capture / "capture.toml").write_text(text)
    with pytest.raises(CaptureError, match=message) as e:
        load_capture(capture)
    assert "capture.toml" in str(e.value) or "nothing.obj" in str(e.value)


def test_missing_capture(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="capture folder not found"):
        load_capture(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CaptureError, match="capture.toml: file not found"):
        load_capture(tmp_path / "empty")


# --------------------------------------------------------------------------- poses
def test_quaternion_matrix_round_trip() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        R = quat_to_matrix(q)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(matrix_to_quat(R), q, atol=1e-10)
    # 90° about z sends x to y
    c = math.cos(math.pi / 4)
    np.testing.assert_allclose(quat_to_matrix([c, 0, 0, c]) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # the branches for traces ≤ 0: rotations by π about each axis
    for axis in np.eye(3):
        q = np.concatenate([[0.0], axis])
        np.testing.assert_allclose(np.abs(matrix_to_quat(quat_to_matrix(q))), q, atol=1e-12)


def test_slerp_constant_angular_speed() -> None:
    q0 = np.array([1.0, 0, 0, 0])
    q1 = np.array([math.cos(0.6), math.sin(0.6), 0, 0])  # 1.2 rad about x
    for a in (0.0, 0.25, 0.5, 1.0):
        q = slerp(q0, q1, a)
        assert np.linalg.norm(q) == pytest.approx(1.0)
        assert 2 * math.acos(min(1.0, q[0])) == pytest.approx(1.2 * a, abs=1e-9)
    np.testing.assert_allclose(slerp(q0, -q1, 0.5), slerp(q0, q1, 0.5), atol=1e-12)  # shortest arc


def test_apply_pose() -> None:
    c = math.cos(math.pi / 4)
    p = apply_pose([1, 2, 3, c, 0, 0, c], np.array([[1.0, 0, 0], [0, 0, 1]]))
    np.testing.assert_allclose(p, [[1, 3, 3], [1, 2, 4]], atol=1e-12)


def test_keyframe_track_interpolates() -> None:
    ctl = parse_controls({"handles": [{"name": "h", "select": {"ids": [0]}, "keyframes": {
        "frame": [0, 10, 20], "pose": [[0, 0, 0, 1, 0, 0, 0], [1, 0, 0, 1, 0, 0, 0],
                                       [1, 0, 0, 0, 1, 0, 0]]}}]}, Path("controls.json"))
    tr = ctl.handles[0].poses
    assert tr.n_frames == 21 and ctl.n_frames == 21
    np.testing.assert_allclose(tr.at(5), [0.5, 0, 0, 1, 0, 0, 0])
    np.testing.assert_allclose(tr.at(15)[:3], [1, 0, 0])
    np.testing.assert_allclose(tr.at(15)[3:], [math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0], atol=1e-12)
    np.testing.assert_allclose(tr.at(99), tr.at(20))  # the last value holds
    s = tr.sample(25)
    assert s.shape == (25, 7)
    np.testing.assert_allclose(s[10], [1, 0, 0, 1, 0, 0, 0])


def test_controls_round_trip_and_defaults() -> None:
    data = {
        "handles": [{"name": "l", "select": {"box": [[0, 0, 0], [1, 1, 1]]}, "stiffness": 5.0,
                     "poses": [[0, 0, 0, 2, 0, 0, 0], [0, 0, 1, 1, 0, 0, 0]]}],
        "loads": [{"name": "w", "select": {"plane": {"normal": [0, 0, 1], "offset": 0.5}},
                   "force": [[0, 0, -1.0]]}],
        "obstacles": [{"name": "floor", "shape": "plane", "normal": [0, 0, 2], "offset": 0.0},
                      {"name": "s", "shape": "sphere", "radius": 0.1,
                       "keyframes": {"frame": [0, 4], "pose": [[0, 0, 0, 1, 0, 0, 0], [1, 0, 0, 1, 0, 0, 0]]}},
                      {"name": "b", "shape": "box", "half_extents": [1, 2, 3]}],
        "friction": 0.3,
    }
    ctl = parse_controls(data, Path("c.json"))
    np.testing.assert_allclose(ctl.handles[0].poses.values[0], [0, 0, 0, 1, 0, 0, 0])  # normalised quaternion
    np.testing.assert_allclose(ctl.obstacles[0].normal, [0, 0, 1])
    again = parse_controls(json.loads(json.dumps(ctl.to_json())), Path("c.json"))
    for a, b in zip(ctl.handles + ctl.loads, again.handles + again.loads):
        assert a.name == b.name
    np.testing.assert_allclose(again.obstacles[1].poses.sample(5), ctl.obstacles[1].poses.sample(5))
    np.testing.assert_allclose(again.handles[0].poses.sample(3), ctl.handles[0].poses.sample(3))
    assert again.friction == 0.3 and again.n_frames == 5
    assert Controls().n_frames is None


@pytest.mark.parametrize("data, message", [
    ([], "should hold a JSON object"),
    ({"handles": {"name": "x"}}, "'handles' should be a list"),
    ({"handle": []}, "'handle' is not a known key \\(did you mean 'handles'\\?\\)"),
    ({"handles": [{"name": "a", "select": {"ids": [0]}}, {"name": "a", "select": {"ids": [1]}}]},
     "repeats the name 'a'"),
    ({"handles": [{"name": "a", "select": {"box": [[0, 0, 0]]}}]}, "'handles\\[0\\].select.box' should be two"),
    ({"handles": [{"name": "a", "select": {"sphere": 1}}]}, "'handles\\[0\\].select.sphere' is not a known key"),
    ({"handles": [{"name": "a", "select": {"ids": [0]}, "stiffness": "stiff"}]},
     "'handles\\[0\\].stiffness' should be a finite number"),
    ({"handles": [{"name": "a", "select": {"ids": [0]}, "poses": [[0, 0, 0, 0, 0, 0, 0]]}]}, "zero quaternion"),
    ({"handles": [{"name": "a", "select": {"ids": [0]}, "poses": [[0, 0, 0]]}]}, "list of 7 finite numbers"),
    ({"handles": [{"name": "a", "select": {"ids": [0]}, "keyframes": {"frame": [0, 0], "pose": []}}]},
     "strictly increasing"),
    ({"loads": [{"name": "w", "select": {"ids": [0]}}]}, "needs 'force'"),
    ({"obstacles": [{"name": "o", "shape": "cone"}]}, "should be 'plane', 'sphere' or 'box'"),
    ({"obstacles": [{"name": "o", "shape": "sphere", "radius": -1}]}, "radius' should be positive"),
    ({"friction": -0.1}, "should not be negative"),
])
def test_controls_errors(data, message: str) -> None:
    with pytest.raises(CaptureError, match=message) as e:
        parse_controls(data, Path("some/controls.json"))
    assert str(e.value).startswith("some/controls.json: ")


def test_controls_file_errors(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="file not found"):
        load_controls(tmp_path / "controls.json")
    (tmp_path / "controls.json").write_text("{\"handles\": [}")
    with pytest.raises(CaptureError, match="not valid JSON"):
        load_controls(tmp_path / "controls.json")


def test_select_handles(sample_data: Path) -> None:
    import meshio

    v = meshio.read(sample_data / "bar" / "object.mesh").points
    ctl = load_controls(sample_data / "bar" / "controls.json")
    h = select_handles(ctl, v)
    assert set(h) == {"left", "right"}
    assert np.allclose(v[h["left"], 0], v[:, 0].min()) and np.allclose(v[h["right"], 0], v[:, 0].max())
    assert len(h["left"]) >= 9 and len(h["right"]) >= 9
    far = parse_controls({"handles": [{"name": "x", "select": {"box": [[5, 5, 5], [6, 6, 6]]}}]}, Path("c.json"))
    with pytest.raises(CaptureError, match="c.json: handle 'x' selects no vertex"):
        select_handles(far, v, "c.json")
    big = parse_controls({"handles": [{"name": "x", "select": {"ids": [10_000]}}]}, Path("c.json"))
    with pytest.raises(CaptureError, match="selects vertex id 10000 but the mesh has 341"):
        select_handles(big, v, "c.json")
    plane = parse_controls({"loads": [{"name": "top", "select": {"plane": {"normal": [0, 0, 1], "offset": 0.04}},
                                       "force": [[0, 0, -1]]}]}, Path("c.json"))
    assert select_handles(plane, v) == {}  # loads are checked, not returned


# --------------------------------------------------------------------------- frames, markers, truth, cameras
def _frames(root: Path, cam: str, n: int, start: int = 0) -> None:
    for i in range(start, start + n):
        img = np.full((6, 8, 3), 10 * i, np.uint8)
        img[0, 0] = (255, 0, 0)
        write_image(root / "frames" / cam / f"{i:06d}.png", img)


def test_frames_from_png_folders(capture: Path) -> None:
    _frames(capture, "a", 3)
    _frames(capture, "b", 3)
    cap = load_capture(capture)
    assert cap.frame_count() == 3
    src = cap.frame_source("a")
    f1 = src.read(1)
    assert f1.shape == (6, 8, 3) and f1.dtype == np.uint8
    assert tuple(f1[0, 0]) == (255, 0, 0) and f1[1, 1, 0] == 10  # RGB order kept
    assert src.read_all().shape == (3, 6, 8, 3)
    with pytest.raises(CaptureError, match="frame 3 out of range"):
        src.read(3)


def test_frames_from_video(capture: Path) -> None:
    import cv2

    (capture / "frames").mkdir()
    w = cv2.VideoWriter(str(capture / "frames" / "a.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (16, 12))
    for i in range(4):
        w.write(np.full((12, 16, 3), 40 * i, np.uint8))
    w.release()
    src = load_capture(capture).frame_source("a")
    assert src.count == 4
    frames = src.read_all()
    assert frames.shape == (4, 12, 16, 3)
    assert abs(int(src.read(2)[5, 5, 0]) - 80) <= 3


def test_frame_errors(capture: Path) -> None:
    _frames(capture, "a", 3)
    _frames(capture, "b", 2)
    cap = load_capture(capture)
    with pytest.raises(CaptureError, match=r"unequal frame counts \(a: 3, b: 2\)"):
        cap.frame_count()
    shutil.rmtree(capture / "frames" / "b")
    _frames(capture, "b", 2, start=1)
    with pytest.raises(CaptureError, match="frame 0 is missing"):
        cap.frame_source("b")
    with pytest.raises(CaptureError, match="no frames for camera 'c'"):
        cap.frame_source("c")


def test_background_and_calib_views(capture: Path) -> None:
    cap = load_capture(capture)
    assert cap.background("a") is None and cap.calib_views() == {}
    write_image(capture / "background" / "a.png", np.zeros((4, 4, 3), np.uint8))
    write_image(capture / "calib" / "a" / "v1.png", np.zeros((4, 4, 3), np.uint8))
    write_image(capture / "calib" / "b" / "v1.png", np.zeros((4, 4, 3), np.uint8))
    assert cap.background("a").shape == (4, 4, 3)
    assert {c: list(v) for c, v in cap.calib_views().items()} == {"a": ["v1"], "b": ["v1"]}


def test_markers_round_trip_and_errors(tmp_path: Path) -> None:
    m = np.random.default_rng(0).normal(size=(4, 3, 3))
    write_markers(tmp_path / "markers.csv", m)
    np.testing.assert_allclose(read_markers(tmp_path / "markers.csv"), m, rtol=1e-8)
    (tmp_path / "bad.csv").write_text("frame,marker,x,y\n0,0,1,2\n")
    with pytest.raises(CaptureError, match="bad.csv: header should be"):
        read_markers(tmp_path / "bad.csv")
    (tmp_path / "late.csv").write_text("frame,marker,x,y,z\n0,0,1,2,3\n1,0,1,2,3\n1,1,1,2,3\n")
    late = read_markers(tmp_path / "late.csv")  # marker 1 first seen at frame 1: accepted (bound to its track)
    assert np.isnan(late[0, 1]).all() and np.allclose(late[1, 1], [1, 2, 3])
    (tmp_path / "bad.csv").write_text("frame,marker,x,y,z\n0,0,,,\n1,0,1,2,3\n1,1,1,2,3\n")
    with pytest.raises(CaptureError, match="bad.csv: no marker is observed at frame 0"):
        read_markers(tmp_path / "bad.csv")
    (tmp_path / "bad.csv").write_text("frame,marker,x,y,z\n0,0,1,2,nan\n")
    with pytest.raises(CaptureError, match="line 2 should hold 5 finite values"):
        read_markers(tmp_path / "bad.csv")


def test_markers_with_gaps_round_trip_as_nan(tmp_path: Path) -> None:
    """A (frame, marker) row that is absent (or has x, y, z all empty) is a gap: NaN; write_markers leaves NaN
    entries out and keeps a frame that sees no marker as one empty row."""
    rng = np.random.default_rng(1)
    m = rng.normal(size=(5, 4, 3))
    m[1, 2] = np.nan
    m[3, [0, 3]] = np.nan
    m[4] = np.nan  # no marker seen at the last frame
    m[2, 1, 0] = np.nan  # one NaN coordinate: the whole entry is a gap
    write_markers(tmp_path / "markers.csv", m)
    text = (tmp_path / "markers.csv").read_text()
    assert "nan" not in text.lower() and text.splitlines()[-1] == "4,0,,,"
    assert len(text.strip().splitlines()) == 1 + 20 - 1 - 2 - 1 - 4 + 1
    got = read_markers(tmp_path / "markers.csv")
    gap = ~np.all(np.isfinite(m), axis=-1)
    assert got.shape == (5, 4, 3)
    np.testing.assert_array_equal(np.isnan(got).all(-1), gap)
    assert not np.any(np.isnan(got[~gap]))
    np.testing.assert_allclose(got[~gap], m[~gap], rtol=1e-8)
    # an explicit gap row reads the same as an absent row; marker ids need not be contiguous
    (tmp_path / "g.csv").write_text("frame,marker,x,y,z\n0,3,1,2,3\n0,7,4,5,6\n1,3,,,\n1,7,1,1,1\n2,7,2,2,2\n")
    got = read_markers(tmp_path / "g.csv")
    assert got.shape == (3, 2, 3)
    assert np.isnan(got[1, 0]).all() and np.isnan(got[2, 0]).all()
    np.testing.assert_array_equal(got[:, 1], [[4, 5, 6], [1, 1, 1], [2, 2, 2]])


@pytest.mark.parametrize("text, expect", [
    ("frame,marker,x,y,z\n0,0,1,2,3\n0,1,1,inf,3\n", "line 3 should hold 5 finite values"),
    ("frame,marker,x,y,z\n0,0,1,2,3\n0,1,1,,3\n", "line 3 is not 'frame,marker,x,y,z' numbers"),
    ("frame,marker,x,y,z\n0,0,1,2,3\n2,0,1,2,3\n", "frames should run 0..T-1"),
    ("frame,marker,x,y,z\n0,0,1,2,3\n0,1,,,\n1,0,1,2,3\n1,1,,,\n", "marker(s) 1 are never observed"),
    ("frame,marker,x,y,z\n0,0,,,\n1,0,1,2,3\n1,5,1,2,3\n", "no marker is observed at frame 0"),
    ("frame,marker,x,y,z\n0,0,1,2,3\n0,0,1,2,3\n", "marker 0 is listed twice at frame 0"),
    ("frame,mark,x,y,z\n0,0,1,2,3\n", "header should be"),
])
def test_markers_rejections_name_the_file(tmp_path: Path, text: str, expect: str) -> None:
    (tmp_path / "odd.csv").write_text(text)
    with pytest.raises(CaptureError) as e:
        read_markers(tmp_path / "odd.csv")
    msg = str(e.value)
    assert msg.startswith(str(tmp_path / "odd.csv") + ": ") and expect in msg and msg.endswith(".")


def test_truth_round_trip(capture: Path) -> None:
    rng = np.random.default_rng(1)
    young, poisson = rng.uniform(1e4, 1e5, (5, 2)), rng.uniform(0.3, 0.45, (5, 2))
    faces, verts = rng.integers(0, 6, (4, 3)), rng.normal(size=(5, 6, 3))
    write_truth(capture / "truth", young, poisson, ["body", "stiff"], faces, verts)
    t = read_truth(load_capture(capture))
    assert t.region_names == ["body", "stiff"]
    np.testing.assert_allclose(t.young, young, rtol=1e-8)
    np.testing.assert_allclose(t.poisson, poisson, rtol=1e-8)
    np.testing.assert_array_equal(t.faces, faces)
    np.testing.assert_array_equal(t.vertices, verts)


def test_cameras_json_round_trip_and_errors(tmp_path: Path) -> None:
    c = math.cos(0.3)
    cams = [Camera("c0", np.array([[400.0, 0, 100], [0, 400, 80], [0, 0, 1]]), np.array([0.1, 0, 0, 0, 0]),
                   np.array([[c, -math.sin(0.3), 0], [math.sin(0.3), c, 0], [0, 0, 1]]), np.array([0, 0, 2.0]), 200, 160)]
    write_cameras_json(tmp_path / "cameras.json", cams)
    back = read_cameras_json(tmp_path / "cameras.json")
    assert back[0].name == "c0" and (back[0].width, back[0].height) == (200, 160)
    np.testing.assert_allclose(back[0].R, cams[0].R)
    np.testing.assert_allclose(back[0].center, -cams[0].R.T @ cams[0].t)
    data = json.loads((tmp_path / "cameras.json").read_text())
    data["cameras"][0]["R"] = np.eye(3).tolist()[:2]
    (tmp_path / "cameras.json").write_text(json.dumps(data))
    with pytest.raises(CaptureError, match=r"'cameras\[0\].R' should be a 3x3"):
        read_cameras_json(tmp_path / "cameras.json")
    data["cameras"][0]["R"] = (2 * np.eye(3)).tolist()
    (tmp_path / "cameras.json").write_text(json.dumps(data))
    with pytest.raises(CaptureError, match="is not a rotation matrix"):
        read_cameras_json(tmp_path / "cameras.json")


def test_track_constant() -> None:
    t = Track.constant(np.array([1.0, 2.0, 3.0]))
    assert t.n_frames == 1
    np.testing.assert_allclose(t.sample(3), [[1, 2, 3]] * 3)
