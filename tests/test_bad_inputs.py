"""Bad inputs through the real CLI: one clear sentence naming the file, exit code ≠ 0, no artefact left behind.

Every case runs `rsl_cli.app.main()` (the `rsl` entry point) in a child process.  To pay the
CLI's start-up (which imports every stage) once rather than per case, the cases run one
after another in a single child process (`run_batch`); `test_one_case_in_its_own_process`
runs one case through the fixture `rsl` exactly as a shell would.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Callable

import h5py
import numpy as np
import pytest
import trimesh

from stages.artefacts import SCHEMA_VERSION, CamerasArtefact, MeshArtefact
from stages.capture import write_image
from test_artefacts import make_all  # tests/ is on sys.path (rootdir-relative imports)

GOOD_TOML = """[capture]
name = "bad"
cameras = ["a", "b"]
[object]
mesh = "object.mesh"
density = 1000.0
"""


def _capture(root: Path, sample_data: Path) -> Path:
    root.mkdir()
    shutil.copy(sample_data / "bar" / "object.mesh", root / "object.mesh")
    shutil.copy(sample_data / "bar" / "controls.json", root / "controls.json")
    (root / "capture.toml").write_text(GOOD_TOML)
    return root


# Each case breaks a good capture; the message must contain `expect` and name the file `names`.
def _toml(text: str) -> Callable[[Path], None]:
    return lambda r: (r / "capture.toml").write_text(text)


def _controls(data: object) -> Callable[[Path], None]:
    return lambda r: (r / "controls.json").write_text(data if isinstance(data, str) else json.dumps(data))


def _medit(v: list, t: list) -> Callable[[Path], None]:
    def f(r: Path) -> None:
        import meshio

        meshio.write(str(r / "object.mesh"), meshio.Mesh(np.array(v, float) * 0.1, [("tetra", np.array(t))]),
                     file_format="medit")
    return f


def _open_surface(r: Path) -> None:
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    s.update_faces(s.vertices[s.faces].mean(1)[:, 2] < 0.035)
    s.export(r / "object.obj")
    (r / "capture.toml").write_text(GOOD_TOML.replace("object.mesh", "object.obj"))


def _frames(counts: dict[str, int]) -> Callable[[Path], None]:
    def f(r: Path) -> None:
        for cam, n in counts.items():
            for i in range(n):
                write_image(r / "frames" / cam / f"{i:06d}.png", np.zeros((4, 4, 3), np.uint8))
    return f


def _markers(rows: str, header: str = "frame,marker,x,y,z") -> Callable[[Path], None]:
    """A markers.csv (with frames for both cameras, which `rsl info` reads first)."""
    def f(r: Path) -> None:
        _frames({"a": 2, "b": 2})(r)
        (r / "markers.csv").write_text(f"{header}\n{rows}")
    return f


def _open_region(r: Path) -> None:
    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    box.update_faces(np.arange(12) < 8)
    (r / "regions").mkdir()
    box.export(r / "regions" / "soft.obj")


_DRIVER = r"""
import contextlib, io, json, sys
from rsl_cli import app
argv_file, results_file = sys.argv[1], sys.argv[2]
results = []
for argv in json.load(open(argv_file)):
    err, out = io.StringIO(), io.StringIO()
    sys.argv = ["rsl", *argv]
    code = 0
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            app.main()
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    results.append({"returncode": code, "stderr": err.getvalue(), "stdout": out.getvalue()})
json.dump(results, open(results_file, "w"))
"""


def run_batch(commands: list[list], folder: Path) -> list[subprocess.CompletedProcess]:
    """Run several `rsl ...` command lines in one child process; a CompletedProcess for each."""
    (folder / "argv.json").write_text(json.dumps([[str(a) for a in c] for c in commands]))
    env = dict(os.environ, JAX_ENABLE_X64="1", JAX_PLATFORMS="cpu", COLUMNS="200")
    proc = subprocess.run([sys.executable, "-c", _DRIVER, folder / "argv.json", folder / "results.json"],
                          capture_output=True, text=True, env=env, cwd=Path(__file__).resolve().parents[1])
    assert proc.returncode == 0, proc.stderr
    return [subprocess.CompletedProcess(c, r["returncode"], r["stdout"], r["stderr"])
            for c, r in zip(commands, json.loads((folder / "results.json").read_text()))]


TET = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 1]]
CAPTURE_CASES = {
    "missing capture.toml": (lambda r: (r / "capture.toml").unlink(), "tetrahedralize",
                             "file not found; every capture folder needs a capture.toml", "capture.toml"),
    "malformed capture.toml": (_toml("[capture\nname = 1"), "tetrahedralize", "not valid TOML", "capture.toml"),
    "unknown material model": (_toml(GOOD_TOML + "[material]\nmodel = 'mooney'\n"), "tetrahedralize",
                               "'material.model' should be one of stable_neohookean, yeoh, linear", "capture.toml"),
    "poisson out of range": (_toml(GOOD_TOML + "[material]\npoisson = 0.7\n"), "tetrahedralize",
                             "'material.poisson' should lie in [0, 0.5)", "capture.toml"),
    "missing mesh file": (lambda r: (r / "object.mesh").unlink(), "tetrahedralize",
                          "mesh file named by capture.toml 'object.mesh' not found", "object.mesh"),
    "unreadable mesh": (lambda r: (r / "object.mesh").write_text("MeshVersionFormatted 2\nDimension 3\nVertices\nxyz\n"),
                        "tetrahedralize", "cannot read the tet mesh", "object.mesh"),
    "mesh without tets": (_medit(TET, np.zeros((0, 4), int)), "tetrahedralize", "holds no tetrahedra",
                          "object.mesh"),
    "non-watertight surface": (_open_surface, "tetrahedralize", "the surface is not watertight", "object.obj"),
    "inverted tet": (_medit(TET + [[0.2, 0.2, 0.5]], [[0, 1, 2, 3], [0, 2, 1, 4]]), "tetrahedralize",
                     "overlap across a shared face: one of them is inverted", "object.mesh"),
    "degenerate tet": (_medit(TET + [[0.3, 0.3, 0.0]], [[0, 1, 2, 3], [0, 2, 1, 4]]), "tetrahedralize",
                       "1 degenerate tets", "object.mesh"),
    "controls.json with a wrong type": (_controls({"handles": {"name": "left"}}), "tetrahedralize",
                                        "'handles' should be a list, found dict", "controls.json"),
    "controls.json not JSON": (_controls("{handles: []"), "tetrahedralize", "not valid JSON", "controls.json"),
    "handle box that selects no vertex": (
        _controls({"handles": [{"name": "far", "select": {"box": [[5, 5, 5], [6, 6, 6]]}}]}), "tetrahedralize",
        "handle 'far' selects no vertex of the mesh", "controls.json"),
    "handle pose with a wrong length": (
        _controls({"handles": [{"name": "h", "select": {"ids": [0]}, "poses": [[0, 0, 0, 1]]}]}), "tetrahedralize",
        "'handles[0].poses[0]' should be a list of 7 finite numbers", "controls.json"),
    "region mesh not closed": (_open_region, "tetrahedralize", "region mesh is not closed", "soft.obj"),
    "frames of unequal count per camera": (_frames({"a": 3, "b": 2}), "info",
                                           "cameras hold unequal frame counts (a: 3, b: 2)", "frames"),
    "markers.csv with a non-finite value": (_markers("0,0,1,2,3\n0,1,1,nan,3\n"), "info",
                                            "line 3 should hold 5 finite values", "markers.csv"),
    "markers.csv with frames not 0..T-1": (_markers("0,0,1,2,3\n2,0,1,2,3\n"), "info",
                                           "frames should run 0..T-1", "markers.csv"),
    "markers.csv with a marker never observed": (_markers("0,0,1,2,3\n0,1,,,\n1,0,1,2,3\n"), "info",
                                                 "marker(s) 1 are never observed", "markers.csv"),
    "markers.csv with no marker at frame 0": (_markers("0,0,,,\n1,0,1,2,3\n1,1,1,2,3\n"), "info",
                                              "no marker is observed at frame 0", "markers.csv"),
    "markers.csv with a wrong header": (_markers("0,0,1,2,3\n", header="frame,id,x,y,z"), "info",
                                        "header should be 'frame,marker,x,y,z'", "markers.csv"),
    "frames with a gap": ((lambda r: (_frames({"a": 2, "b": 2})(r), (r / "frames" / "b" / "000000.png").unlink())),
                          "info", "frame 0 is missing", "frames/b"),
}


def _capture_case(case: str, folder: Path, sample_data: Path) -> list:
    breaker, command, _, _ = CAPTURE_CASES[case]
    root = _capture(folder / "cap", sample_data)
    breaker(root)
    return [command, root, "-w", folder / "ws"] if command != "info" else [command, root]


@pytest.fixture(scope="module")
def capture_results(tmp_path_factory, sample_data: Path) -> dict:
    base = tmp_path_factory.mktemp("bad_captures")
    cases = sorted(CAPTURE_CASES)
    commands = []
    for i, case in enumerate(cases):
        (base / str(i)).mkdir()
        commands.append(_capture_case(case, base / str(i), sample_data))
    procs = run_batch(commands, base)
    return {case: (proc, base / str(i) / "ws") for i, (case, proc) in enumerate(zip(cases, procs))}


@pytest.mark.parametrize("case", sorted(CAPTURE_CASES))
def test_bad_capture(case: str, capture_results: dict) -> None:
    _, _, expect, names = CAPTURE_CASES[case]
    proc, ws = capture_results[case]
    err = " ".join(proc.stderr.split())  # undo rich's line wrapping
    assert proc.returncode != 0, proc.stderr
    assert "error:" in err and expect in err, err
    assert names in err, err
    assert "Traceback" not in proc.stderr
    assert not (ws / "mesh.h5").exists()
    assert not ws.exists() or not [p for p in ws.iterdir() if p.name.endswith(".tmp")]


def _artefact(tmp_path: Path, kind: str = "mesh", name: str | None = None) -> Path:
    path = tmp_path / (name or f"{kind}.h5")
    make_all(np.random.default_rng(0))[kind].save(path)
    return path


def _set_nan(path: Path) -> None:
    with h5py.File(path, "a") as f:
        v = f["vertices"][()]
        v[0, 0] = np.nan
        f["vertices"][...] = v


def _future(path: Path) -> None:
    with h5py.File(path, "a") as f:
        f.attrs["schema_version"] = SCHEMA_VERSION + 3


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 3])


ARTEFACT_CASES = {
    "wrong artefact kind": ("cameras", "mesh.h5", None, "is a 'cameras' artefact, expected 'mesh'"),
    "future schema version": ("mesh", None, _future, f"schema version {SCHEMA_VERSION + 3} is newer"),
    "NaN in a dataset": ("mesh", None, _set_nan, "dataset 'vertices' holds 1 NaN or infinite values"),
    "truncated HDF5": ("snapshots", None, _truncate, "not a readable HDF5 file"),
    "not HDF5 at all": ("mesh", None, lambda p: p.write_text("hello"), "not a readable HDF5 file"),
    "missing artefact": ("mesh", None, lambda p: p.unlink(), "file not found"),
}


@pytest.fixture(scope="module")
def artefact_results(tmp_path_factory, sample_data: Path) -> dict:
    base = tmp_path_factory.mktemp("bad_artefacts")
    cases = sorted(ARTEFACT_CASES)
    paths = []
    for i, case in enumerate(cases):
        kind, name, breaker, _ = ARTEFACT_CASES[case]
        (base / str(i)).mkdir()
        path = _artefact(base / str(i), kind, name)
        if breaker:
            breaker(path)
        paths.append(path)
    good = _artefact(base, "cameras")
    extra = _status_and_run_commands(base, sample_data)
    procs = run_batch([["info", p] for p in paths] + [["info", good]] + extra, base)
    out = {case: (proc, path) for case, proc, path in zip(cases, procs, paths)}
    out["good"] = (procs[len(paths)], good)
    out["status/run"] = (procs[len(paths) + 1:], base / "ws_run")
    return out


@pytest.mark.parametrize("case", sorted(ARTEFACT_CASES))
def test_bad_artefact(case: str, artefact_results: dict) -> None:
    _, _, _, expect = ARTEFACT_CASES[case]
    proc, path = artefact_results[case]
    err = " ".join(proc.stderr.split())
    assert proc.returncode != 0 and expect in err and path.name in err, err
    assert "Traceback" not in proc.stderr


def _status_and_run_commands(base: Path, sample_data: Path) -> list[list]:
    ws = base / "ws_run"
    return [
        ["status", "-w", base / "nowhere"],
        ["run", sample_data / "bar", "-w", ws, "--until", "mesh"],
        ["run", sample_data / "bar", "-w", ws, "--only", "tetrahedralize", "--set", "tetrahedralize.edge=1"],
        ["run", sample_data / "bar", "-w", ws, "--only", "tetrahedralize", "--set", "tetrahedralize.max_tets=many"],
        ["run", base / "nocapture", "-w", ws, "--only", "tetrahedralize"],
    ]


def test_status_and_run_errors(artefact_results: dict) -> None:
    procs, ws = artefact_results["status/run"]
    errs = [" ".join(p.stderr.split()) for p in procs]
    assert all(p.returncode != 0 for p in procs), errs
    assert "nowhere: workspace folder not found" in errs[0]
    assert "unknown stage 'mesh'" in errs[1] and "tetrahedralize" in errs[1]
    assert "TetrahedralizeConfig has no option 'edge'" in errs[2]
    assert "--set tetrahedralize.max_tets=many: cannot read the value as int" in errs[3]
    assert "stage 'tetrahedralize' failed" in errs[4] and "nocapture: capture folder not found" in errs[4]
    assert not (ws / "mesh.h5").exists()


def test_one_case_in_its_own_process(rsl, sample_data: Path, tmp_path: Path) -> None:
    root = _capture(tmp_path / "cap", sample_data)
    CAPTURE_CASES["handle box that selects no vertex"][0](root)
    proc = rsl("tetrahedralize", root, "-w", tmp_path / "ws")
    err = " ".join(proc.stderr.split())
    assert proc.returncode == 1 and f"{root / 'controls.json'}: handle 'far' selects no vertex" in err


def test_good_artefact_passes_info(artefact_results: dict) -> None:
    """The same checks accept a good file (so the cases above fail for the reason they name)."""
    proc, path = artefact_results["good"]
    assert proc.returncode == 0, proc.stderr
    assert "kind cameras" in proc.stdout and "cameras/cam0/K" in proc.stdout
    assert isinstance(CamerasArtefact.load(path), CamerasArtefact)
    assert MeshArtefact.kind == "mesh"
