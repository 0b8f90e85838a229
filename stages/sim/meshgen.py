"""Structured tet meshes built programmatically (tests and benchmarks): a box of hexes, each split
into 6 tets along its main diagonal (Kuhn), which conforms across neighbouring hexes."""
from __future__ import annotations

import itertools

import numpy as np

from .mesh import rest_quantities, signed_volumes


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
    """Boundary triangles (faces that belong to one tet), oriented outward."""
    local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    faces = tets[:, local].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[cnt[inv.reshape(-1)] == 1]


def mesh_artefact(vertices: np.ndarray, tets: np.ndarray, density: float, tet_region: np.ndarray | None = None,
                  region_names: tuple[str, ...] = ("body",)):
    """A MeshArtefact (in memory) with rest quantities computed from vertices and tets."""
    from ..artefacts import MeshArtefact

    vol, dm_inv, masses = rest_quantities(vertices, tets, density)
    region = np.zeros(len(tets), np.int64) if tet_region is None else np.asarray(tet_region, np.int64)
    return MeshArtefact(vertices=np.asarray(vertices, np.float64), tets=np.asarray(tets, np.int64),
                        surface_faces=surface_faces(tets), tet_region=region, region_names=list(region_names),
                        rest_volumes=vol, dm_inv=dm_inv, vertex_masses=masses, density=float(density))
