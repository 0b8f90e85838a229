"""The material of the Gaussians' anchor, online (`rsl adapt --loss vision --estimator adam`, ``--vision-anchor
estimated``).

The Gaussians are fitted to the images of their fit frame f; online they are re-bound to x_f(θ_a), frame f simulated
from the start with the material θ_a = θ(p_a), p_a = (log E, s) (2R,).  p_a should be the fit frame's material: the
window's current θ as long as the material has not changed since f, the old material once it has (re-simulating
frame f with the new material moves the anchor and holds E back: docs/results/vision_bias.md).  :class:`AnchorMaterial`
keeps p_a and decides, frame by frame, by this rule (p_T: the window's parameters after frame T's update):

1. **tied** — while the window holds f, and until a change of material is confirmed: p_a = p.
2. **candidate** — the window's log E (in one region) has been more than c/2 from its *level*, the median of p
   over frames T−6..T−3 (the frames whose window informed θ: one at rest, or holding f alone, took no step and
   leaves no estimate — the dinosaur's 10 frames before its pusher arrives would make the initial E the level),
   on the same side in each of the last 2 frames, and more than c (``--anchor-change``) in
   at least one of them: a threshold with hysteresis, so that an estimate hovering at c (log E − level 0.466
   then 0.398 around c = 0.4: held back by the tied anchor itself, it falls again) is still a candidate, while
   one frame's excursion past c alone is not.  Converging from a far-off start, Adam moves as far and as fast
   as after a change (from 4x too soft: log E +0.8 in 4 frames after a 4-frame plateau), so this alone cannot
   tell them apart.
3. **test** — which material explains the frames after the fit frame better, the level p_L or the current p_T:
   the loss Σ_{t∈F} loss_t(X_t(θ(p))) of the frames F = f+1 .. T−3 (at most 4w of them, those the level was
   estimated from), simulated from the start with θ(p), the anchor at θ(p) too.  A change since f leaves them
   showing the old material, so the level explains them better: p_a becomes its own unknown, started at p_L.  A
   convergence explains them better with the current estimate: the candidate is dropped and the level's history
   restarts at T (the next candidate at T+7 at the earliest).  No frame in F yet: the test waits.
4. **apart** — p_a is moved by its own Adam along dL/dp_a, the anchor's part of the window's gradient alone
   (WindowObjective.last_anchor_g), so that it stays near the old material while the window's θ follows the new.
   (Held at the level instead, measured 2026-11-24 on bench/accuracy.py's captures, images, reduced space: better
   where the level had settled — bar with E steps, lead-in 3: 7.0 % median settled E error against 9.1 %; the
   dinosaur (constant E, a spurious change confirmed at frame 26 at the level 1.07 E_true, after which p_a's own
   Adam climbed to 1.5 E_true and E with it): 13.9 % against 20.7 % — and much worse where it had not — the bar
   without lead-in, level 0.77 E_true: 46.9 % against 30.5 %.)

With c = 0, p_a is its own unknown as soon as the window no longer holds f (no test).

0. **calibrated** (AdaptConfig.anchor_calibration K > 0, instead of rules 1–4) — the window grows from the first
   frame, anchor tied, until K informed frames; θ is then fitted to all of them, and p_a is held at that fit from
   then on (:meth:`AnchorMaterial.calibrated`): the material is taken to be constant over those first frames.
   With AdaptConfig.recalibrate, each later change rule 5 sees is located (the frame that splits the frames since
   the last fit best into the old and the new material) and has the window's θ refitted the same way over a window
   grown from there (:meth:`AnchorMaterial.restart_watch` then makes that fit rule 5's level); p_a stays.

5. **later changes** (c > 0) — once p_a is apart, the candidate of rule 2 is still watched (against a level whose
   history restarts after each; with rule 0, the last fit itself): it marks a later change of material (or a late
   convergence) without a test, since p_a stays the fit frame's material in either case.  What it limits is the lead-in (AdaptConfig.lead_in):
   :attr:`AnchorMaterial.lead_from`, the first frame a window's lead-in may re-simulate with its θ, is the frame
   of the last change, confirmed (rule 3) or later (this rule) — frames before it showed another material, and
   re-simulating them with the new one holds E back (bar with E ×2, ×4, lead-in 3: E at 0.49–0.84 E_true through
   the 12 frames after the ×4 step).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from stages.parameters import Adam

LEVEL = (3, 6)  # the level: the median of p over frames T−6..T−3
AWAY = 2  # the candidate's frames in a row: log E more than HOLD·c from the level in each, more than c in one
HOLD = 0.5  # the hysteresis: the fraction of c the window's log E must stay beyond in each of the AWAY frames
TEST_WINDOWS = 4  # the test's frames F: at most this many windows' worth


class AnchorMaterial:
    """p_a (2R,), the material the Gaussians' anchor x_f is simulated with, by the rule of this module's docstring.

    Per frame T of the online loop: :meth:`held` before the window's Adam steps (the ``anchor_p`` the window
    objective takes: None while tied), :meth:`after_step` after each of them, :meth:`end_frame` once the frame's
    update is done.  ``apart_from``: the frame from which p_a was its own unknown (None: never); ``tests``: one
    (T, loss at the level, loss at p_T, change?) per test made."""

    def __init__(self, p0: np.ndarray, lr: np.ndarray, beta1: float, n_regions: int, change: float, window: int,
                 fit_frame: int, first: int = 0):
        self.p = np.array(p0, float)  # (2R,) = (log E, s)
        self.adam = Adam(lr, beta1=beta1)  # p_a's optimiser: its moments see the anchor's part from frame 0 on
        self.R, self.change, self.window = n_regions, float(change), window
        self.fit_frame, self.first = fit_frame, first
        self.apart_from: int | None = None
        self.later: list[int] = []  # the frames at which rule 5 saw a later change (after apart_from)
        self._later: tuple[list, list] = ([], [])  # rule 5's (p per frame, deviations) since the last change
        self._quiet = 0  # frames rule 5 still passes over after a fit (restart_watch's ``quiet``)
        self.hist: list[np.ndarray] = []  # p per frame since the level's history (re)started
        self.devs: list[np.ndarray] = []  # log E − level (R,) per untied frame with a level, since the restart
        self.tests: list[tuple[int, float, float, bool]] = []
        self._held = False
        self.fixed = False  # rule 0: p_a held at the calibrated material

    @property
    def apart(self) -> bool:
        return self.apart_from is not None

    @property
    def lead_from(self) -> int | None:
        """The frame of the last change of material seen (rules 3 and 5), before which a lead-in must not reach;
        None: none seen."""
        return self.later[-1] if self.later else self.apart_from

    def calibrated(self, p: np.ndarray, T: int, quiet: int = 0) -> None:
        """Rule 0: p_a = p (2R,), the material fitted to the first frames, held from frame T on (no own steps, no
        tests; rule 5 still watches for later changes, which limit the lead-in; ``quiet``: restart_watch's)."""
        self.p, self.apart_from, self.fixed = np.array(p, float), T, True
        self.restart_watch(p, quiet)

    def restart_watch(self, p: np.ndarray, quiet: int = 0) -> None:
        """Rule 5 restarts at p (2R,), the window's θ (re)fitted: with the anchor calibrated, p is rule 5's level
        from then on (a fit to all the frames since the last change, not a median of the sliding window's steps,
        which follow a step of E slowly enough to drag a running level along and hide it).  Rule 5 passes over the
        next ``quiet`` frames: a restarted Adam's first steps are lr in size whatever the gradient."""
        self._later, self._quiet = ([np.array(p, float)], []), int(quiet)

    def held(self, T: int, tied: bool) -> np.ndarray | None:
        """Before frame T's steps: p_a held apart from the window's p, or None while tied (``tied``: the window holds
        the fit frame, where the anchor is the window's material in any case)."""
        if self.fixed:
            self._held = True
            return self.p
        if not self.apart and not tied and self.change <= 0:  # c = 0: its own unknown from here on
            self.apart_from = T
        self._held = self.apart and not tied
        return self.p if self._held else None

    def after_step(self, p: np.ndarray, g_anchor: np.ndarray | None, idle: bool) -> np.ndarray | None:
        """After one Adam step of the window's p (2R,): p_a's own step along dL/dp_a ``g_anchor`` (2R,; None: no
        anchor part), then p_a = p while tied.  Returns the ``anchor_p`` for the next evaluation."""
        if self.fixed:
            return self.p
        if g_anchor is not None and not idle:
            self.p = self.adam.step(self.p, g_anchor)
        if not self._held:
            self.p = np.array(p, float)
            return None
        return self.p

    def level(self) -> np.ndarray | None:
        """The median of p over frames T−6..T−3 (2R,), None before 7 frames of history."""
        a, b = LEVEL
        if len(self.hist) < b + 1:
            return None
        return np.median(np.stack(self.hist[-(b + 1):-a]), axis=0)

    def candidate(self, devs: list | None = None) -> bool:
        """Whether the last AWAY deviations d = log E − level (R,) (``devs``, default: rule 2's) make a candidate: in
        some region r, |d_r| > HOLD·c with one sign in each of them and |d_r| > c in at least one (rule 2 of the
        module's docstring)."""
        devs = self.devs if devs is None else devs
        if len(devs) < AWAY:
            return False
        d = np.stack(devs[-AWAY:])  # (AWAY, R)
        held = np.all(d > HOLD * self.change, axis=0) | np.all(d < -HOLD * self.change, axis=0)
        return bool(np.any(held & (np.max(np.abs(d), axis=0) > self.change)))

    def test_frames(self, T: int) -> list[int]:
        """F: the frames after the fit frame the level was estimated from, f+1 .. T−3, at most 4w of them."""
        lo = max(self.fit_frame + 1, self.first)
        hi = min(T - LEVEL[0], lo + TEST_WINDOWS * self.window - 1)
        return list(range(lo, hi + 1))

    def end_frame(self, T: int, p: np.ndarray, tied: bool,
                  explains: Callable[[Sequence[int], np.ndarray], float], informed: bool = True) -> bool:
        """After frame T's update (p: the window's parameters (2R,)): the candidate and, when there is one, the test.
        ``explains(F, p)`` = Σ_{t∈F} loss_t of the frames F simulated from the start with θ(p) (the anchor at θ(p)).
        ``informed`` False: the window had no information on θ (it took no step: the object at rest, or the fit
        frame alone), so p is no estimate and stays out of the level's history.  Returns True when p_a became its
        own unknown at this frame."""
        if not informed:
            return False
        self.hist.append(np.array(p, float))
        if self.apart:
            self._watch(T, p)
            return False
        if tied:
            return False
        level = self.level()
        if level is None:
            return False
        R = self.R
        self.devs.append(np.asarray(p[:R], float) - level[:R])
        if not self.candidate():
            return False
        F = self.test_frames(T)
        if not F:
            return False  # nothing to test on yet: test again at the next frame
        at_level, at_p = explains(F, level), explains(F, np.array(p, float))
        changed = bool(at_level < at_p)
        self.tests.append((T, float(at_level), float(at_p), changed))
        if changed:
            self.apart_from, self.p = T, level
            self._later = ([np.array(p, float)], [])  # rule 5's level history starts at the change
        else:  # a convergence: the level's history restarts here
            self.hist, self.devs = [np.array(p, float)], []
        return changed

    def _watch(self, T: int, p: np.ndarray) -> None:
        """Rule 5, once apart: rule 2's candidate against the level of the frames since the last change; a candidate
        is a later change at T (appended to :attr:`later`) and restarts that history."""
        if self.change <= 0:  # c = 0: every sign-consistent wobble would be a candidate
            return
        if self._quiet > 0:
            self._quiet -= 1
            return
        hist, devs = self._later
        if self.fixed:  # rule 0: the level is the last fit (restart_watch), the history's only entry
            level = hist[0]
        else:
            hist.append(np.array(p, float))
            a, b = LEVEL
            if len(hist) < b + 1:
                return
            level = np.median(np.stack(hist[-(b + 1):-a]), axis=0)
        devs.append(np.asarray(p[:self.R], float) - level[:self.R])
        if self.candidate(devs):
            self.later.append(T)
            self._later = ([np.array(p, float)], [])
