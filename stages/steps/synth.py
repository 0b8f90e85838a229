"""`rsl synth`: a complete synthetic capture with ground truth (DESIGN §2).

A tet mesh (given, or fTetWild from a closed surface) is scaled and centred, driven by a
scenario's controls (stretch / twist by two handles, push with a moving sphere, drop on a
floor, pull a cable = a load on a few tip vertices), simulated in full space with a constant,
step-wise or ramped E(t) (optionally a second region with its own E), and filmed by a ring of
cameras with a textured-mesh rasterizer over background plates.  Written, all at once (a
temporary folder renamed into place):

    capture.toml  controls.json  object.obj  regions/NAME.obj  cameras.json
    background/CAM.png  frames/CAM/000000.png  calib/CAM/viewNN.png  markers.csv
    truth/material.csv  truth/surface.npz  truth/masks/CAM/000000.png  truth/forces.csv
    truth/object.mesh (linear truth) or truth/object.vtu (quadratic truth)

Frame 0 is the declared start state ([capture] start, docs/capture.md): the static equilibrium under the
frame-0 controls or the rest shape, at rest, or (``--start moving``) the object mid-motion, ``--lead-frames``
simulated frames after one of those; later frames are ``--substeps`` implicit steps each.  The truth
may use another discretisation than rsl adapt will (``--truth-order 2``, ``--truth-refine K``, substeps, hard
handles): object.obj is always the rest surface of the given mesh, the truth mesh stays in truth/.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import shutil
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from stages.artefacts import Camera, MeshArtefact
from stages.artefacts import mesh_artefact as make_artefact
from stages.capture import (IDENTITY_POSE, SURFACE_SUFFIXES, TET_SUFFIXES, Controls, Handle, Load, Obstacle,
                            Selection, Track, matrix_to_quat, parse_controls, select_handles,
                            write_cameras_json, write_markers, write_truth, write_truth_forces)
from stages.domain.rotations import axis_angle_matrix as _axis_angle
from stages.errors import RslError
from stages.meshing import boundary_faces, orient_tets, read_surface, read_tet_mesh, tetwild
from stages.occluders import clamp_visual, draw_occluders, ignore_mask
from stages.progress import Reporter, SilentReporter
from stages.sim.mesh import rest_quantities
from stages.sim.meshgen import refine_tets

Scenario = Literal["stretch", "twist", "push", "drop", "cable", "sag"]
SCENARIOS = ("stretch", "twist", "push", "drop", "cable", "sag")


@dataclass(frozen=True)
class SynthConfig:
    mesh: Path
    """Object mesh: a closed surface (obj/ply/stl/off, tetrahedralized with fTetWild) or a tet mesh (.mesh/.msh)."""
    out: Path
    """Capture folder to create."""
    scenario: Scenario = "stretch"
    """What drives the object: stretch or twist (two end handles), push (a moving sphere, both ends held), drop
    (onto a floor), cable (one end held, a load pulls the tip), sag (one end held, nothing moves: a cantilever
    hanging at rest under gravity, a static capture for rsl adapt --mode static)."""
    amplitude: float = 1.0
    """Scale of the scenario's motion: stretch distance, twist angle, push depth, drop height, cable force."""
    cameras: int = 4
    """Number of cameras on a ring around the object."""
    frames: int = 60
    """Number of frames to simulate and render."""
    resolution: int = 256
    """Image width and height in pixels."""
    fps: float = 30.0
    """Frames per second (the time step is 1/fps)."""
    young: float = 1.0e5
    """Young's modulus of the body, Pa (constant over time unless --young-schedule is given)."""
    young_schedule: str = ""
    """E(t) as 'E@FRAME,...', e.g. '1e4@0,2e4@20,4e4@40': step-wise, or linear between entries with --ramp."""
    ramp: bool = False
    """Interpolate --young-schedule linearly between its entries instead of holding each value."""
    poisson: float = 0.45
    """Poisson's ratio of every region."""
    region: str = ""
    """A second material region 'NAME=E' or 'NAME=E@AXIS>F', e.g. 'stiff=3e5@x>0.5': tets whose centroid lies
    beyond fraction F of the bounding box along AXIS (x, y or z; default the long axis and 0.5) get the constant
    Young's modulus E."""
    markers: int = 40
    """Number of surface markers followed through the simulation (markers.csv); 0 = none."""
    marker_noise: float = 0.0
    """Standard deviation (m) of Gaussian noise added to the marker positions in markers.csv (each frame, each
    axis, independently; seeded), e.g. 0.002 for motion-capture markers wobbling on soft skin."""
    marker_visibility: int = 0
    """Occlusion of the markers: at each frame a marker is written to markers.csv only when at least this many
    of the cameras see it (inside the image, not hidden by the object itself: its depth within 1.5 pixel
    footprints of the rendered depth at its pixel); the others are gaps.  A marker seen at no frame is left out
    (one first seen after frame 0 stays: rsl adapt binds it to its track).  0 = off: every marker at every frame."""
    seed: int = 0
    """Seed of every random choice (markers, texture, board poses, backgrounds, noise)."""
    size: float = 0.2
    """Scale the mesh so its longest bounding-box side is this many metres (0 = keep its units)."""
    density: float = 1070.0
    """Density, kg/m^3."""
    model: Literal["stable_neohookean", "yeoh", "linear"] = "stable_neohookean"
    """Material model of the simulation."""
    edge_length: float = 0.06
    """fTetWild edge length as a fraction of the bounding-box diagonal (surface input only)."""
    max_tets: int = 0
    """Re-tetrahedralize (coarser) until at most this many tets; 0 = no bound."""
    elevation: float = 45.0
    """Camera ring elevation above the horizontal, degrees."""
    calib_views: int = 6
    """Number of chessboard calibration views (calib/CAM/viewNN.png); 0 = none."""
    board: str = "auto"
    """Calibration board 'chessboard:COLSxROWS:SQUARE_M' (inner corners; square 0 = scaled to the scene), or 'auto'
    (9x6 from 200 px, else 6x4, scaled)."""
    noise: float = 0.0
    """Standard deviation of Gaussian pixel noise added to the frames (0–1 intensity units)."""
    supersample: int = 2
    """Supersampling factor of the rasterizer (anti-aliasing); masks are coverage ≥ ½."""
    newton_iterations: int = 300
    """Most Newton iterations per time step before the simulation gives up."""
    start: Literal["auto", "equilibrium", "rest", "moving"] = "auto"
    """What frame 0 shows (written as [capture] start): equilibrium — the object at rest in its static
    equilibrium under gravity and the frame-0 controls; rest — the rest shape, released at t = 0; auto —
    equilibrium, or rest when nothing holds the object (drop); moving — the object mid-motion, its deformation
    and velocity unknown to rsl: the capture begins --lead-frames frames into the simulation."""
    lead_frames: int = 8
    """With --start moving, the number of frames simulated before the capture's frame 0, from the scenario's
    own start state (what auto resolves to: equilibrium when handles hold the object, rest otherwise); the
    capture shows simulated frames K..K+frames−1 (K = lead_frames) as its frames 0..frames−1, and the
    --young-schedule frames count from its frame 0 (the lead-in has frame 0's E)."""
    truth_order: int = 1
    """Element order of the truth simulation: 1 (linear tets) or 2 (quadratic, 10-node tets)."""
    truth_refine: int = 0
    """Split every truth tet into 8 this many times (a finer truth mesh than the object.obj surface suggests)."""
    substeps: int = 1
    """Implicit-Euler steps per frame in the truth simulation (time step 1/(fps·substeps)); frames record
    every substeps-th state."""
    damping: float = 0.0
    """β (s) of the truth material's viscous damping (Kelvin–Voigt on the Green strain, force ≈ −β K₀ v:
    stages.sim.materials.viscous_density); written to capture.toml [material] damping unless --undeclared-damping.
    0: none (the truth then damps only by implicit Euler's own numerical damping, which depends on --substeps)."""
    undeclared_damping: bool = False
    """Leave [material] damping out of capture.toml (the truth is damped, the capture does not say so: what a lab
    that has not measured its material's damping gives rsl)."""
    handles: Literal["spring", "hard"] = "spring"
    """Handles of the truth: stiff springs, or hard (Dirichlet: the held vertices follow the handle exactly).
    With hard, controls.json declares the handles "hard": true, as a lab describes a clamp."""
    clamp: bool = False
    """Give the first handle a visible clamp: a box around the vertices it holds, written as its ``visual`` in
    controls.json and drawn (dark grey, in front) into the frames; truth/masks show the object it does not hide."""
    plates: bool = True
    """Write background/CAM.png (the empty scene); --no-plates makes a capture without a background plate."""
    overwrite: bool = False
    """Replace CAPTURE_OUT when it exists (it must then be a capture made by rsl synth)."""


# =========================================================================== mesh
@dataclass
class SynthMesh:
    """The simulated tet mesh in world coordinates."""

    vertices: np.ndarray  # (n, 3) m
    tets: np.ndarray  # (m, 4)
    faces: np.ndarray  # (k, 3) outward surface triangles
    tet_region: np.ndarray  # (m,)
    region_names: list[str]
    region_box: np.ndarray | None  # (2, 3) box holding the second region's centroids

    @property
    def surface_ids(self) -> np.ndarray:
        return np.unique(self.faces)


def load_tets(path: Path, edge_length: float, max_tets: int, reporter: Reporter) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (n, 3), tets (m, 4)) from a tet mesh or a closed surface (fTetWild)."""
    path = Path(path)
    if not path.is_file():
        raise RslError(f"{path}: mesh file not found.")
    suf = path.suffix.lower()
    if suf in TET_SUFFIXES:
        v, t, _ = read_tet_mesh(path)
        if max_tets > 0 and len(t) > max_tets:
            raise RslError(f"{path}: has {len(t)} tets, more than --max-tets {max_tets}; give a coarser mesh "
                           f"or its surface.")
        return v, t
    if suf in SURFACE_SUFFIXES:
        sv, sf = read_surface(path, reporter)
        v, t, _ = tetwild(sv, sf, edge_length=edge_length, max_tets=max_tets, threads=1, reporter=reporter)
        return v, t
    raise RslError(f"{path}: unsupported mesh type '{path.suffix}'; use obj, ply, stl, off, mesh or msh.")


def prepare_mesh(vertices: np.ndarray, tets: np.ndarray, size: float, region: str,
                 tilt_deg: float = 0.0, source: str = "mesh") -> SynthMesh:
    """Scale (longest side = size), optionally tilt about x, centre at the origin, orient the tets
    positively, extract the surface and assign the optional second region."""
    v = np.asarray(vertices, np.float64).copy()
    ext = v.max(0) - v.min(0)
    if size > 0:
        v *= size / ext.max()
    if tilt_deg:
        a = np.radians(tilt_deg)
        v = v @ _axis_angle([1.0, 0.0, 0.0], a).T
    v -= 0.5 * (v.max(0) + v.min(0))
    t, _ = orient_tets(v, tets)
    try:
        faces = boundary_faces(t)
    except ValueError as e:
        raise RslError(f"{source}: {e}.") from None
    region_ids = np.zeros(len(t), np.int64)
    names = ["body"]
    box = None
    if region:
        name, _, axis, frac = parse_region(region, v)
        lo, hi = v.min(0), v.max(0)
        cut = lo[axis] + frac * (hi[axis] - lo[axis])
        centroids = v[t].mean(axis=1)
        inside = centroids[:, axis] > cut
        if not inside.any() or inside.all():
            raise RslError(f"--region {region!r}: the cut at {frac} along {'xyz'[axis]} leaves one side empty.")
        region_ids[inside] = 1
        names.append(name)
        pad = 0.05 * (hi - lo).max()
        box = np.stack([lo - pad, hi + pad])
        box[0, axis] = cut
    return SynthMesh(v, t, faces, region_ids, names, box)


_REGION_RE = re.compile(r"^\s*([A-Za-z_][\w-]*)\s*=\s*([0-9.eE+-]+)\s*(?:@\s*([xyzXYZ])\s*>\s*([0-9.eE+-]+))?\s*$")


def parse_region(spec: str, vertices: np.ndarray | None = None) -> tuple[str, float, int, float]:
    """'NAME=E[@AXIS>F]' -> (name, E Pa, axis index, fraction); the default axis is the long one."""
    m = _REGION_RE.match(spec)
    if not m:
        raise RslError(f"--region {spec!r} should read 'NAME=E' or 'NAME=E@AXIS>F', e.g. 'stiff=3e5@x>0.5'.")
    name, e = m.group(1), float(m.group(2))
    if name == "body":
        raise RslError("--region: 'body' is the name of the main region; choose another name.")
    if not e > 0:
        raise RslError(f"--region {spec!r}: Young's modulus should be positive.")
    if m.group(3):
        axis = "xyz".index(m.group(3).lower())
    else:
        axis = int(np.argmax(np.ptp(vertices, axis=0))) if vertices is not None else 0
    frac = float(m.group(4)) if m.group(4) else 0.5
    if not 0 < frac < 1:
        raise RslError(f"--region {spec!r}: the fraction F should lie strictly between 0 and 1.")
    return name, e, axis, frac


def mesh_artefact(mesh: SynthMesh, density: float, controls: Controls) -> MeshArtefact:
    """The in-memory MeshArtefact the simulation runs on (what `rsl tetrahedralize` would write)."""
    vol, dm_inv, masses = rest_quantities(mesh.vertices, mesh.tets, density)
    return MeshArtefact(vertices=mesh.vertices, tets=mesh.tets, surface_faces=mesh.faces,
                        tet_region=mesh.tet_region, region_names=list(mesh.region_names), rest_volumes=vol,
                        dm_inv=dm_inv, vertex_masses=masses, density=float(density),
                        handles=select_handles(controls, mesh.vertices), quality={})


# =========================================================================== material
def young_schedule(spec: str, young: float, frames: int, ramp: bool) -> np.ndarray:
    """E(t) (frames,) Pa from 'E@FRAME,...': held from each entry's frame on, or linear between entries
    (ramp); before the first entry its value holds."""
    if not spec.strip():
        if ramp:
            raise RslError("--ramp needs a --young-schedule to ramp between, e.g. '1e4@0,4e4@40'.")
        return np.full(frames, float(young))
    pts = []
    for item in spec.split(","):
        m = re.match(r"^\s*([0-9.eE+-]+)\s*@\s*(\d+)\s*$", item)
        if not m:
            raise RslError(f"--young-schedule entry {item!r} should read 'E@FRAME', e.g. '2e4@20'.")
        e, f = float(m.group(1)), int(m.group(2))
        if not (math.isfinite(e) and e > 0):
            raise RslError(f"--young-schedule entry {item!r}: Young's modulus should be positive.")
        pts.append((f, e))
    fr = [p[0] for p in pts]
    if any(b <= a for a, b in zip(fr, fr[1:])):
        raise RslError(f"--young-schedule {spec!r}: frames should increase strictly.")
    f = np.array(fr, np.float64)
    e = np.array([p[1] for p in pts])
    t = np.arange(frames, dtype=np.float64)
    if ramp:
        return np.interp(t, f, e)
    idx = np.clip(np.searchsorted(f, t, side="right") - 1, 0, len(e) - 1)
    return e[idx]


# =========================================================================== scenarios
def _smooth(frames: int) -> np.ndarray:
    """Up-and-back profile s(t) = sin²(π t / (T−1)) ∈ [0, 1], (T,)."""
    t = np.arange(frames) / max(frames - 1, 1)
    return np.sin(np.pi * t) ** 2


def _rot_about(axis: np.ndarray, angle: float, center: np.ndarray) -> np.ndarray:
    """Pose [t, q] of a rotation by ``angle`` about the line through ``center`` along ``axis``: t = c − R c."""
    R = _axis_angle(axis, angle)
    return np.concatenate([center - R @ center, matrix_to_quat(R)])


def scenario_controls(scenario: str, vertices: np.ndarray, faces: np.ndarray, frames: int, mass_kg: float,
                      gravity: np.ndarray, young_max: float, amp: float = 1.0, hard: bool = False
                      ) -> tuple[Controls, dict]:
    """Controls of a scenario for a mesh centred at the origin: (controls, notes).

    The long axis a is the bounding box's longest side; 'up' is −g. End handles hold the
    vertices within 8 % of the length from each end, with a total stiffness 200 E A / L. Motions
    follow s(t) = sin²(π t/(T−1)) (out and back), scaled by ``amp``: stretch 0.25·L; twist 120° about
    a with a 0.1·L push-in; push: a sphere of radius L/4 comes down to 0.15·L below the centre;
    drop: from 0.1·L above a floor (friction 0.3); cable: a load of 0.8 × the weight on 6 tip vertices;
    sag: the end face (the vertices within 1 % of L of it) held still, nothing else (gravity alone; ``amp``
    unused): a wall-mounted cantilever that every mesh of the surface clamps alike.
    """
    lo, hi = vertices.min(0), vertices.max(0)
    ext = hi - lo
    ai = int(np.argmax(ext))
    a = np.eye(3)[ai]
    L = float(ext[ai])
    g = np.asarray(gravity, np.float64)
    up = -g / np.linalg.norm(g) if np.linalg.norm(g) > 0 else np.array([0, 0, 1.0])
    side = np.cross(up, a)
    if np.linalg.norm(side) < 1e-6:  # long axis vertical
        side = np.eye(3)[(ai + 1) % 3]
    side /= np.linalg.norm(side)
    down = -(up - (up @ a) * a)
    down = down / np.linalg.norm(down) if np.linalg.norm(down) > 1e-6 else -side
    area = float(np.prod(np.delete(ext, ai)))
    s = _smooth(frames)
    pad = 0.05 * L

    def end_box(which: int, depth: float = 0.08) -> Selection:
        b0, b1 = lo - pad, hi + pad
        if which == 0:
            b1 = b1.copy()
            b1[ai] = lo[ai] + depth * L
        else:
            b0 = b0.copy()
            b0[ai] = hi[ai] - depth * L
        return Selection("box", box=np.stack([b0, b1]))

    def handle(name: str, which: int, poses: np.ndarray, depth: float = 0.08) -> Handle:
        sel = end_box(which, depth)
        n_sel = max(1, len(sel.select(vertices)))
        k = 200.0 * young_max * area / L / n_sel
        h = Handle(name, sel, float(f"{k:.4g}"), Track(np.arange(len(poses)), poses, True))
        h.hard = bool(hard)
        return h

    still = np.tile(IDENTITY_POSE, (frames, 1))
    ctl = Controls()
    notes: dict = {"long_axis": "xyz"[ai], "length_m": L}
    if scenario == "stretch":
        moved = still.copy()
        moved[:, :3] = (0.25 * amp * L * s)[:, None] * a
        ctl.handles = [handle("left", 0, still), handle("right", 1, moved)]
        notes["max_stretch_m"] = 0.25 * amp * L
    elif scenario == "twist":
        c_right = np.array(vertices[end_box(1).select(vertices)].mean(0))
        poses = np.stack([_rot_about(a, np.radians(120.0 * amp) * si, c_right) for si in s])
        poses[:, :3] += (-0.1 * amp * L * s)[:, None] * a
        ctl.handles = [handle("left", 0, still), handle("right", 1, poses)]
        notes["max_twist_deg"] = 120.0 * amp
    elif scenario == "push":
        thick = float(np.max((vertices - vertices.mean(0)) @ (-down)))  # top surface above the centre
        r = 0.25 * L
        start = -down * (thick + r + 0.05 * L)
        depth = thick + 0.15 * amp * L + 0.05 * L
        track = still.copy()
        track[:, :3] = start + (depth * s)[:, None] * down
        ctl.handles = [handle("left", 0, still), handle("right", 1, still)]
        ctl.obstacles = [Obstacle("pusher", "sphere", radius=float(r), poses=Track(np.arange(frames), track, True))]
        notes["pusher_radius_m"] = r
        notes["push_depth_below_top_m"] = thick + 0.15 * amp * L  # lowest point of the sphere under the rest top
    elif scenario == "drop":
        height = float(np.min(vertices @ up))
        ctl.obstacles = [Obstacle("floor", "plane", normal=up.copy(), offset=height - 0.1 * amp * L)]
        ctl.friction = 0.3
        notes["drop_height_m"] = 0.1 * amp * L
    elif scenario == "cable":
        tip = hi[ai]
        surf = np.unique(faces)
        d = np.abs(vertices[surf, ai] - tip) + 0.2 * np.abs((vertices[surf] - vertices.mean(0)) @ side)
        ids = np.sort(surf[np.argsort(d)[:6]])
        weight = mass_kg * max(np.linalg.norm(g), 9.81)
        direction = 0.9 * up + 0.35 * side
        force = (0.8 * amp * weight * s)[:, None] * direction
        ctl.handles = [handle("base", 0, still)]
        ctl.loads = [Load("cable", Selection("ids", ids=ids), Track(np.arange(frames), force, False))]
        notes["max_cable_force_n"] = float(np.linalg.norm(force, axis=1).max())
    elif scenario == "sag":  # the end face alone (1 % of L deep): any mesh of the surface holds the same nodes
        ctl.handles = [handle("base", 0, still, depth=0.01)]
    else:
        raise RslError(f"unknown scenario {scenario!r}; use one of {', '.join(SCENARIOS)}.")
    return ctl, notes


# =========================================================================== rendering helpers
def parse_board(spec: str, resolution: int) -> tuple[int, int, float]:
    """(cols, rows, square_m or 0 = auto) of 'chessboard:COLSxROWS:SQUARE' or 'auto'."""
    if spec == "auto":
        return (9, 6, 0.0) if resolution >= 200 else (6, 4, 0.0)
    m = re.match(r"^chessboard:(\d+)x(\d+)(?::([0-9.eE+-]+))?$", spec.strip())
    if not m:
        raise RslError(f"--board {spec!r} should read 'chessboard:COLSxROWS:SQUARE_M' (e.g. chessboard:9x6:0.025) "
                       f"or 'auto'.")
    cols, rows = int(m.group(1)), int(m.group(2))
    if cols < 3 or rows < 3:
        raise RslError(f"--board {spec!r}: a chessboard needs at least 3x3 inner corners.")
    return cols, rows, float(m.group(3) or 0.0)


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.round(np.asarray(img) * 255.0), 0, 255).astype(np.uint8)


def _write_png(path: Path, img: np.ndarray) -> None:
    """RGB (H, W, 3) or gray (H, W) uint8 as a maximally compressed PNG (captures are shipped)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = cv2.cvtColor(img, cv2.COLOR_RGB2BGR) if img.ndim == 3 else img
    if not cv2.imwrite(str(path), arr, [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        raise RslError(f"{path}: cannot write image.")


def _write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        f.write("# written by rsl synth\n")
        for p in vertices:
            f.write(f"v {p[0]:.17g} {p[1]:.17g} {p[2]:.17g}\n")
        for t in faces:
            f.write(f"f {t[0] + 1} {t[1] + 1} {t[2] + 1}\n")


def _box_mesh(box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A closed, outward-oriented box surface (8 vertices, 12 triangles) spanning corners box (2, 3)."""
    lo, hi = box
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def sample_surface_points(vertices: np.ndarray, faces: np.ndarray, count: int, rng: np.random.Generator
                          ) -> tuple[np.ndarray, np.ndarray]:
    """``count`` area-uniform points on the surface: (face index (M,), barycentric weights (M, 3))."""
    p = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    fi = rng.choice(len(faces), size=count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return fi, bary


def _toml_value(v) -> str:
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    return str(v)


def capture_toml(sections: dict[str, dict]) -> str:
    """A TOML document from {section: {key: value}} (flat tables; dotted section names allowed)."""
    lines = []
    for sec, tab in sections.items():
        lines.append(f"[{sec}]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in tab.items()]
        lines.append("")
    return "\n".join(lines)


# =========================================================================== the truth
SYNTH_STARTS = ("auto", "equilibrium", "rest", "moving")  # --start (SynthConfig.start)


def resolve_start(start: str, controls: Controls) -> str:
    """The declared start state: "auto" is equilibrium, or rest when nothing holds the object (no handle);
    "moving" stays moving (its lead-in starts from what "auto" resolves to)."""
    if start == "auto":
        return "equilibrium" if controls.handles else "rest"
    if start not in SYNTH_STARTS[1:]:
        raise RslError(f"--start {start!r} is unknown; use equilibrium, rest, moving or auto.")
    if start == "equilibrium" and not controls.handles:
        raise RslError("--start equilibrium needs an object held by handles; nothing holds it in this scenario "
                       "(it would fall): use --start rest.")
    return start


def truth_mesh(mesh: SynthMesh, density: float, refine: int, order: int) -> tuple[SynthMesh, MeshArtefact]:
    """The truth discretisation of the shipped rest shape: ``refine`` × 8-fold splits (Bey), then P2 nodes
    when order = 2 (straight mid-edge nodes: the same geometry).  (SynthMesh, MeshArtefact)."""
    v, t, reg = mesh.vertices, mesh.tets, mesh.tet_region
    for _ in range(refine):
        v, t, reg = refine_tets(v, t, reg)
    art = make_artefact(v, t, density, reg, tuple(mesh.region_names), order=order)
    tm = SynthMesh(np.asarray(art.vertices), np.asarray(art.tets), np.asarray(art.surface_faces),
                   np.asarray(art.tet_region), list(mesh.region_names), mesh.region_box)
    return tm, art


def truth_forces(scene, ctl: Controls, X: np.ndarray, states: list, young: np.ndarray, poisson: np.ndarray,
                 substeps: int, fps: float, contact_distance: float = 1.0e-3) -> list[list]:
    """Rows of truth/forces.csv (stages.capture.FORCE_HEADER): per frame, per handle and obstacle, the sum of
    the internal nodal forces over its vertices, their magnitude sum, the force it exerts on the object
    (spring pull, hard-handle reaction = −residual of Φ without the handle at its vertices, or −∂E_c/∂x)
    and its vertex count — what ``rsl export --forces`` computes, on the truth simulation (the same numbers as
    stages.forces.step_forces / replay_forces: the last substep's residual; tests/test_forces_truth.py).
    ``states``: per frame (x_{t−1}, x_{t−2}) of the last substep (stages.sim.static.simulate_from_start)."""
    from stages.sim.scene import frame_inputs, handle_reactions, internal_forces  # jax + numba: loaded on use
    from stages.sim.stress import set_forces

    fine = scene if substeps == 1 else dataclasses.replace(scene, dt=scene.dt / substeps)
    rows = []
    for t in range(len(X)):
        x, (xp, xpp) = X[t], states[t]
        inputs = frame_inputs(fine, ctl, t)
        f_int = internal_forces(x, fine, young[t], poisson[t], x_prev=xp)  # (viscous with damping)
        sets = set_forces(fine, inputs, x, xp, f_int, contact_distance, x_prev2=xpp)
        react = handle_reactions(fine, inputs, x, xp, xpp, young[t], poisson[t])
        for i, f in enumerate(sets):
            applied = react[i] if f.kind == "handle" else f.applied  # scene.handle_reactions: spring or hard
            rows.append([t, t / fps, f.name, f.kind, *map(float, f.internal), float(f.magnitude_sum),
                         *map(float, applied), int(f.n_vertices)])
    return rows


def write_truth_mesh(folder: Path, mesh: SynthMesh) -> Path:
    """truth/object.mesh (Medit, linear tets, region as medit:ref) or truth/object.vtu (quadratic tets,
    VTK_QUADRATIC_TETRA node order, region as cell data "region")."""
    import meshio

    folder.mkdir(parents=True, exist_ok=True)
    if mesh.tets.shape[1] == 10:
        path = folder / "object.vtu"
        meshio.write(str(path), meshio.Mesh(mesh.vertices, [("tetra10", mesh.tets)],
                                            cell_data={"region": [mesh.tet_region]}))
    else:
        path = folder / "object.mesh"
        meshio.write(str(path), meshio.Mesh(mesh.vertices, [("tetra", mesh.tets)],
                                            cell_data={"medit:ref": [mesh.tet_region]}), file_format="medit")
    return path


# =========================================================================== the stage
def _check_config(c: SynthConfig) -> None:
    if c.scenario not in SCENARIOS:
        raise RslError(f"--scenario {c.scenario!r} is unknown; use one of {', '.join(SCENARIOS)}.")
    if c.model not in ("stable_neohookean", "yeoh", "linear"):
        raise RslError(f"--model {c.model!r} is unknown; use stable_neohookean, yeoh or linear.")
    if c.truth_order not in (1, 2):
        raise RslError(f"--truth-order should be 1 or 2, found {c.truth_order}.")
    if c.handles not in ("spring", "hard"):
        raise RslError(f"--handles {c.handles!r} is unknown; use spring or hard.")
    if c.start not in SYNTH_STARTS:
        raise RslError(f"--start {c.start!r} is unknown; use equilibrium, rest, moving or auto.")
    if c.start == "moving" and c.lead_frames < 1:
        raise RslError(f"--lead-frames should be at least 1 with --start moving (the frames simulated before "
                       f"the capture's frame 0), found {c.lead_frames}.")
    if not 0 <= c.truth_refine <= 3:
        raise RslError(f"--truth-refine should lie in 0..3 (each level multiplies the tets by 8), found "
                       f"{c.truth_refine}.")
    for name, val, lo in (("--cameras", c.cameras, 1), ("--frames", c.frames, 1), ("--resolution", c.resolution, 16),
                          ("--supersample", c.supersample, 1), ("--substeps", c.substeps, 1)):
        if val < lo:
            raise RslError(f"{name} should be at least {lo}, found {val}.")
    if not 0 <= c.poisson < 0.5:
        raise RslError(f"--poisson should lie in [0, 0.5), found {c.poisson}.")
    if not c.young > 0 or not c.fps > 0 or not c.density > 0:
        raise RslError("--young, --fps and --density should be positive.")
    if not c.amplitude > 0:
        raise RslError(f"--amplitude should be positive, found {c.amplitude}.")
    if not (c.damping >= 0 and np.isfinite(c.damping)):
        raise RslError(f"--damping should be a finite number of seconds ≥ 0, found {c.damping}.")
    if c.markers < 0 or c.calib_views < 0 or c.noise < 0 or c.marker_noise < 0 or c.marker_visibility < 0:
        raise RslError("--markers, --calib-views, --noise, --marker-noise and --marker-visibility should not be "
                       "negative.")
    if c.marker_visibility > c.cameras:
        raise RslError(f"--marker-visibility {c.marker_visibility} asks for more cameras than --cameras "
                       f"{c.cameras}.")


def _check_out(out: Path, overwrite: bool) -> None:
    """Refuse to replace a folder that is not empty (unless --overwrite and made by rsl synth)."""
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        if not overwrite:
            raise RslError(f"{out}: already exists and is not empty; choose a new folder or pass --overwrite.")
        if not (out / "capture.toml").is_file() or "[synth]" not in (out / "capture.toml").read_text():
            raise RslError(f"{out}: --overwrite only replaces a capture made by rsl synth, and this is not one.")


def _prepare_out(out: Path, overwrite: bool) -> Path:
    """A temporary folder beside ``out`` to write the capture into."""
    out = Path(out)
    _check_out(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))


def run(config: SynthConfig, reporter: Reporter = SilentReporter()) -> Path:
    """Simulate and film a scenario; write the capture folder ``config.out`` and return its path."""
    from stages.sim.scene import SimulationError, frame_inputs, make_scene  # jax + numba: loaded on use
    from stages.sim.static import simulate_from_start
    from stages.synth_views import background_plate, board_poses, camera_ring

    c = config
    _check_config(c)
    lead = c.lead_frames if c.start == "moving" else 0  # simulated frames before the capture's frame 0
    n_sim = lead + c.frames
    cols, rows, square = parse_board(c.board, c.resolution)
    schedule = young_schedule(c.young_schedule, c.young, c.frames, c.ramp)  # per capture frame
    schedule = np.concatenate([np.full(lead, schedule[0]), schedule])  # per simulated frame
    region_e = parse_region(c.region)[1] if c.region else None
    gravity = np.array([0.0, 0.0, -9.81])
    rng = np.random.default_rng(c.seed)
    _check_out(Path(c.out), c.overwrite)

    # ---------------------------------------------------------------- mesh and controls
    v, t = load_tets(Path(c.mesh), c.edge_length, c.max_tets, reporter)
    mesh = prepare_mesh(v, t, c.size, c.region, tilt_deg=20.0 if c.scenario == "drop" else 0.0,
                        source=str(c.mesh))
    R = len(mesh.region_names)
    young = np.tile(schedule[:, None], (1, R))
    if region_e is not None:
        young[:, 1] = region_e
    poisson = np.full((n_sim, R), c.poisson)
    _, _, masses = rest_quantities(mesh.vertices, mesh.tets, c.density)
    ctl, notes = scenario_controls(c.scenario, mesh.vertices, mesh.faces, n_sim, float(masses.sum()),
                                   gravity, float(young.max()), c.amplitude, hard=c.handles == "hard")
    if c.clamp:  # a visible clamp over the first handle's vertices (stages/occluders.py)
        if not ctl.handles:
            raise RslError(f"--clamp needs a handle to draw; the {c.scenario} scenario has none.")
        ctl.handles[0].visual = clamp_visual(mesh.vertices[ctl.handles[0].select.select(mesh.vertices)])
    # the simulation runs on the controls as JSON gives them back; controls.json holds them ``lead`` frames on
    # (its frame f is simulated frame f + lead, the same floats)
    sim_ctl = parse_controls(json.loads(json.dumps(ctl.to_json())), Path("controls.json"))
    controls_json = ctl.shifted(lead).to_json()
    ctl = parse_controls(json.loads(json.dumps(controls_json)), Path("controls.json"))  # exactly what is written
    art = mesh_artefact(mesh, c.density, ctl)

    start = resolve_start(c.start, ctl)
    sim_start = resolve_start("auto", ctl) if start == "moving" else start
    start_desc = f"moving (after {lead} lead-in frames from {sim_start})" if lead else start
    tmesh, tart = truth_mesh(mesh, c.density, c.truth_refine, c.truth_order)

    # ---------------------------------------------------------------- simulate
    scene = make_scene(tart, sim_ctl, c.model, 1.0 / c.fps, gravity, damping=c.damping)
    states: list = []
    with reporter.task(f"simulating {c.scenario} (truth: P{c.truth_order}, {len(tart.tets)} tets, "
                       f"{c.substeps} substep{'s' * (c.substeps > 1)}, {c.handles} handles, start {start_desc})",
                       n_sim) as task:
        try:
            X = simulate_from_start(scene, lambda f: frame_inputs(scene, sim_ctl, f), young, poisson, n_sim,
                                    sim_start, c.substeps, callback=lambda _t: task.advance(1), states=states,
                                    max_iterations=c.newton_iterations)
        except SimulationError as e:
            raise RslError(f"{c.mesh}: the truth simulation failed: {e}") from None
    if not np.all(np.isfinite(X)):
        raise RslError("the simulation produced non-finite positions.")
    forces = [[t - lead, (t - lead) / c.fps, *rest]  # simulated frame t is the capture's frame t − lead
              for t, _, *rest in truth_forces(scene, sim_ctl, X, states, young, poisson, c.substeps, c.fps)
              if t >= lead]
    X, young, poisson = X[lead:], young[lead:], poisson[lead:]  # the capture's frames

    # ---------------------------------------------------------------- views
    lo = np.minimum(X.min(axis=(0, 1)), mesh.vertices.min(0))
    hi = np.maximum(X.max(axis=(0, 1)), mesh.vertices.max(0))
    target = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo)) * 1.05
    step = max(1, X.shape[0] * X.shape[1] // 20000)
    cams = camera_ring(c.cameras, target, radius, c.resolution, -gravity, elevation_deg=c.elevation,
                       points=X.reshape(-1, 3)[::step])
    backgrounds = {cam.name: background_plate(c.resolution, c.resolution, c.seed * 1000 + i)
                   for i, cam in enumerate(cams)}
    poses: list = []
    if c.calib_views:
        auto = square <= 0
        base = 0.75 * 2 * radius / (cols + 3)
        for shrink in ((1.0, 0.9, 0.8, 0.7, 0.6, 0.5) if auto else (1.0,)):
            if auto:
                square = round(base * shrink, 4)
            poses = board_poses(cams, target, -gravity, cols, rows, square, c.calib_views, seed=c.seed,
                                shift_m=0.1 * radius, margin_px=2.0)
            if len(poses) == c.calib_views:
                break
        if len(poses) < c.calib_views:
            raise RslError(f"--board {cols}x{rows} with {square * 1000:.1f} mm squares: found only {len(poses)} of "
                           f"{c.calib_views} poses that every camera sees whole; use a smaller board or fewer "
                           f"cameras.")
    elif square <= 0:
        square = round(0.75 * 2 * radius / (cols + 3), 4)

    tmp = _prepare_out(Path(c.out), c.overwrite)
    try:
        notes.update(start=start, truth_vertices=int(len(tart.vertices)), truth_tets=int(len(tart.tets)),
                     lead_frames=lead)
        if lead:
            notes["lead_start"] = sim_start
        _write_capture(tmp, c, mesh, tmesh, ctl, controls_json, X, young, poisson, cams, backgrounds,
                       (cols, rows, square), poses, notes, rng, reporter, start, forces)
        out = Path(c.out)
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    disp = float(np.linalg.norm(X - tmesh.vertices[None], axis=2).max())
    e_desc = (f"E {young[0, 0]:.3g} Pa" if np.all(young[:, 0] == young[0, 0])
              else f"E {young[:, 0].min():.3g}–{young[:, 0].max():.3g} Pa")
    reg = f", region {mesh.region_names[1]} E {region_e:.3g} Pa" if region_e is not None else ""
    truth_desc = ("" if (c.truth_order, c.truth_refine, c.substeps, c.handles) == (1, 0, 1, "spring") else
                  f" (truth: P{c.truth_order}, {len(tart.vertices)} vertices / {len(tart.tets)} tets, "
                  f"{c.substeps} substeps, {c.handles} handles)")
    reporter.summary(f"{out}: {c.scenario}, {c.frames} frames × {c.cameras} cameras at {c.resolution}², "
                     f"{len(art.vertices)} vertices / {len(art.tets)} tets{truth_desc}, start {start_desc}, "
                     f"{e_desc}{reg}, ν {c.poisson}, "
                     f"max displacement {disp * 1000:.1f} mm, {len(poses)} board views "
                     f"(chessboard:{cols}x{rows}:{square:g})")
    return out


def occlude_markers(pts: np.ndarray, seen_by: np.ndarray, need: int) -> np.ndarray:
    """Marker positions (T, M, 3) with NaN (a gap) where fewer than ``need`` cameras see the marker
    (``seen_by`` (T, M) counts).  A marker first seen after frame 0 keeps its frames (rsl adapt binds it to its
    track); one seen at no frame is all gaps, which markers.csv leaves out."""
    if not np.any(seen_by[0] >= need):
        raise RslError(f"--marker-visibility {need}: no marker is seen by {need} cameras at frame 0; lower "
                       f"--marker-visibility or add cameras.")
    out = np.array(pts, float)
    out[seen_by < need] = np.nan
    return out


def _write_capture(root: Path, c: SynthConfig, mesh: SynthMesh, tmesh: SynthMesh, ctl: Controls,
                   controls_json: dict, X: np.ndarray, young: np.ndarray, poisson: np.ndarray,
                   cams: list[Camera], backgrounds: dict, board: tuple[int, int, float], poses: list,
                   notes: dict, rng: np.random.Generator, reporter: Reporter, start: str,
                   forces: list[list]) -> None:
    """Write the capture into ``root``: ``mesh`` is the shipped rest shape (object.obj), ``tmesh`` the truth
    mesh that X (T, n_truth, 3) moves (private: truth/object.mesh or .vtu)."""
    from stages.render.mesh_raster import procedural_texture, render_mesh  # numba: loaded on use
    from stages.synth_views import first_corner_pose, render_board, visible_points

    cols, rows, square = board
    T = X.shape[0]
    surf = mesh.surface_ids
    remap = np.full(len(mesh.vertices), -1, np.int64)
    remap[surf] = np.arange(len(surf))
    _write_obj(root / "object.obj", mesh.vertices[surf], remap[mesh.faces])
    mesh = tmesh  # from here on: the truth
    surf = mesh.surface_ids
    remap = np.full(len(mesh.vertices), -1, np.int64)
    remap[surf] = np.arange(len(surf))
    faces_s = remap[mesh.faces]

    # ---------------------------------------------------------------- geometry, controls, truth
    if mesh.region_box is not None:
        bv, bf = _box_mesh(mesh.region_box)
        _write_obj(root / "regions" / f"{mesh.region_names[1]}.obj", bv, bf)
    (root / "controls.json").write_text(json.dumps(controls_json))
    write_cameras_json(root / "cameras.json", cams)
    write_truth(root / "truth", young, poisson, mesh.region_names, faces_s, X[:, surf])
    write_truth_forces(root / "truth", forces)
    write_truth_mesh(root / "truth", mesh)
    pts = seen_by = None
    if c.markers:
        fi, bary = sample_surface_points(mesh.vertices, mesh.faces, c.markers, rng)
        tri = mesh.faces[fi]  # (M, 3)
        pts = np.einsum("mk,tmkd->tmd", bary, X[:, tri])
        true_pts = pts
        if c.marker_noise > 0:  # own stream: the other random choices stay those of the noise-free capture
            pts = pts + np.random.default_rng([c.seed, 11]).normal(0.0, c.marker_noise, pts.shape)
        if c.marker_visibility:  # written after the frames: visibility comes from their depth buffers
            seen_by = np.zeros(pts.shape[:2], np.int64)
        else:
            write_markers(root / "markers.csv", pts)

    young_all = young.ravel()
    toml = {
        "capture": {"name": Path(c.out).name, "fps": float(c.fps), "gravity": [0.0, 0.0, -9.81],
                    "cameras": [cam.name for cam in cams], "start": start},
        "object": {"mesh": "object.obj", "density": float(c.density)},
        "material": {"model": c.model, "young": float(young[0, 0]), "poisson": float(poisson[0, 0]),
                     "young_range": [float(f"{young_all.min() / 5:.3g}"), float(f"{young_all.max() * 5:.3g}")],
                     "poisson_range": [min(0.3, float(poisson.min())), max(0.49, float(poisson.max()))]},
    }
    if c.damping > 0 and not c.undeclared_damping:
        toml["material"]["damping"] = float(c.damping)
    for r, name in enumerate(mesh.region_names[1:], start=1):
        toml[f"regions.{name}"] = {"young": float(young[0, r]), "poisson": float(poisson[0, r])}
    toml["calibration"] = {"board": f"chessboard:{cols}x{rows}:{square:g}"}
    synth = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(c).items() if k not in ("out",)}
    synth.update({k: v for k, v in notes.items()})
    synth["n_vertices"], synth["n_tets"] = int(notes["truth_vertices"]), int(notes["truth_tets"])
    toml["synth"] = synth
    (root / "capture.toml").write_text("# made by rsl synth; truth/ holds the ground truth\n" + capture_toml(toml))

    # ---------------------------------------------------------------- images
    texture = procedural_texture(cell_m=float(np.ptp(mesh.vertices, axis=0).max()) / 8, seed=c.seed)
    for cam in cams if c.plates else ():
        _write_png(root / "background" / f"{cam.name}.png", _to_u8(backgrounds[cam.name]))
    board_json = {}
    for k, pose in enumerate(poses):
        for cam in cams:
            img = render_board(cam, pose, cols, rows, square, backgrounds[cam.name])
            _write_png(root / "calib" / cam.name / f"view{k:02d}.png", _to_u8(img))
        board_json[f"view{k:02d}"] = [float(v) for v in first_corner_pose(pose, cols, rows, square)]
    if poses:
        (root / "calib" / "board_poses.json").write_text(json.dumps(
            {"board": f"chessboard:{cols}x{rows}:{square:g}", "origin": "first_corner", "poses": board_json},
            indent=1))
    noise_rng = np.random.default_rng([c.seed, 7])
    min_cov = {cam.name: 1.0 for cam in cams}
    with reporter.task("rendering frames", T) as task:
        for f in range(T):
            for cam in cams:
                rgb, cov, depth = render_mesh(X[f], mesh.faces, mesh.vertices, cam.K, cam.R, cam.t, cam.width,
                                              cam.height, texture, backgrounds[cam.name], cam.dist, c.supersample)
                if seen_by is not None:  # the true (noise-free) marker positions are what the cameras see
                    seen_by[f] += visible_points(true_pts[f], cam, depth)
                mask = cov >= 0.5
                if c.clamp:  # drawn in front; the truth mask is the object it leaves visible
                    rgb = draw_occluders(rgb, ctl, f, cam, supersample=c.supersample)
                    mask &= ~ignore_mask(ctl, f, cam, margin_px=0)
                if c.noise > 0:
                    rgb = rgb + noise_rng.normal(0.0, c.noise, rgb.shape)
                min_cov[cam.name] = min(min_cov[cam.name], float(mask.mean()))
                _write_png(root / "frames" / cam.name / f"{f:06d}.png", _to_u8(rgb))
                _write_png(root / "truth" / "masks" / cam.name / f"{f:06d}.png", mask.astype(np.uint8) * 255)
            task.advance(1)
    empty = [n for n, v in min_cov.items() if v == 0.0]
    if empty:
        raise RslError(f"camera(s) {', '.join(empty)} see nothing of the object in some frame; the ring does not "
                       f"frame the scene.")
    if seen_by is not None:
        write_markers(root / "markers.csv", occlude_markers(pts, seen_by, c.marker_visibility))
        kept = seen_by[0] >= c.marker_visibility
        observed = (seen_by >= c.marker_visibility) & kept
        reporter.info(f"--marker-visibility {c.marker_visibility}: {int(kept.sum())} of {len(kept)} markers seen "
                      f"at frame 0; {observed.mean():.1%} of the {observed.size} marker observations written "
                      f"({1 - observed.mean():.1%} lost to occlusion).")
