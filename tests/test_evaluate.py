"""`rsl evaluate` pieces: the surface distance it reports, and its errors on bad input."""
from __future__ import annotations

import numpy as np
import pytest

from stages.steps.evaluate import point_surface_distance, surface_samples, symmetric_surface_distance


def _square(z: float, k: int = 4, size: float = 1.0):
    """A k×k-cell square in the plane at height z (triangulated), vertices (·, 3), faces (·, 3)."""
    g = np.linspace(0, size, k + 1)
    X, Y = np.meshgrid(g, g, indexing="ij")
    v = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], 1)
    idx = np.arange(v.shape[0]).reshape(k + 1, k + 1)
    f = []
    for i in range(k):
        for j in range(k):
            a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
            f += [[a, b, c], [a, c, d]]
    return v, np.array(f)


def test_samples_are_area_weighted_and_on_the_surface():
    v, f = _square(0.3, k=3, size=2.0)
    p, w = surface_samples(v, f)
    assert np.isclose(w.sum(), 1.0)
    assert np.allclose(p[:, 2], 0.3)
    assert np.allclose(w @ p[:, :2], [1.0, 1.0])  # centroid of the square


def test_point_to_surface_distance_is_exact_for_planes_and_edges():
    v, f = _square(0.0)
    pts = np.array([[0.5, 0.5, 0.25], [0.5, 0.5, -0.1], [1.5, 0.5, 0.0], [2.0, 2.0, 1.0]])
    d = point_surface_distance(pts, v, f)
    assert np.allclose(d, [0.25, 0.1, 0.5, np.sqrt(1 + 1 + 1)], atol=1e-6)


def test_symmetric_distance_between_different_meshes_of_parallel_squares():
    va, fa = _square(0.0, k=2)
    vb, fb = _square(0.02, k=7)  # another triangulation, 2 cm above
    assert symmetric_surface_distance(va, fa, vb, fb) == pytest.approx(0.02, abs=1e-6)
    assert symmetric_surface_distance(va, fa, va, fa) == pytest.approx(0.0, abs=1e-7)
    # symmetric: a small patch inside a large one is close one way, far the other way
    vs, fs = _square(0.0, k=2, size=0.1)
    d1 = symmetric_surface_distance(vs, fs, va, fa)
    d2 = symmetric_surface_distance(va, fa, vs, fs)
    assert d1 == pytest.approx(d2) and d1 > 0.1


def test_evaluate_cli_needs_truth(rsl, tmp_path):
    cap = tmp_path / "cap"
    cap.mkdir()
    (cap / "capture.toml").write_text('[object]\nmesh = "object.obj"\n')
    (cap / "object.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    proc = rsl("evaluate", cap, "-w", tmp_path / "ws")
    assert proc.returncode != 0
    assert "material.csv" in proc.stderr and "truth" in proc.stderr
