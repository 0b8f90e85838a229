"""Reduced dynamics (stages.subspace.reduced): energy, Hessian, cubature, trajectories, window adjoint.

Snapshots come from the full-space simulator (stages.sim.scene.simulate) on a small cantilever bar
whose clamped end is moved and turned differently in each sequence.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stages.domain.rotations import rotvec_to_matrix
from stages.sim import potential as P
from stages.sim.meshgen import box_tets
from stages.sim.mesh import rest_quantities
from stages.sim.scene import FrameInputs, HandleSpec, ObstacleSpec, Scene, simulate
from stages.subspace import ReducedModel
from stages.subspace.cubature import ReducedForceSampler, fit_cubature
from stages.subspace.train import fit_subspace

YOUNG, POISSON = np.array([2e4, 6e4]), np.array([0.40, 0.45])
FRAMES = 16


def bar_scene(obstacle: bool = False) -> Scene:
    """0.2 m bar, 8×2×2 cells, clamped at x = 0 by a stiff handle, two material regions."""
    v, t = box_tets((8, 2, 2), (0.2, 0.05, 0.05))
    vol, dmi, m = rest_quantities(v, t, 1000.0)
    region = (v[t].mean(1)[:, 0] > 0.1).astype(np.int64)
    hid = np.nonzero(v[:, 0] < 1e-9)[0]
    obs = (ObstacleSpec("floor", "plane", np.array([0.0, 0.0, 1.0]), -0.03, 0.0, None),) if obstacle else ()
    return Scene(rest=v, tets=t, dm_inv=dmi, volumes=vol, masses=m, tet_region=region, n_regions=2,
                 region_names=("a", "b"), material="stable_neohookean", dt=1 / 30, gravity=np.array([0, 0, -9.81]),
                 handles=(HandleSpec("clamp", hid, 1e3),), loads=(), obstacles=obs, friction=0.0,
                 contact_stiffness=2e3, contact_margin=1e-3)


def sequence_inputs(scene: Scene, seed: int, frames: int = FRAMES) -> list[FrameInputs]:
    """The clamp rises/sinks and turns about x and y by a random amount over the sequence."""
    rng = np.random.default_rng(seed)
    amp = rng.uniform(-1, 1, 4) * np.array([0.02, 0.6, 0.4, 0.01])  # dz m, rx rad, ry rad, dx m
    hid = scene.handles[0].ids
    out = []
    for f in range(frames):
        s = np.sin(0.5 * np.pi * min(f / 10, 1.0))
        rx, ry = amp[1] * s, amp[2] * s
        R = rotvec_to_matrix(np.array([rx, 0.0, 0.0])) @ rotvec_to_matrix(np.array([0.0, ry, 0.0]))
        target = scene.rest[hid] @ R.T + np.array([amp[3] * s, 0, amp[0] * s])
        n_obs = len(scene.obstacles)
        out.append(FrameInputs((target,), np.zeros_like(scene.rest), np.tile([0, 0, 0, 1.0, 0, 0, 0], (n_obs, 1))))
    return out


@pytest.fixture(scope="module")
def data():
    scene = bar_scene()
    seqs = []
    for s in range(7):
        inp = sequence_inputs(scene, s)
        seqs.append((inp, simulate(scene, inp, YOUNG, POISSON)))
    train = np.concatenate([x for _, x in seqs[:6]])
    return scene, seqs, train


@pytest.fixture(scope="module")
def ae(data):
    scene, _, train = data
    sub, _ = fit_subspace("autoencoder", scene.rest, scene.masses, train, 6, epochs=150, seed=0, pca_dim=16)
    return sub


@pytest.fixture(scope="module")
def pca(data):
    scene, _, train = data
    sub, _ = fit_subspace("pca", scene.rest, scene.masses, train, 12)
    return sub


def _state(sub, seqs):
    """Three consecutive reduced states from the held-out sequence."""
    x = seqs[6][1]
    z = np.asarray(sub.encode(jnp.asarray(x[8:11])))
    return z[2], z[1], z[0], seqs[6][0][10]


# --------------------------------------------------------------------------- energy, gradient, Hessian
def test_fast_path_with_all_tets_equals_reference(data, ae):
    """Exact inertia in q and the restricted scene give the same gradient and Hessian as Φ(φ(z))."""
    scene, seqs, _ = data
    z, z1, z2, inp = _state(ae, seqs)
    fast, ref = ReducedModel(ae, scene), ReducedModel(ae, scene, reference=True)
    args = (inp, YOUNG, POISSON, z1, z2)
    g_f, g_r = fast.gradient(z, *args), ref.gradient(z, *args)
    assert np.linalg.norm(g_f - g_r) <= 1e-10 * np.linalg.norm(g_r)
    h_f, h_r = fast.hessian(z, *args), ref.hessian(z, *args)
    assert np.abs(h_f - h_r).max() <= 1e-10 * np.abs(h_r).max()
    # energies agree up to the constant terms the fast path drops
    dz = 1e-3 * np.random.default_rng(0).normal(size=z.shape)
    de_f = fast.energy(z + dz, *args) - fast.energy(z, *args)
    de_r = ref.energy(z + dz, *args) - ref.energy(z, *args)
    assert abs(de_f - de_r) <= 1e-9 * abs(de_r)


def test_gradient_matches_finite_differences(data, ae):
    scene, seqs, _ = data
    z, z1, z2, inp = _state(ae, seqs)
    model = ReducedModel(ae, scene)
    args = (inp, YOUNG, POISSON, z1, z2)
    g = model.gradient(z, *args)
    h = 1e-6
    fd = np.array([(model.energy(z + h * e, *args) - model.energy(z - h * e, *args)) / (2 * h)
                   for e in np.eye(len(z))])
    assert np.linalg.norm(fd - g) <= 1e-6 * np.linalg.norm(g)


def test_assembled_hessian_equals_forward_over_reverse_on_a_cubature_subset(data, ae, pca):
    """The assembled ∂²E/∂z² (D_eᵀ ∂²Ψ/∂F² D_e at the cubature tets, decoder curvature) against its JAX
    forward-over-reverse twin, and against central differences of the gradient."""
    scene, seqs, _ = data
    ids = np.arange(0, len(scene.tets), 3)
    wts = np.random.default_rng(1).uniform(0.5, 3.0, len(ids))
    for sub in (ae, pca):
        z, z1, z2, inp = _state(sub, seqs)
        model = ReducedModel(sub, scene, (ids, wts))
        assert model._assembled
        args = model._args(z, z1, z2, YOUNG, POISSON, model.reduce_inputs(inp))
        h_fast = np.asarray(model._H(*args))
        h_twin = np.asarray(model._EGH(*args)[2])
        assert np.abs(h_fast - h_twin).max() <= 1e-10 * np.abs(h_twin).max()
        eps = 1e-6
        grad = lambda zz: model.gradient(zz, inp, YOUNG, POISSON, z1, z2)  # noqa: E731
        fd = np.stack([(grad(z + eps * e) - grad(z - eps * e)) / (2 * eps) for e in np.eye(len(z))])
        assert np.abs(fd - h_fast).max() <= 1e-5 * np.abs(h_fast).max()


def test_quasi_newton_and_newton_reach_the_same_state(data, ae):
    """The BFGS-updated step (default) and plain Newton (a fresh Hessian per iteration) converge to the
    same z, both to the residual tolerance; quasi-Newton takes fewer exact Hessians."""
    scene, seqs, _ = data
    inp = seqs[6][0]
    rtol = 1e-9
    out = {}
    for reuse in (True, False):
        model = ReducedModel(ae, scene)
        z1 = z2 = model.z_rest
        zs, hess = [], 0
        for t in range(8):
            z, info = model.step(inp[t], YOUNG, POISSON, z1, z2, rtol=rtol, reuse_hessian=reuse)
            assert info["residual_rel"] <= rtol
            zs.append(z)
            hess += info["hessians"]
            z2, z1 = z1, z
        out[reuse] = np.stack(zs), hess
    np.testing.assert_allclose(out[True][0], out[False][0], atol=1e-6 * np.abs(out[False][0]).max())
    assert out[True][1] < out[False][1]


def test_quasi_newton_cut_short_goes_on_as_newton_to_the_same_state(data, pca):
    """Quasi-Newton that has not converged after max_iterations (here 5; it takes 8–12 on this sequence, plain
    Newton 4–5) goes on as plain Newton: every frame still converges, to plain Newton's state."""
    scene, seqs, _ = data
    inp = seqs[6][0]
    rtol = 1e-9
    out, fallbacks = {}, 0
    for reuse in (True, False):
        model = ReducedModel(pca, scene)
        z1 = z2 = model.z_rest
        zs = []
        for t in range(8):
            z, info = model.step(inp[t], YOUNG, POISSON, z1, z2, rtol=rtol, reuse_hessian=reuse,
                                 max_iterations=5 if reuse else 200)
            assert info["residual_rel"] <= rtol
            assert info["newton_fallback"] == (reuse and info["iterations"] > 5)
            fallbacks += info["newton_fallback"]
            zs.append(z)
            z2, z1 = z1, z
        out[reuse] = np.stack(zs)
    assert fallbacks > 0
    np.testing.assert_allclose(out[True], out[False], atol=1e-6 * np.abs(out[False]).max())


@pytest.mark.slow
def test_reduced_hessian_against_dense_JtHJ(data, ae):
    """∂²E/∂z² = Jᵀ H J + Σ_i r_i ∂²φ_i/∂z² with H, r the dense full-space Hessian and residual."""
    scene, seqs, _ = data
    z, z1, z2, inp = _state(ae, seqs)
    model = ReducedModel(ae, scene)
    s = P.scene_data(scene)
    mu, lam = P.tet_lame(scene, YOUNG, POISSON)
    x, x1, x2 = (np.asarray(ae.decode(jnp.asarray(a))) for a in (z, z1, z2))

    def phi_energy(xx):
        return P.incremental_potential(xx, 2 * x1 - x2, s, inp, mu, lam, x1)

    n = len(x)
    H = np.asarray(jax.hessian(phi_energy)(jnp.asarray(x))).reshape(3 * n, 3 * n)
    r = np.asarray(jax.grad(phi_energy)(jnp.asarray(x))).reshape(-1)
    J = model.jacobian(z).reshape(3 * n, -1)
    curv = np.asarray(jax.hessian(lambda zz: jnp.dot(jnp.asarray(r), ae.decode(zz).reshape(-1)))(jnp.asarray(z)))
    gn = J.T @ H @ J
    h_full = model.hessian(z, inp, YOUNG, POISSON, z1, z2)
    h_gn = model.hessian(z, inp, YOUNG, POISSON, z1, z2, curvature=False)
    assert np.abs(h_gn - gn).max() <= 1e-9 * np.abs(gn).max()
    assert np.abs(h_full - (gn + curv)).max() <= 1e-9 * np.abs(gn).max()
    assert np.abs(curv).max() > 1e-8 * np.abs(gn).max()  # the decoder-curvature term is really there


@pytest.mark.slow
def test_handles_and_contact_act_in_the_reduced_solve(data, pca):
    """With a floor in the scene, the fast path (surface vertices decoded) matches the reference."""
    _, seqs, _ = data
    scene = bar_scene(obstacle=True)
    inp = sequence_inputs(scene, 3, 12)
    fast, ref = ReducedModel(pca, scene), ReducedModel(pca, scene, reference=True)
    zf = fast.simulate(inp, YOUNG, POISSON)
    zr = ref.simulate(inp, YOUNG, POISSON)
    assert np.abs(zf - zr).max() <= 1e-7 * np.abs(zr).max()
    x = fast.decode(zf[-1])
    zfree = ReducedModel(pca, bar_scene()).simulate(sequence_inputs(bar_scene(), 3, 12), YOUNG, POISSON)
    # the floor at z = −0.03 m holds the bar up where the free bar sinks through it
    assert x[:, 2].min() > -0.032
    assert fast.decode(zfree[-1])[:, 2].min() < x[:, 2].min() - 1e-3


# --------------------------------------------------------------------------- cubature
@pytest.mark.slow
def test_cubature_forces_against_all_tet_reference(data, ae):
    scene, seqs, train = data
    mu, lam = P.tet_lame(scene, YOUNG, POISSON)
    z_fit = np.asarray(ae.encode(jnp.asarray(train[::4])))
    sampler = ReducedForceSampler(ae, z_fit, scene.tets, scene.dm_inv, scene.volumes, np.asarray(mu),
                                  np.asarray(lam), scene.material)
    ids, w, info = fit_cubature(sampler, scene.tet_region, 2, max_tets=60, tol=1e-3, seed=0)
    assert len(ids) <= 60 and np.all(w > 0) and info["error_rel"] < 0.05
    cub, ref = ReducedModel(ae, scene, (ids, w)), ReducedModel(ae, scene, reference=True)
    z, z1, z2, inp = _state(ae, seqs)  # held-out sequence
    # reduced forces and Hessian (inertia and handle terms are exact in both, so the gap is the cubature's)
    g_c, g_r = cub.gradient(z, inp, YOUNG, POISSON, z1, z2), ref.gradient(z, inp, YOUNG, POISSON, z1, z2)
    h_c, h_r = cub.hessian(z, inp, YOUNG, POISSON, z1, z2), ref.hessian(z, inp, YOUNG, POISSON, z1, z2)
    assert np.linalg.norm(g_c - g_r) <= 0.05 * np.linalg.norm(g_r)
    assert np.linalg.norm(h_c - h_r) <= 0.05 * np.linalg.norm(h_r)
    # and the elastic energy itself on held-out poses
    from stages.subspace.cubature import tet_energies

    for x in seqs[6][1][::5]:
        xr = np.asarray(ae.decode(ae.encode(jnp.asarray(x))))
        e = np.asarray(tet_energies(jnp.asarray(xr), scene.tets, scene.dm_inv, scene.volumes, mu, lam, scene.material))
        assert abs(np.dot(w, e[ids]) - e.sum()) <= 0.05 * e.sum() + 1e-12


# --------------------------------------------------------------------------- trajectories
def test_reduced_trajectory_follows_full_space_on_held_out_sequence(data, ae, pca):
    """Mean vertex error of the reduced trajectory over the bounding-box diagonal: < 6 % for the r = 6
    autoencoder with 60-tet cubature, < 2 % for PCA r = 12 (their reconstruction errors: ~0.8 %, ~0.14 %)."""
    scene, seqs, train = data
    inp, x_full = seqs[6]
    diag = np.linalg.norm(scene.rest.max(0) - scene.rest.min(0))
    mu, lam = P.tet_lame(scene, YOUNG, POISSON)
    sampler = ReducedForceSampler(ae, np.asarray(ae.encode(jnp.asarray(train[::4]))), scene.tets, scene.dm_inv,
                                  scene.volumes, np.asarray(mu), np.asarray(lam), scene.material)
    ids, w, _ = fit_cubature(sampler, scene.tet_region, 2, max_tets=60, tol=1e-3, seed=0)
    errs = {}
    for name, model in (("ae", ReducedModel(ae, scene, (ids, w))), ("pca", ReducedModel(pca, scene))):
        Z = model.simulate(inp, YOUNG, POISSON)
        errs[name] = np.linalg.norm(model.decode(Z) - x_full, axis=-1).mean() / diag
    assert errs["ae"] < 0.06, errs
    assert errs["pca"] < 0.02, errs
    motion = np.linalg.norm(x_full - scene.rest, axis=-1).mean() / diag
    assert errs["ae"] < 0.25 * motion  # far better than standing still


# --------------------------------------------------------------------------- window adjoint
def _window(model, seqs, w=3, t0=6):
    inp_all = seqs[6][0]
    Z = model.simulate(inp_all[: t0 + w], YOUNG, POISSON, rtol=1e-12)
    return inp_all[t0: t0 + w], Z[t0 - 2: t0], Z[t0: t0 + w]


def _rollout(model, inp, young, poisson, zb, rtol=1e-12):
    z2, z1 = zb
    out = []
    for t in range(len(inp)):
        z, _ = model.step(inp[t], young[t], poisson[t], z1, z2, rtol=rtol)
        out.append(z)
        z2, z1 = z1, z
    return np.stack(out)


def test_window_adjoint_against_finite_differences(data, ae):
    scene, seqs, _ = data
    model = ReducedModel(ae, scene)
    w = 3
    inp, zb, Z = _window(model, seqs, w)
    rng = np.random.default_rng(1)
    c = rng.normal(size=Z.shape)
    young, poisson = np.tile(YOUNG, (w, 1)), np.tile(POISSON, (w, 1))
    g = model.window_adjoint(inp, young, poisson, Z, zb, dL_dZ=c)

    def loss(y, nu, zb_):
        return float(np.sum(c * _rollout(model, inp, y, nu, zb_)))

    for t in range(w):
        for r in range(2):
            for key, theta, h in (("young", young, 1e-4 * YOUNG[r]), ("poisson", poisson, 1e-6)):
                tp, tm = theta.copy(), theta.copy()
                tp[t, r] += h
                tm[t, r] -= h
                if key == "young":
                    fd = (loss(tp, poisson, zb) - loss(tm, poisson, zb)) / (2 * h)
                else:
                    fd = (loss(young, tp, zb) - loss(young, tm, zb)) / (2 * h)
                assert abs(fd - g[key][t, r]) <= 1e-3 * abs(fd) + 1e-12, (key, t, r, fd, g[key][t, r])
    # dL/dz_before
    for i in range(2):
        for k in range(model.r):
            h = 1e-6
            zp, zm = zb.copy(), zb.copy()
            zp[i, k] += h
            zm[i, k] -= h
            fd = (loss(young, poisson, zp) - loss(young, poisson, zm)) / (2 * h)
            assert abs(fd - g["z_before"][i, k]) <= 1e-3 * max(abs(fd), 1e-3 * np.abs(g["z_before"]).max())


@pytest.mark.slow
def test_window_adjoint_against_autodiff_through_unrolled_newton(data, ae):
    """Tiny case: jax.grad through 12 unrolled full Newton steps per frame equals the adjoint."""
    scene, seqs, _ = data
    model = ReducedModel(ae, scene)
    w = 2
    inp, zb, Z = _window(model, seqs, w)
    rins = [model.reduce_inputs(u) for u in inp]
    c = np.random.default_rng(2).normal(size=Z.shape)
    E = model.energy_jax

    def unrolled(young):
        z2, z1 = jnp.asarray(zb[0]), jnp.asarray(zb[1])
        total = 0.0
        for t in range(w):
            z = 2 * z1 - z2
            for _ in range(12):
                g = jax.grad(E)(z, z1, z2, young, jnp.asarray(POISSON), rins[t])
                H = jax.hessian(E)(z, z1, z2, young, jnp.asarray(POISSON), rins[t])
                z = z - jnp.linalg.solve(H, g)
            total = total + jnp.dot(jnp.asarray(c[t]), z)
            z2, z1 = z1, z
        return total

    g_ad = np.asarray(jax.grad(unrolled)(jnp.asarray(YOUNG)))
    g = model.window_adjoint(inp, np.tile(YOUNG, (w, 1)), np.tile(POISSON, (w, 1)), Z, zb, dL_dZ=c)
    g_adj = g["young"].sum(0)  # θ shared over the window
    assert np.allclose(g_adj, g_ad, rtol=1e-6, atol=1e-12 * np.abs(g_ad).max())


def test_window_adjoint_dL_dX_is_projected_by_Jt(data, ae):
    scene, seqs, _ = data
    model = ReducedModel(ae, scene)
    inp, zb, Z = _window(model, seqs, 2)
    a = np.random.default_rng(3).normal(size=(2, len(scene.rest), 3))
    g_x = model.window_adjoint(inp, YOUNG, POISSON, Z, zb, dL_dX=a)
    dz = np.stack([model.jacobian(Z[t]).reshape(-1, model.r).T @ a[t].reshape(-1) for t in range(2)])
    g_z = model.window_adjoint(inp, YOUNG, POISSON, Z, zb, dL_dZ=dz)
    assert np.allclose(g_x["young"], g_z["young"], rtol=1e-10)
    assert np.allclose(g_x["z_before"], g_z["z_before"], rtol=1e-10, atol=1e-14)


# --------------------------------------------------------------------------- viscous damping (Scene.damping)
DAMPING = 0.01  # s


def test_damped_fast_path_and_assembled_hessian_equal_their_twins(data, ae, pca):
    """With β > 0: the fast path over all tets against the reference Φ(φ(z)) (which takes the full-space damping
    term, stages.sim.potential.damping_energy), gradient and Hessian to 1e-10; the assembled Hessian on a cubature
    subset against forward-over-reverse; and the damping really moves the gradient."""
    import dataclasses

    scene0, seqs, _ = data
    scene = dataclasses.replace(scene0, damping=DAMPING)
    z, z1, z2, inp = _state(ae, seqs)
    fast, ref = ReducedModel(ae, scene), ReducedModel(ae, scene, reference=True)
    args = (inp, YOUNG, POISSON, z1, z2)
    g_f, g_r = fast.gradient(z, *args), ref.gradient(z, *args)
    assert np.linalg.norm(g_f - g_r) <= 1e-10 * np.linalg.norm(g_r)
    g0 = ReducedModel(ae, scene0).gradient(z, *args)
    assert np.linalg.norm(g_f - g0) > 1e-3 * np.linalg.norm(g0)
    h_f, h_r = fast.hessian(z, *args), ref.hessian(z, *args)
    assert np.abs(h_f - h_r).max() <= 1e-10 * np.abs(h_r).max()
    ids = np.arange(0, len(scene.tets), 3)
    wts = np.random.default_rng(1).uniform(0.5, 3.0, len(ids))
    for sub in (ae, pca):
        z, z1, z2, inp = _state(sub, seqs)
        model = ReducedModel(sub, scene, (ids, wts))
        a = model._args(z, z1, z2, YOUNG, POISSON, model.reduce_inputs(inp))
        h_fast, h_twin = np.asarray(model._H(*a)), np.asarray(model._EGH(*a)[2])
        assert np.abs(h_fast - h_twin).max() <= 1e-10 * np.abs(h_twin).max()


def test_damped_window_adjoint_against_finite_differences(data, ae):
    """dL/dE_t and dL/dz_before through damped reduced steps (the viscous term couples z_t to z_{t−1})."""
    import dataclasses

    scene, seqs, _ = data
    model = ReducedModel(ae, dataclasses.replace(scene, damping=DAMPING))
    w = 3
    inp, zb, Z = _window(model, seqs, w)
    c = np.random.default_rng(2).normal(size=Z.shape)
    young, poisson = np.tile(YOUNG, (w, 1)), np.tile(POISSON, (w, 1))
    g = model.window_adjoint(inp, young, poisson, Z, zb, dL_dZ=c)

    def loss(y, zb_):
        return float(np.sum(c * _rollout(model, inp, y, poisson, zb_)))

    for t in range(w):
        h = 1e-4 * YOUNG[0]
        tp, tm = young.copy(), young.copy()
        tp[t, 0] += h
        tm[t, 0] -= h
        fd = (loss(tp, zb) - loss(tm, zb)) / (2 * h)
        assert abs(fd - g["young"][t, 0]) <= 1e-3 * abs(fd) + 1e-12, (t, fd, g["young"][t, 0])
    for k in range(model.r):
        zp, zm = zb.copy(), zb.copy()
        zp[1, k] += 1e-6
        zm[1, k] -= 1e-6
        fd = (loss(young, zp) - loss(young, zm)) / 2e-6
        assert abs(fd - g["z_before"][1, k]) <= 1e-3 * max(abs(fd), 1e-3 * np.abs(g["z_before"]).max())


def test_cubature_fitted_to_the_viscous_forces_too_integrates_them(data, ae):
    """A damped material: a cubature fitted to the elastic forces alone misses the viscous ones (their integrand,
    strain rates, is another: 7.6 % on held-out pose pairs when written); stacking the viscous rows
    (ViscousForceSampler at consecutive training poses) brings it under 2 % (0.3 %) and below a fifth of the
    elastic-only fit's, while the elastic error stays under 2 % (0.4 %)."""
    from stages.sim.quadrature import linear_quadrature
    from stages.subspace.cubature import StackedSampler, ViscousForceSampler, cubature_error

    scene, seqs, _ = data
    mu, lam = (np.asarray(a) for a in P.tet_lame(scene, YOUNG, POISSON))
    quad = linear_quadrature(scene.tets, scene.dm_inv, scene.volumes)
    now = np.concatenate([x[1:][::3] for _, x in seqs[:6]])
    before = np.concatenate([x[:-1][::3] for _, x in seqs[:6]])
    z_now = np.asarray(ae.encode(jnp.asarray(now)))
    elastic = ReducedForceSampler(ae, z_now, quad, mu, lam, scene.material)
    viscous = ViscousForceSampler(ae, z_now, before, quad, mu, lam)
    x6 = seqs[6][1]
    held_elastic = ReducedForceSampler(ae, np.asarray(ae.encode(jnp.asarray(x6[1::2]))), quad, mu, lam, scene.material)
    held_viscous = ViscousForceSampler(ae, np.asarray(ae.encode(jnp.asarray(x6[1::2]))), x6[:-1:2], quad, mu, lam)
    fits = {name: fit_cubature(s, scene.tet_region, 2, max_points=60, tol=1e-3, seed=0)
            for name, s in (("elastic", elastic), ("both", StackedSampler(elastic, viscous)))}
    err = {name: (cubature_error(held_elastic, scene.tet_region, 2, ids, w),
                  cubature_error(held_viscous, scene.tet_region, 2, ids, w)) for name, (ids, w, _) in fits.items()}
    assert err["both"][1] < 0.02 and err["both"][1] < 0.2 * err["elastic"][1], err
    assert err["both"][0] < 0.02, err


# --------------------------------------------------------------------------- ν: the cubature at two ratios λ/μ
@pytest.mark.parametrize("model", ["stable_neohookean", "yeoh", "linear"])
def test_reduced_forces_are_linear_in_the_lame_parameters(data, ae, model):
    """g_q(μ₁ + μ₂, λ₁ + λ₂) = g_q(μ₁, λ₁) + g_q(μ₂, λ₂) per point (the energies are linear in (μ, λ), stable
    Neo-Hookean up to a constant of F): what lets a cubature fitted at two ratios λ/μ integrate every ν
    (train_subspace.cubature_materials)."""
    from stages.sim.quadrature import linear_quadrature

    scene, seqs, _ = data
    quad = linear_quadrature(scene.tets, scene.dm_inv, scene.volumes)
    z = np.asarray(ae.encode(jnp.asarray(seqs[6][1][4::6])))
    ids = np.arange(0, quad.n_points, 7)
    m1, l1 = (np.asarray(a) for a in P.tet_lame(scene, YOUNG, np.array([0.30, 0.30])))
    m2, l2 = (np.asarray(a) for a in P.tet_lame(scene, 0.5 * YOUNG, np.array([0.49, 0.49])))
    cols = [ReducedForceSampler(ae, z, quad, mu, lam, model).columns(ids) for mu, lam in ((m1, l1), (m2, l2),
                                                                                         (m1 + m2, l1 + l2))]
    np.testing.assert_allclose(cols[0] + cols[1], cols[2], rtol=1e-7, atol=1e-9 * np.abs(cols[2]).max())


def test_cubature_fitted_at_both_ends_of_nu_integrates_every_nu_between(data, ae):
    """A cubature fitted at one ν matches the sum μ g^μ + λ g^λ there, not each part: held out at ν = 0.49 (the
    volumetric part ~25 × the shear part's coefficient) its reduced-force error is several times that of one fitted
    at ν = 0.30 and 0.49 (train_subspace.cubature_materials), which stays under 2 % at 0.30, 0.42 and 0.49."""
    from stages.sim.quadrature import linear_quadrature
    from stages.steps.train_subspace import cubature_materials
    from stages.subspace.cubature import StackedSampler, cubature_error

    scene, seqs, train = data
    quad = linear_quadrature(scene.tets, scene.dm_inv, scene.volumes)
    z_fit = np.asarray(ae.encode(jnp.asarray(train[::4])))
    z_held = np.asarray(ae.encode(jnp.asarray(seqs[6][1][1::2])))

    def sampler(z, nu):
        mu, lam = (np.asarray(a) for a in P.tet_lame(scene, YOUNG, np.full(2, nu)))
        return ReducedForceSampler(ae, z, quad, mu, lam, scene.material)

    span = cubature_materials(np.array([[0.3, 0.3], [0.42, 0.4], [0.49, 0.49]]))
    assert [list(s) for s in span] == [[0.3, 0.3], [0.49, 0.49]]
    assert len(cubature_materials(np.full((4, 2), 0.45))) == 1
    # the capture's prior range, when known, is the range adapt estimates ν in
    assert [list(s) for s in cubature_materials(np.full((4, 2), 0.45), (0.3, 0.49))] == [[0.3, 0.3], [0.49, 0.49]]
    assert [list(s) for s in cubature_materials(np.full((4, 2), 0.4), (0.45, 0.45))] == [[0.45, 0.45]]
    fits = {"one": fit_cubature(sampler(z_fit, 0.40), scene.tet_region, 2, max_points=40, tol=1e-3, seed=0),
            "two": fit_cubature(StackedSampler(sampler(z_fit, 0.30), sampler(z_fit, 0.49)), scene.tet_region, 2,
                                max_points=40, tol=1e-3, seed=0)}
    err = {(name, nu): cubature_error(sampler(z_held, nu), scene.tet_region, 2, ids, w)
           for name, (ids, w, _) in fits.items() for nu in (0.30, 0.42, 0.49)}
    assert all(err[("two", nu)] < 0.02 for nu in (0.30, 0.42, 0.49)), err
    assert err[("one", 0.49)] > 3 * err[("two", 0.49)], err
