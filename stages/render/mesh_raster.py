"""A textured-mesh rasterizer for synthetic captures (numpy + numba; not differentiable).

Pinhole cameras in the OpenCV convention: x_cam = R x_world + t, pixel u = fx x/z + cx,
v = fy y/z + cy, with pixel centres at integer coordinates (u = column, v = row).

- ``project_points``: world points -> pixels and depth (with OpenCV k1 k2 p1 p2 k3 distortion).
- ``rasterize``: z-buffer with perspective-correct barycentrics; a compiled (numba) loop
  beside ``rasterize_reference``, its plain numpy twin that tests hold it to.
- ``render_mesh``: supersampled Lambertian shading of a procedural texture evaluated at each
  pixel's rest-space point, composited over a background plate.

Pure functions over arrays: no file I/O, no printing.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numba
import numpy as np


@dataclass(frozen=True)
class Raster:
    """What each pixel sees: depth (H, W) m (inf = empty), face (H, W) int (-1 = empty),
    bary (H, W, 3) perspective-correct barycentric weights of the face's three vertices."""

    depth: np.ndarray
    face: np.ndarray
    bary: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool: pixels covered by a face."""
        return self.face >= 0


# --------------------------------------------------------------------------- cameras
def project_points(points: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
                   dist: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (n, 2) and camera depth z (n,) of world points (n, 3).

    x_c = R p + t;  (a, b) = (x/z, y/z);  r² = a² + b²;
    a' = a (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 a b + p2 (r² + 2a²)  (b' likewise);  u = K (a', b', 1).
    """
    pc = np.asarray(points, np.float64) @ np.asarray(R, np.float64).T + np.asarray(t, np.float64)
    z = pc[:, 2]
    zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
    a, b = pc[:, 0] / zs, pc[:, 1] / zs
    if dist is not None and np.any(np.asarray(dist) != 0):
        k1, k2, p1, p2, k3 = np.asarray(dist, np.float64)[:5]
        r2 = a * a + b * b
        radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
        a, b = (a * radial + 2 * p1 * a * b + p2 * (r2 + 2 * a * a),
                b * radial + p1 * (r2 + 2 * b * b) + 2 * p2 * a * b)
    K = np.asarray(K, np.float64)
    u = K[0, 0] * a + K[0, 1] * b + K[0, 2]
    v = K[1, 1] * b + K[1, 2]
    return np.stack([u, v], axis=1), z


def look_at(center: np.ndarray, target: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a camera at ``center`` looking at ``target``: z forward, x right, y down (OpenCV).

    z = (target − center)/‖·‖,  x = z × up /‖·‖,  y = z × x;  t = −R center.
    """
    center = np.asarray(center, np.float64)
    z = np.asarray(target, np.float64) - center
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, np.float64))
    if np.linalg.norm(x) < 1e-9:  # looking along up: pick any right vector
        x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ center


def supersampled_K(K: np.ndarray, factor: int) -> np.ndarray:
    """Intrinsics of the same camera at ``factor``× resolution (pixel centres at integers):
    u' = f·(u + ½) − ½."""
    Ks = np.asarray(K, np.float64).copy()
    Ks[:2, :] *= factor
    Ks[0, 2] += 0.5 * (factor - 1)
    Ks[1, 2] += 0.5 * (factor - 1)
    return Ks


# --------------------------------------------------------------------------- rasterization
@numba.njit(cache=True)
def _raster_kernel(uv, z, faces, height, width, near, depth, face, bary):  # pragma: no cover - compiled
    for f in range(faces.shape[0]):
        ia, ib, ic = faces[f, 0], faces[f, 1], faces[f, 2]
        z0, z1, z2 = z[ia], z[ib], z[ic]
        if z0 <= near or z1 <= near or z2 <= near:
            continue
        x0, y0 = uv[ia, 0], uv[ia, 1]
        x1, y1 = uv[ib, 0], uv[ib, 1]
        x2, y2 = uv[ic, 0], uv[ic, 1]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if abs(area) < 1e-12:
            continue
        jmin = max(0, int(np.ceil(min(x0, min(x1, x2)))))
        jmax = min(width - 1, int(np.floor(max(x0, max(x1, x2)))))
        imin = max(0, int(np.ceil(min(y0, min(y1, y2)))))
        imax = min(height - 1, int(np.floor(max(y0, max(y1, y2)))))
        for i in range(imin, imax + 1):
            py = float(i)
            for j in range(jmin, jmax + 1):
                px = float(j)
                w0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) / area
                w1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) / area
                w2 = ((x0 - px) * (y1 - py) - (x1 - px) * (y0 - py)) / area
                if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                    continue
                q0, q1, q2 = w0 / z0, w1 / z1, w2 / z2
                zz = 1.0 / (q0 + q1 + q2)
                if zz < depth[i, j]:
                    depth[i, j] = zz
                    face[i, j] = f
                    bary[i, j, 0] = q0 * zz
                    bary[i, j, 1] = q1 * zz
                    bary[i, j, 2] = q2 * zz


def _check(uv: np.ndarray, z: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    uv = np.ascontiguousarray(uv, np.float64)
    z = np.ascontiguousarray(z, np.float64)
    faces = np.ascontiguousarray(faces, np.int64)
    assert uv.ndim == 2 and uv.shape[1] == 2 and z.shape == (uv.shape[0],), (uv.shape, z.shape)
    assert faces.ndim == 2 and faces.shape[1] == 3, faces.shape
    return uv, z, faces


def rasterize(uv: np.ndarray, z: np.ndarray, faces: np.ndarray, height: int, width: int,
              near: float = 1e-6) -> Raster:
    """Z-buffer rasterization (compiled).

    uv (n, 2) pixels, z (n,) camera depth, faces (k, 3). A pixel centre (j, i) is inside a
    face when its three screen-space barycentrics wᵢ ≥ 0; its depth is the perspective-correct
    z = 1 / Σ wᵢ/zᵢ and the nearest face wins (first one on exact ties). Faces with a vertex at
    z ≤ near are skipped.
    """
    uv, z, faces = _check(uv, z, faces)
    depth = np.full((height, width), np.inf)
    face = np.full((height, width), -1, np.int64)
    bary = np.zeros((height, width, 3))
    _raster_kernel(uv, z, faces, int(height), int(width), float(near), depth, face, bary)
    return Raster(depth, face, bary)


def rasterize_reference(uv: np.ndarray, z: np.ndarray, faces: np.ndarray, height: int, width: int,
                        near: float = 1e-6) -> Raster:
    """Plain numpy twin of :func:`rasterize` (same equations, vectorised over each face's box)."""
    uv, z, faces = _check(uv, z, faces)
    depth = np.full((height, width), np.inf)
    face = np.full((height, width), -1, np.int64)
    bary = np.zeros((height, width, 3))
    for f, (ia, ib, ic) in enumerate(faces):
        z0, z1, z2 = z[ia], z[ib], z[ic]
        if min(z0, z1, z2) <= near:
            continue
        (x0, y0), (x1, y1), (x2, y2) = uv[ia], uv[ib], uv[ic]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if abs(area) < 1e-12:
            continue
        jmin, jmax = max(0, int(np.ceil(min(x0, x1, x2)))), min(width - 1, int(np.floor(max(x0, x1, x2))))
        imin, imax = max(0, int(np.ceil(min(y0, y1, y2)))), min(height - 1, int(np.floor(max(y0, y1, y2))))
        if jmin > jmax or imin > imax:
            continue
        py, px = np.meshgrid(np.arange(imin, imax + 1, dtype=np.float64),
                             np.arange(jmin, jmax + 1, dtype=np.float64), indexing="ij")
        w0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) / area
        w1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) / area
        w2 = ((x0 - px) * (y1 - py) - (x1 - px) * (y0 - py)) / area
        q0, q1, q2 = w0 / z0, w1 / z1, w2 / z2
        zz = 1.0 / (q0 + q1 + q2)
        sub = depth[imin:imax + 1, jmin:jmax + 1]
        win = (w0 >= 0) & (w1 >= 0) & (w2 >= 0) & (zz < sub)
        sub[win] = zz[win]
        face[imin:imax + 1, jmin:jmax + 1][win] = f
        bsub = bary[imin:imax + 1, jmin:jmax + 1]
        bsub[win] = np.stack([q0 * zz, q1 * zz, q2 * zz], axis=-1)[win]
    return Raster(depth, face, bary)


def interpolate(raster: Raster, attributes: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per-pixel attribute Σᵢ baryᵢ a[face[i]], (H, W, A) from per-vertex (n, A); 0 where empty."""
    attributes = np.asarray(attributes)
    out = np.zeros(raster.face.shape + attributes.shape[1:], dtype=np.float64)
    m = raster.mask
    tri = np.asarray(faces)[raster.face[m]]  # (P, 3)
    out[m] = np.einsum("pk,pk...->p...", raster.bary[m], attributes[tri])
    return out


# --------------------------------------------------------------------------- shading
def vertex_normals(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (n, 3): Σ over incident faces of (x1−x0)×(x2−x0)."""
    p = x[faces]
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    vn = np.zeros_like(x, dtype=np.float64)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return vn / np.where(norm > 0, norm, 1.0)


def lambert(albedo: np.ndarray, normals: np.ndarray, view_dirs: np.ndarray, lights: np.ndarray,
            ambient: float = 0.3) -> np.ndarray:
    """Two-sided Lambertian shading: c = albedo · (ambient + (1 − ambient) Σₗ wₗ max(0, n·lₗ)).

    albedo (P, 3), normals (P, 3) unit, view_dirs (P, 3) unit from surface to camera (normals are
    flipped to face the camera), lights (L, 4) rows [direction to light (unit), weight].
    """
    n = np.where((np.sum(normals * view_dirs, axis=1) < 0)[:, None], -normals, normals)
    diffuse = np.zeros(len(n))
    for l in np.atleast_2d(lights):
        diffuse += l[3] * np.maximum(0.0, n @ l[:3])
    return albedo * (ambient + (1.0 - ambient) * np.clip(diffuse, 0.0, 1.0))[:, None]


def downsample(img: np.ndarray, factor: int) -> np.ndarray:
    """Box-filter an (H·f, W·f, ...) image to (H, W, ...)."""
    if factor == 1:
        return img
    h, w = img.shape[0] // factor, img.shape[1] // factor
    return img.reshape(h, factor, w, factor, *img.shape[2:]).mean(axis=(1, 3))


DEFAULT_LIGHTS = np.array([[0.3, -0.4, 0.866, 0.8], [-0.5, 0.5, 0.5, 0.35]])  # world dir, weight


def render_mesh(x: np.ndarray, faces: np.ndarray, rest: np.ndarray, K: np.ndarray, R: np.ndarray,
                t: np.ndarray, width: int, height: int,
                texture: Callable[[np.ndarray], np.ndarray],
                background: np.ndarray | None = None, dist: np.ndarray | None = None,
                supersample: int = 2, lights: np.ndarray = DEFAULT_LIGHTS, ambient: float = 0.3,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render a textured triangle mesh: (rgb (H, W, 3) float in [0, 1], coverage (H, W) in [0, 1],
    depth (H, W) m, inf where empty).

    x (n, 3) deformed vertices, faces (k, 3), rest (n, 3) rest positions where ``texture``
    (P, 3) -> (P, 3) albedo is evaluated, so the pattern moves with the material. Lights are world
    directions (unit after normalising) with weights; shading is two-sided Lambertian. The image is
    rendered at ``supersample``× resolution and box-filtered down.
    """
    s = int(supersample)
    Ks = supersampled_K(K, s)
    uv, z = project_points(x, Ks, R, t, dist)
    ras = rasterize(uv, z, faces, height * s, width * s)
    m = ras.mask
    rgb = np.zeros((height * s, width * s, 3))
    if background is not None:
        bg = np.asarray(background, np.float64)
        bg = bg / 255.0 if bg.max() > 1.0 else bg
        rgb[:] = np.repeat(np.repeat(bg, s, axis=0), s, axis=1)
    if np.any(m):
        tri = faces[ras.face[m]]
        b = ras.bary[m]
        p_world = np.einsum("pk,pkd->pd", b, x[tri])
        p_rest = np.einsum("pk,pkd->pd", b, rest[tri])
        vn = vertex_normals(x, faces)
        nrm = np.einsum("pk,pkd->pd", b, vn[tri])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        cam_center = -np.asarray(R).T @ np.asarray(t)
        view = cam_center - p_world
        view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-12)
        lights = np.array(lights, np.float64)
        lights[:, :3] /= np.linalg.norm(lights[:, :3], axis=1, keepdims=True)
        rgb[m] = lambert(np.clip(texture(p_rest), 0.0, 1.0), nrm, view, lights, ambient)
    depth = np.where(m, ras.depth, np.inf)
    depth_small = depth.reshape(height, s, width, s).min(axis=(1, 3))  # nearest sample per pixel
    return np.clip(downsample(rgb, s), 0.0, 1.0), downsample(m.astype(np.float64), s), depth_small


# --------------------------------------------------------------------------- textures
def procedural_texture(cell_m: float, seed: int = 0, base=(0.85, 0.45, 0.25), alt=(0.95, 0.85, 0.55),
                       noise: float = 0.25) -> Callable[[np.ndarray], np.ndarray]:
    """A 3D checkerboard of cell size ``cell_m`` in rest coordinates, blended with smooth noise.

    albedo(p) = mix(base, alt, checker(p)) · (1 + noise Σₖ aₖ sin(ωₖ·p + φₖ)) with checker(p) =
    (⌊p_x/c⌋ + ⌊p_y/c⌋ + ⌊p_z/c⌋) mod 2 and random ωₖ of wavelength ~ c … 4c.
    """
    rng = np.random.default_rng(seed)
    k = 6
    dirs = rng.normal(size=(k, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    omegas = dirs * (2 * np.pi / (cell_m * rng.uniform(0.7, 4.0, size=(k, 1))))
    phases = rng.uniform(0, 2 * np.pi, size=k)
    amps = rng.uniform(0.5, 1.0, size=k) / k * 2
    tints = rng.uniform(-1, 1, size=(k, 3)) * 0.3 + 1.0
    base_c, alt_c = np.asarray(base, np.float64), np.asarray(alt, np.float64)

    def texture(p: np.ndarray) -> np.ndarray:
        p = np.asarray(p, np.float64)
        checker = (np.floor(p / cell_m).astype(np.int64).sum(axis=1) % 2).astype(np.float64)
        col = base_c + (alt_c - base_c) * checker[:, None]
        waves = np.sin(p @ omegas.T + phases) * amps  # (P, k)
        return col * (1.0 + noise * waves @ tints / 1.5)

    return texture
