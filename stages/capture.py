"""Reading a capture folder (DESIGN §2): capture.toml, the object mesh, regions,
cameras, calibration views, frames (PNG folders or MP4), background plates,
controls.json, markers.csv and truth/.

Every problem raises :class:`CaptureError` with one sentence that names the file
and the field.  Nothing here does physics.
"""
from __future__ import annotations

import csv
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stages.errors import RslError

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

SURFACE_SUFFIXES = (".obj", ".ply", ".stl", ".off")
TET_SUFFIXES = (".mesh", ".msh")
MATERIAL_MODELS = ("stable_neohookean", "yeoh", "linear")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


class CaptureError(RslError):
    """A capture folder is missing something or holds malformed data."""


# =========================================================================== rigid poses
def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion (w, x, y, z); q is normalised first."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z) with w ≥ 0 of a rotation matrix."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    return q if q[0] >= 0 else -q


def slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions (w, x, y, z), a ∈ [0, 1]."""
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + a * (q1 - q0)
        return q / np.linalg.norm(q)
    th = math.acos(min(d, 1.0))
    return (math.sin((1 - a) * th) * q0 + math.sin(a * th) * q1) / math.sin(th)


def apply_pose(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """p = R(q) p_rest + t for a pose [tx, ty, tz, qw, qx, qy, qz]; points (k, 3)."""
    pose = np.asarray(pose, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ quat_to_matrix(pose[3:]).T + pose[:3]


IDENTITY_POSE = np.array([0.0, 0, 0, 1, 0, 0, 0])


@dataclass
class Track:
    """A per-frame quantity: explicit values (T, D), or keyframes interpolated linearly
    (poses: linear translation and slerp rotation).  Past the last entry the last value holds."""

    frames: np.ndarray  # (K,) increasing frame ids
    values: np.ndarray  # (K, D)
    is_pose: bool = False

    @property
    def n_frames(self) -> int:
        """Frames covered (last keyframe + 1)."""
        return int(self.frames[-1]) + 1

    def at(self, frame: float) -> np.ndarray:
        f = self.frames
        if frame <= f[0]:
            return self.values[0].copy()
        if frame >= f[-1]:
            return self.values[-1].copy()
        k = int(np.searchsorted(f, frame, side="right")) - 1
        a = (frame - f[k]) / (f[k + 1] - f[k])
        v0, v1 = self.values[k], self.values[k + 1]
        if not self.is_pose:
            return (1 - a) * v0 + a * v1
        return np.concatenate([(1 - a) * v0[:3] + a * v1[:3], slerp(v0[3:], v1[3:], a)])

    def sample(self, n_frames: int) -> np.ndarray:
        """Values at frames 0..n_frames-1, shape (n_frames, D)."""
        return np.stack([self.at(i) for i in range(n_frames)])

    @staticmethod
    def constant(value: np.ndarray, is_pose: bool = False) -> "Track":
        return Track(np.array([0]), np.asarray(value, dtype=np.float64)[None], is_pose)


# =========================================================================== controls
@dataclass
class Selection:
    """Which rest vertices something acts on: a box, a plane side (n·p ≥ d) or explicit ids."""

    kind: str  # "box" | "plane" | "ids"
    box: np.ndarray | None = None  # (2, 3) corners
    normal: np.ndarray | None = None
    offset: float = 0.0
    ids: np.ndarray | None = None

    def select(self, vertices: np.ndarray, surface_ids: np.ndarray | None = None) -> np.ndarray:
        """Vertex ids (sorted) selected among ``vertices`` (n, 3).

        Boxes and planes select among all vertices; ``ids`` refer to vertices of the rest
        mesh directly.
        """
        if self.kind == "box":
            lo, hi = np.minimum(self.box[0], self.box[1]), np.maximum(self.box[0], self.box[1])
            inside = np.all((vertices >= lo - 1e-12) & (vertices <= hi + 1e-12), axis=1)
            return np.flatnonzero(inside)
        if self.kind == "plane":
            n = self.normal / np.linalg.norm(self.normal)
            return np.flatnonzero(vertices @ n >= self.offset - 1e-12)
        return np.unique(self.ids)

    def to_json(self) -> dict:
        if self.kind == "box":
            return {"box": self.box.tolist()}
        if self.kind == "plane":
            return {"plane": {"normal": self.normal.tolist(), "offset": self.offset}}
        return {"ids": self.ids.tolist()}


@dataclass
class Handle:
    """Vertices pulled by stiff springs (N/m per vertex) to rigidly moved rest positions."""

    name: str
    select: Selection
    stiffness: float
    poses: Track  # (·, 7)


@dataclass
class Load:
    """A known total force (N) spread evenly over the selected vertices."""

    name: str
    select: Selection
    force: Track  # (·, 3)


@dataclass
class Obstacle:
    """A rigid collider: an infinite plane (n·p ≥ offset is outside), a sphere, or a box."""

    name: str
    shape: str  # "plane" | "sphere" | "box"
    normal: np.ndarray | None = None  # plane
    offset: float = 0.0  # plane
    radius: float = 0.0  # sphere, m
    half_extents: np.ndarray | None = None  # box, m
    poses: Track = field(default_factory=lambda: Track.constant(IDENTITY_POSE, True))


@dataclass
class Controls:
    """The known inputs of an experiment (controls.json)."""

    handles: list[Handle] = field(default_factory=list)
    loads: list[Load] = field(default_factory=list)
    obstacles: list[Obstacle] = field(default_factory=list)
    friction: float = 0.0

    @property
    def n_frames(self) -> int | None:
        """Frames the explicit per-frame tracks cover (max over tracks); None if all constant."""
        tracks = [h.poses for h in self.handles] + [ld.force for ld in self.loads] + \
                 [o.poses for o in self.obstacles]
        n = [t.n_frames for t in tracks if t.n_frames > 1]
        return max(n) if n else None

    def to_json(self) -> dict:
        def track(t: Track, key: str) -> dict:
            if len(t.frames) == t.n_frames and np.array_equal(t.frames, np.arange(len(t.frames))):
                return {key: t.values.tolist()}
            return {"keyframes": {"frame": t.frames.tolist(), key[:-1] if key == "poses" else key:
                                  t.values.tolist()}}

        out: dict[str, Any] = {"handles": [], "loads": [], "obstacles": [], "friction": self.friction}
        for h in self.handles:
            out["handles"].append({"name": h.name, "select": h.select.to_json(),
                                   "stiffness": h.stiffness, **track(h.poses, "poses")})
        for ld in self.loads:
            out["loads"].append({"name": ld.name, "select": ld.select.to_json(), **track(ld.force, "force")})
        for o in self.obstacles:
            d: dict[str, Any] = {"name": o.name, "shape": o.shape}
            if o.shape == "plane":
                d.update(normal=o.normal.tolist(), offset=o.offset)
            elif o.shape == "sphere":
                d.update(radius=o.radius)
            else:
                d.update(half_extents=o.half_extents.tolist())
            d.update(track(o.poses, "poses"))
            out["obstacles"].append(d)
        return out


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
    unknown = set(data) - {"handles", "loads", "obstacles", "friction"}
    if unknown:
        v.fail(sorted(unknown)[0], "is not a known field (handles, loads, obstacles, friction).")
    ctl = Controls(friction=v.number(data, "friction", "controls", default=0.0, nonneg=True))
    for i, h in enumerate(v.named_list(data, "handles")):
        w = f"handles[{i}]"
        ctl.handles.append(Handle(h["name"], v.selection(h, w),
                                  v.number(h, "stiffness", w, default=1.0e4, positive=True),
                                  v.track(h, "poses", 7, w, is_pose=True, required=False)))
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
    return ctl


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


def select_handles(controls: Controls, vertices: np.ndarray, path: Path | str = "controls.json"
                   ) -> dict[str, np.ndarray]:
    """Vertex ids of each handle; a selection that picks no vertex is an error."""
    out = {}
    n = len(vertices)
    for h in controls.handles:
        ids = h.select.select(vertices)
        if h.select.kind == "ids" and ids.size and ids.max() >= n:
            raise CaptureError(f"{path}: handle '{h.name}' selects vertex id {int(ids.max())} but the mesh "
                               f"has {n} vertices.")
        if ids.size == 0:
            raise CaptureError(f"{path}: handle '{h.name}' selects no vertex of the mesh.")
        out[h.name] = ids
    for ld in controls.loads:
        ids = ld.select.select(vertices)
        if ids.size == 0 or (ld.select.kind == "ids" and ids.max() >= n):
            raise CaptureError(f"{path}: load '{ld.name}' selects no valid vertex of the mesh.")
    return out


# =========================================================================== capture.toml
@dataclass
class MaterialSettings:
    model: str = "stable_neohookean"
    young: float = 1.0e5  # Pa, initial guess for adapt
    poisson: float = 0.45
    young_range: tuple[float, float] = (1.0e4, 1.0e6)  # prior range for generate-data
    poisson_range: tuple[float, float] = (0.3, 0.49)
    regions: dict[str, dict[str, float]] = field(default_factory=dict)  # NAME -> {young, poisson}

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
        return self.root / "markers.csv"

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

    def frame_count(self) -> int:
        """Frames per camera; unequal counts across cameras are an error."""
        counts = {c: self.frame_source(c).count for c in self.camera_names}
        if len(set(counts.values())) > 1:
            detail = ", ".join(f"{c}: {n}" for c, n in counts.items())
            raise CaptureError(f"{self.root / 'frames'}: cameras hold unequal frame counts ({detail}).")
        return next(iter(counts.values())) if counts else 0

    def markers(self) -> np.ndarray | None:
        """markers.csv as (T, M, 3) metres (NaN where a marker was not observed: a gap), or None when absent."""
        if not self.markers_path.exists():
            return None
        return read_markers(self.markers_path)


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
    regions = raw.get("regions", {})
    if not isinstance(regions, dict):
        v.fail("regions", "should be a table of tables.")
    reg_mat: dict[str, dict[str, float]] = {}
    for name, tab in regions.items():
        if not isinstance(tab, dict):
            v.fail(f"regions.{name}", "should be a table.")
        reg_mat[name] = {}
        if "young" in tab:
            reg_mat[name]["young"] = v.number(tab, "young", f"regions.{name}", positive=True)
        if "poisson" in tab:
            reg_mat[name]["poisson"] = v.number(tab, "poisson", f"regions.{name}")
    material = MaterialSettings(model, young, poisson, (float(yr[0]), float(yr[1])),
                                (float(pr[0]), float(pr[1])), reg_mat)
    name = cap.get("name", root.name)
    return Capture(root, str(name), fps, gravity, list(cams), mesh_path, density, material, raw)


# =========================================================================== images and frames
def read_image(path: str | Path) -> np.ndarray:
    """An image file as RGB uint8 (H, W, 3)."""
    import cv2

    path = Path(path)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise CaptureError(f"{path}: cannot read image (missing, empty or not an image).")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def write_image(path: str | Path, rgb: np.ndarray) -> None:
    """Write RGB uint8 (H, W, 3) or gray (H, W) as PNG/JPG."""
    import cv2

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
                import cv2

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
        import cv2

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
        import cv2

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
    """markers.csv (header frame,marker,x,y,z, metres) -> (T, M, 3), NaN where a marker was not observed.

    A (frame, marker) pair with no row, or a row whose x, y and z are all empty, is a gap (a marker no
    camera saw): NaN in the returned array.  Markers are the distinct marker ids in increasing order;
    frames must run 0..T−1 (each frame with at least one row, empty coordinates allowed).  Rejected,
    each with one sentence naming the file: a header other than frame,marker,x,y,z; a row that is not
    numbers, or writes a non-finite value (nan, inf) or only some of x, y, z; a repeated (frame, marker)
    row; frames not 0..T−1; a marker that is never observed; a marker not observed at frame 0 (rsl adapt
    binds every marker to the surface point nearest its frame-0 position).
    """
    path = Path(path)
    rows: list[tuple[int, int, float, float, float]] = []
    with open(path, newline="") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None or [h.strip() for h in header] != ["frame", "marker", "x", "y", "z"]:
            raise CaptureError(f"{path}: header should be 'frame,marker,x,y,z', found {header}.")
        for ln, row in enumerate(reader, start=2):
            if not row:
                continue
            if len(row) == 5 and all(not v.strip() for v in row[2:5]):
                xyz = [math.nan] * 3  # an explicit gap
                try:
                    fr, mk = int(row[0]), int(row[1])
                except ValueError:
                    raise CaptureError(f"{path}: line {ln} is not 'frame,marker,x,y,z' numbers: {row}.") from None
            else:
                try:
                    fr, mk = int(row[0]), int(row[1])
                    xyz = [float(v) for v in row[2:5]]
                except (ValueError, IndexError):
                    raise CaptureError(f"{path}: line {ln} is not 'frame,marker,x,y,z' numbers "
                                       f"(a gap leaves x, y and z all empty): {row}.") from None
                if len(row) != 5 or not all(math.isfinite(v) for v in xyz):
                    raise CaptureError(f"{path}: line {ln} should hold 5 finite values (or a gap: x, y and z all "
                                       f"empty), found {row}.")
            rows.append((fr, mk, *xyz))
    if not rows:
        raise CaptureError(f"{path}: holds no marker rows.")
    arr = np.array(rows)
    frames = np.unique(arr[:, 0]).astype(int)
    markers = np.unique(arr[:, 1]).astype(int)
    if not np.array_equal(frames, np.arange(len(frames))):
        raise CaptureError(f"{path}: frames should run 0..T-1 without gaps (a frame where no marker is seen "
                           f"needs one row with x, y and z empty).")
    out = np.full((len(frames), len(markers), 3), np.nan)
    seen = np.zeros((len(frames), len(markers)), bool)
    mindex = {m: i for i, m in enumerate(markers)}
    for fr, mk, x, y, z in arr:
        t, m = int(fr), mindex[int(mk)]
        if seen[t, m]:
            raise CaptureError(f"{path}: marker {int(mk)} is listed twice at frame {t}.")
        seen[t, m] = True
        out[t, m] = (x, y, z)
    observed = np.isfinite(out[..., 0])
    never = markers[~observed.any(axis=0)]
    if len(never):
        raise CaptureError(f"{path}: marker(s) {', '.join(map(str, never[:10]))} are never observed.")
    late = markers[~observed[0]]
    if len(late):
        raise CaptureError(f"{path}: marker(s) {', '.join(map(str, late[:10]))} are not observed at frame 0; every "
                           f"marker must be seen at frame 0, where rsl adapt binds it to the surface.")
    return out


def write_markers(path: str | Path, markers: np.ndarray) -> None:
    """(T, M, 3) -> markers.csv; an entry with a NaN (a gap) is left out, and a frame with no observed marker
    is written as one row of the first observed marker with x, y and z empty, so that the file still holds
    frames 0..T−1."""
    markers = np.asarray(markers, float)
    anywhere = np.flatnonzero(np.all(np.isfinite(markers), axis=-1).any(axis=0))
    placeholder = int(anywhere[0]) if len(anywhere) else 0
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", "marker", "x", "y", "z"])
        for t in range(markers.shape[0]):
            seen = np.all(np.isfinite(markers[t]), axis=-1)
            if not seen.any():
                w.writerow([t, placeholder, "", "", ""])
            for m in np.flatnonzero(seen):
                w.writerow([t, m, *(f"{v:.9g}" for v in markers[t, m])])


@dataclass
class Truth:
    """Ground truth of a synthetic capture (read by `rsl evaluate` alone)."""

    young: np.ndarray  # (T, R) Pa
    poisson: np.ndarray  # (T, R)
    region_names: list[str]
    faces: np.ndarray  # (k, 3)
    vertices: np.ndarray  # (T, v, 3) m


def read_truth(capture: Capture) -> Truth:
    """truth/material.csv and truth/surface.npz."""
    d = capture.truth_dir
    mat_path, surf_path = d / "material.csv", d / "surface.npz"
    for p in (mat_path, surf_path):
        if not p.is_file():
            raise CaptureError(f"{p}: file not found; `rsl evaluate` needs a synthetic capture with truth/.")
    rows = []
    with open(mat_path, newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames != ["frame", "region", "young", "poisson"]:
            raise CaptureError(f"{mat_path}: header should be 'frame,region,young,poisson'.")
        for r in reader:
            try:
                rows.append((int(r["frame"]), r["region"], float(r["young"]), float(r["poisson"])))
            except (TypeError, ValueError):
                raise CaptureError(f"{mat_path}: malformed row {r}.") from None
    regions = sorted({r[1] for r in rows}, key=[r[1] for r in rows].index)
    n_frames = max(r[0] for r in rows) + 1
    young = np.full((n_frames, len(regions)), np.nan)
    poisson = np.full((n_frames, len(regions)), np.nan)
    for fr, reg, e, nu in rows:
        young[fr, regions.index(reg)] = e
        poisson[fr, regions.index(reg)] = nu
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


# =========================================================================== cameras.json
def read_cameras_json(path: str | Path) -> list:
    """cameras.json -> list of artefacts.Camera (OpenCV convention, R world->camera)."""
    from stages.artefacts import Camera

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
