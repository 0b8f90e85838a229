"""Nothing silently wrong in `rsl adapt` and downstream (issue 14), through the real CLI.

A complete adapt.h5 is never replaced by a failed or interrupted run (that one goes to adapt.partial.h5, which
downstream stages refuse); an unreadable frame anywhere is an error naming the file; MP4 frames are read like
PNG folders; frames at another size than cameras.h5 are refused; a mesh.h5 from another capture, a renumbered
mesh with the old Gaussians or adapt.h5, an obstacle inside the object, and a far too soft E that collapses the
mesh each end with one sentence that says what to change.

One module fixture builds a tiny workspace (bar_synth's frames with the sample bar's tet mesh: tetrahedralize,
calibrate from cameras.json, a 300-Gaussian fit, a 3-frame markers adapt); the cases run in one child process.
"""
from __future__ import annotations

import json
import re
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest

from reliability import (SAMPLE, assert_one_sentence, batch, copy_capture, edit, flat, rsl_proc, tree_bytes)
from stages.capture import read_image, write_image

GROUPS = {"test_adapt_case": "rsl adapt: frames, meshes, obstacles, material",
          "test_failed_run_keeps_adapt_h5": "rsl adapt: unfinished runs never replace adapt.h5",
          "test_ctrl_c_keeps_adapt_h5": "rsl adapt: unfinished runs never replace adapt.h5",
          "test_downstream_refuses_partial": "rsl adapt: unfinished runs never replace adapt.h5",
          "test_downstream_takes_the_partial_run_when_asked": "rsl adapt: unfinished runs never replace adapt.h5",
          "test_ctrl_c_lost_in_compiled_code_still_stops_and_keeps_the_frames":
              "rsl adapt: unfinished runs never replace adapt.h5",
          "test_second_ctrl_c_during_the_save_does_not_abort_it": "rsl adapt: unfinished runs never replace adapt.h5",
          "test_a_frame_record_cut_half_way_is_dropped": "rsl adapt: unfinished runs never replace adapt.h5",
          "test_mp4_frames_are_read": "legal inputs are accepted (no false alarm)",
          "test_solve_guard_tolerates_a_sliver_but_not_a_collapse": "rsl adapt: frames, meshes, obstacles, material",
          "test_rotation_angle_small_angles": "arithmetic: rotation angle"}
LABELS = {"test_failed_run_keeps_adapt_h5": "a run that fails after some frames (the mesh collapses): adapt.h5 kept, "
                                            "the frames done in adapt.partial.h5",
          "test_ctrl_c_keeps_adapt_h5": "Ctrl-C of a non-follow run: adapt.h5 kept, the frames done in "
                                        "adapt.partial.h5, the sentence says so",
          "test_second_ctrl_c_during_the_save_does_not_abort_it": "a second Ctrl-C while adapt.partial.h5 is "
                                                                  "written: the write completes",
          "test_a_frame_record_cut_half_way_is_dropped": "Ctrl-C between the appends of one frame's record: "
                                                         "that frame is dropped, the others saved",
          "test_mp4_frames_are_read": "frames given as MP4 videos: the vision loss reads them"}

MARKERS = ["--space", "full", "--loss", "markers", "--window", "2"]
VISION = ["--space", "full", "--loss", "vision", "--window", "1", "--iters-per-frame", "1", "--frames", "0:2"]


def _syn(dst: Path) -> Path:
    cap = copy_capture(dst)
    shutil.copy(SAMPLE / "bar" / "object.mesh", cap / "object.mesh")
    edit(cap / "capture.toml", 'mesh = "object.obj"', 'mesh = "object.mesh"')
    return cap


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("adapt_base")
    cap, ws = _syn(root / "cap"), root / "ws"
    procs = batch([["tetrahedralize", cap, "-w", ws, "--no-preview", "--order", "1"], ["calibrate", cap, "-w", ws],
                   ["fit-gaussians", cap, "-w", ws, "--iterations", "5", "--gaussians", "300",
                    "--max-resolution", "64"],
                   ["adapt", cap, "-w", ws, *MARKERS, "--frames", "0:3"]], root / "setup")
    for p in procs:
        assert p.returncode == 0, p.stderr
    return cap, ws


def _copy(base: tuple[Path, Path], dst: Path) -> tuple[Path, Path]:
    cap, ws = base
    shutil.copytree(cap, dst / "cap")
    shutil.copytree(ws, dst / "ws")
    return dst / "cap", dst / "ws"


def _bad_png(name: str, data: bytes | None = None):
    def f(cap: Path) -> None:
        p = cap / "frames" / "cam1" / name
        p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2] if data is None else data)
    return f


def _resize(cap: Path) -> None:
    import cv2

    for p in sorted((cap / "frames" / "cam0").glob("*.png")):
        write_image(p, cv2.resize(read_image(p), (64, 64)))


def _sphere_inside(cap: Path, radius: float = 0.02) -> None:
    data = json.loads((cap / "controls.json").read_text())
    data["obstacles"] = [{"name": "pusher", "shape": "sphere", "radius": radius}]
    (cap / "controls.json").write_text(json.dumps(data))


def _other_mesh(ws: Path) -> None:
    from stages.artefacts import MeshArtefact, Provenance

    art = MeshArtefact.load(ws / "other" / "mesh.h5")  # tetrahedralized from sample_data/dino in the fixture
    shutil.copy(ws / "other" / "mesh.h5", ws / "mesh.h5")
    assert art.n_vertices > 0 and Provenance


def _renumber(ws: Path) -> None:
    from stages.artefacts import MeshArtefact, Provenance

    m = MeshArtefact.load(ws / "mesh.h5")
    perm = np.random.default_rng(0).permutation(m.n_vertices)
    inv = np.argsort(perm)
    m.vertices, m.vertex_masses = m.vertices[perm], m.vertex_masses[perm]
    m.tets, m.surface_faces = inv[m.tets], inv[m.surface_faces]
    m.handles = {k: inv[v] for k, v in m.handles.items()}
    m.loads = {k: inv[v] for k, v in m.loads.items()}
    cap = ws.parent / "cap"
    m.save(ws / "mesh.h5", Provenance.make({"capture": str(cap), "workspace": str(ws)}, [cap / "object.mesh"]))


def _toml(old: str, new: str):
    return lambda cap: edit(cap / "capture.toml", old, new)


WIDE = _toml("young_range = [20000.0, 1000000.0]", "young_range = [0.5, 1000000.0]")

# case -> (change the capture, change the workspace, command after "adapt CAP -w WS" or a full command
#          (a list starting with a command name), texts of the one sentence)
CASES = {
    "unreadable frame in the middle": (_bad_png("000001.png", b"not a png"), None, VISION,
                                       ["frames/cam1/000001.png: cannot read image"]),
    "truncated frame in the middle": (_bad_png("000001.png"), None, VISION, ["frames/cam1/000001.png"]),
    "frames at another size than cameras.h5": (_resize, None, VISION,
                                               ["frames/cam0/000000.png: the frame is 64x64 but camera 'cam0' in "
                                                "cameras.h5 is calibrated for 128x128 images"]),
    "a frame missing in the middle": (lambda c: (c / "frames" / "cam2" / "000005.png").unlink(), None, VISION,
                                      ["frames/cam2: frames should be numbered from 0 without gaps; frame 5 is "
                                       "missing"]),
    "mesh.h5 of another capture": (None, _other_mesh, [*MARKERS, "--frames", "0:2"],
                                   ["mesh.h5: was made from another object mesh than", "object.mesh",
                                    "run `rsl tetrahedralize`"]),
    "sphere obstacle inside the rest shape": (_sphere_inside, None, [*MARKERS, "--frames", "0:2"],
                                              ["controls.json: obstacle 'pusher' starts inside the object at "
                                               "frame 0", "move it out of the rest shape"]),
    "sphere obstacle deep inside the rest shape, moving start": (
        lambda cap: (_sphere_inside(cap, 0.06), edit(cap / "capture.toml", 'start = "equilibrium"',
                                                     'start = "moving"')),
        None, [*MARKERS, "--frames", "0:2"],
        ["controls.json: obstacle 'pusher' lies up to", "mm inside the rest shape at frame 0",
         "more than a capture filmed mid-motion (start = \"moving\") may press it (10% of the object's size)"]),
    "--young-init outside young_range": (None, None, [*MARKERS, "--frames", "0:2", "--young-init", "1"],
                                         ["capture.toml: --young-init 1 Pa lies outside [material] young_range"]),
    "--poisson-init outside poisson_range": (None, None, [*MARKERS, "--frames", "0:2", "--poisson-init", "0.495"],
                                             ["capture.toml: --poisson-init 0.495 lies outside poisson_range "
                                              "[0.3, 0.49]"]),
    "--young-init 1 collapses the start state": (WIDE, None, [*MARKERS, "--frames", "0:2", "--young-init", "1"],
                                                 ["capture.toml: the simulation failed at frame 0 with E = body 1 Pa",
                                                  "start from a larger E (--young-init"]),
    "renumbered mesh with the old gaussians.h5": (None, _renumber, VISION,
                                                  ["gaussians.h5: was made from a different mesh.h5",
                                                   "run `rsl fit-gaussians` again"]),
    "renumbered mesh with the old adapt.h5 (export)": (None, _renumber, ["export", "--stress", "--no-plots",
                                                                         "--no-render", "--no-vtk", "--no-forces"],
                                                       ["adapt.h5: was made from a different mesh.h5"]),
    "renumbered mesh with the old adapt.h5 (evaluate)": (None, _renumber, ["evaluate"],
                                                         ["adapt.h5: was made from a different mesh.h5"]),
}


@pytest.fixture(scope="module")
def results(base, tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("adapt_cases")
    other = root / "other"
    commands, where = [["tetrahedralize", SAMPLE / "dino", "-w", other, "--no-preview", "--order", "1"]], {}
    names = sorted(CASES)
    for i, name in enumerate(names):
        cap, ws = _copy(base, root / f"c{i}")
        where[name] = (cap, ws, tree_bytes(ws))
        cmd = CASES[name][2]
        if cmd[0] in ("export", "evaluate"):
            commands.append([cmd[0], *([cap] if cmd[0] == "evaluate" else []), "-w", ws, *cmd[1:]])
        else:
            commands.append(["adapt", cap, "-w", ws, *cmd])
    # first the dino mesh (a mesh.h5 of another capture), then the breakers, then the cases
    first = batch(commands[:1], root / "run0")
    assert first[0].returncode == 0, first[0].stderr
    for name in names:
        cap, ws, _ = where[name]
        (ws / "other").mkdir()
        shutil.copy(other / "mesh.h5", ws / "other" / "mesh.h5")
        if CASES[name][0]:
            CASES[name][0](cap)
        if CASES[name][1]:
            CASES[name][1](ws)
        where[name] = (cap, ws, tree_bytes(ws))
    procs = batch(commands[1:], root / "run1")
    return {name: (proc, *where[name]) for name, proc in zip(names, procs)}


@pytest.mark.parametrize("case", sorted(CASES))
def test_adapt_case(case: str, results: dict) -> None:
    proc, cap, ws, before = results[case]
    msg = assert_one_sentence(proc, *CASES[case][3])
    assert str(cap) in msg or str(ws) in msg, msg  # names the file with its folder
    assert tree_bytes(ws) == before  # adapt.h5 (and every other artefact) intact
    assert not (ws / "adapt.partial.h5").exists()  # each of these is found before any frame is adapted


def test_failed_run_keeps_adapt_h5(base, tmp_path: Path) -> None:
    """A run that fails after some frames (the mesh collapses): adapt.h5 stays, the frames done go to
    adapt.partial.h5 (status failed), and the sentence says both and what to change."""
    from stages.artefacts import AdaptArtefact

    cap, ws = _copy(base, tmp_path)
    WIDE(cap)
    text = (cap / "capture.toml").read_text()
    text = re.sub(r'(?m)^start = .*\n', "", text).replace("[capture]\n", '[capture]\nstart = "rest"\n', 1)
    (cap / "capture.toml").write_text(text)
    before = tree_bytes(ws)
    proc, status = batch([["adapt", cap, "-w", ws, *MARKERS, "--frames", "0:6", "--young-init", "30"],
                          ["status", "-w", ws]], tmp_path / "run")
    msg = assert_one_sentence(proc, "capture.toml: the simulation", "far too soft for this object",
                              "start from a larger E", "adapt.h5 is unchanged")
    assert {k: v for k, v in tree_bytes(ws).items() if k != "adapt.partial.h5"} == before
    if (ws / "adapt.partial.h5").exists():
        assert "kept in adapt.partial.h5" in msg
        part = AdaptArtefact.load(ws / "adapt.partial.h5", allow_partial=True)
        assert part.extra["status"] == "failed" and len(part.frames) >= 1
    assert "adapt adapt.h5 up to date" in " ".join(flat(status.stdout).replace("│", " ").split())


def _sigint_default() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture(scope="module")
def interrupted(base, tmp_path_factory) -> dict:
    """A non-follow adapt stopped by Ctrl-C after a few frames, then what downstream does with the result."""
    root = tmp_path_factory.mktemp("ctrl_c")
    cap, ws = _copy(base, root)
    before = tree_bytes(ws)
    # SIGINT at its default in the child, as a terminal's Ctrl-C finds it: a pytest started in the background
    # (`make test &`, nohup) passes SIG_IGN on, and rsl (rightly) keeps ignoring it, so the run would end complete
    proc = rsl_proc("-v", "adapt", cap, "-w", ws, *MARKERS, "--frames", "0:40", "--iters-per-frame", "8",
                    preexec_fn=_sigint_default)
    lines = []
    for line in proc.stderr:  # --verbose without a terminal: a line per frame; stop after the third
        lines.append(line)
        if "adapt online" in line and ": 3/40" in line:
            break
    proc.send_signal(signal.SIGINT)
    rest = proc.stderr.read()
    code = proc.wait()
    after = tree_bytes(ws)
    assert (ws / "adapt.partial.h5").exists(), f"exit {code}; no adapt.partial.h5 after Ctrl-C:\n{''.join(lines)}{rest}"
    # downstream of a workspace whose adapt.h5 is that unfinished run (as an older rsl would have left it)
    ws2 = root / "ws_partial"
    shutil.copytree(ws, ws2)
    shutil.copy(ws / "adapt.partial.h5", ws2 / "adapt.h5")
    down = batch([["export", "-w", ws2, "--stress", "--no-plots", "--no-render", "--no-vtk", "--no-forces"],
                  ["evaluate", cap, "-w", ws2], ["info", ws2 / "adapt.h5"], ["info", ws / "adapt.partial.h5"],
                  ["status", "-w", ws2], ["run", cap, "-w", ws2, "--only", "adapt", "--dry-run"],
                  ["status", "-w", ws],
                  ["export", "-w", ws, "--source", "partial", "--stress", "--no-plots", "--no-render", "--no-vtk",
                   "--no-forces"], ["evaluate", cap, "-w", ws, "--partial"]], root / "down")
    return {"code": code, "stderr": "".join(lines) + rest, "before": before, "after": after, "ws": ws,
            "ws2": ws2, "down": down}


def test_ctrl_c_keeps_adapt_h5(interrupted: dict) -> None:
    from stages.artefacts import AdaptArtefact

    ws = interrupted["ws"]
    err = flat(interrupted["stderr"])
    assert interrupted["code"] == 130, err
    assert "Traceback" not in interrupted["stderr"]
    assert "interrupted; the" in err and f"frame(s) done are kept in {ws / 'adapt.partial.h5'}; adapt.h5 is " \
                                         f"unchanged." in err, err
    assert {k: v for k, v in interrupted["after"].items() if k != "adapt.partial.h5"} == interrupted["before"]
    part = AdaptArtefact.load(ws / "adapt.partial.h5", allow_partial=True)
    assert part.extra["status"] == "interrupted" and 1 <= len(part.frames) < 40
    status = " ".join(flat(interrupted["down"][6].stdout).replace("│", " ").split())
    assert "adapt adapt.h5 up to date" in status and "adapt.partial.h5: the frames of an unfinished" in status


DOWNSTREAM = {"export refuses it": (0, "adapt.h5: holds an unfinished (interrupted) run"),
              "evaluate refuses it": (1, "adapt.h5: holds an unfinished (interrupted) run"),
              "rsl info adapt.h5 refuses it": (2, "adapt.h5: holds an unfinished (interrupted) run"),
              "rsl info adapt.partial.h5 shows it": (3, None),
              "rsl status calls it invalid": (4, "adapt adapt.h5 invalid"),
              "rsl run remakes it": (5, "adapt run adapt.h5 invalid")}


@pytest.mark.parametrize("case", sorted(DOWNSTREAM))
def test_downstream_refuses_partial(case: str, interrupted: dict) -> None:
    i, text = DOWNSTREAM[case]
    proc = interrupted["down"][i]
    if case.startswith("rsl info adapt.partial"):
        assert proc.returncode == 0 and "kind adapt" in flat(proc.stdout), proc.stderr
        assert "status interrupted (unfinished: downstream stages refuse it)" in flat(proc.stdout)
    elif i in (4, 5):
        assert proc.returncode == 0, proc.stderr
        out = " ".join(flat(proc.stdout).replace("│", " ").split())
        assert text in out, proc.stdout
        assert i == 5 or "holds an unfinished (interrupted) run, not a complete one" in out, proc.stdout
    else:
        assert_one_sentence(proc, text, "not a complete one")


def test_downstream_takes_the_partial_run_when_asked(interrupted: dict) -> None:
    """export --source partial and evaluate --partial read adapt.partial.h5 on purpose."""
    import json

    ws = interrupted["ws"]
    export, evaluate = interrupted["down"][7], interrupted["down"][8]
    assert export.returncode == 0, export.stderr
    assert (ws / "export_partial" / "stress.h5").exists() and not (ws / "export").exists()
    assert evaluate.returncode == 0, evaluate.stderr
    assert len(json.loads((ws / "evaluation.json").read_text())["young_rel_error_per_frame"]) >= 3


def test_mp4_frames_are_read(base, tmp_path: Path) -> None:
    """frames/CAM.mp4 instead of PNG folders: the vision loss reads them as segment does (a correct result)."""
    import cv2

    from stages.artefacts import AdaptArtefact, read_provenance

    cap, ws = _copy(base, tmp_path)
    for cam in ("cam0", "cam1", "cam2"):
        files = sorted((cap / "frames" / cam).glob("*.png"))
        first = read_image(files[0])
        vw = cv2.VideoWriter(str(cap / "frames" / f"{cam}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30,
                             (first.shape[1], first.shape[0]))
        for p in files:
            vw.write(cv2.cvtColor(read_image(p), cv2.COLOR_RGB2BGR))
        vw.release()
        shutil.rmtree(cap / "frames" / cam)
    proc, = batch([["adapt", cap, "-w", ws, *VISION]], tmp_path / "run")
    assert proc.returncode == 0, proc.stderr
    art = AdaptArtefact.load(ws / "adapt.h5")
    assert list(art.frames) == [0, 1] and art.loss_kind == "vision" and np.all(np.isfinite(art.young))
    inputs = {i["path"] for i in read_provenance(ws / "adapt.h5")["inputs"]}
    assert {"frames/cam0.mp4", "frames/cam1.mp4", "frames/cam2.mp4"} <= inputs, inputs


@pytest.mark.parametrize("angle_rad", [1e-12, 1e-8, 1e-4, 0.5, 3.0, np.pi - 1e-6], ids=lambda a: f"angle {a:.9g} rad")
def test_rotation_angle_small_angles(angle_rad: float) -> None:
    """rotation_angle_deg = atan2(|skew|, tr − 1) keeps full relative precision down to 1e-12 rad (arccos of the
    trace could not resolve angles below ~1e-6°) and up to π; the axis does not matter."""
    from stages.vision.geometry import rotation_angle_deg, rotvec_to_matrix

    for axis in (np.array([1.0, 0, 0]), np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])):
        got = rotation_angle_deg(rotvec_to_matrix(angle_rad * axis))
        assert got == pytest.approx(np.degrees(angle_rad), rel=1e-9, abs=0.0)


def test_solve_guard_tolerates_a_sliver_but_not_a_collapse(tmp_path: Path) -> None:
    """One inverted sliver among many elements is no collapse; many inverted elements, NaN or a blow-up are."""
    from stages.window_backends import SolveCollapsed, SolveGuard
    from stages.sim.meshgen import box_tets

    v, t = box_tets((20, 6, 6), (1.0, 0.3, 0.3))
    guard = SolveGuard(v, t, ["body"], tmp_path / "capture.toml", 1e5)
    young = np.array([[1e5]])
    x = v.copy()
    guard([0], x[None], young)  # rest: fine
    one = x.copy()
    one[t[0, 0]] = 2 * one[t[0, 1]] - one[t[0, 0]]  # fold one corner across its neighbour: a few slivers invert
    p = one[t]
    bad = int(np.sum(np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) <= 0))
    assert 1 <= bad <= 0.001 * len(t)
    guard([0], one[None], young)
    with pytest.raises(SolveCollapsed, match="inverted"):
        guard([3], (x * np.array([1.0, 1.0, -1.0]))[None], young)  # mirrored: every element inverted
    with pytest.raises(SolveCollapsed, match="NaN"):
        guard([1], np.full_like(x, np.nan)[None], young)


# --------------------------------------------------------------------------- Ctrl-C at a bad moment (in-process)
# A Ctrl-C that arrives while compiled code runs can be lost (numba's _numba_unpickle, called back from an njit
# kernel, drops the KeyboardInterrupt) or come out as a SystemError; a second Ctrl-C can land inside the save.
# signal.raise_signal runs the Python handler before it returns, so each moment is hit exactly.

@pytest.fixture
def default_sigint():
    """Python's own SIGINT handler for the test (a pytest started in the background inherits SIG_IGN)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signal handlers need the main thread")
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


def _ctrl_c_run(base, tmp_path: Path, monkeypatch, at_frame: int, how: str):
    """adapt.run (markers, gn, frames 0:4) with a Ctrl-C injected at the `at_frame`-th frame's σ computation."""
    from stages.steps import adapt

    cap, ws = _copy(base, tmp_path)
    before = tree_bytes(ws)
    real, calls = adapt.sigma_from_cov, [0]

    def sigma(*a, **k):
        calls[0] += 1
        if calls[0] == at_frame + 1:
            if how == "lost":
                try:
                    signal.raise_signal(signal.SIGINT)
                except KeyboardInterrupt:
                    pass  # what compiled code does with it
            elif how == "systemerror":
                try:
                    signal.raise_signal(signal.SIGINT)
                except KeyboardInterrupt as e:
                    raise SystemError("returned a result with an exception set") from e
            else:
                signal.raise_signal(signal.SIGINT)
        return real(*a, **k)

    monkeypatch.setattr(adapt, "sigma_from_cov", sigma)
    config = adapt.AdaptConfig(capture=cap, workspace=ws, space="full", loss="markers", window=2, frames="0:4",
                               iters_per_frame=2, estimator="gn")
    return adapt, config, ws, before


def _assert_partial(ws: Path, before: dict, n_frames: int) -> None:
    from stages.artefacts import AdaptArtefact

    assert {k: v for k, v in tree_bytes(ws).items() if k != "adapt.partial.h5"} == before  # adapt.h5 unchanged
    part = AdaptArtefact.load(ws / "adapt.partial.h5", allow_partial=True)
    assert part.extra["status"] == "interrupted" and part.extra["ended"] == "ctrl-c"
    assert list(part.frames) == list(range(n_frames))
    assert len(part.extra["innovation_ratio"]) == n_frames


@pytest.mark.parametrize("how,kept", [("lost", 2), ("systemerror", 1)],
                         ids=["Ctrl-C whose KeyboardInterrupt compiled code loses: the run stops a frame later",
                              "Ctrl-C that compiled code turns into a SystemError: interrupted, not a crash"])
def test_ctrl_c_lost_in_compiled_code_still_stops_and_keeps_the_frames(base, tmp_path, monkeypatch, how, kept,
                                                                        default_sigint):
    """Lost: the run stops once the frame under way is recorded (2 frames kept); turned into a SystemError: the
    run ends as interrupted with the frame done before (1 frame), not as a crash."""
    from stages.errors import Interrupted

    adapt, config, ws, before = _ctrl_c_run(base, tmp_path, monkeypatch, 1, how)
    handler = signal.getsignal(signal.SIGINT)
    with pytest.raises(Interrupted, match="adapt.partial.h5"):
        adapt.run(config)
    _assert_partial(ws, before, kept)
    assert signal.getsignal(signal.SIGINT) == handler  # the caller's handler is back


def test_second_ctrl_c_during_the_save_does_not_abort_it(base, tmp_path, monkeypatch, default_sigint):
    """Ctrl-C at frame 1, and again while adapt.partial.h5 is being written: the write completes."""
    from stages.artefacts import AdaptArtefact
    from stages.errors import Interrupted

    adapt, config, ws, before = _ctrl_c_run(base, tmp_path, monkeypatch, 1, "raise")
    real_save = AdaptArtefact.save

    def save(self, *a, **k):
        signal.raise_signal(signal.SIGINT)
        return real_save(self, *a, **k)

    monkeypatch.setattr(AdaptArtefact, "save", save)
    try:
        adapt.run(config)
    except KeyboardInterrupt:  # (caught here: left alone it would end the pytest session)
        pytest.fail("the second Ctrl-C escaped from the save")
    except Interrupted as e:
        assert "adapt.partial.h5" in str(e)
    else:
        pytest.fail("the run was not interrupted")
    _assert_partial(ws, before, 1)


def test_a_frame_record_cut_half_way_is_dropped() -> None:
    """A Ctrl-C between the appends of one frame's record: the save keeps the frames every list has."""
    from stages.steps.adapt import _Record, _trim_record

    rec = _Record(frames=[0, 1, 2], young=[1, 2, 3], poisson=[1, 2], loss=[1, 2, 3], frame_loss=[1, 2, 3],
                  t_fwd=[1, 2, 3], t_bwd=[1, 2, 3], t_ren=[1, 2, 3], t_tot=[1, 2, 3])
    rec.innovation = [0.1, 0.2, 0.3, 0.4]
    _trim_record(rec)
    assert rec.frames == [0, 1] and rec.t_tot == [1, 2] and rec.innovation == [0.1, 0.2]
    assert rec.young_sigma == []  # Adam records none: not a reason to drop frames
    rec.young_sigma, rec.poisson_sigma = [1, 2], [1]
    _trim_record(rec)
    assert rec.frames == [0] and rec.young_sigma == [1] and rec.poisson_sigma == [1]
