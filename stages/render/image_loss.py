"""The image observation model of ``rsl adapt``, ``rsl evaluate`` and ``rsl report`` (paper Eq. 7) and its
gradient with respect to vertex positions.

L = Σ_t Σ_c |R(G(x_t), c) − Ĩ_t^c|, the L1 distance between the render of the Gaussians bound to the mesh and
the masked image Ĩ = I·m + bg·(1 − m) (what a render is compared with: stages/observations.py);
dL/dx_t comes from torch autograd through the rasterizer.  The Gaussians were fitted to the images of one
frame with the mesh posed at x_fit (gaussians.h5 ``fit_positions``: that frame's state under the capture's
start convention with the initial θ; the rest shape for older files); :meth:`ImageLoss.rebind` re-binds them
to the tets of that frame's configuration simulated with the current θ (so that rendered there they are exactly
the fitted ones), see :func:`stages.sim.locate.locate_in_elements`; dL/dx_f (that configuration's part of
dL/dθ) comes from :meth:`ImageLoss.anchored_geometry`.

torch and the numba kernels are imported when an ImageLoss is built, not with this module: the stage modules
that import it (evaluate, report) keep ``rsl STAGE --help`` free of torch.  Nothing here reads files or prints.
"""
from __future__ import annotations

import numpy as np

from stages.sim.locate import locate_in_elements
from stages.sim.mesh import deformation_gradients
from stages.sim.quadrature import point_map


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
