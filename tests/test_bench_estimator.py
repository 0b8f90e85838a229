"""bench/estimator.py runs rsl adapt at its own default --substeps and its page names the substeps each run
recorded in adapt.h5 (not a constant of the script)."""
from __future__ import annotations

import types
from pathlib import Path

import numpy as np
from test_bench_text import load_bench


def _bench():
    return load_bench("estimator")


def test_substeps_option_is_passed_only_when_asked() -> None:
    m = _bench()
    assert m._substeps_option(None) == []
    assert m._substeps_option(3) == ["--substeps", 3]


def test_substeps_used_is_read_from_the_provenance(tmp_path: Path) -> None:
    import h5py

    m = _bench()
    with h5py.File(tmp_path / "adapt.h5", "w") as f:
        f.attrs["config"] = '{"substeps": 5, "window": 3}'
    assert m.adapt_substeps_used(tmp_path / "adapt.h5") == 5


def _case(m, substeps, seed: int) -> dict:
    T = 12
    rel = 1.0 + 0.01 * np.sin(np.arange(T) + seed)
    sd = np.full(T, 0.02)
    nu, sdn = np.full(T, 0.45), np.full(T, 0.02)
    return {"scene": "bar constant", "seed": seed, "region": "body", "estimator": "gn", "options": [],
            "steps": [], "synth_s": 1.0, "s_per_frame": 1.0, "changes_detected": [], "innovation_ratio": [1.0] * T,
            **({} if substeps is None else {"adapt_substeps": substeps}),
            **m.metrics(rel, sd, np.ones(T), [], nu, sdn, nu),
            "young_rel": rel.tolist(), "sigma_rel": sd.tolist(), "poisson": nu.tolist(), "poisson_sigma": sdn.tolist()}


def test_page_names_the_recorded_substeps(tmp_path: Path) -> None:
    m = _bench()
    m.OUT = tmp_path
    args = types.SimpleNamespace(from_json=False, wall_s=60.0)
    m.write([_case(m, 6, 0), _case(m, 6, 1)], args)
    text = (tmp_path / "estimator.md").read_text()
    assert "6 substeps per frame (its default, read from adapt.h5's provenance)" in text
    assert "2 substeps per frame" not in text
    m.write([_case(m, 2, 0), _case(m, 6, 1)], args)  # runs that disagree: both values are named
    assert "2 / 6 substeps per frame" in (tmp_path / "estimator.md").read_text()
    assert m._used_substeps([_case(m, None, 0)]) == "unrecorded"
