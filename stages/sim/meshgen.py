"""Structured tet meshes built programmatically (tests and benchmarks): a box of hexes, each split
into 6 tets along its main diagonal (Kuhn), which conforms across neighbouring hexes."""
from __future__ import annotations

import itertools

import numpy as np

from .mesh import boundary_faces, signed_volumes


def box_tets(cells: tuple[int, int, int], size: tuple[float, float, float],
             origin: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (n, 3) m, tets (6·nx·ny·nz, 4)) of an axis-aligned box of nx×ny×nz hex cells."""
    nx, ny, nz = cells
    gx, gy, gz = (np.linspace(0.0, s, c + 1) + o for s, c, o in zip(size, cells, origin))
    X, Y, Z = np.meshgrid(gx, gy, gz, indexing="ij")
    verts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    vid = np.arange(verts.shape[0]).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"))
    tets = []
    for perm in itertools.permutations(range(3)):
        corner = np.zeros(3, int)
        path = [corner.copy()]
        for ax in perm:
            corner[ax] = 1
            path.append(corner.copy())
        tets.append(np.stack([vid[i + c[0], j + c[1], k + c[2]] for c in path], axis=1))
    tets = np.concatenate(tets, axis=0)
    neg = signed_volumes(verts, tets) < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    return verts, tets


def surface_faces(tets: np.ndarray) -> np.ndarray:
    """Boundary triangles (faces that belong to one tet), oriented outward (:func:`.mesh.boundary_faces`)."""
    return boundary_faces(tets)


def refine_tets(vertices: np.ndarray, tets: np.ndarray, tet_region: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split every linear tet (m, 4) into 8 through its edge midpoints (Bey 1995): (vertices (n + e, 3),
    tets (8m, 4), tet_region (8m,)); the first n vertices are the original ones, so positions of the
    coarse mesh are a prefix of the fine mesh's."""
    vertices = np.asarray(vertices, np.float64)
    tets = np.asarray(tets, np.int64)
    n = len(vertices)
    edges = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])
    e = np.sort(tets[:, edges].reshape(-1, 2), axis=1)
    uniq, inv = np.unique(e, axis=0, return_inverse=True)
    mid = 0.5 * (vertices[uniq[:, 0]] + vertices[uniq[:, 1]])
    m = inv.reshape(-1, 6) + n  # midpoint ids: 01 02 03 12 13 23
    a, b, c, d = tets.T
    m01, m02, m03, m12, m13, m23 = m.T
    children = [
        (a, m01, m02, m03), (m01, b, m12, m13), (m02, m12, c, m23), (m03, m13, m23, d),
        (m01, m02, m03, m13), (m01, m02, m12, m13), (m02, m03, m13, m23), (m02, m12, m13, m23),
    ]
    new = np.stack([np.stack(ch, axis=1) for ch in children], axis=1).reshape(-1, 4)
    verts = np.vstack([vertices, mid])
    neg = signed_volumes(verts, new) < 0  # keep positive orientation
    new[neg] = new[neg][:, [0, 2, 1, 3]]
    return verts, new, np.repeat(np.asarray(tet_region), 8)
