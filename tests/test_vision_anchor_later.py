"""Rule 5 of stages/vision_anchor.py: once the anchor's material is its own unknown, a later change of material is
still seen (rule 2's candidate against the level since the last change, no test) and limits the lead-in
(AnchorMaterial.lead_from), while the anchor's material itself stays the fit frame's."""
from __future__ import annotations

import numpy as np

from stages.vision_anchor import AnchorMaterial

E0 = 1e5


def _feed(young, truth, change: float = 0.4, window: int = 3):
    """AnchorMaterial fed one E per frame (ν's s = 0) with explains(F, p) = Σ_{t∈F} (log E(p) − log E_true(t))²;
    returns the rule and lead_from after each frame."""
    rule = AnchorMaterial(np.array([np.log(young[0]), 0.0]), np.array([0.15, 0.05]), 0.5, 1, change, window, 0)
    leads = []
    for T, e in enumerate(young):
        tied = T - window + 1 <= 0
        rule.held(T, tied)
        rule.end_frame(T, np.array([np.log(e), 0.0]), tied,
                       lambda F, p: float(sum((p[0] - np.log(truth(t))) ** 2 for t in F)))
        leads.append(rule.lead_from)
    return rule, leads


def _steps(t):
    return E0 * (4.0 if t >= 24 else 2.0 if t >= 12 else 1.0)


# the estimate follows each step within 4 frames (E ×2 at 12, ×4 at 24), with a little wobble while settled
FOLLOWS = ([1.0, 0.98, 1.03, 0.99, 1.01, 1.0, 0.97, 1.02, 1.0, 0.99, 1.01, 1.0]
           + [1.2, 1.45, 1.7, 1.9, 2.0, 2.02, 1.97, 2.0, 2.01, 1.99, 2.0, 2.0]
           + [2.5, 2.9, 3.4, 3.8, 4.0, 4.05, 3.96, 4.0, 4.01, 3.99, 4.0, 4.0])


def test_a_later_step_limits_the_lead_in_and_keeps_the_anchor_at_the_fit_frames_material():
    rule, leads = _feed([E0 * y for y in FOLLOWS], _steps)
    assert rule.apart_from is not None and 12 <= rule.apart_from <= 16, (rule.apart_from, rule.tests)
    assert abs(rule.p[0] - np.log(E0)) < 0.05  # the anchor: the old material (no Adam step is fed here)
    assert len(rule.later) == 1 and 24 <= rule.later[0] <= 28, rule.later  # the ×4 step, seen once
    assert leads[rule.later[0]] == rule.later[0] and leads[-1] == rule.later[0]
    assert all(x == rule.apart_from for x in leads[rule.apart_from:rule.later[0]])
    assert len(rule.tests) == 1  # no test for the later change: the anchor stays apart in any case


def test_no_later_change_while_the_material_stays_after_the_first():
    young = FOLLOWS[:24] + [2.0, 2.03, 1.98, 2.0, 2.02, 1.97, 2.0, 2.01, 1.99, 2.0, 2.0, 2.0]
    rule, leads = _feed([E0 * y for y in young], lambda t: E0 * (2.0 if t >= 12 else 1.0))
    assert rule.apart_from is not None and rule.later == [] and leads[-1] == rule.apart_from


def test_with_anchor_change_zero_no_later_change_is_marked():
    """--anchor-change 0 (p_a its own unknown from the first untied frame, no level): rule 5 is off, so the lead-in
    is limited by nothing but that first frame."""
    rule, leads = _feed([E0 * y for y in FOLLOWS], _steps, change=0.0)
    assert rule.apart_from == 3 and rule.later == [] and set(leads[3:]) == {3}


def test_frames_without_information_stay_out_of_the_level():
    """The dinosaur's case: 10 frames at rest (the pusher still approaching: no step, ``informed`` False) leave the
    initial E, then the estimate converges from 0.5 E_true within 5 frames.  The level is formed from informed frames
    only, so the convergence makes no candidate (with the frames at rest counted, the level was the initial E, and
    the convergence went to a test whose frames carried next to no information)."""
    young = [0.5] * 10 + [0.55, 0.6, 0.85, 0.95, 1.0, 1.02, 0.98, 1.0, 1.01, 0.99, 1.0, 1.0]
    rule = AnchorMaterial(np.array([np.log(0.5 * E0), 0.0]), np.array([0.15, 0.05]), 0.5, 1, 0.4, 3, 0)
    for T, e in enumerate(young):
        tied = T <= 2
        rule.held(T, tied)
        rule.end_frame(T, np.array([np.log(e * E0), 0.0]), tied, lambda F, p: 0.0, informed=T >= 10)
    assert rule.tests == [] and not rule.apart and len(rule.hist) == len(young) - 10
