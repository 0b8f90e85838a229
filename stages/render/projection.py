"""Pinhole cameras (OpenCV convention, optional distortion) and EWA projection of 3D Gaussians.

All functions are differentiable PyTorch over tensors (float32 for rendering,
float64 in gradient checks).  Conventions (DESIGN §2): x_cam = R x_world + t,
x right, y down, z forward; pixel centres sit at integer coordinates.

Projection of a point:  (x, y, z) → (xₙ, yₙ) = (x/z, y/z) → distortion
(k1, k2, p1, p2, k3) → (x_d, y_d) → u = K[:2,:2] (x_d, y_d) + K[:2,2].

EWA splatting (Zwicker et al. 2002; 3DGS): a Gaussian N(μ, Σ) in the world
becomes N(u(μ), J R Σ Rᵀ Jᵀ + 0.3 I) in the image, J = ∂u/∂x_cam at μ (2×3).
The rasterizer consumes the conic (a, b, c) = the inverse 2D covariance
[[a, b], [b, c]].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

NEAR_M = 0.01
"""Gaussians closer to the camera than this (m) are culled."""
LOW_PASS_PX2 = 0.3
"""Added to the diagonal of every 2D covariance (px²), the 3DGS anti-aliasing filter."""
FOV_MARGIN = 1.3
"""Normalised coordinates are clamped to this multiple of the image's extent for the Jacobian."""


@dataclass(frozen=True)
class CameraTensors:
    """One camera as tensors: K (3,3), dist (5,), R (3,3) world→camera, t (3,) m, image size."""

    K: torch.Tensor
    dist: torch.Tensor
    R: torch.Tensor
    t: torch.Tensor
    width: int
    height: int
    name: str = ""

    @staticmethod
    def from_camera(cam, dtype: torch.dtype = torch.float32) -> "CameraTensors":
        """From an artefacts.Camera (numpy)."""
        d = np.zeros(5)
        dist = np.asarray(cam.dist, np.float64).ravel()
        d[: min(5, dist.size)] = dist[:5]
        f = lambda a: torch.as_tensor(np.asarray(a, np.float64), dtype=dtype)  # noqa: E731
        return CameraTensors(f(cam.K), f(d), f(cam.R), f(np.asarray(cam.t).ravel()),
                             int(cam.width), int(cam.height), str(getattr(cam, "name", "")))

    @property
    def centre(self) -> torch.Tensor:
        """Camera centre in the world, −Rᵀ t (3,)."""
        return -self.R.T @ self.t

    @property
    def has_distortion(self) -> bool:
        return bool(torch.any(self.dist != 0))

    def normalised_extent(self) -> tuple[float, float]:
        """Largest |xₙ|, |yₙ| of a pixel inside the image (undistorted pinhole)."""
        K = self.K.detach().double().cpu().numpy()
        ex = max(abs(-0.5 - K[0, 2]), abs(self.width - 0.5 - K[0, 2])) / K[0, 0]
        ey = max(abs(-0.5 - K[1, 2]), abs(self.height - 0.5 - K[1, 2])) / K[1, 1]
        return float(ex), float(ey)


def distort(xn: torch.Tensor, yn: torch.Tensor, dist: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """OpenCV radial-tangential model: x_d = x(1+k1r²+k2r⁴+k3r⁶) + 2p1xy + p2(r²+2x²), likewise y."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r2 = xn * xn + yn * yn
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
    return xd, yd


def distort_jacobian(xn: torch.Tensor, yn: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """∂(x_d, y_d)/∂(xₙ, yₙ), (N, 2, 2)."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r2 = xn * xn + yn * yn
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad_dr2 = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    drx, dry = 2 * xn * drad_dr2, 2 * yn * drad_dr2
    j00 = radial + xn * drx + 2 * p1 * yn + 6 * p2 * xn
    j01 = xn * dry + 2 * p1 * xn + 2 * p2 * yn
    j10 = yn * drx + 2 * p1 * xn + 2 * p2 * yn
    j11 = radial + yn * dry + 6 * p1 * yn + 2 * p2 * xn
    return torch.stack([torch.stack([j00, j01], -1), torch.stack([j10, j11], -1)], -2)


def world_to_camera(points: torch.Tensor, cam: CameraTensors) -> torch.Tensor:
    """x_cam = R x + t, (N, 3) → (N, 3) m."""
    return points @ cam.R.T + cam.t


def project_points(points: torch.Tensor, cam: CameraTensors) -> tuple[torch.Tensor, torch.Tensor]:
    """World points (N, 3) → pixels (N, 2) and depths z (N,) (OpenCV model, as cv2.projectPoints)."""
    pc = world_to_camera(points, cam)
    z = pc[:, 2]
    xn, yn = pc[:, 0] / z, pc[:, 1] / z
    if cam.has_distortion:
        xn, yn = distort(xn, yn, cam.dist)
    K = cam.K
    u = K[0, 0] * xn + K[0, 1] * yn + K[0, 2]
    v = K[1, 1] * yn + K[1, 2]
    return torch.stack([u, v], -1), z


@dataclass
class Projected:
    """Gaussians in one image: means2d (N,2) px, conics (N,3) px⁻², depths (N,) m, visible (N,) bool."""

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    cov2d: torch.Tensor  # (N, 2, 2) px²
    visible: torch.Tensor


def project_gaussians(means: torch.Tensor, covs: torch.Tensor | None, cam: CameraTensors,
                      near: float = NEAR_M, factors: torch.Tensor | None = None) -> Projected:
    """EWA: means (N,3) m, covariances (N,3,3) m² (world) → image-space Gaussians.

    Σ₂ = J R Σ Rᵀ Jᵀ + 0.3 I with J = K₂ ∂dist/∂xₙ ∂xₙ/∂x_cam; conic = Σ₂⁻¹.  Instead of ``covs``
    a factor M with Σ = M Mᵀ (N,3,3) may be given (``factors``): then Σ₂ = T Tᵀ + 0.3 I with
    T = J R M, which is cheaper.  A Gaussian is visible when z > near and its normalised
    position lies within 1.5× the image extent (so that the distortion polynomial is not
    folded back).
    """
    pc = world_to_camera(means, cam)
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    visible = z > near
    zs = torch.where(visible, z, torch.ones_like(z))  # keep culled rows finite
    xn, yn = x / zs, y / zs
    ex, ey = cam.normalised_extent()
    visible = visible & (xn.abs() <= 1.5 * ex + 0.1) & (yn.abs() <= 1.5 * ey + 0.1)
    # Jacobian evaluated at clamped coordinates, as 3DGS does (limits far-off-screen blow-up).
    lx, ly = FOV_MARGIN * ex, FOV_MARGIN * ey
    xc, yc = xn.clamp(-lx, lx), yn.clamp(-ly, ly)
    # ∂xₙ/∂x_world = [(R₀ − xₙ R₂)/z ; (R₁ − yₙ R₂)/z]  (N, 2, 3)
    R = cam.R
    inv_z = (1 / zs)[:, None]
    n0 = (R[0] - xc[:, None] * R[2]) * inv_z
    n1 = (R[1] - yc[:, None] * R[2]) * inv_z
    K = cam.K
    if cam.has_distortion:
        xd, yd = distort(xn, yn, cam.dist)
        jd = distort_jacobian(xc, yc, cam.dist)  # (N, 2, 2)
        d0 = jd[:, 0, 0:1] * n0 + jd[:, 0, 1:2] * n1
        d1 = jd[:, 1, 0:1] * n0 + jd[:, 1, 1:2] * n1
    else:
        xd, yd = xn, yn
        d0, d1 = n0, n1
    jw0 = K[0, 0] * d0 + K[0, 1] * d1  # rows of J R, (N, 3) each
    jw1 = K[1, 1] * d1
    u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    v = K[1, 1] * yd + K[1, 2]
    if factors is not None:
        T = torch.stack([jw0, jw1], 1) @ factors  # J R M, (N, 2, 3)
        S = T @ T.transpose(1, 2)
        a = S[:, 0, 0] + LOW_PASS_PX2
        b = S[:, 0, 1]
        c = S[:, 1, 1] + LOW_PASS_PX2
    else:
        s0 = (covs * jw0[:, None, :]).sum(2)  # Σ (J R)₀ᵀ, (N, 3)
        s1 = (covs * jw1[:, None, :]).sum(2)
        a = (jw0 * s0).sum(1) + LOW_PASS_PX2
        b = (jw0 * s1).sum(1)
        c = (jw1 * s1).sum(1) + LOW_PASS_PX2
    cov2d = torch.stack([torch.stack([a, b], -1), torch.stack([b, c], -1)], -2)
    det = a * c - b * b
    visible = visible & (det > 0)
    det = torch.where(visible, det, torch.ones_like(det))
    conics = torch.stack([c / det, -b / det, a / det], -1)
    return Projected(torch.stack([u, v], -1), conics, z, cov2d, visible)
