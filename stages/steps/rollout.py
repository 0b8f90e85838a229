"""`rsl rollout`: predict what new handle/obstacle motions do to the object, with the adapted material.

"What shape will this action give": simulate NEW_CONTROLS.json with θ from adapt.h5 —
the last adapted θ (``material="last"``) or θ(t) replayed frame by frame (``"replay"``,
holding the last value past the adapted sequence) — starting from the adapted state
(the last two adapted positions, so the object keeps its velocity) or from rest.

Writes WS/rollout.h5, an AdaptArtefact with mode "rollout" and space "full" whose
frames index the new controls (0 = the first predicted step), so that
``rsl export --source rollout`` turns it into stress, forces, VTU and renders.  Its
``extra`` holds per-frame summaries a controller can read without the mesh:
von Mises max / mean / 99th percentile and, per handle and obstacle, the internal
force sum, the sum of magnitudes and the applied (spring / contact) force.

The simulation is the full-space implicit Euler of stages/sim/scene.py, or the reduced
dynamics of stages/subspace (x = φ(z)) when the adaptation ran in the reduced space and
WS/subspace.h5 is there (``space="auto"``), or when asked for (``space="reduced"``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from stages.artefacts import KIND_FILES, AdaptArtefact, MeshArtefact, Provenance, SubspaceArtefact
from stages.capture import Controls, load_capture, load_controls, select_handles
from stages.errors import RslError
from stages.artefacts import check_same_mesh
from stages.workspace import prepare_workspace
from stages.progress import Reporter, SilentReporter
from stages.sim import stress as st

ROLLOUT_FILE = "rollout.h5"
MATERIALS = ("last", "replay")
SPACES = ("auto", "full", "reduced")


class RolloutError(RslError):
    """A rollout cannot be made from what it was given."""


@dataclass(frozen=True)
class RolloutConfig:
    capture: Path
    """Capture folder (material model, fps, gravity)."""
    workspace: Path
    """Workspace folder holding adapt.h5 and mesh.h5; rollout.h5 is written there."""
    controls: Path
    """The new controls (controls.json format): handle and obstacle motions to predict."""
    frames: int = 0
    """Frames to simulate; 0 = as many as the new controls describe (or as adapt.h5 holds, if constant)."""
    material: Literal["last", "replay"] = "last"
    """Material θ: 'last' (the last adapted θ) or 'replay' (θ(t) of the adapted frames, then the last)."""
    from_rest: bool = False
    """Start from the rest shape instead of the last two adapted positions."""
    space: Literal["auto", "full", "reduced"] = "auto"
    """Simulate in 'full' space, in the 'reduced' subspace (needs subspace.h5), or 'auto': reduced when
    adapt.h5 was adapted in the reduced space and subspace.h5 exists."""
    solver: Literal["auto", "cholmod", "splu"] = "auto"
    """Linear solver of the full-space Newton steps (see stages/sim/linsolve.py)."""
    contact_distance: float = 1.0e-3
    """A vertex touches an obstacle when closer than the contact margin plus this distance, m."""


def material_schedule(adapt: AdaptArtefact, mode: str, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(young, poisson), (frames, R) each: the last adapted θ, or θ(t) replayed holding the last row."""
    if mode == "last":
        return (np.repeat(adapt.young[-1:], frames, axis=0), np.repeat(adapt.poisson[-1:], frames, axis=0))
    rows = np.minimum(np.arange(frames), len(adapt.frames) - 1)
    return adapt.young[rows], adapt.poisson[rows]


def run(config: RolloutConfig, reporter: Reporter = SilentReporter()) -> Path:
    """Simulate the new controls with the adapted material; writes WS/rollout.h5 and returns its path."""
    from stages.sim.scene import frame_inputs, make_scene, simulate  # numba kernels: loaded on use

    ws = Path(config.workspace)
    if config.material not in MATERIALS:
        raise RolloutError(f"--material '{config.material}' is neither 'last' nor 'replay'.")
    if config.space not in SPACES:
        raise RolloutError(f"--space '{config.space}' is not one of {', '.join(SPACES)}.")
    if config.frames < 0:
        raise RolloutError(f"--frames {config.frames} is negative.")
    capture = load_capture(config.capture)
    adapt_path, mesh_path = ws / KIND_FILES["adapt"], ws / KIND_FILES["mesh"]
    prepare_workspace(ws)  # writable? (before the compute) and no stale temp files of a killed run
    adapt = AdaptArtefact.load(adapt_path)
    mesh = MeshArtefact.load(mesh_path)
    check_same_mesh(mesh_path, adapt_path, ws / KIND_FILES["subspace"] if config.space != "full" else None)
    if adapt.positions.shape[1] != mesh.n_vertices:
        raise RolloutError(f"{adapt_path}: positions hold {adapt.positions.shape[1]} vertices but {mesh_path} "
                           f"has {mesh.n_vertices}; the two come from different meshes.")
    if adapt.young.shape[1] != len(mesh.region_names):
        raise RolloutError(f"{adapt_path}: holds θ for {adapt.young.shape[1]} regions but {mesh_path} has "
                           f"{len(mesh.region_names)}.")
    if len(adapt.frames) == 0:
        raise RolloutError(f"{adapt_path}: holds no frame to start from.")
    controls_path = Path(config.controls)
    controls = load_controls(controls_path)
    # name the new controls file when a selection picks nothing (make_scene would say "controls.json")
    unknown = [h for h in controls.handles if h.name not in mesh.handles]
    select_handles(Controls(handles=unknown, loads=controls.loads), mesh.vertices, controls_path)
    T = config.frames or controls.n_frames or len(adapt.frames)
    scene = make_scene(mesh, controls, capture.material.model, capture.dt, capture.gravity,
                       damping=capture.material.damping)
    inputs = [frame_inputs(scene, controls, t) for t in range(T)]
    young, poisson = material_schedule(adapt, config.material, T)

    sub_path = ws / KIND_FILES["subspace"]
    space = config.space
    if space == "auto":
        space = "reduced" if adapt.space == "reduced" and sub_path.exists() else "full"
    inputs_used = [adapt_path, mesh_path, controls_path, capture.toml_path]

    t0 = time.perf_counter()
    with reporter.task(f"rollout ({space} space)", T) as task:
        if space == "full":
            if config.from_rest:
                x_prev, x_prev2, start = scene.rest, scene.rest, "rest"
            else:
                x_prev = adapt.positions[-1]
                x_prev2 = adapt.positions[-2] if len(adapt.frames) >= 2 else x_prev
                start = f"adapted frame {int(adapt.frames[-1])}"
            X = simulate(scene, inputs, young, poisson, x_prev=x_prev, x_prev2=x_prev2, solver=config.solver,
                         callback=lambda t: task.advance(1))
            Z = np.zeros((T, 0))
        else:
            from stages.subspace import ReducedModel  # equinox: only for a reduced-space rollout

            if not sub_path.exists():
                raise RolloutError(f"{sub_path}: file not found; --space reduced needs `rsl train-subspace`.")
            model = ReducedModel.from_artefacts(SubspaceArtefact.load(sub_path), scene)
            inputs_used.append(sub_path)
            if config.from_rest:
                z1 = z2 = np.asarray(model.z_rest)
                start = "rest"
            else:
                if adapt.z.shape[1] == model.dim:  # adapted in this subspace: its states
                    zs = adapt.z[-2:]
                else:  # adapted in full space: project the last positions
                    zs = np.stack([model.encode(x) for x in adapt.positions[-2:]])
                z1, z2 = zs[-1], zs[0]
                start = f"adapted frame {int(adapt.frames[-1])}"
            Z = np.asarray(model.simulate([model.reduce_inputs(i) for i in inputs], young, poisson, z_prev=z1,
                                          z_prev2=z2, callback=lambda t: task.advance(1)))
            X = np.asarray(model.decode(Z))
            x_prev = np.asarray(model.decode(z1))
            x_prev2 = np.asarray(model.decode(z2))
    t_sim = time.perf_counter() - t0

    summary, worst = _summaries(scene, inputs, X, young, poisson, (x_prev, x_prev2), mesh, capture.material.model,
                                config.contact_distance)
    per_frame = np.full(T, t_sim / T)
    extra = {
        "controls": str(controls_path.resolve()), "material": config.material, "start": start,
        "dt": capture.dt, "gravity": np.asarray(capture.gravity).tolist(),
        "material_model": capture.material.model, "source_mode": adapt.mode, "source_space": adapt.space,
        "space": space,
        **summary,
    }
    out = ws / ROLLOUT_FILE
    AdaptArtefact(
        frames=np.arange(T), young=young, poisson=poisson, z=Z, positions=X, loss=np.zeros(T),
        time_forward_s=per_frame, time_backward_s=np.zeros(T), time_render_s=np.zeros(T),
        time_total_s=per_frame, region_names=list(mesh.region_names), mode="rollout", space=space,
        loss_kind="none", window=0, extra=extra,
    ).save(out, Provenance.make(config, inputs_used))
    reporter.summary(
        f"rollout: {T} frames ({space} space) from {start} with θ {config.material} "
        f"(E = {', '.join(f'{e:.3g}' for e in young[-1])} Pa) in {t_sim:.1f} s; "
        f"max von Mises {worst / 1e3:.3g} kPa → {out}")
    return out


def _summaries(scene, inputs, X, young, poisson, x_before, mesh, model, contact_distance) -> tuple[dict, float]:
    """Per-frame von Mises summaries and handle/obstacle forces, as JSON-able lists."""
    stress = {k: [] for k in ("max_pa", "mean_pa", "p50_pa", "p90_pa", "p99_pa")}
    forces: dict[str, dict] = {}
    x_prev, x_prev2 = x_before  # (x_{−1}, x_{−2}) before the first rolled-out frame
    quad = scene.quad  # quadrature points: one per linear tet, 4 per quadratic tet
    for t in range(X.shape[0]):
        mu, lam = st.tet_lame_from_regions(young[t], poisson[t], mesh.tet_region)
        s = st.point_stress(X[t], quad, mu[quad.element], lam[quad.element], model)
        for k, v in st.stress_summary(s["von_mises"], quad.weight).items():
            stress[k].append(v)
        f_int = st.point_nodal_forces(s["P"], quad, mesh.n_vertices)
        for f in st.set_forces(scene, inputs[t], X[t], x_prev, f_int, contact_distance, x_prev2=x_prev2):
            d = forces.setdefault(f.name, {"kind": f.kind, "internal_N": [], "magnitude_sum_N": [],
                                           "applied_N": [], "n_vertices": []})
            d["internal_N"].append(np.asarray(f.internal).tolist())
            d["magnitude_sum_N"].append(f.magnitude_sum)
            d["applied_N"].append(np.asarray(f.applied).tolist())
            d["n_vertices"].append(f.n_vertices)
        x_prev2, x_prev = x_prev, X[t]
    worst = max(stress["max_pa"]) if stress["max_pa"] else 0.0
    return {"stress": stress, "forces": forces}, worst
