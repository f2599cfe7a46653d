#!/usr/bin/env bash
# The CPU-scale experiment of docs/results/cpu_experiment.md: DVFB vs FB, small preset, seed 0,
# pre-trained on point_mass_maze and walker, zero-shot on every task of each domain, plus a
# uniform-random policy. Runs one job at a time (the machine has 2 cores).
#   usage: scripts/cpu_experiment.sh [FRAMES] [OUT_DIR]
set -euo pipefail
FRAMES=${1:-50000}
OUT=${2:-runs/cpu_experiment}
DVFB=${DVFB:-dvfb}
mkdir -p "$OUT"
for domain in point_mass_maze walker; do
  "$DVFB" random-policy --domain "$domain" --episodes 10 --output "$OUT/random_${domain}.json" --overwrite
  for agent in dvfb fb; do
    run="$OUT/${agent}_${domain}_s0"
    if [ -f "$run/pretrain_summary.json" ]; then
      echo "== $run already pre-trained"
    elif [ -f "$run/checkpoints/latest" ]; then
      "$DVFB" pretrain --agent "$agent" --domain "$domain" --preset small --frames "$FRAMES" --seed 0 \
        --run-dir "$run" --no-progress --resume
    else
      "$DVFB" pretrain --agent "$agent" --domain "$domain" --preset small --frames "$FRAMES" --seed 0 \
        --run-dir "$run" --no-progress --overwrite
    fi
    "$DVFB" zeroshot "$run" --task all --overwrite
  done
done
