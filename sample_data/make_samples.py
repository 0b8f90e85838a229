"""Rebuild sample_data/bar and sample_data/dino from the AutoDef meshes (Fulton et al. 2019, MIT).

    .venv/bin/python sample_data/make_samples.py [/path/to/shared/data]

bar:  onekbar.mesh (341 vertices, 979 tets; 0.5 × 1.5 × 0.5 units, long along y), scaled by 1/6
      to 0.25 m, turned so its axis is x, centred on the origin.  Both ends are held by handles;
      over 40 frames the right end is pulled 3 cm outward (frames 0–20) and then twisted by 90°
      about the bar's axis (frames 20–40) while the left end stays put.
dino: dino_ultra_low.mesh (256 vertices, 586 tets, 0.22 m tall, y up), turned to z up and set
      on the floor z = 0; a sphere of radius 3 cm moves in from the side and pushes its chest.
"""
from __future__ import annotations

import json
import math
import shutil
import sys
from pathlib import Path

import meshio
import numpy as np

HERE = Path(__file__).resolve().parent
SRC = Path(sys.argv[1]) if len(sys.argv) > 1 else HERE.parents[1] / "shared" / "data"

TOML = """[capture]
name = "{name}"
fps = 30.0
gravity = [0.0, 0.0, -9.81]
cameras = []

[object]
mesh = "object.mesh"
density = 1070.0

[material]
model = "stable_neohookean"
young = 1.0e5
poisson = 0.45
young_range = [1.0e4, 1.0e6]
poisson_range = [0.3, 0.49]
"""


def write_mesh(path: Path, v: np.ndarray, t: np.ndarray) -> None:
    meshio.write(str(path), meshio.Mesh(np.round(v, 9), [("tetra", t)]), file_format="medit")


def bar() -> None:
    m = meshio.read(SRC / "autodef_fulton" / "onekbar.mesh")
    v, t = np.asarray(m.points, float), np.asarray(m.cells_dict["tetra"])
    v = v / 6.0
    v = np.stack([v[:, 1], -v[:, 0], v[:, 2]], axis=1)  # rotation about z by −90°: axis y -> x
    v -= 0.5 * (v.min(0) + v.max(0))
    out = HERE / "bar"
    out.mkdir(exist_ok=True)
    write_mesh(out / "object.mesh", v, t)
    (out / "capture.toml").write_text(TOML.format(name="bar"))
    lo, hi = v.min(0), v.max(0)
    eps = 1e-3
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)  # 90° about x
    ident = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    controls = {
        "handles": [
            {"name": "left", "select": {"box": [[lo[0] - eps, lo[1] - eps, lo[2] - eps],
                                                [lo[0] + eps, hi[1] + eps, hi[2] + eps]]},
             "stiffness": 1.0e4, "keyframes": {"frame": [0, 40], "pose": [ident, ident]}},
            {"name": "right", "select": {"box": [[hi[0] - eps, lo[1] - eps, lo[2] - eps],
                                                 [hi[0] + eps, hi[1] + eps, hi[2] + eps]]},
             "stiffness": 1.0e4, "keyframes": {"frame": [0, 20, 40], "pose": [
                 ident, [0.03, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], [0.03, 0.0, 0.0, c, s, 0.0, 0.0]]}},
        ],
        "loads": [],
        "obstacles": [],
        "friction": 0.0,
    }
    (out / "controls.json").write_text(json.dumps(_rounded(controls), indent=1) + "\n")


def dino() -> None:
    m = meshio.read(SRC / "autodef_fulton" / "dino_ultra_low.mesh")
    v, t = np.asarray(m.points, float), np.asarray(m.cells_dict["tetra"])
    v = np.stack([v[:, 2], v[:, 0], v[:, 1]], axis=1)  # cyclic (x,y,z) -> (z,x,y): y up becomes z up
    v[:, :2] -= 0.5 * (v[:, :2].min(0) + v[:, :2].max(0))
    v[:, 2] -= v[:, 2].min()
    out = HERE / "dino"
    out.mkdir(exist_ok=True)
    write_mesh(out / "object.mesh", v, t)
    (out / "capture.toml").write_text(TOML.format(name="dino"))
    # Chest height and depth: the vertices 55–75 % of the way up.
    z0, z1 = v[:, 2].min(), v[:, 2].max()
    band = v[(v[:, 2] > z0 + 0.55 * (z1 - z0)) & (v[:, 2] < z0 + 0.75 * (z1 - z0))]
    cx, cz = float(np.median(band[:, 0])), float(np.median(band[:, 2]))
    y_side = float(v[:, 1].min())
    r = 0.03
    start = [cx, y_side - r - 0.02, cz, 1.0, 0.0, 0.0, 0.0]
    touch = [cx, y_side - r, cz, 1.0, 0.0, 0.0, 0.0]
    push = [cx, y_side - r + 0.03, cz, 1.0, 0.0, 0.0, 0.0]
    controls = {
        "handles": [],
        "loads": [],
        "obstacles": [
            {"name": "floor", "shape": "plane", "normal": [0.0, 0.0, 1.0], "offset": 0.0},
            {"name": "pusher", "shape": "sphere", "radius": r,
             "keyframes": {"frame": [0, 10, 30, 40], "pose": [start, touch, push, push]}},
        ],
        "friction": 0.8,
    }
    (out / "controls.json").write_text(json.dumps(_rounded(controls), indent=1) + "\n")


def _rounded(obj):
    if isinstance(obj, float):
        return round(obj, 6)
    if isinstance(obj, dict):
        return {k: _rounded(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_rounded(v) for v in obj]
    return obj


if __name__ == "__main__":
    bar()
    dino()
    shutil.copyfile(SRC / "autodef_fulton" / "LICENSE", HERE / "LICENSE.autodef")
    print("wrote", HERE / "bar", HERE / "dino")
