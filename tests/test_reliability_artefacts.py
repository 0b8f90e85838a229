"""Nothing lost (issue 14): verified artefact writes, stale temporary files, orphaned workers, read-only
workspaces, and provenance that sees every input (frames, a swapped mesh.h5, a copied workspace).

Every case runs the real CLI in a child process (tests/reliability.py).  Faults the operating system would give
are made for real where the test may (a full tmpfs, a read-only remount: the tests run as root in CI; skipped
where mounting is not permitted) and otherwise by a write hook injected into h5py in the child process that
fails the same way (an h5py error on close, data lost, a flipped byte).
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from reliability import SAMPLE, assert_one_sentence, batch, copy_capture, edit, flat, rsl_proc, tree_bytes
from stages.capture import read_image, write_image

GROUPS = {"test_write_fault": "artefact writes: faults while writing",
          "test_disk_full_on_a_tmpfs": "artefact writes: faults while writing",
          "test_stale_temp_files_are_removed": "killed runs: temp files and workers",
          "test_generate_data_workers_die_with_their_parent": "killed runs: temp files and workers",
          "test_read_only_workspace": "workspace: read-only",
          "test_provenance_and_status": "provenance and staleness (rsl status / run)",
          "test_mesh_mismatch_refused": "artefacts made from another mesh.h5"}
LABELS = {"test_mesh_mismatch_refused": "a renumbered mesh.h5 (same counts) with the old snapshots.h5: "
                                        "train-subspace refuses"}


def _mount_tmpfs(where: Path, size: str) -> None:
    where.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)], capture_output=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({proc.stderr.decode().strip()})")


def _umount(where: Path) -> None:
    subprocess.run(["umount", "-l", str(where)], capture_output=True)


@pytest.fixture(scope="module")
def syn(tmp_path_factory) -> Path:
    """bar_synth (3 cameras, 40 frames, background plates) with the sample bar's tet mesh (fast tetrahedralize)."""
    cap = copy_capture(tmp_path_factory.mktemp("syn") / "cap")
    shutil.copy(SAMPLE / "bar" / "object.mesh", cap / "object.mesh")
    edit(cap / "capture.toml", 'mesh = "object.obj"', 'mesh = "object.mesh"')
    return cap


@pytest.fixture(scope="module")
def good_ws(syn, tmp_path_factory) -> Path:
    """A workspace with mesh.h5, masks.h5 and snapshots.h5 made by the CLI."""
    ws = tmp_path_factory.mktemp("good") / "ws"
    procs = batch([["tetrahedralize", syn, "-w", ws, "--no-preview", "--order", "1"],
                   ["segment", syn, "-w", ws, "--method", "background"],
                   ["generate-data", syn, "-w", ws, "--sequences", "1", "--frames", "2"]], ws.parent / "run")
    for p in procs:
        assert p.returncode == 0, p.stderr
    return ws


# =========================================================================== write faults
_HOOK = r"""
import os, h5py
MODE = {mode!r}
_close = h5py.File.close
_busy = []
def _hooked_close(self):
    name = self.filename if self.id.valid else ""
    writable = bool(name) and self.mode == "r+"
    _close(self)
    if _busy or not writable or not os.path.basename(name).startswith(".mesh.h5."):
        return
    _busy.append(1)
    try:
        if MODE == "enospc":  # what h5py raises when the disk fills while the file is closed
            raise OSError(28, "Unable to synchronously close file (file write failed: errno = 28, "
                              "error message = 'No space left on device')")
        if MODE == "zeros":  # the data never reached the disk; the file itself is well formed
            with h5py.File(name, "r+") as f:
                f["vertices"][...] = 0.0
        if MODE == "flip":  # one byte of a dataset's chunk changed on the way to the disk
            with h5py.File(name, "r") as f:
                off = f["vertices"].id.get_chunk_info(0).byte_offset
            with open(name, "r+b") as g:
                g.seek(off + 5)
                b = g.read(1)
                g.seek(off + 5)
                g.write(bytes([b[0] ^ 0xFF]))
    finally:
        _busy.clear()
h5py.File.close = _hooked_close
"""

WRITE_FAULTS = {
    "h5py error on close (disk full)": ("enospc", "writing failed (Unable to synchronously close file"),
    "data lost on the way to the disk": ("zeros", "reads back with other values than were written"),
    "a flipped byte in a dataset (Fletcher-32)": ("flip", "it cannot be read back"),
}


@pytest.fixture(scope="module")
def fault_results(syn, good_ws, tmp_path_factory) -> dict:
    out = {}
    for name, (mode, _) in WRITE_FAULTS.items():
        ws = tmp_path_factory.mktemp(mode) / "ws"
        shutil.copytree(good_ws, ws)
        before = tree_bytes(ws)
        procs = batch([["tetrahedralize", syn, "-w", ws, "--no-preview", "--order", "1"], ["info", ws / "mesh.h5"]],
                      ws.parent / "run", prelude=_HOOK.format(mode=mode))
        out[name] = (procs, ws, before)
    return out


@pytest.mark.parametrize("case", sorted(WRITE_FAULTS))
def test_write_fault(case: str, fault_results: dict) -> None:
    """The write is verified before the rename: the old mesh.h5 stays, byte for byte, and is still valid."""
    (proc, info), ws, before = fault_results[case]
    assert_one_sentence(proc, f"{ws / 'mesh.h5'}: ", WRITE_FAULTS[case][1], "the previous mesh.h5 is kept")
    assert tree_bytes(ws) == before
    assert not list(ws.glob(".*.tmp"))
    assert info.returncode == 0, info.stderr


@pytest.mark.parametrize("case", ["a real full disk (1 MiB tmpfs) under tetrahedralize"])
def test_disk_full_on_a_tmpfs(case: str, syn, good_ws, tmp_path: Path) -> None:
    """A real full disk: a 1 MiB tmpfs holding a good mesh.h5 and a filler; the new write fails, the old stays."""
    mnt = tmp_path / "full"
    _mount_tmpfs(mnt, "1m")
    try:
        shutil.copy(good_ws / "mesh.h5", mnt / "mesh.h5")
        shutil.copy(good_ws / ".rsl_hashes.json", mnt / ".rsl_hashes.json")
        before = tree_bytes(mnt)
        fd = os.open(mnt / "filler", os.O_WRONLY | os.O_CREAT)  # fill the disk, then leave 32 KiB free:
        try:  # less than mesh.h5 needs
            while True:
                os.write(fd, b"\0" * 4096)
        except OSError:
            pass
        finally:
            os.close(fd)
        os.truncate(mnt / "filler", max(0, (mnt / "filler").stat().st_size - 32 * 1024))
        proc, status = batch([["tetrahedralize", syn, "-w", mnt, "--no-preview", "--order", "1"], ["info", mnt / "mesh.h5"]],
                             tmp_path / "run")
        assert_one_sentence(proc, f"{mnt / 'mesh.h5'}: writing failed", "No space left on device",
                            "the previous mesh.h5 is kept")
        assert tree_bytes(mnt) == before and not list(mnt.glob(".*.tmp"))
        assert status.returncode == 0, status.stderr
    finally:
        _umount(mnt)


# =========================================================================== killed runs
def _dead_pid() -> int:
    p = subprocess.Popen(["true"])
    p.wait()
    return p.pid


@pytest.mark.parametrize("case", ["temp file of a killed run (dead PID)", "temp file without a PID, an hour old",
                                  "temp file of a running process is kept"])
def test_stale_temp_files_are_removed(case: str, syn, good_ws, tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    shutil.copytree(good_ws, ws)
    dead = ws / f".mesh.h5.{_dead_pid()}.k1llEd.tmp"
    old = ws / ".snapshots.h5.abc123xy.tmp"
    live = ws / f".masks.h5.{os.getpid()}.w0rk1n.tmp"
    for p in (dead, old, live):
        p.write_bytes(b"\0" * 1000)
    hour_ago = time.time() - 3600
    os.utime(old, (hour_ago, hour_ago))
    proc, = batch([["tetrahedralize", syn, "-w", ws, "--no-preview", "--order", "1"]], tmp_path / "run")
    assert proc.returncode == 0, proc.stderr
    if case.startswith("temp file of a killed"):
        assert not dead.exists()
    elif case.startswith("temp file without"):
        assert not old.exists()
    else:
        assert live.exists()


def _children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2:].split()
            if int(fields[1]) == pid:
                out.append(int(d.name))
    return out


def _running(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rindex(")") + 2:].split()[0] not in ("Z", "X")


@pytest.mark.parametrize("case", ["kill -9 of generate-data with 2 workers"])
def test_generate_data_workers_die_with_their_parent(case: str, syn, good_ws, tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    ws.mkdir()
    shutil.copy(good_ws / "mesh.h5", ws / "mesh.h5")
    proc = rsl_proc("generate-data", syn, "-w", ws, "--sequences", "6", "--frames", "40", "--workers", "2")
    workers: list[int] = []
    for _ in range(1200):  # wait (up to 2 min) until both workers run
        workers = [c for c in _children(proc.pid) if "spawn_main" in Path(f"/proc/{c}/cmdline").read_text()]
        if len(workers) >= 2 or proc.poll() is not None:
            break
        time.sleep(0.1)
    assert len(workers) >= 2, proc.stderr.read() if proc.poll() is not None else "no workers started"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    for _ in range(600):  # the watchdog polls twice a second
        if not any(_running(w) for w in workers):
            break
        time.sleep(0.1)
    alive = [w for w in workers if _running(w)]
    for w in alive:  # do not leave them behind if the test fails
        os.kill(w, signal.SIGKILL)
    assert not alive
    assert not (ws / "snapshots.h5").exists()


# =========================================================================== read-only workspace
@pytest.mark.parametrize("stage", ["tetrahedralize", "generate-data"], ids=lambda s: f"{s} into a read-only workspace")
def test_read_only_workspace(stage: str, syn, good_ws, tmp_path: Path) -> None:
    """A workspace that cannot be written is reported before any compute, and nothing in it changes."""
    mnt = tmp_path / "ro"
    _mount_tmpfs(mnt, "4m")
    try:
        shutil.copy(good_ws / "mesh.h5", mnt / "mesh.h5")
        before = tree_bytes(mnt)
        if subprocess.run(["mount", "-o", "remount,ro", str(mnt)], capture_output=True).returncode != 0:
            pytest.skip("cannot remount read-only here")
        args = {"tetrahedralize": ["--no-preview", "--order", "1"], "generate-data": ["--sequences", "50", "--frames", "40"]}[stage]
        proc, = batch([[stage, syn, "-w", mnt, *args]], tmp_path / "run")
        assert_one_sentence(proc, f"{mnt}: the workspace is not writable", "Read-only file system",
                            "nothing was computed")
        assert tree_bytes(mnt) == before
    finally:
        _umount(mnt)


# =========================================================================== provenance and staleness
@pytest.fixture(scope="module")
def status_results(syn, good_ws, tmp_path_factory) -> dict:
    base = tmp_path_factory.mktemp("status")
    # (a) frames 3..7 of one camera replaced (same size, other content) in a copy of the capture
    cap_a = copy_capture(base / "cap_a", syn)
    ws_a = base / "ws_a"
    shutil.copytree(good_ws, ws_a)
    # (b) a copied workspace, unchanged; (c) a copy whose mesh.h5 is another capture's; (d) a deleted input
    ws_b, ws_c = base / "moved" / "ws_b", base / "ws_c"
    shutil.copytree(good_ws, ws_b)
    shutil.copytree(good_ws, ws_c)
    other = base / "other_ws"
    cap_d = copy_capture(base / "cap_d", syn)
    ws_d = base / "ws_d"
    setup = batch([["tetrahedralize", SAMPLE / "dino", "-w", other, "--no-preview", "--order", "1"],
                   ["tetrahedralize", cap_d, "-w", ws_d, "--no-preview", "--order", "1"]], base / "setup")
    assert all(p.returncode == 0 for p in setup), [p.stderr for p in setup]
    shutil.copy(other / "mesh.h5", ws_c / "mesh.h5")
    (cap_d / "controls.json").unlink()
    # masks.h5 of ws_a was made from syn's frames: point it at cap_a by re-running segment there, then edit
    batch([["segment", cap_a, "-w", ws_a, "--method", "background"]], base / "seg")
    for t in range(3, 8):
        p = cap_a / "frames" / "cam1" / f"{t:06d}.png"
        write_image(p, 255 - read_image(p))
    procs = batch([["status", "-w", ws_a], ["run", cap_a, "-w", ws_a, "--only", "segment", "--dry-run"],
                   ["status", "-w", ws_b], ["status", "-w", ws_c], ["status", "-w", ws_d]], base / "after")
    return {"frames": procs[0], "dry_run": procs[1], "copied": procs[2],
            "swapped": procs[3], "deleted": procs[4]}


STATUS_CASES = {
    "frames 3–7 of a camera replaced": ("frames", ["segment masks.h5 stale", "input frames/cam1 (its files) changed"]),
    "rsl run remakes what replaced frames feed": ("dry_run", ["segment run masks.h5 stale: input frames/cam1 (its files) changed"]),
    "a copied workspace is up to date": ("copied", ["tetrahedralize mesh.h5 up to date",
                                                    "segment masks.h5 up to date",
                                                    "generate-data snapshots.h5 up to date"]),
    "a copied workspace with a swapped mesh.h5": ("swapped", ["generate-data snapshots.h5 stale",
                                                              "input mesh.h5 changed"]),
    "an input of the capture deleted": ("deleted", ["tetrahedralize mesh.h5 stale", "input controls.json is missing"]),
}


@pytest.mark.parametrize("case", sorted(STATUS_CASES))
def test_provenance_and_status(case: str, status_results: dict) -> None:
    key, needles = STATUS_CASES[case]
    proc = status_results[key]
    assert proc.returncode == 0, proc.stderr
    text = flat(proc.stdout).replace("│", " ").replace("┃", " ")
    text = " ".join(text.split())
    for n in needles:
        assert n in text, (n, text)


@pytest.fixture(scope="module")
def renumbered(syn, good_ws, tmp_path_factory) -> Path:
    """good_ws with mesh.h5 replaced by the same mesh with its vertices renumbered (same counts)."""
    from stages.artefacts import MeshArtefact, Provenance

    ws = tmp_path_factory.mktemp("renumbered") / "ws"
    shutil.copytree(good_ws, ws)
    m = MeshArtefact.load(ws / "mesh.h5")
    perm = np.random.default_rng(0).permutation(m.n_vertices)
    inv = np.argsort(perm)
    m.vertices, m.vertex_masses = m.vertices[perm], m.vertex_masses[perm]
    m.tets, m.surface_faces = inv[m.tets], inv[m.surface_faces]
    m.handles = {k: inv[v] for k, v in m.handles.items()}
    m.loads = {k: inv[v] for k, v in m.loads.items()}
    m.save(ws / "mesh.h5", Provenance.make({"capture": str(syn), "workspace": str(ws)}, [syn / "object.mesh"]))
    return ws


def test_mesh_mismatch_refused(renumbered: Path, syn) -> None:
    """snapshots.h5 made from the mesh before renumbering: train-subspace refuses, whatever the counts."""
    before = tree_bytes(renumbered)
    proc, = batch([["train-subspace", "-w", renumbered, "--kind", "pca", "--dim", "2"]], renumbered.parent / "run")
    assert_one_sentence(proc, f"{renumbered / 'snapshots.h5'}: was made from a different mesh.h5",
                        "run `rsl generate-data` again")
    assert tree_bytes(renumbered) == before
