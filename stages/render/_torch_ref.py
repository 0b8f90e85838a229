"""Plain PyTorch twins of the rasterizer: a dense one (every pixel × every Gaussian) and a tiled one.

Both compute exactly the image formation of ``stages/render/rasterize.py``
with ordinary torch ops, and autograd supplies the backward pass:

    αᵢ(p) = min(0.99, oᵢ exp(−½ dᵀ Σᵢ⁻¹ d)) if ≥ 1/255 else 0,   d = μᵢ − p
    keepᵢ(p) = [Πⱼ≤ᵢ (1 − αⱼ) ≥ 10⁻⁴]  (the early stop; transmittance is monotone)
    C(p) = Σᵢ keepᵢ αᵢ cᵢ Πⱼ<ᵢ (1 − keepⱼ αⱼ),   A(p) = 1 − Πᵢ (1 − keepᵢ αᵢ)

``rasterize_dense`` builds (H·W, N) tensors — only for small scenes (tests,
gradcheck).  ``rasterize_tiled`` runs the same maths tile by tile; its tile
lists come from ``bin_gaussians_torch`` (footprint boxes → (tile, depth rank)
keys → sort → per-tile ranges, all torch ops), which lists exactly what the
numba ``rasterize.bin_gaussians`` lists.  It is the pure-PyTorch baseline of
bench/render.py; ``rasterize_tiled_lean`` is the same maths on the compiled
binning (the baseline the benchmark used before, kept as an extra column).
"""
from __future__ import annotations

import functools

import torch

from stages.render.rasterize import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE, bin_gaussians


def footprint_extent_torch(conics: torch.Tensor, opacities: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``rasterize.footprint_extent`` in torch (float64): box half-widths √(2 ln(255 o) Σ_xx) + 1 etc."""
    a, b, c = conics.detach().double().unbind(1)
    det = a * c - b * b
    lg = torch.log(torch.clamp(255.0 * opacities.detach().double(), min=1e-30))
    rx = torch.sqrt(torch.clamp(2.0 * lg * c / det, min=0.0)) + 1.0
    ry = torch.sqrt(torch.clamp(2.0 * lg * a / det, min=0.0)) + 1.0
    ok = (det > 0) & (lg > 0) & torch.isfinite(rx) & torch.isfinite(ry)
    zero = torch.zeros_like(rx)
    return torch.where(ok, rx, zero), torch.where(ok, ry, zero)


def bin_gaussians_torch(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
                        depths: torch.Tensor, visible: torch.Tensor, width: int, height: int
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """Tile lists in torch ops: (tile_start (ntiles+1,), entries (K,)) as ``rasterize.bin_gaussians``.

    Each visible Gaussian with a footprint is depth-ranked (stable sort), listed in every tile its
    footprint box touches — one (tile, Gaussian) pair per tile, expanded with repeat_interleave — and
    the pairs are sorted by the key tile · n + rank, so each tile's range lists front to back.
    """
    tx_n = (width + TILE - 1) // TILE
    ty_n = (height + TILE - 1) // TILE
    rx, ry = footprint_extent_torch(conics, opacities)
    m = means2d.detach().double()
    d = depths.detach()
    keep = visible.bool() & (rx > 0) & torch.isfinite(m).all(1) & torch.isfinite(d)
    idx = torch.nonzero(keep).flatten()
    order = idx[torch.argsort(d[idx], stable=True)]
    mx, my, rxo, ryo = m[order, 0], m[order, 1], rx[order], ry[order]
    # clamp in float before the integer cast (far off-screen means stay finite but huge)
    x0 = torch.floor((mx - rxo) / TILE).clamp(0, tx_n).long()
    x1 = torch.floor((mx + rxo) / TILE).clamp(-1, tx_n - 1).long()
    y0 = torch.floor((my - ryo) / TILE).clamp(0, ty_n).long()
    y1 = torch.floor((my + ryo) / TILE).clamp(-1, ty_n - 1).long()
    nx = (x1 - x0 + 1).clamp(min=0)
    ny = (y1 - y0 + 1).clamp(min=0)
    cnt = nx * ny
    n = order.numel()
    rank = torch.repeat_interleave(torch.arange(n), cnt)
    first = torch.cumsum(cnt, 0) - cnt
    j = torch.arange(rank.numel()) - first[rank]
    tile = (y0[rank] + j // nx[rank]) * tx_n + x0[rank] + j % nx[rank]
    key = tile * max(n, 1) + rank
    _, perm = torch.sort(key)
    entries = order[rank[perm]]
    tile_start = torch.zeros(tx_n * ty_n + 1, dtype=torch.long)
    tile_start[1:] = torch.cumsum(torch.bincount(tile, minlength=tx_n * ty_n), 0)
    return tile_start, entries


def _composite(dx: torch.Tensor, dy: torch.Tensor, conics: torch.Tensor, colors: torch.Tensor,
               opacities: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """dx, dy (P, N) = μ − p for N depth-sorted Gaussians → colour (P, 3), coverage (P,)."""
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    alpha = torch.clamp(opacities * torch.exp(torch.clamp(power, max=0.0)), max=ALPHA_MAX)
    valid = (power <= 0) & (alpha >= ALPHA_MIN)
    alpha = torch.where(valid, alpha, torch.zeros_like(alpha))
    with torch.no_grad():
        keep = torch.cumprod(1 - alpha, dim=1) >= T_MIN
    alpha = alpha * keep
    one_minus = 1 - alpha
    trans = torch.cumprod(one_minus, dim=1)
    t_excl = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], dim=1)
    w = alpha * t_excl  # (P, N)
    return w @ colors, 1 - trans[:, -1]


def rasterize_dense(means2d: torch.Tensor, conics: torch.Tensor, colors: torch.Tensor,
                    opacities: torch.Tensor, depths: torch.Tensor, visible: torch.Tensor,
                    width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Same contract as ``rasterize.rasterize``; (H·W, N) memory, so small scenes only."""
    dt = means2d.dtype
    idx = torch.nonzero(visible).flatten()
    idx = idx[torch.argsort(depths.detach()[idx], stable=True)]
    ys, xs = torch.meshgrid(torch.arange(height, dtype=dt), torch.arange(width, dtype=dt), indexing="ij")
    if idx.numel() == 0:
        return torch.zeros(height, width, 3, dtype=dt), torch.zeros(height, width, dtype=dt)
    m = means2d[idx]
    dx = m[None, :, 0] - xs.reshape(-1, 1)
    dy = m[None, :, 1] - ys.reshape(-1, 1)
    col, acc = _composite(dx, dy, conics[idx], colors[idx], opacities[idx])
    return col.reshape(height, width, 3), acc.reshape(height, width)


def rasterize_tiled(means2d: torch.Tensor, conics: torch.Tensor, colors: torch.Tensor,
                    opacities: torch.Tensor, depths: torch.Tensor, visible: torch.Tensor,
                    width: int, height: int, binning: str = "torch") -> tuple[torch.Tensor, torch.Tensor]:
    """Same contract; per 16×16 tile, the dense maths over that tile's depth-sorted list.

    ``binning``: "torch" (``bin_gaussians_torch``, so the whole render is PyTorch) or "numba" (the
    compiled ``rasterize.bin_gaussians``; same lists).
    """
    dt = means2d.dtype
    if binning == "torch":
        tile_start, entries_t = bin_gaussians_torch(means2d, conics, opacities, depths, visible, width, height)
    else:
        f = lambda x: x.detach().cpu().numpy()  # noqa: E731
        ts, entries = bin_gaussians(f(means2d), f(conics), f(opacities), f(depths), f(visible).astype(bool),
                                    width, height)
        tile_start, entries_t = torch.from_numpy(ts), torch.from_numpy(entries)
    tile_start = tile_start.tolist()
    tx_n = (width + TILE - 1) // TILE
    ty_n = (height + TILE - 1) // TILE
    rows = []
    for ty in range(ty_n):
        h = min(TILE, height - ty * TILE)
        row_c, row_a = [], []
        for tx in range(tx_n):
            w = min(TILE, width - tx * TILE)
            t = ty * tx_n + tx
            s, e = tile_start[t], tile_start[t + 1]
            if e == s:
                row_c.append(torch.zeros(h, w, 3, dtype=dt))
                row_a.append(torch.zeros(h, w, dtype=dt))
                continue
            ids = entries_t[s:e]
            ys, xs = torch.meshgrid(torch.arange(ty * TILE, ty * TILE + h, dtype=dt),
                                    torch.arange(tx * TILE, tx * TILE + w, dtype=dt), indexing="ij")
            m = means2d[ids]
            dx = m[None, :, 0] - xs.reshape(-1, 1)
            dy = m[None, :, 1] - ys.reshape(-1, 1)
            col, acc = _composite(dx, dy, conics[ids], colors[ids], opacities[ids])
            row_c.append(col.reshape(h, w, 3))
            row_a.append(acc.reshape(h, w))
        rows.append((torch.cat(row_c, 1), torch.cat(row_a, 1)))
    return torch.cat([r[0] for r in rows], 0), torch.cat([r[1] for r in rows], 0)


rasterize_tiled_lean = functools.partial(rasterize_tiled, binning="numba")
"""``rasterize_tiled`` on the compiled binning: torch maths only per tile (the lean baseline)."""
