"""The silhouette observation of ``rsl adapt`` (issue 15): the soft coverage of the simulated surface per pixel
against the segmentation masks (masks.h5) — geometry only, so it still depends on E on a static capture,
where the Gaussians (fitted to that very frame and re-bound to x_0(θ)) render the same image for every θ.

Soft coverage of camera c (a differentiable rasteriser of the surface triangles, SoftRas-like):

    d_f(p)  = signed distance (pixels) of pixel centre p to the projected triangle f (> 0 inside: the
              smallest distance to its three edge lines; < 0 outside: minus the distance to its boundary)
    A_c(p)  = 1 − exp(−Σ_f softplus((d_f(p) − δ)/τ))     (= 1 − Π_f (1 − σ((d_f − δ)/τ)), a union of soft
              triangles)

τ = 0.25 px gives an edge about the slope of a one-pixel box filter.  The outline of a closed surface is the
shared edge of a front and a back face, two soft edges on the same side: δ = −τ log(√2 − 1) = 0.881 τ puts
A = ½ exactly on it (without δ, A = ¾ there and the silhouette grows by ~½ px all round, which on a sagging bar
7 px thick biased E by −4.5 %).  Residual per pixel:

    r_c = G_s [(A_c(x_t) − m_t^c) · keep_t^c]      (keep = 0 under an occluder, controls.json visuals)

G_s a Gaussian blur of s = 2 px (SilhouetteObservation.blur_px; zero beyond the image, so Gᵀ = G), and A_c(x, b) the
coverage with the outline moved outwards by b pixels (softplus((d_f + b − δ)/τ)), b matched per camera and frame
so that the areas agree, Σ keep·(A_c(x, b) − m) = 0 (:meth:`SilhouetteObservation.outline`; |b| ≤ GROW_MAX_PX).
A mask's outline sits wherever its maker's convention puts it (rsl synth's truth masks, 2 × 2-supersampled
coverage ≥ ½, lie ~0.1–0.25 px outside the ½-coverage outline; GrabCut's elsewhere): the blur mixes that uniform
offset with the outline's motion, and on a 64² bar 7 px thick it moved the loss minimum to 1.10 E_true (blur 0 /
0.5 / 1 / 2 px: 1.016 / 1.027 / 1.067 / 1.101; with b matched: 1.000 / – / 1.006 / 1.007, truth masks).  b(x)
is an implicit function of x, so J and dL/dx carry its derivative db/dx·v = −⟨keep, ∂A/∂x·v⟩ / ⟨keep, ∂A/∂b⟩.  Without it
a Gauss–Newton step moves the outline by about the soft edge's width, τ: ∂r/∂x is non-zero only within ~τ of the
simulated outline, where the saturated misfit (±1 over the whole gap) cannot show how far the mask's outline lies —
from a start 2.5× too soft the beam's outline crept ~0.3 px per iteration (10 iterations: E 0.63 E_true).  The
blur spreads both the misfit and ∂r/∂x over ~s, so a step reaches ~2.5 s px; it weights the same misfit
differently (GᵀG), so a perfect fit stays the minimum.  Loss Σ r²; J = ∂r/∂x · dX by forward-mode autodiff (jax.jvp), dL/dx by reverse mode (exact, FD-checked in
tests/test_silhouette.py).

Sparse evaluation (the default): a triangle's term is evaluated only at the pixels whose centres lie within its
projected bounding box grown by m pixels on every side.  A pixel outside it is at least m from the triangle, so
the term left out is softplus(−(m + δ)/τ) ≤ exp(−(m + δ)/τ); with

    m = τ (ln(F / ε) − δ/τ)      (F the surface triangles, ε = CUT_EPS = 10⁻⁶)

the terms dropped at one pixel sum to at most ε, and A (1 − e^{−S} is 1-Lipschitz in S) moves by at most ε.
``dense=True`` evaluates every triangle at every pixel of the object's box (grown by 40 τ, where each term is
below e⁻⁴⁰): the slow obvious twin the tests hold the sparse one to.

σ of the estimate: a mask's error along the outline is shared by neighbouring pixels (and repeats in every frame
of a still capture), so the residuals are clustered in 8 × 8 pixel blocks (:meth:`SilhouetteObservation.clusters`)
and Gauss–Newton reports the cluster-robust sandwich (stages.estimator.cluster_scale2) instead of RSS/(m − k),
which takes ~10⁴ pixels as independent (measured against other block sizes in docs/results/static.md).  A mask
error that looks like a change of E leaves no residual (E takes it up), so no sandwich sees it; the outline floor
adds it: an outline error e_c of σ_o pixels in each block c, independent between blocks, moves the
mask by Δm = e_c ∂A/∂b there (b taking up its area), and p by

    σ²_floor,k = σ_o² Σ_c g_{c,k}² / (J_kᵀ J_k)²,   g_c = Jᵀ ∂r/∂e_c        (:meth:`SilhouetteObservation.sigma_floor`)

which adapt adds to --model-error in quadrature.  σ_o is the RMS outline misfit the masks show at the estimate
(Σ_c (Σ_{p∈c} keep (A − m))² / a_c over Σ_c a_c, a_c = Σ_{p∈c} keep ∂A/∂b the outline's length in c: GrabCut's
errors), at least OUTLINE_PX, the resolution floor of masks that are right but drawn on the pixel grid — measured
in bench/static.py ("Resolution floor": the spread of E from truth masks as the camera moves by sub-pixel offsets,
over its σ_floor per pixel: 0.091 / 0.135 px on the bar at 64² / 96², 0.011–0.012 px on the beam).
"""
from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from scipy.ndimage import gaussian_filter

from stages.artefacts import KIND_FILES, CamerasArtefact, MasksArtefact
from stages.capture import Capture, CaptureError
from stages.errors import RslError
from stages.observations import pick_cameras
from stages.occluders import has_occluders, ignore_mask
from stages.render.mesh_raster import project_points

jax.config.update("jax_enable_x64", True)

TAU_PX = 0.25  # soft edge width τ, pixels
SHIFT_TAU = -float(np.log(np.sqrt(2.0) - 1.0))  # δ/τ: two faces meeting on the outline make A = ½ there
CUT_EPS = 1e-6  # sparse evaluation: the most the triangles' terms left out change A at any pixel (module doc)
GROW_MAX_PX = 1.0  # the most the outline offset b moves the outline, pixels (either way; module doc)
OUTLINE_PX = 0.14  # σ of a mask's outline error per block_px × block_px block, pixels (module doc: measured)
_MARGIN_TAU = 40.0  # dense twin: bounding-box margin in units of τ (softplus(−40) ≈ 4e-18)
_CHUNK = 64  # dense twin: triangles per scan step (memory: pixels × chunk)
_ROUND = 32  # dense twin: the pixel box is rounded up to this many pixels (fewer re-compilations)


def _project(x, K, R, t, dist):
    """Pixels (n, 2) and depth (n,) of world points x (n, 3) — stages.render.mesh_raster.project_points in jax."""
    pc = x @ R.T + t
    z = pc[:, 2]
    zs = jnp.where(jnp.abs(z) < 1e-12, 1e-12, z)
    a, b = pc[:, 0] / zs, pc[:, 1] / zs
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r2 = a * a + b * b
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    a, b = (a * radial + 2 * p1 * a * b + p2 * (r2 + 2 * a * a),
            b * radial + p1 * (r2 + 2 * b * b) + 2 * p2 * a * b)
    u = K[0, 0] * a + K[0, 1] * b + K[0, 2]
    v = K[1, 1] * b + K[1, 2]
    return jnp.stack([u, v], axis=1), z


def _signed_distance(pix, tri):
    """Signed distance (...) of pixel centres pix (..., 2) to triangles tri (..., 3, 2) (the leading shapes
    broadcast): inside > 0 (the smallest distance to the edge lines), outside < 0 (minus the distance to the
    nearest edge segment); either orientation."""
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    area2 = (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])
    s = jnp.where(area2 >= 0, 1.0, -1.0)
    lines, segs = [], []
    for p, q in ((a, b), (b, c), (c, a)):
        e = q - p  # (..., 2)
        L2 = jnp.sum(e * e, axis=-1) + 1e-24
        w = pix - p  # (..., 2)
        cross = e[..., 0] * w[..., 1] - e[..., 1] * w[..., 0]
        lines.append(s * cross / jnp.sqrt(L2))
        u = jnp.clip(jnp.sum(w * e, axis=-1) / L2, 0.0, 1.0)
        dv = w - u[..., None] * e
        segs.append(jnp.sum(dv * dv, axis=-1))
    inner = jnp.minimum(jnp.minimum(lines[0], lines[1]), lines[2])
    d2 = jnp.minimum(jnp.minimum(segs[0], segs[1]), segs[2])
    outer = -jnp.sqrt(jnp.where(d2 > 0, d2, 1.0)) * (d2 > 0)
    return jnp.where(inner >= 0, inner, outer)


@partial(jax.jit, static_argnames=("tau",))
def _coverage(x, grow, faces, valid, pix, K, R, t, dist, tau):
    """Dense twin: soft coverage (P,) at pixel centres pix (P, 2) of every triangle faces (F, 3) of x (n, 3), the
    outline moved outwards by ``grow`` pixels; faces padded to a multiple of _CHUNK rows, ``valid`` (F,) 0 for
    the padding."""
    uv, z = _project(x, K, R, t, dist)
    tri = uv[faces]  # (F, 3, 2)
    ok = valid * jnp.all(z[faces] > 1e-3, axis=1)
    nch = faces.shape[0] // _CHUNK

    def step(S, k):
        sl = jax.lax.dynamic_slice_in_dim(tri, k * _CHUNK, _CHUNK)
        w = jax.lax.dynamic_slice_in_dim(ok, k * _CHUNK, _CHUNK)
        d = _signed_distance(pix[:, None, :], sl[None])  # (P, chunk)
        return S + jnp.sum(w[None] * jax.nn.softplus((d + grow) / tau - SHIFT_TAU), axis=1), None

    S, _ = jax.lax.scan(step, jnp.zeros(pix.shape[0], x.dtype), jnp.arange(nch))
    return 1.0 - jnp.exp(-S)


def _coverage_pairs(x, grow, faces, pair_face, pair_pix, pair_xy, pair_w, K, R, t, dist, tau, npix):
    """Sparse: soft coverage (npix,) of the image's pixels (row-major) from the (triangle, pixel) pairs
    pair_face, pair_pix (N,) (pixel centres pair_xy (N, 2), weight pair_w (N,) 0 for padding):
    S(p) = Σ_{pairs at p} softplus((d + b − δ)/τ), A = 1 − e^{−S}, b = ``grow`` (pixels)."""
    uv, z = _project(x, K, R, t, dist)
    fv = faces[pair_face]  # (N, 3)
    ok = pair_w * jnp.all(z[fv] > 1e-3, axis=1)
    d = _signed_distance(pair_xy, uv[fv])  # (N,)
    S = jax.ops.segment_sum(ok * jax.nn.softplus((d + grow) / tau - SHIFT_TAU), pair_pix, num_segments=npix)
    return 1.0 - jnp.exp(-S)


_cov_sparse = jax.jit(_coverage_pairs, static_argnames=("tau", "npix"))


@partial(jax.jit, static_argnames=("tau", "npix"))
def _jvp_sparse(x, grow, V, *args, tau, npix):
    """dA/dx · V (k, npix) for directions V (k, n, 3)."""
    return jax.vmap(lambda v: jax.jvp(lambda y: _coverage_pairs(y, grow, *args, tau=tau, npix=npix), (x,),
                                      (v,))[1])(V)


@partial(jax.jit, static_argnames=("tau", "npix"))
def _vjp_sparse(x, grow, g, *args, tau, npix):
    """(dA/dx)ᵀ g (n, 3) for a cotangent g (npix,)."""
    _, back = jax.vjp(lambda y: _coverage_pairs(y, grow, *args, tau=tau, npix=npix), x)
    return back(g)[0]


@partial(jax.jit, static_argnames=("tau", "npix"))
def _dgrow_sparse(x, grow, *args, tau, npix):
    """(A, ∂A/∂b) (npix,) each, b the outline offset ``grow``."""
    return jax.jvp(lambda b: _coverage_pairs(x, b, *args, tau=tau, npix=npix), (grow,), (jnp.ones_like(grow),))


def _bucket(n: int) -> int:
    """n rounded up to 1024 · 2^k · {1, 1.25, 1.5, 1.75} (few array shapes: few re-compilations)."""
    if n <= 1024:
        return 1024
    p = 1 << (int(n - 1).bit_length() - 1)
    for f in (1.0, 1.25, 1.5, 1.75, 2.0):
        if n <= int(p * f):
            return int(p * f)
    return 2 * p


class SoftSilhouette:
    """Soft coverage A (H, W) of a surface (faces (F, 3), vertex ids) in one camera, with its forward- and
    reverse-mode derivatives in the vertex positions.  ``dense``: the slow obvious twin (every triangle at
    every pixel of the object's box) instead of the sparse (triangle, nearby pixel) pairs (module doc)."""

    def __init__(self, faces: np.ndarray, camera, tau_px: float = TAU_PX, dense: bool = False):
        faces = np.asarray(faces, np.int64)[:, :3]
        F = len(faces)
        self._faces_np = faces
        pad = (-F) % _CHUNK
        self.faces = jnp.asarray(np.vstack([faces, np.zeros((pad, 3), np.int64)]))
        self.faces_sparse = jnp.asarray(faces if F else np.zeros((1, 3), np.int64))
        self.valid = jnp.asarray(np.r_[np.ones(F), np.zeros(pad)])
        self.H, self.W = int(camera.height), int(camera.width)
        dist = np.zeros(5)
        d = np.asarray(camera.dist, np.float64).reshape(-1)[:5]
        dist[:len(d)] = d
        self.cam = tuple(jnp.asarray(np.asarray(a, np.float64)) for a in
                         (camera.K, camera.R, np.asarray(camera.t, np.float64).reshape(3), dist))
        self._used = np.unique(faces)
        self._camera = camera
        self.tau = float(tau_px)
        self.dense = bool(dense)
        # m = τ (ln(F/ε) − δ/τ) + b_max: F triangles each below ε/F beyond m pixels for |b| ≤ b_max (module doc)
        self.margin_px = self.tau * max(float(np.log(max(F, 1) / CUT_EPS)) - SHIFT_TAU, 0.0) + GROW_MAX_PX
        self.pairs = 0  # (triangle, pixel) pairs of the last sparse evaluation (without the padding)
        self._npad = 0  # padded pair count: it only grows (one compilation serves the states that follow)

    # ---------------------------------------------------------------------------------------------- sparse
    def _pair_arrays(self, x: np.ndarray) -> tuple:
        """The (triangle, pixel) pairs at positions x (n, 3): every pixel centre within the triangle's projected
        bounding box grown by margin_px, padded with weight-0 pairs to the largest :func:`_bucket` so far."""
        c, f = self._camera, self._faces_np
        uv, z = project_points(np.asarray(x, np.float64), c.K, c.R, c.t, c.dist)
        front = np.all(z[f] > 1e-3, axis=1)
        fid = np.flatnonzero(front)
        tri = uv[f[fid]]  # (F', 3, 2)
        m = self.margin_px + 1e-6  # (the jax projection may differ from numpy's in the last bits)
        x0 = np.clip(np.ceil(tri[..., 0].min(1) - m), 0, self.W).astype(np.int64)
        x1 = np.clip(np.floor(tri[..., 0].max(1) + m) + 1, 0, self.W).astype(np.int64)
        y0 = np.clip(np.ceil(tri[..., 1].min(1) - m), 0, self.H).astype(np.int64)
        y1 = np.clip(np.floor(tri[..., 1].max(1) + m) + 1, 0, self.H).astype(np.int64)
        w, h = np.maximum(x1 - x0, 0), np.maximum(y1 - y0, 0)
        cnt = w * h
        N = int(cnt.sum())
        self.pairs = N
        face = np.repeat(fid, cnt)
        local = np.arange(N) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        wr = np.repeat(w, cnt)
        px = np.repeat(x0, cnt) + local % np.maximum(wr, 1)
        py = np.repeat(y0, cnt) + local // np.maximum(wr, 1)
        self._npad = max(self._npad, _bucket(N))
        pad = self._npad - N
        face = np.r_[face, np.zeros(pad, np.int64)]
        pix = np.r_[py * self.W + px, np.zeros(pad, np.int64)]
        xy = np.stack([pix % self.W, pix // self.W], axis=1).astype(np.float64)
        wt = np.r_[np.ones(N), np.zeros(pad)]
        return (self.faces_sparse, jnp.asarray(face, jnp.int32), jnp.asarray(pix, jnp.int32), jnp.asarray(xy),
                jnp.asarray(wt), *self.cam)

    # ----------------------------------------------------------------------------------------------- dense
    def box(self, x: np.ndarray) -> tuple[int, int, int, int]:
        """Dense twin: (y0, y1, x0, x1), the pixels where A may be non-zero at positions x (n, 3)."""
        c = self._camera
        uv, z = project_points(np.asarray(x)[self._used], c.K, c.R, c.t, c.dist)
        uv = uv[z > 1e-3]
        if not len(uv):
            return 0, 0, 0, 0
        m = _MARGIN_TAU * self.tau + 1.0 + GROW_MAX_PX
        x0 = int(np.clip(np.floor(uv[:, 0].min() - m), 0, self.W))
        y0 = int(np.clip(np.floor(uv[:, 1].min() - m), 0, self.H))
        x1 = int(np.clip(np.ceil(uv[:, 0].max() + m) + 1, 0, self.W))
        y1 = int(np.clip(np.ceil(uv[:, 1].max() + m) + 1, 0, self.H))
        # round up (fewer shapes to compile), staying inside the image
        w, h = -(-(x1 - x0) // _ROUND) * _ROUND, -(-(y1 - y0) // _ROUND) * _ROUND
        x1, y1 = min(self.W, x0 + w), min(self.H, y0 + h)
        x0, y0 = max(0, x1 - w), max(0, y1 - h)
        return y0, y1, x0, x1

    def _pix(self, box):
        y0, y1, x0, x1 = box
        yy, xx = np.mgrid[y0:y1, x0:x1]
        return jnp.asarray(np.stack([xx.ravel(), yy.ravel()], axis=1).astype(np.float64))

    def _f(self, box, grow: float = 0.0):
        pix = self._pix(box)
        b = jnp.asarray(float(grow), jnp.float64)
        return lambda x: _coverage(x, b, self.faces, self.valid, pix, *self.cam, tau=self.tau)

    @staticmethod
    def _grow(grow: float) -> jnp.ndarray:
        if not abs(float(grow)) <= GROW_MAX_PX:
            raise ValueError(f"outline offset {grow} px is beyond ±GROW_MAX_PX = {GROW_MAX_PX}")
        return jnp.asarray(float(grow), jnp.float64)

    # ---------------------------------------------------------------------------------------------- public
    def coverage(self, x: np.ndarray, box=None, grow: float = 0.0) -> np.ndarray:
        """A (H, W) at positions x (n, 3), the outline moved outwards by ``grow`` pixels (|grow| ≤ GROW_MAX_PX)."""
        xj, b = jnp.asarray(x, jnp.float64), self._grow(grow)
        if not self.dense:
            A = _cov_sparse(xj, b, *self._pair_arrays(x), tau=self.tau, npix=self.H * self.W)
            return np.asarray(A).reshape(self.H, self.W)
        box = box or self.box(x)
        out = np.zeros((self.H, self.W))
        y0, y1, x0, x1 = box
        if y1 > y0 and x1 > x0:
            out[y0:y1, x0:x1] = np.asarray(self._f(box, grow)(xj)).reshape(y1 - y0, x1 - x0)
        return out

    def coverage_dgrow(self, x: np.ndarray, grow: float = 0.0, box=None) -> tuple[np.ndarray, np.ndarray]:
        """(A, ∂A/∂b) (H, W) each at positions x (n, 3) and outline offset b = ``grow`` pixels."""
        xj, b = jnp.asarray(x, jnp.float64), self._grow(grow)
        if not self.dense:
            A, dA = _dgrow_sparse(xj, b, *self._pair_arrays(x), tau=self.tau, npix=self.H * self.W)
            return np.asarray(A).reshape(self.H, self.W), np.asarray(dA).reshape(self.H, self.W)
        box = box or self.box(x)
        A, dA = np.zeros((self.H, self.W)), np.zeros((self.H, self.W))
        y0, y1, x0, x1 = box
        if y1 > y0 and x1 > x0:
            pix = self._pix(box)
            a, da = jax.jvp(lambda g: _coverage(xj, g, self.faces, self.valid, pix, *self.cam, tau=self.tau), (b,),
                            (jnp.ones_like(b),))
            A[y0:y1, x0:x1] = np.asarray(a).reshape(y1 - y0, x1 - x0)
            dA[y0:y1, x0:x1] = np.asarray(da).reshape(y1 - y0, x1 - x0)
        return A, dA

    def jvp(self, x: np.ndarray, V: np.ndarray, box=None, grow: float = 0.0) -> np.ndarray:
        """dA/dx · V (k, H, W) for position directions V (k, n, 3)."""
        xj, b = jnp.asarray(x, jnp.float64), self._grow(grow)
        if not self.dense:
            if not len(V):
                return np.zeros((0, self.H, self.W))
            J = _jvp_sparse(xj, b, jnp.asarray(V, jnp.float64), *self._pair_arrays(x), tau=self.tau,
                            npix=self.H * self.W)
            return np.asarray(J).reshape(len(V), self.H, self.W)
        box = box or self.box(x)
        y0, y1, x0, x1 = box
        out = np.zeros((len(V), self.H, self.W))
        if y1 > y0 and x1 > x0:
            f = self._f(box, grow)
            for j, v in enumerate(V):
                out[j, y0:y1, x0:x1] = np.asarray(jax.jvp(f, (xj,), (jnp.asarray(v, jnp.float64),))[1]
                                                  ).reshape(y1 - y0, x1 - x0)
        return out

    def vjp(self, x: np.ndarray, g: np.ndarray, box=None, grow: float = 0.0) -> np.ndarray:
        """(dA/dx)ᵀ g (n, 3) for a pixel cotangent g (H, W)."""
        xj, b = jnp.asarray(x, jnp.float64), self._grow(grow)
        if not self.dense:
            return np.asarray(_vjp_sparse(xj, b, jnp.asarray(np.asarray(g, np.float64).ravel()),
                                          *self._pair_arrays(x), tau=self.tau, npix=self.H * self.W))
        box = box or self.box(x)
        y0, y1, x0, x1 = box
        if not (y1 > y0 and x1 > x0):
            return np.zeros_like(np.asarray(x, np.float64))
        _, back = jax.vjp(self._f(box, grow), xj)
        return np.asarray(back(jnp.asarray(np.asarray(g, np.float64)[y0:y1, x0:x1].ravel()))[0])


class SilhouetteObservation:
    """Masks (masks.h5) against the soft coverage of the simulated surface in each chosen camera (module doc):
    for static captures with images, where the Gaussian image loss is flat in θ."""

    kind = "silhouette"
    huber = None  # plain least squares: residuals are bounded in [−1, 1]
    blur_px = 2.0  # σ of the Gaussian blur of the residual images, pixels (module doc: the Gauss–Newton step's reach)
    noise_floor = 1e-3  # of a pixel's coverage

    def __init__(self, capture: Capture, ws: Path, cam_spec: str, mesh, tau_px: float = TAU_PX):
        self.capture, self.n = capture, mesh.n_vertices
        cams_path, masks_path = ws / KIND_FILES["cameras"], ws / KIND_FILES["masks"]
        if not masks_path.exists():
            raise RslError(f"{masks_path}: file not found; the silhouette loss compares the simulated surface with "
                           f"the masks of `rsl segment`.")
        cams_art = CamerasArtefact.load(cams_path)
        self.masks = MasksArtefact.load(masks_path).masks
        names = pick_cameras(cam_spec, [c.name for c in cams_art.cameras], cams_path)
        self.cameras = [c for c in names if c in self.masks]
        if not self.cameras:
            raise RslError(f"{masks_path}: holds no mask of the cameras {', '.join(names)} of cameras.h5.")
        self._cams = [cams_art.by_name(c) for c in self.cameras]
        for c, cam in zip(self.cameras, self._cams):
            if self.masks[c].shape[1:] != (cam.height, cam.width):
                raise RslError(f"{masks_path}: the masks of camera '{c}' are {self.masks[c].shape[2]}x"
                               f"{self.masks[c].shape[1]} but cameras.h5 calibrates it for {cam.width}x{cam.height}.")
        # quadratic tets: surface_faces are already each curved face split into 4 flat ones through its mid-edge
        # nodes (stages.sim.quadrature.quadratic_surface), so the silhouette follows the curved surface
        faces = np.asarray(mesh.surface_faces)[:, :3]
        self.soft = [SoftSilhouette(faces, cam, tau_px) for cam in self._cams]
        self.controls = capture.controls()
        self.occluded = has_occluders(self.controls)
        self._ignore: dict[int, list] = {}
        self.grow_px: dict[tuple[int, int], float] = {}  # (frame, camera index) -> the last outline offset b
        self._outline_at: dict = {}  # (frame, camera index) -> (x, mask, outline()) of the last call
        self.sources = {}  # the frames are not read: masks.h5 holds what is compared

    def rebind(self, x_anchor: np.ndarray) -> None:
        """Nothing is bound to the surface: the coverage is of x_t itself."""

    def available(self) -> int:
        """Frames with a mask in every chosen camera."""
        return min(len(self.masks[c]) for c in self.cameras)

    def count_checked(self) -> int:
        return self.available()

    def keep(self, t: int) -> list[np.ndarray]:
        """Per camera, (H, W) 1.0 where the pixel counts at frame t, 0 under an occluder."""
        if t not in self._ignore:
            self._ignore[t] = [(~ignore_mask(self.controls, t, c)).astype(np.float64) if self.occluded
                               else np.ones((c.height, c.width)) for c in self._cams]
        return self._ignore[t]

    def _check(self, t: int) -> None:
        if t >= self.available():
            raise CaptureError(f"masks.h5 holds no mask of frame {t} (rerun rsl segment).")

    def blur(self, img: np.ndarray) -> np.ndarray:
        """G img: the Gaussian blur of ``blur_px`` pixels (zero beyond the image; a symmetric operator, Gᵀ = G)
        — (..., H, W) image by image."""
        if not self.blur_px:
            return img
        sig = (0,) * (img.ndim - 2) + (self.blur_px, self.blur_px)
        return gaussian_filter(np.asarray(img, np.float64), sig, mode="constant", cval=0.0, truncate=4.0)

    match_outline = True  # the outline offset b matched per camera and frame (module doc); False: b = 0

    def outline(self, t: int, j: int, x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray | None]:
        """(b, A, ∂A/∂b, β) of camera j at frame t, positions x (n, 3): the outline offset b (pixels) with
        Σ keep·(A(x, b) − m) = 0 (safeguarded Newton in b, from the last b of this frame and camera), A and ∂A/∂b
        (H, W) there, and β = ∂A/∂b / ⟨keep, ∂A/∂b⟩ (H, W), which gives db/dx·v = −⟨keep, ∂A/∂x·v⟩ / ⟨keep, ∂A/∂b⟩
        — None where b = 0 is held (match_outline off) or pinned at ±GROW_MAX_PX (the root lies beyond)."""
        s, k, src = self.soft[j], self.keep(t)[j], self.masks[self.cameras[j]]
        m = src[t].astype(np.float64)
        if not self.match_outline:
            A, dA = s.coverage_dgrow(x, 0.0)
            return 0.0, A, dA, None
        cache = self.__dict__.setdefault("_outline_at", {})
        last = cache.get((t, j))
        if last is not None and last[1] is src and last[0].shape == x.shape and np.array_equal(last[0], x):
            return last[2]  # the same positions and masks as the last call (residuals, then jacobian, at one x)
        out = self._outline(s, k, m, t, j, x)
        cache[(t, j)] = (np.array(x, copy=True), src, out)
        return out

    def _outline(self, s, k, m, t, j, x):
        lo, hi = -GROW_MAX_PX, GROW_MAX_PX
        b = float(np.clip(self.grow_px.get((t, j), 0.0), lo, hi))
        for _ in range(80):
            A, dA = s.coverage_dgrow(x, b)
            f, fp = float(np.sum(k * (A - m))), float(np.sum(k * dA))  # f increases with b
            if (f < 0 and b >= GROW_MAX_PX) or (f > 0 and b <= -GROW_MAX_PX) or fp <= 0:
                self.grow_px[(t, j)] = b  # the root lies beyond the bound (or nothing of the outline is seen)
                return b, A, dA, None
            if f > 0:
                hi = b
            else:
                lo = b
            nb = b - f / fp
            if not lo < nb < hi:  # outside the bracket: the bound itself if not tried yet, else bisect
                nb = (GROW_MAX_PX if nb >= hi == GROW_MAX_PX else -GROW_MAX_PX if nb <= lo == -GROW_MAX_PX
                      else 0.5 * (lo + hi))
            if abs(nb - b) < 1e-11:
                break
            b = nb
        else:  # (not reached in practice: Newton from a bracket converges in a few steps)
            A, dA = s.coverage_dgrow(x, b)
            fp = float(np.sum(k * dA))
        self.grow_px[(t, j)] = b
        return b, A, dA, dA / fp

    def residual_images(self, t: int, x: np.ndarray) -> list[np.ndarray]:
        """Per camera, r (H, W) = G((A(x, b) − m_t)·keep_t), b the matched outline offset (:meth:`outline`)."""
        self._check(t)
        if not self.match_outline:
            return [self.blur((s.coverage(x[:self.n]) - self.masks[c][t].astype(np.float64)) * k)
                    for s, c, k in zip(self.soft, self.cameras, self.keep(t))]
        return [self.blur((self.outline(t, j, x[:self.n])[1] - self.masks[c][t].astype(np.float64)) * k)
                for j, (c, k) in enumerate(zip(self.cameras, self.keep(t)))]

    def residuals(self, frames: Sequence[int], X: np.ndarray) -> list[np.ndarray]:
        """Per frame, r_f over every pixel of every chosen camera, flattened."""
        return [np.concatenate([r.ravel() for r in self.residual_images(t, x)]) for t, x in zip(frames, X)]

    def loss(self, frames: Sequence[int], X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(per-frame Σ r² (w,), dL/dX (w, n, 3)) — the gradient exact by reverse mode, through b(x) too:
        dL/dx = (∂A/∂x)ᵀ (w − ⟨β, w⟩ keep),  w = keep · G(2r)."""
        self._check(max(frames, default=0))
        losses, grad = np.zeros(len(frames)), np.zeros_like(np.asarray(X, np.float64))
        for i, (t, x) in enumerate(zip(frames, X)):
            for j, (s, c, k) in enumerate(zip(self.soft, self.cameras, self.keep(t))):
                b, A, _, beta = self.outline(t, j, x[:self.n])
                r = self.blur((A - self.masks[c][t].astype(np.float64)) * k)
                losses[i] += float(np.sum(r * r))
                w = self.blur(2.0 * r) * k
                if beta is not None:
                    w = w - float(np.sum(beta * w)) * k
                grad[i, :self.n] += s.vjp(x[:self.n], w, grow=b)
        return losses, grad

    def jacobian(self, frames: Sequence[int], X: np.ndarray, dX: np.ndarray) -> list[np.ndarray]:
        """Per frame, ∂r_f/∂p (pixels, k) = G(keep · (J_v − ⟨keep, J_v⟩ β)), J_v = (∂A/∂x) dX[:, f], by forward
        mode (exact; β from :meth:`outline`: b follows x).  Also sets :attr:`floor_unit` and
        :attr:`outline_rms_px` (module doc, "σ of the estimate") for these frames."""
        out, nk = [], len(dX)
        g = [np.zeros((nk, self._nblocks(c))) for c in self._cams]  # per camera, Jᵀ ∂r/∂e_c (k, blocks)
        jtj, e2, elen = np.zeros(nk), 0.0, 0.0
        for i, (t, x) in enumerate(zip(frames, X)):
            cols = []
            for j, (s, k, c) in enumerate(zip(self.soft, self.keep(t), self.cameras)):
                b, A, dA, beta = self.outline(t, j, x[:self.n])
                Jv = s.jvp(x[:self.n], dX[:, i, :self.n], grow=b)
                if beta is not None:
                    Jv = Jv - np.einsum("khw,hw->k", Jv, k)[:, None, None] * beta[None]
                Jb = self.blur(Jv * k[None])
                cols.append(Jb.reshape(nk, -1))
                # an outline error e_c (pixels) of the mask in block c: Δm = e_c ∂A/∂b on c, b taking up its area
                ids, kd = self._block_ids(self._cams[j]), (k * dA).ravel()
                GJ = self.blur(Jb).reshape(nk, -1)
                a_c = np.bincount(ids, kd, minlength=g[j].shape[1])
                h = np.stack([np.bincount(ids, GJ[q] * kd, minlength=g[j].shape[1]) for q in range(nk)])
                g[j] += (h if beta is None else h - (GJ @ (k * beta).ravel())[:, None] * a_c[None])
                jtj += np.einsum("kp,kp->k", cols[-1], cols[-1])
                num = np.bincount(ids, (k * (A - self.masks[c][t])).ravel(), minlength=len(a_c))
                seen = a_c > 0.5  # blocks the outline crosses (∂A/∂b sums to its length in pixels)
                e2, elen = e2 + float(np.sum(num[seen] ** 2 / a_c[seen])), elen + float(np.sum(a_c[seen]))
            out.append(np.concatenate(cols, axis=1).T)
        self.floor_unit = np.sqrt(sum(np.sum(gj * gj, axis=1) for gj in g)) / np.maximum(jtj, 1e-300)
        self.outline_rms_px = float(np.sqrt(e2 / elen)) if elen > 0 else 0.0
        return out

    floor_unit = None  # (k,) σ of each parameter per pixel of outline error per block (set by jacobian)
    outline_rms_px = 0.0  # RMS outline misfit of the mask against A, pixels, over the outline's blocks (jacobian)
    outline_px = OUTLINE_PX  # σ of a mask's outline error per block, pixels (module doc)

    def sigma_floor(self) -> np.ndarray:
        """(k,) σ of each parameter of the last :meth:`jacobian` that a mask's outline error of σ_o pixels per
        block, independent between blocks, makes — an error no residual shows where it looks like a change of θ
        (module doc); σ_o = max(``outline_px``, the RMS outline misfit the masks show there); adapt adds it to
        --model-error in quadrature."""
        if self.floor_unit is None:
            raise RuntimeError("sigma_floor() needs a jacobian() first")
        return max(self.outline_px, self.outline_rms_px) * np.asarray(self.floor_unit)

    def _nblocks(self, c) -> int:
        return -(-c.width // self.block_px) * -(-c.height // self.block_px)

    def _block_ids(self, c) -> np.ndarray:
        b = self.block_px
        yy, xx = np.divmod(np.arange(c.height * c.width), c.width)
        return (yy // b) * -(-c.width // b) + xx // b

    block_px = 8  # side of the pixel blocks whose errors are taken as correlated (:meth:`clusters`)

    def clusters(self, frames: Sequence[int]) -> np.ndarray:
        """Cluster id (m,) of each residual of :meth:`residuals` over ``frames``: its camera's block of
        ``block_px`` × ``block_px`` pixels, the same block in every frame (a still capture shows one equilibrium:
        a mask's error along the outline repeats from frame to frame), for the estimator's cluster-robust σ
        (stages.estimator.cluster_scale2, as stages.observations.VisionObservation.clusters)."""
        ids, base = [], 0
        for c in self._cams:
            ids.append(base + self._block_ids(c))
            base += self._nblocks(c)
        return np.tile(np.concatenate(ids), len(frames))

    def noise_scale(self, r: np.ndarray) -> float:
        """σ of one pixel residual: the RMS over the pixels that differ (> 10⁻³; the pixels far from every edge,
        which match to rounding, are left out)."""
        a = r[np.abs(r) > 1e-3]
        return float(np.sqrt(np.mean(a * a))) if len(a) else 0.0
