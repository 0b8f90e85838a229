"""One Gaussian renderer: the fused numba projection of Gaussians given by (β, L) — the binding ImageLoss re-anchors
(stages.render.bind_project.project_bound) — held to its torch twin (render.gaussians.bound_geometry +
projection.project_gaussians), values and gradients in positions, β and L, on linear and curved quadratic tets;
and ImageLoss on the fused path held to ImageLoss on the twin after a rebind, anchor gradient included."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from stages.render.bind_project import bind_project, fitted_binding, project_bound
from stages.render.gaussians import BoundGaussians, bound_geometry
from stages.render.projection import project_gaussians
from test_fit_gaussians import box_tet_mesh, look_at, mesh_artefact, truth_gaussians
from test_p2_downstream import p2_box_mesh, p2_gaussians


def _mesh_and_gaussians(order: int, n: int):
    if order == 1:
        verts, tets, faces = box_tet_mesh()
        mesh = mesh_artefact(verts, tets, faces)
        return mesh, truth_gaussians(mesh, n, seed=2)
    mesh = p2_box_mesh()
    return mesh, p2_gaussians(mesh, n, 4)


def _binding(order: int, n: int, seed: int):
    """Gaussians bound by (β, L) with β off the softmax's range (some coordinates slightly negative, as after a
    rebind near a face) and L not of the form R S (an arbitrary factor), float64."""
    mesh, art = _mesh_and_gaussians(order, n)
    g = BoundGaussians.from_artefact(art, mesh).double()
    rng = np.random.default_rng(seed)
    beta = rng.dirichlet(np.ones(4) * 2, n) + rng.normal(scale=0.02, size=(n, 4))
    beta /= beta.sum(1, keepdims=True)
    L = 0.004 * (np.eye(3) + 0.4 * rng.normal(size=(n, 3, 3)))
    return mesh, g, torch.as_tensor(beta), torch.as_tensor(L)


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("eye", [[0.3, 0.1, 0.2], [0.06, 0.02, 0.04]], ids=["outside", "inside-the-box"])
def test_project_bound_matches_its_torch_twin(order, eye):
    mesh, g, beta, L = _binding(order, 300, 7)
    cam = g.camera(look_at("c", eye, 48, f=50.0))
    rng = np.random.default_rng(8)
    x = torch.as_tensor(mesh.vertices + rng.normal(scale=0.002, size=mesh.vertices.shape))
    wm, wc = torch.as_tensor(rng.normal(size=(300, 2))), torch.as_tensor(rng.normal(size=(300, 3)))
    res = []
    for fused in (True, False):
        xr, br, Lr = (a.clone().requires_grad_(True) for a in (x, beta, L))
        if fused:
            m, c, d, v = project_bound(xr, br, Lr, g.host_vertices, g.shape, cam)
        else:
            means, M = bound_geometry(xr, br, Lr, g.host_vertices, g.shape, torch.float64)
            p = project_gaussians(means, None, cam, factors=M)
            m, c, d, v = p.means2d, p.conics, p.depths, p.visible
        (m * wm)[v].sum().add((c * wc)[v].sum()).backward()
        res.append((m.detach(), c.detach(), d.detach(), v, xr.grad, br.grad, Lr.grad))
    (m1, c1, d1, v1, *g1), (m2, c2, d2, v2, *g2) = res
    assert torch.equal(v1, v2) and 0 < int(v1.sum())
    torch.testing.assert_close(m1[v1], m2[v1], rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(c1[v1], c2[v1], rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(d1, d2, rtol=1e-12, atol=1e-15)
    for a, b in zip(g1, g2):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9 * float(b.abs().max()))
    assert float(g1[1].abs().max()) > 0 and float(g1[2].abs().max()) > 0  # β and L gradients reach the kernel


@pytest.mark.parametrize("order", [1, 2])
def test_project_bound_gradcheck(order):
    mesh, g, beta, L = _binding(order, 300, 9)
    keep = torch.arange(10)
    hv, shape = g.host_vertices[keep], g.shape[keep]
    cam = g.camera(look_at("c", [0.3, 0.1, 0.2], 48, f=50.0))
    rng = np.random.default_rng(10)
    wm, wc = torch.as_tensor(rng.normal(size=(10, 2))), torch.as_tensor(rng.normal(size=(10, 3)))

    def f(x, b, l):
        m, c, _, _ = project_bound(x, b, l, hv, shape, cam)
        return (m * wm).sum() + (c * wc).sum()

    ins = [torch.as_tensor(mesh.vertices).clone().requires_grad_(True), beta[keep].clone().requires_grad_(True),
           L[keep].clone().requires_grad_(True)]
    assert torch.autograd.gradcheck(f, ins, eps=1e-7, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("order", [1, 2])
def test_bind_project_is_project_bound_on_the_fitted_binding(order):
    """bind_project = project_bound at (β, L) = fitted_binding(logits, log-scales, rotations): the same floats."""
    mesh, art = _mesh_and_gaussians(order, 200)
    g = BoundGaussians.from_artefact(art, mesh)
    cam = g.camera(look_at("c", [0.3, 0.1, 0.2], 48, f=50.0))
    x = torch.as_tensor(mesh.vertices)
    a = bind_project(x, g.bary_logits, g.log_scales, g.rotations, g.host_vertices, g.shape, cam)
    beta, L = fitted_binding(g.bary_logits, g.log_scales, g.rotations)
    b = project_bound(x, torch.as_tensor(beta), torch.as_tensor(L), g.host_vertices, g.shape, cam, g.dtype)
    for u, v in zip(a, b):
        assert torch.equal(u, v)


@pytest.mark.parametrize("order", [1, 2])
def test_image_loss_fused_equals_its_torch_twin_after_a_rebind(order):
    """ImageLoss on the fused kernel and on the torch twin (forced): the loss, dL/dx and the anchor's dL/dx_a."""
    from stages.render.image_loss import ImageLoss

    mesh, art = _mesh_and_gaussians(order, 300)
    art.opacity_logit = np.full(300, 2.0)
    cams = [look_at("a", [0.3, 0.1, 0.2], 48, f=50.0), look_at("b", [-0.1, 0.3, 0.15], 40, f=45.0)]
    rng = np.random.default_rng(11)
    x_a = mesh.vertices + rng.normal(scale=0.001, size=mesh.vertices.shape)
    x = x_a + 0.01 * np.sin(mesh.vertices[:, [1, 2, 0]] * 20.0)
    targets = [rng.uniform(0, 1, (c.height, c.width, 3)).astype(np.float32) for c in cams]
    out = []
    for fused in (True, False):
        il = ImageLoss(art, mesh, cams)
        if not fused:
            il.g.fusable = lambda cam: False
        il.rebind(x_a)
        out.append(il(x, targets, anchor_grad=True))
    (l1, gx1, ga1), (l2, gx2, ga2) = out
    assert abs(l1 - l2) < 1e-5 * abs(l2)
    for a, b in ((gx1, gx2), (ga1, ga2)):
        assert np.abs(b).max() > 0
        assert np.abs(a - b).max() < 1e-4 * np.abs(b).max(), np.abs(a - b).max() / np.abs(b).max()
