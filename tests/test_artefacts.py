"""Artefacts: round trip of every kind, provenance, atomic writes, validation on read."""
from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import h5py
import numpy as np
import pytest

from stages import artefacts as A
from stages.artefacts import (ARTEFACT_TYPES, KIND_FILES, AdaptArtefact, ArtefactError, Camera, CamerasArtefact,
                              GaussiansArtefact, MasksArtefact, MeshArtefact, Provenance, SnapshotsArtefact,
                              SubspaceArtefact, describe, file_sha256, load_any, read_provenance)
from stages.errors import RslError
from stages.sim.mesh import rest_quantities


def _rot(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def make_all(rng: np.random.Generator) -> dict[str, object]:
    """One small, valid instance of every artefact kind."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float) * 0.1
    t = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    t[1] = t[1][[0, 2, 1, 3]] if np.linalg.det((v[t[1, 1:]] - v[t[1, 0]]).T) < 0 else t[1]
    vol, dm_inv, m = rest_quantities(v, t, 1000.0)
    cams = [Camera(f"cam{i}", np.array([[500, 0, 320], [0, 500, 240], [0, 0, 1.0]]), rng.normal(size=5) * 0.01,
                   _rot(rng), rng.normal(size=3), 640, 480, 0.3 + i) for i in range(2)]
    g = 6
    q = rng.normal(size=(g, 4))
    bary = rng.random((g, 4))
    return {
        "cameras": CamerasArtefact(cams, "synth"),
        "masks": MasksArtefact({"cam0": rng.random((3, 8, 10)) > 0.5, "cam1": rng.random((3, 8, 10)) > 0.5},
                               "background", {"cam0": 0.9}),
        "mesh": MeshArtefact(v, t, np.array([[0, 2, 1], [0, 1, 3]]), np.array([0, 1]), ["body", "stiff"], vol,
                             dm_inv, m, 1000.0, {"left": np.array([0, 2])}, {"min_volume": float(vol.min())}),
        "gaussians": GaussiansArtefact(rng.integers(0, 2, g), bary / bary.sum(1, keepdims=True),
                                       rng.normal(size=(g, 3)), q / np.linalg.norm(q, axis=1, keepdims=True),
                                       rng.normal(size=g), rng.normal(size=(g, 4, 3)), {"cam0": 31.5},
                                       np.array([0.1, 0.2, 0.3])),
        "snapshots": SnapshotsArtefact(rng.normal(size=(4, 5, 3)), rng.uniform(1e4, 1e6, (4, 2)),
                                       rng.uniform(0.3, 0.49, (4, 2)), np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1]),
                                       ["body", "stiff"]),
        "subspace": SubspaceArtefact("autoencoder", 3, {"W0": rng.normal(size=(15, 3)), "idx": np.arange(4)},
                                     1e-4, 2e-4, {"layers": [200, 200]}),
        "adapt": AdaptArtefact(np.arange(3), rng.uniform(1e4, 1e5, (3, 2)), rng.uniform(0.3, 0.45, (3, 2)),
                               rng.normal(size=(3, 3)), rng.normal(size=(3, 5, 3)), rng.random(3), rng.random(3),
                               rng.random(3), rng.random(3), rng.random(3), ["body", "stiff"], "online", "reduced",
                               "vision", 5, {"note": "test"}),
    }


def _equal(a: object, b: object, float32: bool = False) -> None:
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, list) and x and isinstance(x[0], Camera):
            for c, d in zip(x, y):
                _equal(c, d)
        elif isinstance(x, dict):
            assert set(x) == set(y), f.name
            for k in x:
                if isinstance(x[k], np.ndarray):
                    np.testing.assert_array_equal(x[k], y[k])
                else:
                    assert x[k] == y[k]
        elif isinstance(x, np.ndarray):
            rtol = 1e-6 if float32 else 0
            np.testing.assert_allclose(np.asarray(y, float), np.asarray(x, float), rtol=rtol, atol=0, err_msg=f.name)
        elif isinstance(x, float) and np.isnan(x):
            assert np.isnan(y)
        else:
            assert x == y, f.name


@pytest.mark.parametrize("kind", sorted(KIND_FILES))
def test_round_trip_and_provenance(kind: str, tmp_path: Path) -> None:
    obj = make_all(np.random.default_rng(0))[kind]
    src = tmp_path / "input.txt"
    src.write_text("hello")
    path = tmp_path / KIND_FILES[kind]
    obj.save(path, Provenance.make({"capture": Path("cap"), "seed": np.int64(3)}, [src, tmp_path / "absent"]))
    back = ARTEFACT_TYPES[kind].load(path)
    _equal(obj, back, float32=(kind == "gaussians"))
    assert type(load_any(path)) is type(obj)
    prov = read_provenance(path)
    assert prov["rsl_kind"] == kind and prov["schema_version"] == A.SCHEMA_VERSION
    assert prov["rsl_version"] == A.RSL_VERSION and prov["created"].startswith("20")
    assert prov["config"] == {"capture": "cap", "seed": 3}
    assert prov["inputs"] == [{"path": "input.txt", "base": "workspace", "sha256": file_sha256(src)}]
    d = describe(path)
    assert d["attrs"]["rsl_kind"] == kind and len(d["datasets"]) >= 1
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_sha256_is_content_hash(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    a.write_bytes(b"x" * 3_000_000)
    b.write_bytes(b"x" * 3_000_000)
    assert file_sha256(a) == file_sha256(b)
    b.write_bytes(b"x" * 2_999_999 + b"y")
    assert file_sha256(a) != file_sha256(b)
    import hashlib

    assert file_sha256(a) == hashlib.sha256(a.read_bytes()).hexdigest()


def test_failed_write_keeps_old_artefact(tmp_path: Path) -> None:
    arts = make_all(np.random.default_rng(1))
    path = tmp_path / "mesh.h5"
    arts["mesh"].save(path)
    before = path.read_bytes()
    with pytest.raises(RuntimeError, match="boom"):
        with A.atomic_h5(path, "mesh", Provenance()) as f:
            f.create_dataset("vertices", data=np.zeros((2, 3)))
            assert any(p.name.endswith(".tmp") for p in tmp_path.iterdir())
            raise RuntimeError("boom")
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh.h5"]
    MeshArtefact.load(path)


def test_failed_save_of_bad_data_keeps_old_artefact(tmp_path: Path) -> None:
    """A save that fails half-way (an unconvertible field) leaves the old file and no temp file."""
    arts = make_all(np.random.default_rng(2))
    path = tmp_path / "adapt.h5"
    arts["adapt"].save(path)
    before = path.read_bytes()
    bad = dataclasses.replace(arts["adapt"], loss=np.array(["not", "a", "number"], dtype=object))
    with pytest.raises(Exception):
        bad.save(path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adapt.h5"]


def _write(tmp_path: Path, kind: str = "mesh") -> Path:
    path = tmp_path / KIND_FILES[kind]
    make_all(np.random.default_rng(3))[kind].save(path)
    return path


def test_reader_rejects_wrong_kind(tmp_path: Path) -> None:
    path = _write(tmp_path, "cameras")
    with pytest.raises(ArtefactError, match=r"cameras\.h5: is a 'cameras' artefact, expected 'mesh'"):
        MeshArtefact.load(path)


def test_reader_rejects_future_schema(tmp_path: Path) -> None:
    path = _write(tmp_path)
    with h5py.File(path, "a") as f:
        f.attrs["schema_version"] = A.SCHEMA_VERSION + 1
    with pytest.raises(ArtefactError, match="newer than this rsl understands"):
        MeshArtefact.load(path)


def test_reader_rejects_nan(tmp_path: Path) -> None:
    path = _write(tmp_path)
    with h5py.File(path, "a") as f:
        v = f["vertices"][()]
        v[1, 2] = np.nan
        f["vertices"][...] = v
    with pytest.raises(ArtefactError, match=r"mesh\.h5: dataset 'vertices' holds 1 NaN"):
        MeshArtefact.load(path)


def test_reader_rejects_truncated_file(tmp_path: Path) -> None:
    path = _write(tmp_path, "snapshots")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ArtefactError, match="snapshots.h5: not a readable HDF5 file"):
        SnapshotsArtefact.load(path)


def test_reader_rejects_missing_file_and_plain_hdf5(tmp_path: Path) -> None:
    with pytest.raises(ArtefactError, match="file not found"):
        MeshArtefact.load(tmp_path / "mesh.h5")
    with h5py.File(tmp_path / "plain.h5", "w") as f:
        f["x"] = np.zeros(3)
    with pytest.raises(ArtefactError, match="not an rsl artefact"):
        load_any(tmp_path / "plain.h5")


@pytest.mark.parametrize("edit, message", [
    (lambda f: f.__delitem__("tets"), "dataset 'tets' is missing"),
    (lambda f: (f.__delitem__("tets"), f.create_dataset("tets", data=np.zeros((2, 3), int))),
     r"'tets' should have shape \(\*, 4\)"),
    (lambda f: (f.__delitem__("tets"), f.create_dataset("tets", data=np.array([[0, 1, 2, 9]] * 2))),
     "outside 0..4"),
    (lambda f: f["rest_volumes"].__setitem__(0, -1.0), "non-positive rest volume"),
    (lambda f: (f.__delitem__("tets"), f.create_dataset("tets", data=np.zeros((2, 4)) + 0.5)),
     "should hold integers"),
])
def test_mesh_reader_validates(tmp_path: Path, edit, message: str) -> None:
    path = _write(tmp_path)
    with h5py.File(path, "a") as f:
        edit(f)
    with pytest.raises(ArtefactError, match=message) as e:
        MeshArtefact.load(path)
    assert str(path) in str(e.value)
    assert isinstance(e.value, RslError)


def test_cameras_reader_rejects_non_rotation(tmp_path: Path) -> None:
    path = _write(tmp_path, "cameras")
    with h5py.File(path, "a") as f:
        f["cameras/cam1/R"][...] = 2 * np.eye(3)
    with pytest.raises(ArtefactError, match="camera 'cam1' has a rotation R with determinant 8"):
        CamerasArtefact.load(path)


def test_masks_reader_rejects_unequal_frame_counts(tmp_path: Path) -> None:
    MasksArtefact({"a": np.zeros((3, 4, 4), bool), "b": np.zeros((2, 4, 4), bool)}, "x").save(tmp_path / "m.h5")
    with pytest.raises(ArtefactError, match=r"unequal frame counts \[2, 3\]"):
        MasksArtefact.load(tmp_path / "m.h5")


def test_gaussians_reader_checks_barycentrics(tmp_path: Path) -> None:
    g = make_all(np.random.default_rng(4))["gaussians"]
    dataclasses.replace(g, bary=g.bary * 2).save(tmp_path / "g.h5")
    with pytest.raises(ArtefactError, match="do not sum to 1"):
        GaussiansArtefact.load(tmp_path / "g.h5")


def test_masks_are_compressed_and_chunked(tmp_path: Path) -> None:
    MasksArtefact({"a": np.zeros((5, 64, 64), bool)}, "x").save(tmp_path / "m.h5")
    with h5py.File(tmp_path / "m.h5") as f:
        assert f["masks/a"].compression == "gzip" and f["masks/a"].chunks == (1, 64, 64)
    assert os.path.getsize(tmp_path / "m.h5") < 5 * 64 * 64


def test_provenance_config_json_is_sorted_and_plain(tmp_path: Path) -> None:
    @dataclasses.dataclass(frozen=True)
    class Cfg:
        capture: Path = Path("c")
        window: int = 5
        cams: tuple = (0, 1)

    path = tmp_path / "s.h5"
    make_all(np.random.default_rng(5))["subspace"].save(path, Provenance.make(Cfg()))
    with h5py.File(path) as f:
        raw = f.attrs["config"]
    assert json.loads(raw) == {"capture": "c", "cams": [0, 1], "window": 5}
