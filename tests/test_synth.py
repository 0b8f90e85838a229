"""`rsl synth`: a complete synthetic capture that the rest of the pipeline accepts, and whose
truth is what the simulator computes from the capture's own files."""
from __future__ import annotations

import json
from pathlib import Path

import meshio
import numpy as np
import pytest

from stages.capture import load_capture, read_cameras_json, read_image, read_truth
from stages.progress import SilentReporter
from stages.sim.meshgen import box_tets
from stages.steps.synth import (SynthConfig, parse_region, prepare_mesh, run, scenario_controls, young_schedule)
from stages.errors import RslError
from conftest import run_rsl


@pytest.fixture(scope="module")
def box_mesh(tmp_path_factory) -> Path:
    """A 0.2 × 0.05 × 0.05 m bar of 6×2×2 hex cells (144 tets) as a Medit file."""
    v, t = box_tets((6, 2, 2), (0.2, 0.05, 0.05))
    path = tmp_path_factory.mktemp("mesh") / "bar.mesh"
    meshio.write(str(path), meshio.Mesh(v, [("tetra", t)]), file_format="medit")
    return path


@pytest.fixture(scope="module")
def capture(box_mesh, tmp_path_factory) -> Path:
    """A stretch capture made by the real CLI: 2 cameras at 48 px, 6 frames, a stiff region, a ramp."""
    out = tmp_path_factory.mktemp("synth") / "bar_synth"
    proc = run_rsl("synth", box_mesh, out, "--scenario", "stretch", "--cameras", "2", "--frames", "6",
               "--resolution", "48", "--young-schedule", "5e4@0,1e5@5", "--ramp", "--region", "stiff=3e5@x>0.5",
               "--markers", "7", "--calib-views", "2", "--seed", "3")
    assert proc.returncode == 0, proc.stderr
    assert "stretch, 6 frames × 2 cameras" in proc.stderr
    return out


def _resimulate(cap, max_iterations: int = 300) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions (T, n, 3) from truth/object.mesh + controls.json + truth material under the capture's
    declared start state ([capture] start), and (faces, tets)."""
    from stages.artefacts import mesh_artefact
    from stages.sim.scene import frame_inputs, make_scene
    from stages.sim.static import simulate_from_start

    m = meshio.read(str(cap.truth_dir / "object.mesh"))
    tets = np.asarray(m.cells_dict["tetra"], np.int64)
    region = np.asarray(m.cell_data_dict["medit:ref"]["tetra"], np.int64)
    truth = read_truth(cap)
    art = mesh_artefact(np.asarray(m.points, np.float64), tets, cap.density, region, tuple(truth.region_names))
    ctl = cap.controls()
    scene = make_scene(art, ctl, cap.material.model, cap.dt, cap.gravity)
    X = simulate_from_start(scene, lambda f: frame_inputs(scene, ctl, f), truth.young, truth.poisson,
                            truth.young.shape[0], cap.start, max_iterations=max_iterations)
    return X, art.surface_faces, tets


def test_capture_is_complete_and_readable(capture):
    cap = load_capture(capture)
    assert cap.camera_names == ["cam0", "cam1"]
    assert cap.frame_count() == 6
    img = cap.frame_source("cam0").read(5)
    assert img.shape == (48, 48, 3) and img.dtype == np.uint8
    assert cap.background("cam1").shape == (48, 48, 3)
    cams = read_cameras_json(cap.cameras_json)
    assert [c.name for c in cams] == ["cam0", "cam1"] and cams[0].width == 48
    views = cap.calib_views()
    assert set(views) == {"cam0", "cam1"} and set(views["cam0"]) == set(views["cam1"]) == {"view00", "view01"}
    assert cap.markers().shape == (6, 7, 3)
    assert list(cap.region_meshes()) == ["stiff"]
    assert cap.material.young == pytest.approx(5e4)
    assert cap.material.region_young("stiff") == pytest.approx(3e5)
    assert cap.material.young_range[0] <= 5e4 and cap.material.young_range[1] >= 3e5
    assert cap.raw["calibration"]["board"].startswith("chessboard:6x4:")
    ctl = cap.controls()
    assert [h.name for h in ctl.handles] == ["left", "right"]
    truth = read_truth(cap)
    assert truth.region_names == ["body", "stiff"]
    assert np.allclose(truth.young[:, 0], np.linspace(5e4, 1e5, 6))
    assert np.allclose(truth.young[:, 1], 3e5) and np.allclose(truth.poisson, 0.45)
    assert truth.vertices.shape[0] == 6 and truth.faces.max() < truth.vertices.shape[1]
    # truth masks cover the object where the frame differs from the background plate
    mask = read_image(capture / "truth" / "masks" / "cam0" / "000003.png")[..., 0] > 127
    frame = cap.frame_source("cam0").read(3).astype(int)
    diff = np.abs(frame - cap.background("cam0").astype(int)).sum(axis=2)
    assert 0.02 < mask.mean() < 0.8
    assert np.all(diff[~mask] <= 3 * 255 * 0.5)  # outside: at most partial coverage at the edge
    assert np.median(diff[mask]) > 20


def test_truth_matches_resimulation_from_capture_files(capture):
    cap = load_capture(capture)
    X, faces, tets = _resimulate(cap)
    truth = read_truth(cap)
    surf = np.unique(faces)
    assert np.allclose(truth.vertices, X[:, surf], rtol=0, atol=1e-9)
    # the markers are surface points bound to a triangle at frame 0 that move with it
    markers = cap.markers()
    assert np.linalg.norm(markers[3] - markers[0], axis=1).max() > 1e-3
    for p0, p3 in zip(markers[0], markers[3]):
        tri, w = _binding(p0, truth.vertices[0], truth.faces)
        assert np.allclose(w @ truth.vertices[3][truth.faces[tri]], p3, atol=1e-8)
    # the right handle moved by +x as controls.json says, the left stayed
    ctl = cap.controls()
    right = ctl.handles[1].select.select(X[0] * 0 + _rest(cap))
    assert X[3, right, 0].mean() - _rest(cap)[right, 0].mean() > 0.01


def _binding(p: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> tuple[int, np.ndarray]:
    """The triangle that holds point p and p's barycentric weights (3,) in it."""
    for k, (a, b, c) in enumerate(verts[faces]):
        A = np.stack([b - a, c - a], axis=1)
        w, *_ = np.linalg.lstsq(A, p - a, rcond=None)
        if np.linalg.norm(A @ w - (p - a)) < 1e-9 and w.min() >= -1e-9 and w.sum() <= 1 + 1e-9:
            return k, np.array([1 - w.sum(), w[0], w[1]])
    raise AssertionError(f"marker {p} lies on no surface triangle")


def _rest(cap) -> np.ndarray:
    return np.asarray(meshio.read(str(cap.truth_dir / "object.mesh")).points, np.float64)


def test_regions_file_selects_the_same_tets(capture):
    from stages.steps.tetrahedralize import assign_regions

    cap = load_capture(capture)
    m = meshio.read(str(cap.truth_dir / "object.mesh"))
    tets = np.asarray(m.cells_dict["tetra"], np.int64)
    region, names = assign_regions(np.asarray(m.points, np.float64), tets, cap.region_meshes(), SilentReporter())
    assert names == ["body", "stiff"]
    assert np.array_equal(region, np.asarray(m.cell_data_dict["medit:ref"]["tetra"]))
    assert 0 < region.mean() < 1


def test_tetrahedralize_accepts_the_capture(capture, tmp_path):
    from stages.artefacts import MeshArtefact
    from stages.steps.tetrahedralize import TetrahedralizeConfig
    from stages.steps.tetrahedralize import run as tetrahedralize

    tetrahedralize(TetrahedralizeConfig(capture=capture, workspace=tmp_path / "ws", edge_length=0.2))

    mesh = MeshArtefact.load(tmp_path / "ws" / "mesh.h5")
    assert set(mesh.handles) == {"left", "right"}
    assert mesh.region_names == ["body", "stiff"]


def test_existing_output_is_not_replaced_without_overwrite(capture, box_mesh, tmp_path):
    with pytest.raises(RslError, match="already exists and is not empty.*--overwrite"):
        run(SynthConfig(mesh=box_mesh, out=capture, frames=2, resolution=32))
    assert load_capture(capture).frame_count() == 6
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(RslError, match="only replaces a capture made by rsl synth"):
        run(SynthConfig(mesh=box_mesh, out=other, frames=2, resolution=32, overwrite=True))
    assert (other / "notes.txt").read_text() == "mine"


def test_bad_options_fail_with_one_clear_sentence(box_mesh, tmp_path, rsl):
    proc = rsl("synth", box_mesh, tmp_path / "a", "--young-schedule", "1e4 at 0")
    assert proc.returncode == 1 and "--young-schedule entry '1e4 at 0'" in proc.stderr
    proc = rsl("synth", tmp_path / "missing.mesh", tmp_path / "b")
    assert proc.returncode == 1 and "missing.mesh: mesh file not found" in proc.stderr
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_young_schedule_steps_and_ramps():
    steps = young_schedule("1e4@0,2e4@20,4e4@40", 0, 50, ramp=False)
    assert steps[0] == steps[19] == 1e4 and steps[20] == steps[39] == 2e4 and steps[49] == 4e4
    ramp = young_schedule("1e4@0,2e4@20,4e4@40", 0, 50, ramp=True)
    assert ramp[10] == pytest.approx(1.5e4) and ramp[30] == pytest.approx(3e4) and ramp[45] == 4e4
    assert np.all(young_schedule("", 7e4, 5, ramp=False) == 7e4)
    late = young_schedule("3e4@5", 0, 8, ramp=False)
    assert np.all(late == 3e4)
    with pytest.raises(RslError, match="increase strictly"):
        young_schedule("1e4@5,2e4@5", 0, 8, ramp=False)


def test_parse_region_defaults_to_the_long_axis():
    v = np.array([[0, 0, 0], [0.05, 0.3, 0.02]], float)
    assert parse_region("hard=2e5", v) == ("hard", 2e5, 1, 0.5)
    assert parse_region("hard=2e5@z>0.25", v) == ("hard", 2e5, 2, 0.25)
    with pytest.raises(RslError, match="'body' is the name of the main region"):
        parse_region("body=2e5", v)
    with pytest.raises(RslError, match="--region 'stiff' should read"):
        parse_region("stiff", v)


@pytest.mark.parametrize("scenario", ["stretch", "twist", "push", "drop", "cable"])
def test_scenarios_simulate_and_move_the_object(scenario, box_mesh, tmp_path):
    out = run(SynthConfig(mesh=box_mesh, out=tmp_path / scenario, scenario=scenario, cameras=1, frames=8,
                          resolution=32, markers=0, calib_views=0, young=2e5))
    cap = load_capture(out)
    truth = read_truth(cap)
    ctl = cap.controls()
    rest = truth.vertices[0]
    motion = np.linalg.norm(truth.vertices - rest[None], axis=2).max()
    assert motion > 2e-3, scenario
    if scenario == "drop":
        floor = ctl.obstacles[0]
        heights = truth.vertices @ floor.normal - floor.offset
        assert heights.min() > -2e-3  # does not sink through the floor
        assert heights[-1].min() < heights[0].min()  # fell towards it
    if scenario == "push":
        assert ctl.obstacles[0].shape == "sphere"
        assert np.ptp(ctl.obstacles[0].poses.values[:, 2]) > 0.01
    if scenario == "cable":
        assert ctl.loads[0].select.kind == "ids" and len(ctl.loads[0].select.ids) == 6
        assert np.abs(ctl.loads[0].force.values).max() > 0
    if scenario == "twist":
        q = ctl.handles[1].poses.values[:, 3:]
        assert np.abs(q[:, 1]).max() > 0.3  # rotated about the long (x) axis


def test_scenario_controls_scale_with_the_object():
    v, t = box_tets((4, 1, 1), (0.4, 0.05, 0.05))
    mesh = prepare_mesh(v, t, 0.0, "")
    ctl, notes = scenario_controls("stretch", mesh.vertices, mesh.faces, 10, 1.0, np.array([0, 0, -9.81]), 1e5)
    assert notes["long_axis"] == "x" and notes["length_m"] == pytest.approx(0.4)
    left = ctl.handles[0].select.select(mesh.vertices)
    assert np.allclose(mesh.vertices[left, 0], -0.2)  # only the end face of a 0.1 m cell mesh
    json.dumps(ctl.to_json())  # serialisable
    half, notes_half = scenario_controls("stretch", mesh.vertices, mesh.faces, 10, 1.0, np.array([0, 0, -9.81]),
                                         1e5, amp=0.5)
    assert notes_half["max_stretch_m"] == pytest.approx(0.5 * notes["max_stretch_m"]) == pytest.approx(0.05)
    assert np.allclose(half.handles[1].poses.values[:, :3], 0.5 * ctl.handles[1].poses.values[:, :3])


def test_surface_mesh_input_is_tetrahedralized(tmp_path):
    import trimesh

    box = trimesh.creation.box(extents=(0.3, 0.06, 0.06))
    box.export(tmp_path / "box.obj")
    out = run(SynthConfig(mesh=tmp_path / "box.obj", out=tmp_path / "cap", scenario="cable", cameras=1, frames=3,
                          resolution=32, markers=3, calib_views=0, edge_length=0.15, size=0.0))
    cap = load_capture(out)
    m = meshio.read(str(cap.truth_dir / "object.mesh"))
    v = np.asarray(m.points)
    assert len(m.cells_dict["tetra"]) > 10
    assert np.allclose(np.ptp(v, axis=0), (0.3, 0.06, 0.06), atol=1e-3)  # size 0 keeps the units
    assert read_truth(cap).vertices.shape[0] == 3 and cap.markers().shape == (3, 3, 3)


def test_same_seed_gives_identical_captures(box_mesh, tmp_path):
    outs = []
    for k in range(2):
        outs.append(run(SynthConfig(mesh=box_mesh, out=tmp_path / f"c{k}", scenario="push", cameras=1, frames=3,
                                    resolution=32, markers=4, calib_views=1, noise=0.02, seed=5)))
    files = sorted(p.relative_to(outs[0]) for p in outs[0].rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(outs[1]) for p in outs[1].rglob("*") if p.is_file())
    for rel in files:
        if rel.name == "capture.toml":  # names the output folder
            continue
        assert (outs[0] / rel).read_bytes() == (outs[1] / rel).read_bytes(), rel


def test_marker_noise_perturbs_only_the_markers(box_mesh, tmp_path):
    """--marker-noise M adds seeded N(0, M²) noise to markers.csv; frames and truth stay those of M = 0."""
    import tomllib

    clean = run(SynthConfig(mesh=box_mesh, out=tmp_path / "clean", scenario="push", cameras=1, frames=3,
                            resolution=32, markers=50, calib_views=0, seed=2))
    noisy = tmp_path / "noisy"
    proc = run_rsl("synth", box_mesh, noisy, "--scenario", "push", "--cameras", "1", "--frames", "3",
                   "--resolution", "32", "--markers", "50", "--calib-views", "0", "--seed", "2",
                   "--marker-noise", "0.003")
    assert proc.returncode == 0, proc.stderr
    d = load_capture(noisy).markers() - load_capture(clean).markers()
    assert d.shape == (3, 50, 3)
    assert abs(d.mean()) < 1e-3 and 0.0025 < d.std() < 0.0035
    assert tomllib.loads((noisy / "capture.toml").read_text())["synth"]["marker_noise"] == 0.003
    assert tomllib.loads((clean / "capture.toml").read_text())["synth"]["marker_noise"] == 0.0
    for rel in ("frames/cam0/000002.png", "truth/surface.npz"):
        assert (clean / rel).read_bytes() == (noisy / rel).read_bytes(), rel
    with pytest.raises(RslError, match="--marker-noise"):
        run(SynthConfig(mesh=box_mesh, out=tmp_path / "bad", marker_noise=-1.0))


def _sphere_views():
    """A unit-ish sphere (radius 0.05 m) and two cameras on opposite sides of it (+x and −x), 64 px."""
    import trimesh

    from stages.artefacts import Camera
    from stages.render.mesh_raster import look_at, render_mesh

    s = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    x, faces = np.asarray(s.vertices), np.asarray(s.faces)
    f = 32 / np.tan(np.radians(25))
    K = np.array([[f, 0, 31.5], [0, f, 31.5], [0, 0, 1.0]])
    cams, depths = [], []
    for k, eye in enumerate(([0.3, 0.02, 0.01], [-0.3, -0.01, 0.02])):
        R, t = look_at(np.array(eye), np.zeros(3), np.array([0, 0, 1.0]))
        cam = Camera(f"c{k}", K, np.zeros(5), R, t, 64, 64, 0.0)
        cams.append(cam)
        depths.append(render_mesh(x, faces, x, K, R, t, 64, 64, lambda p: np.ones_like(p), None, None, 2)[2])
    return x, faces, cams, depths


def test_visible_points_sees_the_near_side_of_a_sphere_and_agrees_with_ray_casting():
    """A point on the far side of a convex object is hidden from a camera and seen from the opposite one; the
    depth-buffer test agrees with ray casting against every triangle away from the silhouette."""
    from stages.synth_views import visible_points, visible_points_reference

    x, faces, cams, depths = _sphere_views()
    far_side = np.array([[-1.0, 0.0, 0.0], [-1.0, 0.0, 1.0]])  # the −x side, on the sphere (radius 0.05)
    far_side = far_side / np.linalg.norm(far_side, axis=1, keepdims=True) * 0.0499
    assert not visible_points(far_side, cams[0], depths[0]).any()
    assert visible_points(far_side, cams[1], depths[1]).all()
    assert not visible_points_reference(far_side, cams[0], x, faces).any()
    # surface points: barycentres of random triangles
    rng = np.random.default_rng(0)
    fi = rng.choice(len(faces), 120, replace=False)
    pts = x[faces[fi]].mean(1)
    for cam, depth in zip(cams, depths):
        fast = visible_points(pts, cam, depth)
        slow = visible_points_reference(pts, cam, x, faces)
        view = cam.center - pts
        cos = np.sum(view * pts, 1) / np.linalg.norm(view, axis=1) / np.linalg.norm(pts, axis=1)
        # away from the silhouette (beyond 60° from facing the camera the nearest sample of a pixel lies more
        # than the tolerance in front of a point on this coarse 22-px-wide sphere: seen by the ray, not the buffer)
        clear = np.abs(cos) > 0.5
        assert clear.sum() > 40 and 0.25 < fast.mean() < 0.6
        np.testing.assert_array_equal(fast[clear], slow[clear])
        np.testing.assert_array_equal(fast[clear], cos[clear] > 0)
    # outside the image: not seen
    assert not visible_points(np.array([[0.0, 0.5, 0.0]]), cams[0], depths[0]).any()


def test_occlude_markers_keeps_markers_seen_by_enough_cameras():
    from stages.steps.synth import occlude_markers

    x, faces, cams, depths = _sphere_views()
    pts = np.array([[0.0499, 0, 0], [-0.0499, 0, 0]])[None]  # near side of camera 0, far side of camera 0
    seen = np.stack([visible_points_counts(pts[0], cams, depths)])
    assert seen.tolist() == [[1, 1]]
    one = occlude_markers(pts, np.stack([visible_points_counts(pts[0], cams[:1], depths[:1])]), 1)
    assert np.isfinite(one[0, 0]).all() and np.isnan(one[0, 1]).all()  # a single camera: the far marker dropped
    both = occlude_markers(pts, seen, 1)
    np.testing.assert_array_equal(both, pts)  # seen from the other side: kept
    with pytest.raises(RslError, match="no marker is seen by 2 cameras at frame 0"):
        occlude_markers(pts, seen, 2)
    T = np.tile(pts, (3, 1, 1))
    counts = np.array([[1, 1], [1, 0], [0, 1]])
    got = occlude_markers(T, counts, 1)
    assert np.isnan(got[1, 1]).all() and np.isnan(got[2, 0]).all() and np.isfinite(got[[0, 1], 0]).all()
    counts[0, 1] = 0  # marker 1 not seen at frame 0: kept where it is seen (rsl adapt binds it to its track)
    late = occlude_markers(T, counts, 1)
    assert np.isnan(late[[0, 1], 1]).all() and np.isfinite(late[2, 1]).all()


def visible_points_counts(points, cams, depths):
    from stages.synth_views import visible_points

    return sum(visible_points(points, c, d).astype(int) for c, d in zip(cams, depths))


def test_marker_visibility_leaves_gaps_and_zero_leaves_the_capture_unchanged(box_mesh, tmp_path):
    """--marker-visibility 0 writes the capture of before (markers.csv byte for byte); with 1 camera and N = 1
    the markers it does not see are gaps, and the ones written are the positions of N = 0."""
    base = dict(mesh=box_mesh, scenario="push", cameras=1, frames=3, resolution=32, markers=40,
                calib_views=0, seed=4)
    ref = run(SynthConfig(out=tmp_path / "ref", **base))
    zero = tmp_path / "zero"
    proc = run_rsl("synth", box_mesh, zero, "--scenario", "push", "--cameras", "1", "--frames", "3",
                   "--resolution", "32", "--markers", "40", "--calib-views", "0", "--seed", "4",
                   "--marker-visibility", "0")
    assert proc.returncode == 0, proc.stderr
    for rel in ("markers.csv", "frames/cam0/000002.png", "truth/surface.npz"):
        assert (ref / rel).read_bytes() == (zero / rel).read_bytes(), rel
    vis = tmp_path / "vis"
    proc = run_rsl("synth", box_mesh, vis, "--scenario", "push", "--cameras", "1", "--frames", "3",
                   "--resolution", "32", "--markers", "40", "--calib-views", "0", "--seed", "4",
                   "--marker-visibility", "1")
    assert proc.returncode == 0, proc.stderr
    assert "lost to occlusion" in " ".join(proc.stderr.split())
    for rel in ("frames/cam0/000002.png", "truth/surface.npz"):
        assert (ref / rel).read_bytes() == (vis / rel).read_bytes(), rel
    import csv

    all_m = load_capture(ref).markers()
    with open(vis / "markers.csv") as f:
        rows = [r for r in csv.DictReader(f)]
    ids = sorted({int(r["marker"]) for r in rows})
    got = load_capture(vis).markers()
    assert got.shape == (3, len(ids), 3) and 5 < len(ids) < 40  # a box seen by one camera: some faces hidden
    seen = np.isfinite(got[..., 0])
    np.testing.assert_allclose(got[seen], all_m[:, ids][seen], rtol=1e-8)
    assert seen[0].any() and seen.any(axis=0).all()  # a marker first seen later stays (rsl adapt binds it)
    with pytest.raises(RslError, match="--marker-visibility 2 asks for more cameras than --cameras 1"):
        run(SynthConfig(out=tmp_path / "bad", marker_visibility=2, **base))
