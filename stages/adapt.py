"""Stage ``rsl adapt``: online real-to-sim adaptation of E and ν per region (paper §3–4).

Online, at each new frame T_e the window W = T_e−w+1..T_e is re-simulated from the two stored
states before it with the current θ = (E, ν) per region, the window loss L (vision, Eq. 7, or
markers, Eq. 4 windowed) and dL/dX are evaluated, the adjoint over the window turns dL/dX into
dL/dθ (θ shared by the window frames: the per-frame gradients are summed), and a few Adam steps
move the parameters p = (log E, s) with ν = ν_lo + (ν_hi − ν_lo)·sigmoid(s).  The window's
states are then stored; a state is final once its frame leaves the window.

Observations are anchored at frame 0 (one step from rest): markers are bound to the frame-0 surface
simulated with the current θ, and Gaussians fitted with the mesh at rest to frame f are re-bound to the
tets of frame f simulated with the current θ (``gaussian_anchor = "rebind"``: rendered at x_f they are
exactly the fitted Gaussians; the older first-order ``"offset"`` renders at x_t − (x_f − rest), which
biased E low by 10–20 % on the dinosaur, whose frame 0 sags up to 11 mm below rest); both anchors are
refreshed as θ changes.  adapt.h5 stores, per frame, θ after
that frame's Adam steps, the frame's final state (z and positions), the window loss and the time
spent in forward simulation, adjoint, rendering (loss forward + backward) and in total.

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
from typing import Callable, Literal, Sequence

import numpy as np

from stages.adapt_loss import (Adam, MarkerBinding, bind_markers, chain_params, marker_residuals,
                               params_from_theta, theta_from_params)
from stages.artefacts import KIND_FILES, AdaptArtefact, MeshArtefact, Provenance
from stages.capture import IMAGE_SUFFIXES, Capture, CaptureError, load_capture, read_image
from stages.errors import RslError
from stages.progress import Reporter, SilentReporter


@dataclass(frozen=True)
class AdaptConfig:
    capture: Path
    """Capture folder (capture.toml, frames/, controls.json, markers.csv)."""
    workspace: Path
    """Workspace folder holding mesh.h5 and the other artefacts; adapt.h5 is written there."""
    window: int = 5
    """Sliding-window size w: frames re-simulated and compared at each new frame."""
    space: Literal["reduced", "full"] = "reduced"
    """Simulate in the neural subspace (needs subspace.h5) or in the full FEM space."""
    mode: Literal["online", "offline"] = "online"
    """online: sliding window, θ updated every frame; offline: one θ fitted to the whole sequence."""
    loss: Literal["vision", "markers"] = "vision"
    """Observation: rendered Gaussians vs images (needs gaussians.h5, cameras.h5) or markers.csv."""
    cameras: str = ""
    """Cameras used by the vision loss: indices or names, comma separated (empty: all)."""
    frames: str = ""
    """Frame range A:B (B exclusive; empty: every frame)."""
    iters_per_frame: int = 2
    """Adam steps per new frame (online) — each one a forward, a loss and an adjoint over the window."""
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
    """Initial ν for every region (default: capture.toml)."""
    fit_poisson: bool = True
    """Adapt ν as well as E (ν stays inside capture.toml's poisson_range)."""
    refine: int = 0
    """Full space only: split every tet into 8 this many times (E of a finer discretisation)."""
    appearance: bool = False
    """Vision loss: also refine Gaussian colours and opacities by the same loss."""
    gaussian_anchor: Literal["rebind", "offset"] = "rebind"
    """Vision loss: how the Gaussians (fitted with the mesh at rest to the images of their fit frame f) follow
    the simulation.  rebind: each Gaussian is re-bound to the tet of frame f simulated with the current θ that
    holds it (exact at frame f); offset: rendered at x_t − (x_f − rest) (first order in x_f − rest; biased
    when frame f is far from rest)."""
    follow: bool = False
    """Process frames as they appear in the capture folder; Ctrl-C ends with everything saved."""
    follow_timeout: float = 0.0
    """With --follow: stop after this many seconds without a new frame (0: wait until Ctrl-C)."""
    solver: str = "auto"
    """Linear solver of the full-space Newton steps (passed to stages.sim)."""
    seed: int = 0
    """Seed of every random choice (none at present; kept for reruns)."""


# =========================================================================== backends
class _FullSpace:
    """Full-space FEM window simulation and adjoint (stages.sim.scene). State = positions (n, 3)."""

    space = "full"

    def __init__(self, scene, inputs: Callable[[int], object], solver: str):
        self.scene, self.inputs, self.solver = scene, inputs, solver
        self.dim = 0

    @property
    def rest_state(self) -> np.ndarray:
        return np.asarray(self.scene.rest)

    def decode(self, states: np.ndarray) -> np.ndarray:
        return states

    def z(self, states: np.ndarray) -> np.ndarray:
        return np.zeros((len(states), 0))

    def forward(self, frames: Sequence[int], young: np.ndarray, poisson: np.ndarray,
                before: np.ndarray) -> np.ndarray:
        """States (w, n, 3) of ``frames`` from ``before`` = [x_{t0−2}, x_{t0−1}]; young/poisson (w, R)."""
        from stages.sim.scene import simulate

        return np.asarray(simulate(self.scene, [self.inputs(t) for t in frames], young, poisson,
                                   x_prev=before[1], x_prev2=before[0], solver=self.solver))

    def backward(self, frames: Sequence[int], young: np.ndarray, poisson: np.ndarray, states: np.ndarray,
                 before: np.ndarray, dL_dX: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(dL/dE, dL/dν), each (w, R): one row per window frame's θ."""
        from stages.sim.scene import window_adjoint

        g = window_adjoint(self.scene, [self.inputs(t) for t in frames], young, poisson, states, before, dL_dX)
        return np.asarray(g["young"]), np.asarray(g["poisson"])


class _ReducedSpace:
    """Reduced window simulation and adjoint (stages.subspace.ReducedModel). State = z (r,)."""

    space = "reduced"

    def __init__(self, model, inputs: Callable[[int], object]):
        self.model, self._inputs = model, inputs
        self.dim = int(model.dim)
        self._rin: dict[int, object] = {}

    def inputs(self, t: int):
        """ReducedInputs of frame t (cached: the projection of loads is done once)."""
        if t not in self._rin:
            self._rin[t] = self.model.reduce_inputs(self._inputs(t))
        return self._rin[t]

    @property
    def rest_state(self) -> np.ndarray:
        return np.asarray(self.model.z_rest)

    def decode(self, states: np.ndarray) -> np.ndarray:
        return np.asarray(self.model.decode(states))

    def z(self, states: np.ndarray) -> np.ndarray:
        return np.asarray(states)

    def forward(self, frames, young, poisson, before):
        return np.asarray(self.model.simulate([self.inputs(t) for t in frames], young, poisson,
                                              z_prev=before[1], z_prev2=before[0]))

    def backward(self, frames, young, poisson, states, before, dL_dX):
        """dL/dX → dL/dZ = Jᵀ dL/dX → reduced adjoint over the window → (dL/dE, dL/dν) (w, R)."""
        g = self.model.window_adjoint([self.inputs(t) for t in frames], young, poisson, states, before,
                                      dL_dX=dL_dX)
        return np.asarray(g["young"]), np.asarray(g["poisson"])


# =========================================================================== observations
class _Markers:
    """Marker observations (markers.csv) bound to the rest surface."""

    kind = "markers"

    def __init__(self, capture: Capture, vertices: np.ndarray, faces: np.ndarray, n_vertices: int):
        self.capture, self.faces, self.n = capture, faces, n_vertices
        self.P = self._read()
        self.rebind(vertices)
        far = float(self.binding.distance.max())
        diag = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
        self.far = far / max(diag, 1e-12)

    def rebind(self, x0: np.ndarray) -> None:
        """Bind each marker to the point of the frame-0 surface x0 (n, 3) nearest its frame-0 position."""
        self.binding: MarkerBinding = bind_markers(x0[:self.n], self.faces, self.P[0])

    def _read(self) -> np.ndarray:
        P = self.capture.markers()
        if P is None:
            raise CaptureError(f"{self.capture.markers_path}: file not found; --loss markers needs markers.csv.")
        return P

    def available(self) -> int:
        """Frames observed so far (markers.csv is re-read: it may grow in --follow mode).  Since a marker may
        be missing from a frame (a gap), a writer in --follow mode should add each frame's rows at once
        (e.g. write a new file and rename it over markers.csv): the rows of a frame read while still being
        written count as gaps."""
        if self.capture.markers_path.exists():
            try:
                self.P = self._read()
            except CaptureError:
                pass  # a half-written line: keep what we had
        return len(self.P)

    def loss(self, frames: Sequence[int], X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame losses (w,) and dL/dX (w, n, 3) for X on the mesh (n, 3) per frame; only the observed
        markers count (a gap, NaN in markers.csv's array, adds nothing; a frame seeing none gives 0)."""
        P = self.P[list(frames)]
        r = marker_residuals(self.binding, X[:, :self.n], P)
        grad = np.zeros_like(X)
        grad[:, :self.n] = self.binding.scatter(2.0 * r, self.n)
        return np.sum(r * r, axis=(1, 2)), grad


class _Vision:
    """Image observations: render the Gaussians bound to the mesh in each chosen camera (stages.render)."""

    kind = "vision"

    def __init__(self, capture: Capture, ws: Path, cam_spec: str, mesh: MeshArtefact, appearance: bool,
                 anchor: str = "rebind"):
        from stages.artefacts import CamerasArtefact, GaussiansArtefact, MasksArtefact
        from stages.adapt_loss import ImageLoss

        self.capture, self.n = capture, mesh.n_vertices
        cams_art = CamerasArtefact.load(ws / KIND_FILES["cameras"])
        gauss = GaussiansArtefact.load(ws / KIND_FILES["gaussians"])
        masks_path = ws / KIND_FILES["masks"]
        self.masks = MasksArtefact.load(masks_path).masks if masks_path.exists() else None
        self.cameras = _pick_cameras(cam_spec, [c.name for c in cams_art.cameras], ws / KIND_FILES["cameras"])
        for name in self.cameras:
            if name not in capture.camera_names:
                raise CaptureError(f"{capture.toml_path}: camera '{name}' of cameras.h5 is not listed in "
                                   f"[capture] cameras.")
        self.sources = {c: capture.frame_source(c) for c in self.cameras}
        self.loss_fn = ImageLoss(gauss, mesh, [cams_art.by_name(c) for c in self.cameras], appearance=appearance)
        # Without masks the renders are composited over the capture's background plates (when there are
        # any) and compared with the raw frames; with masks, the frames' backgrounds are replaced.
        self.plates = {c: (None if self.masks is not None and c in self.masks else capture.background(c))
                       for c in self.cameras}
        self.loss_fn.set_backgrounds([None if p is None else p.astype(np.float32) / 255.0
                                      for p in self.plates.values()])
        self._cache: dict[int, list[np.ndarray]] = {}
        # The Gaussians were fitted to frame ``fit_frame`` with the mesh at rest: they are anchored to the
        # object's configuration at that frame, x_fit simulated with the current θ (re-anchored as θ
        # changes, like the marker binding; the anchor is held fixed within one gradient).  "rebind":
        # re-bound to the tets of x_fit (ImageLoss.rebind), rendered at x_t; "offset": rendered at
        # x_t − (x_fit − rest) (first order in x_fit − rest).
        from stages.artefacts import read_provenance

        if anchor not in ("rebind", "offset"):
            raise RslError(f"gaussian_anchor should be 'rebind' or 'offset', found '{anchor}'.")
        self.anchor_kind = anchor

        self.fit_frame = int(read_provenance(ws / KIND_FILES["gaussians"]).get("config", {}).get("frame", 0) or 0)
        self.rest = mesh.vertices
        self.anchor = np.zeros_like(mesh.vertices)  # (n, 3) x_fit − rest

    def rebind(self, x_fit: np.ndarray) -> None:
        """Anchor the Gaussians at the simulated fit-frame positions x_fit (n, 3)."""
        if self.anchor_kind == "rebind":
            self.loss_fn.rebind(x_fit[:self.n])
        else:
            self.anchor = x_fit[:self.n] - self.rest

    def available(self) -> int:
        """Frames whose images exist and decode in every chosen camera (counted on from the last call)."""
        n = getattr(self, "_n_ready", 0)
        while _frame_ready(self.capture, self.cameras, n):
            n += 1
        self._n_ready = n
        return n

    def targets(self, t: int) -> list[np.ndarray]:
        """Masked images Ĩ_t^c = I·m + bg·(1 − m) (raw I without masks), float32 (H, W, 3) in [0, 1]."""
        if t not in self._cache:
            out = []
            for c in self.cameras:
                img = _read_frame(self.capture, c, t).astype(np.float32) / 255.0
                if self.masks is not None and c in self.masks and t < len(self.masks[c]):
                    m = self.masks[c][t][..., None].astype(np.float32)
                    img = img * m + self.loss_fn.background[None, None, :] * (1 - m)
                out.append(img)
            self._cache[t] = out
            for old in [k for k in self._cache if k < t - 64]:
                del self._cache[old]
        return self._cache[t]

    def loss(self, frames: Sequence[int], X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        losses, grad = np.zeros(len(frames)), np.zeros_like(X)
        for i, t in enumerate(frames):
            li, gi = self.loss_fn(X[i, :self.n] - self.anchor, self.targets(t))
            losses[i], grad[i, :self.n] = li, gi
        return losses, grad


def _pick_cameras(spec: str, names: list[str], path: Path) -> list[str]:
    if not spec.strip():
        return list(names)
    out = []
    for tok in (s.strip() for s in spec.split(",") if s.strip()):
        if tok.isdigit():
            k = int(tok)
            if k >= len(names):
                raise RslError(f"{path}: --cameras asks for camera {k} but it holds {len(names)} cameras.")
            out.append(names[k])
        elif tok in names:
            out.append(tok)
        else:
            raise RslError(f"{path}: --cameras names '{tok}', which is not one of {', '.join(names)}.")
    return list(dict.fromkeys(out))


def _frame_file(capture: Capture, cam: str, t: int) -> Path | None:
    folder = capture.root / "frames" / cam
    for stem in (f"{t:06d}", str(t)):
        for suf in IMAGE_SUFFIXES:
            p = folder / f"{stem}{suf}"
            if p.is_file():
                return p
    return None


def _read_frame(capture: Capture, cam: str, t: int) -> np.ndarray:
    p = _frame_file(capture, cam, t)
    if p is None:
        return capture.frame_source(cam).read(t)
    return read_image(p)


def _frame_ready(capture: Capture, cams: Sequence[str], t: int) -> bool:
    """Frame t counts when every camera's image for it exists and decodes completely."""
    import cv2

    for c in cams:
        p = _frame_file(capture, c, t)
        if p is None:
            return False
        data = np.fromfile(p, dtype=np.uint8)
        if p.suffix.lower() == ".png" and not data[-12:].tobytes().endswith(b"IEND\xaeB`\x82"):
            return False  # still being written
        if data.size == 0 or cv2.imdecode(data, cv2.IMREAD_COLOR) is None:
            return False
    return True


# =========================================================================== the window objective
class WindowObjective:
    """L(p) over a window of frames and dL/dp, p = (log E (R,), s (R,)), θ shared by the window:

        X = sim(θ; x_{t0−2}, x_{t0−1}),  L = Σ_t loss_t(X_t),
        dL/dθ = Σ_t (adjoint over the window of dL/dX)_t,  dL/dp by the chain rule of the transforms.

    The observation is first re-anchored with θ: markers are bound to the frame-0 surface simulated with
    θ, Gaussians anchored at their fit frame simulated with θ (held fixed within the gradient).
    """

    def __init__(self, backend, obs, n_regions: int, poisson_range: tuple[float, float]):
        self.backend, self.obs, self.R, self.prange = backend, obs, n_regions, poisson_range
        self.rebind = True
        self.anchor_frame = int(getattr(obs, "fit_frame", 0))
        rest = backend.rest_state
        self._rest2 = np.stack([rest, rest])

    def anchor_positions(self, E: np.ndarray, nu: np.ndarray) -> np.ndarray:
        """The anchor frame (0 for markers, the Gaussians' fit frame for images) simulated from rest with θ,
        positions (n, 3)."""
        k = self.anchor_frame + 1
        X = self.backend.forward(list(range(k)), np.tile(E, (k, 1)), np.tile(nu, (k, 1)), self._rest2)
        return self.backend.decode(X[-1:])[0]

    def __call__(self, frames: Sequence[int], p: np.ndarray, before: np.ndarray, need_grad: bool = True):
        """(states (w, …), per-frame losses (w,), dL/dp (2R,) or None, (forward_s, backward_s, loss_s))."""
        R, backend = self.R, self.backend
        E, nu = theta_from_params(p[:R], p[R:], self.prange)
        w = len(frames)
        Ew, nuw = np.tile(E, (w, 1)), np.tile(nu, (w, 1))
        t0 = time.perf_counter()
        if self.rebind:
            self.obs.rebind(self.anchor_positions(E, nu))
        states = backend.forward(list(frames), Ew, nuw, before)
        X = backend.decode(states)
        t1 = time.perf_counter()
        losses, dX = self.obs.loss(frames, X)
        t2 = time.perf_counter()
        g = None
        if need_grad:
            dE, dnu = backend.backward(list(frames), Ew, nuw, states, before, dX)
            g = np.concatenate(chain_params(dE.sum(0), dnu.sum(0), E, p[R:], self.prange))
        t3 = time.perf_counter()
        return states, losses, g, (t1 - t0, t3 - t2, t2 - t1)


# =========================================================================== mesh refinement
def refine_tets(vertices: np.ndarray, tets: np.ndarray, tet_region: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split every tet into 8 through its edge midpoints (Bey 1995); the first n vertices are the
    original ones, so positions of the coarse mesh are a prefix of the fine mesh's."""
    n = len(vertices)
    edges = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])
    e = np.sort(tets[:, edges].reshape(-1, 2), axis=1)
    uniq, inv = np.unique(e, axis=0, return_inverse=True)
    mid = 0.5 * (vertices[uniq[:, 0]] + vertices[uniq[:, 1]])
    m = inv.reshape(-1, 6) + n  # midpoint ids: 01 02 03 12 13 23
    a, b, c, d = tets.T
    m01, m02, m03, m12, m13, m23 = m.T
    children = [
        (a, m01, m02, m03), (m01, b, m12, m13), (m02, m12, c, m23), (m03, m13, m23, d),
        (m01, m02, m03, m13), (m01, m02, m12, m13), (m02, m03, m13, m23), (m02, m12, m13, m23),
    ]
    new = np.stack([np.stack(ch, axis=1) for ch in children], axis=1).reshape(-1, 4)
    verts = np.vstack([vertices, mid])
    # keep positive orientation
    p = verts[new]
    vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    flip = vol < 0
    new[flip] = new[flip][:, [0, 2, 1, 3]]
    return verts, new, np.repeat(tet_region, 8)


def _refined_mesh(mesh: MeshArtefact, levels: int) -> MeshArtefact:
    from stages.sim.mesh import rest_quantities

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
    from stages.sim.scene import frame_inputs, make_scene

    ws = Path(config.workspace)
    capture = load_capture(config.capture)
    if config.window < 1:
        raise RslError(f"{capture.toml_path}: --window must be at least 1, found {config.window}.")
    if config.iters_per_frame < 1 or config.offline_iters < 1:
        raise RslError(f"{capture.toml_path}: --iters-per-frame and --offline-iters must be at least 1.")
    if config.refine and config.space != "full":
        raise RslError(f"{ws / KIND_FILES['subspace']}: --refine needs --space full (the subspace is "
                       f"trained on mesh.h5's vertices).")
    mesh_path = ws / KIND_FILES["mesh"]
    mesh = MeshArtefact.load(mesh_path)
    controls = capture.controls()
    sim_mesh = _refined_mesh(mesh, config.refine) if config.refine else mesh
    scene = make_scene(sim_mesh, controls, capture.material.model, capture.dt, capture.gravity)
    n = mesh.n_vertices
    inputs_cache: dict[int, object] = {}

    def inputs(t: int):
        if t not in inputs_cache:
            inputs_cache[t] = frame_inputs(scene, controls, t)
        return inputs_cache[t]

    inputs_used = [mesh_path, capture.toml_path, capture.controls_path]
    if config.space == "full":
        backend = _FullSpace(scene, inputs, config.solver)
    else:
        from stages.artefacts import SubspaceArtefact
        from stages.subspace import ReducedModel

        sub_path = ws / KIND_FILES["subspace"]
        backend = _ReducedSpace(ReducedModel.from_artefacts(SubspaceArtefact.load(sub_path), scene), inputs)
        inputs_used.append(sub_path)

    R = scene.n_regions
    names = list(scene.region_names)
    mat = capture.material
    young0 = np.array([config.young_init or mat.region_young(r) for r in names], float)
    poisson0 = np.array([config.poisson_init if config.poisson_init is not None else mat.region_poisson(r)
                         for r in names], float)
    if config.loss == "markers":
        # Markers bind to the simulated frame-0 surface; the binding is refreshed as θ changes
        # (frame 0 is already one step from rest, so it depends on θ).
        rest = backend.rest_state
        x0 = backend.decode(backend.forward([0], young0[None], poisson0[None], np.stack([rest, rest])))[0]
        obs = _Markers(capture, x0, mesh.surface_faces, n)
        inputs_used.append(capture.markers_path)
        if obs.far > 0.05:
            reporter.warn(f"{capture.markers_path}: a frame-0 marker lies {obs.far:.1%} of the object size "
                          f"away from the rest surface; is the marker frame the mesh's frame?")
    else:
        obs = _Vision(capture, ws, config.cameras, mesh, config.appearance, config.gaussian_anchor)
        inputs_used += [ws / KIND_FILES[k] for k in ("cameras", "gaussians", "masks")]

    prange = mat.poisson_range
    if not config.fit_poisson:  # ν held at its initial value, per region
        prange = (poisson0.copy(), poisson0.copy())
    if np.any(young0 <= 0):
        raise RslError(f"{capture.toml_path}: the initial Young's modulus must be positive.")
    if config.fit_poisson and config.poisson_init is not None and not prange[0] <= config.poisson_init <= prange[1]:
        raise RslError(f"{capture.toml_path}: --poisson-init {config.poisson_init} lies outside "
                       f"poisson_range {list(prange)}.")
    log_e, s_nu = params_from_theta(young0, np.clip(poisson0, *prange), prange)

    n_avail = None if config.follow else obs.available()
    if n_avail == 0:
        raise CaptureError(f"{capture.root}: holds no frame to adapt to.")
    first, last = _parse_frames(config.frames, n_avail, capture.toml_path)
    rec = _Record()
    stored: dict[int, np.ndarray] = {}  # frame -> latest state (positions or z)
    t_start = time.perf_counter()
    interrupted = False
    status = "failed"

    def state_at(t: int) -> np.ndarray:
        return stored[t] if t >= 0 else backend.rest_state

    # Frames before the range: a plain forward simulation with the initial θ.
    if first > 0:
        with reporter.task("simulating frames before the range", None):
            X0 = backend.forward(list(range(first)), np.tile(young0, (first, 1)),
                                 np.tile(theta_from_params(log_e, s_nu, prange)[1], (first, 1)),
                                 np.stack([backend.rest_state, backend.rest_state]))
        for t in range(first):
            stored[t] = X0[t]

    lr = np.concatenate([np.full(R, config.lr), np.full(R, config.lr_poisson if config.fit_poisson else 0.0)])
    adam = Adam(lr, beta1=config.beta1)
    params = np.concatenate([log_e, s_nu])

    objective = WindowObjective(backend, obs, R, prange)

    def evaluate(frames: list[int], p: np.ndarray, need_grad: bool):
        before = np.stack([state_at(frames[0] - 2), state_at(frames[0] - 1)])
        return objective(frames, p, before, need_grad)

    try:
        if config.mode == "online":
            _online(config, obs, capture, first, last, params, adam, evaluate, stored, rec, R, prange, reporter,
                    backend)
        else:
            if last is None:
                raise RslError(f"{capture.toml_path}: --mode offline needs a finite frame range (not --follow "
                               f"without --frames).")
            params = _offline(config, first, last, params, adam, evaluate, stored, rec, R, prange, reporter)
        status = "complete"
    except KeyboardInterrupt:
        interrupted, status = True, "interrupted"
    finally:
        # Whatever ends the loop (the last frame, Ctrl-C, a failed solve), the frames so far are saved
        # (atomically); extra["status"] says which.
        if rec.frames:
            path = _save(config, ws, backend, mesh, rec, stored, names, inputs_used, obs,
                         status, time.perf_counter() - t_start, n)
    if not rec.frames:
        if interrupted:
            raise KeyboardInterrupt
        raise RslError(f"{capture.root}: no frame was processed (none arrived within --follow-timeout).")
    if interrupted and not config.follow:
        raise KeyboardInterrupt
    _report(config, reporter, rec, names, backend, scene, mesh, path, interrupted)
    return path


def _online(config, obs, capture, first, last, params, adam, evaluate, stored, rec, R, prange, reporter, backend):
    w = config.window
    total = None if last is None else last - first
    with reporter.task(f"adapt online ({backend.space}, {obs.kind}, w={w})", total) as task:
        T = first
        while last is None or T < last:
            if config.follow and not _wait_for(obs, T, config.follow_timeout):
                break
            frames = list(range(max(first, T - w + 1), T + 1))
            tt = time.perf_counter()
            tf = tb = tr = 0.0
            for _ in range(config.iters_per_frame):
                states, losses, g, (a, b, c) = evaluate(frames, params, True)
                tf, tb, tr = tf + a, tb + b, tr + c
                params[:] = adam.step(params, g)
            for i, t in enumerate(frames):
                stored[t] = states[i]
            E, nu = theta_from_params(params[:R], params[R:], prange)
            rec.frames.append(T)
            rec.young.append(E)
            rec.poisson.append(nu)
            rec.loss.append(float(losses.sum()))
            rec.frame_loss.append(float(losses[-1]))
            rec.t_fwd.append(tf)
            rec.t_bwd.append(tb)
            rec.t_ren.append(tr)
            rec.t_tot.append(time.perf_counter() - tt)
            task.advance(1, frame=T, E=" ".join(f"{e:.4g}" for e in E), loss=float(losses.sum()),
                         s_per_frame=rec.t_tot[-1])
            T += 1


def _wait_for(obs, t: int, timeout: float, poll: float = 0.1) -> bool:
    """Wait until frame t is observed; False after ``timeout`` s without it (0: wait for ever)."""
    t0 = time.monotonic()
    while obs.available() <= t:
        if timeout and time.monotonic() - t0 > timeout:
            return False
        time.sleep(poll)
    return True


def _offline(config, first, last, params, adam, evaluate, stored, rec, R, prange, reporter):
    frames = list(range(first, last))
    tf = tb = tr = 0.0
    best = (math.inf, params.copy())
    with reporter.task(f"adapt offline ({len(frames)} frames)", config.offline_iters) as task:
        for _ in range(config.offline_iters):
            _, losses, g, (a, b, c) = evaluate(frames, params, True)
            tf, tb, tr = tf + a, tb + b, tr + c
            if losses.sum() < best[0]:
                best = (float(losses.sum()), params.copy())
            params = adam.step(params, g)
            E, _ = theta_from_params(params[:R], params[R:], prange)
            task.advance(1, E=" ".join(f"{e:.4g}" for e in E), loss=float(losses.sum()))
        states, losses, _, (a, b, c) = evaluate(frames, params, False)
        tf, tr = tf + a, tr + c
        if losses.sum() > best[0]:  # keep the best iterate
            params = best[1]
            states, losses, _, _ = evaluate(frames, params, False)
    E, nu = theta_from_params(params[:R], params[R:], prange)
    k = len(frames)
    for i, t in enumerate(frames):
        stored[t] = states[i]
        rec.frames.append(t)
        rec.young.append(E)
        rec.poisson.append(nu)
        rec.loss.append(float(losses[i]))
        rec.frame_loss.append(float(losses[i]))
        rec.t_fwd.append(tf / k)
        rec.t_bwd.append(tb / k)
        rec.t_ren.append(tr / k)
        rec.t_tot.append((tf + tb + tr) / k)
    return params


def _save(config, ws, backend, mesh, rec, stored, names, inputs_used, obs, status, wall_s, n) -> Path:
    frames = np.asarray(rec.frames, np.int64)
    states = np.stack([stored[t] for t in rec.frames])
    X = backend.decode(states)[:, :n]
    extra = {
        "capture": str(Path(config.capture).resolve()),
        "frame_loss": rec.frame_loss,
        "iters_per_frame": config.iters_per_frame,
        "cameras": getattr(obs, "cameras", []),
        "gaussian_anchor": getattr(obs, "anchor_kind", None),
        "refine": config.refine,
        "status": status,  # complete | interrupted | failed
        "wall_s": wall_s,
        "young_meaning": _young_meaning(config, mesh),
    }
    art = AdaptArtefact(
        frames=frames, young=np.asarray(rec.young), poisson=np.asarray(rec.poisson), z=backend.z(states),
        positions=X, loss=np.asarray(rec.loss), time_forward_s=np.asarray(rec.t_fwd),
        time_backward_s=np.asarray(rec.t_bwd), time_render_s=np.asarray(rec.t_ren),
        time_total_s=np.asarray(rec.t_tot), region_names=names, mode=config.mode, space=backend.space,
        loss_kind=obs.kind, window=config.window if config.mode == "online" else len(frames), extra=extra)
    path = ws / KIND_FILES["adapt"]
    art.save(path, Provenance.make(config, inputs_used))
    return path


def _young_meaning(config: AdaptConfig, mesh: MeshArtefact) -> str:
    m = mesh.n_tets * 8 ** config.refine
    return (f"E is the effective modulus of the linear-tet discretisation used ({m} tets"
            + (f", mesh.h5 refined {config.refine}x" if config.refine else "")
            + "): coarse linear tets are too stiff (they lock as ν → 0.5), so the adapted E is lower than the "
            "continuum E"
            + ("" if config.refine else "; --space full --refine 1 estimates it on a finer mesh") + ".")


def _report(config, reporter, rec, names, backend, scene, mesh, path, interrupted) -> None:
    med = lambda a: float(np.median(a)) if a else float("nan")  # noqa: E731
    f, b, r, t = med(rec.t_fwd), med(rec.t_bwd), med(rec.t_ren), med(rec.t_tot)
    reporter.info(f"{'space':>8} {'dofs':>7} {'r':>4} {'w':>3} | {'forward':>8} {'backward':>8} "
                  f"{'render':>8} {'total':>8}  (median s/frame)")
    reporter.info(f"{backend.space:>8} {3 * len(scene.rest):>7} {backend.dim:>4} {config.window:>3} | "
                  f"{f:8.3f} {b:8.3f} {r:8.3f} {t:8.3f}")
    reporter.info(_young_meaning(config, mesh))
    E, nu = rec.young[-1], rec.poisson[-1]
    mats = ", ".join(f"{nm}: E={e:.4g} Pa ν={v:.3f}" for nm, e, v in zip(names, E, nu))
    stop = " (stopped early)" if interrupted else ""
    reporter.summary(f"adapted {len(rec.frames)} frames{stop} {config.mode} in {backend.space} space from "
                     f"{'markers' if config.loss == 'markers' else 'images'}: {mats} "
                     f"(effective E of this mesh); per frame forward {f:.3f} s, backward {b:.3f} s, "
                     f"render {r:.3f} s, total {t:.3f} s → {path}")
