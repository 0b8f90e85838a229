"""stages/silhouette.py: the soft silhouette (coverage of the surface triangles) of the static image loss — its
derivatives against finite differences, the sparse evaluation against its dense twin, its area against the exact
coverage, and the observation's pixel-block clusters for the cluster-robust σ."""
from __future__ import annotations

import numpy as np
import pytest


def _sil_camera(size: int = 48, shift=(-0.1, -0.02)):
    from stages.artefacts import Camera

    c = (size - 1) / 2
    return Camera("c", np.array([[90.0, 0, c], [0, 90.0, c], [0, 0, 1]]), np.array([0.02, -0.01, 1e-3, -1e-3, 0.0]),
                  np.eye(3), np.array([shift[0], shift[1], 0.5]), size, size)


def _bar(seed: int = 0, noise: float = 0.002):
    from stages.sim.meshgen import box_tets, surface_faces

    v, t = box_tets((6, 2, 2), (0.2, 0.04, 0.04))
    x = v + noise * np.random.default_rng(seed).standard_normal(v.shape)
    return x, surface_faces(t)


def test_soft_silhouette_derivatives_match_finite_differences():
    """stages.silhouette.SoftSilhouette (sparse; its dense twin is held to it below): forward mode (the Gauss–Newton Jacobian) and
    reverse mode (Adam's gradient) against central differences of the coverage itself, and
    ⟨vjp(g), v⟩ = ⟨g, jvp(v)⟩."""
    from stages.silhouette import SoftSilhouette

    x, f = _bar()
    rng = np.random.default_rng(1)
    s = SoftSilhouette(f, _sil_camera())
    A = s.coverage(x)
    assert A.shape == (48, 48) and 0.0 <= A.min() and A.max() <= 1.0 and A.max() > 0.99
    V = 1e-3 * rng.standard_normal((2,) + x.shape)
    J = s.jvp(x, V)
    g = rng.standard_normal(A.shape)
    G = s.vjp(x, g)
    for j in range(2):
        h = 1e-3  # V is 1 mm per unit: a 1 µm step (≈ 2e-4 px)
        fd = (s.coverage(x + h * V[j]) - s.coverage(x - h * V[j])) / (2 * h)
        assert np.abs(fd - J[j]).max() < 1e-4 * np.abs(J[j]).max()
        assert np.sum(G * V[j]) == pytest.approx(np.sum(g * J[j]), rel=1e-9)
    # ∂A/∂b, b the outline offset in pixels: central differences in b; the outline's length is Σ ∂A/∂b
    A0, dA = s.coverage_dgrow(x, 0.2)
    fd = (s.coverage(x, grow=0.2 + 1e-4) - s.coverage(x, grow=0.2 - 1e-4)) / 2e-4
    assert np.abs(fd - dA).max() < 1e-5 * np.abs(dA).max() and np.abs(A0 - s.coverage(x, grow=0.2)).max() < 1e-14
    assert s.coverage(x, grow=0.2).sum() > A.sum() + 0.1 * dA.sum()


@pytest.mark.parametrize("shift", [(-0.1, -0.02), (-0.2, 0.03)])
def test_sparse_soft_silhouette_equals_its_dense_twin(shift):
    """The sparse (triangle, nearby pixel) evaluation equals the dense one (every triangle at every pixel of the
    object's box): A within CUT_EPS (the bound on the terms left out beyond the margin), the forward- and
    reverse-mode derivatives to 10⁻⁶ of their size — also with the bar half outside the image (second shift)."""
    from stages.silhouette import CUT_EPS, SoftSilhouette

    x, f = _bar(seed=2)
    cam = _sil_camera(64, shift)
    sp, de = SoftSilhouette(f, cam), SoftSilhouette(f, cam, dense=True)
    rng = np.random.default_rng(3)
    A, Ad = sp.coverage(x), de.coverage(x)
    assert Ad.max() > 0.99 and 0 < sp.pairs < 0.5 * len(f) * A.size  # sparse: far fewer pairs than dense
    assert np.abs(A - Ad).max() <= CUT_EPS * (1 + 1e-9) + 1e-14
    if shift[0] < -0.15:
        assert Ad[:, 0].max() > 0.99  # the bar runs out of the image's left edge
    V = 1e-3 * rng.standard_normal((3,) + x.shape)
    J, Jd = sp.jvp(x, V), de.jvp(x, V)
    assert np.abs(J - Jd).max() < 1e-6 * np.abs(Jd).max()
    g = rng.standard_normal(A.shape)
    G, Gd = sp.vjp(x, g), de.vjp(x, g)
    assert np.abs(G - Gd).max() < 1e-6 * np.abs(Gd).max()
    # with the outline moved (the observation's offset b): coverage, ∂A/∂b and the derivatives in x
    (A, dA), (Ad, dAd) = sp.coverage_dgrow(x, 0.4), de.coverage_dgrow(x, 0.4)
    assert np.abs(A - Ad).max() <= CUT_EPS * (1 + 1e-9) + 1e-14 and np.abs(A - sp.coverage(x, grow=0.4)).max() < 1e-14
    assert np.abs(dA - dAd).max() < 1e-6 * np.abs(dAd).max() and dA.min() >= 0  # growing only adds coverage
    assert np.abs(sp.jvp(x, V, grow=-0.3) - de.jvp(x, V, grow=-0.3)).max() < 1e-6 * np.abs(Jd).max()
    assert np.abs(sp.vjp(x, g, grow=-0.3) - de.vjp(x, g, grow=-0.3)).max() < 1e-6 * np.abs(Gd).max()


def test_sparse_margin_bounds_the_left_out_terms():
    """The margin m = τ (ln(F/ε) − δ/τ) + b_max: one triangle's term at distance m from it, its outline moved out
    by the largest offset b_max, is ε/F (softplus(−(m − b_max + δ)/τ) ≈ e^{−(m − b_max + δ)/τ}), so F of them sum
    to ε; a triangle seen alone, its coverage one pixel beyond its grown box is below ε/F, and what the dense twin
    gives inside the grown box — at b = 0 and at b = ±b_max."""
    from stages.silhouette import CUT_EPS, GROW_MAX_PX, SHIFT_TAU, TAU_PX, SoftSilhouette

    faces = np.array([[0, 1, 2]])
    x = np.array([[0.0, 0.0, 0.5], [0.01, 0.0, 0.5], [0.0, 0.012, 0.5]])
    cam = _sil_camera(48, (0.0, 0.0))
    sp, de = SoftSilhouette(faces, cam), SoftSilhouette(faces, cam, dense=True)
    m = sp.margin_px
    assert m == pytest.approx(TAU_PX * (np.log(1 / CUT_EPS) - SHIFT_TAU) + GROW_MAX_PX)
    assert np.log1p(np.exp(-((m - GROW_MAX_PX) / TAU_PX + SHIFT_TAU))) == pytest.approx(CUT_EPS, rel=1e-6)
    for b in (0.0, GROW_MAX_PX, -GROW_MAX_PX):
        A, Ad = sp.coverage(x, grow=b), de.coverage(x, grow=b)
        assert np.abs(A - Ad).max() <= CUT_EPS
        assert (A == 0).any() and Ad[A == 0].max() <= CUT_EPS  # only terms below ε are left out
    with pytest.raises(ValueError):
        sp.coverage(x, grow=1.5 * GROW_MAX_PX)


def test_soft_silhouette_is_the_hard_silhouette_blurred_by_a_pixel():
    """The soft coverage of a closed surface differs from the exact (supersampled) coverage only along the
    outline: by less than ~2/3 of a pixel per outline pixel summed, its area within ¼ pixel per outline pixel
    (stages.silhouette.SHIFT_TAU: the front and back faces meeting on the outline make A = ½ there).  Inside, a
    pixel stays above ¾ even where the inner edges of the front and the back layer coincide (four soft edges
    through its centre: this structured box seen square-on is the worst case)."""
    from stages.silhouette import SoftSilhouette
    from stages.sweep import silhouette_coverage

    v, f = _bar(noise=0.0)
    cam = _sil_camera(64)
    soft, hard = SoftSilhouette(f, cam).coverage(v), silhouette_coverage(v, f, cam, supersample=8)
    inside = hard == 1.0
    assert np.all(soft[inside] > 0.74)
    outline = np.count_nonzero((hard > 0) & (hard < 1))
    assert np.abs(soft - hard).sum() < 0.67 * outline + 0.1 * np.count_nonzero(inside) ** 0.5
    print(f"soft area {soft.sum():.1f} px², exact {hard.sum():.1f} px², outline {outline} px")
    assert abs(soft.sum() - hard.sum()) < 0.25 * outline



def _observation_with_cameras(cams):
    """A SilhouetteObservation holding only its cameras (what :meth:`clusters` reads)."""
    from stages.silhouette import SilhouetteObservation

    obs = SilhouetteObservation.__new__(SilhouetteObservation)
    obs._cams = cams
    return obs


def test_silhouette_clusters_are_pixel_blocks_repeated_over_frames():
    """SilhouetteObservation.clusters: one id per block_px × block_px pixel block of each camera (a partial block
    at the right and bottom edges), ids of different cameras apart, the same ids in every frame."""
    obs = _observation_with_cameras([_sil_camera(20), _sil_camera(16)])
    ids = obs.clusters([0, 1])
    m = 20 * 20 + 16 * 16
    assert ids.shape == (2 * m,) and np.array_equal(ids[:m], ids[m:])
    a = ids[:400].reshape(20, 20)
    assert len(np.unique(a)) == 9 and len(np.unique(a[:8, :8])) == 1 and len(np.unique(a[16:, 16:])) == 1
    assert a[0, 7] == a[7, 0] != a[0, 8]
    b = ids[400:m].reshape(16, 16)
    assert len(np.unique(b)) == 4 and not set(np.unique(a)) & set(np.unique(b))


def test_cluster_robust_sigma_covers_an_estimate_from_block_correlated_pixel_errors():
    """Why the silhouette's σ is cluster-robust: pixels whose errors are shared by 8 × 8 blocks (and repeat over
    the frames, as a still capture's mask errors do) make a least-squares estimate vary far more than
    independent pixels would; over 400 replications the ±2σ interval from stages.estimator.cluster_scale2 over
    SilhouetteObservation.clusters holds the truth about 95 % of the time, the iid one (RSS/(m − k)) far less."""
    from stages.estimator import cluster_scale2, residual_scale2

    obs = _observation_with_cameras([_sil_camera(48)])
    frames = [0, 1]
    ids = obs.clusters(frames)
    rng = np.random.default_rng(0)
    # an outline moves as a whole: the sensitivity shares its sign over a block (pixels near the outline only)
    J = ((rng.standard_normal(ids.max() + 1)[ids] + 0.3 * rng.standard_normal(len(ids)))
         * (rng.random(len(ids)) < 0.3))[:, None]
    A = float(J[:, 0] @ J[:, 0])
    hits_cl = hits_iid = 0
    n = 400
    for _ in range(n):
        e = 0.1 * rng.standard_normal(ids.max() + 1)[ids] + 0.01 * rng.standard_normal(len(ids))
        p_hat = float(J[:, 0] @ e) / A  # truth 0
        r = e - J[:, 0] * p_hat
        s_cl = np.sqrt(cluster_scale2(r, J, 0.05, None, ids) * 0.05 ** 2 / A)
        s_iid = np.sqrt(residual_scale2(r, 0.05, None, 1) * 0.05 ** 2 / A)
        hits_cl += abs(p_hat) <= 2 * s_cl
        hits_iid += abs(p_hat) <= 2 * s_iid
    print(f"±2σ coverage: cluster-robust {hits_cl / n:.2f}, iid {hits_iid / n:.2f}")
    assert 0.88 <= hits_cl / n <= 0.99 and hits_iid / n < 0.6


def _bar_observation(mask: np.ndarray, n: int, faces: np.ndarray, cam):
    """A SilhouetteObservation of one camera whose masks.h5 would hold ``mask`` (T, H, W), no occluder."""
    from stages.silhouette import SilhouetteObservation, SoftSilhouette

    obs = _observation_with_cameras([cam])
    obs.n, obs.cameras, obs.masks = n, [cam.name], {cam.name: mask}
    obs.soft = [SoftSilhouette(faces, cam)]
    obs.occluded, obs.controls, obs._ignore, obs.grow_px = False, None, {}, {}
    assert isinstance(obs, SilhouetteObservation)
    return obs


def test_silhouette_observation_residuals_jacobian_and_gradient_agree():
    """SilhouetteObservation: r = G((A − m)·keep) with the blur G symmetric (⟨Ga, b⟩ = ⟨a, Gb⟩, zero beyond the
    image); its Jacobian (Gauss–Newton) against central differences of the residuals along position directions,
    and its loss gradient (Adam) against central differences of Σ r²."""
    x, f = _bar(seed=4)
    cam = _sil_camera(48)
    from stages.silhouette import SoftSilhouette

    mask = (SoftSilhouette(f, cam).coverage(_bar(seed=5)[0]) > 0.5)[None].repeat(2, axis=0)
    obs = _bar_observation(mask, len(x), f, cam)
    rng = np.random.default_rng(6)
    a, b = rng.standard_normal((2, 48, 48))
    assert np.sum(obs.blur(a) * b) == pytest.approx(np.sum(a * obs.blur(b)), rel=1e-12)
    assert np.abs(obs.blur(a) - a).max() > 0.1  # it does blur
    X = np.stack([x, x + 1e-4 * rng.standard_normal(x.shape)])
    dX = 1e-3 * rng.standard_normal((2,) + X.shape)  # (k, frames, n, 3)
    Js = obs.jacobian([0, 1], X, dX)
    h = 1e-3
    rp, rm = obs.residuals([0, 1], X + h * dX[1]), obs.residuals([0, 1], X - h * dX[1])
    for i in range(2):
        fd = (rp[i] - rm[i]) / (2 * h)
        assert Js[i].shape == (48 * 48, 2) and np.abs(fd - Js[i][:, 1]).max() < 1e-4 * np.abs(Js[i][:, 1]).max()
    losses, grad = obs.loss([0, 1], X)
    r = obs.residuals([0, 1], X)
    assert losses == pytest.approx([float(ri @ ri) for ri in r], rel=1e-12)
    V = dX[0]
    lp = obs.loss([0, 1], X + h * V)[0].sum()
    lm = obs.loss([0, 1], X - h * V)[0].sum()
    assert np.sum(grad * V) == pytest.approx((lp - lm) / (2 * h), rel=1e-5)


def test_matched_outline_offset_takes_up_a_dilated_mask():
    """A mask whose outline lies b pixels outside the surface's (a segmentation's convention: 2×2-supersampled
    coverage ≥ ½ fattens it by ~¼ px) would pull E through the blurred residual (docs/results/static.md); the
    observation matches the offset per camera and frame (Σ keep·(A(x, b) − m) = 0): at the true positions b is
    the dilation, the residual and the gradient vanish — with b held at 0 neither does.  A mask beyond any offset
    pins b at GROW_MAX_PX, and the derivatives stay exact there (b constant)."""
    from stages.silhouette import GROW_MAX_PX, SoftSilhouette

    x, f = _bar(seed=4)
    cam = _sil_camera(48)
    m = SoftSilhouette(f, cam).coverage(x, grow=0.3)[None]
    obs = _bar_observation(m, len(x), f, cam)
    b, A, _, beta = obs.outline(0, 0, x)
    assert b == pytest.approx(0.3, abs=1e-9) and beta is not None
    assert np.abs(obs.residuals([0], x[None])[0]).max() < 1e-8
    loss, grad = obs.loss([0], x[None])
    assert loss[0] < 1e-15 and np.abs(grad).max() < 1e-6
    obs.match_outline = False
    loss0, grad0 = obs.loss([0], x[None])
    assert loss0[0] > 1.0 and np.abs(grad0).max() > 1e3 * max(np.abs(grad).max(), 1e-9)
    obs.match_outline = True
    # away from the truth the areas still match (b follows x)
    y = x + 2e-3 * np.random.default_rng(1).standard_normal(x.shape)
    b, A, _, _ = obs.outline(0, 0, y)
    assert abs(b - 0.3) > 1e-3 and abs(np.sum(A - m[0])) < 1e-8 * m.sum()
    # pinned: a mask far larger than the surface
    big = np.zeros((1, 48, 48))
    big[:, 5:43, 5:43] = 1.0
    obs = _bar_observation(big, len(x), f, cam)
    b, _, _, beta = obs.outline(0, 0, x)
    assert b == GROW_MAX_PX and beta is None
    dX = 1e-3 * np.random.default_rng(2).standard_normal((1, 1) + x.shape)
    J = obs.jacobian([0], x[None], dX)[0][:, 0]
    h = 1e-3
    fd = (obs.residuals([0], x[None] + h * dX[0])[0] - obs.residuals([0], x[None] - h * dX[0])[0]) / (2 * h)
    assert np.abs(fd - J).max() < 1e-4 * np.abs(J).max()


def test_outline_floor_is_the_spread_that_block_outline_errors_give_the_estimate():
    """SilhouetteObservation.sigma_floor: an outline error e_c of the mask in pixel block c (Δm = e_c ∂A/∂b on c)
    moves the linearised estimate p̂ = −Jᵀr / JᵀJ by w_c e_c; the floor σ_o √(Σ_c w_c²) from :meth:`jacobian`'s
    g_c equals the one from central differences of p̂ in each e_c (b re-matched each time)."""
    from stages.silhouette import SoftSilhouette

    x, f = _bar(seed=4)
    cam = _sil_camera(48)
    soft = SoftSilhouette(f, cam)
    m0, dA = soft.coverage_dgrow(x, 0.2)
    obs = _bar_observation(m0[None].copy(), len(x), f, cam)
    d = np.zeros_like(x)
    d[:, 2] = 0.05 * (x[:, 0] - x[:, 0].min()) ** 2  # a sag-like direction, m per unit of p
    J = obs.jacobian([0], x[None], d[None, None])[0][:, 0]
    assert obs.floor_unit.shape == (1,) and obs.floor_unit[0] > 0
    ids = obs.clusters([0])
    w, h = [], 1e-3
    for c in np.unique(ids[(dA.ravel() > 1e-3)]):
        on = (ids == c).reshape(48, 48)
        est = []
        for e in (h, -h):
            obs.masks[cam.name] = (m0 + e * dA * on)[None]
            est.append(-float(J @ obs.residuals([0], x[None])[0]) / float(J @ J))
        w.append((est[0] - est[1]) / (2 * h))
    fd = max(obs.outline_px, obs.outline_rms_px) * np.sqrt(np.sum(np.square(w)))
    print(f"outline floor {obs.sigma_floor()[0]:.4g} (g_c) vs {fd:.4g} (differences), {len(w)} blocks")
    assert obs.sigma_floor()[0] == pytest.approx(fd, rel=1e-4)
