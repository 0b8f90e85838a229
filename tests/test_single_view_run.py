"""What a lab brings, through `rsl run`: one camera, no background plate, the beam already hanging in its
equilibrium when filming starts, a clamp in view (the holding handle's ``visual``), markers as a C3D file.

The capture comes from `rsl synth --cameras 1 --clamp --no-plates --start equilibrium` (the clamp drawn into
the frames by stages.occluders.draw_occluders; truth masks = the object it leaves visible), with markers.csv
turned into markers.c3d (mm, 30 Hz).  `rsl run` then calibrates (cameras.json), segments (plate-less: GrabCut seeded by the
projected object, the clamp left out), tetrahedralizes, fits Gaussians, generates data, trains a subspace and
adapts (vision), all without an error; adapt from the C3D markers runs as well.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from stages.artefacts import AdaptArtefact, MasksArtefact

SETS = ["fit-gaussians.iterations=40", "fit-gaussians.gaussians=400", "generate-data.sequences=2",
        "generate-data.frames=8", "train-subspace.kind=pca", "train-subspace.dim=8", "adapt.window=3",
        "adapt.iters_per_frame=1", "tetrahedralize.max_tets=400"]


def make_single_view_capture(root: Path, beam: Path, frames: int = 10, resolution: int = 64) -> Path:
    """A single-view, plate-less, start = "equilibrium" capture with a clamp over the held end (rsl synth --clamp
    --no-plates) and its markers as markers.c3d (mm, 30 Hz) instead of markers.csv."""
    from stages import mocap
    from stages.capture import read_markers
    from stages.steps.synth import SynthConfig
    from stages.steps.synth import run as synth

    cap = synth(SynthConfig(mesh=beam, out=root / "cap", scenario="cable", cameras=1, frames=frames,
                            resolution=resolution, young=1.0e5, markers=20, calib_views=0, seed=0,
                            start="equilibrium", clamp=True, plates=False))
    assert 'start = "equilibrium"' in (cap / "capture.toml").read_text()
    assert not (cap / "background").exists()
    assert "visual" in json.loads((cap / "controls.json").read_text())["handles"][0]
    P = read_markers(cap / "markers.csv")
    mocap.write_c3d(cap / "markers.c3d", mocap.MarkerData(P, 30.0), units="mm")
    (cap / "markers.csv").unlink()
    return cap


@pytest.mark.slow
def test_single_view_capture_with_a_clamp_runs_through_rsl_run(tmp_path, shared_data, rsl) -> None:
    beam = shared_data / "autodef_fulton" / "Coarse_beam.mesh"
    cap = make_single_view_capture(tmp_path, beam)
    ws = tmp_path / "ws"
    args = ["run", cap, "-w", ws]
    for s in SETS:
        args += ["--set", s]
    p = rsl(*args)
    text = " ".join(p.stderr.split())
    assert p.returncode == 0, p.stderr[-3000:]
    assert "Traceback" not in p.stderr
    assert "7 stages ran" in text
    assert "segment: auto chose grabcut: no background plate" in text and "occluder pixels left out" in text
    masks = MasksArtefact.load(ws / "masks.h5")
    assert masks.method == "grabcut"
    print("segment IoU vs truth (frame 0):", masks.iou)
    assert masks.iou["cam0"] >= 0.85, masks.iou  # the visible object against the truth (clamp pixels removed)
    adapt = AdaptArtefact.load(ws / "adapt.h5")
    assert np.all(np.isfinite(adapt.young)) and np.all(adapt.young > 0)
    print(f"vision: final E {adapt.young[-1].tolist()} Pa (truth 1e5; one 64² camera, r = 8 PCA, w = 3)")
    # ... to the report (issue 15's done-when: a capture with a visible gripper): headless Chromium loads it
    from test_report import assert_page_loads

    p = rsl("report", "-w", ws, "--frames", "2")
    assert p.returncode == 0 and (ws / "report.html").is_file(), p.stderr[-2000:]
    assert_page_loads(ws / "report.html", tmp_path)
    # nothing changed: a second run has nothing to do
    p = rsl(*args)
    assert p.returncode == 0 and "0 stages ran, 7 up to date" in " ".join(p.stderr.split()), p.stderr[-2000:]
    # the mocap route: adapt from markers.c3d; a C3D at another rate than capture.fps is one sentence
    p = rsl("adapt", cap, "-w", ws, "--loss", "markers", "--space", "full", "--window", "3")
    assert p.returncode == 0, p.stderr[-3000:]
    adapt = AdaptArtefact.load(ws / "adapt.h5")
    assert np.all(np.isfinite(adapt.young)) and np.all(adapt.young > 0)
    print(f"markers.c3d: final E {adapt.young[-1].tolist()} Pa (truth 1e5; full space, w = 3)")
    from stages import mocap

    data = mocap.read_c3d(cap / "markers.c3d")
    mocap.write_c3d(cap / "markers.c3d", mocap.MarkerData(data.positions, 120.0), units="mm")
    p = rsl("adapt", cap, "-w", ws, "--loss", "markers", "--space", "full", "--window", "3")
    text = " ".join(p.stderr.split())
    assert p.returncode == 1 and "Traceback" not in p.stderr, p.stderr[-2000:]
    assert "markers are recorded at 120 Hz but" in text and "'capture.fps' is 30" in text
