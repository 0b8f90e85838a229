"""`rsl segment` on a `rsl synth` capture: IoU against the rendered truth masks."""
from __future__ import annotations

import numpy as np
import pytest

from stages.artefacts import MasksArtefact, MeshArtefact
from stages.steps.calibrate import CalibrateConfig
from stages.steps.calibrate import run as calibrate
from stages.capture import read_image
from stages.errors import RslError
from stages.progress import SilentReporter
from stages.steps.segment import SegmentConfig, run
from stages.sim.mesh import rest_quantities
from stages.vision.segmentation import iou


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Triangles that belong to one tet only (the surface; orientation irrelevant here)."""
    f = np.sort(np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]], tets[:, [1, 2, 3]]]), 1)
    u, c = np.unique(f, axis=0, return_counts=True)
    return u[c == 1]


@pytest.fixture(scope="module")
def synth_ws(tmp_path_factory, shared_data):
    """A 10-frame stretch capture from `rsl synth` (2 cameras, 128²), with cameras.h5 (imported from
    its cameras.json) and mesh.h5 (its rest tet mesh) in a workspace."""
    import meshio

    from stages.steps.synth import SynthConfig
    from stages.steps.synth import run as synth

    root = tmp_path_factory.mktemp("seg")
    cap = synth(SynthConfig(mesh=shared_data / "autodef_fulton" / "onekbar.mesh", out=root / "cap", frames=10,
                            resolution=128, cameras=2, markers=0, calib_views=0))
    ws = root / "ws"
    calibrate(CalibrateConfig(cap, ws))
    m = meshio.read(cap / "truth" / "object.mesh")
    v, tets = np.asarray(m.points, np.float64), np.asarray(m.cells_dict["tetra"], np.int64)
    vol, dm_inv, masses = rest_quantities(v, tets, 1070.0)
    MeshArtefact(v, tets, boundary_faces(tets), np.zeros(len(tets), np.int64), ["body"], vol, dm_inv, masses,
                 1070.0).save(ws / "mesh.h5")
    return cap, ws


def _ious(cap, masks: MasksArtefact) -> dict[str, list[float]]:
    out = {}
    for cam, stack in masks.masks.items():
        out[cam] = [iou(stack[i], read_image(cap / "truth" / "masks" / cam / f"{i:06d}.png")[..., 0] > 127)
                    for i in range(len(stack))]
    return out


def test_background_cli(synth_ws, rsl):
    cap, ws = synth_ws
    p = rsl("segment", cap, "-w", ws, "--method", "background")
    assert p.returncode == 0, p.stderr
    assert "by background" in p.stderr and "IoU vs truth" in p.stderr
    masks = MasksArtefact.load(ws / "masks.h5")
    assert masks.method == "background" and set(masks.masks) == {"cam0", "cam1"}
    assert masks.masks["cam0"].shape == (10, 128, 128)
    for cam, values in _ious(cap, masks).items():
        assert min(values) >= 0.95, (cam, values)
        assert masks.iou[cam] == pytest.approx(values[0])
    for f in (0, 4, 9):  # overlays of the first, middle and last frame (3 by default)
        assert (ws / "segment" / f"cam0_{f:06d}.png").is_file()


def test_grabcut_seeded_by_mesh(synth_ws):
    cap, ws = synth_ws
    rep = SilentReporter()
    masks = MasksArtefact.load(run(SegmentConfig(cap, ws, method="grabcut"), rep))
    assert masks.method == "grabcut"
    for cam, values in _ious(cap, masks).items():
        assert min(values) >= 0.95, (cam, values)
    assert "by grabcut" in rep.messages[-1]
    # auto picks the plates when every camera has one
    assert MasksArtefact.load(run(SegmentConfig(cap, ws, temporal=1, overlays=0))).method == "background"


def test_missing_inputs(synth_ws, tmp_path):
    cap, _ = synth_ws
    with pytest.raises(RslError, match="cameras.h5: file not found; mesh-seeded segmentation needs"):
        run(SegmentConfig(cap, tmp_path / "empty_ws", method="grabcut"))
    with pytest.raises(RslError, match="--method 'magic'"):
        run(SegmentConfig(cap, tmp_path / "empty_ws", method="magic"))
