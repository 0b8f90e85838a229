"""Fused binding + EWA projection (numba, forward and hand-written backward), for pinhole cameras.

Per Gaussian g with barycentric β (4,) in its host element and a rest-frame covariance factor L (3×3)
(Σ₀ = L Lᵀ), in one compiled loop:

    linear tets:     μ = Σₖ βₖ pₖ (corners p₀..p₃),  F = D_s D_m⁻¹
    quadratic tets:  μ = Σ_a N_a(β) x_a,  F = D_x J⁻¹ with D_x = Σ_a x_a ⊗ ∂N_a/∂ξ and J = Σ_a X_a ⊗ ∂N_a/∂ξ
                     at β, X the rest nodes — the quadratic map at the Gaussian's own location
    M = F L,  x_c = R_c μ + t,  (xₙ, yₙ) = (x_c/z, y_c/z),  u = K₂ (xₙ, yₙ) + c
    J R_c rows: K₂ [(R_c0 − x̄ₙ R_c2)/z ; (R_c1 − ȳₙ R_c2)/z]   (x̄ₙ, ȳₙ clamped to 1.3× the image extent)
    T = J R_c M (2×3),  Σ₂ = T Tᵀ + 0.3 I,  conic = Σ₂⁻¹

:func:`project_bound` takes β and L as given (differentiable in positions, β and L; ``ImageLoss`` after a
rebind); :func:`bind_project` first maps the fitted parameters β = softmax(bary_logits),
L = R(q/|q|) diag(exp(log_scales)) (``BoundGaussians``), in numba too.  One kernel serves both element
orders: only the element geometry (:func:`_element_p1` / :func:`_element_p2`) and its backward differ.

The same maths as ``gaussians.bound_geometry`` (``BoundGaussians.centres`` / ``covariance_factors``)
and ``projection.project_gaussians(factors=...)`` in torch, which stay the reference twin
(tests/test_render_gaussians.py and tests/test_render_project_bound.py hold this module to it, forward
and backward).  The torch version costs about a hundred small tensor ops per view; this one loop
replaces them.  Distorted cameras use the torch path.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np
import torch

from stages.render.projection import FOV_MARGIN, LOW_PASS_PX2, NEAR_M, CameraTensors


def camera_array(cam: CameraTensors, near: float = NEAR_M) -> np.ndarray:
    """(24,) float64: fx, skew, cx, fy, cy, R (9), t (3), clamp x, clamp y, cull x, cull y, near, 0.3."""
    K = cam.K.detach().double().numpy()
    ex, ey = cam.normalised_extent()
    return np.concatenate([[K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]],
                           cam.R.detach().double().numpy().ravel(), cam.t.detach().double().numpy(),
                           [FOV_MARGIN * ex, FOV_MARGIN * ey, 1.5 * ex + 0.1, 1.5 * ey + 0.1, near,
                            LOW_PASS_PX2]])


CHUNK = 256
"""Gaussians per parallel work item (scratch arrays are allocated once per item)."""


@nb.njit(inline="always")
def _mm(A, B, out):  # pragma: no cover - compiled
    """out = A B for 3×3 arrays (no BLAS call, no allocation)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@nb.njit(inline="always")
def _rotmat(q0, q1, q2, q3, R):  # pragma: no cover - compiled
    n = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    w, x, y, z = q0 / n, q1 / n, q2 / n, q3 / n
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - w * z)
    R[0, 2] = 2 * (x * z + w * y)
    R[1, 0] = 2 * (x * y + w * z)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - w * x)
    R[2, 0] = 2 * (x * z - w * y)
    R[2, 1] = 2 * (y * z + w * x)
    R[2, 2] = 1 - 2 * (x * x + y * y)
    return n, w, x, y, z


# =========================================================================== parameters → (β, L)
@nb.njit(parallel=True, cache=True)
def _params_forward(bl, ls, rot, beta, RS, sc):  # pragma: no cover - compiled
    """β = softmax(bary_logits) (G, 4), s = exp(log_scales) (G, 3), L = R(q/|q|) diag(s) (G, 3, 3)."""
    for g in nb.prange(bl.shape[0]):
        mx = bl[g, 0]
        for k in range(1, 4):
            mx = max(mx, bl[g, k])
        sb = 0.0
        for k in range(4):
            beta[g, k] = math.exp(bl[g, k] - mx)
            sb += beta[g, k]
        for k in range(4):
            beta[g, k] /= sb
        Rq = np.empty((3, 3))
        _rotmat(rot[g, 0], rot[g, 1], rot[g, 2], rot[g, 3], Rq)
        for j in range(3):
            sc[g, j] = math.exp(ls[g, j])
            for i in range(3):
                RS[g, i, j] = Rq[i, j] * sc[g, j]


@nb.njit(parallel=True, cache=True)
def _params_backward(rot, beta, sc, g_beta, g_RS, g_bl, g_ls, g_rot):  # pragma: no cover - compiled
    """Backward of :func:`_params_forward`: ∂L/∂β (G, 4), ∂L/∂(R S) (G, 3, 3) → the gradients of bary_logits,
    log-scales and the (unnormalised) quaternion."""
    for g in nb.prange(beta.shape[0]):
        sgb = 0.0
        for k in range(4):
            sgb += beta[g, k] * g_beta[g, k]
        for k in range(4):
            g_bl[g, k] = beta[g, k] * (g_beta[g, k] - sgb)
        Rq = np.empty((3, 3))
        gR = np.empty((3, 3))
        qn, qw, qx, qy, qz = _rotmat(rot[g, 0], rot[g, 1], rot[g, 2], rot[g, 3], Rq)
        for j in range(3):
            gs = 0.0
            for i in range(3):
                gR[i, j] = g_RS[g, i, j] * sc[g, j]
                gs += g_RS[g, i, j] * Rq[i, j]
            g_ls[g, j] = gs * sc[g, j]
        gw = 2 * (-qz * gR[0, 1] + qy * gR[0, 2] + qz * gR[1, 0] - qx * gR[1, 2] - qy * gR[2, 0]
                  + qx * gR[2, 1])
        gx = 2 * (qy * gR[0, 1] + qz * gR[0, 2] + qy * gR[1, 0] - 2 * qx * gR[1, 1] - qw * gR[1, 2]
                  + qz * gR[2, 0] + qw * gR[2, 1] - 2 * qx * gR[2, 2])
        gy = 2 * (-2 * qy * gR[0, 0] + qx * gR[0, 1] + qw * gR[0, 2] + qx * gR[1, 0] + qz * gR[1, 2]
                  - qw * gR[2, 0] + qz * gR[2, 1] - 2 * qy * gR[2, 2])
        gz = 2 * (-2 * qz * gR[0, 0] - qw * gR[0, 1] + qx * gR[0, 2] + qw * gR[1, 0] - 2 * qz * gR[1, 1]
                  + qy * gR[1, 2] + qx * gR[2, 0] + qy * gR[2, 1])
        dot = qw * gw + qx * gx + qy * gy + qz * gz
        g_rot[g, 0] = (gw - qw * dot) / qn
        g_rot[g, 1] = (gx - qx * dot) / qn
        g_rot[g, 2] = (gy - qy * dot) / qn
        g_rot[g, 3] = (gz - qz * dot) / qn


# =========================================================================== element geometry
_EDGE_A = np.array([0, 1, 0, 0, 1, 2])
_EDGE_B = np.array([1, 2, 2, 3, 3, 3])


@nb.njit(inline="always")
def _inv3(A, out):  # pragma: no cover - compiled
    """out = A⁻¹ for a 3×3 array (cofactors / det)."""
    c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
    c01 = A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]
    c02 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
    det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
    inv = 1.0 / det
    out[0, 0] = c00 * inv
    out[1, 0] = c01 * inv
    out[2, 0] = c02 * inv
    out[0, 1] = (A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2]) * inv
    out[1, 1] = (A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]) * inv
    out[2, 1] = (A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1]) * inv
    out[0, 2] = (A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]) * inv
    out[1, 2] = (A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]) * inv
    out[2, 2] = (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) * inv


@nb.njit(inline="always")
def _element_p1(g, x, hv, dm_inv, beta, P, Ds, F):  # pragma: no cover - compiled
    """Linear tet: corners P (4, 3), D_s, F = D_s D_m⁻¹; returns μ = Σ βₖ pₖ."""
    m0 = 0.0
    m1 = 0.0
    m2 = 0.0
    for k in range(4):
        v = hv[g, k]
        P[k, 0] = x[v, 0]
        P[k, 1] = x[v, 1]
        P[k, 2] = x[v, 2]
        m0 += beta[g, k] * P[k, 0]
        m1 += beta[g, k] * P[k, 1]
        m2 += beta[g, k] * P[k, 2]
    for j in range(3):
        for d in range(3):
            Ds[d, j] = P[j + 1, d] - P[0, d]
    _mm(Ds, dm_inv[g], F)
    return m0, m1, m2


@nb.njit(inline="always")
def _element_back_p1(g, P, beta, dm_inv, gF, gmu0, gmu1, gmu2, gDs, g_corners, g_beta):  # pragma: no cover
    """Backward of :func:`_element_p1`: F = D_s D_m⁻¹ → ∂L/∂D_s = ∂L/∂F D_m⁻ᵀ; μ = Σ βₖ pₖ."""
    Dmi = dm_inv[g]
    for i in range(3):
        for j in range(3):
            gDs[i, j] = gF[i, 0] * Dmi[j, 0] + gF[i, 1] * Dmi[j, 1] + gF[i, 2] * Dmi[j, 2]
    for j in range(3):
        for d in range(3):
            g_corners[g, j + 1, d] += gDs[d, j]
            g_corners[g, 0, d] -= gDs[d, j]
    for k in range(4):
        g_beta[g, k] = P[k, 0] * gmu0 + P[k, 1] * gmu1 + P[k, 2] * gmu2
        g_corners[g, k, 0] += beta[g, k] * gmu0
        g_corners[g, k, 1] += beta[g, k] * gmu1
        g_corners[g, k, 2] += beta[g, k] * gmu2


@nb.njit(inline="always")
def _element_p2(g, x, hv, xr, beta, N, dNx, Dx, J, Ji, F):  # pragma: no cover - compiled
    """Quadratic tet (rest nodes xr (G, 10, 3)): N_a(β), ∂N_a/∂ξ (10, 3), D_x = Σ x_a ⊗ ∂N_a/∂ξ,
    J = Σ X_a ⊗ ∂N_a/∂ξ, F = D_x J⁻¹; returns μ = Σ N_a x_a."""
    # ∂N/∂L (10, 4) is sparse: corner a has 4β_a − 1 at L_a; edge (a, b) has 4β_b at L_a and 4β_a at L_b;
    # ∂N/∂ξ_j = ∂N/∂L_{j+1} − ∂N/∂L_0
    for a in range(10):
        for j in range(3):
            dNx[a, j] = 0.0
    for a in range(4):
        N[a] = beta[g, a] * (2.0 * beta[g, a] - 1.0)
        d = 4.0 * beta[g, a] - 1.0
        if a == 0:
            for j in range(3):
                dNx[0, j] -= d
        else:
            dNx[a, a - 1] += d
    for e in range(6):
        a, b = _EDGE_A[e], _EDGE_B[e]
        N[4 + e] = 4.0 * beta[g, a] * beta[g, b]
        da, db = 4.0 * beta[g, b], 4.0 * beta[g, a]  # ∂N/∂L_a, ∂N/∂L_b
        if a == 0:
            for j in range(3):
                dNx[4 + e, j] -= da
        else:
            dNx[4 + e, a - 1] += da
        dNx[4 + e, b - 1] += db  # b ≥ 1 for every edge
    m0 = 0.0
    m1 = 0.0
    m2 = 0.0
    for i in range(3):
        for j in range(3):
            Dx[i, j] = 0.0
            J[i, j] = 0.0
    for a in range(10):
        v = hv[g, a]
        m0 += N[a] * x[v, 0]
        m1 += N[a] * x[v, 1]
        m2 += N[a] * x[v, 2]
        for i in range(3):
            for j in range(3):
                Dx[i, j] += x[v, i] * dNx[a, j]
                J[i, j] += xr[g, a, i] * dNx[a, j]
    _inv3(J, Ji)
    _mm(Dx, Ji, F)
    return m0, m1, m2


@nb.njit(inline="always")
def _element_back_p2(g, x, hv, xr, beta, N, dNx, Ji, F, gF, gmu0, gmu1, gmu2, gDx, gJ, gdN, g_corners,
                     g_beta):  # pragma: no cover - compiled
    """Backward of :func:`_element_p2`: F = D_x J⁻¹ → ∂L/∂D_x = gF J⁻ᵀ, ∂L/∂J = −Fᵀ ∂L/∂D_x; both are
    linear in ∂N/∂ξ, which is linear in β; μ = Σ N_a(β) x_a."""
    for i in range(3):
        for j in range(3):
            gDx[i, j] = gF[i, 0] * Ji[j, 0] + gF[i, 1] * Ji[j, 1] + gF[i, 2] * Ji[j, 2]
    for i in range(3):
        for j in range(3):
            gJ[i, j] = -(F[0, i] * gDx[0, j] + F[1, i] * gDx[1, j] + F[2, i] * gDx[2, j])
    for a in range(10):
        v = hv[g, a]
        gN = x[v, 0] * gmu0 + x[v, 1] * gmu1 + x[v, 2] * gmu2
        for d in range(3):
            g_corners[g, a, d] = (N[a] * (gmu0 if d == 0 else (gmu1 if d == 1 else gmu2))
                                  + gDx[d, 0] * dNx[a, 0] + gDx[d, 1] * dNx[a, 1] + gDx[d, 2] * dNx[a, 2])
        for j in range(3):  # ∂L/∂(∂N_a/∂ξ_j)
            gdN[j] = (x[v, 0] * gDx[0, j] + x[v, 1] * gDx[1, j] + x[v, 2] * gDx[2, j]
                      + xr[g, a, 0] * gJ[0, j] + xr[g, a, 1] * gJ[1, j] + xr[g, a, 2] * gJ[2, j])
        # ∂L/∂(∂N_a/∂L_c): c = 0 gets −Σ_j gdN_j, c ≥ 1 gets gdN_{c−1}; then ∂N/∂L is linear in β
        gsum = gdN[0] + gdN[1] + gdN[2]
        if a < 4:
            gD = -gsum if a == 0 else gdN[a - 1]
            g_beta[g, a] += gN * (4.0 * beta[g, a] - 1.0) + 4.0 * gD
        else:
            e = a - 4
            ea, eb = _EDGE_A[e], _EDGE_B[e]
            gDa = -gsum if ea == 0 else gdN[ea - 1]
            gDb = gdN[eb - 1]
            g_beta[g, ea] += gN * 4.0 * beta[g, eb] + 4.0 * gDb
            g_beta[g, eb] += gN * 4.0 * beta[g, ea] + 4.0 * gDa


# =========================================================================== projection
@nb.njit(inline="always")
def _project_one(g, m0, m1, m2, M, cam, Rc, jw0, jw1, means2d, conics, depths, visible):  # pragma: no cover
    """EWA projection of Gaussian g (centre μ, factor M) into the camera: writes its outputs."""
    fx, sk, cx, fy, cy = cam[0], cam[1], cam[2], cam[3], cam[4]
    lx, ly, vx, vy, near, lp = cam[17], cam[18], cam[19], cam[20], cam[21], cam[22]
    p0 = Rc[0, 0] * m0 + Rc[0, 1] * m1 + Rc[0, 2] * m2 + cam[14]
    p1 = Rc[1, 0] * m0 + Rc[1, 1] * m1 + Rc[1, 2] * m2 + cam[15]
    z = Rc[2, 0] * m0 + Rc[2, 1] * m1 + Rc[2, 2] * m2 + cam[16]
    depths[g] = z
    if not z > near:
        visible[g] = False
        means2d[g, 0] = 0.0
        means2d[g, 1] = 0.0
        conics[g, 0] = 0.0
        conics[g, 1] = 0.0
        conics[g, 2] = 0.0
        return
    xn, yn = p0 / z, p1 / z
    vis = abs(xn) <= vx and abs(yn) <= vy
    xc = min(max(xn, -lx), lx)
    yc = min(max(yn, -ly), ly)
    for d in range(3):
        n0 = (Rc[0, d] - xc * Rc[2, d]) / z
        n1 = (Rc[1, d] - yc * Rc[2, d]) / z
        jw0[d] = fx * n0 + sk * n1
        jw1[d] = fy * n1
    a = lp
    b = 0.0
    c = lp
    for j in range(3):
        t0 = jw0[0] * M[0, j] + jw0[1] * M[1, j] + jw0[2] * M[2, j]
        t1 = jw1[0] * M[0, j] + jw1[1] * M[1, j] + jw1[2] * M[2, j]
        a += t0 * t0
        b += t0 * t1
        c += t1 * t1
    det = a * c - b * b
    vis = vis and det > 0
    if not vis:
        det = 1.0
    means2d[g, 0] = fx * xn + sk * yn + cx
    means2d[g, 1] = fy * yn + cy
    conics[g, 0] = c / det
    conics[g, 1] = -b / det
    conics[g, 2] = a / det
    visible[g] = vis


@nb.njit(inline="always")
def _screen_terms(xn, yn, z, M, cam, Rc, n0, n1, jw0, jw1, t0, t1):  # pragma: no cover
    """The terms of :func:`_project_one`'s Σ₂ = T Tᵀ + lp I that its derivatives need, at normalised coordinates
    (xn, yn) and depth z (m) of a Gaussian with factor M (3, 3): fills n0, n1 (rows of ∂(x/z, y/z)/∂p at the clamped
    coordinates, per unit of R_c), jw0, jw1 (J R_c) and t0, t1 (T = J R_c M), each (3,); returns
    (x_free, y_free — xn, yn inside the clamp —, a, b, c of Σ₂ = [[a, b], [b, c]], det)."""
    fx, sk, fy = cam[0], cam[1], cam[3]
    lx, ly, lp = cam[17], cam[18], cam[22]
    x_free = -lx < xn < lx
    y_free = -ly < yn < ly
    xc = min(max(xn, -lx), lx)
    yc = min(max(yn, -ly), ly)
    for d in range(3):
        n0[d] = (Rc[0, d] - xc * Rc[2, d]) / z
        n1[d] = (Rc[1, d] - yc * Rc[2, d]) / z
        jw0[d] = fx * n0[d] + sk * n1[d]
        jw1[d] = fy * n1[d]
    a = lp
    b = 0.0
    c = lp
    for j in range(3):
        t0[j] = jw0[0] * M[0, j] + jw0[1] * M[1, j] + jw0[2] * M[2, j]
        t1[j] = jw1[0] * M[0, j] + jw1[1] * M[1, j] + jw1[2] * M[2, j]
        a += t0[j] * t0[j]
        b += t0[j] * t1[j]
        c += t1[j] * t1[j]
    return x_free, y_free, a, b, c, a * c - b * b


@nb.njit(inline="always")
def _project_back(g, m0, m1, m2, M, cam, Rc, n0, n1, jw0, jw1, t0, t1, gM, g_m2d, g_con):  # pragma: no cover
    """Backward of :func:`_project_one` for a visible Gaussian: fills gM = ∂L/∂M, returns ∂L/∂μ."""
    fx, sk, fy = cam[0], cam[1], cam[3]
    p0 = Rc[0, 0] * m0 + Rc[0, 1] * m1 + Rc[0, 2] * m2 + cam[14]
    p1 = Rc[1, 0] * m0 + Rc[1, 1] * m1 + Rc[1, 2] * m2 + cam[15]
    z = Rc[2, 0] * m0 + Rc[2, 1] * m1 + Rc[2, 2] * m2 + cam[16]
    xn, yn = p0 / z, p1 / z
    x_free, y_free, a, b, c, det = _screen_terms(xn, yn, z, M, cam, Rc, n0, n1, jw0, jw1, t0, t1)
    # ---- conic = (c, −b, a)/det → (a, b, c)
    gA, gB, gC = g_con[g, 0], g_con[g, 1], g_con[g, 2]
    d2 = det * det
    ga = gA * (-c * c / d2) + gB * (b * c / d2) + gC * (1 / det - a * c / d2)
    gb = gA * (2 * b * c / d2) + gB * (-1 / det - 2 * b * b / d2) + gC * (2 * a * b / d2)
    gc = gA * (1 / det - a * c / d2) + gB * (a * b / d2) + gC * (-a * a / d2)
    # ---- T = (J R_c) M; gT rows gt0 = 2 ga t0 + gb t1, gt1 = 2 gc t1 + gb t0
    g_xc = 0.0
    g_yc = 0.0
    g_z = 0.0
    for k in range(3):
        gjw0 = 0.0
        gjw1 = 0.0
        for j in range(3):
            gt0 = 2 * ga * t0[j] + gb * t1[j]
            gt1 = 2 * gc * t1[j] + gb * t0[j]
            gjw0 += M[k, j] * gt0
            gjw1 += M[k, j] * gt1
            gM[k, j] = jw0[k] * gt0 + jw1[k] * gt1
        gn0 = fx * gjw0
        gn1 = sk * gjw0 + fy * gjw1
        g_xc -= gn0 * Rc[2, k] / z
        g_yc -= gn1 * Rc[2, k] / z
        g_z -= (n0[k] * gn0 + n1[k] * gn1) / z
    gu, gv = g_m2d[g, 0], g_m2d[g, 1]
    g_xn = fx * gu + (g_xc if x_free else 0.0)
    g_yn = sk * gu + fy * gv + (g_yc if y_free else 0.0)
    gp0 = g_xn / z
    gp1 = g_yn / z
    gp2 = g_z - (g_xn * xn + g_yn * yn) / z
    gmu0 = Rc[0, 0] * gp0 + Rc[1, 0] * gp1 + Rc[2, 0] * gp2
    gmu1 = Rc[0, 1] * gp0 + Rc[1, 1] * gp1 + Rc[2, 1] * gp2
    gmu2 = Rc[0, 2] * gp0 + Rc[1, 2] * gp1 + Rc[2, 2] * gp2
    return gmu0, gmu1, gmu2


# =========================================================================== the kernels
@nb.njit(parallel=True, cache=True)
def _forward(x, hv, shape, beta, RS, cam, means2d, conics, depths, visible):  # pragma: no cover - compiled
    """means2d, conics, depths, visible of every Gaussian; ``shape`` is D_m⁻¹ (G, 3, 3) for linear tets
    (hv (G, 4)) or the rest nodes (G, 10, 3) for quadratic ones (hv (G, 10))."""
    Rc = cam[5:14].reshape(3, 3)
    n = hv.shape[0]
    quadratic = hv.shape[1] == 10
    for chunk in nb.prange((n + CHUNK - 1) // CHUNK):
        P = np.empty((4, 3))
        Ds = np.empty((3, 3))
        N = np.empty(10)
        dNx = np.empty((10, 3))
        J = np.empty((3, 3))
        Ji = np.empty((3, 3))
        F = np.empty((3, 3))
        M = np.empty((3, 3))
        jw0 = np.empty(3)
        jw1 = np.empty(3)
        for g in range(chunk * CHUNK, min(n, (chunk + 1) * CHUNK)):
            if quadratic:
                m0, m1, m2 = _element_p2(g, x, hv, shape, beta, N, dNx, Ds, J, Ji, F)
            else:
                m0, m1, m2 = _element_p1(g, x, hv, shape, beta, P, Ds, F)
            _mm(F, RS[g], M)
            _project_one(g, m0, m1, m2, M, cam, Rc, jw0, jw1, means2d, conics, depths, visible)


@nb.njit(parallel=True, cache=True)
def _backward(x, hv, shape, beta, RS, cam, visible, g_m2d, g_con, g_corners, g_beta,
              g_RS):  # pragma: no cover - compiled
    """Backward of :func:`_forward`: ∂L/∂(element nodes) (G, k, 3), ∂L/∂β (G, 4), ∂L/∂L (G, 3, 3); zero for
    Gaussians that are not visible."""
    Rc = cam[5:14].reshape(3, 3)
    n = hv.shape[0]
    k_nodes = hv.shape[1]
    quadratic = k_nodes == 10
    for chunk in nb.prange((n + CHUNK - 1) // CHUNK):
        P = np.empty((4, 3))
        Ds = np.empty((3, 3))
        N = np.empty(10)
        dNx = np.empty((10, 3))
        J = np.empty((3, 3))
        Ji = np.empty((3, 3))
        F = np.empty((3, 3))
        M = np.empty((3, 3))
        n0 = np.empty(3)
        n1 = np.empty(3)
        jw0 = np.empty(3)
        jw1 = np.empty(3)
        t0 = np.empty(3)
        t1 = np.empty(3)
        gM = np.empty((3, 3))
        gF = np.empty((3, 3))
        gD = np.empty((3, 3))
        gJ = np.empty((3, 3))
        gdN = np.empty(3)
        for g in range(chunk * CHUNK, min(n, (chunk + 1) * CHUNK)):
            for k in range(4):
                g_beta[g, k] = 0.0
            for k in range(k_nodes):
                for d in range(3):
                    g_corners[g, k, d] = 0.0
            for i in range(3):
                for j in range(3):
                    g_RS[g, i, j] = 0.0
            if not visible[g]:
                continue
            if quadratic:
                m0, m1, m2 = _element_p2(g, x, hv, shape, beta, N, dNx, Ds, J, Ji, F)
            else:
                m0, m1, m2 = _element_p1(g, x, hv, shape, beta, P, Ds, F)
            _mm(F, RS[g], M)
            gmu0, gmu1, gmu2 = _project_back(g, m0, m1, m2, M, cam, Rc, n0, n1, jw0, jw1, t0, t1, gM, g_m2d, g_con)
            # ---- M = F L → ∂L/∂F = gM Lᵀ, ∂L/∂L = Fᵀ gM
            for i in range(3):
                for j in range(3):
                    gF[i, j] = gM[i, 0] * RS[g, j, 0] + gM[i, 1] * RS[g, j, 1] + gM[i, 2] * RS[g, j, 2]
                    g_RS[g, i, j] = F[0, i] * gM[0, j] + F[1, i] * gM[1, j] + F[2, i] * gM[2, j]
            if quadratic:
                _element_back_p2(g, x, hv, shape, beta, N, dNx, Ji, F, gF, gmu0, gmu1, gmu2, gD, gJ, gdN, g_corners,
                                 g_beta)
            else:
                _element_back_p1(g, P, beta, shape, gF, gmu0, gmu1, gmu2, gD, g_corners, g_beta)


@nb.njit(cache=True)
def _scatter_vertices(hv, g_corners, out):  # pragma: no cover - compiled
    for g in range(hv.shape[0]):
        for k in range(hv.shape[1]):
            v = hv[g, k]
            for d in range(3):
                out[v, d] += g_corners[g, k, d]


def _f64(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float64)


class _ProjectBound(torch.autograd.Function):
    @staticmethod
    def forward(ctx, positions, beta, factors, host_vertices, shape, cam_arr, out_dt):
        args = (_f64(positions), np.ascontiguousarray(host_vertices.cpu().numpy()), _f64(shape), _f64(beta),
                _f64(factors), cam_arr)
        g = args[1].shape[0]
        m2d, con, dep = np.empty((g, 2)), np.empty((g, 3)), np.empty(g)
        vis = np.empty(g, np.bool_)
        _forward(*args, m2d, con, dep, vis)
        ctx.args, ctx.vis = args, vis
        ctx.dtypes = (positions.dtype, beta.dtype, factors.dtype)
        visible = torch.from_numpy(vis)
        ctx.mark_non_differentiable(visible)
        return (torch.from_numpy(m2d).to(out_dt), torch.from_numpy(con).to(out_dt),
                torch.from_numpy(dep).to(out_dt), visible)

    @staticmethod
    def backward(ctx, g_m2d, g_con, g_dep, g_vis):
        args, vis = ctx.args, ctx.vis
        g, k = args[1].shape
        gm = _f64(g_m2d) if g_m2d is not None else np.zeros((g, 2))
        gc = _f64(g_con) if g_con is not None else np.zeros((g, 3))
        g_corners, g_beta, g_RS = np.empty((g, k, 3)), np.empty((g, 4)), np.empty((g, 3, 3))
        _backward(*args, vis, gm, gc, g_corners, g_beta, g_RS)
        gx = np.zeros_like(args[0])
        _scatter_vertices(args[1], g_corners, gx)
        pdt, bdt, fdt = ctx.dtypes
        return (torch.from_numpy(gx).to(pdt), torch.from_numpy(g_beta).to(bdt), torch.from_numpy(g_RS).to(fdt),
                None, None, None, None)


class _Params(torch.autograd.Function):
    """(β (G, 4), L (G, 3, 3)) float64 of (bary_logits, log_scales, rotations); gradients in the logits' dtype."""

    @staticmethod
    def forward(ctx, bary_logits, log_scales, rotations):
        rot = _f64(rotations)
        g = rot.shape[0]
        beta, RS, sc = np.empty((g, 4)), np.empty((g, 3, 3)), np.empty((g, 3))
        _params_forward(_f64(bary_logits), _f64(log_scales), rot, beta, RS, sc)
        ctx.saved = (rot, beta, sc)
        ctx.dt = bary_logits.dtype
        return torch.from_numpy(beta), torch.from_numpy(RS)

    @staticmethod
    def backward(ctx, g_beta, g_RS):
        rot, beta, sc = ctx.saved
        g = rot.shape[0]
        gb = _f64(g_beta) if g_beta is not None else np.zeros((g, 4))
        gr = _f64(g_RS) if g_RS is not None else np.zeros((g, 3, 3))
        g_bl, g_ls, g_rot = np.empty((g, 4)), np.empty((g, 3)), np.empty((g, 4))
        _params_backward(rot, beta, sc, gb, gr, g_bl, g_ls, g_rot)
        return tuple(torch.from_numpy(a).to(ctx.dt) for a in (g_bl, g_ls, g_rot))


def fitted_binding(bary_logits: torch.Tensor, log_scales: torch.Tensor, rotations: torch.Tensor
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(β = softmax(bary_logits) (G, 4), L = R(q/|q|) diag(exp(log_scales)) (G, 3, 3)) float64, the very values
    :func:`bind_project` projects with (so :func:`project_bound` on them renders the same floats)."""
    rot = _f64(rotations)
    g = rot.shape[0]
    beta, RS, sc = np.empty((g, 4)), np.empty((g, 3, 3)), np.empty((g, 3))
    _params_forward(_f64(bary_logits), _f64(log_scales), rot, beta, RS, sc)
    return beta, RS


def project_bound(positions: torch.Tensor, beta: torch.Tensor, factors: torch.Tensor, host_vertices: torch.Tensor,
                  shape: torch.Tensor, cam: CameraTensors, dtype: torch.dtype | None = None, near: float = NEAR_M
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(means2d (G,2), conics (G,3), depths (G,), visible (G,) bool) of Gaussians with barycentric β (G,4) in
    their host elements and rest-frame covariance factors L (G,3,3) (Σ₀ = L Lᵀ), differentiable in positions
    (n,3) m, β and L (each gradient in its own dtype).  host_vertices (G,4) int with ``shape`` = D_m⁻¹ (G,3,3)
    of the host tets, or (G,10) with ``shape`` = the host elements' rest node positions (G,10,3) m (F = D_x J⁻¹
    through the quadratic map at β).  Outputs in ``dtype`` (default β's).  Pinhole ``cam`` only (distortion
    is not modelled here).  Depths carry no gradient (they only order the Gaussians)."""
    if cam.has_distortion:
        raise ValueError("bind_project models pinhole cameras only; use the torch path for distortion.")
    return _ProjectBound.apply(positions, beta, factors, host_vertices, shape, camera_array(cam, near),
                               beta.dtype if dtype is None else dtype)


def bind_project(positions: torch.Tensor, bary_logits: torch.Tensor, log_scales: torch.Tensor,
                 rotations: torch.Tensor, host_vertices: torch.Tensor, dm_inv: torch.Tensor, cam: CameraTensors,
                 near: float = NEAR_M) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(means2d (G,2), conics (G,3), depths (G,), visible (G,) bool) of tet-bound Gaussians, differentiable.

    positions (n,3) m (any float dtype; its gradient keeps it), bary_logits (G,4), log_scales (G,3),
    rotations (G,4) wxyz (unnormalised), host_vertices (G,4) int with dm_inv (G,3,3) for linear tets, or
    host_vertices (G,10) with ``dm_inv`` = the host elements' rest node positions (G,10,3) m for quadratic
    tets (F = D_x J⁻¹ through the quadratic map at the Gaussian's barycentric point); pinhole ``cam``
    (distortion is not modelled here).  Outputs in the logits' dtype.  :func:`project_bound` after
    β = softmax(bary_logits), L = R(q/|q|) diag(exp(log_scales)).
    """
    beta, factors = _Params.apply(bary_logits, log_scales, rotations)
    return project_bound(positions, beta, factors, host_vertices, dm_inv, cam, bary_logits.dtype, near)
