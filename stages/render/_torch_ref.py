"""Plain PyTorch twins of the rasterizer: a dense one (every pixel × every Gaussian) and a tiled one.

Both compute exactly the image formation of ``stages/render/rasterize.py``
with ordinary torch ops, and autograd supplies the backward pass:

    αᵢ(p) = min(0.99, oᵢ exp(−½ dᵀ Σᵢ⁻¹ d)) if ≥ 1/255 else 0,   d = μᵢ − p
    keepᵢ(p) = [Πⱼ≤ᵢ (1 − αⱼ) ≥ 10⁻⁴]  (the early stop; transmittance is monotone)
    C(p) = Σᵢ keepᵢ αᵢ cᵢ Πⱼ<ᵢ (1 − keepⱼ αⱼ),   A(p) = 1 − Πᵢ (1 − keepᵢ αᵢ)

``rasterize_dense`` builds (H·W, N) tensors — only for small scenes (tests,
gradcheck).  ``rasterize_tiled`` runs the same maths tile by tile over the
fast path's tile lists; it is the pure-PyTorch baseline of bench/render.py.
"""
from __future__ import annotations

import torch

from stages.render.rasterize import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE, bin_gaussians


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
                    width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Same contract; per 16×16 tile, the dense maths over that tile's depth-sorted list."""
    dt = means2d.dtype
    f = lambda x: x.detach().cpu().numpy()  # noqa: E731
    tile_start, entries = bin_gaussians(f(means2d), f(conics), f(opacities), f(depths),
                                        f(visible).astype(bool), width, height)
    entries_t = torch.from_numpy(entries)
    tx_n = (width + TILE - 1) // TILE
    ty_n = (height + TILE - 1) // TILE
    rows = []
    for ty in range(ty_n):
        h = min(TILE, height - ty * TILE)
        row_c, row_a = [], []
        for tx in range(tx_n):
            w = min(TILE, width - tx * TILE)
            t = ty * tx_n + tx
            s, e = int(tile_start[t]), int(tile_start[t + 1])
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

