"""Energy, gradient and PSD-projected Hessian at quadrature points: a compiled (numba) stable
Neo-Hookean kernel with the analytic eigensystem of Smith et al. 2019, and its JAX twin for every material.

A quadrature point (stages.sim.quadrature.Quadrature) lies in an element with k nodes (4: linear,
10: quadratic tets); its unknowns are the element's nodes x_e = [x_0 … x_{k−1}] (3k,). With G (k, 3)
the shape-function gradients at the point (linear tets: G_a = row a−1 of Dm⁻¹ for a ≥ 1,
G_0 = −Σ_a G_a) and w its weight (linear tets: the rest volume V), F = Σ_a x_a ⊗ G_a, so
    ∂(wΨ)/∂x_a = w P G_a,    ∂²(wΨ)/∂x_{a,i}∂x_{b,k} = w Σ_{jl} ∂²Ψ/∂F_ij∂F_kl G_aj G_bl.
The kernel sums the points of an element into one (3k,) gradient and (3k, 3k) Hessian (``out_index``);
the per-tet entry points (:func:`snh_kernel`, :func:`element_terms`) are the linear case with one
point per tet, bit for bit the per-tet math.
The 9×9 Hessian ∂²Ψ/∂F² = Σ_k λ_k vec(Q_k) vec(Q_k)ᵀ with, for F = U Σ Vᵀ (U, V rotations,
σ_3 may be negative), Ψ = Ψ(I₂, J), I₂ = Σσ², J = σ₁σ₂σ₃:
  - twist  Q = U (e_i e_jᵀ − e_j e_iᵀ)/√2 Vᵀ,  λ = 2Ψ_I₂ + Ψ_J σ_k,
  - flip   Q = U (e_i e_jᵀ + e_j e_iᵀ)/√2 Vᵀ,  λ = 2Ψ_I₂ − Ψ_J σ_k,
  - scaling Q = U diag(q) Vᵀ with (λ, q) the eigenpairs of ∂²Ψ/∂σ² (3×3).
Projection to positive semi-definite clamps λ_k at 0; that equals clamping the eigenvalues of the
9×9 matrix, which is what the JAX twin does with ``eigh``. The exact (unprojected) Hessian skips the
eigensystem: ∂²Ψ/∂F_ij∂F_kl = 2Ψ_I₂ δ_ik δ_jl + 4Ψ_I₂I₂ F_ij F_kl + Ψ_JJ C_ij C_kl + Ψ_J ε_ikp ε_jlq F_pq,
C = cof F = ∂J/∂F.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numba as nb
import numpy as np

from .materials import energy_density, viscous_density

jax.config.update("jax_enable_x64", True)

ENERGY, GRADIENT, HESSIAN = 0, 1, 2  # what a kernel call computes (each includes the previous)


def shape_gradients(dm_inv: np.ndarray) -> np.ndarray:
    """G (m, 4, 3): gradients of the linear shape functions, F = Σ_a x_a ⊗ G_a."""
    g = np.empty(dm_inv.shape[:-2] + (4, 3))
    g[..., 1:, :] = dm_inv
    g[..., 0, :] = -dm_inv.sum(axis=-2)
    return g


# =========================================================================== numba kernel
@nb.njit(cache=True)
def _sym3_eig_into(a, w, q):
    """Eigenpairs of a symmetric 3×3 matrix by cyclic Jacobi, in place: a is destroyed,
    w (3,) eigenvalues, q (3, 3) eigenvectors as columns."""
    for i in range(3):
        for j in range(3):
            q[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(30):
        off = a[0, 1] ** 2 + a[0, 2] ** 2 + a[1, 2] ** 2
        scale = a[0, 0] ** 2 + a[1, 1] ** 2 + a[2, 2] ** 2
        if off <= 1e-32 * scale or off == 0.0:
            break
        for p in range(2):
            for r in range(p + 1, 3):
                apr = a[p, r]
                if apr == 0.0:
                    continue
                theta = (a[r, r] - a[p, p]) / (2.0 * apr)
                t = (1.0 if theta >= 0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(3):  # a = Jᵀ a J
                    akp, akr = a[k, p], a[k, r]
                    a[k, p] = c * akp - s * akr
                    a[k, r] = s * akp + c * akr
                for k in range(3):
                    apk, ark = a[p, k], a[r, k]
                    a[p, k] = c * apk - s * ark
                    a[r, k] = s * apk + c * ark
                for k in range(3):
                    qkp, qkr = q[k, p], q[k, r]
                    q[k, p] = c * qkp - s * qkr
                    q[k, r] = s * qkp + c * qkr
    for i in range(3):
        w[i] = a[i, i]


@nb.njit(cache=True)
def _sym3_eig(a):
    """(w, Q) of a symmetric 3×3 matrix (allocating wrapper of :func:`_sym3_eig_into`)."""
    w = np.empty(3)
    q = np.empty((3, 3))
    _sym3_eig_into(a.copy(), w, q)
    return w, q


@nb.njit(cache=True)
def _rotation_svd_into(F, U, sig, V, work, wv):
    """F = U diag(σ) Vᵀ with U, V proper rotations (σ₃ carries the sign of det F); in place.
    work (3, 3) and wv (3,) are scratch."""
    for i in range(3):
        for j in range(3):
            work[i, j] = F[0, i] * F[0, j] + F[1, i] * F[1, j] + F[2, i] * F[2, j]  # FᵀF
    _sym3_eig_into(work, wv, U)  # U holds the eigenvectors of FᵀF for now
    # sort descending into V
    o0, o1, o2 = 0, 1, 2
    if wv[o0] < wv[o1]:
        o0, o1 = o1, o0
    if wv[o1] < wv[o2]:
        o1, o2 = o2, o1
    if wv[o0] < wv[o1]:
        o0, o1 = o1, o0
    for i in range(3):
        V[i, 0], V[i, 1], V[i, 2] = U[i, o0], U[i, o1], U[i, o2]
    detv = (V[0, 0] * (V[1, 1] * V[2, 2] - V[2, 1] * V[1, 2]) - V[0, 1] * (V[1, 0] * V[2, 2] - V[2, 0] * V[1, 2])
            + V[0, 2] * (V[1, 0] * V[2, 1] - V[2, 0] * V[1, 1]))
    if detv < 0.0:
        for i in range(3):
            V[i, 2] = -V[i, 2]
    # u0 = F v0 / |F v0|
    f0 = wv  # scratch from here on
    for i in range(3):
        f0[i] = F[i, 0] * V[0, 0] + F[i, 1] * V[1, 0] + F[i, 2] * V[2, 0]
    n0 = math.sqrt(f0[0] ** 2 + f0[1] ** 2 + f0[2] ** 2)
    if n0 > 1e-300:
        for i in range(3):
            U[i, 0] = f0[i] / n0
    else:
        U[0, 0], U[1, 0], U[2, 0] = 1.0, 0.0, 0.0
    sig[0] = n0
    for i in range(3):
        f0[i] = F[i, 0] * V[0, 1] + F[i, 1] * V[1, 1] + F[i, 2] * V[2, 1]
    d = U[0, 0] * f0[0] + U[1, 0] * f0[1] + U[2, 0] * f0[2]
    for i in range(3):
        f0[i] -= d * U[i, 0]
    n1 = math.sqrt(f0[0] ** 2 + f0[1] ** 2 + f0[2] ** 2)
    if n1 > 1e-12 * max(n0, 1e-300):
        for i in range(3):
            U[i, 1] = f0[i] / n1
    else:  # any unit vector orthogonal to u0
        if abs(U[0, 0]) < 0.9:
            e0, e1, e2 = 1.0, 0.0, 0.0
        else:
            e0, e1, e2 = 0.0, 1.0, 0.0
        d = U[0, 0] * e0 + U[1, 0] * e1 + U[2, 0] * e2
        e0, e1, e2 = e0 - d * U[0, 0], e1 - d * U[1, 0], e2 - d * U[2, 0]
        ne = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        U[0, 1], U[1, 1], U[2, 1] = e0 / ne, e1 / ne, e2 / ne
    U[0, 2] = U[1, 0] * U[2, 1] - U[2, 0] * U[1, 1]
    U[1, 2] = U[2, 0] * U[0, 1] - U[0, 0] * U[2, 1]
    U[2, 2] = U[0, 0] * U[1, 1] - U[1, 0] * U[0, 1]
    for k in range(1, 3):
        acc = 0.0
        for i in range(3):
            acc += U[i, k] * (F[i, 0] * V[0, k] + F[i, 1] * V[1, k] + F[i, 2] * V[2, k])
        sig[k] = acc


@nb.njit(cache=True)
def _rotation_svd(F):
    """(U, σ, V) with U, V rotations (allocating wrapper of :func:`_rotation_svd_into`)."""
    U, V, work = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    sig, wv = np.empty(3), np.empty(3)
    _rotation_svd_into(np.ascontiguousarray(F), U, sig, V, work, wv)
    return U, sig, V


@nb.njit(cache=True)
def _add_point_hessian(HF, G, V, T, Ho):
    """Ho (3k, 3k) += V Bᵀ HF B for a point's 9×9 ∂²Ψ/∂F² HF (row-major vec F) and shape gradients G (k, 3),
    B[(i,j), (a,kk)] = δ_ik G[a,j]; T (9, 3k) is scratch."""
    k = G.shape[0]
    nd = 3 * k
    for r in range(9):  # T[(i,j), (b,kk)] = Σ_l HF[(i,j),(kk,l)] G[b,l]
        for b in range(k):
            for kk in range(3):
                T[r, 3 * b + kk] = HF[r, 3 * kk] * G[b, 0] + HF[r, 3 * kk + 1] * G[b, 1] + HF[r, 3 * kk + 2] * G[b, 2]
    for a in range(k):  # H[(a,i),(b,kk)] = V Σ_j G[a,j] T[(i,j),(b,kk)]
        for i in range(3):
            for c in range(nd):
                Ho[3 * a + i, c] += V * (G[a, 0] * T[3 * i, c] + G[a, 1] * T[3 * i + 1, c] + G[a, 2] * T[3 * i + 2, c])


@nb.njit(cache=True)
def snh_point_kernel(x, nodes, grad, weight, mu, lam, want, project, out_index, n_out):
    """Stable Neo-Hookean at quadrature points (materials.stable_neohookean, μ' = 4μ/3, λ' = λ + 5μ/6).

    Point p has nodes (k,) = nodes[p] (k = 4 or 10), shape gradients G = grad[p] (k, 3), weight
    w = weight[p] (m³) and F = Σ_a x_a ⊗ G_a.  Its energy w Ψ(F), gradient w P G_a (3k,) and Hessian
    (3k, 3k) are added into row out_index[p] of energies (n_out,), gradients (n_out, 3k) and Hessians
    (n_out, 3k, 3k) — out_index = the element of each point sums them per element.  The Hessian is
    projected to PSD when ``project`` (1/True: eigenvalues clamped at 0; 2: replaced by their
    absolute values).  ``want``: ENERGY, GRADIENT or HESSIAN.  x (n, 3); mu, lam (q,) Pa."""
    q = nodes.shape[0]
    k = nodes.shape[1]
    nd = 3 * k
    energy = np.zeros(n_out)
    gout = np.empty((n_out if want >= 1 else 0, nd))  # a row is zeroed by the first point that adds to it
    hout = np.empty((n_out if want >= 2 else 0, nd, nd))
    first = np.full(n_out, -1)  # the first and last point adding to each output row
    last = np.full(n_out, -1)
    for p in range(q):
        if first[out_index[p]] < 0:
            first[out_index[p]] = p
        last[out_index[p]] = p
    F = np.empty((3, 3))
    C = np.empty((3, 3))  # cof(F) = ∂J/∂F
    U, Vr, A, Qs, work = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    sig, Ji, w3, wv = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    lams9 = np.empty(9)
    Q = np.empty((9, 9))  # row k: vec(Q_k), row-major vec
    wk = np.empty(nd)
    HF = np.empty((9, 9))
    T = np.empty((9, nd))
    O = np.empty((3, 3, 9))  # O[i, j] = vec(u_i v_jᵀ)
    s2 = 1.0 / math.sqrt(2.0)
    log4 = math.log(4.0)
    for p in range(q):
        G = grad[p]
        o = out_index[p]
        ic = 0.0
        for i in range(3):
            for j in range(3):
                acc = 0.0
                for a in range(k):
                    acc += x[nodes[p, a], i] * G[a, j]
                F[i, j] = acc
                ic += acc * acc
        mus = 4.0 / 3.0 * mu[p]
        lams = lam[p] + 5.0 / 6.0 * mu[p]
        alpha = 1.0 + 0.75 * mus / lams
        for i in range(3):  # columns: f1×f2, f2×f0, f0×f1
            i1, i2 = (i + 1) % 3, (i + 2) % 3
            C[i, 0] = F[i1, 1] * F[i2, 2] - F[i2, 1] * F[i1, 2]
            C[i, 1] = F[i1, 2] * F[i2, 0] - F[i2, 2] * F[i1, 0]
            C[i, 2] = F[i1, 0] * F[i2, 1] - F[i2, 0] * F[i1, 1]
        J = F[0, 0] * C[0, 0] + F[1, 0] * C[1, 0] + F[2, 0] * C[2, 0]
        rest = 0.5 * lams * (1.0 - alpha) ** 2 - 0.5 * mus * log4
        psi = 0.5 * mus * (ic - 3.0) + 0.5 * lams * (J - alpha) ** 2 - 0.5 * mus * math.log(ic + 1.0) - rest
        V = weight[p]
        energy[o] += V * psi
        if want < 1:
            continue
        d2 = 0.5 * mus * (1.0 - 1.0 / (ic + 1.0))  # ∂Ψ/∂I₂
        dJ = lams * (J - alpha)  # ∂Ψ/∂J
        d22 = 0.5 * mus / (ic + 1.0) ** 2  # ∂²Ψ/∂I₂²
        if first[o] == p:
            for c in range(nd):
                gout[o, c] = 0.0
        for a in range(k):
            for i in range(3):
                acc = 0.0
                for j in range(3):
                    acc += (2.0 * d2 * F[i, j] + dJ * C[i, j]) * G[a, j]
                gout[o, 3 * a + i] += V * acc
        if want < 2:
            continue
        Ho = hout[o]
        if first[o] == p:
            for r in range(nd):
                for c in range(nd):
                    Ho[r, c] = 0.0
        if not project:
            # exact: ∂²Ψ/∂F_ij∂F_kl = 2Ψ_I₂ δ_ik δ_jl + 4Ψ_I₂I₂ F_ij F_kl + λ' C_ij C_kl + Ψ_J ε_ikp ε_jlq F_pq
            for i in range(3):
                for j in range(3):
                    r = 3 * i + j
                    for kk in range(3):
                        for ll in range(3):
                            h = 4.0 * d22 * F[i, j] * F[kk, ll] + lams * C[i, j] * C[kk, ll]
                            if i == kk and j == ll:
                                h += 2.0 * d2
                            elif i != kk and j != ll:
                                pp, qq = 3 - i - kk, 3 - j - ll
                                sgn = (1.0 if kk == (i + 1) % 3 else -1.0) * (1.0 if ll == (j + 1) % 3 else -1.0)
                                h += dJ * sgn * F[pp, qq]
                            HF[r, 3 * kk + ll] = h
            _add_point_hessian(HF, G, V, T, Ho)
            continue
        _rotation_svd_into(F, U, sig, Vr, work, wv)
        Ji[0], Ji[1], Ji[2] = sig[1] * sig[2], sig[0] * sig[2], sig[0] * sig[1]
        for i in range(3):  # scaling block ∂²Ψ/∂σ²
            for j in range(3):
                A[i, j] = 4.0 * d22 * sig[i] * sig[j] + lams * Ji[i] * Ji[j]
                if i == j:
                    A[i, j] += 2.0 * d2
                else:
                    A[i, j] += dJ * sig[3 - i - j]
        _sym3_eig_into(A, w3, Qs)
        for i in range(3):
            for j in range(3):
                for r in range(3):
                    for c in range(3):
                        O[i, j, 3 * r + c] = U[r, i] * Vr[c, j]
        for m9 in range(3):
            lams9[m9] = w3[m9]
            for z in range(9):
                Q[m9, z] = Qs[0, m9] * O[0, 0, z] + Qs[1, m9] * O[1, 1, z] + Qs[2, m9] * O[2, 2, z]
        for pr in range(3):
            i, j = (0, 1) if pr == 0 else ((0, 2) if pr == 1 else (1, 2))
            kk = 3 - i - j
            lams9[3 + pr] = 2.0 * d2 + dJ * sig[kk]  # twist
            lams9[6 + pr] = 2.0 * d2 - dJ * sig[kk]  # flip
            for z in range(9):
                Q[3 + pr, z] = s2 * (O[i, j, z] - O[j, i, z])
                Q[6 + pr, z] = s2 * (O[i, j, z] + O[j, i, z])
        for m9 in range(9):
            lk = lams9[m9]
            if project and lk <= 0.0:
                if project != 2:
                    continue
                lk = -lk  # project == 2: absolute-value projection (Chen et al. 2024)
            # w = B vec(Q_k): w[(a,i)] = Σ_j Q_k[i, j] G[a, j]
            for a in range(k):
                for i in range(3):
                    wk[3 * a + i] = (Q[m9, 3 * i] * G[a, 0] + Q[m9, 3 * i + 1] * G[a, 1]
                                     + Q[m9, 3 * i + 2] * G[a, 2])
            c0 = V * lk
            for r in range(nd):  # the upper triangle; the lower one once the row's last point is in
                cr = c0 * wk[r]
                for c in range(r, nd):
                    Ho[r, c] += cr * wk[c]
        if last[o] == p:
            for r in range(nd):
                for c in range(r):
                    Ho[r, c] = Ho[c, r]
    for o in range(n_out):  # rows no point adds to
        if first[o] < 0:
            for c in range(gout.shape[1] if want >= 1 else 0):
                gout[o, c] = 0.0
            if want >= 2:
                for r in range(nd):
                    for c in range(nd):
                        hout[o, r, c] = 0.0
    return energy, gout, hout



@nb.njit(cache=True)
def viscous_point_kernel(x, x_prev, nodes, grad, weight, mu, lam, want, project, out_index, n_out):
    """The viscous term w D(F, F_prev) of quadrature points (materials.viscous_density), as snh_point_kernel sums
    the elastic one: energies (n_out,), gradients (n_out, 3k), Hessians (n_out, 3k, 3k) in x, F from x and F_prev
    from x_prev (n, 3); weight (q,) carries β/Δt.  With ΔE = E(F) − E(F_prev), S = 2μ ΔE + λ tr(ΔE) I:
    ∂D/∂F = F S and ∂²D/∂F_ij∂F_kl = δ_ik S_lj + μ F_il F_kj + μ (F Fᵀ)_ik δ_jl + λ F_ij F_kl.  All but the first
    term make 2μ ‖sym(Fᵀ dF)‖² + λ tr(Fᵀ dF)² ≥ 0; the first is tr(dF S dFᵀ), so the Hessian is projected to PSD by
    S's eigenvalues (``project`` 1: clamped at 0; 2: their absolute values; a 3×3 eigensystem, _sym3_eig_into)."""
    q = nodes.shape[0]
    k = nodes.shape[1]
    nd = 3 * k
    energy = np.zeros(n_out)
    gout = np.zeros((n_out if want >= 1 else 0, nd))
    hout = np.zeros((n_out if want >= 2 else 0, nd, nd))
    F, Fp, dE, S, FFt = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    Sp, A3, Q3, w3 = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty(3)
    HF = np.empty((9, 9))
    T = np.empty((9, nd))
    for p in range(q):
        G = grad[p]
        o = out_index[p]
        for i in range(3):
            for j in range(3):
                a1, a0 = 0.0, 0.0
                for a in range(k):
                    a1 += x[nodes[p, a], i] * G[a, j]
                    a0 += x_prev[nodes[p, a], i] * G[a, j]
                F[i, j], Fp[i, j] = a1, a0
        tr = 0.0
        for i in range(3):
            for j in range(3):
                c1, c0 = 0.0, 0.0
                for m in range(3):
                    c1 += F[m, i] * F[m, j]
                    c0 += Fp[m, i] * Fp[m, j]
                dE[i, j] = 0.5 * (c1 - c0)
            tr += dE[i, i]
        ee = 0.0
        for i in range(3):
            for j in range(3):
                ee += dE[i, j] * dE[i, j]
                S[i, j] = 2.0 * mu[p] * dE[i, j] + (lam[p] * tr if i == j else 0.0)
        V = weight[p]
        energy[o] += V * (mu[p] * ee + 0.5 * lam[p] * tr * tr)
        if want < 1:
            continue
        for a in range(k):  # ∂/∂x_{a,i} = V Σ_j (F S)_ij G_aj
            for i in range(3):
                acc = 0.0
                for j in range(3):
                    fs = F[i, 0] * S[0, j] + F[i, 1] * S[1, j] + F[i, 2] * S[2, j]
                    acc += fs * G[a, j]
                gout[o, 3 * a + i] += V * acc
        if want < 2:
            continue
        for i in range(3):
            for kk in range(3):
                FFt[i, kk] = F[i, 0] * F[kk, 0] + F[i, 1] * F[kk, 1] + F[i, 2] * F[kk, 2]
        for i in range(3):
            for j in range(3):
                for kk in range(3):
                    for ll in range(3):
                        h = mu[p] * F[i, ll] * F[kk, j] + lam[p] * F[i, j] * F[kk, ll]
                        if i == kk:
                            h += S[ll, j]
                        if j == ll:
                            h += mu[p] * FFt[i, kk]
                        HF[3 * i + j, 3 * kk + ll] = h
        if project:  # the S term δ_ik S_lj with S⁺ (S's eigenvalues clamped / absolute) in place of S
            A3[:, :] = S
            _sym3_eig_into(A3, w3, Q3)  # (destroys A3)
            for m in range(3):
                w3[m] = abs(w3[m]) if project == 2 else max(w3[m], 0.0)
            for i in range(3):
                for j in range(3):
                    Sp[i, j] = Q3[i, 0] * w3[0] * Q3[j, 0] + Q3[i, 1] * w3[1] * Q3[j, 1] + Q3[i, 2] * w3[2] * Q3[j, 2]
            for i in range(3):
                for ll in range(3):
                    for j in range(3):
                        HF[3 * i + j, 3 * i + ll] += Sp[ll, j] - S[ll, j]
        _add_point_hessian(HF, G, V, T, hout[o])
    return energy, gout, hout


def snh_kernel(x, tets, dm_inv, vol, mu, lam, want, project):
    """Stable Neo-Hookean per linear tet: energies V Ψ (m,), gradients (m, 12) and Hessians (m, 12, 12)
    w.r.t. x_e (:func:`snh_point_kernel` with one point per tet, G from Dm⁻¹).  x (n, 3),
    tets (m, 4), dm_inv (m, 3, 3), vol (m,), mu, lam (m,)."""
    tets = np.ascontiguousarray(tets, np.int64)
    return snh_point_kernel(np.ascontiguousarray(x, np.float64), tets, shape_gradients(np.asarray(dm_inv, np.float64)),
                            np.ascontiguousarray(vol, np.float64), np.ascontiguousarray(mu, np.float64),
                            np.ascontiguousarray(lam, np.float64), want, int(project), np.arange(len(tets)), len(tets))


# =========================================================================== JAX twin
def _point_energy(material):
    psi = energy_density(material)

    def f(xe, g, w, mu, lam):
        """w Ψ(F) of one quadrature point from its element's nodes xe (k, 3) and shape gradients g (k, 3)."""
        F = xe.T @ g
        return w * psi(F, mu, lam)

    return f


_element_energy = _point_energy  # one point per linear tet: V Ψ(F)


def _project_psd(h, how=True):
    """Clamp the eigenvalues of a symmetric matrix at 0 (how="abs": take their absolute values)."""
    w, q = jnp.linalg.eigh(0.5 * (h + h.T))
    return (q * (jnp.abs(w) if how == "abs" else jnp.maximum(w, 0.0))) @ q.T


def _b_matrix(g):
    """B (9, 3k): ∂F_ij/∂x_{a,k} = δ_ik G_aj for shape gradients g (k, 3) (row-major vec F)."""
    return jnp.einsum("ik,aj->ijak", jnp.eye(3), g).reshape(9, 3 * g.shape[0])


def _point_terms_impl(x, nodes, g, weight, mu, lam, material, project):
    """Per point: energies (q,), gradients (q, 3k), Hessians (q, 3k, 3k) (Bᵀ proj(∂²Ψ/∂F²) B w)."""
    psi = energy_density(material)
    xe = x[nodes]  # (q, k, 3)
    nd = 3 * nodes.shape[1]
    fe = _point_energy(material)
    energy = jax.vmap(fe)(xe, g, weight, mu, lam)
    grad = jax.vmap(jax.grad(fe))(xe, g, weight, mu, lam).reshape(-1, nd)

    def hess_one(xe1, g1, v, m1, l1):
        F = xe1.T @ g1
        hf = jax.hessian(psi)(F, m1, l1).reshape(9, 9)  # row-major vec(F)
        if project:
            hf = _project_psd(hf, project)
        B = _b_matrix(g1)
        return v * B.T @ hf @ B

    hess = jax.vmap(hess_one)(xe, g, weight, mu, lam)
    return energy, grad, hess


_point_terms_jit = jax.jit(_point_terms_impl, static_argnums=(6, 7))


def _point_eg_impl(x, nodes, g, weight, mu, lam, material):
    xe = x[nodes]
    fe = _point_energy(material)
    energy = jax.vmap(fe)(xe, g, weight, mu, lam)
    grad = jax.vmap(jax.grad(fe))(xe, g, weight, mu, lam).reshape(-1, 3 * nodes.shape[1])
    return energy, grad


_point_eg_jit = jax.jit(_point_eg_impl, static_argnums=(6,))


def point_terms_jax(x, nodes, grad, weight, mu, lam, material: str, project: bool = True):
    """JAX twin of :func:`snh_point_kernel` for any material, per quadrature point (not summed):
    (energies (q,), gradients (q, 3k), Hessians (q, 3k, 3k)); the Hessian is Bᵀ proj(∂²Ψ/∂F²) B w
    with proj an eigenvalue clamp (project=True), |eigenvalues| (project="abs") or none (False)."""
    return _point_terms_jit(jnp.asarray(x), jnp.asarray(nodes), jnp.asarray(grad), jnp.asarray(weight),
                            jnp.asarray(mu), jnp.asarray(lam), material, project)


def element_terms_jax(x, tets, dm_inv, vol, mu, lam, material: str, project: bool = True):
    """JAX twin of :func:`snh_kernel` for any material, per linear tet with Dm⁻¹: (energies (m,),
    gradients (m, 12), Hessians (m, 12, 12))."""
    dm_inv = jnp.asarray(dm_inv)
    g = jnp.concatenate([-jnp.sum(dm_inv, axis=1, keepdims=True), dm_inv], axis=1)  # (m, 4, 3)
    return point_terms_jax(x, tets, g, vol, mu, lam, material, project)


def _point_damping(xe, xpe, g, w, mu, lam):
    """w D(F, F_prev) of one quadrature point (materials.viscous_density) from its element's nodes now and before."""
    return w * viscous_density(xe.T @ g, xpe.T @ g, mu, lam)


def _damping_terms_impl(x, x_prev, nodes, g, weight, mu, lam, want, project):
    """Per point: energies (q,), gradients (q, 3k), and with want = HESSIAN Hessians (q, 3k, 3k) in x of
    w D(F(x), F(x_prev)): Bᵀ (∂²D/∂F²) B w, projected as viscous_point_kernel projects it."""
    xe, xpe = x[nodes], x_prev[nodes]
    nd = 3 * nodes.shape[1]
    energy = jax.vmap(_point_damping)(xe, xpe, g, weight, mu, lam)
    grad = jax.vmap(jax.grad(_point_damping))(xe, xpe, g, weight, mu, lam).reshape(-1, nd)
    if want < HESSIAN:
        return energy, grad, jnp.zeros((0, nd, nd))

    def hess_one(xe1, xp1, g1, v, m1, l1):
        F, Fp = xe1.T @ g1, xp1.T @ g1
        hf = jax.hessian(lambda FF: viscous_density(FF, Fp, m1, l1))(F).reshape(9, 9)
        if project:  # S's eigenvalues clamped (or absolute) in the term δ_ik S_lj (viscous_point_kernel)
            eye = jnp.eye(3)
            dE = 0.5 * (F.T @ F - Fp.T @ Fp)
            S = 2.0 * m1 * dE + l1 * jnp.trace(dE) * eye
            w, Q = jnp.linalg.eigh(S)
            Sp = (Q * (jnp.abs(w) if project == "abs" else jnp.maximum(w, 0.0))) @ Q.T
            hf = hf + jnp.kron(eye, Sp - S)
        B = _b_matrix(g1)
        return v * B.T @ hf @ B

    return energy, grad, jax.vmap(hess_one)(xe, xpe, g, weight, mu, lam)


_damping_terms_jit = jax.jit(_damping_terms_impl, static_argnums=(7, 8))


def point_damping_terms(x, x_prev, nodes, grad, weight, mu, lam, want: int = HESSIAN, project: bool = True,
                        out_index: np.ndarray | None = None, n_out: int | None = None, backend: str = "auto"):
    """(energies, gradients (·, 3k), Hessians (·, 3k, 3k)) in x of the viscous terms w_q D(F_q(x), F_q(x_prev))
    of quadrature points (materials.viscous_density; weight (q,) carries β/Δt), in numpy, summed into rows
    out_index (q,) of n_out (default one row per point); the Hessian projected as :func:`point_terms`'s.
    backend "auto"/"numba": :func:`viscous_point_kernel`; "jax": its JAX twin (autodiff of the density)."""
    n_out = len(nodes) if out_index is None else int(n_out)
    if backend in ("auto", "numba"):
        idx = np.arange(len(nodes)) if out_index is None else out_index
        return viscous_point_kernel(np.ascontiguousarray(x, np.float64), np.ascontiguousarray(x_prev, np.float64),
                                    np.ascontiguousarray(nodes, np.int64), np.ascontiguousarray(grad, np.float64),
                                    np.ascontiguousarray(weight, np.float64), np.ascontiguousarray(mu, np.float64),
                                    np.ascontiguousarray(lam, np.float64), int(want),
                                    2 if project == "abs" else int(bool(project)),
                                    np.ascontiguousarray(idx, np.int64), n_out)
    e, g, h = _damping_terms_jit(jnp.asarray(x), jnp.asarray(x_prev), jnp.asarray(nodes), jnp.asarray(grad),
                                 jnp.asarray(weight), jnp.asarray(mu), jnp.asarray(lam), int(want), project)
    out = [_segment_sum(np.asarray(a), out_index, n_out) for a in (e, g)]
    return out[0], out[1], (_segment_sum(np.asarray(h), out_index, n_out) if want >= HESSIAN else np.asarray(h))


def _segment_sum(values: np.ndarray, index: np.ndarray | None, n_out: int) -> np.ndarray:
    """Σ of rows of values (q, ...) with the same index (q,) -> (n_out, ...); index None: as they are."""
    if index is None:
        return values
    q = len(index)
    if q and q % n_out == 0 and q // n_out > 0:
        per = q // n_out
        if np.array_equal(index, np.repeat(np.arange(n_out), per)):  # element-major, equal counts
            return values.reshape((n_out, per) + values.shape[1:]).sum(axis=1)
    out = np.zeros((n_out,) + values.shape[1:])
    np.add.at(out, index, values)
    return out


def point_terms(x, nodes, grad, weight, mu, lam, material: str, want: int = HESSIAN, project: bool = True,
                backend: str = "auto", out_index: np.ndarray | None = None, n_out: int | None = None):
    """(energies, gradients (·, 3k), Hessians (·, 3k, 3k)) of quadrature points in numpy, summed into
    rows out_index (q,) of n_out (default: one row per point): numba for stable Neo-Hookean (backend
    "auto"/"numba"), else the JAX twin (backend "jax", and every other material).
    nodes (q, k), grad (q, k, 3) 1/m, weight (q,) m³, mu, lam (q,) Pa."""
    if backend == "numba" and material != "stable_neohookean":
        raise ValueError(f"the numba kernel covers stable_neohookean only, not {material!r}")
    nodes = np.asarray(nodes)
    nd = 3 * nodes.shape[1]
    if material == "stable_neohookean" and backend in ("auto", "numba"):
        code = 2 if project == "abs" else int(bool(project))
        if out_index is None:
            out_index, n_out = np.arange(len(nodes)), len(nodes)
        return snh_point_kernel(np.ascontiguousarray(x, np.float64), np.ascontiguousarray(nodes, np.int64),
                                np.ascontiguousarray(grad, np.float64), np.ascontiguousarray(weight, np.float64),
                                np.ascontiguousarray(mu, np.float64), np.ascontiguousarray(lam, np.float64),
                                want, code, np.ascontiguousarray(out_index, np.int64), int(n_out))
    n_out = len(nodes) if out_index is None else int(n_out)
    args = (jnp.asarray(x), jnp.asarray(nodes), jnp.asarray(grad), jnp.asarray(weight), jnp.asarray(mu),
            jnp.asarray(lam), material)
    if want < HESSIAN:
        e, g = _point_eg_jit(*args)
        return (_segment_sum(np.asarray(e), out_index, n_out), _segment_sum(np.asarray(g), out_index, n_out),
                np.empty((0, nd, nd)))
    e, g, h = _point_terms_jit(*args, project)
    return tuple(_segment_sum(np.asarray(a), out_index, n_out) for a in (e, g, h))


def element_terms(x, tets, dm_inv, vol, mu, lam, material: str, want: int = HESSIAN, project: bool = True,
                  backend: str = "auto"):
    """Per linear tet (energies, gradients (m, 12), Hessians (m, 12, 12)) in numpy from Dm⁻¹ and V:
    :func:`point_terms` with one point per tet."""
    return point_terms(x, tets, shape_gradients(np.asarray(dm_inv, np.float64)), vol, mu, lam, material, want,
                       project, backend)
