"""Reading what ``rsl adapt`` (or ``rsl rollout``) left in a workspace, shared by evaluate, export and report:
the capture an artefact was made from, the material model / time step / gravity of a trajectory, the
states before a row, where the Gaussians sit in the adapted frames, and the stress of every frame.

Stress (stages.sim.stress): linear tets per tet; quadratic tets at each quadrature point, per element the
weight-averaged σ and σ_vM over its points, nodal forces −Σ_q w_q P_q ∇N_a; vertex values volume-averaged.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stages.artefacts import AdaptArtefact, MeshArtefact, read_provenance
from stages.capture import Capture
from stages.progress import Reporter, SilentReporter
from stages.sim import stress as st
from stages.sim.quadrature import build_quadrature, element_order

DEFAULT_MODEL = "stable_neohookean"
DEFAULT_DT_S = 1.0 / 30.0
DEFAULT_GRAVITY = (0.0, 0.0, -9.81)  # m/s²


# =========================================================================== where a result came from
def recorded_capture(prov: dict, ws: Path | None = None) -> Path | None:
    """The capture folder an artefact was made from (its provenance ``prov``), when it exists from here:
    its config's ``capture`` (as recorded, else relative to the workspace ``ws``), else the folder of
    the capture.toml among its hashed inputs.  None when none of them is a folder."""
    rec = prov.get("config", {}).get("capture")
    if rec:
        for cand in (Path(rec),) + ((Path(ws) / rec,) if ws is not None else ()):
            if cand.is_dir():
                return cand
    for item in prov.get("inputs", []):
        p = Path(item.get("path", ""))
        if p.name == "capture.toml" and p.is_file():
            return p.parent
    return None


def material_setting(capture: Capture | None, adapt: AdaptArtefact) -> tuple[str, float, np.ndarray]:
    """(material model, dt s, gravity (3,) m/s²) of a trajectory: the capture's, else what adapt.h5 records."""
    if capture is not None:
        return capture.material.model, float(capture.dt), np.asarray(capture.gravity, np.float64)
    extra = adapt.extra or {}
    return (str(extra.get("material_model", DEFAULT_MODEL)), float(extra.get("dt", DEFAULT_DT_S)),
            np.asarray(extra.get("gravity", DEFAULT_GRAVITY), np.float64))


def material_damping(capture: Capture | None, adapt: AdaptArtefact) -> float:
    """β (s) of the material's viscous damping: what adapt.h5 records it simulated with (the capture's [material]
    damping, --damping, or estimated by --damping auto), else the capture's (an adapt.h5 older than the record)."""
    recorded = (adapt.extra or {}).get("damping")
    if recorded is not None:
        return float(recorded)
    return float(capture.material.damping) if capture is not None else 0.0


def window_young(adapt: AdaptArtefact) -> np.ndarray | None:
    """(T, R) Pa: the sliding window's own E per frame where adapt.h5 records E(t) held at the calibration fits
    (``rsl adapt --hold-fit``, extras ``window_young``); None when it records none or it equals E(t)."""
    wy = (adapt.extra or {}).get("window_young") or []
    if len(wy) != len(adapt.young):
        return None
    wy = np.asarray(wy, np.float64).reshape(np.shape(adapt.young))
    return None if np.array_equal(wy, np.asarray(adapt.young, np.float64)) else wy


def previous_states(frames: np.ndarray, positions: np.ndarray, rest: np.ndarray, row: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(x_{t−1}, x_{t−2}) of row ``row`` of a trajectory (frames (T,), positions (T, n, 3)): the earlier rows
    when their frames are consecutive, else the one before (x_{t−2} = x_{t−1}), else the rest state (n, 3)."""
    out: list[np.ndarray] = []
    for back in (1, 2):
        r = row - back
        if r >= 0 and frames[r] == frames[row] - back:
            out.append(positions[r])
        else:
            out.append(out[-1] if out else rest)
    return out[0], out[1]


def gaussian_anchor(renderer, adapt: AdaptArtefact, gaussians_path: Path) -> np.ndarray | float:
    """Make the Gaussians of ``renderer`` (an ImageLoss) follow the mesh as ``rsl adapt`` made them follow it
    (adapt.h5 extra "gaussian_anchor"; the one rule of evaluate, report and export): "rebind" — re-bound to the tets of the adapted fit-frame shape
    (returns 0); "fitted" (a capture filmed mid-motion) — bound as fitted, at the pose frame 0's masks gave (returns
    0); "offset" (older files) — render at x_t − anchor with anchor = x_fit − fit_positions (n, 3).
    0 when adapt.h5 does not hold the frame the Gaussians were fitted at."""
    if (adapt.extra or {}).get("gaussian_anchor") == "fitted":
        return 0.0
    fit_frame = int(read_provenance(gaussians_path).get("config", {}).get("frame", 0) or 0)
    at = np.flatnonzero(adapt.frames == fit_frame)
    if not len(at):
        return 0.0
    if (adapt.extra or {}).get("gaussian_anchor", "offset") == "rebind":
        renderer.rebind(adapt.positions[at[0]])
        return 0.0
    return adapt.positions[at[0]] - renderer.fit_positions


# =========================================================================== stress
@dataclass
class StressField:
    """Per-frame stress of a whole trajectory (T rows)."""

    von_mises_tet: np.ndarray  # (T, m) Pa (quadratic tets: the weighted mean over the element's points)
    von_mises_vertex: np.ndarray  # (T, n) Pa
    sigma: np.ndarray | None  # (T, m, 3, 3) Pa (None when not asked for)
    forces: np.ndarray  # (T, n, 3) internal nodal forces, N
    von_mises_point: np.ndarray | None = None  # (T, q) Pa per quadrature point (quadratic tets only)
    point_element: np.ndarray | None = None  # (q,) element of each quadrature point


def compute_stress(adapt: AdaptArtefact, mesh: MeshArtefact, model: str, reporter: Reporter = SilentReporter(),
                   sigma: bool = True) -> StressField:
    """σ (when ``sigma``), σ_vM (tet and vertex) and internal nodal forces for every row of ``adapt``
    (positions m, E and ν per region) on ``mesh`` with the material ``model``; warns of inverted elements."""
    T, n, m = len(adapt.frames), mesh.n_vertices, mesh.n_tets
    quad = build_quadrature(mesh.vertices, mesh.tets) if element_order(mesh.tets) == 2 else None
    vm_t = np.zeros((T, m))
    vm_v = np.zeros((T, n))
    sig = np.zeros((T, m, 3, 3)) if sigma else None
    forces = np.zeros((T, n, 3))
    vm_q = None if quad is None else np.zeros((T, quad.n_points))
    what = "tets" if quad is None else "quadrature points"
    with reporter.task("stress", T) as task:
        for i in range(T):
            mu, lam = st.tet_lame_from_regions(adapt.young[i], adapt.poisson[i], mesh.tet_region)
            if quad is None:
                s = st.tet_stress(adapt.positions[i], mesh.tets, mesh.dm_inv, mu, lam, model)
            else:
                s = st.point_stress(adapt.positions[i], quad, mu[quad.element], lam[quad.element], model)
            if np.any(s["J"] <= 0):
                reporter.warn(f"frame {int(adapt.frames[i])}: {int(np.sum(s['J'] <= 0))} inverted {what}; "
                              f"their stress is not physical.")
            if quad is None:
                vm_t[i] = s["von_mises"]
                if sigma:
                    sig[i] = s["sigma"]
                forces[i] = st.nodal_forces(s["P"], mesh.tets, mesh.dm_inv, mesh.rest_volumes, n)
            else:
                vm_q[i] = s["von_mises"]
                vm_t[i] = st.element_average(s["von_mises"], quad, m)
                if sigma:
                    sig[i] = st.element_average(s["sigma"], quad, m)
                forces[i] = st.point_nodal_forces(s["P"], quad, n)
            vm_v[i] = st.vertex_average(vm_t[i], mesh.tets, mesh.rest_volumes, n)
            task.advance(1, max_kpa=float(vm_t[i].max()) / 1e3)
    return StressField(vm_t, vm_v, sig, forces, vm_q, None if quad is None else quad.element)
