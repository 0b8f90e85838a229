"""The cluster path against a real Ray head started here on 127.0.0.1 (one CPU): `rsl generate-data --ray
ADDRESS` and a bench sweep (bench/_parallel.map_tasks) give exactly what the local process pool gives."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import meshio
import numpy as np
import pytest

ray = pytest.importorskip("ray", reason="Ray is a test dependency (pip install -e '.[test]')")

from stages.artefacts import Provenance, SnapshotsArtefact  # noqa: E402
from stages.capture import load_capture, select_handles  # noqa: E402
from stages.steps.generate_data import GenerateDataConfig, run  # noqa: E402
from stages.artefacts import mesh_artefact  # noqa: E402
from stages.sim.meshgen import box_tets  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

# The head: an in-process Ray instance in a child process of the test (its raylet and GCS are that
# process's children), printing its GCS address, shut down when its stdin closes.
HEAD = r"""
import sys, ray
ctx = ray.init(num_cpus=1, include_dashboard=False, _node_ip_address="127.0.0.1", _temp_dir=sys.argv[1],
               log_to_driver=False, configure_logging=False)
print(ctx.address_info["gcs_address"], flush=True)
sys.stdin.read()
ray.shutdown()
"""
RAY_ENV = {"RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0", "JAX_ENABLE_X64": "1",
           "JAX_PLATFORMS": "cpu"}

TOML = """[capture]
name = "tiny"
fps = 30.0
gravity = [0.0, 0.0, -9.81]
cameras = []
[object]
mesh = "object.mesh"
density = 1070.0
[material]
young = 1.0e5
poisson = 0.4
young_range = [5.0e4, 2.0e5]
poisson_range = [0.35, 0.45]
"""
CONTROLS = {
    "handles": [
        {"name": "left", "select": {"box": [[-0.01, -1, -1], [0.001, 1, 1]]}, "stiffness": 2e4,
         "poses": [[0, 0, 0, 1, 0, 0, 0]]},
        {"name": "right", "select": {"box": [[0.199, -1, -1], [0.21, 1, 1]]}, "stiffness": 2e4,
         "keyframes": {"frame": [0, 10], "pose": [[0, 0, 0, 1, 0, 0, 0], [0.03, 0, 0.01, 1, 0, 0, 0]]}},
    ],
}


@pytest.fixture(scope="module")
def ray_head():
    """ADDRESS (127.0.0.1:PORT) of a one-CPU Ray head started for these tests and stopped after them."""
    mp = pytest.MonkeyPatch()
    for k, v in RAY_ENV.items():
        mp.setenv(k, v)  # this process and the `rsl` subprocesses: no token, no usage report
    temp = tempfile.mkdtemp(prefix="rsl-ray-", dir="/tmp")  # short: Ray's socket paths must stay < 108 chars
    err = open(Path(temp) / "head.err", "w+")
    proc = subprocess.Popen([sys.executable, "-c", HEAD, temp], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=err, text=True, env=dict(os.environ))
    try:
        line = proc.stdout.readline().strip()
        if not line:
            err.seek(0)
            pytest.fail(f"the Ray head did not start:\n{err.read()[-3000:]}")
        yield "127.0.0.1:" + line.rsplit(":", 1)[1]
    finally:
        proc.stdin.close()  # the head calls ray.shutdown(), which stops its raylet and GCS
        try:
            proc.wait(timeout=120)
        except subprocess.TimeoutExpired:
            proc.terminate()
            proc.wait()
        err.close()
        shutil.rmtree(temp, ignore_errors=True)
        mp.undo()


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("ray")
    cap, ws = root / "capture", root / "ws"
    cap.mkdir()
    v, t = box_tets((5, 1, 1), (0.2, 0.04, 0.04))
    meshio.write(str(cap / "object.mesh"), meshio.Mesh(v, [("tetra", t)]), file_format="medit")
    (cap / "capture.toml").write_text(TOML)
    (cap / "controls.json").write_text(json.dumps(CONTROLS))
    mesh = mesh_artefact(v, t, load_capture(cap).density)
    mesh.handles = select_handles(load_capture(cap).controls(), v)
    mesh.save(ws / "mesh.h5", Provenance.make({}, []))
    return cap, ws


def _fresh_ws(src: Path, dst: Path) -> Path:
    dst.mkdir()
    shutil.copy(src / "mesh.h5", dst / "mesh.h5")
    return dst


def test_generate_data_on_a_ray_head_equals_the_local_pool(ray_head, tiny, tmp_path, rsl):
    cap, ws = tiny
    pool_ws = _fresh_ws(ws, tmp_path / "pool")
    run(GenerateDataConfig(cap, pool_ws, sequences=3, frames=6, workers=2, seed=3))
    ray_ws = _fresh_ws(ws, tmp_path / "ray")
    proc = rsl("generate-data", cap, "-w", ray_ws, "--sequences", "3", "--frames", "6", "--seed", "3",
               "--ray", ray_head)
    assert proc.returncode == 0, proc.stderr
    assert f"on Ray ({ray_head})" in " ".join(proc.stderr.split())
    a = SnapshotsArtefact.load(pool_ws / "snapshots.h5")
    b = SnapshotsArtefact.load(ray_ws / "snapshots.h5")
    assert a.positions.shape == (18, a.positions.shape[1], 3)
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.young, b.young) and np.array_equal(a.poisson, b.poisson)
    assert np.array_equal(a.sequence, b.sequence) and np.array_equal(a.frame, b.frame)
    assert np.ptp(a.positions[:, :, 0]) > 0  # it moved: the comparison is not of two rest states


def test_generate_data_with_an_unreachable_ray_address_is_one_sentence(tiny, tmp_path, rsl, monkeypatch):
    for k, v in RAY_ENV.items():
        monkeypatch.setenv(k, v)
    cap, ws = tiny
    w = _fresh_ws(ws, tmp_path / "w")
    with socket_port() as port:  # a port where nothing listens
        proc = rsl("generate-data", cap, "-w", w, "--sequences", "1", "--frames", "2", "--ray", f"127.0.0.1:{port}")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert f"nothing answers at 127.0.0.1:{port}" in " ".join(proc.stderr.split())
    assert not (w / "snapshots.h5").exists()


class socket_port:
    """A free TCP port on 127.0.0.1 (bound and released)."""

    def __enter__(self) -> int:
        import socket

        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        s.close()
        return port

    def __exit__(self, *exc) -> None:
        return None


def sag_at(capture: str, workspace: str, young_pa: float, frames: int) -> np.ndarray:
    """One run of a material sweep: positions (n, 3) of the tiny box after ``frames`` steps at E = young_pa."""
    from stages.artefacts import MeshArtefact
    from stages.sim.scene import frame_inputs, make_scene, simulate

    cap = load_capture(Path(capture))
    mesh = MeshArtefact.load(Path(workspace) / "mesh.h5")
    ctl = cap.controls()
    scene = make_scene(mesh, ctl, cap.material.model, cap.dt, cap.gravity)
    inputs = [frame_inputs(scene, ctl, f) for f in range(frames)]
    x = simulate(scene, inputs, np.full((frames, 1), young_pa), np.full((frames, 1), 0.4))
    return np.asarray(x[-1])


def test_bench_sweep_on_a_ray_head_equals_the_local_pool(ray_head, tiny, monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "bench"))  # as when a script in bench/ runs (the pool's workers get it too)
    from _parallel import map_tasks

    cap, ws = tiny
    args = [(str(cap), str(ws), e, 4) for e in (6e4, 1e5, 1.8e5)]
    serial = map_tasks(sag_at, args)
    pool = map_tasks(sag_at, args, workers=2)
    on_ray = map_tasks(sag_at, args, ray=ray_head)
    for s, p, r in zip(serial, pool, on_ray):
        assert np.array_equal(s, p) and np.array_equal(p, r)
    assert not np.array_equal(serial[0], serial[2])  # E changes the result: each run did its own material


@pytest.mark.parametrize("address, endpoint", [
    ("127.0.0.1:6379", ("127.0.0.1", 6379)), ("ray://head.lab:10001", ("head.lab", 10001)),
    ("[::1]:6379", ("::1", 6379)), ("auto", None), ("local", None), ("head.lab", None)])
def test_ray_addresses_that_are_checked_for_an_answer_first(address, endpoint):
    from stages.steps.generate_data import _ray_endpoint

    assert _ray_endpoint(address) == endpoint
