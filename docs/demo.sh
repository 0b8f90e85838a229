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

# 2. A synthetic capture with ground truth: the bar stretched and twisted by two handles,
#    its Young's modulus stepping 10 -> 20 -> 40 kPa (like the paper's gingerbread case).
CAP="$OUT/bar_capture"; WS="$OUT/bar_ws"
step "synth $CAP"
$RSL synth sample_data/bar/object.mesh "$CAP" --scenario stretch --cameras 3 --frames 30 \
    --resolution 96 --young-schedule "1e4@0,2e4@10,4e4@20" --poisson 0.45 --markers 40 --seed 0

# 3. Cameras from the chessboard views, masks from the background plates.
step "calibrate";        $RSL calibrate "$CAP" -w "$WS" --board chessboard:9x6:0.025
step "segment";          $RSL segment "$CAP" -w "$WS" --method background
step "tetrahedralize";   $RSL tetrahedralize "$CAP" -w "$WS"
step "fit-gaussians";    $RSL fit-gaussians "$CAP" -w "$WS" --frame 0
step "generate-data";    $RSL generate-data "$CAP" -w "$WS" --sequences 6 --frames 30 --workers 2
step "train-subspace";   $RSL train-subspace -w "$WS" --dim 12
step "adapt (online, reduced, vision)"
$RSL adapt "$CAP" -w "$WS" --window 3 --space reduced --mode online --loss vision --young-init 4e4
step "evaluate";         $RSL evaluate "$CAP" -w "$WS"
step "export";           $RSL export -w "$WS" --stress --forces --vtk --plots --render

cat <<MSG

Done. Results:
  meshes                 $OUT/bar/mesh.h5, $OUT/dino/mesh.h5
  synthetic capture      $CAP   (frames, calib views, markers, truth/)
  artefacts              $WS/*.h5   (rsl info FILE, rsl status -w $WS)
  E(t) estimate vs truth $WS/evaluation.json, $WS/evaluation_young.png
  stress, forces, VTU    $WS/export/   (open export/*.pvd in ParaView)
MSG
