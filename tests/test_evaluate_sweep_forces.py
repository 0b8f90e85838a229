"""`rsl evaluate` beyond E: the handle forces against truth/forces.csv (stages.forces, shared with `rsl export
--forces`) and `--sweep`, the loss over a grid of fixed E, on a same-model capture (rsl synth's own P1 mesh,
one step per frame, hard handles) — where the truth is reproduced exactly, so the force error vanishes at E_true
and the sweep's minimum lies at E_true."""
from __future__ import annotations

import json
from pathlib import Path

import meshio
import numpy as np
import pytest

from stages.artefacts import AdaptArtefact, MeshArtefact, Provenance

E_TRUE = 6.0e4
FRAMES = 6


@pytest.fixture(scope="module")
def same_model(tmp_path_factory):
    return same_model_capture(tmp_path_factory.mktemp("same"))


def same_model_capture(root: Path) -> tuple[Path, Path]:
    """In ``root``: a stretched bar (hard handles, start = equilibrium, P1 truth, E_TRUE, FRAMES frames) and a
    workspace whose mesh.h5 is the truth's own mesh; returns (capture, workspace)."""
    from conftest import run_rsl
    from stages.sim.meshgen import box_tets

    v, t = box_tets((6, 2, 2), (0.2, 0.04, 0.04))
    meshio.write(str(root / "bar.mesh"), meshio.Mesh(v, [("tetra", t)]), file_format="medit")
    cap = root / "cap"
    p = run_rsl("synth", root / "bar.mesh", cap, "--scenario", "stretch", "--cameras", "1", "--frames", str(FRAMES),
                "--resolution", "32", "--markers", "12", "--calib-views", "0", "--young", str(E_TRUE),
                "--handles", "hard", "--start", "equilibrium", "--amplitude", "0.4")
    assert p.returncode == 0, p.stderr[-2000:]
    toml = cap / "capture.toml"
    toml.write_text(toml.read_text().replace('mesh = "object.obj"', 'mesh = "truth/object.mesh"'))
    ws = root / "ws"
    p = run_rsl("tetrahedralize", cap, "-w", ws, "--order", "1", "--no-preview")
    assert p.returncode == 0, p.stderr[-2000:]
    return cap, ws


def _adapt_h5(cap, ws, young: float) -> None:
    """adapt.h5 of the capture's controls simulated on mesh.h5 with a constant E (full space, declared start)."""
    from stages.capture import load_capture
    from stages.sim.scene import make_scene
    from stages.sweep import simulate_fixed

    capture = load_capture(cap)
    mesh = MeshArtefact.load(ws / "mesh.h5")
    ctl = capture.controls()
    scene = make_scene(mesh, ctl, capture.material.model, capture.dt, capture.gravity)
    X = simulate_fixed(scene, ctl, np.array([young]), np.array([0.45]), FRAMES, capture.start)
    T = FRAMES
    AdaptArtefact(frames=np.arange(T), young=np.full((T, 1), young), poisson=np.full((T, 1), 0.45),
                  z=np.zeros((T, 0)), positions=X, loss=np.zeros(T), time_forward_s=np.zeros(T),
                  time_backward_s=np.zeros(T), time_render_s=np.zeros(T), time_total_s=np.zeros(T),
                  region_names=list(mesh.region_names), mode="offline", space="full", loss_kind="markers",
                  window=T).save(ws / "adapt.h5", Provenance.make({"capture": str(cap), "workspace": str(ws)}))


def test_force_error_vanishes_at_the_truth_and_grows_with_a_wrong_young(same_model, rsl):
    cap, ws = same_model
    errors = {}
    for scale in (1.0, 2.0):
        _adapt_h5(cap, ws, scale * E_TRUE)
        p = rsl("evaluate", cap, "-w", ws, "--psnr-frames", "0", "--no-plot")
        assert p.returncode == 0, p.stderr[-2000:]
        ev = json.loads((ws / "evaluation.json").read_text())
        f = ev["forces"]
        assert set(f["per_set"]) == {"left", "right"} and f["truth"].endswith("forces.csv")
        errors[scale] = f
    same, wrong = errors[1.0], errors[2.0]
    print("force error at E_true:", same["median_relative_error"], "at 2 E_true:", wrong["median_relative_error"])
    assert same["median_relative_error"] < 1e-4  # the same model, mesh and step: the truth's own forces
    for name in ("left", "right"):
        assert same["per_set"][name]["median_relative_error"] < 1e-4
        assert len(same["per_set"][name]["frames"]) >= FRAMES - 2  # the stretch pulls at almost every frame
    # twice as stiff, the same prescribed stretch: the reactions roughly double
    assert wrong["median_relative_error"] > 0.3
    assert wrong["per_set"]["right"]["median_relative_error"] > 0.3


def test_forces_are_replayed_whatever_adapt_h5_recorded(same_model, rsl):
    """An online run's forces come from θ(t) replayed from the start state (stages.forces.adapted_forces), not
    from adapt.h5's positions: recorded positions that no simulation made (an online splice) leave the error at the
    truth's."""
    cap, ws = same_model
    _adapt_h5(cap, ws, E_TRUE)
    a = AdaptArtefact.load(ws / "adapt.h5")
    a.positions = a.positions + np.random.default_rng(0).normal(0.0, 1e-3, a.positions.shape)  # 1 mm jitter
    a.mode, a.window = "online", 3  # an online run: a splice of windows, so its forces are replayed
    a.save(ws / "adapt.h5", Provenance.make({"capture": str(cap), "workspace": str(ws)}))
    # --force-substeps 0: adapt.h5's own step (1 per frame, unrecorded here), the truth's on this same-model capture
    p = rsl("evaluate", cap, "-w", ws, "--psnr-frames", "0", "--no-plot", "--force-substeps", "0",
            "--no-force-extrapolate")
    assert p.returncode == 0, p.stderr[-2000:]
    f = json.loads((ws / "evaluation.json").read_text())["forces"]
    assert f["median_relative_error"] < 1e-4 and "replay" in f["source"] and "1 substep" in f["source"]
    # the default (stages.forces FORCE_SUBSTEPS, FORCE_EXTRAPOLATE): adapt.h5's own substeps, plain, as above
    p = rsl("evaluate", cap, "-w", ws, "--psnr-frames", "0", "--no-plot")
    assert p.returncode == 0, p.stderr[-2000:]
    f = json.loads((ws / "evaluation.json").read_text())["forces"]
    assert f["median_relative_error"] < 1e-4 and "Richardson" not in f["source"], f["source"]
    # Richardson over S and 2S on request, named in the source
    p = rsl("evaluate", cap, "-w", ws, "--psnr-frames", "0", "--no-plot", "--force-substeps", "1",
            "--force-extrapolate")
    assert p.returncode == 0, p.stderr[-2000:]
    f = json.loads((ws / "evaluation.json").read_text())["forces"]
    assert "Richardson-extrapolated from 1 and 2 substeps" in f["source"], f["source"]
    p = rsl("evaluate", cap, "-w", ws, "--psnr-frames", "0", "--no-plot", "--force-substeps", "-1")
    assert p.returncode != 0 and "--force-substeps" in p.stderr and "Traceback" not in p.stderr


def test_export_forces_match_evaluate_on_the_same_trajectory(same_model, rsl, tmp_path):
    """`rsl export --forces` and `rsl evaluate` compute the forces through stages.forces alike: the exported
    forces.csv against truth/forces.csv gives evaluate's numbers."""
    from stages.capture import read_forces_csv
    from stages.forces import force_errors

    cap, ws = same_model
    _adapt_h5(cap, ws, 1.5 * E_TRUE)
    out = tmp_path / "export"
    p = rsl("export", "-w", ws, "--capture", cap, "--forces", "--no-plots", "--no-render", "--no-vtk", "--no-stress",
            "--no-ply", "-o", out)
    assert p.returncode == 0, p.stderr[-2000:]
    p = rsl("evaluate", cap, "-w", ws, "--psnr-frames", "0", "--no-plot")
    assert p.returncode == 0, p.stderr[-2000:]
    ev = json.loads((ws / "evaluation.json").read_text())["forces"]["per_set"]
    mine = force_errors(read_forces_csv(out / "forces.csv"), read_forces_csv(cap / "truth" / "forces.csv"))
    for name in ("left", "right"):
        assert mine[name]["median_relative_error"] == pytest.approx(ev[name]["median_relative_error"], rel=1e-6)


def test_force_errors_by_hand():
    """‖F − F_true‖ / ‖F_true‖ per frame, frames below 5 % of the largest true force left out, the median."""
    from stages.forces import force_errors

    def row(frame, name, f):
        return {"frame": frame, "name": name, "kind": "handle", "applied_fx_N": f[0], "applied_fy_N": f[1],
                "applied_fz_N": f[2]}

    truth = [row(0, "h", (0.0, 0.0, 0.01)), row(1, "h", (1.0, 0.0, 0.0)), row(2, "h", (0.0, 2.0, 0.0)),
             row(3, "h", (0.0, 0.0, 4.0))]
    est = [row(0, "h", (5.0, 0.0, 0.0)), row(1, "h", (1.1, 0.0, 0.0)), row(2, "h", (0.0, 2.0, 1.0)),
           row(3, "h", (0.0, 0.0, 4.0))]
    e = force_errors(est, truth)["h"]
    assert e["frames"] == [1, 2, 3]  # frame 0's 0.01 N is under 5 % of 4 N
    np.testing.assert_allclose(e["rel_error_per_frame"], [0.1, 0.5, 0.0], atol=1e-12)
    assert e["median_relative_error"] == pytest.approx(0.1)
    assert force_errors(est[:1], truth)["h"]["median_relative_error"] is None  # frame 0 alone: no contact


def test_evaluate_sweep_minimum_lies_at_the_truth(same_model, rsl):
    """--sweep (markers, the whole sequence, 7 values from E_true/2 to 2 E_true): the minimum at E_true within
    1 % and the loss there ~ 0 (the same model reproduces the markers); without adapt.h5 as well."""
    cap, ws = same_model
    (ws / "adapt.h5").unlink(missing_ok=True)
    p = rsl("evaluate", cap, "-w", ws, "--sweep", "--sweep-points", "7", "--sweep-min", "0.5", "--sweep-max", "2")
    assert p.returncode == 0, p.stderr[-2000:]
    assert "E_true" in p.stderr
    ev = json.loads((ws / "evaluation.json").read_text())
    sw = ev["sweep"]
    assert "young_rel_error_median" not in ev  # no adapt.h5: the sweep alone
    assert sw["loss"] == "markers" and sw["interior"] and sw["young_true"] == pytest.approx(E_TRUE)
    assert sw["loss_contrast"] > 0.5 and "flat" not in p.stderr
    assert len(sw["young_pa"]) == 7 and sw["young_pa"][3] == pytest.approx(E_TRUE)
    assert abs(sw["min_over_true"] - 1) < 0.01, sw["min_over_true"]
    losses = np.array(sw["loss_values"])
    assert np.argmin(losses) == 3 and losses[3] < 1e-10 * losses.max()
    png = ws / "evaluation_sweep.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    # a bad grid is one sentence
    p = rsl("evaluate", cap, "-w", ws, "--sweep", "--sweep-min", "2", "--sweep-max", "1")
    assert p.returncode != 0 and "Traceback" not in p.stderr and "--sweep-min" in p.stderr
    # a region the mesh does not have is one sentence naming mesh.h5; the one region swept alone is E itself
    p = rsl("evaluate", cap, "-w", ws, "--sweep", "--sweep-region", "tip")
    assert p.returncode != 0 and "Traceback" not in p.stderr and "mesh.h5" in p.stderr and "'tip'" in p.stderr
    p = rsl("evaluate", cap, "-w", ws, "--sweep", "--sweep-points", "3", "--sweep-min", "0.8", "--sweep-max", "1.25",
            "--sweep-region", "body", "--no-plot")
    assert p.returncode == 0, p.stderr[-2000:]
    sw = json.loads((ws / "evaluation.json").read_text())["sweep"]
    assert sw["region"] == "body" and abs(sw["min_over_true"] - 1) < 0.01 and "of region body" in p.stderr
