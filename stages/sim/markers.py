"""The marker observation model of ``rsl adapt`` (paper Eq. 4, windowed) and its gradient.

L = Σ_t Σ_i ‖m_i(x_t) − p_t^i‖² over the observed (t, i) only (a motion-capture gap, NaN in p, adds nothing),
with each marker bound to the surface point nearest its frame-0 position, m_i(x) = Σ_k b_ik x[f_ik]
(barycentric on the nearest surface triangle), so dL/dx_t = Σ_{i observed at t} 2 (m_i − p^i) ⊗ b_i.

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
