"""`rsl tetrahedralize`: tet meshes taken as they are and made by fTetWild, orientation, regions, quality."""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import meshio
import numpy as np
import pytest
import trimesh

from stages.artefacts import MeshArtefact, read_provenance
from stages.capture import CaptureError
from stages.progress import SilentReporter
from stages.sim.mesh import signed_volumes
from stages.steps.tetrahedralize import (TetrahedralizeConfig, boundary_faces, dihedral_angles, enclosed_volume,
                                   orient_tets, run, winding_numbers)

TOML = """[capture]
name = "{name}"
[object]
mesh = "{mesh}"
density = {density}
"""


def make_capture(root: Path, mesh_src: Path | None = None, mesh_name: str | None = None, density: float = 1000.0,
                 controls: dict | None = None) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    name = mesh_name or mesh_src.name
    if mesh_src is not None:
        shutil.copy(mesh_src, root / name)
    (root / "capture.toml").write_text(TOML.format(name=root.name, mesh=name, density=density))
    if controls is not None:
        (root / "controls.json").write_text(json.dumps(controls))
    return root


def check_mesh(m: MeshArtefact, density: float, volume: float, rel: float) -> None:
    """Positive tets, volume = enclosed volume of the outer surface ≈ ``volume``, masses = ρV, Dm⁻¹ right."""
    vol = signed_volumes(m.vertices, m.tets)
    assert np.all(vol > 0)
    np.testing.assert_allclose(m.rest_volumes, vol, rtol=1e-12)
    assert m.rest_volumes.sum() == pytest.approx(volume, rel=rel)
    assert m.vertex_masses.sum() == pytest.approx(density * m.rest_volumes.sum(), rel=1e-12)
    assert np.all(m.vertex_masses > 0)
    # The outward surface encloses exactly the tet volume (divergence theorem) and is closed.
    assert enclosed_volume(m.vertices, m.surface_faces) == pytest.approx(m.rest_volumes.sum(), rel=1e-10)
    assert trimesh.Trimesh(m.vertices, m.surface_faces, process=False).is_watertight
    dm = np.stack([m.vertices[m.tets[:, k]] - m.vertices[m.tets[:, 0]] for k in (1, 2, 3)], axis=-1)
    np.testing.assert_allclose(np.einsum("mij,mjk->mik", m.dm_inv, dm), np.broadcast_to(np.eye(3), dm.shape),
                               atol=1e-8)
    q = m.quality
    assert q["n_tets"] == m.n_tets and q["min_volume"] == pytest.approx(vol.min())
    assert 0 < q["min_dihedral_deg"] < 70.6 < q["max_dihedral_deg"] < 180


# --------------------------------------------------------------------------- pure geometry
def _regular_tet() -> np.ndarray:
    return np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)


def test_dihedral_angles_of_regular_and_corner_tet() -> None:
    ang = dihedral_angles(_regular_tet(), np.array([[0, 1, 2, 3]]))
    np.testing.assert_allclose(ang, math.degrees(math.acos(1 / 3)), atol=1e-10)
    corner = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    ang = np.sort(dihedral_angles(corner, np.array([[0, 1, 2, 3]]))[0])
    np.testing.assert_allclose(ang, sorted([90, 90, 90] + [math.degrees(math.acos(1 / math.sqrt(3)))] * 3),
                               atol=1e-10)


def test_orientation_and_boundary_of_a_cube() -> None:
    box = trimesh.creation.box()  # the unit cube centred on the origin
    v = np.array(box.vertices)
    # The 6-tet Kuhn subdivision of the cube, half of them written inverted.
    lo = np.argmin(v.sum(1))
    hi = np.argmax(v.sum(1))
    idx = {tuple(np.round(p + 0.5).astype(int)): i for i, p in enumerate(v)}
    tets = []
    import itertools

    for perm in itertools.permutations(range(3)):
        path = [np.zeros(3, int)]
        for ax in perm:
            nxt = path[-1].copy()
            nxt[ax] = 1
            path.append(nxt)
        tets.append([idx[tuple(p)] for p in path])
    tets = np.array(tets)
    assert tets[0, 0] == lo and tets[0, 3] == hi
    fixed, flipped = orient_tets(v, tets)
    assert flipped == 3 and np.all(signed_volumes(v, fixed) > 0)
    faces = boundary_faces(fixed)
    assert len(faces) == 12
    assert enclosed_volume(v, faces) == pytest.approx(1.0)
    # Outward: each face normal points away from the centre.
    p = v[faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.all(np.einsum("ij,ij->i", n, p.mean(1)) > 0)


def test_folded_tet_is_detected() -> None:
    # Two tets on either side of the triangle (0,1,2); pushing vertex 4 through it folds the mesh.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 1], [0.2, 0.2, -1]], float)
    tets, _ = orient_tets(v, np.array([[0, 1, 2, 3], [0, 1, 2, 4]]))
    assert len(boundary_faces(tets)) == 6
    v[4, 2] = 0.5  # now on the same side as vertex 3: overlapping tets
    tets, _ = orient_tets(v, np.array([[0, 1, 2, 3], [0, 1, 2, 4]]))
    with pytest.raises(ValueError, match=r"tets \[0, 1\] overlap"):
        boundary_faces(tets)


def test_winding_number_inside_outside() -> None:
    s = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    pts = np.array([[0, 0, 0], [0.5, 0.2, -0.3], [0, 0, 1.5], [2, 2, 2], [0.9, 0, 0]])
    w = winding_numbers(pts, np.asarray(s.vertices), np.asarray(s.faces), chunk=2)
    np.testing.assert_allclose(w, [1, 1, 0, 0, 1], atol=1e-6)
    w_in = winding_numbers(pts, np.asarray(s.vertices), np.asarray(s.faces)[:, ::-1])
    np.testing.assert_allclose(w_in, [-1, -1, 0, 0, -1], atol=1e-6)


# --------------------------------------------------------------------------- the stage
def test_sample_bar(sample_data: Path, tmp_path: Path) -> None:
    r = SilentReporter()
    out = run(TetrahedralizeConfig(sample_data / "bar", tmp_path), r)
    m = MeshArtefact.load(out)
    src = meshio.read(sample_data / "bar" / "object.mesh")
    assert m.n_tets == len(src.cells_dict["tetra"]) <= 2000
    check_mesh(m, 1070.0, 0.25 * (0.5 / 6) ** 2, rel=1e-4)
    assert m.region_names == ["body"] and np.all(m.tet_region == 0)
    assert set(m.handles) == {"left", "right"}
    assert np.allclose(m.vertices[m.handles["right"], 0], m.vertices[:, 0].max())
    prov = read_provenance(out)
    assert {Path(i["path"]).name for i in prov["inputs"]} == {"capture.toml", "object.mesh", "controls.json"}
    assert "979 tets" in r.messages[-1] and "dihedral" in r.messages[-1]
    from stages.capture import read_image

    assert read_image(tmp_path / "mesh.png").shape[2] == 3  # the preview picture
    left = sorted(p.name for p in tmp_path.iterdir() if p.name != ".rsl_hashes.json")  # the input-hash cache
    assert left == ["mesh.h5", "mesh.png"]  # no temp file left


def test_sample_dino_standing_on_floor(sample_data: Path, tmp_path: Path) -> None:
    m = MeshArtefact.load(run(TetrahedralizeConfig(sample_data / "dino", tmp_path)))
    assert m.n_tets <= 2000 and m.handles == {}
    assert m.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    mesh = meshio.read(sample_data / "dino" / "object.mesh")
    t = mesh.cells_dict["tetra"]
    check_mesh(m, 1070.0, abs(signed_volumes(mesh.points, t)).sum(), rel=1e-9)


def test_box_stl_with_ftetwild(shared_data: Path, tmp_path: Path) -> None:
    cap = make_capture(tmp_path / "box", shared_data / "pytetwild_testdata" / "box.stl", density=500.0)
    m = MeshArtefact.load(run(TetrahedralizeConfig(cap, tmp_path / "ws", edge_length=0.15, order=1)))
    surface = trimesh.load(cap / "box.stl")
    check_mesh(m, 500.0, surface.volume, rel=0.01)
    assert m.quality["source"] == "ftetwild" and m.quality["flipped_tets"] == m.n_tets  # fTetWild's are negative
    assert m.quality["input_surface_volume"] == pytest.approx(8.0)


def test_max_tets_coarsens(shared_data: Path, tmp_path: Path) -> None:
    cap = make_capture(tmp_path / "box", shared_data / "pytetwild_testdata" / "box.stl")
    m = MeshArtefact.load(run(TetrahedralizeConfig(cap, tmp_path / "ws", edge_length=0.15, max_tets=800)))
    assert m.n_tets <= 800
    assert m.rest_volumes.sum() == pytest.approx(8.0, rel=0.01)


def test_dino_surface_retetrahedralized(sample_data: Path, tmp_path: Path) -> None:
    """A curved surface through fTetWild: volume within 1 % of what the surface encloses."""
    m0 = MeshArtefact.load(run(TetrahedralizeConfig(sample_data / "dino", tmp_path / "ws0")))
    root = tmp_path / "dino_surface"
    root.mkdir()
    trimesh.Trimesh(m0.vertices, m0.surface_faces).export(root / "dino.obj")
    make_capture(root, mesh_name="dino.obj", density=1070.0)
    m = MeshArtefact.load(run(TetrahedralizeConfig(root, tmp_path / "ws", edge_length=0.08, order=1)))
    check_mesh(m, 1070.0, trimesh.load(root / "dino.obj").volume, rel=0.01)


def test_regions_from_closed_meshes(sample_data: Path, tmp_path: Path) -> None:
    root = make_capture(tmp_path / "bar", sample_data / "bar" / "object.mesh")
    (root / "regions").mkdir()
    trimesh.creation.box(extents=[0.13, 0.2, 0.2], transform=trimesh.transformations.translation_matrix(
        [0.0625 + 0.001, 0, 0])).export(root / "regions" / "stiff.obj")
    trimesh.creation.box(extents=[0.01, 0.01, 0.01], transform=trimesh.transformations.translation_matrix(
        [5, 5, 5])).export(root / "regions" / "elsewhere.obj")
    r = SilentReporter()
    m = MeshArtefact.load(run(TetrahedralizeConfig(root, tmp_path / "ws"), r))
    assert m.region_names == ["body", "stiff"]  # 'elsewhere' holds no tet: dropped with a warning
    assert any("region 'elsewhere'" in s and s.startswith("warning") for s in r.messages)
    c = m.vertices[m.tets].mean(1)[:, 0]
    np.testing.assert_array_equal(m.tet_region == 1, c > -0.0015)
    assert 0 < (m.tet_region == 1).sum() < m.n_tets


def test_surface_with_small_hole_is_repaired(tmp_path: Path) -> None:
    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    box.update_faces(np.arange(len(box.faces)) < 10)  # one quad side missing
    root = tmp_path / "cap"
    root.mkdir()
    box.export(root / "object.obj")
    make_capture(root, mesh_name="object.obj")
    r = SilentReporter()
    m = MeshArtefact.load(run(TetrahedralizeConfig(root, tmp_path / "ws", edge_length=0.2), r))
    assert any("repaired" in s for s in r.messages)
    assert m.rest_volumes.sum() == pytest.approx(1e-3, rel=0.01)


def test_open_surface_is_refused(tmp_path: Path) -> None:
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    s.update_faces(s.vertices[s.faces].mean(1)[:, 2] < 0.035)
    root = tmp_path / "cap"
    root.mkdir()
    s.export(root / "object.obj")
    make_capture(root, mesh_name="object.obj")
    with pytest.raises(CaptureError, match=r"object.obj: the surface is not watertight \(\d+ open edges"):
        run(TetrahedralizeConfig(root, tmp_path / "ws"))
    assert not (tmp_path / "ws" / "mesh.h5").exists()


def _write_medit(path: Path, v: np.ndarray, t: np.ndarray) -> None:
    meshio.write(str(path), meshio.Mesh(v, [("tetra", t)]), file_format="medit")


def test_inverted_and_degenerate_tets_are_refused(tmp_path: Path) -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 1], [0.2, 0.2, 0.5]], float) * 0.1
    root = tmp_path / "cap"
    root.mkdir()
    _write_medit(root / "object.mesh", v, np.array([[0, 1, 2, 3], [0, 2, 1, 4]]))
    make_capture(root, mesh_name="object.mesh")
    with pytest.raises(CaptureError, match=r"object.mesh: tets \[0, 1\] overlap .* inverted"):
        run(TetrahedralizeConfig(root, tmp_path / "ws"))
    v[4] = [0.05, 0.05, 0.0]  # in the plane of face (0, 1, 2): zero volume
    _write_medit(root / "object.mesh", v, np.array([[0, 1, 2, 3], [0, 2, 1, 4]]))
    with pytest.raises(CaptureError, match=r"object.mesh: 1 degenerate tets \(e.g. tet 1"):
        run(TetrahedralizeConfig(root, tmp_path / "ws"))


def test_consistently_inverted_tet_mesh_is_reoriented(sample_data: Path, tmp_path: Path) -> None:
    src = meshio.read(sample_data / "dino" / "object.mesh")
    t = src.cells_dict["tetra"][:, [0, 2, 1, 3]]  # every tet negative, as some writers store them
    root = tmp_path / "cap"
    root.mkdir()
    _write_medit(root / "object.mesh", src.points, t)
    make_capture(root, mesh_name="object.mesh")
    m = MeshArtefact.load(run(TetrahedralizeConfig(root, tmp_path / "ws")))
    assert m.quality["flipped_tets"] == len(t)
    check_mesh(m, 1000.0, abs(signed_volumes(src.points, t)).sum(), rel=1e-9)


def test_gmsh_tet_mesh(shared_data: Path, tmp_path: Path) -> None:
    cap = make_capture(tmp_path / "t", shared_data / "ipc_sim_IPC" / "tetMeshes_bar-651.msh")
    m = MeshArtefact.load(run(TetrahedralizeConfig(cap, tmp_path / "ws")))
    src = meshio.read(cap / "tetMeshes_bar-651.msh")
    t = src.cells_dict["tetra"]
    assert m.n_tets == len(t)
    check_mesh(m, 1000.0, abs(signed_volumes(np.asarray(src.points, float), t)).sum(), rel=1e-9)


def test_tet_mesh_reruns_are_bit_identical(sample_data: Path, tmp_path: Path) -> None:
    a = MeshArtefact.load(run(TetrahedralizeConfig(sample_data / "bar", tmp_path / "a")))
    b = MeshArtefact.load(run(TetrahedralizeConfig(sample_data / "bar", tmp_path / "b")))
    for k in ("vertices", "tets", "surface_faces", "dm_inv", "vertex_masses"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))


def test_id_handles_follow_the_surface_vertices(shared_data: Path, tmp_path: Path) -> None:
    """``ids`` name vertices of the object file; on fTetWild's mesh they become the vertices at those points."""
    box = trimesh.load(shared_data / "pytetwild_testdata" / "box.stl", process=False)
    corner = int(np.argmax(np.asarray(box.vertices).sum(1)))  # the (1, 1, 1) corner, in the file's numbering
    cap = make_capture(tmp_path / "box", shared_data / "pytetwild_testdata" / "box.stl",
                       controls={"handles": [{"name": "corner", "select": {"ids": [corner]}}]})
    m = MeshArtefact.load(run(TetrahedralizeConfig(cap, tmp_path / "ws", edge_length=0.3, preview=False)))
    # fTetWild keeps its surface within the envelope (1e-3 × the bounding-box diagonal) of the input,
    # and is not deterministic: the corner vertex lands at the corner up to that envelope.
    envelope = TetrahedralizeConfig.envelope * float(np.linalg.norm(np.ptp(np.asarray(box.vertices), axis=0)))
    assert len(m.handles["corner"]) == 1
    np.testing.assert_allclose(m.vertices[m.handles["corner"]], [[1, 1, 1]], atol=envelope)
    (cap / "controls.json").write_text(json.dumps({"handles": [{"name": "far", "select": {"ids": [99]}}]}))
    with pytest.raises(CaptureError, match=r"controls.json: 'far' selects vertex id 99 but box.stl has \d+ vertices"):
        run(TetrahedralizeConfig(cap, tmp_path / "ws", edge_length=0.3, preview=False))
