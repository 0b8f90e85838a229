"""The benchmark pages say only what the run measured: fed made-up measurements, the generated text
follows them (ratios, met / not met) and carries none of the hand-written notes' fixed statements."""
from __future__ import annotations

import copy
import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"


def load_bench(name: str):
    """bench/NAME.py loaded as a module (its main() not run)."""
    spec = importlib.util.spec_from_file_location(f"bench_{name}_text", ROOT / "bench" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _scaled(cases: list[dict], key: str, value: float) -> list[dict]:
    out = copy.deepcopy(cases)
    for c in out:
        c[key] = value
    return out


def test_reduced_vs_full_text_follows_the_ratios() -> None:
    m = load_bench("reduced_vs_full")
    d = json.loads((RESULTS / "reduced_vs_full.json").read_text())
    slow = m.markdown(d["machine"], d["date"], _scaled(d["cases"], "ratio", 4.25))
    assert "4.2× (not met)" in slow and "(met)" not in slow and "target holds" not in slow
    fast = m.markdown(d["machine"], d["date"], _scaled(d["cases"], "ratio", 31.5))
    assert "31.5× (met)" in fast and "not met" not in fast
    assert "reduced_vs_full_notes.md" in fast


def test_render_text_follows_the_measurements() -> None:
    m = load_bench("render")
    d = json.loads((RESULTS / "render.json").read_text())
    for key in ("ratio", "ratio_cpu", "ratio_lean", "ratio_lean_cpu"):
        d["cases"] = _scaled(d["cases"], key, 7.5)
    text = m.markdown(d)
    assert "7.5× in wall time" in text and "met in both columns" not in text.replace("not met in both", "")
    assert "render_notes.md" in text and "Between runs on this shared machine" not in text
    assert not hasattr(m, "AB_NOTE")


def test_adapt_text_quotes_the_measured_speedup() -> None:
    m = load_bench("adapt")
    d = json.loads((RESULTS / "adapt.json").read_text())
    for r in d["cases"]:
        if r.get("name") == "bar-like, reduced":
            r["physics_speedup"] = 12.5
    text = m._markdown(d)
    assert "physics speed-up 12.5×" in text
    assert "38×" not in text and "Observations" not in text and "adapt_notes.md" in text


@pytest.mark.parametrize("name", ["adapt", "reduced_vs_full", "render", "fem"])
def test_hand_written_notes_exist_and_are_dated(name: str) -> None:
    notes = RESULTS / f"{name}_notes.md"
    text = notes.read_text()
    assert "hand-written" in text and "never rewrites this file" in text
    date = json.loads((RESULTS / f"{name}.json").read_text())["date"][:10]
    assert date in text  # the note names the run it reads
    assert f"{name}_notes.md" in (RESULTS / f"{name}.md").read_text()


def test_calibration_segments_text_follows_the_rows(tmp_path) -> None:
    """bench/calibration_frames.py --segments: each row's minimum / E_new, where the split lies against the change
    and the grid-end flag come from the row (here one made-up row changed), rows sorted by capture, step, split, S."""
    mod = load_bench("calibration_frames")
    rows = json.loads((RESULTS / "calibration_segments.json").read_text())["rows"]
    made = copy.deepcopy(rows)
    made[0].update(young_min=0.777 * made[0]["e_new"], interior=False, split=made[0]["change"] + 2)
    mod.write_segments(made[::-1], tmp_path)
    md = (tmp_path / "calibration_segments.md").read_text()
    assert f"| {made[0]['split']} (2 late) |" in md and "0.777 (grid end)" in md
    assert md.index("bar_equilibrium") < md.index("bar_rest")
    for r in rows[1:]:
        assert f"{r['young_min'] / r['e_new']:.3f}" in md


def test_loss_sweep_keeps_truths_of_other_time_steps_apart(tmp_path, monkeypatch) -> None:
    """bench/loss_sweep.py --merge: a row against a truth with 24 substeps per frame sits beside the same
    start/loss/mesh row against the 3-substep truth (rows of older runs, without truth_substeps, are 3-substep
    ones), each with its own truth column, and the counts of minima within 3 % (all rows; those at rsl adapt's
    default substeps per truth) follow the ratios."""
    mod = load_bench("loss_sweep")
    old = json.loads((RESULTS / "loss_sweep.json").read_text())
    row = copy.deepcopy(old["cases"][0])
    row.pop("truth_substeps", None)
    far = dict(row, truth="P2 refined ×1, 24 substeps, hard handles", truth_substeps=24, ratio=1.021,
               young_min=1.021 * row["young_true"], adapt_mesh="P2, 6 substeps per frame (rsl adapt's default)")
    near = dict(row, ratio=0.5, young_min=0.5 * row["young_true"])
    (tmp_path / "a.json").write_text(json.dumps(dict(old, cases=[near])))
    (tmp_path / "b.json").write_text(json.dumps(dict(old, cases=[far])))
    monkeypatch.setattr("sys.argv", ["loss_sweep", "--merge", str(tmp_path / "a.json"), str(tmp_path / "b.json"),
                                     "--out", str(tmp_path / "out"), "--work", str(tmp_path / "work")])
    mod.main()
    md = (tmp_path / "out" / "loss_sweep.md").read_text()
    lines = [ln for ln in md.splitlines() if ln.startswith(f"| {row['start']} |")]
    assert len(lines) == 2
    assert any("| 3 |" in ln and "| 0.500 |" in ln for ln in lines)
    assert any("| 24 |" in ln and "| 1.021 |" in ln for ln in lines)
    assert "1 of 2 minima lie within 3 % of E_true" in md
    assert f"against the 24-substep truth 1 of 1 within 3 % ({row['loss']} {row['start']} 1.021)" in md
    assert "3-substep truth" not in md  # the 3-substep row is not at adapt's default


def test_moving_start_page_follows_its_rows(tmp_path) -> None:
    """bench/moving_start.py: the summary sentences carry the rows' own errors, per scene and lead-in; a row in
    several merged files is the last file's."""
    m = load_bench("moving_start")
    d = json.loads((RESULTS / "moving_start.json").read_text())
    rows = copy.deepcopy(d["cases"])
    for r in rows:
        if r.get("scene", "bar") == "bar" and r["lead_frames"] == 8 and r["declared"] == "moving":
            r["median_error"], r["median_ratio"] = 0.123, 1.123
    text = "\n".join(m.summary(rows))
    assert "bar, filmed from 8 frames into the motion: declared moving, median settled E error 12.3 % (E / E_true " \
           "1.123)" in text
    assert text.count("filmed from") == len({(r.get("scene", "bar"), r["lead_frames"]) for r in rows
                                             if r["lead_frames"]})
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps(d))
    b.write_text(json.dumps({**d, "cases": rows}))
    import sys

    argv = sys.argv
    try:
        sys.argv = ["moving_start.py", "--merge", str(a), str(b), "--out", str(tmp_path / "out")]
        m.main()
    finally:
        sys.argv = argv
    page = (tmp_path / "out" / "moving_start.md").read_text()
    assert "12.3 % (E / E_true 1.123)" in page
    assert page.count("| bar |") == sum(r.get("scene", "bar") == "bar" for r in rows)
    assert "](moving_start.png)" in page and (tmp_path / "out" / "moving_start.png").stat().st_size > 0


def test_late_markers_page_follows_its_rows(tmp_path) -> None:
    """bench/late_markers.py: each sentence carries its rows' errors (bound late, deleted, every marker seen over the
    same frames), one per capture and hidden span."""
    m = load_bench("late_markers")
    d = json.loads((RESULTS / "late_markers.json").read_text())
    rows = copy.deepcopy(d["cases"])
    for r in rows:
        if r["lead_frames"] == 0 and r["hidden_frames"] == 4 and r["markers"] == "bound late":
            r["median_error"] = 0.321
    text = "\n".join(m.summary(rows))
    assert "hidden over frames 0–3: bound late 32.1 %" in text
    assert text.count("markers hidden over") == len({(r["lead_frames"], r["hidden_frames"]) for r in rows
                                                     if r["hidden_frames"]})
    ref = next(r for r in rows if r["lead_frames"] == 0 and r["markers"] == "all seen")
    assert f"every marker seen {100 * m.same_frames_error(ref, 4):.1f} % over the same frames" in text


def test_damping_page_follows_its_rows(tmp_path) -> None:
    """bench/damping.py: E declared against undeclared per damped β_true, the truths' differences in time, and the
    plot."""
    m = load_bench("damping")
    d = json.loads((RESULTS / "damping.json").read_text())
    adapts = copy.deepcopy(d["adapt"])
    for r in adapts:
        if r["beta_true"] > 0 and r["declared"] == 0:
            r["median_error"], r["median_ratio"] = 0.234, 0.766
    text = "\n".join(m.summary(d["truths"], adapts))
    assert "undeclared 23.4 % (0.766)" in text
    assert text.count("the truths against") == len({r["beta"] for r in d["truths"]})
    m.write(d["truths"], adapts, tmp_path, d["plan"], d)
    page = (tmp_path / "damping.md").read_text()
    assert "undeclared 23.4 % (0.766)" in page and (tmp_path / "damping.png").stat().st_size > 0


def test_cubature_poisson_page_follows_its_rows() -> None:
    """bench/cubature_poisson.py: each row's errors per region and ν as measured, s / frame against its own
    one-ν run (the same label and options), a failed run said as such."""
    m = load_bench("cubature_poisson")
    d = json.loads((RESULTS / "cubature_poisson.json").read_text())
    rows = [r for r in d["rows"] if len(r.get("median_error", [])) == 2][:2]
    assert [r["variant"] for r in rows] == list(m.VARIANTS)
    rows = copy.deepcopy(rows)
    rows[0]["s_per_frame"], rows[1]["s_per_frame"] = 0.5, 1.6
    rows[1]["median_error"] = [0.0123, 0.0456]
    failed = dict(copy.deepcopy(rows[1]), label="x", adapt_error="the solve failed")
    page = m.markdown(dict(d, rows=rows + [failed]))
    assert "| 1.60 | 3.20 |" in page and "| 0.50 | 1.00 |" in page
    assert f"{rows[1]['regions'][0]} 1.2, {rows[1]['regions'][1]} 4.6" in page
    assert "adapt failed: the solve failed" in page
    rows[0]["median_error"] = [0.03, 0.12]  # one ν: a region past 10 %; two ν: 1.2 and 4.6 %
    page = m.markdown(dict(d, rows=rows + [failed]))
    assert "mean of the rows' largest median settled E error 12.0 % over 1 captures; 0 of 1 within" in page
    assert "error 4.6 % over 1 captures; 1 of 1 within" in page


def test_training_data_page_follows_its_rows() -> None:
    """bench/training_data.py: the coverage table and each run's errors as measured, the summary per (variant,
    sequences, r) computed from the runs, a failed run said as such."""
    m = load_bench("training_data")
    d = json.loads((RESULTS / "training_data.json").read_text())
    two = copy.deepcopy([r for r in d["rows"] if len(r.get("median_error", [])) == 2][0])
    one = copy.deepcopy([r for r in d["rows"] if len(r.get("median_error", [])) == 1][0])
    two.update(variant="v", sequences=7, dim=40, median_error=[0.0123, 0.0956], generate_s=None)
    one.update(variant="v", sequences=7, dim=40, median_error=[0.061])
    failed = dict(copy.deepcopy(one), error="generate-data: the solve failed")
    cov = [dict(d["coverage"][0], nu_p10=0.4321)]
    page = m.markdown(dict(d, rows=[two, one, failed], coverage=cov))
    assert f"{two['regions'][0]} 1.2, {two['regions'][1]} 9.6" in page and "| 0.43 |" in page
    assert "failed: generate-data: the solve failed" in page and "| — |" in page
    assert ("- v, 7 sequences, r = 40: mean of the runs' largest median settled E error 7.8 %, largest 9.6 %, over 2 "
            "runs; 1 of 2 within the targets") in page
    assert m.summary(d["rows"]) == [line for line in m.markdown(d).splitlines() if line.startswith("- ")]


def test_cubature_tol_page_follows_its_rows() -> None:
    """bench/cubature_tol.py: each row's errors as measured, s / frame against its workspace's first tolerance, a
    failed adapt said as such, the summary per tolerance computed from the rows."""
    m = load_bench("cubature_tol")
    base = {"label": "beam", "capture": "c", "workspace": "w", "sequences": 4, "dim": 30, "max_points": 600,
            "regions": ["body", "stiff"], "median_poisson": [0.45, 0.45]}
    rows = [dict(base, tol=0.002, points=100, fit_error_rel=0.0019, median_error=[0.088, 0.156], s_per_frame=0.5),
            dict(base, tol=0.0005, points=200, fit_error_rel=0.0004, median_error=[0.017, 0.014], s_per_frame=0.8),
            dict(base, workspace="w2", regions=["body"], tol=0.002, points=50, fit_error_rel=0.002,
                 median_error=[0.04], s_per_frame=1.0),
            dict(base, workspace="w2", tol=0.0005, points=90, fit_error_rel=0.0005, adapt_error="the solve failed")]
    page = m.markdown({"rows": rows, "ended": "t", "load_average": 1.0, "machine": "m"})
    assert "| body 8.8, stiff 15.6 | 0.50 | 1.00 |" in page and "| body 1.7, stiff 1.4 | 0.80 | 1.60 |" in page
    assert "adapt failed: the solve failed" in page
    assert ("- tol 0.002: mean of the rows' largest median settled E error 9.8 %, largest 15.6 %, over 2 workspaces; "
            "1 of 2 within the targets") in page
    assert "- tol 0.0005: mean of the rows' largest median settled E error 1.7 %" in page and "1.60 × the first" in page


def test_moving_images_page_follows_its_rows(tmp_path) -> None:
    """bench/moving_images.py: the committed page is what its JSON's rows write (but the time it was written), and a
    row's error shows in the table and in the per-capture summary."""
    m = load_bench("moving_images")
    d = json.loads((RESULTS / "moving_images.json").read_text())

    def body(text: str) -> list[str]:
        return [line for line in text.splitlines() if not line.startswith("Ended ")]

    m.write(d["rows"], tmp_path, d["plan"])
    assert body((tmp_path / "moving_images.md").read_text()) == body((RESULTS / "moving_images.md").read_text())
    rows = copy.deepcopy(d["rows"])
    first = rows[0]
    first["median_E_error_pct"] = 12.345
    m.write(rows, tmp_path, d["plan"])
    page = (tmp_path / "moving_images.md").read_text()
    assert "| 12.3 |" in page
    assert f"{first['cameras']} camera(s), k = {first['guess']:g}: 12.3 % against" in page
