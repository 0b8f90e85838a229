"""The workspace folder: where each artefact lives and whether it is up to date.

An artefact is *stale* when one of the input files recorded in its ``inputs``
attribute is missing or its current sha256 differs from the recorded hash, or
(for ``rsl run``) when the config it was made with differs from the config a
stage would run with now.  A file that cannot be read as an artefact is
*invalid*.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import json
import os
import tempfile

from stages.artefacts import (KIND_FILES, ArtefactError, HashCache, _jsonable, clean_stale_temps, read_provenance,
                              resolve_input, start_clock)
from stages.errors import RslError

MISSING, OK, STALE, INVALID = "missing", "up to date", "stale", "invalid"


def artefact_path(workspace: str | Path, kind: str) -> Path:
    """WS/<file of kind>, e.g. WS/mesh.h5."""
    if kind not in KIND_FILES:
        raise KeyError(f"unknown artefact kind {kind!r}")
    return Path(workspace) / KIND_FILES[kind]


@dataclass
class ArtefactState:
    """What ``rsl status`` says about one artefact."""

    kind: str
    path: Path
    state: str  # MISSING | OK | STALE | INVALID
    reasons: list[str] = field(default_factory=list)
    created: str | None = None
    config: dict | None = None
    inputs: list[dict] = field(default_factory=list)


def input_changes(inputs: list[dict], hashes: dict[str, str] | None = None, artefact: Path | None = None,
                  attrs: dict | None = None, cache: HashCache | None = None) -> list[str]:
    """Reasons (one per input) why recorded inputs no longer match the files on disk; [] if all match.

    Relative entries are resolved from the artefact's folder (workspace files) or its capture folder; a folder
    entry (a camera's frames) is compared by the hash over its files.  ``hashes`` caches path -> sha256 across
    calls, ``cache`` the hashes of unchanged files across runs (WS/.rsl_hashes.json).
    """
    hashes = {} if hashes is None else hashes
    cache = cache or HashCache()
    reasons = []
    for item in inputs:
        if not isinstance(item, dict):
            continue
        p = resolve_input(item, artefact, attrs or {}) if artefact is not None else Path(str(item.get("path", "")))
        shown = item.get("path", p)
        is_dir = "files" in item
        if not (p.is_dir() if is_dir else p.is_file()):
            reasons.append(f"input {shown} is missing")
            continue
        key = str(p.resolve())
        if key not in hashes:
            try:
                hashes[key] = cache.entry_sha256(p)
            except OSError as e:
                reasons.append(f"input {shown} cannot be read ({e.strerror or e})")
                continue
        if hashes[key] != item.get("sha256"):
            what = f"{shown} (its files)" if is_dir else Path(str(shown)).name
            reasons.append(f"input {what} changed")
    return reasons


def adapt_status(attrs_or_extra: dict) -> str:
    """``complete`` | ``interrupted`` | ``failed`` of an adapt artefact ('complete' when it does not say)."""
    extra = attrs_or_extra.get("extra", attrs_or_extra)
    if isinstance(extra, str):
        try:
            extra = json.loads(extra)
        except ValueError:
            extra = {}
    return str((extra or {}).get("status", "complete")) if isinstance(extra, dict) else "complete"


def artefact_state(workspace: str | Path, kind: str, hashes: dict[str, str] | None = None) -> ArtefactState:
    """Exists? readable? inputs unchanged? (configs are compared by :func:`config_differences`)."""
    path = artefact_path(workspace, kind)
    if not path.exists():
        return ArtefactState(kind, path, MISSING)
    try:
        prov = read_provenance(path)
    except ArtefactError as e:
        return ArtefactState(kind, path, INVALID, [str(e)])
    found = prov.get("rsl_kind")
    if found != kind:
        return ArtefactState(kind, path, INVALID, [f"holds a {found!r} artefact, expected {kind!r}"])
    inputs = prov.get("inputs") or []
    if not isinstance(inputs, list):
        return ArtefactState(kind, path, INVALID, ["attribute 'inputs' is not a list"])
    if kind == "adapt" and adapt_status(prov) != "complete":
        return ArtefactState(kind, path, INVALID, [f"holds an unfinished ({adapt_status(prov)}) run, not a complete one"],
                             str(prov.get("created", "")), prov.get("config") or {}, inputs)
    cache = HashCache(workspace)
    reasons = input_changes(inputs, hashes, path, prov, cache)
    cache.save()
    return ArtefactState(kind, path, STALE if reasons else OK, reasons, str(prov.get("created", "")),
                         prov.get("config") if isinstance(prov.get("config"), dict) else {}, inputs)


def prepare_workspace(workspace: str | Path) -> Path:
    """Create the workspace if needed, check it is writable before any compute, and remove the temporary
    files a killed stage left (``.NAME.h5.PID.*.tmp``)."""
    ws = Path(workspace)
    try:
        ws.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise RslError(f"{ws}: cannot create the workspace folder ({e.strerror or e}).") from None
    if not ws.is_dir():
        raise RslError(f"{ws}: is not a folder; give a workspace folder with -w.")
    probe = ws / f".rsl_write_test.{os.getpid()}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise RslError(f"{ws}: the workspace is not writable ({e.strerror or e}); nothing was computed.") from None
    clean_stale_temps(ws)
    start_clock()
    return ws


def _norm(key: str, value: Any) -> Any:
    if key == "capture" and value not in (None, ""):
        return str(Path(str(value)).resolve())
    return value


def config_differences(stored: dict | None, config: Any, ignore: tuple[str, ...] = ()) -> list[str]:
    """Fields whose value in ``config`` (a dataclass) differs from the stored JSON config.

    The workspace field (the artefact lies in it by definition) and the fields in
    ``ignore`` are skipped; the capture folder is compared as a resolved path.
    """
    current = _jsonable(dataclasses.asdict(config)) if dataclasses.is_dataclass(config) else _jsonable(config)
    stored = stored or {}
    diffs = []
    for key in sorted(set(current) | set(stored)):
        if key == "workspace" or key in ignore:
            continue
        if key not in stored:
            diffs.append(f"option {key} is new")
        elif key not in current:
            diffs.append(f"option {key} no longer exists")
        elif _norm(key, stored[key]) != _norm(key, current[key]):
            diffs.append(f"{key} was {stored[key]!r}, now {current[key]!r}")
    return diffs


def write_text_atomic(path: Path, text: str) -> None:
    """Write a text file (JSON, HTML) under a temporary name in its folder, then rename it into place,
    readable by all (0644); a failure leaves the previous file as it was."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
