"""Reading a capture folder (DESIGN §2): capture.toml, the object mesh, regions,
cameras, calibration views, frames (PNG folders or MP4), background plates,
controls.json, markers.csv and truth/.

Every problem raises :class:`CaptureError` with one sentence that names the file
and the field.  Nothing here does physics.
"""
from __future__ import annotations

import csv
import difflib
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from stages import mocap
from stages.domain.cameras import Camera
from stages.domain.controls import (IDENTITY_POSE, Controls, Handle, Load, Obstacle,  # noqa: F401 (re-exported)
                                    Selection, Track, Visual, apply_pose, select_handles)
from stages.domain.errors import CaptureError, RslError  # noqa: F401 (re-exported)
from stages.domain.rotations import matrix_to_quat_wxyz as matrix_to_quat  # noqa: F401 (re-exported)
from stages.domain.rotations import quat_wxyz_to_matrix as quat_to_matrix  # noqa: F401 (re-exported)
from stages.domain.rotations import slerp_wxyz as slerp  # noqa: F401 (re-exported)

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

SURFACE_SUFFIXES = (".obj", ".ply", ".stl", ".off")
TET_SUFFIXES = (".mesh", ".msh")
MATERIAL_MODELS = ("stable_neohookean", "yeoh", "linear")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


# =========================================================================== known keys
# Every key a lab may type.  A key not listed here is rejected with the nearest known key (difflib), so a
# typo ("youngs", "[materail]", "stifness") never passes silently.  Helpers adding a key: add it here.
# capture.toml: table -> its keys; "*" = any key (a free-form record); [regions.NAME] uses "regions.*".
KNOWN_KEYS: dict[str, tuple[str, ...]] = {
    "capture": ("name", "fps", "gravity", "cameras", "start"),
    "object": ("mesh", "density"),
    "material": ("model", "young", "poisson", "young_range", "poisson_range", "damping"),
    "regions": (),  # a table of [regions.NAME] tables
    "regions.*": ("young", "poisson"),
    "calibration": ("board",),
    "synth": ("*",),  # written by `rsl synth`: a record of how the capture was made
}
START_STATES = ("equilibrium", "rest", "moving")  # [capture] start: what frame 0 shows (docs/capture.md)
# controls.json: object -> its keys.
CONTROLS_KEYS: dict[str, tuple[str, ...]] = {
    "controls": ("handles", "loads", "obstacles", "friction"),
    "handle": ("name", "select", "stiffness", "hard", "poses", "keyframes", "visual"),
    "load": ("name", "select", "force", "keyframes"),
    "obstacle": ("name", "shape", "normal", "offset", "radius", "half_extents", "poses", "keyframes", "visual"),
    "select": ("box", "plane", "ids"),
    "plane": ("normal", "offset"),
    "pose_keyframes": ("frame", "pose", "poses"),  # keyframes of a handle or an obstacle
    "force_keyframes": ("frame", "force"),  # keyframes of a load
    "visual": ("box", "mesh"),
}


def nearest_key(key: str, known: tuple[str, ...] | list[str]) -> str:
    """" (did you mean 'K'?)" for the known key K nearest ``key`` (difflib), else ''."""
    close = difflib.get_close_matches(str(key), [k for k in known if k != "*"], n=1, cutoff=0.5)
    return f" (did you mean '{close[0]}'?)" if close else ""


def check_keys(obj: dict, known: tuple[str, ...] | list[str], where: str, path: Path) -> None:
    """Reject the first key of ``obj`` not in ``known``, naming the file, where it is and the nearest key."""
    if "*" in known or not isinstance(obj, dict):
        return
    for key in obj:
        if key not in known:
            loc = f"'{where}.{key}'" if where else f"'{key}'"
            listed = ", ".join(known) if known else "none"
            raise CaptureError(f"{path}: {loc} is not a known key{nearest_key(key, known)}; "
                               f"the keys there are {listed}.")


# Track, Selection, Handle, Load, Obstacle, Controls, poses and select_handles live in
# stages/domain/controls.py (add fields there); this module parses controls.json into them.
class _Fields:
    """Field-by-field validation with messages naming the file and the JSON path."""

    def __init__(self, path: Path):
        self.path = path

    def fail(self, where: str, msg: str) -> None:
        raise CaptureError(f"{self.path}: '{where}' {msg}")

    def number(self, obj: dict, key: str, where: str, default: Any = ..., positive: bool = False,
               nonneg: bool = False) -> float:
        if key not in obj:
            if default is ...:
                self.fail(f"{where}.{key}", "is missing.")
            return default
        v = obj[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            self.fail(f"{where}.{key}", f"should be a finite number, found {json.dumps(v)}.")
        if positive and v <= 0:
            self.fail(f"{where}.{key}", f"should be positive, found {v}.")
        if nonneg and v < 0:
            self.fail(f"{where}.{key}", f"should not be negative, found {v}.")
        return float(v)

    def vector(self, v: Any, length: int, where: str) -> np.ndarray:
        if not isinstance(v, list) or len(v) != length or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v):
            self.fail(where, f"should be a list of {length} finite numbers, found {json.dumps(v)[:80]}.")
        return np.asarray(v, dtype=np.float64)

    def track(self, obj: dict, key: str, width: int, where: str, is_pose: bool, required: bool) -> Track:
        single = "pose" if key == "poses" else key
        if key in obj and "keyframes" in obj:
            self.fail(where, f"has both '{key}' and 'keyframes'; give one.")
        if key in obj:
            vals = obj[key]
            if not isinstance(vals, list) or not vals:
                self.fail(f"{where}.{key}", "should be a non-empty list with one entry per frame.")
            arr = np.stack([self.vector(v, width, f"{where}.{key}[{i}]") for i, v in enumerate(vals)])
            t = Track(np.arange(len(arr)), arr, is_pose)
        elif "keyframes" in obj:
            kf = obj["keyframes"]
            if not isinstance(kf, dict):
                self.fail(f"{where}.keyframes", "should be an object with 'frame' and "
                          f"'{single}' lists.")
            frames = kf.get("frame")
            if not isinstance(frames, list) or not frames or not all(
                    isinstance(f, int) and not isinstance(f, bool) and f >= 0 for f in frames):
                self.fail(f"{where}.keyframes.frame", "should be a non-empty list of frame numbers ≥ 0.")
            if any(b <= a for a, b in zip(frames, frames[1:])):
                self.fail(f"{where}.keyframes.frame", "should be strictly increasing.")
            vals = kf.get(single, kf.get(key))
            if not isinstance(vals, list) or len(vals) != len(frames):
                self.fail(f"{where}.keyframes.{single}", f"should hold {len(frames)} entries, one per keyframe.")
            arr = np.stack([self.vector(v, width, f"{where}.keyframes.{single}[{i}]") for i, v in enumerate(vals)])
            t = Track(np.asarray(frames), arr, is_pose)
        elif required:
            self.fail(where, f"needs '{key}' (one entry per frame) or 'keyframes'.")
        else:
            return Track.constant(IDENTITY_POSE if is_pose else np.zeros(width), is_pose)
        if is_pose:
            norms = np.linalg.norm(t.values[:, 3:], axis=1)
            if np.any(norms < 1e-9):
                self.fail(f"{where}.{key}", "holds a zero quaternion; a pose is [tx,ty,tz,qw,qx,qy,qz].")
            t.values[:, 3:] /= norms[:, None]
        return t

    def selection(self, obj: dict, where: str) -> Selection:
        sel = obj.get("select")
        if not isinstance(sel, dict) or len(sel) != 1:
            self.fail(f"{where}.select", "should be an object with exactly one of 'box', 'plane', 'ids'.")
        (kind, v), = sel.items()
        if kind == "box":
            if not isinstance(v, list) or len(v) != 2:
                self.fail(f"{where}.select.box", "should be two corners [[x0,y0,z0],[x1,y1,z1]].")
            return Selection("box", box=np.stack([self.vector(c, 3, f"{where}.select.box[{i}]")
                                                  for i, c in enumerate(v)]))
        if kind == "plane":
            if not isinstance(v, dict):
                self.fail(f"{where}.select.plane", "should be {\"normal\": [...], \"offset\": d}.")
            n = self.vector(v.get("normal"), 3, f"{where}.select.plane.normal")
            if np.linalg.norm(n) < 1e-12:
                self.fail(f"{where}.select.plane.normal", "is the zero vector.")
            return Selection("plane", normal=n, offset=self.number(v, "offset", f"{where}.select.plane"))
        if kind == "ids":
            if not isinstance(v, list) or not v or not all(
                    isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in v):
                self.fail(f"{where}.select.ids", "should be a non-empty list of vertex ids ≥ 0.")
            return Selection("ids", ids=np.asarray(v, dtype=np.int64))
        self.fail(f"{where}.select", f"has unknown kind '{kind}'; use 'box', 'plane' or 'ids'.")
        raise AssertionError

    def named_list(self, data: dict, key: str) -> list[dict]:
        items = data.get(key, [])
        if not isinstance(items, list):
            self.fail(key, f"should be a list, found {type(items).__name__}.")
        names = set()
        for i, it in enumerate(items):
            if not isinstance(it, dict):
                self.fail(f"{key}[{i}]", "should be an object.")
            name = it.get("name")
            if not isinstance(name, str) or not name:
                self.fail(f"{key}[{i}].name", "should be a non-empty string.")
            if name in names:
                self.fail(f"{key}[{i}].name", f"repeats the name '{name}'.")
            names.add(name)
        return items


def parse_controls(data: Any, path: Path) -> Controls:
    """Validate the JSON of controls.json field by field (DESIGN §2)."""
    v = _Fields(path)
    if not isinstance(data, dict):
        raise CaptureError(f"{path}: should hold a JSON object with 'handles', 'loads', 'obstacles'.")
    check_controls_keys(data, path)
    ctl = Controls(friction=v.number(data, "friction", "controls", default=0.0, nonneg=True))
    for i, h in enumerate(v.named_list(data, "handles")):
        w = f"handles[{i}]"
        ctl.handles.append(Handle(h["name"], v.selection(h, w),
                                  v.number(h, "stiffness", w, default=1.0e4, positive=True),
                                  v.track(h, "poses", 7, w, is_pose=True, required=False)))
        ctl.handles[-1].visual = parse_visual(h, w, path)
        if "hard" in h:
            if not isinstance(h["hard"], bool):
                v.fail(f"{w}.hard", "should be true or false.")
            ctl.handles[-1].hard = h["hard"]
    for i, ld in enumerate(v.named_list(data, "loads")):
        w = f"loads[{i}]"
        ctl.loads.append(Load(ld["name"], v.selection(ld, w), v.track(ld, "force", 3, w, False, True)))
    for i, o in enumerate(v.named_list(data, "obstacles")):
        w = f"obstacles[{i}]"
        shape = o.get("shape")
        poses = v.track(o, "poses", 7, w, is_pose=True, required=False)
        if shape == "plane":
            n = v.vector(o.get("normal"), 3, f"{w}.normal")
            if np.linalg.norm(n) < 1e-12:
                v.fail(f"{w}.normal", "is the zero vector.")
            ctl.obstacles.append(Obstacle(o["name"], "plane", normal=n / np.linalg.norm(n),
                                          offset=v.number(o, "offset", w, default=0.0), poses=poses))
        elif shape == "sphere":
            ctl.obstacles.append(Obstacle(o["name"], "sphere", radius=v.number(o, "radius", w, positive=True),
                                          poses=poses))
        elif shape == "box":
            he = v.vector(o.get("half_extents"), 3, f"{w}.half_extents")
            if np.any(he <= 0):
                v.fail(f"{w}.half_extents", "should be positive.")
            ctl.obstacles.append(Obstacle(o["name"], "box", half_extents=he, poses=poses))
        else:
            v.fail(f"{w}.shape", f"should be 'plane', 'sphere' or 'box', found {json.dumps(shape)}.")
        ctl.obstacles[-1].visual = parse_visual(o, w, path)
    return ctl


def parse_visual(obj: dict, where: str, path: Path) -> Visual | None:
    """The optional ``visual`` of a handle or obstacle (INTERFACES §7): {"box": [[x0,y0,z0],[x1,y1,z1]]} or
    {"mesh": "FILE"} (obj/ply/stl/off relative to controls.json), in the frame its pose moves."""
    if "visual" not in obj:
        return None
    v, w = _Fields(path), f"{where}.visual"
    vis = obj["visual"]
    if not isinstance(vis, dict) or len(vis) != 1 or next(iter(vis)) not in ("box", "mesh"):
        v.fail(w, "should be an object with exactly one of 'box' (two corners) or 'mesh' (a file name).")
    (kind, val), = vis.items()
    if kind == "box":
        if not isinstance(val, list) or len(val) != 2:
            v.fail(f"{w}.box", "should be two corners [[x0,y0,z0],[x1,y1,z1]].")
        box = np.stack([v.vector(c, 3, f"{w}.box[{i}]") for i, c in enumerate(val)])
        if np.any(np.abs(box[1] - box[0]) <= 0):
            v.fail(f"{w}.box", "has zero extent along an axis; give two opposite corners.")
        return Visual("box", box=box)
    if not isinstance(val, str) or not val:
        v.fail(f"{w}.mesh", "should be the name of a mesh file (obj, ply, stl, off) beside controls.json.")
    file = Path(path).parent / val
    if file.suffix.lower() not in SURFACE_SUFFIXES:
        v.fail(f"{w}.mesh", f"names '{val}', which is not an obj, ply, stl or off file.")
    if not file.is_file():
        v.fail(f"{w}.mesh", f"names '{val}', but {file} does not exist.")
    import trimesh  # ~1 s to import: only when a surface mesh is read

    try:
        m = trimesh.load(str(file), force="mesh", process=False)
        verts, faces = np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)
    except Exception as e:  # trimesh raises many kinds on a bad file
        raise CaptureError(f"{file}: cannot read the mesh of {path} '{w}.mesh' ({type(e).__name__}: {e}).") from None
    if faces.ndim != 2 or len(faces) == 0 or not np.all(np.isfinite(verts)):
        raise CaptureError(f"{file}: the mesh of {path} '{w}.mesh' holds no triangles (or non-finite vertices).")
    return Visual("mesh", vertices=verts, faces=faces, source=val)


def check_controls_keys(data: dict, path: Path) -> None:
    """Every key of controls.json must be known (CONTROLS_KEYS); the first unknown one is an error."""
    K = CONTROLS_KEYS
    check_keys(data, K["controls"], "", path)
    for lst, kind, kf in (("handles", "handle", "pose_keyframes"), ("loads", "load", "force_keyframes"),
                          ("obstacles", "obstacle", "pose_keyframes")):
        items = data.get(lst)
        if not isinstance(items, list):
            continue
        for i, it in enumerate(items):
            if not isinstance(it, dict):
                continue
            w = f"{lst}[{i}]"
            check_keys(it, K[kind], w, path)
            sel = it.get("select")
            check_keys(sel, K["select"], f"{w}.select", path)
            if isinstance(sel, dict):
                check_keys(sel.get("plane"), K["plane"], f"{w}.select.plane", path)
            check_keys(it.get("keyframes"), K[kf], f"{w}.keyframes", path)
            check_keys(it.get("visual"), K["visual"], f"{w}.visual", path)


MOVING_CONTACT_DEPTH = 0.10
"""A capture filmed mid-motion ([capture] start = "moving") may show an obstacle already pressing the object at
frame 0: its rest vertices may lie this deep inside it (× the object's size), where a declared start allows
``check_obstacles_clear``'s tolerance.  Frame 0's equilibrium is then solved from the rest shape with the contact
pushing those vertices out (the dinosaur pushed by a sphere, filmed 8 frames in, 2 % deep: docs/results/
moving_start.md)."""


def check_obstacles_clear(controls: Controls, vertices: np.ndarray, path: Path | str = "controls.json",
                          tolerance: float = 0.01, start: str = "equilibrium") -> None:
    """An obstacle must not start inside the object: at frame 0, no rest vertex (n, 3) may lie deeper inside a
    plane, sphere or box obstacle than ``tolerance`` × the object's size (its bounding-box diagonal) — or, for a
    capture filmed mid-motion (``start`` "moving"), whose obstacle may already press it, than
    :data:`MOVING_CONTACT_DEPTH` × its size."""
    if start == "moving":
        tolerance = max(tolerance, MOVING_CONTACT_DEPTH)
    v = np.asarray(vertices, dtype=np.float64)
    size = float(np.linalg.norm(v.max(0) - v.min(0)))
    for o in controls.obstacles:
        pose = o.poses.at(0)
        pl = (v - pose[:3]) @ quat_to_matrix(pose[3:])  # R^T (p − t), rows
        if o.shape == "plane":
            depth = o.offset - pl @ (o.normal / np.linalg.norm(o.normal))
        elif o.shape == "sphere":
            depth = o.radius - np.linalg.norm(pl, axis=1)
        else:
            depth = np.min(o.half_extents - np.abs(pl), axis=1)
        inside = depth > tolerance * size
        if np.any(inside) and start == "moving":
            raise CaptureError(f"{path}: obstacle '{o.name}' lies up to {1000 * float(depth.max()):.1f} mm inside the "
                               f"rest shape at frame 0 ({int(inside.sum())} rest vertices), more than a capture filmed "
                               f"mid-motion (start = \"moving\") may press it ({MOVING_CONTACT_DEPTH:.0%} of the "
                               f"object's size); check its poses.")
        if np.any(inside):
            raise CaptureError(f"{path}: obstacle '{o.name}' starts inside the object at frame 0 ({int(inside.sum())} "
                               f"rest vertices up to {1000 * float(depth.max()):.1f} mm deep); move it out of the "
                               f"rest shape with its poses.")


def load_controls(path: str | Path) -> Controls:
    """Read and validate a controls.json file."""
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: file not found.")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise CaptureError(f"{path}: not valid JSON ({e.msg} at line {e.lineno}, column {e.colno}).") from None
    return parse_controls(data, path)


# =========================================================================== capture.toml
@dataclass
class MaterialSettings:
    model: str = "stable_neohookean"
    young: float = 1.0e5  # Pa, initial guess for adapt
    poisson: float = 0.45
    young_range: tuple[float, float] = (1.0e4, 1.0e6)  # prior range for generate-data
    poisson_range: tuple[float, float] = (0.3, 0.49)
    regions: dict[str, dict[str, float]] = field(default_factory=dict)  # NAME -> {young, poisson}
    damping: float = 0.0  # β, s: viscous (Kelvin–Voigt) damping, force ≈ −β K₀ v (stages.sim.materials); 0: none

    def region_young(self, name: str) -> float:
        return float(self.regions.get(name, {}).get("young", self.young))

    def region_poisson(self, name: str) -> float:
        return float(self.regions.get(name, {}).get("poisson", self.poisson))


@dataclass
class Capture:
    """A validated capture folder."""

    root: Path
    name: str
    fps: float
    gravity: np.ndarray  # (3,) m/s^2
    camera_names: list[str]
    mesh_path: Path
    density: float  # kg/m^3
    material: MaterialSettings
    raw: dict = field(default_factory=dict)  # the parsed capture.toml
    start: str = "equilibrium"
    """What frame 0 shows ([capture] start): "equilibrium" — the static equilibrium under gravity and the
    frame-0 controls, at rest; "rest" — the rest shape with zero velocity (held, released at t = 0).
    Either way the states before frame 0 are x_{−1} = x_{−2} = x_0 (docs/capture.md)."""

    # ------------------------------------------------------------------ paths
    @property
    def toml_path(self) -> Path:
        return self.root / "capture.toml"

    @property
    def controls_path(self) -> Path:
        return self.root / "controls.json"

    @property
    def cameras_json(self) -> Path:
        return self.root / "cameras.json"

    @property
    def markers_path(self) -> Path:
        """markers.csv, or markers.c3d when only that one exists (what :meth:`markers` reads)."""
        csv_path, c3d_path = self.root / "markers.csv", self.root / "markers.c3d"
        return c3d_path if c3d_path.exists() and not csv_path.exists() else csv_path

    @property
    def truth_dir(self) -> Path:
        return self.root / "truth"

    @property
    def dt(self) -> float:
        """Time step between frames, s."""
        return 1.0 / self.fps

    def region_meshes(self) -> dict[str, Path]:
        """regions/NAME.obj|ply|stl|off, sorted by name."""
        d = self.root / "regions"
        if not d.is_dir():
            return {}
        return {p.stem: p for p in sorted(d.iterdir()) if p.suffix.lower() in SURFACE_SUFFIXES}

    def controls(self) -> Controls:
        """controls.json, or no controls at all when the file is absent."""
        if not self.controls_path.exists():
            return Controls()
        return load_controls(self.controls_path)

    # ------------------------------------------------------------------ images
    def calib_views(self) -> dict[str, dict[str, Path]]:
        """calib/CAM/NAME.png -> {cam: {view name: path}}."""
        d = self.root / "calib"
        out: dict[str, dict[str, Path]] = {}
        if d.is_dir():
            for cam_dir in sorted(p for p in d.iterdir() if p.is_dir()):
                views = {p.stem: p for p in sorted(cam_dir.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES}
                if views:
                    out[cam_dir.name] = views
        return out

    def background(self, cam: str) -> np.ndarray | None:
        """background/CAM.png as RGB uint8 (H, W, 3), or None."""
        for suf in IMAGE_SUFFIXES:
            p = self.root / "background" / f"{cam}{suf}"
            if p.exists():
                return read_image(p)
        return None

    def frame_source(self, cam: str) -> "FrameSource":
        return FrameSource.open(self.root / "frames", cam)

    def frame_inputs(self, cams: list[str] | None = None, backgrounds: bool = False) -> list[Path]:
        """What a stage reading the frames of ``cams`` (default: all) reads, for its provenance: each camera's
        frame folder (hashed file by file) or video, and with ``backgrounds`` its background plate."""
        out: list[Path] = []
        for c in self.camera_names if cams is None else cams:
            src = self.frame_source(c)
            out.append(self.root / "frames" / c if src.files is not None else src.video)
            if backgrounds:
                out += [self.root / "background" / f"{c}{suf}" for suf in IMAGE_SUFFIXES
                        if (self.root / "background" / f"{c}{suf}").is_file()]
        return out

    def frame_count(self) -> int:
        """Frames per camera; unequal counts across cameras are an error."""
        counts = {c: self.frame_source(c).count for c in self.camera_names}
        if len(set(counts.values())) > 1:
            detail = ", ".join(f"{c}: {n}" for c, n in counts.items())
            raise CaptureError(f"{self.root / 'frames'}: cameras hold unequal frame counts ({detail}).")
        return next(iter(counts.values())) if counts else 0

    def markers(self) -> np.ndarray | None:
        """markers.csv or markers.c3d as (T, M, 3) metres (NaN where a marker was not observed: a gap), or None
        when neither exists.  Both present is an error; so is a C3D frame rate other than capture.fps."""
        csv_path, c3d_path = self.root / "markers.csv", self.root / "markers.c3d"
        if csv_path.exists() and c3d_path.exists():
            raise CaptureError(f"{self.root}: holds both markers.csv and markers.c3d; keep one of them.")
        path = self.markers_path
        if not path.exists():
            return None
        data = mocap.read_markers_file(path)
        mocap.check_rate(data, path, self.fps, self.toml_path)
        mocap.check_bindable(data, path)
        return data.positions


def load_capture(root: str | Path) -> Capture:
    """Read and validate CAPTURE/capture.toml."""
    root = Path(root)
    if not root.is_dir():
        raise CaptureError(f"{root}: capture folder not found.")
    path = root / "capture.toml"
    if not path.is_file():
        raise CaptureError(f"{path}: file not found; every capture folder needs a capture.toml.")
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise CaptureError(f"{path}: not valid TOML ({e}).") from None
    v = _Fields(path)
    check_toml_keys(raw, path)
    cap = raw.get("capture", {})
    obj = raw.get("object", {})
    mat = raw.get("material", {})
    for sec, val in (("capture", cap), ("object", obj), ("material", mat)):
        if not isinstance(val, dict):
            v.fail(sec, "should be a table.")
    fps = v.number(cap, "fps", "capture", default=30.0, positive=True)
    gravity = v.vector(cap.get("gravity", [0.0, 0.0, -9.81]), 3, "capture.gravity")
    cams = cap.get("cameras", [])
    if not isinstance(cams, list) or not all(isinstance(c, str) and c for c in cams):
        v.fail("capture.cameras", "should be a list of camera names.")
    dup = sorted({c for c in cams if cams.count(c) > 1})
    if dup:
        v.fail("capture.cameras", f"lists camera '{dup[0]}' twice; camera names must be unique.")
    mesh_name = obj.get("mesh")
    if not isinstance(mesh_name, str):
        v.fail("object.mesh", "is missing; name the rest-shape mesh file.")
    mesh_path = root / mesh_name
    if mesh_path.suffix.lower() not in SURFACE_SUFFIXES + TET_SUFFIXES:
        v.fail("object.mesh", f"has unsupported type '{mesh_path.suffix}'; use obj, ply, stl, off, mesh or msh.")
    if not mesh_path.is_file():
        raise CaptureError(f"{mesh_path}: mesh file named by capture.toml 'object.mesh' not found.")
    density = v.number(obj, "density", "object", default=1000.0, positive=True)
    model = mat.get("model", "stable_neohookean")
    if model not in MATERIAL_MODELS:
        v.fail("material.model", f"should be one of {', '.join(MATERIAL_MODELS)}, found {json.dumps(model)}.")
    young = v.number(mat, "young", "material", default=1.0e5, positive=True)
    poisson = v.number(mat, "poisson", "material", default=0.45)
    if not 0.0 <= poisson < 0.5:
        v.fail("material.poisson", f"should lie in [0, 0.5), found {poisson}.")
    yr = tuple(v.vector(mat.get("young_range", [young / 10, young * 10]), 2, "material.young_range"))
    pr = tuple(v.vector(mat.get("poisson_range", [0.3, 0.49]), 2, "material.poisson_range"))
    if not 0 < yr[0] <= yr[1]:
        v.fail("material.young_range", f"should be [low, high] with 0 < low ≤ high, found {list(yr)}.")
    if not 0 <= pr[0] <= pr[1] < 0.5:
        v.fail("material.poisson_range", f"should be [low, high] within [0, 0.5), found {list(pr)}.")
    if "young" in mat and not yr[0] <= young <= yr[1]:
        v.fail("material.young", f"= {young:g} Pa lies outside young_range {list(yr)}; widen the range or "
               f"change the initial guess.")
    regions = raw.get("regions", {})
    if not isinstance(regions, dict):
        v.fail("regions", "should be a table of tables.")
    reg_mat: dict[str, dict[str, float]] = {}
    for name, tab in regions.items():
        if not isinstance(tab, dict):
            v.fail(f"regions.{name}", "should be a table.")
        reg_mat[name] = {}
        if "young" in tab:
            reg_mat[name]["young"] = e = v.number(tab, "young", f"regions.{name}", positive=True)
            if not yr[0] <= e <= yr[1]:
                v.fail(f"regions.{name}.young", f"= {e:g} Pa lies outside material.young_range {list(yr)}.")
        if "poisson" in tab:
            reg_mat[name]["poisson"] = nu = v.number(tab, "poisson", f"regions.{name}")
            if not 0.0 <= nu < 0.5:
                v.fail(f"regions.{name}.poisson", f"should lie in [0, 0.5), found {nu}.")
    damping = v.number(mat, "damping", "material", default=0.0, nonneg=True)
    material = MaterialSettings(model, young, poisson, (float(yr[0]), float(yr[1])),
                                (float(pr[0]), float(pr[1])), reg_mat, damping)
    name = cap.get("name", root.name)
    start = cap.get("start", "equilibrium")
    if start not in START_STATES:
        v.fail("capture.start", f"should be \"equilibrium\", \"rest\" or \"moving\", found {json.dumps(start)}.")
    return Capture(root, str(name), fps, gravity, list(cams), mesh_path, density, material, raw, str(start))


def check_toml_keys(raw: dict, path: Path) -> None:
    """Every table and key of capture.toml must be known (KNOWN_KEYS); the first unknown one is an error."""
    tables = [k for k in KNOWN_KEYS if "." not in k]
    for sec, val in raw.items():
        if sec not in KNOWN_KEYS and not isinstance(val, dict):
            homes = [t for t in tables if sec in KNOWN_KEYS[t]]
            hint = f"; write it under its table, as [{homes[0]}] {sec}" if homes else nearest_key(sec, tables)
            raise CaptureError(f"{path}: '{sec}' is not in a table{hint}.")
        if sec not in KNOWN_KEYS:
            raise CaptureError(f"{path}: table '[{sec}]' is not a known table{nearest_key(sec, tables)}; "
                               f"the tables are {', '.join('[' + t + ']' for t in tables)}.")
        if sec == "regions" and isinstance(val, dict):
            for name, tab in val.items():
                check_keys(tab, KNOWN_KEYS["regions.*"], f"regions.{name}", path)
        elif isinstance(val, dict):
            check_keys(val, KNOWN_KEYS[sec], sec, path)


# =========================================================================== images and frames
def read_image(path: str | Path) -> np.ndarray:
    """An image file as RGB uint8 (H, W, 3)."""
    path = Path(path)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise CaptureError(f"{path}: cannot read image (missing, empty or not an image).")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def write_image(path: str | Path, rgb: np.ndarray) -> None:
    """Write RGB uint8 (H, W, 3) or gray (H, W) as PNG/JPG."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.asarray(rgb)
    if img.dtype != np.uint8:
        img = np.clip(np.round(img * 255 if img.max() <= 1.0 else img), 0, 255).astype(np.uint8)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    if not cv2.imwrite(str(path), img):
        raise CaptureError(f"{path}: cannot write image.")


_FRAME_RE = re.compile(r"^(\d+)$")


@dataclass
class FrameSource:
    """The frames of one camera: frames/CAM/000000.png … or frames/CAM.mp4."""

    cam: str
    files: list[Path] | None = None  # PNG folder
    video: Path | None = None  # MP4
    count: int = 0

    @staticmethod
    def open(frames_dir: Path, cam: str) -> "FrameSource":
        folder = frames_dir / cam
        if folder.is_dir():
            files = sorted((p for p in folder.iterdir()
                            if p.suffix.lower() in IMAGE_SUFFIXES and _FRAME_RE.match(p.stem)),
                           key=lambda p: int(p.stem))
            for i, p in enumerate(files):
                if int(p.stem) != i:
                    raise CaptureError(f"{folder}: frames should be numbered from 0 without gaps; "
                                       f"frame {i} is missing.")
            return FrameSource(cam, files=files, count=len(files))
        for suf in (".mp4", ".avi", ".mov", ".mkv"):
            video = frames_dir / f"{cam}{suf}"
            if video.is_file():
                cap = cv2.VideoCapture(str(video))
                if not cap.isOpened():
                    raise CaptureError(f"{video}: cannot open video.")
                n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
                cap.release()
                return FrameSource(cam, video=video, count=n)
        raise CaptureError(f"{frames_dir}: no frames for camera '{cam}' (expected {folder}/000000.png … "
                           f"or {frames_dir / (cam + '.mp4')}).")

    def read(self, i: int) -> np.ndarray:
        """Frame i as RGB uint8 (H, W, 3)."""
        if not 0 <= i < self.count:
            raise CaptureError(f"camera '{self.cam}': frame {i} out of range 0..{self.count - 1}.")
        if self.files is not None:
            return read_image(self.files[i])
        cap = cv2.VideoCapture(str(self.video))
        cap.set(cv2.CAP_PROP_POS_FRAMES, i)
        ok, img = cap.read()
        cap.release()
        if not ok:
            raise CaptureError(f"{self.video}: cannot decode frame {i}.")
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def read_all(self) -> np.ndarray:
        """Every frame, (T, H, W, 3) uint8."""
        if self.files is not None:
            return np.stack([read_image(p) for p in self.files])
        cap = cv2.VideoCapture(str(self.video))
        frames = []
        while True:
            ok, img = cap.read()
            if not ok:
                break
            frames.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
        cap.release()
        if not frames:
            raise CaptureError(f"{self.video}: holds no decodable frame.")
        return np.stack(frames)


# =========================================================================== markers and truth
def read_markers(path: str | Path) -> np.ndarray:
    """markers.csv or markers.c3d (by suffix; stages/mocap.py) -> (T, M, 3) metres, NaN where a marker was not
    observed (a gap).  Besides the file format's rules (stages/mocap.py), rejected with one sentence naming the
    file: a marker that is never observed; a frame 0 that observes no marker (rsl adapt binds the markers seen
    there to the frame-0 surface, a marker first seen later to its track)."""
    data = mocap.read_markers_file(path)
    mocap.check_bindable(data, path)
    return data.positions


def write_markers(path: str | Path, markers: np.ndarray) -> None:
    """(T, M, 3) -> markers.csv (stages.mocap.write_csv): a NaN entry (a gap) is left out, a frame with no
    observed marker is one row with x, y and z empty, so that the file still holds frames 0..T−1."""
    mocap.write_csv(path, markers)


@dataclass
class Truth:
    """Ground truth of a synthetic capture (read by `rsl evaluate` alone)."""

    young: np.ndarray  # (T, R) Pa
    poisson: np.ndarray  # (T, R)
    region_names: list[str]
    faces: np.ndarray  # (k, 3)
    vertices: np.ndarray  # (T, v, 3) m


def read_material_csv(path: Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """truth/material.csv (header frame,region,young,poisson): (young (T, R) Pa, poisson (T, R), region names),
    NaN where a frame does not list a region; (0, 0) arrays when it lists no row."""
    rows = []
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames != ["frame", "region", "young", "poisson"]:
            raise CaptureError(f"{path}: header should be 'frame,region,young,poisson'.")
        for r in reader:
            try:
                rows.append((int(r["frame"]), r["region"], float(r["young"]), float(r["poisson"])))
            except (TypeError, ValueError):
                raise CaptureError(f"{path}: malformed row {r}.") from None
    regions = list(dict.fromkeys(r[1] for r in rows))
    n_frames = max((r[0] for r in rows), default=-1) + 1
    young = np.full((n_frames, len(regions)), np.nan)
    poisson = np.full((n_frames, len(regions)), np.nan)
    for fr, reg, e, nu in rows:
        young[fr, regions.index(reg)] = e
        poisson[fr, regions.index(reg)] = nu
    return young, poisson, regions


def read_truth(capture: Capture) -> Truth:
    """truth/material.csv and truth/surface.npz."""
    d = capture.truth_dir
    mat_path, surf_path = d / "material.csv", d / "surface.npz"
    for p in (mat_path, surf_path):
        if not p.is_file():
            raise CaptureError(f"{p}: file not found; `rsl evaluate` needs a synthetic capture with truth/.")
    young, poisson, regions = read_material_csv(mat_path)
    if young.size == 0:
        raise CaptureError(f"{mat_path}: lists no frame.")
    if np.isnan(young).any():
        raise CaptureError(f"{mat_path}: not every frame lists every region.")
    try:
        z = np.load(surf_path)
        faces, verts = np.asarray(z["faces"]), np.asarray(z["vertices"])
    except (OSError, KeyError, ValueError) as e:
        raise CaptureError(f"{surf_path}: cannot read 'faces' and 'vertices' ({e}).") from None
    return Truth(young, poisson, regions, faces, verts)


def write_truth(folder: str | Path, young: np.ndarray, poisson: np.ndarray, region_names: list[str],
                faces: np.ndarray, vertices: np.ndarray) -> None:
    """Write truth/material.csv and truth/surface.npz."""
    d = Path(folder)
    d.mkdir(parents=True, exist_ok=True)
    with open(d / "material.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", "region", "young", "poisson"])
        for t in range(young.shape[0]):
            for r, name in enumerate(region_names):
                w.writerow([t, name, f"{young[t, r]:.9g}", f"{poisson[t, r]:.9g}"])
    np.savez_compressed(d / "surface.npz", faces=np.asarray(faces, np.int64),
                        vertices=np.asarray(vertices, np.float64))


# the columns of truth/forces.csv and of `rsl export --forces`'s forces.csv (one definition for both):
# fx..fz = Σ internal nodal force over the handle's / obstacle's vertices, magnitude_sum = Σ of their norms,
# applied_* = the force the handle or obstacle exerts on the object, N
FORCE_HEADER = ["frame", "time_s", "name", "kind", "fx_N", "fy_N", "fz_N", "magnitude_sum_N",
                "applied_fx_N", "applied_fy_N", "applied_fz_N", "n_vertices"]


def write_truth_forces(folder: str | Path, rows: list[list]) -> Path:
    """truth/forces.csv: rows in FORCE_HEADER order (one per frame and handle/obstacle)."""
    d = Path(folder)
    d.mkdir(parents=True, exist_ok=True)
    with open(d / "forces.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(FORCE_HEADER)
        for r in rows:
            w.writerow([f"{v:.9g}" if isinstance(v, float) else v for v in r])
    return d / "forces.csv"


def read_forces_csv(path: str | Path) -> list[dict]:
    """A forces.csv (truth/ or `rsl export --forces`) as a list of rows {column: value} (numbers as float)."""
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: file not found.")
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames != FORCE_HEADER:
            raise CaptureError(f"{path}: header should be '{','.join(FORCE_HEADER)}'.")
        out = []
        for r in reader:
            try:
                out.append({k: (v if k in ("name", "kind") else float(v)) for k, v in r.items()})
            except (TypeError, ValueError):
                raise CaptureError(f"{path}: malformed row {r}.") from None
    return out


# =========================================================================== cameras.json
def read_cameras_json(path: str | Path) -> list:
    """cameras.json -> list of artefacts.Camera (OpenCV convention, R world->camera)."""
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: file not found.")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise CaptureError(f"{path}: not valid JSON ({e.msg} at line {e.lineno}).") from None
    v = _Fields(path)
    cams = data.get("cameras") if isinstance(data, dict) else None
    if not isinstance(cams, list) or not cams:
        raise CaptureError(f"{path}: should hold {{\"cameras\": [...]}} with at least one camera.")
    out = []
    for i, c in enumerate(cams):
        w = f"cameras[{i}]"
        if not isinstance(c, dict) or not isinstance(c.get("name"), str):
            v.fail(f"{w}.name", "should be a string.")
        K = np.stack([v.vector(r, 3, f"{w}.K[{j}]") for j, r in enumerate(_rows(c.get("K"), 3, v, f"{w}.K"))])
        R = np.stack([v.vector(r, 3, f"{w}.R[{j}]") for j, r in enumerate(_rows(c.get("R"), 3, v, f"{w}.R"))])
        if abs(np.linalg.det(R) - 1) > 1e-3 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
            v.fail(f"{w}.R", "is not a rotation matrix.")
        t = v.vector(c.get("t"), 3, f"{w}.t")
        dist = v.vector(c.get("dist", [0, 0, 0, 0, 0]), 5, f"{w}.dist")
        width = v.number(c, "width", w, positive=True)
        height = v.number(c, "height", w, positive=True)
        out.append(Camera(c["name"], K, dist, R, t, int(width), int(height)))
    return out


def _rows(v: Any, n: int, f: _Fields, where: str) -> list:
    if not isinstance(v, list) or len(v) != n:
        f.fail(where, f"should be a {n}x{n} list of lists.")
    return v


def write_cameras_json(path: str | Path, cameras: list) -> None:
    """list of artefacts.Camera -> cameras.json."""
    data = {"cameras": [{"name": c.name, "width": int(c.width), "height": int(c.height),
                         "K": np.asarray(c.K).tolist(), "dist": np.asarray(c.dist).tolist(),
                         "R": np.asarray(c.R).tolist(), "t": np.asarray(c.t).tolist()} for c in cameras]}
    Path(path).write_text(json.dumps(data, indent=1))
