"""The renderer's forward mode (stages/render/rasterize_jvp.py, ImageLoss.images_jvp) held to its slow twins:
central differences of the float64 rasterizer, the adjoint identity ⟨u, J v⟩ = ⟨Jᵀ u, v⟩ against the backward
kernels (torch autograd through the same renderer), and torch's own forward mode through the torch projection."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import torch.autograd.forward_ad as fwAD

from stages.artefacts import CamerasArtefact
from stages.render.projection import CameraTensors, project_gaussians
from stages.render.rasterize import rasterize
from stages.render.rasterize_jvp import project_jvp, rasterize_jvp
from test_vision_bias import _bend, _gaussians, _loss, capture  # noqa: F401  (the module-scoped capture fixture)


def _splats(n: int, width: int, height: int, dtype, seed: int = 0):
    """n random 2D Gaussians (means, conics, colours, opacities, depths, visible) in a width × height image."""
    rng = np.random.default_rng(seed)
    m = np.c_[rng.uniform(0, width, n), rng.uniform(0, height, n)]
    s = rng.uniform(1.5, 6.0, (n, 2))
    th = rng.uniform(0, np.pi, n)
    c, sn = np.cos(th), np.sin(th)
    R = np.stack([np.stack([c, -sn], -1), np.stack([sn, c], -1)], -2)
    inv = np.linalg.inv(R @ (s[:, :, None] ** 2 * np.eye(2)) @ R.transpose(0, 2, 1))
    con = np.c_[inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]]
    t = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
    return (t(m), t(con), t(rng.uniform(0, 1, (n, 3))), t(rng.uniform(0.2, 0.9, n)), t(rng.uniform(1, 2, n)),
            torch.ones(n, dtype=torch.bool))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_rasterize_jvp_primal_is_the_render_and_tangents_satisfy_the_adjoint_identity(dtype):
    """rasterize_jvp's colour and coverage are rasterize's (bit for bit), and for each tangent v and a random
    cotangent u, ⟨u, J v⟩ equals ⟨Jᵀ u, v⟩ from the backward kernel (autograd): float64 to 1e-12, float32 to 1e-5."""
    W, H, n, k = 40, 36, 60, 3
    m, con, col, op, dep, vis = _splats(n, W, H, dtype)
    rng = np.random.default_rng(1)
    dm = rng.normal(size=(k, n, 2))
    dc = rng.normal(size=(k, n, 3)) * 0.05 * float(con.abs().max())
    C, A, dC, dA = rasterize_jvp(m, con, col, op, dep, vis, W, H, dm, dc)
    C0, A0 = rasterize(m, con, col, op, dep, vis, W, H)
    assert np.array_equal(C, C0.numpy()) and np.array_equal(A, A0.numpy())
    assert dC.shape == (k, H, W, 3) and dA.shape == (k, H, W)
    u, ua = rng.normal(size=(H, W, 3)), rng.normal(size=(H, W))
    mm, cc = m.clone().requires_grad_(True), con.clone().requires_grad_(True)
    Cq, Aq = rasterize(mm, cc, col, op, dep, vis, W, H)
    ((Cq * torch.as_tensor(u, dtype=dtype)).sum() + (Aq * torch.as_tensor(ua, dtype=dtype)).sum()).backward()
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    for j in range(k):
        lhs = float((u * dC[j]).sum() + (ua * dA[j]).sum())
        rhs = float((mm.grad.double().numpy() * dm[j]).sum() + (cc.grad.double().numpy() * dc[j]).sum())
        assert abs(lhs - rhs) <= tol * (abs(rhs) + np.abs(u).sum() * np.abs(dC[j]).max() * 1e-3), (j, lhs, rhs)


def test_rasterize_jvp_matches_central_differences_in_float64():
    """Each tangent column against (R(p + h v) − R(p − h v)) / 2h of the float64 rasterizer (h = 1e-6: no pixel
    crosses the α cut-off in between)."""
    W, H, n, k = 40, 36, 60, 3
    m, con, col, op, dep, vis = _splats(n, W, H, torch.float64, seed=2)
    rng = np.random.default_rng(3)
    dm = rng.normal(size=(k, n, 2))
    dc = rng.normal(size=(k, n, 3)) * 0.05 * float(con.abs().max())
    _, _, dC, dA = rasterize_jvp(m, con, col, op, dep, vis, W, H, dm, dc)
    h = 1e-6
    for j in range(k):
        Cp, Ap = rasterize(m + h * torch.as_tensor(dm[j]), con + h * torch.as_tensor(dc[j]), col, op, dep, vis, W, H)
        Cm, Am = rasterize(m - h * torch.as_tensor(dm[j]), con - h * torch.as_tensor(dc[j]), col, op, dep, vis, W, H)
        fd, fa = ((Cp - Cm) / (2 * h)).numpy(), ((Ap - Am) / (2 * h)).numpy()
        assert np.abs(fd).max() > 0.05
        assert np.linalg.norm(dC[j] - fd) <= 1e-6 * np.linalg.norm(fd), j
        assert np.linalg.norm(dA[j] - fa) <= 1e-6 * np.linalg.norm(fa), j


def test_project_jvp_matches_torch_forward_mode_of_the_torch_projection(capture):  # noqa: F811
    """project_jvp (numba) against torch's forward mode of projection.project_gaussians (the torch twin, float64), with
    Gaussians beyond the Jacobian's clamp (1.3× the image extent) and behind the near plane among them."""
    cap, ws, _ = capture
    cam = CameraTensors.from_camera(CamerasArtefact.load(ws / "cameras.h5").cameras[0], torch.float64)
    rng = np.random.default_rng(4)
    n, k = 200, 3
    centre = (-cam.R.T @ cam.t).numpy()
    ahead = cam.R[2].numpy()
    # points in front of the camera, spread over ±2× the field of view, a few behind it
    depth = rng.uniform(0.1, 0.5, n)
    depth[:5] = -0.1
    lateral = rng.normal(size=(n, 3)) * depth[:, None] * 0.8
    mu = centre + depth[:, None] * ahead + lateral - (lateral @ ahead)[:, None] * ahead
    M = rng.normal(size=(n, 3, 3)) * 0.01
    d_mu, d_M = rng.normal(size=(k, n, 3)) * 0.01, rng.normal(size=(k, n, 3, 3)) * 0.001
    dm2d, dcon = project_jvp(mu, M, d_mu, d_M, cam)

    vis = project_gaussians(torch.as_tensor(mu), None, cam, factors=torch.as_tensor(M)).visible.numpy()
    assert 0 < vis.sum() < n
    for j in range(k):
        with fwAD.dual_level():  # dual numbers (project_gaussians reads the camera as numpy: no torch.func)
            p = project_gaussians(fwAD.make_dual(torch.as_tensor(mu), torch.as_tensor(d_mu[j])), None, cam,
                                  factors=fwAD.make_dual(torch.as_tensor(M), torch.as_tensor(d_M[j])))
            tm, tc = fwAD.unpack_dual(p.means2d).tangent, fwAD.unpack_dual(p.conics).tangent
        np.testing.assert_allclose(dm2d[j][vis], tm.numpy()[vis], rtol=1e-9, atol=1e-9 * np.abs(tm.numpy()).max())
        np.testing.assert_allclose(dcon[j][vis], tc.numpy()[vis], rtol=1e-9, atol=1e-9 * np.abs(tc.numpy()[vis]).max())
    assert np.all(dm2d[:, :5] == 0) and np.all(dcon[:, :5] == 0)  # behind the near plane: culled, no tangent


@pytest.mark.parametrize("order,distorted", [(1, False), (2, False), (1, True)])
def test_images_jvp_is_the_render_and_the_exact_derivative(capture, order, distorted):  # noqa: F811
    """ImageLoss.images_jvp: the images are images()' (bit for bit), and its columns — positions alone, then with
    the anchor of a rebind moving too (anchored_geometry) — satisfy ⟨u, J v⟩ = ⟨Jᵀ u, v⟩ with Jᵀ u by autograd
    through the same renderer (float32: 1e-4), on linear and quadratic tets, and with lens distortion (the torch
    projection and its dual numbers instead of the fused kernel and project_jvp)."""
    cap, ws, meshes = capture
    mesh = meshes[order]
    cams = CamerasArtefact.load(ws / "cameras.h5").cameras
    if distorted:
        cams = [dataclasses.replace(c, dist=np.array([0.1, -0.05, 0.001, 0.002, 0.0])) for c in cams]
    il = _loss(mesh, cams, _gaussians(mesh, 80, seed=3))
    x = _bend(mesh.vertices, 0.05)
    rng = np.random.default_rng(5)
    size = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    V = np.stack([_bend(mesh.vertices, a) - mesh.vertices for a in (0.02, -0.01)]
                 + [rng.normal(size=mesh.vertices.shape) * 1e-3 * size])
    for anchored in (False, True):
        if anchored:
            il.rebind(_bend(mesh.vertices, 0.02))
            Va = np.stack([0.5 * V[0], -V[1], rng.normal(size=mesh.vertices.shape) * 1e-3 * size])
            binding = il.binding_jvp(il._anchor_x, Va)
        else:
            Va, binding = None, None
        out = il.images_jvp(x, V, binding)
        ref = il.render(x)
        assert all(np.array_equal(o[0], r) for o, r in zip(out, ref))
        u = [rng.normal(size=o[0].shape) for o in out]
        xt = torch.tensor(x, requires_grad=True)
        xa = torch.tensor(il._anchor_x, requires_grad=True) if anchored else None
        sum((im.double() * torch.as_tensor(uu)).sum() for im, uu in zip(il.images(xt, xa), u)).backward()
        for j in range(len(V)):
            lhs = sum(float((uu * o[1][j]).sum()) for uu, o in zip(u, out))
            rhs = float((xt.grad.numpy() * V[j]).sum() + ((xa.grad.numpy() * Va[j]).sum() if anchored else 0.0))
            assert abs(rhs) > 0
            assert lhs == pytest.approx(rhs, rel=1e-4), (anchored, j, lhs, rhs)


def test_images_jvp_columns_agree_with_central_differences_of_the_render(capture):  # noqa: F811
    """The float32 render's exact derivative against its central differences (R(x + h v) − R(x − h v)) / 2h at a
    step moving the Gaussians about 0.05 px: they agree up to the α cut-off's jumps (rasterization is only
    piecewise smooth; measured 10.5 %), within 15 % and at a cosine ≥ 0.99."""
    cap, ws, meshes = capture
    mesh = meshes[1]
    cams = CamerasArtefact.load(ws / "cameras.h5").cameras
    il = _loss(mesh, cams, _gaussians(mesh, 80, seed=3))
    x = _bend(mesh.vertices, 0.05)
    V = np.stack([_bend(mesh.vertices, 0.02) - mesh.vertices])
    out = il.images_jvp(x, V)
    jv = np.concatenate([o[1][0].ravel() for o in out]).astype(np.float64)
    h = 0.05
    fd = (np.concatenate([a.ravel() for a in il.render(x + h * V[0])]).astype(np.float64)
          - np.concatenate([a.ravel() for a in il.render(x - h * V[0])]).astype(np.float64)) / (2 * h)
    assert np.linalg.norm(fd) > 0
    assert np.linalg.norm(jv - fd) <= 0.15 * np.linalg.norm(fd)
    assert jv @ fd >= 0.99 * np.linalg.norm(jv) * np.linalg.norm(fd)


def test_compiled_linear_tangents_are_the_numpy_closed_forms():
    """rasterize_jvp.binding_tangents_linear and geometry_jvp_linear (ImageLoss.jvp_kernel) against ImageLoss's numpy
    matrix products (jvp_kernel False) after a rebind at a bent anchor: dβ, dL of the anchored binding and μ, M, dμ,
    dM of the Gaussians, to rounding (the 3 × 3 inverses by the adjugate, the sums in another order)."""
    from stages.render.image_loss import ImageLoss
    from test_gn_speed_render import tangents_both_ways
    from test_render_project_bound import _mesh_and_gaussians

    mesh, art = _mesh_and_gaussians(1, 300)
    il = ImageLoss(art, mesh, [])
    rng = np.random.default_rng(21)
    v = mesh.vertices
    il.rebind(v + 0.01 * np.sin(v[:, [1, 2, 0]] * 20.0))
    x = v + 0.02 * np.sin(v[:, [2, 0, 1]] * 15.0)
    size = float(np.linalg.norm(np.ptp(v, axis=0)))
    V = rng.normal(size=(3,) + v.shape) * 1e-3 * size
    Va = rng.normal(size=(3,) + v.shape) * 1e-3 * size
    (bf, gf), (bs, gs) = tangents_both_ways(il, "jvp_kernel", x, V, Va)
    assert bf[0] is bs[0] and bf[1] is bs[1]  # the primal binding: the rebind's own
    for a, c in zip(list(bf[2:]) + list(gf), list(bs[2:]) + list(gs)):
        assert a.shape == c.shape and np.abs(c).max() > 0
        np.testing.assert_allclose(a, c, rtol=0, atol=1e-12 * np.abs(c).max())
