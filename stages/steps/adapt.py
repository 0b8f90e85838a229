"""Stage ``rsl adapt``: online real-to-sim adaptation of E and ν per region (paper §3–4).

Online, at each new frame T_e the window W = T_e−w+1..T_e is re-simulated from the two stored
states before it with the current θ = (E, ν) per region, the window loss L (vision, Eq. 7, or
markers, Eq. 4 windowed) and dL/dX are evaluated, the adjoint over the window turns dL/dX into
dL/dθ (θ shared by the window frames: the per-frame gradients are summed), and a few Adam steps
move the parameters p = (log E, s) with ν = ν_lo + (ν_hi − ν_lo)·sigmoid(s).  The window's
states are then stored; a state is final once its frame leaves the window.

Start convention ([capture] start, docs/capture.md): frame 0 is x_0(θ) — the rest shape, or the static
equilibrium under the frame-0 controls solved with the current θ (stages.sim.static) — with x_{−1} = x_{−2} = x_0;
frame t ≥ 1 is an implicit-Euler step (:class:`StartWindow`), or with ``--substeps S`` S steps of Δt/S, the controls
interpolated at the fractional frames (:class:`Substepped`: what rsl synth --substeps films).  A window that holds frame 0 differentiates through
the static solve.  Observations are anchored at frame 0: markers are bound to the frame-0 surface x_0(θ), and
Gaussians fitted with the mesh at rest to frame f are re-bound to the tets of frame f simulated with the current
θ (``gaussian_anchor = "rebind"``: rendered at x_f they are exactly the fitted Gaussians; the older first-order
``"offset"`` renders at x_t − (x_f − rest)); both anchors are refreshed as θ changes (images with Adam: the
Gaussians' anchor keeps the fit frame's material once the window's E is seen to change, ``--vision-anchor``).
adapt.h5 stores, per frame, θ after that frame's update (and its σ with ``--estimator gn``), the frame's final state (z and positions), the
window loss and the time spent in forward simulation, adjoint / sensitivities, rendering and in total (wall
seconds of the frame's whole update; forward includes re-anchoring the observations, render the image loss and
its gradient through the renderer).  Frames 0..w carry the first calls' compilation (numba at frame 0, JAX for
each new window length and, at frame w, for the first window that starts from stored states): steady per-frame
times are those of frames > w (bench/table1.py, bench/adapt_speed.py).

``--estimator gn`` (stages.estimator) replaces the Adam steps by Gauss–Newton / Levenberg–Marquardt on the
window's residuals (markers, or pixels with Huber IRLS weights) with the forward sensitivities dX/dp
(stages.sim.sensitivity, stages.subspace.sensitivity), an arrival-cost prior with process noise, change-point
detection, a correction of the window's starting states, and E ± σ from the normal matrix (:func:`_online_gn`).
``--mode static`` identifies one θ from the static equilibria of the frames alone (:class:`StaticWindow`).

``--mode offline`` is the baseline of §5.3: one θ for the whole sequence, fitted by the same
machinery (forward over all frames, adjoint over all frames, Adam) for a fixed number of
iterations.  ``--space full`` runs on the full-space FEM (stages/sim), ``--space reduced`` on the
neural subspace (stages/subspace).

What the reported E means: linear tets are too stiff in bending and lock as ν → 0.5, so the E
identified on a mesh is the effective modulus *of that discretisation* — lower than the continuum
value, since the simulation offsets the mesh's extra stiffness.  ``--refine 1`` splits every tet
into eight (full space) and reports the E of the finer discretisation, closer to the continuum
value (bench/adapt.py, case refine: a 192-tet box reported 0.56 E_true, refined 0.88 E_true).
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import scipy.optimize

from stages.artefacts import (KIND_FILES, PARTIAL_ADAPT, AdaptArtefact, MeshArtefact, Provenance, SubspaceArtefact,
                              check_mesh_source, check_same_mesh)
from stages.capture import CaptureError, check_obstacles_clear, load_capture
from stages.damping_profile import FLAT_PROFILE, DampingProfile, profile_damping
from stages.errors import Interrupted, RslError
from stages.estimator import (ChangeDetector, Prior, WindowFilter, condition, gauss_newton, huber_weights, marginal,
                              matched_arrival, posterior_cov, process_noise, robust_cost, weakly_informed)
from stages.interrupt import CheckedReporter, CtrlC
from stages.parameters import Adam, params_from_theta, theta_from_params
from stages.progress import Reporter, SilentReporter
from stages.sim.mesh import rest_quantities
from stages.sim.meshgen import refine_tets  # noqa: F401  (re-exported: stages.steps.adapt.refine_tets)
from stages.vision_anchor import AWAY, AnchorMaterial
from stages.window_model import Observation, WindowBackend
from stages.workspace import prepare_workspace
from stages.window_backends import (FullSpace, Guarded, ReducedSpace, SolveCollapsed, SolveGuard, StoredStates,
                                    substepped)
from stages.moving_start import (image_motion, marker_motion, silhouette_pose, start_basis, start_directions,
                                 start_prior)
from stages.observations import MarkerObservation, VisionObservation
from stages.windows import (STATE_PRIOR_SCALE, GNWindow, StartWindow, StaticWindow, WindowObjective, controls_static,
                            model_error_floors, past_directions, sigma_from_cov, state_directions)



@dataclass(frozen=True)
class AdaptConfig:
    capture: Path
    """Capture folder (capture.toml, frames/, controls.json, markers.csv)."""
    workspace: Path
    """Workspace folder holding mesh.h5 and the other artefacts; adapt.h5 is written there."""
    window: int = 5
    """Sliding-window size w: frames re-simulated and compared at each new frame.  The accuracy bench runs 3 (the paper's); one camera's images of a bar filmed mid-motion read 33.7 / 14.2 / 11.9 / 32.7 % at 3 / 5 / 6 / 12 before the change probes (--change-probe), 14.7 / 17.8 % at 3 / 5 with them (three cameras' bar filmed mid-motion with them 7.6 / 6.1 %); on four rows from equilibrium or rest (three cameras) 3 read as well as 5 with images and better with markers (docs/results/accuracy_window/; accuracy_notes.md, twenty-ninth and thirtieth stops)."""
    space: Literal["reduced", "full"] = "reduced"
    """Simulate in the neural subspace (needs subspace.h5) or in the full FEM space."""
    mode: Literal["online", "offline", "static"] = "online"
    """online: sliding window, θ updated every frame; offline: one θ fitted to the whole sequence; static: one θ
    from the static equilibria of the frames alone (an object at rest under gravity and holds; chosen by itself
    when no control moves and [capture] start = "equilibrium")."""
    loss: Literal["vision", "markers", "silhouette"] = "vision"
    """Observation: rendered Gaussians vs images (needs gaussians.h5, cameras.h5), markers.csv, or silhouette: the
    simulated surface's soft coverage vs masks.h5 (stages/silhouette.py; geometry alone, so frame 0's sag informs E
    too — with one camera from a sagged equilibrium it measured E about as well as the Gaussians, at several times
    the time per frame; filmed mid-motion, frame 0 posed from its masks: the bar with steps of E far better, 2.5,
    4.7 and 4.2 % on three meshes against 25–34 % (12.8 and 29.9 % with --unseen-gaussians ignore on two), the
    dinosaur and the two-region beam worse, 7.4 against 3.4 %, docs/results/accuracy_one_camera/,
    process_noise_one_camera/, unseen_gaussians_one_camera/, accuracy_notes.md, twenty-eighth stop)."""
    cameras: str = ""
    """Cameras used by the vision or silhouette loss: indices or names, comma separated (empty: all)."""
    frames: str = ""
    """Frame range A:B (B exclusive; empty: every frame)."""
    iters_per_frame: int | None = None
    """Adam steps per new frame (online) — each one a forward, a loss and an adjoint over the window; gn: the
    Gauss–Newton iterations per new frame (each one a forward and the window's sensitivities).  Default 2; gn with
    images on a capture filmed mid-motion 6 (bar of bench/accuracy.py, E ×2 ×4: median settled E error 43 % at 2,
    5.8 % at 6, at 2.7 × the time per frame; docs/results/accuracy_notes.md)."""
    lead_in: int = 0
    """adam, online: frames before the window that are simulated with the window's θ (from the stored states
    before them) and differentiated through, but not observed — so the observed frames do not start from a past
    simulated with earlier estimates of θ.  Reduced space: the lead-in costs simulation only, no rendering.  Never
    reaches back past a change of material that the images' anchor saw (stages/vision_anchor.py, rules 3 and 5).
    With a lead-in, images: a window whose frames since frame 0 are all at rest (a pusher still approaching) takes
    no step, and the next window starts from x_0(θ) itself (the rest phase of _online).  Images, reduced space,
    6 substeps, median settled E error, lead-in 3 against 0 (bench/accuracy.py's captures, by hand, 2026-11-24,
    accuracy_notes.md): bar released at rest 6.3 against 14.3 %; bar at equilibrium with E ×2, ×4 steps 27.4
    against 30.3 % (9.1 % with --anchor-change 0.2); the dinosaur (constant E) 28.9 against 13.2 %, E falling to
    0.5 E_true in the free ringing after the pusher has left (not understood) — so 0 stays the default."""
    lr: float = 0.15
    """Adam learning rate on log E."""
    lr_poisson: float = 0.05
    """Adam learning rate on the bounded ν parameter s (ν = ν_lo + (ν_hi − ν_lo)·sigmoid(s))."""
    beta1: float = 0.5
    """Adam's momentum β₁ (lower reacts faster to a changing material and overshoots less)."""
    offline_iters: int = 30
    """Iterations of the offline baseline (each over the whole sequence)."""
    young_init: float | None = None
    """Initial E in Pa for every region (default: capture.toml's material and regions tables)."""
    poisson_init: float | None = None
    """Initial ν for every region (default: capture.toml).  With ν adapted it starts at least 5 % of poisson_range's
    width inside the range (at an end the estimator cannot move it; a warning says so)."""
    fit_poisson: bool = True
    """Adapt ν as well as E (ν stays inside capture.toml's poisson_range)."""
    refine: int = 0
    """Full space only: split every tet into 8 this many times (E of a finer discretisation)."""
    appearance: bool = False
    """Vision loss: also refine Gaussian colours and opacities by the same loss."""
    gaussian_anchor: Literal["rebind", "offset"] = "rebind"
    """Vision loss: how the Gaussians (fitted to the images of their fit frame f with the mesh posed at x_fit,
    gaussians.h5 fit_positions: frame f under the start convention with capture.toml's θ; rest for older files)
    follow the simulation.  rebind: each Gaussian is re-bound to the tet of frame f simulated with the current
    θ that holds it (exact at frame f); offset: rendered at x_t − (x_f − x_fit) (first order in x_f − x_fit)."""
    unseen_gaussians: Literal["ignore", "keep"] = "keep"
    """Vision loss: the pixels painted mostly by Gaussians whose colours fit-gaussians hardly saw — a face hidden
    from its cameras, or seen edge-on, that turns into view: each such Gaussian paints more than 1.5 × the image
    weight it had in the fit, beyond what coming nearer or stretching explains — are left out of the loss, the
    object mask's outline kept (ignore), or compared like the others (keep).  Without --appearance only (which
    refines those colours online instead).  One camera's bar filmed mid-motion, on two meshes: median settled E
    error 33.7 / 32.3 % with keep, 12.8 / 29.9 % with ignore; not the default, as three cameras' bar filmed
    mid-motion went 5.9 → 14.1 % and the test's one-camera 40² beam drifted to 0.89 E_true where keep held 0.95
    (docs/results/unseen_gaussians_one_camera/, unseen_gaussians_three_cameras/, accuracy_notes.md, twenty-seventh
    and twenty-eighth stops)."""
    follow: bool = False
    """Process frames as they appear in the capture folder; Ctrl-C ends with everything saved."""
    follow_timeout: float = 0.0
    """With --follow: stop after this many seconds without a new frame (0: wait until Ctrl-C)."""
    solver: Literal["auto", "cholmod", "splu"] = "auto"
    """Linear solver of the full-space Newton steps (passed to stages.sim)."""
    estimator: Literal["auto", "adam", "gn"] = "auto"
    """adam: a few Adam steps on the window loss per frame; gn: Gauss–Newton / Levenberg–Marquardt on the window
    residuals with an arrival-cost prior and process noise (a moving-horizon filter), reporting E ± σ; auto: gn
    with markers (docs/results/estimator.md: steps followed within w + 5 frames, E ± 2σ calibrated), adam with
    images (measured closer to the truth than gn on images from a far start, docs/results/vision_bias.md), gn on a
    capture filmed mid-motion ([capture] start = "moving": only gn estimates its start)."""
    process_noise: float | None = None
    """gn: σ of the random walk of log E (and of the ν parameter) per frame — how fast the material may change —
    while no change of material has been detected in the last w + 5 frames.  Default 0.005: small, so the estimate
    averages over the motion instead of following the model error, which varies with the motion's phase (two-region
    beam: the 3-frame window's loss minimum in the body moves from below 0.94 to 1.03 E_true at 6 substeps, with or
    without marker noise, docs/results/estimator_window_sweep.md); a step of E is caught by the change test
    (--change-threshold), and --process-noise-change applies after it.  0.03 with images or silhouettes on a
    capture filmed mid-motion, where the change test misses the steps (docs/results/accuracy_notes.md,
    twenty-fifth stop)."""
    process_noise_change: float = 0.02
    """gn: σ of the random walk per frame (as --process-noise) during the w + 5 frames after a detected change of
    material, while the estimate re-settles on the new material (the larger of the two: never less than
    --process-noise's)."""
    state_correction: Literal["states", "past", "off"] = "states"
    """gn: also estimate a correction of the window's two starting states, so the simulated past cannot drift
    from what is observed.  states: every latent coordinate of both states in the reduced space (2r unknowns),
    the 12 lowest vibration modes of both in full space (24 unknowns), each with its own prior (markers; with
    images, where each unknown costs renders, as past); past: along their sensitivities to θ only (the past
    re-simulated with another θ, 2R unknowns); off: kept as stored.  Images, past against off on captures filmed
    mid-motion: three cameras' bar (E steps) 3.3 / 9.4 % and dinosaur 5.4 / 4.7 %, one camera's bar 22.0 / 20.6 %,
    dinosaur 6.3 / 4.3 % and two-region beam (its stiff half started 6× low) 9.5 / 11.6 % and 37.6 / 64.5 %: past
    gains most where the past was simulated far from the truth, and loses up to 2 points elsewhere
    (accuracy_notes.md, thirty-second and thirty-third stops).  A capture filmed mid-motion ([capture] start =
    "moving") has the windows that hold frame 0 estimate its shape and velocity offsets whatever this says
    (stages/moving_start.py, docs/capture.md)."""
    change_threshold: float = 3.0
    """gn: the change-of-material test (a CUSUM of the new frame's innovation z = rᵀr/(mσ²) at the predicted θ, σ the
    noise level the windows reach): a frame whose residual RMS exceeds this many σ, or a smaller excess that
    persists over a few frames, is taken as a change: the window restarts there and the θ prior is widened by
    --change-sigma (0: never).  Images: z against its own baseline only (the median of the earlier z, none before
    three), since their σ follows misfits that grow with the motion; and a window whose data lie more than this
    many σ from the arrival cost has the arrival cost's variance of log E matched to them
    (stages/estimator.py matched_arrival)."""
    change_sigma: float = 0.5
    """gn: σ added to log E when a change of material is detected (0.5: a factor 1.65); ν's prior is kept."""
    change_probe: float = 0.5
    """gn, images and silhouettes: after each window's solve its data cost is probed at log E ± this (0.5: a factor
    1.65, per region), simulated and rendered there; where a probe explains the window better than the estimate by
    more than --change-threshold² in the likelihood ratio 2 [C(θ̂) − C(θ_probe)] / (σ² s²), the material changed
    beyond what the image Jacobian's linear model sees (its minimum a few per cent from the estimate where the
    window's cost is lowest at the new E), and the window is solved again from the probe under the widened prior
    of a detected change (0: no probes)."""
    poisson_information: float = 1.0
    """gn: ν is estimated in a window only while the data of the window before informed it (its information
    marginalised over E and the state correction, from the Gauss–Newton normal matrix) at least this many times as
    much as everything before it (the arrival cost); otherwise it is held at its estimate — a window that cannot
    tell ν from E moves ν with the model error, and E with it (0: always estimated)."""
    state_prior: float = 0.5
    """gn, --state-correction past: prior σ of the correction coefficients (in log E units: the past may look
    as if simulated with E off by this factor's exponent)."""
    substeps: int = 6
    """Implicit-Euler substeps per frame: each frame is S steps of Δt = 1/(fps·S) s, substep k taking the controls
    at the fractional frame t − 1 + k/S and θ of frame t.  One step per frame damps the motion (implicit Euler's
    numerical damping, first order in Δt) and biases E on dynamic captures, most right after a change of the
    material.  On the bar whose E steps, against truths simulated with 3, 12 and 24 substeps per frame, the settled
    median error of E is 4.3–47 % with S = 1, 1.9–12 % with S = 3 and 2.2–3.9 % with S = 6, the default
    (docs/results/time_step.md, which also gives the per-frame time)."""
    damping: str = ""
    """β (s) of the material's viscous damping to simulate with: empty, the capture's ([material] damping, 0 when it
    declares none); a number, that β; auto, estimated from the first --damping-frames frames of the range: the run's
    estimator over them for each β tried, β taken where their loss is lowest with E and ν fitted
    (stages/damping_profile.py; adapt.h5 extras damping, damping_profile).  A capture that rings after a pull and
    declares no β gets a biased E (bar, β_true 3 / 10 ms: −4 / +9 %, docs/results/damping.md).  In the reduced
    space the subspace's cubature must integrate the viscous forces (train-subspace --viscous-cubature on)."""
    damping_frames: int = 12
    """--damping auto: the frames, from the first of the range, that each β tried is run over; the material should
    be constant over them, and they should show the object move."""
    model_error: float | None = None
    """gn: relative σ of E that the discretisation itself adds to the reported E ± σ (σ_E = E √(σ²_logE + e_i²)): the
    error of rsl's mesh, time step and reduced space against the material, which more frames do not average out.
    Default (resolve_model_error; adapt.h5's extra model_error records the value that ran): 0.04 with markers,
    0.08 with images and silhouettes — each the smallest floor of the grid 0.02, 0.03, … that puts the
    truth inside ±2σ on at least 90 % of the settled frames of the accuracy bench's rows with that loss (truths on
    another mesh, element order and time step; markers: full space 94 %, reduced 92 % at 0.04; images and
    silhouettes, one camera and three, gn and Adam's held fits pooled: docs/results/sigma_calibration.md).  With
    several regions, e_i = e √(I_max / I_i) (at most 6 e), I_i the data's information on region i's log E summed
    over the windows so far: a region the data tell weakly carries more of the model's error
    (stages.windows.model_error_floors, region_sweep.md)."""
    model_error_poisson: float = 0.02
    """gn: σ of ν that the discretisation itself adds to the reported ν ± σ (in quadrature; ν is weakly identified
    and absorbs model error, calibrated in docs/results/estimator.md)."""
    gn_trust: float | None = None
    """gn: a frame's (last) Gauss–Newton step of at most this many posterior σ is taken on the quadratic model: the
    window's states and residuals at the new estimate by first order along their sensitivities and Jacobian, not
    simulated and rendered there (one evaluation per frame instead of two; with one substep per frame the next
    window continues these first-order states, with more it simulates its frames again); the next frame's
    linearisation renders that estimate, and when its data cost exceeds the prediction by more than 1 (a 1-σ step
    lowers the cost by ½) that frame's step is tested again; larger steps are always tested (Levenberg–Marquardt).
    0: every step is tested.  Default (resolve_gn_trust; adapt.h5's extra gn_trust records the value that ran): 5
    with images, 0 with markers and silhouettes.  Images, Bar-like case, at the default 2 iterations per frame,
    against 0: E moves by ≤ 0.24 σ_E, gn's wall time per frame 0.93 times adam's instead of 1.03 (docs/results/adapt_speed.md; 10 and 20
    took the very same steps at 2 iterations, by hand); markers, bar with E
    steps (3 substeps per frame, by hand on bench/accuracy.py's capture): up to 3.1 σ_E right after a change,
    ≤ 0.2 σ_E elsewhere, and docs/results/estimator.md's accuracy was measured with 0."""
    vision_anchor: Literal["estimated", "simulated"] = "estimated"
    """adam, images: the material θ_a the Gaussians' anchor x_f (their fit frame f, simulated from the start) is
    simulated with.  estimated: the fit frame's own material — the window's θ until a change of material is seen
    (--anchor-change), then its own unknown that stays at the old material while the window's θ follows the new
    one; simulated: always the window's current θ (wrong once E has changed since f: E collapses).  Cable bar with
    E ×2, ×4 steps, median settled E error: estimated 3.6 % full / 7.9 % reduced, simulated 39 % / 40 %; constant
    E: 5.4 % estimated, 5.7 % simulated (docs/results/vision_bias.md)."""
    anchor_change: float = 0.4
    """adam, images, --vision-anchor estimated: the anchor's material is the window's θ until a change of material
    since the fit frame is confirmed: the window's log E has moved more than half this from its level (the median
    over frames T−6..T−3) in 2 frames in a row, more than this in one of them (0.4 is a factor 1.5), AND that level
    explains the frames after the fit frame better than the window's θ does (both simulated from the start: a
    convergence from a far-off start, which moves E as much, is explained better by the current θ).  From then on
    it is its own unknown, started at that level and moved by the anchor's part of the gradient alone (0: its own
    unknown as soon as the window no longer holds the fit frame, untested).  The rule: stages/vision_anchor.py."""
    anchor_calibration: int = 8
    """adam, images, --vision-anchor estimated: the Gaussians' anchor is calibrated on the first frames (rule 0 of
    stages/vision_anchor.py).  Until this many informed frames (after the fit frame, the object moving) the window
    grows from the first frame, simulated from the start with the anchor tied to θ; at the last of them θ is fitted
    to all of them (L-BFGS-B), the anchor is held at that material for the rest of the sequence, and Adam restarts
    from it.  The material is taken to be constant over these frames.  Why: with an equilibrium start the anchor
    x_f(θ_a) is the sagged frame 0, and an error of θ_a shifts every render by the sag's error, which after a step
    to a stiffer material (its own sag small) E must absorb: --anchor-change's rule left the bar with E ×2, ×4
    steps at 30.3 % median settled error.  bench/accuracy.py's captures, reduced space, median settled E error, 0
    (the rule) → 8, without --recalibrate: bar at equilibrium 30.3 → 4.9 % (the paper's scale: 28.8 → 7.4 %), bar
    released at rest 14.3 → 16.8 %, the dinosaur 13.2 → 13.9 %; 11 measured 6.4 / 5.7 / 10.1 % but ends one frame
    before the bar's first step (a change inside the calibration biases the anchor for good: raise it where the
    material is constant for longer; accuracy_notes.md, eleventh stop).  0: --anchor-change's rule."""
    recalibrate: bool = True
    """adam, images, with --anchor-calibration: each later change of material that the anchor's rule 5 sees (log E
    away from the last fit, 1–4 frames after the change) is located — the frame c that splits the frames since the
    last fit best into the old material and the window's (adapt._locate_change) — and starts a growing window
    again at c: once it holds --anchor-calibration frames log E is fitted to all of them (L-BFGS-B; ν held at the
    first fit's: RECALIBRATION_HOLDS_POISSON), c located again with a fit of each split c ± 1, ... of its own
    (adapt._relocate_with_fits) and Adam restarts from it; the anchor stays at the first frames' material.
    The fits and the located changes are recorded (adapt.h5 extra anchor_calibrations, anchor_change_frames): the
    force replay holds each fit over its segment (stages.forces.calibrated_theta).  A false change costs the fit only
    frames, not bias (the material is the same on both sides).  Why: after a step the sliding window starts from
    states simulated with the lagging estimate and overshoots.  bench/accuracy.py's captures, reduced space, K = 8,
    median settled E error without → with: bar released at rest 16.8 → 5.8 %, bar at equilibrium 4.9 → 5.8 %, the
    dinosaur 13.9 → 13.9 %; the paper's scale (bar at equilibrium) 7.4 → 0.9 % (accuracy.md; accuracy_notes.md,
    eleventh stop)."""
    hold_fit: bool = True
    """adam, images, with --anchor-calibration and --recalibrate (and --anchor-change > 0, rule 5's threshold): from
    each calibration's fit until the next change of material rule 5 sees, E(t) and ν(t) are that fit — a fit to
    every frame since the change, which the sliding window's Adam steps (--lr in log E each, whatever the gradient,
    after Adam's restart), from states simulated with its own lagging estimates, only move away from.  The window
    runs on as rule 5's detector of the next change, from states simulated with the fit (each new frame once more,
    with the fit: what a later change is located against), passing over the w frames after each fit (a restarted
    Adam's first steps, --lr whatever the gradient, look like a change); during a recalibration's growing window E(t)
    is its estimate.  A material that drifts slowly is followed in steps of rule 5's threshold.  --no-hold-fit: E(t)
    is the sliding window's Adam estimate at every frame.  Measured: accuracy_notes.md, thirteenth stop.  A held
    fit reports σ (adapt.h5 young_sigma, poisson_sigma; NaN on the other frames): the Gauss–Newton covariance at the
    fit over its frames, with --model-error's floor (_fit_sigma)."""


def resolve_estimator(config: AdaptConfig, start: str = "") -> str:
    """The estimator an "auto" config runs: gn with markers (docs/results/estimator.md), adam with images
    (docs/results/vision_bias.md) and with silhouettes (one camera, the accuracy bench's bar: 5.7 % against gn's
    8.6 %, accuracy_notes.md, twenty-fourth stop) — except on a capture filmed mid-motion (``start`` "moving"), whose
    start offsets only gn estimates."""
    if config.estimator != "auto":
        return config.estimator
    return "gn" if config.loss == "markers" or start == "moving" else "adam"


ITERATIONS = 2
"""--iters-per-frame's default (AdaptConfig.iters_per_frame)."""
MOVING_IMAGE_ITERATIONS = 6
"""--iters-per-frame's default for gn with images on a capture filmed mid-motion: from a far start gn on images
moves E a little per iteration (auto takes adam for images otherwise), and a moving start leaves gn the only
estimator (AdaptConfig.iters_per_frame)."""


def resolve_iterations(config: AdaptConfig, estimator: str, loss: str, start: str) -> int:
    """The --iters-per-frame a run takes: the config's when given, else MOVING_IMAGE_ITERATIONS for gn with images
    on a moving start and ITERATIONS otherwise."""
    if config.iters_per_frame is not None:
        return int(config.iters_per_frame)
    return MOVING_IMAGE_ITERATIONS if (estimator == "gn" and loss == "vision" and start == "moving") else ITERATIONS


PROCESS_NOISE = 0.005
"""--process-noise's default (AdaptConfig.process_noise)."""
MOVING_IMAGE_PROCESS_NOISE = 0.03
"""--process-noise's default for gn with images or silhouettes on a capture filmed mid-motion: there the change
test does not see the steps of E (one camera's silhouettes: z = 0.78 and 0.42 at the steps), so E follows a step
only as fast as the random walk lets it.  The bar with E steps ×2 ×4 filmed mid-motion, truth converged in time,
reduced space, median settled E error at 0.005 / 0.01 / 0.02 / 0.03: one camera's images 15.6 / 12.9 / 12.5 /
11.4 %, its silhouettes 30.4 / 28.7 / 24.6 / 10.1 %, three cameras' images 19.3 / 17.4 / 9.4 / 4.2 %
(docs/results/accuracy_notes.md, twenty-fifth stop).  On another mesh of that one-camera bar at 0.005 / 0.03 /
0.05 (docs/results/process_noise_one_camera/): images 22.6 / 25.3 / 25.2 %, silhouettes 47.1 / 3.3 / 4.9 % before
they took the matched arrival cost and 2.7 / 2.5 / 2.1 % with it."""


POISSON_START_MARGIN = 0.05
"""ν starts at least this fraction of poisson_range's width inside it (:func:`poisson_start`)."""


def poisson_start(poisson: np.ndarray, poisson_range: tuple, margin: float = POISSON_START_MARGIN) -> np.ndarray:
    """The ν an estimate starts from: ``poisson`` clipped to [ν_lo + m w, ν_hi − m w], w = ν_hi − ν_lo.  ν = ν_lo +
    w·sigmoid(s) has dν/ds = w σ(1 − σ), 1/2500 of its middle value at an end (where params_from_theta clips σ to
    1 − 10⁻⁴), so a ν started there never moved: the bench's bar (markers, reduced) from ν = 0.49, the end of
    [0.3, 0.49], held 0.49 with E 6.7 % off; from 0.48 ν went to 0.407 and E read 2.9 % (from the truth's 0.45:
    0.399 and 3.2 %; accuracy_notes.md, thirty-third stop)."""
    lo, hi = (np.broadcast_to(np.asarray(v, float), np.shape(poisson)) for v in poisson_range)
    inset = margin * (hi - lo)
    return np.clip(np.asarray(poisson, float), lo + inset, hi - inset)


def resolve_process_noise(config: AdaptConfig, estimator: str, loss: str, start: str) -> float:
    """The --process-noise a run takes: the config's when given, else MOVING_IMAGE_PROCESS_NOISE for gn with images
    or silhouettes on a moving start and PROCESS_NOISE otherwise."""
    if config.process_noise is not None:
        return float(config.process_noise)
    moving_images = estimator == "gn" and loss in ("vision", "silhouette") and start == "moving"
    return MOVING_IMAGE_PROCESS_NOISE if moving_images else PROCESS_NOISE


def single_camera_warning(cameras_path: Path, camera: str, moving: bool = False) -> str:
    """The warning of a run on one camera's images (the Gaussians): its E is measured less well than from several
    (docs/results/accuracy_one_camera/: the accuracy bench's image rows filmed by one camera); filmed mid-motion
    (``moving``), the Gaussians follow the bar's steps of E since the change probes, the silhouettes measured them
    better before, the Gaussians the dinosaur and the beam."""
    text = (f"{cameras_path}: the images come from one camera ({camera}); on the accuracy bench one camera's images "
            f"left E several times further from the truth than three cameras' on the same bar captures, most of all "
            f"on one filmed mid-motion (docs/results/accuracy_one_camera/accuracy.md): a second camera or "
            f"markers (--loss markers) measure E better.")
    if moving:
        text += (" This capture is filmed mid-motion: there one camera's Gaussians read the bench's bar 14.7–22.0 % "
                 "off with the change probes (--change-probe), its silhouettes (--loss silhouette) 2.5–10.2 % but the "
                 "dinosaur and the two-region beam worse, at about 4 times the time per frame; --unseen-gaussians "
                 "ignore and --window 3 (the default is 5) read better on some meshes and worse on others: compare them "
                 "on your capture (docs/results/accuracy_notes.md, twenty-sixth to thirty-third stops).")
    return text


GN_TRUST_IMAGES = 5.0
"""--gn-trust's default with images (docs/results/adapt_speed.md, rows "1-eval")."""


MODEL_ERROR_MARKERS = 0.04
"""--model-error's default with markers (docs/results/sigma_calibration.md, the markers rows)."""
MODEL_ERROR_IMAGES = 0.08
"""--model-error's default with images and silhouettes (docs/results/sigma_calibration.md, their rows pooled)."""


def resolve_model_error(config: AdaptConfig, obs_kind: str) -> float:
    """The --model-error a run takes: the config's when given, else MODEL_ERROR_MARKERS with markers and
    MODEL_ERROR_IMAGES with images and silhouettes (AdaptConfig.model_error)."""
    if config.model_error is not None:
        return float(config.model_error)
    return MODEL_ERROR_MARKERS if obs_kind == "markers" else MODEL_ERROR_IMAGES


def resolve_gn_trust(config: AdaptConfig, obs_kind: str) -> float:
    """The --gn-trust a run takes: the config's when given, else GN_TRUST_IMAGES with images (obs_kind "vision")
    and 0 (every step tested) with markers and silhouettes (AdaptConfig.gn_trust)."""
    if config.gn_trust is not None:
        return float(config.gn_trust)
    return GN_TRUST_IMAGES if obs_kind == "vision" else 0.0




def _holds_fit(config: AdaptConfig) -> bool:
    """--hold-fit in force: E(t) held at each calibration fit, where rule 5 can see the next change and refit
    (--recalibrate, --anchor-change > 0)."""
    return config.hold_fit and config.recalibrate and config.anchor_change > 0


# =========================================================================== mesh refinement
def _refined_mesh(mesh: MeshArtefact, levels: int) -> MeshArtefact:
    v, t, reg = mesh.vertices, mesh.tets, mesh.tet_region
    for _ in range(levels):
        v, t, reg = refine_tets(v, t, reg)
    vol, dm_inv, masses = rest_quantities(v, t, mesh.density)
    return dataclasses.replace(mesh, vertices=v, tets=t, tet_region=reg, rest_volumes=vol, dm_inv=dm_inv,
                               vertex_masses=masses, handles={})


# =========================================================================== the stage
@dataclass
class _Record:
    frames: list = dataclasses.field(default_factory=list)
    young: list = dataclasses.field(default_factory=list)
    poisson: list = dataclasses.field(default_factory=list)
    loss: list = dataclasses.field(default_factory=list)
    frame_loss: list = dataclasses.field(default_factory=list)
    t_fwd: list = dataclasses.field(default_factory=list)
    t_bwd: list = dataclasses.field(default_factory=list)
    t_ren: list = dataclasses.field(default_factory=list)
    t_tot: list = dataclasses.field(default_factory=list)
    young_sigma: list = dataclasses.field(default_factory=list)
    poisson_sigma: list = dataclasses.field(default_factory=list)
    model_error: list = dataclasses.field(default_factory=list)  # gn: per frame, the relative floor e_i of σ_E (R,)

    def add(self, frame: int, young, poisson, loss: float, frame_loss: float, times: tuple[float, float, float],
            total_s: float, young_sigma=None, poisson_sigma=None) -> None:
        """One frame's row: θ after its update, the window loss, the loss of the frame itself, the seconds spent in
        (forward, adjoint/sensitivities, render) and in total, and E/ν σ (Gauss–Newton only)."""
        self.frames.append(frame)
        self.young.append(young)
        self.poisson.append(poisson)
        self.loss.append(float(loss))
        self.frame_loss.append(float(frame_loss))
        self.t_fwd.append(times[0])
        self.t_bwd.append(times[1])
        self.t_ren.append(times[2])
        self.t_tot.append(total_s)
        if young_sigma is not None:
            self.young_sigma.append(young_sigma)
            self.poisson_sigma.append(poisson_sigma)


@dataclass
class _Loop:
    """What the frame loops share: the settings, the observation, the simulation backend and window objective,
    the stored states (frame -> state) and the record they fill, the frame range [first, last) (last None: follow)."""
    config: AdaptConfig
    obs: Observation
    backend: WindowBackend
    objective: WindowObjective
    stored: dict
    rec: _Record
    prange: tuple
    young_range: tuple
    first: int
    last: int | None
    reporter: Reporter
    moving: object = None  # start = "moving": its offsets' directions (stages.moving_start.StartBasis), else None
    damping: float = 0.0  # β s of the material's viscous damping (capture.toml [material] damping)

    def before_keys(self, t0: int) -> tuple[int, int]:
        """The stored frames whose states a window starting at frame t0 starts from: (t0 − 2, t0 − 1), frame 0 for
        one before it (x_{−1} = x_0, the start convention) — except with a moving start, whose x_{−1} is estimated
        (stored as frame −1)."""
        return (max(t0 - 2, -1 if self.moving is not None else 0), max(t0 - 1, 0))

    def before(self, t0: int) -> np.ndarray:
        """The two stored states a window starting at frame t0 starts from (:meth:`before_keys`); a window holding
        frame 0 ignores them, except with a moving start, whose offsets (Δ_{−1}, Δ_0) it takes: zero, estimated
        anew by each such window (StartWindow)."""
        if self.moving is not None and t0 == 0:
            return np.zeros((2,) + np.shape(self.backend.rest_state))
        return np.stack([self.stored[t] if t in self.stored else self.backend.rest_state
                         for t in self.before_keys(t0)])

    def online_frames(self):
        """The frames of an online run, in order; with --follow it waits for each (and ends after
        --follow-timeout without one)."""
        T = self.first
        while self.last is None or T < self.last:
            if self.config.follow and not _wait_for(self.obs, T, self.config.follow_timeout, reporter=self.reporter):
                return
            yield T
            T += 1

    def total(self) -> int | None:
        return None if self.last is None else self.last - self.first


def _parse_frames(spec: str, n_avail: int | None, where: Path) -> tuple[int, int | None]:
    if not spec.strip():
        return 0, n_avail
    try:
        a_s, b_s = spec.split(":")
        a = int(a_s) if a_s.strip() else 0
        b = int(b_s) if b_s.strip() else n_avail
    except ValueError:
        raise RslError(f"{where}: --frames should be A:B (e.g. 0:60), found '{spec}'.") from None
    if a < 0 or (b is not None and b <= a):
        raise RslError(f"{where}: --frames {spec} is an empty or negative range.")
    if n_avail is not None and b is not None and b > n_avail:
        raise RslError(f"{where}: --frames {spec} asks for frames up to {b - 1} but only {n_avail} exist.")
    return a, b


def run(config: AdaptConfig, reporter: Reporter = SilentReporter()) -> Path:
    """Adapt θ = (E, ν) per region to the capture; writes WS/adapt.h5."""
    if config.loss != "vision":
        return _run(config, reporter)
    from stages.render.gaussians import one_torch_thread

    with one_torch_thread():  # torch's pool only spins against the rasterizer's threads (20× per render under load)
        return _run(config, reporter)


def _run(config: AdaptConfig, reporter: Reporter) -> Path:
    """--damping auto: β estimated first (:func:`_estimate_damping`), then the run with it."""
    if config.damping.strip().lower() != "auto":
        return _adapt(config, reporter)
    return _adapt(config, reporter, _estimate_damping(config, reporter))


def _estimate_damping(config: AdaptConfig, reporter: Reporter) -> DampingProfile:
    """β by the profile of the run's loss over β (stages.damping_profile): for each β tried, the run's estimator
    over the first --damping-frames frames of its range, nothing written, cost = :func:`_profile_cost`."""
    where = load_capture(config.capture).toml_path
    if config.follow:
        raise RslError(f"{where}: --damping auto needs the first {config.damping_frames} frames before the run "
                       f"starts; give β as a number with --follow.")
    if config.damping_frames < 2:
        raise RslError(f"{where}: --damping-frames must be at least 2, found {config.damping_frames}.")
    prepare_workspace(Path(config.workspace))
    sub_path = Path(config.workspace) / KIND_FILES["subspace"]
    if config.space != "full" and sub_path.exists() and not _cubature_viscous(SubspaceArtefact.load(sub_path)):
        raise RslError(f"{sub_path}: its cubature was fitted to elastic forces only, so a run with damping would "
                       f"integrate the viscous forces with elastic weights and bias β and E; run rsl train-subspace "
                       f"--viscous-cubature on before --damping auto.")
    with reporter.task("estimating the viscous damping β", None) as task:
        def cost(beta: float) -> float:
            try:
                return _adapt(dataclasses.replace(config, damping=repr(beta)), SilentReporter(),
                              profile_frames=config.damping_frames)
            except (SolveCollapsed, RslError):  # a β whose run fails explains the frames worst
                return math.inf

        prof = profile_damping(cost, on_try=lambda b, c: task.advance(1, beta=f"{b:.3g} s", cost=f"{c:.4g}"))
    tried = ", ".join(f"{b:.3g} s: {c:.3g}" for b, c in sorted(prof.tried))
    if prof.flat:
        reporter.warn(f"{where}: the first {config.damping_frames} frames do not determine the damping (the loss "
                      f"over β varies by less than {FLAT_PROFILE:.0%}: {tried}); simulating with β = "
                      f"{prof.beta:.3g} s, their lowest.")
    else:
        lo, hi = prof.within()
        reporter.info(f"viscous damping β = {prof.beta:.3g} s estimated from the first {config.damping_frames} "
                      f"frames (the loss within {FLAT_PROFILE:.0%} of its lowest for β {lo:.3g}–{hi:.3g} s; with E, ν "
                      f"fitted, per β: {tried})")
    return prof


def _cubature_viscous(sub: SubspaceArtefact) -> bool:
    """Whether a subspace's energy integrates the viscous term rightly: every point (no cubature), or a cubature
    fitted to the viscous forces too (train-subspace --viscous-cubature)."""
    extra = sub.extra or {}
    return "cubature_points" not in extra or bool(extra.get("cubature_viscous", False))


def _profile_cost(rec: "_Record", window: int) -> float:
    """--damping auto's cost of one β: the mean loss of each window's newest frame at the window's estimate, over
    the frames from the window's length on (all when fewer)."""
    fl = np.asarray(rec.frame_loss, float)
    return float(np.mean(fl[window:] if len(fl) > window else fl)) if len(fl) else math.inf


def _simulated_damping(config: AdaptConfig, capture, profile: DampingProfile | None) -> float:
    """β (s) the run simulates with (AdaptConfig.damping)."""
    if profile is not None:
        return profile.beta
    spec = config.damping.strip()
    if not spec:
        return float(capture.material.damping)
    try:
        beta = float(spec)
    except ValueError:
        beta = math.nan
    if not (math.isfinite(beta) and beta >= 0):
        raise RslError(f"{capture.toml_path}: --damping should be a number of seconds ≥ 0 or auto, found '{spec}'.")
    return beta


def _adapt(config: AdaptConfig, reporter: Reporter, damping_profile: DampingProfile | None = None,
           profile_frames: int | None = None) -> Path | float:
    """The run; writes WS/adapt.h5 and returns its path.  ``profile_frames``: one evaluation of --damping auto's
    profile instead — the first this many frames of the range, nothing written, returns :func:`_profile_cost`."""
    from stages.sim.scene import frame_inputs, make_scene

    ws = Path(config.workspace)
    capture = load_capture(config.capture)
    prepare_workspace(ws)  # writable? (checked before any compute) and no stale temp files
    damping = _simulated_damping(config, capture, damping_profile)
    if not (isinstance(config.substeps, int) and config.substeps >= 1):
        raise RslError(f"{capture.toml_path}: --substeps must be a whole number of at least 1, found "
                       f"{config.substeps}.")
    if config.window < 1:
        raise RslError(f"{capture.toml_path}: --window must be at least 1, found {config.window}.")
    if config.estimator not in ("auto", "adam", "gn"):
        raise RslError(f"{capture.toml_path}: --estimator should be auto, adam or gn, found '{config.estimator}'.")
    estimator = resolve_estimator(config, capture.start)
    if not ((config.process_noise is None or config.process_noise >= 0) and config.process_noise_change >= 0):
        raise RslError(f"{capture.toml_path}: --process-noise and --process-noise-change must be 0 or more, found "
                       f"{config.process_noise} and {config.process_noise_change}.")
    if config.gn_trust is not None and not config.gn_trust >= 0:
        raise RslError(f"{capture.toml_path}: --gn-trust must be 0 or more, found {config.gn_trust}.")
    if config.lead_in < 0:
        raise RslError(f"{capture.toml_path}: --lead-in must be 0 or more, found {config.lead_in}.")
    if config.lead_in and (estimator != "adam" or config.mode != "online"):
        raise RslError(f"{capture.toml_path}: --lead-in applies to --estimator adam online (gn corrects the "
                       f"window's starting states itself, --state-correction); this run is {estimator} "
                       f"{config.mode}.")
    if (config.iters_per_frame is not None and config.iters_per_frame < 1) or config.offline_iters < 1:
        raise RslError(f"{capture.toml_path}: --iters-per-frame and --offline-iters must be at least 1.")
    if capture.start == "moving" and (estimator != "gn" or config.mode != "online"):
        raise RslError(f"{capture.toml_path}: start = \"moving\" needs --estimator gn --mode online (its windows "
                       f"estimate the states before frame 0 together with E and ν); this run is {estimator} "
                       f"{config.mode}.")
    if config.refine and config.space != "full":
        raise RslError(f"{ws / KIND_FILES['subspace']}: --refine needs --space full (the subspace is "
                       f"trained on mesh.h5's vertices).")
    mesh_path = ws / KIND_FILES["mesh"]
    mesh = MeshArtefact.load(mesh_path)
    check_mesh_source(mesh_path, capture.mesh_path)
    controls = capture.controls()
    check_obstacles_clear(controls, mesh.vertices, capture.controls_path, start=capture.start)
    sim_mesh = _refined_mesh(mesh, config.refine) if config.refine else mesh
    scene = make_scene(sim_mesh, controls, capture.material.model, capture.dt, capture.gravity, damping=damping)
    n = mesh.n_vertices
    inputs_cache: dict[int, object] = {}

    def inputs(t: int):
        if t not in inputs_cache:
            inputs_cache[t] = frame_inputs(scene, controls, t)
        return inputs_cache[t]

    inputs_used = [mesh_path, capture.toml_path, capture.controls_path]
    if config.space == "full":
        backend = FullSpace(scene, inputs, config.solver)
    else:
        from stages.subspace import ReducedModel

        sub_path = ws / KIND_FILES["subspace"]
        check_same_mesh(mesh_path, sub_path)
        sub_art = SubspaceArtefact.load(sub_path)
        if damping > 0 and not _cubature_viscous(sub_art):
            reporter.warn(f"{sub_path}: its cubature was fitted to elastic forces only, so the viscous forces of "
                          f"β = {damping:g} s are integrated with elastic weights (7.6 % off on the bar); run rsl "
                          f"train-subspace --viscous-cubature on.")
        backend = ReducedSpace(ReducedModel.from_artefacts(sub_art, scene), inputs)
        inputs_used.append(sub_path)

    R = scene.n_regions
    names = list(scene.region_names)
    mat = capture.material
    young0 = np.array([config.young_init or mat.region_young(r) for r in names], float)
    if config.young_init is not None and not mat.young_range[0] <= config.young_init <= mat.young_range[1]:
        raise RslError(f"{capture.toml_path}: --young-init {config.young_init:g} Pa lies outside [material] "
                       f"young_range {list(mat.young_range)}; give a value inside it or widen the range.")
    backend = substepped(backend, config.substeps, lambda f: frame_inputs(scene, controls, f))  # --substeps
    backend = Guarded(backend, SolveGuard(sim_mesh.vertices, sim_mesh.tets, names, capture.toml_path, mat.young))
    poisson0 = np.array([config.poisson_init if config.poisson_init is not None else mat.region_poisson(r)
                         for r in names], float)
    if config.fit_poisson:
        if config.poisson_init is not None and not mat.poisson_range[0] <= config.poisson_init <= mat.poisson_range[1]:
            raise RslError(f"{capture.toml_path}: --poisson-init {config.poisson_init} lies outside "
                           f"poisson_range {list(mat.poisson_range)}.")
        start = poisson_start(poisson0, mat.poisson_range)
        if not np.array_equal(start, poisson0):
            reporter.warn(f"{capture.toml_path}: ν starts at {', '.join(f'{v:.4g}' for v in start)} instead of "
                          f"{', '.join(f'{v:.4g}' for v in poisson0)}: at an end of poisson_range "
                          f"{list(mat.poisson_range)} the estimator cannot move ν (the slope of its sigmoid vanishes "
                          f"there); widen poisson_range to start at that value, or hold ν there with --fixed-poisson.")
        poisson0 = start
    moving = None  # start = "moving": the directions of frame 0's estimated offsets (stages/moving_start.py)
    if config.loss == "markers":
        # Markers bind to the simulated frame-0 surface; the binding is refreshed as θ changes
        # (frame 0 is x_0(θ): with start = "equilibrium" or "moving" it depends on θ).
        s0 = StartWindow(backend, capture.start).forward([0], young0, poisson0, None)[0]
        obs = MarkerObservation(capture, backend.decode(s0[None])[0], mesh.surface_faces, n)
        inputs_used.append(capture.markers_path)
        if capture.start == "moving":
            moving = start_basis(backend, s0, young0, poisson0)
        if capture.start != "moving":  # (a moving start: once frame 0 is estimated, _online_gn)
            _warn_far_markers(reporter, obs, "simulated with the initial E")
    elif config.loss == "silhouette" or (
            not (ws / KIND_FILES["gaussians"]).exists() and config.mode in ("online", "static") and not config.follow
            and capture.start == "equilibrium" and controls_static(inputs, list(range(max(capture.frame_count(), 1))))):
        # --loss silhouette, or a still capture with images (compared through its silhouettes alone, below): no
        # Gaussians needed
        from stages.silhouette import SilhouetteObservation

        obs = SilhouetteObservation(capture, ws, config.cameras, mesh)
        inputs_used += [ws / KIND_FILES[k] for k in ("cameras", "masks")]
        if capture.start == "moving":
            # a moving start: frame 0 posed from its own masks, as fit-gaussians poses it for the Gaussians
            # (stages.moving_start.silhouette_pose; the sag's first guess is the initial E — --young-init when given,
            # where fit-gaussians takes capture.toml's); the windows
            # holding frame 0 add their estimated offsets to that pose, which frame 0's masks then inform directly
            moving_reference = _pose_state(backend, _silhouette_start_pose(capture, ws, mesh, young0, poisson0))
            moving = start_basis(backend, moving_reference, young0, poisson0)
    else:
        check_same_mesh(mesh_path, ws / KIND_FILES["gaussians"])
        obs = VisionObservation(capture, ws, config.cameras, mesh, config.appearance, config.gaussian_anchor,
                                config.unseen_gaussians)
        inputs_used += [ws / KIND_FILES[k] for k in ("cameras", "gaussians", "masks")]
        inputs_used += [capture.root / "frames" / c if src.files is not None else src.video
                        for c, src in obs.sources.items()]  # the frames read (a hash per camera)
        if len(obs.cameras) == 1:
            reporter.warn(single_camera_warning(ws / KIND_FILES["cameras"], obs.cameras[0],
                                                capture.start == "moving"))
        if capture.start == "moving":
            if obs.fit_frame != 0:
                raise RslError(f"{ws / KIND_FILES['gaussians']}: the Gaussians were fitted to frame {obs.fit_frame}, "
                               f"but with start = \"moving\" rsl estimates frame 0 alone; fit them to frame 0 "
                               f"(rsl fit-gaussians --frame 0).")
            moving_reference = _pose_state(backend, obs.rest)
            moving = start_basis(backend, moving_reference, young0, poisson0)

    prange = mat.poisson_range
    if not config.fit_poisson:  # ν held at its initial value, per region
        prange = (poisson0.copy(), poisson0.copy())
    if np.any(young0 <= 0):
        raise RslError(f"{capture.toml_path}: the initial Young's modulus must be positive.")
    log_e, s_nu = params_from_theta(young0, np.clip(poisson0, *prange), prange)

    n_avail = None if config.follow else (obs.count_checked() if hasattr(obs, "count_checked") else obs.available())
    if n_avail == 0:
        raise CaptureError(f"{capture.root}: holds no frame to adapt to.")
    first, last = _parse_frames(config.frames, n_avail, capture.toml_path)
    if profile_frames is not None:
        last = first + profile_frames if last is None else min(last, first + profile_frames)
    rec = _Record()
    # frame -> latest state (positions or z); with --substeps it tells the backend which state a frame holds
    stored: dict[int, np.ndarray] = StoredStates(backend) if config.substeps > 1 else {}
    t_start = time.perf_counter()
    interrupted = False
    status = "failed"
    failure: BaseException | None = None

    if moving is not None and first > 0:
        raise RslError(f"{capture.toml_path}: start = \"moving\" needs the frame range to start at frame 0 "
                       f"(--frames {first}:…): the state before frame 0 is estimated from the first frames.")
    # Frames before the range: a plain forward simulation with the initial θ.
    if first > 0:
        with reporter.task("simulating frames before the range", None):
            X0 = StartWindow(backend, capture.start).forward(list(range(first)), young0,
                                                             theta_from_params(log_e, s_nu, prange)[1], None)
        for t in range(first):
            stored[t] = X0[t]

    lr = np.concatenate([np.full(R, config.lr), np.full(R, config.lr_poisson if config.fit_poisson else 0.0)])
    adam = Adam(lr, beta1=config.beta1)
    params = np.concatenate([log_e, s_nu])

    objective = WindowObjective(backend, obs, R, prange, capture.start)
    if moving is not None and config.loss != "markers":
        # a moving start with images: frame 0 = x_f + Δ_0, x_{−1} = x_f + Δ_{−1} with x_f the state the Gaussians
        # were fitted at (which frame 0's images confirmed), not x_e(θ); the Gaussians stay bound as fitted, so
        # frame 0's render informs Δ_0 as frame 0's markers do (docs/capture.md)
        objective.win.reference = moving_reference
        objective.rebind = False
        if config.loss == "vision":
            obs.rebind(obs.rest)
    if config.vision_anchor not in ("estimated", "simulated"):
        raise RslError(f"{capture.toml_path}: --vision-anchor should be estimated or simulated, found "
                       f"'{config.vision_anchor}'.")
    if not config.anchor_change >= 0:
        raise RslError(f"{capture.toml_path}: --anchor-change must be 0 or more, found {config.anchor_change}.")
    # the anchor's own material (online Adam with images; gn holds the anchor after a detected change instead)
    # (silhouettes: the same calibrations and held fits; nothing is bound, so the anchor's own gradient is zero)
    objective.anchor_own = (config.loss in ("vision", "silhouette") and config.vision_anchor == "estimated"
                            and estimator == "adam")
    if (config.mode == "online" and not config.follow and capture.start == "equilibrium" and last is not None
            and last - first >= 1 and controls_static(inputs, list(range(first, last)))):
        reporter.info(f"{capture.controls_path}: no control moves over frames {first}..{last - 1}: identifying the "
                      f"material from the static equilibria (--mode static).")
        config = dataclasses.replace(config, mode="static")
    if config.mode == "static":
        if last is None:
            raise RslError(f"{capture.toml_path}: --mode static needs a finite frame range (not --follow without "
                           f"--frames).")
        objective.win = StaticWindow(backend)
        if config.loss in ("vision", "silhouette") and controls_static(inputs, list(range(first, last))):
            # every frame is the fit frame's equilibrium, and the Gaussians re-bound to x_0(θ) render it alike
            # for every θ (docs/tutorial.md, "Static captures"): the images are compared through their masks
            # instead, with the soft coverage of the simulated surface (stages/silhouette.py), by Gauss–Newton
            from stages.silhouette import SilhouetteObservation

            if not isinstance(obs, SilhouetteObservation):
                obs = SilhouetteObservation(capture, ws, config.cameras, mesh)
            objective.obs, objective.rebind, objective.anchor_frame = obs, False, 0
            if config.estimator == "auto":
                config = dataclasses.replace(config, estimator="gn")
                estimator = "gn"
            reporter.info(f"{capture.controls_path}: no control moves, so the Gaussians (fitted to this very "
                          f"equilibrium) cannot tell E: images are compared through their silhouettes, the "
                          f"simulated surface's coverage against masks.h5 ({estimator}).")
        if config.loss == "markers":  # the markers bind to the frame-0 equilibrium
            obs.rebind(backend.decode(objective.win.forward([0], young0, poisson0)[0][None])[0])

    # Ctrl-C raises KeyboardInterrupt at once as usual, but is also counted (stages/interrupt.py): one that
    # compiled code lost ends the loop when the frame is recorded (the progress step), and none can abort the save
    ctrl_c = CtrlC()
    loop = _Loop(config, obs, backend, objective, stored, rec, prange, mat.young_range, first, last,
                 CheckedReporter(reporter, ctrl_c), moving, damping)
    rec.damping_profile = damping_profile  # --damping auto's search (None: β given)
    late = getattr(obs, "late", None)
    if config.mode != "online" and late is not None and late.any():
        reporter.warn(f"{capture.markers_path}: {int(late.sum())} marker(s) are first seen after frame 0; --mode "
                      f"{config.mode} binds markers at frame 0 only, so they are left out (--mode online binds each "
                      f"to its track once a window sees it).")
    if profile_frames is not None:  # one β of --damping auto's profile: nothing is written
        _estimate(loop, estimator, log_e, s_nu, params, adam)
        return _profile_cost(rec, config.window)
    try:
        ctrl_c.install()
        if config.mode != "online" and last is None:
            raise RslError(f"{capture.toml_path}: --mode {config.mode} needs a finite frame range (not --follow "
                           f"without --frames).")
        _estimate(loop, estimator, log_e, s_nu, params, adam)
        status = "complete"
    except KeyboardInterrupt:
        # With --follow, Ctrl-C is the way to end: the frames so far are the complete result.
        interrupted, status = True, ("complete" if config.follow else "interrupted")
    except Exception as e:
        if ctrl_c.pressed:  # after a Ctrl-C an error is its doing (numba turns a KeyboardInterrupt into SystemError)
            interrupted, status = True, ("complete" if config.follow else "interrupted")
        elif isinstance(e, RslError):
            failure = e
        else:
            raise
    finally:
        ctrl_c.defer = True  # first: from here a Ctrl-C is only counted, it cannot abort the save
        # Whatever ends the loop (the last frame, Ctrl-C, a failed solve), the frames so far are saved
        # (atomically); extra["status"] says which.  Only a complete run writes adapt.h5: an interrupted or
        # failed one goes to adapt.partial.h5 and the previous adapt.h5 stays as it was.
        try:
            _trim_record(rec)
            if rec.frames:
                path = _save(loop, ws, mesh, names, inputs_used, status, time.perf_counter() - t_start,
                             ended_by_ctrl_c=interrupted)
        finally:
            ctrl_c.restore()
    final = ws / KIND_FILES["adapt"]
    unchanged = f"{final.name} is unchanged" if final.exists() else f"no {final.name} was written"
    if failure is not None:
        kept = (f"the {len(rec.frames)} frame(s) done are kept in {path.name}, {unchanged}" if rec.frames
                else unchanged)
        raise type(failure)(f"{str(failure).rstrip('.')} ({kept}).") from None
    if not rec.frames:
        if interrupted:
            raise Interrupted(f"no frame was finished; {unchanged}.")
        raise RslError(f"{capture.root}: no frame was processed (none arrived within --follow-timeout).")
    if interrupted and not config.follow:
        raise Interrupted(f"the {len(rec.frames)} frame(s) done are kept in {path}; {unchanged}.")
    _report(loop, reporter, names, 3 * len(scene.rest), mesh, path, interrupted)
    return path


REST_TOL = 1e-6
"""adam, online: a window is *at rest* when every state it simulates from x_0(θ) lies within this fraction of the
object's size (its bounding-box diagonal) of x_0(θ) — 1e-6 is 1e-4 pixel at 96 px on a 0.2 m object, far below any
motion the images show and far above the solves' round-off (an object at its equilibrium stays there exactly)."""


def _at_rest(backend, states: np.ndarray) -> bool:
    """Whether the decoded states (k, …) all lie within REST_TOL × the size of the first of them."""
    X = backend.decode(states)
    size = float(np.linalg.norm(np.ptp(X[0], axis=0)))
    return bool(np.max(np.abs(X - X[0])) <= REST_TOL * size)


def _online(loop: _Loop, params: np.ndarray, adam: Adam) -> None:
    """Online Adam: per new frame T, ``--iters-per-frame`` Adam steps on the window T−w+1..T's loss L(p).

    Images, ``--vision-anchor estimated``: the Gaussians' anchor x_f(θ_a) is simulated with the material of their
    fit frame f, p_a (:class:`stages.vision_anchor.AnchorMaterial`, which gives the rule): the window's p (and dL/dp
    carries the anchor's part) until a change of material is confirmed — the window's log E has moved more than
    ``--anchor-change`` from its level, and the level explains the frames after f better than the current p does
    (a convergence from a far-off start explains them better with the current p) — then its own unknown, moved by
    Adam along the anchor's part of the gradient alone.

    The rest phase (with ``--lead-in`` > 0).  While the simulated object has not moved since frame 0 (no control
    has reached it yet: a pusher still approaching, an equilibrium start), frames 0..T are *at rest*: x_t = x_0(θ)
    for every θ.  A window whose states before it are at rest starts from x_0(θ) itself (frame 0, the static solve,
    differentiated, then its frames from (x_0, x_0)) instead of from stored states, which hold x_0 of the θ of their
    time and would make the object start to move as soon as θ changes.  A window at rest, fit frame included (a window holding only
    frame f too), has no information on θ — the re-bound Gaussians render the fitted ones for every θ, dL/dθ = 0 up
    to round-off — and takes no step (Adam would turn the round-off into a full step)."""
    config, rec, R, obj = loop.config, loop.rec, loop.objective.R, loop.objective
    w = config.window
    vision = loop.obs.kind == "vision"
    anchor = None
    if obj.anchor_own:
        anchor = AnchorMaterial(params, adam.lr, config.beta1, R, config.anchor_change, w, obj.anchor_frame,
                                loop.first)
        obj.want_anchor_grad = True
        rec.anchor_young, rec.anchor_tests = [], anchor.tests
        rec.calibrations = []  # per calibration fit: {"frames": [first, last], "young": (R,), "poisson": (R,)}
        rec.change_frames = []  # the located first frame of each later change of material (--recalibrate)
        rec.window_young = []  # per frame, the window's own E (young holds the fit between changes: --hold-fit)
    f = obj.anchor_frame
    rest_until = -1  # frames 0..rest_until were at rest (simulated from x_0(θ)); −1: none known (a range from A > 0)
    # the rest phase comes with the lead-in (both re-simulate the window's past with its θ); without one, the
    # dinosaur's row measured worse with it (20.7 against 13.2 %, accuracy_notes.md, tenth stop): off by default
    rest_rule = vision and config.lead_in > 0
    # the anchor's calibration: until K informed frames, the window grows from the first frame (anchor tied)
    calibrating = anchor is not None and config.anchor_calibration > 0
    informed = 0  # frames whose window informed θ (it took a step) while calibrating
    calib_from = loop.first  # the growing window's first frame (after a later change: the frame it began)
    seen_later = 0  # the later changes (rule 5) already recalibrated for
    change_lo = loop.first + 1  # the earliest frame a later change may be located at (after the last calibration)
    holding = calibrating and _holds_fit(config)  # E(t) held at the last fit between changes
    fit_sigma = None  # with holding: (σ_E, σ_ν, floors) of the last fit (_fit_sigma)
    calib_p = None  # the last calibration's fit (params), set by it: read only once the anchor is fixed
    iterations = resolve_iterations(config, "adam", config.loss, "")
    with loop.reporter.task(f"adapt online ({loop.backend.space}, {loop.obs.kind}, w={w})", loop.total()) as task:
        for T in loop.online_frames():
            frames = list(range(max(loop.first, T - w + 1), T + 1))
            tt = time.perf_counter()
            times = np.zeros(3)
            if calibrating:  # the growing window: every frame since the first, simulated from the start
                frames = list(range(calib_from, T + 1))
            tied = frames[0] <= f  # the window holds the fit frame (p_a is p there in any case)
            idle = vision and tied and frames == [f]
            if anchor is not None:
                obj.anchor_p = anchor.held(T, tied)
            # the lead-in: never before the first frame nor a confirmed change of material
            lead_from = max(loop.first, anchor.lead_from if anchor is not None and anchor.apart else loop.first)
            sim = list(range(max(lead_from, frames[0] - config.lead_in), frames[0])) + frames
            if rest_rule and loop.first == 0 and 0 < sim[0] and sim[0] - 1 <= rest_until:
                sim = [0] + sim  # the states before it at rest: x_{s−2} = x_{s−1} = x_0(θ)
            lead = len(sim) - len(frames)
            resting = False
            for it in range(iterations):
                states, losses, g, t3 = obj(sim, params, loop.before(sim[0]), True, lead=lead)
                times += t3
                if it == 0 and (rest_rule or calibrating) and sim[0] == 0 and f <= T:  # frames 0..T simulated
                    resting = _at_rest(loop.backend, states)
                    idle = idle or resting
                if not idle:
                    params[:] = adam.step(params, g)
                if anchor is not None:
                    obj.anchor_p = anchor.after_step(params, obj.last_anchor_g, idle)
                if idle:
                    break  # θ does not move: the next steps would repeat this one
            if holding and anchor.fixed and not calibrating:  # the past is the held fit's: frame T simulated with it
                states_fit, t_sim = obj.simulate([T], calib_p, loop.before(T))
                times[0] += t_sim
                loop.stored[T] = states_fit[0]
            else:
                for i, t in enumerate(sim):
                    loop.stored[t] = states[i]
            if sim[0] == 0 and len(sim) > 1 and sim[1] > 1:  # the frames skipped at rest hold x_0(θ)
                for t in range(1, sim[1]):
                    loop.stored[t] = states[0]
            _bind_late_markers(loop, T, sim, states)
            if resting:
                rest_until = T
            informed += calibrating and not idle
            if calibrating and informed >= config.anchor_calibration:
                hold = anchor.fixed and RECALIBRATION_HOLDS_POISSON  # a recalibration: log E alone
                if hold:
                    params[R:] = calib_p[R:]  # ν at the last fit's
                params[:] = _calibrate_anchor(obj, sim, params, loop.before(sim[0]), loop.young_range, times, hold)
                if anchor.fixed:  # a recalibration: the change located again, each split with its own fit
                    c, params[:] = _relocate_with_fits(
                        loop, T, calib_p, params, calib_from,
                        range(max(change_lo, calib_from - 2), min(calib_from + 2, T) + 1), hold, times)
                    if c != calib_from:
                        calib_from, sim, rec.change_frames[-1] = c, list(range(c, T + 1)), c
                states, losses, _, t3 = obj(sim, params, loop.before(sim[0]), False)
                times += t3
                for i, t in enumerate(sim):
                    loop.stored[t] = states[i]
                # Adam restarts from the fit: the growing window's larger gradients, kept, would shrink the next
                # steps (and, with E(t) held, slow the detection of the next change); its first steps are lr in size
                # whatever the gradient, so rule 5 passes over the next w frames while E(t) holds the fit
                quiet = w if holding else 0
                if anchor.fixed:  # a recalibration after a later change: the anchor stays, rule 5 restarts
                    anchor.restart_watch(params, quiet)
                else:
                    anchor.calibrated(params, T, quiet)
                    obj.want_anchor_grad = False  # p_a is held: no anchor part to move it by
                adam.restart()
                calibrating = False
                calib_p = params.copy()  # the material of the frames since the last change
                if holding:  # E(t) holds this fit: its σ (the Laplace covariance over its frames) is held with it
                    fit_sigma = _fit_sigma(loop, sim, params, loop.before(sim[0]))
                fit_e, fit_nu = theta_from_params(params[:R], params[R:], loop.prange)
                rec.calibrations.append({"frames": [calib_from, T], "young": fit_e.tolist(),
                                         "poisson": fit_nu.tolist()})
            if losses.shape[0] > w:  # the growing window: the loss of the last w frames, as a window's
                losses = losses[-w:]
            E, nu = theta_from_params(params[:R], params[R:], loop.prange)
            held_sigma = None  # (σ_E, σ_ν, floors) of the fit E(t) holds at this frame (None: E moves with Adam)
            if anchor is not None:
                rec.window_young.append(E.tolist())
                if holding and anchor.fixed and not calibrating:
                    E, nu = theta_from_params(calib_p[:R], calib_p[R:], loop.prange)  # the last fit, held
                    held_sigma = fit_sigma

                def explains(F, p):  # Σ loss over the frames F simulated from the start with θ(p), anchored there
                    _, fl, _, t3 = obj(list(range(F[-1] + 1)), p, loop.before(0), False)
                    times[:] += t3
                    return float(fl[F].sum())

                anchor.end_frame(T, params, tied or calibrating, explains,
                                 informed=not ((rest_rule and idle) or calibrating))
                if config.recalibrate and anchor.fixed and len(anchor.later) > seen_later:
                    seen_later = len(anchor.later)  # a later change: grow a window again from the frame it began
                    change_lo = max(loop.first + 1, rec.calibrations[-1]["frames"][1] + 1)
                    calib_from = _locate_change(loop, T, calib_p, params, range(
                        min(max(change_lo, T - 2 * w - AWAY), T), min(max(change_lo, T - AWAY + 1), T) + 1), times)
                    rec.change_frames.append(calib_from)
                    calibrating, informed = True, T - calib_from + 1  # frames c..T: the new material, moving
                rec.anchor_apart, rec.anchor_later = anchor.apart_from, list(anchor.later)
                rec.anchor_young.append(theta_from_params(anchor.p[:R], anchor.p[R:], loop.prange)[0].tolist())
            # σ: a held fit's (images, --hold-fit); NaN while E moves with Adam (before the first fit, while a
            # window grows again after a change)
            nan = np.full(R, np.nan)
            sE, sN, floors = held_sigma if held_sigma is not None else (nan, nan, nan)
            if holding:
                rec.model_error.append(np.asarray(floors).tolist())
            rec.add(T, E, nu, losses.sum(), losses[-1], tuple(times), time.perf_counter() - tt,
                    *((sE, sN) if holding else ()))
            task.advance(1, frame=T, E=" ".join(f"{e:.4g}" + (f"±{se:.2g}" if np.isfinite(se) else "")
                                                for e, se in zip(E, sE)),
                         loss=float(losses.sum()), s_per_frame=rec.t_tot[-1])


class _Splits:
    """The frames c0..T after a later change of material, split at k: c0..k−1 simulated with the old material p_old
    from the stored states before c0 (once, here), k..T with a new θ from the old material's states before k.
    ``times`` (3,) accumulates."""

    def __init__(self, loop: _Loop, T: int, p_old: np.ndarray, c0: int, times: np.ndarray):
        self.obj, self.c0, self.times = loop.objective, c0, times
        self.span = list(range(c0, T + 1))
        states, self.old_losses, _, t3 = self.obj(self.span, p_old, loop.before(c0), False)
        times[:] += t3
        self.past = [*loop.before(c0), *states]  # past[t − c0 + 2] = x_t with the old material (past[:2]: before c0)

    def frames(self, k: int) -> list[int]:
        """k..T."""
        return self.span[k - self.c0:]

    def before(self, k: int) -> np.ndarray:
        """The old material's states x_{k−2}, x_{k−1}."""
        return np.stack(self.past[k - self.c0:k - self.c0 + 2])

    def cost(self, k: int, p: np.ndarray) -> float:
        """L(k) = Σ_{t=c0..k−1} loss_t(p_old) + Σ_{t=k..T} loss_t(p)."""
        _, new_losses, _, t3 = self.obj(self.frames(k), p, self.before(k), False)
        self.times[:] += t3
        return float(np.sum(self.old_losses[:k - self.c0]) + np.sum(new_losses))

    def store(self, loop: _Loop, c: int) -> None:
        """Frames c0..c−1 stored as simulated with the old material."""
        for t in range(self.c0, c):
            loop.stored[t] = self.past[t - self.c0 + 2]


def _locate_change(loop: _Loop, T: int, p_old: np.ndarray, p_new: np.ndarray, candidates: range,
                   times: np.ndarray) -> int:
    """The first frame c of a later change of material seen at frame T (rule 5 of stages/vision_anchor.py), among
    ``candidates`` (frames ≤ T): the c of lowest L(c) = Σ_{t=c0..T} loss_t, frames c0..c−1 simulated with the old
    material p_old (the last calibration's fit) and c..T with p_new (the window's p at T), from the stored states
    before c0 = min(candidates).  The frames before c are stored as simulated with p_old: the recalibration's
    window starts at c from a past of the old material.  ``times`` (3,) accumulates."""
    splits = _Splits(loop, T, p_old, candidates[0], times)
    best = (float(np.sum(splits.old_losses)), candidates[-1])  # no frame of the new material: the last candidate
    for c in [*candidates[1:], candidates[0]]:
        cost = splits.cost(c, p_new)
        if cost < best[0]:
            best = (cost, c)
    splits.store(loop, best[1])
    return best[1]


def _relocate_with_fits(loop: _Loop, T: int, p_old: np.ndarray, p_fit: np.ndarray, c: int, candidates: range,
                        hold_poisson: bool, times: np.ndarray) -> tuple[int, np.ndarray]:
    """The change located again after a recalibration: p_fit (2R,) is θ fitted to frames c..T; each neighbouring
    split c ± 1, c ± 2, ... inside ``candidates`` gets its own fit to its frames c'..T (from the old material's
    states before c'), and the split of lowest L(c') = Σ_{t=c0..c'−1} loss_t(p_old) + Σ_{t=c'..T} loss_t(p_c') wins,
    walking while L falls (c0 = min(candidates)).  Comparing splits at one θ favours the split that θ was fitted to
    (a fit that took in a frame of the old material is lower, and that frame then looks new).  The frames before the
    split are stored as simulated with p_old.  Returns (c, p_c); ``times`` (3,) accumulates."""
    splits = _Splits(loop, T, p_old, candidates[0], times)
    best_cost, best_p = splits.cost(c, p_fit), p_fit
    start = c
    for step in (-1, 1):
        if c != start:
            break  # a walk down that moved ends the search
        k = start + step
        while k in candidates:
            p = _calibrate_anchor(loop.objective, splits.frames(k), best_p, splits.before(k), loop.young_range, times,
                                  hold_poisson)
            cost = splits.cost(k, p)
            if cost >= best_cost:
                break
            c, best_cost, best_p, k = k, cost, p, k + step
    splits.store(loop, c)
    return c, best_p


CALIBRATION_ITERATIONS = 30
"""adam, images, --anchor-calibration: the L-BFGS-B iterations of the calibration fit at most (the bars of
bench/accuracy.py's captures converged in 6–11)."""
RECALIBRATION_HOLDS_POISSON = True
"""adam, images, --recalibrate: a recalibration fits log E alone, ν held at the last fit's (the first calibration's).
The frames after a later change start from stored states, and over them ν is not told apart from E: fitted too, it
ran to the bound of its range (0.30–0.32 against 0.45) in every recalibration on the bars of bench/accuracy.py
(accuracy_notes.md, thirteenth stop)."""


def _calibrate_anchor(obj: WindowObjective, sim: list[int], p: np.ndarray, before: np.ndarray,
                      young_range: tuple[float, float] | None, times: np.ndarray,
                      hold_poisson: bool = False) -> np.ndarray:
    """p (2R,) minimising L(p) = Σ_{t∈sim} loss_t(X_t(θ(p))), the frames ``sim`` simulated from ``before`` (the
    start, or the stored states before a later change) with the anchor as ``obj`` holds it (tied to θ at the first
    calibration, held after), by L-BFGS-B from ``p`` with the window's adjoint gradient; log E inside young_range;
    ``hold_poisson``: ν's coordinates p[R:] held at p's (a recalibration, RECALIBRATION_HOLDS_POISSON).
    AdaptConfig.anchor_calibration and recalibrate; ``times`` (3,) accumulates."""
    R = obj.R
    best = [np.inf, np.array(p, float)]  # the lowest L(p) evaluated, and its p

    def cost(q):
        try:
            _, fl, g, t3 = obj(sim, q, before, True)
        except SolveCollapsed:  # a trial too far: L-BFGS-B's line search backs off
            return np.inf, np.zeros(len(q))
        times[:] += t3
        if float(np.sum(fl)) < best[0]:
            best[:] = [float(np.sum(fl)), np.array(q, float)]
        return float(np.sum(fl)), np.asarray(g, float)

    bounds = [(None, None)] * len(p)
    if young_range is not None:
        bounds[:R] = [(float(np.log(young_range[0])), float(np.log(young_range[1])))] * R
    if hold_poisson:
        bounds[R:] = [(float(v), float(v)) for v in p[R:]]
    scipy.optimize.minimize(cost, np.array(p, float), jac=True, method="L-BFGS-B", bounds=bounds,
                            options={"maxiter": CALIBRATION_ITERATIONS})
    return best[1]


def _fit_sigma(loop: _Loop, frames: list[int], params: np.ndarray, before: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(σ_E (R,) Pa, σ_ν (R,), the model-error floors e_i (R,)) of an Adam fit θ(params) over ``frames`` simulated
    from ``before`` (an anchor calibration): the Gauss–Newton (Laplace) covariance at the fit as ``--estimator gn``
    forms it — (Jᵀ W J / (σ² s²))⁻¹ with its Huber weights W, the noise level σ of the fit's residuals and the
    images' cluster-robust s², under a flat prior — and the model-error floors (stages.windows.sigma_from_cov).
    The fit is not moved (no Gauss–Newton step)."""
    config, obs, R = loop.config, loop.obs, loop.objective.R
    gn = GNWindow(loop.objective, config.fit_poisson, params[R:])
    gn.young_range = loop.young_range
    p = np.array(params if config.fit_poisson else params[:R], float)
    gn.rebind_next = True
    primed = gn.evaluate(frames, p, before, None, True)  # the residuals' noise level and the solve's linearisation
    sigma = max(obs.noise_scale(primed[0]), obs.noise_floor)
    res, _ = _gn_solve(gn, frames, p, Prior(p.copy(), np.eye(len(p)) * FLAT_PRIOR_VARIANCE), before, None, sigma, obs,
                       0, primed=primed)
    floors = model_error_floors(resolve_model_error(config, obs.kind), np.diag(res.jtwj)[:R])  # diag(Jᵀ W J)
    sE, sN = sigma_from_cov(gn, res.p, res.cov_scaled[:gn.k_theta, :gn.k_theta], floors, config.model_error_poisson)
    return sE, sN, floors


FLAT_PRIOR_VARIANCE = 1e6
"""_fit_sigma: the prior variance of log E and s of an Adam fit's σ (σ = 1000: no prior information)."""


def _frame_loss(obs, r: np.ndarray) -> float:
    """The loss Adam minimises, from one frame's residuals: Σ r² (markers, silhouettes), Σ |r| (images, L1)."""
    return float(r @ r) if obs.kind in ("markers", "silhouette") else float(np.abs(r).sum())


def _gn_prior(p: np.ndarray) -> "object":
    """The initial arrival cost: N(p, I) — σ = 1 on log E (a factor e either way) and on s."""
    return Prior(p.copy(), np.eye(len(p)))


def _gn_solve(gn: GNWindow, frames, p0, prior, before, D, sigma, obs, iterations: int, scale: float = 1.0,
              primed: tuple | None = None):
    """One window's Gauss–Newton solve; afterwards gn.last_* hold the window evaluated at the estimate.
    log E stays inside [material] young_range and moves at most 0.5 (a factor 1.65) per iteration: in the
    stiff regime the motion hardly depends on E and an unbounded step could run away.  ``scale``: the data term's
    variance factor s² (estimator.gauss_newton); observations with correlated residuals (images: pixel blocks,
    VisionObservation.clusters) get the cluster-robust s² in the result (estimator.cluster_scale2).  ``primed``:
    gn.evaluate(frames, p0, before, D, True) already made (with gn.rebind_next set, the last evaluation of gn):
    the solve starts from it instead of evaluating p0 again (GNWindow.shared_innovation)."""
    k, kt = len(p0), gn.k_theta
    lower, upper, cap = np.full(k, np.nan), np.full(k, np.nan), np.full(k, np.inf)
    if gn.young_range is not None:
        lower[:gn.R], upper[:gn.R] = np.log(gn.young_range[0]), np.log(gn.young_range[1])
    cap[:kt] = 0.5
    if primed is None:
        gn.rebind_next = True
    first = [True]
    lins = [0]  # linearisations so far: a trial step before the last iteration is evaluated ahead (GNWindow.evaluate)
    # the one-evaluation path (gn.trust > 0, AdaptConfig.gn_trust): the last step, when at most gn.trust posterior
    # σ, is taken on the quadratic model without simulating the window there — unless the last frame's such step
    # missed its predicted residuals by more than GN_PREDICTION_SLACK in the cost's units (checked at this frame's
    # linearisation, which simulates and renders that estimate): then this frame's step is tested (two evaluations)
    trusted = [gn.trust > 0]

    def evaluate(pp, nj):
        # a trial step whose simulation collapses (inverted elements, a failed solve) is a rejected step: the
        # damping grows and a shorter step is tried; the first evaluation (the starting point) still raises
        try:
            out = primed if first[0] and nj and primed is not None else gn.evaluate(
                frames, pp, before, D, nj, ahead=not nj and lins[0] < iterations)
            lins[0] += bool(nj)
            if first[0] and nj and gn.prediction is not None:
                gn.last_prediction_error = gn.prediction_error(frames, sigma, obs.huber)
                trusted[0] = trusted[0] and gn.last_prediction_error <= GN_PREDICTION_SLACK
            return out
        except SolveCollapsed:
            if nj or first[0]:
                raise
            gn.last_p = np.full(len(pp), np.nan)  # the observations may be bound to the failed trial: re-evaluate
            return np.full(1, np.inf), None
        finally:
            first[0] = False

    clusters = obs.clusters(frames) if hasattr(obs, "clusters") else None
    skip = (lambda step, size: trusted[0] and size <= gn.trust) if gn.trust > 0 else None
    res = gauss_newton(evaluate, p0, prior, sigma, max_iterations=iterations, huber=obs.huber, max_step=cap,
                       lower=lower, upper=upper, scale=scale, clusters=clusters, skip_trial=skip)
    lin = (list(gn.last_frames), list(gn.last_jac))  # per-frame residuals and Jacobians at res.p_lin
    gn.prediction = None
    if not res.checked:  # the window at the estimate to first order (GNWindow.extrapolate)
        gn.extrapolate(frames, res.p, before, D, float(sigma) ** 2 * float(scale), res.residuals, res.jacobian)
    elif not np.array_equal(gn.last_p, res.p):
        gn.evaluate(frames, res.p, before, D, False)
    return res, lin


GN_PREDICTION_SLACK = 1.0
"""--gn-trust: how far (in units of the Gauss–Newton cost, where a step of 1 posterior σ lowers it by ½) the data term
at an estimate taken without evaluation may exceed its first-order prediction, checked when the next frame
simulates and renders it, before that frame's step must again pass the Levenberg–Marquardt test."""


MOVING_REBINDS = 20
"""A moving start (stages/moving_start.py): at most this many fits of the markers' material points per window that
holds frame 0 (:func:`_rebind_moving_start`).  Frame 0 is estimated there, so where each marker sits on the body
is not known: its material point is fitted to its track over the window's frames (MarkerObservation.
fit_to_tracks), the window solved again with that binding held, until the bound points move by less than
MOVING_REBIND_TOL of the object's size.  The windows' cost falls at every step, so the binding converges; the
bar's windows [0, 1] reach 20 with the points still moving by a few hundredths of a millimetre
(accuracy_notes.md, seventeenth stop)."""
MOVING_REBIND_ITERATIONS = 1
"""Gauss–Newton iterations of each re-solve between two fits of the markers' material points
(:data:`MOVING_REBINDS`).  bench/moving_start.py's bar filmed 4 / 8 / 16 frames in, reduced space, median settled
E error: 2 iterations 0.6 / 1.1 / 2.1 %, 1 iteration 0.7 / 1.0 / 2.1 % at half the windows' Jacobians (the fits
move the binding more than a second iteration moves θ); 1 iteration with 40 fits 0.7 / 4.5 / 1.9 %
(accuracy_notes.md, seventeenth stop)."""
MOVING_REBIND_TOL = 1e-5
"""The RMS motion of the bound marker points between two fits (:data:`MOVING_REBINDS`) under which the binding is
taken as converged, as a fraction of the object's size (2 µm on a 0.2 m object: a tenth of the smallest marker
noise the estimator assumes, MarkerObservation.noise_floor)."""


def _silhouette_start_pose(capture, ws: Path, mesh, young, poisson) -> np.ndarray:
    """(n, 3) m: frame 0 of a moving start posed from its masks (stages.moving_start.silhouette_pose), for
    --loss silhouette, which has no Gaussians and thus no pose of fit-gaussians to start from."""
    from stages.sim.scene import SimulationError

    try:
        return silhouette_pose(capture, ws, mesh, young, poisson, 0)[0]
    except SimulationError as e:
        raise RslError(f"{capture.toml_path}: cannot pose the mesh as frame 0's masks show it (start = 'moving', "
                       f"E = {np.asarray(young).tolist()} Pa): {e}") from None


def _pose_state(backend, x_fit: np.ndarray, iterations: int = 20) -> np.ndarray:
    """The backend's state of a pose x_f (n, 3) m (the Gaussians' fit pose, gaussians.h5 fit_positions; a moving
    start: posed from frame 0's masks): the positions themselves in the full space; in the reduced space the z
    whose decoding is nearest, argmin |φ(z) − x_f|² by Gauss–Newton from the encoder's ψ(x_f).  A moving start
    with images or silhouettes adds its estimated offsets to it."""
    x_fit = np.asarray(x_fit, float)
    if backend.space == "full":
        return x_fit.copy()
    model = backend.model
    z = np.asarray(model.encode(x_fit), float)
    for _ in range(iterations):
        J = model.jacobian(z).reshape(-1, len(z))
        dz = np.linalg.lstsq(J, (x_fit - model.decode(z)).ravel(), rcond=None)[0]
        z = z + dz
        if np.linalg.norm(dz) <= 1e-10 * max(np.linalg.norm(z), 1.0):
            break
    return z


def _rebind_moving_start(gn: GNWindow, objective: WindowObjective, res, lin, frames, prior, before, D, sigma,
                         obs, scale: float, rec):
    """A moving start's window holding frame 0 (:data:`MOVING_REBINDS`): block coordinate descent on the window's
    cost over (θ, the start's offsets) and the markers' material points.  The material points are fitted to
    the tracks of the window's estimate, then the window is solved with them held (the solve's Levenberg–
    Marquardt steps, :data:`MOVING_REBIND_ITERATIONS` per re-solve, and the fit each lower the cost), until the
    bound points on frame 0 move by less than MOVING_REBIND_TOL × the object's size.  From here on the binding is
    held (``objective.rebind`` off).  Returns the last solve's (res, lin); the count goes to
    ``rec.moving_rebinds``."""
    objective.rebind = False
    count = 0
    for count in range(1, MOVING_REBINDS + 1):
        X = np.asarray(objective.backend.decode(gn.last_states))
        moved = obs.fit_to_tracks(frames, X)
        if moved <= MOVING_REBIND_TOL * float(np.linalg.norm(np.ptp(X[0], axis=0))):
            break
        res, lin = _gn_solve(gn, frames, res.p, prior, before, D, sigma, obs, MOVING_REBIND_ITERATIONS, scale,
                             None)
    rec.moving_rebinds = getattr(rec, "moving_rebinds", []) + [count]
    return res, lin


def _warn_far_markers(reporter: Reporter, obs, surface: str) -> None:
    """The markers' frame-0 check: a marker more than 5 % of the object's size from the frame-0 surface (``surface``
    says which: simulated with the initial E, or estimated) points at a wrong frame or a far-off initial E."""
    if obs.far > 0.05:
        reporter.warn(f"{obs.capture.markers_path}: a frame-0 marker lies {obs.far:.1%} of the object size away "
                      f"from the frame-0 surface {surface}; is the marker frame the mesh's frame, or is the initial E "
                      f"far off?")


def _correction_kind(option: str, obs_kind: str, restart: bool, modes_failed: bool) -> str | None:
    """Which correction of the window's starting states a gn window estimates (AdaptConfig.state_correction):
    "states" (markers), "past" (asked for, with images — each direction costs 2 renders per frame and camera in
    the Jacobian's central differences, so the 2R θ-sensitivity directions —, or after the vibration modes
    failed), or None ("off", and a window that starts at a change point: it starts from the states the last
    windows of the old material fitted, and with log E's prior widened a correction of those states trades
    against E — on the demo's ×2 step +20 % at the step, +26 % two frames on; uncorrected −1 %, +6 %, +12 %)."""
    if option == "off" or restart:
        return None
    if option == "states" and obs_kind == "markers" and not modes_failed:
        return "states"
    return "past" if (option == "past" or obs_kind == "vision" or modes_failed) else None


LATE_MARKER_FRAMES = 3
"""A marker first seen after frame 0 is bound by the first window whose frames see it this many times: a track,
not one frame's nearest point (docs/results/late_markers.md)."""


def _bind_late_markers(loop: _Loop, T: int, frames, states) -> None:
    """Markers first seen after frame 0 (hidden at frame 0 by a gripper, say) that this window's frames see: each
    bound at the material point whose track over the frames, on the window's estimated states, fits its
    observations best (MarkerObservation.bind_late); they count from the next window on.  Recorded per frame as
    (T, how many) in ``rec.late_bindings``."""
    obs = loop.obs
    if getattr(obs, "late", None) is None or not obs.late.any():
        return
    n = obs.bind_late(frames, np.asarray(loop.backend.decode(np.stack(list(states)))), LATE_MARKER_FRAMES)
    if n:
        loop.rec.late_bindings = getattr(loop.rec, "late_bindings", []) + [(int(T), n)]


def _probing(config: AdaptConfig, kind: str, frames, T: int, changes: list, w: int, first: int) -> bool:
    """Whether this frame's window is probed (AdaptConfig.change_probe): images or silhouettes, a full window of
    two frames or more, and no change of material within the last w frames."""
    return (config.change_probe > 0 and config.change_threshold > 0 and kind in ("vision", "silhouette")
            and len(frames) > 1 and T >= first + w and (not changes or T - changes[-1] > w))


def _probe_log_e(gn: GNWindow, frames, p_hat: np.ndarray, before, D, sigma: float, obs, scale: float,
                 step: float) -> tuple[float, np.ndarray | None]:
    """The window's data cost probed at each region's log E ± ``step`` (the other unknowns at the estimate
    ``p_hat``, the observations' binding kept): (Λ, p) of the probe with the largest likelihood ratio

        Λ = 2 [C(p̂) − C(p)] / (σ² s²),   C = Σ σ² ρ(r/σ) the robust data cost (estimator.robust_cost),

    s² the data term's variance factor (``scale``); (−∞, None) when no probe could be simulated.  C(p̂) is the
    solve's last evaluation (gn.last_rs); gn's record of the window (last_*), the remembered trajectory and the
    substeps' records are left as the solve left them: the run goes on as without the probes."""
    keep = {name: getattr(gn, name, None) for name in gn._LINEARISATION + gn._EVALUATION + ("prediction",)}
    traj = getattr(gn.obj.win, "_traj", None)  # (StartWindow.memo: the trajectory the next window continues)
    backend = getattr(gn.obj, "backend", None)
    records = getattr(backend, "records", None)  # (Substepped's records of the forwards, the reduced Newton's memory)
    saved = records() if records is not None else None
    c_hat = robust_cost(np.concatenate(gn.last_rs), sigma, obs.huber)
    lo, hi = (np.log(gn.young_range) if gn.young_range is not None else (-np.inf, np.inf))
    best: tuple[float, np.ndarray | None] = (-np.inf, None)
    try:
        for j in range(gn.R):
            for sign in (1.0, -1.0):
                p = np.array(p_hat, float)
                p[j] = float(np.clip(p[j] + sign * step, lo, hi))
                if abs(p[j] - p_hat[j]) < 0.5 * step:  # at a bound of [material] young_range
                    continue
                try:
                    r, _ = gn.evaluate(frames, p, before, D, False, rebind=False)
                except SolveCollapsed:
                    continue
                lam = 2.0 * (c_hat - robust_cost(r, sigma, obs.huber)) / (sigma ** 2 * scale)
                if lam > best[0]:
                    best = (lam, p)
    finally:
        for name, v in keep.items():
            setattr(gn, name, v)
        if traj is not None:
            gn.obj.win._traj = traj
        if saved is not None:
            backend.restore_records(saved)
    return best


def _online_gn(loop: _Loop, log_e: np.ndarray, s_nu: np.ndarray) -> None:
    """Online moving-horizon estimation (stages.estimator): per new frame, Gauss–Newton on the window's
    unknowns against the arrival-cost prior; the frame leaving the window is folded into the prior, which then
    takes one frame of process noise."""
    from scipy.linalg import block_diag

    config, obs, backend, objective, stored, rec = (loop.config, loop.obs, loop.backend, loop.objective, loop.stored,
                                                    loop.rec)
    first = loop.first
    w = config.window
    gn = GNWindow(objective, config.fit_poisson, s_nu)
    gn.young_range = loop.young_range
    gn.trust = resolve_gn_trust(config, obs.kind)
    model_error = resolve_model_error(config, obs.kind)  # the floor of the reported σ (AdaptConfig.model_error)
    start = "moving" if loop.moving is not None else ""
    iterations = resolve_iterations(config, "gn", obs.kind, start)
    k_th = gn.k_theta
    p_th = np.concatenate([log_e, s_nu]) if config.fit_poisson else log_e.copy()
    q_settled = resolve_process_noise(config, "gn", obs.kind, start)
    filt = WindowFilter(_gn_prior(p_th), np.full(k_th, q_settled))
    sigma = None
    sens: dict[int, np.ndarray] = {}  # frame -> d state/dp (k_θ, …)
    sig_hist: list[float] = []
    info_run = np.zeros(gn.R)  # the data's information on each region's log E, summed over the run's windows
    # images: σ is a robust per-pixel level, but the pixels' misfit is correlated (blocks, frames): the data term's
    # variance factor s² is the cluster-robust one of the last windows (median of 5; 1 for markers, whose σ is
    # already their RMS)
    scale_hist: list[float] = []
    changes: list[int] = []  # frames where a change of material was detected
    # images: the innovation is judged against its own baseline only (ChangeDetector.relative): their noise level
    # comes from misfits that grow with the motion and with θ's error, and far from the truth every frame's z
    # exceeded the threshold (a false change, the anchor then held at a far-off θ: bar, 0.5 E_true, 80 % error)
    detector = ChangeDetector(config.change_threshold, relative=obs.kind == "vision")
    rec.innovation = []  # per frame: the normalised innovation z of the change test (NaN: not tested)
    rec.probe = []  # per frame: the best probe's likelihood ratio (NaN: not probed; AdaptConfig.change_probe)
    start_w = first  # the window never reaches before the last change point
    modes_failed = False
    R = objective.R
    # ν of region j (unknown R + j) is held at its estimate in a window when the last window's data informed it
    # less than --poisson-information × its arrival cost does (estimator.marginal_information): ν trades against
    # E, and a window that cannot tell them apart moves ν with the model error and E with it
    hold_nu = np.zeros(R, bool)
    # a moving start: the prior σ of the shape and velocity offsets of (x_{−1}, x_0) (moving_start.start_prior),
    # and their estimate so far (each window holding frame 0 starts from it)
    start_sigma, start_c = None, None
    moving_checked = False  # a moving start: the markers' frame-0 check made (against frame 0 as estimated)
    if loop.moving is not None:
        size = float(np.linalg.norm(np.ptp(backend.decode(backend.rest_state[None])[0], axis=0)))
        if obs.kind == "markers":
            motion = marker_motion(obs.P)
        else:  # images: the outline's motion in masks.h5 at the object's frame-0 pose (the Gaussians' fit pose)
            x0 = backend.decode(np.asarray(objective.win.reference)[None])[0]
            motion = image_motion(obs.masks, obs._cams, x0.mean(axis=0))
        start_sigma = start_prior(loop.moving, motion, size)
        loop.rec.start_motion = motion

    def window_setup(t0: int):
        """(D, prior, p0, past_dirs) of a window starting at t0: the correction of its starting states
        (_correction_kind) and the arrival cost extended by the correction's own prior."""
        nonlocal modes_failed
        kind = _correction_kind(config.state_correction, obs.kind, bool(changes) and t0 == changes[-1],
                                modes_failed)
        sc, past_dirs = None, False
        if loop.moving is not None and t0 == 0:  # a moving start: the offsets of x_{−1}, x_0 are unknowns
            sc, kind = (start_directions(loop.moving), start_sigma), None
        if kind == "states":
            try:
                sc = state_directions(backend, stored, t0, first, STATE_PRIOR_SCALE, gn.theta(p_th)[:2])
            except (ArithmeticError, RuntimeError, ValueError) as e:  # eigsh / a singular K: fall back
                loop.reporter.warn(f"the vibration modes for --state-correction states failed ({e}); correcting "
                                   f"along the θ sensitivities instead (--state-correction past).")
                modes_failed = True
        if kind == "past" or (kind == "states" and modes_failed):
            sc = past_directions(sens, t0, k_th, config.state_prior)
            past_dirs = True
        D, prior, p0 = None, filt.prior, p_th.copy()
        if sc is not None:
            D, sd = sc
            prior = Prior(np.concatenate([filt.prior.mean, np.zeros(len(D))]),
                          block_diag(filt.prior.cov, np.diag(sd ** 2)))
            p0 = np.concatenate([p_th, start_c if start_c is not None and t0 == 0 else np.zeros(len(D))])
        return D, prior, p0, past_dirs

    def declare_change(T: int, from_frame: int) -> np.ndarray:
        """A change of material at frame T (the change test's, or a probe's): the arrival cost's variance of log E
        widened by --change-sigma² (ν's kept: a one-frame window cannot tell ν from E, and ν wandered off with E
        after a step: make demo), T recorded, windows from here on start no earlier than ``from_frame``, and the
        anchor frame (0, or the Gaussians' fit frame), which showed the old material, keeps its binding instead of
        being re-simulated with the new θ.  Returns the widening added to the θ unknowns' variances (k_θ,)."""
        nonlocal start_w
        widen = np.zeros(k_th)
        widen[:R] = config.change_sigma ** 2
        filt.prior = Prior(filt.prior.mean, filt.prior.cov + np.diag(widen))
        changes.append(T)
        rec.changes = changes
        gn.rebind_anchor = False
        start_w = from_frame
        return widen

    with gn.blas_limit(obs.kind), loop.reporter.task(f"adapt online gn ({backend.space}, {obs.kind}, w={w})",
                                                    loop.total()) as task:
        for T in loop.online_frames():
            frames = list(range(max(start_w, T - w + 1), T + 1))
            t0 = frames[0]
            before = loop.before(t0)
            tt = time.perf_counter()
            gn.times = [0.0, 0.0, 0.0]
            z_innov = float("nan")
            primed = None  # the solve's first evaluation, made by the change test (GNWindow.shared_innovation)
            if (sigma is not None and config.change_threshold > 0 and T >= 2 and len(frames) > 1
                    and (not changes or T - changes[-1] > w)  # at most once per window length
                    and (loop.moving is None or T >= w)):  # (a moving start: once the velocity is estimated)
                # innovation test (stages.estimator.ChangeDetector): the new frame simulated from the stored
                # states with the predicted θ, its residuals against the noise level the windows reach
                if gn.shared_innovation and obs.kind == "vision":  # from the window's linearisation at the
                    # predicted θ (images: one render of the new frame less; markers' residuals cost nothing)
                    D, prior, p0, past_dirs = window_setup(t0)
                    gn.rebind_next = True
                    primed = gn.evaluate(frames, p0, before, D, True)
                    rn = gn.last_frames[-1]
                else:
                    Ep, nup, _ = gn.theta(p_th)
                    t_c = time.perf_counter()
                    xs = objective.win.forward([T], Ep, nup, loop.before(T))
                    t_r = time.perf_counter()
                    rn = obs.residuals([T], backend.decode(xs))[0]
                    gn.times[0] += t_r - t_c
                    gn.times[2] += time.perf_counter() - t_r
                z_innov = ChangeDetector.ratio(rn, sigma)
                if len(rn) and detector.update(z_innov):
                    # a change point: the window restarts at T (the frames before it saw the old material and
                    # are not folded into the arrival cost)
                    declare_change(T, T)
                    frames = [T]
                    t0 = T
                    before = loop.before(t0)
                    primed = None
            rec.innovation.append(z_innov)
            if loop.moving is not None and t0 >= 1 and not moving_checked:
                # a moving start, the windows past frame 0: the markers stay bound where the frame-0 windows fitted
                # them (_rebind_moving_start); the frame-0 check, against frame 0 as estimated
                moving_checked = True
                if obs.kind == "markers":
                    _warn_far_markers(loop.reporter, obs, "estimated")
            if primed is None:
                D, prior, p0, past_dirs = window_setup(t0)
            if sigma is None:  # the first window: the noise level seen at the initial θ (conservative)
                r0, _ = gn.evaluate(frames, p0, before, D, False)
                sigma = max(obs.noise_scale(r0), obs.noise_floor)
            scale = float(np.median(scale_hist[-5:])) if scale_hist else 1.0
            solve_prior = prior
            for j in np.flatnonzero(hold_nu):  # ν held: the prior conditioned on s_j at its current estimate
                solve_prior = condition(solve_prior, R + j, p0[R + j])
            res, (r_lin, J_lin) = _gn_solve(gn, frames, p0, solve_prior, before, D, sigma, obs,
                                            iterations, scale, primed)
            if loop.moving is not None and t0 == 0 and obs.kind == "markers":  # the markers' material points
                res, (r_lin, J_lin) = _rebind_moving_start(gn, objective, res, (r_lin, J_lin), frames, solve_prior,
                                                           before, D, sigma, obs, scale, rec)
            lam = float("nan")
            if _probing(config, obs.kind, frames, T, changes, w, loop.first):
                lam, p_probe = _probe_log_e(gn, frames, res.p, before, D, sigma, obs, scale, config.change_probe)
                if lam > config.change_threshold ** 2:
                    # a change of material the linear model missed: declared as the change test declares one, the
                    # window's own prior widened with the arrival cost's, the window solved again from the probe; it
                    # keeps its frames (they all prefer the probe) and later ones start no earlier
                    widen = np.zeros(len(prior.mean))
                    widen[:k_th] = declare_change(T, t0)
                    detector.g = 0.0
                    prior = Prior(prior.mean, prior.cov + np.diag(widen))
                    solve_prior = Prior(solve_prior.mean, solve_prior.cov + np.diag(widen))
                    res, (r_lin, J_lin) = _gn_solve(gn, frames, p_probe, solve_prior, before, D, sigma, obs,
                                                    iterations, scale, None)
            rec.probe.append(lam)
            if hold_nu.any():  # σ (and the information test) with ν's own prior: held, ν is not known better
                res.cov_scaled = posterior_cov(res.jacobian, res.weights, sigma ** 2 * res.scale2, prior, res.jtwj)
            held_now = hold_nu.copy()
            n_data = res.jtwj / (sigma ** 2 * scale)  # the data's normal matrix Jᵀ W J at the last linearisation
            if config.fit_poisson and config.poisson_information > 0 and len(frames) > 1:
                hold_nu = weakly_informed(n_data, prior.info, np.diag(filt.prior.cov), R + np.arange(R),
                                          config.poisson_information)
            if obs.kind in ("vision", "silhouette") and config.change_threshold > 0 and len(frames) > 1:
                # images and silhouettes: the window's states start from a past simulated with earlier estimates,
                # and the frames folded while the estimate was far off (a far start) or the material changed make an
                # arrival cost the window's data contradict: its variance of log E is matched to them (estimator.
                # matched_arrival) where they lie more than --change-threshold σ away (silhouettes filmed
                # mid-motion: their change test sees no step, and the matched arrival follows it; accuracy_notes.md,
                # twenty-sixth stop)
                filt.prior, _ = matched_arrival(filt.prior, res.p, n_data, prior.info,
                                                np.arange(R), config.change_threshold)
            if hasattr(obs, "clusters") and len(frames) > 1:  # (the fit frame alone carries no information)
                scale_hist.append(max(res.scale2, 1.0))
            p_th = res.p[:k_th].copy()
            for i, t in enumerate(frames):
                stored[t] = gn.last_states[i]
                S = gn.last_state_sens  # (k, w, …) at the last linearisation
                # d x_t/dp through the whole past: the window's θ columns plus, by linearity, the columns of the
                # "past" correction (whose directions are the before states' own sensitivities)
                sens[t] = S[:k_th, i] + (S[k_th:2 * k_th, i] if past_dirs and D is not None else 0.0)
            _bind_late_markers(loop, T, frames, gn.last_states)
            if D is not None and t0 >= 1:  # the corrected starting states replace the stored ones
                k2, k1 = loop.before_keys(t0)
                stored[k2], stored[k1] = gn.last_before[0], gn.last_before[1]
            elif D is not None and loop.moving is not None:  # x_{−1} = x_0 − Δ_0 + Δ_{−1} (x_0 stored above)
                start_c = res.p[k_th:].copy()
                stored[-1] = gn.last_states[0] - gn.last_before[1] + gn.last_before[0]
            # σ from the covariance with the noise level this window's own residuals show (RSS/dof, Huber-
            # consistent: estimator.residual_scale2), the ν bounds and the model-error floors (sigma_from_cov): the
            # model's error biases the run's estimate by (Σ Jᵀ W J)⁻¹ Σ Jᵀ δ, so the floor is spread over the
            # regions by the data's information on each log E summed over the windows so far (model_error_floors)
            info_run += np.nan_to_num(np.diag(res.jtwj)[:R])  # Jᵀ W J without σ (σ changes between windows)
            floors = model_error_floors(model_error, info_run)
            sE, sN = sigma_from_cov(gn, res.p, res.cov_scaled[:k_th, :k_th], floors, config.model_error_poisson)
            rec.model_error.append(floors.tolist())
            if len(frames) == w:  # frame t0 leaves the window: fold it into the arrival cost
                s_fold = sigma * float(np.sqrt(max(res.scale2, 1.0)))  # never more certain than σ says
                J0 = J_lin[0][:, :k_th].copy()
                J0[:, R + np.flatnonzero(held_now)] = 0.0  # a window that held ν tells the arrival cost nothing of it
                nuisance = None
                if past_dirs and D is not None:
                    # the "past" correction (the past re-simulated with θ + c) is nearly collinear with θ in the
                    # window's first frame: it is the window's own unknown, integrated out under its prior
                    # (estimator.fold), so the frame informs θ only as far as a corrected past cannot explain it
                    # (taken as known, one frame gave var(log E) → 0 far from the truth: images, bar, 0.73 E_true)
                    r0 = r_lin[0]
                    nuisance = (J_lin[0][:, k_th:], res.p_lin[k_th:], marginal(prior, np.arange(k_th, len(res.p))))
                else:  # ("states", markers: the correction at the window's estimate, taken as known)
                    r0 = r_lin[0] + J_lin[0][:, k_th:] @ (res.p[k_th:] - res.p_lin[k_th:])
                # the process noise of the frame: small while the material is taken as constant, larger during the
                # w + 5 frames after a detected change (the estimate re-settles there)
                filt.q = np.full(k_th, process_noise(T, changes, w, q_settled, config.process_noise_change))
                filt.leave(res.p_lin[:k_th], r0, J0, s_fold, huber_weights(r0, sigma, obs.huber), nuisance)
            r_all = np.concatenate(gn.last_rs)
            # the noise level: the median over the last 5 frames of the windows' residual scale per degree of
            # freedom, √(RSS/(m − k)) (robust: one window's transient misfit does not inflate it at once)
            dof = max(len(r_all) - len(res.p), 1)
            sig_hist.append(max(obs.noise_scale(r_all) * float(np.sqrt(len(r_all) / dof)), obs.noise_floor))
            sigma = float(np.median(sig_hist[-5:]))
            E, nu, _ = gn.theta(res.p)
            losses = [_frame_loss(obs, r) for r in gn.last_rs]
            rec.add(T, E, nu, np.sum(losses), losses[-1], tuple(gn.times), time.perf_counter() - tt, sE, sN)
            task.advance(1, frame=T, E=" ".join(f"{e:.4g}±{s:.2g}" for e, s in zip(E, sE)),
                         loss=rec.loss[-1], s_per_frame=rec.t_tot[-1])


def _offline_gn(loop: _Loop, log_e: np.ndarray, s_nu: np.ndarray) -> None:
    """Offline baseline with the same Gauss–Newton machinery: one θ, every frame in one window."""
    config, obs = loop.config, loop.obs
    gn = GNWindow(loop.objective, config.fit_poisson, s_nu)
    gn.young_range = loop.young_range
    p = np.concatenate([log_e, s_nu]) if config.fit_poisson else log_e.copy()
    frames = list(range(loop.first, loop.last))
    before = loop.before(loop.first)
    with loop.reporter.task(f"adapt offline gn ({len(frames)} frames)", None):
        r0, _ = gn.evaluate(frames, p, before, None, False)
        sigma = max(obs.noise_scale(r0), obs.noise_floor)
        done, q = 0, p.copy()
        while done < config.offline_iters:  # solves of ≤ 5 iterations, the observations re-anchored before each
            n_it = min(5, config.offline_iters - done)
            res, _ = _gn_solve(gn, frames, q, _gn_prior(p), before, None, sigma, obs, n_it)
            done += n_it
            moved = float(np.max(np.abs(res.p - q)))
            q = res.p
            if moved < 1e-4:
                break
        # σ of the estimate with the noise level of the final residuals
        sigma2 = max(obs.noise_scale(np.concatenate(gn.last_rs)), obs.noise_floor)
        res, _ = _gn_solve(gn, frames, q, _gn_prior(p), before, None, sigma2, obs, 1)
    E, nu, _ = gn.theta(res.p)
    cov = np.array(res.cov_scaled, dtype=float)
    if hasattr(obs, "sigma_floor"):  # silhouettes: a mask outline's error no residual shows (stages/silhouette.py)
        cov[np.arange(gn.R), np.arange(gn.R)] += obs.sigma_floor()[:gn.R] ** 2
    floors = model_error_floors(resolve_model_error(config, obs.kind), np.diag(np.asarray(res.jtwj, float))[:gn.R])
    sE, sN = sigma_from_cov(gn, res.p, cov, floors, config.model_error_poisson)
    per_frame = tuple(np.asarray(gn.times) / len(frames))
    for i, t in enumerate(frames):
        loop.stored[t] = gn.last_states[i]
        loss = _frame_loss(obs, gn.last_rs[i])
        loop.rec.add(t, E, nu, loss, loss, per_frame, sum(per_frame), sE, sN)
        loop.rec.model_error.append(floors.tolist())


def _estimate(loop: _Loop, estimator: str, log_e, s_nu, params, adam) -> None:
    """The frame loop of the run's estimator and mode."""
    if estimator == "gn" and loop.config.mode == "online":
        _online_gn(loop, log_e, s_nu)
    elif estimator == "gn":  # offline or static: one θ for every frame
        _offline_gn(loop, log_e, s_nu)
    elif loop.config.mode == "online":
        _online(loop, params, adam)
    else:
        _offline(loop, params, adam)


def _wait_for(obs, t: int, timeout: float, poll: float = 0.1, reporter: Reporter = SilentReporter()) -> bool:
    """Wait until frame t is observed; False after ``timeout`` s without it (0: wait for ever).
    Says once that it waits, so a user (or a script) sees the frames so far are done."""
    t0 = time.monotonic()
    if obs.available() <= t:
        reporter.info(f"waiting for frame {t} (frames 0–{t - 1} done; Ctrl-C ends and saves them)")
    while obs.available() <= t:
        if timeout and time.monotonic() - t0 > timeout:
            return False
        time.sleep(poll)
    return True


def _offline(loop: _Loop, params: np.ndarray, adam: Adam) -> None:
    """Offline Adam baseline (§5.3): one θ for every frame, ``--offline-iters`` Adam steps on the whole sequence's
    loss; the best iterate is kept."""
    config, R = loop.config, loop.objective.R
    frames = list(range(loop.first, loop.last))
    before = loop.before(loop.first)
    times = np.zeros(3)
    best = (math.inf, params.copy())
    with loop.reporter.task(f"adapt offline ({len(frames)} frames)", config.offline_iters) as task:
        for _ in range(config.offline_iters):
            _, losses, g, t3 = loop.objective(frames, params, before, True)
            times += t3
            if losses.sum() < best[0]:
                best = (float(losses.sum()), params.copy())
            params = adam.step(params, g)
            E, _ = theta_from_params(params[:R], params[R:], loop.prange)
            task.advance(1, E=" ".join(f"{e:.4g}" for e in E), loss=float(losses.sum()))
        states, losses, _, (a, b, c) = loop.objective(frames, params, before, False)
        times += (a, 0.0, c)
        if losses.sum() > best[0]:  # keep the best iterate
            params = best[1]
            states, losses, _, _ = loop.objective(frames, params, before, False)
    E, nu = theta_from_params(params[:R], params[R:], loop.prange)
    per_frame = tuple(times / len(frames))
    for i, t in enumerate(frames):
        loop.stored[t] = states[i]
        loop.rec.add(t, E, nu, losses[i], losses[i], per_frame, sum(per_frame))


def _trim_record(rec: _Record) -> None:
    """Drop a frame whose record a Ctrl-C cut half-way (its entries are appended one by one): every per-frame
    list keeps the frames all of them have."""
    sigmas = ("young_sigma", "poisson_sigma", "model_error")
    names = [f.name for f in dataclasses.fields(rec) if f.name not in sigmas]
    names += [k for k in sigmas if getattr(rec, k)]  # empty with Adam
    k = min(len(getattr(rec, f)) for f in names)
    for f in names:
        del getattr(rec, f)[k:]
    if hasattr(rec, "innovation"):  # gn: appended before the frame's other entries
        del rec.innovation[k:]
    if hasattr(rec, "probe"):  # gn: likewise
        del rec.probe[k:]
    if hasattr(rec, "anchor_young"):  # adam, --vision-anchor estimated: likewise (and the window's own E)
        del rec.anchor_young[k:]
        del rec.window_young[k:]
    if hasattr(rec, "calibrations"):  # recorded at its frame, before that frame's other entries
        rec.calibrations[:] = [c for c in rec.calibrations if c["frames"][1] in rec.frames]
        rec.change_frames[:] = [c for c in rec.change_frames if c <= rec.frames[-1]] if rec.frames else []


def _save(loop: _Loop, ws: Path, mesh: MeshArtefact, names: list[str], inputs_used: list, status: str,
          wall_s: float, ended_by_ctrl_c: bool = False) -> Path:
    """adapt.h5 (status complete) or adapt.partial.h5 (interrupted, failed) from the record, atomically."""
    config, backend, obs, rec = loop.config, loop.backend, loop.obs, loop.rec
    frames = np.asarray(rec.frames, np.int64)
    states = np.stack([loop.stored[t] for t in rec.frames])
    X = backend.decode(states)[:, :mesh.n_vertices]
    start = "moving" if loop.moving is not None else ""
    estimator = resolve_estimator(config, start)
    # how the Gaussians followed the mesh (stages.results.gaussian_anchor); a moving start's: bound as fitted
    gaussian_anchor = "fitted" if loop.moving is not None and obs.kind == "vision" else getattr(obs, "anchor_kind",
                                                                                                None)
    extra = {
        "capture": str(Path(config.capture).resolve()),
        "frame_loss": rec.frame_loss,
        "iters_per_frame": resolve_iterations(config, estimator, obs.kind, start),
        "cameras": getattr(obs, "cameras", []),
        "gaussian_anchor": gaussian_anchor,
        # images, --unseen-gaussians ignore: per frame, the pixels painted by Gaussians the fit did not see, left out
        "unseen_pixels": ([getattr(obs, "unseen_pixels", {}).get(int(t), 0) for t in frames]
                          if getattr(obs, "unseen_ignored", False) else None),
        "refine": config.refine,
        "substeps": config.substeps,
        "damping": loop.damping,  # β s of the simulation (capture.toml [material] damping, or --damping)
        # --damping auto: {"beta", "tried": [[β, cost], ...], "flat"} (stages/damping_profile.py); else None
        "damping_profile": None if rec.damping_profile is None else rec.damping_profile.as_record(),
        "status": status,  # complete | interrupted | failed
        "estimator": estimator,
        # gn: the --gn-trust that ran (its default resolved from the loss); the provenance keeps the option as given,
        # so that `rsl run` finds an adapt.h5 made with the default up to date
        "gn_trust": resolve_gn_trust(config, obs.kind),
        # gn: the --process-noise that ran (its default resolved from the loss and the start), as gn_trust
        "process_noise": resolve_process_noise(config, estimator, obs.kind, start),
        # gn: the --model-error that ran (its default resolved from the loss), as gn_trust
        "model_error": resolve_model_error(config, obs.kind),
        "material_changes_detected": list(getattr(rec, "changes", [])),  # gn: frames whose innovation widened θ
        # gn: per frame, the change test's normalised innovation rᵀr/(mσ²) (None: not tested)
        "innovation_ratio": [None if not np.isfinite(z) else float(z) for z in getattr(rec, "innovation", [])],
        # gn, images and silhouettes: per frame, the best probe's likelihood ratio (None: not probed; --change-probe)
        "probe_ratio": [None if not np.isfinite(z) else float(z) for z in getattr(rec, "probe", [])],
        # adam, --vision-anchor estimated: per frame, E (per region) of the Gaussians' anchor (the fit frame's material)
        "anchor_young": list(getattr(rec, "anchor_young", [])),
        "anchor_apart_from": getattr(rec, "anchor_apart", None),  # the frame its own material began (None: never)
        # adam, images: the frames at which a later change of material was seen once apart (the lead-in's limit)
        "anchor_later_changes": list(getattr(rec, "anchor_later", [])),
        # adam, --vision-anchor estimated: the change tests, [frame, loss at the level, loss at the window's p, change?]
        "anchor_tests": [list(x) for x in getattr(rec, "anchor_tests", [])],
        # adam, --anchor-calibration: each fit, {"frames": [first, last] (the frames it was fitted to), "young",
        # "poisson" (R,)}: the material of those frames (stages.forces.replay_theta's smoothed θ(t))
        "anchor_calibrations": list(getattr(rec, "calibrations", [])),
        # adam, --recalibrate: the first frame of each later change of material, located (adapt._locate_change)
        "anchor_change_frames": list(getattr(rec, "change_frames", [])),
        # adam, --hold-fit: per frame, E (per region) of the sliding window's own Adam estimate (young: the fit held)
        "window_young": list(getattr(rec, "window_young", [])),
        "ended": "ctrl-c" if ended_by_ctrl_c else ("last frame" if status == "complete" else "error"),
        "wall_s": wall_s,
        "young_meaning": _young_meaning(config, mesh),
        # gn: per frame and region, the relative model-error floor in young_sigma (stages.windows.model_error_floors:
        # --model-error spread over the regions by how weakly the data inform each), the smoother takes it out
        "young_model_error": list(rec.model_error) if len(rec.model_error) == len(rec.frames) else None,
    }
    late = getattr(obs, "late", None)
    if late is not None and (getattr(rec, "late_bindings", []) or late.any()):
        # markers first seen after frame 0: the frames whose window bound them, how many; and those never bound
        extra["late_markers_bound"] = [list(b) for b in getattr(rec, "late_bindings", [])]
        extra["late_markers_unbound"] = int(late.sum())
    start_positions = None
    if loop.moving is not None and -1 in loop.stored:  # start = "moving": the estimated x_{−1}, x_0 (the force
        start_positions = backend.decode(np.stack([loop.stored[-1], loop.stored[0]]))[:, :mesh.n_vertices]  # replay's)
        # per window holding frame 0, the fits of the markers' material points to their tracks (MOVING_REBINDS)
        extra["moving_start_rebinds"] = list(getattr(loop.rec, "moving_rebinds", []))
        # the observed motion of one frame the offsets' prior was scaled by (m; None: 1 % of the object's size)
        extra["moving_start_motion_m"] = getattr(loop.rec, "start_motion", None)
    art = AdaptArtefact(
        frames=frames, young=np.asarray(rec.young), poisson=np.asarray(rec.poisson), z=backend.z(states),
        positions=X, loss=np.asarray(rec.loss), time_forward_s=np.asarray(rec.t_fwd),
        time_backward_s=np.asarray(rec.t_bwd), time_render_s=np.asarray(rec.t_ren),
        time_total_s=np.asarray(rec.t_tot), region_names=names, mode=config.mode, space=backend.space,
        loss_kind=obs.kind, window=config.window if config.mode == "online" else len(frames), extra=extra,
        start_positions=start_positions, **_sigmas(rec))
    path = ws / (KIND_FILES["adapt"] if status == "complete" else PARTIAL_ADAPT)
    art.save(path, Provenance.make(config, inputs_used))
    if status == "complete":
        (ws / PARTIAL_ADAPT).unlink(missing_ok=True)  # superseded by this complete run
    return path


def _sigmas(rec: _Record) -> dict:
    """young_sigma / poisson_sigma (T, R) of the record (NaN where the estimator gives none: Adam without --hold-fit)."""
    T, R = len(rec.frames), len(rec.young[0])
    out = {}
    for k in ("young_sigma", "poisson_sigma"):
        v = getattr(rec, k)
        out[k] = np.asarray(v, float) if len(v) == T else np.full((T, R), np.nan)
    return out


def _young_meaning(config: AdaptConfig, mesh: MeshArtefact) -> str:
    m = mesh.n_tets * 8 ** config.refine
    if mesh.order == 2:
        return (f"E is the modulus of the material as quadratic (10-node) tets resolve it ({m} tets; on the "
                f"sample bar their static sag is within 2.4 % of a fine reference, docs/results/convergence.md), "
                f"under the declared start state; fast motion the time step does not resolve can still bias it.")
    return (f"E is the effective modulus of the linear-tet discretisation used ({m} tets"
            + (f", mesh.h5 refined {config.refine}x" if config.refine else "")
            + "): coarse linear tets are too stiff (they lock as ν → 0.5), so the adapted E is lower than the "
            "continuum E"
            + ("" if config.refine else "; --space full --refine 1 estimates it on a finer mesh") + ".")


def _report(loop: _Loop, reporter: Reporter, names: list[str], dofs: int, mesh: MeshArtefact, path: Path,
            interrupted: bool) -> None:
    """The timing table, what E means, and the summary line."""
    config, backend, rec = loop.config, loop.backend, loop.rec
    med = lambda a: float(np.median(a)) if a else float("nan")  # noqa: E731
    f, b, r, t = med(rec.t_fwd), med(rec.t_bwd), med(rec.t_ren), med(rec.t_tot)
    reporter.info(f"{'space':>8} {'dofs':>7} {'r':>4} {'w':>3} | {'forward':>8} {'backward':>8} "
                  f"{'render':>8} {'total':>8}  (median s/frame)")
    reporter.info(f"{backend.space:>8} {dofs:>7} {backend.dim:>4} {config.window:>3} | "
                  f"{f:8.3f} {b:8.3f} {r:8.3f} {t:8.3f}")
    reporter.info(_young_meaning(config, mesh))
    if loop.rec.damping_profile is not None:
        reporter.info(f"simulated with the viscous damping β = {loop.damping:.3g} s estimated from the first "
                      f"{config.damping_frames} frames (--damping auto)")
    elif loop.damping > 0:
        source = "--damping" if config.damping.strip() else "the capture's [material] damping"
        reporter.info(f"simulated with the viscous damping β = {loop.damping:g} s ({source})")
    E, nu = rec.young[-1], rec.poisson[-1]
    sE, sN = (rec.young_sigma[-1], rec.poisson_sigma[-1]) if rec.young_sigma else ([np.nan] * len(E),) * 2
    # the estimator's 1σ where it gives one (E ± σ: the truth lies inside ±2σ on most settled frames)
    mats = ", ".join(f"{nm}: E={e:.4g}" + (f" ± {se:.2g}" if np.isfinite(se) else "") + f" Pa ν={v:.3f}"
                     + (f" ± {sn:.2g}" if np.isfinite(sn) else "") for nm, e, se, v, sn in zip(names, E, sE, nu, sN))
    stop = " (stopped early)" if interrupted else ""
    late = getattr(rec, "late_bindings", [])
    if late:  # markers first seen after frame 0, bound when a window first saw them
        reporter.info(f"{sum(n for _, n in late)} marker(s) first seen after frame 0 bound to their tracks at frame(s) "
                      + ", ".join(str(t) for t, _ in late))
    cals = getattr(rec, "calibrations", [])
    if cals:  # adam, images: the anchor calibration's fits (E(t) holds each with --hold-fit)
        held = " (E(t) holds each from its last frame)" if _holds_fit(config) else ""
        reporter.info(f"{len(cals)} calibration fit(s){held}: " + "; ".join(
            f"frames {c['frames'][0]}–{c['frames'][1]} E=" + " ".join(f"{e:.4g}" for e in c["young"]) + " Pa"
            for c in cals))
    reporter.summary(f"adapted {len(rec.frames)} frames{stop} {config.mode} in {backend.space} space from "
                     f"{ {'markers': 'markers', 'silhouette': 'silhouettes'}.get(config.loss, 'images')}: {mats} "
                     f"({'E of the material, P2 tets' if mesh.order == 2 else 'effective E of this linear mesh'}); "
                     f"per frame forward {f:.3f} s, backward {b:.3f} s, "
                     f"render {r:.3f} s, total {t:.3f} s → {path}")
