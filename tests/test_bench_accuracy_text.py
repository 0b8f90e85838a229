"""bench/accuracy.py's page counts only what its rows measured: fed made-up rows, the ≤ 5 % / two-region / force
counts and the row names follow them, rows not re-run are listed apart, and a failed row says so."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np

from test_bench_text import load_bench


def _accuracy():
    return load_bench("accuracy")


def _row(case: str, space: str, errors: list[float], force: float | None) -> dict:
    young_true = [[1e5] * len(errors)] * 4
    return {"case": case, "start": "equilibrium", "order": 2, "loss": "markers", "space": space, "estimator": "gn",
            "dofs": 4914, "settled_frames": 2, "median_error_per_region": errors, "median_error_worst": max(errors),
            "force_error": force, "force_source": "replay", "surface_error_mm": 1.0, "time_per_frame_s": 0.5,
            "load_average": 3.0, "substeps": 1, "ended": "2026-01-01T00:00:00+00:00", "exported": True,
            "young": young_true, "young_true": young_true, "regions": [f"r{j}" for j in range(len(errors))],
            "cubature_tol": 0.002 if space == "reduced" else None, "cubature_points": 60}


def test_accuracy_text_follows_the_rows(tmp_path: Path) -> None:
    m = _accuracy()
    rows = [_row("bar", "reduced", [0.04], 0.09), _row("bar", "full", [0.07], 0.12),
            _row("beam", "reduced", [0.02, 0.12], 0.30), _row("dino", "reduced", [0.2], None)]
    failed = {**copy.deepcopy(rows[0]), "case": "dino", "space": "full", "error": "rsl adapt failed:\nboom"}
    old = _row("beam", "full", [0.01, 0.02], 0.05)
    plan = {"frames": 4, "refine": 0, "rows": [], "adapt_options": [],
            "previous": {"file": "old.json", "date": "2025-01-01", "merged_from": []}, "previous_rows": [old]}
    m.write(rows + [failed], tmp_path, False, plan, quiet=True)
    md = (tmp_path / "accuracy.md").read_text()
    assert "1 of 4 rows have every region's median E error ≤ 5 %; in the reduced space 1 of 3 " \
           "(bar equilibrium P2 markers reduced)" in md
    assert "0 of 1 rows with more than one region have every region within 10 %" in md
    assert "1 of 3 rows with a force error have it ≤ 10 % (bar equilibrium P2 markers reduced)" in md
    assert "Failed rows:" in md and "`boom`" in md
    table, _, rest = md.partition("**Not re-run**")
    assert "| beam | equilibrium | P2 | markers | full |" not in table  # the old row is listed apart only
    assert "| beam | equilibrium | P2 | markers | full |" in rest and "r0 1.0, r1 2.0" in rest
    assert "r0 2.0, r1 12.0" in table and "loss_sweep.md" in md and "accuracy_notes.md" in md
    data = json.loads((tmp_path / "accuracy.json").read_text())
    assert len(data["cases"]) == 5 and (tmp_path / "accuracy.png").is_file()


def test_a_paper_scale_row_is_named_with_its_cameras_and_apart_from_the_table_row(tmp_path: Path) -> None:
    m = _accuracy()
    table_row = {**_row("bar", "reduced", [0.04], 0.09), "force_source": "replay smoothed (1 detected change(s))"}
    paper_row = {**_row("bar", "reduced", [0.03], 0.05), "force_source": "replay smoothed (3 detected change(s))",
                 "scale": "paper", "cameras": 4, "resolution": 128,
                 "truth_refine": 1, "truth_tets": 7832}
    assert m.row_key(paper_row) != m.row_key(table_row)
    plan = {"frames": 4, "refine": 0, "rows": [], "adapt_options": []}
    m.write([table_row, paper_row], tmp_path, False, plan, quiet=True)
    md = (tmp_path / "accuracy.md").read_text()
    assert "| bar (paper scale) | equilibrium | P2 | markers | reduced | gn | 4914 | 4 × 128² |" in md
    assert "| bar | equilibrium | P2 | markers | reduced | gn | 4914 | 3 × 96² |" in md
    assert "Rows marked (paper scale)" in md and "7832 P2 tets" in md
    assert "2 of 2 rows have every region's median E error ≤ 5 %" in md
    assert md.count("replay smoothed (the changes it detected)") == 1  # one sentence per kind of replay


def test_merging_runs_keeps_the_row_that_ended_last(tmp_path: Path, monkeypatch) -> None:
    m = _accuracy()
    old = {**_row("bar", "reduced", [0.30], 0.2), "ended": "2026-01-01T00:00:00+00:00"}
    new = {**_row("bar", "reduced", [0.02], 0.05), "ended": "2026-02-01T00:00:00+00:00"}
    other = _row("dino", "reduced", [0.07], 0.08)
    plan = {"frames": 4, "refine": 0, "rows": [], "adapt_options": []}
    files = []
    for i, rows in enumerate(([new, other], [old])):  # the older run named last: the date decides, not the order
        f = tmp_path / f"run{i}.json"
        f.write_text(json.dumps({"date": "2026-02-02", "mode": "full", "load_average_end": 1.0, "plan": plan,
                                 "cases": rows}))
        files.append(str(f))
    monkeypatch.setattr("sys.argv", ["accuracy.py", "--merge", *files, "--out", str(tmp_path / "out")])
    m.main()
    data = json.loads((tmp_path / "out" / "accuracy.json").read_text())
    assert sorted((r["case"], r["median_error_worst"]) for r in data["cases"]) == [("bar", 0.02), ("dino", 0.07)]


def test_a_run_with_cameras_names_its_camera_count(tmp_path: Path, monkeypatch) -> None:
    """--cameras N (recorded in the plan): the merged page's header says how many cameras filmed the captures."""
    m = _accuracy()
    row = {**_row("bar", "reduced", [0.10], 0.2), "loss": "vision", "cameras": 1, "resolution": 96}
    f = tmp_path / "run.json"
    f.write_text(json.dumps({"date": "2026-02-02", "mode": "full", "load_average_end": 1.0, "cases": [row],
                             "plan": {"frames": 4, "refine": 0, "rows": [], "adapt_options": [], "cameras": 1}}))
    monkeypatch.setattr("sys.argv", ["accuracy.py", "--merge", str(f), "--out", str(tmp_path / "out")])
    m.main()
    md = (tmp_path / "out" / "accuracy.md").read_text()
    assert "1 camera at 96², 40 markers" in md and "| 1 × 96² |" in md


def test_the_header_names_the_tolerances_the_rows_used(tmp_path: Path) -> None:
    """Rows of one case fitted at two cubature tolerances (runs merged across a change of default): the header
    names both and points at the rows' column, not the bench's current default alone."""
    m = _accuracy()
    old, new = _row("bar", "reduced", [0.04], 0.09), {**_row("bar", "reduced", [0.05], 0.09), "start": "rest"}
    new["cubature_tol"] = 0.0005
    m.write([old, new, _row("dino", "full", [0.03], 0.05)], tmp_path, False,
            {"frames": 4, "refine": 0, "rows": [], "adapt_options": []}, quiet=True)
    md = (tmp_path / "accuracy.md").read_text()
    assert "`train-subspace --cubature-tol` bar 0.002 / 0.0005, beam 0.0005, dino 0.0005; each row's in its " \
           "cubature column)" in md


def test_settled_frames_follow_the_window() -> None:
    """Settled: ≥ w + 5 frames after the start and after each step of E_true, w the row's window (the bench's 3
    unless given)."""
    m = _accuracy()
    young = np.array([[1.0]] * 20 + [[2.0]] * 20)
    at3, at5 = m.settled_mask(young), m.settled_mask(young, window=5)
    assert np.flatnonzero(~at3).tolist() == list(range(8)) + list(range(20, 28))
    assert np.flatnonzero(~at5).tolist() == list(range(10)) + list(range(20, 30))


def test_the_poisson_column_shows_the_rows_nu_error_and_a_dash_before_it_was_recorded(tmp_path: Path) -> None:
    m = _accuracy()
    new = {**_row("beam", "reduced", [0.02, 0.12], 0.3), "poisson_abs_error_per_region": [0.0123, 0.0456]}
    old = _row("bar", "reduced", [0.04], 0.09)  # a row from before ν was recorded
    plan = {"frames": 4, "refine": 0, "rows": [], "adapt_options": []}
    m.write([new, old], tmp_path, False, plan, quiet=True)
    md = (tmp_path / "accuracy.md").read_text()
    header = next(line for line in md.splitlines() if line.startswith("| case |"))
    lines = [line for line in md.splitlines() if line.startswith("| beam |") or line.startswith("| bar |")]
    col = header.split(" | ").index("median \\|ν−ν_true\\| per region")  # (escaped: a table cell)
    cells = {line.split(" | ")[0]: line.split(" | ")[col] for line in lines}
    assert cells["| beam"] == "r0 0.012, r1 0.046" and cells["| bar"] == "—"
    cells_in = lambda line: line.replace("\\|", "").count("|")  # noqa: E731  (cell borders)
    assert all(cells_in(line) == cells_in(header) for line in lines) and "|E" not in header.replace("\\|E", "")


def test_rows_of_truths_with_other_substeps_say_so(tmp_path: Path, monkeypatch) -> None:
    m = _accuracy()
    monkeypatch.setattr(m, "TRUTH_SUBSTEPS", 3)
    plan = {"frames": 4, "refine": 0, "rows": [], "adapt_options": []}
    m.write([{**_row("bar", "reduced", [0.04], 0.09), "truth_substeps": 3}], tmp_path, False, plan, quiet=True)
    md = (tmp_path / "accuracy.md").read_text()
    assert "Truth: P2 tets, 3 substeps per frame" in md and "--substeps 3 " in md
    old = _row("dino", "reduced", [0.02], 0.05)  # a row from before the substeps were recorded
    m.write([{**_row("bar", "reduced", [0.04], 0.09), "truth_substeps": 24}, old], tmp_path, False, plan, quiet=True)
    md = (tmp_path / "accuracy.md").read_text()
    assert "as the truth-substeps column says" in md and "--substeps N " in md
    header = next(line for line in md.splitlines() if line.startswith("| case |"))
    col = header.split(" | ").index("truth substeps")
    cells = {line.split(" | ")[0]: line.split(" | ")[col] for line in md.splitlines() if line.startswith("| ")}
    assert cells["| bar"] == "24" and cells["| dino"] == "—"
