"""`rsl export` places the Gaussians as `rsl adapt` anchored them (stages.results.gaussian_anchor), as evaluate and
report render them: at the fit frame of an adapted run its renders and PLY are the fitted Gaussians, not the
fitted binding carried to the adapted fit-frame shape."""
from __future__ import annotations

import numpy as np
import pytest

from stages.artefacts import (AdaptArtefact, Camera, CamerasArtefact, GaussiansArtefact, Provenance,
                              read_provenance)
from stages.steps.export import ExportConfig, run
from test_export import stretch_workspace

FIT_FRAME = 2
SHRINK = 0.85  # the fitted shape: the adapted fit-frame shape shrunk about its centre (inside it everywhere)


def _workspace(root, anchor_kind: str) -> dict:
    """Block stretched over 4 frames (adapt.h5 with extra gaussian_anchor = ``anchor_kind``), Gaussians fitted at
    frame FIT_FRAME with the mesh posed at fit_positions ≠ the adapted x_f, one camera."""
    from stages.render.mesh_raster import look_at

    w = stretch_workspace(root, np.linspace(1.0, 1.15, 4), "online", "images", 2, {"gaussian_anchor": anchor_kind})
    ws, mesh, pos = w["ws"], w["mesh"], w["positions"]
    x_f = pos[FIT_FRAME]
    centre = x_f.mean(0)
    fit_x = centre + SHRINK * (x_f - centre)
    rng = np.random.default_rng(1)
    host = np.repeat(np.arange(mesh.n_tets), 3)
    G = len(host)
    bary = rng.dirichlet(np.ones(4) * 2, size=G)
    sh = ((rng.uniform(0.2, 0.9, (G, 3)) - 0.5) / 0.28209479177387814)[:, None, :]
    gauss = GaussiansArtefact(host, bary, np.full((G, 3), np.log(0.003)), np.tile([1.0, 0, 0, 0], (G, 1)),
                              np.full(G, 3.0), sh, {}, np.zeros(3), fit_positions=fit_x)
    gauss.save(ws / "gaussians.h5", Provenance.make({"frame": FIT_FRAME, "workspace": str(ws)}))
    R, t = look_at(np.array([0.06, -0.25, 0.08]), np.array([0.06, 0.01, 0.01]), np.array([0.0, 0.0, -1.0]))
    K = np.array([[150.0, 0, 47.5], [0, 150.0, 35.5], [0, 0, 1]])
    cam = Camera("cam0", K, np.zeros(5), R, t, 96, 72)
    CamerasArtefact([cam], "synth").save(ws / "cameras.h5")
    return {"ws": ws, "root": root, "mesh": mesh, "x_f": x_f, "fit_x": fit_x, "cam": cam}


@pytest.mark.parametrize("anchor_kind", ["rebind", "offset"])
def test_export_renders_the_fit_frame_as_evaluate_does_and_as_fitted(tmp_path, anchor_kind):
    import imageio.v3 as iio
    import torch

    from stages.render.gaussians import BoundGaussians
    from stages.render.image_loss import ImageLoss
    from stages.render.ply import read_ply
    from stages.results import gaussian_anchor

    w = _workspace(tmp_path, anchor_kind)
    out = run(ExportConfig(workspace=w["ws"], render=True, ply=True, frames=str(FIT_FRAME), orbit_views=1,
                           render_size=32, out=tmp_path / "out"))
    exported = iio.imread(out / "render" / "cam0" / f"appearance_{FIT_FRAME:06d}.png").astype(int)

    def u8(img):
        return (np.clip(np.asarray(img, np.float64), 0, 1) * 255 + 0.5).astype(int)

    gauss = GaussiansArtefact.load(w["ws"] / "gaussians.h5")
    # evaluate's and report's render: ImageLoss anchored by stages.results.gaussian_anchor
    ev = ImageLoss(gauss, w["mesh"], [w["cam"]])
    anchor = gaussian_anchor(ev, AdaptArtefact.load(w["ws"] / "adapt.h5"), w["ws"] / "gaussians.h5")
    evaluated = u8(ev.render(w["x_f"] - anchor)[0])
    assert np.abs(exported - evaluated).max() <= 1
    # both are the fitted Gaussians: the binding as fitted, rendered at the positions they were fitted at
    bound = BoundGaussians.from_artefact(gauss, w["mesh"])
    with torch.no_grad():
        fitted = u8(bound.render(torch.as_tensor(w["fit_x"]), w["cam"]).image)
        carried = u8(bound.render(torch.as_tensor(w["x_f"]), w["cam"]).image)  # what export rendered before
    assert np.abs(exported - fitted).max() <= 2
    assert np.abs(carried - fitted).max() > 30  # the test tells the two placements apart
    # the PLY of the fit frame holds the fitted Gaussians: μ = Σ β x_fit, Σ = F_fit Σ₀ F_fitᵀ
    ply = read_ply(out / "ply" / f"frame_{FIT_FRAME:06d}.ply")
    mesh = w["mesh"]
    np.testing.assert_allclose(ply["means"], np.einsum("gk,gkd->gd", gauss.bary, w["fit_x"][mesh.tets[gauss.host_tet]]),
                               atol=1e-6)
    # isotropic rest Gaussians under the homogeneous F_fit = SHRINK·diag(λ1, λ2, λ2): std devs s·F_fit's diagonal
    l = np.diag(np.linalg.lstsq(mesh.vertices - mesh.vertices.mean(0), w["fit_x"] - w["fit_x"].mean(0),
                                rcond=None)[0])
    np.testing.assert_allclose(np.sort(np.exp(ply["log_scales"]), axis=1),
                               np.tile(np.sort(0.003 * l), (len(gauss.host_tet), 1)), rtol=1e-4)


def test_a_rollout_is_rendered_with_the_gaussians_anchored_by_the_adapted_run(tmp_path):
    """rollout.h5 (a prediction, no anchor of its own): its frames render with the Gaussians as adapt.h5 anchored
    them — re-bound at adapt's fit-frame shape, so at a rollout shape ≠ that one they follow the motion."""
    import imageio.v3 as iio

    from stages.render.image_loss import ImageLoss
    from stages.results import gaussian_anchor

    w = _workspace(tmp_path, "rebind")
    adapt = AdaptArtefact.load(w["ws"] / "adapt.h5")
    centre = w["x_f"].mean(0)
    x_r = centre + 1.05 * (w["x_f"] - centre)  # the rollout's fit-frame shape, not adapt's
    rollout = AdaptArtefact.load(w["ws"] / "adapt.h5")
    rollout.positions = rollout.positions.copy()
    rollout.positions[FIT_FRAME] = x_r
    rollout.extra = {}
    rollout.save(w["ws"] / "rollout.h5", Provenance.make({"capture": read_provenance(w["ws"] / "adapt.h5")["config"]
                                                          ["capture"], "workspace": str(w["ws"])}))
    out = run(ExportConfig(workspace=w["ws"], source="rollout", render=True, frames=str(FIT_FRAME), orbit_views=1,
                           render_size=32, out=tmp_path / "out"))
    exported = iio.imread(out / "render" / "cam0" / f"appearance_{FIT_FRAME:06d}.png").astype(int)
    gauss = GaussiansArtefact.load(w["ws"] / "gaussians.h5")
    ev = ImageLoss(gauss, w["mesh"], [w["cam"]])
    assert gaussian_anchor(ev, adapt, w["ws"] / "gaussians.h5") == 0.0
    expected = (np.clip(ev.render(x_r)[0].astype(np.float64), 0, 1) * 255 + 0.5).astype(int)
    assert np.abs(exported - expected).max() <= 1
    ev.rebind(None)  # as fitted, at x_r − (x_r − x_fit): what the rollout's own "offset" rule would render
    wrong = (np.clip(ev.render(w["fit_x"])[0].astype(np.float64), 0, 1) * 255 + 0.5).astype(int)
    assert np.abs(wrong - expected).max() > 30
