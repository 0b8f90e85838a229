"""Neural and linear subspaces x = φ(z), reduced dynamics and the reduced adjoint (JAX, float64).

Modules
  networks  SubspaceMap: x = x̄ + U q(z) with U mass-orthonormal (PCA of the snapshots, or linear-blend-
            skinning modes for kind "lbs"); q(z) = z (PCA, LBS) or the
            Fulton et al. 2019 autoencoder (an equinox Module: 2×200 ELU layers with a PCA-initialised
            linear skip; stored and used in the jitted solver as named arrays).
  train     pca_basis, lbs_basis (harmonic skinning weights, 12 affine modes per handle), fit_subspace
            (Adam via optax on the equinox module), reconstruction_error.
  cubature  optimised cubature of the reduced elastic energy over quadrature points (one per linear tet,
            four per quadratic tet; An et al. 2008, greedy NNLS).
  reduced   ReducedModel: reduced Newton step / simulate and the window adjoint (paper Eq. 3, 10–12).

API for the adapt stage::

    from stages.subspace import ReducedModel
    model = ReducedModel.from_artefacts(SubspaceArtefact.load(ws / "subspace.h5"), scene)
    model.dim, model.z_rest                       # r; ψ(rest) (= 0)
    x = model.decode(z)                           # (r,) → (n, 3); (T, r) → (T, n, 3)
    z = model.encode(x)                           # (n, 3) → (r,)
    J = model.jacobian(z)                         # (n, 3, r); model.jacobian_transpose(z, v) = Jᵀv (r,)
    z, info = model.step(inputs, young, poisson, z_prev, z_prev2, z_init=None)   # info: iterations, residual
    Z = model.simulate(inputs_seq, young, poisson, z_prev=None, z_prev2=None)   # (T, r); θ (T, R) or (R,)
    g = model.window_adjoint(inputs_seq, young, poisson, Z, z_before, dL_dX=... or dL_dZ=...)
        # {"young": (w, R), "poisson": (w, R), "z_before": (2, r), "lambda": (w, r)}

``inputs`` are stages.sim.scene.FrameInputs (or ReducedInputs from model.reduce_inputs, to reuse);
young/poisson are per region (R,).  ``ReducedModel(sub, scene, reference=True)`` evaluates the full
potential on φ(z) over every quadrature point: the reference the cubature path is tested against.
"""
from stages.subspace.networks import SubspaceMap
from stages.subspace.reduced import ReducedInputs, ReducedModel, ReducedSolveError

__all__ = ["ReducedInputs", "ReducedModel", "ReducedSolveError", "SubspaceMap"]
