"""Motion-capture files: markers.c3d (ezc3d) against markers.csv, the shared C3D sample, Capture.markers()."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from stages import mocap
from stages.capture import CaptureError, load_capture, read_markers, write_markers

pytest.importorskip("ezc3d")


def _trajectories(T: int = 9, M: int = 5, seed: int = 0) -> np.ndarray:
    """Marker paths in metres (a lab-sized volume) with gaps: single entries, a marker lost for a stretch,
    a frame where no marker is seen."""
    rng = np.random.default_rng(seed)
    t = np.arange(T)[:, None, None]
    P = rng.uniform(-1.5, 1.5, size=(1, M, 3)) + 0.01 * t * rng.normal(size=(1, M, 3))
    P[2, 1] = np.nan
    P[4:7, 3] = np.nan
    P[5] = np.nan
    return P


def test_c3d_round_trip_matches_the_csv_reader(tmp_path: Path) -> None:
    """The same data written as C3D (millimetres, float storage) and as CSV (metres) read back the same:
    positions within float32 rounding, the same gaps, the rate and the labels of the C3D."""
    P = _trajectories()
    labels = [f"M{i}" for i in range(P.shape[1])]
    mocap.write_c3d(tmp_path / "markers.c3d", mocap.MarkerData(P, 100.0, labels), units="mm")
    mocap.write_csv(tmp_path / "markers.csv", P)
    c3d = mocap.read_c3d(tmp_path / "markers.c3d")
    csv = mocap.read_csv(tmp_path / "markers.csv")
    assert c3d.positions.shape == csv.positions.shape == P.shape
    assert c3d.rate_hz == 100.0 and csv.rate_hz is None
    assert c3d.labels == labels and csv.labels == [str(i) for i in range(P.shape[1])]
    gap = ~np.all(np.isfinite(P), axis=-1)
    np.testing.assert_array_equal(~c3d.observed, gap)
    np.testing.assert_array_equal(~csv.observed, gap)
    # float32 in mm: |error| ≤ 2⁻²⁴ · 1500 mm ≈ 1e-7 m; CSV keeps 9 significant digits
    np.testing.assert_allclose(c3d.positions[~gap], csv.positions[~gap], rtol=0, atol=1e-6)
    np.testing.assert_allclose(csv.positions[~gap], P[~gap], rtol=1e-8)
    assert not np.array_equal(c3d.positions[~gap], P[~gap] * 0)  # not trivially zero


@pytest.mark.parametrize("units, scale", [("m", 1.0), ("cm", 100.0), ("mm", 1000.0)])
def test_c3d_units_convert_to_metres(tmp_path: Path, units: str, scale: float) -> None:
    import ezc3d

    P = _trajectories(T=8, M=4, seed=3)
    mocap.write_c3d(tmp_path / "m.c3d", mocap.MarkerData(P, 50.0), units=units)
    raw = ezc3d.c3d(str(tmp_path / "m.c3d"))
    stored = raw["data"]["points"][:3].transpose(2, 1, 0)  # as written, in the file's units
    ok = np.all(np.isfinite(P), axis=-1)
    np.testing.assert_allclose(stored[ok], P[ok] * scale, rtol=1e-6)
    np.testing.assert_allclose(mocap.read_c3d(tmp_path / "m.c3d").positions[ok], P[ok], rtol=1e-6)


def test_c3d_negative_residual_is_a_gap(tmp_path: Path) -> None:
    """A point with finite coordinates but a residual < 0 (the C3D 'not seen' flag) reads as NaN."""
    import ezc3d

    P = np.random.default_rng(4).normal(size=(3, 2, 3))
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [30.0]
    c["parameters"]["POINT"]["LABELS"]["value"] = ["a", "b"]
    c["parameters"]["POINT"]["UNITS"]["value"] = ["m"]
    d = np.ones((4, 2, 3))
    d[:3] = P.transpose(2, 1, 0)
    c["data"]["points"] = d
    res = np.zeros((1, 2, 3))
    res[0, 1, 2] = -1.0
    c["data"]["meta_points"] = {"residuals": res}
    c.write(str(tmp_path / "r.c3d"))
    got = mocap.read_c3d(tmp_path / "r.c3d").positions
    assert np.isnan(got[2, 1]).all()
    assert np.isfinite(np.delete(got.reshape(-1, 3), 2 * 2 + 1, axis=0)).all()


def test_shared_optotrak_sample_reads_and_converts(shared_data: Path, tmp_path: Path) -> None:
    """ezc3d's Optotrak sample: 54 markers at 30 Hz over 29 frames, in mm; coordinates of a lab volume in
    metres; its gaps (negative residuals) are NaN; converted to CSV it reads back the same."""
    src = shared_data / "ezc3d_c3d_sample" / "Optotrak.c3d"
    data = mocap.read_c3d(src)
    assert data.positions.shape == (29, 54, 3)
    assert data.rate_hz == 30.0
    assert data.labels[0] == "Marker_1" and data.labels[-1] == "Marker_54"
    obs = data.observed
    assert 0 < (~obs).sum() < obs.size // 10  # a few gaps
    assert not obs[:, 51].any() and not obs[:, 52].any()  # two markers never seen
    P = data.positions[obs]
    assert np.abs(P).max() < 3.0  # metres, not millimetres
    assert np.ptp(P, axis=0).max() > 0.3  # markers spread over a body-sized volume
    steps = np.linalg.norm(np.diff(data.positions, axis=0), axis=-1)
    assert np.nanmax(steps) < 0.2  # under 6 m/s at 30 Hz: plausible marker speeds
    back = mocap.c3d_to_csv(src, tmp_path / "markers.csv")
    csv = mocap.read_csv(tmp_path / "markers.csv")
    seen = obs.any(axis=0)  # the two never-observed markers are left out of the CSV; the ids of the others kept
    assert csv.positions.shape == (29, 52, 3)
    assert csv.labels == [str(i) for i in np.flatnonzero(seen)]
    np.testing.assert_array_equal(csv.observed, back.observed[:, seen])
    np.testing.assert_allclose(csv.positions[csv.observed], P, rtol=1e-8)
    # rsl adapt's rules: every marker seen at least once (marker 53 of the CSV, first seen after frame 0, is
    # accepted: rsl adapt binds it to its track), and some marker at frame 0
    late = read_markers(tmp_path / "markers.csv")
    assert np.isnan(late[0, csv.labels.index("53")]).all() and np.isfinite(late[:, csv.labels.index("53")]).any()
    with pytest.raises(CaptureError, match=r"Marker_52, Marker_53 are never observed"):
        read_markers(src)


TOML = """[capture]
fps = {fps}
cameras = ["a"]
[object]
mesh = "object.mesh"
"""


@pytest.fixture
def capture(tmp_path: Path, sample_data: Path) -> Path:
    root = tmp_path / "cap"
    root.mkdir()
    shutil.copy(sample_data / "bar" / "object.mesh", root / "object.mesh")
    (root / "capture.toml").write_text(TOML.format(fps=30.0))
    return root


def test_capture_reads_markers_c3d(capture: Path) -> None:
    P = _trajectories(T=8, M=4, seed=5)  # every marker seen at frame 0
    mocap.write_c3d(capture / "markers.c3d", mocap.MarkerData(P, 30.0), units="mm")
    cap = load_capture(capture)
    assert cap.markers_path == capture / "markers.c3d"
    got = cap.markers()
    np.testing.assert_array_equal(np.isnan(got), np.isnan(P))
    np.testing.assert_allclose(got[np.isfinite(P)], P[np.isfinite(P)], atol=1e-6)
    # the CSV route gives the same array
    (capture / "markers.c3d").rename(capture / "markers.c3d.off")
    write_markers(capture / "markers.csv", P)
    assert cap.markers_path == capture / "markers.csv"
    np.testing.assert_allclose(cap.markers(), got, atol=1e-6)


def test_capture_markers_errors_are_one_sentence(capture: Path) -> None:
    P = np.random.default_rng(6).normal(size=(4, 2, 3))
    mocap.write_c3d(capture / "markers.c3d", mocap.MarkerData(P, 120.0), units="m")
    cap = load_capture(capture)
    with pytest.raises(CaptureError) as e:
        cap.markers()
    msg = str(e.value)
    assert msg.startswith(str(capture / "markers.c3d") + ": ") and "120 Hz" in msg and "'capture.fps' is 30" in msg
    assert msg.count(". ") == 0 and msg.endswith(".")
    write_markers(capture / "markers.csv", P)
    with pytest.raises(CaptureError, match="holds both markers.csv and markers.c3d; keep one of them."):
        cap.markers()
    (capture / "markers.csv").unlink()
    (capture / "markers.c3d").write_bytes(b"not a c3d file at all")
    with pytest.raises(CaptureError, match=r"markers.c3d: cannot read it as a C3D file"):
        cap.markers()
