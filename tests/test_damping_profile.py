"""β estimated by the profile of the fit's cost over β (stages.damping_profile, rsl adapt --damping auto)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from stages.damping_profile import DAMPING_GRID, profile_damping


def _counted(f):
    calls = []

    def cost(b):
        calls.append(b)
        return f(b)
    return cost, calls


@pytest.mark.parametrize("beta_true", [0.0065, 2e-4, 0.07])
def test_a_cost_quadratic_in_log_beta_has_its_minimum_found_exactly(beta_true):
    """c = (log₁₀ β − log₁₀ β*)² + 1: the grid (extended past its edge where β* lies beyond it) brackets β*, and the
    parabola through the lowest point and its neighbours is the cost itself, so its vertex is β*."""
    cost, calls = _counted(lambda b: 50.0 if b == 0 else (math.log10(b / beta_true)) ** 2 + 1.0)
    prof = profile_damping(cost)
    assert prof.beta == pytest.approx(beta_true, rel=1e-9)
    assert not prof.flat
    assert len(calls) == len(set(calls)) <= 1 + len(DAMPING_GRID) + 3  # each β once: 0, the grid, 2 edges, the vertex
    assert [b for b, _ in prof.tried] == calls and prof.tried[0][0] == 0.0


def test_a_cost_lowest_without_damping_gives_zero():
    prof = profile_damping(lambda b: 1.0 + 100 * b)
    assert prof.beta == 0.0 and not prof.flat
    assert prof.within() == pytest.approx((0.0, 10 ** -3.5), rel=1e-9)  # cost ≤ 1.05
    assert prof.within(0.2) == pytest.approx((0.0, 1e-3), rel=1e-9)  # cost ≤ 1.2


def test_a_flat_profile_is_flagged_and_a_failed_beta_counts_as_the_worst():
    rng = np.random.default_rng(0)
    prof = profile_damping(lambda b: 1.0 + 1e-3 * rng.random())
    assert prof.flat
    prof = profile_damping(lambda b: math.inf if b > 0.02 else 1.0 + (math.log10(b) + 2.5) ** 2 if b > 0 else 9.0)
    assert prof.beta == pytest.approx(10 ** -2.5, rel=0.02) and not prof.flat
    assert any(not math.isfinite(c) for _, c in prof.tried)


def test_adapt_estimates_an_undeclared_damping(tmp_path):
    """rsl synth --damping 0.02 --undeclared-damping (the beam pulled by a cable; adapt on the truth's own mesh, the
    mechanism's check — bench/damping.py --auto measures it on foreign truths):
    rsl adapt --damping auto finds β within 25 % of the truth, runs with it (adapt.h5 extras damping and
    damping_profile, the summary says so) and E within 5 %, where β = 0 is off by more."""
    from stages.artefacts import AdaptArtefact
    from stages.progress import SilentReporter
    from stages.steps import adapt, calibrate, synth, tetrahedralize
    from test_adapt_e2e import BEAM, E_TRUE

    if not BEAM.is_file():
        pytest.skip(f"{BEAM} not present")
    cap, ws = tmp_path / "cap", tmp_path / "ws"
    synth.run(synth.SynthConfig(mesh=BEAM, out=cap, scenario="cable", cameras=1, frames=12, resolution=32,
                                markers=30, calib_views=0, seed=0, young=E_TRUE, damping=0.02,
                                undeclared_damping=True))
    toml = cap / "capture.toml"
    toml.write_text(toml.read_text().replace('mesh = "object.obj"', 'mesh = "truth/object.mesh"'))
    tetrahedralize.run(tetrahedralize.TetrahedralizeConfig(capture=cap, workspace=ws, order=1))
    calibrate.run(calibrate.CalibrateConfig(capture=cap, workspace=ws, from_json=str(cap / "cameras.json")))
    base = dict(capture=cap, workspace=ws, loss="markers", window=3, estimator="gn", space="full", substeps=1,
                young_init=0.5 * E_TRUE, damping_frames=10)
    rep = SilentReporter()
    art = AdaptArtefact.load(adapt.run(adapt.AdaptConfig(damping="auto", **base), rep))
    beta = art.extra["damping"]
    assert abs(beta / 0.02 - 1) < 0.25, art.extra["damping_profile"]
    assert art.extra["damping_profile"]["beta"] == beta and not art.extra["damping_profile"]["flat"]
    assert any("estimated from the first 10 frames" in m for m in rep.messages)
    err_auto = np.median(np.abs(art.young[6:, 0] / E_TRUE - 1))
    undamped = AdaptArtefact.load(adapt.run(adapt.AdaptConfig(**base)))
    err_zero = np.median(np.abs(undamped.young[6:, 0] / E_TRUE - 1))
    assert err_auto < 0.05 and err_auto < err_zero, (err_auto, err_zero)


def test_bad_damping_options_end_with_one_sentence(tmp_path):
    from stages.errors import RslError
    from stages.steps import adapt

    cap = tmp_path / "cap"
    with pytest.raises(RslError, match="--damping should be a number of seconds ≥ 0 or auto, found 'soft'"):
        adapt._simulated_damping(adapt.AdaptConfig(capture=cap, workspace=tmp_path, damping="soft"),
                                 type("C", (), {"toml_path": cap / "capture.toml",
                                                "material": type("M", (), {"damping": 0.0})})(), None)


def test_a_subspace_counts_as_viscous_only_with_every_point_or_a_viscous_cubature():
    from stages.steps.adapt import _cubature_viscous

    sub = lambda extra: type("S", (), {"extra": extra})()  # noqa: E731
    assert _cubature_viscous(sub({}))
    assert not _cubature_viscous(sub({"cubature_points": [1, 2]}))
    assert not _cubature_viscous(sub({"cubature_points": [1, 2], "cubature_viscous": False}))
    assert _cubature_viscous(sub({"cubature_points": [1, 2], "cubature_viscous": True}))


def test_the_force_replay_takes_the_damping_adapt_simulated_with():
    """stages.results.material_damping: adapt.h5's recorded β (declared, --damping, or estimated by --damping auto)
    over the capture's; an adapt.h5 older than the record falls back to the capture's."""
    from stages.results import material_damping

    capture = type("C", (), {"material": type("M", (), {"damping": 0.0})})()
    art = lambda extra: type("A", (), {"extra": extra})()  # noqa: E731
    assert material_damping(capture, art({"damping": 0.0068})) == 0.0068
    assert material_damping(capture, art({})) == 0.0
    assert material_damping(None, art({})) == 0.0
