"""Subspace maps and their training (stages.subspace.networks / train): PCA and the autoencoder.

Sample-like data: a bar bent, twisted and stretched by three random amounts (large rotations, so a
linear subspace of the same size cannot hold them).
"""
from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stages.sim.mesh import rest_quantities
from stages.sim.meshgen import box_tets
from stages.subspace.networks import Autoencoder, SubspaceMap, init_net, net_decode, net_encode, required_weights
from stages.subspace.train import _loss, fit_subspace, pca_basis, reconstruction_error, train_autoencoder


# ---------------------------------------------------------------- the plain-jnp twin of the equinox Autoencoder
def mlp_ref(ws: list, x):
    """x → elu(x W₁ + b₁) → elu(· W₂ + b₂) → · W₃ + b₃, W (in, out): the pre-equinox functional code."""
    h = x
    for i in range(3):
        h = h @ ws[2 * i] + ws[2 * i + 1]
        if i < 2:
            h = jax.nn.elu(h)
    return h


def half_ref(net: dict, h: str, x):
    """x S + f(x) − f(zeros_like(x)) for h = "enc" | "dec"."""
    ws = [net[f"{h}_{k}"] for k in ("w1", "b1", "w2", "b2", "w3", "b3")]
    return x @ net[f"{h}_skip"] + mlp_ref(ws, x) - mlp_ref(ws, jnp.zeros_like(x))


def loss_ref(net: dict, q, scale, total_mass):
    rec = scale * half_ref(net, "dec", half_ref(net, "enc", q / scale))
    return jnp.mean(jnp.sum((rec - q) ** 2, axis=-1)) / total_mass


def random_net(seed: int, r: int, p: int, amp: float = 0.3) -> dict:
    """Named arrays of the stored layout with every entry random (skips and biases too), numpy."""
    rng = np.random.default_rng(seed)
    shapes = {"enc_skip": (p, r), "dec_skip": (r, p)}
    for h, dims in (("enc", (p, 200, 200, r)), ("dec", (r, 200, 200, p))):
        for i in range(3):
            shapes[f"{h}_w{i + 1}"], shapes[f"{h}_b{i + 1}"] = dims[i:i + 2], (dims[i + 1],)
    return {k: amp * rng.normal(size=s) for k, s in shapes.items()}


def bend_twist(rest: np.ndarray, kappa: float, tau: float, stretch: float) -> np.ndarray:
    """Stretch along x, twist τ rad/m about the bar's axis, bend with curvature κ (1/m) about y."""
    c = rest.mean(0)
    x, y, z = rest[:, 0] * (1 + stretch), rest[:, 1] - c[1], rest[:, 2] - c[2]
    a = tau * x
    y, z = y * np.cos(a) - z * np.sin(a), y * np.sin(a) + z * np.cos(a)
    th = x * kappa
    R = 1.0 / kappa
    return np.stack([(R - z) * np.sin(th), y + c[1], R - (R - z) * np.cos(th) + c[2]], -1)


@pytest.fixture(scope="module")
def bar_data():
    v, t = box_tets((12, 3, 3), (0.2, 0.05, 0.05))
    _, _, m = rest_quantities(v, t, 1000.0)
    rng = np.random.default_rng(0)
    X = np.stack([bend_twist(v, rng.choice([-1, 1]) * rng.uniform(0.5, 8), rng.uniform(-10, 10),
                             rng.uniform(-0.1, 0.1)) for _ in range(240)])
    return v, m, X[:200], X[200:]


@pytest.fixture(scope="module")
def ae3(bar_data):
    v, m, xt, xv = bar_data
    sub, info = fit_subspace("autoencoder", v, m, xt, 3, xv, epochs=120, seed=0, pca_dim=24)
    return sub, info


def test_pca_basis_is_mass_orthonormal(bar_data):
    v, m, xt, _ = bar_data
    U, sig = pca_basis(xt - v, m, 10)
    G = np.einsum("nip,n,niq->pq", U, m, U)
    assert np.allclose(G, np.eye(10), atol=1e-10)
    assert np.all(np.diff(sig) <= 1e-12)


def test_decode_encode_identities(bar_data, ae3):
    """φ(0) = rest, ψ(rest) = 0, and PCA's ψ∘φ is the identity."""
    v, m, xt, _ = bar_data
    sub, _ = ae3
    assert np.allclose(np.asarray(sub.decode(jnp.zeros(3))), v, atol=1e-14)
    assert np.allclose(np.asarray(sub.encode(jnp.asarray(v))), 0.0, atol=1e-12)
    pca, _ = fit_subspace("pca", v, m, xt, 5)
    z = np.random.default_rng(0).normal(size=5) * 0.01
    assert np.allclose(np.asarray(pca.encode(pca.decode(jnp.asarray(z)))), z, atol=1e-12)


def test_jacobian_and_row_decoding(bar_data, ae3):
    v, _, _, xv = bar_data
    sub, _ = ae3
    z = np.asarray(sub.encode(jnp.asarray(xv[0])))
    J = np.asarray(sub.jacobian(jnp.asarray(z)))
    h = 1e-6
    fd = np.stack([(np.asarray(sub.decode(jnp.asarray(z + h * e))) - np.asarray(sub.decode(jnp.asarray(z - h * e))))
                   / (2 * h) for e in np.eye(3)], -1)
    assert np.abs(fd - J).max() <= 1e-6 * np.abs(J).max()
    ids = np.array([0, 7, 50, len(v) - 1])
    assert np.allclose(np.asarray(sub.decode_rows(jnp.asarray(z), ids)), np.asarray(sub.decode(jnp.asarray(z)))[ids])


def test_autoencoder_beats_pca_at_equal_dimension(bar_data, ae3):
    v, m, xt, xv = bar_data
    sub, info = ae3
    pca, _ = fit_subspace("pca", v, m, xt, 3)
    e_ae, e_pca = reconstruction_error(sub, xv), reconstruction_error(pca, xv)
    assert e_ae < 0.5 * e_pca, (e_ae, e_pca)
    assert info["history"][-1][0] < info["history"][0][0]  # training lowered the loss


def test_weights_round_trip(bar_data, ae3):
    _, _, _, xv = bar_data
    sub, _ = ae3
    back = SubspaceMap.from_weights("autoencoder", sub.to_weights())
    x = jnp.asarray(xv[:3])
    assert np.allclose(np.asarray(back.decode(back.encode(x))), np.asarray(sub.decode(sub.encode(x))), atol=1e-14)
    assert back.dim == 3 and back.p == 24


def test_training_is_reproducible(bar_data):
    v, m, xt, xv = bar_data
    a, _ = fit_subspace("autoencoder", v, m, xt[:64], 2, epochs=3, seed=4, pca_dim=8)
    b, _ = fit_subspace("autoencoder", v, m, xt[:64], 2, epochs=3, seed=4, pca_dim=8)
    for k in a.net:
        assert np.array_equal(np.asarray(a.net[k]), np.asarray(b.net[k]))


def test_jacobian_q_matches_autodiff_for_pca(bar_data):
    v, m, xt, _ = bar_data
    pca, _ = fit_subspace("pca", v, m, xt, 4)
    assert np.array_equal(np.asarray(pca.jacobian_q(jnp.zeros(4))), np.eye(4))
    J = np.asarray(jax.jacfwd(pca.decode)(jnp.zeros(4)))
    assert np.allclose(J, pca.basis)


# ---------------------------------------------------------------- the equinox module against its twin
def test_module_named_arrays_round_trip_exact():
    net = random_net(0, 4, 11)
    mod = Autoencoder.from_named(net)
    assert isinstance(mod, eqx.Module) and (mod.r, mod.p) == (4, 11)
    back = mod.to_named()
    names = sorted(k for k in required_weights("autoencoder") if k.startswith(("enc_", "dec_")))
    assert sorted(back) == sorted(net) == names
    for k in net:
        assert np.array_equal(np.asarray(back[k]), net[k]), k
    again = Autoencoder.from_named(back)
    assert eqx.tree_equal(again, mod)
    # through SubspaceMap's storage (subspace.h5 named arrays) and back
    sub = SubspaceMap("autoencoder", np.zeros((5, 3)), np.zeros((5, 3, 11)), np.ones(5), np.ones(11),
                      {k: jnp.asarray(v) for k, v in mod.to_named().items()})
    w = SubspaceMap.from_weights("autoencoder", sub.to_weights()).to_weights()
    for k in net:
        assert np.array_equal(w[k], net[k]), k
    assert eqx.tree_equal(SubspaceMap.from_weights("autoencoder", w).autoencoder, mod)


def test_init_is_the_pca_truncation_plus_small_mlps():
    net = init_net(jax.random.PRNGKey(1), 3, 8)
    assert np.array_equal(net["enc_skip"], np.eye(8, 3)) and np.array_equal(net["dec_skip"], np.eye(3, 8))
    assert all(not np.any(net[f"{h}_b{i}"]) for h in ("enc", "dec") for i in (1, 2, 3))
    assert np.abs(net["dec_w3"]).max() < 0.1 * np.abs(net["dec_w2"]).max()  # last layer × out_scale
    mod = Autoencoder.init(jax.random.PRNGKey(1), 3, 8)
    assert eqx.tree_equal(mod, Autoencoder.from_named(net))


@pytest.mark.parametrize("lead", [(), (5,), (2, 3)])
def test_decode_encode_match_plain_twin(lead):
    """Autoencoder.decode / encode (and the net_* wrappers on named arrays) = the plain-jnp twin."""
    r, p = 4, 11
    net = random_net(1, r, p)
    jnet = {k: jnp.asarray(v) for k, v in net.items()}
    rng = np.random.default_rng(2)
    z, q = jnp.asarray(rng.normal(size=lead + (r,))), jnp.asarray(rng.normal(size=lead + (p,)))
    mod = Autoencoder.from_named(jnet)
    for got, want in ((mod.decode(z), half_ref(jnet, "dec", z)), (net_decode(jnet, z), half_ref(jnet, "dec", z)),
                      (mod.encode(q), half_ref(jnet, "enc", q)), (net_encode(jnet, q), half_ref(jnet, "enc", q)),
                      (jax.jit(net_decode)(jnet, z), half_ref(jnet, "dec", z))):
        got, want = np.asarray(got), np.asarray(want)
        assert got.shape == want.shape == lead + (want.shape[-1],)
        assert np.abs(got - want).max() <= 1e-13 * np.abs(want).max(), np.abs(got - want).max()
    # jacobian of the decoder (the reduced solver's path) against the twin's
    z1 = jnp.asarray(rng.normal(size=r))
    ja = np.asarray(jax.jacfwd(lambda a: net_decode(jnet, a))(z1))
    jb = np.asarray(jax.jacfwd(lambda a: half_ref(jnet, "dec", a))(z1))
    assert np.abs(ja - jb).max() <= 1e-13 * np.abs(jb).max()


def test_phi_of_zero_is_rest_exactly(bar_data):
    """φ(0) = x̄ and ψ(x̄) = 0 bit for bit (one z), whatever the weights; batched to rounding (D(0) is
    evaluated once per call, unbatched)."""
    v, m, xt, _ = bar_data
    U, _ = pca_basis(xt - v, m, 11)
    net = {k: jnp.asarray(a) for k, a in random_net(3, 4, 11).items()}
    sub = SubspaceMap("autoencoder", v, U, m, np.linspace(0.5, 2.0, 11), net)
    assert np.array_equal(np.asarray(sub.decode(jnp.zeros(4))), v)
    assert np.array_equal(np.asarray(sub.encode(jnp.asarray(v))), np.zeros(4))
    # compiled with the weights as arguments, as the reduced solver does (closed-over weights let XLA
    # constant-fold D(0) with another rounding, in this code and the pre-equinox one alike)
    assert np.array_equal(np.asarray(jax.jit(net_decode)(net, jnp.zeros(4))), np.zeros(11))
    assert np.array_equal(np.asarray(jax.jit(net_encode)(net, jnp.zeros(11))), np.zeros(4))
    assert np.array_equal(np.asarray(Autoencoder.from_named(net).decode(jnp.zeros(4))), np.zeros(11))
    assert np.abs(np.asarray(sub.decode(jnp.zeros((3, 4)))) - v).max() < 1e-12 * np.ptp(v)
    assert np.abs(np.asarray(sub.decode(jnp.full(4, 0.3))) - v).max() > 1e-3  # the weights do act


def test_loss_gradient_matches_twin_and_finite_differences():
    """eqx.filter_value_and_grad of the training loss = jax.grad of the twin; directional FD agrees."""
    r, p = 3, 7
    net = {k: jnp.asarray(v) for k, v in random_net(4, r, p, amp=0.1).items()}
    rng = np.random.default_rng(5)
    q, scale, mass = jnp.asarray(rng.normal(size=(9, p))), jnp.asarray(rng.uniform(0.5, 2, p)), jnp.asarray(2.5)
    mod = Autoencoder.from_named(net)
    val, g = eqx.filter_value_and_grad(_loss)(mod, q, scale, mass)
    val_ref, g_ref = jax.value_and_grad(loss_ref)(net, q, scale, mass)
    assert abs(float(val) - float(val_ref)) <= 1e-13 * abs(float(val_ref))
    gn = g.to_named()
    for k in net:
        a, b = np.asarray(gn[k]), np.asarray(g_ref[k])
        assert np.abs(a - b).max() <= 1e-11 * np.abs(b).max(), k
    d = {k: jnp.asarray(rng.normal(size=v.shape)) for k, v in net.items()}
    h = 1e-6
    shifted = [Autoencoder.from_named({k: net[k] + s * h * d[k] for k in net}) for s in (1, -1)]
    fd = (float(_loss(shifted[0], q, scale, mass)) - float(_loss(shifted[1], q, scale, mass))) / (2 * h)
    an = sum(float(jnp.sum(gn[k] * d[k])) for k in net)
    assert abs(fd - an) <= 1e-6 * abs(an), (fd, an)


def test_training_reduces_validation_loss(bar_data):
    v, m, xt, xv = bar_data
    U, _ = pca_basis(xt - v, m, 12)
    tmp = SubspaceMap("pca", v, U, m, np.ones(12), {})
    qt, qv = np.asarray(tmp.project(jnp.asarray(xt))), np.asarray(tmp.project(jnp.asarray(xv)))
    net, scale, hist = train_autoencoder(qt, qv, 3, 30, seed=1, total_mass=float(m.sum()))
    k0 = jax.random.split(jax.random.PRNGKey(1))[1]  # train_autoencoder's init key
    args = (jnp.asarray(qv), jnp.asarray(scale), float(m.sum()))
    before = float(loss_ref(init_net(k0, 3, 12), *args))
    after = float(loss_ref({k: jnp.asarray(a) for k, a in net.items()}, *args))
    assert after < 0.5 * before, (after, before)
    assert after == pytest.approx(min(h[1] for h in hist), rel=1e-10)  # the best epoch's weights are returned
