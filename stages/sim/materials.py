"""Hyperelastic energy densities Ψ(F; θ) in JAX (float64), θ = (E, ν) per region.

All functions act on one 3x3 deformation gradient F; vmap them over elements.
Lamé parameters are computed in one place, :func:`lame`.
"""
from __future__ import annotations

import jax.numpy as jnp

MODELS = ("stable_neohookean", "yeoh", "linear")

# Yeoh higher-order coefficients as fractions of μ: Ψ = μ/2 (Ī₁−3) + c2 μ (Ī₁−3)² + c3 μ (Ī₁−3)³ + κ/2 (J−1)²
YEOH_C20_OVER_MU = 0.05
YEOH_C30_OVER_MU = 0.005


def lame(young_pa, poisson):
    """(μ, λ) from Young's modulus E (Pa) and Poisson's ratio ν:
    μ = E / (2(1+ν)),  λ = E ν / ((1+ν)(1−2ν))."""
    mu = young_pa / (2.0 * (1.0 + poisson))
    lam = young_pa * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    return mu, lam


def stable_neohookean(F, mu, lam):
    """Stable Neo-Hookean (Smith et al. 2018, rest-stable form):

    Ψ = μ'/2 (I_C − 3) + λ'/2 (J − α)² − μ'/2 log(I_C + 1),  α = 1 + 3μ'/(4λ'),
    with μ' = 4μ/3 and λ' = λ + 5μ/6 so that small strains match linear elasticity (E, ν).
    """
    mu_s = 4.0 / 3.0 * mu
    lam_s = lam + 5.0 / 6.0 * mu
    ic = jnp.sum(F * F)
    J = jnp.linalg.det(F)
    alpha = 1.0 + 0.75 * mu_s / lam_s
    return 0.5 * mu_s * (ic - 3.0) + 0.5 * lam_s * (J - alpha) ** 2 - 0.5 * mu_s * jnp.log(ic + 1.0) \
        - _snh_rest_energy(mu_s, lam_s)


def _snh_rest_energy(mu_s, lam_s):
    """Ψ_SNH(I) so that Ψ(I) = 0: λ'/2 (1 − α)² − μ'/2 log 4."""
    alpha = 1.0 + 0.75 * mu_s / lam_s
    return 0.5 * lam_s * (1.0 - alpha) ** 2 - 0.5 * mu_s * jnp.log(4.0)


def yeoh(F, mu, lam):
    """Compressible Yeoh: Ψ = μ/2 (Ī₁−3) + c₂μ (Ī₁−3)² + c₃μ (Ī₁−3)³ + κ/2 (J−1)²,
    Ī₁ = J^(−2/3) tr(FᵀF), κ = λ + 2μ/3 (bulk modulus)."""
    J = jnp.linalg.det(F)
    i1 = jnp.sum(F * F) * jnp.abs(J) ** (-2.0 / 3.0)
    d = i1 - 3.0
    kappa = lam + 2.0 / 3.0 * mu
    return 0.5 * mu * d + YEOH_C20_OVER_MU * mu * d ** 2 + YEOH_C30_OVER_MU * mu * d ** 3 \
        + 0.5 * kappa * (J - 1.0) ** 2


def linear(F, mu, lam):
    """Linear elasticity: Ψ = μ ε:ε + λ/2 tr(ε)²,  ε = (F + Fᵀ)/2 − I."""
    eps = 0.5 * (F + F.T) - jnp.eye(3, dtype=F.dtype)
    return mu * jnp.sum(eps * eps) + 0.5 * lam * jnp.trace(eps) ** 2


def viscous_density(F, F_prev, mu, lam):
    """Kelvin–Voigt dissipation density of one step, without its factor β/Δt:

    D = μ ‖ΔE‖² + λ/2 tr(ΔE)²,  ΔE = E(F) − E(F_prev),  E(F) = ½ (FᵀF − I) (the Green strain),

    so β/Δt · D is rigid-motion invariant and, at small strain, ½ β/Δt (x − x_prev)ᵀ K₀ (x − x_prev): Rayleigh's
    stiffness-proportional damping, force −β K₀ v (β in seconds)."""
    eye = jnp.eye(3, dtype=F.dtype)
    dE = 0.5 * (F.T @ F - eye) - 0.5 * (F_prev.T @ F_prev - eye)
    return mu * jnp.sum(dE * dE) + 0.5 * lam * jnp.trace(dE) ** 2


ENERGY_DENSITY = {"stable_neohookean": stable_neohookean, "yeoh": yeoh, "linear": linear}


def energy_density(model: str):
    """Ψ(F, μ, λ) for a model name."""
    try:
        return ENERGY_DENSITY[model]
    except KeyError:
        raise ValueError(f"unknown material model {model!r}; use one of {', '.join(MODELS)}") from None
