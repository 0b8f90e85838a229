"""Fused binding + EWA projection (numba, forward and hand-written backward), for pinhole cameras.

Per Gaussian g in host tet with corners p₀..p₃ (rows of x), in one compiled loop:

    β = softmax(bary_logits),  μ = Σₖ βₖ pₖ,  F = D_s D_m⁻¹,  M = F R(q/|q|) diag(exp(log_scales))
    (quadratic tets, 10 nodes: μ = Σ_a N_a(β) x_a, F = D_x J⁻¹ with D_x = Σ_a x_a ⊗ ∂N_a/∂ξ and
     J = Σ_a X_a ⊗ ∂N_a/∂ξ at β, X the rest nodes — the quadratic map at the Gaussian's own location)
    x_c = R_c μ + t,  (xₙ, yₙ) = (x_c/z, y_c/z),  u = K₂ (xₙ, yₙ) + c
    J R_c rows: K₂ [(R_c0 − x̄ₙ R_c2)/z ; (R_c1 − ȳₙ R_c2)/z]   (x̄ₙ, ȳₙ clamped to 1.3× the image extent)
    T = J R_c M (2×3),  Σ₂ = T Tᵀ + 0.3 I,  conic = Σ₂⁻¹

— the same maths as ``BoundGaussians.centres`` / ``covariance_factors`` and
``projection.project_gaussians(factors=...)`` in torch, which stay the reference twin
(tests hold this module to it, forward and backward).  The torch version costs about
a hundred small tensor ops per view; this one loop replaces them.  Distorted cameras
use the torch path.
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


@nb.njit(inline="always")
def _geometry(g, x, hv, dm_inv, bl, ls, rot, beta, P, Ds, F, Rq, sc, RS, M, cache, reuse):  # pragma: no cover
    """Fill β, corners P, D_s, F, R(q), s, R S, M = F R S for Gaussian g; returns (μ, |q|, q̂).

    ``cache`` (G, 8) holds exp(bary_logits − max) (0..3), exp(log_scales) (4..6) and their softmax sum
    (7) per Gaussian: written when ``reuse`` is False (the forward pass), read when True (the backward
    pass skips the 7 exps; the values are the very same floats, so both passes see identical geometry).
    """
    if reuse:
        sb = cache[g, 7]
        for k in range(4):
            beta[k] = cache[g, k]
    else:
        mx = bl[g, 0]
        for k in range(1, 4):
            mx = max(mx, bl[g, k])
        sb = 0.0
        for k in range(4):
            beta[k] = math.exp(bl[g, k] - mx)
            cache[g, k] = beta[k]
            sb += beta[k]
        cache[g, 7] = sb
    m0 = 0.0
    m1 = 0.0
    m2 = 0.0
    for k in range(4):
        beta[k] /= sb
        v = hv[g, k]
        P[k, 0] = x[v, 0]
        P[k, 1] = x[v, 1]
        P[k, 2] = x[v, 2]
        m0 += beta[k] * P[k, 0]
        m1 += beta[k] * P[k, 1]
        m2 += beta[k] * P[k, 2]
    for j in range(3):
        for d in range(3):
            Ds[d, j] = P[j + 1, d] - P[0, d]
    _mm(Ds, dm_inv[g], F)
    qn, qw, qx, qy, qz = _rotmat(rot[g, 0], rot[g, 1], rot[g, 2], rot[g, 3], Rq)
    for j in range(3):
        if reuse:
            sc[j] = cache[g, 4 + j]
        else:
            sc[j] = math.exp(ls[g, j])
            cache[g, 4 + j] = sc[j]
        for i in range(3):
            RS[i, j] = Rq[i, j] * sc[j]
    _mm(F, RS, M)
    return m0, m1, m2, qn, qw, qx, qy, qz


@nb.njit(inline="always")
def _geometry_p2(g, x, hv, xr, bl, ls, rot, beta, N, dNx, Dx, J, Ji, F, Rq, sc, RS, M, cache,
                 reuse):  # pragma: no cover - compiled
    """Quadratic tets: β = softmax(logits), N_a(β), ∂N_a/∂ξ (10, 3), D_x = Σ x_a ⊗ ∂N_a/∂ξ,
    J = Σ X_a ⊗ ∂N_a/∂ξ (rest nodes xr (G, 10, 3)), F = D_x J⁻¹, M = F R S; returns (μ, |q|, q̂)."""
    if reuse:
        sb = cache[g, 7]
        for k in range(4):
            beta[k] = cache[g, k]
    else:
        mx = bl[g, 0]
        for k in range(1, 4):
            mx = max(mx, bl[g, k])
        sb = 0.0
        for k in range(4):
            beta[k] = math.exp(bl[g, k] - mx)
            cache[g, k] = beta[k]
            sb += beta[k]
        cache[g, 7] = sb
    for k in range(4):
        beta[k] /= sb
    # ∂N/∂L (10, 4) is sparse: corner a has 4β_a − 1 at L_a; edge (a, b) has 4β_b at L_a and 4β_a at L_b;
    # ∂N/∂ξ_j = ∂N/∂L_{j+1} − ∂N/∂L_0
    for a in range(10):
        for j in range(3):
            dNx[a, j] = 0.0
    for a in range(4):
        N[a] = beta[a] * (2.0 * beta[a] - 1.0)
        d = 4.0 * beta[a] - 1.0
        if a == 0:
            for j in range(3):
                dNx[0, j] -= d
        else:
            dNx[a, a - 1] += d
    for e in range(6):
        a, b = _EDGE_A[e], _EDGE_B[e]
        N[4 + e] = 4.0 * beta[a] * beta[b]
        da, db = 4.0 * beta[b], 4.0 * beta[a]  # ∂N/∂L_a, ∂N/∂L_b
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
    qn, qw, qx, qy, qz = _rotmat(rot[g, 0], rot[g, 1], rot[g, 2], rot[g, 3], Rq)
    for j in range(3):
        if reuse:
            sc[j] = cache[g, 4 + j]
        else:
            sc[j] = math.exp(ls[g, j])
            cache[g, 4 + j] = sc[j]
        for i in range(3):
            RS[i, j] = Rq[i, j] * sc[j]
    _mm(F, RS, M)
    return m0, m1, m2, qn, qw, qx, qy, qz


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


@nb.njit(parallel=True, cache=True)
def _forward(x, hv, dm_inv, bl, ls, rot, cam, means2d, conics, depths, visible, cache):  # pragma: no cover
    Rc = cam[5:14].reshape(3, 3)
    n = hv.shape[0]
    for chunk in nb.prange((n + CHUNK - 1) // CHUNK):
        beta = np.empty(4)
        P = np.empty((4, 3))
        Ds = np.empty((3, 3))
        F = np.empty((3, 3))
        Rq = np.empty((3, 3))
        sc = np.empty(3)
        RS = np.empty((3, 3))
        M = np.empty((3, 3))
        jw0 = np.empty(3)
        jw1 = np.empty(3)
        for g in range(chunk * CHUNK, min(n, (chunk + 1) * CHUNK)):
            m0, m1, m2, _, _, _, _, _ = _geometry(g, x, hv, dm_inv, bl, ls, rot, beta, P, Ds, F, Rq, sc, RS, M,
                                                  cache, False)
            _project_one(g, m0, m1, m2, M, cam, Rc, jw0, jw1, means2d, conics, depths, visible)


@nb.njit(parallel=True, cache=True)
def _forward_p2(x, hv, xr, bl, ls, rot, cam, means2d, conics, depths, visible, cache):  # pragma: no cover
    Rc = cam[5:14].reshape(3, 3)
    n = hv.shape[0]
    for chunk in nb.prange((n + CHUNK - 1) // CHUNK):
        beta = np.empty(4)
        N = np.empty(10)
        dNx = np.empty((10, 3))
        Dx = np.empty((3, 3))
        J = np.empty((3, 3))
        Ji = np.empty((3, 3))
        F = np.empty((3, 3))
        Rq = np.empty((3, 3))
        sc = np.empty(3)
        RS = np.empty((3, 3))
        M = np.empty((3, 3))
        jw0 = np.empty(3)
        jw1 = np.empty(3)
        for g in range(chunk * CHUNK, min(n, (chunk + 1) * CHUNK)):
            m0, m1, m2, _, _, _, _, _ = _geometry_p2(g, x, hv, xr, bl, ls, rot, beta, N, dNx, Dx, J, Ji, F, Rq, sc,
                                                     RS, M, cache, False)
            _project_one(g, m0, m1, m2, M, cam, Rc, jw0, jw1, means2d, conics, depths, visible)


@nb.njit(inline="always")
def _project_back(g, m0, m1, m2, M, cam, Rc, n0, n1, jw0, jw1, t0, t1, gM, g_m2d, g_con):  # pragma: no cover
    """Backward of :func:`_project_one` for a visible Gaussian: fills gM = ∂L/∂M, returns ∂L/∂μ."""
    fx, sk, fy = cam[0], cam[1], cam[3]
    lx, ly, lp = cam[17], cam[18], cam[22]
    p0 = Rc[0, 0] * m0 + Rc[0, 1] * m1 + Rc[0, 2] * m2 + cam[14]
    p1 = Rc[1, 0] * m0 + Rc[1, 1] * m1 + Rc[1, 2] * m2 + cam[15]
    z = Rc[2, 0] * m0 + Rc[2, 1] * m1 + Rc[2, 2] * m2 + cam[16]
    xn, yn = p0 / z, p1 / z
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
    det = a * c - b * b
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


@nb.njit(inline="always")
def _factor_back(g, F, RS, Rq, sc, gM, gF, gRS, gR, qn, qw, qx, qy, qz, g_ls, g_rot):  # pragma: no cover
    """M = F R(q) diag(s): fills gF and the gradients of log-scales and the (unnormalised) quaternion."""
    for i in range(3):
        for j in range(3):
            gF[i, j] = gM[i, 0] * RS[j, 0] + gM[i, 1] * RS[j, 1] + gM[i, 2] * RS[j, 2]
            gRS[i, j] = F[0, i] * gM[0, j] + F[1, i] * gM[1, j] + F[2, i] * gM[2, j]
    for j in range(3):
        gs = 0.0
        for i in range(3):
            gR[i, j] = gRS[i, j] * sc[j]
            gs += gRS[i, j] * Rq[i, j]
        g_ls[g, j] = gs * sc[j]
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


@nb.njit(parallel=True, cache=True)
def _backward(x, hv, dm_inv, bl, ls, rot, cam, visible, g_m2d, g_con,
              g_corners, g_bl, g_ls, g_rot, cache):  # pragma: no cover - compiled
    Rc = cam[5:14].reshape(3, 3)
    n = hv.shape[0]
    for chunk in nb.prange((n + CHUNK - 1) // CHUNK):
        beta = np.empty(4)
        P = np.empty((4, 3))
        Ds = np.empty((3, 3))
        F = np.empty((3, 3))
        Rq = np.empty((3, 3))
        sc = np.empty(3)
        RS = np.empty((3, 3))
        M = np.empty((3, 3))
        n0 = np.empty(3)
        n1 = np.empty(3)
        jw0 = np.empty(3)
        jw1 = np.empty(3)
        t0 = np.empty(3)
        t1 = np.empty(3)
        gM = np.empty((3, 3))
        gF = np.empty((3, 3))
        gRS = np.empty((3, 3))
        gR = np.empty((3, 3))
        gDs = np.empty((3, 3))
        gbeta = np.empty(4)
        for g in range(chunk * CHUNK, min(n, (chunk + 1) * CHUNK)):
            for k in range(4):
                g_bl[g, k] = 0.0
                g_rot[g, k] = 0.0
                for d in range(3):
                    g_corners[g, k, d] = 0.0
            for j in range(3):
                g_ls[g, j] = 0.0
            if not visible[g]:
                continue
            m0, m1, m2, qn, qw, qx, qy, qz = _geometry(g, x, hv, dm_inv, bl, ls, rot, beta, P, Ds, F, Rq, sc,
                                                       RS, M, cache, True)
            gmu0, gmu1, gmu2 = _project_back(g, m0, m1, m2, M, cam, Rc, n0, n1, jw0, jw1, t0, t1, gM, g_m2d, g_con)
            _factor_back(g, F, RS, Rq, sc, gM, gF, gRS, gR, qn, qw, qx, qy, qz, g_ls, g_rot)
            # ---- F = Ds Dm⁻¹ → gDs = gF Dm⁻ᵀ; Ds[:, j] = p_{j+1} − p₀
            Dmi = dm_inv[g]
            for i in range(3):
                for j in range(3):
                    gDs[i, j] = gF[i, 0] * Dmi[j, 0] + gF[i, 1] * Dmi[j, 1] + gF[i, 2] * Dmi[j, 2]
            for j in range(3):
                for d in range(3):
                    g_corners[g, j + 1, d] += gDs[d, j]
                    g_corners[g, 0, d] -= gDs[d, j]
            # ---- μ = Σ βₖ pₖ, β = softmax
            sgb = 0.0
            for k in range(4):
                gbeta[k] = P[k, 0] * gmu0 + P[k, 1] * gmu1 + P[k, 2] * gmu2
                sgb += beta[k] * gbeta[k]
                g_corners[g, k, 0] += beta[k] * gmu0
                g_corners[g, k, 1] += beta[k] * gmu1
                g_corners[g, k, 2] += beta[k] * gmu2
            for k in range(4):
                g_bl[g, k] = beta[k] * (gbeta[k] - sgb)


@nb.njit(parallel=True, cache=True)
def _backward_p2(x, hv, xr, bl, ls, rot, cam, visible, g_m2d, g_con,
                 g_corners, g_bl, g_ls, g_rot, cache):  # pragma: no cover - compiled
    """Backward of :func:`_forward_p2`: F = D_x J⁻¹ → ∂L/∂D_x = gF J⁻ᵀ, ∂L/∂J = −Fᵀ ∂L/∂D_x; both are
    linear in ∂N/∂ξ, which is linear in β; μ = Σ N_a(β) x_a."""
    Rc = cam[5:14].reshape(3, 3)
    n = hv.shape[0]
    for chunk in nb.prange((n + CHUNK - 1) // CHUNK):
        beta = np.empty(4)
        N = np.empty(10)
        dNx = np.empty((10, 3))
        Dx = np.empty((3, 3))
        J = np.empty((3, 3))
        Ji = np.empty((3, 3))
        F = np.empty((3, 3))
        Rq = np.empty((3, 3))
        sc = np.empty(3)
        RS = np.empty((3, 3))
        M = np.empty((3, 3))
        n0 = np.empty(3)
        n1 = np.empty(3)
        jw0 = np.empty(3)
        jw1 = np.empty(3)
        t0 = np.empty(3)
        t1 = np.empty(3)
        gM = np.empty((3, 3))
        gF = np.empty((3, 3))
        gRS = np.empty((3, 3))
        gR = np.empty((3, 3))
        gDx = np.empty((3, 3))
        gJ = np.empty((3, 3))
        gdN = np.empty(3)
        gbeta = np.empty(4)
        for g in range(chunk * CHUNK, min(n, (chunk + 1) * CHUNK)):
            for k in range(4):
                g_bl[g, k] = 0.0
                g_rot[g, k] = 0.0
            for k in range(10):
                for d in range(3):
                    g_corners[g, k, d] = 0.0
            for j in range(3):
                g_ls[g, j] = 0.0
            if not visible[g]:
                continue
            m0, m1, m2, qn, qw, qx, qy, qz = _geometry_p2(g, x, hv, xr, bl, ls, rot, beta, N, dNx, Dx, J, Ji, F, Rq,
                                                          sc, RS, M, cache, True)
            gmu0, gmu1, gmu2 = _project_back(g, m0, m1, m2, M, cam, Rc, n0, n1, jw0, jw1, t0, t1, gM, g_m2d, g_con)
            _factor_back(g, F, RS, Rq, sc, gM, gF, gRS, gR, qn, qw, qx, qy, qz, g_ls, g_rot)
            for i in range(3):
                for j in range(3):
                    gDx[i, j] = gF[i, 0] * Ji[j, 0] + gF[i, 1] * Ji[j, 1] + gF[i, 2] * Ji[j, 2]
            for i in range(3):
                for j in range(3):
                    gJ[i, j] = -(F[0, i] * gDx[0, j] + F[1, i] * gDx[1, j] + F[2, i] * gDx[2, j])
            for k in range(4):
                gbeta[k] = 0.0
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
                    gbeta[a] += gN * (4.0 * beta[a] - 1.0) + 4.0 * gD
                else:
                    e = a - 4
                    ea, eb = _EDGE_A[e], _EDGE_B[e]
                    gDa = -gsum if ea == 0 else gdN[ea - 1]
                    gDb = gdN[eb - 1]
                    gbeta[ea] += gN * 4.0 * beta[eb] + 4.0 * gDb
                    gbeta[eb] += gN * 4.0 * beta[ea] + 4.0 * gDa
            sgb = 0.0
            for k in range(4):
                sgb += beta[k] * gbeta[k]
            for k in range(4):
                g_bl[g, k] = beta[k] * (gbeta[k] - sgb)


@nb.njit(cache=True)
def _scatter_vertices(hv, g_corners, out):  # pragma: no cover - compiled
    for g in range(hv.shape[0]):
        for k in range(hv.shape[1]):
            v = hv[g, k]
            for d in range(3):
                out[v, d] += g_corners[g, k, d]


class _BindProject(torch.autograd.Function):
    @staticmethod
    def forward(ctx, positions, bary_logits, log_scales, rotations, host_vertices, dm_inv, cam_arr):
        f64 = lambda t: np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float64)  # noqa: E731
        args = (f64(positions), np.ascontiguousarray(host_vertices.cpu().numpy()), f64(dm_inv), f64(bary_logits),
                f64(log_scales), f64(rotations), cam_arr)
        g = args[1].shape[0]
        m2d, con, dep = np.empty((g, 2)), np.empty((g, 3)), np.empty(g)
        vis = np.empty(g, np.bool_)
        cache = np.empty((g, 8))
        (_forward_p2 if args[1].shape[1] == 10 else _forward)(*args, m2d, con, dep, vis, cache)
        ctx.args, ctx.vis, ctx.cache = args, vis, cache
        ctx.dtypes = (positions.dtype, bary_logits.dtype)
        out_dt = bary_logits.dtype
        visible = torch.from_numpy(vis)
        ctx.mark_non_differentiable(visible)
        return (torch.from_numpy(m2d).to(out_dt), torch.from_numpy(con).to(out_dt),
                torch.from_numpy(dep).to(out_dt), visible)

    @staticmethod
    def backward(ctx, g_m2d, g_con, g_dep, g_vis):
        args, vis = ctx.args, ctx.vis
        g, k = args[1].shape
        f64 = lambda t: np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float64)  # noqa: E731
        gm = f64(g_m2d) if g_m2d is not None else np.zeros((g, 2))
        gc = f64(g_con) if g_con is not None else np.zeros((g, 3))
        g_corners, g_bl, g_ls, g_rot = np.empty((g, k, 3)), np.empty((g, 4)), np.empty((g, 3)), np.empty((g, 4))
        (_backward_p2 if k == 10 else _backward)(*args, vis, gm, gc, g_corners, g_bl, g_ls, g_rot, ctx.cache)
        gx = np.zeros_like(args[0])
        _scatter_vertices(args[1], g_corners, gx)
        pdt, dt = ctx.dtypes
        t = lambda a, d: torch.from_numpy(a).to(d)  # noqa: E731
        return t(gx, pdt), t(g_bl, dt), t(g_ls, dt), t(g_rot, dt), None, None, None


def bind_project(positions: torch.Tensor, bary_logits: torch.Tensor, log_scales: torch.Tensor,
                 rotations: torch.Tensor, host_vertices: torch.Tensor, dm_inv: torch.Tensor, cam: CameraTensors,
                 near: float = NEAR_M) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(means2d (G,2), conics (G,3), depths (G,), visible (G,) bool) of tet-bound Gaussians, differentiable.

    positions (n,3) m (any float dtype; its gradient keeps it), bary_logits (G,4), log_scales (G,3),
    rotations (G,4) wxyz (unnormalised), host_vertices (G,4) int with dm_inv (G,3,3) for linear tets, or
    host_vertices (G,10) with ``dm_inv`` = the host elements' rest node positions (G,10,3) m for quadratic
    tets (F = D_x J⁻¹ through the quadratic map at the Gaussian's barycentric point); pinhole ``cam``
    (distortion is not modelled here).  Depths carry no gradient (they only order the Gaussians).
    """
    if cam.has_distortion:
        raise ValueError("bind_project models pinhole cameras only; use the torch path for distortion.")
    return _BindProject.apply(positions, bary_logits, log_scales, rotations, host_vertices, dm_inv,
                              camera_array(cam, near))
