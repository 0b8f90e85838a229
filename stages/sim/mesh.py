"""Rest-shape quantities of a tet mesh (numpy, float64) and the deformation gradient (JAX)."""
from __future__ import annotations

import numpy as np


def shape_matrices(x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """D = [x1−x0, x2−x0, x3−x0] per tet, (m, 3, 3) with edge vectors as columns."""
    p = x[tets]
    return np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=-1)


def signed_volumes(x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """det(D)/6 per tet, m³ (positive for the orientation rsl uses)."""
    return np.linalg.det(shape_matrices(x, tets)) / 6.0


def rest_quantities(vertices: np.ndarray, tets: np.ndarray, density: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rest volumes (m,), Dm⁻¹ (m,3,3), lumped vertex masses (n,)) — each tet gives ρV/4 to its vertices.
    Quadratic tets (m, 10): V = Σ of the element's quadrature weights (curved elements included), Dm⁻¹
    of the corner tet, HRZ lumped masses (stages.sim.quadrature)."""
    tets = np.asarray(tets)
    if tets.shape[-1] == 10:
        from .quadrature import build_quadrature, element_volumes, lumped_masses  # it imports this module

        vol = element_volumes(build_quadrature(vertices, tets), len(tets))
        dm_inv = np.linalg.inv(shape_matrices(vertices, tets[:, :4]))
        return vol, dm_inv, lumped_masses(vertices, tets, density, vol)
    dm = shape_matrices(vertices, tets)
    vol = np.linalg.det(dm) / 6.0
    dm_inv = np.linalg.inv(dm)
    masses = np.zeros(len(vertices))
    np.add.at(masses, tets.reshape(-1), np.repeat(density * vol / 4.0, 4))
    return vol, dm_inv, masses


def deformation_gradients(x, tets, dm_inv):
    """F = Ds Dm⁻¹ per tet (JAX or numpy), x (n, 3) -> (m, 3, 3)."""
    p = x[tets]
    ds = (p[:, 1:4] - p[:, 0:1]).transpose(0, 2, 1)  # columns x_i − x_0
    return ds @ dm_inv


TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])  # outward faces of a positive tet


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Outward boundary triangles (k, 3) of positively oriented linear tets (m, 4): faces used by one tet."""
    faces = np.asarray(tets)[:, TET_FACES].reshape(-1, 3)
    _, inv, cnt = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    return faces[cnt[inv.reshape(-1)] == 1]
