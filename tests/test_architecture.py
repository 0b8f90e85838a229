"""The layering of docs/architecture.md, checked on the source: every import (module level, inside
functions, importlib.import_module("...")) parsed with ast; rotation code only in the chosen helpers."""
from __future__ import annotations

import ast
import functools
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


# The observation models and the geometry they rest on, and the layer each must stay in (docs/architecture.md,
# "One image formation"): adapt, evaluate, export, report and the sweeps all reach them from layer 2 or 3.
OBSERVATION_MODEL = {
    "stages.render.image_loss": 1,  # ImageLoss: images (paper Eq. 7)
    "stages.sim.markers": 1,  # MarkerBinding, marker_loss: markers (paper Eq. 4)
    "stages.sim.locate": 1,  # point location in (P1 / P2) tets, used by ImageLoss.rebind
    "stages.parameters": 2,  # θ = (E, ν) ↔ p and Adam (optax)
    "stages.observations": 2,  # adapt's observations: frames, masks, background plates
}


def test_the_observation_model_lives_in_its_layers() -> None:
    assert {n: layer(n) for n in OBSERVATION_MODEL if n in MODULES} == OBSERVATION_MODEL
    assert "stages.adapt_loss" not in MODULES  # split into the modules above, no re-export shim


@functools.lru_cache(maxsize=None)
def _top_level_names(path: Path) -> set[str]:
    """Names a module binds at its top level (defs, classes, assignments, imports; inside if/try too)."""
    names: set[str] = set()

    def visit(body) -> None:
        for n in body:
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                names.add(n.name)
            elif isinstance(n, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
                for t in n.targets if isinstance(n, ast.Assign) else [n.target]:
                    names.update(e.id for e in ast.walk(t) if isinstance(e, ast.Name))
            elif isinstance(n, (ast.Import, ast.ImportFrom)):
                names.update((a.asname or a.name).split(".")[0] for a in n.names)
            elif isinstance(n, (ast.If, ast.Try, ast.With)):
                visit(n.body)
                visit(getattr(n, "orelse", []))
                for h in getattr(n, "handlers", []):
                    visit(h.body)
                visit(getattr(n, "finalbody", []))

    visit(ast.parse(path.read_text(encoding="utf-8")).body)
    return names


def _unresolved(path: Path, name: str) -> list[str]:
    """Imports of stages / rsl_cli in ``path`` that name no module of the tree, or a name the module lacks."""
    bad = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.level:
            package = name if path.name == "__init__.py" else name.rpartition(".")[0]
            base = package.split(".")[: len(package.split(".")) - node.level + 1]
            mod, aliases = ".".join(base + ([node.module] if node.module else [])), node.names
        elif isinstance(node, ast.ImportFrom):
            mod, aliases = node.module or "", node.names
        elif isinstance(node, ast.Import):
            mod, aliases = None, node.names
        else:
            continue
        if mod is None:
            bad += [a.name for a in aliases if a.name.split(".")[0] in ("stages", "rsl_cli") and a.name not in MODULES]
            continue
        if mod.split(".")[0] not in ("stages", "rsl_cli"):
            continue
        if mod not in MODULES:
            bad.append(mod)
            continue
        defined = _top_level_names(MODULES[mod])
        bad += [f"{mod}.{a.name}" for a in aliases
                if a.name != "*" and f"{mod}.{a.name}" not in MODULES and a.name not in defined]
    return bad


def test_every_import_of_the_tree_resolves() -> None:
    """Every import of stages / rsl_cli in the library, the CLI, the tests and the benchmarks names a module that
    exists and a name it defines (a module moved or split leaves no stale import behind, even a function-local
    one that only a slow test or a benchmark would run)."""
    files = {**{p: n for n, p in MODULES.items()},
             **{p: p.stem for d in ("tests", "bench") for p in sorted((ROOT / d).rglob("*.py"))}}
    assert [f"{p.relative_to(ROOT)}: {b}" for p, n in files.items() for b in _unresolved(p, n)] == []


def test_the_checker_sees_violations(tmp_path: Path) -> None:
    """The checker itself: a function-local upward import and an import_module string are seen."""
    p = tmp_path / "x.py"
    p.write_text("def f():\n    from stages.steps.adapt import run\n\nst = importlib.import_module('stages.capture')\n")
    got = imports_of("stages.sim.x", p)
    assert ("stages.steps.adapt", 2) in got and ("stages.capture", 4) in got
    assert layer("stages.sim.x") == 1 and layer("stages.steps.adapt") == 3 and layer("stages.domain.controls") == 0
    assert layer("stages.capture") == 2 and layer("rsl_cli.app") == 4
    p.write_text("from stages.adapt_loss import ImageLoss\nfrom stages.sim.markers import bind_markers, nope\n"
                 "def f():\n    import stages.sim.gone\n    from stages.sim import markers, locate\n")
    assert _unresolved(p, "x") == ["stages.adapt_loss", "stages.sim.markers.nope", "stages.sim.gone"]


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


# A rotation matrix or an axis-angle quaternion written out by hand: [[1, 0, 0], [0, cos a, −sin a], ...] or
# [cos(a/2), sin(a/2), 0, 0].  The library, the benchmarks and the tests' helpers build them with
# stages.domain.rotations (axis_angle_matrix, rotvec_to_matrix); tests/test_domain_rotations.py is the
# independent oracle the helpers are held to.
HAND_ROTATION = re.compile(r"(?:np|math|jnp|torch)\.cos\((?P<a>[^()]+)\)\s*,\s*-\s*(?:np|math|jnp|torch)\.sin\((?P=a)\)"
                           r"|(?:np|math)\.cos\((?P<h>\w+) / 2\)\s*,\s*(?:0\s*,\s*)*(?:np|math)\.sin\((?P=h) / 2\)")


@pytest.mark.parametrize("path", _python_files() + sorted((ROOT / "tests").glob("*.py")),
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_no_rotation_matrix_written_by_hand(path: Path) -> None:
    if path.name in ("test_domain_rotations.py", "test_architecture.py"):
        return
    src = path.read_text(encoding="utf-8")
    lines = [src.count("\n", 0, m.start()) + 1 for m in HAND_ROTATION.finditer(src)]
    assert lines == [], f"{path.relative_to(ROOT)}:{lines}: a rotation written out; use stages.domain.rotations"


def test_the_hand_rotation_pattern_matches() -> None:
    assert HAND_ROTATION.search("R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])")
    assert HAND_ROTATION.search("q[0], q[1 + k] = np.cos(a / 2), np.sin(a / 2)")
    assert HAND_ROTATION.search("qy = np.array([np.cos(ry / 2), 0, np.sin(ry / 2), 0])")
    assert not HAND_ROTATION.search("y, z = y * np.cos(a) - z * np.sin(a), y * np.sin(a) + z * np.cos(a)")


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


# --------------------------------------------------------------------------- function-local imports
# Imports are ordinary module-level imports (issue 16).  An import inside a function must earn its place: it
# loads a package from LAZY that its module does not load at import time (so `rsl --help`, which imports
# every rsl_cli command module, and `rsl STAGE --help`, which imports the stage, stay light), or it would
# close an import cycle.  LAZY: heavy to import (JAX, torch, numba kernels, SciPy's big submodules,
# matplotlib, open3d, h5py, OpenCV, ...) or optional (SAM 2, pycolmap, ray, ezc3d, pytetwild, CHOLMOD), and
# click (typer vendors its own; the separate package serves only `rsl help-markdown`).
LAZY = ("jax", "numba", "equinox", "optax", "torch", "scipy.linalg", "scipy.sparse", "scipy.spatial",
        "scipy.optimize", "matplotlib", "open3d", "trimesh", "meshio", "pytetwild", "h5py", "cv2", "typer", "rich",
        "click", "sam2", "pycolmap", "ray", "ezc3d", "sksparse")
LAZY_IMPLIES = {"optax": ("jax",), "equinox": ("jax",)}  # importing the first loads the others


def _lazy_key(mod: str) -> str | None:
    keys = [k for k in LAZY if mod == k or mod.startswith(k + ".")]
    return max(keys, key=len) if keys else None


def _import_targets(node: ast.Import | ast.ImportFrom, name: str, path: Path) -> list[str]:
    """The module an import statement imports first (for ``from a import b``: a, or a.b when b is a module)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if node.level:
        package = (name if path.name == "__init__.py" else name.rpartition(".")[0]).split(".")
        mod = ".".join(package[: len(package) - node.level + 1] + ([node.module] if node.module else []))
    else:
        mod = node.module or ""
    return [mod] + [f"{mod}.{a.name}" for a in node.names if f"{mod}.{a.name}" in MODULES]


def _module_level_imports(name: str, path: Path) -> list[str]:
    """Modules imported when ``path`` is imported: top-level statements, inside top-level if/try too, but not
    under ``if TYPE_CHECKING``."""
    out: list[str] = []

    def visit(body) -> None:
        for n in body:
            if isinstance(n, (ast.Import, ast.ImportFrom)):
                out.extend(_import_targets(n, name, path))
            elif isinstance(n, ast.If) and "TYPE_CHECKING" not in ast.unparse(n.test):
                visit(n.body)
                visit(n.orelse)
            elif isinstance(n, ast.Try):
                visit(n.body)
                visit(n.orelse)
                visit(n.finalbody)
                for h in n.handlers:
                    visit(h.body)

    visit(ast.parse(path.read_text(encoding="utf-8")).body)
    return out


def _parents(mod: str) -> list[str]:
    parts = mod.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts) + 1)]


def _loads_from(imports: list[str]) -> tuple[frozenset[str], frozenset[str]]:
    """(modules of the tree, LAZY keys) that running these imports loads, following module-level imports."""
    seen: set[str] = set()
    keys: set[str] = set()
    todo = list(imports)
    while todo:
        mod = todo.pop()
        if mod.split(".")[0] in ("stages", "rsl_cli"):
            for p in _parents(mod):
                if p in MODULES and p not in seen:
                    seen.add(p)
                    todo += _module_level_imports(p, MODULES[p])
        elif (k := _lazy_key(mod)) is not None:
            keys.update((k, *LAZY_IMPLIES.get(k, ())))
    return frozenset(seen), frozenset(keys)


@functools.lru_cache(maxsize=None)
def _loads(mod: str) -> tuple[frozenset[str], frozenset[str]]:
    return _loads_from([mod])


def local_import_problems(name: str, path: Path) -> list[str]:
    """Function-local imports in ``path`` that load nothing from LAZY the module does not load already and close
    no import cycle: they belong at the top of the module."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    _, own = _loads_from([name, *_module_level_imports(name, path)])
    bad = []

    def visit(node, inside: bool) -> None:
        for ch in ast.iter_child_nodes(node):
            if inside and isinstance(ch, (ast.Import, ast.ImportFrom)):
                targets = _import_targets(ch, name, path)  # `from a import b`: a, and a.b when b is a module
                mods = frozenset().union(*(_loads(t)[0] for t in targets))
                keys = frozenset().union(*(_loads(t)[1] for t in targets))
                target = targets[-1]
                if not keys - own and name not in mods:
                    bad.append(f"{path.relative_to(ROOT) if path.is_relative_to(ROOT) else path.name}:{ch.lineno} "
                               f"imports {target} inside a function; it loads nothing heavy: import it at the top")
            visit(ch, inside or isinstance(ch, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    visit(tree, False)
    return bad


def test_function_local_imports_only_defer_heavy_packages_or_break_cycles() -> None:
    assert [b for n, p in MODULES.items() for b in local_import_problems(n, p)] == []


def test_the_local_import_checker_sees_light_imports(tmp_path: Path) -> None:
    p = tmp_path / "x.py"
    p.write_text("import numpy as np\n\n\ndef f():\n    import dataclasses\n    from stages.errors import RslError\n"
                 "    import torch\n    from stages.sim.scene import step\n    from scipy.spatial import cKDTree\n")
    got = local_import_problems("stages.x", p)
    assert [g.split(" imports ")[1].split()[0] for g in got] == ["dataclasses", "stages.errors"]
    p.write_text("import torch\n\n\ndef f():\n    import torch.nn\n    from stages.render.gaussians import quat_to_rotmat\n"
                 "    from stages.render import gaussians as g\n    from stages.sim import mesh\n")
    got = local_import_problems("stages.x", p)  # torch is loaded at the top already; gaussians adds numba
    assert [g.split(" imports ")[1].split()[0] for g in got] == ["torch.nn", "stages.sim.mesh"]
    # the cycle sim/mesh -> sim/quadrature -> sim/mesh is allowed (mesh imports quadrature inside a function)
    assert local_import_problems("stages.sim.mesh", MODULES["stages.sim.mesh"]) == []
    assert "stages.sim.mesh" in _loads("stages.sim.quadrature")[0]
