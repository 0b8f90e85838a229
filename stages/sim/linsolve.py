"""Sparse assembly on a fixed pattern and the sparse direct solvers of Newton and the adjoint.

The global Hessian is block-sparse with 3×3 blocks between nodes that share an element (4 or 10
nodes), plus the 3×3 diagonal block of every node. :class:`SparsePattern` computes the CSR pattern
once per mesh and the map from every element entry (m, 3k, 3k) and vertex-block entry (n, 3, 3) to its slot in
the CSR data array, so assembly is a scatter-add (numba, with a ``np.bincount`` twin).

Solvers (``solver=`` name): "cholmod" (scikit-sparse; symbolic analysis done once per pattern and
reused), "splu" (scipy SuperLU, always available), "auto" (cholmod when importable, else splu).
"""
from __future__ import annotations

import numba as nb
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

try:  # optional: apt-get install libsuitesparse-dev && pip install "scikit-sparse<0.5"
    from sksparse import cholmod as _cholmod
except Exception:  # pragma: no cover - depends on the machine
    _cholmod = None

SOLVERS = ("auto", "cholmod", "splu")


def available_solvers() -> list[str]:
    """Concrete solver names usable on this machine, fastest first."""
    return (["cholmod"] if _cholmod is not None else []) + ["splu"]


def resolve_solver(name: str) -> str:
    """The concrete solver for a requested name ("auto" picks the fastest available)."""
    if name == "auto":
        return available_solvers()[0]
    if name not in SOLVERS:
        raise ValueError(f"unknown solver {name!r}; use one of {', '.join(SOLVERS)}")
    if name == "cholmod" and _cholmod is None:
        raise ValueError("solver 'cholmod' needs scikit-sparse (pip install 'scikit-sparse<0.5' after "
                         "apt-get install libsuitesparse-dev)")
    return name


class SparsePattern:
    """CSR pattern of a tet mesh's 3n×3n stiffness matrix and the scatter maps into it."""

    def __init__(self, tets: np.ndarray, n_vertices: int):
        tets = np.asarray(tets, np.int64)
        m, n = len(tets), int(n_vertices)
        nd = 3 * tets.shape[1]  # 12 (linear tets) or 30 (quadratic tets)
        dof = (3 * tets[:, :, None] + np.arange(3)).reshape(m, nd)  # (m, 3k) global dofs
        er = np.broadcast_to(dof[:, :, None], (m, nd, nd)).reshape(-1)
        ec = np.broadcast_to(dof[:, None, :], (m, nd, nd)).reshape(-1)
        vd = (3 * np.arange(n)[:, None] + np.arange(3)).reshape(n, 3)
        vr = np.broadcast_to(vd[:, :, None], (n, 3, 3)).reshape(-1)
        vc = np.broadcast_to(vd[:, None, :], (n, 3, 3)).reshape(-1)
        N = 3 * n
        keys = np.concatenate([er * N + ec, vr * N + vc])
        uniq, inv = np.unique(keys, return_inverse=True)
        rows, cols = uniq // N, uniq % N
        self.shape = (N, N)
        self.indices = cols.astype(np.int32)
        self.indptr = np.searchsorted(rows, np.arange(N + 1)).astype(np.int32)
        self.nnz = len(uniq)
        self.elem_map = inv[: m * nd * nd].reshape(m, nd * nd).astype(np.int64)
        self.vert_map = inv[m * nd * nd:].reshape(n, 9).astype(np.int64)
        self.diagonal = np.searchsorted(uniq, np.arange(N) * (N + 1))  # CSR slot of each diagonal entry

    def assemble(self, elem_hess: np.ndarray, vert_blocks: np.ndarray) -> np.ndarray:
        """CSR data of Σ_e (m, 3k, 3k) + Σ_i (n, 3, 3) blocks (numba scatter)."""
        data = np.zeros(self.nnz)
        _scatter(data, self.elem_map, np.ascontiguousarray(elem_hess).reshape(len(self.elem_map), -1),
                 self.vert_map, np.ascontiguousarray(vert_blocks).reshape(-1, 9))
        return data

    def rows_cols(self) -> tuple[np.ndarray, np.ndarray]:
        """(row, column) of every CSR slot, (nnz,) each."""
        rows = np.repeat(np.arange(self.shape[0]), np.diff(self.indptr))
        return rows, self.indices.astype(np.int64)

    def assemble_reference(self, elem_hess: np.ndarray, vert_blocks: np.ndarray) -> np.ndarray:
        """Plain twin of :meth:`assemble` (np.bincount)."""
        idx = np.concatenate([self.elem_map.reshape(-1), self.vert_map.reshape(-1)])
        val = np.concatenate([np.asarray(elem_hess).reshape(-1), np.asarray(vert_blocks).reshape(-1)])
        return np.bincount(idx, weights=val, minlength=self.nnz)

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        return sp.csr_matrix((data, self.indices, self.indptr), shape=self.shape)


@nb.njit(cache=True)
def _scatter(data, elem_map, elem_vals, vert_map, vert_vals):
    for e in range(elem_map.shape[0]):
        for k in range(elem_map.shape[1]):
            data[elem_map[e, k]] += elem_vals[e, k]
    for i in range(vert_map.shape[0]):
        for k in range(9):
            data[vert_map[i, k]] += vert_vals[i, k]


class NotPositiveDefinite(Exception):
    """A Cholesky factorisation met a non-positive pivot."""


class LinearSolver:
    """Factor-then-solve for symmetric matrices on one fixed pattern; CHOLMOD keeps its symbolic
    analysis (fill-reducing ordering and elimination tree) across factorisations."""

    def __init__(self, pattern: SparsePattern, solver: str = "auto"):
        self.pattern = pattern
        self.kind = resolve_solver(solver)
        self._symbolic = None
        self._factor = None

    def factor(self, data: np.ndarray) -> None:
        """Factor the symmetric matrix with CSR data ``data`` (raises NotPositiveDefinite for CHOLMOD)."""
        A = self.pattern.matrix(data)
        if self.kind == "cholmod":
            # symmetric: the CSR arrays read as CSC give the same matrix
            Ac = sp.csc_matrix((data, self.pattern.indices, self.pattern.indptr), shape=self.pattern.shape)
            if self._symbolic is None:
                self._symbolic = _cholmod.analyze(Ac, mode="supernodal", ordering_method="default")
            try:
                self._symbolic.cholesky_inplace(Ac)
            except _cholmod.CholmodNotPositiveDefiniteError as e:
                raise NotPositiveDefinite(str(e)) from None
            self._factor = self._symbolic
        else:
            self._factor = spla.splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A",
                                     options=dict(SymmetricMode=True))

    def solve(self, b: np.ndarray) -> np.ndarray:
        """A⁻¹ b for the last factored matrix, b (3n,)."""
        return np.asarray(self._factor(b) if self.kind == "cholmod" else self._factor.solve(b)).reshape(-1)
