"""fit-gaussians poses the mesh as the fit frame shows the object ([capture] start, docs/capture.md).

The capture, built here: a soft cantilever (0.2 × 0.04 × 0.04 m, linear tets) held at x = −0.1 by a hard
handle, ``start = "equilibrium"``: frame 0 shows the beam sagged under gravity (tip ≈ 4 cm down).  Its two
64² frames are rendered from known, position-coloured Gaussians bound to the mesh at that equilibrium
(stages.sim.static.start_state with capture.toml's E, ν); masks = coverage ≥ ½.

Checked: the fit with the mesh posed at the equilibrium (``--pose capture``, the default) records those
positions in gaussians.h5 and fits clearly better than the fit with the mesh at rest (``--pose rest``, the
old behaviour), both measured here; ImageLoss anchors the fitted Gaussians at ``fit_positions``, so that
re-bound to x_fit(θ_init) they render exactly as fitted (and not with the rest anchor); gaussians.h5 files
written before ``fit_positions`` existed still load (anchored at rest).
"""
from __future__ import annotations

import itertools
import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from stages.artefacts import CamerasArtefact, GaussiansArtefact, MasksArtefact, MeshArtefact
from stages.capture import load_capture, write_image
from stages.sim.mesh import rest_quantities

SIZE = (0.2, 0.04, 0.04)  # m
YOUNG, POISSON, DENSITY = 1.5e5, 0.4, 1000.0
CAMS = ("side", "back")
PSNR_GAIN_DB = 5.0
"""How much better (dB, every camera) the posed fit must be than the fit at rest on the sagged beam."""


def beam_mesh(nx: int = 6, ny: int = 2, nz: int = 2) -> MeshArtefact:
    """A box SIZE centred at the origin, nx × ny × nz cells × 6 tets (Kuhn), one region."""
    axes = [np.linspace(-s / 2, s / 2, k + 1) for s, k in zip(SIZE, (nx, ny, nz))]
    verts = np.array(list(itertools.product(*axes)))
    vid = lambda i, j, k: (i * (ny + 1) + j) * (nz + 1) + k  # noqa: E731
    tets = []
    for i, j, k in itertools.product(range(nx), range(ny), range(nz)):
        c = [vid(i + a, j + b, k + d) for a, b, d in itertools.product((0, 1), repeat=3)]
        for perm in itertools.permutations(range(3)):
            cur, path = [0, 0, 0], [0]
            for ax in perm:
                cur[ax] = 1
                path.append(cur[0] * 4 + cur[1] * 2 + cur[2])
            tets.append([c[p] for p in path])
    tets = np.array(tets)
    p = verts[tets]
    vol = np.linalg.det(np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], -1))
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    faces = np.concatenate([tets[:, [0, 2, 1]], tets[:, [0, 1, 3]], tets[:, [0, 3, 2]], tets[:, [1, 2, 3]]])
    _, inv, cnt = np.unique(np.sort(faces, 1), axis=0, return_inverse=True, return_counts=True)
    faces = faces[cnt[inv.ravel()] == 1]
    vol, dm_inv, masses = rest_quantities(verts, tets, DENSITY)
    return MeshArtefact(verts, tets, faces, np.zeros(len(tets), np.int64), ["body"], vol, dm_inv, masses, DENSITY)


def look_at(name: str, eye, size: int = 64, f: float = 80.0):
    """A camera at ``eye`` looking at (0, 0, −0.01), z up."""
    from stages.artefacts import Camera

    eye, target = np.asarray(eye, float), np.array([0.0, 0.0, -0.01])
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(fwd, right), fwd])
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    return Camera(name, K, np.zeros(5), R, -R @ eye, size, size)


def scene_of(cap, mesh):
    from stages.sim.scene import frame_inputs, make_scene

    ctl = cap.controls()
    scene = make_scene(mesh, ctl, cap.material.model, cap.dt, cap.gravity)
    return scene, frame_inputs(scene, ctl, 0)


def sagged(cap, mesh) -> np.ndarray:
    """x_0 (n, 3): the static equilibrium of frame 0 with capture.toml's E, ν (computed here, independently
    of fit-gaussians)."""
    from stages.sim.static import start_state

    scene, inputs0 = scene_of(cap, mesh)
    return start_state(scene, inputs0, np.array([YOUNG]), np.array([POISSON]), "equilibrium")


def make_capture(root: Path, ws: Path) -> dict:
    """capture/ (toml, controls.json, object.obj, frame 0 of two cameras) and ws/ (mesh.h5, cameras.h5, masks.h5)."""
    from stages.steps.fit_gaussians import rest_centres, seed_gaussians
    from stages.render.gaussians import BoundGaussians, color_to_sh0

    mesh = beam_mesh()
    cams = [look_at("side", (0.0, -0.45, 0.0)), look_at("back", (0.08, 0.45, 0.1))]
    root.mkdir(parents=True)
    ws.mkdir(parents=True)
    (root / "capture.toml").write_text(
        f'[capture]\nname = "beam"\nfps = 30.0\ncameras = {json.dumps(list(CAMS))}\nstart = "equilibrium"\n'
        f'[object]\nmesh = "object.obj"\ndensity = {DENSITY}\n'
        f'[material]\nyoung = {YOUNG}\npoisson = {POISSON}\n')
    x0 = -SIZE[0] / 2
    box = [[x0 - 1e-3, -1.0, -1.0], [x0 + 1e-3, 1.0, 1.0]]
    (root / "controls.json").write_text(json.dumps({"handles": [
        {"name": "clamp", "select": {"box": box}, "poses": [[0, 0, 0, 1, 0, 0, 0]], "hard": True}]}))
    (root / "object.obj").write_text("".join(f"v {a} {b} {c}\n" for a, b, c in mesh.vertices)
                                     + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in mesh.surface_faces))
    cap = load_capture(root)
    x_sag = sagged(cap, mesh)
    # truth: opaque Gaussians bound to the mesh, coloured by their rest position, rendered at the sag
    rng = np.random.default_rng(3)
    n = 5000
    host, bary, log_s = seed_gaussians(mesh, n, 8.0, rng)
    centres = rest_centres(mesh, host, bary)
    colour = 0.5 + 0.45 * np.sin(centres / 0.02 * np.array([1.3, 2.0, 1.7]))
    truth = BoundGaussians(mesh.tets, mesh.dm_inv, host, bary, np.repeat(log_s[:, None], 3, 1) + 0.3,
                           np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 3.0), color_to_sh0(colour)[:, None, :],
                           np.zeros(3), rest=mesh.vertices)
    masks = {}
    with torch.no_grad():
        for cam in cams:
            out = truth.render(torch.as_tensor(x_sag, dtype=torch.float32), cam)
            write_image(root / "frames" / cam.name / "000000.png", np.round(out.image.numpy() * 255).astype(np.uint8))
            masks[cam.name] = (out.alpha.numpy() >= 0.5)[None]
    mesh.save(ws / "mesh.h5")
    CamerasArtefact(cams, "synth").save(ws / "cameras.h5")
    MasksArtefact(masks, "truth").save(ws / "masks.h5")
    return {"mesh": mesh, "cameras": cams, "x_sag": x_sag}


@pytest.fixture(scope="module")
def fits(tmp_path_factory):
    """The same capture fitted twice: posed (the real CLI, default --pose) and at rest (--pose rest)."""
    from conftest import run_rsl

    from stages.steps.fit_gaussians import FitGaussiansConfig
    from stages.steps.fit_gaussians import run as fit

    base = tmp_path_factory.mktemp("fitstart")
    cap, ws = base / "capture", base / "ws"
    made = make_capture(cap, ws)
    ws_rest = base / "ws_rest"
    shutil.copytree(ws, ws_rest)
    common = ["--iterations", "120", "--gaussians", "800"]
    proc = run_rsl("fit-gaussians", cap, "-w", ws, *common)
    assert proc.returncode == 0, proc.stderr[-3000:]
    fit(FitGaussiansConfig(cap, ws_rest, iterations=120, gaussians=800, pose="rest"))
    return {"cap": cap, "ws": ws, "ws_rest": ws_rest, "proc": proc, **made}


def test_the_beam_sags_visibly(fits):
    """The case is meaningful: the frame-0 equilibrium is far from the rest shape at the image's scale."""
    sag = np.max(fits["mesh"].vertices[:, 2] - fits["x_sag"][:, 2])
    assert sag > 0.03, sag  # m; the beam is 0.04 m thick, a camera pixel ≈ 6 mm there


def test_fit_is_posed_at_the_start_state_and_records_it(fits):
    art = GaussiansArtefact.load(fits["ws"] / "gaussians.h5")
    assert art.fit_positions is not None and art.fit_positions.shape == fits["mesh"].vertices.shape
    np.testing.assert_allclose(art.fit_positions, fits["x_sag"], rtol=0, atol=1e-9)
    st = art.fit_state
    assert st["pose"] == "capture" and st["start"] == "equilibrium" and st["frame"] == 0
    assert st["young"] == [YOUNG] and st["poisson"] == [POISSON] and st["regions"] == ["body"]
    text = " ".join(fits["proc"].stderr.split())
    assert "posed as frame 0 under start = 'equilibrium'" in text, text[-2000:]
    rest = GaussiansArtefact.load(fits["ws_rest"] / "gaussians.h5")
    np.testing.assert_array_equal(rest.fit_positions, fits["mesh"].vertices)
    assert rest.fit_state["pose"] == "rest"


def test_posed_fit_beats_the_fit_at_rest(fits):
    posed = GaussiansArtefact.load(fits["ws"] / "gaussians.h5").fit_psnr
    rest = GaussiansArtefact.load(fits["ws_rest"] / "gaussians.h5").fit_psnr
    print(f"fit PSNR on the sagged beam: posed {posed}, at rest {rest} (dB)")
    for c in CAMS:
        assert posed[c] >= rest[c] + PSNR_GAIN_DB, (posed, rest)


def _targets(fits) -> list[np.ndarray]:
    from stages.capture import read_image

    masks = MasksArtefact.load(fits["ws"] / "masks.h5").masks
    out = []
    for c in CAMS:
        img = read_image(fits["cap"] / "frames" / c / "000000.png").astype(np.float32) / 255.0
        out.append(img * masks[c][0][..., None])  # the background colour is black
    return out


def test_rebound_gaussians_at_x_fit_render_as_fitted(fits):
    """ImageLoss anchors the Gaussians where they were fitted: rebind(x_fit(θ_init)) keeps the render exactly
    (and its PSNR is the recorded fit PSNR); the old rest anchor would move them."""
    from stages.render.image_loss import ImageLoss
    from stages.render import loss as rloss

    art = GaussiansArtefact.load(fits["ws"] / "gaussians.h5")
    mesh, cams = fits["mesh"], fits["cameras"]
    il = ImageLoss(art, mesh, cams)
    np.testing.assert_array_equal(il.fit_positions, art.fit_positions)
    x_fit = sagged(load_capture(fits["cap"]), mesh)  # adapt's x_fit at θ_init (frame 0 = x_0(θ))
    fitted = il.render(x_fit)
    il.rebind(x_fit)
    rebound = il.render(x_fit)
    for a, b in zip(fitted, rebound):
        assert np.max(np.abs(a - b)) < 2e-3, np.max(np.abs(a - b))
    for c, img, tgt in zip(CAMS, rebound, _targets(fits)):
        psnr = rloss.psnr(torch.as_tensor(img), torch.as_tensor(tgt))
        assert abs(psnr - art.fit_psnr[c]) < 0.1, (c, psnr, art.fit_psnr[c])
    # the twin without fit_positions (the rest anchor of files made before it) moves the Gaussians at x_fit
    old = ImageLoss(GaussiansArtefact(**{**art.__dict__, "fit_positions": None, "fit_state": {}}), mesh, cams)
    old.rebind(x_fit)
    worst = max(float(np.max(np.abs(a - b))) for a, b in zip(fitted, old.render(x_fit)))
    assert worst > 0.2, worst


def test_gaussians_h5_without_fit_positions_still_loads(fits, tmp_path):
    """A gaussians.h5 written before ``fit_positions`` existed: loads with fit_positions None and is anchored
    at rest (ImageLoss.fit_positions = the rest shape)."""
    from stages.render.image_loss import ImageLoss

    path = tmp_path / "gaussians.h5"
    shutil.copy(fits["ws_rest"] / "gaussians.h5", path)
    with h5py.File(path, "r+") as f:
        del f["fit_positions"]
        del f.attrs["fit_state"]
    art = GaussiansArtefact.load(path)
    assert art.fit_positions is None and art.fit_state == {}
    il = ImageLoss(art, fits["mesh"], fits["cameras"])
    np.testing.assert_array_equal(il.fit_positions, fits["mesh"].vertices)
    ref = ImageLoss(GaussiansArtefact.load(fits["ws_rest"] / "gaussians.h5"), fits["mesh"], fits["cameras"])
    for a, b in zip(il.render(fits["x_sag"]), ref.render(fits["x_sag"])):
        np.testing.assert_array_equal(a, b)


def test_an_object_nothing_holds_is_posed_at_rest(fits, tmp_path):
    """start = "equilibrium" without a handle or an obstacle: no static equilibrium exists; fit_pose uses the
    rest shape and says so."""
    from stages.steps.fit_gaussians import fit_pose

    cap = tmp_path / "free"
    shutil.copytree(fits["cap"], cap)
    (cap / "controls.json").unlink()
    x, st = fit_pose(load_capture(cap), fits["mesh"], 0)
    np.testing.assert_array_equal(x, fits["mesh"].vertices)
    assert st["start"] == "rest" and st["declared_start"] == "equilibrium"


@pytest.mark.parametrize("order", [1, 2])
def test_rebind_at_the_fit_positions_is_exact_for_linear_and_quadratic_tets(order):
    """Gaussians with fit_positions x_fit (a bent beam, not the rest shape): re-bound to x_fit they render exactly
    as the binding as fitted renders at x_fit (centre Σ N_a x_a and F Σ₀ Fᵀ at the Gaussian, P1 and P2)."""
    from stages.render.image_loss import ImageLoss
    from stages.steps.fit_gaussians import seed_gaussians
    from stages.render.gaussians import color_to_sh0
    from stages.artefacts import mesh_artefact

    base = beam_mesh(4, 1, 1)
    mesh = mesh_artefact(base.vertices, base.tets, DENSITY, order=order)
    X = mesh.vertices
    bend = 0.4 * (X[:, 0] + SIZE[0] / 2) ** 2  # m, a smooth downward bend
    x_fit = X + np.stack([np.zeros_like(bend), 0.1 * bend, -bend], 1)
    rng = np.random.default_rng(0)
    n = 400
    host, bary, log_s = seed_gaussians(mesh, n, 4.0, rng)
    q = rng.normal(size=(n, 4))
    art = GaussiansArtefact(host, bary, np.repeat(log_s[:, None], 3, 1) + rng.normal(0, 0.2, (n, 3)),
                            q / np.linalg.norm(q, axis=1, keepdims=True), np.full(n, 2.0),
                            color_to_sh0(rng.uniform(0.2, 0.9, (n, 3)))[:, None, :], fit_positions=x_fit)
    cams = [look_at("side", (0.0, -0.45, 0.0))]
    il = ImageLoss(art, mesh, cams)
    fitted = il.render(x_fit)[0]
    assert fitted.max() > 0.2  # the beam is in view
    il.rebind(x_fit)
    np.testing.assert_allclose(il.render(x_fit)[0], fitted, rtol=0, atol=2e-4)
    il.rebind(None)  # back to the binding as fitted
    np.testing.assert_array_equal(il.render(x_fit)[0], fitted)
