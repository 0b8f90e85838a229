"""HDF5 artefacts: the contract between stages (DESIGN §3).

Every artefact is one HDF5 file whose root carries the attributes
``rsl_kind``, ``schema_version``, ``rsl_version``, ``created``, ``config``
(JSON) and ``inputs`` (JSON list of ``{"path", "sha256"}``).  Each kind has a
typed dataclass with ``save(path, provenance)`` and ``load(path)``.  Writes go
to a temporary file in the same folder that is renamed into place, so a failed
write never replaces a good artefact.  Readers validate kind, version, shapes,
dtypes and finiteness and raise :class:`ArtefactError` with one sentence that
names the file and the problem.
"""
from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import hashlib
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

from stages.errors import RslError

RSL_VERSION = "0.1.0"
SCHEMA_VERSION = 1

KIND_FILES = {
    "cameras": "cameras.h5",
    "masks": "masks.h5",
    "mesh": "mesh.h5",
    "gaussians": "gaussians.h5",
    "snapshots": "snapshots.h5",
    "subspace": "subspace.h5",
    "adapt": "adapt.h5",
}


class ArtefactError(RslError):
    """An artefact is missing, of the wrong kind, or holds malformed data."""


# --------------------------------------------------------------------------- provenance
def file_sha256(path: str | Path, chunk: int = 1 << 20) -> str:
    """Content hash of a file (hex sha256)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while True:
            b = f.read(chunk)
            if not b:
                break
            h.update(b)
    return h.hexdigest()


@dataclass(frozen=True)
class Provenance:
    """Where an artefact came from: the stage config and the hashed inputs."""

    config: dict = field(default_factory=dict)
    inputs: tuple = ()  # of {"path": str, "sha256": str}

    @staticmethod
    def make(config: Any, input_paths: list[str | Path] = ()) -> "Provenance":
        """Build provenance from a config (dataclass or dict) and input files."""
        if dataclasses.is_dataclass(config):
            config = dataclasses.asdict(config)
        inputs = tuple(
            {"path": str(Path(p).resolve()), "sha256": file_sha256(p)}
            for p in input_paths
            if p is not None and Path(p).is_file()
        )
        return Provenance(config=_jsonable(config or {}), inputs=inputs)


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return obj


def read_provenance(path: str | Path) -> dict:
    """Root attributes of an artefact as a dict (config and inputs decoded)."""
    path = Path(path)
    with _open_read(path) as f:
        attrs = {k: _attr(v) for k, v in f.attrs.items()}
    for key in ("config", "inputs"):
        if key in attrs:
            try:
                attrs[key] = json.loads(attrs[key])
            except (TypeError, json.JSONDecodeError):
                raise ArtefactError(f"{path}: root attribute '{key}' is not valid JSON.")
    return attrs


def _attr(v: Any) -> Any:
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.generic):
        return v.item()
    return v


# --------------------------------------------------------------------------- writing
@contextlib.contextmanager
def atomic_h5(path: str | Path, kind: str, provenance: Provenance) -> Iterator[h5py.File]:
    """Open a temporary HDF5 file next to ``path``; rename it into place on success.

    On any exception the temporary file is removed and ``path`` is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["rsl_kind"] = kind
            f.attrs["schema_version"] = SCHEMA_VERSION
            f.attrs["rsl_version"] = RSL_VERSION
            f.attrs["created"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
            f.attrs["config"] = json.dumps(_jsonable(provenance.config), sort_keys=True)
            f.attrs["inputs"] = json.dumps(list(provenance.inputs))
            yield f
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def _put(group: h5py.Group, name: str, value: Any, compress: bool = False) -> None:
    value = np.asarray(value)
    if value.dtype.kind == "U":
        group.create_dataset(name, data=value.astype(object), dtype=h5py.string_dtype())
    elif compress and value.ndim >= 2 and value.size > 0:
        chunks = (1,) + value.shape[1:] if value.ndim == 3 else True
        group.create_dataset(name, data=value, compression="gzip", compression_opts=4, chunks=chunks)
    else:
        group.create_dataset(name, data=value)


# --------------------------------------------------------------------------- reading
@contextlib.contextmanager
def _open_read(path: Path) -> Iterator[h5py.File]:
    if not path.exists():
        raise ArtefactError(f"{path}: file not found (run the stage that writes it first).")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise ArtefactError(f"{path}: not a readable HDF5 file (truncated or corrupt: {e}).") from None
    try:
        yield f
    finally:
        f.close()


class _Reader:
    """Validating access to one open artefact."""

    def __init__(self, f: h5py.File, path: Path):
        self.f, self.path = f, path

    def fail(self, msg: str) -> "None":
        raise ArtefactError(f"{self.path}: {msg}")

    def array(
        self,
        name: str,
        ndim: int | None = None,
        shape: tuple | None = None,
        kind: str = "f",
        finite: bool = True,
        group: h5py.Group | None = None,
    ) -> np.ndarray:
        """Read dataset ``name``; check ndim/shape (None = any), dtype kind ('f','i','b','u','S') and finiteness."""
        g = self.f if group is None else group
        if name not in g:
            self.fail(f"dataset '{_full(g, name)}' is missing.")
        try:
            a = g[name][()]
        except (OSError, KeyError) as e:
            self.fail(f"dataset '{_full(g, name)}' cannot be read ({e}); the file may be truncated.")
        a = np.asarray(a)
        if kind == "S":
            return np.array([x.decode() if isinstance(x, bytes) else str(x) for x in a.ravel()]).reshape(a.shape)
        if kind == "i" and a.dtype.kind not in "iu":
            self.fail(f"dataset '{_full(g, name)}' should hold integers, found {a.dtype}.")
        if kind == "f" and a.dtype.kind not in "fiu":
            self.fail(f"dataset '{_full(g, name)}' should hold numbers, found {a.dtype}.")
        if kind == "b" and a.dtype.kind not in "bu":
            self.fail(f"dataset '{_full(g, name)}' should hold booleans, found {a.dtype}.")
        if ndim is not None and a.ndim != ndim:
            self.fail(f"dataset '{_full(g, name)}' should have {ndim} dimensions, found shape {a.shape}.")
        if shape is not None:
            if len(shape) != a.ndim or any(s is not None and s != d for s, d in zip(shape, a.shape)):
                want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
                self.fail(f"dataset '{_full(g, name)}' should have shape {want}, found {a.shape}.")
        if finite and a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
            self.fail(f"dataset '{_full(g, name)}' holds {bad} NaN or infinite values.")
        return a

    def attr(self, name: str, default: Any = ..., group: h5py.Group | None = None) -> Any:
        g = self.f if group is None else group
        if name not in g.attrs:
            if default is ...:
                self.fail(f"attribute '{name}' is missing on '{g.name}'.")
            return default
        return _attr(g.attrs[name])

    def group(self, name: str) -> h5py.Group:
        if name not in self.f or not isinstance(self.f[name], h5py.Group):
            self.fail(f"group '{name}' is missing.")
        return self.f[name]


def _full(g: h5py.Group, name: str) -> str:
    return name if g.name == "/" else f"{g.name.lstrip('/')}/{name}"


@contextlib.contextmanager
def open_artefact(path: str | Path, kind: str) -> Iterator[_Reader]:
    """Open ``path`` and check that it is an rsl artefact of ``kind`` and a known schema version."""
    path = Path(path)
    with _open_read(path) as f:
        found = _attr(f.attrs.get("rsl_kind", ""))
        if not found:
            raise ArtefactError(f"{path}: not an rsl artefact (no 'rsl_kind' attribute).")
        if found != kind:
            raise ArtefactError(f"{path}: is a '{found}' artefact, expected '{kind}'.")
        version = int(_attr(f.attrs.get("schema_version", -1)))
        if version > SCHEMA_VERSION:
            raise ArtefactError(
                f"{path}: schema version {version} is newer than this rsl understands "
                f"({SCHEMA_VERSION}); upgrade rsl."
            )
        if version < 1:
            raise ArtefactError(f"{path}: invalid schema version {version}.")
        yield _Reader(f, path)


def artefact_kind(path: str | Path) -> str:
    """The ``rsl_kind`` of an artefact file."""
    with _open_read(Path(path)) as f:
        return str(_attr(f.attrs.get("rsl_kind", "")))


def describe(path: str | Path) -> dict:
    """Kind, provenance and every dataset's shape and dtype (for ``rsl info``)."""
    path = Path(path)
    prov = read_provenance(path)
    datasets: list[tuple[str, tuple, str]] = []
    with _open_read(path) as f:

        def visit(name: str, obj: Any) -> None:
            if isinstance(obj, h5py.Dataset):
                datasets.append((name, tuple(obj.shape), str(obj.dtype)))

        f.visititems(visit)
    return {"path": str(path), "attrs": prov, "datasets": datasets}


# =========================================================================== kinds
@dataclass
class Camera:
    """One pinhole camera, OpenCV convention: x_cam = R x_world + t; pixel = K x_cam / z."""

    name: str
    K: np.ndarray  # (3, 3)
    dist: np.ndarray  # (5,) k1 k2 p1 p2 k3
    R: np.ndarray  # (3, 3) world -> camera
    t: np.ndarray  # (3,) metres
    width: int
    height: int
    rms_px: float = float("nan")  # reprojection RMS of the calibration

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, -Rᵀ t."""
        return -self.R.T @ self.t


@dataclass
class CamerasArtefact:
    cameras: list[Camera]
    method: str  # "chessboard", "charuco", "sfm", "json", "colmap", "synth"

    kind = "cameras"

    def by_name(self, name: str) -> Camera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(name)

    def save(self, path: str | Path, provenance: Provenance = Provenance()) -> Path:
        with atomic_h5(path, self.kind, provenance) as f:
            f.attrs["method"] = self.method
            f.attrs["names"] = json.dumps([c.name for c in self.cameras])
            for c in self.cameras:
                g = f.create_group(f"cameras/{c.name}")
                for k in ("K", "dist", "R", "t"):
                    _put(g, k, np.asarray(getattr(c, k), dtype=np.float64))
                g.attrs["width"] = int(c.width)
                g.attrs["height"] = int(c.height)
                g.attrs["rms_px"] = float(c.rms_px)
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "CamerasArtefact":
        with open_artefact(path, cls.kind) as r:
            names = json.loads(r.attr("names"))
            if not names:
                r.fail("holds no camera.")
            cams = []
            for n in names:
                g = r.group(f"cameras/{n}")
                K = r.array("K", shape=(3, 3), group=g)
                dist = r.array("dist", ndim=1, group=g)
                R = r.array("R", shape=(3, 3), group=g)
                t = r.array("t", shape=(3,), group=g)
                if abs(np.linalg.det(R) - 1.0) > 1e-3:
                    r.fail(f"camera '{n}' has a rotation R with determinant {np.linalg.det(R):.4f}, not 1.")
                w, h = int(r.attr("width", group=g)), int(r.attr("height", group=g))
                if w <= 0 or h <= 0:
                    r.fail(f"camera '{n}' has image size {w}x{h}.")
                cams.append(Camera(n, K, dist, R, t, w, h, float(r.attr("rms_px", float("nan"), group=g))))
            return cls(cams, str(r.attr("method")))


@dataclass
class MasksArtefact:
    masks: dict[str, np.ndarray]  # camera -> (T, H, W) bool
    method: str
    iou: dict[str, float] = field(default_factory=dict)  # against truth masks, when known

    kind = "masks"

    def save(self, path: str | Path, provenance: Provenance = Provenance()) -> Path:
        with atomic_h5(path, self.kind, provenance) as f:
            f.attrs["method"] = self.method
            f.attrs["names"] = json.dumps(list(self.masks))
            f.attrs["iou"] = json.dumps(self.iou)
            for n, m in self.masks.items():
                _put(f.require_group("masks"), n, np.asarray(m, dtype=bool), compress=True)
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "MasksArtefact":
        with open_artefact(path, cls.kind) as r:
            names = json.loads(r.attr("names"))
            g = r.group("masks") if names else None
            masks = {n: r.array(n, ndim=3, kind="b", group=g).astype(bool) for n in names}
            counts = {m.shape[0] for m in masks.values()}
            if len(counts) > 1:
                r.fail(f"cameras hold unequal frame counts {sorted(counts)}.")
            return cls(masks, str(r.attr("method")), json.loads(r.attr("iou", "{}")))


@dataclass
class MeshArtefact:
    """Tetrahedral mesh with everything the FEM needs at rest (SI units)."""

    vertices: np.ndarray  # (n, 3) rest positions, m
    tets: np.ndarray  # (m, 4) vertex ids, positive orientation
    surface_faces: np.ndarray  # (k, 3) outward-facing boundary triangles
    tet_region: np.ndarray  # (m,) index into region_names
    region_names: list[str]
    rest_volumes: np.ndarray  # (m,) m^3
    dm_inv: np.ndarray  # (m, 3, 3) inverse rest shape matrices Dm^-1
    vertex_masses: np.ndarray  # (n,) kg, lumped
    density: float  # kg/m^3
    handles: dict[str, np.ndarray] = field(default_factory=dict)  # name -> vertex ids
    quality: dict = field(default_factory=dict)  # min/max volume, worst dihedral (deg), ...
    loads: dict[str, np.ndarray] = field(default_factory=dict)  # load name -> vertex ids (controls.json)

    kind = "mesh"

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_tets(self) -> int:
        return int(self.tets.shape[0])

    def save(self, path: str | Path, provenance: Provenance = Provenance()) -> Path:
        with atomic_h5(path, self.kind, provenance) as f:
            _put(f, "vertices", np.asarray(self.vertices, np.float64))
            _put(f, "tets", np.asarray(self.tets, np.int64))
            _put(f, "surface_faces", np.asarray(self.surface_faces, np.int64))
            _put(f, "tet_region", np.asarray(self.tet_region, np.int32))
            _put(f, "rest_volumes", np.asarray(self.rest_volumes, np.float64))
            _put(f, "dm_inv", np.asarray(self.dm_inv, np.float64))
            _put(f, "vertex_masses", np.asarray(self.vertex_masses, np.float64))
            f.attrs["region_names"] = json.dumps(list(self.region_names))
            f.attrs["density"] = float(self.density)
            f.attrs["quality"] = json.dumps(_jsonable(self.quality))
            for group, sets in (("handles", self.handles), ("loads", self.loads)):
                h = f.create_group(group)
                for name, ids in sets.items():
                    _put(h, name, np.asarray(ids, np.int64))
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "MeshArtefact":
        with open_artefact(path, cls.kind) as r:
            v = r.array("vertices", shape=(None, 3))
            n = v.shape[0]
            tets = r.array("tets", shape=(None, 4), kind="i").astype(np.int64)
            m = tets.shape[0]
            if m == 0:
                r.fail("holds no tetrahedron.")
            if tets.min() < 0 or tets.max() >= n:
                r.fail(f"tets index vertices outside 0..{n - 1}.")
            faces = r.array("surface_faces", shape=(None, 3), kind="i").astype(np.int64)
            region = r.array("tet_region", shape=(m,), kind="i").astype(np.int64)
            vol = r.array("rest_volumes", shape=(m,))
            if np.any(vol <= 0):
                r.fail(f"{int(np.sum(vol <= 0))} tets have non-positive rest volume.")
            dm_inv = r.array("dm_inv", shape=(m, 3, 3))
            masses = r.array("vertex_masses", shape=(n,))
            names = json.loads(r.attr("region_names"))
            if region.max(initial=0) >= len(names):
                r.fail("tet_region refers to a region with no name.")
            sets: dict[str, dict[str, np.ndarray]] = {"handles": {}, "loads": {}}
            for group in sets:
                if group not in r.f:
                    continue
                for name in r.f[group]:
                    ids = r.array(name, ndim=1, kind="i", group=r.f[group]).astype(np.int64)
                    if ids.size and (ids.min() < 0 or ids.max() >= n):
                        r.fail(f"{group[:-1]} '{name}' refers to vertices outside 0..{n - 1}.")
                    sets[group][name] = ids
            handles = sets["handles"]
            return cls(
                v, tets, faces, region, list(names), vol, dm_inv, masses,
                float(r.attr("density")), handles, json.loads(r.attr("quality", "{}")), sets["loads"],
            )


@dataclass
class GaussiansArtefact:
    """3D Gaussians bound to tets (rest frame); see stages/render."""

    host_tet: np.ndarray  # (G,) int
    bary: np.ndarray  # (G, 4) barycentric weights, rows sum to 1
    log_scales: np.ndarray  # (G, 3) log of rest-frame std devs, m
    rotations: np.ndarray  # (G, 4) unit quaternion wxyz, rest frame
    opacity_logit: np.ndarray  # (G,)
    sh: np.ndarray  # (G, K, 3) SH coefficients, K = (degree+1)^2
    fit_psnr: dict[str, float] = field(default_factory=dict)  # camera -> PSNR dB
    background: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) RGB in [0,1]

    kind = "gaussians"

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1

    def save(self, path: str | Path, provenance: Provenance = Provenance()) -> Path:
        with atomic_h5(path, self.kind, provenance) as f:
            _put(f, "host_tet", np.asarray(self.host_tet, np.int64))
            for k in ("bary", "log_scales", "rotations", "opacity_logit", "sh", "background"):
                _put(f, k, np.asarray(getattr(self, k), np.float32))
            f.attrs["fit_psnr"] = json.dumps(self.fit_psnr)
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "GaussiansArtefact":
        with open_artefact(path, cls.kind) as r:
            host = r.array("host_tet", ndim=1, kind="i").astype(np.int64)
            g = host.shape[0]
            bary = r.array("bary", shape=(g, 4))
            if g and np.max(np.abs(bary.sum(1) - 1)) > 1e-3:
                r.fail("barycentric weights do not sum to 1.")
            sh = r.array("sh", shape=(g, None, 3))
            if int(round(np.sqrt(sh.shape[1]))) ** 2 != sh.shape[1]:
                r.fail(f"sh has {sh.shape[1]} coefficients per colour, not a square number.")
            return cls(
                host, bary, r.array("log_scales", shape=(g, 3)), r.array("rotations", shape=(g, 4)),
                r.array("opacity_logit", shape=(g,)), sh, json.loads(r.attr("fit_psnr", "{}")),
                r.array("background", shape=(3,)),
            )


@dataclass
class SnapshotsArtefact:
    """Training positions for the subspace, with the material of each snapshot."""

    positions: np.ndarray  # (S, n, 3) m
    young: np.ndarray  # (S, R) Pa per region
    poisson: np.ndarray  # (S, R)
    sequence: np.ndarray  # (S,) int sequence id
    frame: np.ndarray  # (S,) int frame within its sequence
    region_names: list[str] = field(default_factory=list)

    kind = "snapshots"

    def save(self, path: str | Path, provenance: Provenance = Provenance()) -> Path:
        with atomic_h5(path, self.kind, provenance) as f:
            _put(f, "positions", np.asarray(self.positions, np.float64), compress=True)
            _put(f, "young", np.asarray(self.young, np.float64))
            _put(f, "poisson", np.asarray(self.poisson, np.float64))
            _put(f, "sequence", np.asarray(self.sequence, np.int64))
            _put(f, "frame", np.asarray(self.frame, np.int64))
            f.attrs["region_names"] = json.dumps(list(self.region_names))
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "SnapshotsArtefact":
        with open_artefact(path, cls.kind) as r:
            x = r.array("positions", shape=(None, None, 3))
            s = x.shape[0]
            if s == 0:
                r.fail("holds no snapshot.")
            young = r.array("young", shape=(s, None))
            if np.any(young <= 0):
                r.fail("holds a non-positive Young's modulus.")
            return cls(
                x, young, r.array("poisson", shape=(s, young.shape[1])),
                r.array("sequence", shape=(s,), kind="i"), r.array("frame", shape=(s,), kind="i"),
                json.loads(r.attr("region_names", "[]")),
            )


@dataclass
class SubspaceArtefact:
    """A trained map x = φ(z) with its weights as named arrays."""

    subspace_kind: str  # "autoencoder" | "pca" | "lbs"
    dim: int
    weights: dict[str, np.ndarray]  # named arrays; layout defined by stages/subspace
    train_error_m: float
    val_error_m: float
    extra: dict = field(default_factory=dict)  # JSON-able metadata (layer sizes, cubature error, ...)

    kind = "subspace"

    def save(self, path: str | Path, provenance: Provenance = Provenance()) -> Path:
        with atomic_h5(path, self.kind, provenance) as f:
            f.attrs["subspace_kind"] = self.subspace_kind
            f.attrs["dim"] = int(self.dim)
            f.attrs["train_error_m"] = float(self.train_error_m)
            f.attrs["val_error_m"] = float(self.val_error_m)
            f.attrs["extra"] = json.dumps(_jsonable(self.extra))
            g = f.create_group("weights")
            for k, v in self.weights.items():
                _put(g, k, np.asarray(v))
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "SubspaceArtefact":
        with open_artefact(path, cls.kind) as r:
            g = r.group("weights")
            weights = {}
            for k in g:
                a = g[k][()]
                kind = "i" if np.asarray(a).dtype.kind in "iu" else "f"
                weights[k] = r.array(k, group=g, kind=kind)
            dim = int(r.attr("dim"))
            if dim <= 0:
                r.fail(f"subspace dimension {dim} is not positive.")
            return cls(
                str(r.attr("subspace_kind")), dim, weights, float(r.attr("train_error_m")),
                float(r.attr("val_error_m")), json.loads(r.attr("extra", "{}")),
            )


@dataclass
class AdaptArtefact:
    """Per-frame result of ``rsl adapt``."""

    frames: np.ndarray  # (T,) capture frame ids
    young: np.ndarray  # (T, R) Pa, θ_t per region
    poisson: np.ndarray  # (T, R)
    z: np.ndarray  # (T, r) reduced state (r = 0 in full space)
    positions: np.ndarray  # (T, n, 3) m
    loss: np.ndarray  # (T,)
    time_forward_s: np.ndarray  # (T,)
    time_backward_s: np.ndarray  # (T,)
    time_render_s: np.ndarray  # (T,)
    time_total_s: np.ndarray  # (T,)
    region_names: list[str]
    mode: str  # "online" | "offline"
    space: str  # "reduced" | "full"
    loss_kind: str  # "vision" | "markers"
    window: int
    extra: dict = field(default_factory=dict)

    kind = "adapt"

    _per_frame = ("young", "poisson", "z", "positions", "loss",
                  "time_forward_s", "time_backward_s", "time_render_s", "time_total_s")

    def save(self, path: str | Path, provenance: Provenance = Provenance()) -> Path:
        with atomic_h5(path, self.kind, provenance) as f:
            _put(f, "frames", np.asarray(self.frames, np.int64))
            for k in self._per_frame:
                _put(f, k, np.asarray(getattr(self, k), np.float64), compress=(k == "positions"))
            f.attrs["region_names"] = json.dumps(list(self.region_names))
            for k in ("mode", "space", "loss_kind"):
                f.attrs[k] = getattr(self, k)
            f.attrs["window"] = int(self.window)
            f.attrs["extra"] = json.dumps(_jsonable(self.extra))
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "AdaptArtefact":
        with open_artefact(path, cls.kind) as r:
            frames = r.array("frames", ndim=1, kind="i")
            t = frames.shape[0]
            young = r.array("young", shape=(t, None))
            nreg = young.shape[1]
            if np.any(young <= 0):
                r.fail("holds a non-positive Young's modulus.")
            out = dict(
                frames=frames, young=young, poisson=r.array("poisson", shape=(t, nreg)),
                z=r.array("z", shape=(t, None)), positions=r.array("positions", shape=(t, None, 3)),
                loss=r.array("loss", shape=(t,)),
            )
            for k in ("time_forward_s", "time_backward_s", "time_render_s", "time_total_s"):
                out[k] = r.array(k, shape=(t,))
            return cls(
                **out, region_names=json.loads(r.attr("region_names")), mode=str(r.attr("mode")),
                space=str(r.attr("space")), loss_kind=str(r.attr("loss_kind")),
                window=int(r.attr("window")), extra=json.loads(r.attr("extra", "{}")),
            )


@dataclass
class StressArtefact:
    """Per-frame stress of a trajectory, written by ``rsl export`` (export/stress.h5)."""

    frames: np.ndarray  # (T,) capture frame ids
    time_s: np.ndarray  # (T,) s
    von_mises_tet: np.ndarray  # (T, m) Pa
    von_mises_vertex: np.ndarray  # (T, n) Pa, volume-weighted average of the tets around a vertex
    cauchy_tet: np.ndarray  # (T, m, 3, 3) Pa
    internal_forces: np.ndarray  # (T, n, 3) N
    tet_region: np.ndarray  # (m,)
    region_names: list[str]
    material_model: str

    kind = "stress"

    def save(self, path: str | Path, provenance: Provenance = Provenance()) -> Path:
        with atomic_h5(path, self.kind, provenance) as f:
            _put(f, "frames", np.asarray(self.frames, np.int64))
            _put(f, "time_s", np.asarray(self.time_s, np.float64))
            for k in ("von_mises_tet", "von_mises_vertex", "cauchy_tet", "internal_forces"):
                _put(f, k, np.asarray(getattr(self, k), np.float64), compress=True)
            _put(f, "tet_region", np.asarray(self.tet_region, np.int32))
            f.attrs["region_names"] = json.dumps(list(self.region_names))
            f.attrs["material_model"] = self.material_model
            f.attrs["units"] = json.dumps({"von_mises_tet": "Pa", "von_mises_vertex": "Pa", "cauchy_tet": "Pa",
                                           "internal_forces": "N", "time_s": "s"})
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "StressArtefact":
        with open_artefact(path, cls.kind) as r:
            frames = r.array("frames", ndim=1, kind="i")
            t = frames.shape[0]
            vm = r.array("von_mises_tet", shape=(t, None))
            m = vm.shape[1]
            vmv = r.array("von_mises_vertex", shape=(t, None))
            return cls(
                frames, r.array("time_s", shape=(t,)), vm, vmv, r.array("cauchy_tet", shape=(t, m, 3, 3)),
                r.array("internal_forces", shape=(t, vmv.shape[1], 3)),
                r.array("tet_region", shape=(m,), kind="i"), json.loads(r.attr("region_names")),
                str(r.attr("material_model")),
            )


ARTEFACT_TYPES = {
    c.kind: c
    for c in (CamerasArtefact, MasksArtefact, MeshArtefact, GaussiansArtefact,
              SnapshotsArtefact, SubspaceArtefact, AdaptArtefact, StressArtefact)
}


def load_any(path: str | Path):
    """Load an artefact of whatever kind it says it is (validated)."""
    kind = artefact_kind(path)
    if not kind:
        raise ArtefactError(f"{path}: not an rsl artefact (no 'rsl_kind' attribute).")
    if kind not in ARTEFACT_TYPES:
        raise ArtefactError(f"{path}: unknown artefact kind '{kind}'.")
    return ARTEFACT_TYPES[kind].load(path)
