"""Quadratic (P2, 10-node) tetrahedra and hard (Dirichlet) handles: quadrature-point kernels against
the per-tet math, finite differences and the JAX twin; patch test; rigid motions; HRZ masses; Newton,
simulate and the window adjoint on P2 scenes; hard handles; handle reactions; mesh.h5 of order 2."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stages.capture import Controls, Handle, Selection, Track
from stages.sim import potential as pot
from stages.sim import stress as st
from stages.sim.elements import HESSIAN, element_terms_jax, point_terms, point_terms_jax
from stages.sim.materials import MODELS, lame
from stages.sim.mesh import rest_quantities
from stages.artefacts import mesh_artefact
from stages.sim.meshgen import box_tets
from stages.sim.quadrature import (build_quadrature, element_volumes, lumped_masses, quadratic_surface,
                                   quadratic_tets)
from stages.sim.scene import (apply_hard_targets, fixed_dofs, frame_inputs, handle_reactions, hessian,
                              internal_forces, make_scene, simulate, step, total_energy, window_adjoint)

jax.config.update("jax_enable_x64", True)

IDENTITY = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
FD_RTOL = 1e-6


def clamp(hard: bool, x_max: float = 1e-9, stiffness: float = 1e5, poses=None) -> Controls:
    track = Track.constant(IDENTITY, True) if poses is None else poses
    h = Handle("clamp", Selection("box", box=np.array([[-1.0, -1, -1], [x_max, 1, 1]])), stiffness, track,
               hard=hard)
    return Controls(handles=[h])


def curved_p2(cells=(2, 1, 1), size=(0.2, 0.1, 0.1), bulge=0.01, seed=0):
    """A P2 box whose mid-edge nodes are moved by up to ``bulge`` m (curved elements)."""
    v, t = box_tets(cells, size)
    v2, t2 = quadratic_tets(v, t)
    rng = np.random.default_rng(seed)
    v2[len(v):] += bulge * rng.uniform(-1, 1, size=(len(v2) - len(v), 3)) * np.array(size) / max(size)
    return v2, t2


def random_state(v, noise, seed):
    rng = np.random.default_rng(seed)
    return v + noise * rng.normal(size=v.shape)


# =========================================================================== kernels
def test_p1_quadrature_path_equals_per_tet_math():
    """P1 through the quadrature-point path: one point per tet with G from Dm⁻¹ and weight V — the
    energies, gradients and Hessians equal the per-tet (Dm⁻¹) JAX twin, and build_quadrature's P1 points
    equal rest_quantities bit for bit."""
    v, t = box_tets((3, 2, 2), (0.3, 0.2, 0.2))
    vol, dm_inv, _ = rest_quantities(v, t, 1.0)
    q = build_quadrature(v, t)
    np.testing.assert_array_equal(q.weight, vol)
    np.testing.assert_array_equal(q.grad[:, 1:], dm_inv)
    x = random_state(v, 0.01, 0)
    mu, lam = lame(np.full(len(t), 2e5), np.full(len(t), 0.4))
    for proj in (False, True, "abs"):
        e0, g0, h0 = (np.asarray(a) for a in element_terms_jax(x, t, dm_inv, vol, mu, lam, "stable_neohookean", proj))
        e1, g1, h1 = point_terms(x, q.nodes, q.grad, q.weight, mu, lam, "stable_neohookean", HESSIAN, proj)
        np.testing.assert_allclose(e1, e0, rtol=1e-11, atol=1e-14 * np.abs(e0).max())
        np.testing.assert_allclose(g1, g0, rtol=1e-10, atol=1e-12 * np.abs(g0).max())
        np.testing.assert_allclose(h1, h0, rtol=1e-9, atol=1e-11 * np.abs(h0).max())


@pytest.mark.parametrize("material", MODELS)
def test_p2_point_gradient_and_hessian_match_finite_differences(material):
    """w Ψ(F) at the 4 points of 2 curved P2 tets: gradient and exact Hessian (3k = 30) of the JAX twin
    against central differences."""
    v, t = curved_p2(cells=(1, 1, 1))
    t = t[:1]  # one curved element: a vertex is node a of all its 4 points
    q = build_quadrature(v, t)
    x = random_state(v, 0.01, 1)
    mu, lam = lame(np.full(q.n_points, 1e5), np.full(q.n_points, 0.4))
    e, g, h = (np.asarray(a) for a in point_terms_jax(x, q.nodes, q.grad, q.weight, mu, lam, material, False))
    assert g.shape == (4, 30) and h.shape == (4, 30, 30)

    def eg(z):
        a = point_terms_jax(z, q.nodes, q.grad, q.weight, mu, lam, material, False)
        return np.asarray(a[0]), np.asarray(a[1])

    eps = 1e-7
    for a in range(10):
        for i in range(3):
            dz = np.zeros_like(x)
            dz[t[0, a], i] = eps
            (ep, gp), (em, gm) = eg(x + dz), eg(x - dz)
            np.testing.assert_allclose(g[:, 3 * a + i], (ep - em) / (2 * eps), rtol=FD_RTOL,
                                       atol=1e-8 * np.abs(g).max())
            np.testing.assert_allclose(h[:, :, 3 * a + i], (gp - gm) / (2 * eps), rtol=FD_RTOL,
                                       atol=1e-7 * np.abs(h).max())


@pytest.mark.parametrize("project", [False, True, "abs"])
def test_p2_numba_kernel_matches_jax_twin_and_sums_per_element(project):
    v, t = curved_p2()
    q = build_quadrature(v, t)
    x = random_state(v, 0.02, 2)
    mu, lam = lame(np.full(q.n_points, 3e4), np.full(q.n_points, 0.45))
    e0, g0, h0 = (np.asarray(a) for a in point_terms_jax(x, q.nodes, q.grad, q.weight, mu, lam,
                                                         "stable_neohookean", project))
    e1, g1, h1 = point_terms(x, q.nodes, q.grad, q.weight, mu, lam, "stable_neohookean", HESSIAN, project)
    np.testing.assert_allclose(e1, e0, rtol=1e-10, atol=1e-13 * np.abs(e0).max())
    np.testing.assert_allclose(g1, g0, rtol=1e-9, atol=1e-11 * np.abs(g0).max())
    np.testing.assert_allclose(h1, h0, rtol=1e-7, atol=1e-9 * np.abs(h0).max())
    es, gs, hs = point_terms(x, q.nodes, q.grad, q.weight, mu, lam, "stable_neohookean", HESSIAN, project,
                             out_index=q.element, n_out=len(t))
    np.testing.assert_allclose(hs, h1.reshape(len(t), 4, 30, 30).sum(1), rtol=1e-12, atol=1e-12 * np.abs(hs).max())
    np.testing.assert_allclose(gs, g1.reshape(len(t), 4, 30).sum(1), rtol=1e-12, atol=1e-12 * np.abs(gs).max())
    if project:
        assert np.linalg.eigvalsh(hs).min() > -1e-9 * np.abs(hs).max()


@pytest.mark.parametrize("material", MODELS)
def test_patch_test_affine_motion(material):
    """x = A X + b: F = A at every quadrature point (curved elements too), and on straight elements the
    internal forces of interior nodes vanish (Σ_q w_q P ∇N_a = P ∫∇N_a, which sums to 0 around them)."""
    A = np.array([[1.05, 0.02, -0.01], [0.03, 0.97, 0.04], [-0.02, 0.01, 1.02]])
    b = np.array([0.1, -0.2, 0.3])
    for bulge in (0.01, 0.0):
        v, t = curved_p2(cells=(3, 3, 3), size=(0.3, 0.3, 0.3), bulge=bulge)
        q = build_quadrature(v, t)
        x = v @ A.T + b
        F = np.einsum("qki,qkj->qij", x[q.nodes], q.grad)
        np.testing.assert_allclose(F, np.broadcast_to(A, F.shape), atol=1e-12)
    mesh = mesh_artefact(v, t, 1000.0)
    scene = make_scene(mesh, Controls(), material, 0.01, [0, 0, 0])
    f = internal_forces(x, scene, [1e5], [0.4])
    lo, hi = v.min(0), v.max(0)
    interior = np.all((v > lo + 1e-9) & (v < hi - 1e-9), axis=1)
    assert interior.sum() >= 8 and np.abs(f).max() > 1e-3  # the boundary nodes carry the traction
    assert np.abs(f[interior]).max() < 1e-9 * np.abs(f).max()


@pytest.mark.parametrize("material", MODELS)
def test_rigid_motion_gives_zero_energy_and_stress(material):
    """Rotation + translation of a curved P2 mesh (linear elasticity, not rotation invariant: translation)."""
    from scipy.spatial.transform import Rotation

    v, t = curved_p2()
    mesh = mesh_artefact(v, t, 1000.0)
    scene = make_scene(mesh, Controls(), material, 0.01, [0, 0, 0])
    R = Rotation.from_rotvec([0.3, -0.5, 0.7] if material != "linear" else [0, 0, 0]).as_matrix()
    x = v @ R.T + np.array([1.0, 2.0, -0.5])
    mu, lam = (np.asarray(a) for a in pot.tet_lame(scene, [1e5], [0.45]))
    e = total_energy(scene, frame_inputs(scene, Controls(), 0), x, x, None, mu, lam)
    assert abs(e) < 1e-12
    assert np.abs(internal_forces(x, scene, [1e5], [0.45])).max() < 1e-8
    s = st.point_stress(x, scene.quad, mu[scene.quad.element], lam[scene.quad.element], material)
    assert np.abs(s["sigma"]).max() < 1e-6 and s["von_mises"].max() < 1e-6


def test_p2_masses_volumes_and_surface():
    """HRZ: corners ρV/36, mid-edge nodes 4ρV/27 per straight tet; Σ m = ρV; curved volumes from the
    quadrature equal the enclosed volume of the split quadratic surface only on straight meshes."""
    v, t = box_tets((2, 2, 1), (0.2, 0.2, 0.1))
    v2, t2 = quadratic_tets(v, t)
    vol = element_volumes(build_quadrature(v2, t2), len(t2))
    np.testing.assert_allclose(vol.sum(), 0.2 * 0.2 * 0.1, rtol=1e-13)
    m = lumped_masses(v2, t2, 1000.0)
    np.testing.assert_allclose(m.sum(), 1000.0 * 0.004, rtol=1e-13)
    one = lumped_masses(v2, t2[:1], 1.0)
    np.testing.assert_allclose(one[t2[0, :4]], vol[0] / 36)
    np.testing.assert_allclose(one[t2[0, 4:]], 4 * vol[0] / 27)
    mesh = mesh_artefact(v, t, 1000.0, order=2)
    assert mesh.tets.shape == (len(t), 10) and mesh.n_vertices == len(v2)
    np.testing.assert_allclose(mesh.vertex_masses.sum(), 4.0, rtol=1e-13)
    faces = quadratic_surface(mesh.tets)
    np.testing.assert_array_equal(faces, mesh.surface_faces)
    p = mesh.vertices[faces]
    enclosed = np.einsum("fi,fi->f", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6
    np.testing.assert_allclose(enclosed, 0.004, rtol=1e-12)


def test_mesh_artefact_of_order_2_round_trips(tmp_path):
    from stages.artefacts import MeshArtefact

    v, t = box_tets((2, 1, 1), (0.2, 0.1, 0.1))
    mesh = mesh_artefact(v, t, 1000.0, order=2)
    mesh.handles = {"clamp": np.array([0, 1, len(v) + 2])}
    path = mesh.save(tmp_path / "mesh.h5")
    back = MeshArtefact.load(path)
    assert back.order == 2 and back.tets.shape == (len(t), 10)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    np.testing.assert_array_equal(back.handles["clamp"], mesh.handles["clamp"])


# =========================================================================== scene: potential, Newton, adjoint
@pytest.mark.parametrize("material", MODELS)
def test_p2_numpy_energy_gradient_hessian_match_jax_potential(material):
    v, t = curved_p2(cells=(3, 1, 1), size=(0.3, 0.1, 0.1))
    region = (v[t[:, :4]].mean(1)[:, 0] > 0.15).astype(int)
    mesh = mesh_artefact(v, t, 1000.0, region, ("a", "b"))
    ctl = clamp(False)
    scene = make_scene(mesh, ctl, material, 1 / 30, [0, 0, -9.81])
    inp = frame_inputs(scene, ctl, 0)
    x, xp, xpp = (random_state(scene.rest, 0.003, s) for s in (1, 2, 3))
    young, poisson = np.array([5e4, 2e5]), np.array([0.3, 0.45])
    mu, lam = (np.asarray(a) for a in pot.tet_lame(scene, young, poisson))
    s = pot.scene_data(scene)
    y = 2 * xp - xpp
    phi = float(jax.jit(pot.incremental_potential)(x, y, s, inp, mu, lam, xp))
    assert abs(total_energy(scene, inp, x, y, xp, mu, lam) - phi) < 1e-10 * abs(phi)
    r = np.asarray(jax.jit(jax.grad(pot.step_potential))(x, xp, xpp, young, poisson, s, inp))
    f_int = internal_forces(x, scene, young, poisson)
    f_jax = -np.asarray(jax.grad(pot.elastic_energy)(jnp.asarray(x), s, jnp.asarray(mu), jnp.asarray(lam)))
    np.testing.assert_allclose(f_int, f_jax, atol=1e-10 * np.abs(f_jax).max())
    H = hessian(scene, inp, x, xp, young, poisson, project=False)
    dz = np.random.default_rng(4).normal(size=x.shape)
    hv = np.asarray(jax.jvp(lambda z: jax.grad(pot.step_potential)(z, xp, xpp, young, poisson, s, inp),
                            (jnp.asarray(x),), (jnp.asarray(dz),))[1])
    np.testing.assert_allclose(H @ dz.reshape(-1), hv.reshape(-1), atol=1e-9 * np.abs(hv).max())
    assert np.isfinite(r).all()


def p2_bar(hard: bool, cells=(4, 1, 1), poses=None, material="stable_neohookean", dt=1 / 30):
    v, t = box_tets(cells, (0.2, 0.05, 0.05))
    mesh = mesh_artefact(v, t, 1000.0, order=2)
    ctl = clamp(hard, poses=poses)
    return make_scene(mesh, ctl, material, dt, [0, 0, -9.81]), ctl


@pytest.mark.parametrize("hard", [False, True])
def test_p2_newton_converges_and_hard_dofs_sit_at_targets(hard):
    poses = Track(np.arange(3), np.array([IDENTITY, [0, 0, 0.003, 1, 0, 0, 0], [0.002, 0, 0.006, 0.995, 0.0998, 0, 0]]),
                  True)
    scene, ctl = p2_bar(hard, poses=poses)
    assert scene.order == 2 and scene.quad.n_points == 4 * len(scene.tets)
    inputs = [frame_inputs(scene, ctl, i) for i in range(3)]
    xp = xpp = scene.rest
    for t in range(3):
        x, info = step(scene, inputs[t], [2e4], [0.45], xp, xpp, rtol=1e-10)
        assert info["residual"] <= 1e-10 or info["iterations"] > 0
        ids = scene.handles[0].ids
        if hard:
            np.testing.assert_array_equal(x[ids], inputs[t].handle_targets[0])
        else:
            assert np.abs(x[ids] - inputs[t].handle_targets[0]).max() > 0
        xpp, xp = xp, x
    assert np.isfinite(x).all() and x[:, 2].min() < scene.rest[:, 2].min() - 1e-4  # it sagged


def test_hard_handle_helpers():
    scene, ctl = p2_bar(True)
    mask = fixed_dofs(scene)
    assert mask.sum() == 3 * len(scene.handles[0].ids)
    inp = frame_inputs(scene, ctl, 0)
    x = apply_hard_targets(scene, inp, scene.rest + 1.0)
    np.testing.assert_array_equal(x[scene.handles[0].ids], inp.handle_targets[0])
    assert fixed_dofs(p2_bar(False)[0]) is None


@pytest.mark.parametrize("hard", [False, True])
def test_handle_reaction_holds_the_weight_at_equilibrium(hard):
    """A bar clamped at one end, quasi-static (Δt = 100 s, two steps): the handle's reaction balances
    the weight, Σ m g, to the solver's tolerance (hard: Σ ∇Φ without the handle over its vertices)."""
    scene, ctl = p2_bar(hard, dt=100.0)
    inp = frame_inputs(scene, ctl, 0)
    x0 = scene.rest
    x1, _ = step(scene, inp, [1e5], [0.4], x0, x0, rtol=1e-12)
    x2, _ = step(scene, inp, [1e5], [0.4], x1, x1, rtol=1e-12)
    f = handle_reactions(scene, inp, x2, x1, x1, [1e5], [0.4])
    weight = scene.masses.sum() * 9.81
    np.testing.assert_allclose(f[0], [0, 0, weight], atol=1e-6 * weight)


@pytest.mark.parametrize("hard", [False, True])
def test_p2_window_adjoint_matches_finite_differences(hard):
    """dL/dθ_t on a P2 scene (two regions), L = Σ_t W_t · x_t over a window of 2 after 2 lead-in frames,
    with the clamp moving; hard: the handle's DOFs are inputs (adjoint zero there)."""
    worst = window_adjoint_fd_error(hard)
    assert worst < 1e-4, worst


def window_adjoint_fd_error(hard: bool, damping: float = 0.0) -> float:
    """The largest relative difference between the window adjoint's dL/dθ_t and central differences of the
    simulation, on the two-region P2 bar of test_p2_window_adjoint_matches_finite_differences (``damping``: the
    scene's β, s)."""
    poses = Track(np.arange(4), np.array([IDENTITY, [0, 0, 0.002, 1, 0, 0, 0], [0, 0, 0.004, 1, 0, 0, 0],
                                          [0.001, 0, 0.005, 1, 0, 0, 0]]), True)
    v, t = box_tets((3, 1, 1), (0.15, 0.05, 0.05))
    region = (v[t].mean(1)[:, 0] > 0.075).astype(int)
    mesh = mesh_artefact(v, t, 1000.0, region, ("a", "b"), order=2)
    ctl = clamp(hard, poses=poses)
    scene = make_scene(mesh, ctl, "stable_neohookean", 1 / 30, [0, 0, -9.81], damping=damping)
    T, w = 4, 2
    inputs = [frame_inputs(scene, ctl, i) for i in range(T)]
    young = np.array([[4e4, 1.5e5]] * T) * (1 + 0.1 * np.arange(T))[:, None]
    poisson = np.array([[0.4, 0.3]] * T)
    W = np.random.default_rng(5).normal(size=(w, scene.n_vertices, 3))

    def loss(E, nu):
        X = simulate(scene, inputs, E, nu, rtol=1e-12)
        return float(np.sum(W * X[T - w:])), X

    _, X = loss(young, poisson)
    g = window_adjoint(scene, inputs[T - w:], young[T - w:], poisson[T - w:], X[T - w:], X[T - w - 2:T - w], W)
    worst = 0.0
    for k in range(w):
        for r in range(2):
            for key, arr, h in (("young", 0, 1e-5 * young[T - w + k, r]), ("poisson", 1, 1e-6)):
                P, M = [young.copy(), poisson.copy()], [young.copy(), poisson.copy()]
                P[arr][T - w + k, r] += h
                M[arr][T - w + k, r] -= h
                fd = (loss(*P)[0] - loss(*M)[0]) / (2 * h)
                worst = max(worst, abs(g[key][k, r] - fd) / abs(fd))
    return worst


def test_p2_stress_and_nodal_forces_per_quadrature_point():
    """Per-point Cauchy stress of a uniaxially stretched P2 block equals the closed form at every point,
    and the nodal forces assembled from the points' P equal the scene's internal forces."""
    v, t = curved_p2(cells=(2, 2, 2), size=(0.2, 0.2, 0.2), bulge=0.0)
    mesh = mesh_artefact(v, t, 1000.0)
    scene = make_scene(mesh, Controls(), "linear", 0.01, [0, 0, 0])
    x = v * np.array([1.01, 1.0, 1.0])
    mu, lam = lame(1e5, 0.3)
    q = scene.quad
    s = st.point_stress(x, q, np.full(q.n_points, mu), np.full(q.n_points, lam), "linear")
    np.testing.assert_allclose(s["P"][:, 0, 0], (lam + 2 * mu) * 0.01, rtol=1e-10)
    f = st.point_nodal_forces(s["P"], q, scene.n_vertices)
    np.testing.assert_allclose(f, internal_forces(x, scene, [1e5], [0.3]), atol=1e-9 * np.abs(f).max())


# =========================================================================== rsl tetrahedralize --order 2
def test_tetrahedralize_order_2_cli_on_a_tet_mesh(sample_data, tmp_path):
    """A linear .mesh input with --order 2: straight mid-edge nodes, handles hold whole edges, HRZ
    masses sum to ρV, `rsl info` reports order 2."""
    from conftest import run_rsl
    from stages.artefacts import MeshArtefact

    run_rsl("tetrahedralize", sample_data / "bar", "-w", tmp_path / "p1", "--order", "1", "--no-preview", check=True)
    run_rsl("tetrahedralize", sample_data / "bar", "-w", tmp_path / "p2", "--order", "2", "--no-preview", check=True)
    m1, m2 = MeshArtefact.load(tmp_path / "p1" / "mesh.h5"), MeshArtefact.load(tmp_path / "p2" / "mesh.h5")
    assert m1.order == 1 and m2.order == 2 and m2.tets.shape == (m1.n_tets, 10)
    np.testing.assert_array_equal(m2.vertices[:m1.n_vertices], m1.vertices)
    mid = m2.vertices[m2.tets[:, 4:]]
    ends = 0.5 * (m2.vertices[m2.tets[:, [0, 1, 0, 0, 1, 2]]] + m2.vertices[m2.tets[:, [1, 2, 2, 3, 3, 3]]])
    np.testing.assert_allclose(mid, ends, atol=1e-15)
    np.testing.assert_allclose(m2.rest_volumes, m1.rest_volumes, rtol=1e-12)
    np.testing.assert_allclose(m2.vertex_masses.sum(), m1.vertex_masses.sum(), rtol=1e-12)
    for name, ids in m1.handles.items():
        ids2 = m2.handles[name]
        assert set(ids) < set(ids2) and np.all(ids2[len(ids):] >= m1.n_vertices)
        np.testing.assert_allclose(m2.vertices[ids2, 0], m1.vertices[ids, 0][0], atol=1e-12)  # the end face
    p = run_rsl("info", tmp_path / "p2" / "mesh.h5", check=True)
    assert "order = 2" in p.stdout
    bad = run_rsl("tetrahedralize", sample_data / "bar", "-w", tmp_path / "p3", "--order", "3")
    assert bad.returncode != 0 and "--order should be 1" in bad.stderr + bad.stdout
    assert "Traceback" not in bad.stderr


def test_tetrahedralize_order_2_puts_boundary_nodes_on_a_curved_surface(tmp_path):
    """A sphere surface: boundary mid-edge nodes lie on the input surface (not on the chords), so the
    P2 volume is closer to the surface's enclosed volume than the same mesh's straight-sided (corner) tets; no
    element folds.  (The same mesh: fTetWild's output varies by a few tets between runs.)"""
    import trimesh

    from stages.artefacts import MeshArtefact
    from stages.meshing import closest_points_on_surface
    from stages.sim.quadrature import jacobian_ratio
    from stages.steps.tetrahedralize import TetrahedralizeConfig, run

    cap = tmp_path / "ball"
    cap.mkdir()
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    sphere.export(cap / "ball.obj")
    (cap / "capture.toml").write_text('[capture]\nname = "ball"\n[object]\nmesh = "ball.obj"\ndensity = 1000.0\n')
    m2 = MeshArtefact.load(run(TetrahedralizeConfig(cap, tmp_path / "p2", edge_length=0.25, preview=False, order=2)))
    assert m2.order == 2 and m2.quality["order"] == 2
    corners = m2.vertices[m2.tets[:, :4]]  # (T, 4, 3): the straight-sided tets of the same mesh
    edges = corners[:, 1:] - corners[:, :1]
    linear_volume = np.abs(np.linalg.det(edges)).sum() / 6.0
    target = sphere.volume
    assert abs(m2.rest_volumes.sum() - target) < 0.5 * abs(linear_volume - target)  # measured 0.27–0.28
    surf_mid = np.unique(m2.surface_faces)
    surf_mid = surf_mid[surf_mid > m2.tets[:, :4].max()]  # fTetWild's corners lie within its envelope only
    assert len(surf_mid) > 100
    written = trimesh.load(cap / "ball.obj", force="mesh", process=False)  # as the file holds it
    on = closest_points_on_surface(m2.vertices[surf_mid], written.vertices, written.faces)
    assert np.abs(m2.vertices[surf_mid] - on).max() < 1e-10
    assert jacobian_ratio(m2.vertices, m2.tets).min() >= 0.2
    np.testing.assert_allclose(m2.vertex_masses.sum(), 1000.0 * m2.rest_volumes.sum(), rtol=1e-12)


# =========================================================================== convergence (bench/convergence.py)
def _bench_convergence():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "bench" / "convergence.py"
    spec = importlib.util.spec_from_file_location("bench_convergence", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_p2_coarse_cantilever_within_3_percent_of_fine_reference():
    """Static cantilever clamped by a hard handle at ν = 0.45: P2 on 20×2×2 cells against P2 on 40×4×4
    (bench/convergence.py; its table uses a finer reference). P1 on the coarse mesh is far off (locking)."""
    bench = _bench_convergence()
    ref = bench.cantilever((40, 4, 4), 2, 0.45)["deflection_m"]
    p2 = bench.cantilever((20, 2, 2), 2, 0.45)["deflection_m"]
    p1 = bench.cantilever((20, 2, 2), 1, 0.45)["deflection_m"]
    assert abs(p2 / ref - 1) < 0.03
    assert p1 / ref < 0.5
    assert abs(ref / bench.euler_bernoulli() - 1) < 0.05  # and the reference agrees with beam theory


def test_set_forces_of_a_hard_handle_match_handle_reactions():
    """stress.set_forces / applied_forces (what export writes) agree with scene.handle_reactions for a
    hard handle in a dynamic step, and say what they need when x_prev2 is missing."""
    poses = Track(np.arange(3), np.array([IDENTITY, [0, 0, 0.003, 1, 0, 0, 0], [0, 0, 0.005, 1, 0, 0, 0]]), True)
    scene, ctl = p2_bar(True, poses=poses)
    inputs = [frame_inputs(scene, ctl, i) for i in range(3)]
    X = simulate(scene, inputs, [2e4], [0.45], rtol=1e-12)
    ref = handle_reactions(scene, inputs[2], X[2], X[1], X[0], [2e4], [0.45])
    f_int = internal_forces(X[2], scene, [2e4], [0.45])
    rows = st.set_forces(scene, inputs[2], X[2], X[1], f_int, x_prev2=X[0])
    np.testing.assert_allclose(rows[0].applied, ref[0], rtol=1e-8, atol=1e-10)
    per_vertex = st.applied_forces(scene, inputs[2], X[2], X[1], x_prev2=X[0], f_int=f_int)
    np.testing.assert_allclose(per_vertex.sum(0), ref[0], rtol=1e-8, atol=1e-10)
    with pytest.raises(ValueError, match="x_prev2"):
        st.set_forces(scene, inputs[2], X[2], X[1], f_int)
    with pytest.raises(ValueError, match="point_stress"):
        st.tet_stress(X[2], scene.tets, scene.dm_inv, np.ones(len(scene.tets)), np.ones(len(scene.tets)))


def test_controls_json_hard_handle_is_parsed_and_validated(tmp_path):
    from stages.capture import CaptureError, parse_controls

    path = tmp_path / "controls.json"
    data = {"handles": [{"name": "clamp", "select": {"box": [[-1, -1, -1], [0, 1, 1]]}, "hard": True}]}
    ctl = parse_controls(data, path)
    assert ctl.handles[0].hard is True
    assert parse_controls(ctl.to_json(), path).handles[0].hard is True  # written back and read again
    data["handles"][0]["hard"] = "yes"
    with pytest.raises(CaptureError, match="hard"):
        parse_controls(data, path)
    del data["handles"][0]["hard"]
    assert parse_controls(data, path).handles[0].hard is False
