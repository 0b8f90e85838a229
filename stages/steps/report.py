"""`rsl report`: one self-contained HTML page of what a workspace holds → WS/report.html.

Sections (each made from the artefacts present; one that cannot be made says why):

* material   E(t) and ν(t) per region from adapt.h5, with the band E ± σ where adapt.h5 holds
             ``young_sigma`` (Pa) and the truth of truth/material.csv when the capture has one;
* renders    for a few frames: the capture's photo, the adapted Gaussians rendered from the same
             camera (stages.render.image_loss.ImageLoss, as ``rsl evaluate`` renders them), the residual
             |render − photo| as adapt's image loss compares them (stages.observations.target_image) and the
             same Gaussians coloured by von Mises stress (turbo map, 0 … 99th percentile);
* stress     max / 99th percentile / median von Mises per frame (stages.sim.stress, as ``rsl export``);
* forces     per handle and obstacle over time, ‖Σ f_int‖ and ‖applied‖ (stages.sim.stress.set_forces,
             or WS/export/forces.csv), with truth/forces.csv overlaid when present;
* timings    per-frame forward / backward / render of adapt.h5 and the time each artefact records;
* evaluation the numbers of WS/evaluation.json;
* provenance every artefact's kind, config, hashed inputs, attributes and datasets (``rsl info``).

Every image is a base64 PNG inside the page (no external URL); plots are matplotlib.  A small
inline script writes, once the page has loaded, whether every image decoded into the element
``#rsl-report-status`` (read by the headless-browser test).
"""
from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stages.artefacts import (KIND_FILES, AdaptArtefact, ArtefactError, CamerasArtefact, GaussiansArtefact,
                              MasksArtefact, MeshArtefact, describe, read_provenance)
from stages.capture import Capture, CaptureError, load_capture, read_forces_csv, read_material_csv
from stages.errors import RslError
from stages.forces import FORCE_SUBSTEPS, adapted_forces, filter_model, replay_substeps
from stages.observations import read_frame, render_backgrounds, target_image
from stages.progress import Reporter, SilentReporter
from stages.render.image_loss import ImageLoss
from stages.results import (compute_stress, gaussian_anchor, material_damping, material_setting, recorded_capture,
                            window_young)
from stages.workspace import artefact_state, write_text_atomic

REPORT_FILE = "report.html"


@dataclass(frozen=True)
class ReportConfig:
    workspace: Path
    """Workspace folder whose artefacts the report shows."""
    out: Path | None = None
    """HTML file to write; default WORKSPACE/report.html."""
    capture: Path | None = None
    """Capture folder (photos, controls, truth/); default the one recorded in the workspace's artefacts."""
    frames: int = 3
    """Frames shown as photo / render / stress render (evenly spaced over adapt.h5)."""
    cameras: int = 2
    """Most capture cameras shown per frame."""
    contact_distance: float = 1.0e-3
    """A vertex touches an obstacle when closer than the contact margin plus this distance, m (as rsl export)."""


class SectionMissing(Exception):
    """A section cannot be made from what the workspace holds; the message says why."""


@dataclass
class Section:
    key: str
    title: str
    body: str = ""
    missing: str = ""  # why the section could not be made ("" = made)


@dataclass
class Context:
    """What the sections share, loaded once (None where absent, with the reason in ``why``)."""

    config: ReportConfig
    ws: Path
    adapt: AdaptArtefact | None = None
    mesh: MeshArtefact | None = None
    capture: Capture | None = None
    why: dict = field(default_factory=dict)  # "adapt" | "mesh" | "capture" -> reason it is None
    _stress: np.ndarray | None = None  # (T, n) von Mises per vertex, Pa
    _stress_tet: np.ndarray | None = None  # (T, m) Pa
    _f_int: np.ndarray | None = None  # (T, n, 3) N
    model: str = "stable_neohookean"
    dt: float = 1.0 / 30.0
    gravity: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))

    def need(self, *what: str) -> None:
        for w in what:
            if getattr(self, w) is None:
                raise SectionMissing(self.why.get(w, f"no {w}"))

    @property
    def times(self) -> np.ndarray:
        return self.adapt.frames.astype(np.float64) * self.dt

    def stress(self) -> tuple[np.ndarray, np.ndarray]:
        """((T, m), (T, n)) von Mises per element and per vertex of every adapt.h5 frame, Pa."""
        self._compute_stress()
        return self._stress_tet, self._stress

    def internal_forces(self) -> np.ndarray:
        """(T, n, 3) internal nodal forces of every adapt.h5 frame, N."""
        self._compute_stress()
        return self._f_int

    def _compute_stress(self) -> None:
        """As ``rsl export`` computes them (stages.results.compute_stress), without σ."""
        self.need("adapt", "mesh")
        if self._stress is None:
            field = compute_stress(self.adapt, self.mesh, self.model, sigma=False)
            self._stress_tet, self._stress, self._f_int = field.von_mises_tet, field.von_mises_vertex, field.forces


# =========================================================================== HTML helpers
def _esc(x) -> str:
    return html.escape(str(x), quote=True)


def png_data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _img(png: bytes, alt: str, cls: str = "") -> str:
    c = f' class="{cls}"' if cls else ""
    return f'<img{c} alt="{_esc(alt)}" src="{png_data_uri(png)}">'


def _fig_png(fig) -> bytes:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    return buf.getvalue()


def _image_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an RGB image (H, W, 3) uint8 or float in [0, 1]."""
    import matplotlib.image as mpimg

    a = np.asarray(rgb)
    if a.dtype != np.uint8:
        a = (np.clip(a, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)
    buf = io.BytesIO()
    mpimg.imsave(buf, np.ascontiguousarray(a), format="png")
    return buf.getvalue()


def _table(header: list[str], rows: list[list]) -> str:
    th = "".join(f"<th>{_esc(h)}</th>" for h in header)
    tr = "".join("<tr>" + "".join(f"<td>{_esc(v)}</td>" for v in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{th}</tr></thead><tbody>{tr}</tbody></table>"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# =========================================================================== loading
def _recorded_capture(ws: Path) -> Path | None:
    """The capture folder recorded in the workspace's artefacts (adapt.h5 first), resolved from here
    or from the workspace."""
    for kind in ("adapt", "gaussians", "masks", "mesh", "cameras", "snapshots"):
        p = ws / KIND_FILES[kind]
        if not p.exists():
            continue
        try:
            found = recorded_capture(read_provenance(p), ws)
        except ArtefactError:
            continue
        if found is not None:
            return found
    return None


def load_context(config: ReportConfig) -> Context:
    ws = Path(config.workspace)
    ctx = Context(config, ws)
    mesh_path, adapt_path = ws / KIND_FILES["mesh"], ws / KIND_FILES["adapt"]
    for name, path, cls in (("mesh", mesh_path, MeshArtefact), ("adapt", adapt_path, AdaptArtefact)):
        if not path.exists():
            ctx.why[name] = f"{path.name} is not in the workspace (run `rsl {'tetrahedralize' if name == 'mesh' else 'adapt'}`)."
            continue
        try:
            setattr(ctx, name, cls.load(path))
        except RslError as e:
            ctx.why[name] = f"{path.name} cannot be read: {e}"
    if ctx.adapt is not None and ctx.mesh is not None and ctx.adapt.positions.shape[1] != ctx.mesh.n_vertices:
        ctx.why["adapt"] = (f"adapt.h5 holds {ctx.adapt.positions.shape[1]} vertices but mesh.h5 has "
                            f"{ctx.mesh.n_vertices}: they come from different meshes.")
        ctx.adapt = None
    cap_path = config.capture if config.capture is not None else _recorded_capture(ws)
    if cap_path is None:
        ctx.why["capture"] = "no capture folder is known (none recorded in the artefacts that exists from here; " \
                             "pass --capture)."
    else:
        try:
            ctx.capture = load_capture(cap_path)
        except CaptureError as e:
            if config.capture is not None:
                raise
            ctx.why["capture"] = f"the capture folder cannot be read: {e}"
    if ctx.capture is not None or ctx.adapt is not None:
        ctx.model, ctx.dt, ctx.gravity = material_setting(ctx.capture, ctx.adapt)
    return ctx


def _truth_material(ctx: Context):
    """(young (T, R), poisson (T, R), region names) of truth/material.csv, or None when absent or empty."""
    if ctx.capture is None:
        return None
    path = ctx.capture.truth_dir / "material.csv"
    if not path.is_file():
        return None
    try:
        young, poisson, names = read_material_csv(path)
    except CaptureError as e:
        raise SectionMissing(str(e)) from None
    return (young, poisson, names) if young.size else None


# =========================================================================== sections
def section_material(ctx: Context) -> str:
    ctx.need("adapt")
    ad = ctx.adapt
    plt = _plt()
    truth = _truth_material(ctx)
    sig_e = getattr(ad, "young_sigma", None)
    sig_nu = getattr(ad, "poisson_sigma", None)
    t = ad.frames
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    notes = []
    window = window_young(ad)
    if window is not None:
        notes.append("E(t) holds each calibration fit until the next change of material (rsl adapt --hold-fit); "
                     "the dotted line is the sliding window's own estimate.")
    for r, name in enumerate(ad.region_names):
        c = f"C{r % 10}"
        a0.plot(t, ad.young[:, r], marker=".", color=c, label=f"{name} estimated")
        if window is not None:
            a0.plot(t, window[:, r], ":", lw=1, color=c, label=f"{name} window's own")
        a1.plot(t, ad.poisson[:, r], marker=".", color=c, label=f"{name} estimated")
        for ax, val, sig, log in ((a0, ad.young[:, r], sig_e, True), (a1, ad.poisson[:, r], sig_nu, False)):
            if sig is not None and np.any(np.isfinite(np.asarray(sig)[:, r])):
                s = np.asarray(sig)[:, r]  # NaN where unknown: no band there
                lo = np.maximum(val - s, 1e-3 * val) if log else val - s  # a log axis shows no E <= 0
                ax.fill_between(t, lo, val + s, color=c, alpha=0.2, lw=0, label=f"{name} ± σ")
        if truth is not None and name in truth[2]:
            k = truth[2].index(name)
            ok = t < truth[0].shape[0]
            a0.plot(t[ok], truth[0][t[ok], k], "--", color=c, label=f"{name} truth")
            a1.plot(t[ok], truth[1][t[ok], k], "--", color=c, label=f"{name} truth")
    a0.set_yscale("log")
    a0.set_ylabel("Young's modulus E (Pa)")
    a1.set_ylabel("Poisson's ratio ν")
    a1.set_xlabel("frame")
    a0.set_title(f"adapt.h5: {ad.mode}, {ad.space} space, {ad.loss_kind} loss, window {ad.window}")
    a0.legend(fontsize=8)
    a0.grid(alpha=0.3, which="both")
    a1.grid(alpha=0.3)
    fig.tight_layout()
    png = _fig_png(fig)
    if sig_e is None or not np.any(np.isfinite(np.asarray(sig_e))):
        notes.append("adapt.h5 holds no σ of E (the estimator did not give one): no band drawn.")
    if truth is None:
        notes.append("no truth/material.csv in the capture: no truth drawn." if ctx.capture is not None
                      else f"no truth drawn: {ctx.why.get('capture', 'no capture')}")
    rows = []
    for r, name in enumerate(ad.region_names):
        row = [name, f"{ad.young[-1, r]:.4g}", f"{ad.poisson[-1, r]:.3f}"]
        if sig_e is not None and np.isfinite(np.asarray(sig_e)[-1, r]):
            row.append(f"{np.asarray(sig_e)[-1, r]:.3g}")
        else:
            row.append("—")
        if truth is not None and name in truth[2] and ad.frames[-1] < truth[0].shape[0]:
            e_true = truth[0][ad.frames[-1], truth[2].index(name)]
            row += [f"{e_true:.4g}", f"{(ad.young[-1, r] - e_true) / e_true:+.1%}"]
        else:
            row += ["—", "—"]
        rows.append(row)
    table = _table(["region", f"E at frame {int(ad.frames[-1])} (Pa)", "ν", "σ of E (Pa)", "E truth (Pa)",
                    "E error"], rows)
    return _img(png, "E(t) and nu(t) per region", "plot") + table + "".join(f"<p class='note'>{_esc(n)}</p>"
                                                                        for n in notes)


RESIDUAL_SCALE = 0.5
"""The renders' residual images: |render − photo| (intensity in [0, 1]) drawn at the colour map's top."""


def _render_rows(ctx: Context) -> np.ndarray:
    T = len(ctx.adapt.frames)
    n = max(1, min(int(ctx.config.frames), T))
    return np.unique(np.linspace(0, T - 1, n).round().astype(int))


def section_renders(ctx: Context, reporter: Reporter) -> str:
    ctx.need("adapt", "mesh", "capture")
    ws = ctx.ws
    gpath, cpath = ws / KIND_FILES["gaussians"], ws / KIND_FILES["cameras"]
    for p, stage in ((gpath, "fit-gaussians"), (cpath, "calibrate")):
        if not p.exists():
            raise SectionMissing(f"{p.name} is not in the workspace (run `rsl {stage}`).")
    cams = CamerasArtefact.load(cpath)
    names = [c.name for c in cams.cameras if c.name in ctx.capture.camera_names][:max(1, ctx.config.cameras)]
    if not names:
        raise SectionMissing("none of the cameras of cameras.h5 is a camera of the capture.")
    gauss = GaussiansArtefact.load(gpath)
    if gauss.host_tet.size and gauss.host_tet.max() >= ctx.mesh.n_tets:
        raise SectionMissing("gaussians.h5 is bound to another mesh than mesh.h5.")
    import torch

    from stages.render.gaussians import color_to_sh0

    renderer = ImageLoss(gauss, ctx.mesh, [cams.by_name(c) for c in names])
    ad = ctx.adapt
    anchor = gaussian_anchor(renderer, ad, gpath)  # the Gaussians follow the mesh as rsl adapt made them
    rows = _render_rows(ctx)
    _, vm_v = ctx.stress()
    vmax = float(np.percentile(vm_v[rows], 99)) or 1.0
    corners = ctx.mesh.tets[gauss.host_tet][:, :4]  # (G, 4) corner nodes: the fitted binding's barycentrics
    from matplotlib import colormaps

    turbo, magma = colormaps["turbo"], colormaps["magma"]
    masks_path = ws / KIND_FILES["masks"]
    masks = MasksArtefact.load(masks_path).masks if masks_path.exists() else None
    plates = render_backgrounds(ctx.capture, names, masks)  # what adapt's image loss composites over
    app_sh = renderer.g.sh.data.clone()
    blocks = []
    with reporter.task("report renders", len(rows)) as task, torch.no_grad():
        for i in rows:
            t = int(ad.frames[i])
            x = ad.positions[i] - anchor
            renderer.g.sh.data = app_sh
            renderer.set_backgrounds(plates)
            app = [im.detach().numpy() for im in renderer.images(x)]
            vm_g = np.sum(np.asarray(gauss.bary, np.float64) * vm_v[i][corners], axis=1)
            rgb = np.asarray(turbo(np.clip(vm_g / vmax, 0, 1)))[:, :3]
            sh = torch.as_tensor(color_to_sh0(rgb)[:, None, :], dtype=renderer.g.sh.dtype)
            renderer.g.sh.data = torch.zeros_like(app_sh)
            renderer.g.sh.data[:, :1, :] = sh
            renderer.set_backgrounds([np.ones((cams.by_name(c).height, cams.by_name(c).width, 3), np.float32)
                                      for c in names])
            stress = [im.detach().numpy() for im in renderer.images(x)]
            cells = []
            for c, a, s in zip(names, app, stress):
                src = ctx.capture.frame_source(c)
                image = read_frame(ctx.capture, c, t) if t < src.count else None
                photo, residual, note = None, None, ""
                if image is not None:
                    photo = _image_png(image)
                    # |R − Ĩ| as the loss sees it (Ĩ: the frame, its background replaced where masks.h5 has a mask)
                    r = np.abs(a - target_image(image, masks, c, t, renderer.background)).mean(axis=2)
                    residual = _image_png(np.asarray(magma(np.clip(r / RESIDUAL_SCALE, 0, 1)))[..., :3])
                    note = f" (mean {r.mean():.3f})"
                none = "<div class='px none'>no photo</div>"
                cells.append(
                    "<figure class='trio'>"
                    + (_img(photo, f"photo {c} frame {t}", "px") if photo else none)
                    + _img(_image_png(a), f"render {c} frame {t}", "px")
                    + (_img(residual, f"residual {c} frame {t}", "px") if residual else none)
                    + _img(_image_png(s), f"stress render {c} frame {t}", "px")
                    + f"<figcaption>{_esc(c)}, frame {t}: photo · render · |render − photo|{note} · von Mises"
                      f"</figcaption></figure>")
            blocks.append("<div class='row'>" + "".join(cells) + "</div>")
            task.advance(1)
    renderer.g.sh.data = app_sh
    plt = _plt()
    import matplotlib as mpl

    fig = plt.figure(figsize=(5, 1.0))
    ax = fig.add_axes((0.05, 0.5, 0.9, 0.25))
    fig.colorbar(mpl.cm.ScalarMappable(norm=mpl.colors.Normalize(0, vmax / 1e3), cmap="turbo"), cax=ax,
                 orientation="horizontal", label="von Mises stress (kPa)")
    bar = _img(_fig_png(fig), "stress colour bar", "bar")
    return ("<p>Left to right: the capture's photo, the adapted Gaussians rendered from the same camera (over the "
            "background the image loss uses), their difference as the image loss compares them (|render − photo| "
            f"per pixel, mean over the colour channels, black 0 … bright {RESIDUAL_SCALE:g} and above, the photo's "
            "background replaced where masks.h5 has a mask: a bright patch on the object is what the simulated "
            "Gaussians do not explain — a face the fit never saw, a shadow, a pose off), and the same Gaussians "
            "coloured by von Mises stress (0 … 99th percentile of the frames shown).</p>"
            + "".join(blocks) + bar)


def section_stress(ctx: Context) -> str:
    vm_t, _ = ctx.stress()
    plt = _plt()
    t = ctx.times
    fig, ax = plt.subplots(figsize=(8, 3.5))
    ax.plot(t, vm_t.max(axis=1) / 1e3, marker=".", label="max")
    ax.plot(t, np.percentile(vm_t, 99, axis=1) / 1e3, label="99th percentile")
    ax.plot(t, np.median(vm_t, axis=1) / 1e3, label="median")
    names = ctx.mesh.region_names
    if len(names) > 1:
        for r, nm in enumerate(names):
            sel = ctx.mesh.tet_region == r
            if sel.any():
                ax.plot(t, vm_t[:, sel].max(axis=1) / 1e3, ls=":", label=f"max in {nm}")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("von Mises stress (kPa)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    i = int(np.argmax(vm_t.max(axis=1)))
    return (_img(_fig_png(fig), "von Mises stress over time", "plot")
            + f"<p>Largest von Mises stress {vm_t.max() / 1e3:.4g} kPa at frame {int(ctx.adapt.frames[i])}.</p>")


def _read_force_csv(path: Path) -> dict:
    """name -> {"t": (k,), "internal": (k, 3), "applied": (k, 3)} from a forces.csv (export's header)."""
    out: dict = {}
    for r in read_forces_csv(path):
        d = out.setdefault(r["name"], {"t": [], "internal": [], "applied": []})
        d["t"].append(r["time_s"])
        d["internal"].append([r["fx_N"], r["fy_N"], r["fz_N"]])
        d["applied"].append([r["applied_fx_N"], r["applied_fy_N"], r["applied_fz_N"]])
    return {k: {kk: np.asarray(vv, np.float64) for kk, vv in v.items()} for k, v in out.items()}


def _compute_forces(ctx: Context) -> dict:
    """The same forces as ``rsl export --forces`` (stages.forces.adapted_forces) for every adapt.h5 frame."""
    from stages.sim.scene import make_scene  # numba kernels: loaded on use

    ad, mesh = ctx.adapt, ctx.mesh
    controls = ctx.capture.controls()
    if not controls.handles and not controls.obstacles:
        raise SectionMissing(f"{ctx.capture.controls_path}: no handle and no obstacle.")
    scene = make_scene(mesh, controls, ctx.model, ctx.dt, ctx.gravity,
                       damping=material_damping(ctx.capture, ctx.adapt))
    substeps = replay_substeps(FORCE_SUBSTEPS, ad)  # rsl export --forces' default replay
    walk = filter_model(read_provenance(ctx.ws / KIND_FILES["adapt"]).get("config"),
                        ctx.capture.material.poisson_range, ad.extra)  # the gn filter's random walk (θ rule "smoothed")
    rows, _, _ = adapted_forces(scene, controls, ad, ctx.capture.start, substeps, ctx.internal_forces,
                                ctx.config.contact_distance, model=walk)
    out: dict = {}
    for frame, sf in rows:
        d = out.setdefault(sf.name, {"t": [], "internal": [], "applied": []})
        d["t"].append(frame * ctx.dt)
        d["internal"].append(np.asarray(sf.internal, np.float64))
        d["applied"].append(np.asarray(sf.applied, np.float64))
    return {k: {kk: np.asarray(vv, np.float64) for kk, vv in v.items()} for k, v in out.items()}


def section_forces(ctx: Context) -> str:
    source = ""
    if ctx.adapt is not None and ctx.mesh is not None and ctx.capture is not None:
        forces = _compute_forces(ctx)
        source = "computed from adapt.h5 with the capture's controls (as `rsl export --forces`)"
    elif (ctx.ws / "export" / "forces.csv").is_file():
        forces = _read_force_csv(ctx.ws / "export" / "forces.csv")
        source = "read from export/forces.csv"
    else:
        ctx.need("adapt", "mesh", "capture")
        raise SectionMissing("no forces can be made")
    truth, notes = None, []
    if ctx.capture is not None and (ctx.capture.truth_dir / "forces.csv").is_file():
        truth = _read_force_csv(ctx.capture.truth_dir / "forces.csv")
    else:
        notes.append("no truth/forces.csv in the capture: no truth drawn.")
    plt = _plt()
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
    for k, (name, d) in enumerate(forces.items()):
        c = f"C{k % 10}"
        a0.plot(d["t"], np.linalg.norm(d["internal"], axis=1), marker=".", color=c, label=f"{name}")
        a1.plot(d["t"], np.linalg.norm(d["applied"], axis=1), marker=".", color=c, label=f"{name}")
        if truth is not None and name in truth:
            tr = truth[name]
            a0.plot(tr["t"], np.linalg.norm(tr["internal"], axis=1), "--", color=c, label=f"{name} truth")
            a1.plot(tr["t"], np.linalg.norm(tr["applied"], axis=1), "--", color=c, label=f"{name} truth")
    a0.set_ylabel("‖Σ internal force‖ (N)")
    a1.set_ylabel("‖applied force‖ (N)")
    a1.set_xlabel("time (s)")
    a0.set_title("handle / obstacle forces")
    for a in (a0, a1):
        a.legend(fontsize=8)
        a.grid(alpha=0.3)
    fig.tight_layout()
    rows = [[name, f"{np.linalg.norm(d['internal'], axis=1).max():.4g}",
             f"{np.linalg.norm(d['applied'], axis=1).max():.4g}"] for name, d in forces.items()]
    return (f"<p>Forces {_esc(source)}.</p>" + _img(_fig_png(fig), "handle and contact forces over time", "plot")
            + _table(["handle / obstacle", "max ‖Σ f_int‖ (N)", "max ‖applied‖ (N)"], rows)
            + "".join(f"<p class='note'>{_esc(n)}</p>" for n in notes))


def _artefact_files(ws: Path) -> list[Path]:
    """The HDF5 artefacts of a workspace: the known kinds in pipeline order, then any other *.h5."""
    known = [ws / f for f in KIND_FILES.values() if (ws / f).is_file()]
    extra = sorted(p for p in list(ws.glob("*.h5")) + list(ws.glob("export*/*.h5"))
                   if p not in known and not p.name.startswith("."))
    return known + extra


def section_timings(ctx: Context) -> str:
    parts, rows, walls = [], [], {}
    for p in _artefact_files(ctx.ws):
        try:
            attrs = read_provenance(p)
        except RslError:
            continue
        wall = attrs.get("wall_s")  # seconds from the stage's start to this write (stages.artefacts)
        if not isinstance(wall, (int, float)) and p.name == KIND_FILES["adapt"] and ctx.adapt is not None:
            wall = (ctx.adapt.extra or {}).get("wall_s")  # older adapt.h5: its own record
        ok = isinstance(wall, (int, float)) and np.isfinite(wall)
        if ok:
            walls[str(p.relative_to(ctx.ws))] = float(wall)
        rows.append([p.relative_to(ctx.ws), attrs.get("rsl_kind", "?"), attrs.get("created", "?"),
                     f"{float(wall):.3g}" if ok else "not recorded by the stage"])
    if walls:
        plt = _plt()
        fig, ax = plt.subplots(figsize=(8, 0.45 * len(walls) + 1.2))
        names = list(walls)[::-1]
        ax.barh(names, [walls[n] for n in names], color="C0")
        ax.set_xlabel("wall time of the stage that wrote it (s)")
        ax.set_title("time per stage")
        ax.grid(alpha=0.3, axis="x")
        fig.tight_layout()
        parts.append(_img(_fig_png(fig), "time per stage", "plot"))
    if rows:
        parts.append(_table(["artefact", "kind", "written (UTC)", "stage wall time (s)"], rows))
    if ctx.adapt is not None:
        ad = ctx.adapt
        plt = _plt()
        other = np.maximum(ad.time_total_s - ad.time_forward_s - ad.time_backward_s - ad.time_render_s, 0.0)
        fig, ax = plt.subplots(figsize=(8, 3.5))
        bottom = np.zeros(len(ad.frames))
        for vals, label in ((ad.time_forward_s, "forward"), (ad.time_backward_s, "backward"),
                            (ad.time_render_s, "render"), (other, "other")):
            ax.bar(ad.frames, vals, bottom=bottom, label=label, width=0.85)
            bottom = bottom + vals
        ax.set_xlabel("frame")
        ax.set_ylabel("time (s)")
        ax.set_title("rsl adapt: time per frame")
        ax.legend(fontsize=8)
        fig.tight_layout()
        parts.append(_img(_fig_png(fig), "adapt time per frame", "plot"))
        med = [[k, f"{np.median(getattr(ad, 'time_' + k + '_s')):.4g}", f"{np.sum(getattr(ad, 'time_' + k + '_s')):.4g}"]
               for k in ("forward", "backward", "render", "total")]
        parts.append(_table(["adapt, per frame", "median (s)", "sum over frames (s)"], med))
    else:
        parts.append(f"<p class='note'>No per-frame timings: {_esc(ctx.why.get('adapt', ''))}</p>")
    if not rows and ctx.adapt is None:
        raise SectionMissing("the workspace holds no artefact.")
    return "".join(parts)


def section_evaluation(ctx: Context) -> str:
    path = ctx.ws / "evaluation.json"
    if not path.is_file():
        raise SectionMissing("evaluation.json is not in the workspace (run `rsl evaluate` on a capture with truth/).")
    try:
        ev = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise SectionMissing(f"{path.name} is not valid JSON ({e}).") from None
    rows = []
    for key in ("young_rel_error_median", "young_rel_error_final", "poisson_abs_error_median",
                "vertex_error_mean_m", "vertex_error_rel_mean", "psnr_mean"):
        v = ev.get(key)
        if isinstance(v, (int, float)):
            text = (f"{v:.2%}" if key.startswith("young") or key.endswith("rel_mean") else
                    f"{v * 1e3:.3g} mm" if key.endswith("_m") else f"{v:.2f} dB" if key.startswith("psnr") else f"{v:.4g}")
            rows.append([key, text])
    if not rows:
        raise SectionMissing(f"{path.name} holds none of the known error measures.")
    return _table(["measure (evaluation.json)", "value"], rows)


def section_provenance(ctx: Context) -> str:
    files = _artefact_files(ctx.ws)
    if not files:
        raise SectionMissing("the workspace holds no artefact.")
    kinds = {f: k for k, f in KIND_FILES.items()}
    out = []
    hashes: dict = {}
    for p in files:
        try:
            d = describe(p)
        except RslError as e:
            out.append(f"<details><summary>{_esc(p.name)}: cannot be read</summary><p>{_esc(e)}</p></details>")
            continue
        attrs = d["attrs"]
        state = ""
        if p.parent == ctx.ws and p.name in kinds:
            s = artefact_state(ctx.ws, kinds[p.name], hashes)
            state = s.state + (f" ({'; '.join(s.reasons)})" if s.reasons else "")
        head = (f"{p.relative_to(ctx.ws)} — kind {attrs.get('rsl_kind', '?')}, schema {attrs.get('schema_version')}, "
                f"rsl {attrs.get('rsl_version')}, written {attrs.get('created')}" + (f", {state}" if state else ""))
        config = attrs.get("config") or {}
        cfg = _table(["option", "value"], [[k, json.dumps(v, default=str)] for k, v in config.items()]) \
            if config else "<p>no config recorded</p>"
        inputs = attrs.get("inputs") or []
        inp = _table(["input", "sha256"], [[i.get("path"), i.get("sha256")] for i in inputs]) \
            if inputs else "<p>no input recorded</p>"
        other = {k: v for k, v in attrs.items() if k not in ("rsl_kind", "schema_version", "rsl_version", "created",
                                                              "config", "inputs")}
        oth = _table(["attribute", "value"], [[k, (v if isinstance(v, str) else json.dumps(v, default=str))[:400]]
                                               for k, v in other.items()]) if other else ""
        ds = _table(["dataset", "shape", "dtype"], [[n, list(s), t] for n, s, t in d["datasets"]])
        out.append(f"<details><summary>{_esc(head)}</summary><h4>config</h4>{cfg}<h4>inputs</h4>{inp}"
                   f"{'<h4>attributes</h4>' + oth if oth else ''}<h4>datasets</h4>{ds}</details>")
    return "".join(out)


# =========================================================================== the page
_STYLE = """
body{font-family:system-ui,sans-serif;margin:1.5em auto;max-width:1100px;color:#222;padding:0 1em}
h1{font-size:1.5em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.6em 0;font-size:.85em}td,th{border:1px solid #ddd;padding:.2em .5em;
text-align:left;vertical-align:top;word-break:break-all}th{background:#f4f4f4}
img.plot{max-width:100%;display:block;margin:.5em 0}img.bar{max-width:420px;display:block}
img.px{width:160px;image-rendering:pixelated;margin-right:4px;border:1px solid #ddd}
div.px.none{display:inline-block;width:160px;height:160px;background:#eee;text-align:center}
figure.trio{display:inline-block;margin:.3em 1em .3em 0}figcaption{font-size:.8em;color:#555}
.missing{color:#a33}.note{color:#666;font-size:.9em}details{margin:.3em 0}summary{cursor:pointer}
#rsl-report-status{color:#888;font-size:.8em;margin-top:2em}
"""

# Runs after the page has loaded: every image decoded (natural width > 0) and no script error → "ok".
_CHECK = """
(function () {
  var errors = [];
  window.addEventListener("error", function (e) { errors.push(String(e.message || e)); });
  window.addEventListener("load", function () {
    var imgs = Array.prototype.slice.call(document.images);
    var broken = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); });
    var s = document.getElementById("rsl-report-status");
    s.setAttribute("data-images", String(imgs.length));
    s.setAttribute("data-broken", String(broken.length));
    s.setAttribute("data-errors", String(errors.length));
    s.setAttribute("data-status", broken.length || errors.length ? "error" : "ok");
    s.textContent = "page check: " + (imgs.length - broken.length) + " of " + imgs.length + " images decoded" +
      (errors.length ? "; script errors: " + errors.join("; ") : "");
  });
})();
"""

SECTIONS = (
    ("material", "Material: E(t) and ν(t) per region"),
    ("renders", "Renders beside the photos"),
    ("stress", "Stress over time"),
    ("forces", "Handle and contact forces"),
    ("timings", "Timings"),
    ("evaluation", "Errors against the truth"),
    ("provenance", "Provenance of every artefact"),
)


def make_sections(ctx: Context, reporter: Reporter) -> list[Section]:
    makers = {"material": section_material, "renders": lambda c: section_renders(c, reporter),
              "stress": section_stress, "forces": section_forces, "timings": section_timings,
              "evaluation": section_evaluation, "provenance": section_provenance}
    out = []
    for key, title in SECTIONS:
        s = Section(key, title)
        try:
            s.body = makers[key](ctx)
        except SectionMissing as e:
            s.missing = str(e)
        except (RslError, OSError) as e:  # a stage input that cannot be used: the section says why
            s.missing = str(e)
        except Exception as e:  # noqa: BLE001 — one section failing must not cost the others; it is reported
            s.missing = f"it failed ({type(e).__name__}: {e})"
            reporter.warn(f"report: section '{title}' failed: {type(e).__name__}: {e}")
        if s.missing:
            reporter.info(f"report: section '{title}' not made: {s.missing}")
        out.append(s)
    return out


def render_page(ctx: Context, sections: list[Section]) -> str:
    cap = ctx.capture.root if ctx.capture is not None else None
    now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    nav = "".join(f"<li><a href='#{s.key}'>{_esc(s.title)}</a>{' (not made)' if s.missing else ''}</li>"
                  for s in sections)
    body = []
    for s in sections:
        content = f"<p class='missing'>Not made: {_esc(s.missing)}</p>" if s.missing else s.body
        body.append(f"<section id='{s.key}'><h2>{_esc(s.title)}</h2>{content}</section>")
    return ("<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
            f"<title>rsl report: {_esc(ctx.ws.name)}</title><style>{_STYLE}</style></head><body>"
            f"<h1>rsl report: {_esc(ctx.ws)}</h1>"
            f"<p>Workspace {_esc(ctx.ws.resolve())}; capture {_esc(cap.resolve() if cap else 'unknown')}; "
            f"written {now}.</p><ul>{nav}</ul>" + "".join(body)
            + f"<div id='rsl-report-status' data-status='pending'>page check: not run</div>"
            f"<script>{_CHECK}</script></body></html>\n")


def run(config: ReportConfig, reporter: Reporter = SilentReporter()) -> Path:
    """Write the HTML report of config.workspace; returns its path."""
    ws = Path(config.workspace)
    if not ws.is_dir():
        raise RslError(f"{ws}: workspace folder not found.")
    if config.frames < 1 or config.cameras < 1:
        raise RslError("--frames and --cameras should each be at least 1.")
    if not _artefact_files(ws):
        raise RslError(f"{ws}: holds no artefact (*.h5); run the pipeline first (rsl run CAPTURE -w {ws}).")
    ctx = load_context(config)
    sections = make_sections(ctx, reporter)
    out = Path(config.out) if config.out is not None else ws / REPORT_FILE
    write_text_atomic(out, render_page(ctx, sections))
    made = [s.title.split(":")[0] for s in sections if not s.missing]
    reporter.summary(f"report: {len(made)} of {len(sections)} sections ({', '.join(made) or 'none'}), "
                     f"{out.stat().st_size / 1e6:.2f} MB → {out}")
    return out
