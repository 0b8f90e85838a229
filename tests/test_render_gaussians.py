"""Projection (OpenCV model, EWA), Gaussians bound to tets, losses."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from stages.artefacts import Camera, GaussiansArtefact
from stages.render.gaussians import SH_C0, SH_C1, BoundGaussians, quat_to_rotmat, rotmat_to_quat, sh_to_color
from stages.render.loss import l1_dssim, psnr, ssim
from stages.render.projection import CameraTensors, project_gaussians, project_points
from test_fit_gaussians import box_tet_mesh, look_at, mesh_artefact, truth_gaussians


def _camera(dist=(0.0,) * 5, skew: float = 0.5) -> Camera:
    R = quat_to_rotmat(torch.tensor([[0.95, 0.1, -0.2, 0.05]], dtype=torch.float64))[0].numpy()
    K = np.array([[120.0, skew, 40.0], [0, 118.0, 30.0], [0, 0, 1]])
    return Camera("c", K, np.array(dist, float), R, np.array([0.02, -0.01, 0.5]), 80, 60)


def _rot(seed: int) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(1, 4))
    return quat_to_rotmat(torch.as_tensor(q))[0].numpy()


def test_project_points_matches_opencv():
    import cv2

    cam = _camera((0.1, -0.05, 0.002, -0.001, 0.01), skew=0.0)  # cv2.projectPoints ignores skew
    pts = np.random.default_rng(0).uniform(-0.1, 0.1, size=(50, 3))
    uv, z = project_points(torch.as_tensor(pts), CameraTensors.from_camera(cam, torch.float64))
    ref, _ = cv2.projectPoints(pts, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, cam.dist)
    np.testing.assert_allclose(uv.numpy(), ref[:, 0], atol=1e-9)
    np.testing.assert_allclose(z.numpy(), (pts @ cam.R.T + cam.t)[:, 2])


@pytest.mark.parametrize("dist", [(0.0,) * 5, (0.1, -0.05, 0.002, -0.001, 0.01)], ids=["pinhole", "distorted"])
def test_ewa_covariance_uses_the_projection_jacobian(dist):
    """Σ₂ = J R Σ Rᵀ Jᵀ + 0.3 I with J the autograd Jacobian of project_points at the mean."""
    cam = CameraTensors.from_camera(_camera(dist), torch.float64)
    rng = np.random.default_rng(1)
    means = torch.as_tensor(rng.uniform(-0.05, 0.05, size=(5, 3)))
    A = torch.as_tensor(rng.normal(size=(5, 3, 3))) * 0.01
    covs = A @ A.transpose(1, 2)
    proj = project_gaussians(means, covs, cam)
    assert proj.visible.all()
    for i in range(5):
        J = torch.autograd.functional.jacobian(lambda p: project_points(p[None], cam)[0][0], means[i])  # (2, 3)
        expect = J @ covs[i] @ J.T + 0.3 * torch.eye(2, dtype=torch.float64)
        torch.testing.assert_close(proj.cov2d[i], expect, rtol=1e-9, atol=1e-12)
        inv = torch.linalg.inv(expect)
        torch.testing.assert_close(proj.conics[i], torch.stack([inv[0, 0], inv[0, 1], inv[1, 1]]))
    uv, _ = project_points(means, cam)
    torch.testing.assert_close(proj.means2d, uv)


def test_points_behind_the_camera_are_culled():
    cam = CameraTensors.from_camera(_camera(), torch.float64)
    cam_pts = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0]], dtype=torch.float64)  # behind, at the centre
    means = (cam_pts - cam.t) @ cam.R  # camera → world
    proj = project_gaussians(means, torch.eye(3, dtype=torch.float64).expand(2, 3, 3) * 1e-4, cam)
    assert not proj.visible.any()


def test_quaternion_round_trip():
    q = torch.as_tensor(np.random.default_rng(2).normal(size=(64, 4)))
    R = quat_to_rotmat(q).numpy()
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    q2 = rotmat_to_quat(R)
    np.testing.assert_allclose(quat_to_rotmat(torch.as_tensor(q2)).numpy(), R, atol=1e-12)


def test_sh_colour():
    sh = torch.zeros(2, 4, 3, dtype=torch.float64)
    sh[:, 0] = torch.tensor([0.3, -0.2, 0.1])
    sh[:, 3] = torch.tensor([0.5, 0.0, 0.0])  # −C₁ x term
    dirs = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0]], dtype=torch.float64)
    c = sh_to_color(sh, dirs)
    torch.testing.assert_close(c[0], torch.clamp(0.5 + SH_C0 * sh[0, 0] - SH_C1 * sh[0, 3], min=0))
    torch.testing.assert_close(c[1], torch.clamp(0.5 + SH_C0 * sh[1, 0] + SH_C1 * sh[1, 3], min=0))


@pytest.fixture(scope="module")
def bound():
    verts, tets, faces = box_tet_mesh()
    mesh = mesh_artefact(verts, tets, faces)
    art = truth_gaussians(mesh, 400, seed=1)
    rng = np.random.default_rng(5)
    art.rotations = rng.normal(size=(400, 4))
    art.log_scales = art.log_scales + rng.normal(scale=0.3, size=(400, 3))
    return mesh, art


def test_gaussians_follow_a_rigid_motion_exactly(bound):
    """x → Q x + s moves centres the same way and covariances to Q Σ Qᵀ (F = Q in every tet)."""
    mesh, art = bound
    g = BoundGaussians.from_artefact(art, mesh).double()
    Q, s = _rot(3), np.array([0.1, -0.2, 0.05])
    x0 = torch.as_tensor(mesh.vertices)
    x1 = torch.as_tensor(mesh.vertices @ Q.T + s)
    with torch.no_grad():
        c0, c1 = g.centres(x0), g.centres(x1)
        S0, S1 = g.covariances(x0), g.covariances(x1)
        F = g.deformation(x1)
    Qt = torch.as_tensor(Q)
    torch.testing.assert_close(c1, c0 @ Qt.T + torch.as_tensor(s), rtol=0, atol=1e-14)
    torch.testing.assert_close(F, Qt.expand_as(F), rtol=0, atol=1e-12)
    torch.testing.assert_close(S1, Qt @ S0 @ Qt.T, rtol=1e-10, atol=1e-16)
    torch.testing.assert_close(S0, g.rest_covariances())


def test_rigidly_moved_scene_renders_the_same(bound):
    """Moving the mesh and the camera by one rigid motion leaves the image unchanged."""
    mesh, art = bound
    g = BoundGaussians.from_artefact(art, mesh)
    cam = look_at("c", [0.3, 0.1, 0.2], 64)
    Q, s = _rot(4), np.array([0.05, 0.02, -0.1])
    moved = Camera("c", cam.K, cam.dist, cam.R @ Q.T, cam.t - cam.R @ Q.T @ s, 64, 64)
    with torch.no_grad():
        a = g.render(torch.as_tensor(mesh.vertices), cam).image
        b = g.render(torch.as_tensor(mesh.vertices @ Q.T + s), moved).image
    assert float(a.max()) > 0.2
    assert float((a - b).abs().max()) < 2e-4


def test_position_gradients_fast_dense_and_fd(bound):
    """d loss / d positions: fast = dense (float64), and = central differences on a few coordinates.

    Few, half-transparent Gaussians, so that no pixel reaches the transmittance cut-off (the
    image is then smooth in the positions except where an α crosses 1/255).
    """
    mesh, art = bound
    sub = GaussiansArtefact(art.host_tet[:60], art.bary[:60], art.log_scales[:60] + 0.5, art.rotations[:60],
                            np.full(60, -0.8), art.sh[:60])
    g = BoundGaussians.from_artefact(sub, mesh).double()
    cam = look_at("c", [0.25, -0.15, 0.2], 24, f=40.0)
    target = torch.rand(24, 24, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    noise = np.random.default_rng(6).normal(size=mesh.vertices.shape)
    x0 = torch.as_tensor(mesh.vertices) + 0.003 * torch.as_tensor(noise)

    def loss(x, r="fast"):
        return ((g.render(x, cam, rasterizer=r).image - target) ** 2).sum()

    grads = {}
    for r in ("fast", "dense"):
        x = x0.clone().requires_grad_(True)
        grads[r] = torch.autograd.grad(loss(x, r), x)[0]
    torch.testing.assert_close(grads["fast"], grads["dense"], rtol=1e-8, atol=1e-10)
    gd = grads["fast"]
    assert float(gd.abs().max()) > 0
    h = 1e-6
    for flat in torch.topk(gd.abs().flatten(), 4).indices.tolist() + [7]:
        e = torch.zeros_like(x0).flatten()
        e[flat] = h
        e = e.reshape(x0.shape)
        with torch.no_grad():
            fd = (loss(x0 + e) - loss(x0 - e)) / (2 * h)
        assert abs(float(fd) - float(gd.flatten()[flat])) <= 1e-4 * max(1.0, abs(float(fd))), (flat, fd)


def test_appearance_gradients_reach_every_parameter(bound):
    mesh, art = bound
    g = BoundGaussians.from_artefact(art, mesh)
    cam = look_at("c", [0.3, 0.1, 0.2], 48)
    out = g.render(torch.as_tensor(mesh.vertices), cam, background=torch.tensor([0.1, 0.2, 0.3]))
    out.image.mean().backward()
    for name, p in g.named_parameters():
        assert p.grad is not None and float(p.grad.abs().max()) > 0, name


def test_artefact_round_trip(bound, tmp_path):
    mesh, art = bound
    g = BoundGaussians.from_artefact(art, mesh)
    back = GaussiansArtefact(**g.arrays(), fit_psnr={"c": 30.0})
    back.save(tmp_path / "g.h5")
    again = GaussiansArtefact.load(tmp_path / "g.h5")
    np.testing.assert_allclose(again.bary, art.bary, atol=1e-6)
    np.testing.assert_allclose(again.sh, art.sh, atol=1e-6)
    q = art.rotations / np.linalg.norm(art.rotations, axis=1, keepdims=True)
    np.testing.assert_allclose(again.rotations, q, atol=1e-6)
    assert again.fit_psnr == {"c": 30.0}


def test_losses():
    gen = torch.Generator().manual_seed(0)
    a = torch.rand(32, 40, 3, generator=gen)
    assert abs(float(ssim(a, a)) - 1.0) < 1e-6
    assert float(l1_dssim(a, a)) < 1e-6
    b = (a + 0.1).clamp(0, 1)
    assert float(ssim(a, b)) < 1.0
    assert abs(psnr(a, a + 0.01) - 40.0) < 1e-3
    # SSIM is symmetric and invariant to nothing else: a constant shift lowers the luminance term only.
    assert abs(float(ssim(a, b)) - float(ssim(b, a))) < 1e-6


def test_sh_degree_one_is_view_dependent(bound):
    """With degree-1 SH the same Gaussians look different from opposite sides, and sh₁..₃ get gradients."""
    mesh, art = bound
    sh = np.zeros((art.sh.shape[0], 4, 3))
    sh[:, 0] = art.sh[:, 0]
    sh[:, 3] = 0.8  # −C₁ x term: brighter when the view direction has x < 0 (camera on the +x side)
    g = BoundGaussians.from_artefact(GaussiansArtefact(art.host_tet, art.bary, art.log_scales, art.rotations,
                                                       art.opacity_logit, sh), mesh)
    x = torch.as_tensor(mesh.vertices)
    a = g.render(x, look_at("a", [0.3, 0.0, 0.1], 32))
    with torch.no_grad():
        b = g.render(x, look_at("b", [-0.3, 0.0, 0.1], 32)).image
        lit_a, lit_b = float(a.image.detach().sum()), float(b.sum())
    assert lit_a > 1.2 * lit_b
    a.image.mean().backward()
    assert float(g.sh.grad[:, 1:].abs().max()) > 0


def _scrambled(mesh, art, n: int, seed: int) -> BoundGaussians:
    """Gaussians with random rotations, anisotropic scales and barycentric logits (float64)."""
    rng = np.random.default_rng(seed)
    g = BoundGaussians.from_artefact(art, mesh).double()
    with torch.no_grad():
        g.rotations.copy_(torch.as_tensor(rng.normal(size=g.rotations.shape)))
        g.log_scales.add_(torch.as_tensor(rng.normal(scale=0.4, size=g.log_scales.shape)))
        g.bary_logits.add_(torch.as_tensor(rng.normal(size=g.bary_logits.shape)))
    return g


@pytest.mark.parametrize("eye", [[0.3, 0.1, 0.2], [0.06, 0.02, 0.04]], ids=["outside", "inside-the-box"])
def test_fused_projection_matches_torch_ops(bound, eye):
    """bind_project (numba) = centres / covariance_factors / project_gaussians (torch), values and gradients.

    The second camera sits inside the box's bounding region, so some Gaussians are behind it or
    far off-screen (culled, clamped Jacobians)."""
    mesh, art = bound
    g = _scrambled(mesh, art, 400, 8)
    cam = g.camera(look_at("c", eye, 48, f=50.0))
    rng = np.random.default_rng(9)
    x = torch.as_tensor(mesh.vertices + rng.normal(scale=0.004, size=mesh.vertices.shape))
    wm = torch.as_tensor(rng.normal(size=(400, 2)))
    wc = torch.as_tensor(rng.normal(size=(400, 3)))
    res = []
    for fused in (True, False):
        xr = x.clone().requires_grad_(True)
        g.zero_grad()
        m, c, d, v, _ = g.project(xr, cam, fused)
        (m * wm)[v].sum().add((c * wc)[v].sum()).backward()
        res.append((m.detach(), c.detach(), d.detach(), v, xr.grad,
                    [p.grad.clone() for p in (g.bary_logits, g.log_scales, g.rotations)]))
    (m1, c1, d1, v1, gx1, gp1), (m2, c2, d2, v2, gx2, gp2) = res
    assert torch.equal(v1, v2) and 0 < int(v1.sum())
    if eye[0] < 0.1:
        assert int(v1.sum()) < 400
    torch.testing.assert_close(m1[v1], m2[v1], rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(c1[v1], c2[v1], rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(d1, d2, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(gx1, gx2, rtol=1e-9, atol=1e-9)
    for a, b in zip(gp1, gp2):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11)


def test_fused_projection_gradcheck(bound):
    from stages.render.bind_project import bind_project

    mesh, art = bound
    sub = GaussiansArtefact(art.host_tet[:12], art.bary[:12], art.log_scales[:12], art.rotations[:12],
                            art.opacity_logit[:12], art.sh[:12])
    g = _scrambled(mesh, sub, 12, 10)
    cam = g.camera(look_at("c", [0.3, 0.1, 0.2], 48, f=50.0))
    rng = np.random.default_rng(11)
    wm, wc = torch.as_tensor(rng.normal(size=(12, 2))), torch.as_tensor(rng.normal(size=(12, 3)))

    def f(x, bl, ls, q):
        m, c, _, v = bind_project(x, bl, ls, q, g.host_vertices, g.dm_inv, cam)
        return (m * wm).sum() + (c * wc).sum()

    ins = [torch.as_tensor(mesh.vertices).clone().requires_grad_(True)] + \
        [p.detach().clone().requires_grad_(True) for p in (g.bary_logits, g.log_scales, g.rotations)]
    assert torch.autograd.gradcheck(f, ins, eps=1e-7, atol=1e-6, rtol=1e-5)
