"""A capture filmed mid-motion (``[capture] start = "moving"``, docs/capture.md): frame 0 shows neither the rest
shape nor an equilibrium but an unknown deformation with an unknown velocity.

``rsl adapt`` (--estimator gn) writes frame 0 and the state before it as the static equilibrium under the frame-0
controls with the current θ plus offsets, x_0 = x_e(θ) + Δ_0 and x_{−1} = x_e(θ) + Δ_{−1}
(stages.windows.StartWindow), and estimates the offsets in every window that holds frame 0, together with θ, as
the Gauss–Newton state correction estimates the starting states of later windows:

- Δ = Σ_j a_j b_j on both states (a correction of the shape) and Σ_j v_j b_j on x_{−1} alone (minus the velocity:
  one frame's displacement), b_j the reduced space's unit vectors of z or the full space's lowest vibration modes
  (:func:`start_directions`);
- each coefficient with a zero-mean prior whose σ is about four frames of the observed motion (:func:`start_prior`),
  so that frame 0's markers and the frames after it fix the shape and the velocity.

Where each marker sits on the body is then unknown too: while a window holds frame 0, each marker's material
point is fitted to its track over the window's frames and the window solved again with it held, until it
settles (adapt._rebind_moving_start, stages.sim.markers.fit_binding_to_tracks); then it is held.

With images the shape comes from the masks instead: rsl fit-gaussians poses frame 0 from its silhouettes
(:func:`silhouette_pose`) and fits the Gaussians there, and adapt adds the offsets to that pose x_f rather than to
x_e(θ) (StartWindow.reference), the Gaussians bound as fitted; the prior's motion scale is the silhouette's motion
(:func:`image_motion`).  With the masks alone (``rsl adapt --loss silhouette``, no Gaussians) adapt poses frame 0
with :func:`silhouette_pose` itself and adds the offsets to that pose the same way.  Pure functions over a window
backend, and the pose fit over the capture's masks."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.estimator import Prior, gauss_newton
from stages.window_backends import FullSpace

START_MOTION_SCALE = 4.0
"""Prior σ of the start's shape and velocity offsets, in frames of the observed motion (the RMS marker
displacement from frame 0 to frame 1): all m directions at 1 σ together move the body by this many frames of
motion (RMS over its vertices).  bench/moving_start.py's bar filmed 4 / 8 / 16 frames in, median settled E error
by this scale (markers fitted to their tracks; accuracy_notes.md, seventeenth stop): 1 → 0.4 / 1.2 / 4.0 %;
2 → 0.7 / 0.8 / 3.1 %; 4 → 0.6 / 1.1 / 2.1 %; 8 → 0.6 / 1.2 / 2.7 %; the capture that starts at its equilibrium
1.4 / 1.0 / 1.0 / 1.1 %.  Flat from 2 to 8: the middle, and the least mean error."""


@dataclass(frozen=True)
class StartBasis:
    """The directions a moving start's offsets are written in, and their size."""

    basis: np.ndarray  # (m, state): unit vectors of z (reduced space) or vibration modes (full space)
    gain: np.ndarray  # (m,) m, the RMS vertex displacement per unit coefficient along each direction


def start_basis(backend, state: np.ndarray, young, poisson) -> StartBasis:
    """The directions at the equilibrium ``state``: the reduced space's unit vectors of z, or the full space's
    lowest vibration modes (mass-orthonormal, backend.modes), as stages.windows.state_directions; with their gains
    (decode's derivative along each, RMS over the vertices)."""
    if backend.space == "reduced":
        basis = np.eye(backend.dim)
    else:
        basis = np.asarray(backend.modes(state, young, poisson))
    dX = np.asarray(backend.decode_sensitivity(np.asarray(state)[None], basis[:, None]))[:, 0]  # (m, n, 3)
    return StartBasis(basis, np.sqrt(np.mean(np.sum(dX * dX, axis=-1), axis=-1)))


def marker_motion(markers: np.ndarray) -> float | None:
    """The observed motion of one frame (m): the RMS marker displacement from frame 0 to frame 1 over the markers
    seen in both (markers (T, M, 3) m); None when frame 1 is not there yet or no marker is seen twice."""
    if len(markers) < 2:
        return None
    d = markers[1] - markers[0]
    ok = np.all(np.isfinite(d), axis=-1)
    return float(np.sqrt(np.mean(np.sum(d[ok] ** 2, axis=-1)))) if ok.any() else None


def image_motion(masks: dict | None, cameras: list, centre: np.ndarray) -> float | None:
    """The observed motion of one frame (m) in the masks of frames 0 and 1 (images): per camera the mean normal
    displacement of the silhouette's outline, |m_0 ⊕ m_1| / |∂m_0| pixels (the pixels that change over the
    outline's length), times a pixel's size at the object's depth, z / f_x (``centre`` (3,) m: where the object
    is); the RMS over the cameras.  The outline's motion along itself is not seen, so this is at most the
    markers' s.  None: no masks of frame 1, or no outline."""
    if not masks:
        return None
    out = []
    for cam in cameras:
        m = masks.get(cam.name)
        if m is None or len(m) < 2 or not m[0].any():
            continue
        m0, m1 = np.asarray(m[0], bool), np.asarray(m[1], bool)
        inner = m0.copy()  # the outline: mask pixels with a 4-neighbour outside (or on the image's border)
        inner[1:-1, 1:-1] &= m0[:-2, 1:-1] & m0[2:, 1:-1] & m0[1:-1, :-2] & m0[1:-1, 2:]
        inner[[0, -1], :] = False
        inner[:, [0, -1]] = False
        outline = int(np.count_nonzero(m0 & ~inner))
        z = float((np.asarray(cam.R) @ np.asarray(centre, float) + np.asarray(cam.t).reshape(3))[2])
        if outline == 0 or z <= 0:
            continue
        out.append(np.count_nonzero(m0 ^ m1) / outline * z / float(np.asarray(cam.K)[0, 0]))
    return float(np.sqrt(np.mean(np.square(out)))) if out else None


def start_prior(sb: StartBasis, motion: float | None, size: float) -> np.ndarray:
    """Prior σ (2m,) of the shape and velocity coefficients (:func:`start_directions`):
    σ_j = START_MOTION_SCALE · s / (g_j √m), s the observed motion of one frame (m; :func:`marker_motion`,
    :func:`image_motion`; 1 % of the object's ``size`` m when it is None: frame 1 not there yet), g_j direction
    j's gain."""
    s = 0.01 * size if motion is None else float(motion)
    g = np.maximum(sb.gain, 1e-3 * max(float(sb.gain.max()), 1e-300))
    sigma = START_MOTION_SCALE * max(s, 1e-6 * size) / (g * np.sqrt(len(g)))
    return np.concatenate([sigma, sigma])


def start_directions(sb: StartBasis) -> np.ndarray:
    """D (2m, 2, state) on the offsets (Δ_{−1}, Δ_0) (GNWindow's correction of a window's ``before``): coefficient
    j < m moves both along basis j (the shape), j ≥ m moves Δ_{−1} alone (minus the velocity)."""
    m = len(sb.basis)
    D = np.zeros((2 * m, 2) + sb.basis.shape[1:])
    D[:m, 0] = sb.basis
    D[:m, 1] = sb.basis
    D[m:, 0] = sb.basis
    return D


POSE_MODES = 12
"""A moving start with images: the frame-0 pose's correction beyond the sag is written in the lowest vibration modes
at the frame-0 equilibrium (:func:`silhouette_pose`), as the full space's start offsets are (:func:`start_basis`)."""
POSE_MOTION_FRAMES = 1.0
"""Prior σ of the frame-0 pose's modal correction (:func:`silhouette_pose`), in frames of the masks' motion (as
START_MOTION_SCALE is for the start offsets): all modes at 1 σ together move the body by this many frames of motion.
Measured on the mid-motion beam of bench/moving_images.py (capture.toml's E at 0.5 / 1 / 2 × the truth's, one and
two cameras), the pose's RMS distance to the truth's frame 0 by this prior, 1 / 2 / 4 / 8 frames: mean over six
captures 0.62 / 0.93 / 1.31 / 2.08 mm (one camera, E right: 1.31 / 2.15 / 2.92 / 5.84 mm — its silhouette leaves the
depth free); on bench/accuracy.py's bar (three cameras) 0.79 mm for each."""
POSE_SAG_PRIOR = float(np.log(3.0))
"""Prior σ of the log of the sag's modulus E_s / E (capture.toml's E): a lab's guess of the material within a factor
3 — the sag, one direction the masks see from almost any side, is where a wrong E puts frame 0."""


@dataclass
class PoseProblem:
    """The silhouette pose fit of :func:`silhouette_pose`: unknowns p = (q, a_1..a_m), the pose x(p), the silhouette
    residuals r(p) and ∂r/∂p (``evaluate(p, need_jacobian)``, as stages.estimator.gauss_newton takes it), the
    prior, and what they are made of."""

    evaluate: object  # (p, need_jacobian) -> (r (pixels,), J (pixels, 1 + m) or None)
    pose: object  # p -> (x_e(E_s) (n, 3), x (n, 3)) m
    prior: object  # stages.estimator.Prior over p
    x_e: np.ndarray  # (n, 3) m, the equilibrium of capture.toml's E (p = 0)
    obs: object  # stages.silhouette.SilhouetteObservation
    motion: float | None  # m, the masks' motion from frame 0 to frame 1 (image_motion)
    regions: list  # the mesh's material regions


def pose_problem(capture, ws, mesh, young, poisson, frame: int = 0) -> PoseProblem:
    """:func:`silhouette_pose`'s unknowns, residuals, Jacobian and prior (its docstring gives the model)."""
    from stages.silhouette import SilhouetteObservation  # jax: loaded on use
    from stages.sim.scene import frame_inputs, make_scene
    from stages.sim.static import equilibrium_sensitivity, start_state

    controls = capture.controls()
    scene = make_scene(mesh, controls, capture.material.model, capture.dt, capture.gravity,
                       damping=capture.material.damping)
    inputs = frame_inputs(scene, controls, frame)
    young, poisson = np.asarray(young, float), np.asarray(poisson, float)
    x_e = np.asarray(start_state(scene, inputs, young, poisson, "equilibrium"))
    modes = FullSpace(scene, lambda t: frame_inputs(scene, controls, t), "auto").modes(x_e, young, poisson,
                                                                                     POSE_MODES)
    obs = SilhouetteObservation(capture, ws, "", mesh)
    sb = StartBasis(modes, np.sqrt(np.mean(np.sum(modes * modes, axis=-1), axis=-1)))
    size = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    motion = image_motion(obs.masks, obs._cams, x_e.mean(axis=0))
    sd = np.concatenate([[POSE_SAG_PRIOR], start_prior(sb, motion, size)[:len(modes)] * POSE_MOTION_FRAMES
                         / START_MOTION_SCALE])
    sag: dict[float, np.ndarray] = {0.0: x_e}  # q -> x_e(E_s)

    def pose(p):
        q = float(p[0])
        if q not in sag:
            near = min(sag, key=lambda k: abs(k - q))
            sag[q] = np.asarray(start_state(scene, inputs, young * np.exp(q), poisson, "equilibrium",
                                            x_init=sag[near]))
        return sag[q], sag[q] + np.tensordot(p[1:], modes, axes=1)

    def evaluate(p, need_jac):
        xs, x = pose(p)
        r = obs.residuals([frame], x[None])[0]
        if not need_jac:
            return r, None
        S = equilibrium_sensitivity(scene, inputs, young * np.exp(p[0]), poisson, xs)  # (2R, n, 3): d/dE, d/dν
        d_sag = np.tensordot(young * np.exp(p[0]), S[:len(young)], axes=1)  # dx_e/dq = Σ_r E_r dx_e/dE_r
        return r, obs.jacobian([frame], x[None], np.concatenate([d_sag[None], modes])[:, None])[0]

    return PoseProblem(evaluate, pose, Prior(np.zeros(len(sd)), np.diag(sd ** 2)), x_e, obs, motion,
                       list(scene.region_names))


def silhouette_pose(capture, ws, mesh, young, poisson, frame: int = 0, iterations: int = 15
                    ) -> tuple[np.ndarray, dict]:
    """(x (n, 3) m, description): frame ``frame`` of a moving start posed from its masks —

        x = x_e(E_s) + Σ_j a_j φ_j,   E_s = ``young`` · e^q (one factor for every region),

    x_e(E_s) the static equilibrium under that frame's controls with E_s and ``poisson`` (the sag: where a wrong E
    in capture.toml puts frame 0), φ_j the POSE_MODES lowest vibration modes at x_e(``young``) (the motion: frame 0
    is mid-motion), fitted by Gauss–Newton (stages.estimator.gauss_newton) to the silhouette residuals of masks.h5
    (stages.silhouette: the soft coverage of the posed surface against the masks, geometry alone) under zero-mean
    priors: σ_q = POSE_SAG_PRIOR, and a_j the start offsets' prior scaled to POSE_MOTION_FRAMES frames of the
    masks' motion from frame 0 to frame 1 (:func:`start_prior`, :func:`image_motion`) — what one camera's
    silhouette does not fix stays near the equilibrium; solved twice, the second time with the data's variance
    scaled by the first solve's cluster-robust s² (estimator.cluster_scale2).  The Gaussians are fitted at x (rsl
    fit-gaussians), and rsl adapt adds its estimated offsets to it: the pose a moving start's images show, not the
    one capture.toml's E would sag to."""
    pp = pose_problem(capture, ws, mesh, young, poisson, frame)
    evaluate, prior, obs, x_e = pp.evaluate, pp.prior, pp.obs, pp.x_e
    p0 = np.zeros(len(prior.mean))
    r0 = evaluate(p0, False)[0]
    sigma = max(obs.noise_scale(r0), obs.noise_floor)
    # the pixels along the outline share their errors (8 × 8 blocks, stages.silhouette): solved once more with the
    # data term's variance scaled by the cluster-robust s² of the first solve, so that the prior holds what the
    # masks see only through correlated pixels (one camera's depth: 7.0 → 2.9 mm from the truth's frame 0)
    clusters = obs.clusters([frame])
    first = gauss_newton(evaluate, p0, prior, sigma, max_iterations=iterations, tol=1e-3, clusters=clusters)
    scale2 = max(first.scale2, 1.0)
    res = gauss_newton(evaluate, p0, prior, sigma, max_iterations=iterations, tol=1e-3, clusters=clusters,
                       scale=scale2) if scale2 > 1.0 else first
    x = pp.pose(res.p)[1]
    r1 = evaluate(res.p, False)[0]
    moved = float(np.sqrt(np.mean(np.sum((x - x_e) ** 2, axis=-1))))
    return x, {"pose": "capture", "start": "silhouette", "declared_start": "moving", "frame": int(frame),
               "regions": pp.regions, "young": np.asarray(young, float).tolist(),
               "poisson": np.asarray(poisson, float).tolist(), "sag_young_factor": float(np.exp(res.p[0])),
               "modes": int(len(prior.mean) - 1), "moved_m": moved, "motion_m": pp.motion, "data_scale2": scale2,
               "silhouette_rms": [float(np.sqrt(np.mean(r0 * r0))), float(np.sqrt(np.mean(r1 * r1)))]}
