"""The closed-form numpy tangents of gn's image Jacobian on linear tets (ImageLoss.jvp_numpy: binding_jvp's anchored
binding, geometry_jvp's matrix products) held to their slow twins — torch.func.jvp through anchored_geometry, and the
einsum sums — and the images' Jacobian built from them to the one built from the twins."""
from __future__ import annotations

import numpy as np

from stages.artefacts import CamerasArtefact
from test_vision_bias import _bend, _gaussians, _loss, capture  # noqa: F401  (the module-scoped capture fixture)


def _setup(capture):  # noqa: F811
    cap, ws, meshes = capture
    mesh = meshes[1]
    cams = CamerasArtefact.load(ws / "cameras.h5").cameras
    il = _loss(mesh, cams, _gaussians(mesh, 80, seed=3))
    rng = np.random.default_rng(9)
    size = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    V = np.stack([_bend(mesh.vertices, a) - mesh.vertices for a in (0.02, -0.01)]
                 + [rng.normal(size=mesh.vertices.shape) * 1e-3 * size])
    Va = np.stack([0.5 * V[0], -V[1], rng.normal(size=mesh.vertices.shape) * 1e-3 * size])
    il.rebind(_bend(mesh.vertices, 0.02))  # the anchor: a bent configuration
    return il, _bend(mesh.vertices, 0.05), V, Va  # (…, x: the configuration the tangents are taken at)


def tangents_both_ways(il, switch: str, x, V, Va) -> tuple:
    """((binding, geometry) with ImageLoss's ``switch`` on, the same with it off): binding_jvp at the anchor along Va
    and geometry_jvp at x along V — a fast path and its twin, to compare."""
    got = {}
    for fast in (True, False):
        setattr(il, switch, fast)
        b = il.binding_jvp(il._anchor_x, Va)
        got[fast] = (b, il.geometry_jvp(x, V, b))
    return got[True], got[False]


def test_binding_and_geometry_tangents_in_closed_form_are_the_torch_and_einsum_twins(capture):  # noqa: F811
    """After a rebind at a bent anchor: dβ, dL of the anchored binding (numpy closed form against torch forward mode)
    and μ, M, dμ, dM of the Gaussians at a bent configuration (matrix products against einsum) agree to rounding."""
    il, x, V, Va = _setup(capture)
    (bf, gf), (bs, gs) = tangents_both_ways(il, "jvp_numpy", x, V, Va)
    for a, c in zip(bf[2:], bs[2:]):
        assert np.abs(c).max() > 0
        np.testing.assert_allclose(a, c, rtol=0, atol=1e-10 * np.abs(c).max())
    for a, c in zip(gf, gs):
        assert np.abs(c).max() > 0
        np.testing.assert_allclose(a, c, rtol=0, atol=1e-12 * np.abs(c).max())


def test_images_jacobian_from_the_closed_form_tangents_is_the_twins(capture):  # noqa: F811
    """images_jvp with the numpy tangents: the same images bit for bit and the same derivative images (float32
    rendering) as with the torch / einsum twins, with the anchor of a rebind moving too."""
    il, x, V, Va = _setup(capture)
    out = {}
    for fast in (True, False):
        il.jvp_numpy = fast
        out[fast] = il.images_jvp(x, V, il.binding_jvp(il._anchor_x, Va))
    for (im1, d1), (im0, d0) in zip(out[True], out[False]):
        assert np.array_equal(im1, im0)
        assert np.abs(d0).max() > 0
        np.testing.assert_allclose(d1, d0, rtol=0, atol=1e-4 * np.abs(d0).max())
