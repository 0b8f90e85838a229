"""Fast differentiable CPU rasterizer of 2D Gaussians (numba tile kernels in a torch.autograd.Function).

Image formation (3DGS, front to back over Gaussians sorted by depth):

    αᵢ(p) = min(0.99, oᵢ exp(−½ dᵀ Σᵢ⁻¹ d)),  d = μᵢ − p      (skipped when αᵢ < 1/255)
    C(p)  = Σᵢ cᵢ αᵢ Tᵢ,  Tᵢ = Πⱼ<ᵢ (1 − αⱼ),   A(p) = 1 − T_final

and a pixel stops at the first Gaussian that would bring T below 10⁻⁴.  The
outputs are the premultiplied colour C (H, W, 3) and the coverage A (H, W); a
background b is composited outside, I = C + (1 − A) b.

Speed comes from: tile binning (16×16 px tiles; each Gaussian is listed only
in the tiles its footprint touches: the bounding box of the opacity-aware ellipse
dᵀ Σ⁻¹ d ≤ 2 ln(255 o) outside which α < 1/255), one depth sort (a single sort of
packed (depth, index) keys), a counting sort into per-tile lists that stay
depth-ordered, and compiled numba loops parallel over tiles in which each Gaussian
updates, row by row over its footprint box, all 16 pixels of a tile row at once:
the row loop is branch-free (per-pixel tests are selects, exp is a polynomial) so
LLVM vectorizes it (16 float32 lanes with AVX-512) — see the note above the kernels
for what it takes to make numba emit that.  A per-pixel early stop ends a tile when
all its pixels saturate.  Gaussian rows are packed in depth order so a tile's list
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


def depth_order(depths: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``idx`` sorted by ``depths[idx]``, ties in index order: ``idx[np.argsort(depths[idx], kind="stable")]``.

    Depths must not be NaN (callers filter them).  For float32 depths the same permutation comes from one
    sort of unique uint64 keys (order-preserving bits of the depth above the index; numpy's SIMD sort),
    about 4× faster than the stable argsort.
    """
    d = depths[idx]
    if d.dtype != np.float32 or idx.size >= 2 ** 32:
        return idx[np.argsort(d, kind="stable")].astype(np.int64)
    u = (d + np.float32(0.0)).view(np.uint32).astype(np.uint64)  # + 0: −0 sorts with +0
    u = np.where(u >> np.uint64(31), ~u & np.uint64(0xFFFFFFFF), u | np.uint64(0x80000000))
    keys = np.sort((u << np.uint64(32)) | np.arange(d.size, dtype=np.uint64))
    return idx[(keys & np.uint64(0xFFFFFFFF)).astype(np.int64)].astype(np.int64)


def _bin_ranked(means2d, conics, opacities, depths, visible, width, height, extent, by_rank):
    """bin_gaussians plus the depth order; ``by_rank``: entries index that order, not the Gaussians."""
    rx, ry = footprint_extent(conics, opacities) if extent is None else extent
    keep = visible & (rx > 0) & np.isfinite(means2d).all(1) & np.isfinite(depths)
    idx = np.nonzero(keep)[0]
    order = depth_order(depths, idx)
    tile_start, entries = _bin(means2d[:, 0].astype(np.float64), means2d[:, 1].astype(np.float64), rx, ry,
                               order, int(width), int(height), TILE, by_rank)
    return tile_start, entries, order


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


# --------------------------------------------------------------------------- exp
EXP_LO = -16.0
"""Lowest exponent the kernels evaluate; thr is clipped to it (α ≥ 1/255 below it needs o > e¹⁶/255)."""
_LN2_HI = 0.693145751953125  # ln 2 with 17 significant bits: m · _LN2_HI is exact for m < 2⁶
_LN2_LO = math.log(2.0) - _LN2_HI
EXP_COEF64 = tuple(1.0 / math.factorial(j) for j in range(11, -1, -1))
"""Taylor coefficients of exp, highest first: degree 11 on |r| ≤ ln2/2 (truncation < 7·10⁻¹⁵ relative)."""
EXP_COEF32 = EXP_COEF64[4:]
"""Degree 7 (truncation < 6·10⁻⁹, below float32's ulp)."""


def exp_coefficients(dtype) -> tuple:
    """The polynomial of ``_exp_neg`` for rendering in ``dtype``."""
    return EXP_COEF32 if np.dtype(dtype) == np.float32 else EXP_COEF64


@nb.njit(inline="always")
def _exp_neg(x, coef):  # pragma: no cover - compiled
    """exp(x) for EXP_LO ≤ x ≤ 0 (clamped into that range), branch- and table-free so pixel loops vectorize.

    numba has no vector exp here (no SVML), and a table gather also keeps LLVM from vectorizing, so:
    x = −m ln2 + r with m = round(−x / ln2) ≤ 23, |r| ≤ ln2/2 (Cody–Waite, two-part ln2);
    exp(r) by Horner over ``coef`` (Taylor, highest degree first; a tuple, so its length is part of
    the compiled type); 2⁻ᵐ built from its float32 bit pattern.
    """
    dt = type(x)
    xc = min(max(x, dt(EXP_LO)), dt(0.0))
    m = np.uint32(dt(0.5) - xc * dt(1.4426950408889634))
    fm = dt(m)
    r = (xc + fm * dt(_LN2_HI)) + fm * dt(_LN2_LO)
    p = dt(0.0)
    for c in coef:
        p = p * r + dt(c)
    s = dt(np.uint32((127 - m) << 23).view(np.float32))  # 2⁻ᵐ, exact in float32 for m ≤ 23
    return p * s


@nb.njit(inline="always")
def _row_hit(dy, ca, cb, cc, thr):  # pragma: no cover - compiled
    """False when no pixel of a row at offset dy can have power ≥ thr (the quadratic in dx has no root).

    power = −½(a dx² + 2b dx dy + c dy²) ≥ thr ⇔ a dx² + 2 b dy dx + c dy² + 2 thr ≤ 0; the discriminant
    is widened by 10⁻⁹ of its terms' scale, so a row is skipped only when certainly empty.
    """
    a = float(ca)
    if a <= 0.0:
        return True
    bd = float(cb) * float(dy)
    dd = float(dy) * float(dy)
    disc = bd * bd - a * (float(cc) * dd + 2.0 * thr)
    return disc + 1e-9 * (bd * bd + abs(a * float(cc)) * dd + abs(2.0 * a * thr)) >= 0.0


# --------------------------------------------------------------------------- kernels
# gdata columns: 0 mx, 1 my, 2 a, 3 b, 4 c, 5 opacity, 6..8 colour, 9 rx, 10 ry (footprint half-widths),
# 11 thr = max(−ln(255 o) − 10⁻³, EXP_LO) (power < thr ⇒ α < 1/255; a conservative pre-test, α is still
# tested).  Both passes run Gaussian-outer within a tile: each Gaussian of the tile's depth-ordered
# list visits the tile rows its footprint box covers (the backward pass skips rows the ellipse misses;
# in the forward pass that test's branch cost more than it saved) and updates all 16 pixels of a row
# in one branch-free loop — per-pixel conditions are selects, exp is ``_exp_neg`` — which LLVM turns
# into SIMD code over the row.  Lanes outside the ellipse compute and are masked.  What it took:
#   * a tile's per-pixel state in one scratch buffer ``S`` with its fields at constant offsets, so LLVM
#     sees that the row loop's loads and stores do not overlap (separate arrays: scalar code);
#   * unsigned indices: numba adds a negative-index wraparound select to signed ones, which makes the
#     addresses non-affine;
#   * a runtime trip count (``tile``, always TILE): with the constant 16, LLVM unrolls the loop first
#     and then does not vectorize it;
#   * no int64 values in the loop (the lane's x offset and the saturation count are floats): they
#     halve the vector width;
#   * the per-tile work in plain (serial) njit functions called from the prange over blocks: compiled
#     inside the parfor body, the same loops stay scalar.
# Measured on the 20K-Gaussian 256² bench view, one thread: forward kernel 11.9 → 5.2 ms, backward
# 14.3 → 8.4 ms against the previous scalar kernels (which skipped pixels outside exact per-row spans).
_NF = 6
"""Fields of the forward scratch: T, C0, C1, C2, last contributor + 1, active (1/0)."""
_NB = 7
"""Fields of the backward scratch: T, B (see ``_backward_tile``), contribution count, ∂L/∂C 0..2,
∂L/∂A · T_final."""


@nb.njit(cache=True, fastmath=True, error_model="numpy")
def _forward_tile(gdata, entries, s, k, x0, y0, w, h, tile, ecoef, S, row_active,
                  out_color, out_alpha, t_final, n_contrib):  # pragma: no cover - compiled
    """One tile of ``_forward``: list entries s … s + k − 1, pixels [x0, x0 + w) × [y0, y0 + h)."""
    dt = gdata.dtype.type
    one = dt(1.0)
    zero = dt(0.0)
    half = dt(0.5)
    amin = dt(ALPHA_MIN)
    amax = dt(ALPHA_MAX)
    tmin = dt(T_MIN)
    nn = TILE * TILE
    o1 = np.uint64(nn)
    o2 = np.uint64(2 * nn)
    o3 = np.uint64(3 * nn)
    o4 = np.uint64(4 * nn)
    o5 = np.uint64(5 * nn)
    for q in range(nn):
        S[q] = one
        S[nn + q] = zero
        S[2 * nn + q] = zero
        S[3 * nn + q] = zero
        S[4 * nn + q] = zero
        S[5 * nn + q] = one if (q % TILE) < w and (q // TILE) < h else zero  # padding never counts
    for ly in range(TILE):
        row_active[ly] = w if ly < h else 0  # unsaturated pixels per row
    remaining = h * w
    fx0 = dt(x0)
    for i in range(k):
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
        thr = gdata[gi, 11]
        py0 = max(y0, int(math.ceil(my - gdata[gi, 10])))
        py1 = min(y0 + h - 1, int(math.floor(my + gdata[gi, 10])))
        mxl = mx - fx0  # exact, so dx below rounds as μx − px does
        fi = dt(i + 1)
        for py in range(py0, py1 + 1):
            ly = py - y0
            if row_active[ly] == 0:
                continue
            dy = my - dt(py)
            cdy = cc * dy * dy  # (no _row_hit test here: its branch costs more than the rows it skips)
            b = ly * TILE
            nsat = zero  # counted in dt: an int64 reduction would halve the vector width
            flx = zero  # px − x0 as a float induction (an int64 one would halve the vector width, too)
            for lx in range(tile):
                q = np.uint64(b + lx)
                dx = mxl - flx  # rounds once, as μx − px does
                flx += one
                power = -half * (ca * dx * dx + cdy) - cb * dx * dy
                alpha = min(amax, op * _exp_neg(power, ecoef))
                tp = S[q]
                test_t = tp * (one - alpha)
                ok = (S[o5 + q] > zero) & (power <= zero) & (power >= thr) & (alpha >= amin)
                sat = ok & (test_t < tmin)
                use = ok & (test_t >= tmin)
                wgt = alpha * tp if use else zero
                S[o1 + q] += c0 * wgt
                S[o2 + q] += c1 * wgt
                S[o3 + q] += c2 * wgt
                S[q] = test_t if use else tp
                S[o4 + q] = fi if use else S[o4 + q]
                S[o5 + q] = zero if sat else S[o5 + q]
                nsat += one if sat else zero
            row_active[ly] -= int(nsat)
            remaining -= int(nsat)
        if remaining == 0:
            break
    for ly in range(h):
        for lx in range(w):
            q = ly * TILE + lx
            out_color[y0 + ly, x0 + lx, 0] = S[nn + q]
            out_color[y0 + ly, x0 + lx, 1] = S[2 * nn + q]
            out_color[y0 + ly, x0 + lx, 2] = S[3 * nn + q]
            out_alpha[y0 + ly, x0 + lx] = one - S[q]
            t_final[y0 + ly, x0 + lx] = S[q]
            n_contrib[y0 + ly, x0 + lx] = np.int32(S[4 * nn + q])


@nb.njit(parallel=True, cache=True)
def _forward(gdata, tile_start, entries, tile_order, block_start, width, height, tile, ecoef,
             out_color, out_alpha, t_final, n_contrib):  # pragma: no cover - compiled
    """Front to back over each tile's list: colour, coverage, final T and contribution count per pixel."""
    tx_n = (width + tile - 1) // tile
    for blk in nb.prange(block_start.shape[0] - 1):
        S = np.empty(_NF * TILE * TILE, gdata.dtype)
        row_active = np.empty(TILE, np.int64)
        for j in range(block_start[blk], block_start[blk + 1]):
            t = tile_order[j]
            x0 = (t % tx_n) * tile
            y0 = (t // tx_n) * tile
            _forward_tile(gdata, entries, tile_start[t], tile_start[t + 1] - tile_start[t], x0, y0,
                          min(tile, width - x0), min(tile, height - y0), tile, ecoef, S, row_active,
                          out_color, out_alpha, t_final, n_contrib)


@nb.njit(cache=True, fastmath=True, error_model="numpy")
def _backward_tile(gdata, entries, s, k, x0, y0, w, h, tile, ecoef, S, A, row_n, t_final, n_contrib,
                   grad_color, grad_alpha, grad_entries):  # pragma: no cover - compiled
    """One tile of ``_backward``.

    Per pixel lane, S holds T (recovered back to front), B = Σ_{j>i} (∂L/∂C · c_j) α_j T_j (the loss
    weight of the colour behind Gaussian i), the contribution count, ∂L/∂C and ∂L/∂A · T_final; then

        ∂L/∂αᵢ = Tᵢ (∂L/∂C · cᵢ) + (∂L/∂A · T_final − B) / (1 − αᵢ)

    (∂C/∂αᵢ = cᵢ Tᵢ − Σ_{j>i} c_j α_j T_j / (1 − αᵢ), ∂A/∂αᵢ = T_final / (1 − αᵢ)).  ``A`` (9 × 16; a
    separate array: inside S, LLVM cannot tell it apart from the pixel fields and keeps the loop
    scalar) holds per-lane gradient sums of the current Gaussian, summed over its rows and reduced once
    per Gaussian rather than once per row.
    """
    dt = gdata.dtype.type
    one = dt(1.0)
    zero = dt(0.0)
    half = dt(0.5)
    amin = dt(ALPHA_MIN)
    amax = dt(ALPHA_MAX)
    nn = TILE * TILE
    o1 = np.uint64(nn)  # B
    o2 = np.uint64(2 * nn)  # contribution count
    o3 = np.uint64(3 * nn)  # ∂L/∂C (3 fields)
    o4 = np.uint64(4 * nn)
    o5 = np.uint64(5 * nn)
    o6 = np.uint64(6 * nn)  # ∂L/∂A · T_final
    p1 = np.uint64(TILE)
    p2 = np.uint64(2 * TILE)
    p3 = np.uint64(3 * TILE)
    p4 = np.uint64(4 * TILE)
    p5 = np.uint64(5 * TILE)
    p6 = np.uint64(6 * TILE)
    p7 = np.uint64(7 * TILE)
    p8 = np.uint64(8 * TILE)
    for q in range(_NB * nn):
        S[q] = zero
    for ly in range(TILE):
        row_n[ly] = 0  # largest contribution count per row
    nmax = 0
    for ly in range(h):
        for lx in range(w):
            q = ly * TILE + lx
            tf = t_final[y0 + ly, x0 + lx]
            nc = n_contrib[y0 + ly, x0 + lx]
            S[q] = tf
            S[2 * nn + q] = dt(nc)
            S[3 * nn + q] = grad_color[y0 + ly, x0 + lx, 0]
            S[4 * nn + q] = grad_color[y0 + ly, x0 + lx, 1]
            S[5 * nn + q] = grad_color[y0 + ly, x0 + lx, 2]
            S[6 * nn + q] = grad_alpha[y0 + ly, x0 + lx] * tf
            row_n[ly] = max(row_n[ly], nc)
        nmax = max(nmax, row_n[ly])
    for i in range(nmax, k):
        for jj in range(9):
            grad_entries[s + i, jj] = 0.0
    fx0 = dt(x0)
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
        thr = gdata[gi, 11]
        py0 = max(y0, int(math.ceil(my - gdata[gi, 10])))
        py1 = min(y0 + h - 1, int(math.floor(my + gdata[gi, 10])))
        mxl = mx - fx0
        fi = dt(i)
        touched = False  # (tile, Gaussian) pairs whose rows are all skipped need no sums
        for py in range(py0, py1 + 1):
            ly = py - y0
            if i >= row_n[ly]:
                continue
            dy = my - dt(py)
            if not _row_hit(dy, ca, cb, cc, thr):
                continue
            if not touched:
                for q in range(9 * TILE):
                    A[q] = zero
                touched = True
            cdy = cc * dy * dy
            b = ly * TILE
            flx = zero
            for lx in range(tile):
                q = np.uint64(b + lx)
                r = np.uint64(lx)
                dx = mxl - flx
                flx += one
                power = -half * (ca * dx * dx + cdy) - cb * dx * dy
                G = _exp_neg(power, ecoef)
                raw = op * G
                alpha = min(amax, raw)
                m = (fi < S[o2 + q]) & (power <= zero) & (power >= thr) & (alpha >= amin)
                inv = one / (one - alpha)
                Tq = S[q]
                tp = Tq * inv
                S[q] = tp if m else Tq
                wgt = alpha * tp if m else zero
                gc0 = S[o3 + q]
                gc1 = S[o4 + q]
                gc2 = S[o5 + q]
                cg = c0 * gc0 + c1 * gc1 + c2 * gc2
                Bq = S[o1 + q]
                dl_dalpha = tp * cg + (S[o6 + q] - Bq) * inv
                S[o1 + q] = Bq + cg * wgt
                mg = m & (raw <= amax)  # clamped: no gradient through α
                dl_dpow = op * G * dl_dalpha if mg else zero
                A[r] += -dl_dpow * (ca * dx + cb * dy)
                A[p1 + r] += -dl_dpow * (cb * dx + cc * dy)
                A[p2 + r] += -half * dl_dpow * dx * dx
                A[p3 + r] += -dl_dpow * dx * dy
                A[p4 + r] += -half * dl_dpow * dy * dy
                A[p5 + r] += G * dl_dalpha if mg else zero
                A[p6 + r] += wgt * gc0
                A[p7 + r] += wgt * gc1
                A[p8 + r] += wgt * gc2
        for jj in range(9):
            acc = zero
            if touched:
                for lx in range(TILE):
                    acc += A[jj * TILE + lx]
            grad_entries[s + i, jj] = acc


@nb.njit(parallel=True, cache=True)
def _backward(gdata, tile_start, entries, tile_order, block_start, width, height, tile, ecoef, t_final,
              n_contrib, grad_color, grad_alpha, grad_entries):  # pragma: no cover - compiled
    """Back to front over each tile's list: writes ∂L/∂(mx, my, a, b, c, o, r, g, b) per tile entry.

    Per pixel, T is recovered from the stored final transmittance, Tᵢ = Tᵢ₊₁ / (1 − αᵢ), and the loss
    weight of the colour behind each Gaussian is summed on the way (``_backward_tile``), so that
    ∂C/∂αᵢ and ∂A/∂αᵢ need no per-pixel list.  A pixel lane takes part where i is below its
    contribution count and αᵢ ≥ 1/255.
    """
    tx_n = (width + tile - 1) // tile
    for blk in nb.prange(block_start.shape[0] - 1):
        S = np.empty(_NB * TILE * TILE, gdata.dtype)
        A = np.empty(9 * TILE, gdata.dtype)
        row_n = np.empty(TILE, np.int64)
        for j in range(block_start[blk], block_start[blk + 1]):
            t = tile_order[j]
            x0 = (t % tx_n) * tile
            y0 = (t // tx_n) * tile
            _backward_tile(gdata, entries, tile_start[t], tile_start[t + 1] - tile_start[t], x0, y0,
                           min(tile, width - x0), min(tile, height - y0), tile, ecoef, S, A, row_n, t_final,
                           n_contrib, grad_color, grad_alpha, grad_entries)


@nb.njit(cache=True)
def _scatter(entries, grad_entries, order, out):  # pragma: no cover - compiled
    """out[order[r]] = Σ over the tile entries of rank r (float64 sums, in tile order: deterministic)."""
    acc = np.zeros((order.shape[0], 9), np.float64)
    for e in range(entries.shape[0]):
        r = entries[e]
        for j in range(9):
            acc[r, j] += grad_entries[e, j]
    for r in range(order.shape[0]):
        for j in range(9):
            out[order[r], j] = acc[r, j]


def _pack(means2d, conics, colors, opacities) -> np.ndarray:
    """(N, 12) contiguous array: mx, my, a, b, c, opacity, r, g, b, rx, ry, thr (see the kernels' note)."""
    f = lambda x: x.detach().cpu().numpy()  # noqa: E731
    con, op = f(conics), f(opacities)
    rx, ry = footprint_extent(con, op)
    thr = np.maximum(-np.log(255.0 * np.maximum(op.astype(np.float64), 1e-30)) - 1e-3, EXP_LO)
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
        _forward(gdata, tile_start, entries, tile_order, block_start, width, height, TILE, exp_coefficients(dt),
                 color, alpha, t_final, n_contrib)
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
        ge = np.empty((entries.shape[0], 9), dt)  # the kernel sums in dt: storing in dt loses nothing
        _backward(gdata, tile_start, entries, tile_order, block_start, width, height, TILE, exp_coefficients(dt),
                  t_final, n_contrib, gc, ga, ge)
        out = np.zeros((n_all, 9), dt)
        _scatter(entries, ge, order, out)
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
