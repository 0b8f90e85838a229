"""Window losses of ``rsl adapt`` and their gradients with respect to vertex positions.

Two observation models, each a pure function of simulated positions X (w, n, 3):

* markers (paper Eq. 4, windowed): L = Σ_t Σ_i ‖m_i(x_t) − p_t^i‖² over the observed (t, i) only (a
  motion-capture gap, NaN in p, adds nothing), with each marker bound to the surface point nearest its
  frame-0 position, m_i(x) = Σ_k b_ik x[f_ik] (barycentric on the nearest surface triangle), so
  dL/dx_t = Σ_{i observed at t} 2 (m_i − p^i) ⊗ b_i.
* vision (paper Eq. 7): L = Σ_t Σ_c |R(G(x_t), c) − Ĩ_t^c|, the L1 distance between the
  render of the Gaussians bound to the mesh and the masked image Ĩ = I·m + bg·(1 − m);
  dL/dx_t comes from torch autograd through the rasterizer (stages/render).  The Gaussians were
  fitted to the images of one frame with the mesh posed at x_fit (gaussians.h5 ``fit_positions``: that
  frame's state under the capture's start convention with the initial θ; the rest shape for older files);
  :meth:`ImageLoss.rebind` re-binds them to the tets of that frame's configuration simulated with the
  current θ (so that rendered there they are exactly the fitted ones), see :func:`locate_in_tets`;
  dL/dx_f (that configuration's part of dL/dθ) comes from :meth:`ImageLoss.anchored_geometry`.

Nothing here reads files or prints.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from stages.sim.mesh import deformation_gradients, shape_matrices
from stages.sim.quadrature import point_map, shape_reference_gradients, shape_values


# =========================================================================== markers
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


# =========================================================================== point location in tets
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


# =========================================================================== vision
class ImageLoss:
    """L = Σ_c |R(G(x), c) − Ĩ^c|₁ (sum over pixels and channels, paper Eq. 7) and dL/dx.

    G(x) are the Gaussians bound to the mesh (stages.render.gaussians.BoundGaussians); dL/dx flows
    image → Gaussian centres and covariances → vertex positions through torch autograd.  With
    ``appearance`` the Gaussians' colours and opacities take an Adam step on the same loss at each
    evaluation (paper §4.3: θ and the Gaussian attributes are optimised together).

    The Gaussians are bound to the tets in the rest frame (host, β, Σ₀) and were fitted with the mesh posed
    at x_fit (gaussians.h5 ``fit_positions``; the rest shape when absent): fitted centre μ = Σ_a N_a(β) x_fit,a
    and world covariance Σ = F_fit Σ₀ F_fitᵀ.  The simulated fit-frame configuration x_f(θ) differs from
    x_fit as θ changes: :meth:`rebind` moves each Gaussian (μ and Σ as fitted, in world space) into the tet
    of x_f that holds μ, with barycentric β = bary(μ; x_f) and rest covariance F_f⁻¹ Σ F_f⁻ᵀ: rendered at x_f
    the Gaussians are then exactly the fitted ones, and at x_t they follow the motion from x_f to x_t.
    Since x_f = x_f(θ), dL/dθ has a part through the anchor: :meth:`anchored_geometry` is the binding as a
    differentiable function of x_f and ``__call__(..., anchor_grad=True)`` returns dL/dx_f beside dL/dx (held
    fixed, frame f's loss — constant in θ — still pulled θ: docs/results/vision_bias.md).
    """

    def __init__(self, gaussians, mesh, cameras: list, appearance: bool = False, lr_appearance: float = 2e-3,
                 rasterizer: str = "fast"):
        import torch  # torch and the numba renderer load only when images are used (rsl adapt --help stays fast)

        from stages.render.bind_project import fitted_binding
        from stages.render.gaussians import BoundGaussians

        self.torch = torch
        self.g = BoundGaussians.from_artefact(gaussians, mesh)
        for p in self.g.parameters():
            p.requires_grad_(False)
        self._tets = np.asarray(mesh.tets, np.int64)
        self._dm_inv_all = np.asarray(mesh.dm_inv, np.float64)
        self._rest = np.asarray(mesh.vertices, np.float64)
        self.quadratic = self._tets.shape[1] == 10
        fit_x = getattr(gaussians, "fit_positions", None)
        if fit_x is not None and np.shape(fit_x) != self._rest.shape:
            raise ValueError(f"the Gaussians were fitted at {np.shape(fit_x)[0]} vertex positions but the mesh "
                             f"has {len(self._rest)} vertices")
        #: (n, 3) m, the mesh positions the Gaussians were fitted at (the rest shape for older files)
        self.fit_positions = self._rest if fit_x is None else np.asarray(fit_x, np.float64)
        # the binding as fitted: host tets, barycentrics β, rest-frame covariance factors L₀ = R S and Σ₀ = L₀ L₀ᵀ
        # (the floats BoundGaussians.render projects with)
        self._fit_host = np.asarray(gaussians.host_tet, np.int64)
        self._fit_bary, self._fit_factor0 = fitted_binding(self.g.bary_logits, self.g.log_scales, self.g.rotations)
        self._fit_cov0 = self._fit_factor0 @ self._fit_factor0.transpose(0, 2, 1)
        # the fitted Gaussians in world space: μ = Σ_a N_a x_fit,a and Σ = F_fit Σ₀ F_fitᵀ at x_fit
        N, G, _ = point_map(self._rest, self._tets, self._fit_host, self._fit_bary)
        xe = self.fit_positions[self._tets[self._fit_host]]
        self._fit_means = np.einsum("gk,gkd->gd", N, xe)
        F_fit = np.einsum("gki,gkj->gij", xe, G)
        self._fit_cov = F_fit @ self._fit_cov0 @ F_fit.transpose(0, 2, 1)
        self._fit_factor = F_fit @ self._fit_factor0  # (G, 3, 3): Σ = F_fit L₀ (F_fit L₀)ᵀ in world space
        self._anchor_x = None  # (n, 3) the configuration of the last rebind (None: bound as fitted)
        self._set_binding(self._fit_host, self._fit_bary, self._fit_cov0, self._fit_factor0)
        self.cams = [self.g.camera(c) for c in cameras]
        self.background = self.g.background.detach().numpy().astype(np.float32)  # (3,)
        self.rasterizer = rasterizer
        self.backgrounds: list = [None] * len(self.cams)
        self.opt = None
        if appearance:
            ps = [self.g.sh, self.g.opacity_logit]
            for p in ps:
                p.requires_grad_(True)
            self.opt = torch.optim.Adam(ps, lr=lr_appearance)

    def _set_binding(self, host: np.ndarray, bary: np.ndarray, cov0: np.ndarray, factor: np.ndarray) -> None:
        """The binding :meth:`images` renders: host element (G,), barycentric β (G, 4), rest covariance
        Σ₀ (G, 3, 3) = L Lᵀ with its factor L (G, 3, 3); Σ₀ itself is kept for inspection (``_cov0``)."""
        torch, f64 = self.torch, self.torch.float64
        self.host_tet = np.asarray(host, np.int64)
        self._bary_np = np.asarray(bary, np.float64)
        self._host = torch.as_tensor(self._tets[self.host_tet])  # (G, 4 | 10) vertex ids
        self._cov0 = torch.as_tensor(np.asarray(cov0, np.float64), dtype=f64)
        self._beta64 = torch.as_tensor(self._bary_np, dtype=f64)
        self._factor = torch.as_tensor(np.asarray(factor, np.float64), dtype=f64)
        # the element map's rest data (render.gaussians.element_geometry): D_m⁻¹ (P1) or the rest nodes (P2)
        shape = self._rest[self._tets[self.host_tet]] if self.quadratic else self._dm_inv_all[self.host_tet]
        self._shape = torch.as_tensor(shape, dtype=f64)

    def rebind(self, x_fit: np.ndarray | None) -> None:
        """Bind the fitted Gaussians to the tets of configuration x_fit (n, 3) (None: back to the binding as
        fitted, in the rest frame); see the class docstring.  Always starts from the fitted Gaussians."""
        if x_fit is None:
            self._anchor_x = None
            self._set_binding(self._fit_host, self._fit_bary, self._fit_cov0, self._fit_factor0)
            return
        x = np.asarray(x_fit, np.float64)
        self._anchor_x = x.copy()  # (n, 3): the configuration of the binding (see :meth:`anchored_geometry`)
        host, bary = locate_in_elements(self._fit_means, x, self._tets, hint=self.host_tet)  # x moves little
        if self.quadratic:  # F = Σ x_a ⊗ G_a at each Gaussian's new location
            _, G, _ = point_map(self._rest, self._tets, host, bary)
            F = np.einsum("gki,gkj->gij", x[self._tets[host]], G)
        else:
            F = deformation_gradients(x, self._tets[host], self._dm_inv_all[host])  # (G, 3, 3) at x_fit
        Finv = np.linalg.inv(F)
        self._set_binding(host, bary, Finv @ self._fit_cov @ Finv.transpose(0, 2, 1), Finv @ self._fit_factor)

    def set_backgrounds(self, backgrounds: list[np.ndarray | None]) -> None:
        """Per camera: None (the Gaussians' background colour) or an (H, W, 3) plate in [0, 1]."""
        self.backgrounds = [None if b is None else self.torch.as_tensor(np.asarray(b, np.float32))
                            for b in backgrounds]

    def anchored_geometry(self, xa) -> tuple:
        """The binding of :meth:`rebind` as a differentiable function of the anchor configuration xa (n, 3)
        (torch): (β (G, 4), Σ₀ (G, 3, 3), and for quadratic tets N (G, 10), G (G, 10, 3)), each Gaussian staying
        in the element :meth:`rebind` found.  β(xa) solves Σ_a N_a(β) xa_a = μ_fit (linear tets: the barycentric
        coordinates of μ_fit in the tet of xa; quadratic: one Newton step of the element map's inverse from the
        β of :meth:`rebind` — at xa = the rebind configuration its value is that β and its derivative exact,
        by the implicit-function theorem), Σ₀(xa) = F_a⁻¹ Σ_fit F_a⁻ᵀ with F_a the deformation gradient at the
        Gaussian in xa.  So dμ_t/dxa = −F_t F_a⁻¹ Σ N_a(β) (the Gaussians stay where they were fitted at the
        fit frame, whatever the anchor), which the gradient of :meth:`__call__` with ``anchor_grad`` carries."""
        beta, Fi, N, G = self._anchored(xa)
        cov_fit = self.torch.as_tensor(self._fit_cov, dtype=self.torch.float64)
        return beta, Fi @ cov_fit @ Fi.transpose(1, 2), N, G

    def _anchored(self, xa) -> tuple:
        """(β, F_a⁻¹, N, G) of :meth:`anchored_geometry` at xa (n, 3), float64 torch."""
        torch = self.torch
        f64 = torch.float64
        xa = torch.as_tensor(xa).to(f64)
        mu = torch.as_tensor(self._fit_means, dtype=f64)
        hv = self._host.reshape(-1)
        ca = xa.index_select(0, hv).reshape(-1, self._host.shape[1], 3)  # (G, k, 3)
        if self.quadratic:
            from stages.render.gaussians import p2_shape

            b0 = torch.as_tensor(self._bary_np, dtype=f64)
            N0, dN0 = p2_shape(b0)
            Jxi = torch.einsum("gai,gaj->gij", ca, dN0)  # ∂x/∂ξ at β₀
            dxi = torch.linalg.solve(Jxi, (mu - (N0[:, :, None] * ca).sum(1))[..., None])[..., 0]
            beta = b0 + torch.cat([-dxi.sum(1, keepdim=True), dxi], 1)
            N, dN = p2_shape(beta)
            Xr = torch.as_tensor(self._rest[self._tets[self.host_tet]], dtype=f64)
            Jr = torch.einsum("gai,gaj->gij", Xr, dN)  # ∂X/∂ξ (rest)
            G = torch.einsum("gaj,gij->gai", dN, torch.linalg.inv(Jr).transpose(1, 2))  # J⁻ᵀ ∂N/∂ξ
            Fa = torch.einsum("gai,gaj->gij", ca, G)
        else:
            D = (ca[:, 1:4] - ca[:, 0:1]).transpose(1, 2)  # (G, 3, 3) columns x_k − x_0
            lam = torch.linalg.solve(D, (mu - ca[:, 0])[..., None])[..., 0]
            beta = torch.cat([1.0 - lam.sum(1, keepdim=True), lam], 1)
            N = G = None
            Fa = D @ torch.as_tensor(self._dm_inv_all[self.host_tet], dtype=f64)
        return beta, torch.linalg.inv(Fa), N, G

    def images(self, xt, xa=None) -> list:
        """Renders (H, W, 3) of every camera at positions xt (n, 3), torch, differentiable.

        ``BoundGaussians.shade`` on the Gaussians of the current binding — barycentric β and rest covariance
        factors L fixed (only colours and opacities are ever refined here): those as fitted, or those of
        :meth:`rebind`; with ``xa`` (n, 3) torch after a :meth:`rebind`, those of :meth:`anchored_geometry` at
        xa (differentiable in xa too) — projected by the fused numba kernel (bind_project.project_bound) where
        it applies (rasterizer "fast", pinhole camera, SH degree 0), else by its torch twin
        (gaussians.bound_geometry + project_gaussians): μ = Σ βₖ xₖ (quadratic tets: Σ N_a(β) x_a),
        M = F L, Σ = M Mᵀ.
        """
        from stages.render.bind_project import project_bound
        from stages.render.gaussians import bound_geometry
        from stages.render.projection import project_gaussians

        g = self.g
        xt = self.torch.as_tensor(xt)
        beta, factor = self._beta64, self._factor
        if xa is not None and self._anchor_x is not None:
            beta, Fi, _, _ = self._anchored(xa)
            factor = Fi @ self.torch.as_tensor(self._fit_factor)
        twin = None  # (centres, factors) in torch, computed once for every camera that needs them
        out = []
        for cam, bg in zip(self.cams, self.backgrounds):
            if self.rasterizer == "fast" and g.fusable(cam):
                m2d, con, dep, vis = project_bound(xt, beta, factor, self._host, self._shape, cam, g.dtype)
                means = None
            else:
                if twin is None:
                    twin = bound_geometry(xt, beta, factor, self._host, self._shape, g.dtype)
                means = twin[0]
                proj = project_gaussians(means, None, cam, factors=twin[1])
                m2d, con, dep, vis = proj.means2d, proj.conics, proj.depths, proj.visible
            out.append(g.shade(m2d, con, dep, vis, means, cam, bg, self.rasterizer).image)
        return out

    def __call__(self, x: np.ndarray, targets: list[np.ndarray], ignore: list[np.ndarray | None] | None = None,
                 anchor_grad: bool = False) -> tuple:
        """(L, dL/dx (n, 3)) for positions x (n, 3) and one target image (H, W, 3) in [0, 1] per camera.

        ``ignore``: per camera None or an (H, W) bool mask of pixels left out of the loss (an occluder covers
        them, stages/occluders.py): L = Σ_c Σ_{p not ignored} |R_p − Ĩ_p|₁, so those pixels add nothing to L
        or to dL/dx whatever the render and the target hold there.
        ``anchor_grad``: (L, dL/dx, dL/dxa (n, 3)), dL/dxa the derivative with respect to the configuration of the
        last :meth:`rebind` (:meth:`anchored_geometry`; zeros without one) — the anchor is x_f(θ), so a
        gradient in θ needs dL/dxa · dx_f/dθ as well as dL/dx · dx/dθ.
        """
        torch = self.torch
        xt = torch.tensor(np.asarray(x, np.float64), requires_grad=True)
        anchored = anchor_grad and self._anchor_x is not None
        xa = torch.tensor(self._anchor_x, requires_grad=True) if anchored else None
        if self.opt is not None:
            self.opt.zero_grad()
        ignore = list(ignore) if ignore is not None else [None] * len(targets)
        loss = 0.0
        for img, target, ign in zip(self.images(xt, xa), targets, ignore):
            diff = (img - torch.as_tensor(target, dtype=torch.float32)).abs()
            if ign is not None:
                keep = torch.as_tensor(~np.asarray(ign, bool))[..., None]
                diff = torch.where(keep, diff, torch.zeros_like(diff))
            loss = loss + diff.sum()
        loss.backward()
        if self.opt is not None:
            self.opt.step()
        out = (float(loss.detach()), xt.grad.numpy().copy())
        if not anchor_grad:
            return out
        return out + (xa.grad.numpy().copy() if anchored else np.zeros_like(out[1]),)

    def render(self, x: np.ndarray) -> list[np.ndarray]:
        """Images (H, W, 3) float32 in [0, 1], one per camera, at positions x (n, 3)."""
        torch = self.torch
        with torch.no_grad():
            return [im.numpy().copy() for im in self.images(torch.tensor(np.asarray(x, np.float64)))]
