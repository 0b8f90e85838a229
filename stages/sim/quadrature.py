"""Linear (P1, 4-node) and quadratic (P2, 10-node) tetrahedra: shape functions, quadrature points,
lumped masses, mid-edge nodes (numpy, float64).

P2 node order is VTK_QUADRATIC_TETRA (meshio "tetra10"): corners 0–3, then the mid-edge nodes of the
edges (0,1), (1,2), (0,2), (0,3), (1,3), (2,3).  With barycentric coordinates L = (L0, L1, L2, L3),
L1..L3 = ξ the reference coordinates and L0 = 1 − ξ1 − ξ2 − ξ3:

    P1: N_a = L_a;            P2: N_a = L_a (2 L_a − 1) at corners,  N_ab = 4 L_a L_b at edge (a, b).

The element map is isoparametric, X(ξ) = Σ_a N_a(ξ) X_a, so mid-edge nodes moved onto a curved
surface give curved elements; J = ∂X/∂ξ, ∇_X N_a = J⁻ᵀ ∂N_a/∂ξ, and at any point

    x(ξ) = Σ_a N_a(ξ) x_a,        F(ξ) = Σ_a x_a ⊗ ∇_X N_a(ξ).

Elasticity is integrated over quadrature points (:class:`Quadrature`): P1 one point per tet (exact),
P2 the 4-point degree-2 rule (Keast), which integrates ∇N_a·∇N_b — the small-strain P2 stiffness —
exactly on straight tets.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .mesh import boundary_faces, shape_matrices

P2_EDGES = np.array([(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)])
NODES_PER_ORDER = {1: 4, 2: 10}
_DL_DXI = np.array([[-1.0, -1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # ∂L_a/∂ξ_j

# Quadrature rules on the reference tet: barycentric points (Q, 4), weights as fractions of the volume.
_A, _B = 0.5854101966249685, 0.1381966011250105  # (5 + 3√5)/20, (5 − √5)/20
RULES = {
    1: (np.full((1, 4), 0.25), np.ones(1)),
    2: (np.array([[_A, _B, _B, _B], [_B, _A, _B, _B], [_B, _B, _A, _B], [_B, _B, _B, _A]]), np.full(4, 0.25)),
}


def element_order(tets: np.ndarray) -> int:
    """1 for (m, 4) linear tets, 2 for (m, 10) quadratic tets."""
    k = int(np.shape(tets)[-1])
    if k not in (4, 10):
        raise ValueError(f"a tet has 4 (linear) or 10 (quadratic) nodes, not {k}")
    return 1 if k == 4 else 2


def shape_values(order: int, bary: np.ndarray) -> np.ndarray:
    """N_a at points given by barycentric coordinates bary (p, 4) -> (p, 4 | 10)."""
    L = np.asarray(bary, np.float64)
    if order == 1:
        return L.copy()
    corners = L * (2.0 * L - 1.0)
    edges = 4.0 * L[:, P2_EDGES[:, 0]] * L[:, P2_EDGES[:, 1]]
    return np.concatenate([corners, edges], axis=1)


def shape_reference_gradients(order: int, bary: np.ndarray) -> np.ndarray:
    """∂N_a/∂ξ (p, k, 3) at barycentric points (p, 4)."""
    L = np.asarray(bary, np.float64)
    p = len(L)
    if order == 1:
        return np.broadcast_to(_DL_DXI, (p, 4, 3)).copy()
    dN_dL = np.zeros((p, 10, 4))  # ∂N_a/∂L_b
    for a in range(4):
        dN_dL[:, a, a] = 4.0 * L[:, a] - 1.0
    for e, (a, b) in enumerate(P2_EDGES):
        dN_dL[:, 4 + e, a] = 4.0 * L[:, b]
        dN_dL[:, 4 + e, b] = 4.0 * L[:, a]
    return dN_dL @ _DL_DXI


def point_map(vertices: np.ndarray, tets: np.ndarray, element_ids: np.ndarray, bary: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For points of elements ``element_ids`` (p,) at barycentric coordinates ``bary`` (p, 4) of the
    reference tet: shape values N (p, k), rest-space gradients G (p, k, 3) and det J (p,), so that a
    point moves as Σ_a N_a x_a and has F = Σ_a x_a ⊗ G_a.  vertices (n, 3) are the rest positions."""
    tets = np.asarray(tets)
    order = element_order(tets)
    element_ids = np.asarray(element_ids, np.int64)
    N = shape_values(order, bary)
    dN = shape_reference_gradients(order, bary)  # (p, k, 3)
    Xe = np.asarray(vertices, np.float64)[tets[element_ids]]  # (p, k, 3)
    J = np.einsum("pki,pkj->pij", Xe, dN)  # J_ij = ∂X_i/∂ξ_j
    detJ = np.linalg.det(J)
    G = np.einsum("pkj,pij->pki", dN, np.linalg.inv(J).transpose(0, 2, 1))  # J⁻ᵀ ∂N/∂ξ
    return N, G, detJ


@dataclass(frozen=True, eq=False)
class Quadrature:
    """Quadrature points of a tet mesh: Σ_e ∫_e V Ψ(F) ≈ Σ_q weight_q Ψ(F_q), F_q = x[nodes_q]ᵀ grad_q."""

    nodes: np.ndarray  # (q, k) int: node ids of the point's element (k = 4 or 10)
    grad: np.ndarray  # (q, k, 3): ∇_X N_a at the point, 1/m
    weight: np.ndarray  # (q,) m³
    element: np.ndarray  # (q,) int: the element the point lies in

    @property
    def n_points(self) -> int:
        return int(len(self.weight))

    def subset(self, ids: np.ndarray) -> "Quadrature":
        """The points ``ids`` only (e.g. a cubature selection)."""
        ids = np.asarray(ids, np.int64)
        return Quadrature(self.nodes[ids], self.grad[ids], self.weight[ids], self.element[ids])


def linear_quadrature(tets: np.ndarray, dm_inv: np.ndarray, volumes: np.ndarray) -> Quadrature:
    """One point per linear tet from its Dm⁻¹ (m, 3, 3) and rest volume (m,): G_a = row a−1 of Dm⁻¹,
    G_0 = −Σ_a G_a, weight = V (the per-tet math of stages.sim.mesh.rest_quantities, bit for bit)."""
    tets = np.ascontiguousarray(tets, np.int64)
    dm_inv = np.asarray(dm_inv, np.float64)
    g = np.empty(dm_inv.shape[:-2] + (4, 3))
    g[..., 1:, :] = dm_inv
    g[..., 0, :] = -dm_inv.sum(axis=-2)
    return Quadrature(nodes=tets, grad=g, weight=np.ascontiguousarray(volumes, np.float64),
                      element=np.arange(len(tets)))


def build_quadrature(vertices: np.ndarray, tets: np.ndarray) -> Quadrature:
    """The quadrature points of every element (P1: 1 per tet, P2: 4 per tet), element-major.
    Raises ValueError when an element is inverted or degenerate at a quadrature point (det J ≤ 0)."""
    tets = np.asarray(tets, np.int64)
    order = element_order(tets)
    if order == 1:
        dm = shape_matrices(np.asarray(vertices, np.float64), tets)
        vol = np.linalg.det(dm) / 6.0
        if np.any(vol <= 0):
            raise ValueError(f"element {int(np.flatnonzero(vol <= 0)[0])} is inverted or degenerate (volume ≤ 0)")
        return linear_quadrature(tets, np.linalg.inv(dm), vol)
    pts, frac = RULES[order]
    m, Q = len(tets), len(frac)
    element = np.repeat(np.arange(m), Q)
    bary = np.tile(pts, (m, 1))
    _, G, detJ = point_map(vertices, tets, element, bary)
    if np.any(detJ <= 0):
        bad = int(element[np.flatnonzero(detJ <= 0)[0]])
        raise ValueError(f"element {bad} is inverted or degenerate (det J ≤ 0 at a quadrature point)")
    weight = np.tile(frac, m) * detJ / 6.0
    return Quadrature(nodes=tets[element], grad=G, weight=weight, element=element)


def element_volumes(quad: Quadrature, n_elements: int) -> np.ndarray:
    """Rest volume of each element, (m,) m³ (the sum of its quadrature weights)."""
    return np.bincount(quad.element, weights=quad.weight, minlength=n_elements)


def lumped_masses(vertices: np.ndarray, tets: np.ndarray, density: float, volumes: np.ndarray | None = None
                  ) -> np.ndarray:
    """Lumped nodal masses (n,) kg.  P1: ρV/4 per corner.  P2: HRZ lumping (the diagonal of the
    consistent mass matrix scaled to the element mass): ρV/36 per corner, 4ρV/27 per mid-edge node."""
    tets = np.asarray(tets, np.int64)
    order = element_order(tets)
    if volumes is None:
        volumes = element_volumes(build_quadrature(vertices, tets), len(tets))
    share = np.full(4, 0.25) if order == 1 else np.concatenate([np.full(4, 1 / 36), np.full(6, 4 / 27)])
    masses = np.zeros(len(vertices))
    np.add.at(masses, tets.reshape(-1), (density * np.asarray(volumes)[:, None] * share[None, :]).reshape(-1))
    return masses


def edge_midpoints(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The unique edges (e, 2) of linear tets (m, 4) and, per tet, the index (m, 6) of its edges
    (0,1), (1,2), (0,2), (0,3), (1,3), (2,3) into them."""
    e = np.sort(np.asarray(tets)[:, P2_EDGES].reshape(-1, 2), axis=1)
    uniq, inv = np.unique(e, axis=0, return_inverse=True)
    return uniq, inv.reshape(-1, 6)


def quadratic_tets(vertices: np.ndarray, tets: np.ndarray, project=None) -> tuple[np.ndarray, np.ndarray]:
    """P2 mesh from a P1 mesh: (vertices (n + e, 3), tets (m, 10)); the first n vertices are the
    corners as given, then one node per unique edge at its midpoint.  ``project`` (optional) maps the
    midpoints of boundary edges (b, 3) onto the curved input surface, e.g. a closest-point query."""
    tets = np.asarray(tets, np.int64)
    vertices = np.asarray(vertices, np.float64)
    edges, per_tet = edge_midpoints(tets)
    mid = 0.5 * (vertices[edges[:, 0]] + vertices[edges[:, 1]])
    if project is not None:
        faces = boundary_faces(tets)
        fe = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        on_boundary = np.isin(_edge_keys(edges, len(vertices)), _edge_keys(fe, len(vertices)))
        if on_boundary.any():
            mid[on_boundary] = np.asarray(project(mid[on_boundary]), np.float64)
    n = len(vertices)
    return np.vstack([vertices, mid]), np.concatenate([tets, per_tet + n], axis=1)


def jacobian_ratio(vertices: np.ndarray, tets10: np.ndarray) -> np.ndarray:
    """Per quadratic element, min det J / det J_straight over its corners, mid-edge nodes, centroid and
    quadrature points (m,): 1 for straight elements, ≤ 0 for an element folded by curved edges."""
    tets10 = np.asarray(tets10, np.int64)
    L = np.vstack([np.eye(4), 0.5 * (np.eye(4)[P2_EDGES[:, 0]] + np.eye(4)[P2_EDGES[:, 1]]),
                   np.full((1, 4), 0.25), RULES[2][0]])  # (15, 4) sample points
    m, S = len(tets10), len(L)
    _, _, detJ = point_map(vertices, tets10, np.repeat(np.arange(m), S), np.tile(L, (m, 1)))
    straight = np.linalg.det(shape_matrices(np.asarray(vertices, np.float64), tets10[:, :4]))
    return (detJ.reshape(m, S) / straight[:, None]).min(axis=1)


def mid_edge_closure(ids: np.ndarray, tets10: np.ndarray) -> np.ndarray:
    """Vertex ids ``ids`` (sorted) plus every mid-edge node of a quadratic mesh whose two edge ends are
    in ``ids`` (so a handle or load selected on corners holds whole edges); linear tets: ids as given."""
    tets10 = np.asarray(tets10, np.int64)
    if tets10.shape[1] != 10:
        return np.asarray(ids, np.int64)
    ids = np.unique(np.asarray(ids, np.int64))
    if ids.size == 0:
        return ids
    a, b, mid = tets10[:, P2_EDGES[:, 0]], tets10[:, P2_EDGES[:, 1]], tets10[:, 4:]
    both = np.isin(a, ids) & np.isin(b, ids)
    return np.union1d(ids, mid[both])


def _edge_keys(edges: np.ndarray, n: int) -> np.ndarray:
    return edges[:, 0].astype(np.int64) * n + edges[:, 1]


def quadratic_surface(tets10: np.ndarray) -> np.ndarray:
    """Outward boundary triangles (4k, 3) of a P2 mesh over all its nodes: each quadratic face
    (a, b, c) with mid-edge nodes m_ab, m_bc, m_ca is split into (a, m_ab, m_ca), (m_ab, b, m_bc),
    (m_ca, m_bc, c), (m_ab, m_bc, m_ca)."""
    tets10 = np.asarray(tets10, np.int64)
    corner = boundary_faces(tets10[:, :4])
    n = int(tets10.max()) + 1
    keys = {}
    for e, (a, b) in enumerate(P2_EDGES):
        u, v = np.minimum(tets10[:, a], tets10[:, b]), np.maximum(tets10[:, a], tets10[:, b])
        for k, node in zip(u * n + v, tets10[:, 4 + e]):
            keys[int(k)] = int(node)

    def mid(a, b):
        return np.array([keys[int(min(i, j) * n + max(i, j))] for i, j in zip(a, b)], np.int64)

    a, b, c = corner.T
    mab, mbc, mca = mid(a, b), mid(b, c), mid(c, a)
    tris = np.stack([np.stack([a, mab, mca], 1), np.stack([mab, b, mbc], 1), np.stack([mca, mbc, c], 1),
                     np.stack([mab, mbc, mca], 1)], axis=1)
    return tris.reshape(-1, 3)
