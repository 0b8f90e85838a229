"""The image observation model of ``rsl adapt``, ``rsl evaluate``, ``rsl report`` and ``rsl export``'s renders and
PLY (paper Eq. 7) and its gradient with respect to vertex positions.

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

from stages.sim.locate import Relocator, locate_in_elements
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
        self._relocator: Relocator | None = None  # (made at the first rebind, :attr:`relocate`)
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

    #: :meth:`rebind` finds the Gaussians' new tets with a :class:`stages.sim.locate.Relocator` (a walk from their
    #: last tets, one k-d tree query for the rest); False: the search of locate_in_elements with the hint — the slow
    #: twin, the same tets and floats (tests/test_render_rebind_speed.py)
    relocate = True

    def rebind(self, x_fit: np.ndarray | None) -> None:
        """Bind the fitted Gaussians to the tets of configuration x_fit (n, 3) (None: back to the binding as
        fitted, in the rest frame); see the class docstring.  Always starts from the fitted Gaussians."""
        if x_fit is None:
            self._anchor_x = None
            self._set_binding(self._fit_host, self._fit_bary, self._fit_cov0, self._fit_factor0)
            return
        x = np.asarray(x_fit, np.float64)
        if self._anchor_x is not None and np.array_equal(x, self._anchor_x):
            return  # bound there already (the same floats would come out)
        self._anchor_x = x.copy()  # (n, 3): the configuration of the binding (see :meth:`anchored_geometry`)
        if self.relocate and self._relocator is None:
            self._relocator = Relocator(self._fit_means, self._tets)
        host, bary = locate_in_elements(self._fit_means, x, self._tets, hint=self.host_tet,  # x moves little
                                        relocator=self._relocator if self.relocate else None)
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

    def images(self, xt, xa=None, views: list | None = None) -> list:
        """Renders (H, W, 3) of every camera at positions xt (n, 3), torch, differentiable.

        ``BoundGaussians.shade`` on the Gaussians of the current binding — barycentric β and rest covariance
        factors L fixed (only colours and opacities are ever refined here): those as fitted, or those of
        :meth:`rebind`; with ``xa`` (n, 3) torch after a :meth:`rebind`, those of :meth:`anchored_geometry` at
        xa (differentiable in xa too) — projected by the fused numba kernel (bind_project.project_bound) where
        it applies (rasterizer "fast", pinhole camera, SH degree 0), else by its torch twin
        (gaussians.bound_geometry + project_gaussians): μ = Σ βₖ xₖ (quadratic tets: Σ N_a(β) x_a),
        M = F L, Σ = M Mᵀ.  ``views``: [(camera, background)] to render instead of the loss's own cameras and
        backgrounds (:meth:`render_views`).
        """
        g = self.g
        beta, factor = self._beta64, self._factor
        if xa is not None and self._anchor_x is not None:
            beta, Fi, _, _ = self._anchored(xa)
            factor = Fi @ self.torch.as_tensor(self._fit_factor)
        pairs = list(zip(self.cams, self.backgrounds)) if views is None else views
        return [g.shade(*proj, cam, bg, self.rasterizer).image
                for proj, (cam, bg) in zip(self._projected(xt, beta, factor, [c for c, _ in pairs]), pairs)]

    def _projected(self, xt, beta, factor, cams: list) -> list:
        """Per camera (means2d, conics, depths, visible, means — None on the fused path) of the Gaussians of the
        binding (β, factors L) at positions xt: the fused numba kernel (bind_project.project_bound) where it
        applies (rasterizer "fast", pinhole camera, SH degree 0), else its torch twin (gaussians.bound_geometry +
        project_gaussians)."""
        from stages.render.bind_project import project_bound
        from stages.render.gaussians import bound_geometry
        from stages.render.projection import project_gaussians

        g = self.g
        xt = self.torch.as_tensor(xt)
        twin = None  # (centres, factors) in torch, computed once for every camera that needs them
        out = []
        for cam in cams:
            if self.rasterizer == "fast" and g.fusable(cam):
                out.append((*project_bound(xt, beta, factor, self._host, self._shape, cam, g.dtype), None))
                continue
            if twin is None:
                twin = bound_geometry(xt, beta, factor, self._host, self._shape, g.dtype)
            proj = project_gaussians(twin[0], None, cam, factors=twin[1])
            out.append((proj.means2d, proj.conics, proj.depths, proj.visible, twin[0]))
        return out

    def blend_weights(self, x: np.ndarray, cameras: list | None = None) -> np.ndarray:
        """(C, G): per camera (``cameras``, artefacts.Camera; None: the loss's own), each Gaussian's blending weight
        summed over the image, Σ_p α_i(p) Π_{j<i}(1 − α_j(p)) (pixels), at positions x (n, 3) with the current
        binding — ∂/∂c_i of the summed render of colours c (torch autograd through the rasterizer): how much of
        the image Gaussian i paints."""
        from stages.render.gaussians import RASTERIZERS

        torch, g = self.torch, self.g
        cams = self.cams if cameras is None else [g.camera(c) for c in cameras]
        out = []
        for (m2d, con, dep, vis, _), cam in zip(self._projected(torch.tensor(np.asarray(x, np.float64)),
                                                                self._beta64, self._factor, cams), cams):
            colors = torch.ones((len(vis), 3), dtype=m2d.dtype, requires_grad=True)
            premult, _ = RASTERIZERS[self.rasterizer](m2d.detach(), con.detach(), colors, g.opacities().detach(),
                                                      dep.detach(), vis, cam.width, cam.height)
            premult[..., 0].sum().backward()
            out.append(colors.grad[:, 0].numpy().astype(np.float64))
        return np.stack(out)

    def painted_share(self, x: np.ndarray, flags: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per camera (s (H, W), A (H, W)) at positions x (n, 3): s = Σ_i w_i(p) f_i, the part of each pixel painted
        by the Gaussians flagged in ``flags`` (C, G) (that camera's row), and A = Σ_i w_i(p) the coverage."""
        from stages.render.gaussians import RASTERIZERS

        torch, g = self.torch, self.g
        out = []
        with torch.no_grad():
            for (m2d, con, dep, vis, _), cam, f in zip(self._projected(torch.tensor(np.asarray(x, np.float64)),
                                                                       self._beta64, self._factor, self.cams),
                                                       self.cams, np.asarray(flags)):
                colors = torch.as_tensor(np.repeat(np.asarray(f, np.float64)[:, None], 3, axis=1), dtype=m2d.dtype)
                premult, alpha = RASTERIZERS[self.rasterizer](m2d, con, colors, g.opacities(), dep, vis,
                                                              cam.width, cam.height)
                out.append((premult[..., 0].numpy().astype(np.float64), alpha.numpy().astype(np.float64)))
        return out

    @property
    def jvp_supported(self) -> bool:
        """Whether :meth:`images_jvp` models these Gaussians: the fast rasterizer and SH degree 0 (colours that do
        not depend on the view direction, so on the positions)."""
        return self.rasterizer == "fast" and self.g.sh.shape[1] == 1

    def binding_jvp(self, xa: np.ndarray | None = None, Va: np.ndarray | None = None, k: int = 0) -> tuple:
        """(β (G, 4), L (G, 3, 3), dβ (k, G, 4), dL (k, G, 3, 3)): the current binding (as fitted, or :meth:`rebind`'s
        — what :meth:`images` renders at xt alone) and its tangents: after a :meth:`rebind` and given the anchor
        configuration xa (n, 3) (that rebind's), those of :meth:`anchored_geometry`'s β(xa), L(xa) = F_a⁻¹ L_fit
        along Va (k, n, 3) (torch.func.jvp; β(xa), L(xa) themselves equal the rebind's up to rounding); else zeros
        (k of them).  β, L torch float64; the tangents numpy."""
        from torch.func import jvp, vmap

        torch, f64 = self.torch, self.torch.float64
        if xa is None or self._anchor_x is None:
            return (self._beta64, self._factor, np.zeros((k,) + tuple(self._beta64.shape)),
                    np.zeros((k,) + tuple(self._factor.shape)))
        fit_factor = torch.as_tensor(self._fit_factor, dtype=f64)

        def binding(xa_):
            b, Fi, _, _ = self._anchored(xa_)
            return b, Fi @ fit_factor

        if not self.quadratic and self.jvp_numpy:  # linear tets: the closed form below (compiled, or in numpy)
            if self.jvp_kernel:
                from stages.render.rasterize_jvp import binding_tangents_linear

                db, dL = binding_tangents_linear(xa, Va, self._host.numpy(), self._fit_means,
                                                 self._dm_inv_all[self.host_tet], self._fit_factor)
            else:
                db, dL = self._binding_tangents_linear(np.asarray(xa, np.float64), np.asarray(Va, np.float64))
            return self._beta64, self._factor, db, dL
        xa_t = torch.as_tensor(np.asarray(xa, np.float64))
        Va_t = torch.as_tensor(np.asarray(Va, np.float64))
        db, dL = vmap(lambda va: jvp(binding, (xa_t,), (va,))[1])(Va_t)
        return self._beta64, self._factor, db.numpy(), dL.numpy()  # (the primal: the very floats images() renders)

    #: linear tets: :meth:`binding_jvp` and :meth:`geometry_jvp` by their closed forms in numpy (matrix products);
    #: False: torch.func.jvp through :meth:`anchored_geometry` and einsum — the slow twins the tests hold them to
    jvp_numpy = True
    #: with :attr:`jvp_numpy`: those closed forms in one compiled pass per Gaussian (rasterize_jvp.geometry_jvp_linear,
    #: binding_tangents_linear: ≈ 10× fewer seconds than numpy's stacked 3 × 3 products on the Bar of
    #: bench/adapt_speed.py); False: the numpy matrix products — their twin (tests/test_render_jvp.py)
    jvp_kernel = True

    def _binding_tangents_linear(self, xa: np.ndarray, Va: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(dβ (k, G, 4), dL (k, G, 3, 3)) of :meth:`anchored_geometry` on linear tets along Va (k, n, 3) at xa (n, 3):
        with D = [x₁ − x₀, x₂ − x₀, x₃ − x₀] of the host tet at xa, λ = D⁻¹ (μ_fit − x₀), β = (1 − Σλ, λ),
        F_a = D D_m⁻¹, L = F_a⁻¹ L_fit:
            dλ = −D⁻¹ (dx₀ + dD λ),   dF_a = dD D_m⁻¹,   dL = −F_a⁻¹ dF_a F_a⁻¹ L_fit."""
        hv = self._host.numpy()
        ca, dca = xa[hv], Va[:, hv]  # (G, 4, 3), (k, G, 4, 3)
        D = (ca[:, 1:4] - ca[:, :1]).transpose(0, 2, 1)  # (G, 3, 3), columns x_j − x_0
        dD = (dca[:, :, 1:4] - dca[:, :, :1]).transpose(0, 1, 3, 2)  # (k, G, 3, 3)
        Dinv = np.linalg.inv(D)
        lam = (Dinv @ (np.asarray(self._fit_means, np.float64) - ca[:, 0])[..., None])  # (G, 3, 1)
        dlam = -(Dinv[None] @ (dca[:, :, 0, :, None] + dD @ lam[None]))[..., 0]  # (k, G, 3)
        db = np.concatenate([-dlam.sum(-1, keepdims=True), dlam], axis=-1)
        Dmi = np.asarray(self._dm_inv_all[self.host_tet], np.float64)
        Fi = np.linalg.inv(D @ Dmi)
        dL = -(Fi[None] @ (dD @ Dmi[None]) @ Fi[None]) @ np.asarray(self._fit_factor, np.float64)[None]
        return db, dL

    def geometry_jvp(self, xt: np.ndarray, V: np.ndarray, binding: tuple) -> tuple:
        """(μ (G, 3), M (G, 3, 3), dμ (k, G, 3), dM (k, G, 3, 3)) float64 numpy: the Gaussians' centres and covariance
        factors (Σ = M Mᵀ) at positions xt (n, 3) with ``binding`` = :meth:`binding_jvp`'s (β, L, dβ, dL), and their
        tangents along V (k, n, 3) and the binding's tangents.  Linear tets: μ = Σ β_k p_k, M = D_s D_m⁻¹ L, so
        dμ = Σ (β_k dp_k + dβ_k p_k), dM = dD_s D_m⁻¹ L + D_s D_m⁻¹ dL; quadratic tets: torch.func.jvp through
        gaussians.bound_geometry (the torch twin of the projection's element geometry)."""
        from torch.func import jvp, vmap

        from stages.render.gaussians import bound_geometry

        torch, f64 = self.torch, self.torch.float64
        beta, factor, db, dL = binding
        x = np.asarray(xt, np.float64)
        V = np.asarray(V, np.float64)
        if self.quadratic:
            args = (torch.as_tensor(x), beta, factor)

            def geom(x_, b_, L_):
                return bound_geometry(x_, b_, L_, self._host, self._shape, f64)

            means, M = geom(*args)
            dmu, dM = vmap(lambda v, b_, l_: jvp(geom, args, (v, b_, l_))[1])(
                torch.as_tensor(V), torch.as_tensor(db), torch.as_tensor(dL))
            return means.numpy(), M.numpy(), dmu.numpy(), dM.numpy()
        hv = self._host.numpy()
        b, Lf, Dmi = beta.numpy(), factor.numpy(), self._shape.numpy()
        if self.jvp_numpy and self.jvp_kernel:
            from stages.render.rasterize_jvp import geometry_jvp_linear

            return geometry_jvp_linear(x, V, hv, b, Lf, Dmi, db, dL)
        P, dP = x[hv], V[:, hv]  # (G, 4, 3), (k, G, 4, 3)
        if self.jvp_numpy:  # the same sums as matrix products
            mu = (b[:, None, :] @ P)[:, 0]
            dmu = (b[None, :, None, :] @ dP)[:, :, 0] + (db[:, :, None, :] @ P[None])[:, :, 0]
            F = (P[:, 1:4] - P[:, :1]).transpose(0, 2, 1) @ Dmi
            dF = (dP[:, :, 1:4] - dP[:, :, :1]).transpose(0, 1, 3, 2) @ Dmi[None]
            return mu, F @ Lf, dmu, dF @ Lf + F[None] @ dL
        mu = np.einsum("gk,gkd->gd", b, P)
        dmu = np.einsum("gk,jgkd->jgd", b, dP) + np.einsum("jgk,gkd->jgd", db, P)
        F = np.einsum("gjd,gje->gde", P[:, 1:4] - P[:, :1], Dmi)  # D_s D_m⁻¹, D_s columns p_j − p_0
        dF = np.einsum("kgjd,gje->kgde", dP[:, :, 1:4] - dP[:, :, :1], Dmi)
        return mu, F @ Lf, dmu, dF @ Lf + F[None] @ dL

    def images_jvp(self, xt: np.ndarray, V: np.ndarray, binding: tuple | None = None
                   ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per camera (image (H, W, 3), d image (k, H, W, 3)) float32 numpy: the render of :meth:`images` at positions
        xt (n, 3) (the same floats) and its exact derivatives along k tangents V (k, n, 3) of the positions and of
        the binding (``binding`` = :meth:`binding_jvp`'s, with the anchor's tangents after a :meth:`rebind`; None:
        the current binding held).

        Forward mode: the tangents of the Gaussians' centres and covariance factors (:meth:`geometry_jvp`), of their
        pinhole projection (rasterize_jvp.project_jvp; with distortion, dual numbers through the torch twin
        project_gaussians), then the rasterizer's own forward mode (rasterize_jvp.rasterize_jvp: every tangent in
        one pass).  Colours and opacities are held.  Needs :attr:`jvp_supported`."""
        import torch.autograd.forward_ad as fwAD

        from stages.render.bind_project import project_bound
        from stages.render.gaussians import bound_geometry, sh_to_color
        from stages.render.projection import CameraTensors, project_gaussians
        from stages.render.rasterize_jvp import project_jvp, rasterize_jvp

        if not self.jvp_supported:
            raise ValueError("images_jvp models the fast rasterizer with SH degree 0 only")
        torch, g = self.torch, self.g
        V = np.asarray(V, np.float64)
        if binding is None:
            binding = self.binding_jvp(k=len(V))
        beta, factor = binding[0], binding[1]
        x = torch.as_tensor(np.asarray(xt, np.float64))
        means_np, M_np, d_means_np, d_M_np = self.geometry_jvp(np.asarray(xt, np.float64), V, binding)
        with torch.no_grad():
            colors, opac = sh_to_color(g.sh, None), g.opacities()  # as BoundGaussians.shade at SH degree 0
        out = []
        for cam, bg in zip(self.cams, self.backgrounds):
            if g.fusable(cam):  # the primal exactly as images() projects it
                m2d, con, dep, vis = project_bound(x, beta, factor, self._host, self._shape, cam, g.dtype)
            else:
                tw = bound_geometry(x, beta, factor, self._host, self._shape, g.dtype)
                proj = project_gaussians(tw[0], None, cam, factors=tw[1])
                m2d, con, dep, vis = proj.means2d, proj.conics, proj.depths, proj.visible
            if cam.has_distortion:  # the torch twin's forward mode (dual numbers; slow, but general)
                cam64 = CameraTensors(cam.K.double(), cam.dist.double(), cam.R.double(), cam.t.double(), cam.width,
                                      cam.height, cam.name)
                mu_t, M_t = torch.as_tensor(means_np), torch.as_tensor(M_np)
                dm2d, dcon = [], []
                for a, b in zip(d_means_np, d_M_np):
                    with fwAD.dual_level():
                        p = project_gaussians(fwAD.make_dual(mu_t, torch.as_tensor(a)), None, cam64,
                                              factors=fwAD.make_dual(M_t, torch.as_tensor(b)))
                        dm2d.append(fwAD.unpack_dual(p.means2d).tangent.numpy())
                        dcon.append(fwAD.unpack_dual(p.conics).tangent.numpy())
                dm2d, dcon = np.stack(dm2d), np.stack(dcon)
            else:
                dm2d, dcon = project_jvp(means_np, M_np, d_means_np, d_M_np, cam)
            C, A, dC, dA = rasterize_jvp(m2d.detach(), con.detach(), colors, opac, dep.detach(), vis,
                                         cam.width, cam.height, dm2d, dcon)
            bgt = g.background if bg is None else torch.as_tensor(bg, dtype=g.dtype)
            image = torch.from_numpy(C) + (1 - torch.from_numpy(A))[..., None] * bgt  # as BoundGaussians.shade
            out.append((image.numpy(), dC - dA[..., None] * bgt.detach().numpy()))
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

    def render_views(self, x: np.ndarray, cameras: list, backgrounds: list | None = None) -> list[np.ndarray]:
        """:meth:`render` into other cameras: images (H, W, 3) float32 at positions x (n, 3), one per camera of
        ``cameras`` (artefacts.Camera), over ``backgrounds`` (per camera None — the Gaussians' colour — or an
        (H, W, 3) image in [0, 1]; default None each), with the current binding (as fitted or :meth:`rebind`'s)."""
        torch = self.torch
        bgs = [None] * len(cameras) if backgrounds is None else backgrounds
        views = [(self.g.camera(c), None if b is None else torch.as_tensor(np.asarray(b, np.float32)))
                 for c, b in zip(cameras, bgs)]
        with torch.no_grad():
            return [im.numpy().copy() for im in self.images(torch.tensor(np.asarray(x, np.float64)), views=views)]

    @property
    def bary(self) -> np.ndarray:
        """(G, 4) float64: the barycentric coordinates β of the current binding in the elements ``host_tet``."""
        return self._bary_np

    def geometry(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(centres μ (G, 3) m, covariances Σ = M Mᵀ (G, 3, 3) m²) float64 of the current binding's Gaussians at
        positions x (n, 3) — what :meth:`images` projects (gaussians.bound_geometry in float64)."""
        from stages.render.gaussians import bound_geometry

        torch = self.torch
        with torch.no_grad():
            mu, M = bound_geometry(torch.as_tensor(np.asarray(x, np.float64)), self._beta64, self._factor,
                                   self._host, self._shape, torch.float64)
        M = M.numpy()
        return mu.numpy().copy(), M @ M.transpose(0, 2, 1)
