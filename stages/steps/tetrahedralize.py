"""`rsl tetrahedralize`: the capture's rest shape as a tet mesh with everything the FEM needs (mesh.h5).

The object is a closed surface (obj/ply/stl/off), tetrahedralized with fTetWild
(pytetwild), or a tet mesh (Medit .mesh, gmsh .msh) taken as it is.  Then:

- orientation: every tet gets det[x1−x0, x2−x0, x3−x0] > 0 (two vertices swapped
  where negative); a tet folded over its neighbours (an interior face seen with the
  same orientation from both sides) or a degenerate tet (|V| tiny against the mean)
  is an error;
- regions: a tet whose centroid lies inside the closed mesh ``regions/NAME.obj``
  (generalised winding number ≥ ½) belongs to NAME, else to "body";
- handles: vertex sets from controls.json (``ids`` refer to the vertices of the object
  file as written and are moved to the nearest vertex of the tet mesh);
- rest volumes V, Dm⁻¹ and lumped masses m_i = Σ ρV/4 (stages.sim.mesh);
- the outer surface: boundary triangles oriented outward;
- quality: volumes, dihedral angles, and ``enclosed_volume``, the volume the
  boundary surface encloses (divergence theorem), which equals Σ V for a valid mesh.

fTetWild is not deterministic (two runs on one surface give slightly different
meshes, whatever the thread count); a tet mesh taken as it is gives the same
mesh.h5 every time, and ``rsl run`` reruns this stage only when its inputs or
options change.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stages.artefacts import KIND_FILES, MeshArtefact, Provenance
from stages.capture import SURFACE_SUFFIXES, CaptureError, load_capture, select_handles
from stages.errors import RslError
from stages.workspace import prepare_workspace
from stages.progress import Reporter, SilentReporter
from stages.meshing import (TET_FACES, assign_regions, boundary_faces, dihedral_angles, enclosed_volume,  # noqa: F401
                            map_id_selections, mesh_quality, orient_tets, quadratic_mesh, read_surface, read_tet_mesh,
                            tet_faces, tetwild, winding_numbers)
from stages.sim.mesh import rest_quantities, signed_volumes
from stages.sim.quadrature import jacobian_ratio, mid_edge_closure, quadratic_surface


@dataclass(frozen=True)
class TetrahedralizeConfig:
    capture: Path
    """Capture folder holding capture.toml and the object mesh."""
    workspace: Path
    """Workspace folder; mesh.h5 is written there."""
    edge_length: float = 0.05
    """Target tet edge length as a fraction of the bounding-box diagonal (surface input only)."""
    max_tets: int = 0
    """Upper bound on the number of tets: coarsen (longer edges) until under it; 0 = no bound."""
    optimize: bool = True
    """Let fTetWild improve tet quality (slower, better elements)."""
    threads: int = 0
    """Threads for fTetWild (0 = all cores); fTetWild itself is not deterministic, so reruns on a surface may differ."""
    envelope: float = 1e-3
    """Largest distance of the tet mesh's surface from the input surface, as a fraction of the bounding-box diagonal."""
    degenerate_tol: float = 1e-6
    """A tet with |volume| below this fraction of the mean tet volume is degenerate (an error)."""
    preview: bool = True
    """Also draw WS/mesh.png: three views with regions and handles, and the dihedral-angle histogram."""
    order: int = 2
    """Element order: 2 = quadratic 10-node tets, mid-edge nodes on the input surface (docs/results/convergence.md);
    1 = linear 4-node tets (faster per DOF, far too stiff in bending)."""


def build_mesh(config: TetrahedralizeConfig, reporter: Reporter = SilentReporter()) -> tuple[MeshArtefact, list[Path]]:
    """Everything of mesh.h5 from the capture, and the input files it was made from."""
    cap = load_capture(config.capture)
    src = cap.mesh_path
    inputs = [cap.toml_path, src]
    quality: dict = {}
    surface = None  # the input surface, onto which P2 mid-edge nodes of boundary edges are projected
    if src.suffix.lower() in SURFACE_SUFFIXES:
        sv, sf = read_surface(src, reporter)
        surface = (sv, sf)
        quality["input_surface_volume"] = enclosed_volume(sv, sf)
        v, t, fac = tetwild(sv, sf, config.edge_length, config.max_tets, config.optimize, config.threads,
                             config.envelope, reporter)
        quality.update(source="ftetwild", edge_length_fac=fac)
    else:
        v, t, notes = read_tet_mesh(src)
        for n in notes:
            reporter.warn(f"{src.name}: {n}.")
        quality.update(source="tet mesh")
        if config.max_tets > 0 and len(t) > config.max_tets:
            reporter.info(f"{src.name} has {len(t)} tets > --max-tets {config.max_tets}; re-tetrahedralizing its surface")
            tt, _ = orient_tets(v, t)
            try:
                bf = boundary_faces(tt)
            except ValueError as e:
                raise CaptureError(f"{src}: {e}.") from None
            used = np.unique(bf)
            remap = np.full(len(v), -1, dtype=np.int64)
            remap[used] = np.arange(len(used))
            v, t, fac = tetwild(v[used], remap[bf], config.edge_length, config.max_tets, config.optimize,
                                config.threads, config.envelope, reporter)
            quality.update(source="tet mesh surface re-tetrahedralized by ftetwild", edge_length_fac=fac)

    # Degenerate tets first (their sign means nothing), then orientation, then folds.
    vol = signed_volumes(v, t)
    mean = float(np.mean(np.abs(vol)))
    tiny = np.abs(vol) <= config.degenerate_tol * mean
    if mean <= 0 or tiny.any():
        i = int(np.flatnonzero(tiny)[0]) if tiny.any() else 0
        raise CaptureError(f"{src}: {int(tiny.sum())} degenerate tets (e.g. tet {i}, volume {vol[i]:.3g} m³ "
                           f"against a mean of {mean:.3g} m³); fix the mesh or re-tetrahedralize the surface.")
    t, flipped = orient_tets(v, t)
    if 0 < flipped < len(t):
        reporter.info(f"re-oriented {flipped} of {len(t)} tets to positive volume")
    try:
        faces = boundary_faces(t)
    except ValueError as e:
        raise CaptureError(f"{src}: {e}.") from None

    if "body" in cap.region_meshes():
        raise CaptureError(f"{cap.region_meshes()['body']}: the region name 'body' is reserved for the tets "
                           f"outside every region; rename the file.")
    region, region_names = assign_regions(v, t, cap.region_meshes(), reporter)
    inputs += list(cap.region_meshes().values())
    for name in cap.material.regions:
        if name not in cap.region_meshes():
            reporter.warn(f"capture.toml sets material for region '{name}' but regions/{name}.obj does not exist.")

    controls = map_id_selections(cap.controls(), src, v, cap.controls_path)
    quality["order"] = int(config.order)
    corners = t
    if config.order == 2:  # vertices: the corners, then one node per edge (on the input surface if any)
        v, t, reverted = quadratic_mesh(v, t, surface)
        faces = quadratic_surface(t)
        quality.update(curved_nodes_reverted=reverted, min_jacobian_ratio=float(jacobian_ratio(v, t).min()))
        if reverted:
            reporter.info(f"{reverted} mid-edge nodes kept on straight edges (curving them would fold their tets)")
    handles = {k: mid_edge_closure(ids, t) for k, ids in select_handles(controls, v, cap.controls_path).items()}
    loads = {ld.name: mid_edge_closure(ld.select.select(v), t) for ld in controls.loads}
    if cap.controls_path.exists():
        inputs.append(cap.controls_path)

    volumes, dm_inv, masses = rest_quantities(v, t, cap.density)
    quality.update(mesh_quality(v, corners, volumes))
    quality.update(n_vertices=int(len(v)), n_tets=int(len(t)), n_surface_faces=int(len(faces)),
                   flipped_tets=flipped, enclosed_volume=enclosed_volume(v, faces))
    mesh = MeshArtefact(vertices=v, tets=t, surface_faces=faces, tet_region=region, region_names=region_names,
                        rest_volumes=volumes, dm_inv=dm_inv, vertex_masses=masses, density=cap.density,
                        handles=handles, quality=quality, loads=loads)
    return mesh, inputs


def draw_preview(mesh: MeshArtefact, path: Path) -> None:
    """PNG: the surface seen along x, y and z (tet centroids coloured by region, handles in red) and a
    histogram of the dihedral angles."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import PolyCollection
    from matplotlib.figure import Figure

    fig = Figure(figsize=(16, 4), dpi=90)
    FigureCanvasAgg(fig)
    v, f = mesh.vertices, mesh.surface_faces
    cent = v[mesh.tets[:, :4]].mean(axis=1)
    for k, (i, j) in enumerate([(0, 1), (0, 2), (1, 2)]):
        ax = fig.add_subplot(1, 4, k + 1)
        ax.add_collection(PolyCollection(v[f][:, :, [i, j]], facecolors="none", edgecolors=(0, 0, 0, 0.15),
                                         linewidths=0.4))
        for r, name in enumerate(mesh.region_names):
            sel = mesh.tet_region == r
            ax.scatter(cent[sel, i], cent[sel, j], s=3, label=f"{name} ({int(sel.sum())} tets)")
        for name, ids in mesh.handles.items():
            ax.scatter(v[ids, i], v[ids, j], s=8, c="red", marker="x")
        ax.set_aspect("equal")
        ax.autoscale_view()
        ax.set_xlabel("xyz"[i] + " (m)")
        ax.set_ylabel("xyz"[j] + " (m)")
        if k == 0:
            fig.legend(loc="upper center", ncol=max(1, len(mesh.region_names)), fontsize=8, markerscale=3)
    ax = fig.add_subplot(1, 4, 4)
    ax.hist(dihedral_angles(v, mesh.tets[:, :4]).ravel(), bins=60, color="gray")
    ax.set_xlabel("dihedral angle (deg)")
    ax.set_ylabel("count")
    ax.set_title(f"{mesh.n_tets} tets (order {mesh.order}), {mesh.n_vertices} vertices, handles in red", fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.92))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    fig.savefig(tmp, format="png")
    tmp.replace(path)


def run(config: TetrahedralizeConfig, reporter: Reporter = SilentReporter()) -> Path:
    """Write WS/mesh.h5 from the capture's object mesh; returns its path."""
    if config.edge_length <= 0:
        raise RslError(f"--edge-length should be positive, found {config.edge_length}.")
    if config.order not in (1, 2):
        raise RslError(f"--order should be 1 (linear tets) or 2 (quadratic tets), found {config.order}.")
    load_capture(config.capture)  # a bad capture is reported before the workspace is touched
    prepare_workspace(config.workspace)  # writable? (before the compute) and no stale temp files
    mesh, inputs = build_mesh(config, reporter)
    out = Path(config.workspace) / KIND_FILES["mesh"]
    mesh.save(out, Provenance.make(config, inputs))
    if config.preview:
        draw_preview(mesh, out.with_suffix(".png"))
    q = mesh.quality
    regions = ", ".join(f"{n} {int(np.sum(mesh.tet_region == i))}" for i, n in enumerate(mesh.region_names))
    reporter.summary(
        f"{out}: {mesh.n_vertices} vertices, {mesh.n_tets} tets of order {mesh.order} ({regions}), "
        f"{len(mesh.surface_faces)} surface "
        f"triangles, {len(mesh.handles)} handles; volume {q['total_volume']:.4g} m³, mass "
        f"{mesh.vertex_masses.sum():.4g} kg; tet volume {q['min_volume']:.3g}–{q['max_volume']:.3g} m³, "
        f"dihedral angles {q['min_dihedral_deg']:.1f}°–{q['max_dihedral_deg']:.1f}°"
        + (f"; picture {out.with_suffix('.png').name}" if config.preview else ""))
    return out
