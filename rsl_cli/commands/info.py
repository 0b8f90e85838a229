"""`rsl info FILE.h5`: an artefact's kind, provenance and datasets; `rsl info CAPTURE`: a capture folder checked."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import typer

from rich.markup import escape

from rsl_cli.console import out
from stages.errors import RslError

ORDER = 90

_ROOT_KEYS = ("rsl_kind", "schema_version", "rsl_version", "created", "config", "inputs")


def register(app: typer.Typer) -> None:
    @app.command("info", help="Kind, provenance (config and hashed inputs) and datasets with shapes of an "
                              "artefact file; given a capture folder, reads and checks all of it.")
    def _cmd(
        path: Path = typer.Argument(..., help="An artefact file (WS/mesh.h5, ...) or a capture folder."),
        as_json: bool = typer.Option(False, "--json", help="Print everything as one JSON object."),
        check: bool = typer.Option(True, "--check/--no-check",
                                   help="Validate the artefact fully (kind, version, shapes, finite values)."),
    ) -> None:
        if path.is_dir():
            _capture_info(path, as_json)
        else:
            _artefact_info(path, as_json, check)

    register_docs(app)


def _artefact_info(path: Path, as_json: bool, check: bool) -> None:
    from stages.artefacts import ARTEFACT_TYPES, KIND_FILES, describe, load_any  # h5py: loaded on use

    d = describe(path)
    attrs = d["attrs"]
    if not attrs.get("rsl_kind"):
        raise RslError(f"{path}: not an rsl artefact (no 'rsl_kind' attribute).")
    if check:
        # A file with a workspace name (mesh.h5, ...) must hold that kind, as the stages expect.
        expected = {f: k for k, f in KIND_FILES.items()}.get(path.name)
        ARTEFACT_TYPES[expected].load(path) if expected else load_any(path)
    if as_json:
        out(json.dumps({"path": d["path"], "attrs": attrs,
                        "datasets": [{"name": n, "shape": list(s), "dtype": t} for n, s, t in d["datasets"]]},
                       indent=1, default=str), markup=False)
        return
    out(f"[bold]{escape(str(path))}[/]  kind [cyan]{escape(str(attrs.get('rsl_kind')))}[/]  "
        f"schema {escape(str(attrs.get('schema_version')))}  rsl {escape(str(attrs.get('rsl_version')))}  "
        f"created {escape(str(attrs.get('created')))}")
    try:
        extra = json.loads(attrs.get("extra", "{}")) if isinstance(attrs.get("extra"), str) else {}
    except ValueError:
        extra = {}
    if isinstance(extra, dict) and "status" in extra:  # an adapt run: complete | interrupted | failed
        out(f"status {extra['status']}" + ("" if extra["status"] == "complete" else
                                           " (unfinished: downstream stages refuse it)"), markup=False)
    config = attrs.get("config") or {}
    if config:
        out("[bold]config[/]")
        for k, v in config.items():
            out(f"  {k} = {json.dumps(v)}", markup=False)
    inputs = attrs.get("inputs") or []
    out(f"[bold]inputs[/] ({len(inputs)})")
    for item in inputs:
        base = f"  (in the {item['base']} folder)" if item.get("base") else ""
        files = f"  {item['files']} files" if "files" in item else ""
        out(f"  {item.get('path')}  sha256 {str(item.get('sha256', ''))[:12]}…{files}{base}", markup=False)
    other = {k: v for k, v in attrs.items() if k not in _ROOT_KEYS}
    if other:
        out("[bold]attributes[/]")
        for k, v in other.items():
            text = v if isinstance(v, str) else json.dumps(v, default=str)
            out(f"  {k} = {text if len(text) <= 200 else text[:200] + '…'}", markup=False)
    out(f"[bold]datasets[/] ({len(d['datasets'])})")
    for name, shape, dtype in d["datasets"]:
        out(f"  {name:<32} {str(shape):<20} {dtype}", markup=False)


def _capture_info(root: Path, as_json: bool) -> None:
    """Read every part of a capture folder (capture.toml, controls, cameras, frames, markers) and list it."""
    from stages.capture import load_capture, read_cameras_json

    cap = load_capture(root)
    controls = cap.controls()
    info: dict = {
        "capture": str(root), "name": cap.name, "fps": cap.fps, "gravity": cap.gravity.tolist(),
        "mesh": str(cap.mesh_path), "density": cap.density, "material": cap.material.__dict__,
        "regions": {k: str(v) for k, v in cap.region_meshes().items()},
        "cameras": cap.camera_names,
        "frames": cap.frame_count() if cap.camera_names else 0,
        "known_cameras": [c.name for c in read_cameras_json(cap.cameras_json)] if cap.cameras_json.exists() else [],
        "calibration_views": {c: len(v) for c, v in cap.calib_views().items()},
        "controls": {"handles": [h.name for h in controls.handles], "loads": [ld.name for ld in controls.loads],
                     "obstacles": [f"{o.name} ({o.shape})" for o in controls.obstacles],
                     "frames": controls.n_frames, "friction": controls.friction},
    }
    markers = cap.markers()
    info["markers"] = None if markers is None else list(markers.shape)
    info["truth"] = cap.truth_dir.is_dir()
    if as_json:
        out(json.dumps(info, indent=1, default=str), markup=False)
        return
    out(f"[bold]{escape(str(root))}[/]  capture [cyan]{escape(str(cap.name))}[/]  {cap.fps:g} fps")
    for key, value in info.items():
        if key not in ("capture", "name", "fps"):
            out(f"  {key:<18} {json.dumps(value, default=str)}", markup=False)


def register_docs(app: typer.Typer) -> None:
    """A hidden command that writes the CLI reference (docs/cli.md) from the --help texts."""

    @app.command("help-markdown", hidden=True, help="Print the reference of every command as Markdown.")
    def _docs() -> None:
        import click  # typer vendors its own click: this one loads only for help-markdown

        root = typer.main.get_command(app)
        ctx = click.Context(root, info_name="rsl")
        lines = ["# Command-line reference", "",
                 "Generated from the `--help` texts (`rsl help-markdown > docs/cli.md`); the option help of "
                 "each stage is the docstring of its Config field, and the defaults are the Config's.", "",
                 "Global options, given before the command: `--quiet/-q` (no progress bars or info lines), "
                 "`--verbose/-v` (tracebacks on errors).  A stage reads its inputs from the workspace `-w WS`, "
                 "writes one artefact there (docs/artefacts.md) and ends with one summary line; bad input ends "
                 "with one red sentence naming the file and exit code 1.", "",
                 "```", "rsl run CAPTURE -w WS                      # every stage, skipping what is up to date",
                 "rsl run CAPTURE -w WS --until tetrahedralize --set tetrahedralize.max_tets=2000",
                 "rsl status -w WS                           # what exists, what is stale and why",
                 "rsl info WS/mesh.h5                        # kind, provenance, datasets",
                 "rsl info CAPTURE                           # check a capture folder", "```", ""]
        for name in root.list_commands(ctx):
            cmd = root.get_command(ctx, name)
            if cmd is None or cmd.hidden:
                continue
            usage = " ".join(["[OPTIONS]"] + [p.name.upper() for p in cmd.params if p.param_type_name == "argument"])
            lines += [f"## rsl {name}", "", f"`rsl {name} {usage}`", "", " ".join((cmd.help or "").split()), ""]
            rows = []
            for p in cmd.params:
                if p.param_type_name == "argument":
                    rows.append((p.name.upper(), getattr(p, "help", "") or "", ""))
                elif not p.hidden and p.name != "help":
                    flags = ", ".join(f"`{o}`" for o in p.opts + p.secondary_opts)
                    default = "" if p.required or p.default in (None, ()) else f"`{p.default}`"
                    choices = getattr(getattr(p, "type_descriptor", None), "choices", None)  # Literal[...] fields
                    one_of = f" One of: {', '.join(f'`{c}`' for c in choices)}." if choices else ""
                    rows.append((flags, (p.help or "") + one_of, default))
            if rows:
                lines += ["| argument / option | meaning | default |", "| --- | --- | --- |"]
                lines += [f"| {a} | {' '.join(h.split()).replace('|', chr(92) + '|')} | {d} |" for a, h, d in rows]
                lines.append("")
        sys.stdout.write("\n".join(lines) + "\n")  # plain text: no rich markup in a Markdown file
