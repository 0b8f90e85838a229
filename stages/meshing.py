"""Tet-mesh geometry shared by the stages that build meshes (tetrahedralize, synth):
reading tet meshes and surfaces, fTetWild, orientation, boundary faces, winding numbers,
quality measures, regions and the mapping of controls' vertex ids onto a tet mesh.
Pure functions over arrays and mesh files; no artefacts are written here."""
from __future__ import annotations

import contextlib
import dataclasses
import os
import tempfile
from pathlib import Path

import numpy as np

from stages.capture import SURFACE_SUFFIXES, CaptureError
from stages.errors import RslError
from stages.progress import Reporter, SilentReporter
from stages.sim.mesh import TET_FACES, signed_volumes
from stages.sim.mesh import boundary_faces as _boundary_faces
from stages.sim.quadrature import jacobian_ratio, quadratic_tets


@contextlib.contextmanager
def _in_temporary_directory():
    """fTetWild writes a scratch file (__tracked_surface.stl) into the working directory: give it its own."""
    old = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="rsl-tetwild-") as d:
        os.chdir(d)
        try:
            yield
        finally:
            os.chdir(old)


# =========================================================================== pure geometry
def orient_tets(vertices: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, int]:
    """Swap vertices 1 and 2 of every tet with negative signed volume; returns (tets (m,4), count flipped)."""
    tets = np.array(tets, dtype=np.int64, copy=True)
    neg = signed_volumes(vertices, tets) < 0
    tets[neg, 1], tets[neg, 2] = tets[neg, 2].copy(), tets[neg, 1].copy()
    return tets, int(neg.sum())


def _canonical(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted vertex triple of each face (k,3) and its orientation parity (+1/−1) relative to it."""
    keys = np.sort(faces, axis=1)
    # An oriented triangle is an even or odd permutation of its sorted triple.
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    even = ((a < b) & (b < c)) | ((b < c) & (c < a)) | ((c < a) & (a < b))
    return keys, np.where(even, 1, -1)


def tet_faces(tets: np.ndarray) -> np.ndarray:
    """The 4 outward-oriented faces of each positively oriented tet, (4m, 3); face 4t+k is opposite vertex k."""
    return tets[:, TET_FACES].reshape(-1, 3)


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Outward boundary triangles (k, 3) of a consistently, positively oriented tet mesh.

    Raises ValueError naming a tet when an interior face is shared by more than two
    tets or seen with the same orientation from both sides (a folded, inverted tet).
    """
    faces = tet_faces(tets)
    keys, parity = _canonical(faces)
    uniq, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    if counts.max(initial=0) > 2:
        f = int(np.flatnonzero(counts[inverse] > 2)[0])
        raise ValueError(f"face {uniq[inverse[f]].tolist()} of tet {f // 4} is shared by "
                         f"{int(counts[inverse[f]])} tets (non-manifold mesh)")
    # Interior faces: the two tets must see them with opposite orientation.
    psum = np.zeros(len(uniq), dtype=np.int64)
    np.add.at(psum, inverse, parity)
    bad = (counts == 2) & (psum != 0)
    if bad.any():
        f = int(np.flatnonzero(bad[inverse])[0])
        tets_sharing = np.flatnonzero(inverse == inverse[f]) // 4
        raise ValueError(f"tets {tets_sharing.tolist()} overlap across a shared face: one of them is "
                         f"inverted (folded over its neighbour)")
    return _boundary_faces(tets)  # the faces used by one tet (the extraction lives in stages.sim.mesh)


def enclosed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Volume inside a closed outward-oriented triangle surface: Σ a·(b×c)/6 (divergence theorem), m³."""
    p = vertices[faces]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


def dihedral_angles(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """The 6 interior dihedral angles of each tet in degrees, (m, 6): π − angle between outward face normals."""
    p = vertices[tets[:, TET_FACES]]  # (m, 4, 3, 3)
    n = np.cross(p[:, :, 1] - p[:, :, 0], p[:, :, 2] - p[:, :, 0])  # (m, 4, 3) outward
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    cos = np.stack([np.einsum("ij,ij->i", n[:, i], n[:, j]) for i, j in pairs], axis=1)
    return np.degrees(np.pi - np.arccos(np.clip(cos, -1.0, 1.0)))


def winding_numbers(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                    chunk: int = 2048) -> np.ndarray:
    """Generalised winding number of a closed triangle surface at points (k, 3): Σ Ω_f / 4π.

    Ω_f is the signed solid angle of triangle f (Van Oosterom & Strackee 1983):
    tan(Ω/2) = a·(b×c) / (|a||b||c| + (a·b)|c| + (a·c)|b| + (b·c)|a|), a, b, c the corners
    relative to the point.  ≈1 inside an outward-oriented surface, ≈0 outside.
    """
    tri = vertices[faces]  # (f, 3, 3)
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        d = tri[None] - points[s:s + chunk, None, None, :]  # (c, f, 3, 3)
        a, b, c = d[:, :, 0], d[:, :, 1], d[:, :, 2]
        la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
        det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc
               + np.einsum("pfi,pfi->pf", a, c) * lb + np.einsum("pfi,pfi->pf", b, c) * la)
        out[s:s + chunk] = 2.0 * np.arctan2(det, den).sum(axis=1) / (4.0 * np.pi)
    return out


def mesh_quality(vertices: np.ndarray, tets: np.ndarray, volumes: np.ndarray) -> dict:
    """Min/max/mean tet volume (m³), worst (smallest and largest) dihedral angle (deg), edge lengths (m)."""
    ang = dihedral_angles(vertices, tets)
    e = vertices[tets[:, [1, 2, 3, 2, 3, 3]]] - vertices[tets[:, [0, 0, 0, 1, 1, 2]]]
    lengths = np.linalg.norm(e, axis=-1)
    return {
        "min_volume": float(volumes.min()), "max_volume": float(volumes.max()),
        "mean_volume": float(volumes.mean()), "total_volume": float(volumes.sum()),
        "min_dihedral_deg": float(ang.min()), "max_dihedral_deg": float(ang.max()),
        "min_edge": float(lengths.min()), "max_edge": float(lengths.max()), "mean_edge": float(lengths.mean()),
    }


# =========================================================================== reading inputs
def read_tet_mesh(path: Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """A Medit/gmsh tet mesh -> (vertices (n,3), tets (m,4) as stored, notes); unused vertices dropped."""
    import meshio

    notes: list[str] = []
    try:
        m = meshio.read(str(path))
    except Exception as e:  # meshio raises many kinds of errors on malformed files
        raise CaptureError(f"{path}: cannot read the tet mesh ({type(e).__name__}: {e}).") from None
    blocks = [np.asarray(c.data) for c in m.cells if c.type == "tetra"]
    quad = [np.asarray(c.data)[:, :4] for c in m.cells if c.type == "tetra10"]
    if quad:
        notes.append("quadratic tets reduced to their 4 corner vertices")
    blocks += quad
    if not blocks or sum(len(b) for b in blocks) == 0:
        kinds = sorted({c.type for c in m.cells}) or ["nothing"]
        raise CaptureError(f"{path}: holds no tetrahedra (found {', '.join(kinds)}); give a tet mesh "
                           f"or a closed surface.")
    tets = np.concatenate(blocks).astype(np.int64)
    pts = np.asarray(m.points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise CaptureError(f"{path}: vertices should be 3-D, found shape {pts.shape}.")
    if tets.min() < 0 or tets.max() >= len(pts):
        raise CaptureError(f"{path}: tets refer to vertices outside 0..{len(pts) - 1}.")
    if not np.all(np.isfinite(pts)):
        raise CaptureError(f"{path}: holds NaN or infinite vertex coordinates.")
    used = np.unique(tets)
    if len(used) < len(pts):
        remap = np.full(len(pts), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        tets, pts = remap[tets], pts[used]
    return pts, tets, notes


def read_surface(path: Path, reporter: Reporter) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangle surface -> (vertices (n,3), faces (k,3) outward); small holes are filled."""
    import trimesh

    mesh = _load_triangles(path, "surface mesh")
    if not np.all(np.isfinite(mesh.vertices)):
        raise CaptureError(f"{path}: holds NaN or infinite vertex coordinates.")
    if not mesh.is_watertight:
        before = _open_edges(mesh)
        mesh.merge_vertices()
        mesh.update_faces(mesh.nondegenerate_faces())
        mesh.update_faces(mesh.unique_faces())
        trimesh.repair.fill_holes(mesh)
        if not mesh.is_watertight:
            raise CaptureError(f"{path}: the surface is not watertight ({_open_edges(mesh)} open edges after "
                               f"repair); close its holes or give a tet mesh.")
        reporter.warn(f"{path.name}: surface had {before} open edges; repaired (merged vertices, filled holes).")
    trimesh.repair.fix_winding(mesh)
    if mesh.volume < 0:
        mesh.invert()
    if not mesh.volume > 0:
        raise CaptureError(f"{path}: the surface encloses no volume.")
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def _load_triangles(path: Path, what: str):
    """trimesh.load of a triangle mesh with at least one face; ``what`` ("surface mesh", "region mesh")
    names it in the error."""
    import trimesh

    try:
        mesh = trimesh.load(str(path), force="mesh", process=True)
    except Exception as e:
        raise CaptureError(f"{path}: cannot read the {what} ({type(e).__name__}: {e}).") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise CaptureError(f"{path}: the {what} holds no triangles.")
    return mesh


def _open_edges(mesh) -> int:
    import trimesh

    edges = mesh.edges_sorted
    groups = trimesh.grouping.group_rows(edges, require_count=1)
    return int(len(groups))


def _closed_surface(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A region mesh: must be closed; returned outward-oriented."""
    import trimesh

    mesh = _load_triangles(path, "region mesh")
    if not mesh.is_watertight:
        raise CaptureError(f"{path}: region mesh is not closed ({_open_edges(mesh)} open edges); a region "
                           f"must be a watertight surface.")
    trimesh.repair.fix_winding(mesh)
    if mesh.volume < 0:
        mesh.invert()
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def tetwild(vertices: np.ndarray, faces: np.ndarray, edge_length: float = 0.05, max_tets: int = 0,
            optimize: bool = True, threads: int = 0, envelope: float = 1e-3,
            reporter: Reporter = SilentReporter()) -> tuple[np.ndarray, np.ndarray, float]:
    """fTetWild; over ``max_tets`` tets it retries with coarsening on and longer edges.

    Returns (vertices (n,3), tets (m,4) as fTetWild orients them, edge length used as a
    fraction of the bounding-box diagonal).
    """
    import pytetwild

    fac, coarsen = float(edge_length), False
    for attempt in range(8):
        with reporter.task(f"tetrahedralizing (edge {fac:.3g} × diagonal{', coarsening' if coarsen else ''})", None):
            with _in_temporary_directory():
                v, t = pytetwild.tetrahedralize(np.asarray(vertices, np.float64), np.asarray(faces, np.int32),
                                                edge_length_fac=fac, optimize=optimize, coarsen=coarsen,
                                                epsilon=envelope, num_threads=threads, quiet=True)
        v, t = np.asarray(v, np.float64), np.asarray(t, np.int64)
        if len(t) == 0:
            raise RslError(f"fTetWild produced no tetrahedra at edge length {fac:.3g} × diagonal; "
                           f"the surface may be too thin for it.")
        if max_tets <= 0 or len(t) <= max_tets:
            return v, t, fac
        reporter.info(f"{len(t)} tets > --max-tets {max_tets}; coarsening")
        if coarsen:
            fac *= max(1.15, 1.05 * (len(t) / max_tets) ** (1.0 / 3.0))
        coarsen = True
        if fac > 1.0:
            break
    raise RslError(f"cannot get under --max-tets {max_tets} tets (edge length reached {fac:.3g} × diagonal); "
                   f"raise the cap.")


def assign_regions(vertices: np.ndarray, tets: np.ndarray, region_meshes: dict[str, Path],
                   reporter: Reporter) -> tuple[np.ndarray, list[str]]:
    """Region index per tet (m,) and region names; "body" first, then regions/NAME in name order.

    A tet belongs to the first region whose closed mesh contains its centroid; regions
    left without any tet are dropped with a warning.
    """
    centroids = vertices[tets].mean(axis=1)
    names = ["body"] + list(region_meshes)
    region = np.zeros(len(tets), dtype=np.int64)
    for k, (name, path) in enumerate(region_meshes.items(), start=1):
        rv, rf = _closed_surface(path)
        inside = (winding_numbers(centroids, rv, rf) >= 0.5) & (region == 0)
        region[inside] = k
    counts = np.bincount(region, minlength=len(names))
    keep = [i for i, c in enumerate(counts) if c > 0]
    for i, c in enumerate(counts):
        if c == 0 and i > 0:
            reporter.warn(f"region '{names[i]}' ({region_meshes[names[i]].name}) contains no tet centroid; dropped.")
    remap = np.full(len(names), -1, dtype=np.int64)
    remap[keep] = np.arange(len(keep))
    return remap[region], [names[i] for i in keep]


def map_id_selections(controls, src: Path, vertices: np.ndarray, controls_path: Path):
    """Controls whose ``ids`` selections (vertex ids of the object file as written) point at the nearest
    vertices of the tet mesh, which fTetWild or the removal of unused vertices renumbered."""
    sels = [h for h in controls.handles + controls.loads if h.select.kind == "ids"]
    if not sels:
        return controls
    if src.suffix.lower() in SURFACE_SUFFIXES:
        import trimesh

        original = np.asarray(trimesh.load(str(src), force="mesh", process=False).vertices, np.float64)
    else:
        import meshio

        original = np.asarray(meshio.read(str(src)).points, np.float64)
    from scipy.spatial import cKDTree

    tree = cKDTree(vertices)

    def mapped(item):
        ids = np.asarray(item.select.ids)
        if ids.max() >= len(original):
            raise CaptureError(f"{controls_path}: '{item.name}' selects vertex id {int(ids.max())} but {src.name} "
                               f"has {len(original)} vertices.")
        _, near = tree.query(original[ids])
        return dataclasses.replace(item, select=dataclasses.replace(item.select, ids=np.unique(near)))

    return dataclasses.replace(
        controls, handles=[mapped(h) if h.select.kind == "ids" else h for h in controls.handles],
        loads=[mapped(ld) if ld.select.kind == "ids" else ld for ld in controls.loads])


# =========================================================================== the stage


# =========================================================================== quadratic (P2) meshes
def closest_points_on_surface(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The closest point (p, 3) on a triangle surface to each point (p, 3): the nearest triangle from
    open3d's RaycastingScene, then the closest point on it in float64 (Ericson, Real-Time Collision
    Detection §5.1.5, by the triangle's Voronoi regions)."""
    import open3d as o3d

    points = np.asarray(points, np.float64)
    if len(points) == 0:
        return points.copy()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(faces, np.uint32)))
    fid = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))["primitive_ids"].numpy()
    tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)[fid.astype(np.int64)]]  # (p, 3, 3)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac, ap, bp, cp = b - a, c - a, points - a, points - b, points - c
    dot = lambda u, v: np.einsum("pi,pi->p", u, v)  # noqa: E731
    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    out = np.empty_like(points)
    done = np.zeros(len(points), bool)

    def put(mask, value):
        m = mask & ~done
        out[m] = value[m]
        done[m] = True

    with np.errstate(divide="ignore", invalid="ignore"):
        put((d1 <= 0) & (d2 <= 0), a)
        put((d3 >= 0) & (d4 <= d3), b)
        put((d6 >= 0) & (d5 <= d6), c)
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + (d1 / (d1 - d3))[:, None] * ab)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + (d2 / (d2 - d6))[:, None] * ac)
        put((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[:, None] * (c - b))
        denom = 1.0 / (va + vb + vc)
        put(np.ones(len(points), bool), a + (vb * denom)[:, None] * ab + (vc * denom)[:, None] * ac)
    return out


def quadratic_mesh(vertices: np.ndarray, tets: np.ndarray, surface: tuple[np.ndarray, np.ndarray] | None = None,
                   min_jacobian: float = 0.2) -> tuple[np.ndarray, np.ndarray, int]:
    """P2 mesh (vertices (n + e, 3), tets (m, 10), number of reverted mid-edge nodes) from linear tets.
    With ``surface`` = (vertices, faces) of the input surface, the mid-edge nodes of boundary edges go to
    their closest point on it (curved elements); an element whose det J falls below ``min_jacobian``
    × its straight value somewhere (stages.sim.quadrature.jacobian_ratio) gets its mid-edge nodes back
    on the straight edges."""
    project = None if surface is None else (lambda p: closest_points_on_surface(p, *surface))
    v2, t2 = quadratic_tets(vertices, tets, project)
    if surface is None:
        return v2, t2, 0
    straight, _ = quadratic_tets(vertices, tets)
    reverted = np.zeros(len(v2), bool)
    for _ in range(4):
        bad = jacobian_ratio(v2, t2) < min_jacobian
        if not bad.any():
            break
        nodes = np.unique(t2[bad, 4:])
        reverted[nodes[np.any(v2[nodes] != straight[nodes], axis=1)]] = True
        v2[nodes] = straight[nodes]
    return v2, t2, int(reverted.sum())
