"""Quadratic (P2, 10-node) tets downstream of the FEM core: the reduced model and its cubature over
quadrature points, Gaussians bound through the quadratic map, and VTK quadratic-tetra export.

The P2 scene is a small cantilever bar (stages.sim.meshgen.box_tets + quadrature.quadratic_tets), the
P1 scene the same bar with linear tets.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from stages.domain.rotations import axis_angle_matrix
from stages.sim import quadrature as Q
from stages.sim.meshgen import box_tets
from stages.sim.mesh import rest_quantities
from stages.sim.scene import FrameInputs, HandleSpec, Scene
from stages.subspace import ReducedModel
from stages.subspace.cubature import ReducedForceSampler, cubature_error, fit_cubature, point_energies, \
    scene_quadrature
from stages.subspace.networks import SubspaceMap
from stages.subspace.train import fit_subspace, mass_orthonormalise

YOUNG, POISSON = np.array([3e4, 6e4]), np.array([0.40, 0.45])
SIZE = (0.2, 0.05, 0.05)


def bar_scene(order: int = 2, cells=(6, 1, 1), curved: float = 0.0) -> Scene:
    """Bar clamped at x = 0 by a stiff handle, two regions; ``curved`` bows the mid-edge nodes of the
    top face up by that many metres (curved quadratic elements)."""
    v, t = box_tets(cells, SIZE)
    if order == 2:
        v, t = Q.quadratic_tets(v, t)
        if curved:
            n_corner = int(t[:, :4].max()) + 1
            top = np.zeros(len(v), bool)
            top[n_corner:] = np.abs(v[n_corner:, 2] - SIZE[2]) < 1e-12
            v = v.copy()
            v[top, 2] += curved * np.sin(np.pi * v[top, 0] / SIZE[0])
    vol, dmi, m = rest_quantities(v, t, 1000.0)
    region = (v[t[:, :4]].mean(1)[:, 0] > 0.1).astype(np.int64)
    hid = np.nonzero(v[:, 0] < 1e-9)[0]
    return Scene(rest=v, tets=t, dm_inv=dmi, volumes=vol, masses=m, tet_region=region, n_regions=2,
                 region_names=("a", "b"), material="stable_neohookean", dt=1 / 30, gravity=np.array([0, 0, -9.81]),
                 handles=(HandleSpec("clamp", hid, 1e3),), loads=(), obstacles=(), friction=0.0,
                 contact_stiffness=2e3, contact_margin=1e-3)


def synthetic_snapshots(scene: Scene, count: int, seed: int) -> np.ndarray:
    """Smooth bending / twisting deformations of the bar (S, n, 3): rotations of the cross-sections
    growing along x (nonlinear in the angles), a few mm to cm."""
    rng = np.random.default_rng(seed)
    X = scene.rest
    s = X[:, 0] / SIZE[0]
    out = []
    for _ in range(count):
        ay, az, ax = rng.uniform(-0.6, 0.6, 3)
        ty, tz, tx = ay * s ** 2, az * s ** 2, ax * s  # bending about y, z and twist about x
        y, z = X[:, 1] - SIZE[1] / 2, X[:, 2] - SIZE[2] / 2
        x = X.copy()
        x[:, 1] = SIZE[1] / 2 + np.cos(tx) * y - np.sin(tx) * z
        x[:, 2] = SIZE[2] / 2 + np.sin(tx) * y + np.cos(tx) * z
        x[:, 2] += 0.1 * SIZE[0] * np.sin(ty) * s
        x[:, 1] += 0.1 * SIZE[0] * np.sin(tz) * s
        x[:, 0] -= 0.05 * (z * np.sin(ty) + y * np.sin(tz))
        out.append(x)
    return np.stack(out)


def frame_inputs_bar(scene: Scene, lift: float) -> FrameInputs:
    hid = scene.handles[0].ids
    target = scene.rest[hid] + np.array([0.0, 0.2 * lift, lift])
    return FrameInputs((target,), np.zeros_like(scene.rest), np.zeros((0, 7)))


@pytest.fixture(scope="module")
def p2():
    scene = bar_scene(2)
    snaps = synthetic_snapshots(scene, 60, 0)
    ae, _ = fit_subspace("autoencoder", scene.rest, scene.masses, snaps, 4, epochs=40, seed=0, pca_dim=8)
    pca, _ = fit_subspace("pca", scene.rest, scene.masses, snaps, 6)
    return scene, snaps, ae, pca


def _states(sub, snaps):
    z = np.asarray(sub.encode(jnp.asarray(snaps[:3])))
    return z[2], z[1], z[0]


# --------------------------------------------------------------------------- quadrature of the scene
def test_scene_quadrature_is_the_p1_tets_and_four_points_per_p2_tet():
    s1, s2 = bar_scene(1), bar_scene(2)
    q1, q2 = scene_quadrature(s1), scene_quadrature(s2)
    assert q1.n_points == len(s1.tets) and np.array_equal(q1.element, np.arange(len(s1.tets)))
    assert np.array_equal(q1.weight, s1.volumes)
    assert q2.n_points == 4 * len(s2.tets) and q2.nodes.shape == (q2.n_points, 10)
    assert np.isclose(q2.weight.sum(), np.prod(SIZE), rtol=1e-12)
    # a P2 point's energy at an affine deformation is the homogeneous one: Σ_q V_q Ψ(A) = V Ψ(A)
    A = np.array([[1.1, 0.05, 0.0], [0.0, 0.95, 0.02], [0.01, 0.0, 1.03]])
    mu, lam = np.full(q2.n_points, 1e4), np.full(q2.n_points, 4e4)
    e2 = np.asarray(point_energies(jnp.asarray(s2.rest @ A.T), q2, mu, lam, "stable_neohookean"))
    e1 = np.asarray(point_energies(jnp.asarray(s1.rest @ A.T), q1, mu[: q1.n_points], lam[: q1.n_points],
                                   "stable_neohookean"))
    assert np.isclose(e2.sum(), e1.sum(), rtol=1e-12)


# --------------------------------------------------------------------------- reduced model on P2
def test_p2_reduced_gradient_and_hessian_against_finite_differences(p2):
    scene, snaps, ae, pca = p2
    inp = frame_inputs_bar(scene, 0.01)
    for sub in (ae, pca):
        z, z1, z2 = _states(sub, snaps)
        model = ReducedModel(sub, scene)
        assert model.cubature_points.shape == (4 * len(scene.tets),)
        args = (inp, YOUNG, POISSON, z1, z2)
        g = model.gradient(z, *args)
        h = 1e-7
        fd = np.array([(model.energy(z + h * e, *args) - model.energy(z - h * e, *args)) / (2 * h)
                       for e in np.eye(len(z))])
        assert np.linalg.norm(fd - g) <= 1e-6 * np.linalg.norm(g), np.linalg.norm(fd - g) / np.linalg.norm(g)
        H = model.hessian(z, *args)
        fdh = np.stack([(model.gradient(z + h * e, *args) - model.gradient(z - h * e, *args)) / (2 * h)
                        for e in np.eye(len(z))])
        assert np.abs(fdh - H).max() <= 1e-5 * np.abs(H).max()


def test_p2_fast_path_with_all_points_equals_reference(p2):
    """All quadrature points with weight 1 = the full incremental potential Φ(φ(z)) of stages.sim.potential
    (gradient, Hessian, energy differences)."""
    scene, snaps, ae, _ = p2
    z, z1, z2 = _states(ae, snaps)
    inp = frame_inputs_bar(scene, 0.01)
    fast, ref = ReducedModel(ae, scene), ReducedModel(ae, scene, reference=True)
    args = (inp, YOUNG, POISSON, z1, z2)
    g_f, g_r = fast.gradient(z, *args), ref.gradient(z, *args)
    assert np.linalg.norm(g_f - g_r) <= 1e-10 * np.linalg.norm(g_r)
    h_f, h_r = fast.hessian(z, *args), ref.hessian(z, *args)
    assert np.abs(h_f - h_r).max() <= 1e-10 * np.abs(h_r).max()
    dz = 1e-3 * np.random.default_rng(0).normal(size=z.shape)
    de_f = fast.energy(z + dz, *args) - fast.energy(z, *args)
    de_r = ref.energy(z + dz, *args) - ref.energy(z, *args)
    assert abs(de_f - de_r) <= 1e-9 * abs(de_r)


@pytest.mark.slow
def test_p2_reduced_rollout_follows_full_space(p2):
    """PCA r = 12 with a 60-point cubature, trained on full-space P2 sequences of a clamp that lifts and
    turns, against the full-space P2 simulation of a held-out sequence."""
    from stages.sim.materials import lame
    from stages.sim.scene import simulate

    scene = p2[0]
    hid = scene.handles[0].ids
    c = scene.rest[hid].mean(0)

    def seq(seed, frames=12):
        rng = np.random.default_rng(seed)
        amp = rng.uniform(-1, 1, 3) * np.array([0.01, 0.5, 0.3])
        out = []
        for f in range(frames):
            s = np.sin(0.5 * np.pi * min(f / 8, 1.0))
            a, b = amp[1] * s, amp[2] * s
            Rx, Rz = axis_angle_matrix([1.0, 0.0, 0.0], a), axis_angle_matrix([0.0, 0.0, 1.0], b)
            target = (scene.rest[hid] - c) @ (Rx @ Rz).T + c + np.array([0, 0, amp[0] * s])
            out.append(FrameInputs((target,), np.zeros_like(scene.rest), np.zeros((0, 7))))
        return out

    ins = [seq(s) for s in range(5)]
    xs = [simulate(scene, i, YOUNG, POISSON) for i in ins]
    train = np.concatenate(xs[:4])
    sub, _ = fit_subspace("pca", scene.rest, scene.masses, train, 12)
    quad = scene_quadrature(scene)
    mu, lam = (np.asarray(a)[scene.tet_region[quad.element]] for a in lame(YOUNG, POISSON))
    sampler = ReducedForceSampler(sub, np.asarray(sub.encode(jnp.asarray(train[::3]))), quad, mu, lam,
                                  scene.material)
    ids, w, _ = fit_cubature(sampler, scene.tet_region[quad.element], 2, max_points=60, tol=1e-3, seed=0)
    diag = np.linalg.norm(scene.rest.max(0) - scene.rest.min(0))
    errs = {}
    for name, model in (("cubature", ReducedModel(sub, scene, (ids, w))), ("all points", ReducedModel(sub, scene))):
        Z = model.simulate(ins[4], YOUNG, POISSON)
        errs[name] = np.linalg.norm(model.decode(Z) - xs[4], axis=-1).mean() / diag
    motion = np.linalg.norm(xs[4] - scene.rest, axis=-1).mean() / diag
    assert errs["all points"] < 0.02 and errs["cubature"] < 0.03, errs
    assert errs["cubature"] < 0.2 * motion, (errs, motion)


def test_hard_handle_is_a_spring_of_its_stiffness_in_the_subspace(p2):
    """The subspace cannot hold vertices exactly: a hard handle acts as its spring, in the fast path and in
    the reference alike."""
    import dataclasses

    scene, snaps, _, pca = p2
    hard = dataclasses.replace(scene, handles=(dataclasses.replace(scene.handles[0], hard=True),))
    z, z1, z2 = _states(pca, snaps)
    args = (frame_inputs_bar(scene, 0.01), YOUNG, POISSON, z1, z2)
    g_spring = ReducedModel(pca, scene).gradient(z, *args)
    g_fast = ReducedModel(pca, hard).gradient(z, *args)
    g_ref = ReducedModel(pca, hard, reference=True).gradient(z, *args)
    assert np.allclose(g_fast, g_spring, rtol=1e-12, atol=0)
    assert np.linalg.norm(g_ref - g_fast) <= 1e-10 * np.linalg.norm(g_fast)


def test_p2_assembled_hessian_equals_forward_over_reverse_on_a_point_subset(p2):
    scene, snaps, ae, pca = p2
    quad = scene_quadrature(scene)
    ids = np.arange(0, quad.n_points, 3)
    wts = np.random.default_rng(1).uniform(0.5, 3.0, len(ids))
    inp = frame_inputs_bar(scene, 0.01)
    for sub in (ae, pca):
        z, z1, z2 = _states(sub, snaps)
        model = ReducedModel(sub, scene, (ids, wts))
        assert model._assembled
        args = model._args(z, z1, z2, YOUNG, POISSON, model.reduce_inputs(inp))
        h_fast, h_twin = np.asarray(model._H(*args)), np.asarray(model._EGH(*args)[2])
        assert np.abs(h_fast - h_twin).max() <= 1e-10 * np.abs(h_twin).max()


def test_p2_cubature_energy_is_the_weighted_point_sum(p2):
    """The reduced elastic energy with a cubature (ids, w) = Σ w_q V_q Ψ(F_q) of the decoded positions,
    F_q from the quadratic shape functions (quadrature.point_map at the Keast points)."""
    scene, snaps, ae, _ = p2
    quad = scene_quadrature(scene)
    ids = np.array([0, 5, 17, 42, quad.n_points - 1])
    w = np.array([1.0, 2.0, 0.5, 3.0, 1.5])
    model = ReducedModel(ae, scene, (ids, w))
    z = _states(ae, snaps)[0]
    x = model.decode(z)
    # independent F: the element's quadratic map at the rule's barycentric points
    pts, frac = Q.RULES[2]
    el = quad.element[ids]
    bary = pts[ids % 4]
    N, G, detJ = Q.point_map(scene.rest, scene.tets, el, bary)
    F = np.einsum("pki,pkj->pij", x[scene.tets[el]], G)
    from stages.sim.materials import energy_density, lame

    mu, lam = lame(YOUNG, POISSON)
    reg = scene.tet_region[el]
    psi = energy_density("stable_neohookean")
    e_ref = sum(wi * f * dj / 6 * float(psi(jnp.asarray(Fi), mu[r], lam[r]))
                for wi, f, dj, Fi, r in zip(w, frac[ids % 4], detJ, F, reg))
    from stages.subspace.reduced import _cubature_elastic

    e = float(_cubature_elastic(jnp.asarray(x[model.vertex_subset]), jnp.asarray(YOUNG), jnp.asarray(POISSON),
                                model.data, "stable_neohookean"))
    assert np.isclose(e, e_ref, rtol=1e-12)


def test_p2_cubature_fit_over_quadrature_points(p2):
    scene, snaps, ae, _ = p2
    quad = scene_quadrature(scene)
    from stages.sim.materials import lame

    mu, lam = (np.asarray(a)[scene.tet_region[quad.element]] for a in lame(YOUNG, POISSON))
    z_fit = np.asarray(ae.encode(jnp.asarray(snaps[::3])))
    sampler = ReducedForceSampler(ae, z_fit, quad, mu, lam, scene.material)
    region = scene.tet_region[quad.element]
    ids, w, info = fit_cubature(sampler, region, 2, max_points=60, tol=1e-3, seed=0)
    assert len(ids) <= 60 and np.all(w > 0) and info["error_rel"] < 0.05
    assert ids.max() < quad.n_points
    sv = ReducedForceSampler(ae, np.asarray(ae.encode(jnp.asarray(snaps[1::7]))), quad, mu, lam, scene.material)
    assert cubature_error(sv, region, 2, ids, w) < 0.1
    # all points with weight 1 reproduce the totals exactly
    allp = np.arange(quad.n_points)
    assert cubature_error(sv, region, 2, allp, np.ones(quad.n_points)) < 1e-12
    # the reduced forces of the cubature model are close to the all-points model's at held-out poses
    cub, full = ReducedModel(ae, scene, (ids, w)), ReducedModel(ae, scene)
    inp = frame_inputs_bar(scene, 0.0)
    z = np.asarray(ae.encode(jnp.asarray(snaps[50])))
    zr = ae.encode(jnp.asarray(scene.rest))
    g_c = cub.gradient(z, inp, YOUNG, POISSON, z, z) - cub.gradient(zr, inp, YOUNG, POISSON, zr, zr)
    g_f = full.gradient(z, inp, YOUNG, POISSON, z, z) - full.gradient(zr, inp, YOUNG, POISSON, zr, zr)
    assert np.linalg.norm(g_c - g_f) <= 0.1 * np.linalg.norm(g_f)


def test_p1_sampler_old_and_quadrature_forms_agree():
    scene = bar_scene(1)
    snaps = synthetic_snapshots(scene, 12, 1)
    sub, _ = fit_subspace("pca", scene.rest, scene.masses, snaps, 4)
    from stages.sim.materials import lame

    mu, lam = (np.asarray(a)[scene.tet_region] for a in lame(YOUNG, POISSON))
    z = np.asarray(sub.encode(jnp.asarray(snaps[:3])))
    a = ReducedForceSampler(sub, z, scene.tets, scene.dm_inv, scene.volumes, mu, lam, scene.material)
    b = ReducedForceSampler(sub, z, scene_quadrature(scene), mu, lam, scene.material)
    ids = np.arange(len(scene.tets))
    assert np.array_equal(a.columns(ids), b.columns(ids))


def test_p2_window_adjoint_against_finite_differences(p2):
    scene, snaps, ae, _ = p2
    model = ReducedModel(ae, scene)
    z0 = np.asarray(ae.encode(jnp.asarray(scene.rest)))
    inp = [frame_inputs_bar(scene, 0.004 * (t + 1)) for t in range(5)]
    Z = model.simulate(inp, YOUNG, POISSON, z0, z0, rtol=1e-12)
    w, t0 = 3, 2
    zb, Zw, inw = Z[t0 - 2: t0], Z[t0: t0 + w], inp[t0: t0 + w]
    c = np.random.default_rng(1).normal(size=Zw.shape)
    young, poisson = np.tile(YOUNG, (w, 1)), np.tile(POISSON, (w, 1))
    g = model.window_adjoint(inw, young, poisson, Zw, zb, dL_dZ=c)

    def loss(y, nu):
        z2, z1 = zb
        tot = 0.0
        for t in range(w):
            z, _ = model.step(inw[t], y[t], nu[t], z1, z2, rtol=1e-12)
            tot += float(c[t] @ z)
            z2, z1 = z1, z
        return tot

    for t in range(w):
        for r in range(2):
            for key, h in (("young", 1e-4 * YOUNG[r]), ("poisson", 1e-6)):
                tp, tm = (young.copy(), young.copy()) if key == "young" else (poisson.copy(), poisson.copy())
                tp[t, r] += h
                tm[t, r] -= h
                fd = ((loss(tp, poisson) - loss(tm, poisson)) if key == "young"
                      else (loss(young, tp) - loss(young, tm))) / (2 * h)
                assert abs(fd - g[key][t, r]) <= 2e-3 * abs(fd) + 1e-9 * np.abs(g[key]).max(), (key, t, r)


def test_subspace_cubature_of_another_order_is_refused(p2):
    from stages.artefacts import SubspaceArtefact
    from stages.errors import RslError

    scene, _, _, pca = p2
    art = SubspaceArtefact("pca", pca.dim, pca.to_weights(), 0.0, 0.0,
                           {"cubature_points": [0, 1], "cubature_weights": [1.0, 1.0], "cubature_order": 1})
    with pytest.raises(RslError, match="order"):
        ReducedModel.from_artefacts(art, scene)
    art.extra["cubature_order"] = 2
    assert np.array_equal(ReducedModel.from_artefacts(art, scene).cubature_points, [0, 1])


def test_lbs_basis_on_p2_mesh_spans_affine_maps(p2):
    scene, snaps, _, _ = p2
    sub, info = fit_subspace("lbs", scene.rest, scene.masses, snaps, 24, tets=scene.tets)
    W = info["lbs"]["weights"]
    assert W.shape[0] == len(scene.rest) and np.allclose(W.sum(1), 1.0) and W.min() >= 0
    # mid-edge nodes carry the mean of their edge's corner weights
    t = scene.tets
    for e, (a, b) in enumerate(Q.P2_EDGES):
        assert np.allclose(W[t[:, 4 + e]], 0.5 * (W[t[:, a]] + W[t[:, b]]))
    # an affine map of the rest shape lies in the span (whole span: 2 handles × 12 = 24 = r)
    A = np.array([[0.02, 0.01, 0.0], [0.0, -0.01, 0.03], [0.01, 0.0, 0.02]])
    x = scene.rest + scene.rest @ A.T + np.array([0.01, 0.0, -0.02])
    err = np.abs(np.asarray(sub.decode(sub.encode(jnp.asarray(x)))) - x).max()
    assert err < 1e-10


# --------------------------------------------------------------------------- Gaussians on P2
def p2_box_mesh(bow: float = 0.006):
    """The 0.1 m test box (2×2×2 cubes × 6 tets) with quadratic tets whose boundary mid-edge nodes are
    pushed outwards by up to ``bow`` m (curved elements), as a MeshArtefact."""
    from stages.artefacts import MeshArtefact
    from test_fit_gaussians import box_tet_mesh

    verts, tets, _ = box_tet_mesh()
    v2, t2 = Q.quadratic_tets(verts, tets, project=lambda p: p * (1 + bow / np.linalg.norm(p, axis=1)[:, None]))
    vol, dmi, m = rest_quantities(v2, t2, 1000.0)
    return MeshArtefact(v2, t2, Q.quadratic_surface(t2), np.zeros(len(t2), np.int64), ["body"], vol, dmi, m, 1000.0)


def p2_gaussians(mesh, n: int, seed: int):
    from stages.artefacts import GaussiansArtefact

    rng = np.random.default_rng(seed)
    host = rng.integers(0, len(mesh.tets), n)
    bary = rng.dirichlet(np.ones(4), n)
    return GaussiansArtefact(host, bary, np.log(rng.uniform(0.002, 0.006, (n, 3))), rng.normal(size=(n, 4)),
                             rng.normal(size=n), rng.normal(scale=0.5, size=(n, 1, 3)))


def test_p2_binding_is_the_quadratic_map_at_the_gaussian():
    """centre = Σ N_a x_a and F = Σ x_a ⊗ G_a with N, G from quadrature.point_map at the Gaussian's bary."""
    import torch

    from stages.render.gaussians import BoundGaussians

    mesh = p2_box_mesh()
    art = p2_gaussians(mesh, 50, 0)
    g = BoundGaussians.from_artefact(art, mesh).double()
    rng = np.random.default_rng(1)
    x = mesh.vertices + rng.normal(scale=0.003, size=mesh.vertices.shape)
    bary = g.bary().detach().numpy()
    N, G, _ = Q.point_map(mesh.vertices, mesh.tets, art.host_tet, bary)
    xe = x[mesh.tets[art.host_tet]]
    mu = np.einsum("gk,gkd->gd", N, xe)
    F = np.einsum("gki,gkj->gij", xe, G)
    with torch.no_grad():
        np.testing.assert_allclose(g.centres(torch.as_tensor(x)).numpy(), mu, rtol=0, atol=1e-14)
        # the module keeps its rest nodes in float32 (rendering precision): F to float32 round-off
        np.testing.assert_allclose(g.deformation(torch.as_tensor(x)).numpy(), F, rtol=0, atol=1e-6)


def test_p2_binding_on_straight_elements_equals_p1_under_affine_motion():
    import torch

    from stages.render.gaussians import BoundGaussians
    from test_fit_gaussians import box_tet_mesh, mesh_artefact

    verts, tets, faces = box_tet_mesh()
    m1 = mesh_artefact(verts, tets, faces)
    m2 = p2_box_mesh(bow=0.0)
    art = p2_gaussians(m2, 40, 3)
    g1, g2 = BoundGaussians.from_artefact(art, m1).double(), BoundGaussians.from_artefact(art, m2).double()
    A = np.array([[1.1, 0.1, 0.0], [-0.05, 0.9, 0.2], [0.0, 0.1, 1.05]])
    x1, x2 = verts @ A.T + 0.01, m2.vertices @ A.T + 0.01
    with torch.no_grad():
        np.testing.assert_allclose(g2.centres(torch.as_tensor(x2)), g1.centres(torch.as_tensor(x1)), atol=1e-15)
        np.testing.assert_allclose(g2.deformation(torch.as_tensor(x2)), g1.deformation(torch.as_tensor(x1)),
                                   atol=1e-12)
        np.testing.assert_allclose(g2.deformation(torch.as_tensor(x2)).numpy(), np.broadcast_to(A, (40, 3, 3)),
                                   atol=1e-12)


def test_p2_fused_projection_matches_torch_forward_and_backward():
    """bind_project's quadratic kernels = BoundGaussians' torch ops (curved elements, non-affine motion),
    values and the gradients of the same random upstream gradient."""
    import torch

    from stages.render.gaussians import BoundGaussians
    from test_fit_gaussians import look_at

    mesh = p2_box_mesh()
    art = p2_gaussians(mesh, 300, 4)
    g = BoundGaussians.from_artefact(art, mesh).double()
    rng = np.random.default_rng(5)
    with torch.no_grad():
        g.bary_logits.add_(torch.as_tensor(rng.normal(size=g.bary_logits.shape)))
    cam = g.camera(look_at("c", [0.3, 0.1, 0.2], 48, f=50.0))
    x = torch.as_tensor(mesh.vertices + rng.normal(scale=0.004, size=mesh.vertices.shape))
    wm, wc = torch.as_tensor(rng.normal(size=(300, 2))), torch.as_tensor(rng.normal(size=(300, 3)))
    res = []
    for fused in (True, False):
        xr = x.clone().requires_grad_(True)
        g.zero_grad()
        m, c, d, v, _ = g.project(xr, cam, fused)
        (m * wm)[v].sum().add((c * wc)[v].sum()).backward()
        res.append((m.detach(), c.detach(), d.detach(), v, xr.grad,
                    [p.grad.clone() for p in (g.bary_logits, g.log_scales, g.rotations)]))
    (m1, c1, d1, v1, gx1, gp1), (m2, c2, d2, v2, gx2, gp2) = res
    assert torch.equal(v1, v2) and int(v1.sum()) > 250
    torch.testing.assert_close(m1[v1], m2[v1], rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(c1[v1], c2[v1], rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(d1, d2, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(gx1, gx2, rtol=1e-9, atol=1e-9)
    for a, b in zip(gp1, gp2):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11)


def test_p2_binding_gradcheck_reference_and_fused():
    import torch

    from stages.render.bind_project import bind_project
    from stages.render.gaussians import BoundGaussians
    from stages.render.projection import project_gaussians
    from test_fit_gaussians import look_at

    mesh = p2_box_mesh()
    g = BoundGaussians.from_artefact(p2_gaussians(mesh, 10, 6), mesh).double()
    cam = g.camera(look_at("c", [0.3, 0.1, 0.2], 48, f=50.0))
    rng = np.random.default_rng(7)
    wm, wc = torch.as_tensor(rng.normal(size=(10, 2))), torch.as_tensor(rng.normal(size=(10, 3)))

    def fused(x, bl, ls, q):
        m, c, _, _ = bind_project(x, bl, ls, q, g.host_vertices, g.rest_nodes, cam)
        return (m * wm).sum() + (c * wc).sum()

    def reference(x, bl, ls, q):
        with torch.no_grad():
            g.bary_logits.copy_(bl)
            g.log_scales.copy_(ls)
            g.rotations.copy_(q)
        # the same maths with the leaf tensors spliced in
        from stages.render.gaussians import p2_shape, quat_to_rotmat

        beta = torch.softmax(bl, 1)
        N, dN = p2_shape(beta)
        p = x[g.host_vertices]
        mu = (N[:, :, None] * p).sum(1)
        F = torch.einsum("gai,gaj->gij", p, dN) @ torch.linalg.inv(torch.einsum("gai,gaj->gij", g.rest_nodes, dN))
        M = F @ (quat_to_rotmat(q) * torch.exp(ls)[:, None, :])
        proj = project_gaussians(mu, None, cam, factors=M)
        return (proj.means2d * wm).sum() + (proj.conics * wc).sum()

    x0 = torch.as_tensor(mesh.vertices + rng.normal(scale=0.003, size=mesh.vertices.shape))
    ins = [x0.clone().requires_grad_(True)] + \
        [p.detach().clone().requires_grad_(True) for p in (g.bary_logits, g.log_scales, g.rotations)]
    assert torch.autograd.gradcheck(reference, ins, eps=1e-7, atol=1e-6, rtol=1e-5)
    assert torch.autograd.gradcheck(fused, ins, eps=1e-7, atol=1e-6, rtol=1e-5)


def test_p2_point_location_inverts_the_curved_element_map():
    from stages.sim.locate import locate_in_elements

    mesh = p2_box_mesh(bow=0.01)
    rng = np.random.default_rng(8)
    x = mesh.vertices + rng.normal(scale=0.002, size=mesh.vertices.shape)  # a deformed, curved configuration
    host = rng.integers(0, len(mesh.tets), 200)
    bary = rng.dirichlet(np.ones(4) * 3, 200)
    N, _, _ = Q.point_map(mesh.vertices, mesh.tets, host, bary)
    pts = np.einsum("gk,gkd->gd", N, x[mesh.tets[host]])
    h, b = locate_in_elements(pts, x, mesh.tets)
    N2 = Q.shape_values(2, b)
    np.testing.assert_allclose(np.einsum("gk,gkd->gd", N2, x[mesh.tets[h]]), pts, atol=1e-13)
    assert b.min() > -1e-9  # found inside an element
    inner = bary.min(1) > 0.05  # well inside: the same element and coordinates
    assert np.array_equal(h[inner], host[inner])
    np.testing.assert_allclose(b[inner], bary[inner], atol=1e-10)


def test_p2_image_loss_matches_bound_gaussians_and_rebinds_exactly():
    import torch

    from stages.render.image_loss import ImageLoss
    from stages.render.gaussians import BoundGaussians
    from test_fit_gaussians import look_at

    mesh = p2_box_mesh()
    art = p2_gaussians(mesh, 400, 9)
    art.opacity_logit = np.full(400, 2.0)
    cam = look_at("c", [0.3, 0.1, 0.2], 48, f=50.0)
    loss = ImageLoss(art, mesh, [cam])
    rng = np.random.default_rng(10)
    x = mesh.vertices + rng.normal(scale=0.003, size=mesh.vertices.shape)
    with torch.no_grad():
        a = loss.images(torch.as_tensor(x))[0]
        b = BoundGaussians.from_artefact(art, mesh).render(torch.as_tensor(x), cam).image
    assert float((a - b).abs().max()) < 1e-4 and float(a.std()) > 0.01
    # rebind to a deformed fit-frame shape: rendered there, the Gaussians are the fitted ones
    loss.rebind(x)
    N, G, _ = Q.point_map(mesh.vertices, mesh.tets, loss.host_tet, loss._bary_np)
    xe = x[mesh.tets[loss.host_tet]]
    np.testing.assert_allclose(np.einsum("gk,gkd->gd", N, xe), loss._fit_means, atol=1e-6)
    F = np.einsum("gki,gkj->gij", xe, G)
    cov = F @ loss._cov0.double().numpy() @ F.transpose(0, 2, 1)
    np.testing.assert_allclose(cov, loss._fit_cov, rtol=1e-4, atol=1e-10)


def test_markers_bind_to_the_p2_surface():
    from stages.sim.markers import bind_markers

    mesh = p2_box_mesh()
    faces = mesh.surface_faces
    rng = np.random.default_rng(11)
    f = rng.integers(0, len(faces), 30)
    b = rng.dirichlet(np.ones(3), 30)
    m0 = np.einsum("mk,mkd->md", b, mesh.vertices[faces[f]])
    binding = bind_markers(mesh.vertices, faces, m0)
    assert binding.distance.max() < 1e-12 and binding.faces.max() >= mesh.tets[:, :4].max()  # mid-edge nodes
    np.testing.assert_allclose(binding.positions(mesh.vertices), m0, atol=1e-12)


# --------------------------------------------------------------------------- export
SIZE_EXPORT = (0.1, 0.02, 0.02)  # test_export.SIZE
@pytest.fixture(scope="module")
def p2_stretch_ws(tmp_path_factory):
    """test_export's uniaxial stretch ramp on a quadratic-tet block (homogeneous F at every point)."""
    from stages.artefacts import AdaptArtefact, MeshArtefact, Provenance
    from stages.sim.materials import lame
    from test_export import E, NU, SIZE, snh_uniaxial, stretch_controls, write_capture
    from test_stress_meshes import block_mesh

    root = tmp_path_factory.mktemp("export_p2")
    v, t, _ = block_mesh(SIZE, (4, 1, 1))
    v2, t2 = Q.quadratic_tets(v, t)
    vol, dmi, m = rest_quantities(v2, t2, 1000.0)
    mesh = MeshArtefact(v2, t2, Q.quadratic_surface(t2), np.zeros(len(t2), np.int64), ["body"], vol, dmi, m, 1000.0)
    ws = root / "ws"
    ws.mkdir()
    mesh.save(ws / "mesh.h5")
    stretches = np.linspace(1.0, 1.2, 4)
    mu, lam = lame(E, NU)
    l2s = np.array([snh_uniaxial(l1, mu, lam)[0] for l1 in stretches])
    cap = write_capture(root / "capture", mesh, stretch_controls(stretches, l2s))
    pos = np.stack([v2 * np.array([l1, l2, l2]) for l1, l2 in zip(stretches, l2s)])
    T = len(stretches)
    AdaptArtefact(
        frames=np.arange(T), young=np.full((T, 1), E), poisson=np.full((T, 1), NU), z=np.zeros((T, 0)),
        positions=pos, loss=np.linspace(1.0, 0.1, T), time_forward_s=np.full(T, 0.1),
        time_backward_s=np.full(T, 0.2), time_render_s=np.full(T, 0.05), time_total_s=np.full(T, 0.4),
        region_names=["body"], mode="offline", space="full", loss_kind="markers", window=T,  # forces from positions
    ).save(ws / "adapt.h5", Provenance.make({"capture": str(cap), "workspace": str(ws)}))
    return {"ws": ws, "mesh": mesh, "stretches": stretches, "l2s": l2s, "root": root, "mu": mu, "lam": lam}


def test_p2_export_stress_per_point_and_vtk_quadratic_tetra(p2_stretch_ws):
    import meshio
    import pyvista

    from stages.artefacts import StressArtefact
    from stages.steps.export import ExportConfig, read_pvd, run
    from test_export import snh_uniaxial

    d = p2_stretch_ws
    out = run(ExportConfig(workspace=d["ws"], stress=True, vtk=True, out=d["root"] / "out"))
    art = StressArtefact.load(out / "stress.h5")
    mesh = d["mesh"]
    m = len(mesh.tets)
    assert art.von_mises_point.shape == (4, 4 * m) and np.array_equal(art.point_element, np.repeat(np.arange(m), 4))
    series = read_pvd(out / "vtk" / "adapt.pvd")
    assert len(series) == 4
    for i, (_, path) in enumerate(series):
        s11 = abs(snh_uniaxial(d["stretches"][i], d["mu"], d["lam"])[2])
        np.testing.assert_allclose(art.von_mises_point[i], s11, rtol=1e-6, atol=1e-9 * 2e5)
        np.testing.assert_allclose(art.von_mises_tet[i], s11, rtol=1e-6, atol=1e-9 * 2e5)
        vm = meshio.read(path)
        assert vm.points.shape == mesh.vertices.shape
        np.testing.assert_array_equal(vm.cells_dict["tetra10"], mesh.tets)
        np.testing.assert_allclose(vm.cell_data["von_mises"][0], art.von_mises_tet[i])
        grid = pyvista.read(path)  # what ParaView reads: VTK's own XML reader
        assert grid.n_points == len(mesh.vertices) and grid.n_cells == m
        assert set(np.asarray(grid.celltypes).tolist()) == {24}  # VTK_QUADRATIC_TETRA
        l1, l2 = d["stretches"][i], d["l2s"][i]
        assert np.isclose(grid.volume, np.prod(SIZE_EXPORT) * l1 * l2 * l2, rtol=1e-9)
    # internal nodal forces balance (no external load in the elastic forces)
    np.testing.assert_allclose(art.internal_forces.sum(1), 0.0, atol=1e-9)


def test_p2_gaussian_values_follow_the_quadratic_field(p2_stretch_ws):
    from stages.steps.export import gaussian_values

    mesh = p2_stretch_ws["mesh"]
    art = p2_gaussians(mesh, 20, 12)
    field = mesh.vertices[:, 0] ** 2  # quadratic: reproduced exactly by the P2 interpolant
    N, _, _ = Q.point_map(mesh.vertices, mesh.tets, art.host_tet, art.bary)
    pos = np.einsum("gk,gkd->gd", N, mesh.vertices[mesh.tets[art.host_tet]])
    np.testing.assert_allclose(gaussian_values(art, mesh, field), pos[:, 0] ** 2, atol=1e-15)


@pytest.mark.slow
def test_fit_gaussians_on_a_p2_mesh_reaches_psnr(tmp_path):
    """rsl fit-gaussians (the real CLI) on test_fit_gaussians' box capture with a quadratic-tet mesh.h5."""
    from conftest import run_rsl
    from stages.artefacts import GaussiansArtefact
    from test_fit_gaussians import FIT_PSNR_DB, make_capture

    cap, ws = tmp_path / "capture", tmp_path / "ws"
    make_capture(cap, ws)
    p2_box_mesh(bow=0.0).save(ws / "mesh.h5")
    proc = run_rsl("fit-gaussians", cap, "-w", ws, "--iterations", "60", "--gaussians", "1500")
    assert proc.returncode == 0, proc.stderr
    art = GaussiansArtefact.load(ws / "gaussians.h5")
    assert art.host_tet.max() < 48 and min(art.fit_psnr.values()) >= FIT_PSNR_DB, art.fit_psnr


# --------------------------------------------------------------------------- generate-data → train-subspace
@pytest.mark.slow
def test_generate_data_and_train_subspace_on_a_p2_mesh_through_the_cli(tmp_path, rsl):
    """The real CLI on a quadratic-tet mesh.h5: snapshots over all nodes, an autoencoder and a cubature of
    quadrature points, which ReducedModel loads and steps with."""
    import json

    import meshio

    from stages.artefacts import MeshArtefact, Provenance, SnapshotsArtefact, SubspaceArtefact
    from stages.capture import load_capture, select_handles
    from stages.artefacts import mesh_artefact
    from stages.sim.scene import frame_inputs, make_scene
    from test_generate_data import TOML, _controls

    cap_dir, ws = tmp_path / "capture", tmp_path / "ws"
    cap_dir.mkdir()
    v, t = box_tets((5, 1, 1), (0.2, 0.04, 0.04))
    meshio.write(str(cap_dir / "object.mesh"), meshio.Mesh(v, [("tetra", t)]), file_format="medit")
    (cap_dir / "capture.toml").write_text(TOML)
    (cap_dir / "controls.json").write_text(json.dumps(_controls()))
    cap = load_capture(cap_dir)
    mesh = mesh_artefact(v, t, cap.density, order=2)
    mesh.handles = select_handles(cap.controls(), mesh.vertices)
    mesh.save(ws / "mesh.h5", Provenance.make({}, []))
    proc = rsl("generate-data", cap_dir, "-w", ws, "--sequences", "4", "--frames", "8", "--workers", "1")
    assert proc.returncode == 0, proc.stderr
    snap = SnapshotsArtefact.load(ws / "snapshots.h5")
    assert snap.positions.shape == (32, len(mesh.vertices), 3)
    proc = rsl("train-subspace", "-w", ws, "--dim", "3", "--epochs", "20", "--cubature-tets", "40",
               "--cubature-poses", "10")
    assert proc.returncode == 0, proc.stderr
    assert "quadrature points" in proc.stdout + proc.stderr
    art = SubspaceArtefact.load(ws / "subspace.h5")
    pts = np.asarray(art.extra["cubature_points"])
    assert art.extra["cubature_order"] == 2 and 0 < len(pts) <= 40 and pts.max() < 4 * len(mesh.tets)
    mesh = MeshArtefact.load(ws / "mesh.h5")
    scene = make_scene(mesh, cap.controls(), "stable_neohookean", 1 / 30, np.array([0, 0, -9.81]))
    model = ReducedModel.from_artefacts(art, scene)
    Z = model.simulate([frame_inputs(scene, cap.controls(), f) for f in range(3)], np.array([1e5]), np.array([0.4]))
    assert Z.shape == (3, 3) and np.all(np.isfinite(Z))


def test_p2_export_forces_match_closed_form(p2_stretch_ws):
    """forces.csv on the quadratic-tet block: the handles' internal-force sums are ∓P₁₁·area."""
    import csv

    from stages.steps.export import ExportConfig, run
    from test_export import snh_uniaxial

    d = p2_stretch_ws
    out = run(ExportConfig(workspace=d["ws"], forces=True, out=d["root"] / "forces"))
    with open(out / "forces.csv") as f:
        rows = list(csv.DictReader(f))
    area = SIZE_EXPORT[1] * SIZE_EXPORT[2]
    for i, l1 in enumerate(d["stretches"]):
        P11 = snh_uniaxial(l1, d["mu"], d["lam"])[1]
        r = {row["name"]: row for row in rows if int(row["frame"]) == i}
        assert float(r["right"]["fx_N"]) == pytest.approx(-P11 * area, rel=1e-6, abs=1e-9)
        assert float(r["left"]["fx_N"]) == pytest.approx(P11 * area, rel=1e-6, abs=1e-9)
