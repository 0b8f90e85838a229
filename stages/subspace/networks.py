"""Subspace maps x = φ(z) in JAX: PCA, LBS modes and the Fulton et al. 2019 autoencoder (an equinox Module).

Both kinds share one outer linear layer, the mass-orthonormal PCA basis U of the
training displacements (Uᵀ M U = I, M the lumped mass matrix):

    x = φ(z) = x̄ + U q(z)                 x̄ rest positions (n, 3), U (n, 3, p), q ∈ ℝᵖ
    z = ψ(x) = e(q),   q = Uᵀ M (x − x̄)   (the M-orthogonal projection onto span U)

PCA: p = r and q(z) = z, e(q) = q.  Autoencoder (Fulton et al. 2019, §3): the
PCA layer is the outer layer of both halves; between it and the latent code sit
fully connected layers 2×200 with ELU, plus a linear skip initialised to the
PCA truncation, so that training starts from the PCA subspace:

    q(z) = s ⊙ (z S_d + D(z) − D(0)),   e(q) = (q/s) S_e + E(q/s) − E(0),

D, E the MLPs, s the per-coefficient scale of the training q.  Subtracting
D(0), E(0) makes φ(0) = x̄ and ψ(x̄) = 0 exactly.  Because x − x̄ = U q, the
decoder is linear after q: decoding a vertex subset only needs U's rows.

LBS ("lbs", stages.subspace.train.lbs_basis): a linear kind like PCA (q(z) = z, s = 1) whose U is
built from linear-blend-skinning modes w_j(x) e_a ⊗ [x̄ − c_j; 1] (affine handle transformations
blended by harmonic skinning weights) instead of the snapshots' leading modes.  It stores what PCA
stores plus the aux arrays lbs_handles (k, 3) and lbs_skin_weights (n, k) (informational).

The trained part is ``Autoencoder``, an eqx.Module of two ``SkipMLP`` halves
(Dense layers, weights (in, out)), trained with optax through eqx.filter_value_and_grad.
SubspaceMap.net and subspace.h5 hold it as named arrays (enc_skip (p, r), enc_w1
(p, 200), enc_b1 (200,), …, dec_b3 (p,)); Autoencoder.from_named / to_named convert
at that boundary (the same arrays, renamed).  net_decode / net_encode take either form.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

KINDS = ("autoencoder", "pca", "lbs")
LINEAR_KINDS = ("pca", "lbs")  # q(z) = z: x = x̄ + U z
HIDDEN = (200, 200)  # paper §5.1
_LAYERS = ("w1", "b1", "w2", "b2", "w3", "b3")  # named arrays of one MLP, W (in, out), b (out,)


class Dense(eqx.Module):
    """y = x W + b, x (..., n_in) → (..., n_out).

    W is kept (n_in, n_out), the layout of subspace.h5, so the named arrays convert without copies and
    the reduced solver's jacobians contract the tangents on W's leading axis (eqx.nn.Linear's (out, in)
    layout with vmap measured about 2× slower there).
    """

    weight: jax.Array  # (n_in, n_out)
    bias: jax.Array | None  # (n_out,) or None

    def __call__(self, x):
        y = x @ self.weight
        return y if self.bias is None else y + self.bias


class SkipMLP(eqx.Module):
    """y(x) = x S + f(x) − f(0): a linear skip S plus an ELU MLP f, shifted so that y(0) = 0 exactly.

    Maps (..., n_in) → (..., n_out); f = Dense → ELU → Dense → ELU → Dense (n_in → 200 → 200 → n_out).
    """

    skip: Dense  # S (n_in, n_out), no bias
    layers: tuple  # of Dense

    def mlp(self, x):
        """f(x), (..., n_in) → (..., n_out)."""
        for layer in self.layers[:-1]:
            x = jax.nn.elu(layer(x))
        return self.layers[-1](x)

    def __call__(self, x):
        """x (..., n_in) → (..., n_out)."""
        f0 = self.mlp(jnp.zeros(x.shape[-1], x.dtype))  # f(0) (n_out,): once for any batch
        return self.skip(x) + self.mlp(x) - f0

    @staticmethod
    def init(keys, n_in: int, n_out: int, hidden=HIDDEN, out_scale: float = 1e-2) -> "SkipMLP":
        """Skip = the truncation S = I (n_in × n_out); MLP Glorot-normal with zero biases, last layer × out_scale.

        keys: one PRNG key per MLP layer (len(hidden) + 1).
        """
        dims = (n_in, *hidden, n_out)
        layers = []
        for i in range(len(dims) - 1):
            scale = out_scale if i == len(dims) - 2 else 1.0
            w = scale * jax.random.normal(keys[i], dims[i:i + 2]) * np.sqrt(2.0 / (dims[i] + dims[i + 1]))
            layers.append(Dense(w, jnp.zeros(dims[i + 1])))
        return SkipMLP(Dense(jnp.eye(n_in, n_out), None), tuple(layers))

    @staticmethod
    def from_named(skip, ws: dict) -> "SkipMLP":
        """From the stored layout: skip S (n_in, n_out), ws {w1, b1, w2, b2, …} with W (in, out)."""
        n = len(ws) // 2
        return SkipMLP(Dense(skip, None), tuple(Dense(ws[f"w{i}"], ws[f"b{i}"]) for i in range(1, n + 1)))

    def to_named(self) -> tuple:
        """(S, {w1, b1, …}): the inverse of from_named (the same arrays)."""
        ws = {}
        for i, layer in enumerate(self.layers):
            ws[f"w{i + 1}"], ws[f"b{i + 1}"] = layer.weight, layer.bias
        return self.skip.weight, ws


class Autoencoder(eqx.Module):
    """The Fulton et al. 2019 autoencoder between normalised PCA coefficients q̂ = q/s (p,) and z (r,).

    encode: z = q̂ S_e + E(q̂) − E(0);  decode: q̂ = z S_d + D(z) − D(0).  The outer PCA layer U and the
    scale s are fixed (SubspaceMap); these are the trained parts.
    """

    encoder: SkipMLP  # (..., p) → (..., r)
    decoder: SkipMLP  # (..., r) → (..., p)

    @property
    def r(self) -> int:
        return int(self.decoder.skip.weight.shape[0])

    @property
    def p(self) -> int:
        return int(self.encoder.skip.weight.shape[0])

    def encode(self, qn):
        """q̂ (..., p) → z (..., r)."""
        return self.encoder(qn)

    def decode(self, z):
        """z (..., r) → q̂ (..., p)."""
        return self.decoder(z)

    def __call__(self, qn):
        """The reconstruction q̂ → decode(encode(q̂)), (..., p) → (..., p)."""
        return self.decode(self.encode(qn))

    @staticmethod
    def init(key, r: int, p: int, hidden=HIDDEN, out_scale: float = 1e-2) -> "Autoencoder":
        """Skips = the PCA truncation (S_e = [I; 0], S_d = [I, 0]): at init the map is PCA of dimension r
        up to the MLPs' small (× out_scale) last layers."""
        keys = jax.random.split(key, 2 * (len(hidden) + 1))
        h = len(hidden) + 1
        return Autoencoder(SkipMLP.init(keys[:h], p, r, hidden, out_scale),
                           SkipMLP.init(keys[h:], r, p, hidden, out_scale))

    @staticmethod
    def from_named(net: dict) -> "Autoencoder":
        """From the named arrays of subspace.h5 (enc_skip (p, r), enc_w1 (p, 200), …, dec_b3 (p,))."""
        halves = []
        for h in ("enc", "dec"):
            halves.append(SkipMLP.from_named(net[f"{h}_skip"], {k: net[f"{h}_{k}"] for k in _LAYERS}))
        return Autoencoder(*halves)

    def to_named(self) -> dict:
        """Named arrays (JAX) for SubspaceMap.net / subspace.h5; from_named's inverse, exact."""
        net = {}
        for h, half in (("enc", self.encoder), ("dec", self.decoder)):
            skip, ws = half.to_named()
            net[f"{h}_skip"] = skip
            net.update({f"{h}_{k}": v for k, v in ws.items()})
        return net


def _module(net):
    return net if isinstance(net, Autoencoder) else Autoencoder.from_named(net)


def net_decode(net, z):
    """q̂(z) = z S_d + D(z) − D(0) (normalised coefficients), z (..., r) → (..., p).

    net: named arrays (the reduced solver passes these to its jitted kernels) or an Autoencoder.
    """
    return _module(net).decode(z)


def net_encode(net, qn):
    """z(q̂) = q̂ S_e + E(q̂) − E(0), q̂ (..., p) → (..., r); net: named arrays or an Autoencoder."""
    return _module(net).encode(qn)


def init_net(key, r: int, p: int, hidden=HIDDEN, out_scale: float = 1e-2) -> dict:
    """Autoencoder.init as named arrays (skips = PCA truncation; MLPs Glorot, last layer × out_scale)."""
    return Autoencoder.init(key, r, p, hidden, out_scale).to_named()


@dataclass(frozen=True)
class SubspaceMap:
    """φ and ψ of one trained subspace (numpy/JAX arrays, float64)."""

    kind: str  # "autoencoder" | "pca" | "lbs"
    rest: np.ndarray  # (n, 3) x̄, m
    basis: np.ndarray  # (n, 3, p) U, mass-orthonormal: Uᵀ M U = I
    masses: np.ndarray  # (n,) lumped masses M, kg
    q_scale: np.ndarray  # (p,) s
    net: dict  # named MLP arrays (empty for the linear kinds), Autoencoder.to_named's layout
    aux: dict = field(default_factory=dict)  # lbs: lbs_handles (k, 3) m, lbs_skin_weights (n, k); else empty

    @property
    def autoencoder(self) -> Autoencoder | None:
        """The trained network as an equinox Module (None for PCA)."""
        return Autoencoder.from_named(self.net) if self.kind == "autoencoder" else None

    @property
    def dim(self) -> int:
        return int(self.net["dec_skip"].shape[0]) if self.kind == "autoencoder" else int(self.basis.shape[2])

    @property
    def p(self) -> int:
        return int(self.basis.shape[2])

    # ------------------------------------------------------------------ q-space
    def q_of_z(self, z):
        """q(z), (..., r) → (..., p)."""
        if self.kind in LINEAR_KINDS:
            return z
        return self.q_scale * net_decode(self.net, z)

    def z_of_q(self, q):
        """e(q), (..., p) → (..., r)."""
        if self.kind in LINEAR_KINDS:
            return q
        return net_encode(self.net, q / self.q_scale)

    def project(self, x):
        """q = Uᵀ M (x − x̄), x (..., n, 3) → (..., p)."""
        d = (x - self.rest) * self.masses[:, None]
        return jnp.einsum("...ni,nip->...p", d, self.basis)

    # ------------------------------------------------------------------ φ, ψ
    def decode(self, z):
        """x = x̄ + U q(z), z (..., r) → (..., n, 3)."""
        return self.rest + jnp.einsum("nip,...p->...ni", self.basis, self.q_of_z(z))

    def decode_rows(self, z, vertex_ids):
        """φ restricted to vertices: x̄[ids] + U[ids] q(z), (k, 3)."""
        return self.rest[vertex_ids] + jnp.einsum("nip,p->ni", self.basis[vertex_ids], self.q_of_z(z))

    def encode(self, x):
        """z = e(Uᵀ M (x − x̄)), x (..., n, 3) → (..., r)."""
        return self.z_of_q(self.project(x))

    def jacobian_q(self, z):
        """∂q/∂z (p, r)."""
        if self.kind in LINEAR_KINDS:
            return jnp.eye(self.p)
        return jax.jacfwd(self.q_of_z)(z)

    def jacobian(self, z):
        """J = ∂φ/∂z = U ∂q/∂z, (n, 3, r)."""
        return jnp.einsum("nip,pr->nir", self.basis, self.jacobian_q(z))

    # ------------------------------------------------------------------ storage
    def to_weights(self) -> dict:
        """Named arrays for SubspaceArtefact.weights."""
        w = {"rest": np.asarray(self.rest), "basis": np.asarray(self.basis), "masses": np.asarray(self.masses),
             "q_scale": np.asarray(self.q_scale)}
        w.update({k: np.asarray(v) for k, v in self.net.items()})
        w.update({k: np.asarray(v) for k, v in self.aux.items()})
        return w

    @staticmethod
    def from_weights(kind: str, weights: dict) -> "SubspaceMap":
        net = {k: jnp.asarray(v, jnp.float64) for k, v in weights.items()
               if k.startswith(("enc_", "dec_"))}
        aux = {k: np.asarray(v, np.float64) for k, v in weights.items() if k.startswith("lbs_")}
        return SubspaceMap(kind, np.asarray(weights["rest"], np.float64), np.asarray(weights["basis"], np.float64),
                           np.asarray(weights["masses"], np.float64), np.asarray(weights["q_scale"], np.float64),
                           net, aux)


def required_weights(kind: str) -> tuple[str, ...]:
    """Names a SubspaceArtefact of this kind must hold."""
    base = ("rest", "basis", "masses", "q_scale")
    if kind in LINEAR_KINDS:
        return base
    return base + tuple(f"{h}_{k}" for h in ("enc", "dec") for k in ("skip", "w1", "b1", "w2", "b2", "w3", "b3"))
