"""Fast differentiable CPU rasterizer of 2D Gaussians (numba tile kernels in a torch.autograd.Function).

Image formation (3DGS, front to back over Gaussians sorted by depth):

    αᵢ(p) = min(0.99, oᵢ exp(−½ dᵀ Σᵢ⁻¹ d)),  d = μᵢ − p      (skipped when αᵢ < 1/255)
    C(p)  = Σᵢ cᵢ αᵢ Tᵢ,  Tᵢ = Πⱼ<ᵢ (1 − αⱼ),   A(p) = 1 − T_final

and a pixel stops at the first Gaussian that would bring T below 10⁻⁴.  The
outputs are the premultiplied colour C (H, W, 3) and the coverage A (H, W); a
background b is composited outside, I = C + (1 − A) b.

Speed comes from: tile binning (16×16 px tiles; each Gaussian is listed only
in the tiles its footprint touches: the bounding box of the opacity-aware ellipse
dᵀ Σ⁻¹ d ≤ 2 ln(255 o) outside which α < 1/255), one depth sort, a counting
sort into per-tile lists that stay depth-ordered, compiled numba loops parallel
over tiles in which each Gaussian visits, row by row, only the pixels inside its
footprint ellipse (exact per-row span from the conic's quadratic, float32 maths,
per-Gaussian threshold precomputed), and a per-pixel early stop (a tile ends when
all its pixels saturate).  Gaussian rows are packed in depth order so a tile's list
streams through memory, and tiles are dealt to threads in blocks of about equal
work (longest first) rather than prange's contiguous chunks, which left the busy
centre of the image on one thread.  The
backward pass walks each pixel back to front from the stored final
transmittance and contribution count (as 3DGS does) and writes
per-(tile, Gaussian) gradients that a serial pass sums — no per-pixel ×
per-Gaussian tensor, no races, and deterministic.

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
def footprint_extent(conics: np.ndarray, opacities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Half-widths (rx, ry) px of the box outside which α < 1/255; 0 where o ≤ 1/255.

    α ≥ 1/255 ⇔ dᵀ Σ⁻¹ d ≤ 2 ln(255 o), an ellipse whose bounding box has half-widths
    √(2 ln(255 o) Σ_xx) and √(2 ln(255 o) Σ_yy); one pixel of margin is added.
    conics (N, 3) = (a, b, c) of Σ⁻¹.
    """
    a, b, c = (conics[:, i].astype(np.float64) for i in range(3))
    det = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        lg = np.log(np.maximum(255.0 * opacities.astype(np.float64), 1e-30))
        rx = np.sqrt(np.maximum(2.0 * lg * c / det, 0.0)) + 1.0
        ry = np.sqrt(np.maximum(2.0 * lg * a / det, 0.0)) + 1.0
    ok = (det > 0) & (lg > 0) & np.isfinite(rx) & np.isfinite(ry)
    return np.where(ok, rx, 0.0), np.where(ok, ry, 0.0)


@nb.njit(cache=True)
def _bin(mx, my, rxs, rys, order, width, height, tile, by_rank=False):  # pragma: no cover - compiled
    """Counting sort of (tile, Gaussian) pairs; ``order`` lists Gaussians front to back.

    Returns tile_start (ntiles + 1,) and entries (K,) of Gaussian ids (``by_rank``: positions in
    ``order``), depth-ordered per tile.
    """
    tx_n = (width + tile - 1) // tile
    ty_n = (height + tile - 1) // tile
    nt = tx_n * ty_n
    counts = np.zeros(nt + 1, np.int64)
    n = order.shape[0]
    rect = np.empty((n, 4), np.int64)
    for k in range(n):
        g = order[k]
        rx = rxs[g]
        ry = rys[g]
        x0 = int(math.floor((mx[g] - rx) / tile))
        x1 = int(math.floor((mx[g] + rx) / tile))
        y0 = int(math.floor((my[g] - ry) / tile))
        y1 = int(math.floor((my[g] + ry) / tile))
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
                entries[fill[t]] = k if by_rank else g
                fill[t] += 1
    return counts, entries


def bin_gaussians(means2d: np.ndarray, conics: np.ndarray, opacities: np.ndarray, depths: np.ndarray,
                  visible: np.ndarray, width: int, height: int, extent: tuple | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Tile lists: (tile_start (ntiles+1,), entries (K,)) for the visible Gaussians with a footprint."""
    tile_start, entries, _ = _bin_ranked(means2d, conics, opacities, depths, visible, width, height, extent,
                                         False)
    return tile_start, entries


def _bin_ranked(means2d, conics, opacities, depths, visible, width, height, extent, by_rank):
    """bin_gaussians plus the depth order; ``by_rank``: entries index that order, not the Gaussians."""
    rx, ry = footprint_extent(conics, opacities) if extent is None else extent
    keep = visible & (rx > 0) & np.isfinite(means2d).all(1) & np.isfinite(depths)
    idx = np.nonzero(keep)[0]
    order = idx[np.argsort(depths[idx], kind="stable")].astype(np.int64)
    tile_start, entries = _bin(means2d[:, 0].astype(np.float64), means2d[:, 1].astype(np.float64), rx, ry,
                               order, int(width), int(height), TILE, by_rank)
    return tile_start, entries, order


@nb.njit(inline="always")
def _row_span(mx, dy, ca, cb, cc, thr, px0, px1):  # pragma: no cover - compiled
    """Pixel columns [q0, q1] ⊆ [px0, px1] of a row at offset dy where power ≥ thr can hold.

    power = −½(a dx² + 2b dx dy + c dy²) ≥ thr ⇔ a dx² + 2 b dy dx + c dy² + 2 thr ≤ 0, a quadratic
    in dx = mx − px; its roots (float64, widened by 0.01 px) bound the row's footprint exactly, so the
    per-pixel test still decides and only pixels outside the ellipse are skipped.  Empty: q0 > q1.
    """
    a = float(ca)
    if a <= 0.0:
        return px0, px1
    bd = float(cb) * float(dy)
    disc = bd * bd - a * (float(cc) * float(dy) * float(dy) + 2.0 * thr)
    if disc < 0.0:
        disc = disc + 1e-9 * (bd * bd + abs(a * float(cc)) * float(dy) * float(dy) + abs(2.0 * a * thr))
        if disc < 0.0:
            return px0, px0 - 1
        disc = 0.0
    sq = math.sqrt(disc)
    m = float(mx)
    q0 = max(px0, int(math.ceil(m - (-bd + sq) / a - 0.01)))
    q1 = min(px1, int(math.floor(m - (-bd - sq) / a + 0.01)))
    return q0, q1


@nb.njit(cache=True)
def _schedule(tile_start, nblocks):  # pragma: no cover - compiled
    """Tiles split into ``nblocks`` blocks of about equal work (tile-list length + 1), one per thread.

    Longest-first greedy; returns (tile_order, block_start) with block b = tile_order[block_start[b]:
    block_start[b + 1]].  (prange hands each thread one contiguous chunk of iterations; over tiles
    that put the busy centre of the image on one thread.)
    """
    nt = tile_start.shape[0] - 1
    work = np.empty(nt, np.int64)
    for t in range(nt):
        work[t] = tile_start[t + 1] - tile_start[t] + 1
    by_work = np.argsort(-work, kind="mergesort")
    load = np.zeros(nblocks, np.int64)
    owner = np.empty(nt, np.int64)
    count = np.zeros(nblocks + 1, np.int64)
    for j in range(nt):
        t = by_work[j]
        b = np.argmin(load)
        load[b] += work[t]
        owner[t] = b
        count[b + 1] += 1
    for b in range(nblocks):
        count[b + 1] += count[b]
    fill = count[:-1].copy()
    order = np.empty(nt, np.int64)
    for j in range(nt):
        t = by_work[j]
        order[fill[owner[t]]] = t
        fill[owner[t]] += 1
    return order, count


# --------------------------------------------------------------------------- kernels
# gdata columns: 0 mx, 1 my, 2 a, 3 b, 4 c, 5 opacity, 6..8 colour, 9 rx, 10 ry (footprint half-widths),
# 11 thr = −ln(255 o) − 10⁻³ (power < thr ⇒ α < 1/255; a conservative pre-test, α is still tested).
# Both kernels run Gaussian-outer within a tile: each Gaussian of the tile's depth-ordered list
# visits only the pixels of its footprint box (clipped to the tile) and updates their running
# state (transmittance, colour; in the backward pass the back-to-front accumulators), so the
# work is the footprint area, not tile area × list length.  A tile ends when all its pixels
# have saturated.
@nb.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _forward(gdata, tile_start, entries, tile_order, block_start, width, height, tile,
             out_color, out_alpha, t_final, n_contrib):  # pragma: no cover - compiled
    tx_n = (width + tile - 1) // tile
    dt = gdata.dtype.type
    one = dt(1.0)
    half = dt(0.5)
    amin = dt(ALPHA_MIN)
    amax = dt(ALPHA_MAX)
    tmin = dt(T_MIN)
    for blk in nb.prange(block_start.shape[0] - 1):
        for j in range(block_start[blk], block_start[blk + 1]):
            t = tile_order[j]
            s = tile_start[t]
            k = tile_start[t + 1] - s
            x0 = (t % tx_n) * tile
            y0 = (t // tx_n) * tile
            w = min(tile, width - x0)
            h = min(tile, height - y0)
            T = np.ones((h, w), gdata.dtype)
            C = np.zeros((h, w, 3), gdata.dtype)
            last = np.zeros((h, w), np.int32)
            done = np.zeros((h, w), np.bool_)
            row_active = np.full(h, w, np.int64)  # unsaturated pixels per row
            remaining = h * w
            for i in range(k):
                gi = entries[s + i]
                mx = gdata[gi, 0]
                my = gdata[gi, 1]
                ca = gdata[gi, 2]
                cb = gdata[gi, 3]
                cc = gdata[gi, 4]
                op = gdata[gi, 5]
                thr = gdata[gi, 11]  # −ln(255 o) − 10⁻³: power < thr ⇒ α < 1/255
                px0 = max(x0, int(math.ceil(mx - gdata[gi, 9])))
                px1 = min(x0 + w - 1, int(math.floor(mx + gdata[gi, 9])))
                py0 = max(y0, int(math.ceil(my - gdata[gi, 10])))
                py1 = min(y0 + h - 1, int(math.floor(my + gdata[gi, 10])))
                for py in range(py0, py1 + 1):
                    ly = py - y0
                    if row_active[ly] == 0:
                        continue
                    dy = my - dt(py)
                    q0, q1 = _row_span(mx, dy, ca, cb, cc, thr, px0, px1)
                    for px in range(q0, q1 + 1):
                        lx = px - x0
                        if done[ly, lx]:
                            continue
                        dx = mx - dt(px)
                        power = -half * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                        if power > 0 or power < thr:
                            continue
                        alpha = min(amax, op * math.exp(power))
                        if alpha < amin:
                            continue
                        tp = T[ly, lx]
                        test_t = tp * (one - alpha)
                        if test_t < tmin:
                            done[ly, lx] = True
                            row_active[ly] -= 1
                            remaining -= 1
                            continue
                        wgt = alpha * tp
                        C[ly, lx, 0] += gdata[gi, 6] * wgt
                        C[ly, lx, 1] += gdata[gi, 7] * wgt
                        C[ly, lx, 2] += gdata[gi, 8] * wgt
                        T[ly, lx] = test_t
                        last[ly, lx] = i + 1
                if remaining == 0:
                    break
            for ly in range(h):
                for lx in range(w):
                    out_color[y0 + ly, x0 + lx, 0] = C[ly, lx, 0]
                    out_color[y0 + ly, x0 + lx, 1] = C[ly, lx, 1]
                    out_color[y0 + ly, x0 + lx, 2] = C[ly, lx, 2]
                    out_alpha[y0 + ly, x0 + lx] = one - T[ly, lx]
                    t_final[y0 + ly, x0 + lx] = T[ly, lx]
                    n_contrib[y0 + ly, x0 + lx] = last[ly, lx]


@nb.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _backward(gdata, tile_start, entries, tile_order, block_start, width, height, tile, t_final, n_contrib,
              grad_color, grad_alpha, grad_entries):  # pragma: no cover - compiled
    """Back to front over each tile's list: writes ∂L/∂(mx, my, a, b, c, o, r, g, b) per tile entry.

    Per pixel, T is recovered from the stored final transmittance, Tᵢ = Tᵢ₊₁ / (1 − αᵢ), and
    Sᵢ = Σ_{j>i} c_j α_j Π_{i<l<j} (1 − α_l) by Sᵢ = α_{i+1} c_{i+1} + (1 − α_{i+1}) S_{i+1}, so that
    ∂C/∂αᵢ = Tᵢ (cᵢ − Sᵢ) and ∂A/∂αᵢ = T_final / (1 − αᵢ).
    """
    tx_n = (width + tile - 1) // tile
    dt = gdata.dtype.type
    one = dt(1.0)
    half = dt(0.5)
    amin = dt(ALPHA_MIN)
    amax = dt(ALPHA_MAX)
    for blk in nb.prange(block_start.shape[0] - 1):
        for j in range(block_start[blk], block_start[blk + 1]):
            t = tile_order[j]
            s = tile_start[t]
            k = tile_start[t + 1] - s
            x0 = (t % tx_n) * tile
            y0 = (t // tx_n) * tile
            w = min(tile, width - x0)
            h = min(tile, height - y0)
            T = np.empty((h, w), gdata.dtype)
            acc = np.zeros((h, w, 3), gdata.dtype)
            lcol = np.zeros((h, w, 3), gdata.dtype)
            last_a = np.zeros((h, w), gdata.dtype)
            nmax = 0
            row_n = np.zeros(h, np.int64)  # largest contribution count per row
            ncl = np.empty((h, w), np.int32)  # tile-local copies of the per-pixel inputs
            gcl = np.empty((h, w, 3), gdata.dtype)
            gat = np.empty((h, w), gdata.dtype)  # ∂L/∂A · T_final
            for ly in range(h):
                for lx in range(w):
                    T[ly, lx] = t_final[y0 + ly, x0 + lx]
                    ncl[ly, lx] = n_contrib[y0 + ly, x0 + lx]
                    gcl[ly, lx, 0] = grad_color[y0 + ly, x0 + lx, 0]
                    gcl[ly, lx, 1] = grad_color[y0 + ly, x0 + lx, 1]
                    gcl[ly, lx, 2] = grad_color[y0 + ly, x0 + lx, 2]
                    gat[ly, lx] = grad_alpha[y0 + ly, x0 + lx] * t_final[y0 + ly, x0 + lx]
                    row_n[ly] = max(row_n[ly], n_contrib[y0 + ly, x0 + lx])
                nmax = max(nmax, row_n[ly])
            for i in range(nmax, k):
                for j in range(9):
                    grad_entries[s + i, j] = 0.0
            for i in range(nmax - 1, -1, -1):
                gi = entries[s + i]
                mx = gdata[gi, 0]
                my = gdata[gi, 1]
                ca = gdata[gi, 2]
                cb = gdata[gi, 3]
                cc = gdata[gi, 4]
                op = gdata[gi, 5]
                c0 = gdata[gi, 6]
                c1 = gdata[gi, 7]
                c2 = gdata[gi, 8]
                thr = gdata[gi, 11]  # −ln(255 o) − 10⁻³: power < thr ⇒ α < 1/255
                px0 = max(x0, int(math.ceil(mx - gdata[gi, 9])))
                px1 = min(x0 + w - 1, int(math.floor(mx + gdata[gi, 9])))
                py0 = max(y0, int(math.ceil(my - gdata[gi, 10])))
                py1 = min(y0 + h - 1, int(math.floor(my + gdata[gi, 10])))
                g0 = dt(0.0)
                g1 = dt(0.0)
                g2 = dt(0.0)
                g3 = dt(0.0)
                g4 = dt(0.0)
                g5 = dt(0.0)
                g6 = dt(0.0)
                g7 = dt(0.0)
                g8 = dt(0.0)
                for py in range(py0, py1 + 1):
                    ly = py - y0
                    if i >= row_n[ly]:
                        continue
                    dy = my - dt(py)
                    q0, q1 = _row_span(mx, dy, ca, cb, cc, thr, px0, px1)
                    for px in range(q0, q1 + 1):
                        lx = px - x0
                        if i >= ncl[ly, lx]:
                            continue
                        dx = mx - dt(px)
                        power = -half * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                        if power > 0 or power < thr:
                            continue
                        G = math.exp(power)
                        raw = op * G
                        alpha = min(amax, raw)
                        if alpha < amin:
                            continue
                        tp = T[ly, lx] / (one - alpha)
                        T[ly, lx] = tp
                        wgt = alpha * tp
                        gc0 = gcl[ly, lx, 0]
                        gc1 = gcl[ly, lx, 1]
                        gc2 = gcl[ly, lx, 2]
                        g6 += wgt * gc0
                        g7 += wgt * gc1
                        g8 += wgt * gc2
                        la = last_a[ly, lx]
                        a0 = la * lcol[ly, lx, 0] + (one - la) * acc[ly, lx, 0]
                        a1 = la * lcol[ly, lx, 1] + (one - la) * acc[ly, lx, 1]
                        a2 = la * lcol[ly, lx, 2] + (one - la) * acc[ly, lx, 2]
                        acc[ly, lx, 0] = a0
                        acc[ly, lx, 1] = a1
                        acc[ly, lx, 2] = a2
                        lcol[ly, lx, 0] = c0
                        lcol[ly, lx, 1] = c1
                        lcol[ly, lx, 2] = c2
                        last_a[ly, lx] = alpha
                        dl_dalpha = tp * ((c0 - a0) * gc0 + (c1 - a1) * gc1 + (c2 - a2) * gc2) \
                            + gat[ly, lx] / (one - alpha)
                        if raw > amax:  # clamped: no gradient through α
                            continue
                        g5 += G * dl_dalpha
                        dl_dpow = op * G * dl_dalpha
                        g0 += -dl_dpow * (ca * dx + cb * dy)
                        g1 += -dl_dpow * (cb * dx + cc * dy)
                        g2 += -half * dl_dpow * dx * dx
                        g3 += -dl_dpow * dx * dy
                        g4 += -half * dl_dpow * dy * dy
                grad_entries[s + i, 0] = g0
                grad_entries[s + i, 1] = g1
                grad_entries[s + i, 2] = g2
                grad_entries[s + i, 3] = g3
                grad_entries[s + i, 4] = g4
                grad_entries[s + i, 5] = g5
                grad_entries[s + i, 6] = g6
                grad_entries[s + i, 7] = g7
                grad_entries[s + i, 8] = g8


@nb.njit(cache=True)
def _scatter(entries, grad_entries, out):  # pragma: no cover - compiled
    for e in range(entries.shape[0]):
        g = entries[e]
        for j in range(9):
            out[g, j] += grad_entries[e, j]


def _pack(means2d, conics, colors, opacities) -> np.ndarray:
    """(N, 12) contiguous array: mx, my, a, b, c, opacity, r, g, b, rx, ry, thr = −ln(255 o) − 10⁻³."""
    f = lambda x: x.detach().cpu().numpy()  # noqa: E731
    con, op = f(conics), f(opacities)
    rx, ry = footprint_extent(con, op)
    thr = -np.log(255.0 * np.maximum(op.astype(np.float64), 1e-30)) - 1e-3
    return np.concatenate([f(means2d), con, op[:, None], f(colors), rx[:, None].astype(con.dtype),
                           ry[:, None].astype(con.dtype), thr[:, None].astype(con.dtype)], 1)


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, visible, width, height):
        gdata = _pack(means2d, conics, colors, opacities)
        dt = gdata.dtype
        vis = visible.detach().cpu().numpy().astype(bool)
        tile_start, entries, order = _bin_ranked(gdata[:, 0:2], gdata[:, 2:5], gdata[:, 5],
                                                 depths.detach().cpu().numpy(), vis, width, height,
                                                 (gdata[:, 9].astype(np.float64), gdata[:, 10].astype(np.float64)),
                                                 True)
        n_all = gdata.shape[0]
        # rows in depth order: a tile's list then reads them in increasing memory order
        gdata = np.ascontiguousarray(gdata[order])
        color = np.empty((height, width, 3), dt)
        alpha = np.empty((height, width), dt)
        t_final = np.empty((height, width), dt)
        n_contrib = np.empty((height, width), np.int32)
        tile_order, block_start = _schedule(tile_start, max(1, nb.get_num_threads()))
        _forward(gdata, tile_start, entries, tile_order, block_start, width, height, TILE, color, alpha,
                 t_final, n_contrib)
        ctx.state = (gdata, order, n_all, tile_start, entries, tile_order, block_start, t_final, n_contrib, width,
                     height)
        return torch.from_numpy(color), torch.from_numpy(alpha)

    @staticmethod
    def backward(ctx, grad_color, grad_alpha):
        (gdata, order, n_all, tile_start, entries, tile_order, block_start, t_final, n_contrib, width,
         height) = ctx.state
        dt = gdata.dtype
        gc = np.ascontiguousarray(grad_color.detach().cpu().numpy().astype(dt, copy=False))
        ga = np.ascontiguousarray(grad_alpha.detach().cpu().numpy().astype(dt, copy=False))
        ge = np.empty((entries.shape[0], 9), np.float64)
        _backward(gdata, tile_start, entries, tile_order, block_start, width, height, TILE, t_final, n_contrib,
                  gc, ga, ge)
        out_sorted = np.zeros((gdata.shape[0], 9), np.float64)
        _scatter(entries, ge, out_sorted)
        out = np.zeros((n_all, 9), dt)
        out[order] = out_sorted
        g = torch.from_numpy(out)
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
