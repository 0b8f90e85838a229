"""The layering of docs/architecture.md, checked on the source: every import (module level, inside
functions, importlib.import_module("...")) parsed with ast; rotation code only in the chosen helpers."""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from stages.registry import STAGES

ROOT = Path(__file__).resolve().parents[1]
STAGES_PACKAGE = "stages.steps"  # every stage module lives here (tested below against the registry)
ENGINES = ("stages.sim", "stages.subspace", "stages.render", "stages.vision")
DOMAIN = ("stages.domain", "stages.errors")
IO_PACKAGES = ("h5py", "rich", "typer", "click")
HEAVY = ("jax", "torch", "numba", "cv2", "h5py", "rich", "typer", "click", "equinox", "optax")

# Edges that break the rule today, each with what removes it (docs/architecture.md, "what remains").
# Empty: the last one (sim/meshgen.mesh_artefact building a MeshArtefact) moved to stages/artefacts.py.
KNOWN_EXCEPTIONS: set[tuple[str, str]] = set()


def _modules() -> dict[str, Path]:
    out = {}
    for p in sorted(list((ROOT / "stages").rglob("*.py")) + list((ROOT / "rsl_cli").rglob("*.py"))):
        parts = p.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = p
    return out


MODULES = _modules()


def imports_of(name: str, path: Path) -> list[tuple[str, int]]:
    """(imported module, line) for every import in ``path``: top level, function-local, relative, and the
    string argument of importlib.import_module(...)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.append((mod, node.lineno))
            out += [(f"{mod}.{a.name}", node.lineno) for a in node.names if f"{mod}.{a.name}" in MODULES]
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant) \
                and isinstance(node.args[0].value, str):
            fn = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            if fn == "import_module" and node.args[0].value.startswith(("stages", "rsl_cli")):
                out.append((node.args[0].value, node.lineno))
    return out


def _under(mod: str, prefixes) -> bool:
    return any(mod == p or mod.startswith(p + ".") for p in prefixes)


def layer(mod: str) -> int:
    """0 domain, 1 engines (physics, rendering, vision), 2 I/O and helpers, 3 stages, 4 the CLI."""
    if _under(mod, DOMAIN):
        return 0
    if _under(mod, ENGINES):
        return 1
    if _under(mod, (STAGES_PACKAGE,)):
        return 3
    if _under(mod, ("rsl_cli",)):
        return 4
    return 2  # stages.artefacts, stages.capture and the helpers beside the stages


def _violations() -> list[str]:
    bad = []
    for name, path in MODULES.items():
        for mod, line in imports_of(name, path):
            where = f"{path.relative_to(ROOT)}:{line} imports {mod}"
            if (name, mod) in KNOWN_EXCEPTIONS or (name, mod.rpartition(".")[0]) in KNOWN_EXCEPTIONS:
                continue
            if mod.startswith(("stages", "rsl_cli")) and mod != "stages":
                if layer(mod) > layer(name):
                    bad.append(f"{where}: layer {layer(name)} may not import layer {layer(mod)}")
                if layer(name) == 3 and layer(mod) == 3 and mod != name:
                    bad.append(f"{where}: a stage imports another stage")
            top = mod.split(".")[0]
            if layer(name) == 1 and top in IO_PACKAGES:
                bad.append(f"{where}: physics/rendering/vision touch no files, HDF5 or console")
            if layer(name) == 0 and top in HEAVY:
                bad.append(f"{where}: the domain layer is pure (numpy, scipy, stdlib)")
    return bad


def test_every_registered_stage_is_in_the_stages_package() -> None:
    assert all(s.module.startswith(STAGES_PACKAGE + ".") for s in STAGES)
    assert {s.module for s in STAGES} == {n for n in MODULES if n.startswith(STAGES_PACKAGE + ".")}


def test_import_graph_follows_the_layers() -> None:
    assert _violations() == []


def test_known_exceptions_still_exist() -> None:
    """An exception that no longer happens must leave KNOWN_EXCEPTIONS (so the list only shrinks)."""
    edges = {(n, m) for n, p in MODULES.items() for m, _ in imports_of(n, p)}
    assert KNOWN_EXCEPTIONS <= edges


def test_the_checker_sees_violations(tmp_path: Path) -> None:
    """The checker itself: a function-local upward import and an import_module string are seen."""
    p = tmp_path / "x.py"
    p.write_text("def f():\n    from stages.steps.adapt import run\n\nst = importlib.import_module('stages.capture')\n")
    got = imports_of("stages.sim.x", p)
    assert ("stages.steps.adapt", 2) in got and ("stages.capture", 4) in got
    assert layer("stages.sim.x") == 1 and layer("stages.steps.adapt") == 3 and layer("stages.domain.controls") == 0
    assert layer("stages.capture") == 2 and layer("rsl_cli.app") == 4


# --------------------------------------------------------------------------- rotations in one place
ROTATION_HOME = "stages/domain/rotations.py"
# Differentiable or compiled twins that must stay where they are (tests/test_domain_rotations.py holds them
# to the scipy helpers): (file, function).
ROTATION_TWINS = {
    ("stages/sim/potential.py", "_quat_matrix"),  # JAX, differentiated through obstacle poses
    ("stages/render/gaussians.py", "quat_to_rotmat"),  # torch, differentiated through Gaussian rotations
    ("stages/render/gaussians.py", "rotmat_to_quat"),  # numpy; delegates to stages.domain.rotations
    ("stages/render/bind_project.py", "_rotmat"),  # numba kernel of the fused bind+project
}
ROTATION_NAME = re.compile(r"quat|rotvec|rodrigues|axis_angle|slerp|euler_ang|rotmat|rot_matrix|rotation_matrix", re.I)
QUAT_FORMULA = re.compile(r"1\s*-\s*2\s*\*\s*\(\s*\w\s*\*\s*\w\s*\+\s*\w\s*\*\s*\w\s*\)")


def _python_files() -> list[Path]:
    return sorted(p for d in ("stages", "rsl_cli", "bench") for p in (ROOT / d).rglob("*.py"))


@pytest.mark.parametrize("path", _python_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_rotation_code_outside_the_helpers(path: Path) -> None:
    rel = str(path.relative_to(ROOT))
    if rel == ROTATION_HOME:
        return
    src = path.read_text(encoding="utf-8")
    assert "spatial.transform" not in src, f"{rel}: use stages.domain.rotations instead of scipy Rotation directly"
    tree = ast.parse(src)
    defs = {n.name: n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
    own = [name for name in defs if ROTATION_NAME.search(name) and (rel, name) not in ROTATION_TWINS]
    assert own == [], f"{rel} defines rotation code {own}; use stages.domain.rotations"
    for m in QUAT_FORMULA.finditer(src):
        line = src.count("\n", 0, m.start()) + 1
        inside = [n for n, d in defs.items() if d.lineno <= line <= (d.end_lineno or d.lineno)]
        assert any((rel, n) in ROTATION_TWINS for n in inside), f"{rel}:{line}: a quaternion→matrix formula"


# --------------------------------------------------------------------------- pure layers
FILE_CALLS = {"open", "read_text", "write_text", "read_bytes", "write_bytes", "mkdir", "unlink", "rename"}


def _calls(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = set()
    for n in ast.walk(tree):
        if isinstance(n, ast.Call):
            out.add(n.func.attr if isinstance(n.func, ast.Attribute) else getattr(n.func, "id", ""))
    return out


@pytest.mark.parametrize("name", [n for n in MODULES if layer(n) <= 1], ids=str)
def test_domain_and_engines_neither_print_nor_touch_files(name: str) -> None:
    calls = _calls(MODULES[name])
    assert "print" not in calls, f"{name} prints"
    if layer(name) == 0:
        assert not calls & FILE_CALLS, f"{name} touches files: {sorted(calls & FILE_CALLS)}"
