"""`rsl report`: a self-contained HTML page that a real headless Chromium loads without errors, with
every image decoded; sections that cannot be made say why; forces match `rsl export --forces`."""
from __future__ import annotations

import base64
import csv
import io
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from stages.artefacts import AdaptArtefact, Provenance, read_provenance

BEAM = Path(__file__).resolve().parents[2] / "shared" / "data" / "autodef_fulton" / "Coarse_beam.mesh"
FRAMES, CAMERAS = 6, 2


def chromium() -> str:
    """Path of a Chromium binary; the test is skipped (with the reason) when none is installed."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip("no Chromium installed (make setup installs Debian's `chromium`); the browser test needs one")


def load_in_chromium(page: Path, tmp: Path) -> tuple[str, str]:
    """(DOM after the load event, browser stderr) of ``page`` in headless Chromium, nothing fetched from outside."""
    proc = subprocess.run(
        [chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-extensions",
         f"--user-data-dir={tmp / 'chromium-profile'}", "--enable-logging=stderr", "--v=0",
         "--virtual-time-budget=10000", "--dump-dom", page.resolve().as_uri()],
        capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout, proc.stderr


def status_of(dom: str) -> dict:
    m = re.search(r'<div id="rsl-report-status"([^>]*)>([^<]*)</div>', dom)
    assert m, "the status element is missing from the DOM"
    attrs = dict(re.findall(r'data-([a-z]+)="([^"]*)"', m.group(1)))
    attrs["text"] = m.group(2)
    return attrs


def console_errors(stderr: str) -> list[str]:
    """Console messages of the page (Chromium logs them as CONSOLE lines) that report an error."""
    return [ln for ln in stderr.splitlines() if "CONSOLE" in ln and ("Uncaught" in ln or "Error" in ln)]


def assert_page_loads(page: Path, tmp: Path, n_images: int | None = None) -> str:
    """Load ``page`` in headless Chromium and hold it to a clean load: status ok, no broken image, no page error,
    no console error (and ``n_images`` images, when given).  Returns the DOM after the load event."""
    dom, stderr = load_in_chromium(page, tmp)
    status = status_of(dom)
    assert status["status"] == "ok" and status["broken"] == "0" and status["errors"] == "0", status
    if n_images is not None:
        assert int(status["images"]) == n_images, status
    assert not console_errors(stderr), console_errors(stderr)
    return dom


def images(page_html: str) -> list[tuple[str, bytes]]:
    """(alt, PNG bytes) of every <img> of the page; each must be an inline data: URI."""
    out = []
    for tag in re.findall(r"<img[^>]*>", page_html):
        alt = re.search(r'alt="([^"]*)"', tag).group(1)
        src = re.search(r'src="([^"]*)"', tag).group(1)
        assert src.startswith("data:image/png;base64,"), f"image {alt!r} is not embedded: {src[:60]}"
        out.append((alt, base64.b64decode(src.split(",", 1)[1])))
    return out


@pytest.fixture(scope="module")
def full_ws(tmp_path_factory) -> dict:
    """A tiny synthetic capture run through calibrate, segment, tetrahedralize, fit-gaussians, adapt
    (full space, markers), evaluate and export --forces, in this process."""
    from stages.steps import adapt, calibrate, evaluate, export, fit_gaussians, segment, synth, tetrahedralize

    if not BEAM.is_file():
        pytest.skip(f"{BEAM} not present")
    root = tmp_path_factory.mktemp("report")
    cap, ws = root / "cap", root / "ws"
    synth.run(synth.SynthConfig(mesh=BEAM, out=cap, scenario="cable", cameras=CAMERAS, frames=FRAMES,
                                resolution=32, young=1.0e5, markers=20, calib_views=0, seed=0))
    toml = cap / "capture.toml"
    toml.write_text(toml.read_text().replace('mesh = "object.obj"', 'mesh = "truth/object.mesh"'))
    tetrahedralize.run(tetrahedralize.TetrahedralizeConfig(capture=cap, workspace=ws))
    calibrate.run(calibrate.CalibrateConfig(capture=cap, workspace=ws, from_json=str(cap / "cameras.json")))
    segment.run(segment.SegmentConfig(capture=cap, workspace=ws, method="background"))
    fit_gaussians.run(fit_gaussians.FitGaussiansConfig(capture=cap, workspace=ws, iterations=20, gaussians=1500))
    adapt.run(adapt.AdaptConfig(capture=cap, workspace=ws, space="full", loss="markers", window=2,
                                young_init=5.0e4))
    evaluate.run(evaluate.EvaluateConfig(capture=cap, workspace=ws, psnr_frames=0, plot=False))
    export.run(export.ExportConfig(workspace=ws, forces=True))
    return {"cap": cap, "ws": ws, "root": root}


def test_report_loads_in_headless_chromium_with_every_plot(full_ws, rsl, tmp_path):
    ws = full_ws["ws"]
    proc = rsl("report", "-w", ws, "--frames", "2")
    assert proc.returncode == 0, proc.stderr
    page = ws / "report.html"
    assert "7 of 7 sections" in proc.stderr and str(page) in " ".join(proc.stderr.split())
    text = page.read_text()
    # self-contained: nothing is fetched from elsewhere
    assert not re.search(r"""(src|href)\s*=\s*["'](https?:|//|file:)""", text)
    assert "<link" not in text and "@import" not in text and "url(" not in text
    alts = [a for a, _ in images(text)]
    for plot in ("E(t) and nu(t) per region", "von Mises stress over time", "handle and contact forces over time",
                 "adapt time per frame", "stress colour bar", "time per stage"):
        assert plot in alts, f"plot {plot!r} missing; images: {alts}"
    for frame in (0, FRAMES - 1):  # --frames 2: the first and the last, each camera: photo, render, residual, stress
        for cam in ("cam0", "cam1"):
            for kind in ("photo", "render", "residual", "stress render"):
                assert f"{kind} {cam} frame {frame}" in alts
    import matplotlib.image as mpimg

    for alt, png in images(text):  # each decodes to a non-empty picture that is not one flat colour
        a = mpimg.imread(io.BytesIO(png), format="png")
        assert a.shape[0] > 0 and a.shape[1] > 0 and np.ptp(a[..., :3]) > 0.05, alt

    dom = assert_page_loads(page, tmp_path, len(alts))
    assert "Not made" not in dom
    # provenance of every artefact, with the hashed inputs
    for name in ("mesh.h5", "cameras.h5", "masks.h5", "gaussians.h5", "adapt.h5", "export/stress.h5"):
        assert f"{name} — kind" in dom or name.endswith("stress.h5"), name
    sha = read_provenance(ws / "adapt.h5")["inputs"][0]["sha256"]
    assert sha in text


def test_report_forces_equal_export_forces_csv(full_ws):
    from stages.steps.report import ReportConfig, _compute_forces, load_context

    ctx = load_context(ReportConfig(workspace=full_ws["ws"]))
    ours = _compute_forces(ctx)
    with open(full_ws["ws"] / "export" / "forces.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows and set(ours) == {r["name"] for r in rows}
    for name, d in ours.items():
        mine = [r for r in rows if r["name"] == name]
        ref = np.array([[float(r[k]) for k in ("fx_N", "fy_N", "fz_N")] for r in mine])
        app = np.array([[float(r[k]) for k in ("applied_fx_N", "applied_fy_N", "applied_fz_N")] for r in mine])
        np.testing.assert_allclose(d["internal"], ref, rtol=1e-6, atol=1e-9)  # the CSV keeps 9 digits
        np.testing.assert_allclose(d["applied"], app, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(d["t"], [float(r["time_s"]) for r in mine], rtol=1e-8)


def test_report_draws_sigma_band_and_truth_forces_when_present(full_ws, tmp_path):
    """adapt.h5 with σ of E, and a capture with truth/forces.csv: the table shows σ, no 'missing' notes."""
    from stages.progress import SilentReporter
    from stages.steps.report import ReportConfig, run

    ws, cap = tmp_path / "ws", tmp_path / "cap"
    shutil.copytree(full_ws["ws"], ws)
    shutil.copytree(full_ws["cap"], cap)
    ad = AdaptArtefact.load(ws / "adapt.h5")
    prov = read_provenance(ws / "adapt.h5")
    ad.young_sigma = 0.1 * ad.young
    ad.poisson_sigma = np.full_like(ad.poisson, 0.01)
    ad.save(ws / "adapt.h5", Provenance(config=prov["config"], inputs=tuple(prov["inputs"])))
    shutil.copy(ws / "export" / "forces.csv", cap / "truth" / "forces.csv")
    rep = SilentReporter()
    out = run(ReportConfig(workspace=ws, capture=cap, frames=1, cameras=1), rep)
    text = out.read_text()
    assert f"{0.1 * ad.young[-1, 0]:.3g}" in text  # σ of E at the last frame in the material table
    assert "no band drawn" not in text and "no truth/forces.csv" not in text and "no truth drawn" not in text
    assert "7 of 7 sections" in rep.messages[-1]


def test_report_on_a_workspace_with_only_a_mesh_says_why_sections_are_missing(full_ws, rsl, tmp_path):
    ws = tmp_path / "ws"
    ws.mkdir()
    shutil.copy(full_ws["ws"] / "mesh.h5", ws / "mesh.h5")
    proc = rsl("report", "-w", ws, "-o", tmp_path / "r.html")
    assert proc.returncode == 0, proc.stderr
    assert "2 of 7 sections" in proc.stderr  # timings (the artefacts' table) and provenance
    text = (tmp_path / "r.html").read_text()
    assert text.count("Not made:") == 5
    assert "adapt.h5 is not in the workspace (run `rsl adapt`)" in text
    assert "evaluation.json is not in the workspace" in text
    dom, stderr = load_in_chromium(tmp_path / "r.html", tmp_path)
    assert status_of(dom)["status"] == "ok" and not console_errors(stderr)


def test_report_bad_workspace_is_one_sentence(rsl, tmp_path):
    proc = rsl("report", "-w", tmp_path / "nowhere")
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    (tmp_path / "empty").mkdir()
    proc = rsl("report", "-w", tmp_path / "empty")
    assert proc.returncode == 1 and "holds no artefact" in proc.stderr and "Traceback" not in proc.stderr
