"""Point location in a tet mesh: the element holding a point and its barycentric coordinates, in linear
(m, 4) or quadratic (m, 10) tets (the quadratic element map inverted by Newton).

Used to re-bind the Gaussians to the tets of a deformed configuration (stages/render/image_loss.py).
Pure functions over arrays: nothing here reads files or prints.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from stages.sim.mesh import shape_matrices
from stages.sim.quadrature import shape_reference_gradients, shape_values


def tet_barycentrics(points: np.ndarray, vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (P, 4) of points (P, 3) in the tets (P, 4) given per point (rows sum to 1;
    all ≥ 0 inside the tet, affine extrapolation outside)."""
    lam = np.linalg.solve(shape_matrices(vertices, tets), (points - vertices[tets[:, 0]])[..., None])[..., 0]
    return np.concatenate([1.0 - lam.sum(1, keepdims=True), lam], axis=1)


def locate_in_tets_brute(points: np.ndarray, vertices: np.ndarray, tets: np.ndarray, candidates: int = 16,
                         widen: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """(tet (P,), barycentric (P, 4)): for each point, among the ``candidates`` tets whose centroids are nearest,
    the one whose smallest barycentric coordinate is the largest — a tet holding the point when one of them
    does; when none does (the point is outside the mesh, or in a sliver far from its centroid), the same over
    the ``candidates · widen`` nearest.  One point and one tet at a time (the slow twin of
    :func:`locate_in_tets`)."""
    cent = vertices[tets].mean(1)
    k1, k2 = min(candidates, len(tets)), min(candidates * widen, len(tets))
    tet = np.empty(len(points), np.int64)
    for i, p in enumerate(points):
        order = np.argsort(np.linalg.norm(cent - p, axis=1), kind="stable")
        for k in (k1, k2):
            scores = [tet_barycentrics(p[None], vertices, tets[[j]])[0].min() for j in order[:k]]
            tet[i] = order[int(np.argmax(scores))]
            if max(scores) >= -1e-9:
                break
    return tet, tet_barycentrics(points, vertices, tets[tet])


def locate_in_tets(points: np.ndarray, vertices: np.ndarray, tets: np.ndarray, candidates: int = 16,
                   widen: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """:func:`locate_in_tets_brute`, vectorised with a k-d tree of the tet centroids."""
    points = np.asarray(points, np.float64)
    c = vertices[tets]  # (M, 4, 3)
    x0 = c[:, 0]
    tree = cKDTree(c.mean(1))
    every: list = []  # D⁻¹ of every tet (M, 3, 3), made once if few points do not need only their candidates'

    def best(p: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        _, cand = tree.query(p, k=k)
        cand = np.asarray(cand, np.int64).reshape(len(p), k)
        if cand.size < len(tets) and not every:  # the candidates' inverses only (the same floats)
            Dc = np.linalg.inv(shape_matrices(vertices, tets[cand.ravel()])).reshape(len(p), k, 3, 3)
        else:
            if not every:
                every.append(np.linalg.inv(shape_matrices(vertices, tets)))
            Dc = every[0][cand]
        lam = np.einsum("pkij,pkj->pki", Dc, p[:, None] - x0[cand])
        b = np.concatenate([1.0 - lam.sum(-1, keepdims=True), lam], axis=-1)  # (P, k, 4)
        j = np.argmax(b.min(2), axis=1)
        r = np.arange(len(p))
        return cand[r, j], b[r, j]

    tet, bary = best(points, min(candidates, len(tets)))
    far = np.flatnonzero(bary.min(1) < -1e-9)
    if len(far):
        tet[far], bary[far] = best(points[far], min(candidates * widen, len(tets)))
    return tet, bary


def invert_element_map(points: np.ndarray, vertices: np.ndarray, tets: np.ndarray, element: np.ndarray,
                       bary0: np.ndarray, iterations: int = 30, tol: float = 1e-13) -> np.ndarray:
    """Barycentric (corner) coordinates (P, 4) of points (P, 3) in their elements (P,) of a quadratic mesh
    (vertices (n, 3), tets (m, 10)): Newton on Σ_a N_a(ξ) x_a = p from bary0 (e.g. the corner tet's
    barycentrics), ξ = (β₁, β₂, β₃), the update solving (Σ_a x_a ⊗ ∂N_a/∂ξ) Δξ = p − x(ξ); stops when
    every |Δξ| < tol."""
    xe = np.asarray(vertices, np.float64)[np.asarray(tets)[element]]  # (P, 10, 3)
    xi = np.asarray(bary0, np.float64)[:, 1:].copy()
    for _ in range(iterations):
        b = np.concatenate([1.0 - xi.sum(1, keepdims=True), xi], axis=1)
        r = np.asarray(points, np.float64) - np.einsum("pk,pkd->pd", shape_values(2, b), xe)
        J = np.einsum("pki,pkj->pij", xe, shape_reference_gradients(2, b))
        det = np.linalg.det(J)
        ok = np.isfinite(det) & (np.abs(det) > 1e-300)
        J[~ok] = np.eye(3)
        d = np.where(ok[:, None], np.linalg.solve(J, r[..., None])[..., 0], np.nan)  # NaN: a singular map
        xi += d
        if np.nanmax(np.abs(d), initial=0.0) < tol:
            break
    return np.concatenate([1.0 - xi.sum(1, keepdims=True), xi], axis=1)


def locate_in_elements(points: np.ndarray, vertices: np.ndarray, tets: np.ndarray, candidates: int = 16,
                       hint: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(element (P,), barycentric corner coordinates (P, 4)) of points (P, 3) in a mesh of linear (m, 4) or
    quadratic (m, 10) tets at positions vertices (n, 3): :func:`locate_in_tets` in the corner tets, then for
    quadratic tets the exact inverse of the (curved) element map (:func:`invert_element_map`); a point that
    this puts outside its element (a curved element bulges past its corner tet) is inverted in each of the
    ``candidates`` elements with the nearest corner centroids and kept in the one it is most inside.
    ``hint`` (P,): a guess of each point's element (e.g. its host before a small motion); a point strictly inside
    the hinted corner tet (every barycentric > 1e-9: the one tet that holds it) keeps it without the search."""
    tets = np.asarray(tets, np.int64)
    points = np.asarray(points, np.float64)
    if hint is None:
        host, bary = locate_in_tets(points, vertices, tets[:, :4])
    else:
        host = np.asarray(hint, np.int64).copy()
        c = tets[host, :4]  # the arithmetic of locate_in_tets, so a kept hint gives the very same floats
        lam = np.einsum("pij,pj->pi", np.linalg.inv(shape_matrices(vertices, c)), points - vertices[c[:, 0]])
        bary = np.concatenate([1.0 - lam.sum(-1, keepdims=True), lam], axis=-1)
        out = np.flatnonzero(~(bary.min(1) > 1e-9))
        if len(out):
            host[out], bary[out] = locate_in_tets(points[out], vertices, tets[:, :4])
    if tets.shape[1] != 10:
        return host, bary
    bary = invert_element_map(points, vertices, tets, host, bary)
    far = np.flatnonzero(~(bary.min(1) >= -1e-9))  # outside, or NaN
    if len(far):  # a curved element holds the point, not the corner tet: the exact inverse in nearby elements
        k = min(candidates, len(tets))
        _, cand = cKDTree(vertices[tets[:, :4]].mean(1)).query(points[far], k=k)
        cand = np.asarray(cand, np.int64).reshape(len(far), k).ravel()
        rep = np.repeat(points[far], k, axis=0)
        b0 = tet_barycentrics(rep, vertices, tets[cand, :4])
        b = invert_element_map(rep, vertices, tets, cand, b0).reshape(len(far), k, 4)
        score = np.where(np.isfinite(b).all(2), b.min(2), -np.inf)
        j = np.argmax(score, axis=1)
        better = score[np.arange(len(far)), j] > np.nan_to_num(bary[far].min(1), nan=-np.inf)
        pick = far[better]
        host[pick] = cand.reshape(len(far), k)[better, j[better]]
        bary[pick] = b[better, j[better]]
    return host, bary
