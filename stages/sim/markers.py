"""The marker observation model of ``rsl adapt`` (paper Eq. 4, windowed) and its gradient.

L = Σ_t Σ_i ‖m_i(x_t) − p_t^i‖² over the observed (t, i) only (a motion-capture gap, NaN in p, adds nothing),
with each marker bound to the surface point nearest its frame-0 position, m_i(x) = Σ_k b_ik x[f_ik]
(barycentric on the nearest surface triangle), so dL/dx_t = Σ_{i observed at t} 2 (m_i − p^i) ⊗ b_i.  Where
frame 0 itself is estimated (a capture filmed mid-motion), each marker's material point is fitted to its track
instead (fit_binding_to_tracks).

Pure functions over arrays: nothing here reads files or prints.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MarkerBinding:
    """Markers bound to surface triangles: m_i(x) = Σ_k bary[i, k] · x[faces[i, k]]."""

    faces: np.ndarray  # (M, 3) vertex ids of each marker's triangle
    bary: np.ndarray  # (M, 3) barycentric weights, rows sum to 1
    distance: np.ndarray  # (M,) m, distance from the frame-0 marker to the surface

    def positions(self, x: np.ndarray) -> np.ndarray:
        """Marker positions (…, M, 3) of vertex positions x (…, n, 3)."""
        return np.einsum("...mkd,mk->...md", x[..., self.faces, :], self.bary)

    def scatter(self, g: np.ndarray, n_vertices: int) -> np.ndarray:
        """Adjoint of :meth:`positions`: per-marker gradients (…, M, 3) -> per-vertex (…, n, 3)."""
        lead = g.shape[:-2]
        out = np.zeros(lead + (n_vertices, 3))
        contrib = g[..., :, None, :] * self.bary[:, :, None]  # (…, M, 3, 3)
        flat_out = out.reshape(-1, n_vertices, 3)
        flat_c = contrib.reshape(-1, *contrib.shape[-3:])
        for b in range(flat_out.shape[0]):
            np.add.at(flat_out[b], self.faces.reshape(-1), flat_c[b].reshape(-1, 3))
        return flat_out.reshape(out.shape)


def closest_points_on_triangles(points: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest point on each triangle to each point (Ericson, Real-Time Collision Detection §5.1.5).

    points (P, 3), tri (F, 3, 3) -> (closest (P, F, 3), barycentric (P, F, 3)).
    """
    a, b, c = tri[None, :, 0], tri[None, :, 1], tri[None, :, 2]
    p = points[:, None, :]
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.sum(ab * ap, -1), np.sum(ac * ap, -1)
    bp = p - b
    d3, d4 = np.sum(ab * bp, -1), np.sum(ac * bp, -1)
    cp = p - c
    d5, d6 = np.sum(ab * cp, -1), np.sum(ac * cp, -1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    shape = d1.shape
    bary = np.zeros(shape + (3,))
    done = np.zeros(shape, bool)

    def put(mask, u, v, w):
        nonlocal done
        m = mask & ~done
        bary[m] = np.stack([u[m] if np.ndim(u) else np.full(m.sum(), u),
                            v[m] if np.ndim(v) else np.full(m.sum(), v),
                            w[m] if np.ndim(w) else np.full(m.sum(), w)], -1)
        done = done | m

    with np.errstate(divide="ignore", invalid="ignore"):
        put((d1 <= 0) & (d2 <= 0), 1.0, 0.0, 0.0)  # vertex a
        put((d3 >= 0) & (d4 <= d3), 0.0, 1.0, 0.0)  # vertex b
        t = d1 / (d1 - d3)
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), 1 - t, t, 0.0)  # edge ab
        put((d6 >= 0) & (d5 <= d6), 0.0, 0.0, 1.0)  # vertex c
        t = d2 / (d2 - d6)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), 1 - t, 0.0, t)  # edge ac
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        put((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), 0.0, 1 - t, t)  # edge bc
        denom = 1.0 / (va + vb + vc)
        v, w = vb * denom, vc * denom
        put(np.ones(shape, bool), 1 - v - w, v, w)  # interior
    closest = np.einsum("pfk,fkd->pfd", bary, tri)
    return closest, bary


def bind_markers(vertices: np.ndarray, faces: np.ndarray, markers0: np.ndarray,
                 chunk: int = 64) -> MarkerBinding:
    """Bind each marker (M, 3) to the nearest point of the surface (vertices (n, 3), faces (F, 3))."""
    tri = vertices[faces]
    fids, barys, dists = [], [], []
    for s in range(0, len(markers0), chunk):
        p = markers0[s:s + chunk]
        closest, bary = closest_points_on_triangles(p, tri)
        d = np.linalg.norm(closest - p[:, None], axis=-1)
        k = np.argmin(d, axis=1)
        r = np.arange(len(p))
        fids.append(k)
        barys.append(bary[r, k])
        dists.append(d[r, k])
    fid = np.concatenate(fids)
    return MarkerBinding(faces[fid].astype(np.int64), np.concatenate(barys), np.concatenate(dists))


TRACK_CANDIDATES = 8
"""fit_binding_to_tracks: the triangles searched per marker, nearest its frame-0 position first.  A marker's
material point moves by at most a few triangles from its nearest point (the frame-0 estimate's error)."""


def fit_binding_to_tracks(X: np.ndarray, faces: np.ndarray, P: np.ndarray,
                          candidates: int = TRACK_CANDIDATES, chunk: int = 64) -> MarkerBinding:
    """Each marker's material point fitted to its track: the triangle f and barycentrics b (inside the triangle)
    minimising Σ_t ‖Σ_k b_k x_t[f_k] − p_t‖² over the observed frames, for vertex tracks X (w, n, 3), faces
    (F, 3) and marker tracks P (w, M, 3) (NaN at a gap), searched over the ``candidates`` triangles nearest the
    marker on the surface of the first frame that sees it.  On one triangle the cost is a convex quadratic in
    (b_1, b_2): its unconstrained minimum if it lies inside, else the best of the three edges' clamped 1-D minima.
    With one frame this is the nearest surface point (bind_markers).  ``distance``: the residual ‖m_i(x_f) − p_f‖
    at the marker's first observed frame f (0 where never seen)."""
    seen = np.all(np.isfinite(P), axis=-1)  # (w, M)
    first = np.argmax(seen, axis=0)  # (M,) each marker's first observed frame (never seen: 0, searched from X[0]'s
    # centre)
    p0 = np.where(seen.any(axis=0)[:, None], P[first, np.arange(P.shape[1])], X[0].mean(axis=0))
    k = min(candidates, len(faces))
    cand = np.empty((len(p0), k), np.int64)  # (M, k), nearest first on the surface of the marker's first frame
    for f in np.unique(first):
        ids = np.flatnonzero(first == f)
        for s in range(0, len(ids), chunk):  # in chunks of markers, as bind_markers
            sel = ids[s:s + chunk]
            closest, _ = closest_points_on_triangles(p0[sel], X[f][faces])
            d = np.linalg.norm(closest - p0[sel, None], axis=-1)
            near = np.argpartition(d, k - 1, axis=1)[:, :k]
            cand[sel] = np.take_along_axis(near, np.argsort(np.take_along_axis(d, near, 1), axis=1), 1)
    tri = X[:, faces[cand]]  # (w, M, k, 3, 3)
    w = seen[:, :, None, None].astype(float)
    r0 = (tri[..., 0, :] - np.where(seen[..., None], P, 0.0)[:, :, None]) * w  # (w, M, k, 3)
    e1 = (tri[..., 1, :] - tri[..., 0, :]) * w
    e2 = (tri[..., 2, :] - tri[..., 0, :]) * w

    def dot(a, b):
        return np.sum(a * b, axis=(0, 3))  # over frames and xyz: (M, k)

    def cost(b1, b2):
        r = r0 + e1 * b1[None, ..., None] + e2 * b2[None, ..., None]
        return dot(r, r)

    g11, g12, g22, h1, h2 = dot(e1, e1), dot(e1, e2), dot(e2, e2), -dot(e1, r0), -dot(e2, r0)
    with np.errstate(divide="ignore", invalid="ignore"):
        det = g11 * g22 - g12 ** 2
        b1, b2 = (g22 * h1 - g12 * h2) / det, (g11 * h2 - g12 * h1) / det
    inside = np.isfinite(b1) & np.isfinite(b2) & (b1 >= 0) & (b2 >= 0) & (b1 + b2 <= 1)
    best1, best2 = np.where(inside, b1, 0.0), np.where(inside, b2, 0.0)
    best = np.where(inside, cost(best1, best2), np.inf)
    for (u0, v0), (du, dv) in (((0.0, 0.0), (1.0, 0.0)), ((0.0, 0.0), (0.0, 1.0)), ((1.0, 0.0), (-1.0, 1.0))):
        ra, ed = r0 + e1 * u0 + e2 * v0, e1 * du + e2 * dv  # the edge (u0, v0) + s (du, dv), s ∈ [0, 1]
        s = np.clip(-dot(ed, ra) / np.maximum(dot(ed, ed), 1e-300), 0.0, 1.0)
        c1, c2 = u0 + s * du, v0 + s * dv
        c = cost(c1, c2)
        better = ~inside & (c < best)
        best1, best2, best = np.where(better, c1, best1), np.where(better, c2, best2), np.where(better, c, best)
    j = np.argmin(best, axis=1)
    m = np.arange(len(j))
    bary = np.stack([1.0 - best1[m, j] - best2[m, j], best1[m, j], best2[m, j]], axis=-1)
    fid = faces[cand[m, j]].astype(np.int64)
    at = np.einsum("mkd,mk->md", X[first, fid.T].transpose(1, 0, 2), bary)  # on the first observed frame
    return MarkerBinding(fid, bary, np.where(seen.any(axis=0), np.linalg.norm(at - p0, axis=-1), 0.0))


def marker_residuals(binding: MarkerBinding, X: np.ndarray, P: np.ndarray) -> np.ndarray:
    """r_t^i = m_i(x_t) − p_t^i (w, M, 3) where marker i is observed at frame t (P finite), 0 at a gap
    (a NaN in P: the marker was not seen)."""
    observed = np.all(np.isfinite(P), axis=-1, keepdims=True)
    return np.where(observed, binding.positions(X) - np.where(observed, P, 0.0), 0.0)


def marker_loss(binding: MarkerBinding, X: np.ndarray, P: np.ndarray) -> tuple[float, np.ndarray]:
    """L = Σ_t Σ_{i observed at t} ‖m_i(x_t) − p_t^i‖² and dL/dX, for X (w, n, 3) and markers P (w, M, 3), NaN
    at a gap; a frame with no observed marker adds 0 to L and to dL/dX."""
    r = marker_residuals(binding, X, P)
    return float(np.sum(r * r)), binding.scatter(2.0 * r, X.shape[1])
