"""`rsl synth --start moving`: a capture that begins mid-motion is the tail of a plain capture that begins
--lead-frames frames earlier — the same truth, material, forces and markers, and controls read that much later."""
from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from stages.capture import load_capture, read_forces_csv, read_truth
from stages.domain.controls import IDENTITY_POSE, Track
from stages.errors import RslError
from stages.progress import SilentReporter
from stages.steps.synth import SynthConfig, run
from test_synth import box_mesh  # noqa: F401  (the module-scoped bar mesh fixture)

FRAMES, LEAD = 5, 2  # 7 simulated frames: the sin² motion is at its fastest at frames 2–3
BASE = dict(cameras=1, resolution=32, markers=6, calib_views=0, seed=3, young=8e4)


@pytest.fixture(scope="module", params=["stretch", "cable"])
def pair(request, box_mesh, tmp_path_factory) -> tuple[Path, Path, list[str]]:
    """(moving capture, plain equilibrium capture with LEAD more frames, the moving run's messages): the same
    scenario, seed and options; E steps up at capture frame 2 (plain frame 2 + LEAD)."""
    root = tmp_path_factory.mktemp(request.param)
    reporter = SilentReporter()
    moving = run(SynthConfig(mesh=box_mesh, out=root / "moving", scenario=request.param, frames=FRAMES,
                             start="moving", lead_frames=LEAD, young_schedule="8e4@0,1.2e5@2", **BASE), reporter)
    plain = run(SynthConfig(mesh=box_mesh, out=root / "plain", scenario=request.param, frames=FRAMES + LEAD,
                            start="equilibrium", young_schedule=f"8e4@0,1.2e5@{2 + LEAD}", **BASE))
    return moving, plain, reporter.messages


def test_capture_declares_a_moving_start_and_its_lead_in(pair):
    moving, _, messages = pair
    cap = load_capture(moving)
    assert cap.start == "moving"
    synth = tomllib.loads((moving / "capture.toml").read_text())["synth"]
    assert synth["start"] == "moving" and synth["lead_frames"] == LEAD and synth["lead_start"] == "equilibrium"
    assert f"start moving (after {LEAD} lead-in frames from equilibrium)" in messages[-1]
    assert cap.frame_count() == FRAMES and cap.markers().shape == (FRAMES, 6, 3)
    assert read_truth(cap).vertices.shape[0] == FRAMES


def test_truth_is_the_plain_capture_after_the_lead_in(pair):
    moving, plain = (load_capture(p) for p in pair[:2])
    tm, tp = read_truth(moving), read_truth(plain)
    np.testing.assert_allclose(tm.vertices, tp.vertices[LEAD:], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(tm.young, tp.young[LEAD:])
    np.testing.assert_array_equal(tm.young[:, 0], [8e4, 8e4, 1.2e5, 1.2e5, 1.2e5])  # schedule frames = capture frames
    np.testing.assert_array_equal(tm.poisson, tp.poisson[LEAD:])
    np.testing.assert_allclose(moving.markers(), plain.markers()[LEAD:], rtol=0, atol=1e-12)
    fm = read_forces_csv(moving.truth_dir / "forces.csv")
    fp = [r for r in read_forces_csv(plain.truth_dir / "forces.csv") if r["frame"] >= LEAD]
    assert [r["frame"] for r in fm] == [r["frame"] - LEAD for r in fp]
    assert [r["time_s"] for r in fm] == pytest.approx([r["frame"] / moving.fps for r in fm])
    for a, b in zip(fm, fp):
        assert a["name"] == b["name"]
        assert [a[k] for k in a if k.endswith("_N")] == pytest.approx([b[k] for k in b if k.endswith("_N")],
                                                                       rel=1e-8, abs=1e-10)


def _tracks(ctl) -> list[Track]:
    return [h.poses for h in ctl.handles] + [ld.force for ld in ctl.loads] + [o.poses for o in ctl.obstacles]


def test_controls_are_the_plain_ones_read_lead_frames_later(pair):
    cm, cp = (load_capture(p).controls() for p in pair[:2])
    assert [h.name for h in cm.handles] == [h.name for h in cp.handles] and len(cm.loads) == len(cp.loads)
    assert any(np.ptp(t.values, axis=0).max() > 0 for t in _tracks(cm))  # something moves
    for a, b in zip(_tracks(cm), _tracks(cp)):
        for f in np.arange(0.0, FRAMES + 1.0, 0.5):  # past the last frame too: the last value holds
            np.testing.assert_allclose(a.at(f), b.at(f + LEAD), rtol=0, atol=1e-12)


def test_frame0_is_mid_motion(pair):
    moving, plain = (load_capture(p) for p in pair[:2])
    xm, xp = read_truth(moving).vertices, read_truth(plain).vertices
    motion = np.linalg.norm(xp - xp[0], axis=2).max()
    came = np.linalg.norm(xp[LEAD] - xp[LEAD - 1], axis=1).max()  # the step into frame 0: its velocity × Δt
    goes = np.linalg.norm(xm[1] - xm[0], axis=1).max()
    assert motion > 1e-3 and came > 0.05 * motion and goes > 0.05 * motion


def test_track_shifted_reads_later_and_keeps_what_lies_before():
    t = Track(np.array([0, 2, 6]), np.array([[0.0], [2.0], [10.0]]))
    for k in (0, 1, 2, 3, 8):
        s = t.shifted(k)
        assert s.frames[0] == 0 and np.all(np.diff(s.frames) > 0)
        for f in np.arange(0.0, 9.0, 0.25):
            np.testing.assert_allclose(s.at(f), t.at(f + k), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(t.shifted(2).frames, [0, 4])  # a keyframe at the new 0: kept as is
    still = Track.constant(IDENTITY_POSE, True).shifted(5)
    assert still.frames.tolist() == [0] and np.array_equal(still.values[0], IDENTITY_POSE)


def test_lead_frames_must_be_positive_with_a_moving_start(box_mesh, tmp_path):
    with pytest.raises(RslError, match="--lead-frames should be at least 1 with --start moving"):
        run(SynthConfig(mesh=box_mesh, out=tmp_path / "bad", start="moving", lead_frames=0, **BASE))
    assert not (tmp_path / "bad").exists()
