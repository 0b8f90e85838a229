"""Forward-mode (Jacobian-vector products) of the fast rasterizer for k tangents at once.

For the Gauss–Newton normal matrix the estimator needs the image Jacobian ∂I/∂p along a few (k ≈ 2–10)
directions p; central differences cost 2k renders.  Here one front-to-back pass per tile carries, beside each
pixel's transmittance T, the k tangents dT and dC of the image formation of ``rasterize.py``:

    power = −½(a dx² + c dy²) − b dx dy,   dx = μx − px, dy = μy − py
    d power = −(a dx + b dy) dμx − (b dx + c dy) dμy − ½ dx² da − dx dy db − ½ dy² dc
    α = o e^power (not clamped at 0.99: else dα = 0),   dα = α d power
    C += c α T,   dC += c (dα T + α dT),     T ← T (1 − α),   dT ← dT (1 − α) − T dα
    A = 1 − T_final,   dA = −dT_final

over the same contributions as the primal: a Gaussian counts at a pixel where it did in the render (below the
pixel's contribution count, α ≥ 1/255 and power within its pre-test range; the render's early stop is
respected).  The tangents of the projected Gaussians (d means2d, d conics) come from the caller.  The primal
outputs are those of ``rasterize.rasterize`` itself (the same packing, binning and kernel: bit-identical);
colours and opacities are held fixed (no tangent).

The obvious twins (tests/test_render_jvp.py): central differences of the float64 rasterizer, and the adjoint
identity ⟨u, J v⟩ = ⟨Jᵀ u, v⟩ against the backward kernel of ``rasterize.py``.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np
import torch

from stages.render.bind_project import _inv3, _mm, _screen_terms, camera_array
from stages.render.projection import CameraTensors
from stages.render.rasterize import (ALPHA_MAX, ALPHA_MIN, TILE, _bin_ranked, _exp_neg, _forward, _pack, _schedule,
                                     exp_coefficients)


@nb.njit(cache=True, fastmath=True, error_model="numpy")
def _jvp_tile(gdata, gtan, entries, s, k, x0, y0, w, h, tile, ecoef, S, L, row_n, n_contrib,
              d_color, d_trans):  # pragma: no cover - compiled
    """One tile of ``_jvp``: list entries s … s + k − 1, pixels [x0, x0 + w) × [y0, y0 + h).

    S holds per pixel lane T, the contribution count, then per tangent j dT_j and dC_j (3 fields); L (5 × TILE)
    per lane of the current row: dx, α (0 where the Gaussian does not count), α for dα (0 where α is clamped
    too) and T before the Gaussian."""
    dt = gdata.dtype.type
    one = dt(1.0)
    zero = dt(0.0)
    half = dt(0.5)
    amin = dt(ALPHA_MIN)
    amax = dt(ALPHA_MAX)
    nn = TILE * TILE
    nt = gtan.shape[1]
    o1 = np.uint64(nn)
    for q in range((2 + 4 * nt) * nn):
        S[q] = zero
    for q in range(nn):
        S[q] = one
    for ly in range(TILE):
        row_n[ly] = 0
    nmax = 0
    for ly in range(h):
        for lx in range(w):
            q = ly * TILE + lx
            nc = n_contrib[y0 + ly, x0 + lx]
            S[nn + q] = dt(nc)
            row_n[ly] = max(row_n[ly], nc)
        nmax = max(nmax, row_n[ly])
    p1 = np.uint64(TILE)
    p2 = np.uint64(2 * TILE)
    p3 = np.uint64(3 * TILE)
    fx0 = dt(x0)
    for i in range(min(nmax, k)):
        gi = entries[s + i]
        mx = gdata[gi, 0]
        my = gdata[gi, 1]
        ca = gdata[gi, 2]
        cb = gdata[gi, 3]
        cc = gdata[gi, 4]
        op = gdata[gi, 5]
        c0 = gdata[gi, 6]
        c1 = gdata[gi, 7]
        c2 = gdata[gi, 8]
        thr = gdata[gi, 11]
        py0 = max(y0, int(math.ceil(my - gdata[gi, 10])))
        py1 = min(y0 + h - 1, int(math.floor(my + gdata[gi, 10])))
        mxl = mx - fx0
        fi = dt(i)
        for py in range(py0, py1 + 1):
            ly = py - y0
            if i >= row_n[ly]:
                continue
            dy = my - dt(py)
            cdy = cc * dy * dy
            b = ly * TILE
            flx = zero
            for lx in range(tile):  # the primal, as the render made it
                q = np.uint64(b + lx)
                r = np.uint64(lx)
                dx = mxl - flx
                flx += one
                power = -half * (ca * dx * dx + cdy) - cb * dx * dy
                raw = op * _exp_neg(power, ecoef)
                alpha = min(amax, raw)
                m = (fi < S[o1 + q]) & (power <= zero) & (power >= thr) & (alpha >= amin)
                Tq = S[q]
                L[r] = dx
                L[p1 + r] = alpha if m else zero
                L[p2 + r] = raw if m & (raw <= amax) else zero
                L[p3 + r] = Tq
                S[q] = Tq * (one - alpha) if m else Tq
            for j in range(nt):
                dmx = gtan[gi, j, 0]
                dmy = gtan[gi, j, 1]
                da = gtan[gi, j, 2]
                db = gtan[gi, j, 3]
                dc = gtan[gi, j, 4]
                ky = -(cb * dy) * dmx - (cc * dy) * dmy - half * dy * dy * dc  # the dx-free part of d power
                kx = -ca * dmx - cb * dmy - dy * db
                ot = np.uint64((2 + 4 * j) * nn + b)
                oc0 = np.uint64((3 + 4 * j) * nn + b)
                oc1 = np.uint64((4 + 4 * j) * nn + b)
                oc2 = np.uint64((5 + 4 * j) * nn + b)
                for lx in range(tile):
                    r = np.uint64(lx)
                    dx = L[r]
                    alpha = L[p1 + r]
                    Tq = L[p3 + r]
                    dpow = ky + dx * kx - half * dx * dx * da
                    dal = L[p2 + r] * dpow
                    dT = S[ot + r]
                    g = dal * Tq + alpha * dT
                    S[oc0 + r] += c0 * g
                    S[oc1 + r] += c1 * g
                    S[oc2 + r] += c2 * g
                    S[ot + r] = dT * (one - alpha) - Tq * dal
    for j in range(nt):
        for ly in range(h):
            for lx in range(w):
                q = ly * TILE + lx
                d_trans[j, y0 + ly, x0 + lx] = S[(2 + 4 * j) * nn + q]
                d_color[j, y0 + ly, x0 + lx, 0] = S[(3 + 4 * j) * nn + q]
                d_color[j, y0 + ly, x0 + lx, 1] = S[(4 + 4 * j) * nn + q]
                d_color[j, y0 + ly, x0 + lx, 2] = S[(5 + 4 * j) * nn + q]


@nb.njit(parallel=True, cache=True)
def _jvp(gdata, gtan, tile_start, entries, tile_order, block_start, width, height, tile, ecoef, n_contrib,
         d_color, d_trans):  # pragma: no cover - compiled
    """Front to back over each tile's list: the k tangents of the colour and of the final transmittance."""
    tx_n = (width + tile - 1) // tile
    nt = gtan.shape[1]
    for blk in nb.prange(block_start.shape[0] - 1):
        S = np.empty((2 + 4 * nt) * TILE * TILE, gdata.dtype)
        L = np.empty(4 * TILE, gdata.dtype)
        row_n = np.empty(TILE, np.int64)
        for jj in range(block_start[blk], block_start[blk + 1]):
            t = tile_order[jj]
            x0 = (t % tx_n) * tile
            y0 = (t // tx_n) * tile
            _jvp_tile(gdata, gtan, entries, tile_start[t], tile_start[t + 1] - tile_start[t], x0, y0,
                      min(tile, width - x0), min(tile, height - y0), tile, ecoef, S, L, row_n, n_contrib, d_color,
                      d_trans)


def rasterize_jvp(means2d: torch.Tensor, conics: torch.Tensor, colors: torch.Tensor, opacities: torch.Tensor,
                  depths: torch.Tensor, visible: torch.Tensor, width: int, height: int, d_means2d: np.ndarray,
                  d_conics: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(colour (H, W, 3), coverage A (H, W), d colour (k, H, W, 3), dA (k, H, W)) numpy in the inputs' dtype:
    ``rasterize.rasterize``'s outputs (the same floats) and their derivatives along k tangents of the projected
    Gaussians, d_means2d (k, N, 2) px and d_conics (k, N, 3) px⁻² (colours, opacities, depths held).
    Inputs as for ``rasterize.rasterize`` (torch, float32 or float64)."""
    gdata = _pack(means2d, conics, colors, opacities)
    dt = gdata.dtype
    vis = visible.detach().cpu().numpy().astype(bool)
    tile_start, entries, order = _bin_ranked(gdata[:, 0:2], gdata[:, 2:5], gdata[:, 5], depths.detach().cpu().numpy(),
                                             vis, width, height,
                                             (gdata[:, 9].astype(np.float64), gdata[:, 10].astype(np.float64)), True)
    gdata = np.ascontiguousarray(gdata[order])
    color = np.empty((height, width, 3), dt)
    alpha = np.empty((height, width), dt)
    t_final = np.empty((height, width), dt)
    n_contrib = np.empty((height, width), np.int32)
    tile_order, block_start = _schedule(tile_start, max(1, nb.get_num_threads()))
    ecoef = exp_coefficients(dt)
    _forward(gdata, tile_start, entries, tile_order, block_start, width, height, TILE, ecoef, color, alpha, t_final,
             n_contrib)
    k = int(np.shape(d_means2d)[0])
    gtan = np.concatenate([np.asarray(d_means2d, np.float64), np.asarray(d_conics, np.float64)], axis=2)  # (k, N, 5)
    gtan = np.ascontiguousarray(gtan.transpose(1, 0, 2)[order], dtype=dt)  # (N_kept, k, 5), depth order
    d_color = np.empty((k, height, width, 3), dt)
    d_trans = np.empty((k, height, width), dt)
    if k:
        _jvp(gdata, gtan, tile_start, entries, tile_order, block_start, width, height, TILE, ecoef, n_contrib,
             d_color, d_trans)
    return color, alpha, d_color, -d_trans


# =========================================================================== the projection's forward mode
@nb.njit(parallel=True, cache=True)
def _project_jvp(mu, M, d_mu, d_M, cam, d_m2d, d_con):  # pragma: no cover - compiled
    """Tangents of bind_project._project_one's outputs (means2d, conics) along (d_mu (k, G, 3), d_M (k, G, 3, 3))
    at centres mu (G, 3) and covariance factors M (G, 3, 3); zero for a Gaussian behind the near plane."""
    fx, sk, fy = cam[0], cam[1], cam[3]
    near = cam[21]
    Rc = cam[5:14].reshape(3, 3)
    n = mu.shape[0]
    nt = d_mu.shape[0]
    for g in nb.prange(n):
        m0, m1, m2 = mu[g, 0], mu[g, 1], mu[g, 2]
        p0 = Rc[0, 0] * m0 + Rc[0, 1] * m1 + Rc[0, 2] * m2 + cam[14]
        p1 = Rc[1, 0] * m0 + Rc[1, 1] * m1 + Rc[1, 2] * m2 + cam[15]
        z = Rc[2, 0] * m0 + Rc[2, 1] * m1 + Rc[2, 2] * m2 + cam[16]
        if not z > near:
            for j in range(nt):
                d_m2d[j, g, 0] = 0.0
                d_m2d[j, g, 1] = 0.0
                d_con[j, g, 0] = 0.0
                d_con[j, g, 1] = 0.0
                d_con[j, g, 2] = 0.0
            continue
        xn, yn = p0 / z, p1 / z
        n0 = np.empty(3)
        n1 = np.empty(3)
        jw0 = np.empty(3)
        jw1 = np.empty(3)
        t0 = np.empty(3)
        t1 = np.empty(3)
        x_free, y_free, a, b, c, det = _screen_terms(xn, yn, z, M[g], cam, Rc, n0, n1, jw0, jw1, t0, t1)
        if not det > 0:
            det = 1.0
        for j in range(nt):
            dp0 = Rc[0, 0] * d_mu[j, g, 0] + Rc[0, 1] * d_mu[j, g, 1] + Rc[0, 2] * d_mu[j, g, 2]
            dp1 = Rc[1, 0] * d_mu[j, g, 0] + Rc[1, 1] * d_mu[j, g, 1] + Rc[1, 2] * d_mu[j, g, 2]
            dz = Rc[2, 0] * d_mu[j, g, 0] + Rc[2, 1] * d_mu[j, g, 1] + Rc[2, 2] * d_mu[j, g, 2]
            dxn = (dp0 - xn * dz) / z
            dyn = (dp1 - yn * dz) / z
            d_m2d[j, g, 0] = fx * dxn + sk * dyn
            d_m2d[j, g, 1] = fy * dyn
            dxc = dxn if x_free else 0.0
            dyc = dyn if y_free else 0.0
            da = 0.0
            db = 0.0
            dc = 0.0
            for jj in range(3):
                dt0 = 0.0
                dt1 = 0.0
                for d in range(3):
                    dn0 = (-dxc * Rc[2, d] - n0[d] * dz) / z
                    dn1 = (-dyc * Rc[2, d] - n1[d] * dz) / z
                    djw0 = fx * dn0 + sk * dn1
                    djw1 = fy * dn1
                    dt0 += djw0 * M[g, d, jj] + jw0[d] * d_M[j, g, d, jj]
                    dt1 += djw1 * M[g, d, jj] + jw1[d] * d_M[j, g, d, jj]
                da += 2.0 * t0[jj] * dt0
                db += dt0 * t1[jj] + t0[jj] * dt1
                dc += 2.0 * t1[jj] * dt1
            ddet = da * c + a * dc - 2.0 * b * db
            d2 = det * det
            d_con[j, g, 0] = dc / det - c * ddet / d2
            d_con[j, g, 1] = -db / det + b * ddet / d2
            d_con[j, g, 2] = da / det - a * ddet / d2


def project_jvp(means: np.ndarray, factors: np.ndarray, d_means: np.ndarray, d_factors: np.ndarray,
                cam: CameraTensors) -> tuple[np.ndarray, np.ndarray]:
    """(d means2d (k, G, 2) px, d conics (k, G, 3) px⁻²): the forward mode of the fused EWA projection
    (bind_project's pinhole model: u = K₂ (x/z, y/z) + c, Σ₂ = T Tᵀ + 0.3 I with T = J R_c M at the clamped
    normalised coordinates, conic = Σ₂⁻¹) at centres (G, 3) m and covariance factors M (G, 3, 3) m (Σ = M Mᵀ),
    along tangents d_means (k, G, 3) and d_factors (k, G, 3, 3).  Pinhole cameras only."""
    if cam.has_distortion:
        raise ValueError("project_jvp models pinhole cameras only")
    f = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    k, g = np.shape(d_means)[:2]
    d_m2d, d_con = np.empty((k, g, 2)), np.empty((k, g, 3))
    _project_jvp(f(means), f(factors), f(d_means), f(d_factors), camera_array(cam), d_m2d, d_con)
    return d_m2d, d_con


# =========================================================================== the linear-tet geometry's forward mode
@nb.njit(parallel=True, cache=True)
def _geometry_jvp_linear(x, V, host, beta, factor, dm_inv, d_beta, d_factor, mu, M, d_mu, d_M):  # pragma: no cover
    """ImageLoss.geometry_jvp on linear tets, per Gaussian g (host corners p_a = x[host[g, a]]):
    μ = Σ_a β_a p_a,  F = D_s D_m⁻¹ (D_s columns p_j − p_0),  M = F L,
    dμ = Σ_a (β_a dp_a + dβ_a p_a),  dM = dD_s D_m⁻¹ L + F dL  (dp_a = V[j, host[g, a]])."""
    n = host.shape[0]
    k = V.shape[0]
    for g in nb.prange(n):
        P = np.empty((4, 3))
        for a in range(4):
            for d in range(3):
                P[a, d] = x[host[g, a], d]
        F = np.zeros((3, 3))
        for d in range(3):
            mu[g, d] = beta[g, 0] * P[0, d] + beta[g, 1] * P[1, d] + beta[g, 2] * P[2, d] + beta[g, 3] * P[3, d]
            for e in range(3):
                F[d, e] = ((P[1, d] - P[0, d]) * dm_inv[g, 0, e] + (P[2, d] - P[0, d]) * dm_inv[g, 1, e]
                           + (P[3, d] - P[0, d]) * dm_inv[g, 2, e])
        for d in range(3):
            for e in range(3):
                M[g, d, e] = F[d, 0] * factor[g, 0, e] + F[d, 1] * factor[g, 1, e] + F[d, 2] * factor[g, 2, e]
        dP = np.empty((4, 3))
        dF = np.empty((3, 3))
        for j in range(k):
            for a in range(4):
                for d in range(3):
                    dP[a, d] = V[j, host[g, a], d]
            for d in range(3):
                s = 0.0
                for a in range(4):
                    s += beta[g, a] * dP[a, d] + d_beta[j, g, a] * P[a, d]
                d_mu[j, g, d] = s
                for e in range(3):
                    dF[d, e] = ((dP[1, d] - dP[0, d]) * dm_inv[g, 0, e] + (dP[2, d] - dP[0, d]) * dm_inv[g, 1, e]
                                + (dP[3, d] - dP[0, d]) * dm_inv[g, 2, e])
            for d in range(3):
                for e in range(3):
                    s = 0.0
                    for c in range(3):
                        s += dF[d, c] * factor[g, c, e] + F[d, c] * d_factor[j, g, c, e]
                    d_M[j, g, d, e] = s


def geometry_jvp_linear(x: np.ndarray, V: np.ndarray, host: np.ndarray, beta: np.ndarray, factor: np.ndarray,
                        dm_inv: np.ndarray, d_beta: np.ndarray, d_factor: np.ndarray) -> tuple:
    """(μ (G, 3), M (G, 3, 3), dμ (k, G, 3), dM (k, G, 3, 3)) float64: the Gaussians of a binding in linear tets —
    host (G, 4) vertex ids, β (G, 4), covariance factors L (G, 3, 3), the rest D_m⁻¹ (G, 3, 3) — at positions x
    (n, 3), and their tangents along V (k, n, 3) and the binding's dβ (k, G, 4), dL (k, G, 3, 3)
    (ImageLoss.geometry_jvp's closed form, in one compiled pass)."""
    f = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    k, G = len(V), len(host)
    out = (np.empty((G, 3)), np.empty((G, 3, 3)), np.empty((k, G, 3)), np.empty((k, G, 3, 3)))
    _geometry_jvp_linear(f(x), f(V), np.ascontiguousarray(host, dtype=np.int64), f(beta), f(factor), f(dm_inv),
                         f(d_beta), f(d_factor), *out)
    return out


@nb.njit(parallel=True, cache=True)
def _binding_tangents_linear(xa, Va, host, mu_fit, dm_inv, fit_factor, d_beta, d_factor):  # pragma: no cover
    """ImageLoss._binding_tangents_linear per Gaussian g: D (columns x_j − x_0 of its host at xa),
    λ = D⁻¹(μ_fit − x_0), F_a = D D_m⁻¹;  dλ = −D⁻¹ (dx_0 + dD λ),  dβ = (−Σ dλ, dλ),
    dL = −F_a⁻¹ dD D_m⁻¹ F_a⁻¹ L_fit."""
    n = host.shape[0]
    k = Va.shape[0]
    for g in nb.prange(n):
        D = np.empty((3, 3))
        Di = np.empty((3, 3))
        Fa = np.empty((3, 3))
        Fi = np.empty((3, 3))
        FiL = np.empty((3, 3))
        lam = np.empty(3)
        u = np.empty(3)
        dD = np.empty((3, 3))
        dDm = np.empty((3, 3))
        T = np.empty((3, 3))
        h0 = host[g, 0]
        for d in range(3):
            for j in range(3):
                D[d, j] = xa[host[g, j + 1], d] - xa[h0, d]
        _inv3(D, Di)
        for d in range(3):
            lam[d] = (Di[d, 0] * (mu_fit[g, 0] - xa[h0, 0]) + Di[d, 1] * (mu_fit[g, 1] - xa[h0, 1])
                      + Di[d, 2] * (mu_fit[g, 2] - xa[h0, 2]))
        _mm(D, dm_inv[g], Fa)
        _inv3(Fa, Fi)
        _mm(Fi, fit_factor[g], FiL)
        for j in range(k):
            for d in range(3):
                for c in range(3):
                    dD[d, c] = Va[j, host[g, c + 1], d] - Va[j, h0, d]
            for d in range(3):  # dx_0 + dD λ
                u[d] = Va[j, h0, d] + dD[d, 0] * lam[0] + dD[d, 1] * lam[1] + dD[d, 2] * lam[2]
            s = 0.0
            for d in range(3):
                dl = -(Di[d, 0] * u[0] + Di[d, 1] * u[1] + Di[d, 2] * u[2])
                d_beta[j, g, d + 1] = dl
                s += dl
            d_beta[j, g, 0] = -s
            _mm(dD, dm_inv[g], dDm)  # dD D_m⁻¹
            _mm(Fi, dDm, T)  # F_a⁻¹ dD D_m⁻¹
            dL = d_factor[j, g]
            _mm(T, FiL, dL)  # −(F_a⁻¹ dD D_m⁻¹)(F_a⁻¹ L_fit)
            for d in range(3):
                for e in range(3):
                    dL[d, e] = -dL[d, e]


def binding_tangents_linear(xa: np.ndarray, Va: np.ndarray, host: np.ndarray, mu_fit: np.ndarray,
                            dm_inv: np.ndarray, fit_factor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(dβ (k, G, 4), dL (k, G, 3, 3)) float64 of ImageLoss.anchored_geometry on linear tets along Va (k, n, 3) at
    the anchor xa (n, 3): host (G, 4) vertex ids, the fitted centres μ_fit (G, 3), the rest D_m⁻¹ (G, 3, 3) and the
    fitted world factors L_fit (G, 3, 3) (ImageLoss._binding_tangents_linear's closed form, in one compiled pass;
    3 × 3 inverses by the adjugate)."""
    f = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    k, G = len(Va), len(host)
    d_beta, d_factor = np.empty((k, G, 4)), np.empty((k, G, 3, 3))
    _binding_tangents_linear(f(xa), f(Va), np.ascontiguousarray(host, dtype=np.int64), f(mu_fit), f(dm_inv),
                             f(fit_factor), d_beta, d_factor)
    return d_beta, d_factor
