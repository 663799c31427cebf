#!/usr/bin/env bash
# The first reference results (2026-11-21/23, one tenth of the paper's sizes, chosen for a
# 2-core CPU machine; the paper's full sizes are the experiments' defaults: drop --trials).
# Today's headline numbers: analysis/results/reference/ (analysis/make_reference.py).
set -euo pipefail
cd "$(dirname "$0")/.."
DG=${DG:-drake-grasp}
R=analysis/results
$DG evaluate --experiment isolation --workers 2 --seed 0 --out $R/isolation
# CTR alone on the 40 configurations x 3 seeds (trials 40-119 repeat the configurations).
$DG evaluate --experiment isolation --conditions ctr --trials 120 --workers 2 --seed 0 \
    --out $R/isolation-ctr120
$DG evaluate --experiment sim-distance --trials 40 --workers 2 --seed 0 --out $R/sim-distance
$DG evaluate --experiment clutter --trials 3 --workers 2 --seed 0 --out $R/clutter
$DG evaluate --experiment clutter-shift --trials 3 --workers 2 --seed 0 --out $R/clutter-shift
# Timing and calibration sweeps (README: Timing and calibration), 20 trials per point.
for e in sweep-latency sweep-control-period sweep-dropped-frames sweep-camera-translation \
         sweep-camera-rotation; do
    $DG evaluate --experiment $e --trials 20 --workers 2 --seed 0 --out $R/$e
done
# Its combined report goes to tenth-size/, not the top of analysis/results/ (whose current
# numbers are reference/, written by analysis/make_reference.py).
T=$R/tenth-size
mkdir -p $T
python analysis/table1.py $R/isolation $R/clutter $R/clutter-shift --out $T/table1.md
python analysis/figure5.py $R/sim-distance --out $T/figure5.png
python -c "from drake_grasp.evaluation.report import make_combined_report; make_combined_report(['$R/isolation', '$R/sim-distance', '$R/clutter', '$R/clutter-shift'], '$T')"
