"""stages/results.py, the reading of an adapt result shared by evaluate, export and report: each helper against
the plain rule it states (hand-written twins below)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from stages.artefacts import Provenance, mesh_artefact
from stages.results import compute_stress, gaussian_anchor, material_setting, previous_states, recorded_capture
from stages.results import window_young
from stages.sim import stress as st
from stages.sim.meshgen import box_tets


def test_previous_states_takes_consecutive_rows_else_the_one_before_else_rest():
    rest = np.zeros((2, 3))
    pos = np.arange(5)[:, None, None] + np.ones((5, 2, 3))  # row i holds i + 1
    frames = np.array([0, 1, 2, 5, 6])
    a, b = previous_states(frames, pos, rest, 2)
    assert a[0, 0] == 2 and b[0, 0] == 1  # frames 1 and 0
    a, b = previous_states(frames, pos, rest, 3)
    assert a is rest and b is rest  # frame 5 follows 2: a gap
    a, b = previous_states(frames, pos, rest, 4)
    assert a[0, 0] == 4 and b[0, 0] == 4  # frame 5 before, frame 4 missing: x_{t−2} = x_{t−1}
    a, b = previous_states(frames, pos, rest, 0)
    assert a is rest and b is rest


def test_recorded_capture_resolves_the_config_then_the_workspace_then_the_inputs(tmp_path):
    cap = tmp_path / "cap"
    cap.mkdir()
    (cap / "capture.toml").write_text("")
    ws = tmp_path / "ws"
    ws.mkdir()
    assert recorded_capture({"config": {"capture": str(cap)}}) == cap
    rel = "h6_capture_beside_the_workspace"  # relative: found from the workspace, not from the current folder
    (ws / rel).mkdir()
    assert recorded_capture({"config": {"capture": rel}}, ws) == ws / rel
    assert recorded_capture({"config": {"capture": rel}}) is None
    gone = {"config": {"capture": str(tmp_path / "gone")}, "inputs": [{"path": str(cap / "capture.toml")}]}
    assert recorded_capture(gone) == cap
    assert recorded_capture({"config": {}}) is None


def test_material_setting_prefers_the_capture_then_adapt_extra():
    adapt = SimpleNamespace(extra={"material_model": "neohookean", "dt": 0.01, "gravity": [0, -9.8, 0]})
    model, dt, g = material_setting(None, adapt)
    assert (model, dt) == ("neohookean", 0.01) and np.allclose(g, [0, -9.8, 0])
    model, dt, g = material_setting(None, SimpleNamespace(extra={}))
    assert (model, dt) == ("stable_neohookean", 1.0 / 30.0) and np.allclose(g, [0, 0, -9.81])
    cap = SimpleNamespace(material=SimpleNamespace(model="corotated"), dt=0.02, gravity=np.array([0, 0, -1.0]))
    model, dt, g = material_setting(cap, adapt)
    assert (model, dt) == ("corotated", 0.02) and np.allclose(g, [0, 0, -1])


def _trajectory(order: int):
    v, t = box_tets((2, 1, 1), (0.2, 0.1, 0.1))
    region = (np.arange(len(t)) % 2).astype(np.int64)
    mesh = mesh_artefact(v, t, 1000.0, region, ("a", "b"), order=order)
    rng = np.random.default_rng(0)
    T = 3
    pos = mesh.vertices[None] * np.array([1.05, 0.98, 1.0]) + 1e-3 * rng.normal(size=(T,) + mesh.vertices.shape)
    adapt = SimpleNamespace(frames=np.arange(T), positions=pos, young=np.tile([5e4, 2e5], (T, 1)),
                            poisson=np.tile([0.3, 0.45], (T, 1)))
    return mesh, adapt


def test_stress_of_linear_tets_is_the_per_tet_stress_and_its_volume_average():
    mesh, adapt = _trajectory(1)
    field = compute_stress(adapt, mesh, "stable_neohookean")
    n, m = mesh.n_vertices, mesh.n_tets
    for i in range(len(adapt.frames)):
        mu, lam = st.tet_lame_from_regions(adapt.young[i], adapt.poisson[i], mesh.tet_region)
        s = st.tet_stress(adapt.positions[i], mesh.tets, mesh.dm_inv, mu, lam, "stable_neohookean")
        np.testing.assert_allclose(field.von_mises_tet[i], s["von_mises"], rtol=1e-12)
        np.testing.assert_allclose(field.sigma[i], s["sigma"], rtol=1e-12, atol=1e-9)
        num, den = np.zeros(n), np.zeros(n)  # a_i = Σ_{e∋i} V_e a_e / Σ_{e∋i} V_e, written out
        for e in range(m):
            for k in mesh.tets[e]:
                num[k] += mesh.rest_volumes[e] * s["von_mises"][e]
                den[k] += mesh.rest_volumes[e]
        np.testing.assert_allclose(field.von_mises_vertex[i], num / den, rtol=1e-12)
        # internal forces sum to zero (translation invariance of the elastic energy)
        np.testing.assert_allclose(field.forces[i].sum(0), 0.0, atol=1e-9 * np.abs(field.forces[i]).max())
    assert field.von_mises_point is None and field.point_element is None


@pytest.mark.parametrize("order", [1, 2])
def test_stress_without_sigma_gives_the_same_fields(order):
    mesh, adapt = _trajectory(order)
    full = compute_stress(adapt, mesh, "stable_neohookean")
    lean = compute_stress(adapt, mesh, "stable_neohookean", sigma=False)
    assert lean.sigma is None and full.sigma.shape == (3, mesh.n_tets, 3, 3)
    for name in ("von_mises_tet", "von_mises_vertex", "forces"):
        np.testing.assert_array_equal(getattr(lean, name), getattr(full, name))
    if order == 2:
        assert full.von_mises_point.shape[0] == 3 and len(full.point_element) == full.von_mises_point.shape[1]


class _Renderer:
    def __init__(self, fit_positions):
        self.fit_positions, self.rebound = fit_positions, None

    def rebind(self, x):
        self.rebound = x


def test_gaussian_anchor_rebinds_or_offsets_at_the_fit_frame(tmp_path):
    mesh, adapt = _trajectory(1)
    path = mesh.save(tmp_path / "g.h5", Provenance(config={"frame": 1}))  # any artefact: only its provenance
    fit = mesh.vertices
    r = _Renderer(fit)
    adapt.extra = {"gaussian_anchor": "rebind"}
    assert gaussian_anchor(r, adapt, path) == 0.0
    np.testing.assert_array_equal(r.rebound, adapt.positions[1])
    r = _Renderer(fit)
    adapt.extra = {}  # older files: the offset
    np.testing.assert_array_equal(gaussian_anchor(r, adapt, path), adapt.positions[1] - fit)
    assert r.rebound is None
    adapt.frames = np.array([5, 6, 7])  # the fit frame is not in adapt.h5
    assert gaussian_anchor(_Renderer(fit), adapt, path) == 0.0


def test_window_young_is_the_windows_own_estimate_only_where_e_is_held():
    """stages.results.window_young: extras ``window_young`` (T, R) where it differs from E(t) (rsl adapt --hold-fit
    held E at the fits); None without it, with the wrong length, or equal to E(t)."""
    young = np.array([[1.0e5], [1.0e5], [2.0e5]])
    own = [[0.9e5], [1.1e5], [2.0e5]]
    np.testing.assert_array_equal(window_young(SimpleNamespace(young=young, extra={"window_young": own})), own)
    assert window_young(SimpleNamespace(young=young, extra={})) is None
    assert window_young(SimpleNamespace(young=young, extra=None)) is None
    assert window_young(SimpleNamespace(young=young, extra={"window_young": own[:2]})) is None
    assert window_young(SimpleNamespace(young=young, extra={"window_young": young.tolist()})) is None
