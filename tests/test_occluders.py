"""Occluders (controls.json ``visual`` of handles and obstacles): parsing, their pixels in a camera, and the
image loss leaving those pixels out (its gradient is the gradient of the loss with the pixels removed)."""
from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from stages.artefacts import Camera, GaussiansArtefact
from stages.capture import CaptureError, load_controls, parse_controls
from stages.occluders import ignore_mask, visual_world
from stages.render.mesh_raster import look_at, project_points
from stages.artefacts import mesh_artefact
from stages.sim.meshgen import box_tets


def _camera(res: int = 64, centre=(0.35, -0.25, 0.3), target=(0.05, 0.02, 0.02)) -> Camera:
    R, t = look_at(np.array(centre), np.array(target), np.array([0.0, 0.0, 1.0]))
    K = np.array([[1.1 * res, 0, (res - 1) / 2], [0, 1.1 * res, (res - 1) / 2], [0, 0, 1]])
    return Camera("c0", K, np.zeros(5), R, t, res, res)


def _pose(t, axis=(0.3, 0.2, 1.0), angle=0.4) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    q = Rotation.from_rotvec(np.asarray(axis) / np.linalg.norm(axis) * angle).as_quat()  # x y z w
    return np.concatenate([t, [q[3], q[0], q[1], q[2]]])


def _controls(box, poses, where="handles") -> dict:
    item = {"name": "clamp", "visual": {"box": box}, "poses": poses}
    if where == "handles":
        item["select"] = {"box": [[-1, -1, -1], [0.001, 1, 1]]}
    else:
        item.update(shape="sphere", radius=0.01)
    return {where: [item]}


# =========================================================================== parsing
def test_visual_box_and_mesh_parse_and_round_trip(tmp_path: Path) -> None:
    box = [[0.0, -0.01, -0.01], [0.02, 0.01, 0.03]]
    poses = [list(_pose([0.01, 0, 0])), list(_pose([0.02, 0, 0]))]
    for where in ("handles", "obstacles"):
        ctl = parse_controls(_controls(box, poses, where), tmp_path / "controls.json")
        item = getattr(ctl, where)[0]
        assert item.visual.kind == "box"
        np.testing.assert_array_equal(item.visual.box, box)
        again = parse_controls(json.loads(json.dumps(ctl.to_json())), tmp_path / "controls.json")
        np.testing.assert_array_equal(getattr(again, where)[0].visual.box, box)
    # a mesh beside controls.json, in its own frame
    (tmp_path / "gripper.obj").write_text("v 0 0 0\nv 0.02 0 0\nv 0 0.02 0\nv 0 0 0.02\n"
                                          "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    data = {"obstacles": [{"name": "g", "shape": "sphere", "radius": 0.01, "visual": {"mesh": "gripper.obj"}}]}
    (tmp_path / "controls.json").write_text(json.dumps(data))
    ctl = load_controls(tmp_path / "controls.json")
    v, f = ctl.obstacles[0].visual.triangles()
    assert v.shape == (4, 3) and f.shape == (4, 3)
    assert ctl.to_json()["obstacles"][0]["visual"] == {"mesh": "gripper.obj"}


@pytest.mark.parametrize("visual, expect", [
    ({"box": [[0, 0, 0]]}, "'handles[0].visual.box' should be two corners"),
    ({"box": [[0, 0, 0], [0, 1, 1]]}, "'handles[0].visual.box' has zero extent"),
    ({"mesh": "nowhere.obj"}, "'handles[0].visual.mesh' names 'nowhere.obj', but"),
    ({"mesh": "gripper.txt"}, "which is not an obj, ply, stl or off file"),
    ({"box": [[0, 0, 0], [1, 1, 1]], "mesh": "a.obj"}, "'handles[0].visual' should be an object with exactly one"),
])
def test_bad_visuals_are_one_sentence_naming_the_file(tmp_path: Path, visual: dict, expect: str) -> None:
    data = {"handles": [{"name": "h", "select": {"ids": [0]}, "visual": visual}]}
    with pytest.raises(CaptureError) as e:
        parse_controls(data, tmp_path / "controls.json")
    msg = str(e.value)
    assert msg.startswith(str(tmp_path / "controls.json")) and expect in msg and msg.endswith(".")


# =========================================================================== coverage
def test_box_visual_covers_the_convex_hull_of_its_projected_corners_and_moves_with_its_pose() -> None:
    """A box projects onto the convex hull of its 8 projected corners: the rasterized ignore mask (no margin)
    equals the pixel centres inside that hull (matplotlib's point-in-polygon, an independent twin)."""
    from matplotlib.path import Path as MplPath
    from scipy.spatial import ConvexHull

    cam = _camera(res=80)
    box = [[0.0, -0.012, -0.01], [0.03, 0.015, 0.025]]
    poses = [list(_pose([0.02, 0.0, 0.01])), list(_pose([0.06, 0.03, 0.0], angle=1.1))]
    ctl = parse_controls(_controls(box, poses), Path("controls.json"))
    vis = ctl.handles[0].visual
    jj, ii = np.meshgrid(np.arange(80), np.arange(80))
    centres = np.stack([jj.ravel(), ii.ravel()], 1).astype(float)
    masks = []
    for t in (0, 1):
        m = ignore_mask(ctl, t, cam, margin_px=0)
        v, _ = visual_world(vis, np.asarray(poses[t]))
        uv, z = project_points(v, cam.K, cam.R, cam.t)
        assert np.all(z > 0)
        hull = uv[ConvexHull(uv).vertices]
        want = MplPath(hull).contains_points(centres).reshape(80, 80)
        assert 30 < want.sum() < 0.6 * want.size
        np.testing.assert_array_equal(m, want)
        masks.append(m)
    assert (masks[0] != masks[1]).sum() > 20  # the pose moved it
    # with a margin the mask grows by about the perimeter
    grown = ignore_mask(ctl, 0, cam, margin_px=2)
    assert np.all(grown[masks[0]]) and grown.sum() > masks[0].sum() + 20
    # no visual: nothing ignored
    plain = parse_controls({"handles": [{"name": "h", "select": {"ids": [0]}}]}, Path("controls.json"))
    assert not ignore_mask(plain, 0, cam).any()


# =========================================================================== the image loss
def box_bar_gaussians(rng, n: int, scale: float, opacity_logit: float) -> tuple:
    """A 6×3×3-cell bar (0.12 × 0.04 × 0.04 m) and n Gaussians of one scale (m) at random points of its tets, with
    random colours drawn from ``rng``: (vertices, mesh artefact, GaussiansArtefact)."""
    v, tets = box_tets((6, 3, 3), (0.12, 0.04, 0.04), origin=(-0.01, 0.0, 0.0))
    gauss = GaussiansArtefact(host_tet=rng.integers(0, len(tets), n), bary=rng.dirichlet(np.ones(4), n),
                              log_scales=np.full((n, 3), np.log(scale)), rotations=np.tile([1.0, 0, 0, 0], (n, 1)),
                              opacity_logit=np.full(n, opacity_logit), sh=rng.normal(0, 1.0, (n, 1, 3)),
                              background=np.zeros(3))
    return v, mesh_artefact(v, tets, 1000.0), gauss


def one_camera_capture(root: Path, mesh, cam, gauss, frame: np.ndarray, controls: dict) -> tuple[Path, Path]:
    """(capture, workspace) under ``root`` for VisionObservation: the capture holds the mesh, camera "c0" (start
    rest), ``controls`` and frame 0 = ``frame`` (uint8); the workspace cameras.h5 and gaussians.h5."""
    import meshio

    from stages.artefacts import CamerasArtefact
    from stages.capture import write_image

    cap, ws = root / "cap", root / "ws"
    (cap / "frames" / "c0").mkdir(parents=True)
    meshio.write(str(cap / "object.mesh"), meshio.Mesh(mesh.vertices, [("tetra", mesh.tets)]), file_format="medit")
    (cap / "capture.toml").write_text('[capture]\ncameras = ["c0"]\nstart = "rest"\n[object]\nmesh = "object.mesh"\n')
    (cap / "controls.json").write_text(json.dumps(controls))
    write_image(cap / "frames" / "c0" / "000000.png", frame)
    ws.mkdir()
    CamerasArtefact([cam], "json").save(ws / "cameras.h5")
    gauss.save(ws / "gaussians.h5")
    return cap, ws


@pytest.fixture(scope="module")
def scene():
    """A 6×3×3-cell bar with random Gaussians in view of one camera, and a box occluder over one end."""
    from stages.render.image_loss import ImageLoss

    rng = np.random.default_rng(0)
    v, mesh, gauss = box_bar_gaussians(rng, 150, 0.006, 1.5)
    cam = _camera(res=48)
    loss = ImageLoss(gauss, mesh, [cam])
    box = [[-0.02, -0.02, -0.02], [0.0, 0.02, 0.02]]  # over the bar's far end, in front of it
    ctl = parse_controls(_controls(box, [list(_pose([0.09, 0.02, 0.02], angle=0.0))]), Path("controls.json"))
    ign = ignore_mask(ctl, 0, cam)
    x = v + 0.002 * np.sin(v[:, [1, 2, 0]] * 80.0)
    target = np.clip(loss.render(v)[0] + rng.normal(0, 0.05, (48, 48, 3)), 0, 1).astype(np.float32)
    target = np.round(target * 255) / 255  # exactly what an 8-bit frame holds
    return SimpleNamespace(loss=loss, x=x, target=target, ign=ign, mesh=mesh, cam=cam, gauss=gauss,
                           controls=_controls(box, [list(_pose([0.09, 0.02, 0.02], angle=0.0))]))


def test_the_occluder_covers_object_pixels(scene) -> None:
    loss, x, ign = scene.loss, scene.x, scene.ign
    img = loss.render(x)[0]
    obj = np.abs(img - loss.background).max(-1) > 0.05
    assert 0.1 * obj.sum() < (obj & ign).sum() < 0.9 * obj.sum()


def test_ignored_pixels_contribute_nothing_and_the_gradient_is_that_of_the_loss_without_them(scene) -> None:
    """L_ign(x) = Σ_{p ∉ ignore} |R_p(x) − Ĩ_p|: its gradient equals the gradient of the L1 loss of the render and
    the target both multiplied by (1 − ignore) by hand; changing the target under the occluder changes
    neither L nor dL/dx; and the gradient differs from the one that counts those pixels."""
    import torch

    loss, x, target, ign = scene.loss, scene.x, scene.target, scene.ign
    L_full, g_full = loss(x, [target])
    L_ign, g_ign = loss(x, [target], [ign])
    # the twin: mask render and target by hand
    xt = torch.tensor(x, requires_grad=True)
    w = torch.as_tensor(~ign, dtype=torch.float32)[..., None]
    img = loss.images(xt)[0]
    twin = (img * w - torch.as_tensor(target) * w).abs().sum()
    twin.backward()
    assert L_ign == pytest.approx(float(twin.detach()), rel=1e-6)
    scale = np.abs(g_ign).max()
    np.testing.assert_allclose(g_ign, xt.grad.numpy(), rtol=0, atol=1e-6 * scale)
    # anything under the occluder: same loss, same gradient
    other = target.copy()
    other[ign] = np.random.default_rng(1).random((int(ign.sum()), 3)).astype(np.float32)
    L2, g2 = loss(x, [other], [ign])
    assert L2 == L_ign
    np.testing.assert_array_equal(g2, g_ign)
    L3, _ = loss(x, [other])
    assert L3 != L_full  # without the ignore mask those pixels count
    # the occluded pixels carried part of the gradient
    assert L_ign < L_full
    assert np.linalg.norm(g_ign - g_full) > 0.05 * np.linalg.norm(g_full)
    # no ignore mask, or an empty one: the plain loss
    L4, g4 = loss(x, [target], [np.zeros_like(ign)])
    assert L4 == L_full
    np.testing.assert_array_equal(g4, g_full)


# =========================================================================== rsl synth --clamp
def test_synth_clamp_draws_the_handle_visual_and_no_plates_leaves_background_out(tmp_path, shared_data, rsl) -> None:
    """`rsl synth --clamp --no-plates`: controls.json's first handle carries a box visual around the vertices it
    holds; the frames show it (dark, where its ignore mask is) and the truth masks hold only the visible object."""
    import cv2
    import trimesh

    from stages.capture import load_capture, read_cameras_json, read_image

    beam = shared_data / "autodef_fulton" / "Coarse_beam.mesh"
    cap = tmp_path / "cap"
    p = rsl("synth", beam, cap, "--scenario", "cable", "--cameras", "1", "--frames", "3", "--resolution", "48",
            "--markers", "0", "--calib-views", "0", "--clamp", "--no-plates")
    assert p.returncode == 0, p.stderr[-2000:]
    assert not (cap / "background").exists()
    ctl = load_capture(cap).controls()
    vis = ctl.handles[0].visual
    assert vis is not None and vis.kind == "box"
    surf = np.asarray(trimesh.load(cap / "object.obj", process=False).vertices)
    held = surf[ctl.handles[0].select.select(surf)]
    assert len(held) and np.all(vis.box[0] < held.min(0)) and np.all(vis.box[1] > held.max(0))  # encloses them
    cam = read_cameras_json(cap / "cameras.json")[0]
    for t in range(3):
        cover = ignore_mask(ctl, t, cam, margin_px=0)
        img = read_image(cap / "frames" / "cam0" / f"{t:06d}.png").astype(float) / 255
        truth = read_image(cap / "truth" / "masks" / "cam0" / f"{t:06d}.png")[..., 0] > 127
        assert cover.sum() > 20 and truth.sum() > 20
        inner = cv2.erode(cover.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)  # away from its outline
        assert inner.sum() > 5 and img[inner].max() < 0.45  # the dark clamp
        assert not np.any(truth & cover)


# =========================================================================== rsl adapt's vision observations
def test_adapt_vision_observations_leave_the_occluder_out(scene, tmp_path) -> None:
    """stages.steps.adapt.VisionObservation on a capture whose handle carries a visual: the L1 loss it passes ImageLoss carries
    the occluder's ignore mask, and the Gauss–Newton residuals, their Jacobian columns and Jᵀ W r are zero /
    unchanged under it, whatever the frame holds there."""
    from stages.observations import VisionObservation
    from stages.capture import load_capture, write_image

    loss, x, target, ign, mesh, cam = scene.loss, scene.x, scene.target, scene.ign, scene.mesh, scene.cam
    frame = np.round(target * 255).astype(np.uint8)
    cap, ws = one_camera_capture(tmp_path, mesh, cam, scene.gauss, frame, scene.controls)
    obs = VisionObservation(load_capture(cap), ws, "", mesh, False)
    assert obs.occluded
    np.testing.assert_array_equal(obs.ignore(0)[0], ign)
    tgt = obs.targets(0)[0]
    L, G = obs.loss([0], x[None])
    L_ref, g_ref = loss(x, [tgt], [ign])
    assert L[0] == pytest.approx(L_ref, rel=1e-6)
    np.testing.assert_allclose(G[0], g_ref, atol=1e-6 * np.abs(g_ref).max())
    r = obs.residuals([0], x[None])[0].reshape(48, 48, 3)
    assert np.all(r[ign] == 0) and np.abs(r[~ign]).max() > 0
    dX = np.random.default_rng(2).normal(size=(2, 1) + x.shape) * 1e-3
    J = obs.jacobian([0], x[None], dX)[0].reshape(48, 48, 3, 2)
    assert np.all(J[ign] == 0) and np.abs(J[~ign]).max() > 0
    W = [np.ones(48 * 48 * 3)]
    g1 = obs.exact_jtwr([0], x[None], dX, [r.reshape(-1)], W)
    # a frame that differs only under the occluder gives the same residuals and Jᵀ W r
    other = frame.copy()
    other[ign] = 255 - other[ign]
    write_image(cap / "frames" / "c0" / "000000.png", other)
    obs2 = VisionObservation(load_capture(cap), ws, "", mesh, False)
    np.testing.assert_array_equal(obs2.residuals([0], x[None])[0], r.reshape(-1))
    np.testing.assert_allclose(obs2.exact_jtwr([0], x[None], dX, [r.reshape(-1)], W), g1, rtol=1e-12)


def test_clean_mask_keeps_an_object_cut_in_two_by_an_occluder() -> None:
    """A bar crossed by a gripper band: without the ignore mask the largest component drops one half; with it
    both halves stay (connected through the ignored band) and the band itself is in no mask — even when the
    band is larger than the object."""
    from stages.vision.segmentation import clean_mask

    m = np.zeros((40, 60), bool)
    m[15:25, 5:55] = True  # the bar
    band = np.zeros_like(m)
    band[:, 24:34] = True  # the gripper, floor to ceiling
    seen = m & ~band
    seen[2, 2] = True  # a speck away from everything
    plain = clean_mask(seen, 0, 0)
    assert plain[20, 10] != plain[20, 45]  # one half lost
    kept = clean_mask(seen, 0, 0, ignore=band)
    np.testing.assert_array_equal(kept, m & ~band)
    big = np.zeros_like(m)
    big[:, 20:40] = True
    big[0:5, :] = True  # larger than both halves together
    seen = m & ~big
    seen[35, 2] = True  # a speck, not connected to the band
    kept = clean_mask(seen, 0, 0, ignore=big)
    np.testing.assert_array_equal(kept, m & ~big)


# =========================================================================== rsl fit-gaussians
def test_fit_gaussians_leaves_the_occluder_pixels_out(scene, tmp_path) -> None:
    """Fitted with the clamp's pixels marked background in masks.h5 (as segment leaves them), Gaussians under the
    clamp are driven transparent when controls.json does not declare it; declared (visual), those pixels weigh
    nothing and they keep their opacity."""
    import meshio

    from stages.artefacts import CamerasArtefact, GaussiansArtefact, MasksArtefact
    from stages.capture import write_image
    from stages.steps.fit_gaussians import FitGaussiansConfig
    from stages.steps.fit_gaussians import run as fit
    from stages.render.mesh_raster import project_points as project

    mesh, cam, ign = scene.mesh, scene.cam, scene.ign
    frame = scene.loss.render(mesh.vertices)[0]
    obj = np.abs(frame - scene.loss.background).max(-1) > 0.02
    opac = {}
    for declared in (True, False):
        cap = tmp_path / f"cap{declared}"
        (cap / "frames" / "c0").mkdir(parents=True)
        meshio.write(str(cap / "object.mesh"), meshio.Mesh(mesh.vertices, [("tetra", mesh.tets)]),
                     file_format="medit")
        (cap / "capture.toml").write_text('[capture]\ncameras = ["c0"]\nstart = "rest"\n'
                                          '[object]\nmesh = "object.mesh"\n')
        ctl = json.loads(json.dumps(scene.controls))
        if not declared:
            del ctl["handles"][0]["visual"]
        (cap / "controls.json").write_text(json.dumps(ctl))
        write_image(cap / "frames" / "c0" / "000000.png", np.round(frame * 255).astype(np.uint8))
        ws = tmp_path / f"ws{declared}"
        ws.mkdir()
        mesh.save(ws / "mesh.h5")
        CamerasArtefact([cam], "json").save(ws / "cameras.h5")
        MasksArtefact({"c0": (obj & ~ign)[None]}, "lab").save(ws / "masks.h5")
        fit(FitGaussiansConfig(cap, ws, iterations=25, gaussians=200, seed=0))
        g = GaussiansArtefact.load(ws / "gaussians.h5")
        centres = np.einsum("gk,gkd->gd", g.bary, mesh.vertices[mesh.tets[g.host_tet]])
        uv, _ = project(centres, cam.K, cam.R, cam.t)
        px = np.clip(np.round(uv).astype(int), 0, 47)
        under = ign[px[:, 1], px[:, 0]] & obj[px[:, 1], px[:, 0]]
        assert under.sum() > 10
        opac[declared] = float(np.mean(1 / (1 + np.exp(-g.opacity_logit[under]))))
    print("mean opacity of the Gaussians under the clamp: declared", opac[True], "undeclared", opac[False])
    assert opac[True] > opac[False] + 0.1
