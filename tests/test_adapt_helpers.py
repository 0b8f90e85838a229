"""Pieces of `rsl adapt` that need no simulator: tet refinement of the stiff regions, the choice of cameras and
the frame range (parameter maps and Adam: tests/test_parameters.py)."""
from __future__ import annotations

import numpy as np
import pytest


def test_refine_tets_keeps_volume_orientation_and_coarse_vertices():
    from stages.steps.adapt import refine_tets
    from stages.sim.mesh import signed_volumes

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float)
    t = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    t[1] = t[1][[0, 2, 1, 3]] if signed_volumes(v, t[1:])[0] < 0 else t[1]
    v2, t2, r2 = refine_tets(v, t, np.array([0, 1]))
    assert np.array_equal(v2[:5], v)
    vol = signed_volumes(v2, t2)
    assert np.all(vol > 0)
    assert np.allclose(vol.reshape(2, 8).sum(1), signed_volumes(v, t))
    assert np.array_equal(r2, [0] * 8 + [1] * 8)
    assert len(v2) == 5 + 9  # 9 distinct edges


def test_camera_choice_by_index_or_name_and_its_errors():
    from pathlib import Path

    from stages.observations import pick_cameras
    from stages.errors import RslError

    names = ["cam0", "cam1", "cam2"]
    assert pick_cameras("", names, Path("cameras.h5")) == names
    assert pick_cameras("2, 0", names, Path("cameras.h5")) == ["cam2", "cam0"]
    assert pick_cameras("cam1,1", names, Path("cameras.h5")) == ["cam1"]
    with pytest.raises(RslError, match="asks for camera 5 but it holds 3"):
        pick_cameras("5", names, Path("cameras.h5"))
    with pytest.raises(RslError, match="'left', which is not one of"):
        pick_cameras("left", names, Path("cameras.h5"))


def test_frame_range_parsing():
    from pathlib import Path

    from stages.steps.adapt import _parse_frames
    from stages.errors import RslError

    assert _parse_frames("", 40, Path("c")) == (0, 40)
    assert _parse_frames("5:20", 40, Path("c")) == (5, 20)
    assert _parse_frames("5:", 40, Path("c")) == (5, 40)
    assert _parse_frames(":7", None, Path("c")) == (0, 7)
    for bad, msg in (("7:3", "empty or negative"), ("0:50", "only 40 exist"), ("a:b", "should be A:B")):
        with pytest.raises(RslError, match=msg):
            _parse_frames(bad, 40, Path("c"))
