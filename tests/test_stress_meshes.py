"""Structured tet meshes for the stress, export and rollout tests (no tests here)."""
from __future__ import annotations

import itertools

import numpy as np

from stages.artefacts import MeshArtefact
from stages.sim.mesh import rest_quantities


def block_mesh(size=(0.1, 0.02, 0.02), cells=(5, 1, 1), origin=(0.0, 0.0, 0.0)):
    """Box [origin, origin+size] split into cells, each cube into 6 positive tets (Freudenthal).

    Returns (vertices (n, 3), tets (m, 4), surface faces (k, 3) outward)."""
    nx, ny, nz = cells
    xs = [np.linspace(origin[d], origin[d] + size[d], cells[d] + 1) for d in range(3)]
    grid = np.stack(np.meshgrid(*xs, indexing="ij"), axis=-1).reshape(-1, 3)

    def vid(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    tets = []
    for i, j, k in itertools.product(range(nx), range(ny), range(nz)):
        for perm in itertools.permutations(range(3)):
            c = np.array([i, j, k])
            path = [vid(*c)]
            for ax in perm:
                c = c.copy()
                c[ax] += 1
                path.append(vid(*c))
            tets.append(path)
    tets = np.array(tets, np.int64)
    p = grid[tets]
    det = np.linalg.det(np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], -1))
    flip = det < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    faces = {}
    for t in tets:
        for a, b, c, d in ((0, 2, 1, 3), (0, 1, 3, 2), (0, 3, 2, 1), (1, 2, 3, 0)):
            key = tuple(sorted((t[a], t[b], t[c])))
            faces.setdefault(key, []).append((t[a], t[b], t[c]))
    surf = np.array([v[0] for v in faces.values() if len(v) == 1], np.int64)
    return grid, tets, surf


def block_artefact(size=(0.1, 0.02, 0.02), cells=(5, 1, 1), density=1000.0, region_split_x=None,
                   origin=(0.0, 0.0, 0.0)) -> MeshArtefact:
    """A MeshArtefact of a block; with region_split_x, tets whose centroid x > split are region 'b'."""
    v, tets, faces = block_mesh(size, cells, origin)
    vol, dm_inv, masses = rest_quantities(v, tets, density)
    region = np.zeros(len(tets), np.int64)
    names = ["body"]
    if region_split_x is not None:
        region = (v[tets].mean(axis=1)[:, 0] > region_split_x).astype(np.int64)
        names = ["body", "b"]
    return MeshArtefact(v, tets, faces, region, names, vol, dm_inv, masses, density)
