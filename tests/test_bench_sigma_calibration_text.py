"""bench/sigma_calibration.py's page follows the rows it reads: the truth inside ±2σ on the settled frames with the
floor each row ran with and with σ recomputed for other floors, the floor that just covers 90 % of them, and the
rows it cannot use left out by name."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from test_bench_text import load_bench


def _row(rel_error: np.ndarray, s_log: float, floor: float | None, regions: int = 1, **kw) -> dict:
    """A gn row of bench/accuracy.py: 36 frames, E_true constant 1e5, E = E_true (1 + rel_error) per frame, σ_E = E
    √(s_log² + floor²) (floor None: not recorded, the run's 2 %)."""
    e = 0.02 if floor is None else floor
    yt = np.full((36, regions), 1e5)
    y = yt * (1 + np.asarray(rel_error, float).reshape(36, -1))
    row = {"case": "bar", "start": "equilibrium", "loss": "markers", "space": "reduced", "order": 2,
           "cubature_tol": 0.0005, "cameras": 3, "adapt_options": [], "young": y.tolist(), "young_true": yt.tolist(),
           "young_sigma": (y * np.sqrt(s_log ** 2 + e ** 2)).tolist()}
    if floor is not None:
        row["young_model_error"] = np.full((36, regions), floor).tolist()
    return {**row, **kw}


def test_coverage_and_the_floor_that_covers_ninety_percent(tmp_path: Path) -> None:
    m = load_bench("sigma_calibration")
    # settled frames: 8..35 (≥ w + 5 after the start); 21 of 28 at 3 % error, 7 at 9 %; σ_logE = 1 %
    err = np.zeros(36)
    err[8:29], err[29:] = 0.03, 0.09
    f = m.row_frames(_row(err, 0.01, None), 0.02)
    assert len(f["rel"]) == 28 and f["floor"] == 0.02
    # 2σ at e = 0.02: 2 √(1e-4 + 4e-4) = 4.47 % relative to E (the error is relative to E as well)
    rel = err[8:] / (1 + err[8:])
    assert np.allclose(f["rel"], rel)
    assert np.mean(m.coverage(f)) == np.mean(rel <= 2 * np.sqrt(1e-4 + 4e-4))
    assert np.mean(m.coverage(f, 0.08)) == 1.0
    need = m.needed_floor(f)
    assert np.allclose(need, np.sqrt(np.maximum((rel / 2) ** 2 - 1e-4, 0)))
    assert np.all(m.coverage(f, float(need.max()) + 1e-9))  # the largest needed floor covers every frame
    # Adam on images: σ on its held fits only, NaN elsewhere; those frames are not counted
    adam = _row(err, 0.01, 0.04)
    adam["young_sigma"] = [[np.nan] if 10 <= t < 20 else s for t, s in enumerate(adam["young_sigma"])]
    adam["young_model_error"] = [[np.nan] if 10 <= t < 20 else e for t, e in enumerate(adam["young_model_error"])]
    g = m.row_frames(adam, 0.02)
    assert len(g["rel"]) == 18 and g["floor"] == 0.04 and np.allclose(g["rel"], np.r_[rel[:2], rel[12:]])


def test_page_leaves_out_rows_it_cannot_use_and_reads_recorded_floors(tmp_path: Path) -> None:
    m = load_bench("sigma_calibration")
    err = np.full(36, 0.03)
    page = tmp_path / "accuracy.json"
    rows = [_row(err, 0.005, 0.04),  # recorded floors
            _row(err, 0.005, None, space="full", cubature_tol=None),  # the 2 % of its time
            _row(err, 0.005, None, order=1),  # P1 in adapt: not read
            _row(err, 0.005, None, cubature_tol=0.002),  # another cubature tolerance: not read
            _row(np.full((36, 2), 0.03), 0.005, None, regions=2, case="beam"),  # spread floors not recorded
            {**_row(err, 0.005, None), "young_sigma": None}]  # Adam: no σ
    page.write_text(json.dumps({"plan": {"truth_substeps": 24}, "cases": rows}))
    got, skipped = m.load_rows([page], 0.0005, 0.02)
    assert [(r["space"], r["frames"]["floor"]) for r in got] == [("reduced", 0.04), ("full", 0.02)]
    assert len(skipped) == 1 and "beam" in skipped[0] and "floors not recorded" in skipped[0]
    m.write(got, skipped, [page], tmp_path / "out", 0.0005)
    md = (tmp_path / "out" / "sigma_calibration.md").read_text()
    # 3 % error, σ_logE 0.5 %: covered from e′ = 0.02 on (2 √(0.005² + 0.02²) = 4.1 % ≥ 2.9 %)
    assert "| reduced, markers, gn | 1 | 28 | 100 % | 100 % | 100 % | 100 % | 100 % | 100 % | 100 % |" in md
    assert "- Markers, full space: 100 % of 28 settled frames within ±2σ" in md
    assert "Left out (σ recorded, floors not recoverable): " in md
    assert (tmp_path / "out" / "sigma_calibration.json").is_file()
    assert (tmp_path / "out" / "sigma_calibration.png").is_file()
