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
                       hint: np.ndarray | None = None, relocator: "Relocator | None" = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """(element (P,), barycentric corner coordinates (P, 4)) of points (P, 3) in a mesh of linear (m, 4) or
    quadratic (m, 10) tets at positions vertices (n, 3): :func:`locate_in_tets` in the corner tets, then for
    quadratic tets the exact inverse of the (curved) element map (:func:`invert_element_map`); a point that
    this puts outside its element (a curved element bulges past its corner tet) is inverted in each of the
    ``candidates`` elements with the nearest corner centroids and kept in the one it is most inside.
    ``hint`` (P,): a guess of each point's element (e.g. its host before a small motion); a point strictly inside
    the hinted corner tet (every barycentric > 1e-9: the one tet that holds it) keeps it without the search.
    ``relocator``: a :class:`Relocator` of these points in these tets, which finds the corner tets from ``hint``
    with less work (the same tets and floats as without it)."""
    tets = np.asarray(tets, np.int64)
    points = np.asarray(points, np.float64)
    if hint is None:
        host, bary = locate_in_tets(points, vertices, tets[:, :4])
    elif relocator is not None:
        if not (np.array_equal(relocator.points, points) and np.array_equal(relocator.tets, tets[:, :4])):
            raise ValueError("the relocator was made for other points or another mesh")
        host, bary = relocator(vertices, hint)
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


def tet_neighbours(tets: np.ndarray) -> np.ndarray:
    """(M, 4): the tet across the face opposite each corner of each tet (M, 4) (the face corner i's barycentric
    coordinate vanishes on), −1 on the mesh's boundary."""
    tets = np.asarray(tets, np.int64)[:, :4]
    M = len(tets)
    faces = np.sort(np.stack([np.delete(tets, i, axis=1) for i in range(4)], axis=1).reshape(-1, 3), axis=1)
    order = np.lexsort(faces.T[::-1])
    same = np.flatnonzero(np.all(faces[order[1:]] == faces[order[:-1]], axis=1))  # a face shared by two tets
    out = np.full(4 * M, -1, np.int64)
    a, b = order[same], order[same + 1]
    out[a], out[b] = b // 4, a // 4
    return out.reshape(M, 4)


class Relocator:
    """:func:`locate_in_tets` of the same points (P, 3) in one tet mesh (M, 4 | 10: its corner tets) as the mesh
    moves, given a guess of each point's tet — the same tets and floats, with less work:

    1. a point strictly inside its hinted tet (every barycentric > 1e-9: the one tet that holds it) keeps it;
    2. the others walk from it through the face of their most negative barycentric coordinate (at most ``walk``
       steps, stopping at the boundary) and keep the first tet that holds them strictly;
    3. the rest (outside the mesh, on a face, or off the walk) get :func:`locate_in_tets`'s own rule — the best of
       the ``candidates`` tets with the nearest centroids, else of the ``candidates · widen`` nearest — from one
       k-d tree query of the ``candidates · widen`` nearest (sorted: their first ``candidates`` are the nearest
       ``candidates``), the barycentrics of each candidate tet computed once.

    Every barycentric is computed with :func:`locate_in_tets`' arithmetic (D⁻¹ per tet by numpy's batched inverse,
    the same einsums), so a tet found here gives the very floats the search gives (tests/test_sim_locate.py).
    (A list of each point's nearest tets kept from an earlier configuration, valid while the centroids move less
    than its margin, was tried: on the Bar of bench/adapt_speed.py the anchor's centroids move by 0.5–9 mm between
    re-bindings, more than the margin of twice the needed list, and nearly every call had to query again.)"""

    def __init__(self, points: np.ndarray, tets: np.ndarray, candidates: int = 16, widen: int = 4, walk: int = 8):
        self.points = np.array(points, np.float64)  # (P, 3)
        self.tets = np.ascontiguousarray(np.asarray(tets, np.int64)[:, :4])  # (M, 4)
        M = len(self.tets)
        self.k1, self.k2 = min(candidates, M), min(candidates * widen, M)
        self.walk = walk
        self.neighbours = tet_neighbours(self.tets)  # (M, 4)

    def __call__(self, vertices: np.ndarray, hint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(tet (P,), barycentric (P, 4)) of the points in the tets at ``vertices`` (n, 3); ``hint`` (P,) a guess of
        each point's tet (e.g. its tet before a small motion)."""
        x = np.asarray(vertices, np.float64)
        P, M = len(self.points), len(self.tets)
        dinv = np.empty((M, 3, 3))
        have = np.zeros(M, bool)

        def inverses(ids: np.ndarray) -> np.ndarray:  # D⁻¹ of the tets ``ids`` (any shape), each inverted once a call
            flat = ids.ravel()
            new = flat[~have[flat]]
            if len(new):
                new = np.unique(new)
                dinv[new] = np.linalg.inv(shape_matrices(x, self.tets[new]))
                have[new] = True
            return dinv[ids]

        def bary(rows: np.ndarray, t: np.ndarray) -> np.ndarray:  # (P', 4) of points ``rows`` in tets t (P',)
            lam = np.einsum("pij,pj->pi", inverses(t), self.points[rows] - x[self.tets[t, 0]])
            return np.concatenate([1.0 - lam.sum(-1, keepdims=True), lam], axis=-1)

        tet = np.asarray(hint, np.int64).copy()
        b = bary(np.arange(P), tet)
        rows = np.flatnonzero(~(b.min(1) > 1e-9))
        walkers, cur, bc = rows, tet[rows], b[rows]
        for _ in range(self.walk):
            nxt = self.neighbours[cur, np.argmin(bc, axis=1)]  # across the face of the most negative coordinate
            go = nxt >= 0
            walkers, cur = walkers[go], nxt[go]
            if not len(walkers):
                break
            bc = bary(walkers, cur)
            ok = bc.min(1) > 1e-9
            tet[walkers[ok]], b[walkers[ok]] = cur[ok], bc[ok]
            walkers, cur, bc = walkers[~ok], cur[~ok], bc[~ok]
        rest = rows[~(b[rows].min(1) > 1e-9)]
        if len(rest):  # locate_in_tets' rule on the nearest k1, then (none holding the point) on the nearest k2
            p = self.points[rest]
            _, near = cKDTree(x[self.tets].mean(1)).query(p, k=self.k2)
            near = np.asarray(near, np.int64).reshape(len(rest), self.k2)
            lam = np.einsum("pkij,pkj->pki", inverses(near), p[:, None] - x[self.tets[near, 0]])
            bb = np.concatenate([1.0 - lam.sum(-1, keepdims=True), lam], axis=-1)  # (R, k2, 4)
            score = bb.min(2)
            r = np.arange(len(rest))
            j = np.argmax(score[:, :self.k1], axis=1)
            far = score[r, j] < -1e-9
            j[far] = np.argmax(score[far], axis=1)
            tet[rest], b[rest] = near[r, j], bb[r, j]
        return tet, b
