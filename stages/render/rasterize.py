"""Fast differentiable CPU rasterizer of 2D Gaussians (numba tile kernels in a torch.autograd.Function).

Image formation (3DGS, front to back over Gaussians sorted by depth):

    αᵢ(p) = min(0.99, oᵢ exp(−½ dᵀ Σᵢ⁻¹ d)),  d = μᵢ − p      (skipped when αᵢ < 1/255)
    C(p)  = Σᵢ cᵢ αᵢ Tᵢ,  Tᵢ = Πⱼ<ᵢ (1 − αⱼ),   A(p) = 1 − T_final

and a pixel stops at the first Gaussian that would bring T below 10⁻⁴.  The
outputs are the premultiplied colour C (H, W, 3) and the coverage A (H, W); a
background b is composited outside, I = C + (1 − A) b.

Speed comes from: tile binning (16×16 px tiles; each Gaussian is listed only
in the tiles its footprint touches, with the opacity-aware radius
r = √(2 λ_max ln(255 o)) beyond which α < 1/255), one depth sort, a counting
sort into per-tile lists that stay depth-ordered, per-pixel early stop, and
compiled numba loops parallel over tiles.  The backward pass walks each
pixel back to front from the stored final transmittance and contribution
count (as 3DGS does) and writes per-(tile, Gaussian) gradients that a serial
pass sums — no per-pixel × per-Gaussian tensor, no races, and deterministic.

The dense, obvious twin is ``stages/render/_torch_ref.py``; the tests hold
this module to it, forward and backward.
"""
from __future__ import annotations

import math
import os

import numba as nb
import numpy as np
import torch

if "NUMBA_THREADING_LAYER" not in os.environ:
    # numba's OpenMP layer (the system libgomp) and torch's own libgomp each busy-wait after a
    # parallel region; interleaved, every small torch op then waits for spinning threads
    # (measured 4-5x slower fits).  The workqueue layer sleeps between kernels.
    nb.config.THREADING_LAYER = "workqueue"

TILE = 16
"""Tile edge in pixels."""
ALPHA_MIN = 1.0 / 255.0
"""A Gaussian whose α at a pixel is below this is skipped there."""
ALPHA_MAX = 0.99
"""α is clamped to this (keeps 1 − α invertible in the backward pass)."""
T_MIN = 1e-4
"""A pixel stops when its transmittance would fall below this."""


# --------------------------------------------------------------------------- binning
def footprint_radius(conics: np.ndarray, opacities: np.ndarray) -> np.ndarray:
    """Radius (px) outside which α < 1/255: √(2 λ_max ln(255 o)) + 1, 0 where o ≤ 1/255.

    conics (N, 3) = (a, b, c) of Σ⁻¹; λ_max is the largest eigenvalue of Σ.
    """
    a, b, c = (conics[:, i].astype(np.float64) for i in range(3))
    det = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s00, s11, s01 = c / det, a / det, -b / det  # Σ = conic⁻¹
        mid = 0.5 * (s00 + s11)
        lam = mid + np.sqrt(np.maximum(mid * mid - (s00 * s11 - s01 * s01), 0.0))
        lg = np.log(np.maximum(255.0 * opacities.astype(np.float64), 1e-30))
        r = np.sqrt(np.maximum(2.0 * lam * lg, 0.0)) + 1.0
    ok = (det > 0) & (lg > 0) & np.isfinite(r)
    return np.where(ok, r, 0.0)


@nb.njit(cache=True)
def _bin(mx, my, radius, order, width, height, tile):  # pragma: no cover - compiled
    """Counting sort of (tile, Gaussian) pairs; ``order`` lists Gaussians front to back.

    Returns tile_start (ntiles + 1,) and entries (K,) of Gaussian ids, depth-ordered per tile.
    """
    tx_n = (width + tile - 1) // tile
    ty_n = (height + tile - 1) // tile
    nt = tx_n * ty_n
    counts = np.zeros(nt + 1, np.int64)
    n = order.shape[0]
    rect = np.empty((n, 4), np.int64)
    for k in range(n):
        g = order[k]
        r = radius[g]
        x0 = int(math.floor((mx[g] - r) / tile))
        x1 = int(math.floor((mx[g] + r) / tile))
        y0 = int(math.floor((my[g] - r) / tile))
        y1 = int(math.floor((my[g] + r) / tile))
        x0 = max(x0, 0)
        y0 = max(y0, 0)
        x1 = min(x1, tx_n - 1)
        y1 = min(y1, ty_n - 1)
        rect[k, 0] = x0
        rect[k, 1] = x1
        rect[k, 2] = y0
        rect[k, 3] = y1
        for ty in range(y0, y1 + 1):
            for tx in range(x0, x1 + 1):
                counts[ty * tx_n + tx + 1] += 1
    for t in range(nt):
        counts[t + 1] += counts[t]
    fill = counts[:-1].copy()
    entries = np.empty(counts[nt], np.int64)
    for k in range(n):
        g = order[k]
        for ty in range(rect[k, 2], rect[k, 3] + 1):
            for tx in range(rect[k, 0], rect[k, 1] + 1):
                t = ty * tx_n + tx
                entries[fill[t]] = g
                fill[t] += 1
    return counts, entries


def bin_gaussians(means2d: np.ndarray, conics: np.ndarray, opacities: np.ndarray, depths: np.ndarray,
                  visible: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Tile lists: (tile_start (ntiles+1,), entries (K,)) for the visible Gaussians with a footprint."""
    radius = footprint_radius(conics, opacities)
    keep = visible & (radius > 0)
    idx = np.nonzero(keep)[0]
    order = idx[np.argsort(depths[idx], kind="stable")].astype(np.int64)
    return _bin(means2d[:, 0].astype(np.float64), means2d[:, 1].astype(np.float64), radius, order,
                int(width), int(height), TILE)


# --------------------------------------------------------------------------- kernels
# gdata columns: 0 mx, 1 my, 2 a, 3 b, 4 c, 5 opacity, 6..8 colour.
@nb.njit(cache=True, inline="always")
def _load_tile(gdata, entries, s, k):  # pragma: no cover - compiled
    """Copy a tile's Gaussians into a contiguous block; thr = ln(1/(255 o)) − margin.

    power < thr implies α < 1/255, so the exponential is skipped there; the margin keeps
    the exact α test in charge near the threshold (identical results, fewer exp calls).
    """
    loc = np.empty((k, 9), gdata.dtype)
    thr = np.empty(k, gdata.dtype)
    for i in range(k):
        for j in range(9):
            loc[i, j] = gdata[entries[s + i], j]
        thr[i] = -math.log(255.0 * max(loc[i, 5], 1e-30)) - 1e-3
    return loc, thr


@nb.njit(parallel=True, cache=True)
def _forward(gdata, tile_start, entries, width, height, tile,
             out_color, out_alpha, t_final, n_contrib):  # pragma: no cover - compiled
    tx_n = (width + tile - 1) // tile
    nt = tile_start.shape[0] - 1
    one = gdata.dtype.type(1.0)
    half = gdata.dtype.type(0.5)
    amin = gdata.dtype.type(ALPHA_MIN)
    amax = gdata.dtype.type(ALPHA_MAX)
    tmin = gdata.dtype.type(T_MIN)
    for t in nb.prange(nt):
        s = tile_start[t]
        k = tile_start[t + 1] - s
        x0 = (t % tx_n) * tile
        y0 = (t // tx_n) * tile
        loc, thr = _load_tile(gdata, entries, s, k)
        for py in range(y0, min(y0 + tile, height)):
            for px in range(x0, min(x0 + tile, width)):
                T = one
                r = gdata.dtype.type(0.0)
                g = gdata.dtype.type(0.0)
                b = gdata.dtype.type(0.0)
                fx = gdata.dtype.type(px)
                fy = gdata.dtype.type(py)
                last = 0
                for i in range(k):
                    dx = loc[i, 0] - fx
                    dy = loc[i, 1] - fy
                    power = -half * (loc[i, 2] * dx * dx + loc[i, 4] * dy * dy) - loc[i, 3] * dx * dy
                    if power > 0 or power < thr[i]:
                        continue
                    alpha = min(amax, loc[i, 5] * math.exp(power))
                    if alpha < amin:
                        continue
                    test_t = T * (one - alpha)
                    if test_t < tmin:
                        break
                    w = alpha * T
                    r += loc[i, 6] * w
                    g += loc[i, 7] * w
                    b += loc[i, 8] * w
                    T = test_t
                    last = i + 1
                out_color[py, px, 0] = r
                out_color[py, px, 1] = g
                out_color[py, px, 2] = b
                out_alpha[py, px] = one - T
                t_final[py, px] = T
                n_contrib[py, px] = last


@nb.njit(parallel=True, cache=True)
def _backward(gdata, tile_start, entries, width, height, tile, t_final, n_contrib,
              grad_color, grad_alpha, grad_entries):  # pragma: no cover - compiled
    """Per pixel, back to front: writes ∂L/∂(mx, my, a, b, c, o, r, g, b) per tile entry."""
    tx_n = (width + tile - 1) // tile
    nt = tile_start.shape[0] - 1
    one = gdata.dtype.type(1.0)
    zero = gdata.dtype.type(0.0)
    half = gdata.dtype.type(0.5)
    amin = gdata.dtype.type(ALPHA_MIN)
    amax = gdata.dtype.type(ALPHA_MAX)
    for t in nb.prange(nt):
        s = tile_start[t]
        k = tile_start[t + 1] - s
        x0 = (t % tx_n) * tile
        y0 = (t // tx_n) * tile
        loc, thr = _load_tile(gdata, entries, s, k)
        acc_g = np.zeros((k, 9), np.float64)
        for py in range(y0, min(y0 + tile, height)):
            for px in range(x0, min(x0 + tile, width)):
                n = n_contrib[py, px]
                if n == 0:
                    continue
                tf = t_final[py, px]
                T = tf
                gc0 = grad_color[py, px, 0]
                gc1 = grad_color[py, px, 1]
                gc2 = grad_color[py, px, 2]
                ga = grad_alpha[py, px]
                acc0 = zero
                acc1 = zero
                acc2 = zero
                last_a = zero
                lc0 = zero
                lc1 = zero
                lc2 = zero
                fx = gdata.dtype.type(px)
                fy = gdata.dtype.type(py)
                for i in range(n - 1, -1, -1):
                    dx = loc[i, 0] - fx
                    dy = loc[i, 1] - fy
                    power = -half * (loc[i, 2] * dx * dx + loc[i, 4] * dy * dy) - loc[i, 3] * dx * dy
                    if power > 0 or power < thr[i]:
                        continue
                    G = math.exp(power)
                    raw = loc[i, 5] * G
                    alpha = min(amax, raw)
                    if alpha < amin:
                        continue
                    T = T / (one - alpha)
                    w = alpha * T
                    acc_g[i, 6] += w * gc0
                    acc_g[i, 7] += w * gc1
                    acc_g[i, 8] += w * gc2
                    acc0 = last_a * lc0 + (one - last_a) * acc0
                    acc1 = last_a * lc1 + (one - last_a) * acc1
                    acc2 = last_a * lc2 + (one - last_a) * acc2
                    lc0 = loc[i, 6]
                    lc1 = loc[i, 7]
                    lc2 = loc[i, 8]
                    last_a = alpha
                    dl_dalpha = T * ((lc0 - acc0) * gc0 + (lc1 - acc1) * gc1 + (lc2 - acc2) * gc2) \
                        + ga * tf / (one - alpha)
                    if raw > amax:  # clamped: no gradient through α
                        continue
                    acc_g[i, 5] += G * dl_dalpha
                    dl_dpow = loc[i, 5] * G * dl_dalpha
                    acc_g[i, 0] += -dl_dpow * (loc[i, 2] * dx + loc[i, 3] * dy)
                    acc_g[i, 1] += -dl_dpow * (loc[i, 3] * dx + loc[i, 4] * dy)
                    acc_g[i, 2] += -half * dl_dpow * dx * dx
                    acc_g[i, 3] += -dl_dpow * dx * dy
                    acc_g[i, 4] += -half * dl_dpow * dy * dy
        for i in range(k):
            for j in range(9):
                grad_entries[s + i, j] = acc_g[i, j]


@nb.njit(cache=True)
def _scatter(entries, grad_entries, out):  # pragma: no cover - compiled
    for e in range(entries.shape[0]):
        g = entries[e]
        for j in range(9):
            out[g, j] += grad_entries[e, j]


def _pack(means2d, conics, colors, opacities) -> np.ndarray:
    """(N, 9) contiguous array: mx, my, a, b, c, opacity, r, g, b."""
    f = lambda x: x.detach().cpu().numpy()  # noqa: E731
    return np.concatenate([f(means2d), f(conics), f(opacities)[:, None], f(colors)], 1)


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, visible, width, height):
        gdata = _pack(means2d, conics, colors, opacities)
        dt = gdata.dtype
        vis = visible.detach().cpu().numpy().astype(bool)
        tile_start, entries = bin_gaussians(gdata[:, 0:2], gdata[:, 2:5], gdata[:, 5],
                                            depths.detach().cpu().numpy(), vis, width, height)
        color = np.empty((height, width, 3), dt)
        alpha = np.empty((height, width), dt)
        t_final = np.empty((height, width), dt)
        n_contrib = np.empty((height, width), np.int32)
        _forward(gdata, tile_start, entries, width, height, TILE, color, alpha, t_final, n_contrib)
        ctx.state = (gdata, tile_start, entries, t_final, n_contrib, width, height)
        ctx.n_entries = int(entries.shape[0])
        return torch.from_numpy(color), torch.from_numpy(alpha)

    @staticmethod
    def backward(ctx, grad_color, grad_alpha):
        gdata, tile_start, entries, t_final, n_contrib, width, height = ctx.state
        dt = gdata.dtype
        gc = np.ascontiguousarray(grad_color.detach().cpu().numpy().astype(dt, copy=False))
        ga = np.ascontiguousarray(grad_alpha.detach().cpu().numpy().astype(dt, copy=False))
        ge = np.empty((entries.shape[0], 9), np.float64)
        _backward(gdata, tile_start, entries, width, height, TILE, t_final, n_contrib, gc, ga, ge)
        out = np.zeros((gdata.shape[0], 9), np.float64)
        _scatter(entries, ge, out)
        g = torch.from_numpy(out.astype(dt))
        return g[:, 0:2], g[:, 2:5], g[:, 6:9], g[:, 5], None, None, None, None


def rasterize(means2d: torch.Tensor, conics: torch.Tensor, colors: torch.Tensor, opacities: torch.Tensor,
              depths: torch.Tensor, visible: torch.Tensor, width: int, height: int
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """Premultiplied colour (H, W, 3) and coverage A (H, W) of 2D Gaussians, differentiable.

    means2d (N, 2) px, conics (N, 3) = (a, b, c) of Σ⁻¹ px⁻², colors (N, 3), opacities (N,) in (0, 1),
    depths (N,) sort key (front first), visible (N,) bool.  Gradients flow to means2d, conics,
    colors and opacities.  Float32 or float64 (all inputs of one dtype).
    """
    n = means2d.shape[0]
    assert means2d.shape == (n, 2) and conics.shape == (n, 3) and colors.shape == (n, 3)
    assert opacities.shape == (n,) and depths.shape == (n,) and visible.shape == (n,)
    return _Rasterize.apply(means2d, conics, colors, opacities, depths, visible, int(width), int(height))


def tile_stats(means2d, conics, opacities, depths, visible, width, height) -> dict:
    """Number of (tile, Gaussian) pairs and the longest tile list (for benchmarks)."""
    f = lambda x: x.detach().cpu().numpy()  # noqa: E731
    ts, e = bin_gaussians(f(means2d), f(conics), f(opacities), f(depths), f(visible).astype(bool),
                          width, height)
    return {"pairs": int(e.shape[0]), "max_per_tile": int(np.max(np.diff(ts))) if len(ts) > 1 else 0}
