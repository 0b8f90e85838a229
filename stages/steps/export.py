"""`rsl export`: what the adapted simulation reveals — stress, forces, VTU/PVD, 3DGS PLY,
rendered stress views, plots, scan distances and a COLMAP model of the cameras.

Reads WS/adapt.h5 (or WS/rollout.h5 with ``source="rollout"``), WS/mesh.h5, and where
needed WS/gaussians.h5 and WS/cameras.h5, plus the capture folder recorded in the
artefact's config (for the material model, fps, gravity and controls).  Writes
into one output folder (default WS/export/, or WS/export_rollout/ for a rollout):

    stress.h5, stress_summary.csv      Cauchy σ and von Mises per tet, per-vertex von Mises
    forces.csv                         per frame and handle/obstacle: Σ internal nodal force and the force
                                       it exerts (adapt.h5 from frame 0: of θ(t) replayed in the full
                                       space, as truth/forces.csv; stages.forces)
    vtk/<source>.pvd, vtk/*.vtu        a ParaView time series
    ply/frame_NNNNNN.ply               3DGS PLY of the deformed Gaussians
    render/...png, render/*.mp4        capture and orbit views, appearance and stress
    plots/*.png                        E(t), loss, time breakdown, forces, stress
    scan/                              distance of the simulated surface to a scan
    (--colmap DIR)                     the cameras as a COLMAP text model

Every file is written to a temporary name and renamed into place.  The
equations live in stages/sim/stress.py; this module only orchestrates and writes.
"""
from __future__ import annotations

import contextlib
import copy
import csv
import dataclasses
import json
import math
import os
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Literal

import cv2
import numpy as np

from stages.artefacts import (KIND_FILES, PARTIAL_ADAPT, AdaptArtefact, CamerasArtefact, GaussiansArtefact,
                              MeshArtefact, Provenance, StressArtefact, check_same_mesh, read_provenance)
from stages.capture import FORCE_HEADER, Capture, CaptureError, Controls, load_capture, load_controls, write_image
from stages.domain.cameras import Camera
from stages.errors import RslError
from stages.forces import (FORCE_EXTRAPOLATE, FORCE_SUBSTEPS, FORCE_THETA, adapted_forces, filter_model,
                           replay_substeps, trajectory_forces)
from stages.progress import Reporter, SilentReporter
from stages.render.ply import covariance_to_scale_rotation, write_ply
from stages.results import (StressField, gaussian_anchor, material_damping, material_setting, previous_states,
                            recorded_capture, window_young)
from stages.results import compute_stress as results_stress
from stages.sim import stress as st
from stages.sim.quadrature import element_order, shape_values
from stages.vision.colmap_io import write_colmap

ROLLOUT_FILE = "rollout.h5"


class ExportError(RslError):
    """An export cannot be made from what the workspace holds."""


@dataclass(frozen=True)
class ExportConfig:
    workspace: Path
    """Workspace folder holding adapt.h5 (or rollout.h5) and mesh.h5."""
    out: Path | None = None
    """Output folder; default WORKSPACE/export (WORKSPACE/export_rollout with --source rollout)."""
    source: Literal["adapt", "partial", "rollout"] = "adapt"
    """Which trajectory to export: adapt.h5 (the adapted sequence), adapt.partial.h5 (the frames an interrupted or
    failed `rsl adapt` kept; refused unless asked for this way) or rollout.h5 (a prediction)."""
    stress: bool | None = None
    """Cauchy and von Mises stress per tet and vertex (stress.h5) with a per-frame summary CSV (unset: made when no product is flagged on)."""
    forces: bool | None = None
    """Per frame and handle/obstacle: sum of internal nodal forces and of their magnitudes (forces.csv) (unset: made when no product is flagged on)."""
    vtk: bool | None = None
    """A VTU per frame and a PVD time series for ParaView (unset: made when no product is flagged on)."""
    ply: bool | None = None
    """3DGS PLY files of the deformed Gaussians for the chosen frames (needs gaussians.h5) (unset: made when no product is flagged on)."""
    render: bool | None = None
    """PNG frames and MP4s from the capture cameras and orbit views, appearance and stress (needs gaussians.h5) (unset: made when no product is flagged on)."""
    plots: bool | None = None
    """PNG plots: E(t) per region, loss, time per frame, handle forces, stress (unset: made when no product is flagged on)."""
    colmap: Path | None = None
    """Also write the cameras as a COLMAP text model into this folder."""
    scan: Path | None = None
    """A scanned point cloud (PLY/PCD/XYZ, metres): distance of the simulated surface to it."""
    scan_frame: int = -1
    """Which frame of the trajectory the scan shows (capture frame id; -1 = the last)."""
    frames: str = "all"
    """Frames for PLY and rendering: all, last, a list 0,10,20 or a range 0:60:5 (capture frame ids)."""
    capture: Path | None = None
    """Capture folder; default the one recorded in the source artefact."""
    contact_distance: float = 1.0e-3
    """A vertex touches an obstacle when closer than the contact margin plus this distance, m."""
    ply_stress: bool = False
    """Colour the PLY Gaussians by von Mises stress instead of their appearance."""
    stress_max: float = 0.0
    """Upper end of the stress colour map, Pa; 0 = the 99th percentile over all exported frames."""
    orbit_views: int = 36
    """Number of novel views on a circle around the object for the orbit renders."""
    render_size: int = 384
    """Width and height of the orbit renders, px."""
    video_fps: float = 0.0
    """Frame rate of the MP4s; 0 = the capture's fps."""
    force_substeps: int = FORCE_SUBSTEPS
    """Implicit-Euler steps per frame S of the full-space replay the forces are computed on; 0 (the default) = adapt's --substeps, the time step θ was estimated with (docs/results/forces_converged.md, forces_damped.md)."""
    force_extrapolate: bool = FORCE_EXTRAPOLATE
    """Richardson-extrapolate the replay's forces in time, 2 F(2S) − F(S) from replays with S and 2S steps per frame: cancels implicit Euler's first-order error, costs 3S steps per frame.  Off by default: plain at adapt's 6 substeps came closer to truths converged in time than Richardson (1, 2) on every capture measured (docs/results/forces_converged.md, forces_damped.md)."""
    force_theta: Literal["online", "segment", "smoothed"] = FORCE_THETA
    """θ(t) of the replay: smoothed (the default) = adapt.h5's E ± σ and ν ± σ smoothed over the whole run (Rauch–Tung–Striebel) under the gn filter's own random walk (its --process-noise, --change-sigma at each detected change); online = each frame's estimate as adapt.h5 records it (frame t's force uses estimates up to t); segment = the last estimate of each segment between the material changes adapt's gn estimator detected.  On the frames where the truth's force converges in time (a constant E; before a step of E) smoothed erred less than online on every capture measured (two-region beam 26 → 5 %, bar before its step 7.8 → 1.1 %, docs/results/forces_theta.md); it carries a later material into earlier frames when a change is detected a few frames before the true one.  An adam run with images is held per segment between its located changes at its anchor calibrations' fits (adapt.h5 anchor_calibrations); one without keeps its recorded θ(t)."""


# =========================================================================== small file helpers
@contextlib.contextmanager
def _atomic_path(path: Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it into place on success."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600; exports are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def _write_csv(path: Path, header: list[str], rows: list[list[Any]]) -> Path:
    with _atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        for r in rows:
            w.writerow([_csv_value(v) for v in r])
    return path


def _csv_value(v: Any) -> Any:
    if isinstance(v, (float, np.floating)):
        return f"{float(v) + 0.0:.9g}"  # + 0.0: no "-0"
    return v


def _write_json(path: Path, data: dict) -> Path:
    with _atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2))
    return path


# =========================================================================== the loaded sequence
@dataclass
class Sequence:
    """Everything export needs, loaded and checked once."""

    source_path: Path
    adapt: AdaptArtefact
    mesh: MeshArtefact
    capture: Capture | None
    model: str  # material model name
    dt: float  # s
    times: np.ndarray  # (T,) s
    provenance_inputs: list[Path]
    controls: Controls | None = None  # what drove the trajectory (capture's, or the rollout's own)
    controls_path: Path | None = None
    gravity: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))

    @property
    def n_frames(self) -> int:
        return int(self.adapt.frames.shape[0])

    def previous(self, row: int) -> tuple[np.ndarray, np.ndarray]:
        """(x_{t−1}, x_{t−2}) of a row: earlier rows when consecutive, else the rest state."""
        return previous_states(self.adapt.frames, self.adapt.positions, self.mesh.vertices, row)


def load_sequence(config: ExportConfig) -> Sequence:
    """Read and cross-check the source artefact, mesh.h5 and the capture folder."""
    ws = Path(config.workspace)
    if not ws.is_dir():
        raise ExportError(f"{ws}: workspace folder not found.")
    if config.source not in ("adapt", "partial", "rollout"):
        raise ExportError(f"--source '{config.source}' is none of adapt, partial, rollout.")
    src = ws / {"adapt": KIND_FILES["adapt"], "partial": PARTIAL_ADAPT, "rollout": ROLLOUT_FILE}[config.source]
    if not src.exists():
        hint = "rsl rollout" if config.source == "rollout" else "rsl adapt"
        raise ExportError(f"{src}: file not found; run `{hint}` first.")
    adapt = AdaptArtefact.load(src, allow_partial=config.source == "partial")
    mesh_path = ws / KIND_FILES["mesh"]
    mesh = MeshArtefact.load(mesh_path)
    check_same_mesh(mesh_path, src)  # made from this very mesh.h5, whatever the counts
    if adapt.positions.shape[1] != mesh.n_vertices:
        raise ExportError(f"{src}: positions hold {adapt.positions.shape[1]} vertices but {mesh_path} has "
                          f"{mesh.n_vertices}; the two come from different meshes.")
    if adapt.young.shape[1] != len(mesh.region_names):
        raise ExportError(f"{src}: holds θ for {adapt.young.shape[1]} regions but {mesh_path} has "
                          f"{len(mesh.region_names)} ({', '.join(mesh.region_names)}).")
    if adapt.frames.shape[0] == 0:
        raise ExportError(f"{src}: holds no frame.")
    prov = read_provenance(src)
    recorded = prov.get("config", {})
    cap_path = config.capture if config.capture is not None else _recorded_capture(prov)
    capture = None
    if cap_path is not None:
        try:
            capture = load_capture(cap_path)
        except CaptureError as e:
            if config.capture is not None:
                raise
            raise ExportError(f"{src}: the capture folder it records cannot be read ({e}); "
                              f"pass --capture.") from None
    model, dt, gravity = material_setting(capture, adapt)
    times = adapt.frames.astype(np.float64) * dt
    inputs = [src, mesh_path]
    controls, controls_path = None, None
    if recorded.get("controls"):  # a rollout records the controls it simulated
        controls_path = Path(adapt.extra.get("controls") or recorded["controls"])
        if not controls_path.is_file():
            raise ExportError(f"{src}: the controls file it records, {controls_path}, no longer exists.")
        controls = load_controls(controls_path)
    elif capture is not None:
        controls_path = capture.controls_path
        controls = capture.controls()
    return Sequence(src, adapt, mesh, capture, model, dt, times, inputs, controls, controls_path, gravity)


def _recorded_capture(prov: dict) -> Path | None:
    """The capture folder an artefact was made from (stages.results.recorded_capture), else its config's
    ``capture`` as recorded (load_capture then says why it cannot be read)."""
    rec = prov.get("config", {}).get("capture")
    return recorded_capture(prov) or (Path(rec) if rec else None)


def select_rows(seq: Sequence, spec: str, path_hint: str = "--frames") -> np.ndarray:
    """Row indices of the frames named by ``spec``: all, last, 0,10,20 or start:stop[:step]."""
    frames = seq.adapt.frames
    spec = spec.strip().lower()
    if spec in ("", "all"):
        return np.arange(len(frames))
    if spec == "last":
        return np.array([len(frames) - 1])
    try:
        if ":" in spec:
            parts = [int(p) if p else None for p in spec.split(":")]
            if len(parts) > 3:
                raise ValueError
            wanted = np.arange(int(frames.max()) + 1)[slice(*parts)]
            rows = np.flatnonzero(np.isin(frames, wanted))
        else:
            wanted = [int(p) for p in spec.split(",") if p.strip()]
            rows = []
            for w in wanted:
                hit = np.flatnonzero(frames == (frames[w] if w < 0 else w))
                if not hit.size:
                    raise ExportError(f"{seq.source_path}: holds no frame {w} (it covers frames "
                                      f"{int(frames.min())}..{int(frames.max())}); fix {path_hint}.")
                rows.append(int(hit[0]))
            rows = np.array(rows, np.int64)
    except ValueError:
        raise ExportError(f"{path_hint} '{spec}' is not all, last, a list like 0,10,20 or a range like 0:60:5.") \
            from None
    if len(rows) == 0:
        raise ExportError(f"{seq.source_path}: {path_hint} '{spec}' selects no frame of the sequence.")
    return np.asarray(rows, np.int64)


# =========================================================================== stress
def compute_stress(seq: Sequence, reporter: Reporter) -> StressField:
    """σ, σ_vM (tet and vertex) and internal nodal forces for every row (stages.results.compute_stress)."""
    return results_stress(seq.adapt, seq.mesh, seq.model, reporter)


def write_stress(seq: Sequence, field: StressField, out: Path, config: ExportConfig) -> list[Path]:
    """stress.h5 (a StressArtefact) and stress_summary.csv (one row per frame, plus per region if several)."""
    h5 = StressArtefact(seq.adapt.frames, seq.times, field.von_mises_tet, field.von_mises_vertex, field.sigma,
                        field.forces, seq.mesh.tet_region, list(seq.mesh.region_names), seq.model,
                        field.von_mises_point, field.point_element
                        ).save(out / "stress.h5", Provenance.make(config, seq.provenance_inputs))
    names = list(seq.mesh.region_names)
    rows = []
    for i in range(seq.n_frames):
        groups = [("all", np.ones(seq.mesh.n_tets, bool))]
        if len(names) > 1:
            groups += [(nm, seq.mesh.tet_region == r) for r, nm in enumerate(names)]
        for gname, sel in groups:
            s = st.stress_summary(field.von_mises_tet[i][sel], seq.mesh.rest_volumes[sel])
            rows.append([int(seq.adapt.frames[i]), seq.times[i], gname, s["max_pa"], s["mean_pa"],
                         s["p50_pa"], s["p90_pa"], s["p99_pa"]])
    csv_path = _write_csv(out / "stress_summary.csv",
                          ["frame", "time_s", "region", "max_pa", "mean_pa", "p50_pa", "p90_pa", "p99_pa"], rows)
    return [h5, csv_path]


# =========================================================================== forces
@dataclass
class ForceRow:
    frame: int
    time_s: float
    force: st.SetForce




def compute_forces(seq: Sequence, field: StressField, config: ExportConfig, reporter: Reporter
                   ) -> tuple[list[ForceRow], np.ndarray]:
    """Per frame, per handle and per obstacle: the internal-force sums over its vertices and the force it
    exerts (stages.forces.trajectory_forces, shared with rsl evaluate), with the controls the trajectory was
    made with; and the per-vertex force (T, n, 3) N that handles and obstacles apply."""
    from stages.sim.scene import make_scene  # JAX and numba physics: loaded on use (rsl export --help)

    controls = seq.controls
    if config.force_substeps < 0:
        raise ExportError(f"--force-substeps should be 0 (adapt's) or at least 1, found {config.force_substeps}.")
    if not controls.handles and not controls.obstacles:
        reporter.warn(f"{seq.controls_path}: no handle and no obstacle; forces.csv holds no row.")
    scene = make_scene(seq.mesh, controls, seq.model, seq.dt, seq.gravity,
                       damping=material_damping(seq.capture, seq.adapt))
    if config.source in ("adapt", "partial"):
        # an online trajectory is spliced from windows (and reduced-space states): the forces of its θ(t)
        # replayed in the full space, as truth/forces.csv defines them (stages.forces module doc)
        substeps = replay_substeps(config.force_substeps, seq.adapt)
        start = seq.capture.start if seq.capture is not None else None
        # the gn filter's random walk (--force-theta smoothed)
        walk = (filter_model(read_provenance(seq.source_path).get("config"), seq.capture.material.poisson_range,
                             seq.adapt.extra) if seq.capture is not None else None)
        rows, applied, _ = adapted_forces(scene, controls, seq.adapt, start, substeps, lambda: field.forces,
                                          config.contact_distance, reporter, config.force_extrapolate,
                                          config.force_theta, walk)
    else:
        rows, applied = trajectory_forces(scene, controls, seq.adapt.frames, seq.adapt.positions, field.forces,
                                          config.contact_distance, reporter)
    times = dict(zip(seq.adapt.frames.tolist(), seq.times.tolist()))
    return [ForceRow(frame, float(times[frame]), f) for frame, f in rows], applied


def write_forces(rows: list[ForceRow], out: Path) -> Path:
    data = [[r.frame, r.time_s, r.force.name, r.force.kind, *r.force.internal, r.force.magnitude_sum,
             *r.force.applied, r.force.n_vertices] for r in rows]
    return _write_csv(out / "forces.csv", FORCE_HEADER, data)


# =========================================================================== VTU / PVD
def write_vtk(seq: Sequence, field: StressField, applied: np.ndarray | None, out: Path,
              reporter: Reporter) -> list[Path]:
    """vtk/frame_NNNNNN.vtu per frame and vtk/<source>.pvd listing them with their times.

    Point data: displacement (m), von_mises (Pa), internal_force (N) and, when forces were
    computed, applied_force (N, handles and contacts); cell data: von_mises, region, young_pa, poisson.
    Quadratic tets are written as VTK_QUADRATIC_TETRA (meshio "tetra10", the same node order), cell
    von_mises being the mean over the element's quadrature points."""
    import meshio  # loaded on use: only VTU output needs it

    mesh, ad = seq.mesh, seq.adapt
    folder = out / "vtk"
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    region = mesh.tet_region.astype(np.int32)
    cell_type = "tetra" if element_order(mesh.tets) == 1 else "tetra10"
    with reporter.task("vtk", seq.n_frames) as task:
        for i in range(seq.n_frames):
            x = ad.positions[i]
            young_tet = ad.young[i][mesh.tet_region]
            point_data = {"displacement": x - mesh.vertices, "von_mises": field.von_mises_vertex[i],
                          "internal_force": field.forces[i]}
            if applied is not None:
                point_data["applied_force"] = applied[i]
            m = meshio.Mesh(
                points=x, cells=[(cell_type, mesh.tets.astype(np.int64))], point_data=point_data,
                cell_data={"von_mises": [field.von_mises_tet[i]], "region": [region],
                           "young_pa": [young_tet], "poisson": [ad.poisson[i][mesh.tet_region]]},
            )
            path = folder / f"frame_{int(ad.frames[i]):06d}.vtu"
            with _atomic_path(path) as tmp:
                meshio.write(str(tmp), m, file_format="vtu")
            written.append(path)
            task.advance(1)
    pvd = folder / f"{seq.source_path.stem}.pvd"
    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">', "  <Collection>"]
    for t, p in zip(seq.times, written):
        lines.append(f'    <DataSet timestep="{t:.9g}" group="" part="0" file="{p.name}"/>')
    lines += ["  </Collection>", "</VTKFile>", ""]
    with _atomic_path(pvd) as tmp:
        tmp.write_text("\n".join(lines))
    return [pvd] + written


def read_pvd(path: str | Path) -> list[tuple[float, Path]]:
    """(time, VTU path) of each data set of a PVD file."""
    path = Path(path)
    root = ET.parse(path).getroot()
    return [(float(d.get("timestep", "0")), path.parent / d.get("file"))
            for d in root.iter("DataSet")]


# =========================================================================== Gaussians: PLY and renders
def _load_gaussians(seq: Sequence, ws: Path, gauss: GaussiansArtefact | None = None):
    """(GaussiansArtefact, ImageLoss, anchor): the Gaussians of WS/gaussians.h5 (or ``gauss``, another appearance of
    them) placed on the mesh as ``rsl adapt`` placed them and evaluate and report render them
    (stages.results.gaussian_anchor on adapt.h5 — the source artefact itself, or WS/adapt.h5 for a rollout;
    bound as fitted without one): a row's positions x render and write as the Gaussians at x − anchor."""
    from stages.render.image_loss import ImageLoss  # scipy.spatial here, torch and numba when built: loaded on use

    path = ws / KIND_FILES["gaussians"]
    if not path.exists():
        raise ExportError(f"{path}: file not found; PLY and renders need the Gaussians (run `rsl fit-gaussians`).")
    if gauss is None:
        gauss = GaussiansArtefact.load(path)
    if gauss.host_tet.size and gauss.host_tet.max() >= seq.mesh.n_tets:
        raise ExportError(f"{path}: Gaussians are bound to tet {int(gauss.host_tet.max())} but "
                          f"{ws / KIND_FILES['mesh']} has {seq.mesh.n_tets} tets; they belong to another mesh.")
    try:
        renderer = ImageLoss(gauss, seq.mesh, [])
    except ValueError as e:
        raise ExportError(f"{path}: {e}.") from None
    adapt = seq.adapt
    if seq.source_path.name == ROLLOUT_FILE:  # a prediction: the Gaussians as the adapted run anchored them
        adapt_path = ws / KIND_FILES["adapt"]
        adapt = AdaptArtefact.load(adapt_path) if adapt_path.exists() else None
    anchor = 0.0 if adapt is None else gaussian_anchor(renderer, adapt, path)
    return gauss, renderer, anchor


def gaussian_values(gauss, mesh: MeshArtefact, vertex_values: np.ndarray) -> np.ndarray:
    """A per-vertex field carried by the Gaussians of a binding ``gauss`` (host_tet (G,), bary (G, 4): a
    GaussiansArtefact as fitted, or an ImageLoss's current binding): v_g = Σ_k β_gk v[tet_g,k] (quadratic tets:
    Σ_a N_a(β_g) v[tet_g,a] over all nodes), (G,) from (n,)."""
    nodes = mesh.tets[gauss.host_tet]  # (G, 4 | 10)
    w = shape_values(element_order(mesh.tets), np.asarray(gauss.bary, np.float64))
    return np.sum(w * np.asarray(vertex_values)[nodes], axis=1)


def stress_scale(config: ExportConfig, field: StressField, rows: np.ndarray) -> float:
    """Upper end of the stress colour map, Pa: --stress-max, else the 99th percentile of the vertex field."""
    if config.stress_max > 0:
        return float(config.stress_max)
    hi = float(np.percentile(field.von_mises_vertex[rows], 99))
    return hi if hi > 0 else 1.0


def write_ply_frames(seq: Sequence, field: StressField, rows: np.ndarray, config: ExportConfig, out: Path,
                     reporter: Reporter) -> list[Path]:
    """ply/frame_NNNNNN.ply per chosen row: the Gaussians deformed with the frame's positions, placed as
    :func:`_load_gaussians` places them (centre Σ β x, covariance F Σ₀ Fᵀ), in the standard 3DGS layout; colours
    by stress with ply_stress."""
    from stages.render.gaussians import color_to_sh0

    gauss, placed, anchor = _load_gaussians(seq, Path(config.workspace))
    vmax = stress_scale(config, field, rows)
    written = []
    with reporter.task("ply", len(rows)) as task:
        for i in rows:
            means, covs = placed.geometry(seq.adapt.positions[i] - anchor)
            log_scales, rotations = covariance_to_scale_rotation(covs)
            sh = gauss.sh
            if config.ply_stress:
                vm = gaussian_values(placed, seq.mesh, field.von_mises_vertex[i])
                sh = color_to_sh0(colormap(vm / vmax))[:, None, :]
            path = out / "ply" / f"frame_{int(seq.adapt.frames[i]):06d}.ply"
            written.append(write_ply(path, means, log_scales, rotations, gauss.opacity_logit, sh))
            task.advance(1)
    return written


def orbit_cameras(center: np.ndarray, radius: float, n_views: int, size: int, up: np.ndarray,
                  elevation_deg: float = 20.0, fov_deg: float = 40.0) -> list:
    """Cameras on a circle around ``center`` (m), looking at it, the object of ``radius`` (m) filling the view."""
    from stages.render.mesh_raster import look_at  # numba: loaded on use

    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    half = math.radians(fov_deg) / 2
    dist = 1.15 * radius / math.sin(half)
    f = 0.5 * size / math.tan(half)
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1.0]])
    el = math.radians(elevation_deg)
    cams = []
    for k in range(n_views):
        phi = 2 * math.pi * k / n_views
        eye = center + dist * (math.cos(el) * (math.cos(phi) * e1 + math.sin(phi) * e2) + math.sin(el) * up)
        R, t = look_at(eye, center, -up)  # image y points down, i.e. against up
        cams.append(Camera(f"orbit{k:03d}", K, np.zeros(5), R, t, size, size))
    return cams


def add_colorbar(image: np.ndarray, vmax_pa: float, label: str = "von Mises") -> np.ndarray:
    """The image (H, W, 3) uint8 with a turbo colour bar 0 … vmax (kPa) on a white strip to its right."""
    h = image.shape[0]
    scale = max(0.3, h / 900)
    line = int(22 * scale) + 6  # text line height, px
    bar_w = max(64, h // 5, int(10 * 18 * scale))
    strip = np.full((h, bar_w, 3), 255, np.uint8)
    top, bottom = 2 * line + 6, int(0.92 * h)
    ramp = np.linspace(1.0, 0.0, max(bottom - top, 2))
    colors = (colormap(ramp) * 255).astype(np.uint8)  # (L, 3)
    x0, x1 = 6, 6 + max(8, bar_w // 5)
    strip[top:top + len(colors), x0:x1] = colors[:, None, :]
    font = cv2.FONT_HERSHEY_SIMPLEX
    ink = (20, 20, 20)
    cv2.putText(strip, label, (x0, line - 4), font, scale, ink, 1, cv2.LINE_AA)
    cv2.putText(strip, "kPa", (x0, 2 * line - 4), font, scale, ink, 1, cv2.LINE_AA)
    cv2.putText(strip, f"{vmax_pa / 1e3:.3g}", (x1 + 3, top + line // 2), font, scale, ink, 1, cv2.LINE_AA)
    cv2.putText(strip, "0", (x1 + 3, bottom), font, scale, ink, 1, cv2.LINE_AA)
    return np.concatenate([image, strip], axis=1)


def write_video(frames: list[np.ndarray], path: Path, fps: float) -> Path | None:
    """An MP4 (OpenCV, mp4v) of RGB uint8 frames of equal size; None when no encoder is available."""
    if not frames:
        return None
    h, w = frames[0].shape[:2]
    path.parent.mkdir(parents=True, exist_ok=True)
    with _atomic_path(path) as tmp:
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
        if not writer.isOpened():
            return None
        for f in frames:
            writer.write(cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2BGR))
        writer.release()
    return path


def _to_uint8(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) float in [0, 1] → uint8, rounded."""
    return (np.clip(image, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)


def write_renders(seq: Sequence, field: StressField, rows: np.ndarray, config: ExportConfig, out: Path,
                  reporter: Reporter) -> list[Path]:
    """render/<view>/{appearance,stress}_NNNNNN.png and render/<view>_{appearance,stress}.mp4 for the
    capture cameras (cameras.h5) and an orbit of novel views; stress as a turbo map with a colour bar."""
    import torch

    from stages.render.gaussians import color_to_sh0

    ws = Path(config.workspace)
    gauss, bound, anchor = _load_gaussians(seq, ws)
    stress_art = copy.copy(gauss)
    stress_art.sh = np.zeros((gauss.host_tet.shape[0], 1, 3))
    stress_art.background = np.ones(3)
    _, stress_g, _ = _load_gaussians(seq, ws, stress_art)  # the same placement, coloured by stress per frame
    vmax = stress_scale(config, field, rows)

    xs = seq.adapt.positions[rows]
    lo, hi = xs.reshape(-1, 3).min(0), xs.reshape(-1, 3).max(0)
    g = np.asarray(seq.gravity, np.float64)
    up = -g / np.linalg.norm(g) if np.linalg.norm(g) > 0 else np.array([0.0, 0.0, 1.0])
    n_orbit = max(int(config.orbit_views), 1)
    orbit = orbit_cameras(0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo)), n_orbit, config.render_size, up)

    def tag(i: int) -> str:
        return f"{int(seq.adapt.frames[i]):06d}"

    # (folder, [(row, camera, file tag)]): the capture cameras see every chosen frame; the orbit
    # camera advances one view per frame, or circles a single chosen frame.
    views: list[tuple[str, list]] = []
    cam_path = ws / KIND_FILES["cameras"]
    if cam_path.exists():
        for cam in CamerasArtefact.load(cam_path).cameras:
            views.append((cam.name, [(i, cam, tag(i)) for i in rows]))
    else:
        reporter.warn(f"{cam_path}: not found; rendering the orbit views only.")
    if len(rows) == 1:
        views.append(("orbit", [(rows[0], c, f"{tag(rows[0])}_{k:03d}") for k, c in enumerate(orbit)]))
    else:
        views.append(("orbit", [(i, orbit[k % n_orbit], tag(i)) for k, i in enumerate(rows)]))

    fps = config.video_fps or (1.0 / seq.dt)
    written: list[Path] = []
    total = sum(len(c) for _, c in views)
    with reporter.task("render", total) as task, torch.no_grad():
        for name, cams in views:
            app_frames, stress_frames = [], []
            for i, cam, name_tag in cams:
                x = seq.adapt.positions[i] - anchor
                app = _to_uint8(bound.render_views(x, [cam])[0])
                vm = gaussian_values(stress_g, seq.mesh, field.von_mises_vertex[i])
                stress_g.g.sh.data = torch.as_tensor(color_to_sh0(colormap(vm / vmax))[:, None, :], dtype=torch.float32)
                stress = add_colorbar(_to_uint8(stress_g.render_views(x, [cam])[0]), vmax)
                for kind, img, store in (("appearance", app, app_frames), ("stress", stress, stress_frames)):
                    path = out / "render" / name / f"{kind}_{name_tag}.png"
                    with _atomic_path(path) as tmp:
                        write_image(tmp, img)
                    written.append(path)
                    store.append(img)
                task.advance(1)
            for kind, frames in (("appearance", app_frames), ("stress", stress_frames)):
                if len(frames) > 1:
                    video = write_video(frames, out / "render" / f"{name}_{kind}.mp4", fps)
                    if video is None:
                        reporter.warn("OpenCV has no mp4v encoder here; the PNG frames are written, no MP4.")
                    else:
                        written.append(video)
    return written


# =========================================================================== plots
def write_plots(seq: Sequence, field: StressField | None, force_rows: list[ForceRow] | None, out: Path
                ) -> list[Path]:
    """young.png, loss.png, timing.png, forces.png (with forces), stress.png (with stress)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ad = seq.adapt
    folder = out / "plots"
    folder.mkdir(parents=True, exist_ok=True)
    t = seq.times
    written = []

    def save(fig, name):
        path = folder / name
        with _atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=120, format="png")
        plt.close(fig)
        written.append(path)

    fig, (a0, a1) = plt.subplots(2, 1, figsize=(7, 5.5), sharex=True)
    window = window_young(ad)  # --hold-fit: E(t) holds the fits; the window's own estimate dotted
    for r, nm in enumerate(ad.region_names):
        line, = a0.plot(t, ad.young[:, r], marker=".", label=nm)
        if window is not None:
            a0.plot(t, window[:, r], ":", lw=1, color=line.get_color(), label=f"{nm}: the window's own (Adam)")
        sd = np.asarray(getattr(ad, "young_sigma", np.full(ad.young.shape, np.nan)))[:, r]
        if np.any(np.isfinite(sd)):  # the estimator's E ± σ as a band
            a0.fill_between(t, np.maximum(ad.young[:, r] - sd, 1e-12 * ad.young[:, r]), ad.young[:, r] + sd,
                            color=line.get_color(), alpha=0.25, lw=0, label=f"{nm} E ± σ")
        a1.plot(t, ad.poisson[:, r], marker=".", label=nm)
    a0.set_yscale("log")
    a0.set_ylabel("Young's modulus E (Pa)")
    a1.set_ylabel("Poisson's ratio ν")
    a1.set_xlabel("time (s)")
    a0.legend(title="region")
    a0.set_title(f"{seq.source_path.name}: material per region ({ad.mode}, {ad.space}, window {ad.window})")
    a0.grid(alpha=0.3, which="both")
    a1.grid(alpha=0.3)
    fig.tight_layout()
    save(fig, "young.png")

    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.plot(t, ad.loss, marker=".", color="C3")
    if np.all(ad.loss > 0):
        ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"{ad.loss_kind} loss")
    ax.set_title("window loss per frame")
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    save(fig, "loss.png")

    fig, ax = plt.subplots(figsize=(7, 3.5))
    other = np.maximum(ad.time_total_s - ad.time_forward_s - ad.time_backward_s - ad.time_render_s, 0.0)
    bottom = np.zeros_like(t)
    for vals, label in ((ad.time_forward_s, "forward"), (ad.time_backward_s, "backward"),
                        (ad.time_render_s, "render"), (other, "other")):
        ax.bar(ad.frames, vals, bottom=bottom, label=label, width=0.85)
        bottom = bottom + vals
    ax.set_xlabel("frame")
    ax.set_ylabel("time (s)")
    ax.set_title(f"time per frame (median total {np.median(ad.time_total_s):.3g} s)")
    ax.legend()
    fig.tight_layout()
    save(fig, "timing.png")

    if force_rows:
        fig, (a0, a1) = plt.subplots(2, 1, figsize=(7, 5.5), sharex=True)
        for k, name in enumerate(dict.fromkeys(r.force.name for r in force_rows)):
            rs = [r for r in force_rows if r.force.name == name]
            tt = [r.time_s for r in rs]
            c = f"C{k % 10}"
            a0.plot(tt, [np.linalg.norm(r.force.internal) for r in rs], marker=".", color=c, label=f"{name} ‖Σ f‖")
            a0.plot(tt, [r.force.magnitude_sum for r in rs], ls="--", color=c, label=f"{name} Σ‖f‖")
            a1.plot(tt, [np.linalg.norm(r.force.applied) for r in rs], marker=".", color=c, label=name)
        a0.set_ylabel("internal force (N)")
        a0.set_title("handle / obstacle forces")
        a1.set_ylabel("applied force (N)")
        a1.set_xlabel("time (s)")
        a0.legend(fontsize=8)
        a1.legend(fontsize=8)
        a0.grid(alpha=0.3)
        a1.grid(alpha=0.3)
        fig.tight_layout()
        save(fig, "forces.png")

    if field is not None:
        fig, ax = plt.subplots(figsize=(7, 3.5))
        ax.plot(t, field.von_mises_tet.max(axis=1) / 1e3, marker=".", label="max")
        ax.plot(t, np.percentile(field.von_mises_tet, 99, axis=1) / 1e3, label="99th percentile")
        ax.plot(t, np.median(field.von_mises_tet, axis=1) / 1e3, label="median")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("von Mises stress (kPa)")
        ax.legend()
        ax.grid(alpha=0.3)
        fig.tight_layout()
        save(fig, "stress.png")
    return written


# =========================================================================== scan distance
def surface_ids(faces: np.ndarray) -> np.ndarray:
    """Vertex ids used by the surface faces, sorted."""
    return np.unique(np.asarray(faces, np.int64).ravel())


def write_scan(seq: Sequence, config: ExportConfig, out: Path) -> tuple[list[Path], dict]:
    """Distance of the simulated surface at ``scan_frame`` to a scanned point cloud (paper Fig. 8c).

    Per surface vertex: distance to the nearest scan point; per scan point: distance to the
    surface triangles; Chamfer = ½ (mean sim→scan + mean scan→sim).  Writes a vertex-coloured
    PLY (viridis, 0 … 95th percentile), the per-vertex CSV and a JSON summary."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    path = Path(config.scan)
    if not path.is_file():
        raise ExportError(f"{path}: scan file not found.")
    pcd = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(pcd.points, np.float64)
    if pts.shape[0] == 0:
        mesh_scan = o3d.io.read_triangle_mesh(str(path))
        pts = np.asarray(mesh_scan.vertices, np.float64)
    if pts.shape[0] == 0:
        raise ExportError(f"{path}: holds no point (is it a PLY, PCD, XYZ or PTS point cloud?).")
    if not np.all(np.isfinite(pts)):
        raise ExportError(f"{path}: holds NaN or infinite coordinates.")
    frame = config.scan_frame
    row = select_rows(seq, "last" if frame == -1 else str(frame), "--scan-frame")[0]
    x = seq.adapt.positions[row]
    faces = seq.mesh.surface_faces
    sids = surface_ids(faces)
    d_sim = cKDTree(pts).query(x[sids])[0]
    tmesh = o3d.t.geometry.TriangleMesh()
    tmesh.vertex.positions = o3d.core.Tensor(x.astype(np.float32))
    tmesh.triangle.indices = o3d.core.Tensor(faces.astype(np.int32))
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(tmesh)
    d_scan = rc.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy().astype(np.float64)
    summary = {
        "scan": str(path.resolve()), "frame": int(seq.adapt.frames[row]), "scan_points": int(len(pts)),
        "surface_vertices": int(len(sids)),
        "sim_to_scan_mean_m": float(d_sim.mean()), "sim_to_scan_max_m": float(d_sim.max()),
        "scan_to_sim_mean_m": float(d_scan.mean()), "scan_to_sim_max_m": float(d_scan.max()),
        "chamfer_m": float(0.5 * (d_sim.mean() + d_scan.mean())),
    }
    folder = out / "scan"
    dist_full = np.zeros(seq.mesh.n_vertices)
    dist_full[sids] = d_sim
    hi = float(np.percentile(d_sim, 95)) or 1e-12
    colors = colormap(dist_full / hi, "viridis")
    ply = folder / f"surface_distance_{int(seq.adapt.frames[row]):06d}.ply"
    out_mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(x), o3d.utility.Vector3iVector(faces))
    out_mesh.vertex_colors = o3d.utility.Vector3dVector(colors)
    folder.mkdir(parents=True, exist_ok=True)
    with _atomic_path(ply) as tmp:
        if not o3d.io.write_triangle_mesh(str(tmp), out_mesh, write_ascii=False):
            raise ExportError(f"{ply}: open3d could not write the coloured surface.")
    csv_path = _write_csv(folder / "surface_distance.csv", ["vertex", "distance_m"],
                          [[int(i), float(d)] for i, d in zip(sids, d_sim)])
    js = _write_json(folder / "scan_distance.json", summary)
    return [ply, csv_path, js], summary


def colormap(values: np.ndarray, name: str = "turbo") -> np.ndarray:
    """RGB in [0, 1] (…, 3) of values clipped to [0, 1] through a matplotlib colour map."""
    from matplotlib import colormaps

    return np.asarray(colormaps[name](np.clip(np.asarray(values, np.float64), 0.0, 1.0)))[..., :3]


# =========================================================================== COLMAP
def write_colmap_model(ws: Path, folder: Path) -> list[Path]:
    cams = CamerasArtefact.load(ws / KIND_FILES["cameras"])
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    res = write_colmap(cams.cameras, folder)
    return [Path(p) for p in res] if isinstance(res, (list, tuple)) else [folder]


# =========================================================================== orchestration
PRODUCTS = ("stress", "forces", "vtk", "ply", "render", "plots")


def chosen_products(config: ExportConfig, ws: Path) -> set[str]:
    """The products to make: those flagged on (--stress, ...); with none flagged on (and no --scan, --colmap),
    every one whose inputs exist except those flagged off (--no-forces, ...)."""
    chosen = {p for p in PRODUCTS if getattr(config, p)}
    if chosen or config.scan is not None or config.colmap is not None:
        return chosen
    chosen = {"stress", "forces", "vtk", "plots"}
    if (ws / KIND_FILES["gaussians"]).exists():
        chosen |= {"ply", "render"}  # render: the capture cameras when cameras.h5 exists, orbit views always
    return {p for p in chosen if getattr(config, p) is not False}


def run(config: ExportConfig, reporter: Reporter = SilentReporter()) -> Path:
    """Write the chosen exports into config.out (default WS/export); returns that folder."""
    ws = Path(config.workspace)
    seq = load_sequence(config)
    out = Path(config.out) if config.out is not None else \
        ws / {"adapt": "export", "partial": "export_partial", "rollout": "export_rollout"}[config.source]
    out.mkdir(parents=True, exist_ok=True)
    chosen = chosen_products(config, ws)
    if "forces" in chosen and seq.controls is None:
        if any(getattr(config, p) for p in PRODUCTS):
            raise ExportError(f"{seq.source_path}: forces need the capture's controls.json, but no capture "
                              f"folder is known; pass --capture.")
        reporter.warn("no capture folder known: skipping forces (pass --capture).")
        chosen.discard("forces")
    rows = select_rows(seq, config.frames) if chosen & {"ply", "render"} else None  # fail early on bad --frames
    done: list[str] = []
    field = None
    if chosen:
        field = compute_stress(seq, reporter)
    if "stress" in chosen:
        write_stress(seq, field, out, config)
        done.append(f"stress (max σ_vM {field.von_mises_tet.max() / 1e3:.3g} kPa)")
    force_rows, applied = None, None
    if "forces" in chosen:
        force_rows, applied = compute_forces(seq, field, config, reporter)
        write_forces(force_rows, out)
        names = sorted({r.force.name for r in force_rows})
        done.append(f"forces ({len(names)} handles/obstacles)")
    if "vtk" in chosen:
        paths = write_vtk(seq, field, applied, out, reporter)
        done.append(f"{len(paths) - 1} VTU + PVD")
    if rows is not None:
        if "ply" in chosen:
            paths = write_ply_frames(seq, field, rows, config, out, reporter)
            done.append(f"{len(paths)} PLY")
        if "render" in chosen:
            paths = write_renders(seq, field, rows, config, out, reporter)
            n_png = sum(p.suffix == ".png" for p in paths)
            done.append(f"{n_png} PNG + {len(paths) - n_png} MP4 renders")
    if "plots" in chosen:
        paths = write_plots(seq, field, force_rows, out)
        done.append(f"{len(paths)} plots")
    if config.scan is not None:
        _, summary = write_scan(seq, config, out)
        done.append(f"scan Chamfer {summary['chamfer_m'] * 1e3:.3g} mm")
    if config.colmap is not None:
        write_colmap_model(ws, Path(config.colmap))
        done.append(f"COLMAP model in {config.colmap}")
    reporter.summary(f"export: {seq.n_frames} frames of {seq.source_path.name} → {out}: "
                     + (", ".join(done) if done else "nothing to export"))
    return out
