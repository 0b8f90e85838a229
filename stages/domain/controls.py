"""The known inputs of an experiment (controls.json) as plain types: rigid poses, per-frame tracks,
vertex selections, handles, loads, obstacles; and which mesh vertices each handle holds.

Pure: no files, no printing.  stages/capture.py parses controls.json into these types.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from stages.domain.errors import CaptureError
from stages.domain.rotations import quat_wxyz_to_matrix, slerp_wxyz


# =========================================================================== rigid poses
def apply_pose(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """p = R(q) p_rest + t for a pose [tx, ty, tz, qw, qx, qy, qz]; points (k, 3)."""
    pose = np.asarray(pose, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ quat_wxyz_to_matrix(pose[3:]).T + pose[:3]


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
        return np.concatenate([(1 - a) * v0[:3] + a * v1[:3], slerp_wxyz(v0[3:], v1[3:], a)])

    def sample(self, n_frames: int) -> np.ndarray:
        """Values at frames 0..n_frames-1, shape (n_frames, D)."""
        return np.stack([self.at(i) for i in range(n_frames)])

    @staticmethod
    def constant(value: np.ndarray, is_pose: bool = False) -> "Track":
        return Track(np.array([0]), np.asarray(value, dtype=np.float64)[None], is_pose)

    def shifted(self, frames: int) -> "Track":
        """The track seen ``frames`` frames later: its at(f) is self.at(f + frames) for every f ≥ 0 (keyframes
        moved back by ``frames``; the ones falling before 0 give way to the value at 0)."""
        f = self.frames - int(frames)
        keep = f >= 0
        if keep.any() and f[keep][0] == 0:
            return Track(f[keep], self.values[keep].copy(), self.is_pose)
        return Track(np.concatenate([[0], f[keep]]), np.concatenate([self.at(frames)[None], self.values[keep]]),
                     self.is_pose)


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
class Visual:
    """What a camera sees of a handle or obstacle (an occluder, INTERFACES §7): a box (2, 3) of corners or a
    triangle mesh (vertices (k, 3) m, faces (f, 3)), in the frame its pose moves (world = R(q) p + t).
    ``source`` is the mesh file as controls.json names it (relative to controls.json)."""

    kind: str  # "box" | "mesh"
    box: np.ndarray | None = None  # (2, 3)
    vertices: np.ndarray | None = None  # (k, 3), mesh
    faces: np.ndarray | None = None  # (f, 3), mesh
    source: str = ""

    def triangles(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertices (k, 3), faces (f, 3)) of the visual in its own frame (a box: 8 corners, 12 triangles)."""
        if self.kind == "mesh":
            return np.asarray(self.vertices, np.float64), np.asarray(self.faces, np.int64)
        lo, hi = np.minimum(self.box[0], self.box[1]), np.maximum(self.box[0], self.box[1])
        v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
        return v, f

    def to_json(self) -> dict:
        return {"box": np.asarray(self.box).tolist()} if self.kind == "box" else {"mesh": self.source}


@dataclass
class Handle:
    """Vertices pulled by stiff springs (N/m per vertex) to rigidly moved rest positions, or held
    exactly there when ``hard`` (Dirichlet; the stiffness is then unused)."""

    name: str
    select: Selection
    stiffness: float
    poses: Track  # (·, 7)
    visual: Visual | None = None  # what the cameras see of the gripper, moved by ``poses``
    hard: bool = False  # Dirichlet handle: its vertices sit exactly at their targets


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
    visual: Visual | None = None  # what the cameras see of it, moved by ``poses``


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

    def shifted(self, frames: int) -> "Controls":
        """The controls seen ``frames`` frames later (a capture that starts at frame ``frames`` of this one):
        every track :meth:`Track.shifted`, everything else shared."""
        return Controls([replace(h, poses=h.poses.shifted(frames)) for h in self.handles],
                        [replace(ld, force=ld.force.shifted(frames)) for ld in self.loads],
                        [replace(o, poses=o.poses.shifted(frames)) for o in self.obstacles], self.friction)

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
            if h.visual is not None:
                out["handles"][-1]["visual"] = h.visual.to_json()
            if h.hard:
                out["handles"][-1]["hard"] = True
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
            if o.visual is not None:
                d["visual"] = o.visual.to_json()
            out["obstacles"].append(d)
        return out


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
