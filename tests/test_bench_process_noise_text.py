"""bench/process_noise.py's page follows what its rows measured: per-segment errors of E over the settled frames,
the lowest value of each row in bold and its ratio to the baseline, one row per code that ran a workspace."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from test_bench_text import load_bench


def _row(value: float, err: float, code: str = "abc1234") -> dict:
    young_true = [[1e5]] * 12 + [[2e5]] * 12 + [[4e5]] * 12
    young = (np.asarray(young_true) * (1 + err)).tolist()
    return {"value": value, "case": "bar", "start": "moving", "loss": "silhouette", "space": "reduced",
            "cameras": 1, "dofs": 5000, "code": code, "median_error": err, "segment_errors": [err] * 3,
            "force_error": 0.3, "young": young, "young_true": young_true}


def test_segment_errors_are_medians_over_each_segments_settled_frames() -> None:
    m = load_bench("process_noise")
    young_true = np.array([[1.0]] * 12 + [[2.0]] * 12 + [[4.0]] * 12)
    young = young_true.copy()
    young[8:12] *= 1.1      # settled frames of the first segment (≥ w + 5 = 8 after the start)
    young[12:20] *= 0.5     # the second segment's unsettled frames: not counted
    young[32:] *= 0.98
    assert np.allclose(m.segment_errors(young, young_true), [0.1, 0.0, 0.02])


def test_process_noise_page_marks_the_lowest_value_and_keeps_codes_apart(tmp_path: Path) -> None:
    m = load_bench("process_noise")
    rows = [_row(0.005, 0.47, "old"), _row(0.03, 0.033, "old"), _row(0.005, 0.027, "new"), _row(0.03, 0.025, "new")]
    m.write(rows, [0.005, 0.03], tmp_path, {"truth_substeps": 24, "sequences": 12, "runs": []})
    md = (tmp_path / "process_noise.md").read_text()
    assert "| bar moving | silhouette | 1 | 5000 | old | 47.0 | **3.3** | 0.03 | 0.07 |" in md
    assert "| bar moving | silhouette | 1 | 5000 | new | 2.7 | **2.5** | 0.03 | 0.93 |" in md
    assert "| bar moving | silhouette | 1 | 5000 | new | 2.7 / 2.7 / 2.7 | 2.5 / 2.5 / 2.5 |" in md


def test_another_option_names_its_page_and_keeps_its_values_as_text(tmp_path: Path) -> None:
    """--option=--unseen-gaussians --values keep,ignore: the page unseen_gaussians.md, its columns the values as
    given, the baseline the first."""
    m = load_bench("process_noise")
    assert m.value("0.03") == 0.03 and m.value("keep") == "keep"
    rows = [{**_row(0.0, 0.337, "new"), "value": "keep", "loss": "vision"},
            {**_row(0.0, 0.166, "new"), "value": "ignore", "loss": "vision"}]
    m.write(rows, ["keep", "ignore"], tmp_path, {"truth_substeps": 24, "sequences": 12, "runs": [],
                                                 "option": "--unseen-gaussians"})
    md = (tmp_path / "unseen_gaussians.md").read_text()
    assert md.startswith("# `rsl adapt --unseen-gaussians` on captures filmed mid-motion")
    rows.append({**_row(0.0, 0.02, "new"), "value": "keep", "loss": "vision", "start": "equilibrium"})
    m.write(rows, ["keep", "ignore"], tmp_path, {"truth_substeps": 24, "sequences": 12, "runs": [],
                                                 "option": "--unseen-gaussians"})
    md = (tmp_path / "unseen_gaussians.md").read_text()
    assert md.startswith("# `rsl adapt --unseen-gaussians` on the accuracy bench's captures")
    assert "| bar equilibrium | vision | 1 | 5000 | new | **2.0** | — | keep | 1.00 |" in md
    assert "| capture | loss | cameras | DOFs | code | keep | ignore | best | best ÷ keep |" in md
    assert "| bar moving | vision | 1 | 5000 | new | 33.7 | **16.6** | ignore | 0.49 |" in md
    assert (tmp_path / "unseen_gaussians.json").is_file() and (tmp_path / "unseen_gaussians.png").is_file()
    assert not (tmp_path / "process_noise.md").exists()
