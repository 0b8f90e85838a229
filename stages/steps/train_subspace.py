"""Stage ``train-subspace``: fit x = φ(z) to the snapshots and its reduced-energy cubature.

Reads WS/mesh.h5 and WS/snapshots.h5, splits the snapshots into training and validation
sets by sequence, fits a mass-weighted PCA, the Fulton et al. 2019 autoencoder or builds the
data-free LBS basis (stages.subspace.train), fits the optimised cubature of the reduced elastic
energy (stages.subspace.cubature) and writes WS/subspace.h5.

LBS (--kind lbs): k = ceil(r/12) handles at farthest-point samples of the rest vertices (the first
drawn with --seed), harmonic skinning weights, 12 affine modes per handle, mass-orthonormalised.
When the span is wider than r, the r kept directions are the leading mass-weighted PCA directions
of the training displacements projected onto the span (the snapshots choose directions, they do not
shape the span).  The summary and extra report the span's dimension, the handles and the errors of
both the r-dim basis and the whole span on the snapshots.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from stages.artefacts import KIND_FILES, MeshArtefact, Provenance, SnapshotsArtefact, SubspaceArtefact, \
    read_provenance
from stages.capture import load_capture
from stages.errors import RslError
from stages.artefacts import check_same_mesh
from stages.workspace import prepare_workspace
from stages.progress import Reporter, SilentReporter
from stages.sim.quadrature import element_order


FEW_SEQUENCES = 12  # fewer training sequences: a warning (docs/results/training_data.md)


@dataclass(frozen=True)
class TrainSubspaceConfig:
    workspace: Path
    """Workspace folder holding mesh.h5 and snapshots.h5; subspace.h5 is written there."""
    capture: Path | None = None
    """Capture folder, read for the material model only (default: the one generate-data used)."""
    dim: int = 30
    """Latent dimension r of the subspace."""
    kind: Literal["autoencoder", "pca", "lbs"] = "autoencoder"
    """autoencoder (Fulton et al. 2019: PCA outer layers, 2×200 hidden), pca (linear baseline) or lbs
    (linear-blend-skinning modes: ceil(dim/12) handles, harmonic weights; snapshots pick dim directions)."""
    epochs: int = 300
    """Training epochs of the autoencoder (passes over the training snapshots)."""
    learning_rate: float = 1e-3
    """Adam learning rate."""
    batch_size: int = 64
    """Snapshots per training step."""
    pca_dim: int = 0
    """Width p of the autoencoder's PCA layer (0: max(2r, r + 20))."""
    validation_fraction: float = 0.15
    """Fraction of the sequences held out for validation (at least one when there are two or more)."""
    cubature_tets: int = 300
    """Largest number of cubature points for the reduced elastic energy: quadrature points, one per linear
    tet, four per quadratic tet (0: integrate over every point)."""
    cubature_tol: float = 0.0005
    """Stop adding cubature points once the relative reduced-force error is below this.  0.0005 against 0.002, the
    same networks refitted (docs/results/cubature_tol.md: seven workspaces of the foreign captures, markers, r = 30):
    the mean of the largest median settled E error 8.8 → 5.6 %, 1 → 5 of 7 within the accuracy targets (two-region
    beam 8.3 / 17.9 → 1.7 / 1.4 %, dinosaur 9.8 → 4.3 %; one bar 5.0 → 9.7 %), 1.5–1.8 × the points, s / frame
    1.11 × (median).  (Before, 0.01 → 0.002 measured better on three of four captures.)"""
    cubature_poses: int = 40
    """Training snapshots the cubature is fitted on."""
    viscous_cubature: Literal["auto", "on", "off"] = "auto"
    """Fit the cubature to the viscous (damping) forces as well, at pairs of consecutive training poses: auto, when
    the capture declares a damping ([material] damping > 0); on, also when it does not — for ``rsl adapt --damping
    auto`` or a β given there (fitted to elastic forces alone, the bar's viscous forces are 7.6 % off, 0.3 % with
    them: docs/results/damping.md)."""
    cubature_poisson: Literal["median", "range"] = "median"
    """ν the cubature's forces are fitted at: median — the snapshots' median ν alone (it matches the sum of the
    shear and volumetric forces there, not each); range — both ends of capture.toml's poisson_range (the
    snapshots' ν without a capture), so that it integrates each part and ν moves the forces as in full space
    (cubature_materials).  Measured on 12 captures, the same networks, rsl adapt back to back (docs/results/
    cubature_poisson.md): range is better on 6 of the 8 bar and beam rows with markers (the two-region beam's stiff
    half 15.0 → 6.7 %, the damped bar released from rest 7.6 → 3.9 %), worse on the dinosaur (6.6 → 11.9 %,
    4.9 → 13.7 %) and on both bar rows with images (1.0 → 3.8 %, 3.8 → 7.1 %): ν then wanders where the data
    inform it weakly and E follows.  Mean median settled E error 5.2 % median against 5.6 % range: the default
    stays median; use range for markers on bars and beams."""
    material: str = ""
    """Material model for the cubature (default: the capture's)."""
    seed: int = 0
    """Seed of the split, the initial weights, the batches, the first LBS handle and the cubature candidates."""


def _split(snap: SnapshotsArtefact, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray, str]:
    """Train / validation snapshot indices, by sequence (by frame when there is one sequence)."""
    seqs = np.unique(snap.sequence)
    rng = np.random.default_rng(seed)
    if len(seqs) >= 2:
        n_val = min(len(seqs) - 1, max(1, int(round(fraction * len(seqs)))))
        val_seqs = rng.choice(seqs, size=n_val, replace=False)
        val = np.isin(snap.sequence, val_seqs)
        return np.nonzero(~val)[0], np.nonzero(val)[0], f"{len(seqs) - n_val} training / {n_val} validation sequences"
    s = len(snap.positions)
    n_val = int(round(fraction * s)) if s >= 4 else 0
    order = np.argsort(snap.frame, kind="stable")
    return np.sort(order[: s - n_val]), np.sort(order[s - n_val:]), "one sequence: its last frames validate"


def _capture_material(config: TrainSubspaceConfig, snap_path: Path):
    """The capture's MaterialSettings (--capture, else the capture generate-data used), or None."""
    capture = config.capture
    if capture is None:
        try:
            capture = read_provenance(snap_path).get("config", {}).get("capture")
        except RslError:
            capture = None
    if capture:
        try:
            return load_capture(Path(capture)).material
        except (RslError, OSError):
            pass
    return None


def cubature_materials(poisson: np.ndarray, prior_range: tuple[float, float] | None = None) -> list[np.ndarray]:
    """The ν per region (R,) the cubature's forces are fitted at: both ends of the capture's [material]
    poisson_range (``prior_range``, the range rsl adapt estimates ν in) when known, else the smallest and the
    largest of the snapshots' ν (S, R); one value where the two ends are equal.  The energies are linear in (μ, λ)
    (stable Neo-Hookean up to a constant: μ_s[½(I_C − 3) − ¾(J − 1) − ½ log(I_C + 1)] + ½ λ_s (J − 1)²; Yeoh,
    linear, viscous), so the reduced forces are g_q = μ g_q^μ + λ g_q^λ, and a cubature fitted at two ratios λ/μ
    integrates both parts, hence every ν between (``--cubature-poisson range``).  Fitted at one ν only it matches
    their sum: on the damped bar released from rest against a truth converged in time, adapt's ν then went to
    0.483 and E to 0.92 E_true over the first 12 frames (full space 0.437 and 0.98; accuracy_notes.md,
    twenty-first stop)."""
    poisson = np.asarray(poisson, np.float64)
    lo, hi = poisson.min(axis=0), poisson.max(axis=0)
    if prior_range is not None:
        lo, hi = np.full_like(lo, float(prior_range[0])), np.full_like(hi, float(prior_range[1]))
    return [lo, hi] if np.any(hi - lo > 1e-6) else [lo]


def elastic_samplers(sub, z: np.ndarray, quad, young: np.ndarray, nu_span: list, region_q: np.ndarray, model: str):
    """The reduced elastic forces at poses z (K, r) per ν of ``nu_span`` (cubature_materials), E ``young`` (R,)
    Pa per region, μ and λ per quadrature point of region ``region_q`` (q,): the samplers whose stacked rows the
    cubature is fitted to."""
    from stages.sim.materials import lame
    from stages.subspace.cubature import ReducedForceSampler

    out = []
    for nu in nu_span:
        mu_r, lam_r = lame(np.asarray(young, np.float64), np.asarray(nu, np.float64))
        out.append(ReducedForceSampler(sub, z, quad, np.asarray(mu_r)[region_q], np.asarray(lam_r)[region_q], model))
    return out


def cubature_sampler(sub, snap, ids: np.ndarray, quad, young: np.ndarray, nu_span: list, region_q: np.ndarray,
                     model: str, viscous: bool):
    """(the stacked reduced forces the cubature is fitted to, whether they hold viscous rows) at the snapshots
    ``ids``: the elastic forces per ν of ``nu_span`` (:func:`elastic_samplers`) and, with ``viscous``, the viscous
    forces at those snapshots whose frame before is a snapshot too (:func:`_pose_pairs`), per ν as well."""
    import jax.numpy as jnp

    from stages.subspace.cubature import StackedSampler, ViscousForceSampler

    z = np.asarray(sub.encode(jnp.asarray(snap.positions[ids])))
    elastic = elastic_samplers(sub, z, quad, young, nu_span, region_q, model)
    rows = []
    if viscous:
        now, before = _pose_pairs(snap, ids)
        if len(now):
            z_now = np.asarray(sub.encode(jnp.asarray(snap.positions[now])))
            rows = [ViscousForceSampler(sub, z_now, snap.positions[before], quad, e.mu, e.lam) for e in elastic]
    return StackedSampler(*elastic, *rows), bool(rows)


def _pose_pairs(snap, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ids whose frame before is in the snapshots, the index of that frame), per the snapshots' sequence and
    frame numbers: the pose pairs of the viscous term's cubature rows."""
    key = {(int(s), int(f)): i for i, (s, f) in enumerate(zip(snap.sequence, snap.frame))}
    prev = np.array([key.get((int(snap.sequence[i]), int(snap.frame[i]) - 1), -1) for i in ids], np.int64)
    return ids[prev >= 0], prev[prev >= 0]


def run(config: TrainSubspaceConfig, reporter: Reporter = SilentReporter()) -> Path:
    """Train the subspace and its cubature; write WS/subspace.h5."""
    import jax.numpy as jnp  # JAX, equinox and optax load in run: rsl train-subspace --help stays light

    from stages.sim.materials import MODELS
    from stages.subspace.cubature import StackedSampler, cubature_error, fit_cubature, mesh_quadrature
    from stages.subspace.train import fit_subspace, reconstruction_error

    ws = Path(config.workspace)
    mesh_path, snap_path = ws / KIND_FILES["mesh"], ws / KIND_FILES["snapshots"]
    out = ws / KIND_FILES["subspace"]
    if config.kind not in ("autoencoder", "pca", "lbs"):
        raise RslError(f"--kind {config.kind}: use autoencoder, pca or lbs.")
    if config.dim < 1:
        raise RslError(f"--dim {config.dim}: the latent dimension must be at least 1.")
    if config.cubature_poisson not in ("median", "range"):
        raise RslError(f"--cubature-poisson {config.cubature_poisson}: use median or range.")
    prepare_workspace(ws)  # writable? (before the training) and no stale temp files of a killed run
    mesh = MeshArtefact.load(mesh_path)
    snap = SnapshotsArtefact.load(snap_path)
    check_same_mesh(mesh_path, snap_path)  # made from this very mesh.h5, whatever the counts
    n = mesh.n_vertices
    if snap.positions.shape[1] != n:
        raise RslError(f"{snap_path}: snapshots have {snap.positions.shape[1]} vertices but {mesh_path} has {n}; "
                       "rerun generate-data on this mesh.")
    cap_material = _capture_material(config, snap_path)  # (the model unless --material; the damping)
    model = config.material or (cap_material.model if cap_material is not None else "stable_neohookean")
    if model not in MODELS:
        raise RslError(f"--material {model}: unknown model; use one of {', '.join(MODELS)}.")
    tr, va, split_note = _split(snap, config.validation_fraction, config.seed)
    x_tr, x_va = snap.positions[tr], snap.positions[va]
    rank = int(min(len(tr), 3 * n))
    if config.kind != "lbs" and config.dim > rank:  # the LBS span does not come from the snapshots
        raise RslError(f"{snap_path}: {len(tr)} training snapshots cannot span a {config.dim}-dimensional "
                       "subspace; generate more data or lower --dim.")
    reporter.info(f"{len(tr)} training and {len(va)} validation snapshots ({split_note}); {n} vertices.")
    n_seq = len(np.unique(snap.sequence))
    if config.kind != "lbs" and n_seq < FEW_SEQUENCES:
        reporter.warn(f"{snap_path}: only {n_seq} sequences; the E that rsl adapt identifies in a reduced space "
                      f"trained on so few moves with the draw (the dinosaur's: 6–15 % off over three draws of 4, "
                      f"2–7 % over three of 12, docs/results/training_data.md); generate at least {FEW_SEQUENCES} "
                      f"with `rsl generate-data --sequences` (its default is 20).")
    rest, masses = mesh.vertices, mesh.vertex_masses

    if config.kind == "autoencoder":
        with reporter.task(f"Training autoencoder r={config.dim}", config.epochs) as task:
            sub, info = fit_subspace("autoencoder", rest, masses, x_tr, config.dim, x_va, config.epochs,
                                     config.seed, config.pca_dim or None, config.learning_rate, config.batch_size,
                                     callback=lambda e, tl, vl: task.advance(1, loss=f"{tl:.2e}",
                                                                             val=f"{vl:.2e}"))
    elif config.kind == "lbs":
        k = -(-config.dim // 12)
        if k > n:
            raise RslError(f"--dim {config.dim}: needs {k} LBS handles but the mesh has {n} vertices.")
        with reporter.task(f"LBS r={config.dim} ({k} handles, harmonic weights)", None):
            try:
                sub, info = fit_subspace("lbs", rest, masses, x_tr, config.dim, seed=config.seed, tets=mesh.tets)
            except ValueError as e:
                raise RslError(f"--dim {config.dim}: {e}; lower --dim.") from e
    else:
        with reporter.task(f"PCA r={config.dim}", None):
            sub, info = fit_subspace("pca", rest, masses, x_tr, config.dim)
    with reporter.task("Reconstruction errors", None):
        train_err = reconstruction_error(sub, x_tr)
        val_err = reconstruction_error(sub, x_va) if len(va) else float("nan")
    diag = float(np.linalg.norm(rest.max(0) - rest.min(0)))
    extra_lbs: dict = {}
    if config.kind == "lbs":
        from stages.subspace.networks import SubspaceMap

        li = info["lbs"]
        span = SubspaceMap("lbs", rest, li["span"], masses, np.ones(li["span_dim"]), {})
        span_tr = reconstruction_error(span, x_tr)
        span_va = reconstruction_error(span, x_va) if len(va) else float("nan")
        extra_lbs = {"lbs_handles": int(len(li["handle_ids"])), "lbs_handle_ids": li["handle_ids"].tolist(),
                     "lbs_span_dim": li["span_dim"], "lbs_selection": li["selection"],
                     "lbs_span_train_error_m": span_tr, "lbs_span_val_error_m": span_va,
                     "lbs_span_train_error_rel": span_tr / diag, "lbs_span_val_error_rel": span_va / diag}

    # cubature at the snapshots' median E per region; at their median ν or at both ends of ν's range
    n_reg = len(mesh.region_names)
    per_region = snap.young.shape[1] == n_reg
    young = np.median(snap.young, axis=0) if per_region else np.full(n_reg, np.median(snap.young))
    poisson = np.median(snap.poisson, axis=0) if per_region else np.full(n_reg, np.median(snap.poisson))
    nu_span = [poisson] if config.cubature_poisson == "median" else cubature_materials(
        snap.poisson if per_region else np.tile(snap.poisson.reshape(-1, 1), n_reg),
        cap_material.poisson_range if cap_material is not None else None)
    order = element_order(mesh.tets)
    try:
        quad = mesh_quadrature(mesh.vertices, mesh.tets, mesh.dm_inv, mesh.rest_volumes)
    except ValueError as e:
        raise RslError(f"{mesh_path}: {e}; re-run tetrahedralize.") from None
    region_q = np.asarray(mesh.tet_region)[quad.element]  # the region of each quadrature point
    rng = np.random.default_rng(config.seed)
    m = quad.n_points
    what = "tets" if order == 1 else "quadrature points"
    extra_cub: dict = {}
    if config.cubature_tets > 0 and config.cubature_tets < m:
        pick = rng.choice(len(tr), size=min(config.cubature_poses, len(tr)), replace=False)
        damping = cap_material.damping if cap_material is not None else 0.0
        with reporter.task(f"Cubature (≤ {config.cubature_tets} of {m} {what})", None):
            # the viscous forces too (at training poses and the frame before each): declared damping, or asked for
            viscous = config.viscous_cubature == "on" or (config.viscous_cubature == "auto" and damping > 0)
            sampler, with_viscous = cubature_sampler(sub, snap, np.asarray(tr)[pick], quad, young, nu_span,
                                                     region_q, model, viscous)
            ids, w, cinfo = fit_cubature(sampler, region_q, n_reg, config.cubature_tets,
                                         config.cubature_tol, seed=config.seed)
            val_cub = float("nan")
            if len(va):
                pv = rng.choice(len(va), size=min(config.cubature_poses, len(va)), replace=False)
                z_va = np.asarray(sub.encode(jnp.asarray(x_va[pv])))
                sv = StackedSampler(*elastic_samplers(sub, z_va, quad, young, nu_span, region_q, model))
                val_cub = cubature_error(sv, region_q, n_reg, ids, w)
        # quadrature point ids (for linear tets: tet ids) and weights; the order they index
        extra_cub = {"cubature_points": ids.tolist(), "cubature_weights": w.tolist(), "cubature_order": order,
                     "cubature_error_rel": cinfo["error_rel"], "cubature_error_val_rel": val_cub,
                     "cubature_viscous": with_viscous,
                     "cubature_poisson_fitted": [nu.tolist() for nu in nu_span]}
    r, p = sub.dim, sub.p
    extra = {
        "layers": ([3 * n, p, 200, 200, r] if config.kind == "autoencoder" else [3 * n, r]),
        "pca_dim": p, "activation": "elu" if config.kind == "autoencoder" else "none",
        "normalisation": "q = Uᵀ M (x − rest), U mass-orthonormal; network sees q / q_scale (weights)",
        "material": model, "cubature_young": young.tolist(), "cubature_poisson": poisson.tolist(),
        "bbox_diag_m": diag, "train_error_rel": train_err / diag, "val_error_rel": val_err / diag,
        "n_train": int(len(tr)), "n_val": int(len(va)), "split": split_note,
        "history": info["history"][-1:] if info["history"] else [],
        **extra_cub, **extra_lbs,
    }
    art = SubspaceArtefact(config.kind, r, sub.to_weights(), float(train_err), float(val_err), extra)
    art.save(out, Provenance.make(config, [mesh_path, snap_path]))
    cub = (f"; cubature {len(extra_cub['cubature_points'])} of {m} {what}, force error "
           f"{extra_cub['cubature_error_rel']:.1%}" if extra_cub else f"; all {what} integrated")
    val = f"validation error {val_err * 1e3:.2f} mm ({val_err / diag:.2%} of the bbox diagonal)" if len(va) \
        else f"training error {train_err * 1e3:.2f} mm ({train_err / diag:.2%} of the bbox diagonal)"
    lbs = ""
    if extra_lbs:
        span_e = extra_lbs["lbs_span_val_error_m"] if len(va) else extra_lbs["lbs_span_train_error_m"]
        lbs = (f"; {extra_lbs['lbs_handles']} LBS handles, kept {extra_lbs['lbs_selection']} (whole span: "
               f"{span_e * 1e3:.2f} mm, {span_e / diag:.2%})")
    reporter.summary(f"{config.kind} subspace r={r}: {val}{lbs}{cub} → {out}")
    return out
