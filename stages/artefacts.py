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
import re
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

from stages.domain.cameras import Camera  # noqa: F401 (re-exported; the type lives in the domain layer)
from stages.errors import RslError
from stages.registry import STAGES as _REGISTRY
from stages.sim.mesh import boundary_faces, rest_quantities
from stages.sim.quadrature import element_order, quadratic_surface, quadratic_tets

RSL_VERSION = "0.1.0"
SCHEMA_VERSION = 1

# artefact kind -> its file in the workspace: what the stages of stages/registry.py write
KIND_FILES = {s.produces: s.writes for s in _REGISTRY if s.produces}
PARTIAL_ADAPT = "adapt.partial.h5"  # an interrupted or failed adapt run; adapt.h5 only ever holds a complete one


class ArtefactError(RslError):
    """An artefact is missing, of the wrong kind, or holds malformed data."""


# --------------------------------------------------------------------------- provenance
HASH_CACHE = ".rsl_hashes.json"  # in the workspace: path -> [size, mtime_ns, sha256]
TEMP_RE = re.compile(r"^\.(?P<name>.+?)\.(?P<pid>\d+)\.[^.]+\.tmp$")  # .NAME.h5.PID.RANDOM.tmp


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


class HashCache:
    """sha256 of files, cached by (size, mtime_ns) in WS/.rsl_hashes.json, so that hashing every frame of a
    capture on each run costs one stat per unchanged file."""

    def __init__(self, folder: str | Path | None = None):
        self.path = None if folder is None else Path(folder) / HASH_CACHE
        self.table: dict[str, list] = {}
        self.dirty = False
        if self.path is not None and self.path.is_file():
            with contextlib.suppress(OSError, ValueError):
                t = json.loads(self.path.read_text())
                self.table = t if isinstance(t, dict) else {}

    def sha256(self, path: str | Path) -> str:
        p = Path(path)
        st = p.stat()
        key = str(p.resolve())
        hit = self.table.get(key)
        if isinstance(hit, list) and len(hit) == 3 and hit[0] == st.st_size and hit[1] == st.st_mtime_ns:
            return str(hit[2])
        digest = file_sha256(p)
        self.table[key] = [st.st_size, st.st_mtime_ns, digest]
        self.dirty = True
        return digest

    def folder_sha256(self, folder: str | Path) -> tuple[str, int]:
        """(sha256 over the sorted relative names and contents of the files under ``folder``, number of files);
        hidden files are left out."""
        h = hashlib.sha256()
        folder = Path(folder)
        files = sorted(p for p in folder.rglob("*") if p.is_file()
                       and not any(part.startswith(".") for part in p.relative_to(folder).parts))
        for p in files:
            h.update(f"{p.relative_to(folder).as_posix()}\0{self.sha256(p)}\n".encode())
        return h.hexdigest(), len(files)

    def entry_sha256(self, path: str | Path) -> str:
        """Hash of a file, or of a folder's files (a camera's frames)."""
        p = Path(path)
        return self.folder_sha256(p)[0] if p.is_dir() else self.sha256(p)

    def save(self) -> None:
        """Write the cache back (best effort: a read-only workspace just does not cache)."""
        if self.path is None or not self.dirty or not self.path.parent.is_dir():
            return
        with contextlib.suppress(OSError):
            tmp = self.path.with_name(f".{HASH_CACHE}.{os.getpid()}.tmp")
            tmp.write_text(json.dumps(self.table))
            os.replace(tmp, self.path)
            self.dirty = False


@dataclass(frozen=True)
class Provenance:
    """Where an artefact came from: the stage config and the hashed inputs.

    ``inputs`` holds ``{"path", "sha256"}`` per input (a folder, e.g. a camera's frames, gets one hash over
    its files and a ``files`` count); they are written relative to the workspace (``"base": "workspace"``,
    relative to the artefact's folder) or to the capture folder (``"base": "capture"``), so a copied or moved
    workspace is checked against its own files.  ``mesh_sha256`` is the hash of the mesh.h5 read, if any.
    """

    config: dict = field(default_factory=dict)
    inputs: tuple = ()  # of {"path": str (absolute here; made relative when written), "sha256": str}
    mesh_sha256: str = ""

    @staticmethod
    def make(config: Any, input_paths: list[str | Path] = ()) -> "Provenance":
        """Build provenance from a config (dataclass or dict) and input files or folders (hashed, cached in
        the config's workspace)."""
        if dataclasses.is_dataclass(config):
            config = dataclasses.asdict(config)
        config = dict(config or {})
        ws = config.get("workspace")
        cache = HashCache(ws if ws and Path(str(ws)).is_dir() else None)
        inputs = []
        mesh_sha = ""
        for p in input_paths:
            if p is None or not (Path(p).is_file() or Path(p).is_dir()):
                continue
            p = Path(p)
            item: dict = {"path": str(p.resolve())}
            if p.is_dir():
                item["sha256"], item["files"] = cache.folder_sha256(p)
            else:
                item["sha256"] = cache.sha256(p)
                if p.name == KIND_FILES["mesh"]:
                    mesh_sha = item["sha256"]
            inputs.append(item)
        cache.save()
        return Provenance(config=_jsonable(config), inputs=tuple(inputs), mesh_sha256=mesh_sha)


def relative_inputs(inputs: tuple | list, artefact: Path, capture: str | Path | None,
                    workspace: str | Path | None = None) -> list[dict]:
    """Input entries with paths relative to the artefact's folder (files of the workspace, or of the artefact's
    own folder) or to the capture folder; other paths stay absolute."""
    here = artefact.parent.resolve()
    cap = Path(str(capture)).resolve() if capture not in (None, "") else None
    ws = Path(str(workspace)).resolve() if workspace not in (None, "") else here
    out = []
    for item in inputs:
        item = dict(item)
        p = Path(str(item.get("path", "")))
        if p.is_absolute():
            if cap is not None and p.is_relative_to(cap):
                item.update(path=p.relative_to(cap).as_posix(), base="capture")
            elif p.is_relative_to(here) or (here.is_relative_to(ws) and p.is_relative_to(ws)):
                item.update(path=os.path.relpath(p, here), base="workspace")
        out.append(item)
    return out


def resolve_input(item: dict, artefact: Path, attrs: dict) -> Path:
    """The file an input entry names, as seen from the artefact at ``artefact`` (see :func:`relative_inputs`)."""
    p = Path(str(item.get("path", "")))
    base = item.get("base")
    if base == "workspace":
        return artefact.parent / p
    if base == "capture":
        root = attrs.get("capture_root") or (attrs.get("config") or {}).get("capture") or ""
        return Path(str(root)) / p
    return p


def recorded_mesh_sha256(attrs: dict) -> str:
    """The sha256 of the mesh.h5 an artefact was made from ('' when it does not say)."""
    sha = attrs.get("mesh_sha256")
    if sha:
        return str(sha)
    for item in attrs.get("inputs") or []:
        if isinstance(item, dict) and Path(str(item.get("path", ""))).name == KIND_FILES["mesh"]:
            return str(item.get("sha256", ""))
    return ""


_REMAKE = {"gaussians": "fit-gaussians", "snapshots": "generate-data", "subspace": "train-subspace",
           "adapt": "adapt", "stress": "export"}


def check_same_mesh(mesh_path: str | Path, *paths: str | Path | None) -> None:
    """Each existing artefact in ``paths`` must have been made from the mesh.h5 at ``mesh_path`` (same sha256),
    whatever its vertex and tet counts; otherwise an ArtefactError names it and the stage that remakes it."""
    mesh_path = Path(mesh_path)
    if not mesh_path.is_file():
        return
    current = HashCache(mesh_path.parent).sha256(mesh_path)
    for p in paths:
        if p is None or not Path(p).is_file():
            continue
        attrs = read_provenance(p)
        sha = recorded_mesh_sha256(attrs)
        if sha and sha != current:
            kind = str(attrs.get("rsl_kind", ""))
            redo = _REMAKE.get(kind)
            raise ArtefactError(
                f"{p}: was made from a different mesh.h5 than {mesh_path} (sha256 {sha[:12]}… vs {current[:12]}…); "
                + (f"run `rsl {redo}` again for the current mesh." if redo else "remake it for the current mesh."))


def check_mesh_source(mesh_path: str | Path, source: str | Path) -> None:
    """mesh.h5 must have been made from the capture's object mesh ``source`` (same content): a mesh.h5 from
    another capture would pair its vertices with this capture's handles, markers and frames."""
    mesh_path, source = Path(mesh_path), Path(source)
    if not mesh_path.is_file() or not source.is_file():
        return
    suffixes = (".obj", ".ply", ".stl", ".off", ".mesh", ".msh")
    recorded = [it for it in (read_provenance(mesh_path).get("inputs") or [])
                if isinstance(it, dict) and Path(str(it.get("path", ""))).suffix.lower() in suffixes
                and "regions" not in Path(str(it.get("path", ""))).parts[:-1]]
    if recorded and not any(it.get("sha256") == HashCache(mesh_path.parent).sha256(source) for it in recorded):
        raise ArtefactError(f"{mesh_path}: was made from another object mesh than {source} (another capture?); "
                            f"run `rsl tetrahedralize` for this capture first.")


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
def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def clean_stale_temps(folder: str | Path, min_age_s: float = 60.0) -> list[Path]:
    """Remove temporary files ``.NAME.h5.PID.RANDOM.tmp`` left by a killed stage (its PID is gone; a temp file
    without a PID counts when older than ``min_age_s``); returns the files removed."""
    folder = Path(folder)
    removed = []
    if not folder.is_dir():
        return removed
    now = _dt.datetime.now().timestamp()
    for p in folder.glob(".*.tmp"):
        m = TEMP_RE.match(p.name)
        try:
            if m and ".h5" in m.group("name"):
                stale = int(m.group("pid")) != os.getpid() and not _pid_alive(int(m.group("pid")))
            elif ".h5." in p.name:
                stale = now - p.stat().st_mtime > min_age_s
            else:
                continue
            if stale:
                p.unlink()
                removed.append(p)
        except OSError:
            continue
    return removed


_MANIFESTS: dict[str, dict[str, tuple]] = {}  # temp file -> dataset name -> (shape, dtype, sha256)
_STAGE_CLOCK = [time.monotonic()]  # when the current stage started (workspace.prepare_workspace resets it)


def start_clock() -> None:
    """Mark the start of a stage: the next artefact written records the seconds since as ``wall_s``."""
    _STAGE_CLOCK[0] = time.monotonic()


def _digest(a: np.ndarray) -> str:
    if a.dtype.kind in "OUS":
        return hashlib.sha256("\0".join(map(str, a.ravel().tolist())).encode()).hexdigest()
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


def verify_h5(path: str | Path, kind: str, manifest: dict[str, tuple] | None = None) -> str | None:
    """Re-open a written file and read every dataset back (HDF5 checks the Fletcher-32 checksums); each dataset
    in ``manifest`` must have its recorded shape, dtype and content hash.  The problem found, or None."""
    manifest = manifest or {}
    problems: list[str] = []
    seen: set[str] = set()

    def check(name: str, obj: Any) -> None:
        if not isinstance(obj, h5py.Dataset) or problems:
            return
        seen.add(name)
        a = np.asarray(obj[()])
        if name not in manifest:
            return
        shape, dtype, digest = manifest[name]
        if a.dtype.kind == "O":
            a = np.array([x.decode() if isinstance(x, bytes) else x for x in a.ravel()], dtype=object).reshape(a.shape)
        if a.shape != shape or (a.dtype.kind != "O" and a.dtype.str != dtype):
            problems.append(f"dataset '{name}' reads back as {a.shape} {a.dtype}, written as {shape} {dtype}")
        elif _digest(a) != digest:
            problems.append(f"dataset '{name}' reads back with other values than were written")

    try:
        with h5py.File(path, "r") as f:
            if _attr(f.attrs.get("rsl_kind", "")) != kind:
                return "the root attributes did not reach the disk"
            f.visititems(check)
    except (OSError, RuntimeError, ValueError, KeyError) as e:
        return f"it cannot be read back: {str(e).splitlines()[0] if str(e) else type(e).__name__}"
    if problems:
        return problems[0]
    missing = [n for n in manifest if n not in seen]
    if missing:
        return f"dataset '{missing[0]}' is missing when read back"
    return None


@contextlib.contextmanager
def atomic_h5(path: str | Path, kind: str, provenance: Provenance) -> Iterator[h5py.File]:
    """Open a temporary HDF5 file next to ``path``; rename it into place once verified.

    After the block the file is flushed, closed, fsync'ed, re-opened and every dataset read back (shape, dtype,
    content hash of what was written, Fletcher-32 checksums); only then is it renamed over ``path``.  On any
    failure (a full disk shows only when the file closes) the temporary file is removed, ``path`` is untouched
    and an :class:`ArtefactError` says so in one sentence.  Stale temporary files of killed runs are removed.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        clean_stale_temps(path.parent)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=".tmp", dir=path.parent)
        os.close(fd)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; an artefact gets the usual permissions
    except OSError as e:
        raise ArtefactError(f"{path}: cannot write in {path.parent} ({e.strerror or e}).") from None
    kept = f"the previous {path.name} is kept" if path.exists() else f"no {path.name} was written"
    manifest = _MANIFESTS.setdefault(str(Path(tmp).resolve()), {})
    try:
        try:
            # Built in memory (HDF5's core driver) and written out with plain writes: a full disk is then one
            # OSError here, never an HDF5 library that fails half-way through closing a file (it can crash).
            with h5py.File(tmp, "w", driver="core", backing_store=False) as f:
                f.attrs["rsl_kind"] = kind
                f.attrs["schema_version"] = SCHEMA_VERSION
                f.attrs["rsl_version"] = RSL_VERSION
                f.attrs["created"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
                f.attrs["config"] = json.dumps(_jsonable(provenance.config), sort_keys=True)
                capture = (provenance.config or {}).get("capture")
                f.attrs["inputs"] = json.dumps(relative_inputs(provenance.inputs, path, capture,
                                                               (provenance.config or {}).get("workspace")))
                if capture not in (None, ""):
                    f.attrs["capture_root"] = str(Path(str(capture)).resolve())
                if provenance.mesh_sha256 and kind != "mesh":
                    f.attrs["mesh_sha256"] = provenance.mesh_sha256
                f.attrs["wall_s"] = float(time.monotonic() - _STAGE_CLOCK[0])  # s the stage took to get here
                yield f
                f.flush()
                _write_file(tmp, f.id.get_file_image())
        except OSError as e:
            raise ArtefactError(f"{path}: writing failed ({_oserror_text(e)}); {kept}.") from None
        problem = verify_h5(tmp, kind, manifest)
        if problem:
            raise ArtefactError(f"{path}: the written file did not verify ({problem}); {kept}.")
        try:
            os.replace(tmp, path)
            start_clock()  # the next artefact of this process times its own stage
        except OSError as e:
            raise ArtefactError(f"{path}: cannot move the written file into place ({_oserror_text(e)}); "
                                f"{kept}.") from None
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise
    finally:
        _MANIFESTS.pop(str(Path(tmp).resolve()), None)


def _write_file(path: str, data: bytes) -> None:
    """Write ``data`` to ``path`` (truncated first) and fsync it; an OSError (e.g. ENOSPC) on failure."""
    fd = os.open(path, os.O_WRONLY | os.O_TRUNC)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)


def _oserror_text(e: OSError) -> str:
    text = e.strerror or str(e)
    text = " ".join(str(text).split())
    return text if len(text) <= 160 else text[:160] + "…"


def _put(group: h5py.Group, name: str, value: Any, compress: bool = False) -> None:
    """Write a dataset: chunked with Fletcher-32 checksums (and gzip when ``compress``); recorded for the
    read-back check of :func:`atomic_h5`."""
    value = np.asarray(value)
    if value.dtype.kind == "U":
        value = value.astype(object)
        ds = group.create_dataset(name, data=value, dtype=h5py.string_dtype())
    elif value.ndim >= 1 and value.size > 0:
        kw: dict = {"fletcher32": True, "chunks": True}
        if compress and value.ndim >= 2:
            kw.update(compression="gzip", compression_opts=4,
                      chunks=(1,) + value.shape[1:] if value.ndim == 3 else True)
        ds = group.create_dataset(name, data=value, **kw)
    else:
        ds = group.create_dataset(name, data=value)
    manifest = _MANIFESTS.get(str(Path(group.file.filename).resolve()))
    if manifest is not None:
        manifest[ds.name.lstrip("/")] = (value.shape, value.dtype.str, _digest(value))


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

    vertices: np.ndarray  # (n, 3) rest positions, m (all nodes: corners, then mid-edge nodes for order 2)
    tets: np.ndarray  # (m, 4) vertex ids, positive orientation; (m, 10) quadratic tets (stages.sim.quadrature)
    surface_faces: np.ndarray  # (k, 3) outward-facing boundary triangles
    tet_region: np.ndarray  # (m,) index into region_names
    region_names: list[str]
    rest_volumes: np.ndarray  # (m,) m^3 (order 2: the sum of the element's quadrature weights)
    dm_inv: np.ndarray  # (m, 3, 3) inverse rest shape matrices Dm^-1 of the corner tets
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

    @property
    def order(self) -> int:
        """Element order: 1 for linear (4-node), 2 for quadratic (10-node) tets."""
        return 2 if self.tets.shape[1] == 10 else 1

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
            f.attrs["order"] = self.order  # element order, also readable from tets' shape
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
            tets = r.array("tets", shape=(None, None), kind="i").astype(np.int64)
            if tets.shape[1] not in (4, 10):
                r.fail(f"'tets' should have shape (*, 4) (linear tets) or (*, 10) (quadratic tets), found "
                       f"{tets.shape}.")
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



def mesh_artefact(vertices: np.ndarray, tets: np.ndarray, density: float, tet_region: np.ndarray | None = None,
                  region_names: tuple[str, ...] = ("body",), order: int | None = None) -> MeshArtefact:
    """A MeshArtefact (in memory) with rest quantities computed from vertices (n, 3) m and tets (m, 4) or
    (m, 10); density kg/m^3.  order=2 with linear tets adds straight mid-edge nodes
    (stages.sim.quadrature.quadratic_tets); order None keeps the tets as they are."""
    vertices, tets = np.asarray(vertices, np.float64), np.asarray(tets, np.int64)
    if order not in (None, 1, 2):
        raise ValueError(f"order is 1 or 2, not {order}")
    if order == 2 and element_order(tets) == 1:
        vertices, tets = quadratic_tets(vertices, tets)
    elif order == 1 and element_order(tets) == 2:
        raise ValueError("order=1 asked for quadratic tets")
    vol, dm_inv, masses = rest_quantities(vertices, tets, density)
    region = np.zeros(len(tets), np.int64) if tet_region is None else np.asarray(tet_region, np.int64)
    faces = boundary_faces(tets) if element_order(tets) == 1 else quadratic_surface(tets)
    return MeshArtefact(vertices=vertices, tets=tets, surface_faces=faces, tet_region=region,
                        region_names=list(region_names), rest_volumes=vol, dm_inv=dm_inv, vertex_masses=masses,
                        density=float(density))


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
    # (n, 3) m: the mesh's positions the Gaussians were fitted at (the fit frame's start state, e.g. the frame-0
    # equilibrium sag); rendered there with this binding they are the fitted Gaussians.  None: at rest (old files).
    fit_positions: np.ndarray | None = None
    fit_state: dict = field(default_factory=dict)  # how fit_positions were made: start, frame, young, poisson

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
            if self.fit_positions is not None:
                _put(f, "fit_positions", np.asarray(self.fit_positions, np.float64))
            f.attrs["fit_state"] = json.dumps(self.fit_state)
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
                r.array("fit_positions", shape=(None, 3)) if "fit_positions" in r.f else None,
                json.loads(r.attr("fit_state", "{}")),
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
    young_sigma: np.ndarray | None = None  # (T, R) Pa, σ of E per frame (NaN where unknown, e.g. Adam off its held fits)
    poisson_sigma: np.ndarray | None = None  # (T, R), σ of ν per frame (NaN where unknown)
    # (2, n, 3) m, x_{−1} and x_0: the state before frame 0 and frame 0's own, as estimated for a capture filmed
    # mid-motion ([capture] start = "moving"; the force replay starts there); None for the other starts
    start_positions: np.ndarray | None = None

    kind = "adapt"

    def __post_init__(self):
        shape = np.shape(self.young)
        for k in ("young_sigma", "poisson_sigma"):
            if getattr(self, k) is None:
                setattr(self, k, np.full(shape, np.nan))

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
            for k in ("young_sigma", "poisson_sigma"):
                _put(f, k, np.asarray(getattr(self, k), np.float64))
            if self.start_positions is not None:
                _put(f, "start_positions", np.asarray(self.start_positions, np.float64))
        return Path(path)

    @classmethod
    def load(cls, path: str | Path, allow_partial: bool = False) -> "AdaptArtefact":
        """Read and validate; an interrupted or failed run (extra["status"]) is refused unless ``allow_partial``."""
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
            for k in ("young_sigma", "poisson_sigma"):  # absent from older files: NaN (unknown)
                if k in r.f:
                    out[k] = r.array(k, shape=(t, nreg), finite=False)
            if "start_positions" in r.f:
                out["start_positions"] = r.array("start_positions", shape=(2, out["positions"].shape[1], 3))
            extra = json.loads(r.attr("extra", "{}"))
            status = str(extra.get("status", "complete")) if isinstance(extra, dict) else "complete"
            if status != "complete" and not allow_partial:
                r.fail(f"holds an unfinished ({status}) run of {t} frame(s), not a complete one; run `rsl adapt` "
                       f"to the end first.")
            return cls(
                **out, region_names=json.loads(r.attr("region_names")), mode=str(r.attr("mode")),
                space=str(r.attr("space")), loss_kind=str(r.attr("loss_kind")),
                window=int(r.attr("window")), extra=extra,
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
    von_mises_point: np.ndarray | None = None  # (T, q) Pa per quadrature point (quadratic tets; None for linear)
    point_element: np.ndarray | None = None  # (q,) the element of each quadrature point

    kind = "stress"

    def save(self, path: str | Path, provenance: Provenance = Provenance()) -> Path:
        with atomic_h5(path, self.kind, provenance) as f:
            _put(f, "frames", np.asarray(self.frames, np.int64))
            _put(f, "time_s", np.asarray(self.time_s, np.float64))
            for k in ("von_mises_tet", "von_mises_vertex", "cauchy_tet", "internal_forces"):
                _put(f, k, np.asarray(getattr(self, k), np.float64), compress=True)
            if self.von_mises_point is not None:
                _put(f, "von_mises_point", np.asarray(self.von_mises_point, np.float64), compress=True)
                _put(f, "point_element", np.asarray(self.point_element, np.int32))
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
            vmp = pel = None
            if "von_mises_point" in r.f:  # quadratic tets only
                vmp = r.array("von_mises_point", shape=(t, None))
                pel = r.array("point_element", shape=(vmp.shape[1],), kind="i")
            return cls(
                frames, r.array("time_s", shape=(t,)), vm, vmv, r.array("cauchy_tet", shape=(t, m, 3, 3)),
                r.array("internal_forces", shape=(t, vmv.shape[1], 3)),
                r.array("tet_region", shape=(m,), kind="i"), json.loads(r.attr("region_names")),
                str(r.attr("material_model")), vmp, pel,
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
    if kind == "adapt":  # `rsl info adapt.partial.h5` shows an unfinished run as it is
        return ARTEFACT_TYPES[kind].load(path, allow_partial=True)
    return ARTEFACT_TYPES[kind].load(path)
