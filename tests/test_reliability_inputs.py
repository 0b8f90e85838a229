"""Everything a lab types is validated (issue 14): capture.toml and controls.json through the real CLI.

Each case breaks a copy of sample_data/bar (plus frames where needed) and runs `rsl info CAPTURE`, which reads
and checks all of a capture folder; the answer must be exit ≠ 0 and one sentence naming the file, where the
problem is and — for a typo — the nearest known key, with no traceback.  All cases run in one child process
(tests/reliability.py: batch).
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from reliability import SAMPLE, assert_one_sentence, batch, flat
from stages.capture import write_image

GROUPS = {"test_bad_capture_toml": "capture.toml: unknown keys, ranges, cameras",
          "test_bad_controls_json": "controls.json: unknown keys",
          "test_markup_in_user_text": "rich markup in user text",
          "test_good_capture_with_every_new_key": "legal inputs are accepted (no false alarm)"}
LABELS = {"test_good_capture_with_every_new_key": "every key other parts of rsl added ([capture] start, handle "
                                                  "hard, visual) is accepted"}

TOML = (SAMPLE / "bar" / "capture.toml").read_text()


def _toml(old: str, new: str) -> Callable[[Path], None]:
    def f(r: Path) -> None:
        text = (r / "capture.toml").read_text()
        assert old in text, old
        (r / "capture.toml").write_text(text.replace(old, new, 1))
    return f


def _append(extra: str) -> Callable[[Path], None]:
    return lambda r: (r / "capture.toml").write_text((r / "capture.toml").read_text() + extra)


def _controls(change: Callable[[dict], None]) -> Callable[[Path], None]:
    def f(r: Path) -> None:
        data = json.loads((r / "controls.json").read_text())
        change(data)
        (r / "controls.json").write_text(json.dumps(data))
    return f


def _frames(cams: list[str]) -> Callable[[Path], None]:
    def f(r: Path) -> None:
        for cam in dict.fromkeys(cams):
            for i in range(2):
                write_image(r / "frames" / cam / f"{i:06d}.png", np.zeros((4, 4, 3), np.uint8))
        _toml('cameras = []', f"cameras = {json.dumps(cams)}")(r)
    return f


def _rename(d: dict, where: Callable[[dict], dict], old: str, new: str) -> None:
    obj = where(d)
    obj[new] = obj.pop(old)


H0 = lambda d: d["handles"][0]  # noqa: E731
SPHERE = {"name": "pusher", "shape": "sphere", "radius": 0.01, "poses": [[0, 0, 0.5, 1, 0, 0, 0]]}

# case -> (what breaks the capture, the texts the one sentence must hold)
TOML_CASES: dict[str, tuple[Callable[[Path], None], tuple[str, ...]]] = {
    "typo 'youngs' in [material]": (_toml("young = 1.0e5", "youngs = 1.0e5"),
                                    ("capture.toml", "'material.youngs' is not a known key", "did you mean 'young'")),
    "misspelt table [materail]": (_toml("[material]", "[materail]"),
                                  ("capture.toml", "table '[materail]' is not a known table",
                                   "did you mean 'material'")),
    "typo 'fsp' in [capture]": (_toml("fps = 30.0", "fsp = 30.0"), ("'capture.fsp' is not a known key",
                                                                   "did you mean 'fps'")),
    "typo 'densty' in [object]": (_toml("density = 1070.0", "densty = 1070.0"),
                                  ("'object.densty' is not a known key", "did you mean 'density'")),
    "typo 'yung' in [regions.NAME]": (_append("[regions.head]\nyung = 2e5\n"),
                                      ("'regions.head.yung' is not a known key", "did you mean 'young'")),
    "typo 'bord' in [calibration]": (_append("[calibration]\nbord = 'chessboard:6x4:0.02'\n"),
                                     ("'calibration.bord' is not a known key", "did you mean 'board'")),
    "typo 'strat' in [capture]": (_toml("fps = 30.0", "fps = 30.0\nstrat = 'rest'"),
                                  ("'capture.strat' is not a known key", "did you mean 'start'")),
    "a key outside any table": (lambda r: (r / "capture.toml").write_text("fps = 30\n" + TOML),
                                ("capture.toml", "'fps' is not in a table", "[capture] fps")),
    "E outside young_range": (_toml("young = 1.0e5", "young = 5.0e6"),
                              ("'material.young' = 5e+06 Pa lies outside young_range",)),
    "region E outside young_range": (_append("[regions.head]\nyoung = 3e3\n"),
                                     ("'regions.head.young' = 3000 Pa lies outside material.young_range",)),
    "region ν = 0.5": (_append("[regions.head]\npoisson = 0.5\n"),
                       ("'regions.head.poisson' should lie in [0, 0.5), found 0.5",)),
    "region ν = 0.7": (_append("[regions.head]\npoisson = 0.7\n"),
                       ("'regions.head.poisson' should lie in [0, 0.5), found 0.7",)),
    "inverted young_range": (_toml("young_range = [1.0e4, 1.0e6]", "young_range = [1.0e6, 1.0e4]"),
                             ("'material.young_range' should be [low, high] with 0 < low ≤ high",)),
    "inverted poisson_range": (_toml("poisson_range = [0.3, 0.49]", "poisson_range = [0.45, 0.3]"),
                               ("'material.poisson_range' should be [low, high] within [0, 0.5)",)),
    "poisson_range reaching 0.5": (_toml("poisson_range = [0.3, 0.49]", "poisson_range = [0.3, 0.5]"),
                                   ("'material.poisson_range' should be [low, high] within [0, 0.5)",)),
    "duplicate camera names": (_frames(["cam0", "cam1", "cam0"]),
                               ("capture.toml", "'capture.cameras' lists camera 'cam0' twice")),
    "regions not a table of tables": (_append("regions = 3\n"), ("capture.toml",)),
}

CONTROLS_CASES: dict[str, tuple[Callable[[Path], None], tuple[str, ...]]] = {
    "top-level 'handle'": (_controls(lambda d: _rename(d, lambda x: x, "handles", "handle")),
                           ("'handle' is not a known key", "did you mean 'handles'")),
    "handle 'stifness'": (_controls(lambda d: _rename(d, H0, "stiffness", "stifness")),
                          ("'handles[0].stifness' is not a known key", "did you mean 'stiffness'")),
    "handle 'keyframe'": (_controls(lambda d: _rename(d, H0, "keyframes", "keyframe")),
                          ("'handles[0].keyframe' is not a known key", "did you mean 'keyframes'")),
    "keyframes 'frames'": (_controls(lambda d: _rename(d, lambda x: H0(x)["keyframes"], "frame", "frames")),
                           ("'handles[0].keyframes.frames' is not a known key", "did you mean 'frame'")),
    "select 'boxes'": (_controls(lambda d: _rename(d, lambda x: H0(x)["select"], "box", "boxes")),
                       ("'handles[0].select.boxes' is not a known key", "did you mean 'box'")),
    "select plane 'ofset'": (_controls(lambda d: H0(d).update(select={"plane": {"normal": [1, 0, 0], "ofset": 0}})),
                             ("'handles[0].select.plane.ofset' is not a known key", "did you mean 'offset'")),
    "handle 'hardd'": (_controls(lambda d: H0(d).update(hardd=True)),
                       ("'handles[0].hardd' is not a known key", "did you mean 'hard'")),
    "handle visual 'boxx'": (_controls(lambda d: H0(d).update(visual={"boxx": [[0, 0, 0], [1, 1, 1]]})),
                             ("'handles[0].visual.boxx' is not a known key", "did you mean 'box'")),
    "load 'forces'": (_controls(lambda d: d.update(loads=[{"name": "w", "select": {"ids": [0]},
                                                           "forces": [[0, 0, -1]]}])),
                      ("'loads[0].forces' is not a known key", "did you mean 'force'")),
    "load keyframes with 'pose'": (_controls(lambda d: d.update(loads=[{"name": "w", "select": {"ids": [0]},
                                                                        "keyframes": {"frame": [0], "pose": [[0, 0, 0]]}}])),
                                   ("'loads[0].keyframes.pose' is not a known key",)),
    "obstacle 'raduis'": (_controls(lambda d: d.update(obstacles=[{**{k: v for k, v in SPHERE.items()
                                                                       if k != "radius"}, "raduis": 0.01}])),
                          ("'obstacles[0].raduis' is not a known key", "did you mean 'radius'")),
    "obstacle 'pose'": (_controls(lambda d: d.update(obstacles=[{**{k: v for k, v in SPHERE.items()
                                                                     if k != "poses"}, "pose": SPHERE["poses"]}])),
                        ("'obstacles[0].pose' is not a known key", "did you mean 'poses'")),
    "top-level 'fricton'": (_controls(lambda d: d.update(fricton=0.2)),
                            ("'fricton' is not a known key", "did you mean 'friction'")),
}


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> dict:
    base = tmp_path_factory.mktemp("inputs")
    cases = {**TOML_CASES, **CONTROLS_CASES}
    commands, roots = [], {}
    for i, (name, (breaker, _)) in enumerate(sorted(cases.items())):
        root = base / f"c{i}"
        shutil.copytree(SAMPLE / "bar", root)
        breaker(root)
        roots[name] = root
        commands.append(["info", root])
    # rich markup in user text: a capture folder named like markup, with a bad key / a good one
    odd = base / "odd[bold]x[/]y"
    shutil.copytree(SAMPLE / "bar", odd)
    _toml("young = 1.0e5", "youngs = 1.0e5")(odd)
    odd_ok = base / "ok[red]z"
    shutil.copytree(SAMPLE / "bar", odd_ok)
    _toml('name = "bar"', 'name = "[/][bold]b"')(odd_ok)
    new_keys = base / "new_keys"
    shutil.copytree(SAMPLE / "bar", new_keys)
    _toml("fps = 30.0", "fps = 30.0\nstart = 'rest'")(new_keys)
    _controls(lambda d: (H0(d).update(hard=True), H0(d).update(visual={"box": [[0, 0, 0], [0.01, 0.01, 0.01]]})))(
        new_keys)
    extra = [["info", odd], ["info", odd_ok], ["info", new_keys], ["tetrahedralize", odd, "-w", base / "ws[/]w"]]
    procs = batch(commands + extra, base / "run")
    out = {name: (proc, roots[name]) for name, proc in zip(sorted(cases), procs)}
    out["_extra"] = (procs[len(commands):], odd, odd_ok)
    return out


@pytest.mark.parametrize("case", sorted(TOML_CASES))
def test_bad_capture_toml(case: str, results: dict) -> None:
    proc, root = results[case]
    assert_one_sentence(proc, str(root / "capture.toml"), *TOML_CASES[case][1])


@pytest.mark.parametrize("case", sorted(CONTROLS_CASES))
def test_bad_controls_json(case: str, results: dict) -> None:
    proc, root = results[case]
    assert_one_sentence(proc, str(root / "controls.json"), *CONTROLS_CASES[case][1])


@pytest.mark.parametrize("case", ["error naming a path with markup", "info of a name with markup",
                                  "stage error naming a workspace with markup"])
def test_markup_in_user_text(case: str, results: dict) -> None:
    """`[...]` in a path or a value is printed as it is, never eaten as rich markup nor a MarkupError."""
    procs, odd, odd_ok = results["_extra"]
    if case == "error naming a path with markup":
        assert_one_sentence(procs[0], f"{odd / 'capture.toml'}: 'material.youngs' is not a known key")
    elif case == "info of a name with markup":
        assert procs[1].returncode == 0, procs[1].stderr
        assert str(odd_ok) in flat(procs[1].stdout) and "capture [/][bold]b" in flat(procs[1].stdout)
    else:
        assert_one_sentence(procs[3], f"{odd / 'capture.toml'}: 'material.youngs'")


def test_good_capture_with_every_new_key(results: dict) -> None:
    """The keys other parts of rsl added ([capture] start, handle hard and visual) are known: no false alarm."""
    procs, _, _ = results["_extra"]
    assert procs[2].returncode == 0, procs[2].stderr
