"""`rsl fit-gaussians` end to end on a tiny capture built here, plus its bad-input messages.

The capture: a 0.1 m box meshed 2×2×2 cubes × 6 tets, three 64×64 cameras around it,
and frame-0 images rendered from a known, densely seeded Gaussian set whose colours
vary over the box (so the fit must place colour, not just coverage); masks = coverage ≥ ½.
"""
from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from stages.artefacts import (Camera, CamerasArtefact, GaussiansArtefact, MasksArtefact, MeshArtefact,
                              Provenance)
from stages.capture import write_image
from stages.sim.mesh import rest_quantities

FIT_PSNR_DB = 25.0
"""PSNR the fit must reach on every camera of the test capture (frame 0)."""
SYNTH_FIT_PSNR_DB = 28.0
"""PSNR the fit must reach on every camera of a textured `rsl synth` capture (slow test)."""


def box_tet_mesh(n: int = 2, half: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, tets, boundary faces) of a cube [−half, half]³ split into n³ cubes × 6 tets (Kuhn)."""
    g = np.linspace(-half, half, n + 1)
    verts = np.array(list(itertools.product(g, g, g)))
    vid = lambda i, j, k: (i * (n + 1) + j) * (n + 1) + k  # noqa: E731
    tets = []
    for i, j, k in itertools.product(range(n), repeat=3):
        c = [vid(i + a, j + b, k + d) for a, b, d in itertools.product((0, 1), repeat=3)]
        for perm in itertools.permutations(range(3)):
            path = [0]
            cur = [0, 0, 0]
            for ax in perm:
                cur[ax] = 1
                path.append(cur[0] * 4 + cur[1] * 2 + cur[2])
            tets.append([c[p] for p in path])
    tets = np.array(tets)
    p = verts[tets]
    vol = np.linalg.det(np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], -1))
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    faces = np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]], tets[:, [1, 2, 3]]])
    key = np.sort(faces, 1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return verts, tets, faces[cnt[inv.ravel()] == 1]


def mesh_artefact(verts, tets, faces) -> MeshArtefact:
    vol, dm_inv, masses = rest_quantities(verts, tets, 1000.0)
    return MeshArtefact(verts, tets, faces, np.zeros(len(tets), np.int64), ["body"], vol, dm_inv, masses, 1000.0)


def look_at(name: str, eye, size: int = 64, f: float = 90.0) -> Camera:
    """A camera at ``eye`` looking at the origin, z up in the world."""
    eye = np.asarray(eye, float)
    fwd = -eye / np.linalg.norm(eye)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    return Camera(name, K, np.zeros(5), R, -R @ eye, size, size)


def truth_gaussians(mesh: MeshArtefact, n: int, seed: int) -> GaussiansArtefact:
    """Opaque Gaussians on the box's faces, coloured by position (red along x, green along y, blue along z)."""
    from stages.steps.fit_gaussians import seed_gaussians
    from stages.render.gaussians import color_to_sh0

    rng = np.random.default_rng(seed)
    host, bary, log_s = seed_gaussians(mesh, n, 8.0, rng)
    centres = np.einsum("gk,gkd->gd", bary, mesh.vertices[mesh.tets[host]])
    colour = 0.5 + 0.45 * np.sin(centres / 0.05 * np.array([2.0, 3.0, 1.5]))
    sh = color_to_sh0(colour)[:, None, :]
    return GaussiansArtefact(host, bary, np.repeat(log_s[:, None], 3, 1) + 0.3,
                             np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 3.0), sh)


def make_capture(root: Path, ws: Path, size: int = 64) -> dict:
    """Write capture/ (toml, object.obj, frames) and ws/ (mesh.h5, cameras.h5, masks.h5)."""
    from stages.render.gaussians import BoundGaussians

    verts, tets, faces = box_tet_mesh()
    mesh = mesh_artefact(verts, tets, faces)
    cams = [look_at(f"cam{i}", 0.35 * np.array([np.cos(a), np.sin(a), 0.6]), size)
            for i, a in enumerate((0.3, 2.4, 4.4))]
    root.mkdir(parents=True)
    ws.mkdir(parents=True)
    (root / "capture.toml").write_text(
        '[capture]\nname = "box"\nfps = 30.0\ncameras = ["cam0", "cam1", "cam2"]\n'
        '[object]\nmesh = "object.obj"\ndensity = 1000.0\n')
    (root / "object.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in verts)
                                     + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
    truth = BoundGaussians.from_artefact(truth_gaussians(mesh, 6000, seed=7), mesh)
    masks = {}
    x = torch.as_tensor(verts, dtype=torch.float32)
    with torch.no_grad():
        for cam in cams:
            out = truth.render(x, cam)
            write_image(root / "frames" / cam.name / "000000.png",
                        np.round(out.image.numpy() * 255).astype(np.uint8))
            masks[cam.name] = (out.alpha.numpy() >= 0.5)[None]
    mesh.save(ws / "mesh.h5")
    CamerasArtefact(cams, "synth").save(ws / "cameras.h5")
    MasksArtefact(masks, "truth").save(ws / "masks.h5")
    return {"mesh": mesh, "cameras": cams}


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    from conftest import run_rsl

    base = tmp_path_factory.mktemp("fit")
    cap, ws = base / "capture", base / "ws"
    make_capture(cap, ws)
    proc = run_rsl("fit-gaussians", cap, "-w", ws, "--iterations", "60", "--gaussians", "1500")
    return cap, ws, proc


def test_fit_gaussians_reaches_psnr(fitted):
    cap, ws, proc = fitted
    assert proc.returncode == 0, proc.stderr
    art = GaussiansArtefact.load(ws / "gaussians.h5")
    assert art.host_tet.shape == (1500,)
    assert set(art.fit_psnr) == {"cam0", "cam1", "cam2"}
    assert min(art.fit_psnr.values()) >= FIT_PSNR_DB, art.fit_psnr
    for c in ("cam0", "cam1", "cam2"):
        assert (ws / "fit_gaussians" / f"{c}.png").is_file()
    assert "PSNR" in proc.stderr
    assert json.loads(json.dumps(art.fit_psnr))  # JSON-able for rsl info


def test_fit_gaussians_is_reproducible(fitted, tmp_path):
    """Same seed and inputs → bit-identical parameters (a shorter run, through the library)."""
    from stages.steps.fit_gaussians import FitGaussiansConfig, run

    cap, ws, _ = fitted
    arrays = []
    for i in range(2):
        w = tmp_path / f"ws{i}"
        w.mkdir()
        for f in ("mesh.h5", "cameras.h5", "masks.h5"):
            (w / f).write_bytes((ws / f).read_bytes())
        run(FitGaussiansConfig(capture=cap, workspace=w, iterations=3, gaussians=300, seed=3))
        a = GaussiansArtefact.load(w / "gaussians.h5")
        arrays.append(np.concatenate([a.sh.ravel(), a.log_scales.ravel(), a.bary.ravel()]))
    np.testing.assert_array_equal(arrays[0], arrays[1])


def test_fit_gaussians_missing_mesh_fails_cleanly(fitted, tmp_path, rsl):
    cap, _, _ = fitted
    proc = rsl("fit-gaussians", cap, "-w", tmp_path / "empty")
    assert proc.returncode != 0
    assert "mesh.h5" in proc.stderr and "not found" in proc.stderr


def test_fit_gaussians_camera_seeing_nothing_fails(fitted, tmp_path, rsl):
    cap, ws, _ = fitted
    w = tmp_path / "ws"
    w.mkdir()
    for f in ("mesh.h5", "masks.h5"):
        (w / f).write_bytes((ws / f).read_bytes())
    cams = CamerasArtefact.load(ws / "cameras.h5").cameras
    cams[1].t = cams[1].t + np.array([0, 0, -1.0])  # the box is now behind camera 1
    CamerasArtefact(cams, "synth").save(w / "cameras.h5", Provenance())
    proc = rsl("fit-gaussians", cap, "-w", w, "--iterations", "1", "--gaussians", "50")
    assert proc.returncode != 0
    assert "cam1" in proc.stderr and "sees none of the mesh" in proc.stderr
    assert not (w / "gaussians.h5").exists()


def test_fit_gaussians_wrong_image_size_fails(fitted, tmp_path, rsl):
    cap, ws, _ = fitted
    w = tmp_path / "ws"
    w.mkdir()
    for f in ("mesh.h5", "masks.h5"):
        (w / f).write_bytes((ws / f).read_bytes())
    cams = CamerasArtefact.load(ws / "cameras.h5").cameras
    cams[0].width = 80
    CamerasArtefact(cams, "synth").save(w / "cameras.h5", Provenance())
    proc = rsl("fit-gaussians", cap, "-w", w, "--iterations", "1")
    assert proc.returncode != 0
    assert "cam0" in proc.stderr and "64x64" in proc.stderr


@pytest.mark.slow
def test_fit_gaussians_on_a_synth_capture(tmp_path, rsl, sample_data):
    """The real chain on a textured synthetic capture: synth → tetrahedralize → calibrate → segment → fit."""
    cap, ws = tmp_path / "bar", tmp_path / "ws"
    rsl("synth", sample_data / "bar" / "object.mesh", cap, "--cameras", "3", "--frames", "2",
        "--resolution", "128", "--calib-views", "0", "--markers", "0", check=True)
    rsl("tetrahedralize", cap, "-w", ws, check=True)
    rsl("calibrate", cap, "-w", ws, "--from-json", cap / "cameras.json", check=True)
    rsl("segment", cap, "-w", ws, "--method", "background", check=True)
    proc = rsl("fit-gaussians", cap, "-w", ws, "--iterations", "150", "--gaussians", "5000", check=True)
    art = GaussiansArtefact.load(ws / "gaussians.h5")
    assert min(art.fit_psnr.values()) >= SYNTH_FIT_PSNR_DB, (art.fit_psnr, proc.stderr)
