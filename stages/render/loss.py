"""Image losses (PyTorch): L1, SSIM / D-SSIM (3DGS), PSNR.  Images are (H, W, 3) in [0, 1]."""
from __future__ import annotations

import math

import torch
import torch.nn.functional as tf


def l1(render: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean |render − target| (over the pixels of ``mask`` (H, W) when given)."""
    d = (render - target).abs()
    if mask is None:
        return d.mean()
    m = mask.to(d.dtype)[..., None]
    return (d * m).sum() / (3 * m.sum()).clamp_min(1)


def _gauss_window(size: int, sigma: float, dtype: torch.dtype) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    g = g / g.sum()
    return (g[:, None] * g[None, :])[None, None].repeat(3, 1, 1, 1)  # (3, 1, s, s)


def ssim(render: torch.Tensor, target: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM (Wang et al. 2004) with an 11×11 Gaussian window, σ = 1.5, C₁ = 0.01², C₂ = 0.03²."""
    x = render.permute(2, 0, 1)[None]
    y = target.to(render.dtype).permute(2, 0, 1)[None]
    w = _gauss_window(window, sigma, render.dtype)
    pad = window // 2
    conv = lambda z: tf.conv2d(z, w, padding=pad, groups=3)  # noqa: E731
    mx, my = conv(x), conv(y)
    sxx = conv(x * x) - mx * mx
    syy = conv(y * y) - my * my
    sxy = conv(x * y) - mx * my
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return s.mean()


def l1_dssim(render: torch.Tensor, target: torch.Tensor, lam: float = 0.2) -> torch.Tensor:
    """3DGS photometric loss (1 − λ) L1 + λ (1 − SSIM)."""
    return (1 - lam) * l1(render, target) + lam * (1 - ssim(render, target))


def psnr(render: torch.Tensor, target: torch.Tensor) -> float:
    """10 log₁₀(1 / MSE) in dB for images in [0, 1]."""
    mse = float(((render.detach().double() - target.detach().double()) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)
