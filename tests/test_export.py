"""`rsl export` on fabricated workspaces: stress, forces, VTU/PVD, plots, scan, bad input."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import brentq

from stages.artefacts import AdaptArtefact, Provenance
from stages.steps.export import ExportConfig, read_pvd, run, select_rows, load_sequence
from stages.sim.materials import lame
from test_stress_meshes import block_artefact

E, NU, FPS = 2.0e5, 0.4, 20.0
SIZE = (0.1, 0.02, 0.02)


def snh_uniaxial(l1, mu, lam):
    """Stable Neo-Hookean under F = diag(l1, l2, l2) with zero lateral traction: (l2, P11, σ11).
    P_ii = μ'(1 − 1/(I_C+1)) l_i + λ'(J − α) J / l_i, μ' = 4μ/3, λ' = λ + 5μ/6, α = 1 + 3μ'/(4λ')."""
    mu_s, lam_s = 4.0 / 3.0 * mu, lam + 5.0 / 6.0 * mu
    alpha = 1.0 + 0.75 * mu_s / lam_s

    def p(l2, li):
        ic, J = l1 * l1 + 2 * l2 * l2, l1 * l2 * l2
        return mu_s * (1 - 1 / (ic + 1)) * li + lam_s * (J - alpha) * J / li

    l2 = brentq(lambda s: p(s, s), 0.3, 1.5, xtol=1e-15)
    P11 = p(l2, l1)
    return l2, P11, P11 / (l2 * l2)


def write_capture(root: Path, mesh, controls: dict, young=E, poisson=NU, model="stable_neohookean",
                  fps=FPS, gravity=(0.0, 0.0, 0.0)) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    lines = [f"v {a:.9g} {b:.9g} {c:.9g}" for a, b, c in mesh.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.surface_faces]
    (root / "object.obj").write_text("\n".join(lines) + "\n")
    (root / "capture.toml").write_text(
        f'[capture]\nname = "block"\nfps = {fps}\ngravity = {list(gravity)}\ncameras = []\n'
        f'[object]\nmesh = "object.obj"\ndensity = {mesh.density}\n'
        f'[material]\nmodel = "{model}"\nyoung = {young}\npoisson = {poisson}\n')
    (root / "controls.json").write_text(json.dumps(controls))
    return root


def stretch_controls(stretches, l2s):
    """Two handles: the x=0 face fixed, the x=L face pulled to x = λ1 L (targets = F X exactly)."""
    eps = 1e-6
    left = {"name": "left", "select": {"box": [[-eps, -1, -1], [eps, 1, 1]]}, "stiffness": 1e4,
            "poses": [[0, 0, 0, 1, 0, 0, 0]] * len(stretches)}
    right = {"name": "right", "select": {"box": [[SIZE[0] - eps, -1, -1], [SIZE[0] + eps, 1, 1]]},
             "stiffness": 1e4, "poses": [[(l1 - 1) * SIZE[0], 0, 0, 1, 0, 0, 0] for l1 in stretches]}
    return {"handles": [left, right]}


def stretch_workspace(root: Path, stretches: np.ndarray, mode: str, loss_kind: str, window: int,
                      extra: dict | None = None) -> dict:
    """Workspace ROOT/ws: block mesh, adapt.h5 (``mode``, ``loss_kind``, ``window``, ``extra``) of a uniaxial
    stretch ramp (homogeneous F) by ``stretches`` (T,), capture folder ROOT/capture."""
    mesh = block_artefact(SIZE, (5, 2, 2), density=1000.0)
    ws = root / "ws"
    ws.mkdir(parents=True)
    mesh.save(ws / "mesh.h5")
    mu, lam = lame(E, NU)
    l2s = np.array([snh_uniaxial(l1, mu, lam)[0] for l1 in stretches])
    cap = write_capture(root / "capture", mesh, stretch_controls(stretches, l2s))
    pos = np.stack([mesh.vertices * np.array([l1, l2, l2]) for l1, l2 in zip(stretches, l2s)])
    T = len(stretches)
    AdaptArtefact(
        frames=np.arange(T), young=np.full((T, 1), E), poisson=np.full((T, 1), NU), z=np.zeros((T, 0)),
        positions=pos, loss=np.linspace(1.0, 0.1, T), time_forward_s=np.full(T, 0.1),
        time_backward_s=np.full(T, 0.2), time_render_s=np.full(T, 0.05), time_total_s=np.full(T, 0.4),
        region_names=["body"], mode=mode, space="full", loss_kind=loss_kind, window=window, extra=extra or {},
    ).save(ws / "adapt.h5", Provenance.make({"capture": str(cap), "workspace": str(ws)}))
    return {"ws": ws, "cap": cap, "mesh": mesh, "stretches": stretches, "l2s": l2s, "root": root, "positions": pos}


@pytest.fixture(scope="module")
def stretch_ws(tmp_path_factory):
    """Workspace: block mesh, adapt.h5 of a uniaxial stretch ramp (homogeneous F), capture folder."""
    stretches = np.linspace(1.0, 1.2, 5)
    # offline, window T: one trajectory, so the forces come from its positions
    return stretch_workspace(tmp_path_factory.mktemp("export"), stretches, "offline", "markers", len(stretches))


def read_csv(path: Path) -> list[dict]:
    with open(path) as f:
        return list(csv.DictReader(f))


# ------------------------------------------------------------------------------------------ stress
def test_stress_h5_and_summary_match_closed_form(stretch_ws):
    out = run(ExportConfig(workspace=stretch_ws["ws"], stress=True))
    assert out == stretch_ws["ws"] / "export"
    mu, lam = lame(E, NU)
    from stages.artefacts import StressArtefact, read_provenance

    art = StressArtefact.load(out / "stress.h5")
    vm, vmv, sig = art.von_mises_tet, art.von_mises_vertex, art.cauchy_tet
    assert art.material_model == "stable_neohookean" and art.region_names == ["body"]
    np.testing.assert_allclose(art.time_s, np.arange(len(stretch_ws["stretches"])) / FPS)
    assert read_provenance(out / "stress.h5")["config"]["stress"] is True
    rows = read_csv(out / "stress_summary.csv")
    assert len(rows) == len(stretch_ws["stretches"])
    for i, l1 in enumerate(stretch_ws["stretches"]):
        s11 = snh_uniaxial(l1, mu, lam)[2]
        np.testing.assert_allclose(vm[i], abs(s11), rtol=1e-2, atol=1e-6 * E)
        np.testing.assert_allclose(vmv[i], abs(s11), rtol=1e-2, atol=1e-6 * E)
        np.testing.assert_allclose(sig[i, :, 0, 0], s11, rtol=1e-2, atol=1e-6 * E)
        assert int(rows[i]["frame"]) == i and float(rows[i]["time_s"]) == pytest.approx(i / FPS)
        assert float(rows[i]["max_pa"]) == pytest.approx(abs(s11), rel=1e-2, abs=1e-6 * E)
    assert vm[0].max() < 1e-6 * E  # frame 0 is the rest state


def test_forces_csv_matches_closed_form(stretch_ws):
    pytest.importorskip("stages.sim.scene")
    out = run(ExportConfig(workspace=stretch_ws["ws"], forces=True, out=stretch_ws["root"] / "forces"))
    rows = read_csv(out / "forces.csv")
    assert list(rows[0])[:7] == ["frame", "time_s", "name", "kind", "fx_N", "fy_N", "fz_N"]
    assert "magnitude_sum_N" in rows[0]
    T = len(stretch_ws["stretches"])
    assert len(rows) == T * 2  # one row per frame and handle
    mu, lam = lame(E, NU)
    area = SIZE[1] * SIZE[2]
    for i, l1 in enumerate(stretch_ws["stretches"]):
        P11 = snh_uniaxial(l1, mu, lam)[1]
        r = {row["name"]: row for row in rows if int(row["frame"]) == i}
        assert float(r["right"]["fx_N"]) == pytest.approx(-P11 * area, rel=1e-2, abs=1e-9)
        assert float(r["left"]["fx_N"]) == pytest.approx(P11 * area, rel=1e-2, abs=1e-9)
        assert float(r["right"]["magnitude_sum_N"]) == pytest.approx(P11 * area, rel=1e-2, abs=1e-9)
        # handle targets are F X exactly along x; the spring pulls the lateral contraction back
        assert float(r["right"]["applied_fx_N"]) == pytest.approx(0.0, abs=1e-9)
        assert int(r["right"]["n_vertices"]) == 9


# ------------------------------------------------------------------------------------------ VTU
def test_vtk_series_reads_back(stretch_ws):
    import meshio

    out = run(ExportConfig(workspace=stretch_ws["ws"], vtk=True, out=stretch_ws["root"] / "vtk_out"))
    pvd = out / "vtk" / "adapt.pvd"
    series = read_pvd(pvd)
    mesh = stretch_ws["mesh"]
    assert len(series) == len(stretch_ws["stretches"])
    mu, lam = lame(E, NU)
    for i, (t, path) in enumerate(series):
        assert t == pytest.approx(i / FPS)
        m = meshio.read(path)
        assert m.points.shape == mesh.vertices.shape
        np.testing.assert_array_equal(m.cells_dict["tetra"], mesh.tets)
        for key in ("displacement", "von_mises", "internal_force"):
            assert key in m.point_data
        for key in ("von_mises", "region", "young_pa"):
            assert key in m.cell_data
        l1, l2 = stretch_ws["stretches"][i], stretch_ws["l2s"][i]
        np.testing.assert_allclose(m.point_data["displacement"], mesh.vertices * ([l1, l2, l2]) - mesh.vertices,
                                   atol=1e-12)
        np.testing.assert_allclose(m.cell_data["von_mises"][0], abs(snh_uniaxial(l1, mu, lam)[2]),
                                   rtol=1e-2, atol=1e-6 * E)


# ------------------------------------------------------------------------------------------ plots
def test_plots_are_pngs_with_content(stretch_ws):
    import imageio.v3 as iio

    out = run(ExportConfig(workspace=stretch_ws["ws"], plots=True, out=stretch_ws["root"] / "plots_out"))
    for name in ("young.png", "loss.png", "timing.png", "stress.png"):
        img = iio.imread(out / "plots" / name)
        assert img.ndim == 3 and img.shape[0] > 100
        assert img[..., :3].std() > 5  # not blank


# ------------------------------------------------------------------------------------------ scan
def test_scan_distance_of_a_plane_above_the_top_face(stretch_ws):
    """Scan = a dense grid δ above the top face of the last frame: scan→surface is exactly δ,
    and the top-face vertices are δ from the scan."""
    mesh = stretch_ws["mesh"]
    l1, l2 = stretch_ws["stretches"][-1], stretch_ws["l2s"][-1]
    top_z = SIZE[2] * l2
    delta = 0.002
    gx = np.linspace(0.0, SIZE[0] * l1, 41)
    gy = np.linspace(0.0, SIZE[1] * l2, 9)
    pts = np.stack(np.meshgrid(gx, gy, [top_z + delta], indexing="ij"), -1).reshape(-1, 3)
    scan = stretch_ws["root"] / "scan.xyz"
    np.savetxt(scan, pts)
    out = run(ExportConfig(workspace=stretch_ws["ws"], scan=scan, out=stretch_ws["root"] / "scan_out"))
    summary = json.loads((out / "scan" / "scan_distance.json").read_text())
    assert summary["frame"] == len(stretch_ws["stretches"]) - 1
    assert summary["scan_to_sim_mean_m"] == pytest.approx(delta, rel=1e-4)
    rows = read_csv(out / "scan" / "surface_distance.csv")
    top = {int(r["vertex"]): float(r["distance_m"]) for r in rows if np.isclose(mesh.vertices[int(r["vertex"]), 2], SIZE[2])}
    assert len(top) == 18 and np.allclose(list(top.values()), delta, rtol=1e-6)
    assert summary["chamfer_m"] > delta / 2
    assert not (out / "stress.h5").exists()  # --scan alone makes only the scan product
    import open3d as o3d

    m = o3d.io.read_triangle_mesh(str(next((out / "scan").glob("*.ply"))))
    assert len(m.vertices) == mesh.n_vertices and m.has_vertex_colors()


# ------------------------------------------------------------------------------------------ frames
def test_select_rows(stretch_ws):
    seq = load_sequence(ExportConfig(workspace=stretch_ws["ws"]))
    assert select_rows(seq, "all").tolist() == [0, 1, 2, 3, 4]
    assert select_rows(seq, "last").tolist() == [4]
    assert select_rows(seq, "0,2").tolist() == [0, 2]
    assert select_rows(seq, "1:5:2").tolist() == [1, 3]
    with pytest.raises(Exception, match="holds no frame 9"):
        select_rows(seq, "9")


# ------------------------------------------------------------------------------------------ bad input
def test_cli_missing_adapt(rsl, tmp_path):
    (tmp_path / "ws").mkdir()
    p = rsl("export", "-w", tmp_path / "ws", "--stress")
    assert p.returncode != 0
    assert "adapt.h5: file not found" in p.stderr


def test_mesh_mismatch_and_bad_frames(stretch_ws, tmp_path):
    import shutil

    from stages.errors import RslError

    ws = tmp_path / "ws"
    ws.mkdir()
    shutil.copy(stretch_ws["ws"] / "adapt.h5", ws / "adapt.h5")
    block_artefact(SIZE, (3, 1, 1)).save(ws / "mesh.h5")
    with pytest.raises(RslError, match="adapt.h5: positions hold 54 vertices but .*mesh.h5 has 16"):
        run(ExportConfig(workspace=ws, stress=True))
    with pytest.raises(RslError, match="--frames 'x:y' is not all, last"):
        select_rows(load_sequence(ExportConfig(workspace=stretch_ws["ws"])), "x:y")
    with pytest.raises(RslError, match="--source 'both' is none of adapt, partial, rollout"):
        run(ExportConfig(workspace=stretch_ws["ws"], source="both"))


def test_cli_stress_runs(rsl, stretch_ws, tmp_path):
    p = rsl("export", "-w", stretch_ws["ws"], "--stress", "--out", tmp_path / "o")
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "o" / "stress.h5").exists() and "export:" in p.stderr


# ------------------------------------------------------------------------------------------ Gaussians
@pytest.fixture(scope="module")
def gauss_ws(stretch_ws):
    """stretch_ws plus gaussians.h5 (Gaussians spread over every tet) and one capture camera."""
    from stages.artefacts import Camera, CamerasArtefact, GaussiansArtefact
    from stages.render.mesh_raster import look_at

    mesh = stretch_ws["mesh"]
    rng = np.random.default_rng(0)
    per_tet = 3
    host = np.repeat(np.arange(mesh.n_tets), per_tet)
    bary = rng.dirichlet(np.ones(4) * 2, size=len(host))
    G = len(host)
    sh = ((rng.uniform(0.2, 0.9, (G, 3)) - 0.5) / 0.28209479177387814)[:, None, :]
    GaussiansArtefact(host, bary, np.full((G, 3), np.log(0.004)), np.tile([1.0, 0, 0, 0], (G, 1)),
                      np.full(G, 3.0), sh, {}, np.zeros(3)).save(stretch_ws["ws"] / "gaussians.h5")
    R, t = look_at(np.array([0.06, -0.25, 0.08]), np.array([0.06, 0.01, 0.01]), np.array([0.0, 0.0, -1.0]))
    K = np.array([[150.0, 0, 47.5], [0, 150.0, 35.5], [0, 0, 1]])
    CamerasArtefact([Camera("cam0", K, np.zeros(5), R, t, 96, 72)], "synth").save(stretch_ws["ws"] / "cameras.h5")
    yield stretch_ws
    (stretch_ws["ws"] / "gaussians.h5").unlink()
    (stretch_ws["ws"] / "cameras.h5").unlink()


def test_ply_frames_read_back_deformed(gauss_ws):
    from stages.artefacts import GaussiansArtefact
    from stages.render.ply import read_ply

    out = run(ExportConfig(workspace=gauss_ws["ws"], ply=True, frames="0,4", out=gauss_ws["root"] / "ply_out"))
    gauss = GaussiansArtefact.load(gauss_ws["ws"] / "gaussians.h5")
    mesh = gauss_ws["mesh"]
    l1, l2 = gauss_ws["stretches"][4], gauss_ws["l2s"][4]
    F = np.diag([l1, l2, l2])
    ply = read_ply(out / "ply" / "frame_000004.ply")
    x = mesh.vertices @ F.T
    np.testing.assert_allclose(ply["means"], np.einsum("gk,gkd->gd", gauss.bary, x[mesh.tets[gauss.host_tet]]),
                               atol=1e-6)
    # covariance F Σ Fᵀ of an isotropic rest Gaussian: std devs s·(λ1, λ2, λ2)
    np.testing.assert_allclose(np.sort(np.exp(ply["log_scales"]), axis=1),
                               np.tile(np.sort(0.004 * np.array([l1, l2, l2])), (len(gauss.host_tet), 1)), rtol=1e-4)
    np.testing.assert_allclose(ply["sh"], gauss.sh, atol=1e-6)
    np.testing.assert_allclose(ply["opacity_logit"], gauss.opacity_logit)
    assert sorted(p.name for p in (out / "ply").iterdir()) == ["frame_000000.ply", "frame_000004.ply"]
    # coloured by stress: the rest frame is stress-free, the stretched one is uniformly stressed (one colour)
    out = run(ExportConfig(workspace=gauss_ws["ws"], ply=True, ply_stress=True, frames="last",
                           out=gauss_ws["root"] / "ply_stress"))
    sh = read_ply(out / "ply" / "frame_000004.ply")["sh"]
    assert sh.shape[1] == 1 and np.ptp(sh[:, 0, :], axis=0).max() < 1e-3


def test_render_pngs_and_videos(gauss_ws):
    import cv2
    import imageio.v3 as iio

    out = run(ExportConfig(workspace=gauss_ws["ws"], render=True, frames="0:5:2", orbit_views=4, render_size=64,
                           out=gauss_ws["root"] / "render_out"))
    r = out / "render"
    cam = sorted((r / "cam0").glob("*.png"))
    assert [p.name for p in cam] == [f"{k}_{f:06d}.png" for k in ("appearance", "stress") for f in (0, 2, 4)]
    img = iio.imread(r / "cam0" / "appearance_000004.png")
    assert img.shape == (72, 96, 3) and img.std() > 10  # the block covers part of a black background
    stress = iio.imread(r / "cam0" / "stress_000004.png")
    assert stress.shape[0] == 72 and stress.shape[1] > 96  # colour bar appended
    assert np.abs(stress[:, :96].astype(int) - 255).max() > 50  # coloured Gaussians on white
    orbit = sorted((r / "orbit").glob("appearance_*.png"))
    assert len(orbit) == 3 and iio.imread(orbit[0]).shape == (64, 64, 3)
    assert iio.imread(orbit[0]).std() > 10
    for name in ("cam0_appearance.mp4", "cam0_stress.mp4", "orbit_stress.mp4"):
        cap = cv2.VideoCapture(str(r / name))
        assert cap.isOpened() and int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 3
        cap.release()


def test_colmap_model_round_trip(gauss_ws, tmp_path):
    from stages.artefacts import CamerasArtefact
    from stages.vision.colmap_io import read_colmap

    run(ExportConfig(workspace=gauss_ws["ws"], colmap=tmp_path / "colmap", out=tmp_path / "o"))
    cams = read_colmap(tmp_path / "colmap")
    ref = CamerasArtefact.load(gauss_ws["ws"] / "cameras.h5").cameras
    assert [c.name for c in cams] == [c.name for c in ref]
    np.testing.assert_allclose(cams[0].R, ref[0].R, atol=1e-9)
    np.testing.assert_allclose(cams[0].K, ref[0].K, atol=1e-9)
    assert not (tmp_path / "o" / "stress.h5").exists()


def test_no_flag_exports_everything_available(gauss_ws):
    out = run(ExportConfig(workspace=gauss_ws["ws"], frames="last", orbit_views=2, render_size=32,
                           out=gauss_ws["root"] / "all_out"))
    for rel in ("stress.h5", "stress_summary.csv", "forces.csv", "vtk/adapt.pvd", "vtk/frame_000004.vtu",
                "ply/frame_000004.ply", "render/cam0/stress_000004.png", "render/orbit/stress_000004_001.png",
                "render/orbit_stress.mp4", "plots/young.png", "plots/forces.png"):
        assert (out / rel).is_file(), rel
    assert not (out / "ply" / "frame_000000.ply").exists()  # --frames last
