#!/usr/bin/env bash
# The whole rsl pipeline on sample_data/, small enough for a 2-core laptop.
# Usage: bash docs/demo.sh [OUT]   (make demo calls it with OUT=out)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-out}
RSL=${RSL:-.venv/bin/rsl}
export JAX_ENABLE_X64=1
mkdir -p "$OUT"
step() { printf '\n\033[1m== %s\033[0m\n' "$*"; }

# 1. The foundation: tet meshes of the two sample objects, as a lab would bring them.
for s in bar dino; do
  step "tetrahedralize sample_data/$s"
  $RSL tetrahedralize "sample_data/$s" -w "$OUT/$s"
done
$RSL status -w "$OUT/bar"
$RSL info "$OUT/bar/mesh.h5"

# 2. `rsl synth`: a capture with ground truth, made from a mesh (the dinosaur pushed by a sphere).
step "synth $OUT/dino_capture"
$RSL synth sample_data/dino/object.mesh "$OUT/dino_capture" --scenario push --cameras 2 --frames 20 \
    --resolution 64 --young 6e4 --markers 20 --seed 1 --overwrite

# 3. The whole pipeline on a synthetic bar capture made from sample_data/bar: a cable pulls the
#    free end of the bar while its Young's modulus steps 100 -> 200 kPa at frame 20 (force-driven,
#    so E shows in the motion). Adaptation starts from a guess 2.5x too soft.
#    The capture is not an inverse crime: its truth is simulated on quadratic (10-node) tets with
#    2 implicit substeps per frame and a hard clamp, and frame 0 shows the bar already sagging in its
#    static equilibrium ([capture] start = "equilibrium"); rsl sees only object.obj, the frames and
#    controls.json, and meshes the object itself.
CAP="$OUT/bar_capture"; WS="$OUT/bar_ws"
step "synth $CAP"
$RSL synth sample_data/bar/object.mesh "$CAP" --scenario cable --cameras 3 --frames 40 \
    --resolution 128 --calib-views 10 --young-schedule "1e5@0,2e5@20" --markers 40 --seed 0 \
    --truth-order 2 --substeps 2 --handles hard --start equilibrium --overwrite
BOARD=$(sed -n 's/^board = "\(.*\)"/\1/p' "$CAP/capture.toml" | head -1)
step "calibrate";        $RSL calibrate "$CAP" -w "$WS" --board "$BOARD"
step "tetrahedralize";   $RSL tetrahedralize "$CAP" -w "$WS"
step "segment";          $RSL segment "$CAP" -w "$WS" --method background
step "fit-gaussians";    $RSL fit-gaussians "$CAP" -w "$WS" --frame 0
step "generate-data";    $RSL generate-data "$CAP" -w "$WS" --sequences 4 --frames 40 --workers 2
# r = 12, default cubature (--cubature-tol 0.002, chosen from docs/results/accuracy.md's foreign captures);
# docs/results/reduced_accuracy.md has the subspace and cubature study.
step "train-subspace";   $RSL train-subspace -w "$WS" --dim 12
# Online adaptation from the 40 motion-capture markers with the Gauss-Newton window estimator
# (E ± σ per frame). The vision loss (--loss vision, Adam) runs on the same workspace: its minimum lies within
# 2 % of the truth, and on a bar whose E steps x2 and x4 Adam settles within 7-8 % in the reduced and full space
# (docs/results/vision_bias.md); markers, with E ± σ, are the more accurate path and the one this demo shows.
step "adapt (online, reduced space, markers, Gauss-Newton)"
$RSL adapt "$CAP" -w "$WS" --window 3 --space reduced --mode online --loss markers --young-init 4e4
step "evaluate";         $RSL evaluate "$CAP" -w "$WS"
# the E estimate beside the truth, every 5th frame
.venv/bin/python - "$CAP" "$WS" <<'PY'
import sys
from stages.artefacts import AdaptArtefact
from stages.capture import load_capture, read_truth
cap, ws = sys.argv[1], sys.argv[2]
a, truth = AdaptArtefact.load(f"{ws}/adapt.h5"), read_truth(load_capture(cap))
print(f"{'frame':>5}  {'E estimated (Pa)':>17}  {'± σ (Pa)':>9}  {'E truth (Pa)':>13}  {'error':>7}")
for i, f in enumerate(a.frames):
    if f % 5 == 0 or i == len(a.frames) - 1:
        e, s, t = a.young[i, 0], a.young_sigma[i, 0], truth.young[min(f, len(truth.young) - 1), 0]
        print(f"{f:>5}  {e:>17.4g}  {s:>9.2g}  {t:>13.4g}  {100 * (e - t) / t:>+6.1f}%")
PY
step "export";           $RSL export -w "$WS"
$RSL status -w "$WS"

cat <<MSG

Done. Results:
  sample meshes          $OUT/bar/mesh.h5, $OUT/dino/mesh.h5   (rsl info FILE)
  a fresh synth capture  $OUT/dino_capture   (frames, calib views, markers, truth/)
  bar capture, pipeline $CAP, $WS/*.h5   (rsl status -w $WS)
  E(t) estimate vs truth $WS/evaluation.json, $WS/evaluation_young.png
  stress, forces, VTU,   $WS/export/   (open the .pvd in ParaView; PNG/MP4 renders and plots)
  renders and plots
MSG

# The page a lab takes away: E(t) ± σ against the truth, renders beside the photos, stress, forces,
# timings and every artefact's provenance, in one self-contained HTML file.
step "report";           $RSL report -w "$WS"
echo
echo "Report: $(cd "$(dirname "$WS/report.html")" && pwd)/report.html"
