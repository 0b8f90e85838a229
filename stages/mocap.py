"""Motion-capture marker files: markers.csv and markers.c3d -> one (T, M, 3) array in metres.

Both formats read into :class:`MarkerData`: positions (T, M, 3) in metres with NaN where a marker was
not observed (a gap), the frame rate (Hz, None for CSV, which does not record one) and the marker labels.

- markers.csv: header ``frame,marker,x,y,z`` (metres); a gap is an absent (frame, marker) row or a row with
  x, y and z all empty; markers are the distinct integer ids in increasing order; frames run 0..T−1.
- markers.c3d (read and written with ezc3d): POINT:UNITS (mm, cm, m, in, ft) scales to metres; the rate is
  the header's point frame rate; a point whose residual is negative (the C3D convention for "not seen") or
  whose coordinates are not finite is a gap; labels from POINT:LABELS.  The first recorded frame is frame 0.

:func:`check_bindable` holds the rules ``rsl adapt`` needs on top of the file format (each marker seen at
least once, some marker at frame 0).  Every problem raises
:class:`~stages.domain.errors.CaptureError` with one sentence naming the file.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stages.domain.errors import CaptureError

UNIT_TO_M = {"mm": 1e-3, "millimeter": 1e-3, "millimeters": 1e-3, "cm": 1e-2, "m": 1.0, "meter": 1.0,
             "meters": 1.0, "in": 0.0254, "inch": 0.0254, "ft": 0.3048}
"""POINT:UNITS of a C3D file -> metres per unit."""
CSV_HEADER = ["frame", "marker", "x", "y", "z"]


def _error(message: str) -> CaptureError:
    return CaptureError(message)


@dataclass
class MarkerData:
    """Marker trajectories: positions (T, M, 3) m, NaN at a gap; rate in Hz (None: unknown); labels (M,)."""

    positions: np.ndarray
    rate_hz: float | None = None
    labels: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.positions = np.asarray(self.positions, np.float64)
        if not self.labels:
            self.labels = [str(i) for i in range(self.positions.shape[1])]

    @property
    def observed(self) -> np.ndarray:
        """(T, M) bool: the marker's three coordinates are finite."""
        return np.all(np.isfinite(self.positions), axis=-1)


# =========================================================================== CSV
def read_csv(path: str | Path) -> MarkerData:
    """markers.csv -> MarkerData (module doc); labels are the marker ids as text, rate None.

    Rejected, each with one sentence naming the file: a header other than frame,marker,x,y,z; a row that is
    not numbers, or writes a non-finite value (nan, inf) or only some of x, y, z; a repeated (frame, marker)
    row; frames not 0..T−1.
    """
    path = Path(path)
    rows: list[tuple[int, int, float, float, float]] = []
    try:
        f = open(path, newline="")
    except OSError as e:
        raise _error(f"{path}: cannot read the file ({e.strerror}).") from None
    with f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None or [h.strip() for h in header] != CSV_HEADER:
            raise _error(f"{path}: header should be 'frame,marker,x,y,z', found {header}.")
        for ln, row in enumerate(reader, start=2):
            if not row:
                continue
            if len(row) == 5 and all(not v.strip() for v in row[2:5]):
                xyz = [math.nan] * 3  # an explicit gap
                try:
                    fr, mk = int(row[0]), int(row[1])
                except ValueError:
                    raise _error(f"{path}: line {ln} is not 'frame,marker,x,y,z' numbers: {row}.") from None
            else:
                try:
                    fr, mk = int(row[0]), int(row[1])
                    xyz = [float(v) for v in row[2:5]]
                except (ValueError, IndexError):
                    raise _error(f"{path}: line {ln} is not 'frame,marker,x,y,z' numbers "
                                 f"(a gap leaves x, y and z all empty): {row}.") from None
                if len(row) != 5 or not all(math.isfinite(v) for v in xyz):
                    raise _error(f"{path}: line {ln} should hold 5 finite values (or a gap: x, y and z all "
                                 f"empty), found {row}.")
            rows.append((fr, mk, *xyz))
    if not rows:
        raise _error(f"{path}: holds no marker rows.")
    arr = np.array(rows)
    frames = np.unique(arr[:, 0]).astype(int)
    markers = np.unique(arr[:, 1]).astype(int)
    if not np.array_equal(frames, np.arange(len(frames))):
        raise _error(f"{path}: frames should run 0..T-1 without gaps (a frame where no marker is seen "
                     f"needs one row with x, y and z empty).")
    out = np.full((len(frames), len(markers), 3), np.nan)
    seen = np.zeros((len(frames), len(markers)), bool)
    mindex = {m: i for i, m in enumerate(markers)}
    for fr, mk, x, y, z in arr:
        t, m = int(fr), mindex[int(mk)]
        if seen[t, m]:
            raise _error(f"{path}: marker {int(mk)} is listed twice at frame {t}.")
        seen[t, m] = True
        out[t, m] = (x, y, z)
    return MarkerData(out, None, [str(m) for m in markers])


def write_csv(path: str | Path, positions: np.ndarray) -> None:
    """(T, M, 3) metres -> markers.csv with marker ids 0..M−1.  An entry with a NaN (a gap) is left out, so a
    marker never observed does not appear at all (its id is skipped); a frame with no observed marker is
    written as one row of the first observed marker with x, y and z empty (so the file still holds frames
    0..T−1)."""
    markers = np.asarray(positions, float)
    seen_all = np.all(np.isfinite(markers), axis=-1)  # (T, M)
    anywhere = np.flatnonzero(seen_all.any(axis=0))
    placeholder = int(anywhere[0]) if len(anywhere) else 0
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_HEADER)
        for t in range(markers.shape[0]):
            seen = seen_all[t]
            if not seen.any():
                w.writerow([t, placeholder, "", "", ""])
            for m in np.flatnonzero(seen):
                w.writerow([t, m, *(f"{v:.9g}" for v in markers[t, m])])


# =========================================================================== C3D
def read_c3d(path: str | Path) -> MarkerData:
    """markers.c3d -> MarkerData in metres (module doc)."""
    path = Path(path)
    if not path.is_file():
        raise _error(f"{path}: file not found.")
    import ezc3d

    try:
        c = ezc3d.c3d(str(path), extract_forceplat_data=False)
    except Exception as e:  # ezc3d raises RuntimeError / IOError with its own text
        raise _error(f"{path}: cannot read it as a C3D file ({str(e).strip() or type(e).__name__}).") from None
    params = c["parameters"].get("POINT", {})
    pts = np.asarray(c["data"]["points"], np.float64)  # (4, M, T)
    if pts.ndim != 3 or pts.shape[1] == 0 or pts.shape[2] == 0:
        raise _error(f"{path}: holds no 3D points (POINT:USED is 0 or no frames).")
    units = [str(u).strip().lower() for u in params.get("UNITS", {}).get("value", []) if str(u).strip()]
    if not units:
        raise _error(f"{path}: POINT:UNITS is missing; cannot tell the marker units.")
    if units[0] not in UNIT_TO_M:
        raise _error(f"{path}: POINT:UNITS is '{units[0]}'; expected one of mm, cm, m, in, ft.")
    scale = UNIT_TO_M[units[0]]
    rate = float(c["header"]["points"]["frame_rate"])
    if not rate > 0:
        rate_p = params.get("RATE", {}).get("value", [])
        rate = float(rate_p[0]) if len(rate_p) else 0.0
    if not rate > 0:
        raise _error(f"{path}: records no point frame rate (header and POINT:RATE are 0).")
    xyz = pts[:3].transpose(2, 1, 0) * scale  # (T, M, 3)
    gap = ~np.all(np.isfinite(xyz), axis=-1)
    res = c["data"].get("meta_points", {}).get("residuals")
    if res is not None and np.shape(res)[1:] == pts.shape[1:]:
        gap |= (np.asarray(res)[0] < 0).T
    xyz[gap] = np.nan
    m = pts.shape[1]
    labels = [str(s).strip() for s in params.get("LABELS", {}).get("value", [])][:m]
    labels += [f"marker{i}" for i in range(len(labels), m)]
    return MarkerData(xyz, rate, labels)


def write_c3d(path: str | Path, data: MarkerData, units: str = "mm") -> None:
    """MarkerData (metres) -> a C3D file with POINT:UNITS ``units`` (float storage); a gap is written as
    NaN coordinates with residual −1."""
    import ezc3d

    if units not in UNIT_TO_M:
        raise ValueError(f"units {units!r}: use one of {', '.join(UNIT_TO_M)}")
    if not data.rate_hz or not data.rate_hz > 0:
        raise ValueError("a C3D file needs a positive frame rate")
    P = np.asarray(data.positions, np.float64)
    T, M, _ = P.shape
    gap = ~data.observed
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(data.rate_hz)]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(data.labels)
    c["parameters"]["POINT"]["UNITS"]["value"] = [units]
    d = np.ones((4, M, T))
    d[:3] = np.where(gap[..., None], np.nan, P / UNIT_TO_M[units]).transpose(2, 1, 0)
    c["data"]["points"] = d
    c["data"]["meta_points"] = {"residuals": np.where(gap, -1.0, 0.0).T[None]}
    c.write(str(path))


# =========================================================================== either
def read_markers_file(path: str | Path) -> MarkerData:
    """markers.csv or markers.c3d by the file's suffix."""
    path = Path(path)
    if path.suffix.lower() == ".c3d":
        return read_c3d(path)
    if path.suffix.lower() == ".csv":
        return read_csv(path)
    raise _error(f"{path}: marker files are .csv or .c3d.")


def check_bindable(data: MarkerData, path: str | Path) -> None:
    """What ``rsl adapt`` needs: every marker observed at least once, and some marker at frame 0 (those seen there
    are bound to the surface point nearest their frame-0 position; a marker first seen later is bound to its track
    once seen, stages.observations.MarkerObservation)."""
    obs = data.observed
    labels = np.asarray(data.labels, dtype=object)
    never = labels[~obs.any(axis=0)]
    if len(never):
        raise _error(f"{path}: marker(s) {', '.join(map(str, never[:10]))} are never observed.")
    if len(labels) and not obs[0].any():
        raise _error(f"{path}: no marker is observed at frame 0; rsl adapt binds the markers seen there to the "
                     f"frame-0 surface, so at least one must be.")


def check_rate(data: MarkerData, path: str | Path, fps: float, toml_path: str | Path) -> None:
    """A recorded rate must equal the capture's frame rate (markers are read one row per video frame)."""
    if data.rate_hz is not None and abs(data.rate_hz - fps) > 1e-6 * max(fps, 1.0):
        raise _error(f"{path}: markers are recorded at {data.rate_hz:g} Hz but {toml_path} 'capture.fps' is "
                     f"{fps:g}; resample the markers to the video frame rate (one sample per frame).")


def c3d_to_csv(src: str | Path, dst: str | Path) -> MarkerData:
    """Convert markers.c3d to markers.csv (metres, marker ids 0..M−1 in the C3D's order; a marker never observed
    is left out, its id skipped); returns what was read."""
    data = read_c3d(src)
    write_csv(dst, data.positions)
    return data
