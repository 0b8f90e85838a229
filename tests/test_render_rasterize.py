"""The numba rasterizer against its dense PyTorch twin, forward and backward, and gradchecks."""
from __future__ import annotations

import math

import numba as nb
import numpy as np
import pytest
import torch

from stages.render._torch_ref import (bin_gaussians_torch, footprint_extent_torch, rasterize_dense, rasterize_tiled,
                                      rasterize_tiled_lean)
from stages.render.rasterize import (ALPHA_MAX, EXP_LO, _exp_neg, bin_gaussians, depth_order, exp_coefficients,
                                     footprint_extent, rasterize)

GRADCHECK_KWARGS = dict(eps=1e-6, atol=1e-5, rtol=1e-4)
"""Tolerances of torch.autograd.gradcheck in float64."""
FP32_REL = 2e-5
"""Largest difference of the fast float32 render from the dense twin's float64 one on the same float32 scene, relative
to the largest magnitude of the quantity.  (Against the dense twin's own float32 render, 40 Gaussians on 37×29 read
4.67e-5 once in five full runs on one machine, 3.9e-7 in every other run and alone: a float32 reference can itself
be off.)"""


def random_scene(n: int, width: int, height: int, seed: int, dtype=torch.float32, spread: float = 0.25):
    """n Gaussians, some off-screen (means up to ``spread`` of the size outside), some invisible."""
    g = torch.Generator().manual_seed(seed)
    lo = torch.tensor([-spread * width, -spread * height])
    span = torch.tensor([(1 + 2 * spread) * width, (1 + 2 * spread) * height])
    means = lo + torch.rand(n, 2, generator=g) * span
    L = torch.randn(n, 2, 2, generator=g) * 2.5 + torch.eye(2) * 3
    cov = L @ L.transpose(1, 2) + 0.3 * torch.eye(2)
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], 1)
    colors = torch.rand(n, 3, generator=g)
    opac = 0.02 + 0.97 * torch.rand(n, generator=g)
    opac[: max(1, n // 10)] = 0.999  # some reach the α clamp
    depths = torch.rand(n, generator=g)
    visible = torch.rand(n, generator=g) > 0.1
    cast = lambda x: x.to(dtype)  # noqa: E731
    return cast(means), cast(conics), cast(colors), cast(opac), cast(depths), visible


def _grads(fn, scene, width, height, g_col, g_alpha):
    ins = [x.clone().requires_grad_(True) for x in scene[:4]]
    col, alpha = fn(*ins, *scene[4:], width, height)
    grads = torch.autograd.grad((col * g_col).sum() + (alpha * g_alpha).sum(), ins)
    return col.detach(), alpha.detach(), grads


CASES = [(40, 37, 29, 0), (300, 64, 48, 1), (1500, 80, 64, 2), (800, 33, 70, 3)]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n,width,height,seed", CASES)
def test_fast_matches_dense(n, width, height, seed, dtype):
    scene = random_scene(n, width, height, seed, dtype)
    gen = torch.Generator().manual_seed(100 + seed)
    g_col = torch.randn(height, width, 3, generator=gen).to(dtype)
    g_alpha = torch.randn(height, width, generator=gen).to(dtype)
    cf, af, gf = _grads(rasterize, scene, width, height, g_col, g_alpha)
    # the dense twin in float64, on the same scene (float32 values, exactly representable)
    scene64 = tuple(x.double() if x.is_floating_point() else x for x in scene)
    cd, ad, gd = _grads(rasterize_dense, scene64, width, height, g_col.double(), g_alpha.double())
    assert cf.shape == (height, width, 3) and af.shape == (height, width)
    assert float(af.max()) > 0.5  # the scene is not empty
    if dtype == torch.float64:
        torch.testing.assert_close(cf, cd, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(af, ad, rtol=1e-10, atol=1e-12)
        for a, b in zip(gf, gd):
            torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11)
    else:
        assert float((cf - cd).abs().max()) <= FP32_REL * max(1.0, float(cd.abs().max()))
        assert float((af - ad).abs().max()) <= FP32_REL
        for a, b in zip(gf, gd):
            assert float((a - b).abs().max()) <= FP32_REL * float(b.abs().max()) + 1e-7


@pytest.mark.parametrize("fn", [rasterize_tiled, rasterize_tiled_lean], ids=["torch-binning", "numba-binning"])
def test_tiled_reference_matches_dense(fn):
    scene = random_scene(500, 70, 50, 5, torch.float64)
    gen = torch.Generator().manual_seed(9)
    g_col = torch.randn(50, 70, 3, generator=gen, dtype=torch.float64)
    g_alpha = torch.randn(50, 70, generator=gen, dtype=torch.float64)
    ct, at, gt = _grads(fn, scene, 70, 50, g_col, g_alpha)
    cd, ad, gd = _grads(rasterize_dense, scene, 70, 50, g_col, g_alpha)
    torch.testing.assert_close(ct, cd)
    torch.testing.assert_close(at, ad)
    for a, b in zip(gt, gd):
        torch.testing.assert_close(a, b)


def tiny_scene(dtype=torch.float64):
    """4 broad Gaussians on a 7×5 image: α ≥ 1/255 everywhere, no clamp, no early stop (smooth)."""
    means = torch.tensor([[2.0, 1.5], [4.5, 3.0], [3.0, 2.5], [5.5, 1.0]], dtype=dtype)
    conics = torch.tensor([[0.08, 0.01, 0.06], [0.05, -0.02, 0.07], [0.1, 0.0, 0.05], [0.06, 0.02, 0.09]],
                          dtype=dtype)
    colors = torch.tensor([[0.9, 0.1, 0.2], [0.1, 0.8, 0.3], [0.2, 0.3, 0.9], [0.5, 0.5, 0.1]], dtype=dtype)
    opac = torch.tensor([0.6, 0.5, 0.7, 0.4], dtype=dtype)
    depths = torch.tensor([0.3, 0.1, 0.2, 0.4], dtype=dtype)
    return means, conics, colors, opac, depths, torch.ones(4, dtype=torch.bool)


@pytest.mark.parametrize("fn", [rasterize_dense, rasterize], ids=["dense", "fast"])
def test_gradcheck_float64(fn):
    m, c, col, o, d, v = tiny_scene()
    gen = torch.Generator().manual_seed(0)
    wc = torch.randn(5, 7, 3, generator=gen, dtype=torch.float64)
    wa = torch.randn(5, 7, generator=gen, dtype=torch.float64)

    def f(m, c, col, o):
        img, alpha = fn(m, c, col, o, d, v, 7, 5)
        return (img * wc).sum() + (alpha * wa).sum()

    ins = [x.clone().requires_grad_(True) for x in (m, c, col, o)]
    assert torch.autograd.gradcheck(f, ins, **GRADCHECK_KWARGS)


def test_compositing_identities():
    """One Gaussian: C = α c, A = α at its centre; a stack of opaque ones stops early (T ≥ 10⁻⁴)."""
    m = torch.tensor([[3.0, 2.0]], dtype=torch.float64)
    c = torch.tensor([[0.5, 0.0, 0.5]], dtype=torch.float64)
    col = torch.tensor([[0.2, 0.4, 0.6]], dtype=torch.float64)
    o = torch.tensor([0.7], dtype=torch.float64)
    img, alpha = rasterize(m, c, col, o, torch.zeros(1, dtype=torch.float64), torch.ones(1, dtype=torch.bool), 6, 4)
    assert abs(float(alpha[2, 3]) - 0.7) < 1e-12
    torch.testing.assert_close(img[2, 3], 0.7 * col[0])
    # 6 opaque Gaussians at one pixel: (1 − 0.99)² = 10⁻⁴ is not < 10⁻⁴, the third would be → two count.
    n = 6
    m = torch.full((n, 2), 1.0, dtype=torch.float64)
    c = torch.tensor([[1.0, 0.0, 1.0]] * n, dtype=torch.float64)
    col = torch.eye(3, dtype=torch.float64).repeat(2, 1)
    o = torch.full((n,), 0.999, dtype=torch.float64)
    d = torch.arange(n, dtype=torch.float64)
    img, alpha = rasterize(m, c, col, o, d, torch.ones(n, dtype=torch.bool), 3, 3)
    expect = ALPHA_MAX * col[0] + ALPHA_MAX * (1 - ALPHA_MAX) * col[1]
    torch.testing.assert_close(img[1, 1], expect)
    dense, _ = rasterize_dense(m, c, col, o, d, torch.ones(n, dtype=torch.bool), 3, 3)
    torch.testing.assert_close(img, dense)


def test_offscreen_and_invisible_gaussians_contribute_nothing():
    m = torch.tensor([[-50.0, 10.0], [10.0, 10.0], [200.0, 5.0]])
    c = torch.tensor([[0.5, 0.0, 0.5]] * 3)
    col = torch.rand(3, 3)
    o = torch.full((3,), 0.8)
    vis = torch.tensor([True, False, True])
    ins = [x.clone().requires_grad_(True) for x in (m, c, col, o)]
    img, alpha = rasterize(*ins, torch.zeros(3), vis, 32, 24)
    assert float(alpha.detach().abs().max()) == 0.0 and float(img.detach().abs().max()) == 0.0
    (img.sum() + alpha.sum()).backward()
    assert all(float(x.grad.abs().max()) == 0.0 for x in ins)


def test_binning_lists_every_touched_tile_in_depth_order():
    scene = random_scene(400, 96, 64, 11, torch.float64)
    m, c, col, o, d, v = (x.numpy() for x in scene)
    start, entries = bin_gaussians(m, c, o, d, v, 96, 64)
    assert start[0] == 0 and start[-1] == len(entries) and len(start) == 6 * 4 + 1
    for t in range(24):
        ids = entries[start[t]:start[t + 1]]
        assert all(v[ids])
        assert (d[ids][1:] >= d[ids][:-1]).all()


def test_backward_is_deterministic():
    scene = random_scene(2000, 96, 96, 4)
    g = torch.randn(96, 96, 3, generator=torch.Generator().manual_seed(1))
    a = _grads(rasterize, scene, 96, 96, g, torch.zeros(96, 96))[2]
    b = _grads(rasterize, scene, 96, 96, g, torch.zeros(96, 96))[2]
    for x, y in zip(a, b):
        assert torch.equal(x, y)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n,width,height,seed",
                         [(400, 96, 64, 11), (1500, 80, 64, 2), (300, 37, 29, 6), (0, 32, 32, 0)])
def test_torch_binning_lists_exactly_what_numba_lists(n, width, height, seed, dtype):
    """bin_gaussians_torch (the pure-PyTorch baseline's binning) = rasterize.bin_gaussians, list for list."""
    scene = random_scene(max(n, 1), width, height, seed, dtype, spread=0.5)
    if n == 0:
        scene = tuple(x[:0] for x in scene)
    m, c, col, o, d, v = scene
    o = o.clone()
    if n:
        o[: n // 20] = 0.003  # below 1/255: no footprint, listed nowhere
        m = m.clone()
        m[n // 20: n // 10] += 1e7  # far off-screen but finite
    ts_n, e_n = bin_gaussians(m.numpy(), c.numpy(), o.numpy(), d.numpy(), v.numpy(), width, height)
    ts_t, e_t = bin_gaussians_torch(m, c, o, d, v, width, height)
    assert np.array_equal(ts_t.numpy(), ts_n) and np.array_equal(e_t.numpy(), e_n)
    if n:
        assert len(e_n) > n // 2  # the scene is not trivially empty
    rx_n, ry_n = footprint_extent(c.numpy(), o.numpy())
    rx_t, ry_t = footprint_extent_torch(c, o)
    np.testing.assert_allclose(rx_t.numpy(), rx_n, rtol=1e-14)
    np.testing.assert_allclose(ry_t.numpy(), ry_n, rtol=1e-14)


@nb.njit(cache=True)
def _exp_neg_all(xs, coef):
    out = np.empty_like(xs)
    for i in range(xs.shape[0]):
        out[i] = _exp_neg(xs[i], coef)
    return out


@pytest.mark.parametrize("dtype,tol", [(np.float32, 3e-7), (np.float64, 1e-14)])
def test_vector_exp_matches_math_exp(dtype, tol):
    """The kernels' polynomial exp, relative to exp in float64, over [EXP_LO, 0]; clamped outside."""
    xs = np.concatenate([np.linspace(EXP_LO, 0.0, 20001), -np.random.default_rng(0).uniform(0, -EXP_LO, 5000),
                         [-math.log(2) * k for k in range(24)]]).astype(dtype)
    got = _exp_neg_all(xs, exp_coefficients(dtype))
    ref = np.exp(xs.astype(np.float64))
    assert np.max(np.abs(got - ref) / ref) < tol
    edge = _exp_neg_all(np.array([1.0, 5.0, EXP_LO - 3.0], dtype), exp_coefficients(dtype))
    np.testing.assert_allclose(edge.astype(np.float64), [1.0, 1.0, math.exp(EXP_LO)], rtol=tol)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_depth_order_is_the_stable_argsort(dtype):
    rng = np.random.default_rng(3)
    d = rng.normal(size=5000).astype(dtype)
    d[::7] = d[3]  # ties
    d[1::11] = 0.0
    d[2::13] = -0.0
    d[5] = np.inf
    d[6] = -np.inf
    idx = np.sort(rng.choice(5000, 4000, replace=False))
    np.testing.assert_array_equal(depth_order(d, idx), idx[np.argsort(d[idx], kind="stable")])
