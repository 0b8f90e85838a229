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

from stages.artefacts import KIND_FILES, ArtefactError, _jsonable, file_sha256, read_provenance

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


def input_changes(inputs: list[dict], hashes: dict[str, str] | None = None) -> list[str]:
    """Reasons (one per input) why recorded inputs no longer match the files on disk; [] if all match.

    ``hashes`` caches path -> sha256 across calls.
    """
    hashes = {} if hashes is None else hashes
    reasons = []
    for item in inputs:
        p = Path(str(item.get("path", "")))
        if not p.is_file():
            reasons.append(f"input {p} is missing")
            continue
        key = str(p)
        if key not in hashes:
            hashes[key] = file_sha256(p)
        if hashes[key] != item.get("sha256"):
            reasons.append(f"input {p.name} changed")
    return reasons


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
    reasons = input_changes(inputs, hashes)
    return ArtefactState(kind, path, STALE if reasons else OK, reasons, str(prov.get("created", "")),
                         prov.get("config") if isinstance(prov.get("config"), dict) else {}, inputs)


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
