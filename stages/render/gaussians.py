"""3D Gaussians bound to the tets of a simulation mesh (paper §4.1), rendered with the CPU rasterizer.

A Gaussian g lives in host tet h(g) with barycentric weights β (4,), a
rest-frame rotation q and scales s.  Given the mesh's current vertex
positions x (n, 3):

    centre   μ_g = Σₖ βₖ x[tet_h, k]
    F_h      = D_s(x) D_m⁻¹          (deformation gradient of the host tet)
    quadratic tets (10 nodes): μ_g = Σ_a N_a(β) x_a and F_g = D_x J⁻¹ at the Gaussian's own location,
             D_x = Σ_a x_a ⊗ ∂N_a/∂ξ(β), J = Σ_a X_a ⊗ ∂N_a/∂ξ(β) (X the rest nodes; stages.sim.quadrature)
    Σ_g      = F_h R(q) S² R(q)ᵀ F_hᵀ,  S = diag(exp(log_scales))
    colour   c_g = 0.5 + SH(sh_g, view direction)   (degree 0, optionally 1), clamped ≥ 0
    opacity  o_g = sigmoid(opacity_logit_g)

API for the stages (fit-gaussians; adapt, evaluate, report and export through render.image_loss.ImageLoss)::

    g = BoundGaussians.from_artefact(GaussiansArtefact.load(...), MeshArtefact.load(...))
    out = g.render(positions, camera, background=None)   # positions: torch (n,3), any float dtype
    out.image  # (H, W, 3) float32 = C + (1 − A) · background, differentiable w.r.t. positions
    out.alpha  # (H, W) coverage A
    g.parameters()  # appearance (sh, opacity_logit, log_scales, rotations, bary_logits) for torch.optim
    GaussiansArtefact(**g.arrays(), fit_psnr={...})      # what fit-gaussians writes

``camera`` is an ``artefacts.Camera`` (or a ``projection.CameraTensors``);
``background`` is None (the artefact's colour), a (3,) colour or an (H, W, 3)
image.  ``rasterizer="fast"`` (numba, default), ``"tiled"`` or ``"dense"``
(the pure-PyTorch twins) pick the implementation; with "fast", binding and projection
run fused in numba too (``bind_project.py``; pinhole cameras, SH degree 0), else as
torch ops (:func:`bound_geometry`).  A binding given directly by barycentrics β and rest covariance factors
L (Σ₀ = L Lᵀ) — ``ImageLoss`` after a rebind — projects with ``bind_project.project_bound`` (or
:func:`bound_geometry`) and shades with :meth:`BoundGaussians.shade`, so every render of the Gaussians is
this module's image formation.  Rendering runs in float32;
gradients flow back to ``positions`` in its own dtype.  ``g.double()`` renders in float64
(for gradient checks).

Threads: the rasterizer's numba kernels use every core; the many small torch ops around it
are fastest with ``torch.set_num_threads(1)`` (on a shared 2-core machine a 30-iteration fit took
56 s wall with 2 torch threads, 12 s with 1; ``rsl fit-gaussians`` sets it for its run, ``rsl adapt`` with
images through :func:`one_torch_thread`).
"""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import torch

from stages.domain.rotations import matrix_to_quat_wxyz
from stages.render import _torch_ref
from stages.render.bind_project import bind_project
from stages.render.projection import CameraTensors, project_gaussians
from stages.render.rasterize import rasterize

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199

@contextmanager
def one_torch_thread():
    """Run the body with ``torch.set_num_threads(1)`` (restored after): the small per-Gaussian torch ops around
    the numba kernels only spin against those kernels' threads with more (module docstring, Threads)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


RASTERIZERS = {"fast": rasterize, "tiled": _torch_ref.rasterize_tiled, "dense": _torch_ref.rasterize_dense,
               "tiled_lean": _torch_ref.rasterize_tiled_lean}  # tiled_lean: torch maths on the numba tile lists


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Unit-normalised quaternion (N, 4) wxyz → rotation matrices (N, 3, 3)."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) → unit quaternions wxyz (N, 4), w ≥ 0 (numpy)."""
    return matrix_to_quat_wxyz(R)


def sh_to_color(sh: torch.Tensor, dirs: torch.Tensor | None) -> torch.Tensor:
    """RGB (N, 3) = 0.5 + C₀ sh₀ [− C₁ y sh₁ + C₁ z sh₂ − C₁ x sh₃], clamped ≥ 0 (3DGS convention).

    sh (N, K, 3) with K = 1 or 4; dirs (N, 3) unit view directions (camera → Gaussian), needed for K = 4.
    """
    c = SH_C0 * sh[:, 0]
    if sh.shape[1] >= 4:
        x, y, z = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]
        c = c - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
    return torch.clamp(c + 0.5, min=0.0)


_P2_EDGES = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))


def p2_shape(beta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Quadratic-tet shape values N (G, 10) and reference gradients ∂N/∂ξ (G, 10, 3) at barycentric
    β (G, 4) (torch twin of stages.sim.quadrature.shape_values / shape_reference_gradients)."""
    corners = beta * (2 * beta - 1)
    edges = torch.stack([4 * beta[:, a] * beta[:, b] for a, b in _P2_EDGES], 1)
    N = torch.cat([corners, edges], 1)
    zero = torch.zeros_like(beta[:, 0])
    rows = []  # ∂N_a/∂L (4,) per node
    for a in range(4):
        rows.append(torch.stack([4 * beta[:, a] - 1 if c == a else zero for c in range(4)], 1))
    for a, b in _P2_EDGES:
        rows.append(torch.stack([4 * beta[:, b] if c == a else (4 * beta[:, a] if c == b else zero)
                                 for c in range(4)], 1))
    dN_dL = torch.stack(rows, 1)  # (G, 10, 4)
    return N, dN_dL[:, :, 1:] - dN_dL[:, :, :1]  # ∂L_0/∂ξ_j = −1, ∂L_{j+1}/∂ξ_j = 1


def color_to_sh0(rgb: np.ndarray) -> np.ndarray:
    """Inverse of degree-0 ``sh_to_color``: (N, 3) RGB → (N, 3) DC coefficients."""
    return (np.asarray(rgb) - 0.5) / SH_C0


@dataclass
class RenderOutput:
    image: torch.Tensor  # (H, W, 3) composited over the background
    alpha: torch.Tensor  # (H, W) coverage
    premultiplied: torch.Tensor  # (H, W, 3) colour before the background


class BoundGaussians(torch.nn.Module):
    """Gaussians bound to tets; appearance parameters are torch Parameters (float32).

    tets (m, 4) or quadratic (m, 10); for quadratic tets ``rest`` (n, 3), the rest node positions, is
    needed (the element map's Jacobian J at each Gaussian)."""

    def __init__(self, tets: np.ndarray, dm_inv: np.ndarray, host_tet: np.ndarray, bary: np.ndarray,
                 log_scales: np.ndarray, rotations: np.ndarray, opacity_logit: np.ndarray, sh: np.ndarray,
                 background: np.ndarray | None = None, rest: np.ndarray | None = None):
        super().__init__()
        f32 = lambda a: torch.as_tensor(np.asarray(a, np.float64), dtype=torch.float32)  # noqa: E731
        host_tet = np.asarray(host_tet, np.int64)
        tets = np.asarray(tets, np.int64)
        self.quadratic = tets.shape[1] == 10
        self.register_buffer("host_vertices", torch.as_tensor(tets[host_tet]))  # (G, 4 | 10)
        self.register_buffer("dm_inv", f32(np.asarray(dm_inv)[host_tet]))  # (G, 3, 3) of the corner tet
        if self.quadratic:
            if rest is None:
                raise ValueError("Gaussians bound to quadratic tets need the rest node positions")
            self.register_buffer("rest_nodes", f32(np.asarray(rest, np.float64)[tets[host_tet]]))  # (G, 10, 3)
        self.host_tet = host_tet
        self.bary_logits = torch.nn.Parameter(f32(np.log(np.clip(bary, 1e-6, None))))
        self.log_scales = torch.nn.Parameter(f32(log_scales))
        self.rotations = torch.nn.Parameter(f32(rotations))
        self.opacity_logit = torch.nn.Parameter(f32(opacity_logit))
        self.sh = torch.nn.Parameter(f32(sh))
        self.register_buffer("background", f32(np.zeros(3) if background is None else background))

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_artefact(cls, gaussians, mesh) -> "BoundGaussians":
        """From a GaussiansArtefact and the MeshArtefact it is bound to."""
        return cls(mesh.tets, mesh.dm_inv, gaussians.host_tet, gaussians.bary, gaussians.log_scales,
                   gaussians.rotations, gaussians.opacity_logit, gaussians.sh, gaussians.background,
                   rest=mesh.vertices)

    def arrays(self) -> dict[str, np.ndarray]:
        """Current parameters as float64 numpy arrays, named as the fields of a GaussiansArtefact (the stage that
        writes one builds it from these): host_tet (G,), bary (G, 4) renormalised, log_scales (G, 3),
        rotations (G, 4) unit wxyz, opacity_logit (G,), sh (G, K, 3), background (3,)."""
        with torch.no_grad():
            q = self.rotations / self.rotations.norm(dim=1, keepdim=True)
            return {"host_tet": self.host_tet.copy(), "bary": self.bary().double().numpy(),
                    "log_scales": self.log_scales.double().numpy(), "rotations": q.double().numpy(),
                    "opacity_logit": self.opacity_logit.double().numpy(), "sh": self.sh.double().numpy(),
                    "background": self.background.double().numpy()}

    @property
    def n(self) -> int:
        return int(self.host_vertices.shape[0])

    # ------------------------------------------------------------------ geometry
    def bary(self) -> torch.Tensor:
        """Barycentric weights (G, 4) = softmax(bary_logits): always inside the host tet."""
        return torch.softmax(self.bary_logits, dim=1)

    @property
    def dtype(self) -> torch.dtype:
        """Rendering dtype: float32, or float64 after ``.double()`` (gradient checks)."""
        return self.dm_inv.dtype

    @property
    def shape(self) -> torch.Tensor:
        """What the element map needs besides the positions: D_m⁻¹ (G, 3, 3) of the host tets, or for quadratic
        tets their rest nodes (G, 10, 3)."""
        return self.rest_nodes if self.quadratic else self.dm_inv

    def _corners(self, positions: torch.Tensor) -> torch.Tensor:
        return element_nodes(torch.as_tensor(positions).to(self.dtype), self.host_vertices)

    def centres(self, positions: torch.Tensor, corners: torch.Tensor | None = None) -> torch.Tensor:
        """μ = Σₖ βₖ x_k over the host tet's corners (quadratic: Σ_a N_a(β) x_a over its nodes), (G, 3)."""
        p = self._corners(positions) if corners is None else corners
        return element_geometry(p, self.bary(), self.shape)[0]

    def deformation(self, positions: torch.Tensor, corners: torch.Tensor | None = None) -> torch.Tensor:
        """F = D_s D_m⁻¹ of each Gaussian's host tet (quadratic: D_x J⁻¹ at the Gaussian), (G, 3, 3)."""
        p = self._corners(positions) if corners is None else corners
        return element_geometry(p, self.bary(), self.shape)[1]

    def rest_factors(self) -> torch.Tensor:
        """L = R S with the rest covariance Σ₀ = L Lᵀ, (G, 3, 3) m."""
        return quat_to_rotmat(self.rotations) * torch.exp(self.log_scales)[:, None, :]

    def rest_covariances(self) -> torch.Tensor:
        """R S² Rᵀ, (G, 3, 3) m²."""
        R = quat_to_rotmat(self.rotations)
        s2 = torch.exp(2 * self.log_scales)
        return (R * s2[:, None, :]) @ R.transpose(1, 2)

    def covariance_factors(self, positions: torch.Tensor, corners: torch.Tensor | None = None) -> torch.Tensor:
        """M = F R S with Σ = M Mᵀ, (G, 3, 3) m."""
        return self.deformation(positions, corners) @ self.rest_factors()

    def covariances(self, positions: torch.Tensor) -> torch.Tensor:
        """F R S² Rᵀ Fᵀ, (G, 3, 3) m²."""
        M = self.covariance_factors(positions)
        return M @ M.transpose(1, 2)

    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logit)

    # ------------------------------------------------------------------ rendering
    def camera(self, camera) -> CameraTensors:
        if isinstance(camera, CameraTensors):
            return camera
        return CameraTensors.from_camera(camera, self.dtype)

    def project(self, positions: torch.Tensor, cam: CameraTensors, fused: bool = True
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """(means2d, conics, depths, visible, centres or None) in ``cam``.

        ``fused``: the numba twin (bind_project.py) where it applies (pinhole camera, SH degree 0);
        otherwise the torch ops (:func:`bound_geometry`, project_gaussians).
        """
        if fused and self.fusable(cam):
            m2d, con, dep, vis = bind_project(torch.as_tensor(positions), self.bary_logits, self.log_scales,
                                              self.rotations, self.host_vertices, self.shape, cam)
            return m2d, con, dep, vis, None
        means, M = bound_geometry(positions, self.bary(), self.rest_factors(), self.host_vertices, self.shape,
                                  self.dtype)
        proj = project_gaussians(means, None, cam, factors=M)
        return proj.means2d, proj.conics, proj.depths, proj.visible, means

    def fusable(self, cam: CameraTensors) -> bool:
        """Whether the fused numba projection models ``cam`` and these Gaussians (pinhole, SH degree 0)."""
        return not cam.has_distortion and self.sh.shape[1] == 1

    def shade(self, m2d, con, dep, vis, means, cam: CameraTensors, background=None, rasterizer: str = "fast"
              ) -> RenderOutput:
        """Colours (SH at the view direction camera → centre, needing ``means`` for degree ≥ 1), opacities and
        the rasterizer on projected Gaussians; image = premultiplied colour + (1 − A) · background."""
        dirs = None
        if self.sh.shape[1] >= 4:
            d = means - cam.centre
            dirs = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
        colors = sh_to_color(self.sh, dirs)
        premult, alpha = RASTERIZERS[rasterizer](m2d, con, colors, self.opacities(), dep, vis,
                                                 cam.width, cam.height)
        bg = self.background if background is None else torch.as_tensor(background, dtype=self.dtype)
        image = premult + (1 - alpha)[..., None] * bg
        return RenderOutput(image, alpha, premult)

    def render(self, positions: torch.Tensor, camera, background: torch.Tensor | np.ndarray | None = None,
               rasterizer: str = "fast", fused_projection: bool = True) -> RenderOutput:
        """Render the Gaussians at mesh positions (n, 3) into ``camera``; see the module docstring."""
        cam = self.camera(camera)
        m2d, con, dep, vis, means = self.project(positions, cam, fused_projection and rasterizer == "fast")
        return self.shade(m2d, con, dep, vis, means, cam, background, rasterizer)


# =========================================================================== geometry of a binding (torch)
def element_nodes(x: torch.Tensor, host_vertices: torch.Tensor) -> torch.Tensor:
    """Node positions (G, k, 3) of each Gaussian's host element (host_vertices (G, k)) from x (n, 3)."""
    # index_select: its backward is index_add_, much faster on the CPU than advanced indexing's
    k = host_vertices.shape[1]
    return x.index_select(0, host_vertices.reshape(-1)).reshape(-1, k, 3)


def element_geometry(nodes: torch.Tensor, beta: torch.Tensor, shape: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """(μ (G, 3), F (G, 3, 3)) at barycentric β (G, 4) in elements with nodes (G, k, 3): linear tets (k = 4,
    ``shape`` = D_m⁻¹ (G, 3, 3)) μ = Σ βₖ pₖ, F = D_s D_m⁻¹; quadratic (k = 10, ``shape`` = rest nodes
    (G, 10, 3)) μ = Σ_a N_a(β) x_a, F = D_x J⁻¹ (module docstring).  The torch twin of bind_project's
    element geometry."""
    if nodes.shape[1] == 10:
        N, dN = p2_shape(beta)  # (G, 10), (G, 10, 3)
        dx = torch.einsum("gai,gaj->gij", nodes, dN)
        J = torch.einsum("gai,gaj->gij", shape, dN)
        return (N[:, :, None] * nodes).sum(1), dx @ torch.linalg.inv(J)
    ds = (nodes[:, 1:4] - nodes[:, 0:1]).transpose(1, 2)
    return (beta[:, :, None] * nodes).sum(1), ds @ shape


def bound_geometry(positions: torch.Tensor, beta: torch.Tensor, factors: torch.Tensor, host_vertices: torch.Tensor,
                   shape: torch.Tensor, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """(centres μ (G, 3), covariance factors M = F L (G, 3, 3), Σ = M Mᵀ) in ``dtype`` of Gaussians at barycentric
    β (G, 4) with rest-frame factors L (G, 3, 3) (Σ₀ = L Lᵀ), mesh positions (n, 3): torch ops, the twin of
    bind_project.project_bound's geometry (see :func:`element_geometry` for host_vertices and shape)."""
    nodes = element_nodes(torch.as_tensor(positions).to(dtype), host_vertices)
    means, F = element_geometry(nodes, beta.to(dtype), shape.to(dtype))
    return means, F @ factors.to(dtype)
