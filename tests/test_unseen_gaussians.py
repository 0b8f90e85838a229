"""Gaussians whose colours the fit did not see (rsl adapt --unseen-gaussians): the blending weights against the
render they sum (premultiplied colour is linear in the colours), nothing flagged at the fit pose, and the face
hidden from the camera flagged once it turns into view — its pixels then left out of the residuals and the loss."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from test_occluders import _camera, box_bar_gaussians, one_camera_capture

RES = 48
CAMERA = dict(res=RES, centre=(0.05, -0.3, 0.12), target=(0.05, 0.02, 0.02))


@pytest.fixture(scope="module")
def bar(tmp_path_factory):
    """A 6×3×3-cell bar (0.12 × 0.04 × 0.04 m) with 400 small Gaussians throughout, one camera in front of its
    y = 0 face, one frame (the render at rest, so the fit pose is the rest shape); a capture and workspace for
    VisionObservation."""
    from stages.render.image_loss import ImageLoss

    v, mesh, gauss = box_bar_gaussians(np.random.default_rng(0), 400, 0.004, 2.0)
    cam = _camera(**CAMERA)
    img = ImageLoss(gauss, mesh, [cam]).render(v)[0]
    cap, ws = one_camera_capture(tmp_path_factory.mktemp("unseen"), mesh, cam, gauss,
                                 np.round(np.clip(img, 0, 1) * 255).astype(np.uint8), {})
    centre = v.mean(axis=0)
    turned = (v - centre) @ Rotation.from_rotvec([np.pi, 0, 0]).as_matrix().T + centre  # the far face in front
    return SimpleNamespace(cap=cap, ws=ws, mesh=mesh, v=v, turned=turned)


def _obs(bar, unseen="ignore", appearance=False):
    from stages.capture import load_capture
    from stages.observations import VisionObservation

    return VisionObservation(load_capture(bar.cap), bar.ws, "", bar.mesh, appearance, "rebind", unseen)


def test_blend_weights_are_what_the_render_sums(bar):
    """Σ_p premult(p) = Σ_i w_i c_i for any colours c (the premultiplied colour is linear in them), and the
    weights of all Gaussians sum to the coverage in every pixel."""
    obs = _obs(bar)
    lf = obs.loss_fn
    for x in (bar.v, bar.turned):
        w = lf.blend_weights(x)
        assert w.shape == (1, 400) and np.all(w >= -1e-6)
        f = np.random.default_rng(1).uniform(0, 1, (1, 400))
        share, cover = lf.painted_share(x, f)[0]
        assert share.sum() == pytest.approx(float(w[0] @ f[0]), rel=1e-4)
        everything, cover2 = lf.painted_share(x, np.ones((1, 400)))[0]
        np.testing.assert_allclose(everything, cover, atol=1e-5)
        np.testing.assert_array_equal(cover, cover2)
        assert cover.sum() == pytest.approx(float(w.sum()), rel=1e-4)


def test_nothing_is_left_out_at_the_fit_pose_and_the_face_turned_into_view_is(bar):
    """At the pose of the fit every Gaussian paints what it painted there: no pixel flagged.  Turned 180° about
    the bar's axis, the face the camera never saw is in front: its pixels are flagged (most of the object's),
    their residuals are 0, and the frame keeps the pixels found at its first evaluation."""
    obs = _obs(bar)
    assert obs.unseen(0, bar.v) == [None]
    assert obs.unseen_pixels[0] == 0
    obs2 = _obs(bar)
    mask = obs2.unseen(0, bar.turned)[0]
    cover = obs2.loss_fn.painted_share(bar.turned, np.ones((1, 400)))[0][1]
    obj = cover >= 0.05
    assert mask is not None and mask.sum() >= 0.5 * obj.sum() and not np.any(mask & ~obj)
    r = obs2.residuals([0], bar.turned[None])[0].reshape(RES, RES, 3)
    assert np.all(r[mask] == 0) and np.abs(r[~mask & obj]).max() > 0
    np.testing.assert_array_equal(obs2.ignore(0, bar.v)[0], mask)  # found at the first evaluation, kept
    L, _ = obs2.loss([0], bar.turned[None])
    L_ref, _ = obs2.loss_fn(bar.turned, obs2.targets(0), [mask])
    assert L[0] == pytest.approx(L_ref, rel=1e-6)


def test_the_outline_of_the_object_mask_stays_in(bar):
    """With masks, the flagged pixels within UNSEEN_OUTLINE_PX of the mask's outline stay in the loss (their
    coverage tells the shape whatever the colours); those deeper inside are still left out."""
    import cv2

    from stages.observations import UNSEEN_OUTLINE_PX

    obs = _obs(bar)
    full = obs.unseen(0, bar.turned)[0]
    obj = obs.loss_fn.painted_share(bar.turned, np.ones((1, 400)))[0][1] >= 0.05
    obs2 = _obs(bar)
    obs2.masks = {"c0": obj[None].astype(np.uint8)}
    m = obs2.unseen(0, bar.turned)[0]
    inside = cv2.erode(obj.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=UNSEEN_OUTLINE_PX).astype(bool)
    assert m is not None and not np.any(m & ~inside) and np.array_equal(m, full & inside)
    assert (full & ~inside).sum() > 0  # the outline held flagged pixels


def test_a_bar_nearer_the_camera_or_stretched_is_not_unseen(bar):
    """Brought 35 % nearer the camera, each Gaussian paints about (1/0.65)² ≈ 2.4 × its fit weight, more than
    UNSEEN_RATIO, and stretched by 1.6 along its axis 1.6 ×: both are the faces the fit saw, imaged larger, so
    nothing is flagged (the weight is compared with the fit's scaled by the face-on image size)."""
    obs = _obs(bar)
    cam = np.array(CAMERA["centre"])
    near = bar.v + 0.35 * (cam - bar.v.mean(axis=0))
    grown = obs.loss_fn.blend_weights(near)[0] / np.maximum(obs.fit_weight, 1e-9)
    seen = obs.fit_weight > 1.0
    assert np.median(grown[seen]) > 2 * obs.UNSEEN_RATIO / 1.5  # the plain ratio alone would flag them
    assert obs.unseen(0, near) == [None]
    stretched = bar.v * np.array([1.6, 1.0, 1.0])
    assert _obs(bar).unseen(0, stretched) == [None]


def test_keep_and_appearance_leave_every_pixel_in(bar):
    for obs in (_obs(bar, unseen="keep"), _obs(bar, appearance=True)):
        assert not obs.unseen_ignored and obs.ignore(0, bar.turned) == [None]
    with pytest.raises(Exception, match="unseen_gaussians should be 'ignore' or 'keep'"):
        _obs(bar, unseen="drop")


def test_adapt_records_the_pixels_it_left_out(tmp_path):
    """rsl adapt --unseen-gaussians ignore on the cable-pulled beam filmed by one camera (40², 8 frames, Gaussians
    fitted to frame 0): adapt.h5's extra unseen_pixels holds one count per frame, none at the fit frame and some
    once the beam has turned; with the default keep it is None."""
    from stages.artefacts import AdaptArtefact
    from stages.steps import adapt, fit_gaussians
    from test_adapt_e2e import E_TRUE, _make_capture

    cap, ws = _make_capture(tmp_path, frames=8, cameras=1, resolution=40)
    fit_gaussians.run(fit_gaussians.FitGaussiansConfig(capture=cap, workspace=ws, iterations=40, gaussians=400))
    runs = {}
    for unseen in ("ignore", "keep"):
        adapt.run(adapt.AdaptConfig(capture=cap, workspace=ws, space="full", loss="vision", window=3, estimator="gn",
                                    young_init=E_TRUE, substeps=1, unseen_gaussians=unseen))
        runs[unseen] = AdaptArtefact.load(ws / "adapt.h5").extra["unseen_pixels"]
    counts = runs["ignore"]
    assert len(counts) == 8 and counts[0] == 0 and all(isinstance(c, int) and c >= 0 for c in counts)
    assert sum(counts) > 0, counts
    assert runs["keep"] is None
